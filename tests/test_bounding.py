"""Tests of the bounding gait (hyqjax.bounding: params, gait, controller, cycle, batch, rollout, summary; cli/bound).

CPU-sized: two compiled MJX programs (one batched forward-mode return map, one Levenberg-Marquardt step) and the
closed-loop batch on C MuJoCo (its controller compiled in JAX), about 2 minutes on 2 cores, most of it XLA tracing and
compiling the MJX programs.
"""
from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.bounding import batch as bbatch
from hyqjax.bounding import controller as bctrl
from hyqjax.bounding import cycle as bc
from hyqjax.bounding import defaults as bdef
from hyqjax.bounding import gait as bgait
from hyqjax.bounding import params as bd
from hyqjax.bounding import rollout as brollout
from hyqjax.bounding import summary as bs

#: Periodicity tolerance of the stored cycle: scaled residual norm (Eq. C2 units: 1 = 1 cm, 0.01 rad,
#: 0.05 m/s, 0.05 m/s, 0.1 rad/s, 1 cm of drift). 0.01 means e.g. 0.1 mm of height, 1e-4 rad of pitch (measured: 3.4e-4).
PERIODIC_TOL = 0.01
#: Forward mode vs central differences (eps = 2 N on 800 N amplitudes, float32 MJX): relative tolerance on
#: the Jacobian columns' norm (measured: 2e-4).
GRAD_RTOL = 0.01


# ----------------------------------------------------------------------------------------------
# Pure pieces (fast)
# ----------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_profile_impulse_matches_kappa_and_park_kim_balance():
    for prof in ("half_sine", "bezier"):
        gait = bd.GaitParams.make(profile=prof)
        s = jnp.linspace(0.0, 1.0, 20001)
        beta = np.asarray(bgait.profile(gait, s))
        assert beta[0] == pytest.approx(0.0, abs=1e-6) and beta[-1] == pytest.approx(0.0, abs=1e-6)
        assert np.trapezoid(beta, np.asarray(s)) == pytest.approx(float(gait.kappa), rel=1e-4)
        assert float(bgait.profile(gait, jnp.float32(1.5))) == 0.0
        # Eq. B2: weight carried over a period and zero net pitch moment about com_x.
        af, ah = bgait.impulse_guess(gait, mass=80.0, com_x=0.01)
        d, T, k = np.asarray(gait.duty), float(gait.period), float(gait.kappa)
        xf, xh = float(gait.foot_xy[0, 0]), float(gait.foot_xy[2, 0])
        assert 2 * k * (af * d[0] + ah * d[1]) * T == pytest.approx(80.0 * 9.81 * T, rel=1e-6)
        assert af * d[0] * (xf - 0.01) + ah * d[1] * (xh - 0.01) == pytest.approx(0.0, abs=1e-6)


def test_leg_phase_stance_windows():
    gait = bd.GaitParams.make(period=0.4, duty=(0.4, 0.4), touchdown_phase=(0.55, 0.05))
    st, s_st, _ = bgait.leg_phase(gait, jnp.float32(0.0))  # apex: all legs in flight
    assert not np.any(np.asarray(st))
    st, s_st, _ = bgait.leg_phase(gait, jnp.float32(0.1))  # hind mid-stance window
    assert list(np.asarray(st)) == [False, False, True, True]
    assert np.allclose(np.asarray(s_st)[2:], (0.25 - 0.05) / 0.4, atol=1e-5)
    st, _, _ = bgait.leg_phase(gait, jnp.float32(0.3))  # front stance
    assert list(np.asarray(st)) == [True, True, False, False]


def test_centrifugal_compensation_leans_into_the_turn():
    # Right turn (psidot < 0) at 1 m/s: feet move outward (+y), trunk rolls right-side down (phi > 0).
    a_y, dy, lean = (float(v) for v in bctrl.centrifugal_compensation(1.0, -0.5, 0.6))
    assert a_y == pytest.approx(-0.5)
    assert dy == pytest.approx(0.6 * 0.5 / 9.81, rel=1e-5) and dy > 0
    assert lean == pytest.approx(np.arctan(dy / 0.6), rel=1e-5)
    assert all(float(v) == 0.0 for v in bctrl.centrifugal_compensation(1.0, -0.5, 0.6, on=0.0))


