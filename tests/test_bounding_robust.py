"""Tests of the bound's command envelope and its robust baseline optimisation (hyqjax.bounding: tracking, envelope,
robust; experiments.bounding_envelope, experiments.bounding_robust).

Fast lane: the parameter space, stored parameters, the envelope's statistics and area, failure reasons, option
checks. Slow lane (two compiled programs, tiny; 8.5 minutes on 2 cores under a load average of 11, most of it
compile time): the
forward-mode derivative of the training cost against central differences, and a small map.
"""
from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.bounding import envelope as be
from hyqjax.bounding import falls
from hyqjax.bounding import params as bp
from hyqjax.bounding import robust as rb
from hyqjax.bounding import tracking as bt
from hyqjax.core.params import param_ranges


# ----------------------------------------------------------------------------------------------
# Parameter space and stored parameters
# ----------------------------------------------------------------------------------------------


def test_space_starts_at_the_paper_controller_and_stays_in_the_declared_ranges():
    base = bp.paper_params()
    sp = rb.RobustSpace.make(base)
    assert sp.size == len(rb.COORDS) == 22
    got = sp.describe(np.zeros(sp.size))
    for n in sp.names:
        assert got[n] == pytest.approx(rb.value_of(base, n), rel=1e-6, abs=1e-9)
    ranges = param_ranges(bp.BoundingGains)
    for name, scale, lo, hi in rb.COORDS:
        assert scale > 0 and lo < hi and lo <= rb.value_of(base, name) <= hi
        if name in ranges:
            assert ranges[name].in_range(np.array([lo, hi])).all(), name
    # Any theta, however large, gives parameters inside [lo, hi], which the parameter classes accept.
    rng = np.random.default_rng(0)
    for th in (rng.normal(0, 100, sp.size),):
        vals = sp.describe(th)
        p = rb.params_from_values(vals)
        assert p.validate() is p
        for name, _, lo, hi in rb.COORDS:
            assert lo - 1e-6 <= vals[name] <= hi + 1e-6
    # theta_of inverts values; apply writes the amplitudes on both legs of a pair and the gains.
    th = sp.theta_of(dict(a_fz=850.0, k_speed=300.0))
    p = sp.apply(jnp.asarray(th, jnp.float32), base)
    amp = np.asarray(p.amplitudes)
    assert amp[0, 2] == pytest.approx(850.0) and amp[1, 2] == pytest.approx(850.0)
    assert amp[2, 2] == pytest.approx(float(base.amplitudes[2, 2]))
    assert float(p.gains.k_speed) == pytest.approx(300.0)
    with pytest.raises(ValueError, match="names"):
        rb.RobustSpace.make(base, names=("k_unknown",))


def test_space_apply_is_differentiable():
    base = bp.paper_params()
    sp = rb.RobustSpace.make(base, names=("a_fz", "k_speed"))
    g = jax.jacfwd(lambda th: jnp.stack([sp.apply(th, base).amplitudes[1, 2], sp.apply(th, base).gains.k_speed]))(
        jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(g), np.diag([40.0, 100.0]), rtol=1e-6)


def test_stored_parameters_round_trip_and_bad_files(tmp_path):
    sp = rb.RobustSpace.make()
    vals = sp.describe(np.linspace(-1, 1, sp.size))
    path = tmp_path / "params.json"
    rb.save_params(path, vals, dict(method="test"))
    back = rb.load_params(path)
    assert back.keys() == vals.keys()
    for k in vals:
        assert back[k] == pytest.approx(vals[k], rel=1e-12)
    p = rb.params_from_values(back, speed=0.5)
    assert float(p.gains.k_yaw) == pytest.approx(vals["k_yaw"], rel=1e-6)
    assert float(p.amplitudes[2, 0]) == pytest.approx(vals["a_hx"], rel=1e-6)
    assert float(p.command.velocity[0]) == 0.5
    with pytest.raises(ValueError, match="unknown parameter"):
        rb.save_params(tmp_path / "x.json", dict(k_nope=1.0))
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(dict(format=rb.FORMAT, amplitudes={}, gains=dict(k_nope=1.0))))
    with pytest.raises(ValueError, match="k_nope"):
        rb.load_params(bad)
    bad.write_text("{")
    with pytest.raises(ValueError, match="bad.json"):
        rb.load_params(bad)
    # A stored value outside a declared range is refused when the controller is built, naming the gain.
    with pytest.raises(ValueError, match="k_speed"):
        rb.params_from_values(dict(k_speed=-5.0))


