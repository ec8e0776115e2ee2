"""A batch of bounding instances: per-instance parameters, randomisation, and the checks of a batch's settings.

Every instance of a :class:`Batch` carries its own :class:`hyqjax.bounding.params.BoundingParams` (command,
switches), terrain (friction, payload), initial apex state, roll and yaw rate and :class:`hyqjax.core.types.Push`,
so in-place, forward, turning and the four ablation combinations share ONE compiled batch runner
(:mod:`hyqjax.bounding.rollout` runs a batch). :func:`make_batch` draws the randomisation
(:class:`Randomisation`) from a seed; :func:`validate_run` checks every setting of a batched bound before
anything compiles, a bad one a :class:`SettingError` naming it and its allowed range.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding.params import BoundingCommand, BoundingParams
from hyqjax.core.types import Push
from hyqjax.sim import model as hmodel

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
    push: Push


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
    push = Push(jnp.asarray(force, jnp.float32), jnp.full(b, push_time, jnp.float32),
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
