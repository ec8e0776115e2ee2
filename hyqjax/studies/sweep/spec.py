"""The sweep specification: grid / random / fixed sections over the axes of :mod:`hyqjax.studies.sweep.axes`, validation.

A :class:`SweepSpec` names, for every *axis* of :data:`AXES` (step height, rough terrain amplitude,
friction, payload, initial pose, foot sequence, joint PD gains, lateral push, sensor noise, control
latency, reflex on/off and every :class:`hyqjax.reflex.step.ReflexParams` field), either

* ``grid``: a list of values; the sweep runs the Cartesian product of all grid axes, or
* ``random``: a range ``[lo, hi]`` (uniform) or, for a choice axis, a list of options, drawn per
  instance, ``samples`` draws per grid point, or
* ``fixed``: one value; axes named nowhere take their default (:data:`AXES`).

Instance ``i`` is grid point ``g = i // samples`` and draw ``s = i % samples``. Its random inputs come
from ``numpy.random.default_rng([seed, key])`` with ``key = s`` (``paired = true``, the default: every
grid point sees the same ``samples`` random draws, i.e. common random numbers, so reflex on/off or
two heights are compared on identical payloads, frictions, ...) or ``key = i`` (``paired = false``).
Either way the inputs of an instance depend on the sweep seed and its index only, never on chunking.

Validation (:meth:`SweepSpec.from_dict`, :func:`load_spec`) needs no JAX compile: every error is a
:class:`SpecError` whose message names the field and its allowed range.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import threading
from typing import Any

import numpy as np

from hyqjax.reflex import step as hreflex
from hyqjax.sim import model as hmodel
from hyqjax.studies.sweep.axes import AXES, SENSOR_AXES, Axis, SpecError, axis_value, get_axis  # noqa: F401

_TOP_KEYS = ("seed", "samples", "paired", "duration", "control_dt", "max_tilt", "min_progress", "blocks",
             "grid", "random", "fixed", "maps", "bins", "preset")


def _preset(name, axes: dict) -> str:
    """A crawl preset's name (``""``: none), checked by name and kind; a per-leg preset whose per-leg field is also
    an axis is refused."""
    if name in ("", None):
        return ""
    from hyqjax.presets import registry as presets

    if not isinstance(name, str):
        raise SpecError(f"preset must be the name of a crawl preset ({', '.join(presets.names('crawl'))}), "
                        f"got {name!r}")
    try:
        p = presets.check_kind(name, "crawl", "preset")
    except ValueError as e:
        raise SpecError(str(e)) from None
    clash = sorted(k.replace(".", "_") for k in p.scheduled_fields if k.replace(".", "_") in axes)
    if clash:
        raise SpecError(f"axis {clash[0]!r}: preset {name} sets it per leg; leave the axis out")
    return name


_BUILDING = threading.local()  # inside SweepSpec.from_dict (which validates) on this thread


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
      duration, control_dt, max_tilt, min_progress: :class:`hyqjax.studies.stepdown.StepdownConfig`.
      blocks: ``(n_blocks_x, n_blocks_y)`` rough-terrain grid per level (0: none).
      maps: axis pairs of the success maps.
      bins: bins of a random float axis in maps and height curves.
      preset: the crawl preset (:mod:`hyqjax.presets`) every instance runs, its values wherever no axis sets the
        field ("" : the paper's crawl, ``CrawlParams.make()``); a per-leg preset's per-leg fields take no axis.
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
    preset: str = ""

    def __post_init__(self):
        """Direct construction (``SweepSpec(...)``, ``dataclasses.replace``) is validated as :meth:`from_dict` is."""
        if getattr(_BUILDING, "depth", 0):
            return
        try:
            d = self.to_dict()
        except (TypeError, ValueError):
            raise SpecError("SweepSpec(grid=..., random=..., fixed=...) takes ((axis, value(s)), ...) pairs; build a "
                            "spec from a dict with SweepSpec.from_dict") from None
        SweepSpec.from_dict(d)

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
                get_axis(k, f"[{name}]")
                if k in seen:
                    raise SpecError(f"axis {k!r} appears in both [{seen[k]}] and [{name}]; name it once")
                seen[k] = name
            return sec

        grid = []
        for k, vals in sorted(section("grid").items()):
            a = AXES[k]
            if not isinstance(vals, (list, tuple)) or not vals:
                raise SpecError(f"[grid] {k} must be a non-empty list of values, got {vals!r}")
            norm = tuple(axis_value(a, v, f"[grid] {k}") for v in vals)
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
                random.append((k, tuple(axis_value(a, v, f"[random] {k}") for v in rng)))
                continue
            if not isinstance(rng, (list, tuple)) or len(rng) != 2:
                raise SpecError(f"[random] {k} must be [lo, hi] within [{a.lo}, {a.hi}] {a.unit}, got {rng!r}")
            lo, hi = (axis_value(a, v, f"[random] {k}") for v in rng)
            if lo > hi:
                raise SpecError(f"[random] {k}: lo={lo} must be <= hi={hi}")
            random.append((k, (lo, hi)))
        fixed = tuple((k, axis_value(AXES[k], v, f"[fixed] {k}")) for k, v in sorted(section("fixed").items()))

        blocks = d.get("blocks", [0, 0])
        if (not isinstance(blocks, (list, tuple)) or len(blocks) != 2
                or any(isinstance(b, bool) or not isinstance(b, int) or not 0 <= b <= 20 for b in blocks)):
            raise SpecError(f"blocks must be [n_blocks_x, n_blocks_y], integers in [0, 20], got {blocks!r}")
        maps = d.get("maps", [["height", "friction"], ["height", "payload_mass"]])
        if not isinstance(maps, (list, tuple)) or any(not isinstance(p, (list, tuple)) or len(p) != 2 for p in maps):
            raise SpecError(f"maps must be a list of [axis, axis] pairs, got {maps!r}")
        for p in maps:
            for k in p:
                get_axis(k, "maps")
        _BUILDING.depth = getattr(_BUILDING, "depth", 0) + 1  # validated here, not again in __post_init__
        try:
            spec = SweepSpec(
                grid=tuple(grid), random=tuple(random), fixed=fixed,
                samples=num("samples", 1, 10**7, 1, integer=True), seed=num("seed", 0, 2**63 - 1, 0, integer=True),
                paired=bool(d.get("paired", True)), duration=num("duration", 0.01, 600.0, 18.0),
                control_dt=num("control_dt", 1e-4, 0.02, 0.002), max_tilt=num("max_tilt", 0.01, 1.5, 0.4),
                min_progress=num("min_progress", -10.0, 10.0, 0.5), blocks=(int(blocks[0]), int(blocks[1])),
                maps=tuple((str(a), str(b)) for a, b in maps), bins=num("bins", 1, 100, 4, integer=True),
                preset=_preset(d.get("preset", ""), seen),
            )
        finally:
            _BUILDING.depth -= 1
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
        spec._check_reflex_stability()
        return spec

    def to_dict(self) -> dict:
        """Canonical plain-JSON form (what the spec hash covers; ``preset`` only when set, so a spec without one
        keeps the hash it always had)."""
        return dict(**({"preset": self.preset} if self.preset else {}),
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
        return any(self.axis_max(k) > 0 for k in SENSOR_AXES)

    @property
    def max_delay(self) -> int:
        return int(round(self.axis_max("latency") / self.control_dt))

    def stepdown_config(self) -> "stepdown.StepdownConfig":  # noqa: F821
        from hyqjax.studies import stepdown  # MJX: imported when a sweep runs, not when a spec is checked

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

    def _check_reflex_stability(self):
        """``ReflexParams.validate(dt=control_dt)`` at the spec's worst corner (largest gains, smallest minimum
        damping), which bounds every instance: the reflex's step-size condition ``dt lambda_max < 2``."""
        from hyqjax.core.params import ParameterError

        worst = {f.name: float(self.axis_values(f"reflex_{f.name}")[0]) for f in dataclasses.fields(hreflex.ReflexParams)}
        for n in ("k_x", "k_x_max", "k_base", "k_kl"):
            worst[n] = max(float(v) for v in self.axis_values(f"reflex_{n}"))
        for n in ("d_sw_min", "d_st_min"):
            worst[n] = min(float(v) for v in self.axis_values(f"reflex_{n}"))
        for lo, hi in (("d_sw_min", "d_sw_max"), ("d_st_min", "d_st_max"), ("m_min", "m_max")):
            worst[hi] = max(worst[hi], max(float(v) for v in self.axis_values(f"reflex_{hi}")))
        try:
            hreflex.ReflexParams(**worst).validate(dt=self.control_dt)
        except ParameterError as e:
            raise SpecError(f"reflex_{e.param}: {e} (at the spec's largest gains and smallest damping: "
                            f"{', '.join(f'reflex_{k}={worst[k]:g}' for k in ('k_x', 'k_base', 'k_kl', 'd_sw_min', 'd_st_min'))})") from None

    def preset_defaults(self) -> dict:
        """``{axis: value}`` of the preset's shared reflex values (``reflex_<field>``), the values of the axes the
        spec does not name (empty without a preset: the axes' own defaults, Table I)."""
        if not self.preset:
            return {}
        from hyqjax.presets import registry as presets

        vals = presets.get(self.preset).values.get("reflex", {})
        return {f"reflex_{k}": float(v) for k, v in vals.items() if f"reflex_{k}" in AXES}

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
        defaults = self.preset_defaults()
        for k, a in AXES.items():
            if k not in rows:
                rows[k] = np.full(n, defaults.get(k, a.default), dtype=object)
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
    return SweepSpec.from_dict(load_spec_dict(path))


def load_spec_dict(path: str) -> dict:
    """The table of a ``.toml`` / ``.json`` spec file, unvalidated. Every problem with the file (missing, a
    directory, not UTF-8, malformed, not a table) is a :class:`SpecError` naming the file."""
    if not path.endswith((".toml", ".json")):
        raise SpecError(f"SPEC {path}: a sweep spec file must end in .toml or .json")
    if os.path.isdir(path):
        raise SpecError(f"SPEC {path} is a directory; give a .toml or .json sweep spec file")
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except OSError as e:
        raise SpecError(f"SPEC {path}: cannot read the file ({e.strerror})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise SpecError(f"SPEC {path}: not UTF-8 text (byte {e.start}); save the file as UTF-8") from None
    if path.endswith(".toml"):
        import tomllib

        try:
            d = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise SpecError(f"SPEC {path}: invalid TOML: {e}") from None
    else:
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise SpecError(f"SPEC {path}: invalid JSON: {e}") from None
    if not isinstance(d, dict):
        raise SpecError(f"SPEC {path}: the top level must be a table/object of spec keys, got a {type(d).__name__}")
    return d
