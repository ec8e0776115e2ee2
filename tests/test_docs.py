"""The commands in README.md and docs/*.md stay true: every ``hyqjax ...``, ``python -m MODULE ...`` and
``python SCRIPT.py ...`` line of a fenced code block parses with the argument parser of what it runs (nothing is
simulated: parsing stops the command before its work), and every module or script it names exists.

A command line may continue over lines ending in ``\\``, follow ``&&`` / ``;`` in a chain, and carry environment
assignments (``MUJOCO_GL=egl hyqjax render ...``) or ``nice`` / ``time`` in front; ``#`` starts a comment.
Placeholders in capitals (``DIR``, ``SPEC``) are ordinary arguments to a parser. Lines that are not commands
(Python code, TOML, output) are not checked here; docs/api.md's Python is run by tests/test_api.py.
"""
from __future__ import annotations

import argparse
import contextlib
import glob
import importlib
import importlib.util
import io
import os
import re
import shlex
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = [os.path.join(ROOT, "README.md"), *sorted(glob.glob(os.path.join(ROOT, "docs", "*.md"))),
        os.path.join(ROOT, "benchmarks", "README.md")]
FENCE = re.compile(r"^(\s*)```")
PREFIXES = ("nice", "time", "env", "exec")
ENV = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")


def code_blocks(path: str):
    """``(line number, text)`` of every line inside a fenced code block of ``path``, with ``\\`` continuations
    joined (the line number of the first)."""
    out, inside, lang, pending, start = [], False, "", "", 0
    with open(path, encoding="utf-8") as f:
        for i, line in enumerate(f, 1):
            m = FENCE.match(line)
            if m:
                inside, lang = (not inside), line.strip()[3:].strip().lower()
                continue
            if not inside or lang in ("python", "py", "toml", "json", "text", "txt"):
                continue
            text = line.rstrip("\n")
            if not pending:
                start = i
            if text.rstrip().endswith("\\"):
                pending += text.rstrip()[:-1] + " "
                continue
            out.append((start, pending + text))
            pending = ""
    return out


def commands(path: str):
    """``(line, argv)`` of every ``hyqjax`` / ``python`` command in the code blocks of ``path``."""
    found = []
    for line, text in code_blocks(path):
        text = text.strip()
        if text.startswith(("$ ", "% ")):
            text = text[2:]
        try:
            words = shlex.split(text, comments=True)
        except ValueError:
            continue
        part: list[str] = []
        for w in [*words, "&&"]:
            if w in ("&&", ";", "||", "|"):
                if part:
                    while part and (ENV.match(part[0]) or part[0] in PREFIXES):
                        part = part[1:]
                    if part and (part[0] == "hyqjax" or re.fullmatch(r"python(3(\.\d+)?)?", part[0])):
                        found.append((line, part))
                part = []
            else:
                part.append(w)
    return found


def all_commands():
    out = []
    for path in DOCS:
        if os.path.isfile(path):
            out += [(os.path.relpath(path, ROOT), line, argv) for line, argv in commands(path)]
    return out


CASES = all_commands()
#: ``python ...`` cases import their module (JAX, MuJoCo, experiment code: seconds each): not in the unit lane.
PARAMS = [pytest.param(p, n, a, id=f"{p}:{n}", marks=() if a[0] == "hyqjax" else pytest.mark.slow)
          for p, n, a in CASES]


class Parsed(Exception):
    """Raised by the patched ``parse_args``: the command line parsed, nothing runs."""


@contextlib.contextmanager
def parse_only():
    original = argparse.ArgumentParser.parse_args

    def parse_args(self, args=None, namespace=None):
        ns = original(self, args, namespace)
        raise Parsed(ns)

    argparse.ArgumentParser.parse_args = parse_args
    try:
        yield
    finally:
        argparse.ArgumentParser.parse_args = original


def elide(argv: list[str]) -> list[str]:
    """``...`` in a documented command stands for more of the same: an option's value (``--out ...``) becomes a
    placeholder, a trailing ``...`` (more options) is dropped."""
    out = []
    for w in argv:
        if w == "...":
            if out and out[-1].startswith("--"):
                out.append("X")
            continue
        out.append(w)
    return out


def check_parses(main, argv: list[str], what: str) -> None:
    argv = elide(argv)
    err = io.StringIO()
    with parse_only(), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(argv)
        except Parsed:
            return
        except SystemExit as e:  # --help exits 0 after printing; a parse error exits 2
            if e.code in (0, None):
                return
            raise AssertionError(f"{what}: the parser refused it: {err.getvalue().strip()}") from None
    raise AssertionError(f"{what}: ran without parsing a command line")


def test_the_docs_have_commands():
    """The extraction finds the README's commands (a guard against a silently empty check)."""
    readme = [argv for path, _, argv in CASES if path == "README.md"]
    assert any(a[:2] == ["hyqjax", "stepdown"] for a in readme)
    assert any(a[:2] == ["python", "-m"] for a in readme)
    assert len(CASES) >= 20


@pytest.mark.parametrize("path, line, argv", PARAMS)
def test_documented_command_parses(path, line, argv):
    what = f"{path}:{line}: {' '.join(argv)}"
    if argv[0] == "hyqjax":
        from hyqjax.cli.app import main

        check_parses(main, argv[1:], what)
        return
    args = argv[1:]
    while args and args[0].startswith("-") and args[0] not in ("-m",):  # python -X, -u, ...
        args = args[1:]
    if not args:
        pytest.skip("an interactive python")
    if args[0] == "-m":
        module = args[1]
        if module in ("pip", "venv", "pytest", "hyqjax.cli"):
            if module == "pytest":
                assert all(os.path.exists(os.path.join(ROOT, a)) for a in args[2:]
                           if not a.startswith("-") and "/" in a and "::" not in a), what
            return
        assert importlib.util.find_spec(module) is not None, f"{what}: no module {module}"
        mod = importlib.import_module(module)
        assert hasattr(mod, "main"), f"{what}: {module} has no main(argv)"
        check_parses(mod.main, args[2:], what)
        return
    script = os.path.join(ROOT, args[0])
    assert os.path.isfile(script), f"{what}: no script {args[0]}"
    spec = importlib.util.spec_from_file_location(f"_doc_script_{os.path.basename(script)[:-3]}", script)
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, os.path.dirname(script))
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(os.path.dirname(script))
    assert hasattr(mod, "main"), f"{what}: {args[0]} has no main(argv)"
    check_parses(mod.main, args[1:], what)
