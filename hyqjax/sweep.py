"""Robustness sweeps of the step-down experiment (Focchi et al. 2017, Section IV) over a declarative grid.

A :class:`SweepSpec` names, for every *axis* of :data:`AXES` (step height, rough terrain amplitude,
friction, payload, initial pose, foot sequence, joint PD gains, lateral push, sensor noise, control
latency, reflex on/off and every :class:`hyqjax.reflex.ReflexParams` field), either

* ``grid``: a list of values; the sweep runs the Cartesian product of all grid axes, or
* ``random``: a range ``[lo, hi]`` (uniform) or, for a choice axis, a list of options, drawn per
  instance, ``samples`` draws per grid point, or
* ``fixed``: one value; axes named nowhere take their default (:data:`AXES`).

Instance ``i`` is grid point ``g = i // samples`` and draw ``s = i % samples``. Its random inputs come
from ``numpy.random.default_rng([seed, key])`` with ``key = s`` (``paired = true``, the default: every
grid point sees the same ``samples`` random draws, i.e. common random numbers, so reflex on/off or
two heights are compared on identical payloads, frictions, ...) or ``key = i`` (``paired = false``).
Either way the inputs of an instance depend on the sweep seed and its index only, never on chunking.

Execution (:func:`run_sweep`): instances run in chunks of ``chunk_size`` (padded to a whole chunk and
to a multiple of the local device count, so one program is compiled), sharded over the local devices
along the ``batch`` axis of :func:`hyqjax.sim.batch_mesh`. Every finished chunk is written to
``DIR/chunks/NNNNN.npz`` and then recorded in ``DIR/manifest.json`` (both atomically: write a
temporary file, then ``os.replace``). The manifest holds the schema, the canonical spec and its
SHA-256; running the same spec in the same directory resumes, skipping recorded chunks; a different
spec there is refused (:class:`StoreMismatch`).

Outcome: a row per instance holds the inputs and :func:`hyqjax.stepdown.summarize_instances`'s
metrics. :func:`count_outcomes` makes ``success`` false, with a reason, for diverged instances and for
instances with non-finite metrics. :func:`summarize_sweep` reports success probability maps (e.g.
height x friction) with Wilson 95% intervals per reflex setting and the largest safe height:

* ``h95_wilson`` (conservative): the largest height level ``h`` such that, at every level ``<= h``,
  the Wilson 95% lower bound of the success probability (pooled over all other axes) is ``>= 0.95``.
  It needs at least 73 instances per level (73/73 gives a lower bound of 0.950); None otherwise.
* ``h95_logistic`` (point estimate): the height where a logistic fit
  ``P(success | h) = sigmoid(a + b h)`` (maximum likelihood, Newton) crosses 0.95; None if the fit
  has ``b >= 0`` or does not converge (e.g. all successes).

Height levels are the grid values, or equal-width bins over ``[lo, hi]`` (``bins``) for a random axis.

Sensor noise and control latency are applied by wrapping the crawl controller
(:func:`sensed_controller`): Gaussian noise on the joint encoders, joint velocities, IMU orientation
(a small random rotation) and angular rate and the estimated foot forces; a latency of ``d`` ticks
hands the controller the (noisy) observation of ``d`` ticks ago, from a ring buffer in the controller
state. A sweep without those axes runs the crawl controller unwrapped, as :func:`stepdown.run_batch`.
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import math
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import crawl, impedance, model as hmodel, reflex as hreflex, sim, stepdown
from hyqjax.io import atomic_write

SCHEMA = "hyqjax.sweep/1"


class SpecError(ValueError):
    """A sweep specification is invalid (the message names the field and the allowed range)."""


class StoreMismatch(RuntimeError):
    """The output directory holds a sweep of a different specification (or schema)."""


@dataclasses.dataclass(frozen=True)
class Axis:
    """One sweepable input: allowed range ``[lo, hi]`` (or ``options``), unit, default."""

    name: str
    lo: float
    hi: float
    unit: str
    default: Any
    doc: str
    kind: str = "float"  # "float", "bool", "choice", "int"
    options: tuple = ()


def _reflex_axes():
    p = hreflex.ReflexParams()
    ranges = dict(k_x=(0.0, 1e5), k_x_max=(0.0, 1e6), k_base=(0.0, 1e5), k_kl=(0.0, 1e5), delta=(1e-4, 0.4999),
                  d_st_min=(1e-3, 1e5), d_st_max=(1e-3, 1e5), d_sw_min=(1e-3, 1e5), d_sw_max=(1e-3, 1e5),
                  m_min=(1e-4, 1.0), m_max=(1e-4, 1.0))
    units = dict(k_x="N/m", k_x_max="N/m", k_base="N m/rad", k_kl="N m/rad", delta="rad", m_min="m/rad",
                 m_max="m/rad")
    return [Axis(f"reflex_{n}", lo, hi, units.get(n, "N m s/rad"), float(getattr(p, n)),
                 f"ReflexParams.{n} (Table I default)") for n, (lo, hi) in ranges.items()]


_AXES_LIST = [
    Axis("height", 0.0, hmodel.MAX_PLATFORM_HEIGHT, "m", 0.21, "platform (step) height"),
    Axis("roughness", 0.0, 2 * hmodel.BLOCK_HALF_Z, "m", 0.0,
         "rough-terrain amplitude: block heights ~ U(0, roughness) per block (needs blocks > 0)"),
    Axis("friction", 0.05, 5.0, "", 0.8, "sliding friction of the terrain"),
    Axis("payload_mass", 0.0, 100.0, "kg", 0.0, "payload on the trunk"),
    Axis("payload_com_x", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame x"),
    Axis("payload_com_y", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame y"),
    Axis("payload_com_z", -0.5, 0.5, "m", 0.0, "payload CoM, trunk frame z"),
    Axis("start_distance", 0.0, 1.5, "m", 0.02, "front feet distance before the platform edge at the start"),
    Axis("lateral_offset", -0.5, 0.5, "m", 0.0, "initial lateral trunk offset"),
    Axis("yaw", -0.5, 0.5, "rad", 0.0, "initial heading"),
    Axis("speed", -0.3, 0.3, "m/s", 0.1, "desired forward velocity (CrawlParams.forward_velocity)"),
    Axis("foot_sequence", 0, 0, "", "rh-rf-lh-lf", "crawl leg order (CrawlParams.foot_sequence)", "choice",
         tuple(sorted(crawl.FOOT_SEQUENCES))),
    Axis("kp_haa", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, HAA"),
    Axis("kp_hfe", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, HFE"),
    Axis("kp_kfe", 1.0, 5000.0, "N m/rad", 300.0, "joint PD stiffness, KFE"),
    Axis("kd_haa", 0.01, 200.0, "N m s/rad", 8.0, "joint PD damping, HAA"),
    Axis("kd_hfe", 0.01, 200.0, "N m s/rad", 8.0, "joint PD damping, HFE"),
    Axis("kd_kfe", 0.01, 200.0, "N m s/rad", 6.0, "joint PD damping, KFE"),
    Axis("push_force_x", -5000.0, 5000.0, "N", 0.0, "push on the trunk, world x"),
    Axis("push_force_y", -5000.0, 5000.0, "N", 0.0, "lateral push on the trunk, world y"),
    Axis("push_t_start", 0.0, 600.0, "s", 0.0, "push start time"),
    Axis("push_duration", 0.0, 10.0, "s", 0.0, "push duration"),
    Axis("noise_joint_pos", 0.0, 0.1, "rad", 0.0, "std of joint encoder noise"),
    Axis("noise_joint_vel", 0.0, 10.0, "rad/s", 0.0, "std of joint velocity noise"),
    Axis("noise_imu", 0.0, 0.1, "rad", 0.0, "std of IMU orientation noise (small random rotation)"),
    Axis("noise_gyro", 0.0, 2.0, "rad/s", 0.0, "std of IMU angular-rate noise"),
    Axis("noise_foot_force", 0.0, 200.0, "N", 0.0, "std of estimated foot force noise"),
    Axis("latency", 0.0, 0.05, "s", 0.0, "control latency (rounded to whole control ticks)"),
    Axis("reflex", 0, 1, "", True, "height reflex on/off", "bool"),
    *_reflex_axes(),
]
#: Every sweepable axis by name.
AXES: dict[str, Axis] = {a.name: a for a in _AXES_LIST}
_SENSOR_AXES = ("noise_joint_pos", "noise_joint_vel", "noise_imu", "noise_gyro", "noise_foot_force", "latency")
_TOP_KEYS = ("seed", "samples", "paired", "duration", "control_dt", "max_tilt", "min_progress", "blocks",
             "grid", "random", "fixed", "maps", "bins")


def _axis_value(axis: Axis, v, where: str):
    """Validate and normalise one value of ``axis`` (``where`` names it in errors)."""
    if axis.kind == "bool":
        if isinstance(v, str) and v.lower() in ("on", "off", "true", "false"):
            return v.lower() in ("on", "true")
        if isinstance(v, (bool, np.bool_)) or v in (0, 1):
            return bool(v)
        raise SpecError(f"{where}: {axis.name} must be true/false (or 'on'/'off'), got {v!r}")
    if axis.kind == "choice":
        if v not in axis.options:
            raise SpecError(f"{where}: {axis.name} must be one of {list(axis.options)}, got {v!r}")
        return str(v)
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise SpecError(f"{where}: {axis.name} must be a number in [{axis.lo}, {axis.hi}] {axis.unit}, got {v!r}")
    f = float(v)
    if not math.isfinite(f) or not (axis.lo <= f <= axis.hi):
        raise SpecError(f"{where}: {axis.name}={v!r} out of range: must be in [{axis.lo}, {axis.hi}] {axis.unit}")
    return f


def _get_axis(name: str, where: str) -> Axis:
    if name not in AXES:
        raise SpecError(f"{where}: unknown axis {name!r}; allowed axes: {sorted(AXES)}")
    return AXES[name]


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    """A validated sweep (see the module docstring). Build with :meth:`from_dict` / :func:`load_spec`.

    Attributes:
      grid: ``((axis, (values...)), ...)``: Cartesian product.
      random: ``((axis, (lo, hi) or (options...)), ...)``: per-instance draws.
      fixed: ``((axis, value), ...)``.
      samples: random draws per grid point.
      seed: sweep seed.
      paired: random draws keyed by the draw index (shared by grid points) rather than the instance.
      duration, control_dt, max_tilt, min_progress: :class:`hyqjax.stepdown.StepdownConfig`.
      blocks: ``(n_blocks_x, n_blocks_y)`` rough-terrain grid per level (0: none).
      maps: axis pairs of the success maps.
      bins: bins of a random float axis in maps and height curves.
    """

    grid: tuple = ()
    random: tuple = ()
    fixed: tuple = ()
    samples: int = 1
    seed: int = 0
    paired: bool = True
    duration: float = 18.0
    control_dt: float = 0.002
    max_tilt: float = 0.4
    min_progress: float = 0.5
    blocks: tuple = (0, 0)
    maps: tuple = (("height", "friction"), ("height", "payload_mass"))
    bins: int = 4

    # ---------------------------------------------------------------- construction / validation
    @staticmethod
    def from_dict(d: dict) -> "SweepSpec":
        """Validate a spec given as a dict (parsed TOML / JSON); errors name the field and range."""
        if not isinstance(d, dict):
            raise SpecError(f"a sweep spec must be a table/object, got {type(d).__name__}")
        unknown = set(d) - set(_TOP_KEYS)
        if unknown:
            raise SpecError(f"unknown sweep spec key(s) {sorted(unknown)}; allowed: {list(_TOP_KEYS)}")

        def num(key, lo, hi, default, integer=False):
            v = d.get(key, default)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not float(v).is_integer()):
                raise SpecError(f"{key} must be {'an integer' if integer else 'a number'} in [{lo}, {hi}], got {v!r}")
            if not (math.isfinite(v) and lo <= v <= hi):
                raise SpecError(f"{key}={v!r} out of range: must be in [{lo}, {hi}]")
            return int(v) if integer else float(v)

        seen: dict[str, str] = {}

        def section(name):
            sec = d.get(name, {})
            if not isinstance(sec, dict):
                raise SpecError(f"[{name}] must be a table of axis = value(s), got {type(sec).__name__}")
            for k in sec:
                _get_axis(k, f"[{name}]")
                if k in seen:
                    raise SpecError(f"axis {k!r} appears in both [{seen[k]}] and [{name}]; name it once")
                seen[k] = name
            return sec

        grid = []
        for k, vals in sorted(section("grid").items()):
            a = AXES[k]
            if not isinstance(vals, (list, tuple)) or not vals:
                raise SpecError(f"[grid] {k} must be a non-empty list of values, got {vals!r}")
            norm = tuple(_axis_value(a, v, f"[grid] {k}") for v in vals)
            if len(set(norm)) != len(norm):
                raise SpecError(f"[grid] {k} has repeated values {list(vals)}")
            grid.append((k, norm))
        random = []
        for k, rng in sorted(section("random").items()):
            a = AXES[k]
            if a.kind == "bool":
                raise SpecError(f"[random] {k}: a bool axis cannot be random; put it in [grid] (e.g. [false, true])")
            if a.kind == "choice":
                if not isinstance(rng, (list, tuple)) or not rng:
                    raise SpecError(f"[random] {k} must be a non-empty list of options from {list(a.options)}")
                random.append((k, tuple(_axis_value(a, v, f"[random] {k}") for v in rng)))
                continue
            if not isinstance(rng, (list, tuple)) or len(rng) != 2:
                raise SpecError(f"[random] {k} must be [lo, hi] within [{a.lo}, {a.hi}] {a.unit}, got {rng!r}")
            lo, hi = (_axis_value(a, v, f"[random] {k}") for v in rng)
            if lo > hi:
                raise SpecError(f"[random] {k}: lo={lo} must be <= hi={hi}")
            random.append((k, (lo, hi)))
        fixed = tuple((k, _axis_value(AXES[k], v, f"[fixed] {k}")) for k, v in sorted(section("fixed").items()))

        blocks = d.get("blocks", [0, 0])
        if (not isinstance(blocks, (list, tuple)) or len(blocks) != 2
                or any(isinstance(b, bool) or not isinstance(b, int) or not 0 <= b <= 20 for b in blocks)):
            raise SpecError(f"blocks must be [n_blocks_x, n_blocks_y], integers in [0, 20], got {blocks!r}")
        maps = d.get("maps", [["height", "friction"], ["height", "payload_mass"]])
        if not isinstance(maps, (list, tuple)) or any(not isinstance(p, (list, tuple)) or len(p) != 2 for p in maps):
            raise SpecError(f"maps must be a list of [axis, axis] pairs, got {maps!r}")
        for p in maps:
            for k in p:
                _get_axis(k, "maps")
        spec = SweepSpec(
            grid=tuple(grid), random=tuple(random), fixed=fixed,
            samples=num("samples", 1, 10**7, 1, integer=True), seed=num("seed", 0, 2**63 - 1, 0, integer=True),
            paired=bool(d.get("paired", True)), duration=num("duration", 0.01, 600.0, 18.0),
            control_dt=num("control_dt", 1e-4, 0.02, 0.002), max_tilt=num("max_tilt", 0.01, 1.5, 0.4),
            min_progress=num("min_progress", -10.0, 10.0, 0.5), blocks=(int(blocks[0]), int(blocks[1])),
            maps=tuple((str(a), str(b)) for a, b in maps), bins=num("bins", 1, 100, 4, integer=True),
        )
        if not isinstance(d.get("paired", True), bool):
            raise SpecError(f"paired must be true or false, got {d.get('paired')!r}")
        if spec.n_instances > 10**8:
            raise SpecError(f"the sweep has {spec.n_instances} instances; at most 1e8 are allowed")
        if (spec.blocks[0] == 0) != (spec.blocks[1] == 0):
            raise SpecError(f"blocks must be both zero or both positive, got {list(spec.blocks)}")
        if spec.blocks[0] == 0 and spec.axis_max("roughness") > 0:
            raise SpecError("roughness > 0 needs rough-terrain blocks: set blocks = [nx, ny] with nx, ny >= 1")
        if spec.axis_max("push_t_start") > spec.duration:
            raise SpecError(f"push_t_start must be in [0, duration={spec.duration}] s")
        if spec.axis_max("latency") > 20 * spec.control_dt + 1e-12:
            raise SpecError(f"latency must be in [0, {20 * spec.control_dt}] s (at most 20 control ticks)")
        spec._check_reflex_order()
        return spec

    def to_dict(self) -> dict:
        """Canonical plain-JSON form (what the spec hash covers)."""
        return dict(
            grid={k: list(v) for k, v in self.grid}, random={k: list(v) for k, v in self.random},
            fixed=dict(self.fixed), samples=self.samples, seed=self.seed, paired=self.paired,
            duration=self.duration, control_dt=self.control_dt, max_tilt=self.max_tilt,
            min_progress=self.min_progress, blocks=list(self.blocks), maps=[list(p) for p in self.maps],
            bins=self.bins)

    @property
    def spec_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()

    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple(len(v) for _, v in self.grid)

    @property
    def n_instances(self) -> int:
        return int(np.prod(self.grid_shape, dtype=np.int64)) * self.samples

    def varying(self) -> list[str]:
        return [k for k, v in self.grid if len(v) > 1] + [k for k, v in self.random]

    def axis_values(self, name: str) -> list:
        """Every value ``name`` can take (grid values, random bounds / options, fixed or default)."""
        for sec in (self.grid, self.random, self.fixed):
            for k, v in sec:
                if k == name:
                    return list(v) if isinstance(v, tuple) else [v]
        return [AXES[name].default]

    def axis_max(self, name: str) -> float:
        return max(float(v) for v in self.axis_values(name))

    @property
    def sensed(self) -> bool:
        """Whether the controller sees sensor noise or latency (wraps the crawl controller)."""
        return any(self.axis_max(k) > 0 for k in _SENSOR_AXES)

    @property
    def max_delay(self) -> int:
        return int(round(self.axis_max("latency") / self.control_dt))

    def stepdown_config(self) -> stepdown.StepdownConfig:
        layout = hmodel.TerrainLayout(n_blocks_x=self.blocks[0], n_blocks_y=self.blocks[1])
        return stepdown.StepdownConfig(duration=self.duration, control_dt=self.control_dt, record_every=0,
                                       max_tilt=self.max_tilt, min_progress=self.min_progress, layout=layout)

    def _check_reflex_order(self):
        """``k_x <= k_x_max``, ``d_*_min < d_*_max``, ``m_min < m_max`` for every possible combination."""
        for lo, hi, strict in (("k_x", "k_x_max", False), ("d_st_min", "d_st_max", True),
                               ("d_sw_min", "d_sw_max", True), ("m_min", "m_max", True)):
            a, b = self.axis_values(f"reflex_{lo}"), self.axis_values(f"reflex_{hi}")
            worst_a, worst_b = max(float(x) for x in a), min(float(x) for x in b)
            bad = worst_a >= worst_b if strict else worst_a > worst_b
            if bad:
                rel = "<" if strict else "<="
                raise SpecError(f"reflex_{lo} must be {rel} reflex_{hi} for every combination; the spec allows "
                                f"reflex_{lo}={worst_a} with reflex_{hi}={worst_b} (ReflexParams.validate)")

    # ---------------------------------------------------------------- instances
    def instance_inputs(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Input rows of instances ``start..stop-1`` (deterministic in ``seed`` and the index only)."""
        if not (0 <= start <= stop <= self.n_instances):
            raise ValueError(f"instance range [{start}, {stop}) outside [0, {self.n_instances}]")
        idx = np.arange(start, stop, dtype=np.int64)
        n = idx.size
        g = idx // self.samples
        s = idx % self.samples
        rows: dict[str, Any] = dict(index=idx, grid_index=g, sample=s)
        gidx = np.unravel_index(g, self.grid_shape) if self.grid else ()
        for (k, vals), gi in zip(self.grid, gidx):
            rows[k] = np.asarray(vals, dtype=object)[gi]
        keys = s if self.paired else idx
        rows["instance_seed"] = keys.copy()
        n_blocks = hmodel.TerrainLayout(*self.blocks).n_blocks
        draws = {k: np.empty(n, dtype=object) for k, _ in self.random}
        block_u = np.zeros((n, n_blocks))
        for j, key in enumerate(keys):
            rng = np.random.default_rng([self.seed, int(key)])
            for k, r in self.random:  # sorted axis order: adding an axis changes draws, by design of the hash
                a = AXES[k]
                draws[k][j] = r[int(rng.integers(len(r)))] if a.kind == "choice" else float(rng.uniform(r[0], r[1]))
            block_u[j] = rng.uniform(0.0, 1.0, n_blocks)
        rows.update(draws)
        for k, v in self.fixed:
            rows[k] = np.full(n, v, dtype=object)
        for k, a in AXES.items():
            if k not in rows:
                rows[k] = np.full(n, a.default, dtype=object)
        out = {}
        for k, v in rows.items():
            a = AXES.get(k)
            if a is None:
                out[k] = np.asarray(v, np.int64)
            elif a.kind == "bool":
                out[k] = np.asarray(v, bool)
            elif a.kind == "choice":
                out[k] = np.asarray(v, dtype=str)
            else:
                out[k] = np.asarray(v, np.float64)
        out["block_heights"] = block_u * out["roughness"][:, None]
        _check_rows_reflex(out)
        return out


