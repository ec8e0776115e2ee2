"""The stored guided comparison on the 68 coordinates of ``per_leg_cond`` (``docs/results/tune_guided_h200x2_3min_68``,
two H200s, MuJoCo Warp, seeds 0-4): what docs/tuning.md says of it, recomputed from the per-seed records."""
import json
import os

import numpy as np
import pytest

STORED = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "tune_guided_h200x2_3min_68")
GUIDED, CMA, SNES = "guided_es/per_leg_cond", "cma_es/per_leg_cond", "snes/per_leg_cond"


@pytest.fixture(scope="module")
def results():
    from experiments.tune_study import finished_seeds

    out = finished_seeds(STORED)
    assert sorted(out) == [0, 1, 2, 3, 4]
    return out


def test_comparison_recomputed_from_the_seed_records_equals_the_stored_one(results):
    from hyqjax.studies.tune.study import guided

    comp = json.loads(json.dumps(guided.compare(results, 3)))
    with open(os.path.join(STORED, "comparison.json")) as f:
        assert comp == json.load(f)
    with open(os.path.join(STORED, "comparison.md")) as f:
        assert guided.markdown(comp) + "\n" == f.read()
    # SNES's interval over seeds lies above guided ES's; CMA-ES's overlaps it, though Welch's difference is above 0
    assert GUIDED in comp["summary"][SNES]["apart_from"] and GUIDED not in comp["summary"][CMA]["apart_from"]
    assert comp["summary"][CMA]["clean"]["ci95"][0] < comp["summary"][GUIDED]["clean"]["ci95"][1]
    assert comp["differences"][f"{CMA} - {GUIDED}"]["ci95"][0] > 0
    assert comp["differences"][f"{SNES} - {GUIDED}"]["p_two_sided"] < 0.01


def test_guided_es_returned_its_start_in_four_seeds_and_in_seed_4_an_iterate_inside_the_starts_interval(results):
    for s, res in results.items():
        assert res["complete"] and res["config"]["seed"] == s
        held = res["heldout"]
        for key in held:
            assert held[key]["failure_counts"]["diverged"] == 0, (s, key)
        sel = res["runs"][GUIDED]["selection"]["log"]
        if s < 4:
            assert [e["iteration"] for e in sel if e["selected"]] == [0]
            assert all(e["clean"] < sel[0]["clean"] for e in sel[1:])
            # the start's set, evaluated in another batch shape, differs by at most one of 512 outcomes
            assert abs(held[f"{GUIDED}@3min"]["clean"] - held["start"]["clean"]) * 512 <= 1
        else:  # its iteration 5 validated above the start and holds out 9 more clean of 512, inside its interval
            assert [e["iteration"] for e in sel if e["selected"]] == [0, 5]
            assert round((held[f"{GUIDED}@3min"]["clean"] - held["start"]["clean"]) * 512) == 9
            lo, hi = held["start"]["clean_ci95"]
            assert lo < held[f"{GUIDED}@3min"]["clean"] < hi


def test_the_surrogate_points_downhill_more_often_than_not_but_its_cosines_are_small(results):
    slopes, cosines, sampled = [], [], []
    for res in results.values():
        rows = res["runs"][GUIDED]["log"]
        slopes += [e["descent_slope"] for e in rows]
        cosines += [e["cos_zero_order"] for e in rows]
        sampled.append([e["cos_sampled"] for e in rows])
    assert len(slopes) == 45 and sum(x > 0 for x in slopes) == 33
    assert np.max(np.abs(cosines)) < 0.065
    # inside the sampled directions: a weak, mostly right-signed agreement in every seed
    assert all(0.1 < np.median(c) < 0.3 for c in sampled)
    assert sum(x > 0 for c in sampled for x in c) == 34


def test_warp_kernel_build_fell_in_the_first_processes_only_and_outside_the_clock(results):
    """The clock of a run in one segment is its wall less the kernel build plus its compile charges; a run resumed
    after a segment left out the restart's own seconds too."""
    for s, res in results.items():
        runs = res["runs"]
        builds = {k: r["kernel_build_s"] for k, r in runs.items()}
        if s in (0, 1):  # the first process on each GPU of a fresh machine: guided ES is its first method
            assert builds[GUIDED] > 60 and builds[CMA] == builds[SNES] == 0
        elif s == 4:  # a later process on another machine, its kernels built by an earlier one: loaded from the cache
            assert max(builds.values()) < 1.0
        else:
            assert set(builds.values()) == {0.0}
        for key, run in runs.items():
            assert 180 <= run["elapsed_s"] < 180 + 15, (s, key, run["elapsed_s"])
            clock = run["wall_s"] - run["kernel_build_s"] + run["charged_s"]
            if run["segments"] == 1:
                assert run["elapsed_s"] == pytest.approx(clock, abs=0.5), (s, key)
            else:
                assert run["elapsed_s"] < clock, (s, key)
