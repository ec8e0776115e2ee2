"""The bounding limit cycle: apex return map through MJX and its optimisation.

Apex state and return map
-------------------------
The Poincare section is the gait clock's phase 0 (mid-flight before the hind stance, the apex).
The sagittal apex state is ``s = (z, theta, xdot, zdot, thetadot)`` (:class:`hyqjax.bounding.params.Apex`;
arrays in that order). :func:`apex_data` places HyQ in the air at ``s`` (roll, yaw, lateral motion
zero; legs at the controller's phase-0 swing references, joint rates zero) and the controller's
estimator at the true ``(z, xdot, zdot)``; :func:`return_map` simulates one period ``T`` of the
closed loop (``sim.rollout``, ``mjx.step``) and reads ``s`` again:

.. math:: s_{k+1} = P(s_k, a), \\qquad a = (a_{f,z}, a_{h,z}, a_{f,x}, a_{h,x}).                \\qquad (C1)

Periodicity (cycle optimisation)
--------------------------------
A limit cycle is a fixed point ``s* = P(s*, a*)``. The decision vector is
``u = (a_{f,z}, a_{h,z}, a_{f,x}, a_{h,x}, z_0, zdot_0, thetadot_0, xdot_0)`` with ``theta_0 = 0``;
the feedback (Eqs. B4, B5, B7, B8) is switched off. :func:`residual` (6,) is
``r(u) = (W (P(s_0(u), a(u)) - s_0(u)), Delta x / 0.01 m)``, per-component scales
``W = diag(1 / RESIDUAL_SCALE)``, plus the forward displacement over the period (bounding *in place*
has zero net drift, not only a periodic speed). The family of cycles has free directions (height,
``a_{f,x} - a_{h,x}``), fixed by a soft prior; the least-squares problem is

.. math:: \\min_u \\tfrac12 \\|r(u)\\|^2 + \\tfrac{\\lambda}{2} \\Big[\\Big(\\frac{z_0 - z^d}{0.02}\\Big)^2 +
          \\Big(\\frac{a_{f,x}}{100}\\Big)^2 + \\Big(\\frac{a_{h,x}}{100}\\Big)^2\\Big].   \\qquad (C2)

:func:`optimise_cycle` solves it with ``optimistix.LevenbergMarquardt`` (trust-region damping, QR
solves) from many initial guesses at once (``vmap``). Its Jacobian is forward mode (``jac="fwd"``):
the residual carries a ``jax.custom_jvp`` whose rule is one ``jax.jacfwd`` (eight tangents through
``mjx.step``; reverse mode needs :func:`hyqjax.sim.reverse_mode.fixed_length_solver`, not used here), so each LM step costs
one batched forward-mode return map. :func:`gradient_check` compares the forward-mode Jacobian with
central finite differences. The linearisation and feedback design are in :mod:`hyqjax.bounding.stability`.
"""
from __future__ import annotations

import copy
import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optimistix as optx
from mujoco import mjx

from hyqjax.bounding import controller as bctrl
from hyqjax.bounding import defaults as bdef
from hyqjax.bounding import estimator
from hyqjax.bounding import gait as bgait
from hyqjax.bounding import kinematic
from hyqjax.bounding.params import Apex, BoundingParams
from hyqjax.core import kinematics
from hyqjax.core.batching import vmap_unless_one
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim

#: Residual scales of ``(z, theta, xdot, zdot, thetadot)``: a residual of 1 is 1 cm, 0.01 rad, 0.05 m/s,
#: 0.05 m/s, 0.1 rad/s.
RESIDUAL_SCALE = np.array([0.01, 0.01, 0.05, 0.05, 0.1])
#: Scale of the sixth residual, the forward displacement over one period (m): bounding *in place*.
DISPLACEMENT_SCALE = 0.01
N_DECISION = 8
#: Scales of the decision vector ``u`` (the optimiser works on ``u / DECISION_SCALE``).
DECISION_SCALE = np.array([100.0, 100.0, 100.0, 100.0, 0.05, 0.1, 1.0, 0.05])
DECISION_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx", "z0", "zdot0", "thetadot0", "xdot0")


