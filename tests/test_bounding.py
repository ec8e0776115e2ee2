"""Tests of the bounding gait (hyqjax.bounding, bounding_cycle, bounding_experiment, commands/bound).

CPU-sized: two compiled programs (one batched forward-mode return map, one batched closed-loop rollout),
about 3-4 minutes on 2 cores, most of it XLA compile time.
"""
from __future__ import annotations

import argparse

import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax import bounding as bd, bounding_cycle as bc, bounding_experiment as bx

#: Periodicity tolerance of the stored cycle: scaled residual norm (Eq. C2 units: 1 = 1 cm, 0.01 rad,
#: 0.05 m/s, 0.05 m/s, 0.1 rad/s, 1 cm of drift). 0.01 means e.g. 0.1 mm of height, 1e-4 rad of pitch (measured: 3.4e-4).
PERIODIC_TOL = 0.01
#: Forward mode vs central differences (eps = 2 N on 800 N amplitudes, float32 MJX): relative tolerance on
#: the Jacobian columns' norm (measured: 2e-4).
GRAD_RTOL = 0.01


# ----------------------------------------------------------------------------------------------
# Pure pieces (fast)
# ----------------------------------------------------------------------------------------------


def test_profile_impulse_matches_kappa_and_park_kim_balance():
    for prof in ("half_sine", "bezier"):
        gait = bd.GaitParams.make(profile=prof)
        s = jnp.linspace(0.0, 1.0, 20001)
        beta = np.asarray(bd.profile(gait, s))
        assert beta[0] == pytest.approx(0.0, abs=1e-6) and beta[-1] == pytest.approx(0.0, abs=1e-6)
        assert np.trapezoid(beta, np.asarray(s)) == pytest.approx(float(gait.kappa), rel=1e-4)
        assert float(bd.profile(gait, jnp.float32(1.5))) == 0.0
        # Eq. B2: weight carried over a period and zero net pitch moment about com_x.
        af, ah = bd.impulse_guess(gait, mass=80.0, com_x=0.01)
        d, T, k = np.asarray(gait.duty), float(gait.period), float(gait.kappa)
        xf, xh = float(gait.foot_xy[0, 0]), float(gait.foot_xy[2, 0])
        assert 2 * k * (af * d[0] + ah * d[1]) * T == pytest.approx(80.0 * 9.81 * T, rel=1e-6)
        assert af * d[0] * (xf - 0.01) + ah * d[1] * (xh - 0.01) == pytest.approx(0.0, abs=1e-6)


def test_leg_phase_stance_windows():
    gait = bd.GaitParams.make(period=0.4, duty=(0.4, 0.4), touchdown_phase=(0.55, 0.05))
    st, s_st, _ = bd.leg_phase(gait, jnp.float32(0.0))  # apex: all legs in flight
    assert not np.any(np.asarray(st))
    st, s_st, _ = bd.leg_phase(gait, jnp.float32(0.1))  # hind mid-stance window
    assert list(np.asarray(st)) == [False, False, True, True]
    assert np.allclose(np.asarray(s_st)[2:], (0.25 - 0.05) / 0.4, atol=1e-5)
    st, _, _ = bd.leg_phase(gait, jnp.float32(0.3))  # front stance
    assert list(np.asarray(st)) == [True, True, False, False]


def test_centrifugal_compensation_leans_into_the_turn():
    # Right turn (psidot < 0) at 1 m/s: feet move outward (+y), trunk rolls right-side down (phi > 0).
    a_y, dy, lean = (float(v) for v in bd.centrifugal_compensation(1.0, -0.5, 0.6))
    assert a_y == pytest.approx(-0.5)
    assert dy == pytest.approx(0.6 * 0.5 / 9.81, rel=1e-5) and dy > 0
    assert lean == pytest.approx(np.arctan(dy / 0.6), rel=1e-5)
    assert all(float(v) == 0.0 for v in bd.centrifugal_compensation(1.0, -0.5, 0.6, on=0.0))


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
        (lambda: bd.default_params(cycle_apex=[0.1, 0, 0, 0, 0]), "cycle_apex"),
        (lambda: bx.Randomisation(friction=(0.0, 1.0)), "friction"),
        (lambda: bx.make_batch([bd.default_params()] * 3, n_unique=2), "n_unique"),
        (lambda: bx.make_batch([bd.default_params()], push_force=1e5), "push_force"),
        (lambda: bc.optimise_cycle(bd.default_params(), np.zeros((1, 8)), method="bfgs"), "method"),
        (lambda: bc.gradient_check(bd.default_params(), np.zeros(8), indices=(9,)), "indices"),
        (lambda: bc.initial_guesses(bd.default_params(), 0), "n"),
    ]
    for fn, name in cases:
        with pytest.raises(ValueError, match=name):
            fn()


