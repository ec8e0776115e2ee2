"""The README and the docs pages keep their shape: a README a newcomer reads in minutes (at most 200 lines, no commit
hash, no timing by the hour of a machine), every docs page opening with a summary of at most 10 lines, every relative
link and anchor resolving, the README's presets table naming exactly the registry's presets, each headline result
naming a preset and a command of the README, and the README's library example computing a derivative that central
finite differences confirm, and CI installing and testing exactly as the README says. (The commands of the code
blocks are parsed by tests/test_docs.py.)"""
from __future__ import annotations

import glob
import os
import re

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README = os.path.join(ROOT, "README.md")
PAGES = sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")) + glob.glob(os.path.join(ROOT, "docs", "notes", "*.md")))
LINKED = [README, *PAGES, *sorted(glob.glob(os.path.join(ROOT, "benchmarks", "*.md")))]
FENCE = re.compile(r"^\s*```")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
LINK = re.compile(r"\]\(([^)\s]+)\)")
HASH = re.compile(r"\b(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b")


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        return f.read()


def _prose(text: str):
    """``(line number, line)`` of the lines outside fenced code blocks."""
    inside = False
    for i, line in enumerate(text.split("\n"), 1):
        if FENCE.match(line):
            inside = not inside
            continue
        if not inside:
            yield i, line


def slug(title: str) -> str:
    """GitHub's anchor of a heading: link text kept, lower case, punctuation but ``-`` and ``_`` dropped, spaces to
    ``-``."""
    title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title).strip().lower()
    return re.sub(r"[^\w\- ]", "", title).replace(" ", "-")


def anchors(path: str) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, line in _prose(_read(path)):
        m = HEADING.match(line)
        if not m:
            continue
        s = slug(m.group(2))
        out.add(s if s not in seen else f"{s}-{seen[s] + 1}")
        seen[s] = seen.get(s, -1) + 1
    return out


def _table(text: str, header: str) -> list[list[str]]:
    """The rows (cells stripped) of the Markdown table whose header line starts with ``header``."""
    lines = text.split("\n")
    start = next(i for i, line in enumerate(lines) if line.startswith(header))
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows


def test_readme_is_a_short_page_without_commit_hashes_or_hourly_timings():
    text = _read(README)
    assert len(text.rstrip("\n").split("\n")) <= 200
    hashes = [(i, m.group(0)) for i, line in _prose(text) for m in HASH.finditer(line)]
    assert not hashes, f"commit hashes in the README: {hashes}"
    assert not re.search(r"\bhours?\b", text), "timings by the hour belong in benchmarks/RESULTS.md"
    assert "docs/img/stepdown_24cm_reflex.gif" in text and "hyqjax/assets/NOTICE.md" in text


@pytest.mark.parametrize("path", PAGES, ids=[os.path.relpath(p, ROOT) for p in PAGES])
def test_docs_page_opens_with_a_summary_of_at_most_ten_lines(path):
    lines = _read(path).split("\n")
    assert lines[0].startswith("# "), "a page starts with its title"
    body = lines[1:]
    first = next(i for i, line in enumerate(body) if line.strip())
    assert body[first].startswith("**In brief.**"), "the first paragraph after the title is the summary"
    end = next((i for i in range(first, len(body)) if not body[i].strip()), len(body))
    assert end - first <= 10, f"summary of {end - first} lines"


def test_relative_links_and_anchors_resolve():
    cache: dict[str, set[str]] = {}
    broken = []
    for src in LINKED:
        for i, line in _prose(_read(src)):
            for m in LINK.finditer(line):
                target = m.group(1)
                if re.match(r"^[a-z]+:", target):
                    continue
                path, _, anchor = target.partition("#")
                dest = os.path.normpath(os.path.join(os.path.dirname(src), path)) if path else src
                where = f"{os.path.relpath(src, ROOT)}:{i}: {target}"
                if not os.path.exists(dest):
                    broken.append(f"{where} (no such file)")
                elif anchor and dest.endswith(".md"):
                    if dest not in cache:
                        cache[dest] = anchors(dest)
                    if anchor not in cache[dest]:
                        broken.append(f"{where} (no such heading)")
    assert not broken, "\n".join(broken)


