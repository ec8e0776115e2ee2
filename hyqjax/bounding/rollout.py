"""The bounding closed loop as a JAX function, compiled once per static config.

:func:`make_bounding_rollout` ``(cfg) -> BoundingRollout`` (cached: one object per :class:`BoundingRolloutConfig`
and float width):

* ``rollout(params, terrain, apex0, push=None, roll=0.0, yaw_rate=0.0) -> (BoundingOutcome, mjx.Data)``
  simulates ONE instance from the apex state ``apex0`` (:func:`hyqjax.bounding.cycle.apex_data`) for
  ``cfg.duration`` s with :data:`hyqjax.bounding.controller.bounding_controller` on the instance's terrain
  (:func:`hyqjax.sim.model.instance_model`), accumulating :func:`fall_metrics`. It is pure JAX: ``jax.jit``,
  ``jax.vmap`` and (``impl="jax"``) ``jax.jacfwd`` reach every leaf of ``params``, ``terrain``, ``apex0`` and
  ``push``; under ``impl="warp"`` a derivative is a ``ValueError``.
* ``rollout.run(batch, progress=None)`` runs a :class:`hyqjax.bounding.batch.Batch` through the simulator's batch
  runner (:func:`hyqjax.sim.runner.make_batch_runner` under MJX, compiled once per batch shape) and returns the
  outcomes (leading batch axis) and the :class:`hyqjax.sim.rollout.RolloutResult` (final state, fall metrics,
  trace). :func:`run` is this with the trace as NumPy arrays.

Bounding is a task (:class:`BoundingTask`, :mod:`hyqjax.sim.task`) run by the generic
:class:`hyqjax.sim.task.Rollout`; :mod:`hyqjax.studies.tasks` registers it as ``bound``.

The run starts at an apex (gait phase 0) and lasts a whole number of gait periods, so its final state is an
apex again: :class:`BoundingOutcome` holds the final apex state (forward speed along the heading included), the
final yaw and position, and the fall and divergence flags.

The bound's trace sample (:func:`record`) and its initial state (:func:`apex_initial_data`) live here with the
outcome they make; its device metrics (:class:`hyqjax.bounding.falls.FallMetrics`: a fall is the trunk below
``FALL_HEIGHT`` or ``|roll|`` or ``|pitch|`` above ``FALL_ANGLE``) are :mod:`hyqjax.bounding.falls`'s, and the
batch of instances they run on is :mod:`hyqjax.bounding.batch`'s.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hyqjax.bounding import batch as bbatch
from hyqjax.bounding import controller as bctrl
from hyqjax.bounding import cycle as bc
from hyqjax.bounding.falls import FallMetrics, fall_metrics
from hyqjax.bounding.params import Apex, BoundingParams
from hyqjax.bounding.state import BoundingInfo
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.sim import backend
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim
from hyqjax.sim import task
from hyqjax.studies import tasks

#: Largest controller period (s) and trace decimation (ticks) of a :class:`BoundingRolloutConfig`.
MAX_CONTROL_DT = 0.02
MAX_RECORD_EVERY = 10_000
#: The simulators bounding runs on (:mod:`hyqjax.sim.backend`: MJX-JAX, MuJoCo Warp, C MuJoCo; its initial apex state
#: is made on MJX-JAX and handed to the simulator by ``from_jax_data``); declared once, in the task registry.
SUPPORTED_IMPLS = tasks.get("bound").impls


@dataclasses.dataclass(frozen=True)
class BoundingRolloutConfig:
    """Static settings of a bounding rollout (changing them recompiles); hashable.

    Attributes:
      duration: simulated time (s), in ``(0, MAX_DURATION]``; a whole number of gait periods (checked when the
        gait period is known, at run time).
      control_dt: controller period and physics timestep (s), in ``(0, MAX_CONTROL_DT]``.
      record_every: trace decimation in ticks (0: no trace), an int in ``[0, MAX_RECORD_EVERY]`` dividing the
        ticks of a gait period.
      impl: simulator, ``auto | jax | warp | c`` (:mod:`hyqjax.sim.backend`); derivatives need ``jax``, and
        ``c`` runs batches only (``rollout.run``).
    """

    duration: float = 6.0
    control_dt: float = 0.002
    record_every: int = 0
    impl: str = "auto"

    def __post_init__(self):
        def need(ok, name, rule):
            if not ok:
                raise bbatch.SettingError(name, f"{name} must be {rule}, got {getattr(self, name)!r}")

        num = (int, float, np.integer, np.floating)
        need(isinstance(self.duration, num) and np.isfinite(self.duration) and 0 < self.duration <= bbatch.MAX_DURATION,
             "duration", f"in (0, {bbatch.MAX_DURATION:g}] s")
        dt_ok = isinstance(self.control_dt, num) and np.isfinite(self.control_dt)
        need(dt_ok and 0 < self.control_dt <= MAX_CONTROL_DT, "control_dt", f"in (0, {MAX_CONTROL_DT:g}] s")
        need(isinstance(self.record_every, (int, np.integer)) and 0 <= self.record_every <= MAX_RECORD_EVERY,
             "record_every", f"an int in [0, {MAX_RECORD_EVERY}]")
        n_ticks = round(self.duration / self.control_dt)
        need(abs(n_ticks * self.control_dt - self.duration) <= 1e-6, "duration",
             f"a whole number of control periods of {self.control_dt:g} s")
        need(self.record_every == 0 or n_ticks % self.record_every == 0, "record_every",
             f"0 or a divisor of the {n_ticks} control ticks of duration")
        try:
            backend.validate_impl(self.impl, SUPPORTED_IMPLS)
        except ValueError as e:
            raise bbatch.SettingError("impl", str(e)) from None

    def sim_config(self) -> sim.SimConfig:
        """The :class:`hyqjax.sim.rollout.SimConfig` of this config (one physics step per control tick)."""
        return sim.SimConfig(control_dt=float(self.control_dt), duration=float(self.duration),
                             record_every=int(self.record_every))

    def check_period(self, period) -> None:
        """Check a gait period (s) against this config: a whole number of control ticks, dividing ``duration``,
        and (with a trace) a multiple of ``record_every`` ticks; else :class:`hyqjax.bounding.batch.SettingError`.
        ``period`` may hold one value per instance; they must agree."""
        p = np.asarray(period, np.float64).reshape(-1)
        if p.size == 0 or not np.allclose(p, p[0]):
            raise bbatch.SettingError("period", "all instances must share the gait period")
        period = float(p[0])
        n_per = int(round(period / self.control_dt))
        off_grid = abs(n_per * self.control_dt - period) > 1e-6
        if n_per < 1 or off_grid or (self.record_every and n_per % self.record_every):
            raise bbatch.SettingError("period", f"the gait period ({period:g} s) must be a multiple of record_every * "
                                                f"control_dt ({max(self.record_every, 1)} x {self.control_dt:g} s)")
        n = self.duration / period
        if abs(n - round(n)) > 1e-6:
            raise bbatch.SettingError("duration", f"duration must be a multiple of the gait period {period:g} s, "
                                                  f"got {self.duration:g}")


def record(d, obs, info: BoundingInfo) -> dict:
    """One trace sample: ground truth (trunk pose and twist, apex state, full ``qpos`` for replay, foot forces)
    and what the controller commanded / estimated."""
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
    return dict(t=d.time, pos=d.qpos[robot.QPOS_BASE_POS], vel=d.qvel[robot.QVEL_BASE_LIN], rpy=rpy,
                omega=d.qvel[robot.QVEL_BASE_ANG], apex=bc.data_apex(d).array(), yaw_des=info.yaw_des,
                v_des=info.v_des, yaw_rate_des=info.yaw_rate_des, est_vel_h=info.vel_h, est_z=info.est_pos[2],
                roll_des=info.roll_des, qpos=d.qpos, foot_force=obs.foot_force)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class BoundingOutcome:
    """What one bounding run ended with (leaves without a batch axis for one instance, with one for a batch).

    Attributes:
      fell: the trunk fell (:class:`FallMetrics`) at some tick.
      fall_tick: tick of the first fall (-1: none); the fall time is ``(fall_tick + 1) * control_dt``.
      low_trunk, roll, pitch: the first fall's cause (trunk below ``FALL_HEIGHT``; ``|roll|`` or ``|pitch|``
        above ``FALL_ANGLE``, :mod:`hyqjax.bounding.falls`); at most one is set.
      min_z: lowest trunk height (m).  max_roll, max_pitch: largest ``|roll|``, ``|pitch|`` (rad).
      diverged: the simulation diverged (non-finite state or speed limit); its state froze at its last finite
        tick.  diverged_tick: that tick (-1: none).
      final_apex: the ground-truth apex state at the end (:func:`hyqjax.bounding.cycle.data_apex`: height,
        pitch, forward speed along the heading, vertical speed, pitch rate); an apex when ``duration`` is a whole
        number of gait periods.
      final_yaw: heading at the end (rad).  final_position: trunk position at the end (3,) (m).
    """

    fell: jax.Array
    fall_tick: jax.Array
    low_trunk: jax.Array
    roll: jax.Array
    pitch: jax.Array
    min_z: jax.Array
    max_roll: jax.Array
    max_pitch: jax.Array
    diverged: jax.Array
    diverged_tick: jax.Array
    final_apex: Apex
    final_yaw: jax.Array
    final_position: jax.Array

    @property
    def final_speed(self) -> jax.Array:
        """Forward speed along the final heading (m/s), ``final_apex.vx``."""
        return self.final_apex.vx

    @property
    def success(self) -> jax.Array:
        """Neither a fall nor a divergence."""
        return ~self.fell & ~self.diverged


def outcome(res: sim.RolloutResult) -> BoundingOutcome:
    """The :class:`BoundingOutcome` of ONE instance's rollout result (metrics :func:`fall_metrics`; pure JAX)."""
    ms: FallMetrics = res.metrics
    d = res.data
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
    return BoundingOutcome(fell=ms.fall_tick >= 0, fall_tick=ms.fall_tick, low_trunk=ms.low_trunk, roll=ms.roll,
                           pitch=ms.pitch, min_z=ms.min_z, max_roll=ms.max_roll, max_pitch=ms.max_pitch,
                           diverged=res.diverged, diverged_tick=res.diverged_tick, final_apex=bc.data_apex(d),
                           final_yaw=rpy[2], final_position=d.qpos[robot.QPOS_BASE_POS])