def test_input_validation_names_the_parameter():
    cases = [
        (lambda: bd.BoundingCommand.make(speed=3.0), "speed"),
        (lambda: bd.BoundingCommand.make(yaw_rate=-2.0), "yaw_rate"),
        (lambda: bd.GaitParams.make(period=0.05), "period"),
        (lambda: bd.GaitParams.make(duty=(0.95, 0.4)), "duty"),
        (lambda: bd.GaitParams.make(touchdown_phase=(0.7, 0.05)), "touchdown_phase"),
        (lambda: bd.GaitParams.make(profile="square"), "profile"),
        (lambda: bd.GaitParams.make(bezier=(0.1, 1.0, 0.0)), "bezier"),
        (lambda: bd.BoundingGains.make(k_speed=-1.0), "k_speed"),
        (lambda: bd.BoundingGains.make(tau_est=0.0), "tau_est"),
        (lambda: bd.paper_params(cycle_apex=[0.1, 0, 0, 0, 0]), "cycle_apex"),
        (lambda: bbatch.Randomisation(friction=(0.0, 1.0)), "friction"),
        (lambda: bbatch.make_batch([bd.paper_params()] * 3, n_unique=2), "n_unique"),
        (lambda: bbatch.make_batch([bd.paper_params()], push_force=1e5), "push_force"),
        (lambda: bc.optimise_cycle(bd.paper_params(), np.full((1, 8), np.nan)), "u0"),
        (lambda: bc.optimise_cycle(bd.paper_params(), np.zeros((1, 8)), iterations=0), "iterations"),
        (lambda: bd.paper_params().replace(mass=jnp.float32(-1.0)), "mass"),
        (lambda: bd.BoundingGains.make(k_unknown=1.0), "k_unknown"),
        (lambda: bbatch.validate_run(speed=5.0), "speed"),
        (lambda: bbatch.validate_run(instances=0), "instances"),
        (lambda: bbatch.validate_run(friction=(2.0, 1.0)), "friction"),
        (lambda: bbatch.validate_run(payload=(0.0, float("nan"))), "payload"),
        (lambda: bbatch.validate_run(duration=1.3), "duration"),
        (lambda: bbatch.validate_run(push=float("inf")), "push"),
        (lambda: bbatch.validate_run(seed=-1), "seed"),
        (lambda: bc.gradient_check(bd.paper_params(), np.zeros(8), indices=(9,)), "indices"),
        (lambda: bc.initial_guesses(bd.paper_params(), 0), "n"),
    ]
    for fn, name in cases:
        with pytest.raises(ValueError, match=name):
            fn()


@pytest.mark.slow
def test_parameters_validate_batched_leaves_and_stay_differentiable():
    plist = [bd.paper_params(speed=v) for v in (0.0, 0.5, 1.0)]
    batch = bbatch.stack_params(plist)
    assert batch.validate() is batch  # batched leaves are checked element-wise
    with pytest.raises(ValueError, match="k_speed"):  # one bad element of a batch is refused
        dataclasses.replace(batch.gains, k_speed=jnp.array([200.0, -1.0, 200.0]))
    # jax rebuilds the PyTree for gradients (any sign): no validation error, and d a_fz / d k_height of Eq. B4 is
    # a*_fz (z* - z_k) (alpha not clipped).
    p = plist[0]
    apex = p.apex_ref._replace(z=p.apex_ref.z - 0.01)
    zero2 = jnp.zeros(2)

    def a_fz(gains):
        q = dataclasses.replace(p, gains=gains)
        return bctrl.cycle_amplitudes(q, apex, jnp.zeros(3), zero2, jnp.zeros(4))[0, 2]

    g = jax.grad(a_fz)(p.gains)
    assert float(g.k_height) == pytest.approx(float(p.amplitudes[0, 2]) * 0.01, rel=1e-4)
    assert float(g.k_pitch) == pytest.approx(0.0, abs=1e-6)


def test_apex_sample_is_named_and_round_trips():
    a = bd.Apex.of(jnp.arange(5.0))
    assert bd.APEX_NAMES == ("z", "pitch", "vx", "vz", "pitch_rate") and float(a.vz) == 3.0
    np.testing.assert_array_equal(np.asarray(a.array()), np.arange(5.0))
    p = bd.paper_params()
    np.testing.assert_allclose(np.asarray(p.apex_ref.array()), bdef.stored().apex, rtol=1e-6)