def _check_rows_reflex(rows):
    """Row-wise :meth:`ReflexParams.validate` cross-constraints (vectorised)."""
    for lo, hi, strict in (("k_x", "k_x_max", False), ("d_st_min", "d_st_max", True),
                           ("d_sw_min", "d_sw_max", True), ("m_min", "m_max", True)):
        a, b = rows[f"reflex_{lo}"], rows[f"reflex_{hi}"]
        bad = (a >= b) if strict else (a > b)
        if bad.any():
            i = int(np.argmax(bad))
            raise SpecError(f"instance {int(rows['index'][i])}: reflex_{lo}={a[i]} must be "
                            f"{'<' if strict else '<='} reflex_{hi}={b[i]} (ReflexParams.validate)")


def load_spec(path: str) -> SweepSpec:
    """Read a sweep spec from a ``.toml`` (stdlib ``tomllib``) or ``.json`` file and validate it."""
    if path.endswith(".toml"):
        import tomllib

        with open(path, "rb") as f:
            try:
                d = tomllib.load(f)
            except tomllib.TOMLDecodeError as e:
                raise SpecError(f"{path}: invalid TOML: {e}") from e
    elif path.endswith(".json"):
        with open(path) as f:
            try:
                d = json.load(f)
            except json.JSONDecodeError as e:
                raise SpecError(f"{path}: invalid JSON: {e}") from e
    else:
        raise SpecError(f"sweep spec file must end in .toml or .json, got {path!r}")
    return SweepSpec.from_dict(d)


