"""experiments/bounding_guided_seeds.py: the stored comparison over seeds is what its runs say, the paired
statistics are right, and runs that are not comparable are refused in one line."""
from __future__ import annotations

import copy
import json
import os

import numpy as np
import pytest
from scipy import stats

from experiments import bounding_guided_seeds as bgs
from hyqjax.studies.statistics import wilson_interval

ROOT = os.path.join(os.path.dirname(__file__), "..", "docs", "results")
STORED = os.path.join(ROOT, "bounding_guided_h200x2_seeds")
RUNS = ([os.path.join(ROOT, "bounding_guided_h200")] + [os.path.join(STORED, f"seed{s}") for s in (1, 2, 3, 4)]
        + [os.path.join(STORED, "lr0.03", f"seed{s}") for s in (1, 2, 3, 4)])


def test_the_stored_comparison_is_its_runs():
    comp = bgs.compare(bgs.load(RUNS))
    with open(os.path.join(STORED, "comparison.json")) as f:
        stored = json.load(f)
    assert stored["summary"] == json.loads(json.dumps(comp["summary"]))
    assert stored["paired"] == json.loads(json.dumps(comp["paired"]))
    # every row is the run's own record, and pooling adds them up
    for r in comp["rows"]:
        with open(os.path.join(r["dir"], "results.json")) as f:
            res = json.load(f)
        c = res["comparison"][r["method"]]
        assert r["training_best"] == c["training_best"] and r["generations"] == c["generations"]
        assert r["target_falls"] == res["heldout"]["target"][r["method"]]["falls"]
    for member, s in comp["summary"].items():
        rs = [r for r in comp["rows"] if r["member"] == member]
        k, n = sum(r["target_falls"] for r in rs), sum(r["target_runs"] for r in rs)
        assert s["target"] == dict(falls=k, runs=n, ci95=list(wilson_interval(k, n)))
        assert s["target_met"] == sum(r["target_met"] for r in rs)
    assert set(comp["summary"]) == {"cma_es", "guided_es", "guided_es lr 0.03"}
    assert comp["summary"]["cma_es"]["seeds"] == [4242, 1, 2, 3, 4]


def test_paired_difference_matches_scipy_and_the_sign_test():
    rng = np.random.default_rng(3)
    a, b = rng.normal(1.0, 0.5, 7), rng.normal(0.6, 0.5, 7)
    d = bgs.paired_difference(a, b)
    ref = stats.ttest_rel(a, b)
    ci = ref.confidence_interval(0.95)
    assert d["mean"] == pytest.approx(float(np.mean(a - b)))
    assert d["ci95"] == pytest.approx([ci.low, ci.high], rel=1e-9)
    assert d["p"] == pytest.approx(ref.pvalue, rel=1e-9)
    assert d["a_lower"] + d["b_lower"] == 7
    assert d["p_sign"] == pytest.approx(stats.binomtest(d["a_lower"], 7).pvalue)
    # five seeds all one way: the sign test's smallest two-sided p for n = 5, 2 / 32
    assert bgs.paired_difference([1, 2, 3, 4, 5], [0, 0, 0, 0, 0])["p_sign"] == pytest.approx(2 / 32)
    assert bgs.paired_difference([1.0], [0.0]) is None


def test_a_guided_run_with_other_settings_is_its_own_member():
    runs = bgs.load(RUNS[:2])
    other = copy.deepcopy(runs[1])
    other["res"]["config"]["subspace"] = 3
    names = bgs.member_names([runs[0], other])
    assert names[0] == {"cma_es": "cma_es", "guided_es": "guided_es"}
    assert names[1] == {"cma_es": "cma_es", "guided_es": "guided_es subspace 3"}


def test_runs_that_are_not_comparable_are_refused_in_one_line(tmp_path, capsys):
    res = bgs.load(RUNS[1:2])[0]["res"]
    bad = copy.deepcopy(res)
    bad["config"]["broad_seed"] = 1234
    d = tmp_path / "other"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(bad))
    assert bgs.main([RUNS[1], str(d), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "broad_seed" in err[0]
    assert bgs.main([str(tmp_path / "missing"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RUN_DIR" in err[0] and not (tmp_path / "out").exists()
