"""The bounding limit cycle: apex return map through MJX, its optimisation and its linearisation.

Apex state and return map
-------------------------
The Poincare section is the gait clock's phase 0 (mid-flight before the hind stance, the apex).
The sagittal apex state is ``s = (z, theta, xdot, zdot, thetadot)`` (trunk height, pitch, forward
and vertical speed, pitch rate). :func:`apex_data` places HyQ in the air at ``s`` (roll, yaw,
lateral motion zero; legs at the controller's phase-0 swing references, joint rates zero) and
the controller's estimator at the true ``(z, xdot, zdot)``; :func:`return_map` simulates one
period ``T`` of the closed loop (``sim.rollout``, ``mjx.step``) and reads ``s`` again:

.. math:: s_{k+1} = P(s_k, a), \\qquad a = (a_{f,z}, a_{h,z}, a_{f,x}, a_{h,x}).                \\qquad (C1)

Periodicity (cycle optimisation)
--------------------------------
A limit cycle is a fixed point ``s* = P(s*, a*)``. The decision vector is
``u = (a_{f,z}, a_{h,z}, a_{f,x}, a_{h,x}, z_0, zdot_0, thetadot_0, xdot_0)`` with ``theta_0 = 0``;
the feedback (Eqs. B4, B5, B7, B8) is switched off. :func:`residual` (6,) is
``r(u) = (W (P(s_0(u), a(u)) - s_0(u)), Delta x / 0.01 m)``, per-component scales
``W = diag(1 / RESIDUAL_SCALE)``, plus the forward displacement over the period (bounding *in place*
has zero net drift, not only a periodic speed). The family of cycles has free directions (height,
``a_{f,x} - a_{h,x}``), fixed by a soft prior; the loss is

.. math:: L(u) = \tfrac12 \|r(u)\|^2 + \tfrac{\lambda}{2} \Big[\Big(\frac{z_0 - z^d}{0.02}\Big)^2 +
          \Big(\frac{a_{f,x}}{100}\Big)^2 + \Big(\frac{a_{h,x}}{100}\Big)^2\Big].   \qquad (C2)

Its gradient ``J_r^T r + ...`` uses the forward-mode Jacobian ``J_r = jax.jacfwd(residual)``
(eight tangents through ``mjx.step``; reverse mode through MJX's solver ``while_loop`` is not
available). :func:`optimise_cycle` runs optax from many initial guesses at once (``vmap``): by default
the Levenberg-Marquardt step ``-(J^T J + mu I)^{-1} J^T r`` fed to ``optax.sgd`` (step clipped,
warm-up schedule), or ``optax.adam`` on the gradient. :func:`gradient_check` compares the
forward-mode Jacobian with central finite differences.

Stability
---------
:func:`linearise` gives ``A = dP/ds`` and ``B = dP/da`` at the fixed point (``jax.jacfwd``, 9 tangents).
The eigenvalues of ``A`` are the multipliers of the sagittal cycle with the configured feedback
(switches ``apex_feedback``, ``stance_feedback``); the feedback is zero on the cycle, so all maps
share ``s*``. :func:`feedback_matrix` is the apex feedback's ``K`` (``A_stance + B K`` predicts
``A_stance+apex``), :func:`augmented_matrix` adds the per-cycle integrators as states, and
:func:`design_feedback` picks apex gains on the linear model. :func:`reference_table` records the
cycle's ``(z, theta, zdot, thetadot)`` against phase: the stance feedback's reference (Eq. B7).
"""
from __future__ import annotations

import copy
import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax
from mujoco import mjx

from hyqjax import bounding as bd, kinematics, model as hmodel, robot, sim, spatial

