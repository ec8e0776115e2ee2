"""Per-instance and per-group metrics of a bounding batch, all on the simulator's ground truth.

* **yaw error** ``|wrap(psi^d(t) - psi(t))|`` (deg): max and RMS over the run, ``psi^d`` the integral
  of the ramped yaw-rate command from the initial heading (the paper's Fig. 4 quantity; HyQ: always
  below 4 deg);
* **speed error**: per gait cycle, the mean forward speed in the heading frame (displacement over
  one period / T) minus the commanded speed; mean |error| and RMS over the cycles after ``settle`` s;
* **yaw-rate error**: per cycle mean yaw rate minus the command;
* **side slip**: ``|mean lateral speed|`` in the heading frame over the settled cycles (outward drift in a turn);
* **periodicity residual**: ``||W (s_{k+1} - s_k)||`` of consecutive apex states (Eq. C2's scaling),
  median over the settled cycles;
* **failures**: a fall (:class:`hyqjax.bounding.falls.FallMetrics`) or a diverged simulation
  (non-finite state / speed limit), whichever came first, as boolean fields of :class:`InstanceResult`
  with the time; failed instances are counted, never dropped, and left out of the tracking errors.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from hyqjax.bounding import cycle as bc
from hyqjax.bounding.batch import Batch

#: The failure reasons, the boolean fields of :class:`InstanceResult` (at most one is set).
FAIL_REASONS = ("fell_low_trunk", "fell_roll", "fell_pitch", "diverged")


@dataclasses.dataclass(frozen=True)
class InstanceResult:
    """One instance's outcome (host values; ``None`` where undefined, e.g. no settled cycle before a fall).

    Attributes:
      success: no fall and no divergence.  fell_low_trunk, fell_roll, fell_pitch, diverged: the first failure's
        cause.  fail_time: its time (s).
      yaw_error_max_deg, yaw_error_rms_deg: yaw error over the run until a failure.
      speed_cmd, yaw_rate_cmd: the command.  speed_mean, yaw_rate_mean, lateral_speed_mean: per-cycle means.
      speed_error_mean_abs, speed_error_rms, yaw_rate_error_rms: per-cycle tracking errors.
      periodicity_residual: median apex-to-apex residual.  min_height, max_roll_deg, max_pitch_deg: extremes.
      friction, payload, push: the instance's randomised inputs (push: lateral force, N).
    """

    success: bool
    fell_low_trunk: bool
    fell_roll: bool
    fell_pitch: bool
    diverged: bool
    fail_time: float | None
    yaw_error_max_deg: float | None
    yaw_error_rms_deg: float | None
    speed_cmd: float
    yaw_rate_cmd: float
    speed_mean: float | None
    speed_error_mean_abs: float | None
    speed_error_rms: float | None
    lateral_speed_mean: float | None
    yaw_rate_mean: float | None
    yaw_rate_error_rms: float | None
    periodicity_residual: float | None
    min_height: float | None = None
    max_roll_deg: float | None = None
    max_pitch_deg: float | None = None
    friction: float | None = None
    payload: float | None = None
    push: float | None = None

    @property
    def fail_reasons(self) -> tuple[str, ...]:
        return tuple(r for r in FAIL_REASONS if getattr(self, r))

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Summary:
    """A batch's outcome: one :class:`InstanceResult` per instance, the number of failures and their reasons."""

    instances: list
    n: int
    falls: int
    fail_reasons: dict

    def to_dict(self) -> dict:
        return dict(instances=[p.to_dict() for p in self.instances], n=self.n, falls=self.falls,
                    fail_reasons=self.fail_reasons)


def wrap_angle(a):
    """Angle wrapped to ``[-pi, pi)``."""
    return (a + np.pi) % (2 * np.pi) - np.pi


