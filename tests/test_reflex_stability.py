"""The reflex's step-size stability condition (hyqjax.reflex.params), its failure flag, its retrace guard
and hypothesis tests of Eq. 3-6 against a float64 NumPy reference."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core.params import ParameterError
from hyqjax.reflex import params as RP
from hyqjax.reflex import step as R

N_TICKS = 300
X_STAND = np.asarray(kinematics.foot_positions(np.asarray(robot.Q_STANDING)))


def unchecked(params, **kw):
    """``params`` with fields replaced without validation (PyTree unflatten), to run refused sets."""
    leaves = [kw.get(f.name, getattr(params, f.name)) for f in dataclasses.fields(params)]
    return jax.tree_util.tree_unflatten(jax.tree.structure(params), leaves)


@jax.jit
def search(params, dx, leg, depth, speed, tilt, dt):
    """A downward haptic search (Section II) of ``leg`` from perturbed standing feet, ``N_TICKS`` ticks.

    Returns (all finite and no fallback, any tick flagged failed, first tick flagged failed)."""
    x0 = jnp.asarray(X_STAND, jnp.float32) + dx
    t = jnp.arange(N_TICKS, dtype=jnp.float32) * dt
    x_des = jnp.repeat(x0[None], N_TICKS, 0).at[:, leg, 2].add(-jnp.minimum(speed * t, depth))
    n_des = R.planned_terrain_normal(x0, leg) + tilt
    inputs = R.ReflexInputs(x_des=x_des, swing_leg=jnp.full(N_TICKS, leg, jnp.int32), active=jnp.ones(N_TICKS, bool),
                            n_t_des=jnp.tile(n_des, (N_TICKS, 1)),
                            up=jnp.tile(jnp.asarray([0.0, 0.0, 1.0]), (N_TICKS, 1)))
    _, out = R.reflex_rollout(R.reflex_init(x0), inputs, params, dt)
    finite = jnp.all(jnp.isfinite(out.q_r)) & jnp.all(jnp.isfinite(out.x_r)) & jnp.all(jnp.isfinite(out.f_r))
    finite = finite & jnp.all(out.input_ok)
    return finite, jnp.any(out.failed), jnp.argmax(out.failed)


def _f32(p):
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), p)


def _run(p, dt, leg=1, depth=0.1, speed=0.3):
    return search(_f32(p), jnp.zeros((4, 3), jnp.float32), leg, jnp.float32(depth), jnp.float32(speed),
                  jnp.zeros(3, jnp.float32), jnp.float32(dt))


# Two sets that passed the ranges before the stability condition existed, and blew up at dt = 2 ms.
COUNTEREXAMPLES = [
    dict(k_x=2e4, d_sw_min=0.01, d_sw_max=0.02, d_st_min=0.01, d_st_max=0.02),
    dict(k_x=2e4, d_sw_min=0.01, d_sw_max=0.02),
    dict(k_x=5000.0, d_sw_min=0.5, d_sw_max=1.0),
]


@pytest.mark.slow
@pytest.mark.parametrize("kw", COUNTEREXAMPLES)
def test_unstable_sets_refused_and_their_blow_up_flagged(kw):
    p = R.ReflexParams(**kw)  # inside the declared ranges
    with pytest.raises(ParameterError, match=r"^ReflexParams\.d_s[wt]_min=.* must be > .* for stability at dt=0\.002"):
        p.validate(dt=0.002)
    x0 = jnp.asarray(X_STAND, jnp.float32)
    inputs = R.ReflexInputs.make(x0.at[1, 2].add(-0.1), 1)
    with pytest.raises(ParameterError, match="stability"):
        R.reflex_step(R.reflex_init(x0), inputs, p, 0.002)
    from hyqjax.reflex import realtime

    with pytest.raises(ParameterError, match="stability"):
        realtime.make_realtime_reflex(p, 0.002)
    # Run anyway (traced, unchecked): the state leaves the finite numbers or the fallback runs, and the
    # reflex's failure flag says so within the first 150 ticks (0.3 s).
    finite, failed, first = _run(p, 0.002)
    assert bool(failed) and int(first) < 150
    # Accepted at a control period that satisfies the condition, and then it stays finite, never failing.
    lam = max(RP.stability_rates(p, xp=np))
    dt_ok = 1.9 / float(lam)
    p.validate(dt=dt_ok)
    finite, failed, _ = _run(p, dt_ok)
    assert bool(finite) and not bool(failed)


def _boundary_params(draw):
    """A parameter set drawn over the declared ranges with the dampings just above (factor 1 + 1e-4 .. 3)
    what the stability condition requires at ``dt``, plus ``dt``."""
    dt = draw(st.sampled_from([5e-4, 1e-3, 2e-3, 5e-3, 0.02]))
    logu = lambda lo, hi: draw(st.floats(np.log(lo), np.log(hi)).map(np.exp))  # noqa: E731
    k_x, k_x_max = logu(1.0, 1e5), logu(1.0, 1e6)
    k_x_max = max(k_x_max, k_x)
    k_base, k_kl = logu(1.0, 1e5), logu(1.0, 1e5)
    lam_sw = RP.SWING_COMPLIANCE * min(k_x, k_x_max) + k_kl
    lam_st = RP.BASE_COMPLIANCE * k_base + k_kl
    d_sw_min = max(1e-3, 0.5 * dt * lam_sw * logu(1.0 + 1e-4, 3.0))
    d_st_min = max(1e-3, 0.5 * dt * lam_st * logu(1.0 + 1e-4, 3.0))
    d_sw_max = min(1e5, d_sw_min * logu(1.001, 1e3))
    d_st_max = min(1e5, d_st_min * logu(1.001, 1e3))
    m_min = draw(st.floats(0.02, 0.5))
    m_max = m_min + draw(st.floats(1e-3, 0.3))
    return dict(k_x=k_x, k_x_max=k_x_max, k_base=k_base, k_kl=k_kl, delta=draw(st.floats(0.01, 0.45)),
                d_sw_min=d_sw_min, d_sw_max=d_sw_max, d_st_min=d_st_min, d_st_max=d_st_max, m_min=m_min,
                m_max=m_max), dt


@pytest.mark.slow
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])
@given(st.data())
def test_accepted_parameters_stay_finite(data):
    """Any set ``validate(dt=dt)`` accepts (drawn near the boundary of the condition, the hardest case)
    stays finite (no fallback) over a 300-tick search, from perturbed stances, any swing leg, with a tilted
    reference normal (Eq. 8 active) and unreachable depths (end stops active). (``failed`` may still flag
    a joint turned far past its range by end-stop springs too weak for the swing spring.)"""
    kw, dt = _boundary_params(data.draw)
    try:
        p = R.ReflexParams(**kw).validate(dt=dt)
    except ParameterError:  # a clipped damping bound (1e5) or m_max above 1: outside the declaration
        return
    dx = np.asarray(data.draw(st.lists(st.floats(-0.06, 0.06), min_size=12, max_size=12))).reshape(4, 3)
    leg = data.draw(st.integers(0, 3))
    depth, speed = data.draw(st.floats(0.02, 0.4)), data.draw(st.floats(0.05, 1.0))
    tilt = np.asarray(data.draw(st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3)))
    finite, failed, _ = search(_f32(p), jnp.asarray(dx, jnp.float32), leg, jnp.float32(depth), jnp.float32(speed),
                               jnp.asarray(tilt, jnp.float32), jnp.float32(dt))
    assert bool(finite), (kw, dt)


@pytest.mark.slow
def test_dt_checked():
    x0 = jnp.asarray(X_STAND, jnp.float32)
    inputs = R.ReflexInputs.make(x0, 1)
    for dt in (-1.0, 0.0, 0.03, float("nan")):
        with pytest.raises(ParameterError, match=r"^reflex\.dt=.* must be in \(0, 0\.02\] s"):
            R.reflex_step(R.reflex_init(x0), inputs, R.ReflexParams(), dt)
    # Table I: dt lambda_max = 1.6 at 2 ms, refused above 2.5 ms.
    assert float(RP.stability_number(R.ReflexParams(), 0.002)) == pytest.approx(0.8)
    R.ReflexParams().validate(dt=0.0024)
    with pytest.raises(ParameterError, match="d_sw_min=5 out of range: must be > 5.2"):
        R.ReflexParams().validate(dt=0.0026)


def test_swing_compliance_bounds_every_leg_jacobian(x64):
    """``SWING_COMPLIANCE`` >= sigma_max(J)^2 of every leg over all joint angles (random sample, float64)."""
    rng = np.random.default_rng(0)
    q = jnp.asarray(rng.uniform(-np.pi, np.pi, (20000, 12)))
    s = np.linalg.svd(np.asarray(jax.jit(kinematics.foot_jacobians)(q)), compute_uv=False)
    assert (s[..., 0] ** 2).max() <= RP.SWING_COMPLIANCE
    assert (s[..., 0] ** 2).max() > 0.95 * RP.SWING_COMPLIANCE  # and is close: not an arbitrary margin


@pytest.mark.slow
def test_linearised_rates_real_and_bounded(x64):
    """Eigenvalues of ``-d qd / d q`` of the reflex (Eq. 10) at perturbed stances are real, >= 0, and
    below the bound of :mod:`hyqjax.reflex.params` per unit K_x / D_sw and K_base / D_st."""
    base = R.ReflexParams()

    def rates(q, leg, k_x, k_base):
        p = unchecked(base, k_x=k_x, k_x_max=1e9, k_base=k_base, k_kl=0.0, d_st_min=1.0, d_st_max=1.0 + 1e-9,
                      d_sw_min=1.0, d_sw_max=1.0 + 1e-9)
        inputs = R.ReflexInputs.make(kinematics.foot_positions(q), leg, True)  # at rest: f_sw = 0, e_b = 0

        def qd(qq):
            return R.reflex_step(R.ReflexState(qq, jnp.zeros(12)), inputs, p, 1e-3)[1].qd_r

        return jnp.linalg.eigvals(-jax.jacfwd(qd)(q))

    f = jax.jit(jax.vmap(rates, in_axes=(0, 0, None, None)))
    rng = np.random.default_rng(1)
    n = 300
    x = jnp.asarray(X_STAND[None] + rng.uniform(-0.08, 0.08, (n, 4, 3)))
    q = kinematics.inverse_kinematics(x).reshape(n, 12)
    legs = jnp.asarray(rng.integers(0, 4, n))
    for k_x, k_base, bound in ((1.0, 0.0, RP.SWING_COMPLIANCE), (0.0, 1.0, RP.BASE_COMPLIANCE)):
        ev = np.asarray(f(q, legs, k_x, k_base))
        assert np.abs(ev.imag).max() < 1e-9 and ev.real.min() > -1e-9
        assert ev.real.max() <= bound
        assert ev.real.max() > 0.6 * bound  # the bound is attained up to a stated margin


@pytest.mark.slow
def test_reflex_step_does_not_retrace():
    """A jitted reflex_step traces once: new values of the state, inputs, parameters and dt reuse it."""
    traces = []

    @jax.jit
    def step(state, inputs, params, dt):
        traces.append(1)
        return R.reflex_step(state, inputs, params, dt)

    x0 = jnp.asarray(X_STAND, jnp.float32)
    for i, (params, leg) in enumerate(((R.ReflexParams(), 1), (R.ReflexParams(k_base=800.0, d_sw_min=7.0), 2))):
        state = R.reflex_init(x0)
        inputs = R.ReflexInputs.make(x0.at[leg, 2].add(-0.01 * (i + 1)), leg)
        state, out = step(state, inputs, _f32(params), jnp.float32(1e-3 * (i + 1)))
        assert bool(out.active)
    assert len(traces) == 1


# ---------------------------------------------------------------------------------------------
# Eq. 3-6 against a float64 NumPy reference, hypothesis-driven
# ---------------------------------------------------------------------------------------------


@jax.jit
def _eq6_case(dx, d, f_sw, e_b, tau, up, swing, k_base):
    """Feet, Jacobians, the reflex's forces (Eq. 2-6) and the literal Eq. 6 system at perturbed stances."""
    q = kinematics.inverse_kinematics(jnp.asarray(X_STAND) + dx).reshape(12)
    x, j = kinematics.foot_positions(q), kinematics.foot_jacobians(q)
    p = unchecked(R.ReflexParams(), k_base=k_base)
    f_r, degenerate = R.distribute_virtual_forces(x, f_sw, swing, j, d, e_b, p, up=up, tau_kl=tau,
                                                  return_degenerate=True)
    a_mat, b_vec = R.eq6_system(x, f_sw, swing, j, d, e_b, p, up, tau)
    return x, j, f_r, degenerate, a_mat, b_vec