def to_columns(out: BoundingOutcome) -> dict[str, np.ndarray]:
    """The outcome as NumPy columns: its flat fields, ``success``, the final apex state as ``final_z``,
    ``final_pitch``, ``final_speed``, ``final_vz``, ``final_pitch_rate`` and the final ``final_x``, ``final_y``
    (the trunk's final height is ``final_z``)."""
    cols = {f.name: np.asarray(getattr(out, f.name)) for f in dataclasses.fields(out)
            if f.name not in ("final_apex", "final_position")}
    a = out.final_apex
    cols.update(final_z=np.asarray(a.z), final_pitch=np.asarray(a.pitch), final_speed=np.asarray(a.vx),
                final_vz=np.asarray(a.vz), final_pitch_rate=np.asarray(a.pitch_rate),
                final_x=np.asarray(out.final_position)[..., 0], final_y=np.asarray(out.final_position)[..., 1],
                success=np.asarray(out.success))
    return cols


@dataclasses.dataclass(frozen=True)
class BoundingSetup:
    """The bounding model of a static config: ``m`` (C MuJoCo, platform collisions off), ``mx_jax`` (MJX under
    JAX, for the initial apex state), ``mx`` (MJX under ``impl``), ``ids``."""

    m: mujoco.MjModel
    mx_jax: mjx.Model
    mx: mjx.Model
    ids: hmodel.ModelIds
    impl: str

    @property
    def backend(self):
        """The simulator's backend object (:func:`hyqjax.sim.backend.get`)."""
        return backend.get(self.impl)


