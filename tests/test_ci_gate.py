"""The CI gate: expectations (parsing, refusal, Wilson decisions), the baseline comparison (Newcombe, McNemar, Holm
against hand-computed and published values; verdicts on synthetic stores; refusals), the JUnit and Markdown reports
parsed back, and a real C MuJoCo sweep compared with itself (slow)."""
from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from hyqjax.cli.app import main
from hyqjax.studies import sweep
from hyqjax.studies.statistics import wilson_interval
from hyqjax.studies.sweep import compare, expect, gate
from hyqjax.studies.sweep.manifest import StoreMismatch

SPEC = dict(seed=3, samples=20, grid=dict(height=[0.12, 0.2], reflex=[False, True]),
            random=dict(friction=[0.5, 1.0]))
LAYOUT = dict(platform="cpu", device_kind="cpu", devices=1, impl="c")


# ---------------------------------------------------------------- expectations
@pytest.mark.parametrize("text, metric, op, value, where, per_cell", [
    ("clean >= 0.85", "clean", ">=", 0.85, "", False),
    ("completed>=0.95 where height <= 0.21", "completed", ">=", 0.95, "height <= 0.21", False),
    ("clean > .5 where reflex == on and height = 0.16", "clean", ">", 0.5, "reflex == on and height == 0.16", False),
    ("diverged <= 0.01", "diverged", "<=", 0.01, "", False),
    ("clean >= 0.6 per cell where reflex != off", "clean", ">=", 0.6, "reflex != off", True),
    ("success < 1 where foot_sequence == rh-rf-lh-lf", "success", "<", 1.0, "foot_sequence == rh-rf-lh-lf", False),
])
def test_expectations_parse(text, metric, op, value, where, per_cell):
    e = expect.parse(text)
    assert (e.metric, e.op, e.value, e.per_cell) == (metric, op, value, per_cell)
    assert " and ".join(c.text() for c in e.where) == where
    back = expect.parse(e.text())
    assert (back.metric, back.op, back.value, back.where, back.per_cell) == (e.metric, e.op, e.value, e.where,
                                                                             e.per_cell)


@pytest.mark.parametrize("text, says", [
    ("clen >= 0.5", "unknown metric 'clen'"),
    ("clean => 0.5", "bad comparison '=>'"),
    ("clean == 0.5", "bad comparison '=='"),
    ("clean >= 85", "outside [0, 1]"),
    ("clean >= -0.1", "outside [0, 1]"),
    ("clean >= high", "a number in [0, 1]"),
    ("clean >= 0.5 where hieght <= 0.2", "unknown axis 'hieght'"),
    ("clean >= 0.5 where height <= 0.9", "out of range"),
    ("clean >= 0.5 where reflex <= on", "compare it with == or !="),
    ("clean >= 0.5 where reflex == maybe", "on/off/true/false"),
    ("clean >= 0.5 where height ~ 0.2", "bad filter condition"),
    ("clean >= 0.5 height <= 0.2", "unexpected"),
    ("", "an expectation is a string"),
])
def test_bad_expectation_refused(text, says):
    with pytest.raises(sweep.SpecError, match=None) as ei:
        expect.parse(text)
    assert says in str(ei.value) and "\n" not in str(ei.value)