# ------------------------------------------------------------------------------------------------
# Scenarios and the sensed controller
# ------------------------------------------------------------------------------------------------


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensorParams:
    """Per-instance sensor model: noise standard deviations, latency in ticks, PRNG key."""

    joint_pos: jax.Array
    joint_vel: jax.Array
    imu: jax.Array
    gyro: jax.Array
    foot_force: jax.Array
    delay: jax.Array  # int, ticks
    key: jax.Array  # (2,) uint32


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensedParams:
    crawl: crawl.CrawlParams
    sensor: SensorParams


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensedState:
    inner: Any
    buffer: sim.Observation  # leading axis: ticks ago (0 = now)
    key: jax.Array


def _noisy(obs: sim.Observation, sp: SensorParams, key) -> sim.Observation:
    k = jax.random.split(key, 5)
    dt = obs.q.dtype
    q = obs.q + sp.joint_pos * jax.random.normal(k[0], obs.q.shape, dt)
    qd = obs.qd + sp.joint_vel * jax.random.normal(k[1], obs.qd.shape, dt)
    # A small rotation of std ``imu`` per axis: quat <- quat (x) [1, dphi / 2], normalised.
    dphi = sp.imu * jax.random.normal(k[2], (3,), dt)
    w, v = obs.quat[0], obs.quat[1:]
    dq = jnp.concatenate([jnp.ones(1, dt), 0.5 * dphi])
    quat = jnp.concatenate([(w * dq[0] - jnp.dot(v, dq[1:]))[None], w * dq[1:] + dq[0] * v + jnp.cross(v, dq[1:])])
    quat = quat / jnp.linalg.norm(quat)
    gyro = obs.gyro + sp.gyro * jax.random.normal(k[3], (3,), dt)
    ff = obs.foot_force + sp.foot_force * jax.random.normal(k[4], obs.foot_force.shape, dt)
    return dataclasses.replace(obs, q=q, qd=qd, quat=quat, gyro=gyro, foot_force=ff)