#: Residual scales of ``(z, theta, xdot, zdot, thetadot)``: a residual of 1 is 1 cm, 0.01 rad, 0.05 m/s,
#: 0.05 m/s, 0.1 rad/s.
RESIDUAL_SCALE = np.array([0.01, 0.01, 0.05, 0.05, 0.1])
#: Scale of the sixth residual, the forward displacement over one period (m): bounding *in place*.
DISPLACEMENT_SCALE = 0.01
N_DECISION = 8
#: Scales of the decision vector ``u = (a_fz, a_hz, a_fx, a_hx, z0, zdot0, thetadot0)``.
DECISION_SCALE = np.array([100.0, 100.0, 100.0, 100.0, 0.05, 0.1, 1.0, 0.05])
DECISION_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx", "z0", "zdot0", "thetadot0", "xdot0")


@functools.lru_cache(maxsize=4)
def _model(timestep: float = 0.002):
    """HyQ on flat ground: :func:`hyqjax.model.load_model` with the platform's collisions switched off.

    Bounding runs with platform height 0, where the platform's top is flush with the floor for
    ``x < 0``; disabling it removes the duplicate foot-floor contacts (14 instead of 28 contact
    slots), which halves the contact work and shortens the forward-mode compile.
    """
    m = copy.deepcopy(hmodel.load_model(timestep=timestep))
    ids = hmodel.model_ids(m)
    m.geom_contype[ids.platform_geom] = 0
    m.geom_conaffinity[ids.platform_geom] = 0
    with jax.ensure_compile_time_eval():  # concrete arrays even if first called inside a trace
        mx = mjx.put_model(m)
    return m, mx, ids


def apex_state(u: jax.Array) -> jax.Array:
    """``s_0(u) = (z_0, 0, xdot_0, zdot_0, thetadot_0)`` from the decision vector."""
    z = jnp.zeros((), u.dtype)
    return jnp.stack([u[4], z, u[7], u[5], u[6]])


def with_cycle(params: bd.BoundingParams, u: jax.Array) -> bd.BoundingParams:
    """``params`` with amplitudes and apex reference from the decision vector ``u`` (8,)."""
    amp = params.amplitudes
    amp = amp.at[0:2, 2].set(u[0]).at[2:4, 2].set(u[1]).at[0:2, 0].set(u[2]).at[2:4, 0].set(u[3])
    return params.replace(amplitudes=amp, apex_ref=apex_state(u).astype(jnp.float32))


def _fake_obs(s, q, time=0.0):
    dt = s.dtype
    half = 0.5 * s[1]
    quat = jnp.stack([jnp.cos(half), jnp.zeros((), dt), jnp.sin(half), jnp.zeros((), dt)])
    return sim.Observation(q=q, qd=jnp.zeros(12, dt), tau=jnp.zeros(12, dt), quat=quat,
                           gyro=jnp.stack([0.0, s[4], 0.0]).astype(dt), foot_force=jnp.zeros((4, 3), dt),
                           time=jnp.asarray(time, dt))


def reference_joints(params: bd.BoundingParams, s: jax.Array) -> jax.Array:
    """Joint references (12,) of the controller at phase 0 with the trunk at apex state ``s``."""
    q0 = jnp.asarray(robot.Q_STANDING, s.dtype)
    obs = _fake_obs(s, q0)
    p = params.replace(init_estimate=jnp.stack([s[0], s[2], jnp.zeros((), s.dtype), s[3]]).astype(jnp.float32))
    st = bd.bounding_init(p, obs)
    _, rpy, rates = bd._imu(obs)
    stance, s_st, s_sw = bd.leg_phase(p.gait, obs.time)
    v_des, _, _ = bd.ramped_command(p.command, obs.time)
    zero = jnp.zeros((), s.dtype)
    target = bd.touchdown_target(p, jnp.stack([s[2], zero, s[3]]),
                                 st.apex_vel - v_des - jnp.stack([p.apex_ref[2], zero]), zero)
    b_x, _, _ = bd.foot_references(p, st, obs.time, rpy, rates, obs.gyro, stance, s_st, s_sw, v_des, target, zero)
    return jnp.clip(kinematics.inverse_kinematics(b_x).reshape(12), robot.Q_MIN + 0.02, robot.Q_MAX - 0.02)


