"""Guided ES against the gradient-free methods over seeds (``python -m experiments.tune_study --guided-comparison``):
held-out clean success per method and parameterisation over runs (:mod:`.repeats`) and what the per-generation
cosines of guided ES say about its surrogate gradient (:func:`hyqjax.studies.tune.guided.guided_cosines`)."""
from __future__ import annotations

import numpy as np

from hyqjax.studies.statistics import series_summary
from hyqjax.studies.tune.study import repeats


def cosine_summary(log: list, keys=("cos_zero_order", "cos_search")) -> dict:
    """Per guided-ES run: over its generations, the median, mean and share > 0 of each cosine of ``keys`` (by
    default ``cos_zero_order``, the surrogate against the unbiased zero-order estimate on the same population, and
    ``cos_search``; :func:`hyqjax.studies.tune.guided.guided_cosines`), and the mean of the first and last third of
    generations (does the agreement fade as the search moves away from the windows' gait?)."""
    out = dict(generations=len(log))
    for k in keys:
        out[k] = series_summary([r[k] for r in log if k in r], share_positive=True)
    return out


def compare(results: dict, minutes: float) -> dict:
    """``results``: seed -> a study's results.json (same settings but the seed). Held-out clean per member over
    the seeds with 95% t-intervals, Welch's differences, and guided ES's cosine summary per run."""
    names = [f"seed{s}" for s in results]
    summary = repeats.collect(list(results.values()), names, minutes)
    from hyqjax.studies.tune import blend, restarts

    cos, alpha, runs = {}, {}, {}
    for s, res in results.items():
        for key, run in res.get("runs", {}).items():
            if run["method"] == "guided_es":
                cos.setdefault(key, {})[f"seed{s}"] = cosine_summary(run["log"])
            elif run["method"] == "blend":
                alpha.setdefault(key, {})[f"seed{s}"] = blend.summary(run["log"])
            elif run["method"] in ("ipop_cma_es", "bipop_cma_es"):
                runs.setdefault(key, {})[f"seed{s}"] = restarts.summary(run["log"])
    return dict(minutes=float(minutes), seeds=[int(s) for s in results], summary=summary,
                differences=repeats.differences(summary), cosines=cos, blend=alpha, restarts=runs)


def markdown(comp: dict) -> str:
    lines = [repeats.table(comp["summary"], comp["minutes"]), ""]
    for key, runs in comp["cosines"].items():
        for name, c in runs.items():
            z, s = c["cos_zero_order"], c["cos_search"]
            if z is None:
                continue
            lines.append(f"{key} {name}: {c['generations']} generations; cosine of the surrogate gradient with the "
                         f"zero-order estimate on the same population: median {z['median']:+.3f}, share > 0 "
                         f"{z['share_positive']:.2f} (first third {z['first_third']:+.3f}, last third "
                         f"{z['last_third']:+.3f}); with the search's direction: median {s['median']:+.3f}")
    for key, runs in comp.get("blend", {}).items():
        for name, b in runs.items():
            if b["alpha"] is None:
                continue
            lines.append(f"{key} {name}: {b['steps']} steps; alpha median {b['alpha']['median']:.3f} (first third "
                         f"{b['alpha']['first_third']:.3f}, last third {b['alpha']['last_third']:.3f}; the variances "
                         f"alone {b['alpha_var']['median']:.3f}); cosine of the surrogate gradient with the zero-order "
                         f"estimate: median " + (f"{b['cos']['median']:+.3f}" if b["cos"] else "n/a"))
    for key, runs in comp.get("restarts", {}).items():
        for name, r in runs.items():
            lines.append(f"{key} {name}: {len(r['runs'])} runs: " + "; ".join(
                f"{x['regime']} population {x['popsize']} for {x['generations']} generations ({x['ended']})"
                for x in r["runs"]))
    return "\n".join(lines)
