"""Sweep summary: counts, failure reasons, probability maps with Wilson 95% intervals, largest safe height,
for both outcome levels.

Every step-down outcome has two levels (:mod:`hyqjax.studies.stepdown_outcome`): *completed* (the paper's
criterion: all four feet on the lower ground, no lost foothold, no joint past its range, no trunk strike, no
tilt, finite) and *clean* (completed and no shin or trunk contact above the strike force). The rows' ``success``
column is ``clean``. :func:`summarize_sweep` reports, for each level, the counts and rates with their Wilson 95%
intervals (overall and per reflex setting), the height curve, the 2-D maps (e.g. height x friction) and the
largest safe height:

* ``h95_wilson`` (conservative): the largest height level ``h`` such that, at every level ``<= h``,
  the Wilson 95% lower bound of the probability (pooled over all other axes) is ``>= 0.95``.
  It needs at least 73 instances per level (73/73 gives a lower bound of 0.950); None otherwise.
* ``h95_logistic`` (point estimate): the height where a logistic fit
  ``P(level | h) = sigmoid(a + b h)`` (maximum likelihood) crosses 0.95; None if the fit
  has ``b >= 0`` or does not converge (e.g. all instances pass).

The clean level keeps the keys of older summaries (:data:`KEYS`: ``successes``, ``rate``, ``ci95``,
``h95_wilson``, ``h95_logistic``; ``ci95_lo`` / ``ci95_hi`` in a map); the completed level has ``completed``-named
keys next to them (``completed``, ``completed_rate``, ``completed_ci95``, ``h95_completed_wilson``, ...). Rows
without a ``completed`` column (a store written before the hierarchy) give None for every completed entry and
a line in ``notes``; they never raise.

Two counts are kept apart, overall and per reflex setting: ``diverged`` (simulator blow-ups: a non-finite state or
a speed past ``SimConfig.max_speed``) and ``terminated`` (runs that fell, a tilt past ``max_tilt`` or a trunk strike,
and whose episode ended at that failure tick: failures with their reasons, not blow-ups; None for rows written
before the episode end).

Height levels are the grid values, or equal-width bins over ``[lo, hi]`` (``bins``) for a random axis.
An empty map cell has rate and interval ``null`` in ``summary.json`` (strict JSON, no NaN).
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from hyqjax.io.atomic import atomic_write, write_json
from hyqjax.studies import statistics
from hyqjax.studies.sweep.outcomes import KEYS, LEVELS, NO_COMPLETED_NOTE, level_columns
from hyqjax.studies.sweep.plots import plot_height_curves, plot_maps
from hyqjax.studies.sweep.spec import AXES, SweepSpec


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


def logistic_h95(h: np.ndarray, y: np.ndarray, target: float = 0.95):
    """Height where ``sigmoid(a + b h)`` (maximum likelihood) equals ``target``; None if b >= 0 or no fit
    (:func:`hyqjax.studies.statistics.h95_logistic`)."""
    return statistics.h95_logistic(h, y, target)


def rate_entries(y: np.ndarray | None, keys: dict[str, str]) -> dict[str, Any]:
    """``{count, rate, ci95}`` (named by ``keys``, see :data:`KEYS`) of the booleans ``y``; None entries for an
    absent level, rate None and interval NaNs for no instances."""
    if y is None:
        return {keys["count"]: None, keys["rate"]: None, keys["ci95"]: None}
    k, n = int(y.sum()), int(y.size)
    return {keys["count"]: k, keys["rate"]: k / n if n else None, keys["ci95"]: list(statistics.wilson_interval(k, n))}


def height_entries(levels: dict, h_label: np.ndarray, h_index: np.ndarray, height: np.ndarray) -> dict[str, Any]:
    """``height_curve`` (per height level ``n``, clean ``successes`` / ``rate`` / ``ci95`` and the ``completed``
    ones) and both levels' h95 (Wilson and logistic) of one reflex setting's instances."""
    out: dict[str, Any] = {}
    curves = {}
    for lv in LEVELS:
        y, keys = levels[lv], KEYS[lv]
        if y is None:
            out[keys["h95_wilson"]] = out[keys["h95_logistic"]] = None
            continue
        curves[lv] = statistics.success_curve(h_label, y, levels=h_index)
        out[keys["h95_wilson"]] = statistics.h95_wilson(curves[lv])
        out[keys["h95_logistic"]] = logistic_h95(height.astype(float), y.astype(float))
    curve = [dict(c) for c in curves["clean"]]
    done = curves.get("completed")
    keys = KEYS["completed"]
    for i, c in enumerate(curve):
        d = done[i] if done else dict(successes=None, rate=None, ci95=None)
        c.update({keys["count"]: d["successes"], keys["rate"]: d["rate"], keys["ci95"]: d["ci95"]})
    return dict(height_curve=curve, **out)


def map_entries(levels: dict, m: np.ndarray, la: np.ndarray, lb: np.ndarray, shape: tuple[int, int]) -> dict:
    """``n`` and, per level, counts, rates (NaN in an empty cell) and Wilson bounds of a 2-D map."""
    nn = np.zeros(shape, int)
    np.add.at(nn, (la[m], lb[m]), 1)
    out: dict[str, Any] = {}
    for lv in reversed(LEVELS):  # clean first: the keys of older summaries lead
        y, keys = levels[lv], KEYS[lv]
        if y is None:
            out.update({keys[k]: None for k in ("count", "rate", "ci95_lo", "ci95_hi")})
            continue
        k = np.zeros(shape, int)
        np.add.at(k, (la[m], lb[m]), y[m].astype(int))
        ci = np.asarray([[statistics.wilson_interval(int(k[i, j]), int(nn[i, j])) for j in range(shape[1])]
                         for i in range(shape[0])]).reshape(*shape, 2)
        out.update({keys["count"]: k.tolist(), keys["rate"]: np.where(nn > 0, k / np.maximum(nn, 1), np.nan).tolist(),
                    keys["ci95_lo"]: ci[..., 0].tolist(), keys["ci95_hi"]: ci[..., 1].tolist()})
    return dict(n=nn.tolist(), **out)


def _count(rows, key: str, mask=None) -> int | None:
    """Instances with ``rows[key]`` set (within ``mask``); None where the rows have no such column (older stores)."""
    if key not in rows:
        return None
    v = np.asarray(rows[key], bool)
    return int(v[mask].sum() if mask is not None else v.sum())


def summarize_sweep(spec: SweepSpec, rows: dict[str, np.ndarray]) -> dict[str, Any]:
    """Counts, failure reasons, maps with Wilson 95% intervals and max safe heights per reflex setting, for the
    completed and the clean level (module docstring)."""
    n = int(rows["index"].shape[0]) if rows else 0
    summary: dict[str, Any] = dict(n_instances=n, n_planned=spec.n_instances, spec_hash=spec.spec_hash)
    if n == 0:
        return summary
    levels = level_columns(rows)
    succ = levels["clean"]
    reasons: dict[str, int] = {}
    for r in rows["failure_reason"][~succ]:
        for part in str(r).split("; "):
            reasons[part or "unspecified"] = reasons.get(part or "unspecified", 0) + 1
    for lv in reversed(LEVELS):
        summary.update(rate_entries(levels[lv], KEYS[lv]))
    summary.update(diverged=int(rows["diverged"].sum()), terminated=_count(rows, "terminated"), failure_reasons=reasons)
    if levels["completed"] is None:
        summary["notes"] = [NO_COMPLETED_NOTE]
    modes = sorted(set(rows["reflex"].tolist()))
    hl, hlab = _levels(spec, rows, "height")
    by_reflex = {}
    for r in modes:
        m = rows["reflex"] == r
        lv_m = {lv: None if y is None else y[m] for lv, y in levels.items()}
        entry: dict[str, Any] = dict(n=int(m.sum()))
        for lv in reversed(LEVELS):
            entry.update(rate_entries(lv_m[lv], KEYS[lv]))
        entry["mean_mobility"] = float(np.nanmean(rows["mean_mobility"][m]))
        entry.update(diverged=int(rows["diverged"][m].sum()), terminated=_count(rows, "terminated", m))
        entry.update(height_entries(lv_m, np.asarray(hlab, float)[hl[m]], hl[m], rows["height"][m]))
        by_reflex["on" if r else "off"] = entry
    summary["by_reflex"] = by_reflex
    maps = []
    varying = set(spec.varying())
    for a, b in spec.maps:
        if a not in varying and b not in varying:
            continue
        la, lab_a = _levels(spec, rows, a)
        lb, lab_b = _levels(spec, rows, b)
        for r in modes:
            maps.append(dict(x=a, y=b, reflex=bool(r), x_levels=lab_a, y_levels=lab_b,
                             **map_entries(levels, rows["reflex"] == r, la, lb, (len(lab_a), len(lab_b)))))
    summary["maps"] = maps
    return summary


def write_outputs(store, clock=None) -> dict[str, Any]:
    """``instances.csv`` (one row per finished instance), ``summary.json`` and the figures of a
    :class:`hyqjax.studies.sweep.store.SweepStore`, from its verified chunks only; damaged chunks are named in
    ``summary["damaged_chunks"]`` and a note. ``clock`` (:class:`hyqjax.io.phases.Clock`, optional): laps
    ``summary`` before the figures and ``figures`` after them."""
    import csv
    import io

    rows = store.load()
    summary = summarize_sweep(store.spec, rows)
    if rows:
        cols = [k for k in rows if rows[k].ndim == 1]
        buf = io.StringIO()
        w = csv.writer(buf)
        w.writerow(cols)
        for i in range(rows["index"].shape[0]):
            w.writerow([rows[k][i].item() if hasattr(rows[k][i], "item") else rows[k][i] for k in cols])
        atomic_write(os.path.join(store.dir, "instances.csv"), lambda f: f.write(buf.getvalue().encode()))
        if clock is not None:
            clock.lap("summary")
        summary["figures"] = [p for p in (plot_maps(summary, os.path.join(store.dir, "success_maps.png")),
                                          plot_height_curves(summary, os.path.join(store.dir, "success_height.png")))
                              if p]
        if clock is not None:
            clock.lap("figures")
    summary["complete"] = len(store.done()) == store.n_chunks
    if store.problems:  # named, never silently dropped: these rows are in neither file
        summary["damaged_chunks"] = {str(c): why for c, why in sorted(store.problems.items())}
        summary.setdefault("notes", []).append(
            f"{len(store.problems)} damaged chunk(s) left out of this summary and instances.csv (chunks "
            f"{sorted(store.problems)}; `hyqjax verify {store.dir}` names them; the next run recomputes them)")
    write_json(os.path.join(store.dir, "summary.json"), summary)
    return summary


def level_text(entry: dict, level: str, n: int | None = None, h95: bool = True) -> str:
    """One level's ``k/n = rate [lo, hi]`` (and h95) of a summary entry; ``n/a`` where the level is absent."""
    keys = KEYS[level]
    k, rate, ci = entry.get(keys["count"]), entry.get(keys["rate"]), entry.get(keys["ci95"])
    if k is None:
        return f"{level} n/a"
    n = entry.get("n") if n is None else n
    lo, hi = (ci if ci and None not in ci else [float("nan")] * 2)
    text = f"{level} {k}/{n}" + ("" if rate is None else f" = {rate:.2f}") + f" [{lo:.2f}, {hi:.2f}]"
    if h95:
        hw, hl = entry.get(keys["h95_wilson"]), entry.get(keys["h95_logistic"])
        text += (f", h95 Wilson {'-' if hw is None else f'{hw:.3f} m'}, "
                 f"logistic {'-' if hl is None else f'{hl:.3f} m'}")
    return text