def apex_data(mx: mjx.Model, m: mujoco.MjModel, params: bd.BoundingParams, s: jax.Array, xy=(0.0, 0.0), yaw=0.0,
              roll=0.0, vy=0.0, yaw_rate=0.0) -> mjx.Data:
    """MJX data with HyQ in the air at apex state ``s`` (optionally with roll / yaw / lateral speed)."""
    dtype = jnp.float32
    s = jnp.asarray(s, dtype)
    q_legs = reference_joints(params, s)
    rot = spatial.rpy_to_rot(jnp.stack([jnp.asarray(roll, dtype), s[1], jnp.asarray(yaw, dtype)]))
    quat = _rot_to_quat(rot)
    qpos = jnp.concatenate([jnp.stack([jnp.asarray(xy[0], dtype), jnp.asarray(xy[1], dtype), s[0]]), quat,
                            q_legs.astype(dtype)])
    omega_w = jnp.stack([jnp.zeros((), dtype), s[4], jnp.asarray(yaw_rate, dtype)])
    omega_b = rot.T @ omega_w  # pitch rate about the (yaw-rotated) world y axis, approx.
    v = jnp.stack([s[2], jnp.asarray(vy, dtype), s[3]])
    v_w = spatial.rpy_to_rot(jnp.stack([jnp.zeros((), dtype), jnp.zeros((), dtype), jnp.asarray(yaw, dtype)])) @ v
    qvel = jnp.concatenate([v_w, omega_b, jnp.zeros(12, dtype)])
    d = mjx.make_data(mx)
    return d.replace(qpos=qpos.astype(d.qpos.dtype), qvel=qvel.astype(d.qvel.dtype))


def _rot_to_quat(r):
    """Unit quaternion (w, x, y, z) of a rotation matrix (trace branch; fine for |angles| < pi/2)."""
    w = 0.5 * jnp.sqrt(jnp.maximum(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 1e-9))
    return jnp.stack([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])


def data_apex(d: mjx.Data) -> jax.Array:
    """Sagittal apex state ``(z, theta, xdot, zdot, thetadot)`` of MJX data (``xdot`` along the trunk's heading)."""
    rot = spatial.quat_to_rot(d.qpos[3:7])
    rpy = spatial.rot_to_rpy(rot)
    rates = bd.euler_rates(rpy, d.qvel[3:6])
    c, s_ = jnp.cos(rpy[2]), jnp.sin(rpy[2])
    vx = c * d.qvel[0] + s_ * d.qvel[1]
    return jnp.stack([d.qpos[2], rpy[1], vx, d.qvel[2], rates[1]])


def return_map(mx, m, ids, params: bd.BoundingParams, s: jax.Array, n_periods: int = 1,
               control_dt: float = 0.002, period: float | None = None, displacement: bool = False):
    """``P(s)`` (Eq. C1): apex state after ``n_periods`` gait periods of the closed loop from apex state ``s``.

    ``params.apex_ref`` is the cycle the apex feedback regulates to; the estimator starts at the true state.
    ``period`` (static) defaults to ``params.gait.period``, which must then be concrete. With ``displacement``
    also returns the forward displacement over the simulated time.
    """
    s = jnp.asarray(s, jnp.float32)
    p = params.replace(init_estimate=jnp.stack([s[0], s[2], jnp.zeros((), s.dtype), s[3]]))
    d0 = apex_data(mx, m, p, s)
    period = float(params.gait.period) if period is None else period
    cfg = sim.SimConfig(control_dt=control_dt, duration=n_periods * period, record_every=0)
    res = sim.rollout(mx, ids, d0, bd.bounding_controller, p, cfg)
    if displacement:
        return data_apex(res.data), res.data.qpos[0] - d0.qpos[0]
    return data_apex(res.data)