def sensed_controller(inner: sim.Controller, max_delay: int) -> sim.Controller:
    """Wrap ``inner`` (params :class:`SensedParams`) with sensor noise and a latency of ``delay <= max_delay``
    ticks: the controller gets ``obs~(k - delay)`` with ``obs~ = obs + noise`` (independent Gaussian per tick)."""

    def init(p: SensedParams, obs):
        buf = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (max_delay + 1,) + x.shape), obs)
        return SensedState(inner.init(p.crawl, obs), buf, p.sensor.key)

    def step(p: SensedParams, s: SensedState, obs):
        key, sub = jax.random.split(s.key)
        noisy = _noisy(obs, p.sensor, sub)
        buf = jax.tree_util.tree_map(lambda b, x: jnp.concatenate([x[None], b[:-1]], 0), s.buffer, noisy)
        seen = jax.tree_util.tree_map(lambda b: b[jnp.clip(p.sensor.delay, 0, max_delay)], buf)
        cs, tau, info = inner.step(p.crawl, s.inner, seen)
        return SensedState(cs, buf, key), tau, info

    return sim.Controller(init, step)


def build_scenario(rows: dict[str, np.ndarray], spec: SweepSpec) -> tuple[stepdown.Scenario, SensorParams | None]:
    """The :class:`stepdown.Scenario` (and sensor parameters if the spec has noise/latency) of input rows."""
    b = rows["index"].shape[0]
    n_blocks = hmodel.TerrainLayout(*spec.blocks).n_blocks
    com = np.stack([rows["payload_com_x"], rows["payload_com_y"], rows["payload_com_z"]], -1)
    terrain = hmodel.InstanceTerrain.make(rows["height"], rows["friction"], rows["payload_mass"], com,
                                          rows["block_heights"], n_blocks=n_blocks)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    base = crawl.CrawlParams.make()
    params = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + jnp.shape(x)), base)
    seq = np.asarray([crawl.FOOT_SEQUENCES[str(s)] for s in rows["foot_sequence"]], np.int32)
    gains = impedance.ImpedanceGains(
        kp=f32(np.stack([rows["kp_haa"], rows["kp_hfe"], rows["kp_kfe"]], -1)),
        kd=f32(np.stack([rows["kd_haa"], rows["kd_hfe"], rows["kd_kfe"]], -1)))
    rp = hreflex.ReflexParams(**{f.name: f32(rows[f"reflex_{f.name}"])
                                 for f in dataclasses.fields(hreflex.ReflexParams)})
    params = dataclasses.replace(params, forward_velocity=f32(rows["speed"]), foot_sequence=jnp.asarray(seq),
                                 use_reflex=f32(rows["reflex"]), gains=gains, reflex=rp)
    force = np.stack([rows["push_force_x"], rows["push_force_y"], np.zeros(b)], -1)
    push = sim.Push(f32(force), f32(rows["push_t_start"]), f32(rows["push_duration"]))
    scenario = stepdown.Scenario(terrain=terrain, start_distance=f32(rows["start_distance"]),
                                 lateral_offset=f32(rows["lateral_offset"]), yaw=f32(rows["yaw"]),
                                 params=params, push=push)
    if not spec.sensed:
        return scenario, None
    keys = jax.vmap(lambda k: jax.random.fold_in(jax.random.PRNGKey(spec.seed), k))(
        jnp.asarray(rows["index"] % (2**31 - 1), jnp.uint32))
    sensor = SensorParams(f32(rows["noise_joint_pos"]), f32(rows["noise_joint_vel"]), f32(rows["noise_imu"]),
                          f32(rows["noise_gyro"]), f32(rows["noise_foot_force"]),
                          jnp.asarray(np.round(rows["latency"] / spec.control_dt), jnp.int32), keys)
    return scenario, sensor