def test_cycle_file_round_trip_and_bad_file(tmp_path):
    c = bdef.stored()
    u = c.decision_vector()
    assert u.shape == (8,) and u[4] == c.apex[0] and u[7] == c.apex[2]
    path = tmp_path / "cycle.json"
    bdef.save(path, u, c.reference, c.apex_gains, dict(note="round trip"))
    back = bdef.load(path)
    np.testing.assert_allclose(back.amplitudes, c.amplitudes, rtol=1e-7)
    np.testing.assert_allclose(back.apex, c.apex, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(back.reference, c.reference, rtol=1e-7)
    assert back.apex_gains == c.apex_gains and back.provenance == dict(note="round trip")
    path.write_text('{"amplitudes": {"a_fz": 1.0}}')
    with pytest.raises(ValueError, match="cycle.json"):
        bdef.load(path)


def test_per_cycle_speeds_of_a_circular_run():
    # A trunk on a circle of radius R at yaw rate w, heading tangent: per cycle the chord 2 R sin(w T / 2) / T
    # along the mid-cycle heading, no lateral speed, yaw rate w.
    period, dt, w, radius = 0.4, 0.02, 0.5, 2.0
    t = np.arange(0.0, 4.0 + 1e-9, dt)
    pos = np.stack([radius * np.sin(w * t), radius * (1 - np.cos(w * t)), np.full_like(t, 0.6)], -1)
    rpy = np.stack([np.zeros_like(t), np.zeros_like(t), bs.wrap_angle(w * t)], -1)
    trace = dict(t=np.stack([t, t]), pos=np.stack([pos, pos]), rpy=np.stack([rpy, rpy]))
    idx, v_fwd, v_lat, yaw_rate = bs.per_cycle(trace, period, control_dt=dt)
    assert len(idx) == 11 and np.allclose(t[idx], np.arange(11) * period)
    np.testing.assert_allclose(v_fwd, 2 * radius * np.sin(w * period / 2) / period, rtol=1e-9)
    np.testing.assert_allclose(v_lat, 0.0, atol=1e-12)
    np.testing.assert_allclose(yaw_rate, w, rtol=1e-9)


def test_aggregate_and_contributions_keep_failures_and_measure_side_slip():
    def inst(result, yaw, slip):
        flags = {r: r == result for r in bs.FAIL_REASONS}
        return bs.InstanceResult(success=result == "ok", **flags, fail_time=None if result == "ok" else 1.0,
                                 yaw_error_max_deg=yaw, yaw_error_rms_deg=yaw / 2, speed_cmd=0.5, yaw_rate_cmd=0.3,
                                 speed_mean=0.5, speed_error_mean_abs=0.01, speed_error_rms=0.02,
                                 lateral_speed_mean=slip, yaw_rate_mean=0.3, yaw_rate_error_rms=0.001,
                                 periodicity_residual=0.5)

    full = bs.aggregate([inst("ok", 1.0, 0.01), inst("ok", 2.0, -0.03), inst("fell_pitch", 9.0, 0.5)])
    assert full["n"] == 3 and full["falls"] == 1 and full["fail_reasons"] == ["fell_pitch"]
    # Tracking errors over the surviving instances only; the fall is counted, not averaged in.
    assert full["yaw_error_max_deg_mean"] == pytest.approx(1.5) and full["yaw_error_max_deg_worst"] == 2.0
    assert full["side_slip_mean"] == pytest.approx(0.02) and full["side_slip_worst"] == pytest.approx(0.03)
    off = bs.aggregate([inst("ok", 1.0, 0.25), inst("ok", 2.0, -0.25), inst("ok", 3.0, 0.25)])
    groups = {k: dict(aggregate=v) for k, v in
              dict(full=full, no_kinematic_adjustment=full, no_centrifugal=off, neither=off).items()}
    c = bs.contributions(groups)
    assert c["centrifugal"]["side_slip_mean_increase_when_off"] == pytest.approx(0.23)
    assert c["centrifugal"]["falls_increase_when_off"] == pytest.approx(-1.0)
    assert c["kinematic_adjustment"]["side_slip_mean_increase_when_off"] == pytest.approx(0.0)


def test_cli_validation_names_the_option():
    from hyqjax.cli import bound

    p = argparse.ArgumentParser()
    bound.add_arguments(p)
    for argv, name in ((["--duration", "1.3"], "--duration"), (["--instances", "0"], "--instances"),
                       (["--friction", "0.9", "0.5"], "--friction"), (["--payload", "-1"], "--payload"),
                       (["--speed", "9"], "--speed"), (["--yaw-rate", "-2"], "--yaw-rate"),
                       (["--lateral-speed", "nan"], "--lateral-speed"), (["--ramp-time", "-1"], "--ramp-time"),
                       (["--push", "1e5"], "--push"), (["--push-duration", "11"], "--push-duration")):
        with pytest.raises(ValueError, match=name):
            bound.check_options(p.parse_args(argv))
    with pytest.raises(ValueError, match="speed"):
        bound.run(p.parse_args(["--speed", "9", "--out", "/tmp/hyqjax_test_bound_unused"]))


# ----------------------------------------------------------------------------------------------
# Return map: forward-mode gradient vs finite differences, periodicity (one compiled vmap of jvp)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cycle_check():
    params = bd.paper_params(apex_feedback=False, stance_feedback=False)
    u = bc.stored_cycle()
    return bc.gradient_check(params, u, indices=(0, 1), eps=(2.0, 2.0))


@pytest.mark.slow
def test_forward_mode_gradient_matches_central_differences(cycle_check):
    _, j_fwd, j_fd = cycle_check
    assert np.all(np.isfinite(j_fwd)) and np.all(np.isfinite(j_fd))
    # The amplitudes move the apex state: the Jacobian is not trivially zero (>= 0.02 scaled units per N).
    assert np.linalg.norm(j_fwd[:, 0]) > 0.02 and np.linalg.norm(j_fwd[:, 1]) > 0.02
    for k in range(2):
        err = np.linalg.norm(j_fwd[:, k] - j_fd[:, k])
        assert err <= GRAD_RTOL * np.linalg.norm(j_fd[:, k]), (k, j_fwd[:, k], j_fd[:, k])


@pytest.mark.slow
def test_stored_cycle_is_periodic(cycle_check):
    r0, _, _ = cycle_check
    assert r0.shape == (6,)
    assert np.linalg.norm(r0) < PERIODIC_TOL, r0


def test_levenberg_marquardt_batch_rows_are_their_single_runs():
    """The cycle's Levenberg-Marquardt driver on Rosenbrock's residual ``(10 (x1 - x0^2), 1 - x0)``: a batch of two
    guesses (``vmap``) gives each guess's run alone (no ``vmap``: ``vmap_unless_one``) to float32 rounding, both
    reach the minimum (1, 1) within 1e-3, the second stopping early, and a guess that starts there keeps it."""
    def f(x):
        return jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])

    x0 = jnp.asarray([[-1.2, 1.0], [0.5, -0.3]], jnp.float32)
    xb, rb, sb = bc.levenberg_marquardt(f, x0, 30, 1e-6, 1e-6)
    for i in range(2):
        x1, r1, s1 = bc.levenberg_marquardt(f, x0[i:i + 1], 30, 1e-6, 1e-6)
        np.testing.assert_allclose(np.asarray(xb[i]), np.asarray(x1[0]), atol=1e-5)
        np.testing.assert_allclose(rb[:, i], r1[:, 0], atol=1e-4)
        assert sb[i] == s1[0]
    np.testing.assert_allclose(np.asarray(xb), 1.0, atol=1e-3)
    assert rb.shape == (30, 2, 2) and sb[1] < 30
    xs, _, ss = bc.levenberg_marquardt(f, jnp.ones((1, 2), jnp.float32), 3, 1e-6, 1e-6)
    np.testing.assert_array_equal(np.asarray(xs), 1.0)
    assert ss[0] <= 1


