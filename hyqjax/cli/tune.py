"""Tune the height reflex and the crawl for the step-down by gradient through the closed loop (crawl +
reflex + joint impedance + MJX), with CMA-ES and random search at the same simulation budget (on the same
objective and on closed-loop success directly) and a held-out closed-loop evaluation against Table I
(hyqjax.studies.tune, docs/tuning.md).

DIR holds gradient/ (config.json, log.jsonl: one line per Adam step, checkpoint.npz: resumed by the same
command), results.json (parameters, costs, gradient statistics, baselines, held-out success with Wilson
intervals per height) and tuning.png (held-out success against simulation budget). --objective kinematic
runs the former kinematic surrogate instead; --warm-start N starts the closed-loop tuning from N
surrogate steps. One run at a time holds DIR/.lock (--wait queues behind it); DIR/fingerprint.json records
every setting that changes the results, and a resume with other settings is refused naming them, before
anything is compiled.
"""
from __future__ import annotations

import argparse

NAME = "tune"
HELP = "tune the height reflex and crawl by gradient through the closed-loop MJX step-down"
ORDER = 30

#: The baselines (the names of :data:`hyqjax.studies.tune.study.METHODS` after the gradient), checked here before
#: anything heavy is imported.
BASELINES = ("cma_es", "random_search", "cma_es_success", "random_search_success")


def _floats(s):
    return tuple(float(x) for x in s.split(",") if x.strip())


def _ints(s):
    return tuple(int(x) for x in s.split(",") if x.strip())


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/tune", help="run directory (the gradient run resumes from its checkpoint)")
    p.add_argument("--objective", default="closed_loop", choices=["closed_loop", "kinematic"],
                   help="closed_loop: jacfwd through MJX windows (default); kinematic: the reflex-only surrogate")
    p.add_argument("--groups", default="k_base,damping,mobility,k_x,delta,body_height,step_length,step_height,"
                                       "search_forward,terrain_adaptation",
                   help="tuned groups, comma-separated, from k_base, damping, mobility, k_x, delta, k_kl, "
                        "body_height, step_length, step_height, search_speed, search_forward, terrain_adaptation")
    p.add_argument("--paper-crawl", action="store_true",
                   help="tune the paper's crawl (no shin-strike remedy; search_forward then has no effect); "
                        "default: the crawl with the remedy (docs/tuning.md)")
    p.add_argument("--steps", type=int, default=20, help="Adam steps (total, across resumes)")
    p.add_argument("--lr", type=float, default=0.1, help="Adam learning rate (unconstrained parameters)")
    p.add_argument("--line-search", type=_floats, default=(0.125, 0.25, 0.5, 1.0, 2.0),
                   help="scales of the Adam update tried per step (one batched forward evaluation of the windows, "
                        "counted in the budget); the best is taken only if it lowers the objective; '' for plain Adam")
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--train-heights", type=_floats, default=(0.16, 0.20, 0.24, 0.28), help="training heights (m)")
    p.add_argument("--train-per-height", type=int, default=2, help="training scenarios per height")
    p.add_argument("--windows-per-scenario", type=int, default=2, help="snapshot windows per scenario (legs over the edge)")
    p.add_argument("--lead", type=float, default=10.0, help="forward run that takes the snapshots (s)")
    p.add_argument("--window-ticks", type=int, default=750, help="window length (control ticks of 2 ms)")
    p.add_argument("--prefixes", type=_ints, default=(50, 125, 250, 500),
                   help="shorter window lengths (ticks) at which the gradient statistics are also reported")
    p.add_argument("--warm-start", type=int, default=0, help="kinematic-surrogate steps before the closed loop")
    p.add_argument("--baselines", default=",".join(BASELINES),
                   help="baselines at the same budget (comma-separated; empty for none)")
    p.add_argument("--sigma", type=float, default=0.5, help="initial step of CMA-ES and random search (theta units)")
    p.add_argument("--success-instances", type=int, default=8, help="full runs per candidate for the success baselines")
    p.add_argument("--success-duration", type=float, default=24.0, help="simulated seconds of those runs")
    p.add_argument("--heldout", type=int, default=36, help="held-out closed-loop instances per method (0: skip)")
    p.add_argument("--heldout-seed", type=int, default=7777, help="held-out seed (never used for training)")
    p.add_argument("--heldout-duration", type=float, default=24.0, help="simulated seconds per held-out instance")
    p.add_argument("--curve-instances", type=int, default=0,
                   help="held-out instances per point of the success-vs-budget curve (0: final points only)")
    p.add_argument("--baseline-wall-s", type=float, default=0.0,
                   help="also stop each success baseline after this many wall seconds (0: budget only; the "
                        "window-objective baselines always get the whole budget)")
    p.add_argument("--select-instances", type=int, default=16,
                   help="keep the gradient iterate with the best clean success over this many full runs of "
                        "selection scenarios (counted in the budget; 0: the last iterate)")
    p.add_argument("--select-every", type=int, default=5, help="iterates compared by the selection: every N steps")
    p.add_argument("--offset", type=int, default=0, help="window start, control ticks after the snapshot trigger")
    p.add_argument("--checkpoint-every", type=int, default=5, help="checkpoint period (Adam steps)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--wait", action="store_true", help="if another run is writing DIR, wait for it instead of stopping")
    from hyqjax.cli.common import add_impl_argument

    add_impl_argument(p)  # the forward-only runs; the gradient always runs under impl jax


