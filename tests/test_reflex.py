"""Tests of the height reflex (Focchi et al. 2017, Section III) in ``hyqjax.reflex.step``.

Every test jits what it calls. Float64 tests enable x64 through the ``x64`` fixture, which
restores the previous setting afterwards.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core.params import ParameterError
from hyqjax.reflex import step as R

DT = 1e-3
RF, LH = robot.RF, robot.LH


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


# Small helpers are jitted too: run eagerly, every primitive would be compiled on its own.
@functools.partial(jax.jit, static_argnames=("dtype",))
def standing_feet(dtype=jnp.float64):
    return kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, dtype))


@jax.jit
def constant_inputs(x_des, swing_leg):
    """Active inputs for ``swing_leg`` with the plan ``x_des`` and ``n_t^d`` from the plan."""
    return R.ReflexInputs.make(x_des, jnp.asarray(swing_leg, jnp.int32), True)


init = jax.jit(R.reflex_init)


def search_inputs(x0, swing_leg, depth, speed, n_steps, dt=DT):
    """Downward searching plan (Section II): the swing foot descends at ``speed`` to ``depth``."""
    t = jnp.arange(n_steps, dtype=x0.dtype) * dt
    z = -jnp.minimum(speed * t, depth)
    x_des = jnp.repeat(x0[None], n_steps, 0).at[:, swing_leg, 2].add(z)
    n_des = R.planned_terrain_normal(x0, swing_leg)
    return R.ReflexInputs(
        x_des=x_des,
        swing_leg=jnp.full(n_steps, swing_leg, jnp.int32),
        active=jnp.ones(n_steps, bool),
        n_t_des=jnp.tile(n_des, (n_steps, 1)),
        up=jnp.tile(jnp.asarray([0.0, 0.0, 1.0], x0.dtype), (n_steps, 1)),
    )


@jax.jit
def step(state, inputs, params):
    return R.reflex_step(state, inputs, params, DT)


@jax.jit
def rollout_seq(state, inputs, params):
    """Rollout over per-tick inputs (leading time axis)."""
    return R.reflex_rollout(state, inputs, params, DT)


def rollout_const(state, inputs, params, n_steps):
    """Rollout with constant inputs (tiled in time, so it shares ``rollout_seq``'s compilation)."""
    seq = jax.tree.map(lambda a: jnp.broadcast_to(a, (n_steps,) + jnp.shape(a)), inputs)
    return rollout_seq(state, seq, params)


@jax.jit
def search_rollout(params):
    """5 s downward search of the RF foot at 0.1 m/s to 20 cm below standing (Section II)."""
    x0 = standing_feet(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    return rollout_seq(R.reflex_init(x0), search_inputs(x0, RF, depth=0.2, speed=0.1, n_steps=5000), params)


def unchecked(params, **kw):
    """``params`` with fields replaced *without* validation (PyTree unflatten), to test the fallbacks."""
    names = [f.name for f in dataclasses.fields(params)]
    leaves = [kw.get(n, getattr(params, n)) for n in names]
    return jax.tree_util.tree_unflatten(jax.tree.structure(params), leaves)


def stance_distances(x_feet, swing_leg):
    st = x_feet[..., R.STANCE_LEGS[swing_leg], :]
    return np.stack([np.linalg.norm(st[..., i, :] - st[..., j, :], axis=-1) for i, j in R.STANCE_PAIRS], -1)


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"d_st_min": -1.0}, "d_st_min"),
        ({"d_st_min": 2000.0}, "d_st_min"),
        ({"d_sw_min": 200.0}, "d_sw_min"),
        ({"d_sw_max": 0.0}, "d_sw_max"),
        ({"m_min": 0.0}, "m_min"),
        ({"m_min": 0.3}, "m_min"),
        ({"delta": 0.0}, "delta"),
        ({"delta": 0.6}, "delta"),
        ({"k_base": -5.0}, "k_base"),
        ({"k_kl": -1.0}, "k_kl"),
        ({"k_x": 3e4}, "k_x"),
        ({"k_x": float("nan")}, "k_x"),
        ({"k_x_max": float("inf")}, "k_x_max"),
        ({"k_x": "stiff"}, "k_x"),
        ({"d_sw_min": -5.0}, "d_sw_min"),
    ],
)
def test_validation_names_parameter(kwargs, name):
    """Construction, ``make``, ``replace`` and ``dataclasses.replace`` all refuse, naming the field."""
    for build in (lambda: R.ReflexParams.make(**kwargs), lambda: R.ReflexParams(**kwargs),
                  lambda: R.ReflexParams().replace(**kwargs), lambda: dataclasses.replace(R.ReflexParams(), **kwargs)):
        with pytest.raises(ParameterError, match=rf"^ReflexParams\.{name}=.*must be") as e:
            build()
        assert "\n" not in str(e.value) and e.value.param == name


