"""The step-down experiment of Focchi et al. (2017), Section IV: HyQ crawls off a platform.

HyQ starts on a platform of height ``h`` (front feet ``start_distance`` before the edge) and crawls
forward; the experiment runs the same batch with the height reflex on and off.

The experiment is a task (:class:`StepdownTask`, :mod:`hyqjax.sim.task`): the crawl controller, the step-down
metrics and outcome, and how a :class:`Scenario` becomes a simulator's model and initial data; the generic
:class:`hyqjax.sim.task.Rollout` runs it. :mod:`hyqjax.studies.tasks` registers it as ``stepdown``.

Entry points:

* :func:`make_stepdown_rollout` ``(cfg) -> StepdownRollout``, compiled once per static config (cached):
  ``rollout(params, scenario) -> (StepdownOutcome, mjx.Data)`` for ONE instance, pure JAX on MJX-JAX (``jax.jit``,
  ``jax.vmap``, ``jax.jacfwd`` reach every parameter), and ``rollout.run(scenario)`` for a batch through the
  simulator's batch runner (``cfg.impl``, :mod:`hyqjax.sim.backend`: MJX's jitted, sharded, chunked runner
  :func:`hyqjax.sim.runner.make_batch_runner`, or C MuJoCo's :class:`hyqjax.sim.cpu_backend.CBatchRunner`).
* :func:`run_batch`: the same batch as NumPy columns (a thin layer on ``rollout.run``), and
  :func:`hyqjax.studies.stepdown_table.summarize` for the paper's table.

Outcomes (completed / clean, boolean failure reasons) and metrics are defined in
:mod:`hyqjax.studies.stepdown_outcome`.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hyqjax.core import robot
from hyqjax.core.batching import row_index, take_rows
from hyqjax.crawl import controller as crawl
from hyqjax.crawl import scheduled
from hyqjax.sim import backend
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim
from hyqjax.sim import task
from hyqjax.studies import stepdown_outcome as so
from hyqjax.studies import tasks
from hyqjax.studies.stepdown_outcome import FAILURE_REASONS, StepdownOutcome, failure_labels  # noqa: F401
from hyqjax.studies.stepdown_table import format_table, summarize, wilson_interval  # noqa: F401


#: The simulators the step-down runs on (:mod:`hyqjax.sim.backend`; declared once, in the task registry).
SUPPORTED_IMPLS = tasks.get("stepdown").impls


@dataclasses.dataclass(frozen=True)
class StepdownConfig:
    """Static settings of a step-down batch (changing them recompiles).

    Attributes:
      duration: simulated time (s).
      control_dt: controller period (s).
      record_every: trace decimation in ticks (0: no traces).
      max_tilt: bound on |roll| and |pitch| (rad) for a completed run.
      min_progress: a completed run advances the trunk at least this far (m).
      strike_force: a shin or trunk contact pressing on the terrain harder than this (N) is a strike.
      layout: terrain structure (rough blocks).
      impl: simulator, ``auto | jax | warp | c`` (:mod:`hyqjax.sim.backend`; ``auto`` is C MuJoCo on a machine
        without an accelerator, MuJoCo Warp on a CUDA GPU with warp-lang, MJX-JAX otherwise).
      terminate: end a run's episode when it falls (tilt past ``max_tilt`` or a trunk strike) and freeze it there
        (:mod:`hyqjax.studies.stepdown_outcome`); False runs every instance to ``duration``.
    """

    duration: float = 24.0
    control_dt: float = 0.002
    record_every: int = 0
    max_tilt: float = 0.4
    min_progress: float = 0.5
    strike_force: float = 100.0
    layout: hmodel.TerrainLayout = hmodel.TerrainLayout()
    impl: str = "auto"
    terminate: bool = True

    def __post_init__(self):
        backend.validate_impl(self.impl, SUPPORTED_IMPLS)
        if not isinstance(self.terminate, bool):
            raise ValueError(f"terminate must be True or False, got {self.terminate!r}")
        self.sim_config()  # validates duration, control_dt, record_every
        for name, lo, hi in (("max_tilt", 0.0, np.pi), ("min_progress", 0.0, 100.0), ("strike_force", 0.0, 1e5)):
            v = getattr(self, name)
            if not (lo < v <= hi):
                raise ValueError(f"{name} must be in ({lo}, {hi}], got {v}")

    def sim_config(self) -> sim.SimConfig:
        return sim.SimConfig(control_dt=self.control_dt, duration=self.duration, record_every=self.record_every)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scenario:
    """Per-instance inputs (every field has a leading batch axis in a batch, none for one instance).

    Attributes:
      terrain: platform height, friction, payload, blocks.
      start_distance: distance of the front feet from the platform edge at the start (m).
      lateral_offset: initial lateral offset of the trunk (m).
      yaw: initial heading (rad).
      params: crawl parameters, a ``CrawlParams`` or a per-leg set (:mod:`hyqjax.crawl.scheduled`; with ``use_reflex``
        and the reflex parameters); what :meth:`StepdownRollout.run`
        runs. The single-instance ``rollout(params, scenario)`` takes its parameters as ``params`` instead.
      push: lateral push on the trunk.
    """

    terrain: hmodel.InstanceTerrain
    start_distance: jax.Array
    lateral_offset: jax.Array
    yaw: jax.Array
    params: crawl.CrawlParams
    push: sim.Push

    @property
    def batch_size(self) -> int:
        return int(self.start_distance.shape[0])

    def replace(self, **kwargs) -> "Scenario":
        """A copy with fields replaced, e.g. ``scenario.replace(params=batch_params(...))``."""
        return dataclasses.replace(self, **kwargs)

    def instance(self, i: int) -> "Scenario":
        """Instance ``i`` (an int in ``[-B, B)``) of a batch (leaves without the batch axis)."""
        return take_rows(self, int(row_index(i, self.batch_size, "i")))


@dataclasses.dataclass(frozen=True)
class StepdownSetup:
    """The compiled model of a static config: ``m`` (C MuJoCo), ``mx`` (the model of the simulator ``impl``:
    an ``mjx.Model`` under MJX, ``m`` under C MuJoCo), ``ids``, and ``backend``, the simulator's object
    (:func:`hyqjax.sim.backend.get`)."""

    m: mujoco.MjModel
    mx: Any
    ids: hmodel.ModelIds
    impl: str

    @property
    def backend(self):
        return backend.get(self.impl)


def setup(cfg: StepdownConfig, differentiable: bool = False) -> StepdownSetup:
    """Model, simulator model and ids for ``cfg`` (cached per layout, control period, resolved ``impl`` and JAX's
    float width: under ``jax.enable_x64`` the MJX model is float64). ``differentiable``: for the pure JAX
    one-instance rollout (``impl="auto"`` resolves to ``jax`` there, :func:`hyqjax.sim.backend.resolve_impl`)."""
    impl = backend.resolve_impl(cfg.impl, SUPPORTED_IMPLS, differentiable=differentiable)
    return _setup_cached(cfg.layout, cfg.control_dt, impl, bool(jax.config.jax_enable_x64))


@functools.lru_cache(maxsize=8)
def _setup_cached(layout: hmodel.TerrainLayout, control_dt: float, impl: str, x64: bool) -> StepdownSetup:
    m = hmodel.load_model(layout, timestep=control_dt)
    # Concrete even when the first call comes from inside a trace (a jitted objective): the cache must never hold
    # a tracer.
    with jax.ensure_compile_time_eval():
        mx = backend.get(impl).put_model(m)
    return StepdownSetup(m, mx, hmodel.model_ids(m), impl)


#: The start pose :func:`start_qpos` places (recorded with stored results, so that maps and sweeps of another start
#: pose are never mixed): ``leading-foot``, the leading front foot never nearer the edge than at zero heading.
#: Before it (``hip-line``), a heading moved one front foot forward, over the edge at the smallest start distances.
START_POSE = "leading-foot"
#: The start pose of results that record none: the front hips' line alone under every heading.
EARLIER_START_POSE = "hip-line"


def recorded_start_pose(record: dict) -> str:
    """The start pose a stored configuration or manifest ran: its ``start_pose``, or :data:`EARLIER_START_POSE`
    when it records none (it was written before the pose was recorded)."""
    return record.get("start_pose", EARLIER_START_POSE)


@functools.cache
def standing_front_foot() -> tuple[float, float]:
    """``(x, |y|)`` of a front foot centre in the trunk frame at the standing joint angles (m), from
    :func:`hyqjax.core.kinematics.foot_positions` (0.367, 0.323)."""
    from hyqjax.core import kinematics

    with jax.ensure_compile_time_eval():  # a constant, also when first asked for inside a trace
        p = np.asarray(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float32)), np.float64)
    return float(p[0, 0]), float(abs(p[0, 1]))


def leading_foot_advance(yaw, xp=np):
    """How far a heading ``yaw`` moves the leading front foot forward (+x, towards the edge) when the trunk turns
    about its centre: ``x_f (cos yaw - 1) + |y_f sin yaw|`` for the front foot at ``(x_f, +-y_f)``
    (:func:`standing_front_foot`); exactly 0 at ``yaw = 0``, about 3.0 cm at 0.1 rad."""
    fx, fy = standing_front_foot()
    return fx * (xp.cos(yaw) - 1.0) + fy * xp.abs(xp.sin(yaw))


def start_qpos(stand_qpos, start_distance, lateral_offset, yaw, platform_height, xp=np):
    """Standing keyframe on the platform, heading ``yaw``, front feet ``start_distance`` before the edge.

    At zero heading the front hips are ``start_distance`` before the edge (x = 0), the front foot centres 6.1 mm
    further back. A heading turns the trunk about its centre, which moves one front foot forward by
    :func:`leading_foot_advance`; the trunk starts that much further back, so that no front foot starts nearer the
    edge than at zero heading (:data:`START_POSE`). Without it, headings of up to 0.1 rad put a front foot over the
    edge in about 7 % of the step-down draws with small start distances; that foot dropped and its shin struck the
    edge in every such run.

    Any leading batch shape; ``xp`` is ``numpy`` (the batch path) or ``jax.numpy`` (traceable).
    """
    front_x = float(robot.B_P_HIP[0, 0])
    zero = xp.zeros_like(start_distance)
    base = xp.stack([-start_distance - front_x - leading_foot_advance(yaw, xp), lateral_offset + zero, robot.STANDING_BASE_Z + platform_height + zero,
                     xp.cos(yaw / 2), zero, zero, xp.sin(yaw / 2)], -1)
    joints = xp.broadcast_to(xp.asarray(stand_qpos)[robot.QPOS_JOINTS], base.shape[:-1] + (robot.N_JOINTS,))
    return xp.concatenate([base, joints.astype(base.dtype)], -1)


def initial_qpos(m: mujoco.MjModel, scenario: Scenario) -> np.ndarray:
    """:func:`start_qpos` of every instance of a batch, ``(B, nq)``, in the scenario's float width (the
    arithmetic is that of the scenario's arrays, so a float32 scenario gives the float32 start it always had)."""
    return start_qpos(hmodel.standing_qpos(m), np.asarray(scenario.start_distance), np.asarray(scenario.lateral_offset),
                      np.asarray(scenario.yaw), np.asarray(scenario.terrain.platform_height))