def validate(args) -> None:
    """Every option checked, the configuration built and the run directory probed before anything is compiled
    or written (a refused command leaves nothing behind)."""
    from hyqjax.cli.common import check_all, check_impl, check_out_free, check_range, prepare_out

    check_impl(args.impl)

    check_range("--steps", args.steps, 0, 100000, integer=True)
    check_range("--lr", args.lr, 0.0, 1.0, lo_open=True)
    for c in args.line_search:
        check_range("--line-search", c, 0.0, 10.0, lo_open=True)
    check_range("--seed", args.seed, 0, 2**32 - 1, integer=True)
    check_all("--train-heights", args.train_heights, 0.0, 0.45, "m")
    check_range("--train-per-height", args.train_per_height, 1, 100000, integer=True)
    check_range("--windows-per-scenario", args.windows_per_scenario, 1, 8, integer=True)
    check_range("--lead", args.lead, 0.0, 60.0, "s", lo_open=True)
    check_range("--window-ticks", args.window_ticks, 1, 20000, integer=True)
    for n in args.prefixes:
        check_range("--prefixes", n, 1, 20000, integer=True)
    check_range("--warm-start", args.warm_start, 0, 10000, integer=True)
    check_range("--sigma", args.sigma, 0.0, 5.0, lo_open=True)
    check_range("--success-instances", args.success_instances, 1, 100000, integer=True)
    check_range("--success-duration", args.success_duration, 1.0, 120.0, "s")
    check_range("--heldout", args.heldout, 0, 10**6, integer=True)
    check_range("--heldout-seed", args.heldout_seed, 0, 2**32 - 1, integer=True)
    check_range("--heldout-duration", args.heldout_duration, 1.0, 120.0, "s")
    check_range("--curve-instances", args.curve_instances, 0, 10**6, integer=True)
    check_range("--baseline-wall-s", args.baseline_wall_s, 0.0, 1e7, "s")
    check_range("--offset", args.offset, 0, 5000, integer=True)
    check_range("--select-instances", args.select_instances, 0, 100000, integer=True)
    check_range("--select-every", args.select_every, 1, 100000, integer=True)
    check_range("--checkpoint-every", args.checkpoint_every, 1, 100000, integer=True)
    bad = [b for b in _names(args.baselines) if b not in BASELINES]
    if bad:
        raise ValueError(f"--baselines must be a subset of {list(BASELINES)}, got {bad}")
    from hyqjax.studies.tune import space  # the groups' declarations (JAX's parameter classes, no MJX)

    try:
        space.ParamSpace.make(_names(args.groups))
    except ValueError as e:
        raise ValueError(f"--groups: {e}") from None
    check_out_free(args.out)
    prepare_out(args.out)
    args.options_checked = True


def _names(text: str) -> tuple:
    return tuple(x.strip() for x in text.split(",") if x.strip())


def _config(args):
    """The study configuration; its own checks (groups, baselines, ...) name the option that was given."""
    from hyqjax.studies.tune import objective, optimize, study, windows

    groups, base_list = _names(args.groups), _names(args.baselines)
    try:
        return study.StudyConfig(
            objective=args.objective, groups=groups, seed=args.seed, train_per_height=args.train_per_height,
            train_heights=tuple(args.train_heights),
            window=windows.WindowSpec(per_scenario=args.windows_per_scenario, lead=args.lead, offset=args.offset),
            loss=objective.ClosedLoopObjective(ticks=args.window_ticks,
                                               prefixes=tuple(n for n in args.prefixes if n < args.window_ticks)),
            adam=optimize.AdamConfig(steps=args.steps, lr=args.lr, checkpoint_every=args.checkpoint_every,
                                     line_search=tuple(args.line_search)),
            warm_start=args.warm_start, baselines=base_list, sigma=args.sigma,
            success_instances=args.success_instances, success_duration=args.success_duration,
            heldout=args.heldout, heldout_seed=args.heldout_seed, heldout_duration=args.heldout_duration,
            curve_instances=args.curve_instances, baseline_wall_s=args.baseline_wall_s, impl=args.impl,
            remedy=not args.paper_crawl, select_instances=args.select_instances, select_every=args.select_every)
    except ValueError as e:
        msg = str(e)
        for field in ("groups", "baselines", "objective"):
            if field in msg.split(" ")[0] or msg.startswith(field):
                raise ValueError(f"--{field}: {msg}") from None
        raise ValueError(f"invalid tuning setting: {msg}") from None


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    from hyqjax.io.lock import DirLock

    # The run directory's lock first, before anything heavy is imported: a second run stops (or waits) at once.
    with DirLock(args.out, wait=args.wait, what="tune run"):
        return _run_locked(args)


def _run_locked(args) -> int:
    from hyqjax.cli.common import UsageError

    try:
        cfg = args.study_config = _config(args)
    except ValueError as e:
        raise UsageError(str(e)) from None
    groups, base_list = cfg.groups, cfg.baselines
    from hyqjax.studies.tune import figure, study

    print(f"hyqjax tune: {cfg.objective} objective, {cfg.adam.steps} steps, groups {list(groups)}, "
          f"baselines {list(base_list)}, out {args.out}", flush=True)
    res = study.run_study(cfg, args.out, progress=not args.no_progress, log=lambda s: print(s, flush=True),
                          locked=True)
    import os

    fig = figure.plot_study(res, os.path.join(args.out, "tuning.png"))
    print(figure.summary_markdown(res))
    print(f"wrote {args.out}/results.json and {fig} ({res['wall_s']:.0f} s)")
    return 0