def residual(u: jax.Array, params: bd.BoundingParams, n_periods: int = 1, period: float | None = None) -> jax.Array:
    """Scaled periodicity residual (6,): ``W (P(s_0(u), a(u)) - s_0(u))`` and the drift ``Delta x / 0.01 m``, Eq. C2."""
    m, mx, ids = _model()
    p = with_cycle(params, u)
    s0 = apex_state(u)
    s1, dx = return_map(mx, m, ids, p, s0, n_periods, period=period, displacement=True)
    return jnp.concatenate([(s1 - s0) / jnp.asarray(RESIDUAL_SCALE, s1.dtype), (dx / DISPLACEMENT_SCALE)[None]])


def loss_terms(u, r, z_des, prior_weight):
    prior = jnp.stack([(u[4] - z_des) / 0.02, u[2] / 100.0, u[3] / 100.0])
    return 0.5 * jnp.sum(r**2) + 0.5 * prior_weight * jnp.sum(prior**2), prior


def residual_and_jacobian(u: jax.Array, params: bd.BoundingParams):
    """``(r(u), dr/du)`` in forward mode (``jax.jacfwd``: 8 tangents through ``mjx.step``)."""
    f = lambda uu: (residual(uu, params),) * 2  # noqa: E731
    jac, r = jax.jacfwd(f, has_aux=True)(u)
    return r, jac


@functools.partial(jax.jit, static_argnames=("period",))
def residual_jvp(params: bd.BoundingParams, u: jax.Array, v: jax.Array, period: float):
    """Batched ``(r(u_i), dr/du(u_i) v_i)`` (``vmap`` over rows of ``u``, ``v``): one compile serves the
    forward-mode directional derivatives, the finite-difference points (``v = 0``) and the periodicity check.
    ``period`` must equal ``params.gait.period`` (static: it sets the number of ticks)."""
    return jax.vmap(lambda uu, vv: jax.jvp(lambda x: residual(x, params, period=period), (uu,), (vv,)))(u, v)


@functools.partial(jax.jit, static_argnames=("period",))
def batched_residual(params: bd.BoundingParams, u: jax.Array, period: float) -> jax.Array:
    """``r(u_i)`` for the rows of ``u`` (``vmap``)."""
    return jax.vmap(lambda uu: residual(uu, params, period=period))(u)


class CycleResult(NamedTuple):
    """Optimisation output (numpy). ``u``: (B, 8) decision vectors; ``residual_norm``: (B,) ``||r||``;
    ``history``: (iters, B) loss; ``best``: index of the best guess."""

    u: np.ndarray
    residual: np.ndarray
    residual_norm: np.ndarray
    loss: np.ndarray
    history: np.ndarray
    residual_history: np.ndarray
    best: int


def initial_guesses(params: bd.BoundingParams, n: int, seed: int = 0, z_des: float = 0.6) -> np.ndarray:
    """``n`` decision vectors spread around Park & Kim's impulse balance (Eq. B2)."""
    if not (isinstance(n, int) and 1 <= n <= 4096):
        raise ValueError(f"n (number of initial guesses) must be an int in [1, 4096], got {n}")
    rng = np.random.default_rng(seed)
    af, ah = bd.impulse_guess(params.gait)
    u = np.zeros((n, N_DECISION))
    u[:, 0] = af * rng.uniform(0.9, 1.1, n)
    u[:, 1] = ah * rng.uniform(0.9, 1.1, n)
    u[:, 2:4] = rng.normal(0.0, 20.0, (n, 2))
    u[:, 4] = z_des + rng.uniform(-0.03, 0.03, n)
    u[:, 5] = rng.uniform(-0.1, 0.1, n)
    u[:, 6] = rng.uniform(-3.0, -1.0, n)
    u[:, 7] = rng.uniform(-0.05, 0.05, n)
    u[0] = [af, ah, 0.0, 0.0, z_des, 0.0, -2.0, 0.0]
    return u