# ------------------------------------------------------------------------------------------------
# Chunk runner: one compiled program per (config, chunk size, devices), reused across chunks
# ------------------------------------------------------------------------------------------------

_RUNNERS: dict = {}


def _runner(cfg: stepdown.StepdownConfig, sensed: bool, max_delay: int, devices: tuple):
    """A jitted ``(model, data0, params, push) -> RolloutResult`` (cached: chunks reuse the executable).

    Same computation as :func:`hyqjax.stepdown.run_batch` (``sim.rollout`` under ``vmap``, the step-down
    metrics), sharded over ``devices`` like :func:`hyqjax.sim.batch_rollout` with ``sim.batch_mesh``.
    """
    key = (cfg, sensed, max_delay, devices)
    if key in _RUNNERS:
        return _RUNNERS[key]
    m, mx, ids, slots = stepdown._setup(cfg.layout, cfg.control_dt)
    scfg = cfg.sim_config()
    metrics = stepdown.make_metrics(ids, slots, cfg)
    ctrl = crawl.crawl_controller(scfg.control_dt)
    if sensed:
        ctrl = sensed_controller(ctrl, max_delay)
    cache: dict = {}

    def run(mb, d0, params, push):
        if "fn" not in cache:
            m_axes = hmodel.model_in_axes(mb)
            fn = jax.vmap(lambda mm, dd, pp, pu: sim.rollout(mm, ids, dd, ctrl, pp, scfg, metrics, None, pu),
                          in_axes=(m_axes, 0, 0, 0))
            if len(devices) == 1:
                cache["fn"], cache["put"] = jax.jit(fn), None
            else:
                from jax.sharding import NamedSharding, PartitionSpec

                mesh = sim.batch_mesh(list(devices))
                shard, repl = NamedSharding(mesh, PartitionSpec("batch")), NamedSharding(mesh, PartitionSpec())
                m_sh = jax.tree_util.tree_map(lambda ax: shard if ax == 0 else repl, m_axes,
                                              is_leaf=lambda x: x is None or isinstance(x, int))
                in_sh = (m_sh, *(jax.tree_util.tree_map(lambda _: shard, t) for t in (d0, params, push)))
                out_sh = jax.tree_util.tree_map(lambda _: shard, jax.eval_shape(fn, mb, d0, params, push))
                cache["fn"] = jax.jit(fn, in_shardings=in_sh, out_shardings=out_sh)
                cache["put"] = in_sh
        args = (mb, d0, params, push)
        if cache["put"] is not None:
            args = jax.device_put(args, cache["put"])
        return cache["fn"](*args)

    _RUNNERS[key] = (run, m, mx, ids)
    return _RUNNERS[key]