def format_summary(summary: dict) -> str:
    """The summary as text: totals, per reflex setting one line per level (completed, clean), the height curve
    (both levels on one line per height), failure reasons and notes."""
    n = summary.get("n_instances", 0)
    lines = [f"{n}/{summary.get('n_planned', 0)} instances"
             + "".join(f", {level_text(summary, lv, n, h95=False)}" for lv in LEVELS if n)
             + f", {summary.get('diverged', 0)} diverged"
             + ("" if summary.get("terminated") is None else f", {summary['terminated']} terminated (fell)")]
    for name, r in summary.get("by_reflex", {}).items():
        mob = r.get("mean_mobility")
        lines.append(f"reflex {name:>3} (n = {r['n']}, mean mobility {'-' if mob is None else f'{mob:.3f}'}):")
        lines += [f"  {level_text(r, lv)}" for lv in LEVELS]
        for c in r["height_curve"]:
            lines.append(f"    h = {c['height']:.3f} m: " + ", ".join(level_text(c, lv, h95=False) for lv in LEVELS))
    if summary.get("failure_reasons"):
        lines.append("failure reasons (not clean): " + ", ".join(
            f"{k} x{v}" for k, v in sorted(summary["failure_reasons"].items(), key=lambda t: -t[1])))
    lines += [f"note: {t}" for t in summary.get("notes", [])]
    return "\n".join(lines)


__all__ = ["format_summary", "height_entries", "level_text", "logistic_h95", "map_entries", "rate_entries",
           "summarize_sweep", "write_outputs"]
