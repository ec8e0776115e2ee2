"""Closed-loop simulation of one instance: ``lax.scan`` over control ticks of
``controller(params, state, observation) -> joint torques -> mjx.step``.

The simulation is split the way MJX splits physics: a static :class:`SimConfig` (rates and
horizon), an ``mjx.Model`` (batched per instance by :func:`hyqjax.sim.model.batch_model`), and
pure functions. A controller is a :class:`Controller`, a pair of pure functions::

    init(params, obs) -> ctrl_state
    step(params, ctrl_state, obs) -> (ctrl_state, torques (12,), info)

Metrics are accumulated on the device by a :class:`Metrics` pair (``init``, ``update``) so a
long sweep keeps only summaries; traces are recorded every ``record_every`` ticks.

Observations (:class:`Observation`) hold what HyQ measures: joint positions, velocities and
torques, the IMU's orientation and angular velocity, and foot forces estimated from joint
torques. Ground truth (``mjx.Data``) stays available to metrics, never to controllers.

:class:`Observation`, :class:`Controller`, :class:`Metrics` and :class:`Push` are defined in
:mod:`hyqjax.core.types` (no MJX import, so a controller does not load MJX) and re-exported here.

Batches run through :mod:`hyqjax.sim.runner` (``vmap`` + ``jit`` + sharding + chunked progress), which
builds on this module.

An instance whose state becomes non-finite or whose speed exceeds ``SimConfig.max_speed`` is
*diverged*: its state is frozen at the last finite tick and the flag is returned, so a sweep
counts it as a failure instead of averaging NaN.

An instance whose metrics say it has failed past recovery (``Metrics.terminal``, e.g. the step-down's fall)
is *terminated*: its episode ends at that tick, the *failure tick*, and it is frozen there the same way (state,
controller state and metrics), so a controller that keeps commanding a fallen robot cannot drive it into a
simulator blow-up. An instance that never meets its terminal condition runs exactly as without one.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hyqjax.core.types import Observation, Controller, Metrics, Push  # noqa: F401
from hyqjax.sim import impls
from hyqjax.sim import model as hmodel
from hyqjax.sim import observe as hobs
from hyqjax.core import robot
from hyqjax.core.scan_carry import tie_carry


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Static simulation settings (changing them recompiles).

    Attributes:
      control_dt: controller period (s). HyQ's loop runs at 1 kHz; hyqjax defaults to 500 Hz.
      substeps: physics steps per control tick; the physics timestep is ``control_dt / substeps``.
      duration: simulated time (s).
      record_every: record a trace sample every this many ticks (0: no trace).
      max_speed: a generalized velocity above this (m/s or rad/s) flags divergence.
    """

    control_dt: float = 0.002
    substeps: int = 1
    duration: float = 2.0
    record_every: int = 10
    max_speed: float = 100.0

    def __post_init__(self):
        if not (0.0 < self.control_dt <= 0.02):
            raise ValueError(f"control_dt must be in (0, 0.02] s, got {self.control_dt}")
        if not (isinstance(self.substeps, int) and 1 <= self.substeps <= 100):
            raise ValueError(f"substeps must be an int in [1, 100], got {self.substeps}")
        if not (0.0 < self.duration <= 600.0):
            raise ValueError(f"duration must be in (0, 600] s, got {self.duration}")
        if not (isinstance(self.record_every, int) and self.record_every >= 0):
            raise ValueError(f"record_every must be an int >= 0, got {self.record_every}")
        if self.record_every and self.n_ticks % self.record_every:
            raise ValueError(f"record_every ({self.record_every}) must divide the number of ticks ({self.n_ticks})")

    @property
    def physics_dt(self) -> float:
        return self.control_dt / self.substeps

    @property
    def n_ticks(self) -> int:
        return int(round(self.duration / self.control_dt))


def no_metrics() -> Metrics:
    return Metrics(lambda d: (), lambda m, d, o, i: ())


def observe(ids: hmodel.ModelIds, d: mjx.Data, tau: jax.Array, mx: mjx.Model | None = None) -> Observation:
    """Build an :class:`Observation` from MJX data (the sensors HyQ has): :func:`hyqjax.sim.observe.observation`
    with the generalized force ``g = qfrc_bias + M qacc`` of MJX's last step.

    When ``mx`` is given, ``M qacc`` is the mass matrix times the accelerations of the last physics step (what a
    robot gets by differentiating its encoder velocities, one tick late; under MuJoCo Warp the same product from
    the equation of motion, ``M qdd = qfrc_smooth + qfrc_constraint``); without ``mx``, ``g = qfrc_bias``.
    """
    gen = d.qfrc_bias
    if mx is not None and impls.is_warp_model(mx):
        # M qacc = qfrc_smooth + qfrc_constraint (the equation of motion of the last step; mujoco_warp's
        # mass matrix is not in the layout mjx.mul_m reads). External forces act on the free joint only.
        gen = gen + d.qfrc_smooth + d.qfrc_constraint
    elif mx is not None:
        gen = gen + mjx.mul_m(mx, d, d.qacc)
    return hobs.observation(ids.qpos_joints, ids.dof_joints, d.qpos, d.qvel, gen, tau, d.time)