def initial_batch_data(st: StepdownSetup, mx_batched, scenario: Scenario):
    """Batched initial data of ``scenario`` on ``mx_batched`` (``st.backend.batch_model`` of ``st.mx``) under any
    simulator (under Warp the per-instance terrain poses go into the data: :func:`sim.initial_data`)."""
    return st.backend.initial_data(st.mx, mx_batched, initial_qpos(st.m, scenario), st.m)


def batch_inputs(st: StepdownSetup, scenario: Scenario) -> tuple[Any, Any]:
    """``(batched model, initial data)`` of ``scenario`` for ``st``'s simulator: what its batch runner takes."""
    mb = st.backend.batch_model(st.mx, st.ids, scenario.terrain)
    return mb, initial_batch_data(st, mb, scenario)


def record_trace(d, obs: sim.Observation, info: crawl.CrawlInfo, sites=None):
    """What figures need: trunk pose, joints, commanded/planned feet, reflex activity, damping, mobility."""
    from hyqjax.core import spatial

    return dict(time=d.time, base_pos=d.qpos[robot.QPOS_BASE_POS],
                rpy=spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT])),
                q=obs.q, qd=obs.qd, q_cmd=info.q_cmd, x_plan_b=info.x_plan_b, x_cmd_b=info.x_cmd_b,
                reflex_active=info.reflex_active, swing_down=info.swing_down, swing_leg=info.swing_leg,
                phase=info.phase, damping=info.damping, mobility=info.mobility, foot_force=obs.foot_force,
                feet_world=d.site_xpos[sites] if sites is not None else d.site_xpos, qpos=d.qpos)