def test_readme_presets_table_is_the_registry():
    import hyqjax.presets

    rows = _table(_read(README), "| preset | kind |")
    documented = {r[0].strip("`"): r[1] for r in rows}
    assert set(documented) == set(hyqjax.presets.names())
    for name, kind in documented.items():
        assert hyqjax.presets.get(name).kind == kind, name


def test_readme_headline_results_name_a_preset_and_a_command():
    text = _read(README)
    presets = {r[0].strip("`") for r in _table(text, "| preset | kind |")}
    rows = _table(text, "| result | preset |")
    assert 5 <= len(rows) <= 6
    after = text[text.index("| result | preset |"):]
    block = after[after.index("```bash"):]
    block = block[:block.index("\n```", 7)]
    for result, preset, measured, command in rows:
        assert preset == "–" or preset.strip("`") in presets, preset
        assert re.search(r"\d", result) and measured, result
        for n in re.findall(r"\((\d)\)", command):
            assert re.search(rf"^# .*\({n}\)", block, flags=re.M), f"no command ({n}) below the table"
            line = block[re.search(rf"^# .*\({n}\)", block, flags=re.M).end():].strip().split("\n")
            assert any(w.startswith(("hyqjax ", "python ")) for w in line[:4]), f"command ({n})"


@pytest.mark.slow
def test_readme_library_example_runs_and_its_derivative_is_a_scalar():
    """The README's library example as written: the batch runs on the simulator of this machine and gives the
    paper's outcomes at 16 cm; its derivative line is traced through MJX-JAX (``jax.eval_shape``: every name and
    shape, no XLA compile). That ``jacfwd`` of this closed loop matches central differences is
    ``tests/test_api.py``'s test of docs/api.md's same example."""
    import jax

    code = re.findall(r"```python\n(.*?)```", _read(README), flags=re.S)
    assert len(code) == 1 and len(code[0].strip().split("\n")) <= 16
    assert not re.search(r"\b_[a-z]\w*", code[0]) and "from hyqjax." not in code[0], "public names only"
    grad_line = "jax.jit(jax.jacfwd(trunk_height))(jnp.asarray(1500.0))"
    assert grad_line in code[0]
    ns: dict = {}
    exec(compile(code[0].replace(grad_line, "jax.eval_shape(jax.jacfwd(trunk_height), jnp.asarray(1500.0))"),
                 "README.md", "exec"), ns)
    outcome = ns["outcome"]
    assert np.shape(outcome.completed) == (4,) and np.shape(outcome.clean) == (4,)
    assert not np.any(np.asarray(outcome.clean) & ~np.asarray(outcome.completed))  # clean implies completed
    assert np.any(np.asarray(outcome.completed)[:2])  # 16 cm with the reflex: 99.9% of 1,024 runs
    assert ns["dz_dk"].shape == () and ns["dz_dk"].dtype == jax.numpy.float32


def test_ci_installs_and_tests_exactly_as_the_readme_says():
    """``.ci/run`` is a new user: it creates the README's virtual environment, installs with the README's pip command
    and nothing else (no pip upgrade, no extra package), and runs the README's test command."""
    readme = _read(README)
    blocks = re.findall(r"```bash\n(.*?)```", readme, re.S)
    install, tests = blocks[0].strip(), blocks[1].strip()
    ci = [line.strip() for line in _read(os.path.join(ROOT, ".ci", "run")).split("\n")
          if line.strip() and not line.lstrip().startswith("#")]
    steps = [s.strip() for s in install.split("&&")]
    assert steps[:3] == ["python3 -m venv .venv", ". .venv/bin/activate", 'pip install -e ".[test]"'], steps
    assert steps[0] in ci and steps[1] in ci
    pips = [line for line in ci if re.search(r"\bpip install\b", line)]
    assert pips == ['python -m pip install -q -e ".[test]"'], pips
    assert ci.count(tests) == 1, tests  # the README's test command, as it is written there