def per_cycle(trace: dict, period: float, control_dt: float = 0.002):
    """Per gait cycle, from the trace samples at the apexes (``t = k T``; ``trace`` arrays are ``(B, N, ...)``):
    ``(apex_index (K,), v_fwd, v_lat, yaw_rate)``, the last three ``(B, K - 1)``: the mean forward and lateral speed in the
    heading frame (displacement over one period / T, heading at mid-cycle) and the mean yaw rate."""
    t = trace["t"][0]
    idx = np.nonzero(np.abs(t - np.round(t / period) * period) < 0.5 * control_dt)[0]
    pos = trace["pos"][:, idx]
    yaw_a = np.unwrap(trace["rpy"][:, idx, 2], axis=1)
    dpos = np.diff(pos, axis=1)
    heading = yaw_a[:, :-1] + 0.5 * np.diff(yaw_a, axis=1)
    v_fwd = (np.cos(heading) * dpos[..., 0] + np.sin(heading) * dpos[..., 1]) / period
    v_lat = (-np.sin(heading) * dpos[..., 0] + np.cos(heading) * dpos[..., 1]) / period
    return idx, v_fwd, v_lat, np.diff(yaw_a, axis=1) / period


def summarise(res, trace, batch: Batch, control_dt: float = 0.002, settle: float | None = None) -> Summary:
    """Per-instance results and the failure count of a rollout (``res``, its NumPy ``trace``) of ``batch``."""
    period = float(np.asarray(batch.params.gait.period).reshape(-1)[0])
    ramp = np.asarray(batch.params.command.ramp_time, np.float64)
    t = trace["t"]  # (B, N)
    b, n = t.shape
    settle = float(np.max(ramp)) + 1.0 if settle is None else settle
    diverged = np.asarray(res.diverged)
    fm = res.metrics
    fall_tick = np.asarray(fm.fall_tick)
    causes = dict(fell_low_trunk=np.asarray(fm.low_trunk), fell_roll=np.asarray(fm.roll),
                  fell_pitch=np.asarray(fm.pitch))
    flags, fail_time = [], []
    for i in range(b):
        f = dict.fromkeys(FAIL_REASONS, False)
        if diverged[i] and (fall_tick[i] < 0 or res.diverged_tick[i] <= fall_tick[i]):
            f["diverged"] = True
            fail_time.append(float(np.asarray(res.diverged_tick)[i] + 1) * control_dt)
        elif fall_tick[i] >= 0:
            f.update({k: bool(v[i]) for k, v in causes.items()})
            fail_time.append(float(fall_tick[i] + 1) * control_dt)
        else:
            fail_time.append(None)
        flags.append(f)
    ok = np.array([not any(f.values()) for f in flags])
    yaw = trace["rpy"][..., 2]
    yaw_err = np.degrees(np.abs(wrap_angle(trace["yaw_des"] - yaw)))
    idx, v_fwd, v_lat, yaw_rate_c = per_cycle(trace, period, control_dt)
    ta = t[0, idx]
    mid = 0.5 * (ta[:-1] + ta[1:])
    vdes = np.stack([np.interp(mid, t[i], trace["v_des"][i, :, 0]) for i in range(b)])
    yrdes = np.stack([np.interp(mid, t[i], trace["yaw_rate_des"][i]) for i in range(b)])
    settled = ta[:-1] >= settle
    apex = trace["apex"][:, idx]
    resid = np.linalg.norm((apex[:, 1:] - apex[:, :-1]) / bc.RESIDUAL_SCALE, axis=-1)
    per = []
    for i in range(b):
        alive = ta[1:] <= (fail_time[i] if fail_time[i] is not None else np.inf)
        sel = settled & alive
        se = v_fwd[i, sel] - vdes[i, sel]
        ye = yaw_rate_c[i, sel] - yrdes[i, sel]
        alive_t = t[i] <= (fail_time[i] if fail_time[i] is not None else np.inf)
        per.append(InstanceResult(
            success=bool(ok[i]), **flags[i], fail_time=fail_time[i],
            yaw_error_max_deg=float(np.max(yaw_err[i, alive_t])) if alive_t.any() else None,
            yaw_error_rms_deg=float(np.sqrt(np.mean(yaw_err[i, alive_t] ** 2))) if alive_t.any() else None,
            speed_cmd=float(np.asarray(batch.params.command.velocity)[i, 0]),
            yaw_rate_cmd=float(np.asarray(batch.params.command.yaw_rate)[i]),
            speed_mean=float(np.mean(v_fwd[i, sel])) if sel.any() else None,
            speed_error_mean_abs=float(np.mean(np.abs(se))) if sel.any() else None,
            speed_error_rms=float(np.sqrt(np.mean(se**2))) if sel.any() else None,
            lateral_speed_mean=float(np.mean(v_lat[i, sel])) if sel.any() else None,
            yaw_rate_mean=float(np.mean(yaw_rate_c[i, sel])) if sel.any() else None,
            yaw_rate_error_rms=float(np.sqrt(np.mean(ye**2))) if sel.any() else None,
            periodicity_residual=float(np.median(resid[i, sel])) if sel.any() else None,
            min_height=float(np.asarray(fm.min_z)[i]),
            max_roll_deg=float(np.degrees(np.asarray(fm.max_roll)[i])),
            max_pitch_deg=float(np.degrees(np.asarray(fm.max_pitch)[i])),
            friction=float(np.asarray(batch.terrain.friction)[i]),
            payload=float(np.asarray(batch.terrain.payload_mass)[i]),
            push=float(np.asarray(batch.push.force)[i, 1]),
        ))
    return Summary(instances=per, n=b, falls=int((~ok).sum()),
                   fail_reasons={r: sum(f[r] for f in flags) for r in FAIL_REASONS if any(f[r] for f in flags)})