def test_aggregate_and_contributions_keep_failures_and_measure_side_slip():
    def inst(result, yaw, slip):
        return dict(result=result, yaw_error_max_deg=yaw, yaw_error_rms_deg=yaw / 2, speed_error_mean_abs=0.01,
                    speed_error_rms=0.02, yaw_rate_error_rms=0.001, periodicity_residual=0.5, lateral_speed_mean=slip)

    full = bx.aggregate([inst("ok", 1.0, 0.01), inst("ok", 2.0, -0.03), inst("pitch", 9.0, 0.5)])
    assert full["n"] == 3 and full["falls"] == 1 and full["fail_reasons"] == ["pitch"]
    # Tracking errors over the surviving instances only; the fall is counted, not averaged in.
    assert full["yaw_error_max_deg_mean"] == pytest.approx(1.5) and full["yaw_error_max_deg_worst"] == 2.0
    assert full["side_slip_mean"] == pytest.approx(0.02) and full["side_slip_worst"] == pytest.approx(0.03)
    off = bx.aggregate([inst("ok", 1.0, 0.25), inst("ok", 2.0, -0.25), inst("ok", 3.0, 0.25)])
    groups = {k: dict(aggregate=v) for k, v in
              dict(full=full, no_kinematic_adjustment=full, no_centrifugal=off, neither=off).items()}
    c = bx.contributions(groups)
    assert c["centrifugal"]["side_slip_mean_increase_when_off"] == pytest.approx(0.23)
    assert c["centrifugal"]["falls_increase_when_off"] == pytest.approx(-1.0)
    assert c["kinematic_adjustment"]["side_slip_mean_increase_when_off"] == pytest.approx(0.0)


def test_cli_validation_names_the_option():
    from hyqjax.commands import bound

    p = argparse.ArgumentParser()
    bound.add_arguments(p)
    for argv, name in ((["--duration", "1.3"], "--duration"), (["--instances", "0"], "--instances"),
                       (["--friction", "0.9", "0.5"], "--friction"), (["--payload", "-1"], "--payload"),
                       (["--speed", "9"], "--speed"), (["--yaw-rate", "-2"], "--yaw-rate"),
                       (["--lateral-speed", "nan"], "--lateral-speed"), (["--ramp-time", "-1"], "--ramp-time"),
                       (["--push", "1e5"], "--push"), (["--push-duration", "11"], "--push-duration")):
        with pytest.raises(ValueError, match=name):
            bound._validate(p.parse_args(argv))
    with pytest.raises(ValueError, match="speed"):
        bound.run(p.parse_args(["--speed", "9", "--out", "/tmp/hyqjax_test_bound_unused"]))


# ----------------------------------------------------------------------------------------------
# Return map: forward-mode gradient vs finite differences, periodicity (one compiled vmap of jvp)
# ----------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cycle_check():
    params = bd.default_params(apex_feedback=False, stance_feedback=False)
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


# ----------------------------------------------------------------------------------------------
# Closed loop: in place, forward, turning (one compiled batched rollout)
# ----------------------------------------------------------------------------------------------

SCENARIOS = [dict(), dict(), dict(), dict(speed=0.5), dict(speed=0.8), dict(speed=0.5, yaw_rate=0.4),
             dict(speed=0.5, yaw_rate=-0.4)]
DURATION = 6.0


@pytest.fixture(scope="module")
def closed_loop():
    plist = [bd.default_params(**s) for s in SCENARIOS]
    batch = bx.make_batch(plist, seed=3)
    res, trace = bx.run(batch, duration=DURATION)
    summary = bx.summarise(res, trace, batch)
    return res, trace, summary


@pytest.mark.slow
def test_bounds_in_place_without_falling(closed_loop):
    res, trace, summary = closed_loop
    assert not np.any(np.asarray(res.diverged))
    for i in range(3):
        p = summary["instances"][i]
        assert p["result"] == "ok", p
        assert p["min_height"] > 0.45 and p["max_roll_deg"] < 10.0 and p["max_pitch_deg"] < 20.0, p
        assert np.all(np.isfinite(trace["pos"][i]))
        # In place: little drift, and the motion is periodic (median apex-to-apex residual, Eq. C2 units).
        assert abs(p["speed_mean"]) < 0.1, p
        assert p["periodicity_residual"] < 2.0, p
        # Really bounding: the trunk pitches (front/hind alternation) by several degrees.
        assert np.ptp(trace["rpy"][i, 100:, 1]) > np.radians(8.0)


@pytest.mark.slow
def test_speed_control_tracks_forward_speed(closed_loop):
    _, trace, summary = closed_loop
    for i in (3, 4):
        p = summary["instances"][i]
        assert p["result"] == "ok", p
        assert trace["pos"][i, -1, 0] > 0.5 * p["speed_cmd"] * (DURATION - 1.5)
        assert p["speed_error_mean_abs"] < 0.1, p
    # Faster command, faster robot.
    assert summary["instances"][4]["speed_mean"] > summary["instances"][3]["speed_mean"] + 0.15


@pytest.mark.slow
def test_turning_follows_yaw_rate_sign_and_magnitude(closed_loop):
    _, trace, summary = closed_loop
    for i in (5, 6):
        p = summary["instances"][i]
        assert p["result"] == "ok", p
        assert np.sign(p["yaw_rate_mean"]) == np.sign(p["yaw_rate_cmd"])
        assert abs(p["yaw_rate_mean"] - p["yaw_rate_cmd"]) < 0.1, p
        assert p["yaw_error_max_deg"] < 4.0, p  # the paper: below 4 deg on HyQ
    # Straight bounding does not turn.
    for i in range(5):
        assert abs(summary["instances"][i]["yaw_rate_mean"]) < 0.05


@pytest.mark.slow
def test_trace_records_the_state_render_needs(closed_loop):
    """The bounding trace carries the full qpos (what `hyqjax render` replays) consistent with the trunk trace."""
    _, trace, _ = closed_loop
    assert trace["qpos"].shape[-1] == 19 and trace["foot_force"].shape[-2:] == (4, 3)
    np.testing.assert_allclose(trace["qpos"][..., :3], trace["pos"], atol=1e-6)