def run_rows(rows: dict[str, np.ndarray], spec: SweepSpec, pad_to: int, devices=None) -> dict[str, np.ndarray]:
    """Simulate input rows (padded to ``pad_to`` by repeating the last row); returns the outcome columns."""
    devices = tuple(jax.local_devices() if devices is None else devices)
    n = rows["index"].shape[0]
    pad_to = sim.pad_batch(max(pad_to, n), len(devices))
    padded = {k: np.concatenate([v, np.repeat(v[-1:], pad_to - n, 0)], 0) for k, v in rows.items()}
    scenario, sensor = build_scenario(padded, spec)
    cfg = spec.stepdown_config()
    run, m, mx, ids = _runner(cfg, spec.sensed, spec.max_delay, devices)
    mb = hmodel.batch_model(mx, ids, scenario.terrain)
    d0 = sim.initial_data(mx, stepdown.initial_qpos(m, scenario), pad_to)
    params = scenario.params if sensor is None else SensedParams(scenario.params, sensor)
    res = run(mb, d0, params, scenario.push)
    if sensor is not None:
        res = res._replace(ctrl_state=res.ctrl_state.inner)
    out = stepdown.summarize_instances(res, scenario, cfg, ids)
    out = count_outcomes({k: np.asarray(v)[:n] for k, v in out.items()})
    return out


# ------------------------------------------------------------------------------------------------
# Outcomes
# ------------------------------------------------------------------------------------------------

#: Metrics that must be finite for an instance to count (NaN there means the instance failed).
CRITICAL_METRICS = ("peak_roll", "peak_pitch", "progress", "mean_mobility")


