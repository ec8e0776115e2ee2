"""The command envelope of the bound: fall rate and worst yaw error over a grid of commands.

A map (:class:`EnvelopeSpec`) is a grid of commands, forward speed x yaw rate x lateral speed, with
``instances`` randomised instances per command (initial apex perturbation, friction and payload uniform in
their ranges, the same draws for every command: common random numbers), each run for ``duration`` s with the
command ramped in over ``ramp_time`` s (:func:`hyqjax.bounding.tracking.run_batch`, one compiled batch, MJX's
JAX or Warp implementation). Per command (:func:`summarise`):

* falls and divergences (counted failures with their reasons), the fall rate (failures / n) and its Wilson
  95% interval (:func:`hyqjax.studies.statistics.wilson_interval`);
* the worst and the 95th-percentile yaw error over the surviving instances (deg), and the rate of instances
  whose yaw error exceeds 4 deg (survivors) with its Wilson interval;
* the mean settled forward / lateral speed error.

:func:`safe_area` is the area of the (speed, yaw-rate) plane, per lateral speed, whose commands keep the fall
rate below a threshold (1%): each grid command owns the rectangle between the midpoints to its neighbours
(half cells at the edges), so the area has units m/s x rad/s and does not depend on the grid spacing's
offset. Reported twice: by the point estimate (``rate < threshold``) and by the Wilson upper bound (a
conservative area; it needs ``n >= 370`` instances per command with no fall to be non-zero at 1%).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from hyqjax.bounding import batch as bbatch
from hyqjax.bounding import tracking
from hyqjax.bounding.params import BoundingParams, default_params
from hyqjax.studies import statistics

YAW_LIMIT_DEG = 4.0


def _axis(name, v, lim):
    a = np.atleast_1d(np.asarray(v, np.float64))
    if a.ndim != 1 or a.size < 1 or not np.all(np.isfinite(a)) or np.any(np.abs(a) > lim + 1e-9):
        raise bbatch.SettingError(name, f"{name} must be finite values in [-{lim:g}, {lim:g}], got {a.tolist()}")
    if np.any(np.diff(np.sort(a)) <= 0):
        raise bbatch.SettingError(name, f"{name} values must be distinct, got {a.tolist()}")
    return tuple(float(x) for x in np.sort(a))


@dataclasses.dataclass(frozen=True)
class EnvelopeSpec:
    """A command map (see the module docstring); validated at construction (:class:`SettingError` naming the
    setting)."""

    speeds: tuple = tuple(np.round(np.arange(-1.0, 1.2001, 0.2), 3))
    yaw_rates: tuple = tuple(np.round(np.arange(-1.0, 1.0001, 0.25), 3))
    lateral_speeds: tuple = (0.0,)
    instances: int = 32
    friction: tuple = (0.4, 1.0)
    payload: tuple = (0.0, 15.0)
    duration: float = 8.0
    ramp_time: float = 1.0
    seed: int = 0

    def __post_init__(self):
        object.__setattr__(self, "speeds", _axis("speeds", self.speeds, 1.5))
        object.__setattr__(self, "yaw_rates", _axis("yaw_rates", self.yaw_rates, 1.5))
        object.__setattr__(self, "lateral_speeds", _axis("lateral_speeds", self.lateral_speeds, 0.5))
        if isinstance(self.instances, bool) or not isinstance(self.instances, (int, np.integer)) or not (
                1 <= self.instances <= 100000):
            raise bbatch.SettingError("instances", f"instances must be an int in [1, 100000], got {self.instances!r}")
        bbatch.Randomisation(friction=tuple(self.friction), payload=tuple(self.payload))
        if not (isinstance(self.seed, (int, np.integer)) and 0 <= self.seed < 2**32):
            raise bbatch.SettingError("seed", f"seed must be an int in [0, 2^32), got {self.seed!r}")
        if not (np.isfinite(self.duration) and 0.4 <= self.duration <= bbatch.MAX_DURATION):
            raise bbatch.SettingError("duration",
                                      f"duration must be in [0.4, {bbatch.MAX_DURATION:g}] s, got {self.duration}")
        if not (np.isfinite(self.ramp_time) and 0 <= self.ramp_time <= 10):
            raise bbatch.SettingError("ramp_time", f"ramp_time must be in [0, 10] s, got {self.ramp_time}")

    @property
    def commands(self) -> np.ndarray:
        """``(C, 3)`` grid commands (speed, yaw rate, lateral speed), lateral slowest, speed fastest."""
        lat, yr, sp = np.meshgrid(self.lateral_speeds, self.yaw_rates, self.speeds, indexing="ij")
        return np.stack([sp.ravel(), yr.ravel(), lat.ravel()], -1)

    @property
    def size(self) -> int:
        return len(self.commands) * self.instances

    def batch(self, base: BoundingParams | None = None) -> bbatch.Batch:
        """Every command x ``instances`` (command-major); the randomisation is drawn once for ``instances`` and
        repeated for every command (``make_batch``'s ``n_unique``)."""
        base = base or default_params()
        cmds = np.repeat(self.commands, self.instances, 0)
        p = bbatch.command_params(base, cmds, self.ramp_time)
        return bbatch.make_batch(p, seed=int(self.seed), n_unique=int(self.instances),
                                 rand=bbatch.Randomisation(friction=tuple(self.friction), payload=tuple(self.payload)))

    def to_dict(self) -> dict:
        return dict(dataclasses.asdict(self), friction=list(self.friction), payload=list(self.payload))


def run(spec: EnvelopeSpec, base: BoundingParams | None = None, impl: str = "auto", max_batch: int = 16384,
        progress=None) -> dict[str, np.ndarray]:
    """Simulate the map: per-instance columns of :func:`hyqjax.bounding.tracking.run_batch` plus the command
    (``speed_cmd``, ``yaw_rate_cmd``, ``lateral_cmd``), ``friction`` and ``payload``."""
    batch = spec.batch(base)
    cols = tracking.run_batch(batch, spec.duration, impl, max_batch=max_batch, progress=progress)
    cmd = np.asarray(batch.params.command.velocity, np.float64)
    cols.update(speed_cmd=cmd[:, 0], lateral_cmd=cmd[:, 1],
                yaw_rate_cmd=np.asarray(batch.params.command.yaw_rate, np.float64),
                friction=np.asarray(batch.terrain.friction, np.float64),
                payload=np.asarray(batch.terrain.payload_mass, np.float64))
    return cols


def group_summary(cols: dict, mask=None) -> dict:
    """Failures (with reasons), fall rate and Wilson interval, yaw error (worst, 95th percentile, rate above
    4 deg with its Wilson interval) and settled speed errors of the instances ``mask`` (default: all)."""
    m = np.ones(len(cols["success"]), bool) if mask is None else np.asarray(mask, bool)
    n = int(m.sum())
    ok = np.asarray(cols["success"], bool)[m]
    fails = int(n - ok.sum())
    reasons = {r: int(np.asarray(cols[r], bool)[m].sum()) for r in ("fell_low_trunk", "fell_roll", "fell_pitch",
                                                                     "diverged")}
    yaw = np.asarray(cols["yaw_error_max_deg"], np.float64)[m][ok]
    over = int(np.sum(yaw >= YAW_LIMIT_DEG))
    out = dict(n=n, failures=fails, reasons={k: v for k, v in reasons.items() if v},
               fall_rate=fails / n if n else None, fall_rate_ci95=list(statistics.wilson_interval(fails, n)),
               yaw_error_worst_deg=float(yaw.max()) if yaw.size else None,
               yaw_error_p95_deg=float(np.percentile(yaw, 95)) if yaw.size else None,
               yaw_over_4deg=over, yaw_over_4deg_rate=over / yaw.size if yaw.size else None,
               yaw_over_4deg_ci95=list(statistics.wilson_interval(over, yaw.size)))
    if "speed_cmd" in cols:
        se = (np.asarray(cols["speed_mean"]) - np.asarray(cols["speed_cmd"]))[m][ok]
        le = (np.asarray(cols["lateral_speed_mean"]) - np.asarray(cols["lateral_cmd"]))[m][ok]
        se, le = se[np.isfinite(se)], le[np.isfinite(le)]
        out.update(speed_error_mean_abs=float(np.mean(np.abs(se))) if se.size else None,
                   lateral_error_mean_abs=float(np.mean(np.abs(le))) if le.size else None)
    return out


def summarise(spec: EnvelopeSpec, cols: dict) -> list[dict]:
    """One :func:`group_summary` per grid command (with ``speed``, ``yaw_rate``, ``lateral``), in
    :attr:`EnvelopeSpec.commands` order."""
    out = []
    k = spec.instances
    for i, (v, w, lat) in enumerate(spec.commands):
        m = np.zeros(len(cols["success"]), bool)
        m[i * k:(i + 1) * k] = True
        out.append(dict(speed=float(v), yaw_rate=float(w), lateral=float(lat), **group_summary(cols, m)))
    return out


def cell_widths(values) -> np.ndarray:
    """Width owned by each grid value: from the midpoint to its left neighbour to the midpoint to its right one
    (half cells at the ends; a single value owns width 0)."""
    v = np.asarray(values, np.float64)
    if v.size == 1:
        return np.zeros(1)
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[mid[0] - v[0]], np.diff(mid), [v[-1] - mid[-1]]])