def aggregate(per: list[InstanceResult]) -> dict:
    """Aggregate instances: failures (count, sorted reasons) and the mean / worst tracking errors over the
    surviving instances (a JSON row)."""
    def vals(key):
        return np.array([getattr(p, key) for p in per if getattr(p, key) is not None and p.success], np.float64)

    out = dict(n=len(per), falls=sum(not p.success for p in per),
               fail_reasons=sorted({r for p in per for r in p.fail_reasons}),
               failure_reasons={r: n for r in FAIL_REASONS if (n := sum(r in p.fail_reasons for p in per))})
    for key in ("yaw_error_max_deg", "yaw_error_rms_deg", "speed_error_mean_abs", "speed_error_rms",
                "yaw_rate_error_rms", "periodicity_residual"):
        v = vals(key)
        out[key + "_mean"] = float(np.mean(v)) if v.size else None
        out[key + "_worst"] = float(np.max(v)) if v.size else None
    # Side slip: |mean lateral speed| in the heading frame (the outward drift the centrifugal compensation removes).
    v = np.abs(vals("lateral_speed_mean"))
    out["side_slip_mean"] = float(np.mean(v)) if v.size else None
    out["side_slip_worst"] = float(np.max(v)) if v.size else None
    return out


def contributions(groups: dict) -> dict:
    """Each part's contribution from the four ablation groups: the change of the worst / mean yaw error, speed
    error and falls when the part is switched off (averaged over the other part's two settings)."""
    def metric(name, key):
        return groups[name]["aggregate"].get(key)

    out = {}
    pairs = dict(kinematic_adjustment=(("full", "no_kinematic_adjustment"), ("no_centrifugal", "neither")),
                 centrifugal=(("full", "no_centrifugal"), ("no_kinematic_adjustment", "neither")))
    for part, pp in pairs.items():
        d = {}
        for key in ("yaw_error_max_deg_mean", "yaw_error_rms_deg_mean", "speed_error_rms_mean",
                    "yaw_rate_error_rms_mean", "side_slip_mean", "falls"):
            diffs = [metric(off, key) - metric(on, key) for on, off in pp
                     if metric(on, key) is not None and metric(off, key) is not None]
            d[key + "_increase_when_off"] = float(np.mean(diffs)) if diffs else None
        out[part] = d
    return out