def test_table1_defaults_and_pytree():
    p = R.ReflexParams.table1()
    assert (p.k_x, p.k_base, p.k_kl, p.delta) == (5000.0, 1500.0, 1000.0, 0.05)
    assert (p.d_st_min, p.d_st_max, p.d_sw_min, p.d_sw_max, p.m_min, p.m_max) == (50, 1000, 5, 100, 0.19, 0.21)
    assert len(jax.tree.leaves(p)) == 11
    with pytest.raises(ValueError, match="unknown"):
        R.ReflexParams.make(k_z=1.0)
    with pytest.raises(ValueError, match="outside jit"):
        jax.jit(lambda k: R.ReflexParams(k_x=k).validate())(1.0)
    # Built inside a transformation (traced values), parameters are not checked there.
    assert float(jax.jit(lambda k: R.ReflexParams(k_x=k).replace(k_base=2 * k).k_base)(3.0)) == 6.0
    # vmap over a batch of parameter sets.
    batch = jax.tree.map(lambda a: jnp.full((3,), a), p).replace(k_base=jnp.asarray([100.0, 1500.0, 3000.0]))
    d = jax.jit(jax.vmap(lambda pp: R.damping_schedule(0.2, pp)[0]))(batch)
    assert d.shape == (3,)


# ---------------------------------------------------------------------------------------------
# Eq. 3-6: virtual force distribution
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_eq3_static_equilibrium_random_layouts(x64):
    rng = np.random.default_rng(0)
    n = 32
    base = np.array([[0.37, 0.32, -0.57], [0.37, -0.32, -0.57], [-0.37, 0.32, -0.57], [-0.37, -0.32, -0.57]])
    x_feet = jnp.asarray(base + rng.uniform(-0.06, 0.06, (n, 4, 3)))
    q = kinematics.inverse_kinematics(x_feet).reshape(n, 12)
    x_feet = kinematics.foot_positions(q)  # exactly consistent with q
    j_legs = kinematics.foot_jacobians(q)
    d_diag = jnp.asarray(rng.uniform(5.0, 1000.0, (n, 12)))
    f_sw = jnp.asarray(rng.normal(0.0, 300.0, (n, 3)))
    e_b = jnp.asarray(rng.normal(0.0, 0.1, (n, 3)))
    tau = jnp.asarray(rng.normal(0.0, 20.0, (n, 12)))
    up = jnp.asarray(np.c_[rng.normal(0, 0.1, (n, 2)), np.ones(n)])
    params = R.ReflexParams(k_base=jnp.asarray([100.0, 1500.0, 800.0]))

    @jax.jit
    def solve(swing):  # swing is traced: one compilation for the four swing legs
        f = jax.vmap(
            lambda x, j, d, fs, e, t, u: R.distribute_virtual_forces(
                x, fs, swing, j, d, e, params, up=u, tau_kl=t, return_degenerate=True
            )
        )
        a_b = jax.vmap(lambda x, j, d, fs, e, t, u: R.eq6_system(x, fs, swing, j, d, e, params, up=u, tau_kl=t))
        args = (x_feet, j_legs, d_diag, f_sw, e_b, tau, up)
        return f(*args), a_b(*args)

    for swing in range(4):
        (f_r, degenerate), (a, b) = solve(jnp.asarray(swing))
        assert not np.any(degenerate)
        f_r, xf = np.asarray(f_r), np.asarray(x_feet)
        st = R.STANCE_LEGS[swing]
        e_z = np.asarray(up) / np.linalg.norm(up, axis=-1, keepdims=True)
        f_perp = e_z * np.sum(e_z * np.asarray(f_sw), -1, keepdims=True)
        # Swing row is f_sw itself.
        np.testing.assert_allclose(f_r[:, swing], np.asarray(f_sw), rtol=0, atol=1e-12)
        # Force rows: sum f_i = -f_sw_perp.
        force_res = f_r[:, st].sum(1) + f_perp
        assert np.abs(force_res).max() < 1e-8
        # Moment rows about the swing foot: sum (x_i - x_sw) x f_i = -K_base e_b.
        lever = xf[:, st] - xf[:, swing][:, None]
        moment_res = np.cross(lever, f_r[:, st]).sum(1) + np.asarray([100.0, 1500.0, 800.0]) * np.asarray(e_b)
        assert np.abs(moment_res).max() < 1e-8
        # Same as the literal 9x9 solve of Eq. 6.
        ref = np.linalg.solve(np.asarray(a), np.asarray(b)[..., None])[..., 0]
        np.testing.assert_allclose(f_r[:, st].reshape(n, 9), ref, rtol=1e-9, atol=1e-8)
        # Eq. 5 (with end-stop torques): relative stance velocities along the edges vanish.
        qd = (np.einsum("nlij,nli->nlj", np.asarray(j_legs), f_r).reshape(n, 12) + np.asarray(tau)) / np.asarray(d_diag)
        jt = jax.jit(jax.vmap(R.relative_distance_jacobian, in_axes=(0, 0, None)))(x_feet, j_legs, swing)
        assert np.abs(np.einsum("nkj,nj->nk", np.asarray(jt), qd)).max() < 1e-10


