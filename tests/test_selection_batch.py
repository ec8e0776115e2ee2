"""``python -m experiments.selection_batch``: tuned sets and the tuner's start on the default tuner's validation
batch in another simulator, paired against the start."""
import json
import os

import pytest

STUDY = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "tune_default_repeats_clean_30_h200x2",
                     "study")


@pytest.mark.parametrize("argv, says", [
    (["--tuned-run", "run_0:only_two"], "--tuned-run 'run_0:only_two': must be NAME:PATH:RUN"),
    (["--tuned-run", "a:b:c", "--instances", "6"], "--instances: select_instances must be a multiple of 4"),
    (["--tuned-run", "a:/nowhere/results.json:c"], "--tuned-run a:/nowhere/results.json:c: cannot read"),
])
def test_bad_input_is_refused_in_one_line(tmp_path, capsys, argv, says):
    from experiments import selection_batch

    assert selection_batch.main(["--out", str(tmp_path)] + argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]


@pytest.mark.slow
def test_a_set_gives_the_same_outcomes_at_any_batch_position_and_its_recorded_score(tmp_path):
    """The same stored iterate twice in one C MuJoCo batch (rows of other members between them) gives the same
    outcome on every step-down, the validation score shown is the one the run recorded for that checkpoint on MuJoCo
    Warp (0.847 for run 0 at 10 minutes), and the rows by height add up to the pooled ones."""
    from experiments import selection_batch

    path = os.path.join(STUDY, "run_0", "results.json")
    sets = [f"a:{path}:cma_es/per_leg@10min", f"ret:{path}:cma_es/per_leg", f"b:{path}:cma_es/per_leg@10min"]
    argv = ["--out", str(tmp_path), "--impl", "c", "--instances", "8"]
    assert selection_batch.main(argv + [x for s in sets for x in ("--tuned-run", s)]) == 0
    with open(tmp_path / "selection_batch.json") as f:
        out = json.load(f)
    rows = {r["name"]: r for r in out["sets"]}
    assert out["impl"] == "c" and out["instances"] == 8 and list(rows) == ["start", "a", "ret", "b"]
    for k in ("clean", "completed", "only_set", "only_start", "d"):
        assert rows["a"][k] == rows["b"][k], k
    assert rows["a"]["recorded_validation_clean"] == pytest.approx(0.8474, abs=1e-4)
    assert rows["start"]["recorded_validation_clean"] is None and rows["start"]["p_mcnemar"] is None
    for r in rows.values():
        assert r["d"] == pytest.approx((r["only_set"] - r["only_start"]) / 8)
        assert [h["height"] for h in r["per_height"]] == [0.16, 0.2, 0.24, 0.28]  # the training heights, 2 each
        for k in ("n", "clean", "completed", "only_set", "only_start"):
            assert sum(h[k] for h in r["per_height"]) == r[k], k
    text = (tmp_path / "selection_batch.md").read_text()
    assert text.count("\n| ") == 5 and "Minus the start by height" in text
