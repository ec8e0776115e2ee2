"""Tuned sets on the default tuner's validation batch, in any simulator: whether a set's lead on the batch that
chose it holds when the same step-downs run in another simulator.

    python -m experiments.selection_batch --impl c --out DIR \\
        --tuned-run run_0@10min:STUDY/run_0/results.json:cma_es/per_leg@10min --tuned-run ...

The batch is the selection's validation batch of ``hyqjax tune`` with its defaults (``select_instances`` step-downs
drawn from ``select_seed`` at the training heights on the training spread,
:func:`hyqjax.studies.tune.wallclock_run.validation_scenarios`). The tuner's start point (its ``--preset``'s
``theta``) and each ``--tuned-run`` (``NAME:PATH:RUN``, ``RUN`` a run of the tuning results at ``PATH``, with
``@Nmin`` the iterate it held at that checkpoint) run on it in one batch through the tuner's own forward evaluator
(:class:`hyqjax.studies.tune.forward.SuccessEvaluator`) with ``--impl``. Each set is reported with its clean and
completed counts, the validation score its run recorded for it on the simulator it was tuned on, and its paired
difference from the start on the same step-downs (``b`` step-downs clean with the set only, ``c`` with the start only;
exact McNemar p), pooled and by training height.

A set that leads the start here but not on held-out step-downs was chosen by the batch's draw (the selection's
bias); a set whose recorded lead is gone here differs between the two simulators on the very step-downs that chose
it. Writes ``DIR/selection_batch.json`` and ``.md``.
"""
from __future__ import annotations

import os
import sys
import time

from hyqjax.cli.common import HelpFormatter, UsageError


def parse(argv=None):
    from hyqjax.cli.app import Parser

    ap = Parser(prog="python -m experiments.selection_batch", description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--tuned-run", action="append", required=True, metavar="NAME:PATH:RUN",
                    help="a set to run: NAME, the tuning results.json, its run (RUN@Nmin: the iterate held then)")
    from hyqjax.sim import backend

    ap.add_argument("--impl", default="c", choices=["auto", *backend.ALL_IMPLS],
                    help="simulator: " + backend.describe(backend.ALL_IMPLS))
    ap.add_argument("--instances", type=int, default=None,
                    help="a batch of N drawn like the validation batch from its seed (default: the tuner's "
                         "--select-instances, the batch itself; another size draws other step-downs)")
    ap.add_argument("--out", required=True, help="output directory")
    args = ap.parse_args(argv)
    for t in args.tuned_run:
        if len(t.split(":")) != 3 or not all(t.split(":")):
            raise UsageError(f"--tuned-run {t!r}: must be NAME:PATH:RUN")
    if args.instances is not None and not 1 <= args.instances <= 100000:
        raise UsageError(f"--instances {args.instances}: must be in [1, 100000]")
    return args