def count_outcomes(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Make every diverged or non-finite instance a failure with a reason.

    ``success <- success & ~diverged & all(isfinite(CRITICAL_METRICS))``; the reason gains
    ``"diverged"`` / ``"non-finite metrics"`` where missing. Returns a new dict (``failure_reason`` as str).
    """
    out = dict(out)
    n = np.asarray(out["success"]).shape[0]
    reason = np.asarray(out.get("failure_reason", np.full(n, "")), dtype=object).copy()
    diverged = np.asarray(out.get("diverged", np.zeros(n, bool)), bool)
    finite = np.ones(n, bool)
    for k in CRITICAL_METRICS:
        if k in out:
            finite &= np.isfinite(np.asarray(out[k], np.float64))
    for mask, why in ((diverged, "diverged"), (~finite, "non-finite metrics")):
        for i in np.nonzero(mask)[0]:
            if why not in str(reason[i]):
                reason[i] = why if not reason[i] else f"{reason[i]}; {why}"
    out["success"] = np.asarray(out["success"], bool) & ~diverged & finite
    out["failure_reason"] = np.asarray([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return out


# ------------------------------------------------------------------------------------------------
# Results store
# ------------------------------------------------------------------------------------------------


def _write_json(path: str, obj) -> None:
    from hyqjax import io

    atomic_write(path, lambda f: f.write(json.dumps(obj, indent=1, default=io._default).encode()))


def default_chunk_size(devices=None) -> int:
    """Instances per chunk: 32 per CPU device, 4096 per accelerator."""
    devices = jax.local_devices() if devices is None else devices
    per = 32 if devices[0].platform == "cpu" else 4096
    return per * len(devices)


class SweepStore:
    """``DIR/manifest.json`` + ``DIR/chunks/NNNNN.npz`` (see the module docstring)."""

    def __init__(self, out_dir: str, spec: SweepSpec, chunk_size: int | None = None):
        self.dir = out_dir
        self.spec = spec
        self.path = os.path.join(out_dir, "manifest.json")
        os.makedirs(os.path.join(out_dir, "chunks"), exist_ok=True)
        if os.path.exists(self.path):
            with open(self.path) as f:
                man = json.load(f)
            if man.get("schema") != SCHEMA:
                raise StoreMismatch(f"{self.path} has schema {man.get('schema')!r}, expected {SCHEMA!r}")
            if man.get("spec_hash") != spec.spec_hash:
                raise StoreMismatch(
                    f"{out_dir} holds a different sweep (spec hash {man.get('spec_hash', '?')[:12]}, this spec "
                    f"{spec.spec_hash[:12]}); use another --out directory or remove {out_dir}")
            if chunk_size is not None and chunk_size != man["chunk_size"]:
                print(f"note: resuming with the stored chunk size {man['chunk_size']} (ignoring {chunk_size})")
            self.manifest = man
        else:
            if chunk_size is not None and chunk_size < 1:
                raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
            cs = int(chunk_size or default_chunk_size())
            self.manifest = dict(schema=SCHEMA, spec_hash=spec.spec_hash, spec=spec.to_dict(),
                                 n_instances=spec.n_instances, chunk_size=cs,
                                 n_chunks=-(-spec.n_instances // cs), chunks={},
                                 created=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"))
            _write_json(self.path, self.manifest)

    @property
    def chunk_size(self) -> int:
        return int(self.manifest["chunk_size"])

    @property
    def n_chunks(self) -> int:
        return int(self.manifest["n_chunks"])

    def chunk_range(self, c: int) -> tuple[int, int]:
        return c * self.chunk_size, min((c + 1) * self.chunk_size, self.spec.n_instances)

    def chunk_file(self, c: int) -> str:
        return os.path.join(self.dir, "chunks", f"{c:05d}.npz")

    def done(self) -> set[int]:
        return {int(c) for c in self.manifest["chunks"] if os.path.exists(self.chunk_file(int(c)))}

    def write_chunk(self, c: int, rows: dict[str, np.ndarray], wall_s: float) -> None:
        atomic_write(self.chunk_file(c), lambda f: np.savez(f, **rows))
        start, stop = self.chunk_range(c)
        self.manifest["chunks"][str(c)] = dict(file=os.path.relpath(self.chunk_file(c), self.dir), start=start,
                                               stop=stop, wall_s=round(wall_s, 3),
                                               finished=datetime.datetime.now(datetime.timezone.utc).isoformat(
                                                   timespec="seconds"))
        self.manifest["columns"] = sorted(rows)
        _write_json(self.path, self.manifest)

    def load(self) -> dict[str, np.ndarray]:
        """All finished rows, in instance order."""
        parts = []
        for c in sorted(self.done()):
            with np.load(self.chunk_file(c)) as z:
                parts.append({k: z[k] for k in z.files})
        if not parts:
            return {}
        return {k: np.concatenate([p[k] for p in parts], 0) for k in parts[0]}


def run_sweep(spec: SweepSpec, out_dir: str, chunk_size: int | None = None, max_chunks: int | None = None,
              devices=None, progress: bool = True) -> SweepStore:
    """Run (or resume) ``spec`` into ``out_dir``; at most ``max_chunks`` new chunks in this call."""
    store = SweepStore(out_dir, spec, chunk_size)
    todo = [c for c in range(store.n_chunks) if c not in store.done()]
    if max_chunks is not None:
        todo = todo[:max_chunks]
    from tqdm.auto import tqdm

    done_rows = sum(store.chunk_range(c)[1] - store.chunk_range(c)[0] for c in store.done())
    bar = tqdm(total=spec.n_instances, initial=done_rows, unit="inst", desc="sweep", disable=not progress,
               dynamic_ncols=True)
    try:
        for c in todo:
            start, stop = store.chunk_range(c)
            t0 = time.time()
            rows = spec.instance_inputs(start, stop)
            out = run_rows(rows, spec, store.chunk_size, devices)
            store.write_chunk(c, {**rows, **out}, time.time() - t0)
            bar.update(stop - start)
            bar.set_postfix(chunk=f"{c + 1}/{store.n_chunks}", ok=int(out["success"].sum()))
    finally:
        bar.close()
    return store


# ------------------------------------------------------------------------------------------------
# Summary
# ------------------------------------------------------------------------------------------------


def _levels(spec: SweepSpec, rows, axis: str):
    """Level index per row and level labels of ``axis`` (grid values, bins of a random range, or one)."""
    v = rows[axis]
    for k, vals in spec.grid:
        if k == axis:
            labels = list(vals)
            lut = {val: i for i, val in enumerate(labels)}
            return np.asarray([lut[x.item() if hasattr(x, "item") else x] for x in v], int), labels
    for k, r in spec.random:
        if k == axis:
            if AXES[k].kind == "choice":
                labels = list(r)
                return np.asarray([labels.index(str(x)) for x in v], int), labels
            lo, hi = r
            nb = spec.bins if hi > lo else 1
            edges = np.linspace(lo, hi, nb + 1)
            idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, nb - 1)
            return idx, [float(0.5 * (edges[i] + edges[i + 1])) for i in range(nb)]
    return np.zeros(len(v), int), [spec.axis_values(axis)[0]]


def _logistic_h95(h: np.ndarray, y: np.ndarray, target: float = 0.95):
    """Height where ``sigmoid(a + b h)`` (maximum likelihood, Newton) equals ``target``; None if b >= 0 or no fit."""
    if len(np.unique(h)) < 2 or y.all() or not y.any():
        return None
    x = np.stack([np.ones_like(h), h], 1)
    w = np.zeros(2)
    for _ in range(100):
        p = 1 / (1 + np.exp(-(x @ w)))
        g = x.T @ (y - p) - 1e-6 * w
        hess = (x * (p * (1 - p))[:, None]).T @ x + 1e-6 * np.eye(2)
        step = np.linalg.solve(hess, g)
        w = w + step
        if np.max(np.abs(step)) < 1e-10:
            break
    else:
        return None
    a, b = w
    if not (b < 0 and np.isfinite(a)):
        return None
    return float((math.log(target / (1 - target)) - a) / b)


def summarize_sweep(spec: SweepSpec, rows: dict[str, np.ndarray]) -> dict[str, Any]:
    """Counts, failure reasons, success maps with Wilson 95% intervals and max safe heights per reflex setting."""
    n = int(rows["index"].shape[0]) if rows else 0
    summary: dict[str, Any] = dict(n_instances=n, n_planned=spec.n_instances, spec_hash=spec.spec_hash)
    if n == 0:
        return summary
    succ = rows["success"].astype(bool)
    reasons: dict[str, int] = {}
    for r in rows["failure_reason"][~succ]:
        for part in str(r).split("; "):
            reasons[part or "unspecified"] = reasons.get(part or "unspecified", 0) + 1
    summary.update(successes=int(succ.sum()), diverged=int(rows["diverged"].sum()), failure_reasons=reasons)
    modes = sorted(set(rows["reflex"].tolist()))
    by_reflex = {}
    for r in modes:
        m = rows["reflex"] == r
        k, nn = int(succ[m].sum()), int(m.sum())
        hl, hidx = _levels(spec, rows, "height")
        curve = []
        for i, lab in enumerate(hidx):
            mm = m & (hl == i)
            kk, ni = int(succ[mm].sum()), int(mm.sum())
            if ni:
                curve.append(dict(height=float(lab), n=ni, successes=kk, rate=kk / ni,
                                  ci95=list(stepdown.wilson_interval(kk, ni))))
        h95 = None
        for c in sorted(curve, key=lambda c: c["height"]):
            if c["ci95"][0] >= 0.95:
                h95 = c["height"]
            else:
                break
        by_reflex["on" if r else "off"] = dict(
            n=nn, successes=k, rate=k / nn, ci95=list(stepdown.wilson_interval(k, nn)),
            mean_mobility=float(np.nanmean(rows["mean_mobility"][m])), height_curve=curve, h95_wilson=h95,
            h95_logistic=_logistic_h95(rows["height"][m].astype(float), succ[m].astype(float)))
    summary["by_reflex"] = by_reflex
    maps = []
    varying = set(spec.varying())
    for a, b in spec.maps:
        if a not in varying and b not in varying:
            continue
        la, lab_a = _levels(spec, rows, a)
        lb, lab_b = _levels(spec, rows, b)
        for r in modes:
            m = rows["reflex"] == r
            k = np.zeros((len(lab_a), len(lab_b)), int)
            nn = np.zeros_like(k)
            np.add.at(k, (la[m], lb[m]), succ[m].astype(int))
            np.add.at(nn, (la[m], lb[m]), 1)
            ci = np.asarray([[stepdown.wilson_interval(int(k[i, j]), int(nn[i, j])) for j in range(len(lab_b))]
                             for i in range(len(lab_a))])
            maps.append(dict(x=a, y=b, reflex=bool(r), x_levels=lab_a, y_levels=lab_b, successes=k.tolist(),
                             n=nn.tolist(), rate=np.where(nn > 0, k / np.maximum(nn, 1), np.nan).tolist(),
                             ci95_lo=ci[..., 0].tolist(), ci95_hi=ci[..., 1].tolist()))
    summary["maps"] = maps
    return summary


def plot_maps(summary: dict, path: str) -> str | None:
    """Heat maps of the success probability (cell text: rate and Wilson 95% interval)."""
    maps = summary.get("maps", [])
    if not maps:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = sorted({(m["x"], m["y"]) for m in maps}, key=lambda p: [(mm["x"], mm["y"]) for mm in maps].index(p))
    modes = sorted({m["reflex"] for m in maps})
    fig, axes = plt.subplots(len(pairs), len(modes), figsize=(4.8 * len(modes), 3.8 * len(pairs)), squeeze=False)
    im = None
    for i, p in enumerate(pairs):
        for j, r in enumerate(modes):
            ax = axes[i, j]
            mm = [m for m in maps if (m["x"], m["y"]) == p and m["reflex"] == r]
            if not mm:
                ax.axis("off")
                continue
            m = mm[0]
            rate = np.asarray(m["rate"], float).T
            im = ax.imshow(rate, origin="lower", vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
            lo, hi, nn = np.asarray(m["ci95_lo"]).T, np.asarray(m["ci95_hi"]).T, np.asarray(m["n"]).T
            for yy in range(rate.shape[0]):
                for xx in range(rate.shape[1]):
                    if nn[yy, xx]:
                        ax.text(xx, yy, f"{rate[yy, xx]:.2f}\n[{lo[yy, xx]:.2f},{hi[yy, xx]:.2f}]\nn={nn[yy, xx]}",
                                ha="center", va="center", fontsize=7)
            fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
            ax.set_xticks(range(len(m["x_levels"])), [fmt(v) for v in m["x_levels"]], fontsize=8)
            ax.set_yticks(range(len(m["y_levels"])), [fmt(v) for v in m["y_levels"]], fontsize=8)
            ax.set_xlabel(f"{p[0]} [{AXES[p[0]].unit}]")
            ax.set_ylabel(f"{p[1]} [{AXES[p[1]].unit}]")
            ax.set_title(f"reflex {'on' if r else 'off'}")
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.8, label="success probability")
    fig.suptitle("Step-down success probability (Wilson 95% intervals)")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_height_curves(summary: dict, path: str) -> str | None:
    br = summary.get("by_reflex")
    if not br:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in br.items():
        c = r["height_curve"]
        if not c:
            continue
        h = np.asarray([x["height"] for x in c])
        p = np.asarray([x["rate"] for x in c])
        lo = np.asarray([x["ci95"][0] for x in c])
        hi = np.asarray([x["ci95"][1] for x in c])
        ax.errorbar(h * 100, p, yerr=[p - lo, hi - p], marker="o", capsize=3, label=f"reflex {name}")
    ax.axhline(0.95, color="k", lw=0.6, ls=":")
    ax.set_xlabel("step height [cm]")
    ax.set_ylabel("success probability")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_outputs(store: SweepStore) -> dict[str, Any]:
    """``instances.csv`` (one row per finished instance), ``summary.json`` and the figures."""
    import csv

    rows = store.load()
    summary = summarize_sweep(store.spec, rows)
    if rows:
        cols = [k for k in rows if rows[k].ndim == 1]
        tmp = os.path.join(store.dir, f"instances.csv.tmp{os.getpid()}")
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(cols)
            for i in range(rows["index"].shape[0]):
                w.writerow([rows[k][i].item() if hasattr(rows[k][i], "item") else rows[k][i] for k in cols])
        os.replace(tmp, os.path.join(store.dir, "instances.csv"))
        summary["figures"] = [p for p in (plot_maps(summary, os.path.join(store.dir, "success_maps.png")),
                                          plot_height_curves(summary, os.path.join(store.dir, "success_height.png")))
                              if p]
    summary["complete"] = len(store.done()) == store.n_chunks
    _write_json(os.path.join(store.dir, "summary.json"), summary)
    return summary


def format_summary(summary: dict) -> str:
    lines = [f"{summary.get('n_instances', 0)}/{summary.get('n_planned', 0)} instances, "
             f"{summary.get('successes', 0)} successes, {summary.get('diverged', 0)} diverged"]
    for name, r in summary.get("by_reflex", {}).items():
        lo, hi = r["ci95"]
        h95w, h95l = r["h95_wilson"], r["h95_logistic"]
        lines.append(f"reflex {name:>3}: success {r['successes']}/{r['n']} = {r['rate']:.2f} [{lo:.2f}, {hi:.2f}], "
                     f"mean mobility {r['mean_mobility']:.3f}, h95 (Wilson) "
                     f"{'-' if h95w is None else f'{h95w:.3f} m'}, h95 (logistic) "
                     f"{'-' if h95l is None else f'{h95l:.3f} m'}")
        for c in r["height_curve"]:
            lines.append(f"    h = {c['height']:.3f} m: {c['successes']}/{c['n']} [{c['ci95'][0]:.2f}, "
                         f"{c['ci95'][1]:.2f}]")
    if summary.get("failure_reasons"):
        lines.append("failure reasons: " + ", ".join(f"{k} x{v}" for k, v in
                                                     sorted(summary["failure_reasons"].items(), key=lambda t: -t[1])))
    return "\n".join(lines)


__all__ = ["AXES", "SCHEMA", "SpecError", "StoreMismatch", "SweepSpec", "SweepStore", "build_scenario",
           "count_outcomes", "default_chunk_size", "format_summary", "load_spec", "run_rows", "run_sweep",
           "sensed_controller", "summarize_sweep", "write_outputs"]