def make_metrics(ids: hmodel.ModelIds, cfg: StepdownConfig) -> sim.Metrics:
    """The step-down metrics of :mod:`hyqjax.studies.stepdown_outcome` for ``cfg`` (with the episode end at a fall
    when ``cfg.terminate``)."""
    return so.make_metrics(ids, cfg.strike_force, cfg.max_tilt if cfg.terminate else None)


class StepdownTask(task.Task):
    """The step-down as a :class:`hyqjax.sim.task.Task`: the crawl with the reflex (:func:`hyqjax.crawl.controller.
    crawl_controller`), the step-down metrics with the episode end at a fall (:func:`make_metrics`), the figures'
    trace (:func:`record_trace`), the outcome of :mod:`hyqjax.studies.stepdown_outcome`; an instance is a
    :class:`Scenario` without batch axes (its ``params`` field unused: the parameters are the rollout's
    argument), a batch is a :class:`Scenario` with them."""

    def __init__(self, cfg: StepdownConfig):
        self.cfg = cfg
        self.sim_config = cfg.sim_config()
        self.controller = crawl.crawl_controller(cfg.control_dt)
        self.ids = setup(cfg).ids  # the same model under every simulator
        self.metrics = make_metrics(self.ids, cfg)
        sites = np.asarray(self.ids.foot_sites)
        self.record = lambda d, o, i: record_trace(d, o, i, sites)

    def setup(self, differentiable: bool = False) -> StepdownSetup:
        return setup(self.cfg, differentiable=differentiable)

    def outcome(self, res: sim.RolloutResult) -> StepdownOutcome:
        return so.outcome(res, self.ids, self.cfg.max_tilt, self.cfg.min_progress)

    def instance_inputs(self, st: StepdownSetup, params, scenario: Scenario):
        mx1 = hmodel.instance_model(st.mx, st.ids, scenario.terrain)
        q0 = start_qpos(jnp.asarray(hmodel.standing_qpos(st.m), st.mx.qpos0.dtype), scenario.start_distance,
                        scenario.lateral_offset, scenario.yaw, scenario.terrain.platform_height, xp=jnp)
        return mx1, sim.initial_data(mx1, q0, m=st.m), scenario.push

    def batch_inputs(self, st: StepdownSetup, scenario: Scenario):
        return batch_inputs(st, scenario)