@pytest.mark.slow
def test_levenberg_marquardt_returns_to_the_cycle():
    """optimistix's LM with forward-mode Jacobians, from the stored cycle with its vertical impulses moved by
    +-15 N: three LM steps shrink the periodicity residual (Eq. C2) by more than 10x."""
    params = bd.paper_params(apex_feedback=False, stance_feedback=False)
    u0 = bc.stored_cycle() + np.array([15.0, -15.0, 0, 0, 0, 0, 0, 0])
    res = bc.optimise_cycle(params, u0[None], iterations=3, progress=False)
    r0, r1 = res.residual_history[0, 0], res.residual_norm[0]  # at the guess, at the last accepted iterate
    assert res.history.shape == (3, 1) and np.isfinite(r1)
    assert r0 > 0.1, r0  # the perturbation really breaks periodicity
    assert r1 < 0.1 * r0 and r1 < 0.05, (r0, r1)
    assert np.all(np.diff(res.history[:, 0]) <= 1e-6 * res.history[0, 0])  # LM accepts only steps lowering Eq. C2


# ----------------------------------------------------------------------------------------------
# Closed loop: in place, forward, turning (one batch of 6 s runs on C MuJoCo: the controller's properties, in about a
# third of MJX-JAX's time on a CPU; the bound on MJX-JAX, and C MuJoCo following it, are tests/test_api.py's)
# ----------------------------------------------------------------------------------------------

