"""The equal-wall-clock study as a grid: every (method, parameterisation) cell at one budget, gathered from the
study directories that ran it (one process per method and parameterisation writes one directory each).

A cell is a method (with its gradient mode, when it is a gradient method run in reverse mode) on a
parameterisation; its value at ``minutes`` is the held-out clean success of what each of its runs returned then:

* one run: that rate with its Wilson 95% interval over the held-out instances;
* several runs (other seeds): their mean with the 95% Student-t interval over runs (:func:`.repeats.over_runs`),
  the interval that counts the run-to-run spread.

Every input must be of one configuration but for its seed, methods, parameterisations and gradient mode
(:data:`FREE_SETTINGS`), on one kind of device (a wall-clock budget buys different work on another) and the same
held-out set; anything else is refused naming the first difference. The same run given twice is refused too.
Each cell also carries its completed rate, its runs' not-completed and diverged counts and physics steps, so the
table states failures next to successes. ``python -m experiments.tune_cells`` prints the table and draws the
figure.
"""
from __future__ import annotations

import numpy as np

from hyqjax.studies.tune.study import repeats
from hyqjax.studies.tune.names import DIMS, METHODS
from hyqjax.studies.tune.wallclock_results import member_key

#: Settings in which the runs of one grid may differ.
FREE_SETTINGS = ("seed", "methods", "dims", "grad_mode")


def label(method: str, grad_mode: str | None) -> str:
    """A cell's method label: the method, with ``(reverse mode)`` for a gradient method run in reverse mode."""
    return f"{method} (reverse mode)" if method in ("gradient", "hybrid") and grad_mode == "reverse" else method


def check_one_device(results: list[dict]) -> None:
    """Refuse runs of several kinds of device: a wall-clock budget buys other work on each."""
    devices = {res.get("device") for res in results}
    if len(devices) > 1:
        raise ValueError(f"runs of several kinds of device ({', '.join(sorted(map(str, devices)))}): a wall-clock "
                         f"budget buys other work on each; give one kind")


def gather(results: list[dict], names: list[str], minutes: float) -> dict:
    """``{"cells": {dim: {label: cell}}, "start": {...}, "device": ...}`` of the runs in ``results`` (module
    docstring); ``names`` name the inputs in refusals and in each run's record."""
    if not results:
        raise ValueError("no study given")
    repeats.check_comparable(results, names, FREE_SETTINGS)
    check_one_device(results)
    cells: dict = {}
    sizes: dict = {}  # coordinates of each parameterisation, as its runs stored them
    seen: dict = {}
    starts = []
    for res, name in zip(results, names):
        cfg = res["config"]
        if "start" in res.get("heldout", {}):
            starts.append(res["heldout"]["start"]["clean"])
        for run in res.get("runs", {}).values():
            h = res.get("heldout", {}).get(member_key(run["method"], run["dim"], 60.0 * minutes))
            if h is None:
                continue
            lab = label(run["method"], cfg.get("grad_mode", "jacfwd"))
            key = (run["dim"], lab, cfg.get("seed"))
            if key in seen:
                raise ValueError(f"{name} and {seen[key]} both hold {lab} on {run['dim']} with seed {key[2]}; give one")
            seen[key] = name
            sizes[run["dim"]] = run.get("size")
            pt = next((p for p in run["points"] if abs(p["seconds"] - 60.0 * minutes) < 1e-6), {})
            fc = h.get("failure_counts", {})
            cells.setdefault(run["dim"], {}).setdefault(lab, []).append(dict(
                run=name, seed=cfg.get("seed"), n=h["n"], clean=h["clean"], clean_ci95=h["clean_ci95"],
                completed=h["completed"], not_completed=int(round(h["n"] * (1.0 - h["completed"]))),
                diverged=int(fc.get("diverged", 0)), physics_steps=pt.get("physics_steps")))
    out = {}
    for dim, by_label in cells.items():
        out[dim] = {}
        for lab, runs in by_label.items():
            if len(runs) == 1:
                mean, ci, kind = runs[0]["clean"], runs[0]["clean_ci95"], "wilson"
            else:
                o = repeats.over_runs([r["clean"] for r in runs])
                mean, ci, kind = o["mean"], o["ci95"], "over_runs"
            out[dim][lab] = dict(runs=runs, clean=mean, clean_ci95=ci, interval=kind,
                                 completed=float(np.mean([r["completed"] for r in runs])))
    return dict(minutes=minutes, device=results[0].get("device"), cells=out, sizes=sizes,
                start=dict(min=min(starts), max=max(starts)) if starts else None)