def main(argv=None) -> int:
    from hyqjax.io.phases import process_age

    t0 = time.perf_counter() - (process_age() or 0.0)
    try:
        args = parse(argv)
    except UsageError as e:
        print(f"selection_batch: {e}", file=sys.stderr)
        return 2
    import dataclasses

    import numpy as np

    from hyqjax.cli import tune as tune_cli
    from hyqjax.io.atomic import atomic_write, write_json
    from hyqjax.studies.sweep.compare import mcnemar_exact
    from hyqjax.studies.tune import tuned, wallclock, wallclock_run

    os.makedirs(args.out, exist_ok=True)
    try:
        cfg = tune_cli.default_config(os.path.join(args.out, "tune"), args.impl)
        if args.instances is not None:
            cfg = dataclasses.replace(cfg, select_instances=args.instances)
    except (UsageError, ValueError) as e:
        print(f"selection_batch: {'--instances: ' if isinstance(e, ValueError) else ''}{e}", file=sys.stderr)
        return 2
    param, theta0, ev = wallclock.start_evaluator(cfg)
    names, thetas, recorded = ["start"], [theta0], [None]
    for t in args.tuned_run:
        name, path, run = t.split(":")
        try:
            res = tuned.read(path)
            base, minutes = tuned.split_checkpoint(run)
            key = tuned.pick_run(res, base, path)
            theta = (tuned.checkpoint_theta(res, key, minutes, path) if minutes
                     else np.asarray(res["runs"][key]["theta"]))
        except (OSError, ValueError, KeyError) as e:
            print(f"selection_batch: --tuned-run {t}: {e}", file=sys.stderr)
            return 2
        stored = res.get("config") or {}
        if (stored.get("start_preset"), tuple(stored.get("groups") or ())) != (cfg.start_preset, tuple(cfg.groups)) \
                or len(theta) != param.size:
            print(f"selection_batch: --tuned-run {t}: a run of another start or parameterisation than the default "
                  f"tuner's ({cfg.start_preset}, {param.size} coordinates)", file=sys.stderr)
            return 2
        names.append(name)
        thetas.append(theta)
        recorded.append((tuned.checkpoint_point(res, key, minutes) or {}).get("validation_clean"))
    sc = wallclock_run.validation_scenarios(cfg)
    t_run = time.perf_counter()
    r = ev(np.stack(thetas), sc)
    wall = time.perf_counter() - t_run
    clean, completed = np.asarray(r["clean"]).astype(bool), np.asarray(r["completed"]).astype(bool)
    n = clean.shape[1]
    height = np.round(np.asarray(sc.terrain.platform_height, np.float64), 4)
    rows = []
    for i, name in enumerate(names):
        only_set, only_start = clean[i] & ~clean[0], ~clean[i] & clean[0]
        b, c = int(only_set.sum()), int(only_start.sum())
        per_height = [dict(height=float(h), n=int(at.sum()), clean=int(clean[i][at].sum()),
                           completed=int(completed[i][at].sum()), only_set=int(only_set[at].sum()),
                           only_start=int(only_start[at].sum()))
                      for h in np.unique(height) for at in [height == h]]
        rows.append(dict(name=name, clean=int(clean[i].sum()), completed=int(completed[i].sum()), n=n,
                         recorded_validation_clean=recorded[i], only_set=b, only_start=c,
                         d=(b - c) / n, p_mcnemar=mcnemar_exact(b, c) if i else None, per_height=per_height))
    out = dict(impl=ev.setup.impl, instances=n, select_seed=cfg.select_seed, heights=list(cfg.train_heights),
               spread=cfg.train_spread, duration=cfg.train_duration, wall_s_batch=wall,
               physics_steps=int(ev.physics_steps), sets=rows, tuned_runs=args.tuned_run)
    lines = [f"The default tuner's validation batch ({n} step-downs, select_seed {cfg.select_seed}) on "
             f"{ev.setup.impl}, paired against the start on the same step-downs", "",
             "| set | clean | completed | recorded validation clean | clean here | minus the start (only set / only "
             "start) | McNemar p |", "|---|---:|---:|---:|---:|---|---:|"]
    for row in rows:
        rec = "" if row["recorded_validation_clean"] is None else f"{row['recorded_validation_clean']:.3f}"
        diff = "" if row["p_mcnemar"] is None else f"{row['d']:+.3f} ({row['only_set']} / {row['only_start']})"
        p = "" if row["p_mcnemar"] is None else f"{row['p_mcnemar']:.2g}"
        lines.append(f"| {row['name']} | {row['clean']} | {row['completed']} | {rec} | {row['clean'] / n:.3f} | "
                     f"{diff} | {p} |")
    lines += ["", "Minus the start by height (only set / only start): "
              + "; ".join(f"{row['name']}: " + ", ".join(f"{h['height'] * 100:g} cm {h['only_set']} / {h['only_start']}"
                                                         for h in row["per_height"]) for row in rows[1:])]
    text = "\n".join(lines) + "\n"
    write_json(os.path.join(args.out, "selection_batch.json"), out)
    atomic_write(os.path.join(args.out, "selection_batch.md"), lambda f: f.write(text.encode()))
    print(text)
    print(f"wall {time.perf_counter() - t0:.1f} s in all (since the process started): the batch {wall:.1f} s "
          f"(compile included); {args.out}/selection_batch.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