SCENARIOS = [dict(), dict(), dict(), dict(speed=0.5), dict(speed=0.8), dict(speed=0.5, yaw_rate=0.4),
             dict(speed=0.5, yaw_rate=-0.4)]
DURATION = 6.0


@pytest.fixture(scope="module")
def closed_loop():
    plist = [bd.paper_params(**s) for s in SCENARIOS]
    batch = bbatch.make_batch(plist, seed=3)
    res, trace = brollout.run(batch, duration=DURATION, impl="c")
    summary = bs.summarise(res, trace, batch)
    return res, trace, summary


@pytest.mark.slow
def test_bounds_in_place_without_falling(closed_loop):
    res, trace, summary = closed_loop
    assert not np.any(np.asarray(res.diverged))
    for i in range(3):
        p = summary.instances[i]
        assert p.success, p
        assert p.min_height > 0.45 and p.max_roll_deg < 10.0 and p.max_pitch_deg < 20.0, p
        assert np.all(np.isfinite(trace["pos"][i]))
        # In place: little drift, and the motion is periodic (median apex-to-apex residual, Eq. C2 units).
        assert abs(p.speed_mean) < 0.1, p
        assert p.periodicity_residual < 2.0, p
        # Really bounding: the trunk pitches (front/hind alternation) by several degrees.
        assert np.ptp(trace["rpy"][i, 100:, 1]) > np.radians(8.0)


@pytest.mark.slow
def test_speed_control_tracks_forward_speed(closed_loop):
    _, trace, summary = closed_loop
    for i in (3, 4):
        p = summary.instances[i]
        assert p.success, p
        assert trace["pos"][i, -1, 0] > 0.5 * p.speed_cmd * (DURATION - 1.5)
        assert p.speed_error_mean_abs < 0.1, p
    # Faster command, faster robot.
    assert summary.instances[4].speed_mean > summary.instances[3].speed_mean + 0.15


@pytest.mark.slow
def test_turning_follows_yaw_rate_sign_and_magnitude(closed_loop):
    _, trace, summary = closed_loop
    for i in (5, 6):
        p = summary.instances[i]
        assert p.success, p
        assert np.sign(p.yaw_rate_mean) == np.sign(p.yaw_rate_cmd)
        assert abs(p.yaw_rate_mean - p.yaw_rate_cmd) < 0.1, p
        assert p.yaw_error_max_deg < 4.0, p  # the paper: below 4 deg on HyQ
    # Straight bounding does not turn.
    for i in range(5):
        assert abs(summary.instances[i].yaw_rate_mean) < 0.05


@pytest.mark.slow
def test_trace_records_the_state_render_needs(closed_loop):
    """The bounding trace carries the full qpos (what `hyqjax render` replays) consistent with the trunk trace."""
    _, trace, _ = closed_loop
    assert trace["qpos"].shape[-1] == 19 and trace["foot_force"].shape[-2:] == (4, 3)
    np.testing.assert_allclose(trace["qpos"][..., :3], trace["pos"], atol=1e-6)
