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
``u = (a_{f,z}, a_{h,z}, a_{f,x}, a_{h,x}, z_0, zdot_0, thetadot_0)`` with ``theta_0 = xdot_0 = 0``
(bounding in place). :func:`residual` is ``r(u) = W (P(s_0(u), a(u)) - s_0(u))`` with per-component
scales ``W = diag(1 / RESIDUAL_SCALE)``. The cycle family has two free directions (height and
``a_{f,x} - a_{h,x}``), fixed by a soft prior; the loss is

.. math:: L(u) = \\tfrac12 \\|r(u)\\|^2 + \\tfrac{\\lambda}{2} \\Big[\\Big(\\frac{z_0 - z^d}{0.02}\\Big)^2 +
          \\Big(\\frac{a_{f,x}}{100}\\Big)^2 + \\Big(\\frac{a_{h,x}}{100}\\Big)^2\\Big].   \\qquad (C2)

Its gradient ``J_r^T r + ...`` uses the forward-mode Jacobian ``J_r = jax.jacfwd(residual)``
(seven tangents through ``mjx.step``; reverse mode through MJX's solver ``while_loop`` is not
available). :func:`optimise_cycle` runs optax (Adam on the scaled ``u``, or a Levenberg-Marquardt
direction fed through ``optax.scale_by_schedule``) from many initial guesses at once (``vmap``).

Stability
---------
:func:`return_map_jacobian` is ``dP/ds`` at the fixed point (``jax.jacfwd`` w.r.t. the apex state);
its eigenvalues are the Floquet multipliers of the sagittal cycle, with the apex feedback
(Eq. B4) switched on or off. The feedback is zero on the cycle, so both maps share ``s*``.
"""
from __future__ import annotations

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
#: Scales of the decision vector ``u = (a_fz, a_hz, a_fx, a_hx, z0, zdot0, thetadot0)``.
DECISION_SCALE = np.array([100.0, 100.0, 100.0, 100.0, 0.05, 0.1, 1.0])
DECISION_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx", "z0", "zdot0", "thetadot0")


@functools.lru_cache(maxsize=4)
def _model(timestep: float = 0.002):
    m = hmodel.load_model(timestep=timestep)
    with jax.ensure_compile_time_eval():  # concrete arrays even if first called inside a trace
        mx = mjx.put_model(m)
    return m, mx, hmodel.model_ids(m)


def apex_state(u: jax.Array) -> jax.Array:
    """``s_0(u) = (z_0, 0, 0, zdot_0, thetadot_0)`` from the decision vector."""
    z = jnp.zeros((), u.dtype)
    return jnp.stack([u[4], z, z, u[5], u[6]])


def with_cycle(params: bd.BoundingParams, u: jax.Array) -> bd.BoundingParams:
    """``params`` with amplitudes and apex reference from the decision vector ``u`` (7,)."""
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
    v_des, yr, _ = bd.ramped_command(p.command, obs.time)
    b_x, _, _ = bd.foot_references(p, st, obs.time, rpy, rates, obs.gyro, stance, s_st, s_sw, v_des, yr,
                                   jnp.zeros((), s.dtype))
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
               control_dt: float = 0.002) -> jax.Array:
    """``P(s)`` (Eq. C1): apex state after ``n_periods`` gait periods of the closed loop from apex state ``s``.

    ``params.apex_ref`` is the cycle the apex feedback regulates to; the estimator starts at the true state.
    """
    s = jnp.asarray(s, jnp.float32)
    p = params.replace(init_estimate=jnp.stack([s[0], s[2], jnp.zeros((), s.dtype), s[3]]))
    d0 = apex_data(mx, m, p, s)
    period = float(params.gait.period)
    cfg = sim.SimConfig(control_dt=control_dt, duration=n_periods * period, record_every=0)
    res = sim.rollout(mx, ids, d0, bd.bounding_controller, p, cfg)
    return data_apex(res.data)


def residual(u: jax.Array, params: bd.BoundingParams, n_periods: int = 1) -> jax.Array:
    """Scaled periodicity residual ``W (P(s_0(u), a(u)) - s_0(u))`` (5,), Eq. C2."""
    m, mx, ids = _model()
    p = with_cycle(params, u)
    s0 = apex_state(u)
    s1 = return_map(mx, m, ids, p, s0, n_periods)
    return (s1 - s0) / jnp.asarray(RESIDUAL_SCALE, s1.dtype)


def loss_terms(u, r, z_des, prior_weight):
    prior = jnp.stack([(u[4] - z_des) / 0.02, u[2] / 100.0, u[3] / 100.0])
    return 0.5 * jnp.sum(r**2) + 0.5 * prior_weight * jnp.sum(prior**2), prior


def residual_and_jacobian(u: jax.Array, params: bd.BoundingParams):
    """``(r(u), dr/du)`` with forward mode (``jax.jacfwd``, 7 tangents)."""
    f = lambda uu: residual(uu, params)  # noqa: E731
    r, jvp_fn = jax.linearize(f, u)
    jac = jax.vmap(jvp_fn, in_axes=1, out_axes=1)(jnp.eye(u.shape[0], dtype=u.dtype))
    return r, jac


class CycleResult(NamedTuple):
    """Optimisation output (numpy). ``u``: (B, 7) decision vectors; ``residual_norm``: (B,) ``||r||``;
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
    u = np.zeros((n, 7))
    u[:, 0] = af * rng.uniform(0.9, 1.1, n)
    u[:, 1] = ah * rng.uniform(0.9, 1.1, n)
    u[:, 2:4] = rng.normal(0.0, 20.0, (n, 2))
    u[:, 4] = z_des + rng.uniform(-0.03, 0.03, n)
    u[:, 5] = rng.uniform(-0.1, 0.1, n)
    u[:, 6] = rng.uniform(-3.0, -1.0, n)
    u[0] = [af, ah, 0.0, 0.0, z_des, 0.0, -2.0]
    return u


