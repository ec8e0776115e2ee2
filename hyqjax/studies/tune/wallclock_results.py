"""The equal-wall-clock study's results (:mod:`.wallclock`): the held-out summary of one parameter set, the budget
curves of every run, and the winner at a budget.

* :func:`member_key`: the name of a (method, parameterisation, checkpoint) iterate in ``results.json``'s
  ``heldout``;
* :func:`summarize`: clean and completed success with Wilson 95% intervals, per height, and the failure counts;
* :func:`budget_curves`: per run, held-out clean / completed at every checkpoint with its wall-clock and physics
  steps;
* :func:`winner`: the best held-out clean success at a budget, and whether its interval is clear of every other
  run's (a lone run is clear of nothing).
"""
from __future__ import annotations

import numpy as np

from hyqjax.studies import statistics, stepdown
from hyqjax.studies import stepdown_outcome as so


def member_key(method: str, dim: str, seconds: float) -> str:
    return f"{method}/{dim}@{seconds / 60.0:g}min"


def summarize(heights, cols: dict) -> dict:
    """Clean / completed success with Wilson 95% intervals, per height, and the failure counts of one set."""
    clean, comp = np.asarray(cols["clean"], bool), np.asarray(cols["completed"], bool)
    n = int(clean.size)
    per = []
    for a, b in zip(statistics.success_curve(heights, clean), statistics.success_curve(heights, comp)):
        per.append(dict(height=a["height"], n=a["n"], clean=a["rate"], clean_ci95=a["ci95"], completed=b["rate"],
                        completed_ci95=b["ci95"]))
    return dict(n=n, clean=float(clean.mean()), clean_ci95=list(stepdown.wilson_interval(int(clean.sum()), n)),
                completed=float(comp.mean()), completed_ci95=list(stepdown.wilson_interval(int(comp.sum()), n)),
                failure_counts={k: int(np.sum(cols[k])) for k in so.FAILURE_REASONS}, per_height=per)


def budget_curves(res: dict) -> list:
    """Per (method, dim): held-out clean / completed at every checkpoint, with the wall-clock and physics steps."""
    out = []
    for key, r in res["runs"].items():
        pts = []
        for pt in r["points"]:
            h = res["heldout"].get(member_key(r["method"], r["dim"], pt["seconds"]))
            if h is None:
                continue
            pts.append(dict(minutes=pt["seconds"] / 60.0, physics_steps=pt["physics_steps"], clean=h["clean"],
                            clean_ci95=h["clean_ci95"], completed=h["completed"], completed_ci95=h["completed_ci95"]))
        out.append(dict(method=r["method"], dim=r["dim"], size=r["size"], points=pts))
    return out


def winner(res: dict, minutes: float) -> dict | None:
    """The (method, dim) with the highest held-out clean success at ``minutes`` (ties: higher completed), how many
    other (method, dim) runs it was compared with (``others``), and whether its 95% interval is clear of every
    other's (False when there is no other: a lone run wins nothing)."""
    rows = []
    for c in res.get("budget_curves", []):
        p = next((p for p in c["points"] if abs(p["minutes"] - minutes) < 1e-9), None)
        if p:
            rows.append((p["clean"], p["completed"], c["method"], c["dim"], p))
    if not rows:
        return None
    rows.sort(key=lambda r: (r[0], r[1]), reverse=True)
    best = rows[0]
    clear = len(rows) > 1 and all(best[4]["clean_ci95"][0] > r[4]["clean_ci95"][1] for r in rows[1:])
    return dict(method=best[2], dim=best[3], clean=best[0], completed=best[1], clean_ci95=best[4]["clean_ci95"],
                others=len(rows) - 1, clear_of_all_others=bool(clear))


def step_cost_line(dim: str, cost: dict, grad_mode: str) -> str:
    """One line on the gradient's step cost on ``dim`` (``GradientPrograms.step_cost``'s dict): both exact steps
    (``jacfwd``, reverse mode) and, where measured, the forward gradient, in forward-window evaluations on MJX-JAX;
    ``grad_mode`` is the mode the study's steps used."""
    c = cost
    return (f"gradient on {dim} (the study's steps: {grad_mode}): one jacfwd step ({c['tangents']} tangents) "
            f"{c['jacfwd_s']:.3f} s = {c['jacfwd_over_value']:.1f} forward windows ({c['window_value_s']:.3f} s, one "
            f"candidate, MJX-JAX); one reverse-mode step {c['reverse_s']:.3f} s = {c['reverse_over_value']:.1f}"
            + (f"; forward gradient ({c['forward_gradient_directions']} directions) {c['forward_gradient_s']:.3f} s = "
               f"{c['forward_gradient_over_value']:.1f}" if "forward_gradient_s" in c else ""))
