"""The step-down table of the paper, per (height, reflex) cell: completed and clean runs with Wilson 95%
intervals (the outcome hierarchy of :mod:`hyqjax.studies.stepdown_outcome`), the share of runs that lost a
foothold or pushed a joint past its range, mobility (Eq. 12, footnote 8), peak pitch, time to get all
feet down, and the failure reasons of the runs that are not clean (the names of
:data:`hyqjax.studies.stepdown_outcome.FAILURE_REASONS`, as ``hyqjax sweep`` prints them)."""
from __future__ import annotations

from typing import Any

import numpy as np

from hyqjax.studies.statistics import wilson_interval
from hyqjax.studies.stepdown_outcome import FAILURE_REASONS

#: What the two outcome levels mean (printed under every step-down table and in ``hyqjax stepdown --help``).
OUTCOME_HIERARCHY = ("completed: all four feet on the lower ground past the edge, forward progress, no lost foothold, "
                     "no joint past its range, no trunk strike, no tilt, no reflex failure, finite; clean: completed and "
                     "no shin contact above the strike force (100 N)")


def failure_reasons(out: dict[str, np.ndarray], mask: np.ndarray | None = None) -> dict[str, int]:
    """``{reason: runs}`` over the runs (``mask``) that are not clean, for each failure reason of
    :data:`FAILURE_REASONS` that is set in at least one (a run can have several), in display order."""
    clean = np.asarray(out["clean"], bool)
    sel = ~clean if mask is None else (np.asarray(mask, bool) & ~clean)
    counts = {k: int(np.sum(np.asarray(out[k], bool)[sel])) for k in FAILURE_REASONS if k in out}
    return {k: v for k, v in counts.items() if v}


def reasons_text(reasons: dict[str, int]) -> str:
    """``feet_not_down 2, shin_strike 1`` (``-`` for none)."""
    return ", ".join(f"{k} {v}" for k, v in reasons.items()) or "-"


def _rate(mask: np.ndarray) -> tuple[int, float, tuple[float, float]]:
    k, n = int(np.sum(mask)), int(mask.size)
    return k, k / n, wilson_interval(k, n)


def _nan_stat(fn, x: np.ndarray) -> float:
    return float(fn(x)) if np.isfinite(x).any() else float("nan")


def summarize(table: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """One row per (height, reflex) of the instance ``table`` (inputs) and ``out`` (outcome columns).

    ``completed`` / ``clean``: counts, rates and Wilson 95% intervals (``success*`` repeat ``clean`` for readers of
    older results); ``lost_foothold_share``: share of runs with at least one lost foothold;
    ``mean_lost_footholds``: lost footholds per run; ``joint_past_range``: share of runs; ``diverged`` and
    ``terminated`` (runs that fell and were ended at their failure tick): counts, kept apart;
    ``failure_reasons``: :func:`failure_reasons` of the cell (runs per reason among those not clean).
    """
    rows = []
    for h in sorted(set(table["height"].tolist())):
        for r in [False, True]:
            mask = (table["height"] == h) & (table["reflex"] == r)
            if not mask.any():
                continue
            n = int(mask.sum())
            kc, pc, cic = _rate(np.asarray(out["completed"])[mask])
            kk, pk, cik = _rate(np.asarray(out["clean"])[mask])
            rows.append(dict(
                height=h, reflex=r, n=n,
                completed=kc, completed_rate=pc, completed_ci95=cic,
                clean=kk, clean_rate=pk, clean_ci95=cik,
                successes=kk, success_rate=pk, success_ci95=cik,
                all_feet_down=float(np.mean(~np.asarray(out["feet_not_down"])[mask])),
                lost_foothold_share=float(np.mean(np.asarray(out["lost_foothold"])[mask])),
                mean_lost_footholds=float(np.mean(out["lost_footholds"][mask])),
                joint_past_range=float(np.mean(out["joint_past_range"][mask])),
                shin_strike=float(np.mean(out["shin_strike"][mask])),
                min_swing_mobility=_nan_stat(np.nanmin, out["min_swing_mobility"][mask]),
                mean_mobility=float(np.mean(out["mean_mobility"][mask])),
                peak_pitch=float(np.mean(out["peak_pitch"][mask])),
                time_all_down=_nan_stat(np.nanmean, out["time_all_down"][mask]),
                diverged=int(np.sum(out["diverged"][mask])),
                failure_reasons=failure_reasons(out, mask),
                terminated=int(np.sum(out["terminated"][mask])) if "terminated" in out else 0,
            ))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    """The table as text: one line per (height, reflex) cell, the outcome levels with Wilson 95% intervals, the
    shares of runs losing a foothold, with a joint past its range and striking a shin, mobility, pitch, the mean
    time to get all feet down, and the failure reasons (runs per reason among the runs that are not clean)."""
    head = (f"{'height':>7} {'reflex':>6} {'completed':>14} {'95% CI':>11} {'clean':>14} {'95% CI':>11} "
            f"{'lost fh':>7} {'jnt range':>9} {'shin str':>8} {'min m_sw':>8} {'mean m':>7} {'pitch':>6} {'t_down':>6}"
            f"  {'fell':>4} {'div':>3}  failure reasons (runs)")
    lines = [head, "-" * len(head)]
    for r in rows:
        cells = []
        for key in ("completed", "clean"):
            lo, hi = r[f"{key}_ci95"]
            cells.append(f"{r[key]:>5d}/{r['n']:<3d} ({r[f'{key}_rate']:4.0%}) [{lo:4.2f},{hi:4.2f}]")
        reasons = r.get("failure_reasons")
        lines.append(
            f"{r['height']:7.2f} {('on' if r['reflex'] else 'off'):>6} {cells[0]} {cells[1]}"
            f" {r['lost_foothold_share']:7.0%} {r['joint_past_range']:9.0%} {r['shin_strike']:8.0%}"
            f" {r['min_swing_mobility']:8.3f} {r['mean_mobility']:7.3f} {r['peak_pitch']:6.3f} {r['time_all_down']:6.1f}"
            f"  {r.get('terminated', 0):4d} {r.get('diverged', 0):3d}"
            f"  {'n/a' if reasons is None else reasons_text(reasons)}")
    lines.append(OUTCOME_HIERARCHY + ".")
    lines.append("lost fh, jnt range, shin str: share of runs; min m_sw, mean m: swing-leg and overall mobility (Eq. 12); "
                 "pitch: mean peak |pitch| (rad); t_down: mean time to all feet down (s, nan: never); fell: runs ended "
                 "at a fall (tilt or trunk strike: the episode end), div: simulator blow-ups (counts); failure reasons: "
                 "runs per reason among those not clean (a run can have several).")
    return "\n".join(lines)