class StepdownRollout(task.Rollout):
    """The step-down closed loop for one static config (built by :func:`make_stepdown_rollout`): the generic
    :class:`hyqjax.sim.task.Rollout` of :class:`StepdownTask`.

    ``rollout(params, scenario) -> (StepdownOutcome, mjx.Data)``: ONE instance (``scenario`` without batch
    axes; its ``params`` field is ignored), pure JAX under ``jit`` / ``vmap`` / ``jacfwd`` (``impl="jax"``, and
    ``"auto"``, which is MJX-JAX for this function; under ``impl="warp"`` or ``"c"`` a derivative, and the
    one-instance call itself, are a ``ValueError``: Warp runs batches, whose contacts share one buffer, and C
    MuJoCo steps batches outside JAX). ``rollout.run(scenario)``:
    a batch through the simulator's batch runner (jitted, chunked; sharded under MJX), compiled once per batch
    shape and mesh, returning ``(StepdownOutcome, RolloutResult)``.
    """

    def __init__(self, cfg: StepdownConfig):
        super().__init__(StepdownTask(cfg))


def make_stepdown_rollout(cfg: StepdownConfig = StepdownConfig()) -> StepdownRollout:
    """The :class:`StepdownRollout` of ``cfg`` (cached: one per static config and float width, so one compile
    per batch shape)."""
    return _rollout_cached(cfg, bool(jax.config.jax_enable_x64))