@pytest.mark.parametrize("preset, study, file", [("robust", "bounding_robust_h100", "params_gradient.json"),
                                                  ("robust_8s", "bounding_robust_h100_8s", "params_cma_es.json")])
def test_shipped_robust_presets_are_the_measured_results(preset, study, file):
    """Each shipped preset holds the parameters of its H100 study (``robust``: the gradient's of
    docs/results/bounding_robust_h100; ``robust_8s``: CMA-ES's of docs/results/bounding_robust_h100_8s) exactly,
    inside every declared range, and builds a controller that differs from the paper's (bound_paper) only in the 22
    optimised coordinates."""
    import os

    vals = rb.load_params(preset)
    assert rb.load_params(rb.preset_path(preset)) == vals
    measured = os.path.join(os.path.dirname(__file__), "..", "docs", "results", study, file)
    if os.path.exists(measured):  # a source checkout
        assert rb.load_params(measured) == vals
    assert set(vals) == {c[0] for c in rb.COORDS}
    for name, _, lo, hi in rb.COORDS:
        assert lo <= vals[name] <= hi, name
    p = rb.preset_params(preset, speed=0.5, yaw_rate=0.3)
    d = bp.paper_params(speed=0.5, yaw_rate=0.3)
    assert p.validate() is p
    sp = rb.RobustSpace.make(d)
    np.testing.assert_allclose(sp.values(sp.theta_of(vals), np), [vals[n] for n in sp.names], rtol=1e-12)
    for n in sp.names:
        assert rb.value_of(p, n) == pytest.approx(vals[n], rel=1e-6), n
    # Everything else (cycle apex, stance reference, gait, command, other gains) is the paper's: the preset is
    # the paper's controller moved along the optimised coordinates only.
    moved = sp.apply(jnp.asarray(sp.theta_of(vals), jnp.float32), d)
    leaves_p, tree_p = jax.tree_util.tree_flatten(p)
    leaves_m, tree_m = jax.tree_util.tree_flatten(moved)
    assert tree_p == tree_m
    for a, b in zip(leaves_p, leaves_m):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(p.amplitudes), np.asarray(d.amplitudes))
    with pytest.raises(ValueError, match="preset"):
        rb.preset_params("fastest")


def test_training_and_heldout_draws_are_disjoint_and_in_their_boxes():
    d = rb.Draw(speed=(0.0, 1.0), yaw_rate=(-0.8, 0.8), friction=(0.5, 1.0), payload=(0.0, 10.0))
    a, b = d.commands(500, seed=0), d.commands(500, seed=7777)
    assert not np.any(np.all(np.isclose(a[:, None], b[None]), -1))
    for c in (a, b):
        assert c[:, 0].min() >= 0 and c[:, 0].max() <= 1.0 and np.abs(c[:, 1]).max() <= 0.8 and np.all(c[:, 2] == 0)
    batch = d.batch(16, seed=3)
    fr, pm = np.asarray(batch.terrain.friction), np.asarray(batch.terrain.payload_mass)
    assert fr.min() >= 0.5 and fr.max() <= 1.0 and pm.min() >= 0 and pm.max() <= 10.0
    np.testing.assert_allclose(np.asarray(batch.params.command.velocity)[:, 0], d.commands(16, 3)[:, 0], rtol=1e-6)
    with pytest.raises(ValueError, match="speed"):
        rb.Draw(speed=(0.0, 2.0))
    # A population of candidates on a batch: candidate-major, the instances repeated per candidate.
    sp = rb.RobustSpace.make()
    th = np.zeros((3, sp.size))
    th[1, sp.names.index("k_yaw")] = 1.0
    pop = rb.population_batch(sp, th, batch)
    assert pop.apex0.shape == (48, 5)
    k_yaw = np.asarray(pop.params.gains.k_yaw)
    assert np.all(k_yaw[:16] == 200.0) and np.all(k_yaw[16:32] == 350.0)
    np.testing.assert_array_equal(np.asarray(pop.terrain.friction)[32:], fr)