def setup(control_dt: float, impl: str, differentiable: bool = False) -> BoundingSetup:
    """The :class:`BoundingSetup` for timestep ``control_dt`` and ``impl`` (cached per resolved ``impl`` and JAX's
    float width: under ``jax.enable_x64`` the JAX model is float64); ``differentiable``: for a pure JAX function of
    one instance, where ``auto`` is ``jax`` (:func:`hyqjax.sim.backend.resolve_impl`)."""
    return _setup_cached(float(control_dt), backend.resolve_impl(impl, SUPPORTED_IMPLS, differentiable),
                         bool(jax.config.jax_enable_x64))


@functools.lru_cache(maxsize=8)
def _setup_cached(control_dt: float, impl: str, x64: bool) -> BoundingSetup:
    # bc.model() is the cycle optimiser's entry (its default timestep): the same model at 0.002 s, not a second copy.
    m, mx, ids = bc.model() if control_dt == 0.002 else bc.model(control_dt)
    with jax.ensure_compile_time_eval():
        if mx.qpos0.dtype != jnp.dtype(jnp.float64 if x64 else jnp.float32):  # bc.model is cached across widths
            mx = backend.get("jax").put_model(m)
        sim_backend = backend.get(impl)
        return BoundingSetup(m, mx, mx if sim_backend.supports_gradients else sim_backend.put_model(m), ids, impl)