@functools.lru_cache(maxsize=8)
def _rollout_cached(cfg: StepdownConfig, x64: bool) -> StepdownRollout:
    return StepdownRollout(cfg)


def run_batch(scenario: Scenario, cfg: StepdownConfig = StepdownConfig(), mesh=None,
              progress: Callable[[float, float], None] | None = None) -> tuple[dict[str, np.ndarray], Any]:
    """Run one batch of step-down instances; returns ``(outcome columns as numpy arrays, trace or None)``
    (:func:`hyqjax.studies.stepdown_outcome.to_columns`). ``progress(sim_s_done, sim_s_total)`` is called
    between chunks of simulated time."""
    out, res = make_stepdown_rollout(cfg).run(scenario, mesh=mesh, progress=progress)
    trace = jax.tree_util.tree_map(np.asarray, res.trace) if cfg.record_every else None
    return so.to_columns(out), trace


def summarize_instances(res: sim.RolloutResult, scenario: Scenario, cfg: StepdownConfig, ids=None) -> dict[str, np.ndarray]:
    """Outcome columns (numpy) of a batch rollout made with :func:`make_metrics` (e.g. by a sweep's runner)."""
    return so.to_columns(make_stepdown_rollout(cfg)._outcomes(res._replace(trace=None)))


def make_scenarios(heights, reflex_modes, instances: int, seed: int, *, friction=(0.7, 1.0), payload=(0.0, 10.0),
                   start_distance=(0.0, 0.04), lateral=(-0.03, 0.03), yaw=(-0.05, 0.05), params=None,
                   n_blocks: int = 0) -> tuple[Scenario, dict[str, np.ndarray]]:
    """A batch over ``heights x reflex_modes x instances`` with per-instance randomisation from ``seed``.

    The same seed gives every (height, reflex) pair the same randomised instances, so reflex on and off
    are compared on identical scenarios. Returns the scenario and a table of the inputs.
    """
    heights = [float(h) for h in heights]
    modes = [bool(r) for r in reflex_modes]
    if instances < 1:
        raise ValueError(f"instances must be >= 1, got {instances}")
    rng = np.random.default_rng(seed)
    n = instances
    inst = dict(
        friction=rng.uniform(*friction, n), payload_mass=rng.uniform(*payload, n),
        payload_com=np.stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.05, 0.05, n), np.zeros(n)], -1),
        start_distance=rng.uniform(*start_distance, n), lateral_offset=rng.uniform(*lateral, n),
        yaw=rng.uniform(*yaw, n),
    )
    rows = {k: [] for k in ["height", "reflex", "instance", *inst]}
    for h in heights:
        for r in modes:
            for i in range(n):
                rows["height"].append(h)
                rows["reflex"].append(r)
                rows["instance"].append(i)
                for k, v in inst.items():
                    rows[k].append(v[i])
    table = {k: np.asarray(v) for k, v in rows.items()}
    base = params or crawl.CrawlParams.make()
    b = len(table["height"])
    terrain = hmodel.InstanceTerrain.make(table["height"], table["friction"], table["payload_mass"],
                                          table["payload_com"], n_blocks=n_blocks)
    # Broadcast in NumPy, then put (a jnp.broadcast_to of each field would compile one small program per shape).
    batched = lambda x: jnp.asarray(np.broadcast_to(np.asarray(x), (b,) + np.shape(x)))  # noqa: E731
    bparams = jax.tree_util.tree_map(batched, base)
    bparams = scheduled.replace_base(bparams, use_reflex=jnp.asarray(np.asarray(table["reflex"], np.float32)))
    scenario = Scenario(terrain=terrain, start_distance=jnp.asarray(table["start_distance"]),
                        lateral_offset=jnp.asarray(table["lateral_offset"]), yaw=jnp.asarray(table["yaw"]),
                        params=bparams,
                        push=jax.tree_util.tree_map(batched, sim.Push.none()))
    return scenario, table