# ----------------------------------------------------------------------------------------------
# Envelope statistics
# ----------------------------------------------------------------------------------------------


def test_envelope_spec_grid_batch_and_validation():
    spec = be.EnvelopeSpec(speeds=(0.0, 0.5), yaw_rates=(-0.5, 0.0, 0.5), lateral_speeds=(0.0, 0.2), instances=3)
    cmds = spec.commands
    assert cmds.shape == (12, 3) and spec.size == 36
    assert {tuple(c) for c in cmds} == {(v, w, l) for v in (0.0, 0.5) for w in (-0.5, 0.0, 0.5) for l in (0.0, 0.2)}
    b = spec.batch()
    fr = np.asarray(b.terrain.friction).reshape(12, 3)
    assert np.all(fr == fr[0]) and len(set(fr[0])) == 3  # common random numbers across commands
    np.testing.assert_allclose(np.asarray(b.params.command.velocity)[::3, 0], cmds[:, 0], atol=1e-7)
    for kw, name in ((dict(speeds=(0.0, 2.0)), "speeds"), (dict(instances=0), "instances"),
                     (dict(friction=(0.0, 1.0)), "friction"), (dict(payload=(3.0, 1.0)), "payload"),
                     (dict(lateral_speeds=(0.0, 0.0)), "lateral_speeds"), (dict(duration=0.1), "duration")):
        with pytest.raises(ValueError, match=name):
            be.EnvelopeSpec(**kw)


def _cols(success, reasons=(), yaw=None, n=None):
    n = len(success) if n is None else n
    c = dict(success=np.asarray(success, bool), yaw_error_max_deg=np.asarray(yaw if yaw is not None else [1.0] * n))
    for r in ("fell_low_trunk", "fell_roll", "fell_pitch", "diverged"):
        c[r] = np.array([r == x for x in (list(reasons) + [None] * n)[:n]])
    return c


def test_group_summary_counts_failures_with_reasons_and_wilson_intervals():
    cols = _cols([True] * 8 + [False, False], reasons=[None] * 8 + ["fell_pitch", "diverged"],
                 yaw=[1.0, 2.0, 3.0, 5.0, 1.0, 1.0, 1.0, 1.0, 30.0, np.nan])
    s = be.group_summary(cols)
    assert s["n"] == 10 and s["failures"] == 2 and s["reasons"] == dict(fell_pitch=1, diverged=1)
    assert s["fall_rate"] == pytest.approx(0.2)
    lo, hi = s["fall_rate_ci95"]
    assert 0.03 < lo < 0.2 < hi < 0.55
    # Yaw statistics over the survivors only: the fallen instance's 30 deg is not the worst.
    assert s["yaw_error_worst_deg"] == 5.0 and s["yaw_over_4deg"] == 1
    assert s["yaw_over_4deg_rate"] == pytest.approx(1 / 8)


def test_safe_area_is_the_area_owned_by_commands_below_the_threshold():
    spec = be.EnvelopeSpec(speeds=(0.0, 0.5, 1.0), yaw_rates=(-0.4, 0.0, 0.4), instances=100)
    np.testing.assert_allclose(be.cell_widths(spec.speeds), [0.25, 0.5, 0.25])
    pc = []
    for v, w, lat in spec.commands:
        fails = 5 if v == 1.0 else 0  # the fastest column falls 5% of the time
        pc.append(dict(speed=v, yaw_rate=w, lateral=lat, fall_rate=fails / 100,
                       fall_rate_ci95=list(be.statistics.wilson_interval(fails, 100))))
    a = be.safe_area(spec, pc)
    assert a["total_area"] == pytest.approx(1.0 * 0.8)
    assert a["area_point"] == pytest.approx(0.75 * 0.8)
    assert a["area_wilson"] == 0.0  # 0 of 100 cannot show a rate below 1% (upper bound 3.7%)
    g = be.grids(spec, pc, "fall_rate")
    assert g.shape == (1, 3, 3) and np.all(g[0, :, 2] == 0.05)