def _physics(mx: mjx.Model, d: mjx.Data, tau: jax.Array, ids: hmodel.ModelIds, substeps: int,
             push: Push | None) -> mjx.Data:
    d = d.replace(ctrl=tau)
    if push is not None:
        on = (d.time >= push.t_start) & (d.time < push.t_start + push.duration)
        wrench = jnp.concatenate([jnp.where(on, push.force, 0.0), jnp.zeros(3, push.force.dtype)])
        d = d.replace(xfrc_applied=d.xfrc_applied.at[ids.trunk_body].set(wrench.astype(d.xfrc_applied.dtype)))
    if substeps == 1:  # (static) one step, called: a loop of one would be a scan, whose derivative and batching
        return mjx.step(mx, d)  # rules retrace mjx.step until its carry's tangents / batch axes stop changing
    return jax.lax.fori_loop(0, substeps, lambda _, dd: mjx.step(mx, dd), d)


def finite_tree(tree) -> jax.Array:
    """True where every inexact leaf of ``tree`` is finite everywhere (a scalar)."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(x.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


def settle_tick(state_new, state, ctrl_new, ctrl, metrics_state, update_metrics: Callable, tau, tau_prev, div,
                div_tick, k, term, term_tick, *, max_speed: float, terminal: Callable | None = None,
                freeze: Callable | None = None):
    """The divergence and freeze rule of one control tick of one instance: the one home of the rule, for every
    simulator (:func:`rollout_advance` on MJX, :mod:`hyqjax.sim.cpu_backend` on C MuJoCo).

    The instance *diverges* at tick ``k`` when its new state (``qpos``, ``qvel``) or torque ``tau`` is not finite or
    ``|qvel| >= max_speed``; a diverged or terminated (``term``) instance is *frozen*: its state (``freeze(new, old,
    frozen)``, default every leaf of ``state``), controller state, torque and metrics stay at their last values (a
    frozen instance's discarded step never counts as a divergence). Then the metrics are updated
    (``update_metrics(metrics_state, state_new)``) and, with ``terminal``, an instance not frozen that meets
    ``terminal(metrics)`` is terminated at this tick (frozen from the next one on).

    Returns ``(state_new, ctrl_new, metrics_new, tau, div, div_tick, term, term_tick)``."""
    ok = finite_tree((state_new.qpos, state_new.qvel, tau)) & (jnp.max(jnp.abs(state_new.qvel)) < max_speed)
    newly = (~div) & (~term) & (~ok)
    div = div | newly
    frozen = div | term
    keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(frozen, b, a), new, old)  # noqa: E731
    state_new = freeze(state_new, state, frozen) if freeze is not None else keep(state_new, state)
    ctrl_new = keep(ctrl_new, ctrl)
    tau = jnp.where(frozen, tau_prev, tau)
    ms_new = keep(update_metrics(metrics_state, state_new), metrics_state)
    div_tick = jnp.where(newly, k, div_tick)
    if terminal is not None:  # static: the episode ends at the failure tick
        ended = (~frozen) & jnp.asarray(terminal(ms_new), bool)
        term = term | ended
        term_tick = jnp.where(ended, k, term_tick)
    return state_new, ctrl_new, ms_new, tau, div, div_tick, term, term_tick


#: The ``mjx.Data`` fields a diverged instance keeps from its last finite tick: the state ``mjx.step`` reads
#: (positions, velocities, activations, controls, applied forces, warm start, time) and the two derived fields
#: the step-down outcome and the traces read from the final data (``site_xpos``, ``sensordata``). The other
#: derived fields (kinematics, contacts, constraint rows) are recomputed from the state by every step, so
#: selecting them too (``mjx.Data.where`` over every leaf) would only cost memory traffic: about 84 KB per
#: instance and tick, the largest part of the closed loop's overhead over bare physics (benchmarks/NOTES.md).
FROZEN_FIELDS = ("time", "qpos", "qvel", "act", "history", "qacc_warmstart", "plugin_state", "ctrl",
                 "qfrc_applied", "xfrc_applied", "eq_active", "mocap_pos", "mocap_quat", "userdata",
                 "site_xpos", "sensordata")


def freeze_diverged(new: mjx.Data, old: mjx.Data, diverged: jax.Array) -> mjx.Data:
    """``new``, with the :data:`FROZEN_FIELDS` of ``old`` where ``diverged`` (one instance: a scalar flag; the
    rollout passes ``diverged | terminated``).

    An instance that diverged (or was terminated) steps on from its frozen state every tick and its result is
    discarded, so its state and outcome are those of its last finite (live) tick; the other derived fields of its
    final data are those of the discarded step. Valid under both MJX implementations (no batched select over Warp's shared
    contact buffers)."""
    names = [f for f in FROZEN_FIELDS if hasattr(new, f) and getattr(new, f) is not None]
    return new.replace(**{f: jax.tree_util.tree_map(lambda a, b: jnp.where(diverged, b, a), getattr(new, f),
                                                    getattr(old, f)) for f in names})


class RolloutCarry(NamedTuple):
    """The scan carry of one instance between control ticks (what a chunked run hands from chunk to chunk)."""

    data: mjx.Data
    ctrl_state: Any
    metrics: Any
    tau: jax.Array
    diverged: jax.Array
    diverged_tick: jax.Array
    tick: jax.Array
    terminated: jax.Array
    terminated_tick: jax.Array


class RolloutResult(NamedTuple):
    """A rollout's final state, controller state and metrics, its divergence flag and tick (-1: none), the trace,
    and its termination flag and failure tick (``Metrics.terminal``; -1: none). A diverged or terminated instance's
    state, controller state and metrics are those of its last live tick."""

    data: mjx.Data
    ctrl_state: Any
    metrics: Any
    diverged: jax.Array
    diverged_tick: jax.Array
    trace: Any
    terminated: Any = None
    terminated_tick: Any = None


def rollout_init(mx: mjx.Model, ids: hmodel.ModelIds, d0: mjx.Data, controller: Controller, params: Any,
                 metrics: Metrics = no_metrics()) -> RolloutCarry:
    """The carry before the first tick: ``controller.init`` on the first observation (zero torques)."""
    tau0 = jnp.zeros(robot.N_JOINTS, d0.qpos.dtype)
    obs0 = observe(ids, d0, tau0, mx)
    carry = RolloutCarry(d0, controller.init(params, obs0), metrics.init(d0), tau0, jnp.array(False),
                         jnp.array(-1, jnp.int32), jnp.array(0, jnp.int32), jnp.array(False), jnp.array(-1, jnp.int32))
    # Strong types (as the scan's output carry has them), so the chunks after the first reuse its program.
    return jax.tree_util.tree_map(lambda x: jax.lax.convert_element_type(x, jnp.result_type(x)), carry)


def rollout_advance(mx: mjx.Model, ids: hmodel.ModelIds, carry: RolloutCarry, controller: Controller, params: Any,
                    cfg: SimConfig, n_ticks: int, metrics: Metrics = no_metrics(),
                    record: Callable[[mjx.Data, Observation, Any], Any] | None = None,
                    push: Push | None = None) -> tuple[RolloutCarry, Any]:
    """``n_ticks`` control ticks from ``carry`` (``lax.scan``); returns the new carry and the trace of these ticks.

    Per tick: observe, ``controller.step``, clip torques to ``robot.TORQUE_LIMIT``, ``cfg.substeps`` calls of
    ``mjx.step``, divergence check (non-finite state or ``|qvel| >= cfg.max_speed`` freezes the instance at its
    last finite state), metric update, then ``metrics.terminal`` (if given): an instance that meets it is
    terminated at this tick and frozen from the next one on (a frozen instance's discarded step is never counted
    as a divergence). With ``record``, ``n_ticks`` must be a multiple of ``cfg.record_every``.
    """
    def tick(c: RolloutCarry, _):
        d, cs, ms, tau_prev, div, div_tick, k, term, term_tick = c
        obs = observe(ids, d, tau_prev, mx)
        cs_new, tau, info = controller.step(params, cs, obs)
        tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
        d_new = _physics(mx, d, tau, ids, cfg.substeps, push)
        d_new, cs_new, ms_new, tau, div, div_tick, term, term_tick = settle_tick(
            d_new, d, cs_new, cs, ms, lambda m, dd: metrics.update(m, dd, obs, info), tau, tau_prev, div, div_tick,
            k, term, term_tick, max_speed=cfg.max_speed, terminal=metrics.terminal, freeze=freeze_diverged)
        out = record(d_new, obs, info) if record is not None else None
        return RolloutCarry(d_new, cs_new, ms_new, tau, div, div_tick, k + 1, term, term_tick), out

    # The tie serves derivatives only; MJX-Warp has none (and its Data's contact buffers are shared by the batch,
    # so it is not a tree to map over).
    if controller.tie_rollout_carry and impls.supports_gradients(impls.model_impl(mx)):
        carry = tie_carry(carry, params)
    if record is not None and cfg.record_every:
        if n_ticks % cfg.record_every:
            raise ValueError(f"n_ticks ({n_ticks}) must be a multiple of record_every ({cfg.record_every})")

        def block(c, _):
            c, outs = jax.lax.scan(tick, c, None, length=cfg.record_every)
            return c, jax.tree_util.tree_map(lambda x: x[-1], outs)

        return jax.lax.scan(block, carry, None, length=n_ticks // cfg.record_every)
    carry, _ = jax.lax.scan(lambda c, x: (tick(c, x)[0], None), carry, None, length=n_ticks)
    return carry, None


def rollout_result(carry: RolloutCarry, trace: Any = None) -> RolloutResult:
    return RolloutResult(carry.data, carry.ctrl_state, carry.metrics, carry.diverged, carry.diverged_tick, trace,
                         carry.terminated, carry.terminated_tick)


def rollout(mx: mjx.Model, ids: hmodel.ModelIds, d0: mjx.Data, controller: Controller, params: Any,
            cfg: SimConfig, metrics: Metrics = no_metrics(),
            record: Callable[[mjx.Data, Observation, Any], Any] | None = None,
            push: Push | None = None) -> RolloutResult:
    """Simulate ONE instance for ``cfg.n_ticks`` control ticks (``vmap`` it for a batch; pure, differentiable).

    :func:`rollout_init` then :func:`rollout_advance` over all ticks. Returns the final state, metrics, the
    divergence flag and tick, the termination flag and failure tick, and the decimated trace (``record(d, obs, info)``
    every ``cfg.record_every`` ticks). ``push`` optionally applies an external force to the trunk.
    """
    carry = rollout_init(mx, ids, d0, controller, params, metrics)
    rec = record if cfg.record_every else None
    carry, trace = rollout_advance(mx, ids, carry, controller, params, cfg, cfg.n_ticks, metrics, rec, push)
    return rollout_result(carry, trace)


def initial_data(mx: mjx.Model, qpos: jax.Array, batch: int | None = None, m: mujoco.MjModel | None = None,
                 contacts_per_instance: int = impls.CONTACTS_PER_INSTANCE) -> mjx.Data:
    """MJX data at ``qpos`` with zero velocity. With ``batch``, ``qpos`` is ``(batch, nq)`` (or broadcast)
    and every field gets a leading batch axis.

    Under MJX's Warp implementation (``mx`` from ``put_model(m, impl="warp")``, ``m`` required) the data is
    made from ``m`` inside a ``vmap`` (one world per instance) with the contact buffer sized for the batch
    (:func:`hyqjax.sim.impls.warp_capacity`), and the terrain geoms' world positions are written from
    ``mx.geom_pos`` (per instance after :func:`hyqjax.sim.model.batch_model`): mujoco_warp computes the pose
    of geoms welded to the world once, in ``make_data``, never from the model again.
    """
    if impls.is_warp_model(mx):
        if m is None:
            raise ValueError("initial_data under impl='warp' needs the MuJoCo model m (mujoco.MjModel)")
        b = batch or 1
        naconmax, njmax = impls.warp_capacity(int(np.sum(m.jnt_limited)), b, contacts_per_instance)
        qpos = jnp.broadcast_to(jnp.asarray(qpos, jnp.float32), (b, m.nq))
        d = jax.vmap(lambda q: mjx.make_data(m, impl="warp", naconmax=naconmax, njmax=njmax).replace(qpos=q))(qpos)
        static = np.array([g for g in range(m.ngeom) if m.body_weldid[m.geom_bodyid[g]] == 0], int)
        gpos = jnp.asarray(mx.geom_pos)
        gpos = gpos[:, static] if gpos.ndim == 3 else jnp.broadcast_to(gpos[static], (b, len(static), 3))
        d = d.replace(geom_xpos=d.geom_xpos.at[:, static].set(gpos.astype(d.geom_xpos.dtype)))
        return d if batch is not None else jax.tree_util.tree_map(lambda x: x[0], d)
    d = mjx.make_data(mx)
    if batch is None:
        return d.replace(qpos=jnp.asarray(qpos, d.qpos.dtype))
    return _batch_data(d, jnp.asarray(qpos, d.qpos.dtype), int(batch))


@functools.partial(jax.jit, static_argnums=2)
def _batch_data(d: mjx.Data, qpos: jax.Array, batch: int) -> mjx.Data:
    """``d`` with every field repeated along a new leading axis of ``batch`` and ``qpos`` broadcast to
    ``(batch, nq)``: one program per batch size (broadcasting field by field compiles one per field)."""
    db = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), d)
    return db.replace(qpos=jnp.broadcast_to(qpos, (batch, d.qpos.shape[0])))
