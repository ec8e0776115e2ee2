"""Guided ES against CMA-ES on the bounding refinement over training seeds: one table from several
``python -m experiments.bounding_refine --methods ...`` runs.

    python -m experiments.bounding_guided_seeds RUN_DIR [RUN_DIR ...] --out DIR

Each ``RUN_DIR`` is one refinement's ``--out`` (its ``results.json``). The runs must share everything a comparison
needs to be fair: the start preset, the wall-clock limit per method, the population, the training mixture's sizes
and duration, and the held-out instances (the six conditions' seed and size, the broad envelope's seed and size).
They may differ in ``--seed`` (the training instances and the searches' random numbers) and in guided ES's own
settings; a guided-ES run whose settings differ from the first one's is its own member, named after the
difference (``guided_es lr 0.03``).

Per member and seed (``rows``): wall-clock, generations, physics steps (forward + gradient), the training cost
from the start to the best candidate, and of the best candidate on held-out instances: falls on the broad envelope
(``--broad`` runs), falls and the worst yaw error at the low-friction, payload commands (the target: no fall and
worst yaw below 4 deg there), and the same for the method's final mean.

Per member over seeds (``summary``): the training cost's ratio best / start as a mean with its 95% t-interval over
seeds, the held-out falls pooled over seeds with Wilson intervals, and in how many seeds the target is met.

Paired over the seeds both members ran (``paired``, each member against ``cma_es``): the difference of the best
training cost (member - CMA-ES), its mean with a 95% t-interval and the paired t-test's p-value, and the count of
seeds in which each is lower; and the difference of falls at the low-friction, payload commands.

Writes ``DIR/comparison.json`` and ``DIR/comparison.md``.
"""
from __future__ import annotations

import json
import math
import os
import sys

import numpy as np

from hyqjax.cli.common import HelpFormatter, UsageError

#: Settings every run must share (``results.json``'s ``config``).
SHARED = ("start_preset", "max_wall", "popsize", "sigma", "train_envelope", "train_corners", "train_duration",
          "corner_speed", "corner_yaw_rate", "corner_friction", "corner_payload", "instances", "duration",
          "heldout_seed", "broad", "broad_seed", "impl")
#: Guided ES's own settings: a run that differs from the first guided-ES run in one of them is another member.
GUIDED = ("guided_sigma", "guided_lr", "alpha", "subspace", "grad_instances", "grad_duration", "grad_every")
REFERENCE = "cma_es"
SHORT = dict(guided_sigma="sigma", guided_lr="lr", grad_instances="grad instances", grad_duration="grad duration",
             grad_every="grad every")


def parse(argv=None):
    from hyqjax.cli.app import Parser

    ap = Parser(prog="python -m experiments.bounding_guided_seeds", description=__doc__,
                formatter_class=HelpFormatter)
    ap.add_argument("runs", nargs="+", metavar="RUN_DIR", help="bounding_refine --out directories")
    ap.add_argument("--out", required=True, help="directory for comparison.json and comparison.md")
    args = ap.parse_args(argv)
    for d in args.runs:
        if not os.path.exists(os.path.join(d, "results.json")):
            raise UsageError(f"RUN_DIR {d}: no results.json (give a finished bounding_refine --out)")
    return args


def load(run_dirs: list[str]) -> list[dict]:
    out = []
    for d in run_dirs:
        with open(os.path.join(d, "results.json")) as f:
            out.append(dict(dir=d, res=json.load(f)))
    return out


def check_comparable(runs: list[dict]) -> None:
    """Raise ValueError naming the first setting of :data:`SHARED` in which a run differs from the first."""
    ref = runs[0]
    for r in runs[1:]:
        for k in SHARED:
            a, b = ref["res"]["config"].get(k), r["res"]["config"].get(k)
            if a != b:
                raise ValueError(f"{r['dir']} differs from {ref['dir']} in {k}: {b!r} against {a!r}")


def member_names(runs: list[dict]) -> list[dict[str, str]]:
    """Per run, method -> member name: ``cma_es``; ``guided_es``, or ``guided_es <setting> <value>`` where the
    run's guided settings differ from the first guided-ES run's."""
    base = next((r["res"]["config"] for r in runs if "guided_es" in r["res"]["comparison"]), None)
    names = []
    for r in runs:
        cfg, m = r["res"]["config"], {}
        for method in r["res"]["comparison"]:
            name = method
            if method == "guided_es" and base is not None:
                diff = [f"{SHORT.get(k, k)} {cfg[k]:g}" for k in GUIDED if cfg.get(k) != base.get(k)]
                name = " ".join([method] + diff)
            m[method] = name
        names.append(m)
    return names