def optimise_cycle(params: bd.BoundingParams, u0: np.ndarray, iterations: int = 30, method: str = "lm",
                   learning_rate: float = 0.05, z_des: float = 0.6, prior_weight: float = 1e-2,
                   damping: float = 1e-2, progress: bool = True) -> CycleResult:
    """Minimise Eq. C2 from every row of ``u0`` at once (``vmap`` over guesses, forward-mode Jacobians).

    Args:
      method: ``'lm'``: optax SGD (learning rate 1 with a warm-up schedule) applied to the
        Levenberg-Marquardt step ``-(J^T J + mu I)^{-1} g`` (Gauss-Newton, robust for this 7x5 problem);
        ``'adam'``: ``optax.adam(learning_rate)`` on the gradient ``g = J^T r + prior``.
      iterations: optimiser steps (each is one batched jacfwd return map).
    """
    if method not in ("lm", "adam"):
        raise ValueError(f"method must be 'lm' or 'adam', got {method!r}")
    if not (isinstance(iterations, int) and 1 <= iterations <= 10000):
        raise ValueError(f"iterations must be an int in [1, 10000], got {iterations}")
    u0 = np.atleast_2d(np.asarray(u0, np.float64))
    if u0.shape[1] != 7:
        raise ValueError(f"u0 must have shape (B, 7), got {u0.shape}")
    scale = jnp.asarray(DECISION_SCALE, jnp.float32)

    def value_grad(x):
        u = x * scale
        r, jac = residual_and_jacobian(u, params)
        loss, prior = loss_terms(u, r, z_des, prior_weight)
        jx = jac * scale[None, :]
        jp = jnp.zeros((3, 7), jnp.float32).at[0, 4].set(scale[4] / 0.02).at[1, 2].set(scale[2] / 100.0) \
            .at[2, 3].set(scale[3] / 100.0) * jnp.sqrt(prior_weight)
        jall = jnp.concatenate([jx, jp], 0)
        rall = jnp.concatenate([r, jnp.sqrt(prior_weight) * prior])
        g = jall.T @ rall
        if method == "lm":
            h = jall.T @ jall + damping * jnp.eye(7, dtype=jall.dtype)
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


def return_map_jacobian(params: bd.BoundingParams, s_star, apex_feedback: bool, n_periods: int = 1):
    """``(P(s*), dP/ds (5, 5))`` at ``s*`` by ``jax.jacfwd``, with the apex feedback on or off."""
    m, mx, ids = _model()
    p = params.replace(apex_ref=jnp.asarray(s_star, jnp.float32),
                       switches=dataclasses.replace(params.switches,
                                                    apex_feedback=jnp.float32(1.0 if apex_feedback else 0.0)))
    f = lambda s: return_map(mx, m, ids, p, s, n_periods)  # noqa: E731
    s_star = jnp.asarray(s_star, jnp.float32)
    out, jvp_fn = jax.linearize(f, s_star)
    jac = jax.vmap(jvp_fn, in_axes=1, out_axes=1)(jnp.eye(5, dtype=jnp.float32))
    return np.asarray(out), np.asarray(jac)


def amplitude_jacobian(params: bd.BoundingParams, s_star):
    """``dP/da`` (5, 4) at ``s*`` w.r.t. ``(a_fz, a_hz, a_fx, a_hx)`` (feedback off), for feedback design."""
    m, mx, ids = _model()
    p = params.replace(switches=dataclasses.replace(params.switches, apex_feedback=jnp.float32(0.0)))
    s_star = jnp.asarray(s_star, jnp.float32)
    a0 = jnp.stack([p.amplitudes[0, 2], p.amplitudes[2, 2], p.amplitudes[0, 0], p.amplitudes[2, 0]])

    def f(a):
        amp = p.amplitudes.at[0:2, 2].set(a[0]).at[2:4, 2].set(a[1]).at[0:2, 0].set(a[2]).at[2:4, 0].set(a[3])
        return return_map(mx, m, ids, p.replace(amplitudes=amp), s_star)

    _, jvp_fn = jax.linearize(f, a0)
    return np.asarray(jax.vmap(jvp_fn, in_axes=1, out_axes=1)(jnp.eye(4, dtype=jnp.float32)))


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


def finite_difference_jacobian(u: np.ndarray, params: bd.BoundingParams, eps: np.ndarray):
    """Central finite differences of :func:`residual` w.r.t. ``u`` (all ``2 * 7`` points in one ``vmap``)."""
    u = np.asarray(u, np.float64)
    eps = np.broadcast_to(np.asarray(eps, np.float64), u.shape)
    pts = np.concatenate([u + np.diag(eps), u - np.diag(eps)], 0)
    rs = np.asarray(jax.jit(jax.vmap(lambda uu: residual(uu, params)))(jnp.asarray(pts, jnp.float32)), np.float64)
    n = u.shape[0]
    return ((rs[:n] - rs[n:]) / (2 * eps[:, None])).T