def _fmt(v, f="{:.2f}"):
    return "-" if v is None else f.format(v)


def format_table(groups: dict, settle: float | None = None, duration: float | None = None) -> str:
    """A plain-text summary table, one row per configuration: failures with their reasons (runs per reason, the
    names of :data:`FAIL_REASONS`) and the tracking errors over the surviving instances. ``settle`` and
    ``duration`` (s) explain a ``-`` in the footnote."""
    head = (f"{'configuration':26s} {'n':>3s} {'falls':>5s} {'yaw err max [deg]':>18s} {'yaw err rms':>11s} "
            f"{'speed err rms [m/s]':>19s} {'yaw-rate err rms':>16s} {'side slip':>9s} {'periodicity':>11s}"
            f"  failure reasons (runs)")
    lines = [head, "-" * len(head)]
    dash = False
    for name, g in groups.items():
        a = g["aggregate"]
        cells = (_fmt(a['yaw_error_max_deg_mean']), _fmt(a['speed_error_rms_mean'], '{:.3f}'),
                 _fmt(a['yaw_rate_error_rms_mean'], '{:.3f}'), _fmt(a.get('side_slip_mean'), '{:.3f}'),
                 _fmt(a['periodicity_residual_mean']))
        dash = dash or "-" in cells
        reasons = a.get("failure_reasons")
        if reasons is None:  # an aggregate written before the counts: the reasons without them
            reasons_s = ", ".join(a.get("fail_reasons", [])) or "-"
        else:
            reasons_s = ", ".join(f"{k} {v}" for k, v in reasons.items()) or "-"
        lines.append(f"{name:26s} {a['n']:3d} {a['falls']:5d} "
                     f"{_fmt(a['yaw_error_max_deg_mean']) + ' / ' + _fmt(a['yaw_error_max_deg_worst']):>18s} "
                     f"{_fmt(a['yaw_error_rms_deg_mean']):>11s} "
                     f"{_fmt(a['speed_error_rms_mean'], '{:.3f}') + ' / ' + _fmt(a['speed_error_rms_worst'], '{:.3f}'):>19s} "
                     f"{cells[2]:>16s} {cells[3]:>9s} {cells[4]:>11s}  {reasons_s}")
    lines.append("(x / y = mean / worst over surviving instances; side slip = |mean lateral speed| [m/s]; periodicity = "
                 "median apex-to-apex residual, Eq. C2 units; failure reasons: fell_low_trunk (trunk below "
                 "0.35 m), fell_roll / fell_pitch (|angle| above 0.7 rad), diverged)")
    if dash:
        when = ""
        if settle is not None and duration is not None:
            when = (f": the per-cycle errors count only the gait cycles that start after the settling time "
                    f"(ramp + 1 s = {settle:g} s) and end by {duration:g} s; run --duration {settle + 0.8:g} s "
                    f"or longer to measure them")
        lines.append(f"- = not measured: no settled gait cycle in the run, or no surviving instance{when}")
    return "\n".join(lines)


def format_contributions(c: dict) -> str:
    lines = ["contribution (increase of the metric when the part is switched off):"]
    for part, d in c.items():
        lines.append(f"  {part:22s} yaw err max {_fmt(d['yaw_error_max_deg_mean_increase_when_off'])} deg, "
                     f"speed err rms {_fmt(d['speed_error_rms_mean_increase_when_off'], '{:+.3f}')} m/s, "
                     f"yaw-rate err rms {_fmt(d['yaw_rate_error_rms_mean_increase_when_off'], '{:+.3f}')} rad/s, "
                     f"side slip {_fmt(d['side_slip_mean_increase_when_off'], '{:+.3f}')} m/s, "
                     f"falls {_fmt(d['falls_increase_when_off'], '{:+.1f}')}")
    return "\n".join(lines)


def trace_slice(trace: dict, i: int) -> dict:
    return {k: v[i] for k, v in trace.items()}