def safe_area(spec: EnvelopeSpec, per_command: list[dict], threshold: float = 0.01) -> dict:
    """Area of the (speed, yaw-rate) plane whose commands keep the fall rate below ``threshold``, per lateral speed
    (``point``: ``rate < threshold``; ``wilson``: the Wilson upper bound below it), and the map's total area."""
    dv, dw = cell_widths(spec.speeds), cell_widths(spec.yaw_rates)
    out = dict(threshold=threshold, total_area=float(dv.sum() * dw.sum()), per_lateral=[])
    for lat in spec.lateral_speeds:
        pt = wi = 0.0
        for c in per_command:
            if c["lateral"] != lat:
                continue
            a = dv[spec.speeds.index(c["speed"])] * dw[spec.yaw_rates.index(c["yaw_rate"])]
            pt += a if c["fall_rate"] < threshold else 0.0
            wi += a if c["fall_rate_ci95"][1] < threshold else 0.0
        out["per_lateral"].append(dict(lateral=lat, area_point=pt, area_wilson=wi))
    out["area_point"] = float(np.mean([r["area_point"] for r in out["per_lateral"]]))
    out["area_wilson"] = float(np.mean([r["area_wilson"] for r in out["per_lateral"]]))
    return out


def grids(spec: EnvelopeSpec, per_command: list[dict], key: str) -> np.ndarray:
    """``(L, Y, S)`` array of ``per_command[key]`` (NaN where None) over lateral x yaw rate x speed."""
    a = np.array([np.nan if c[key] is None else c[key] for c in per_command], np.float64)
    return a.reshape(len(spec.lateral_speeds), len(spec.yaw_rates), len(spec.speeds))


