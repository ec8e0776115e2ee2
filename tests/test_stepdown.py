"""The step-down experiment (Focchi et al. 2017, Section IV) at CPU size: the paper's qualitative result.

One compiled batch: a 16 cm and a 24 cm platform, the reflex off and on, one instance each (the same
randomised instance for every pair), 24 s of closed-loop crawling at 0.1 m/s.
"""
from __future__ import annotations

import numpy as np
import pytest

from hyqjax import crawl, stepdown

HEIGHTS = (0.16, 0.24)


@pytest.fixture(scope="module")
def stepdown_run():
    scenario, table = stepdown.make_scenarios(HEIGHTS, [False, True], 1, seed=0,
                                              params=crawl.CrawlParams.make(forward_velocity=0.1))
    out, _ = stepdown.run_batch(scenario, stepdown.StepdownConfig(duration=24.0))
    return table, out


def _row(table, out, height, reflex):
    i = int(np.nonzero((table["height"] == height) & (table["reflex"] == reflex))[0][0])
    return {k: v[i] for k, v in out.items()}


@pytest.mark.slow
def test_reflex_is_needed_at_24_cm(stepdown_run):
    table, out = stepdown_run
    off, on = _row(table, out, 0.24, False), _row(table, out, 0.24, True)
    # Without the reflex a swing leg stretches to its workspace limit before finding the ground: stance is
    # triggered with the foot in the air (the paper's failure mode).
    assert not off["success"]
    assert off["lost_footholds"] >= 1 and off["n_limit_stops"] >= 1
    # With it, the stance legs take over part of the searching motion and every foot finds the ground.
    # The one failure the reflex does not address is a front shin resting on the edge when a foot lands
    # just past it (blind crawl; 42% of runs at 24 cm on a GPU, README): allowed here, nothing else is.
    assert on["failure_reason"] in ("", "shin strike"), on["failure_reason"]
    assert on["lost_footholds"] == 0 and on["n_limit_stops"] == 0
    assert np.isfinite(on["time_all_down"])
    assert on["min_swing_mobility"] > off["min_swing_mobility"] + 0.01


@pytest.mark.slow
def test_16_cm_every_foot_finds_the_ground_with_the_reflex(stepdown_run):
    table, out = stepdown_run
    on = _row(table, out, 0.16, True)
    assert on["failure_reason"] in ("", "shin strike"), on["failure_reason"]
    assert on["lost_footholds"] == 0 and np.isfinite(on["time_all_down"])
    assert on["peak_pitch"] < 0.4 and on["peak_roll"] < 0.4


@pytest.mark.slow
def test_no_instance_diverges_and_metrics_are_finite(stepdown_run):
    _, out = stepdown_run
    assert not np.any(out["diverged"])
    for k in ("peak_pitch", "peak_roll", "mean_mobility", "min_swing_mobility", "progress"):
        assert np.all(np.isfinite(out[k])), k
    assert np.all(out["progress"] > 0.5)


def test_scenarios_pair_reflex_on_and_off_on_identical_instances():
    _, table = stepdown.make_scenarios([0.16, 0.21], [False, True], 3, seed=7)
    for k in ("friction", "payload_mass", "start_distance", "lateral_offset", "yaw"):
        v = table[k].reshape(2, 2, 3)
        assert np.array_equal(v[:, 0], v[:, 1]) and np.array_equal(v[0], v[1]), k


def test_bad_height_is_rejected_before_compiling():
    with pytest.raises(ValueError, match="platform_height"):
        stepdown.make_scenarios([0.6], [True], 1, seed=0)