def vec(n, lo, hi):
    return st.lists(st.floats(lo, hi, allow_subnormal=False), min_size=n, max_size=n).map(np.asarray)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(vec(12, -0.06, 0.06), vec(12, np.log(5.0), np.log(1000.0)), vec(3, -500, 500), vec(3, -0.2, 0.2),
       vec(12, -30, 30), vec(2, -0.2, 0.2), st.integers(0, 3), vec(3, 0.0, 5000.0))
@pytest.mark.slow
def test_eq3_to_6_residuals_float64(x64, dx, log_d, f_sw, e_b, tau, tilt, swing, k_base):
    """Eq. 3 (force and moment balance), Eq. 4-5 (stance distances kept, with end-stop torques) and the
    literal 9x9 system of Eq. 6, all evaluated in NumPy float64 on the JAX float64 solution."""
    d = np.exp(log_d)
    up = np.r_[tilt, 1.0]
    x, j, f_r, degenerate, a_mat, b_vec = (np.asarray(v) for v in _eq6_case(
        dx.reshape(4, 3), d, f_sw, e_b, tau, up, swing, k_base))
    assert not degenerate
    f_r = np.asarray(f_r)
    stance = list(R.STANCE_LEGS[swing])
    e_z = up / np.linalg.norm(up)
    np.testing.assert_array_equal(f_r[swing], f_sw)
    scale = 1.0 + np.abs(f_sw).max() + np.abs(k_base * e_b).max()
    # Eq. 3: sum f_st = -e_z e_z^T f_sw; sum (x_i - x_sw) x f_i = -K_base e_b.
    assert np.abs(f_r[stance].sum(0) + e_z * (e_z @ f_sw)).max() < 1e-9 * scale
    moment = np.cross(x[stance] - x[swing], f_r[stance]).sum(0)
    assert np.abs(moment + k_base * e_b).max() < 1e-9 * scale
    # Eq. 4-5: the stance-feet distances do not change under qd = D^-1 (J^T f + tau_kl).
    qd = (np.einsum("lij,li->lj", j, f_r).reshape(12) + tau) / d
    xd = np.einsum("lij,lj->li", j, qd.reshape(4, 3))
    for a, b in R.STANCE_PAIRS:
        ia, ib = stance[a], stance[b]
        assert abs((x[ia] - x[ib]) @ (xd[ia] - xd[ib])) < 1e-9 * (1.0 + np.abs(xd).max())
    # Eq. 6: the same forces solve the literal 9x9 system.
    res = np.asarray(a_mat) @ f_r[stance].reshape(9) - np.asarray(b_vec)
    assert np.abs(res).max() < 1e-8 * scale