def test_columns_name_the_first_failure():
    fm = falls.FallMetrics(fall_tick=np.array([-1, 100, 300, 50]), low_trunk=np.array([False, True, False, False]),
                           roll=np.array([False, False, False, True]), pitch=np.zeros(4, bool),
                           ticks=np.full(4, 400), min_z=np.full(4, 0.5), max_roll=np.zeros(4),
                           max_pitch=np.zeros(4))
    z = np.zeros(4)
    ms = bt.TrackingMetrics(fall=fm, max_yaw_err=np.radians([1.0, 2, 3, 4]), eps=np.zeros((4, 2)),
                            settled_v=np.array([[4.0, 0.4], [0, 0], [0, 0], [0, 0]]), settled_n=np.array([8, 0, 0, 0]),
                            alive_n=np.array([400, 100, 300, 50]), sum_yaw2=z, sum_yaw_excess2=z,
                            sum_eps2=np.zeros((4, 2)), sum_margin=z, apex_n=np.ones(4, int), sum_apex2=z)
    c = bt.columns(ms, diverged=np.array([False, False, True, True]), diverged_tick=np.array([-1, -1, 200, 80]))
    assert list(c["success"]) == [True, False, False, False]
    assert list(c["fell_low_trunk"]) == [False, True, False, False]
    assert list(c["diverged"]) == [False, False, True, False]  # diverged at 200, before its fall at 300
    assert list(c["fell_roll"]) == [False, False, False, True]  # fell at 50, diverged later at 80
    np.testing.assert_allclose(c["fail_time"][1:], [0.202, 0.402, 0.102])
    assert c["speed_mean"][0] == 0.5 and np.isnan(c["speed_mean"][1])
    np.testing.assert_allclose(c["yaw_error_max_deg"], [1, 2, 3, 4])
    terms = bt.cost_terms(ms, bt.CostSpec(), np)
    assert list(terms["fall"]) == [0.0, 20.0, 20.0, 20.0] and set(terms) == set(bt.TERMS)


def test_experiment_options_are_checked_before_any_compile(capsys):
    from experiments import bounding_envelope, bounding_robust

    for argv, opt in ((["--train", "0"], "--train"), (["--train-speed", "0", "2"], "--train-speed"),
                      (["--heldout-duration", "1.3"], "--heldout-duration"), (["--impl", "cuda"], "--impl"),
                      (["--heldout-friction", "0", "1"], "--heldout-friction"),
                      (["--opt-seconds", "0"], "--opt-seconds")):
        assert bounding_robust.main(argv + ["--out", "/tmp/hyqjax_unused"]) == 2
        assert opt in capsys.readouterr().err
    for argv, opt in ((["--yaw-rates", "0", "1", "0"], "--yaw-rates"), (["--instances", "0"], "--instances"),
                      (["--params", "/nonexistent.json"], "nonexistent"), (["--duration", "1.0"], "--duration")):
        assert bounding_envelope.main(argv + ["--out", "/tmp/hyqjax_unused"]) == 2
        assert opt in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------
