"""Sweep summary: counts, failure reasons, success maps with Wilson 95% intervals, largest safe height.

:func:`summarize_sweep` reports success probability maps (e.g. height x friction) with Wilson 95%
intervals per reflex setting and the largest safe height:

* ``h95_wilson`` (conservative): the largest height level ``h`` such that, at every level ``<= h``,
  the Wilson 95% lower bound of the success probability (pooled over all other axes) is ``>= 0.95``.
  It needs at least 73 instances per level (73/73 gives a lower bound of 0.950); None otherwise.
* ``h95_logistic`` (point estimate): the height where a logistic fit
  ``P(success | h) = sigmoid(a + b h)`` (maximum likelihood, Newton) crosses 0.95; None if the fit
  has ``b >= 0`` or does not converge (e.g. all successes).

Height levels are the grid values, or equal-width bins over ``[lo, hi]`` (``bins``) for a random axis.
An empty map cell has rate and interval ``null`` in ``summary.json`` (strict JSON, no NaN).
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from hyqjax.io.atomic import atomic_write, write_json
from hyqjax.studies import statistics
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
        curve = statistics.success_curve(np.asarray(hidx, float)[hl[m]], succ[m], levels=hl[m])
        h95 = statistics.h95_wilson(curve)
        by_reflex["on" if r else "off"] = dict(
            n=nn, successes=k, rate=k / nn, ci95=list(statistics.wilson_interval(k, nn)),
            mean_mobility=float(np.nanmean(rows["mean_mobility"][m])), height_curve=curve, h95_wilson=h95,
            h95_logistic=logistic_h95(rows["height"][m].astype(float), succ[m].astype(float)))
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
            ci = np.asarray([[statistics.wilson_interval(int(k[i, j]), int(nn[i, j])) for j in range(len(lab_b))]
                             for i in range(len(lab_a))])
            maps.append(dict(x=a, y=b, reflex=bool(r), x_levels=lab_a, y_levels=lab_b, successes=k.tolist(),
                             n=nn.tolist(), rate=np.where(nn > 0, k / np.maximum(nn, 1), np.nan).tolist(),
                             ci95_lo=ci[..., 0].tolist(), ci95_hi=ci[..., 1].tolist()))
    summary["maps"] = maps
    return summary



def write_outputs(store) -> dict[str, Any]:
    """``instances.csv`` (one row per finished instance), ``summary.json`` and the figures of a
    :class:`hyqjax.studies.sweep.store.SweepStore` (its verified chunks)."""
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
        summary["figures"] = [p for p in (plot_maps(summary, os.path.join(store.dir, "success_maps.png")),
                                          plot_height_curves(summary, os.path.join(store.dir, "success_height.png")))
                              if p]
    summary["complete"] = len(store.done()) == store.n_chunks
    write_json(os.path.join(store.dir, "summary.json"), summary)
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


__all__ = ["format_summary", "logistic_h95", "summarize_sweep", "write_outputs"]