@pytest.mark.slow
def test_eq4_stance_distances_constant_along_trajectory(x64):
    x0 = standing_feet()
    inputs = constant_inputs(x0.at[RF, 2].add(-0.3), RF)  # target far below the workspace
    _, out = rollout_const(init(x0), inputs, R.ReflexParams(), 300)
    x_r = np.asarray(out.x_r)
    d = stance_distances(np.concatenate([np.asarray(x0)[None], x_r]), RF)
    step = np.linalg.norm(np.diff(x_r[:, R.STANCE_LEGS[RF]], axis=0), axis=-1).max()
    stance_motion = np.linalg.norm(x_r[-1] - np.asarray(x0), axis=-1)[R.STANCE_LEGS[RF]]
    assert stance_motion.max() > 0.1  # the stance feet really moved (trunk lowered > 10 cm)
    # Per tick the distances change only to second order in the foot step (|dx|^2 / L).
    per_tick = np.abs(np.diff(d, axis=0)).max()
    assert per_tick < 5.0 * step**2 / 0.6
    assert per_tick < 1e-5
    # Drift over the whole swing (300 ticks) below 1 mm.
    assert np.abs(d - d[0]).max() < 1e-3


@pytest.mark.slow
def test_motion_sharing_depends_on_mobility(x64):
    x0 = standing_feet()
    params = R.ReflexParams()
    # (a) High mobility (m > m_max at the standing pose): nearly all motion in the swing leg.
    _, out = rollout_const(init(x0), constant_inputs(x0.at[RF, 2].add(-0.01), RF), params, 300)
    assert out.mobility[0, RF] > params.m_max
    move = np.linalg.norm(np.asarray(out.x_r[-1] - x0), axis=-1)
    assert move[RF] > 0.0095
    assert move[R.STANCE_LEGS[RF]].max() < 0.01 * move[RF]
    # (b) Stretched swing leg (m < m_min): the stance legs retract (feet up in the base frame),
    # i.e. the trunk lowers relative to the stance feet, while the swing foot goes down. The legs
    # next to the swing leg (LF, RH) retract at once; the diagonal LH leg first extends a little
    # until the base spring has built up its moment (the Fig. 6 effect, tested below).
    q_str = jnp.asarray(robot.Q_STANDING).at[3 * RF + 1].set(0.5).at[3 * RF + 2].set(-0.9)
    x_str = kinematics.foot_positions(q_str)
    state = init(x_str)
    _, out = rollout_const(state, constant_inputs(x_str.at[RF, 2].add(-0.05), RF), params, 300)
    assert out.mobility[0, RF] < params.m_min
    dz = np.asarray(out.x_r[-1, :, 2] - x_str[:, 2])
    assert dz[R.STANCE_LEGS[RF]].mean() > 0.01
    assert dz[robot.LF] > 0.01 and dz[robot.RH] > 0.01
    assert dz[RF] < 0.0
    # Damping was switched: swing leg d_sw_max, stance d_st_min.
    np.testing.assert_allclose(np.asarray(out.d_diag[0]).reshape(4, 3)[RF], params.d_sw_max)
    np.testing.assert_allclose(np.asarray(out.d_diag[0]).reshape(4, 3)[R.STANCE_LEGS[RF]], params.d_st_min)


# ---------------------------------------------------------------------------------------------
# Eq. 9: end stops (Fig. 10)
# ---------------------------------------------------------------------------------------------


def test_end_stop_torques_band_and_sign(x64):
    p = R.ReflexParams(k_kl=1000.0, delta=0.05)
    qmin, qmax = robot.Q_MIN, robot.Q_MAX
    f = jax.jit(lambda q: R.end_stop_torques(q, p))
    mid = 0.5 * (qmin + qmax)
    assert np.all(np.asarray(f(jnp.asarray(mid))) == 0.0)
    assert np.all(np.asarray(f(jnp.asarray(qmax - 0.0501))) == 0.0)
    assert np.all(np.asarray(f(jnp.asarray(qmin + 0.0501))) == 0.0)
    tau_hi = np.asarray(f(jnp.asarray(qmax - 0.02)))
    tau_lo = np.asarray(f(jnp.asarray(qmin + 0.01)))
    np.testing.assert_allclose(tau_hi, -1000.0 * 0.03, rtol=1e-9)  # pushes down, away from q_max
    np.testing.assert_allclose(tau_lo, 1000.0 * 0.04, rtol=1e-9)  # pushes up, away from q_min
    # Beyond the limit the spring keeps growing linearly.
    np.testing.assert_allclose(np.asarray(f(jnp.asarray(qmax + 0.1))), -1000.0 * 0.15, rtol=1e-9)