@pytest.mark.parametrize("argv, says", [
    (["sweep", "--ci", "--expect", "clean >= 1.2"], "outside [0, 1]"),
    (["sweep", "--ci", "--expect", "clena >= 0.2"], "unknown metric"),
    (["sweep", "--ci", "--expect", "clean >= 0.2 where speed2 < 1"], "unknown axis"),
    (["sweep", "--ci", "--expect", "clean >= 0.2 where height == 0.3"], "selects no instance"),
    (["sweep", "--ci", "--inconclusive", "maybe"], "invalid choice"),
    (["sweep", "--ci", "--alpha", "0.7"], "--alpha must be"),
    (["sweep", "--ci", "--allow-change", "colour"], "--allow-change 'colour'"),
])
def test_sweep_refuses_bad_gate_options_before_running(tmp_path, capsys, argv, says):
    out = tmp_path / "out"
    try:
        rc = main([*argv, "--out", str(out)])
    except SystemExit as e:  # the argument parser's own errors
        rc = e.code
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_spec_file_expectations_refused_and_not_hashed(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('expect = ["clean >= 2"]\nsamples = 2\n[grid]\nheight = [0.1]\n')
    assert main(["sweep", str(bad), "--dry-run"]) == 2
    err = capsys.readouterr().err.strip()
    assert "expect 'clean >= 2'" in err and "outside [0, 1]" in err and len(err.splitlines()) == 1
    good = tmp_path / "good.toml"
    good.write_text('expect = ["clean >= 0.2"]\nsamples = 2\n[grid]\nheight = [0.1]\n')
    plain = tmp_path / "plain.toml"
    plain.write_text('samples = 2\n[grid]\nheight = [0.1]\n')
    assert main(["sweep", str(good), "--dry-run"]) == 0
    a = capsys.readouterr().out
    assert main(["sweep", str(plain), "--dry-run"]) == 0
    assert capsys.readouterr().out == a  # same spec hash: expectations are not part of the sweep


def test_ci_spec_is_shipped_and_valid(capsys):
    assert main(["sweep", "--ci", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "128 instances" in out and "24 s each" in out


def _rows(spec, ok):
    """The spec's real input rows plus outcome columns ``ok`` (clean = completed = ok)."""
    rows = spec.instance_inputs(0, spec.n_instances)
    out = dict(success=ok, completed=ok, failure_reason=np.where(ok, "", "tilt"),
               diverged=np.zeros(len(ok), bool), terminated=np.zeros(len(ok), bool),
               mean_mobility=np.full(len(ok), 0.8), peak_pitch=np.zeros(len(ok)))
    return {**rows, **sweep.count_outcomes(out)}


def test_wilson_decisions():
    spec = sweep.SweepSpec.from_dict(dict(samples=100, grid=dict(height=[0.1, 0.2])))
    # height 0.1: 100/100 (Wilson lower bound 0.963); height 0.2: 85/100, Wilson [0.767, 0.907]
    ok = np.r_[np.ones(100, bool), np.arange(100) < 85]
    rows = _rows(spec, ok)
    exps = expect.parse_all(["clean >= 0.95 where height == 0.1", "clean >= 0.95 where height == 0.2",
                             "clean >= 0.85 where height == 0.2", "clean <= 0.9 where height == 0.2",
                             "clean < 0.5 where height == 0.2", "completed >= 0.5 per cell"])
    checks = expect.evaluate(exps, spec, rows)
    assert [c.status for c in checks] == ["pass", "fail", "inconclusive", "inconclusive", "fail", "pass", "pass"]
    lo, hi = wilson_interval(85, 100)
    assert checks[2].ci == (lo, hi) and lo < 0.85 < hi and hi < 0.95
    assert [c.cell for c in checks[-2:]] == ["height=0.1", "height=0.2"]
    assert expect.exit_status(checks) == 1
    assert expect.exit_status(checks[2:4]) == 3
    assert expect.exit_status(checks[2:4], "pass") == 0 and expect.exit_status(checks[2:4], "fail") == 1
    assert expect.exit_status(checks[:1]) == 0


# ---------------------------------------------------------------- statistics
def test_newcombe_matches_published_values():
    # Newcombe (1998), Statistics in Medicine 17:873, Table II, method 10 (hybrid score).
    lo, hi = compare.newcombe_interval(56, 70, 48, 80)
    assert (round(lo, 4), round(hi, 4)) == (0.0524, 0.3339)
    lo, hi = compare.newcombe_interval(9, 10, 3, 10)
    assert (round(lo, 4), round(hi, 4)) == (0.1705, 0.8090)


def test_mcnemar_exact_hand_computed():
    assert compare.mcnemar_exact(0, 0) == 1.0
    assert compare.mcnemar_exact(0, 6) == pytest.approx(2 / 64)  # 2 * 0.5^6
    assert compare.mcnemar_exact(9, 1) == pytest.approx(2 * 11 / 1024)  # 2 * (C(10,0) + C(10,1)) / 2^10
    assert compare.mcnemar_exact(3, 3) == 1.0
    assert compare.mcnemar_exact(0, 5) == pytest.approx(0.0625)  # 5 flips one way are not enough at 0.05


def test_holm_hand_computed():
    np.testing.assert_allclose(compare.holm([0.01, 0.04, 0.03]), [0.03, 0.06, 0.06])
    np.testing.assert_allclose(compare.holm([0.2, 0.001]), [0.2, 0.002])
    np.testing.assert_allclose(compare.holm([0.5, 0.9]), [1.0, 1.0])  # 2 x 0.5 caps at 1, monotone


# ---------------------------------------------------------------- synthetic stores
def _store(path, d, ok, layout=LAYOUT):
    spec = sweep.SweepSpec.from_dict(d)
    rows = _rows(spec, ok)
    with sweep.SweepStore(str(path), spec, spec.n_instances, layout, writer=True) as st:
        st.write_chunk(0, rows, 0.0)
    return spec


def _base_ok(spec):
    rows = spec.instance_inputs(0, spec.n_instances)
    return rows["friction"] > 0.6  # about 80% pass, the same instances in every store of this spec


def test_identical_stores_no_change(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    _store(tmp_path / "b", SPEC, _base_ok(spec))
    c = compare.compare_stores(tmp_path / "a", tmp_path / "b")
    assert c.paired and c.identical and c.verdict == "no significant change"
    assert len(c.tests) == 2 * (4 + 1) and all(t.b == 0 and t.c == 0 and t.p == 1.0 for t in c.tests)


def test_planted_regression_flagged_and_improvement(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    ok = _base_ok(spec)
    worse = ok.copy()
    cell = np.nonzero(spec.instance_inputs(0, spec.n_instances)["grid_index"] == 3)[0]
    flip = cell[ok[cell]][:12]  # 12 passing instances of cell 3 fail in NEW
    worse[flip] = False
    _store(tmp_path / "a", SPEC, ok)
    _store(tmp_path / "b", SPEC, worse)
    c = compare.compare_stores(tmp_path / "a", tmp_path / "b")
    t = {(x.cell, x.level): x for x in c.tests}
    bad = t[("height=0.2, reflex=on", "clean")]
    assert (bad.b, bad.c) == (12, 0) and bad.p == pytest.approx(2 * 0.5 ** 12)
    assert bad.p_holm == pytest.approx(min(1, bad.p * 10)) or bad.p_holm >= bad.p
    assert bad.verdict == "regressed" and c.verdict == "regressed" and c.cells["height=0.2, reflex=on"] == "regressed"
    assert c.cells["height=0.12, reflex=off"] == "no significant change"
    # Newcombe's interval of the difference, from the two Wilson intervals
    assert bad.ci == pytest.approx(compare.newcombe_interval(bad.k_new, bad.n_new, bad.k_base, bad.n_base))
    assert bad.ci[1] < 0
    back = compare.compare_stores(tmp_path / "b", tmp_path / "a")
    assert back.verdict == "improved"


def test_few_flips_not_flagged(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    ok = _base_ok(spec)
    new = ok.copy()
    i = np.nonzero(ok)[0][:3]
    new[i] = False  # 3 discordant pairs: p = 0.25, never significant
    _store(tmp_path / "a", SPEC, ok)
    _store(tmp_path / "b", SPEC, new)
    c = compare.compare_stores(tmp_path / "a", tmp_path / "b")
    assert c.verdict == "no significant change" and not c.identical


def test_refusals_name_the_difference(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    other = dict(SPEC, samples=10)
    _store(tmp_path / "b", other, _base_ok(sweep.SweepSpec.from_dict(other)))
    with pytest.raises(StoreMismatch, match=r"samples: 20 vs 10"):
        compare.compare_stores(tmp_path / "a", tmp_path / "b")
    fixed = dict(SPEC, fixed=dict(reflex_d_st_max=500.0))
    _store(tmp_path / "c", fixed, _base_ok(spec))
    with pytest.raises(StoreMismatch, match=r"\[fixed\] reflex_d_st_max: absent vs 500.0"):
        compare.compare_stores(tmp_path / "a", tmp_path / "c")
    c = compare.compare_stores(tmp_path / "a", tmp_path / "c", allow_change=["reflex_d_st_max"])
    assert c.paired and c.identical and any("reflex_d_st_max" in n for n in c.notes)
    seed = dict(SPEC, seed=4)
    _store(tmp_path / "d", seed, _base_ok(sweep.SweepSpec.from_dict(seed)))
    c = compare.compare_stores(tmp_path / "a", tmp_path / "d", allow_change=["seed"])
    assert not c.paired and all(t.test == "fisher" for t in c.tests)
    # damaged chunk: named
    f = tmp_path / "b" / "chunks" / "00000.parquet"
    blob = bytearray(f.read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    f.write_bytes(bytes(blob))
    with pytest.raises(StoreMismatch, match=r"NEW .* is damaged: .*chunk 0"):
        compare.compare_stores(tmp_path / "a", tmp_path / "b")


def test_other_layout_noted(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    _store(tmp_path / "b", SPEC, _base_ok(spec), dict(LAYOUT, impl="jax"))
    c = compare.compare_stores(tmp_path / "a", tmp_path / "b")
    assert c.verdict == "no significant change" and any("float rounding" in n for n in c.notes)


# ---------------------------------------------------------------- reports parsed back
def test_reports_parse_back(tmp_path, capsys, monkeypatch):
    spec = sweep.SweepSpec.from_dict(SPEC)
    ok = _base_ok(spec)
    worse = ok.copy()
    cell = np.nonzero(spec.instance_inputs(0, spec.n_instances)["grid_index"] == 3)[0]
    worse[cell[ok[cell]][:12]] = False
    _store(tmp_path / "a", SPEC, ok)
    _store(tmp_path / "b", SPEC, worse)
    summary = tmp_path / "step_summary.md"
    summary.write_text("earlier step\n")
    monkeypatch.setenv("GITHUB_STEP_SUMMARY", str(summary))
    x, md, js = tmp_path / "r" / "g.xml", tmp_path / "r" / "g.md", tmp_path / "r" / "g.json"
    rc = main(["compare", str(tmp_path / "a"), str(tmp_path / "b"), "--expect", "clean >= 0.99",
               "--expect", "clean >= 0.3 where height == 0.12", "--expect", "completed >= 0.7 per cell",
               "--junit", str(x), "--markdown", str(md), "--json", str(js)])
    assert rc == 1
    out = capsys.readouterr().out
    assert "REGRESSED" in out and "gate: FAILED (exit status 1)" in out
    verdict = json.loads(js.read_text())
    assert verdict["exit_status"] == 1 and verdict["comparison"]["verdict"] == "regressed"
    # JUnit
    root = ET.parse(x).getroot()
    suites = {s.get("name"): s for s in root.iter("testsuite")}
    exp, base = suites["expectations"], suites["baseline comparison"]
    cases = exp.findall("testcase")
    assert len(cases) == int(exp.get("tests")) == 2 + 4
    failed = [c.get("name") for c in cases if c.find("failure") is not None]
    want = [e["name"] for e in verdict["expectations"] if e["status"] == "fail"]
    assert failed == want and "clean >= 0.99" in failed and int(exp.get("failures")) == len(want)
    assert int(exp.get("skipped")) == sum(e["status"] == "inconclusive" for e in verdict["expectations"])
    bcases = base.findall("testcase")
    assert len(bcases) == len(verdict["comparison"]["tests"]) == 10
    assert [c.get("name") for c in bcases if c.find("failure") is not None] == \
        [t["name"] for t in verdict["comparison"]["tests"] if t["verdict"] == "regressed"]
    assert "clean [height=0.2, reflex=on]" in [c.get("name") for c in bcases if c.find("failure") is not None]
    # Markdown
    text = md.read_text()
    assert text.splitlines()[0] == "### hyqjax compare " + f"{tmp_path / 'a'} {tmp_path / 'b'}: FAILED"
    t_exp, t_cmp = gate.parse_markdown_tables(text)
    assert [r["status"] for r in t_exp] == [e["status"] for e in verdict["expectations"]]
    assert [r["expectation"] for r in t_exp] == [e["name"] for e in verdict["expectations"]]
    assert [r["instances"] for r in t_exp] == [f"{e['k']}/{e['n']}" for e in verdict["expectations"]]
    rows = {(r["cell"], r["level"]): r for r in t_cmp}
    r = rows[("height=0.2, reflex=on", "clean")]
    t = next(t for t in verdict["comparison"]["tests"] if t["name"] == "clean [height=0.2, reflex=on]")
    assert r["verdict"] == "regressed" and r["base"] == f"{t['k_base']}/{t['n_base']}"
    assert float(r["Holm p"]) == pytest.approx(t["p_holm"], rel=1e-2)
    assert summary.read_text() == "earlier step\n" + text + "\n"


def test_compare_refusal_is_one_line(tmp_path, capsys):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    other = dict(SPEC, duration=12.0)
    _store(tmp_path / "b", other, _base_ok(sweep.SweepSpec.from_dict(other)))
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip()
    assert "duration: 18.0 vs 12.0" in err and len(err.splitlines()) == 1
    assert main(["compare", str(tmp_path / "a"), str(tmp_path / "nothing")]) == 2
    assert "NEW" in capsys.readouterr().err


# ---------------------------------------------------------------- a real sweep
@pytest.mark.slow
def test_real_sweep_compared_with_itself(tmp_path, capsys):
    spec = tmp_path / "s.toml"
    spec.write_text('seed = 1\nsamples = 2\nduration = 3.0\nexpect = ["diverged <= 0.5"]\n'
                    '[grid]\nheight = [0.12]\nreflex = [false, true]\n[random]\nfriction = [0.6, 1.0]\n')
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["sweep", str(spec), "--impl", "c", "--out", str(a), "--no-progress"]) in (0, 3)
    capsys.readouterr()
    x = tmp_path / "b.xml"
    rc = main(["sweep", str(spec), "--impl", "c", "--out", str(b), "--no-progress", "--baseline", str(a),
               "--junit", str(x), "--expect", "completed <= 1"])
    out = capsys.readouterr().out
    c = compare.compare_stores(a, b)
    assert c.paired and c.identical and c.verdict == "no significant change", out
    ra, rb = sweep.open_store(str(a)).load(), sweep.open_store(str(b)).load()
    for k in ("success", "completed", "failure_reason", "progress"):
        np.testing.assert_array_equal(ra[k], rb[k])
    root = ET.parse(x).getroot()
    assert not [c for c in root.iter("testcase") if c.find("failure") is not None]
    assert rc == 0 and "gate: PASSED" in out


def test_other_version_columns_refused(tmp_path):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    rows = {**_rows(spec, _base_ok(spec)), "new_metric": np.zeros(spec.n_instances)}
    with sweep.SweepStore(str(tmp_path / "b"), spec, spec.n_instances, LAYOUT, writer=True) as st:
        st.write_chunk(0, rows, 0.0)
    with pytest.raises(StoreMismatch, match=r"different outcome columns \(only in BASE: \[\], only in NEW: \['new_metric'\]"):
        compare.compare_stores(tmp_path / "a", tmp_path / "b")


def test_sweep_baseline_of_another_spec_refused_before_running(tmp_path, capsys):
    spec = sweep.SweepSpec.from_dict(SPEC)
    _store(tmp_path / "a", SPEC, _base_ok(spec))
    out = tmp_path / "out"
    assert main(["sweep", "--ci", "--out", str(out), "--baseline", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--baseline" in err and "holds a different sweep" in err and "samples: 20 vs 64" in err
    assert len(err.splitlines()) == 1 and not out.exists()