def _order(grid: dict) -> tuple[list, list]:
    dims = [d for d in DIMS if d in grid["cells"]]
    labels = sorted({lab for d in dims for lab in grid["cells"][d]},
                    key=lambda s: (METHODS.index(s.split(" ")[0]), s))
    return dims, labels


def markdown(grid: dict) -> str:
    """The grid as a markdown table: a row per method, a column per parameterisation; the best cell of each column
    in bold, and a cell whose interval lies above every other cell of its column marked "clear"."""
    dims, labels = _order(grid)
    head = "| method | " + " | ".join(f"{d} ({grid['sizes'].get(d) or '?'})" for d in dims) + " |"
    lines = [f"held-out clean success at {grid['minutes']:g} min ({grid['device']}); one run: [95% Wilson], "
             f"several: mean [95% over runs] (runs); not completed / diverged of the held-out runs", "",
             head, "|---|" + "---|" * len(dims)]
    best = {}
    for d in dims:
        col = grid["cells"][d]
        b = max(col, key=lambda k: col[k]["clean"])
        clear = all(col[b]["clean_ci95"][0] > col[k]["clean_ci95"][1] for k in col if k != b) and len(col) > 1
        best[d] = (b, clear)
    for lab in labels:
        row = [lab]
        for d in dims:
            c = grid["cells"][d].get(lab)
            if c is None:
                row.append("not run")
                continue
            v = f"{c['clean']:.3f} [{c['clean_ci95'][0]:.3f}, {c['clean_ci95'][1]:.3f}]"
            if best[d][0] == lab:
                v = f"**{v}**" + (" clear" if best[d][1] else "")
            n = len(c["runs"])
            fails = f"{sum(r['not_completed'] for r in c['runs'])} / {sum(r['diverged'] for r in c['runs'])}"
            row.append(v + (f" ({n} runs)" if n > 1 else "") + f"; {fails}")
        lines.append("| " + " | ".join(row) + " |")
    if grid["start"]:
        lines += ["", f"start point (Table I + shin remedy): {grid['start']['min']:.3f}-{grid['start']['max']:.3f} "
                      f"in every input"]
    return "\n".join(lines)


def plot(grid: dict, path: str) -> str:
    """Held-out clean success against the parameterisation's coordinates, one marker per method with its 95%
    interval, the start point's band behind; written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dims, labels = _order(grid)
    fig, ax = plt.subplots(figsize=(9.5, 4.2))
    if grid["start"]:
        ax.axhspan(grid["start"]["min"] - 0.002, grid["start"]["max"] + 0.002, color="0.85", label="start point")
    width = 0.8 / max(len(labels), 1)
    for j, lab in enumerate(labels):
        xs, ys, lo, hi = [], [], [], []
        for i, d in enumerate(dims):
            c = grid["cells"][d].get(lab)
            if c is not None:
                xs.append(i - 0.4 + width * (j + 0.5))
                ys.append(c["clean"])
                lo.append(c["clean"] - c["clean_ci95"][0])
                hi.append(c["clean_ci95"][1] - c["clean"])
        ax.errorbar(xs, ys, yerr=[lo, hi], fmt="o", capsize=3, label=lab)
    ax.set_xticks(range(len(dims)), [f"{d}\n({grid['sizes'].get(d) or '?'} coordinates)" for d in dims])
    ax.set_ylabel(f"held-out clean success at {grid['minutes']:g} min")
    ax.set_title(f"Tuning methods at equal wall-clock ({grid['device']})", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