def instance_args(batch: bbatch.Batch) -> tuple:
    """``(params, terrain, apex0, push, roll, yaw_rate)`` of a batch, each with a leading batch axis: the
    positional arguments of ``BoundingRollout.__call__``, so ``jax.vmap(rollout)(*instance_args(batch))`` runs
    the batch instance by instance."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731  (what apex_initial_data feeds apex_data)
    return batch.params, batch.terrain, f32(batch.apex0), batch.push, f32(batch.roll0), f32(batch.yaw_rate0)


class BoundingTask(task.Task):
    """Bounding as a :class:`hyqjax.sim.task.Task`: :data:`hyqjax.bounding.controller.bounding_controller`, the fall
    metrics (:func:`fall_metrics`), the trace sample :func:`record`, the outcome :func:`outcome`. ONE instance is
    ``(terrain, apex0, push, roll, yaw_rate)`` (:meth:`BoundingRollout.__call__` takes them as arguments), a batch
    is a :class:`hyqjax.bounding.batch.Batch`; both start in the air at an apex state. The one-instance rollout runs
    on the task's simulator whatever it is (a forward run under Warp included)."""

    one_instance_on_every_backend = True

    def __init__(self, cfg: BoundingRolloutConfig):
        self.cfg = cfg
        self.sim_config = cfg.sim_config()
        self.controller = bctrl.bounding_controller
        self.metrics = fall_metrics()
        self.record = record

    def setup(self, differentiable: bool = False) -> BoundingSetup:
        return setup(self.cfg.control_dt, self.cfg.impl, differentiable)

    def outcome(self, res: sim.RolloutResult) -> BoundingOutcome:
        return outcome(res)

    def check_instance(self, params: BoundingParams, instance) -> None:
        if not isinstance(params.gait.period, jax.core.Tracer):
            self.cfg.check_period(params.gait.period)

    def check_batch(self, batch: bbatch.Batch) -> None:
        self.cfg.check_period(batch.params.gait.period)

    def initial_data(self, st: BoundingSetup, mx1, params: BoundingParams, apex0, roll=0.0, yaw_rate=0.0):
        """ONE instance's data in the air at apex state ``apex0`` (:func:`hyqjax.bounding.cycle.apex_data` on the
        JAX model), put into the data of ``st``'s simulator for the instance model ``mx1``."""
        d = bc.apex_data(st.mx_jax, st.m, params, apex0, roll=roll, yaw_rate=yaw_rate)
        return st.backend.from_jax_data(mx1, d, st.m)

    def instance_inputs(self, st: BoundingSetup, params: BoundingParams, instance):
        terrain, apex0, push, roll, yaw_rate = instance
        mx1 = hmodel.instance_model(st.mx, st.ids, terrain)
        return mx1, self.initial_data(st, mx1, params, apex0, roll, yaw_rate), push

    def batch_inputs(self, st: BoundingSetup, batch: bbatch.Batch):
        mb = st.backend.batch_model(st.mx, st.ids, batch.terrain)
        return mb, st.backend.from_jax_data(mb, apex_initial_data(batch, st.m, st.mx_jax), st.m)