def optimise_cycle(params: bd.BoundingParams, u0: np.ndarray, iterations: int = 30, method: str = "lm",
                   learning_rate: float = 0.05, z_des: float = 0.6, prior_weight: float = 1e-2,
                   damping: float = 1e-2, progress: bool = True) -> CycleResult:
    """Minimise Eq. C2 from every row of ``u0`` (B, 8) at once (``vmap`` over guesses, forward-mode Jacobians).

    Args:
      method: ``'lm'``: optax SGD (learning rate 1 with a warm-up schedule) applied to the
        Levenberg-Marquardt step ``-(J^T J + mu I)^{-1} g`` (Gauss-Newton, robust for this 8x9 problem);
        ``'adam'``: ``optax.adam(learning_rate)`` on the gradient ``g = J^T r + prior``.
      iterations: optimiser steps (each is one batched jacfwd return map).
    """
    if method not in ("lm", "adam"):
        raise ValueError(f"method must be 'lm' or 'adam', got {method!r}")
    if not (isinstance(iterations, int) and 1 <= iterations <= 10000):
        raise ValueError(f"iterations must be an int in [1, 10000], got {iterations}")
    u0 = np.atleast_2d(np.asarray(u0, np.float64))
    if u0.shape[1] != N_DECISION:
        raise ValueError(f"u0 must have shape (B, {N_DECISION}), got {u0.shape}")
    scale = jnp.asarray(DECISION_SCALE, jnp.float32)

    def value_grad(x):
        u = x * scale
        r, jac = residual_and_jacobian(u, params)
        loss, prior = loss_terms(u, r, z_des, prior_weight)
        jx = jac * scale[None, :]
        jp = jnp.zeros((3, N_DECISION), jnp.float32).at[0, 4].set(scale[4] / 0.02).at[1, 2].set(scale[2] / 100.0) \
            .at[2, 3].set(scale[3] / 100.0) * jnp.sqrt(prior_weight)
        jall = jnp.concatenate([jx, jp], 0)
        rall = jnp.concatenate([r, jnp.sqrt(prior_weight) * prior])
        g = jall.T @ rall
        if method == "lm":
            h = jall.T @ jall + damping * jnp.eye(N_DECISION, dtype=jall.dtype)
            g = jnp.linalg.solve(h, g)
        return loss, r, g

    if method == "lm":
        opt = optax.chain(optax.clip(0.5), optax.sgd(optax.linear_schedule(0.5, 1.0, 5)))
    else:
        opt = optax.adam(learning_rate)

    @jax.jit
    def step(x, state):
        loss, r, g = jax.vmap(value_grad)(x)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        upd, state = jax.vmap(opt.update)(g, state, x)
        return optax.apply_updates(x, upd), state, loss, r

    x = jnp.asarray(u0 / DECISION_SCALE, jnp.float32)
    state = jax.vmap(opt.init)(x)
    hist, rhist = [], []
    xs = [x]
    it = range(iterations)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc="cycle optimisation", unit="it")
    for _ in it:
        x_new, state, loss, r = step(x, state)
        hist.append(np.asarray(loss))
        rhist.append(np.linalg.norm(np.asarray(r), axis=-1))
        x = x_new
        xs.append(x)
    # Evaluate the final iterate.
    final = jax.jit(jax.vmap(lambda xx: residual(xx * scale, params)))(x)
    final = np.asarray(final)
    u = np.asarray(x) * DECISION_SCALE
    rn = np.linalg.norm(final, axis=-1)
    rn = np.where(np.isfinite(rn), rn, np.inf)
    loss = 0.5 * rn**2
    return CycleResult(u=u, residual=final, residual_norm=rn, loss=loss, history=np.asarray(hist),
                       residual_history=np.asarray(rhist), best=int(np.argmin(rn)))


def cycle_vector(params: bd.BoundingParams) -> jax.Array:
    """``(a_fz, a_hz, a_fx, a_hx)`` of ``params.amplitudes``."""
    amp = params.amplitudes
    return jnp.stack([amp[0, 2], amp[2, 2], amp[0, 0], amp[2, 0]])