@pytest.mark.slow
def test_end_stop_stops_joint_before_limit():
    # Downward search of the RF foot at 0.1 m/s to 20 cm: the trunk squats until a stance knee
    # reaches its end-stop band (Fig. 10 situation).
    _, out = search_rollout(R.ReflexParams())
    q = np.asarray(out.q_r)
    margin = np.minimum(q - robot.Q_MIN, robot.Q_MAX - q)
    entered = np.where(margin.min(0) < 0.05)[0]
    assert entered.size > 0  # some joint entered the end-stop band ...
    assert margin.min() > 0.0  # ... but no joint ever crossed its limit
    j = entered[np.argmin(margin.min(0)[entered])]
    assert abs(float(out.qd_r[-1, j])) < 5e-3  # and it came to rest (near-zero velocity)
    assert abs(float(out.qd_r[-1, j])) < 0.02 * np.abs(np.asarray(out.qd_r[:, j])).max()
    # Without the end-stop springs the same plan drives joints through their limits.
    _, free = search_rollout(R.ReflexParams(k_kl=0.0))
    qf = np.asarray(free.q_r)
    assert np.minimum(qf - robot.Q_MIN, robot.Q_MAX - qf).min() < -0.1


# ---------------------------------------------------------------------------------------------
# Fig. 6: base torsional spring
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_fig6_base_spring_lh_extends_or_retracts():
    x0 = np.asarray(standing_feet(jnp.float32))
    res = {}
    for k_base in (100.0, 1500.0):
        _, out = search_rollout(R.ReflexParams(k_base=k_base))
        dz_lh = np.asarray(out.x_r[:, LH, 2]) - x0[LH, 2]
        res[k_base] = dz_lh, np.linalg.norm(np.asarray(out.e_b), axis=-1), np.asarray(out.f_r[:, LH, 2])
    t_end_ramp = 2000  # the plan reaches its 20 cm depth at t = 2 s
    dz100, eb100, f100 = res[100.0]
    dz1500, eb1500, f1500 = res[1500.0]
    # K_base = 100: the LH leg extends (foot down in the base frame) to aid the RF swing.
    assert dz100[t_end_ramp] < -0.05
    assert f100[t_end_ramp] < 0.0
    # K_base = 1500: the LH leg retracts (after a few-mm transient) and the trunk squats evenly.
    assert dz1500[t_end_ramp] > 0.05
    assert dz1500.min() > -0.01
    assert f1500[t_end_ramp] > 0.0
    # ... with a much smaller base orientation change.
    assert eb1500.max() < 0.5 * eb100.max()


# ---------------------------------------------------------------------------------------------
# Eq. 7, 8: terrain normal and orientation error
# ---------------------------------------------------------------------------------------------


def _np_orientation_error(a, b):
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s == 0:
        return np.zeros(3)
    return np.arccos(np.clip(a @ b, -1, 1)) * axis / s


