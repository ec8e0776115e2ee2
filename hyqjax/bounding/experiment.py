"""Batched bounding experiments: per-instance randomisation, one compiled rollout, device fall metrics.

Every instance of a batch carries its own :class:`hyqjax.bounding.params.BoundingParams` (command,
switches), terrain (friction, payload) and :class:`hyqjax.sim.rollout.Push`, so in-place, forward,
turning and the four ablation combinations share ONE compiled ``sim.batch_rollout``. The device
accumulates :class:`FallMetrics` (a fall: trunk below ``FALL_HEIGHT``, ``|roll|`` or ``|pitch|`` above
``FALL_ANGLE``) and records a trace (:func:`record`); :mod:`hyqjax.bounding.summary` turns both into
tracking metrics per instance.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import controller as bctrl
from hyqjax.bounding import cycle as bc
from hyqjax.bounding.params import BoundingCommand, BoundingParams, default_params
from hyqjax.bounding.state import BoundingInfo
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.sim import backend
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim

FALL_HEIGHT = 0.35
FALL_ANGLE = 0.7


def _dc(cls):
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


#: Limits of a batch's settings (one definition, used by :class:`Randomisation`, :func:`make_batch` and
#: :func:`validate_run`).
MAX_INSTANCES = 4096
MAX_DURATION = 600.0
MAX_FRICTION = 5.0
MAX_PAYLOAD = 100.0
MAX_PUSH_FORCE, MAX_PUSH_TIME, MAX_PUSH_DURATION = 5000.0, 600.0, 10.0


class SettingError(ValueError):
    """A bad setting of a bounding run; ``name`` is the parameter (the CLI option ``--`` + name with ``-``)."""

    def __init__(self, name: str, message: str):
        super().__init__(message)
        self.name = name


def _pair(name, v, lo_open, hi, unit=""):
    """``(lo, hi)`` with ``0 < lo`` (``lo_open``) or ``0 <= lo``, ``lo <= hi <= hi_max``; else :class:`SettingError`."""
    try:
        lo, h = (float(x) for x in v)
    except (TypeError, ValueError):
        raise SettingError(name, f"{name} must be two numbers LO HI, got {v!r}") from None
    ok = np.isfinite(lo) and np.isfinite(h) and (lo > 0 if lo_open else lo >= 0) and lo <= h <= hi
    if not ok:
        rel = "<" if lo_open else "<="
        raise SettingError(name, f"{name} must be LO HI{unit} with 0 {rel} LO <= HI <= {hi:g}, got {lo:g} {h:g}")
    return lo, h


def check_push(force, t_start, duration, force_name="push"):
    """Push settings: finite force with ``|force| <= MAX_PUSH_FORCE`` N, start in ``[0, MAX_PUSH_TIME]`` s,
    duration in ``[0, MAX_PUSH_DURATION]`` s; else :class:`SettingError` naming the setting."""
    f = np.asarray(force, np.float64)
    if not (np.all(np.isfinite(f)) and np.all(np.abs(f) <= MAX_PUSH_FORCE)):
        raise SettingError(force_name, f"{force_name} must be finite with |{force_name}| <= {MAX_PUSH_FORCE:g} N, "
                                       f"got {f.tolist()}")
    for name, v, hi in (("push_time", t_start, MAX_PUSH_TIME), ("push_duration", duration, MAX_PUSH_DURATION)):
        if not (np.isfinite(v) and 0 <= v <= hi):
            raise SettingError(name, f"{name} must be in [0, {hi:g}] s, got {v}")


@dataclasses.dataclass(frozen=True)
class Randomisation:
    """Per-instance randomisation ranges (uniform). Attributes:
      apex: (5,) half-widths on the apex state ``(z, theta, xdot, zdot, thetadot)``.
      roll, yaw_rate: half-widths on the initial roll (rad) and yaw rate (rad/s).
      friction: (lo, hi) ground friction.  payload: (lo, hi) payload mass (kg); payload_com: half-width (m).
    """

    apex: tuple = (0.01, 0.02, 0.05, 0.05, 0.2)
    roll: float = 0.02
    yaw_rate: float = 0.05
    friction: tuple = (0.7, 1.0)
    payload: tuple = (0.0, 5.0)
    payload_com: float = 0.05

    def __post_init__(self):
        if len(self.apex) != 5 or any((not np.isfinite(a)) or a < 0 for a in self.apex):
            raise ValueError(f"apex must be 5 non-negative half-widths, got {self.apex}")
        _pair("friction", self.friction, True, MAX_FRICTION)
        _pair("payload", self.payload, False, MAX_PAYLOAD, " kg")
        if not (0 <= self.payload_com <= 0.2):
            raise ValueError(f"payload_com must be in [0, 0.2] m, got {self.payload_com}")
        for name, v in (("roll", self.roll), ("yaw_rate", self.yaw_rate)):
            if not (np.isfinite(v) and 0 <= v <= 1.0):
                raise ValueError(f"{name} (half-width) must be in [0, 1], got {v}")

    @staticmethod
    def none() -> "Randomisation":
        return Randomisation(apex=(0.0,) * 5, roll=0.0, yaw_rate=0.0, friction=(0.8, 0.8), payload=(0.0, 0.0),
                             payload_com=0.0)


def validate_run(*, speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0, instances=1, duration=6.0,
                 friction=(0.7, 1.0), payload=(0.0, 5.0), push=0.0, push_time=3.0, push_duration=0.1, seed=0,
                 period=0.4) -> None:
    """Check every setting of a batched bound (what :func:`make_batch` and :func:`run` would reject, before any
    compile). Raises :class:`SettingError` whose message names the parameter and its allowed range."""
    def need(ok, name, rule, value):
        if not ok:
            raise SettingError(name, f"{name} must be {rule}, got {value}")

    for name, v in (("speed", speed), ("yaw_rate", yaw_rate), ("lateral_speed", lateral_speed),
                    ("ramp_time", ramp_time)):
        try:
            BoundingCommand.make(**{name: v})
        except ValueError as e:
            raise SettingError(name, str(e)) from None
    need(isinstance(instances, (int, np.integer)) and 1 <= instances <= MAX_INSTANCES, "instances",
         f"an int in [1, {MAX_INSTANCES}]", instances)
    need(isinstance(seed, (int, np.integer)) and 0 <= seed < 2**32, "seed", "an int in [0, 2^32)", seed)
    need(np.isfinite(duration) and period <= duration <= MAX_DURATION, "duration",
         f"in [{period:g}, {MAX_DURATION:g}] s", duration)
    n = duration / period
    need(abs(n - round(n)) <= 1e-6, "duration", f"a multiple of the gait period {period:g} s", duration)
    Randomisation(friction=friction, payload=payload)
    check_push(push, push_time, push_duration)


class Batch(NamedTuple):
    params: BoundingParams  # leading batch axis on every leaf
    terrain: hmodel.InstanceTerrain
    apex0: np.ndarray  # (B, 5) initial apex states
    roll0: np.ndarray
    yaw_rate0: np.ndarray
    push: sim.Push


def stack_params(plist: list[BoundingParams]) -> BoundingParams:
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *plist)


def command_params(base: BoundingParams, commands, ramp_time: float = 1.0) -> BoundingParams:
    """``base`` broadcast to one instance per row of ``commands`` (N, 3) = (forward speed, yaw rate, lateral
    speed), each with its own :class:`hyqjax.bounding.params.BoundingCommand` (validated; vectorised, so a map of
    tens of thousands of instances builds in milliseconds). Leaves of ``base`` may not carry a batch axis."""
    cmd = np.atleast_2d(np.asarray(commands, np.float64))
    if cmd.ndim != 2 or cmd.shape[1] != 3 or cmd.shape[0] < 1:
        raise ValueError(f"commands must have shape (N, 3) (speed, yaw rate, lateral speed), got {cmd.shape}")
    n = cmd.shape[0]
    c = BoundingCommand.make(speed=cmd[:, 0], yaw_rate=cmd[:, 1], lateral_speed=cmd[:, 2],
                             ramp_time=np.full(n, ramp_time))
    p = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(jnp.asarray(x), (n,) + jnp.shape(x)), base)
    return p.replace(command=c)


def make_batch(plist: list[BoundingParams] | BoundingParams, seed: int = 0, rand: Randomisation | None = None,
               push_force=0.0, push_time=2.0, push_duration=0.1, n_unique: int | None = None) -> Batch:
    """Instances from per-instance params, with the seed's randomisation of initial state, friction, payload.

    ``plist``: a list of per-instance params, or params whose every leaf has a leading batch axis (e.g.
    :func:`command_params`).

    ``push_force``: scalar or (B,) lateral push magnitudes (N); the sign alternates over instances
    (``+y`` for even, ``-y`` for odd instances), applied at the trunk CoM during ``[push_time, push_time + push_duration)``.
    ``n_unique``: draw the randomisation for this many instances and repeat it (``B`` must be a multiple), so
    several configurations (e.g. the ablation) run on identical instances.
    """
    rand = rand or Randomisation()
    batched = isinstance(plist, BoundingParams)
    if batched and np.ndim(plist.mass) != 1:
        raise ValueError("plist as one BoundingParams must carry a leading batch axis on every leaf (command_params)")
    b = int(np.shape(plist.mass)[0]) if batched else len(plist)
    if b < 1:
        raise ValueError("plist (instances) must not be empty")
    nu = b if n_unique is None else n_unique
    if not (isinstance(nu, int) and nu >= 1 and b % nu == 0):
        raise ValueError(f"n_unique must be a positive int dividing the batch size {b}, got {n_unique}")
    rng = np.random.default_rng(seed)
    params = plist if batched else stack_params(plist)
    ref = np.asarray(params.apex_ref.array(), np.float64)

    def draw(shape_tail, lo, hi):
        x = rng.uniform(lo, hi, (nu,) + shape_tail)
        return np.tile(x, (b // nu,) + (1,) * len(shape_tail))

    apex0 = ref + draw((5,), -1, 1) * np.asarray(rand.apex)
    roll0 = draw((), -1, 1) * rand.roll
    yr0 = draw((), -1, 1) * rand.yaw_rate
    fr = draw((), rand.friction[0], rand.friction[1])
    pm = draw((), rand.payload[0], rand.payload[1])
    pc = np.concatenate([draw((2,), -1, 1) * rand.payload_com, np.zeros((b, 1))], 1)
    terrain = hmodel.InstanceTerrain.make(np.zeros(b), friction=fr, payload_mass=pm, payload_com=pc)
    pf = np.broadcast_to(np.asarray(push_force, np.float64), (b,))
    check_push(pf, push_time, push_duration, force_name="push_force")
    sign = np.where(np.arange(b) % nu % 2 == 0, 1.0, -1.0)
    force = np.stack([np.zeros(b), sign * pf, np.zeros(b)], 1)
    push = sim.Push(jnp.asarray(force, jnp.float32), jnp.full(b, push_time, jnp.float32),
                    jnp.full(b, push_duration, jnp.float32))
    # The estimator starts at the nominal apex (it does not know the perturbation).
    return Batch(params, terrain, apex0, roll0, yr0, push)


def concat_batches(batches: list[Batch]) -> Batch:
    """One batch from several (so differently randomised groups share one compiled rollout)."""
    cat = lambda *xs: jnp.concatenate([jnp.asarray(x) for x in xs])  # noqa: E731
    params = jax.tree_util.tree_map(cat, *[b.params for b in batches])
    terrain = jax.tree_util.tree_map(cat, *[b.terrain for b in batches])
    push = jax.tree_util.tree_map(cat, *[b.push for b in batches])
    return Batch(params, terrain, np.concatenate([b.apex0 for b in batches]),
                 np.concatenate([b.roll0 for b in batches]), np.concatenate([b.yaw_rate0 for b in batches]), push)


@_dc
class FallMetrics:
    """Device metrics of one instance (accumulated every tick on the ground truth).

    Attributes:
      fall_tick: tick of the first fall (-1: none).  low_trunk, roll, pitch: the first fall's cause (the trunk
        below ``FALL_HEIGHT``; ``|roll|`` / ``|pitch|`` above ``FALL_ANGLE``; checked in that order, one is set).
      ticks: ticks simulated.  min_z: lowest trunk height.  max_roll, max_pitch: largest ``|roll|``, ``|pitch|``.
    """

    fall_tick: jax.Array
    low_trunk: jax.Array
    roll: jax.Array
    pitch: jax.Array
    ticks: jax.Array
    min_z: jax.Array
    max_roll: jax.Array
    max_pitch: jax.Array


def fall_metrics() -> sim.Metrics:
    """:class:`FallMetrics` as a :class:`hyqjax.sim.rollout.Metrics` pair."""

    def init(d):
        f = jnp.zeros((), bool)
        return FallMetrics(fall_tick=jnp.array(-1), low_trunk=f, roll=f, pitch=f, ticks=jnp.array(0),
                           min_z=d.qpos[robot.QPOS_BASE_POS][2], max_roll=jnp.zeros((), d.qpos.dtype),
                           max_pitch=jnp.zeros((), d.qpos.dtype))

    def update(ms: FallMetrics, d, obs, info):
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
        z = d.qpos[robot.QPOS_BASE_POS][2]
        low = z < FALL_HEIGHT
        roll = ~low & (jnp.abs(rpy[0]) > FALL_ANGLE)
        pitch = ~low & ~roll & (jnp.abs(rpy[1]) > FALL_ANGLE)
        new = (ms.fall_tick < 0) & (low | roll | pitch)
        return FallMetrics(fall_tick=jnp.where(new, ms.ticks, ms.fall_tick), low_trunk=ms.low_trunk | (new & low),
                           roll=ms.roll | (new & roll), pitch=ms.pitch | (new & pitch), ticks=ms.ticks + 1,
                           min_z=jnp.minimum(ms.min_z, z), max_roll=jnp.maximum(ms.max_roll, jnp.abs(rpy[0])),
                           max_pitch=jnp.maximum(ms.max_pitch, jnp.abs(rpy[1])))

    return sim.Metrics(init, update)


def record(d, obs, info: BoundingInfo) -> dict:
    """One trace sample: ground truth (trunk pose and twist, apex state, full ``qpos`` for replay, foot forces)
    and what the controller commanded / estimated."""
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
    return dict(t=d.time, pos=d.qpos[robot.QPOS_BASE_POS], vel=d.qvel[robot.QVEL_BASE_LIN], rpy=rpy,
                omega=d.qvel[robot.QVEL_BASE_ANG], apex=bc.data_apex(d).array(), yaw_des=info.yaw_des,
                v_des=info.v_des, yaw_rate_des=info.yaw_rate_des, est_vel_h=info.vel_h, est_z=info.est_pos[2],
                roll_des=info.roll_des, qpos=d.qpos, foot_force=obs.foot_force)


def initial_data(batch: Batch, m, mx, mx_batched=None) -> "jax.Array":
    """Batched MJX data at each instance's initial apex state (:func:`hyqjax.bounding.cycle.apex_data`). Under
    MuJoCo Warp (``mx_batched`` a batched Warp model) the state is computed with the JAX model ``mx`` and put
    into Warp data made by :func:`hyqjax.sim.rollout.initial_data`."""
    def one(p, s, roll, yr):
        return bc.apex_data(mx, m, p, s, roll=roll, yaw_rate=yr)

    d = jax.vmap(one)(batch.params, jnp.asarray(batch.apex0, jnp.float32), jnp.asarray(batch.roll0, jnp.float32),
                      jnp.asarray(batch.yaw_rate0, jnp.float32))
    if mx_batched is None:
        return d
    return backend.get(backend.model_impl(mx_batched)).from_jax_data(mx_batched, d, m)


def runner(cfg: sim.SimConfig, impl: str = "jax"):
    """The batch runner of the bound for a static configuration and resolved MJX implementation
    (:func:`hyqjax.sim.rollout.make_batch_runner`, built once per ``(cfg, impl)``, since a runner fixes the batched
    model's structure, and compiled once per batch shape): ``runner(mx_batched, d0, params, push, progress=None,
    chunk_seconds=None) -> RolloutResult`` with :class:`FallMetrics` and the trace of :func:`record`
    (``cfg.record_every`` 0: none). Every argument has a leading batch axis."""
    return _runner(cfg, impl)


@functools.lru_cache(maxsize=8)
def _runner(cfg: sim.SimConfig, impl: str):
    _, _, ids = bc.model()
    return sim.make_batch_runner(ids, bctrl.bounding_controller, cfg, fall_metrics(), record)


def run(batch: Batch, duration: float, control_dt: float = 0.002, record_every: int = 10, progress=None,
        impl: str = "jax"):
    """Simulate the batch; returns ``(RolloutResult, trace as NumPy dict)``. ``progress(done, total)`` (simulated
    seconds) is called after every simulated second. ``impl``: MJX implementation, ``auto | jax | warp``
    (:mod:`hyqjax.sim.backend`; the cycle optimisation and the return map need ``jax``).

    The batch goes through ``make_bounding_rollout(BoundingRolloutConfig(duration, control_dt, record_every,
    impl)).run(batch)`` (:mod:`hyqjax.bounding.rollout`, which also returns typed outcomes): the settings are
    checked there (:class:`SettingError`; ``duration`` a whole number of gait periods, the period a multiple of
    ``record_every * control_dt``)."""
    from hyqjax.bounding.rollout import BoundingRolloutConfig, make_bounding_rollout

    cfg = BoundingRolloutConfig(duration=duration, control_dt=control_dt, record_every=record_every, impl=impl)
    _, res = make_bounding_rollout(cfg).run(batch, progress=progress)
    return res, jax.tree_util.tree_map(np.asarray, res.trace)