@functools.partial(jax.jit, static_argnames=("period",))
def linearise(params: bd.BoundingParams, s_star: jax.Array, period: float):
    """``(P(s*), A = dP/ds (5, 5), B = dP/da (5, 4))`` at ``s*`` by ``jax.jacfwd`` (9 tangents, one compile).

    ``a = (a_fz, a_hz, a_fx, a_hx)``. ``A`` includes the apex feedback when ``params.switches.apex_feedback``
    is 1 (the feedback reads the apex sample at the start of the period; the estimator starts at the truth).
    """
    m, mx, ids = _model()
    s_star = jnp.asarray(s_star, jnp.float32)
    a0 = cycle_vector(params)

    def f(x):
        s, a = x[:5], x[5:]
        amp = params.amplitudes.at[0:2, 2].set(a[0]).at[2:4, 2].set(a[1]).at[0:2, 0].set(a[2]) \
            .at[2:4, 0].set(a[3])
        out = return_map(mx, m, ids, params.replace(amplitudes=amp), s, period=period)
        return out, out

    jac, out = jax.jacfwd(f, has_aux=True)(jnp.concatenate([s_star, a0]))
    return out, jac[:, :5], jac[:, 5:]


def with_feedback(params: bd.BoundingParams, apex: bool, stance: bool | None = None) -> bd.BoundingParams:
    """``params`` with the apex (Eq. B4) and stance (Eq. B7) feedback switched on / off (stance defaults to apex)."""
    stance = apex if stance is None else stance
    sw = dataclasses.replace(params.switches, apex_feedback=jnp.float32(1.0 if apex else 0.0),
                             stance_feedback=jnp.float32(1.0 if stance else 0.0))
    return params.replace(switches=sw)