@pytest.mark.slow
def test_orientation_error_and_normal_reference_and_gradients(x64):
    rng = np.random.default_rng(1)
    err = jax.jit(R.orientation_error)
    for _ in range(20):
        a = rng.normal(size=3) + np.array([0, 0, 2.0])
        b = rng.normal(size=3) + np.array([0, 0, 2.0])
        e = np.asarray(err(jnp.asarray(a), jnp.asarray(b)))
        np.testing.assert_allclose(e, _np_orientation_error(a, b), atol=1e-12)
    # Tiny angles (acos is inaccurate there; the reference uses the exact small rotation).
    th = 1e-7
    e = np.asarray(err(jnp.asarray([np.sin(th), 0.0, np.cos(th)]), jnp.asarray([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(e, [0.0, -th, 0.0], rtol=1e-6, atol=1e-20)  # a x b = -sin(th) y
    # delta = 0: value and gradient finite (and the Jacobian is the small-angle one).
    n = jnp.asarray([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    assert np.abs(np.asarray(err(n, n))).max() < 1e-15
    jac = np.asarray(jax.jit(jax.jacobian(R.orientation_error))(n, n))
    nn = np.asarray(n)
    skew_n = np.array([[0, -nn[2], nn[1]], [nn[2], 0, -nn[0]], [-nn[1], nn[0], 0]])
    np.testing.assert_allclose(jac, -skew_n, atol=1e-12)  # d(n x n_des)/dn at n = n_des

    def loss(a, b):
        e_t = R.orientation_error(a, b)
        return jnp.sum(e_t**2 + e_t)

    g = np.asarray(jax.jit(jax.grad(loss, argnums=(0, 1)))(n, n))
    assert np.all(np.isfinite(g))
    # Terrain normal (Eq. 7) against NumPy, oriented up, independent of the feet order.
    tn = jax.jit(R.terrain_normal)
    for _ in range(10):
        xs = rng.normal(size=(3, 3)) * [0.4, 0.4, 0.05] + [0, 0, -0.57]
        c = np.cross(xs[0] - xs[1], xs[1] - xs[2])
        ref = c / np.linalg.norm(c) * np.sign(c[2])
        np.testing.assert_allclose(np.asarray(tn(jnp.asarray(xs))), ref, atol=1e-12)
        np.testing.assert_allclose(np.asarray(tn(jnp.asarray(xs[::-1]))), ref, atol=1e-12)
    # Collinear feet: returns `up`, finite gradient.
    xs = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(tn(xs)), [0, 0, 1.0])
    assert np.all(np.isfinite(np.asarray(jax.jit(jax.jacobian(R.terrain_normal))(xs))))
    # e_t is the base rotation: tilting the base by +pitch tilts the terrain normal the other way.
    pitch = 0.1
    n_t = jnp.asarray([-np.sin(pitch), 0.0, np.cos(pitch)])  # R_y(pitch)^T z
    np.testing.assert_allclose(np.asarray(err(n_t, jnp.asarray([0.0, 0.0, 1.0]))), [0, pitch, 0], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Eq. 12: mobility metrics (Fig. 8)
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_velocity_transformation_ratio_reference_and_extension(x64):
    vtr = jax.jit(R.velocity_transformation_ratio)
    rng = np.random.default_rng(2)
    for _ in range(10):
        j = rng.normal(size=(3, 3)) * 0.4
        v = rng.normal(size=3)
        m, w, k = (float(a) for a in vtr(jnp.asarray(j), jnp.asarray(v)))
        vn = v / np.linalg.norm(v)
        sv = np.linalg.svd(j, compute_uv=False)
        # rtol: the 1e-10 relative ridge shifts m by ~1e-10 * tr(JJ^T) / lambda_min(JJ^T).
        np.testing.assert_allclose(m, (vn @ np.linalg.inv(j @ j.T) @ vn) ** -0.5, rtol=1e-6)
        np.testing.assert_allclose(w, np.sqrt(np.linalg.det(j @ j.T)), rtol=1e-6)
        np.testing.assert_allclose(k, sv[-1] / sv[0], rtol=1e-10)
    # Decreasing along the terrain normal as the RF leg extends toward the straight leg.
    kfe = np.linspace(-2.0, -0.05, 40)
    q = np.tile(robot.Q_STANDING, (40, 1))
    q[:, 3 * RF + 2] = kfe
    q[:, 3 * RF + 1] = -kfe / 2  # keep the foot roughly under the hip
    j_rf = kinematics.foot_jacobians(jnp.asarray(q))[:, RF]
    vtr_batch = jax.jit(jax.vmap(R.velocity_transformation_ratio, (0, None)))
    m, w, k = (np.asarray(a) for a in vtr_batch(j_rf, jnp.asarray([0, 0, 1.0])))
    ext = np.asarray(kinematics.leg_extension(jnp.asarray(q))[:, RF])
    assert np.all(np.diff(ext) > 0)
    assert np.all(np.diff(m) < 0)  # m along the normal decreases monotonically (Fig. 8)
    # w and kappa^-1 peak at a bent knee and decrease only over the stretched half.
    assert np.all(np.diff(w[20:]) < 0) and np.all(np.diff(k[20:]) < 0)
    # At an exactly straight leg: finite, tiny, with finite gradients.
    q_straight = jnp.asarray(robot.Q_STANDING).at[3 * RF + 1].set(0.0).at[3 * RF + 2].set(0.0)
    j_s = kinematics.foot_jacobians(q_straight)[RF]
    m_s, w_s, k_s = vtr(j_s, jnp.asarray([0, 0, 1.0]))
    assert 0 < float(m_s) < 1e-4 and float(k_s) < 1e-6
    def total(jj):
        return sum(jnp.sum(a) for a in R.velocity_transformation_ratio(jj, jnp.asarray([0.0, 0.1, 1.0])))

    assert np.all(np.isfinite(np.asarray(jax.jit(jax.grad(total))(j_s))))


# ---------------------------------------------------------------------------------------------
# Section III-E: damping schedule (Fig. 7)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("shape", ["smoothstep", "linear"])
def test_damping_schedule_endpoints_continuity_gradient(x64, shape):
    p = R.ReflexParams()
    sched = jax.jit(lambda m: R.damping_schedule(m, p, shape))
    d_sw, d_st = sched(jnp.asarray([0.0, 0.19, 0.15, 0.21, 0.3]))
    np.testing.assert_allclose(np.asarray(d_sw), [100, 100, 100, 5, 5])
    np.testing.assert_allclose(np.asarray(d_st), [50, 50, 50, 1000, 1000])
    m = jnp.linspace(0.17, 0.23, 6001)
    d_sw, d_st = (np.asarray(a) for a in sched(m))
    assert np.abs(np.diff(d_sw)).max() < 0.1 and np.abs(np.diff(d_st)).max() < 1.0  # continuous
    assert np.all(np.diff(d_sw) <= 0) and np.all(np.diff(d_st) >= 0)  # monotone
    grad = jax.jit(jax.vmap(jax.grad(lambda mm: R.damping_schedule(mm, p, shape)[1])))
    g = np.asarray(grad(jnp.asarray([0.195, 0.2, 0.205])))
    h = 1e-7
    m0 = jnp.asarray([0.195, 0.2, 0.205])
    fd = (np.asarray(sched(m0 + h)[1]) - np.asarray(sched(m0 - h)[1])) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    assert np.all(g > 0)
    if shape == "smoothstep":  # C^1: zero slope at the thresholds
        assert np.all(np.asarray(grad(jnp.asarray([0.19, 0.21]))) == 0.0)
    # Diagonal of D_r with a traced swing leg.
    diag = jax.jit(lambda s: R.damping_matrix_diag(s, 0.3, p, shape))
    for s in range(4):
        d = np.asarray(diag(s)).reshape(4, 3)
        assert np.all(d[s] == 5.0) and np.all(np.delete(d, s, 0) == 1000.0)
    with pytest.raises(ValueError, match="shape"):
        R.damping_schedule(0.2, p, "cubic")


# ---------------------------------------------------------------------------------------------
# Differentiability with respect to every parameter
# ---------------------------------------------------------------------------------------------


@jax.jit
def _grad_scenario():
    """Stance joint inside its end-stop band, swing leg in the damping transition region."""
    q = jnp.asarray(robot.Q_STANDING, jnp.float64)
    q = q.at[3 * robot.LF + 0].set(robot.Q_MAX[0] - 0.03)  # LF HAA inside the 0.05 rad band
    q = q.at[3 * RF + 1].set(0.68).at[3 * RF + 2].set(-1.36)  # RF mobility ~ 0.2 (m_min..m_max)
    x0 = kinematics.foot_positions(q)
    state = R.ReflexState(q_r=q, qd_r=jnp.zeros(12))
    x_des = x0.at[RF, 2].add(-0.04).at[RF, 0].add(0.02)
    inputs = R.ReflexInputs.make(x_des, RF, n_t_des=jnp.asarray([0.05, -0.03, 1.0]))  # e_b != 0
    return state, inputs


@pytest.mark.slow
def test_gradients_wrt_every_param_match_finite_differences(x64):
    state, inputs = _grad_scenario()
    w_q = jnp.asarray(np.random.default_rng(3).normal(size=12))
    w_x = jnp.asarray(np.random.default_rng(4).normal(size=(4, 3)))

    def outcome_and_aux(params):
        s, out = R.reflex_rollout(state, inputs, params, DT, n_steps=40)
        value = jnp.sum(w_q * s.q_r) + jnp.sum(w_x * out.x_r[-1]) + 0.1 * jnp.sum(out.x_r[:, :, 2])
        return value, (out.mobility[:, RF], out.tau_kl[:, 0])

    # One compilation serves both the reverse-mode gradient and the finite differences.
    value_and_grad = jax.jit(jax.value_and_grad(outcome_and_aux, has_aux=True))

    def outcome(params):
        return value_and_grad(params)[0][0]

    base = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), R.ReflexParams())
    # k_x above its bound (non-weak float64 leaves, so the same compilation is reused).
    clipped = unchecked(base, k_x=jnp.asarray(2.5e4, jnp.float64), k_x_max=jnp.asarray(1.2e4, jnp.float64))
    names = [f.name for f in R.ReflexParams.__dataclass_fields__.values()]
    for params, zero_field in ((base, "k_x_max"), (clipped, "k_x")):
        (_, (mobility, tau_lf_haa)), g = value_and_grad(params)
        # The scenario exercises every field: swing mobility inside (m_min, m_max) for some ticks
        # (schedule fields), a stance joint inside its end-stop band (k_kl, delta), e_b != 0 (k_base).
        assert np.any((np.asarray(mobility) > 0.19) & (np.asarray(mobility) < 0.21))
        assert np.all(np.asarray(tau_lf_haa) != 0.0)
        for name in names:
            gv = float(getattr(g, name))
            assert np.isfinite(gv), name
            v = float(getattr(params, name))
            h = 1e-5 * abs(v)
            fp = float(outcome(unchecked(params, **{name: jnp.asarray(v + h, jnp.float64)})))
            fm = float(outcome(unchecked(params, **{name: jnp.asarray(v - h, jnp.float64)})))
            fd = (fp - fm) / (2 * h)
            if name == zero_field:  # the clip min(k_x, k_x_max) makes it inactive here
                assert gv == 0.0 and fd == 0.0, name
            else:
                assert gv != 0.0, name
                atol = 1e-11 * max(1.0, abs(fp)) / h  # round-off of the central difference
                np.testing.assert_allclose(gv, fd, rtol=2e-4, atol=atol, err_msg=name)


# ---------------------------------------------------------------------------------------------
# Degenerate and invalid inputs
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_collinear_stance_feet_flagged_fallback():
    # Stance feet LF, LH, RH on one line (RF swings): LH on the LF-RH diagonal, all at z = -0.5.
    x = np.array(standing_feet(jnp.float32))
    x[:, 2] = -0.5
    d = (x[robot.RH, :2] - x[robot.LF, :2]) / np.linalg.norm(x[robot.RH, :2] - x[robot.LF, :2])
    x[LH, :2] = x[robot.LF, :2] + ((robot.B_P_HIP[LH, :2] - x[robot.LF, :2]) @ d) * d
    x = jnp.asarray(x)
    q = kinematics.inverse_kinematics(x).reshape(12)
    x = kinematics.foot_positions(q)
    j = kinematics.foot_jacobians(q)
    f_sw = jnp.asarray([0.0, 0.0, -200.0])
    d_diag = jnp.full(12, 100.0, jnp.float32)

    @jax.jit
    def distribute(xx, fs):
        e_b = jnp.zeros(3, jnp.float32)
        return R.distribute_virtual_forces(xx, fs, RF, j, d_diag, e_b, R.ReflexParams(), return_degenerate=True)

    f, deg = distribute(x, f_sw)
    assert bool(deg)
    np.testing.assert_array_equal(np.asarray(f)[R.STANCE_LEGS[RF]], 0.0)
    np.testing.assert_array_equal(np.asarray(f)[RF], np.asarray(f_sw))
    # In reflex_step: flagged, stance feet stay put, swing foot moves, no NaN, finite gradients.
    # (End stops off: the LH HAA of this layout is past its limit and its spring would move it.)
    state = jax.device_put(R.ReflexState(q_r=q, qd_r=jnp.zeros(12, jnp.float32)))
    inputs = constant_inputs(x.at[RF, 2].add(-0.05), RF)
    s1, out = step(state, inputs, R.ReflexParams(k_kl=0.0))
    assert bool(out.degenerate) and bool(out.active)
    leaves = jax.tree.leaves(out)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in leaves if np.asarray(a).dtype.kind == "f")
    np.testing.assert_allclose(np.asarray(out.x_r)[R.STANCE_LEGS[RF]], np.asarray(x)[R.STANCE_LEGS[RF]], atol=1e-6)
    assert float(out.x_r[RF, 2]) < float(x[RF, 2])
    # Gradients through the degenerate branch are finite (double-where, no NaN leaks).
    g = jax.jit(jax.grad(lambda xx, fs: jnp.sum(distribute(xx, fs)[0] ** 2), argnums=(0, 1)))(x, f_sw)
    assert all(np.all(np.isfinite(np.asarray(a))) for a in g)


@pytest.mark.slow
def test_nan_inputs_flagged_and_state_held():
    x0 = standing_feet(jnp.float32)
    state = init(x0)
    params = R.ReflexParams()
    good = constant_inputs(x0.at[RF, 2].add(-0.05), RF)
    s1, _ = step(state, good, params)
    s1, _ = step(s1, good, params)
    bad_cases = [
        dataclasses.replace(good, x_des=good.x_des.at[0, 0].set(jnp.nan)),
        dataclasses.replace(good, n_t_des=jnp.full(3, jnp.nan, jnp.float32)),
        dataclasses.replace(good, up=jnp.asarray([0.0, jnp.inf, 1.0])),
    ]
    for bad in bad_cases:
        s2, out = step(s1, bad, params)
        assert not bool(out.input_ok) and not bool(out.active) and bool(out.failed)
        np.testing.assert_array_equal(np.asarray(s2.q_r), np.asarray(s1.q_r))  # held
        assert np.all(np.asarray(s2.qd_r) == 0.0)
        for a in jax.tree.leaves(out):
            a = np.asarray(a)
            if a.dtype.kind == "f":
                assert np.all(np.isfinite(a))
    # NaN parameter: flagged, held.
    s2, out = step(s1, good, unchecked(params, k_base=float("nan")))
    assert not bool(out.input_ok) and bool(out.failed)
    np.testing.assert_array_equal(np.asarray(s2.q_r), np.asarray(s1.q_r))
    # NaN state with a valid plan: restarted from the plan, flagged.
    nan_state = R.ReflexState(q_r=jnp.full(12, jnp.nan, jnp.float32), qd_r=jnp.zeros(12, jnp.float32))
    s3, out = step(nan_state, good, params)
    assert not bool(out.input_ok) and bool(out.failed)
    _, out = step(s1, good, params)
    assert not bool(out.failed)
    q_plan = np.asarray(kinematics.inverse_kinematics(good.x_des).reshape(12))
    np.testing.assert_allclose(np.asarray(s3.q_r), q_plan, atol=1e-6)


# ---------------------------------------------------------------------------------------------
# Activation logic, batching, precision
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_inactive_tracks_plan_and_activation_starts_from_plan(x64):
    x0 = standing_feet()
    n, k_on = 300, 150
    x_des = jnp.repeat(x0[None], n, 0).at[:, RF, 2].add(-jnp.linspace(0.0, 0.3, n))
    active = jnp.arange(n) >= k_on
    inputs = R.ReflexInputs(
        x_des=x_des,
        swing_leg=jnp.full(n, RF, jnp.int32),
        active=active,
        n_t_des=jnp.tile(R.planned_terrain_normal(x0, RF), (n, 1)),
        up=jnp.tile(jnp.asarray([0.0, 0.0, 1.0]), (n, 1)),
    )
    _, out = rollout_seq(init(x0), inputs, R.ReflexParams())
    # Inactive: the plan passes through, q^r = IK(x^d), no virtual forces, no velocity.
    np.testing.assert_array_equal(np.asarray(out.x_r[:k_on]), np.asarray(x_des[:k_on]))
    q_plan = np.asarray(kinematics.inverse_kinematics(x_des[:k_on]).reshape(k_on, 12))
    np.testing.assert_allclose(np.asarray(out.q_r[:k_on]), q_plan, atol=1e-12)
    assert np.all(np.asarray(out.f_r[:k_on]) == 0.0) and np.all(np.asarray(out.qd_r[:k_on]) == 0.0)
    assert not np.any(np.asarray(out.active[:k_on]))
    # First active tick continues smoothly from the plan of the previous tick.
    assert np.abs(np.asarray(out.x_r[k_on] - x_des[k_on - 1])).max() < 2e-3
    assert np.all(np.asarray(out.active[k_on:]))
    # Once active, the stance feet are replanned (they no longer equal the plan).
    assert np.abs(np.asarray(out.x_r[-1] - x_des[-1]))[R.STANCE_LEGS[RF]].max() > 1e-3


@pytest.mark.slow
def test_vmap_batch_matches_single(x64):
    x0 = standing_feet()
    swing = jnp.asarray([0, 1, 2, 3, 1])
    drops = jnp.asarray([0.02, 0.1, 0.05, 0.2, 0.0])
    inputs = jax.jit(jax.vmap(lambda s, d: R.ReflexInputs.make(x0.at[s, 2].add(-d), s)))(swing, drops)
    states = jax.jit(jax.vmap(lambda _: R.reflex_init(x0)))(swing)
    batched = jax.jit(jax.vmap(lambda s, i: R.reflex_rollout(s, i, R.ReflexParams(), DT, n_steps=300)))
    fs, out = batched(states, inputs)
    for b in (1, 3):
        single = constant_inputs(x0.at[int(swing[b]), 2].add(-float(drops[b])), int(swing[b]))
        fs1, _ = rollout_const(init(x0), single, R.ReflexParams(), 300)
        np.testing.assert_allclose(np.asarray(fs.q_r[b]), np.asarray(fs1.q_r), atol=1e-10)
    # Each swing leg moves its own foot down the most.
    for b in range(4):
        dz = np.asarray(out.x_r[b, -1, :, 2] - x0[:, 2])
        assert np.argmin(dz) == int(swing[b])


@pytest.mark.slow
def test_float32_matches_float64_trajectory():
    # The 5 s downward search of the end-stop test (squat of ~25 cm, end stops engaged).
    with jax.enable_x64(True):
        _, out64 = search_rollout(R.ReflexParams())
        x64_ = np.asarray(out64.x_r)
    _, out32 = search_rollout(R.ReflexParams())
    assert out64.x_r.dtype == jnp.float64 and out32.x_r.dtype == jnp.float32
    x32 = np.asarray(out32.x_r)
    assert np.abs(x64_[-1] - x64_[0]).max() > 0.15  # a substantial squat happened
    assert np.abs(x32 - x64_).max() < 1e-3  # float32 stays within 1 mm of float64 over 5000 ticks


@pytest.mark.slow
def test_realtime_packed_step_equals_reflex_step():
    """The flat-vector real-time entry point computes exactly reflex_step, and its state feeds back."""
    from hyqjax.reflex import realtime as RT

    x0 = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float32))
    inputs = R.ReflexInputs.make(x0.at[robot.RF, 2].add(-0.12), robot.RF)
    params = R.ReflexParams.table1()
    step = RT.make_realtime_reflex(params, 1e-3)
    state = R.reflex_init(inputs.x_des)
    v = RT.pack_inputs(state, inputs)
    p32 = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float32), params)
    for _ in range(5):
        out_v = step(v)
        state, out = R.reflex_step(state, inputs, p32, 1e-3)
        np.testing.assert_allclose(out_v[RT.OUT_X_R], out.x_r.reshape(12), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(out_v[RT.OUT_STATE], jnp.concatenate([state.q_r, state.qd_r]), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(out_v[RT.OUT_D_DIAG], out.d_diag, rtol=1e-6)
        np.testing.assert_array_equal(out_v[RT.OUT_FLAGS], [1.0, 0.0, 1.0, 0.0])  # active, ok, not failed
        v = v.at[:24].set(out_v[RT.OUT_STATE])
    with pytest.raises(ValueError, match="dt"):
        RT.make_realtime_reflex(params, 0.5)