def rows(runs: list[dict]) -> list[dict]:
    """One row per (run, method): the run's seed, the member's name and what :mod:`experiments.bounding_refine`
    measured of it (see the module docstring)."""
    out = []
    for r, names in zip(runs, member_names(runs)):
        res = r["res"]
        target = res["heldout"]["target"]
        for method, c in res["comparison"].items():
            best, mean = target[method], target[f"{method}_mean"]
            out.append(dict(
                member=names[method], method=method, seed=int(res["config"]["seed"]), dir=r["dir"],
                wall_s=float(c["wall_s"]), generations=int(c["generations"]),
                physics_steps_forward=int(c["physics_steps_forward"]),
                physics_steps_gradient=int(c["physics_steps_gradient"]),
                training_start=float(c["training_start"]), training_best=float(c["training_best"]),
                broad_runs=int(c["best"]["runs"]), broad_falls=int(c["best"]["falls"]),
                broad_worst_yaw_deg=float(c["best"]["worst_yaw_deg"]),
                broad_falls_mean=int(c["mean"]["falls"]),
                target_runs=int(best["runs"]), target_falls=int(best["falls"]),
                target_worst_yaw_deg=float(best["worst_yaw_deg"]), target_met=bool(best["met"]),
                target_falls_mean=int(mean["falls"]), target_met_mean=bool(mean["met"]),
                start_target_falls=int(target[res["config"]["start_preset"]]["falls"])))
    return out


def _pooled(k: int, n: int) -> dict:
    from hyqjax.studies.statistics import wilson_interval

    return dict(falls=k, runs=n, ci95=list(wilson_interval(k, n)))


def summary(table: list[dict]) -> dict:
    from hyqjax.studies.tune.study.repeats import over_runs

    out = {}
    for member in dict.fromkeys(r["member"] for r in table):
        rs = [r for r in table if r["member"] == member]
        out[member] = dict(
            seeds=[r["seed"] for r in rs],
            wall_s=[r["wall_s"] for r in rs], generations=[r["generations"] for r in rs],
            physics_steps=over_runs([r["physics_steps_forward"] + r["physics_steps_gradient"] for r in rs]),
            training_ratio=over_runs([r["training_best"] / r["training_start"] for r in rs]),
            broad=_pooled(sum(r["broad_falls"] for r in rs), sum(r["broad_runs"] for r in rs)),
            broad_mean=_pooled(sum(r["broad_falls_mean"] for r in rs), sum(r["broad_runs"] for r in rs)),
            broad_worst_yaw_deg=max(r["broad_worst_yaw_deg"] for r in rs),
            target=_pooled(sum(r["target_falls"] for r in rs), sum(r["target_runs"] for r in rs)),
            target_mean=_pooled(sum(r["target_falls_mean"] for r in rs), sum(r["target_runs"] for r in rs)),
            target_worst_yaw_deg=max(r["target_worst_yaw_deg"] for r in rs),
            target_met=sum(r["target_met"] for r in rs), target_met_mean=sum(r["target_met_mean"] for r in rs))
    return out


def paired_difference(a, b) -> dict | None:
    """``a - b`` over paired seeds: the mean with its 95% t-interval, the paired t-test's two-sided p-value
    (``scipy.stats.ttest_rel``), the seeds in which ``a`` is lower and in which ``b`` is, and the two-sided sign
    test's p-value over the seeds that differ (``scipy.stats.binomtest``, which assumes no distribution of the
    differences); None with fewer than two pairs."""
    from scipy import stats

    from hyqjax.studies.tune.study.repeats import over_runs

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.size < 2:
        return None
    d = over_runs(a - b)
    p = float(stats.ttest_rel(a, b).pvalue) if np.any(a != b) else 1.0
    lo_a, lo_b = int(np.sum(a < b)), int(np.sum(b < a))
    sign = float(stats.binomtest(lo_a, lo_a + lo_b).pvalue) if lo_a + lo_b else 1.0
    return dict(d, p=p if math.isfinite(p) else 1.0, a_lower=lo_a, b_lower=lo_b, p_sign=sign)


def paired(table: list[dict], reference: str = REFERENCE) -> dict:
    ref = {r["seed"]: r for r in table if r["member"] == reference}
    out = {}
    for member in dict.fromkeys(r["member"] for r in table):
        if member == reference:
            continue
        pairs = [(r, ref[r["seed"]]) for r in table if r["member"] == member and r["seed"] in ref]
        if len(pairs) < 2:
            continue
        out[member] = dict(
            seeds=[r["seed"] for r, _ in pairs],
            training_best=paired_difference([r["training_best"] for r, _ in pairs],
                                            [q["training_best"] for _, q in pairs]),
            target_falls=paired_difference([r["target_falls"] for r, _ in pairs],
                                           [q["target_falls"] for _, q in pairs]))
    return out