class BoundingRollout(task.Rollout):
    """The bounding closed loop for one static config (built by :func:`make_bounding_rollout`): the generic
    :class:`hyqjax.sim.task.Rollout` of :class:`BoundingTask`.

    ``rollout(params, terrain, apex0, push=None, roll=0.0, yaw_rate=0.0) -> (BoundingOutcome, mjx.Data)``: ONE
    instance (leaves without batch axes; ``apex0`` (5,) in :class:`hyqjax.bounding.params.Apex` order), pure JAX.
    ``rollout.run(batch)``: a batch through the jitted runner, compiled once per batch shape and mesh, returning
    ``(BoundingOutcome, RolloutResult)`` (final state, :class:`FallMetrics`, trace of :func:`record` when
    ``cfg.record_every``).
    """

    def __init__(self, cfg: BoundingRolloutConfig):
        super().__init__(BoundingTask(cfg))

    def initial_data(self, mx1: mjx.Model, params: BoundingParams, apex0, roll=0.0, yaw_rate=0.0) -> mjx.Data:
        """ONE instance's data in the air at apex state ``apex0`` (:func:`hyqjax.bounding.cycle.apex_data` on the
        JAX model; put into the simulator's data of ``mx1`` by the backend, as :meth:`run` does)."""
        return self.task.initial_data(self.setup, mx1, params, apex0, roll, yaw_rate)

    def __call__(self, params: BoundingParams, terrain: hmodel.InstanceTerrain, apex0, push: sim.Push | None = None,
                 roll=0.0, yaw_rate=0.0) -> tuple[BoundingOutcome, mjx.Data]:
        """Simulate ONE instance for ``cfg.duration`` s from apex state ``apex0`` with initial roll (rad) and yaw
        rate (rad/s); returns its outcome and final data. The gait period is checked when concrete."""
        return super().__call__(params, (terrain, apex0, push, roll, yaw_rate))


def make_bounding_rollout(cfg: BoundingRolloutConfig = BoundingRolloutConfig()) -> BoundingRollout:
    """The :class:`BoundingRollout` of ``cfg`` (cached: one per static config and float width, so one compile per
    batch shape)."""
    return _rollout_cached(cfg, bool(jax.config.jax_enable_x64))


@functools.lru_cache(maxsize=8)
def _rollout_cached(cfg: BoundingRolloutConfig, x64: bool) -> BoundingRollout:
    return BoundingRollout(cfg)


#: The jitted initial-state program of each JAX model (:func:`apex_initial_data`), by the model's id (the model
#: is kept alive with it; setups are cached, so there are a few).
_APEX_PROGRAMS: dict = {}


def apex_initial_data(batch: bbatch.Batch, m: mujoco.MjModel, mx: mjx.Model) -> mjx.Data:
    """Batched MJX-JAX data at each instance's initial apex state (:func:`hyqjax.bounding.cycle.apex_data` on the
    JAX model ``mx``); the backend's ``from_jax_data`` puts it into the data of the simulator that runs the batch.
    One jitted program per model, compiled once per batch shape (about 0.7 s; the same ``vmap`` run op by op took
    about 5 s on a CPU)."""
    if id(mx) not in _APEX_PROGRAMS:
        _APEX_PROGRAMS[id(mx)] = (mx, jax.jit(jax.vmap(
            lambda p, s, roll, yr: bc.apex_data(mx, m, p, s, roll=roll, yaw_rate=yr))))
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return _APEX_PROGRAMS[id(mx)][1](batch.params, f32(batch.apex0), f32(batch.roll0), f32(batch.yaw_rate0))


def run(batch: bbatch.Batch, duration: float, control_dt: float = 0.002, record_every: int = 10, progress=None,
        impl: str = "jax"):
    """Simulate the batch; returns ``(RolloutResult, trace as NumPy dict)``. ``progress(done, total)`` (simulated
    seconds) is called after every simulated second. ``impl``: simulator, ``auto | jax | warp | c``
    (:mod:`hyqjax.sim.backend`; the cycle optimisation and the return map need ``jax``).

    The batch goes through ``make_bounding_rollout(BoundingRolloutConfig(duration, control_dt, record_every,
    impl)).run(batch)`` (which also returns typed outcomes): the settings are checked there
    (:class:`hyqjax.bounding.batch.SettingError`; ``duration`` a whole number of gait periods, the period a multiple
    of ``record_every * control_dt``)."""
    cfg = BoundingRolloutConfig(duration=duration, control_dt=control_dt, record_every=record_every, impl=impl)
    _, res = make_bounding_rollout(cfg).run(batch, progress=progress)
    return res, jax.tree_util.tree_map(np.asarray, res.trace)