def figure(spec: EnvelopeSpec, maps: dict[str, list[dict]], path: str, title: str = "") -> str:
    """Fall rate and worst yaw error over (speed, yaw rate), one row per map (e.g. before / after), one pair of
    columns per lateral speed; cells with a fall rate below 1% are outlined."""
    from hyqjax.bounding import plots

    plt = plots._plt()
    nl = len(spec.lateral_speeds)
    fig, axes = plt.subplots(len(maps), 2 * nl, figsize=(5.2 * 2 * nl, 3.9 * len(maps)), squeeze=False)
    ext = _extent(spec.speeds) + _extent(spec.yaw_rates)
    for r, (name, pc) in enumerate(maps.items()):
        fr, yw = grids(spec, pc, "fall_rate"), grids(spec, pc, "yaw_error_worst_deg")
        for j in range(nl):
            ax = axes[r, 2 * j]
            im = ax.imshow(fr[j], origin="lower", extent=ext, aspect="auto", cmap="Reds", vmin=0, vmax=1)
            fig.colorbar(im, ax=ax, label="fall rate")
            _outline(ax, spec, fr[j] < 0.01)
            ax.set_title(f"{name}: fall rate (lateral {spec.lateral_speeds[j]:g} m/s)", fontsize=9)
            ax = axes[r, 2 * j + 1]
            im = ax.imshow(np.minimum(yw[j], 20.0), origin="lower", extent=ext, aspect="auto", cmap="viridis",
                           vmin=0, vmax=20)
            fig.colorbar(im, ax=ax, label="worst yaw error [deg] (clipped at 20)")
            if np.any(np.isfinite(yw[j])):
                ax.contour(spec.speeds, spec.yaw_rates, np.nan_to_num(yw[j], nan=99.0), levels=[YAW_LIMIT_DEG],
                           colors="w", linewidths=1.2)
            ax.set_title(f"{name}: worst yaw error, 4 deg contour", fontsize=9)
            for a in axes[r, 2 * j:2 * j + 2]:
                a.set_xlabel("forward speed command [m/s]")
                a.set_ylabel("yaw-rate command [rad/s]")
    fig.suptitle(title or f"Bounding command envelope ({spec.instances} instances per command, friction "
                          f"{spec.friction[0]:g}-{spec.friction[1]:g}, payload {spec.payload[0]:g}-"
                          f"{spec.payload[1]:g} kg,"
                          f" {spec.duration:g} s)", fontsize=10)
    return plots._save(fig, path)


def _extent(v):
    w = cell_widths(v) if len(v) > 1 else np.array([0.1])
    return [v[0] - w[0], v[-1] + w[-1]] if len(v) > 1 else [v[0] - 0.05, v[0] + 0.05]


def _outline(ax, spec, safe):
    from matplotlib.patches import Rectangle

    dv, dw = cell_widths(spec.speeds), cell_widths(spec.yaw_rates)
    for i, w in enumerate(spec.yaw_rates):
        for k, v in enumerate(spec.speeds):
            if safe[i, k]:
                lo_v = v - (dv[k] if k == 0 else 0.5 * (v - spec.speeds[k - 1]))
                hi_v = v + (dv[k] if k == len(spec.speeds) - 1 else 0.5 * (spec.speeds[k + 1] - v))
                lo_w = w - (dw[i] if i == 0 else 0.5 * (w - spec.yaw_rates[i - 1]))
                hi_w = w + (dw[i] if i == len(spec.yaw_rates) - 1 else 0.5 * (spec.yaw_rates[i + 1] - w))
                ax.add_patch(Rectangle((lo_v, lo_w), hi_v - lo_v, hi_w - lo_w, fill=False, ec="k", lw=0.6))
