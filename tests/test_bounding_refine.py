"""experiments/bounding_refine.py: the warm start, the training mixture, the option checks, and the held-out runner
(one padded call, split back by set) against separate runs."""
from __future__ import annotations

import os

import numpy as np
import pytest

from experiments import bounding_refine as br
from hyqjax import presets
from hyqjax.bounding import robust as rb
from hyqjax.bounding.params import params_of_values


def test_warm_start_reproduces_the_start_preset_exactly():
    space = rb.RobustSpace.make()
    for name in presets.names("bound"):
        vals = rb.load_params(name)
        theta0 = space.theta_of(vals)
        back = space.describe(theta0)
        assert set(back) == set(space.names)
        for k, v in back.items():  # a name the preset does not set stays at the paper's value (the space's start)
            assert v == pytest.approx(rb.value_of(presets.load(name), k), rel=1e-6, abs=1e-6), (name, k)
            if k in vals:
                assert v == pytest.approx(vals[k], rel=1e-12, abs=1e-9), (name, k)
        # the parameter object the refined sets are built from equals the preset's own
        a, b = params_of_values(back), presets.load(name)
        np.testing.assert_allclose(np.asarray(a.amplitudes), np.asarray(b.amplitudes), rtol=1e-6)
        for k in space.names:
            if k not in rb.AMPLITUDE_NAMES:
                assert float(getattr(a.gains, k)) == pytest.approx(float(getattr(b.gains, k)), rel=1e-6)


def test_training_mixture_weights_the_fast_corners():
    args = br.parse(["--train-envelope", "40", "--train-corners", "24", "--seed", "5"])
    batch, labels = br.training_batch(args)
    n = len(labels)
    assert n == 64 and int(np.sum(labels == "corners")) == 24
    speed = np.asarray(batch.params.command.velocity)[:, 0]
    lateral = np.asarray(batch.params.command.velocity)[:, 1]
    yaw = np.asarray(batch.params.command.yaw_rate)
    fr, pl = np.asarray(batch.terrain.friction), np.asarray(batch.terrain.payload_mass)
    c = labels == "corners"
    assert np.all((speed[c] >= 0.85) & (speed[c] <= 1.1))
    assert np.all((np.abs(yaw[c]) >= 0.65) & (np.abs(yaw[c]) <= 0.9))
    assert int(np.sum(yaw[c] > 0)) == int(np.sum(yaw[c] < 0)) == 12
    assert np.all((fr[c] >= 0.4) & (fr[c] <= 0.6)) and np.all((pl[c] >= 8.0) & (pl[c] <= 12.0))
    assert np.all(lateral[c] == 0.0)
    e = ~c  # the robust study's whole-envelope training draw
    assert np.all((speed[e] >= 0.0) & (speed[e] <= 1.1)) and np.all(np.abs(yaw[e]) <= 0.9)
    assert np.all((fr[e] >= 0.4) & (fr[e] <= 1.0)) and np.all((pl[e] >= 0.0) & (pl[e] <= 12.0))
    assert np.ptp(speed[e]) > 0.5 and np.any(fr[e] > 0.6)  # it spans the envelope, not only the corners
    # deterministic in the seed, different for another seed
    again, _ = br.training_batch(args)
    np.testing.assert_array_equal(np.asarray(again.apex0), np.asarray(batch.apex0))
    other, _ = br.training_batch(br.parse(["--train-envelope", "40", "--train-corners", "24", "--seed", "6"]))
    assert not np.allclose(np.asarray(other.apex0), np.asarray(batch.apex0))


@pytest.mark.parametrize("argv, needle", [
    (["--seed", "2911"], "--seed must differ"),
    (["--seed", "7777"], "--seed must differ"),
    (["--train-corners", "3"], "--train-corners must be even"),
    (["--start-preset", "paper"], "--start-preset paper is a crawl preset"),
    (["--start-preset", "nope"], "--start-preset must be one of"),
    (["--duration", "1.0"], "--duration must be a positive multiple"),
    (["--popsize", "2"], "--popsize must be an int"),
    (["--corner-yaw-rate", "0.9", "0.6"], "--corner-yaw-rate must be"),
    (["--impl", "fast"], "--impl"),
])
def test_bad_options_are_refused_in_one_line_before_anything_is_written(tmp_path, capsys, argv, needle):
    out = str(tmp_path / "out")
    assert br.main(argv + ["--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err
    assert not os.path.exists(out)


@pytest.mark.slow
def test_held_out_runner_pads_to_whole_chunks_and_splits_back_by_set():
    from hyqjax.bounding import envelope

    args = br.parse(["--instances", "1", "--duration", "0.8"])
    spec = dict(br.heldout_specs(args))["corners, low friction, payload"]  # 4 commands x 1 instance
    sets = {"start": presets.load("bound_robust"), "paper": presets.load("bound_paper")}
    cols = br.run_sets({n: spec.batch(b) for n, b in sets.items()}, 0.8, "c", chunk=3)  # 8 runs -> 9, chunks of 3
    for n, b in sets.items():
        alone = envelope.run(spec, b, "c")
        for k in ("success", "yaw_error_max_deg", "cost", "speed_cmd", "yaw_rate_cmd", "friction", "payload"):
            np.testing.assert_allclose(cols[n][k], alone[k], rtol=1e-6, err_msg=f"{n} {k}")
    assert not np.allclose(cols["start"]["cost"], cols["paper"]["cost"])