def reference_table(params: bd.BoundingParams, s_star, n: int = 40, control_dt: float = 0.002) -> np.ndarray:
    """Record the open-loop cycle from ``s*`` (feedback off): ``(z, theta, zdot, thetadot)`` at phases ``k / n``.

    This is the reference of the stance feedback (Eq. B7), which therefore vanishes on the cycle.
    """
    period = float(params.gait.period)
    ticks = int(round(period / control_dt))
    if not (isinstance(n, int) and n >= 2 and ticks % n == 0):
        raise ValueError(f"n must be an int >= 2 dividing the ticks per period ({ticks}), got {n}")
    m, mx, ids = _model()
    p = with_feedback(params, False)
    s_star = jnp.asarray(s_star, jnp.float32)

    @jax.jit
    def run(p, s):
        p = p.replace(init_estimate=jnp.stack([s[0], s[2], jnp.zeros((), s.dtype), s[3]]))
        d0 = apex_data(mx, m, p, s)
        cfg = sim.SimConfig(control_dt=control_dt, duration=period, record_every=ticks // n)
        res = sim.rollout(mx, ids, d0, bd.bounding_controller, p, cfg, record=lambda d, o, i: data_apex(d))
        return res.trace

    tr = np.asarray(run(p, s_star), np.float64)  # phases 1/n ... 1
    table = np.concatenate([np.asarray(s_star, np.float64)[None], tr[:-1]], 0)
    return table[:, [0, 1, 3, 4]]


def feedback_matrix(params: bd.BoundingParams, gains: dict | None = None) -> np.ndarray:
    """``d a / d s`` (4, 5) of the apex feedback Eq. B4 at the cycle (the ``K`` of ``A + B K``)."""
    g = params.gains if gains is None else gains
    get = (lambda k: float(getattr(g, k))) if gains is None else (lambda k: float(g[k]))
    af, ah = float(params.amplitudes[0, 2]), float(params.amplitudes[2, 2])
    k = np.zeros((4, 5))
    # alpha = 1 + kz (z* - z) + kzd (zd* - zd); delta = kth (th - th*) + kthd (thd - thd*)
    dalpha = np.array([-get("k_height"), 0, 0, -get("k_height_rate"), 0])
    ddelta = np.array([0, get("k_pitch"), 0, 0, get("k_pitch_rate")])
    k[0] = af * (dalpha + ddelta)
    k[1] = ah * (dalpha - ddelta)
    k[2, 2] = k[3, 2] = -get("k_speed")
    return k


def design_feedback(a_mat: np.ndarray, b_mat: np.ndarray, params: bd.BoundingParams, k_speed: float,
                    grid: dict | None = None):
    """Pick the apex gains (k_height, k_height_rate, k_pitch, k_pitch_rate) minimising the spectral radius of
    ``A + B K(gains)`` on a grid (cheap: numpy on the linearised map). Returns ``(gains, radius)``."""
    grid = grid or dict(k_height=np.linspace(0, 8, 9), k_height_rate=np.linspace(-0.4, 0.4, 9),
                        k_pitch=np.linspace(-1.0, 2.0, 13), k_pitch_rate=np.linspace(-0.2, 0.3, 11))
    best, best_rho = None, np.inf
    for kz in grid["k_height"]:
        for kzd in grid["k_height_rate"]:
            for kt in grid["k_pitch"]:
                for ktd in grid["k_pitch_rate"]:
                    gains = dict(k_height=kz, k_height_rate=kzd, k_pitch=kt, k_pitch_rate=ktd, k_speed=k_speed)
                    k = feedback_matrix(params, gains)
                    rho = np.max(np.abs(np.linalg.eigvals(a_mat + b_mat @ k)))
                    if rho < best_rho - 1e-9:
                        best, best_rho = gains, rho
    return best, best_rho


def gradient_check(params: bd.BoundingParams, u, indices=(0, 1), eps=(2.0, 2.0)):
    """Forward-mode vs central finite differences of the residual w.r.t. ``u[indices]`` (one compiled ``vmap``).

    Returns ``(r(u) (6,), J_fwd (6, k), J_fd (6, k))`` with
    ``J_fd[:, j] = (r(u + eps_j e_j) - r(u - eps_j e_j)) / 2 eps_j``.
    """
    u = np.asarray(u, np.float64)
    idx = list(indices)
    if u.shape != (N_DECISION,):
        raise ValueError(f"u must have shape ({N_DECISION},), got {u.shape}")
    if not idx or any(not (0 <= i < N_DECISION) for i in idx):
        raise ValueError(f"indices must be a non-empty list of ints in [0, {N_DECISION}), got {idx}")
    eps = np.asarray(eps, np.float64)
    if eps.ndim > 1 or (eps.ndim == 1 and eps.shape[0] not in (1, len(idx))):
        raise ValueError(f"eps must be a scalar or have one entry per index, got shape {eps.shape}")
    eps = np.broadcast_to(eps, (len(idx),))
    if np.any(eps <= 0):
        raise ValueError(f"eps must be > 0, got {eps}")
    k = len(idx)
    e = np.zeros((k, N_DECISION))
    e[np.arange(k), idx] = 1.0
    pts = np.concatenate([np.tile(u, (k, 1)), u + eps[:, None] * e, u - eps[:, None] * e], 0)
    tans = np.concatenate([e, np.zeros((2 * k, N_DECISION))], 0)
    r, t = residual_jvp(params, jnp.asarray(pts, jnp.float32), jnp.asarray(tans, jnp.float32),
                        period=float(params.gait.period))
    r, t = np.asarray(r, np.float64), np.asarray(t, np.float64)
    j_fwd = t[:k].T
    j_fd = ((r[k:2 * k] - r[2 * k:]) / (2 * eps[:, None])).T
    return r[0], j_fwd, j_fd


def defaults_source(u, table, apex_gains: dict, note: str = "") -> str:
    """Python source of :mod:`hyqjax.bounding_defaults` for a cycle ``u`` (8,), its reference table and apex gains."""
    u = np.asarray(u, np.float64)
    s = np.asarray(apex_state(jnp.asarray(u, jnp.float32)), np.float64)
    s[0], s[2], s[3], s[4] = u[4], u[7], u[5], u[6]
    fmt = lambda v: "[" + ", ".join(f"{x:.7g}" for x in v) + "]"  # noqa: E731
    rows = ",\n    ".join(fmt(r) for r in np.asarray(table, np.float64))
    gains = ", ".join(f"{k}={float(v):.6g}" for k, v in apex_gains.items())
    return (
        '"""Generated by ``python -m experiments.bounding_figures --write-defaults``: the default bounding limit cycle.\n\n'
        "Do not edit by hand. CYCLE_AMPLITUDES = (a_fz, a_hz, a_fx, a_hx) (N per leg);\n"
        "CYCLE_APEX = (z, theta, xdot, zdot, thetadot) at phase 0; CYCLE_REFERENCE = (z, theta, zdot, thetadot)\n"
        "at phases k / N (the stance feedback's reference, Eq. B7); APEX_GAINS = the apex feedback gains\n"
        "(Eqs. B4, B5): candidates designed on the linearised return map, the most robust one in closed-loop\n"
        "simulation kept (see docs/bounding.md).\n"
        + (f"\n{note}\n" if note else "") + '"""\n'
        "import numpy as np\n\n"
        f"CYCLE_AMPLITUDES = np.array({fmt(u[:4])})\n"
        f"CYCLE_APEX = np.array({fmt(s)})\n"
        f"CYCLE_REFERENCE = np.array([\n    {rows}])\n"
        f"APEX_GAINS = dict({gains})\n")


def stored_cycle() -> np.ndarray:
    """The decision vector ``u*`` (8,) of the stored default cycle (:mod:`hyqjax.bounding_defaults`)."""
    from hyqjax import bounding_defaults as bdef

    a, s = np.asarray(bdef.CYCLE_AMPLITUDES, np.float64), np.asarray(bdef.CYCLE_APEX, np.float64)
    return np.array([a[0], a[1], a[2], a[3], s[0], s[3], s[4], s[2]])


def augmented_matrix(a_closed: np.ndarray, b_mat: np.ndarray, params: bd.BoundingParams) -> np.ndarray:
    """Linearised return map with the per-cycle integrators of Eqs. B4-B5 as extra states.

    ``a_closed`` is ``dP/ds`` with the apex feedback on (its proportional terms, the speed term and the
    placement correction included) and ``b_mat = dP/da``. State ``(s_k - s*, I_{k-1})``:
    ``I_k = I_{k-1} + C (s_k - s*)``, ``s_{k+1} - s* = A_closed (s_k - s*) + B K_i I_k``. Only integrators with a
    non-zero gain are states (an integrator with zero gain is a decoupled eigenvalue 1).
    """
    g = params.gains
    af, ah = float(params.amplitudes[0, 2]), float(params.amplitudes[2, 2])
    rows, cols = [], []
    if float(g.k_height_int):
        rows.append([-1.0, 0, 0, 0, 0])  # z* - z
        cols.append(np.array([af, ah, 0.0, 0.0]) * float(g.k_height_int))
    if float(g.k_pitch_int):
        rows.append([0, 1.0, 0, 0, 0])  # theta - theta*
        cols.append(np.array([af, -ah, 0.0, 0.0]) * float(g.k_pitch_int))
    if float(g.k_speed_int):
        rows.append([0, 0, -1.0, 0, 0])  # xdot* - xdot
        cols.append(np.array([0.0, 0.0, 1.0, 1.0]) * float(g.k_speed_int))
    if not rows:
        return np.asarray(a_closed)
    c = np.asarray(rows)
    ki = np.stack(cols, 1)
    top = np.concatenate([a_closed + b_mat @ ki @ c, b_mat @ ki], 1)
    bot = np.concatenate([c, np.eye(len(rows))], 1)
    return np.concatenate([top, bot], 0)