# Compiled: the gradient of the training cost, a small map
# ----------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_forward_mode_gradient_of_the_training_cost_matches_central_differences():
    """The gradient of make_value_and_jac (jacfwd through 0.4 s of the closed loop, MJX JAX, 4 tangents) along one
    direction against central differences of its own loss: one compiled program, called at theta and theta +- eps v."""
    sp = rb.RobustSpace.make(names=("a_fz", "a_hz", "k_yaw", "k_stance_pitch"))
    batch = rb.Draw(speed=(0.6, 0.6), yaw_rate=(0.5, 0.5)).batch(1, seed=0)
    g = rb.make_value_and_jac(sp, 0.4)
    args = rb.instance_args(batch)
    v = np.array([1.0, -1.0, 0.5, 0.5])
    eps = 0.05
    r0, rp, rm = (g(jnp.asarray(x * v, jnp.float32), args) for x in (0.0, eps, -eps))
    assert bool(r0["ok"][0]) and int(r0["falls"]) == 0 and int(r0["clipped"]) == 0
    der = float(np.asarray(r0["grad"]) @ v)
    fd = (float(rp["loss"]) - float(rm["loss"])) / (2 * eps)
    assert float(r0["loss"]) > 0 and abs(der) > 1e-3 * float(r0["loss"])  # the direction moves the cost
    assert der == pytest.approx(fd, rel=0.05), (float(r0["loss"]), der, fd)
    np.testing.assert_allclose(np.asarray(r0["grad"]), np.asarray(r0["grad_unclipped"]), rtol=1e-6)


@pytest.mark.slow
def test_small_map_tracks_and_counts():
    """Two commands x two instances, 3.2 s on C MuJoCo (the envelope's forward runs on a CPU): in place and 0.5 m/s
    turning at 0.3 rad/s bound without falling, with the yaw error below 4 deg and the settled speed near the
    command; the statistics and the area follow."""
    spec = be.EnvelopeSpec(speeds=(0.0, 0.5), yaw_rates=(0.3,), instances=2, friction=(0.7, 1.0), payload=(0.0, 5.0),
                           duration=3.2)
    cols = be.run(spec, impl="c")
    assert cols["success"].all(), cols
    assert np.all(cols["yaw_error_max_deg"] < 4.0) and np.all(cols["yaw_error_max_deg"] > 0)
    sp = cols["speed_mean"]
    assert np.all(np.abs(sp[:2]) < 0.15) and np.all(np.abs(sp[2:] - 0.5) < 0.2), sp
    assert np.all(np.isfinite(cols["cost"])) and np.all(cols["cost_fall"] == 0)
    pc = be.summarise(spec, cols)
    assert [c["speed"] for c in pc] == [0.0, 0.5] and all(c["failures"] == 0 for c in pc)
    assert be.safe_area(spec, pc)["area_point"] == 0.0  # one yaw rate: a line, no area


def test_heldout_instances_are_stored_one_row_each(tmp_path):
    """The robust-bounding study keeps every held-out instance (command, friction, payload and its outcome
    columns) so that a fall in its summary can be traced to the instance that fell."""
    import os

    from experiments.bounding_robust import save_heldout_instances
    from hyqjax.bounding import batch as bb2
    from hyqjax.bounding import params as bd2

    plist = [bd2.default_params(speed=0.9, yaw_rate=0.5), bd2.default_params(speed=0.2, yaw_rate=-0.3, lateral_speed=0.1)]
    batch = bb2.make_batch(plist, seed=5, rand=bb2.Randomisation(friction=(0.5, 0.9), payload=(0.0, 10.0)))
    cols = dict(success=np.array([True, False]), fell_pitch=np.array([False, True]),
                yaw_error_max_deg=np.array([2.5, np.nan]), cost=np.array([0.1, 3.0]), scalar_total=np.float64(3.1))
    name = save_heldout_instances(str(tmp_path / "heldout_gradient.npz"), batch, cols)
    z = np.load(tmp_path / name)
    np.testing.assert_allclose(z["speed_cmd"], [0.9, 0.2], rtol=1e-6)
    np.testing.assert_allclose(z["yaw_rate_cmd"], [0.5, -0.3], rtol=1e-6)
    np.testing.assert_allclose(z["lateral_cmd"], [0.0, 0.1], atol=1e-7)
    np.testing.assert_allclose(z["friction"], np.asarray(batch.terrain.friction))
    assert np.all((z["friction"] >= 0.5) & (z["friction"] <= 0.9)) and np.all(z["payload"] <= 10.0)
    assert z["fell_pitch"].tolist() == [False, True] and np.isnan(z["yaw_error_max_deg"][1])
    assert "scalar_total" not in z.files and not [f for f in os.listdir(tmp_path) if ".tmp" in f]
