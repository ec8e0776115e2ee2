"""The step-down table of the paper, per (height, reflex) cell: completed and clean runs with Wilson 95%
intervals (the outcome hierarchy of :mod:`hyqjax.studies.stepdown_outcome`), the share of runs that lost a
foothold or pushed a joint past its range, mobility (Eq. 12, footnote 8), peak pitch and time to get all
feet down."""
from __future__ import annotations

from typing import Any

import numpy as np

from hyqjax.studies.statistics import wilson_interval


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
    ``terminated`` (runs that fell and were ended at their failure tick): counts, kept apart.
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
                terminated=int(np.sum(out["terminated"][mask])) if "terminated" in out else 0,
            ))
    return rows


def format_table(rows: list[dict[str, Any]]) -> str:
    head = (f"{'height':>7} {'reflex':>6} {'completed':>14} {'95% CI':>11} {'clean':>14} {'95% CI':>11} "
            f"{'lost fh':>7} {'jnt range':>9} {'shin str':>8} {'min m_sw':>8} {'mean m':>7} {'pitch':>6} {'t_down':>6}"
            f" {'fell':>4} {'div':>3}")
    lines = [head, "-" * len(head)]
    for r in rows:
        cells = []
        for key in ("completed", "clean"):
            lo, hi = r[f"{key}_ci95"]
            cells.append(f"{r[key]:>5d}/{r['n']:<3d} ({r[f'{key}_rate']:4.0%}) [{lo:4.2f},{hi:4.2f}]")
        lines.append(
            f"{r['height']:7.2f} {('on' if r['reflex'] else 'off'):>6} {cells[0]} {cells[1]}"
            f" {r['lost_foothold_share']:7.0%} {r['joint_past_range']:9.0%} {r['shin_strike']:8.0%}"
            f" {r['min_swing_mobility']:8.3f} {r['mean_mobility']:7.3f} {r['peak_pitch']:6.3f}"
            f" {r['time_all_down']:6.1f}"
            f" {r.get('terminated', 0):4d} {r.get('diverged', 0):3d}")
    lines.append("completed: all feet on the lower ground, no lost foothold, no joint past its range, no trunk strike, "
                 "no tilt, finite; clean: completed and no shin/trunk contact above the strike force. "
                 "lost fh, jnt range, shin str: share of runs; fell: runs ended at a fall (tilt or trunk strike), "
                 "div: simulator blow-ups (counts).")
    return "\n".join(lines)
