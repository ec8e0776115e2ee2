"""Tune the height reflex and the crawl for the step-down (hyqjax.studies.tune, docs/tuning.md). Three modes:

* default: the tuner the equal-wall-clock study chose (``names.DEFAULT_METHOD`` on
  ``names.DEFAULT_DIM``) for ``--wall-minutes`` (1 3 10), then the held-out evaluation of what it returns
  next to the start point's and Table I's, and the budget-curve figure (DIR/results.json, DIR/tuning.png);
  ``--quick`` is a small version for a CPU (a few minutes; it checks the pipeline, its numbers mean little);
* ``--study``: the equal-wall-clock study (every method in ``--methods`` on every parameterisation in
  ``--dims``, held-out budget curves against wall-clock and physics steps; hyqjax.studies.tune.wallclock);
* ``--gradient-study``: the gradient study at equal physics budget (hyqjax.studies.tune.study), where

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

from hyqjax.cli import tune_gradient_study as gradient_study
from hyqjax.cli import tune_wallclock as wallclock_run
from hyqjax.cli.tune_gradient_study import BASELINES, split_names

NAME = "tune"
HELP = "tune the height reflex and crawl on the closed-loop step-down (search, gradient, equal-wall-clock study)"
ORDER = 30


def _floats(s):
    return tuple(float(x) for x in s.split(",") if x.strip())


def _ints(s):
    return tuple(int(x) for x in s.split(",") if x.strip())


#: Settings of ``--quick`` (a CPU-sized default run; every value can still be given explicitly).
QUICK = dict(wall_minutes=(1.5, 2.5), popsize=3, train_instances=4, heldout=4, heldout_chunk=4, window_ticks=100,
             grad_train_per_height=1)


#: Options only the gradient study (--gradient-study) uses: refused elsewhere.
GRADIENT_STUDY_ONLY = ("objective", "steps", "line_search", "prefixes", "warm_start", "baselines",
                       "success_instances", "success_duration", "curve_instances", "baseline_wall_s",
                       "offset", "checkpoint_every")
#: Options only the default tuner and --study use: refused with --gradient-study.
WALLCLOCK_ONLY = ("select_every_s", "select_seed", "grad_directions", "grad_mode", "cold_compile", "retake_windows",
                  "train_spread", "contacts_from_distance", "state_every_s", "segment_minutes")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/tune", help="run directory (a study resumes from it)")
    g = p.add_argument_group("the default tuner and the equal-wall-clock study (--study)")
    g.add_argument("--study", action="store_true",
                   help="the equal-wall-clock study: every method on every parameterisation, held-out budget curves")
    g.add_argument("--quick", action="store_true",
                   help="a small version of the default tuner for a CPU: %s" % ", ".join(
                       f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, tuple) else v}"
                       for k, v in QUICK.items()))
    g.add_argument("--methods", type=split_names, default=None,
                   help="--study: methods, comma-separated, from cma_es, snes, open_es, random_search, gradient, "
                        "hybrid (default: all); default tuner: one method (default: the study's winner)")
    g.add_argument("--dims", type=split_names, default=None,
                   help="parameterisations, comma-separated, from shared (14), per_leg (56), per_leg_cond (68), "
                        "per_leg_cond_all (98) (--study default: shared,per_leg_cond)")
    g.add_argument("--wall-minutes", type=float, nargs="+", default=None,
                   help="wall-clock checkpoints per method (minutes, increasing; the last is the budget; compile "
                        "included). Default 1 3 10")
    g.add_argument("--popsize", type=int, default=16, help="population of the search methods (per generation)")
    g.add_argument("--train-instances", type=int, default=32,
                   help="training scenarios per generation, the same for every member (a multiple of 4)")
    g.add_argument("--train-duration", type=float, default=24.0, help="simulated seconds of a training run")
    g.add_argument("--completed-weight", type=float, default=0.1,
                   help="fitness = clean + this x completed (completion breaks ties)")
    g.add_argument("--hybrid-split", type=float, default=0.5, help="share of the budget the hybrid searches first")
    g.add_argument("--heldout-chunk", type=int, default=8, help="parameter sets per held-out batch")
    g.add_argument("--no-compile-charge", action="store_true",
                   help="do not charge each method the compile of its programs (default: charged, as a stand-alone "
                        "run pays it)")
    g.add_argument("--cold-compile", action="store_true",
                   help="compile every program cold: JAX's persistent cache and Warp's kernel cache in a fresh empty "
                        "directory of this process, so a method run in its own process (--methods one,name) pays the "
                        "compile a first run pays; runs of one study may be split over processes into one --out")
    g.add_argument("--state-every-s", type=float, default=30.0,
                   help="seconds between two stores of the running method's state (its search or gradient state, "
                        "clock and trace), from which the same command resumes it after a kill (0: after every "
                        "iteration; default 30)")
    g.add_argument("--segment-minutes", type=float, default=None,
                   help="stop after this many minutes of this process, storing the running method's state, and "
                        "exit with status 75; the same command goes on from there (a budget longer than one machine "
                        "lease runs in segments; default: no stop)")
    g.add_argument("--retake-windows", action="store_true",
                   help="the hybrid re-takes the gradient's snapshot windows under the iterate its gradient starts "
                        "from (paid from its clock), instead of descending from the start point's gait")
    g.add_argument("--select-every-s", type=float, default=0.0,
                   help="selection: also validate the iterate when this many seconds of the method's clock have "
                        "passed since the last validation (0: by iterations only, --select-every)")
    g.add_argument("--select-seed", type=int, default=5555,
                   help="seed of the fixed validation scenarios of the selection (drawn like training; never the "
                        "training or held-out seeds)")
    g.add_argument("--grad-directions", type=int, default=0,
                   help="tangents of the gradient's tuning step: 0 = exact jacfwd (one per parameter); K > 0 = the "
                        "unbiased forward-gradient estimate from K random directions (cheaper, noisier)")
    g.add_argument("--grad-mode", default="jacfwd", choices=["jacfwd", "reverse"],
                   help="exact tuning step: jacfwd (a tangent per parameter) or reverse (cost independent of them)")
    g.add_argument("--contacts-from-distance", type=float, default=0.0, metavar="N_PER_M",
                   help="backward-only springs under the feet in the gradient's windows (2 cm reach); 0: off")
    g.add_argument("--train-spread", default="train", choices=["train", "wide"],
                   help="training draws' ranges: train, or wide (the reach map's; with --train-heights 0.24,...,0.30 "
                        "the reach is the objective)")
    g.add_argument("--start-from", default="",
                   help="warm start: a results.json of an earlier default run or study; its last iterate of the "
                        "same method and parameterisation is the start")
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
    p.add_argument("--train-heights", type=_floats, default=(0.16, 0.20, 0.24, 0.28),
                   help="training heights (m), comma-separated (every mode; the search methods draw train-instances / "
                        "their number per height)")
    p.add_argument("--train-per-height", type=int, default=2, help="training scenarios per height")
    p.add_argument("--windows-per-scenario", type=int, default=2, help="snapshot windows per scenario (legs over the edge)")
    p.add_argument("--lead", type=float, default=10.0, help="forward run that takes the snapshots (s)")
    p.add_argument("--window-ticks", type=int, default=None,
                   help="window length (control ticks of 2 ms; default 750, 500 in the wall-clock modes)")
    p.add_argument("--prefixes", type=_ints, default=(50, 125, 250, 500),
                   help="shorter window lengths (ticks) at which the gradient statistics are also reported")
    p.add_argument("--warm-start", type=int, default=0, help="kinematic-surrogate steps before the closed loop")
    p.add_argument("--baselines", default=",".join(BASELINES),
                   help="baselines at the same budget (comma-separated; empty for none)")
    p.add_argument("--sigma", type=float, default=None,
                   help="initial step of the search methods (theta units; default 0.5, 0.3 in the wall-clock modes)")
    p.add_argument("--success-instances", type=int, default=8, help="full runs per candidate for the success baselines")
    p.add_argument("--success-duration", type=float, default=24.0, help="simulated seconds of those runs")
    p.add_argument("--heldout", type=int, default=None,
                   help="held-out closed-loop instances per parameter set (default 2000; 36 with --gradient-study, "
                        "where 0 skips)")
    p.add_argument("--heldout-seed", type=int, default=7777, help="held-out seed (never used for training)")
    p.add_argument("--heldout-duration", type=float, default=24.0, help="simulated seconds per held-out instance")
    p.add_argument("--curve-instances", type=int, default=0,
                   help="held-out instances per point of the success-vs-budget curve (0: final points only)")
    p.add_argument("--baseline-wall-s", type=float, default=0.0,
                   help="also stop each success baseline after this many wall seconds (0: budget only; the "
                        "window-objective baselines always get the whole budget)")
    p.add_argument("--select-instances", type=int, default=None,
                   help="closed-loop selection: return the iterate with the best clean success over this many fixed "
                        "validation runs (paid from the budget; 0: the last iterate). --study and the default tuner: "
                        "every method's, validated every --select-every iterations; default (popsize + 1) x "
                        "train-instances (544), the rows of a generation, so it runs on the program the search "
                        "compiled. --gradient-study: the gradient's, default 16")
    p.add_argument("--select-every", type=int, default=5,
                   help="iterates compared by the selection: every N iterations (generations or steps; --study: 0 "
                        "with --select-every-s for time only)")
    p.add_argument("--gradient-study", action="store_true",
                   help="the gradient study at equal physics budget (the options above this group's)")
    p.add_argument("--offset", type=int, default=0, help="window start, control ticks after the snapshot trigger")
    p.add_argument("--checkpoint-every", type=int, default=5, help="checkpoint period (Adam steps)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--wait", action="store_true", help="if another run is writing DIR, wait for it instead of stopping")
    from hyqjax.cli.common import add_impl_argument

    add_impl_argument(p)  # the forward-only runs; the gradient always runs under impl jax


def validate(args) -> None:
    """Every option checked, the configuration built and the run directory probed before anything is compiled
    or written (a refused command leaves nothing behind)."""
    from hyqjax.cli.common import UsageError

    if args.study and args.gradient_study:
        raise UsageError("--study and --gradient-study are two different studies; give one")
    if args.quick and (args.study or args.gradient_study):
        raise UsageError("--quick is a small version of the default tuner; it does not combine with --study or "
                         "--gradient-study")
    if args.gradient_study:
        return gradient_study.validate(args, {k: getattr(_defaults(), k) for k in WALLCLOCK_ONLY})
    return _validate_wallclock(args)


def _validate_wallclock(args) -> None:
    """The default tuner and --study: every setting checked in one line before anything compiles."""
    from hyqjax.cli.common import UsageError, check_all, check_impl, check_out_free, check_range, prepare_out
    from hyqjax.studies.tune import names

    check_impl(args.impl)
    defaults = _defaults()
    for k in GRADIENT_STUDY_ONLY:
        if getattr(args, k) != getattr(defaults, k):
            raise UsageError(f"--{k.replace('_', '-')} belongs to --gradient-study; the default tuner and --study "
                             f"do not use it")
    if args.quick:
        for k, v in QUICK.items():
            if getattr(args, k, None) in (None, getattr(defaults, k, None)):
                setattr(args, k, v)
    wm = tuple(args.wall_minutes) if args.wall_minutes else (1.0, 3.0, 10.0)
    check_all("--wall-minutes", wm, 0.0, 600.0, "min", lo_open=True)
    if list(wm) != sorted(set(wm)):
        raise UsageError(f"--wall-minutes must be increasing, got {' '.join(f'{x:g}' for x in wm)}")
    if args.study:
        methods = args.methods if args.methods is not None else names.METHODS
        dims = args.dims if args.dims is not None else ("shared", "per_leg_cond")
    else:
        methods = args.methods if args.methods is not None else (names.DEFAULT_METHOD,)
        dims = args.dims if args.dims is not None else (names.DEFAULT_DIM,)
        if len(methods) != 1 or len(dims) != 1:
            raise UsageError(f"--methods and --dims take one name each without --study, got "
                             f"{','.join(methods)} / {','.join(dims)}")
    for opt, vals, allowed in (("--methods", methods, names.METHODS), ("--dims", dims, names.DIMS)):
        bad = [v for v in vals if v not in allowed]
        if bad or not vals:
            raise UsageError(f"{opt} must be names among {','.join(allowed)}, got {','.join(vals) or 'nothing'}")
        if len(set(vals)) != len(vals):
            raise UsageError(f"{opt} names a method or parameterisation twice: {','.join(vals)}")
    check_range("--popsize", args.popsize, 2, 4096, integer=True)
    check_range("--train-instances", args.train_instances, 4, 100000, integer=True)
    if args.train_instances % 4:
        raise UsageError(f"--train-instances must be a multiple of 4 (one share per training height), "
                         f"got {args.train_instances}")
    check_range("--train-duration", args.train_duration, 0.1, 120.0, "s")
    check_range("--completed-weight", args.completed_weight, 0.0, 10.0)
    check_range("--hybrid-split", args.hybrid_split, 0.0, 1.0, lo_open=True, hi_open=True)
    check_range("--heldout-chunk", args.heldout_chunk, 1, 4096, integer=True)
    args.window_ticks = 500 if args.window_ticks is None else args.window_ticks
    args.sigma = 0.3 if args.sigma is None else args.sigma
    args.heldout = 2000 if args.heldout is None else args.heldout
    check_range("--window-ticks", args.window_ticks, 1, 20000, integer=True)
    check_range("--sigma", args.sigma, 0.0, 5.0, lo_open=True)
    check_range("--heldout", args.heldout, 1, 10**6, integer=True)
    check_range("--seed", args.seed, 0, 2**31 - 1, integer=True)
    check_range("--heldout-seed", args.heldout_seed, 0, 2**31 - 1, integer=True)
    check_range("--heldout-duration", args.heldout_duration, 1.0, 120.0, "s")
    check_range("--train-per-height", args.train_per_height, 1, 1000, integer=True)
    check_range("--windows-per-scenario", args.windows_per_scenario, 1, 8, integer=True)
    check_range("--lead", args.lead, 0.1, 60.0, "s")
    check_range("--lr", args.lr, 0.0, 1.0, lo_open=True)
    if args.select_instances is None:
        args.select_instances = (args.popsize + 1) * args.train_instances
    check_range("--select-instances", args.select_instances, 0, 10**6, integer=True)
    check_range("--select-every", args.select_every, 0, 10**5, integer=True)
    check_range("--select-every-s", args.select_every_s, 0.0, 3600.0, "s")
    check_range("--select-seed", args.select_seed, 0, 2**31 - 1, integer=True)
    check_range("--grad-directions", args.grad_directions, 0, 4096, integer=True)
    check_range("--state-every-s", args.state_every_s, 0.0, 3600.0, "s")
    if args.segment_minutes is not None:
        check_range("--segment-minutes", args.segment_minutes, 0.0, 600.0, "min", lo_open=True)
    if args.heldout_seed == args.seed:
        raise UsageError(f"--heldout-seed must differ from --seed (the held-out scenarios), got {args.heldout_seed}")
    groups = split_names(args.groups)
    from hyqjax.studies.tune import space  # the groups' declarations (JAX's parameter classes, no MJX)

    try:
        space.ParamSpace.make(groups)
    except ValueError as e:
        raise UsageError(f"--groups: {e}") from None
    from hyqjax.studies.tune import wallclock  # the study itself: MJX and the step-down, after every cheap check

    try:
        cfg = wallclock.WallClockConfig(
            methods=tuple(methods), dims=tuple(dims), wall_minutes=wm, groups=groups, remedy=not args.paper_crawl,
            seed=args.seed, popsize=args.popsize, train_instances=args.train_instances,
            train_duration=args.train_duration, sigma=args.sigma, completed_weight=args.completed_weight,
            grad_train_per_height=getattr(args, "grad_train_per_height", None) or args.train_per_height,
            windows_per_scenario=args.windows_per_scenario, window_lead=args.lead, window_ticks=args.window_ticks,
            lr=args.lr, hybrid_split=args.hybrid_split, heldout=args.heldout, heldout_seed=args.heldout_seed,
            heldout_duration=args.heldout_duration, heldout_chunk=args.heldout_chunk, impl=args.impl,
            charge_compile=not args.no_compile_charge, cold_compile=args.cold_compile,
            select_instances=args.select_instances, select_every=args.select_every,
            select_every_s=args.select_every_s, select_seed=args.select_seed, grad_directions=args.grad_directions,
            retake_windows=args.retake_windows, grad_mode=args.grad_mode,
            contacts_from_distance=args.contacts_from_distance,
            train_heights=tuple(float(h) for h in args.train_heights), train_spread=args.train_spread,
            start_from=_start_from(args.start_from, methods, dims, groups) if args.start_from else ())
    except ValueError as e:
        msg = str(e)
        opt = msg.split(" ")[0].replace("_", "-")
        raise UsageError(f"--{opt}: {msg}" if not msg.startswith("--") else msg) from None
    check_out_free(args.out)
    prepare_out(args.out)
    try:
        wallclock.previous(args.out, cfg)
    except RuntimeError as e:
        raise UsageError(str(e)) from None
    args.wallclock_config = cfg
    args.options_checked = True


def _defaults():
    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args([])


def _start_from(path: str, methods, dims, groups) -> tuple:
    """``(("method/dim", theta), ...)`` from an earlier results.json: each run's last iterate, for the runs of the
    same method and parameterisation; refused in one line when absent or of another size."""
    import json
    import os

    from hyqjax.cli.common import UsageError
    from hyqjax.studies.tune import schedule

    if not os.path.isfile(path):
        raise UsageError(f"--start-from {path}: no such file (give a results.json of an earlier run)")
    try:
        with open(path) as f:
            runs = json.load(f).get("runs", {})
    except (OSError, ValueError) as e:
        raise UsageError(f"--start-from {path}: not a readable results.json ({e.__class__.__name__})") from None
    out = []
    for m in methods:
        for d in dims:
            r = runs.get(f"{m}/{d}")
            if r is None:
                continue
            theta = r.get("theta") or []
            size = schedule.make(d, groups).size
            if len(theta) != size:
                raise UsageError(f"--start-from {path}: {m}/{d} has {len(theta)} parameters, the parameterisation "
                                 f"{d} of --groups has {size}")
            out.append((f"{m}/{d}", tuple(float(x) for x in theta)))
    if not out:
        raise UsageError(f"--start-from {path}: no run of {','.join(methods)} on {','.join(dims)} in it "
                         f"(it holds {', '.join(sorted(runs)) or 'none'})")
    return tuple(out)


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    from hyqjax.io.lock import DirLock

    # The run directory's lock first, before anything heavy is imported: a second run stops (or waits) at once.
    with DirLock(args.out, wait=args.wait, what="tune run"):
        if args.gradient_study:
            return gradient_study.run(args)
        return wallclock_run.run(args)