def compare(runs: list[dict]) -> dict:
    check_comparable(runs)
    table = rows(runs)
    cfg = runs[0]["res"]["config"]
    return dict(max_wall_s=float(cfg["max_wall"]), start_preset=cfg["start_preset"], broad=int(cfg["broad"]),
                instances=int(cfg["instances"]), device=runs[0]["res"].get("device"),
                commands=[r["res"]["provenance"]["command"] for r in runs],
                rows=table, summary=summary(table), paired=paired(table))


def _ci(x: dict, fmt: str = "{:.3f}") -> str:
    if x["ci95"] is None:
        return fmt.format(x["mean"])
    return f"{fmt.format(x['mean'])} [{fmt.format(x['ci95'][0])}, {fmt.format(x['ci95'][1])}]"


def _falls(p: dict) -> str:
    return f"{p['falls']:,} of {p['runs']:,} [{100 * p['ci95'][0]:.2f}-{100 * p['ci95'][1]:.2f} %]"


def markdown(comp: dict) -> str:
    s = comp["summary"]
    lines = [f"Bounding refinement from `{comp['start_preset']}`, {comp['max_wall_s']:g} s per method; held-out "
             f"falls pooled over seeds (Wilson 95 %), the training cost's ratio over seeds (95 % t-interval)", "",
             "| member | seeds | generations | physics steps (mean) | training cost best / start | broad falls, best "
             "| worst yaw, broad (deg) | low-friction, payload falls, best | worst yaw there (deg) | target met "
             "(best / mean) | low-friction, payload falls, mean |",
             "|---|---|---|---:|---|---|---:|---|---:|---:|---|"]
    for m, x in s.items():
        lines.append(f"| `{m}` | {', '.join(map(str, x['seeds']))} | {min(x['generations'])}-{max(x['generations'])} "
                     f"| {x['physics_steps']['mean']:.3g} | {_ci(x['training_ratio'])} | {_falls(x['broad'])} | "
                     f"{x['broad_worst_yaw_deg']:.2f} | {_falls(x['target'])} | {x['target_worst_yaw_deg']:.2f} | "
                     f"{x['target_met']} / {x['target_met_mean']} of {len(x['seeds'])} | {_falls(x['target_mean'])} |")
    lines += ["", "Per seed (training cost start -> best; falls at the low-friction, payload commands, best / mean):", ""]
    for r in comp["rows"]:
        lines.append(f"- seed {r['seed']} `{r['member']}`: {r['generations']} generations in {r['wall_s']:.0f} s; "
                     f"training {r['training_start']:.3f} -> {r['training_best']:.3f}; broad falls {r['broad_falls']} "
                     f"of {r['broad_runs']:,}; low-friction, payload falls {r['target_falls']} / "
                     f"{r['target_falls_mean']} of {r['target_runs']:,} (the start {r['start_target_falls']})")
    if comp["paired"]:
        lines += ["", f"Paired over seeds against `{REFERENCE}` (member - {REFERENCE}; 95 % t-interval, paired t-test):",
                  ""]
        for m, p in comp["paired"].items():
            t, f = p["training_best"], p["target_falls"]
            lines.append(f"- `{m}`, seeds {', '.join(map(str, p['seeds']))}: best training cost {_ci(t, '{:+.3f}')}, "
                         f"p {t['p']:.2g}, lower in {t['a_lower']} seeds against {t['b_lower']} (sign test p {t['p_sign']:.2g}); "
                         f"low-friction, "
                         f"payload falls of the best {_ci(f, '{:+.1f}')}, p {f['p']:.2g}")
    return "\n".join(lines)


def main(argv=None) -> int:
    try:
        args = parse(argv)
        runs = load(args.runs)
        comp = compare(runs)
    except (UsageError, ValueError) as e:
        print(f"bounding_guided_seeds: {e}", file=sys.stderr)
        return 2
    from hyqjax.io.atomic import atomic_write, write_json

    os.makedirs(args.out, exist_ok=True)
    write_json(os.path.join(args.out, "comparison.json"), comp)
    text = markdown(comp)
    atomic_write(os.path.join(args.out, "comparison.md"), lambda f: f.write((text + "\n").encode()))
    print(text)
    print(f"wrote {os.path.join(args.out, 'comparison.json')} and comparison.md ({len(runs)} runs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
