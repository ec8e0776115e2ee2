"""How the gradient's window objective ranks iterates whose closed-loop success is known: the diagnostic that
decides whether a gradient of that objective can pay (docs/tuning.md).

For every held-out-evaluated iterate of one or more equal-wall-clock study runs (:mod:`.wallclock`; the start point,
Table I is left out, and every method's checkpoints), :func:`rank_iterates` evaluates the closed-loop window
objective ``L`` (:mod:`.objective`, equations there) on ONE fixed set of snapshot windows, taken at the start point
like the study's gradient takes them (:class:`.gradient_programs.GradientPrograms`, the first run's seed), and each
weighted term ``w_k T_k`` of ``L`` averaged over the valid windows. It reports, over the iterates, Spearman's rank
correlation of ``L`` and of each term with held-out clean success. Lower ``L`` is meant to be better, so an
objective worth descending gives a clearly negative correlation; a positive one means that descending it moves
away from closed-loop success. MJX-JAX (``impl="jax"``) on any machine.
"""
from __future__ import annotations

import numpy as np


def iterates(results: list[dict], names: list[str]) -> list[dict]:
    """Every held-out-evaluated iterate of the runs: name, parameterisation, theta, held-out clean and completed
    (the start point once)."""
    from hyqjax.studies.tune.wallclock_results import member_key

    out, seen_start = [], False
    for res, name in zip(results, names):
        for key, run in res["runs"].items():
            for pt in run["points"]:
                h = res["heldout"].get(member_key(run["method"], run["dim"], pt["seconds"]))
                if h is not None:
                    out.append(dict(name=f"{name}:{member_key(run['method'], run['dim'], pt['seconds'])}",
                                    dim=run["dim"], theta=pt["theta"], clean=h["clean"], completed=h["completed"]))
        if not seen_start and "start" in res["heldout"]:
            seen_start = True
            h = res["heldout"]["start"]
            out.append(dict(name="start", dim=None, theta=None, clean=h["clean"], completed=h["completed"]))
    return out


def rank_iterates(results: list[dict], names: list[str], log=print) -> dict:
    """Window objective and weighted terms of every iterate (:func:`iterates`) on the first run's start-point
    windows; Spearman's correlations with held-out clean success (module docstring)."""
    import jax
    import jax.numpy as jnp
    from scipy import stats

    from hyqjax.studies.tune import objective, schedule, search, wallclock
    from hyqjax.studies.tune.gradient_programs import GradientPrograms
    from hyqjax.studies.tune.wallclock_config import WallClockConfig

    cfg = WallClockConfig.from_dict(results[0]["config"])
    base = wallclock.start_params(cfg)
    grad = GradientPrograms(cfg, base, search.Charges(), log)
    win, su, obj = grad.win, grad.su, grad.obj
    weights = obj.weights()
    programs: dict = {}
    rows = iterates(results, names)
    for row in rows:
        dim = row["dim"] or cfg.dims[0]
        param = schedule.make(dim, cfg.groups)
        if dim not in programs:  # the windows are an argument, not constants folded into the program
            programs[dim] = jax.jit(lambda th, w, param=param: objective.window_losses(th, w, base, param, obj, su))
        theta = param.theta_of(base) if row["theta"] is None else np.asarray(row["theta"], np.float64)
        loss, terms, finite = programs[dim](jnp.asarray(theta, jnp.float32), win)
        ok = np.asarray(win.valid & finite)
        n = max(int(ok.sum()), 1)
        row["windows"] = int(ok.sum())
        row["objective"] = float(np.sum(np.where(ok, np.asarray(loss), 0.0)) / n)
        row["terms"] = {k: float(w * np.sum(np.where(ok, np.asarray(terms[k]), 0.0)) / n) for k, w in weights.items()}
        row.pop("theta")
        log(f"  {row['name']}: L {row['objective']:.3f}, held-out clean {row['clean']:.3f}")
    clean = [r["clean"] for r in rows]

    def rho(vals):
        return float(stats.spearmanr(vals, clean).statistic) if len(set(vals)) > 1 and len(set(clean)) > 1 \
            else float("nan")

    return dict(iterates=rows, windows=int(np.asarray(win.valid).sum()), window_ticks=int(obj.ticks),
                spearman_objective=rho([r["objective"] for r in rows]),
                spearman_terms={k: rho([r["terms"][k] for r in rows]) for k in weights})


def table(out: dict) -> str:
    """Markdown: iterates by held-out clean success, their ``L`` and weighted terms; the correlations."""
    keys = list(out["spearman_terms"])
    lines = ["| iterate | held-out clean | L | " + " | ".join(keys) + " |", "|---|---:|---:|" + "---:|" * len(keys)]
    for r in sorted(out["iterates"], key=lambda r: -r["clean"]):
        lines.append(f"| {r['name']} | {r['clean']:.3f} | {r['objective']:.3f} | "
                     + " | ".join(f"{r['terms'][k]:+.3f}" for k in keys) + " |")
    lines.append(f"| Spearman with held-out clean | | {out['spearman_objective']:+.2f} | "
                 + " | ".join(f"{out['spearman_terms'][k]:+.2f}" for k in keys) + " |")
    return "\n".join(lines)