@functools.lru_cache(maxsize=4)
def model(timestep: float = 0.002):
    """``(MjModel, mjx.Model, ids)`` of HyQ on flat ground: :func:`hyqjax.sim.model.load_model` with the
    platform's collisions switched off.

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


def with_amplitudes(params: BoundingParams, a: jax.Array) -> BoundingParams:
    """``params`` with the cycle amplitudes ``a = (a_fz, a_hz, a_fx, a_hx)`` on both legs of each pair."""
    amp = params.amplitudes
    amp = amp.at[0:2, 2].set(a[0]).at[2:4, 2].set(a[1]).at[0:2, 0].set(a[2]).at[2:4, 0].set(a[3])
    return params.replace(amplitudes=amp)


def with_cycle(params: BoundingParams, u: jax.Array) -> BoundingParams:
    """``params`` with amplitudes and apex reference from the decision vector ``u`` (8,)."""
    return with_amplitudes(params, u[:4]).replace(apex_ref=Apex.of(apex_state(u).astype(jnp.float32)))


def with_estimate(params: BoundingParams, s: jax.Array) -> BoundingParams:
    """``params`` whose estimator starts at the true ``(z, xdot, 0, zdot)`` of apex state ``s``."""
    a = Apex.of(s)
    return params.replace(init_estimate=jnp.stack([a.z, a.vx, jnp.zeros((), s.dtype), a.vz]).astype(jnp.float32))


def cycle_vector(params: BoundingParams) -> jax.Array:
    """``(a_fz, a_hz, a_fx, a_hx)`` of ``params.amplitudes``."""
    amp = params.amplitudes
    return jnp.stack([amp[0, 2], amp[2, 2], amp[0, 0], amp[2, 0]])


def apex_observation(s, q, time=0.0) -> sim.Observation:
    """What the robot measures in flight at apex state ``s`` with joints ``q`` (at rest): pitch and pitch rate."""
    dt = s.dtype
    a = Apex.of(s)
    half = 0.5 * a.pitch
    quat = jnp.stack([jnp.cos(half), jnp.zeros((), dt), jnp.sin(half), jnp.zeros((), dt)])
    return sim.Observation(q=q, qd=jnp.zeros(12, dt), tau=jnp.zeros(12, dt), quat=quat,
                           gyro=jnp.stack([0.0, a.pitch_rate, 0.0]).astype(dt), foot_force=jnp.zeros((4, 3), dt),
                           time=jnp.asarray(time, dt))


def reference_joints(params: BoundingParams, s: jax.Array) -> jax.Array:
    """Joint references (12,) of the controller at phase 0 with the trunk at apex state ``s``."""
    q0 = jnp.asarray(robot.Q_STANDING, s.dtype)
    obs = apex_observation(s, q0)
    a = Apex.of(s)
    p = with_estimate(params, s)
    st = bctrl.bounding_init(p, obs)
    att = estimator.imu(obs)
    stance, s_st, s_sw = bgait.leg_phase(p.gait, obs.time)
    v_des, _, _ = bgait.ramped_command(p.command, obs.time)
    zero = jnp.zeros((), s.dtype)
    target = kinematic.touchdown_target(p, jnp.stack([a.vx, zero, a.vz]),
                                        st.apex_vel - v_des - jnp.stack([p.apex_ref.vx, zero]), zero)
    b_x, _, _ = kinematic.foot_references(p, st, obs.time, att.rpy, att.rates, obs.gyro, stance, s_st, s_sw, v_des,
                                          target, zero)
    return jnp.clip(kinematics.inverse_kinematics(b_x).reshape(12), robot.Q_MIN + 0.02, robot.Q_MAX - 0.02)


def apex_data(mx: mjx.Model, m: mujoco.MjModel, params: BoundingParams, s: jax.Array, xy=(0.0, 0.0), yaw=0.0,
              roll=0.0, vy=0.0, yaw_rate=0.0) -> mjx.Data:
    """MJX data with HyQ in the air at apex state ``s`` (optionally with roll / yaw / lateral speed)."""
    dtype = jnp.float32
    s = jnp.asarray(s, dtype)
    a = Apex.of(s)
    q_legs = reference_joints(params, s)
    rot = spatial.rpy_to_rot(jnp.stack([jnp.asarray(roll, dtype), a.pitch, jnp.asarray(yaw, dtype)]))
    qpos = jnp.concatenate([jnp.stack([jnp.asarray(xy[0], dtype), jnp.asarray(xy[1], dtype), a.z]),
                            spatial.rot_to_quat_trace(rot), q_legs.astype(dtype)])
    omega_w = jnp.stack([jnp.zeros((), dtype), a.pitch_rate, jnp.asarray(yaw_rate, dtype)])
    omega_b = rot.T @ omega_w  # pitch rate about the (yaw-rotated) world y axis, approx.
    v = jnp.stack([a.vx, jnp.asarray(vy, dtype), a.vz])
    v_w = spatial.rot_z(jnp.asarray(yaw, dtype)) @ v
    qvel = jnp.concatenate([v_w, omega_b, jnp.zeros(12, dtype)])
    d = mjx.make_data(mx)
    return d.replace(qpos=qpos.astype(d.qpos.dtype), qvel=qvel.astype(d.qvel.dtype))


def data_apex(d: mjx.Data) -> Apex:
    """Sagittal apex state of MJX data (ground truth; ``vx`` along the trunk's heading)."""
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
    rates = spatial.euler_rates(rpy, d.qvel[robot.QVEL_BASE_ANG])
    v = d.qvel[robot.QVEL_BASE_LIN]
    vx = jnp.cos(rpy[2]) * v[0] + jnp.sin(rpy[2]) * v[1]
    return Apex(z=d.qpos[robot.QPOS_BASE_POS][2], pitch=rpy[1], vx=vx, vz=v[2], pitch_rate=rates[1])


#: The bounding controller of the programs that differentiate a rollout (the return map's residual and its
#: Levenberg-Marquardt Jacobians, the stability Jacobian, :func:`hyqjax.bounding.robust.make_value_and_jac`): its
#: rollout ties the scan's initial carry to the parameters (:func:`hyqjax.core.scan_carry.tie_carry`, values bit for
#: bit), so ``lax.scan``'s forward-mode and batching rules reach their fixed point without transforming the tick
#: three times each. ``jacfwd`` of the robust training cost (4 tangents, 0.4 s): traced in 7.1-7.3 s instead of
#: 11.9-12.0 s, XLA unchanged (6.8-7.1 s), the same value and gradient (benchmarks/RESULTS.md). The batch runner's
#: forward programs keep the untied controller (tied, their compile phase took 0.2 s longer).
DIFFERENTIATED_CONTROLLER = bctrl.bounding_controller._replace(tie_rollout_carry=True)


def return_map(mx, m, ids, params: BoundingParams, s: jax.Array, n_periods: int = 1,
               control_dt: float = 0.002, period: float | None = None, displacement: bool = False):
    """``P(s)`` (5,) (Eq. C1): apex state after ``n_periods`` gait periods of the closed loop from apex state ``s``.

    ``params.apex_ref`` is the cycle the apex feedback regulates to; the estimator starts at the true state.
    ``period`` (static) defaults to ``params.gait.period``, which must then be concrete. With ``displacement``
    also returns the forward displacement over the simulated time.
    """
    s = jnp.asarray(s, jnp.float32)
    p = with_estimate(params, s)
    d0 = apex_data(mx, m, p, s)
    period = float(params.gait.period) if period is None else period
    cfg = sim.SimConfig(control_dt=control_dt, duration=n_periods * period, record_every=0)
    res = sim.rollout(mx, ids, d0, DIFFERENTIATED_CONTROLLER, p, cfg)
    s1 = data_apex(res.data).array()
    if displacement:
        return s1, res.data.qpos[robot.QPOS_BASE_POS][0] - d0.qpos[robot.QPOS_BASE_POS][0]
    return s1


def residual(u: jax.Array, params: BoundingParams, n_periods: int = 1, period: float | None = None) -> jax.Array:
    """Scaled periodicity residual (6,): ``W (P(s_0(u), a(u)) - s_0(u))`` and the drift ``Delta x / 0.01 m``, Eq. C2."""
    m, mx, ids = model()
    s0 = apex_state(u)
    s1, dx = return_map(mx, m, ids, with_cycle(params, u), s0, n_periods, period=period, displacement=True)
    return jnp.concatenate([(s1 - s0) / jnp.asarray(RESIDUAL_SCALE, s1.dtype), (dx / DISPLACEMENT_SCALE)[None]])


#: Lengths of :func:`residual` (the periodicity residual and the drift) and of :func:`prior_residual`.
N_RESIDUAL, N_PRIOR = 6, 3


def prior_residual(u: jax.Array, z_des: float) -> jax.Array:
    """The soft prior of Eq. C2 as residuals (3,): ``((z_0 - z^d) / 0.02, a_fx / 100, a_hx / 100)``."""
    return jnp.stack([(u[4] - z_des) / 0.02, u[2] / 100.0, u[3] / 100.0])


@functools.partial(jax.jit, static_argnames=("period",))
def residual_jvp(params: BoundingParams, u: jax.Array, v: jax.Array, period: float):
    """Batched ``(r(u_i), dr/du(u_i) v_i)`` (``vmap`` over rows of ``u``, ``v``): one compile serves the
    forward-mode directional derivatives, the finite-difference points (``v = 0``) and the periodicity check.
    ``period`` must equal ``params.gait.period`` (static: it sets the number of ticks)."""
    return jax.vmap(lambda uu, vv: jax.jvp(lambda x: residual(x, params, period=period), (uu,), (vv,)))(u, v)


class CycleResult(NamedTuple):
    """Optimisation output (NumPy). ``u``: (B, 8) decision vectors; ``residual``: (B, 6) ``r(u)``;
    ``residual_norm``: (B,) ``||r||``; ``loss``: (B,) Eq. C2; ``history``: (steps, B) loss at the accepted
    iterate after each LM step (row 0: at the initial guess, which optimistix's first step evaluates and
    accepts); ``residual_history``: (steps, B) its ``||r||``; ``steps``: (B,) LM steps
    taken before optimistix's termination test held (or all of them); ``best``: index of the smallest ``||r||``."""

    u: np.ndarray
    residual: np.ndarray
    residual_norm: np.ndarray
    loss: np.ndarray
    history: np.ndarray
    residual_history: np.ndarray
    steps: np.ndarray
    best: int


def initial_guesses(params: BoundingParams, n: int, seed: int = 0, z_des: float = 0.6) -> np.ndarray:
    """``n`` decision vectors spread around Park & Kim's impulse balance (Eq. B2)."""
    if not (isinstance(n, int) and 1 <= n <= 4096):
        raise ValueError(f"n (number of initial guesses) must be an int in [1, 4096], got {n}")
    rng = np.random.default_rng(seed)
    af, ah = bgait.impulse_guess(params.gait)
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


def least_squares_residual(params: BoundingParams, z_des: float, prior_weight: float):
    """``x -> (r(x s), sqrt(lambda) prior(x s))`` (9,) on the scaled decision ``x = u / DECISION_SCALE`` (Eq. C2),
    with a ``custom_jvp`` whose rule materialises the Jacobian by one ``jax.jacfwd``. The function returned is jitted:
    optimistix's ``init`` and ``step`` each differentiate it, and as one jitted function its JVP rule is traced once
    and its transformed program reused (benchmarks/RESULTS.md, "Tracing the bounding cycle's least squares")."""
    scale = jnp.asarray(DECISION_SCALE, jnp.float32)

    @jax.jit  # traced once per shape: optimistix's init and step trace f and its JVP several times
    def full(x):
        u = x * scale
        return jnp.concatenate([residual(u, params), jnp.sqrt(prior_weight) * prior_residual(u, z_des)])

    @jax.custom_jvp
    def f(x):
        return full(x)

    @f.defjvp
    def f_jvp(primals, tangents):
        (x,), (t,) = primals, tangents
        jac, r = jax.jacfwd(lambda xx: (full(xx),) * 2, has_aux=True)(x)
        return r, jac @ t

    return jax.jit(f)


def optimise_cycle(params: BoundingParams, u0: np.ndarray, iterations: int = 10, z_des: float = 0.6,
                   prior_weight: float = 1e-2, rtol: float = 1e-6, atol: float = 1e-6,
                   progress: bool = True) -> CycleResult:
    """Solve Eq. C2 from every row of ``u0`` (B, 8) at once: ``optimistix.LevenbergMarquardt`` stepped
    ``iterations`` times (``vmap`` over guesses, forward-mode Jacobians, one compile of the batched step).

    A guess whose termination test (``rtol``, ``atol`` on the step and the residual) holds keeps its iterate.
    """
    if not (isinstance(iterations, int) and 1 <= iterations <= 10000):
        raise ValueError(f"iterations must be an int in [1, 10000], got {iterations}")
    u0 = np.atleast_2d(np.asarray(u0, np.float64))
    if u0.ndim != 2 or u0.shape[1] != N_DECISION or not np.all(np.isfinite(u0)):
        raise ValueError(f"u0 must be a finite array of shape (B, {N_DECISION}), got shape {u0.shape}")
    if not (np.isfinite(prior_weight) and prior_weight >= 0):
        raise ValueError(f"prior_weight must be finite and >= 0, got {prior_weight}")
    f = least_squares_residual(params, z_des, prior_weight)
    x, r, steps = levenberg_marquardt(f, jnp.asarray(u0 / DECISION_SCALE, jnp.float32), iterations, rtol, atol,
                                      "cycle optimisation (Levenberg-Marquardt)" if progress else None,
                                      n_residuals=N_RESIDUAL + N_PRIOR)
    hist = 0.5 * np.sum(r**2, -1)
    final = r[-1][:, :N_RESIDUAL]
    rn = np.linalg.norm(final, axis=-1)
    rn = np.where(np.isfinite(rn), rn, np.inf)
    return CycleResult(u=np.asarray(x, np.float64) * DECISION_SCALE, residual=final, residual_norm=rn,
                       loss=hist[-1], history=hist, residual_history=np.linalg.norm(r[..., :N_RESIDUAL], axis=-1),
                       steps=steps, best=int(np.argmin(rn)))


def levenberg_marquardt(f, x0, iterations: int, rtol: float, atol: float, progress: str | None = None,
                        n_residuals: int | None = None):
    """``optimistix.LevenbergMarquardt`` on ``f: x (n,) -> r (m,)`` from every row of ``x0`` (B, n) at once, stepped
    ``iterations`` times (forward-mode Jacobians; ``vmap`` over the rows, none for one row:
    :func:`hyqjax.core.batching.vmap_unless_one`); a row whose termination test holds keeps its iterate.
    ``progress``: a progress bar's label (None: none). ``n_residuals``: ``m`` where the caller knows it (``r`` then
    has ``x0``'s dtype), which saves tracing ``f`` once for its output's shape. Returns ``(x (B, n), r (iterations,
    B, m), steps (B,))``: the iterates, the residuals at the accepted iterates, and the steps each row took."""
    fn = lambda x, _: (f(x), None)  # noqa: E731
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    opts, tags = dict(jac="fwd"), frozenset()
    if n_residuals is None:
        f_struct, aux_struct = jax.eval_shape(lambda: fn(x0[0], None))
    else:
        f_struct, aux_struct = jax.ShapeDtypeStruct((int(n_residuals),), x0.dtype), None
    batched = functools.partial(vmap_unless_one, vmap=eqx.filter_vmap)
    init = eqx.filter_jit(batched(lambda x: solver.init(fn, x, None, opts, f_struct, aux_struct, tags)))

    @eqx.filter_jit
    @batched
    def step(x, state):
        done = state.terminate
        x_new, state_new, _ = solver.step(fn, x, None, opts, state, tags)
        return jnp.where(done, x, x_new), state_new, done

    state, x = init(x0), x0
    rs, steps = [], np.zeros(len(x0), np.int64)
    it = range(iterations)
    if progress:
        from tqdm import tqdm

        it = tqdm(it, desc=progress, unit="step")
    for _ in it:
        x, state, done = step(x, state)
        steps += ~np.asarray(done)
        rs.append(np.asarray(state.f_info.residual, np.float64))
    return x, np.stack(rs), steps


def gradient_check(params: BoundingParams, u, indices=(0, 1), eps=(2.0, 2.0)):
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


def stored_cycle() -> np.ndarray:
    """The decision vector ``u*`` (8,) of the stored default cycle (:mod:`hyqjax.bounding.defaults`)."""
    return bdef.stored().decision_vector()
