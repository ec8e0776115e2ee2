"""The tuning studies behind ``hyqjax tune`` (docs/tuning.md): the equal-wall-clock method study (the default mode),
the guided-ES comparison (``--guided-comparison``) and the gradient study at equal physics budget
(``--gradient-study``).

    python -m experiments.tune_study --out out/tune_study --impl warp --wall-minutes 0.25 0.5   # ~12 min, one H100
    python -m experiments.tune_study --out out/tune_study --impl warp --wall-minutes 1 3 10     # the full curves
    python -m experiments.tune_study --guided-comparison --out out/guided --impl warp --wall-minutes 3 10 --seeds 0,1,2,3,4
    python -m experiments.tune_study --gradient-study --out out/tune_gradient --steps 20

The equal-wall-clock study (:mod:`hyqjax.studies.tune.wallclock`) runs every method in ``--methods`` on every
parameterisation in ``--dims`` under the same wall-clock budget (compile included), then evaluates what each
returns on the held-out set. ``--guided-comparison`` is that study for guided ES (MJX-JAX surrogate gradients
inside the search, ``hyqjax.studies.tune.guided.run_guided``) against CMA-ES and SNES on 56 and 68 coordinates,
once per seed of ``--seeds`` (DIR/seed<N>/), with the held-out clean success of every run, the mean and t-interval
over seeds per method and parameterisation, and guided ES's per-generation cosine between the surrogate gradient and
the population's own gradient estimate in DIR/comparison.json. Every option of ``hyqjax tune`` applies; bad
settings are refused in one line before anything compiles, and the same command on the same ``--out`` resumes
without losing finished runs or held-out chunks.
"""
from __future__ import annotations

import argparse
import os
import subprocess

#: Baselines of the gradient study (``--baselines``: the names of :data:`hyqjax.studies.tune.study.gradient.METHODS`
#: after the gradient), checked before anything heavy is imported.
BASELINES = ("cma_es", "random_search", "cma_es_success", "random_search_success")
#: Options only the gradient study uses (refused elsewhere) and their defaults.
GRADIENT_STUDY_ONLY = dict(surrogate="closed_loop", steps=20, line_search=(0.125, 0.25, 0.5, 1.0, 2.0),
                           prefixes=(50, 125, 250, 500), warm_start=0, baselines=",".join(BASELINES),
                           success_instances=8, success_duration=24.0, curve_instances=0, baseline_wall_s=0.0,
                           offset=0, checkpoint_every=5)
#: Options of the wall-clock modes that the gradient study refuses.
WALLCLOCK_ONLY = ("select_every_s", "select_seed", "grad_directions", "grad_mode", "cold_compile", "retake_windows",
                  "train_spread", "contacts_from_distance", "state_every_s", "segment_minutes", "guided_alpha",
                  "guided_subspace", "guided_lr", "guided_grad_every", "blend_gamma", "blend_lr",
                  "restart_stall", "surrogate_weights")
#: ``--guided-comparison``: the methods and parameterisations compared (each may be narrowed by --methods / --dims).
GUIDED_COMPARISON = dict(methods=("guided_es", "cma_es", "snes"), dims=("per_leg", "per_leg_cond"))


def build_parser() -> argparse.ArgumentParser:
    from hyqjax.cli import tune
    from hyqjax.cli.app import Parser
    from hyqjax.cli.common import HelpFormatter

    H = tune.HIDDEN
    p = Parser(prog="python -m experiments.tune_study", description=__doc__,
               formatter_class=HelpFormatter)
    p.add_argument("--debug", action="store_true", help="show the traceback of an error")
    p.add_argument("--no-cache", action="store_true", help="do not use JAX's persistent compilation cache")
    tune.add_arguments(p)
    m = p.add_argument_group("modes (default: the equal-wall-clock study)")
    m.add_argument("--gradient-study", action="store_true",
                   help="the gradient study at equal physics budget (its own group of options below)")
    m.add_argument("--guided-comparison", action="store_true",
                   help="guided ES against CMA-ES and SNES on 56 and 68 coordinates, once per --seeds")
    m.add_argument("--seeds", type=tune.ints, default=None,
                   help="--guided-comparison: training seeds, one study each in DIR/seed<N> (default 0,1,2,3,4)")
    m.add_argument("--gpus", type=int, default=1,
                   help="--guided-comparison: one process per GPU (CUDA_VISIBLE_DEVICES), each with its share of "
                        "--seeds, so every study has a whole GPU for its clocks; their logs in DIR/gpu<K>.log, "
                        "then the comparison over every finished seed (default 1: the seeds one after another)")
    g = p.add_argument_group("the equal-wall-clock study")
    g.add_argument("--train-instances", type=int, default=H["train_instances"],
                   help="training scenarios per generation, the same for every member (a multiple of the number "
                        "of training heights, 4)")
    g.add_argument("--train-duration", type=float, default=H["train_duration"], help="simulated seconds of a training run")
    g.add_argument("--completed-weight", type=float, default=H["completed_weight"],
                   help="fitness = clean + this x completed (completion breaks ties)")
    g.add_argument("--hybrid-split", type=float, default=H["hybrid_split"],
                   help="share of the budget the hybrid searches first")
    g.add_argument("--heldout-chunk", type=int, default=H["heldout_chunk"], help="parameter sets per held-out batch")
    g.add_argument("--no-compile-charge", action="store_true",
                   help="do not charge each method the compile of its programs (default: charged, as a stand-alone "
                        "run pays it)")
    g.add_argument("--cold-compile", action="store_true",
                   help="compile every program cold: JAX's persistent cache and Warp's kernel cache in a fresh empty "
                        "directory of this process, so a method run in its own process (--methods one,name) pays the "
                        "compile a first run pays; runs of one study may be split over processes into one --out")
    g.add_argument("--state-every-s", type=float, default=H["state_every_s"],
                   help="seconds between two stores of the running method's state (0: after every iteration)")
    g.add_argument("--retake-windows", action="store_true",
                   help="the hybrid re-takes the gradient's snapshot windows under the iterate its gradient starts "
                        "from (paid from its clock), instead of descending from the start point's gait")
    g.add_argument("--select-every-s", type=float, default=H["select_every_s"],
                   help="selection: also validate the iterate when this many seconds of the method's clock have "
                        "passed since the last validation (0: by iterations only, --select-every)")
    g.add_argument("--select-seed", type=int, default=H["select_seed"],
                   help="seed of the fixed validation scenarios of the selection")
    g.add_argument("--grad-directions", type=int, default=H["grad_directions"],
                   help="tangents of the gradient's tuning step: 0 = exact jacfwd (one per parameter); K > 0 = the "
                        "unbiased forward-gradient estimate from K random directions")
    g.add_argument("--grad-mode", default=H["grad_mode"], choices=["jacfwd", "reverse"],
                   help="exact tuning step: jacfwd (a tangent per parameter) or reverse (cost independent of them)")
    g.add_argument("--contacts-from-distance", type=float, default=H["contacts_from_distance"], metavar="N_PER_M",
                   help="backward-only springs under the feet in the gradient's windows (2 cm reach); 0: off")
    g.add_argument("--train-spread", default=None, choices=["train", "wide"],
                   help="training draws' ranges (default: train for --objective clean, as every stored study ran; "
                        "wide for reach; hyqjax tune trains on wide)")
    g.add_argument("--train-heights", type=tune.floats, default=None,
                   help="training heights (m), comma-separated (default: --objective's)")
    g.add_argument("--paper-crawl", action="store_true",
                   help="tune the paper's crawl (no shin-strike remedy); default: the crawl with the remedy")
    g.add_argument("--lr", type=float, default=H["lr"], help="Adam learning rate of the gradient methods")
    g.add_argument("--train-per-height", type=int, default=H["train_per_height"],
                   help="scenarios per height of the gradient's snapshot windows")
    g.add_argument("--windows-per-scenario", type=int, default=H["windows_per_scenario"],
                   help="snapshot windows per scenario (legs over the edge)")
    g.add_argument("--lead", type=float, default=H["lead"], help="forward run that takes the snapshots (s)")
    g.add_argument("--window-ticks", type=int, default=None,
                   help="window length (control ticks of 2 ms; default 500, 750 with --gradient-study)")
    g.add_argument("--heldout-seed", type=int, default=H["heldout_seed"], help="held-out seed (never used for training)")
    g.add_argument("--heldout-duration", type=float, default=H["heldout_duration"],
                   help="simulated seconds per held-out instance")
    g.add_argument("--select-instances", type=int, default=None,
                   help="closed-loop selection: the returned iterate is the best by clean success over this many "
                        "fixed validation runs (paid from the budget; 0: the last iterate); default (popsize + 1) x "
                        "train-instances; --gradient-study: 16")
    g.add_argument("--select-every", type=int, default=H["select_every"],
                   help="iterates compared by the selection: every N iterations")
    g.add_argument("--guided-alpha", type=float, default=H["guided_alpha"],
                   help="guided ES: share of the sampling variance in the full space (1: isotropic ES, OpenES's "
                        "samples; the rest in the subspace of the recent surrogate gradients); the variance in all "
                        "is --sigma^2 a coordinate, as for the other methods")
    g.add_argument("--surrogate-weights", nargs="+", default=H["surrogate_weights"], metavar="TERM=W",
                   help="guided ES, the blend, the hybrid: the window objective's term weights other than their "
                        "defaults, e.g. mobility=0 progress=0 stability=0 (terms: clearance, joint, workspace, "
                        "foothold, tilt, mobility, progress, stability; hyqjax.studies.tune.objective)")
    g.add_argument("--guided-subspace", type=int, default=H["guided_subspace"],
                   help="guided ES: number of recent surrogate gradients spanning the guiding subspace")
    g.add_argument("--guided-lr", type=float, default=H["guided_lr"], help="guided ES: Adam learning rate of the mean")
    g.add_argument("--guided-grad-every", type=int, default=H["guided_grad_every"],
                   help="guided ES: a new surrogate gradient every N generations")
    g.add_argument("--blend-gamma", type=float, default=H["blend_gamma"],
                   help="blend: the bias the alpha-order blend may take, relative to the zero-order estimate's norm "
                        "(Suh et al.'s gamma)")
    g.add_argument("--blend-lr", type=float, default=H["blend_lr"], help="blend: Adam learning rate of the iterate")
    g.add_argument("--restart-stall", type=int, default=H["restart_stall"],
                   help="ipop_cma_es / bipop_cma_es: generations without a better validated score that end a run "
                        "(0: the papers' lengths)")
    s = p.add_argument_group("the gradient study at equal physics budget (--gradient-study)")
    d = GRADIENT_STUDY_ONLY
    s.add_argument("--surrogate", default=d["surrogate"], choices=["closed_loop", "kinematic"],
                   help="closed_loop: jacfwd through MJX windows; kinematic: the reflex-only surrogate")
    s.add_argument("--steps", type=int, default=d["steps"], help="Adam steps (total, across resumes)")
    s.add_argument("--line-search", type=tune.floats, default=d["line_search"],
                   help="scales of the Adam update tried per step; '' for plain Adam")
    s.add_argument("--prefixes", type=tune.ints, default=d["prefixes"],
                   help="shorter window lengths (ticks) at which the gradient statistics are also reported")
    s.add_argument("--warm-start", type=int, default=d["warm_start"], help="kinematic-surrogate steps before the closed loop")
    s.add_argument("--baselines", default=d["baselines"], help="baselines at the same budget (comma-separated)")
    s.add_argument("--success-instances", type=int, default=d["success_instances"],
                   help="full runs per candidate for the success baselines")
    s.add_argument("--success-duration", type=float, default=d["success_duration"], help="simulated seconds of those runs")
    s.add_argument("--curve-instances", type=int, default=d["curve_instances"],
                   help="held-out instances per point of the success-vs-budget curve (0: final points only)")
    s.add_argument("--baseline-wall-s", type=float, default=d["baseline_wall_s"],
                   help="also stop each success baseline after this many wall seconds (0: budget only)")
    s.add_argument("--offset", type=int, default=d["offset"], help="window start, control ticks after the snapshot trigger")
    s.add_argument("--checkpoint-every", type=int, default=d["checkpoint_every"], help="checkpoint period (Adam steps)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(run_command=run, validate_command=validate)
    return p


def validate(args) -> None:
    """Every option checked in one line before anything compiles or is written."""
    from hyqjax.cli import tune
    from hyqjax.cli.common import UsageError

    if args.quick:
        raise UsageError("--quick is a small version of hyqjax tune; it does not combine with a study")
    if args.gradient_study and args.guided_comparison:
        raise UsageError("--gradient-study and --guided-comparison are two different studies; give one")
    if args.seeds is not None and not args.guided_comparison:
        raise UsageError("--seeds belongs to --guided-comparison (one study per seed)")
    if args.gpus != 1 and not args.guided_comparison:
        raise UsageError("--gpus belongs to --guided-comparison (one process per GPU, each with its own seeds)")
    if not 1 <= args.gpus <= 64:
        raise UsageError(f"--gpus must be in [1, 64], got {args.gpus}")
    if args.gradient_study:
        return _validate_gradient_study(args)
    for k, v in GRADIENT_STUDY_ONLY.items():
        if getattr(args, k) != v:
            raise UsageError(f"--{k.replace('_', '-')} belongs to --gradient-study; the wall-clock study does not use it")
    args.study = True
    if args.guided_comparison:
        args.methods = args.methods or GUIDED_COMPARISON["methods"]
        args.dims = args.dims or GUIDED_COMPARISON["dims"]
        args.seeds = args.seeds if args.seeds is not None else (0, 1, 2, 3, 4)
        if not args.seeds or len(set(args.seeds)) != len(args.seeds):
            raise UsageError(f"--seeds must be distinct seeds, got {','.join(map(str, args.seeds)) or 'nothing'}")
        for s in args.seeds:
            if s == args.heldout_seed or not 0 <= s < 2**31:
                raise UsageError(f"--seeds must be in [0, 2^31) and differ from --heldout-seed {args.heldout_seed}, "
                                 f"got {s}")
        out, configs = args.out, []
        for s in args.seeds:  # every seed's configuration and directory checked before any runs
            args.seed, args.out, args.options_checked = s, os.path.join(out, f"seed{s}"), False
            tune.validate_wallclock(args)
            configs.append((s, args.out, args.wallclock_config))
        args.out, args.seed, args.comparison = out, args.seeds[0], configs
        return None
    tune.validate_wallclock(args)


def _validate_gradient_study(args) -> None:
    """Every option of ``--gradient-study`` checked in one line before anything compiles; an option of the
    wall-clock modes given a value is refused."""
    from hyqjax.cli import tune
    from hyqjax.cli.common import UsageError, check_all, check_out_free, check_impl, check_range, prepare_out

    for opt, val in (("--method", args.methods), ("--dim", args.dims), ("--wall-minutes", args.wall_minutes),
                     ("--start-from", args.start_from or None), ("--preset", args.preset)):
        if val is not None:
            raise UsageError(f"{opt} belongs to the wall-clock studies, not to --gradient-study")
    check_impl(args.impl)
    for k in WALLCLOCK_ONLY:
        if getattr(args, k) != tune.HIDDEN.get(k):
            raise UsageError(f"--{k.replace('_', '-')} belongs to the wall-clock studies, not to --gradient-study")
    if args.objective != "clean":
        raise UsageError("--objective belongs to the wall-clock studies, not to --gradient-study")
    args.train_heights = args.train_heights or tune.OBJECTIVES["clean"][0]
    args.window_ticks = 750 if args.window_ticks is None else args.window_ticks
    args.sigma = 0.5 if args.sigma is None else args.sigma
    args.heldout = 36 if args.heldout is None else args.heldout
    args.select_instances = 16 if args.select_instances is None else args.select_instances
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
    bad = [b for b in tune.split_names(args.baselines) if b not in BASELINES]
    if bad:
        raise UsageError(f"--baselines must be a subset of {list(BASELINES)}, got {bad}")
    from hyqjax.studies.tune import space  # the groups' declarations (JAX's parameter classes, no MJX)

    try:
        space.ParamSpace.make(tune.split_names(args.groups))
    except ValueError as e:
        raise UsageError(f"--groups: {e}") from None
    check_out_free(args.out)
    prepare_out(args.out)
    args.options_checked = True


def _gradient_study_config(args):
    """The gradient study's configuration; its own checks (groups, baselines, ...) name the option that was given."""
    from hyqjax.cli import tune
    from hyqjax.studies.tune import objective, optimize, windows
    from hyqjax.studies.tune.study import gradient as study

    groups, base_list = tune.split_names(args.groups), tune.split_names(args.baselines)
    try:
        return study.StudyConfig(
            objective=args.surrogate, groups=groups, seed=args.seed, train_per_height=args.train_per_height,
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
        for field, opt in (("groups", "groups"), ("baselines", "baselines"), ("objective", "surrogate")):
            if field in msg.split(" ")[0] or msg.startswith(field):
                raise ValueError(f"--{opt}: {msg}") from None
        raise ValueError(f"invalid tuning setting: {msg}") from None


def _run_gradient_study(args) -> int:
    from hyqjax.cli.common import UsageError

    try:
        cfg = args.study_config = _gradient_study_config(args)
    except ValueError as e:
        raise UsageError(str(e)) from None
    from hyqjax.studies.tune import figure
    from hyqjax.studies.tune.study import gradient as study

    print(f"tune_study: gradient study, {cfg.objective} objective, {cfg.adam.steps} steps, groups {list(cfg.groups)}, "
          f"baselines {list(cfg.baselines)}, out {args.out}", flush=True)
    res = study.run_study(cfg, args.out, progress=not args.no_progress, log=lambda s: print(s, flush=True),
                          locked=True)
    fig = figure.plot_study(res, os.path.join(args.out, "tuning.png"))
    print(figure.summary_markdown(res))
    print(f"wrote {args.out}/results.json and {fig} ({res['wall_s']:.0f} s)")
    return 0


def _run_comparison(args) -> int:
    """``--guided-comparison``: one equal-wall-clock study per seed in DIR/seed<N> (each locked on its own, so
    processes with other ``--seeds`` may share DIR, one per GPU), then DIR/comparison.json over every finished
    seed directory in DIR; ``--gpus K``: the seeds spread over K processes, one per GPU."""
    from hyqjax.cli import tune_wallclock
    from hyqjax.io.lock import DirLock

    out = args.out
    if args.gpus > 1 and len(args.comparison) > 1:
        from hyqjax.io import phases

        rc = _spread_over_gpus(args) or _write_comparison(args, out)
        clock = phases.current()
        clock.lap("tuning")  # the processes of every GPU, their searches and held-out evaluations
        print(clock.line(), flush=True)
        return rc
    for seed, seed_out, cfg in args.comparison:
        args.out, args.seed, args.wallclock_config = seed_out, seed, cfg
        print(f"tune_study: guided comparison, seed {seed} -> {seed_out}", flush=True)
        with DirLock(seed_out, wait=args.wait, what="tune study"):
            rc = tune_wallclock.run(args)
        if rc:
            return rc
    args.out = out
    return _write_comparison(args, out)


def finished_seeds(out: str) -> dict:
    """Seed -> ``results.json`` of every finished study (``complete``) in the seed directories of ``out``."""
    import glob
    import json

    results = {}
    for path in sorted(glob.glob(os.path.join(out, "seed*", "results.json"))):
        with open(path) as f:
            res = json.load(f)
        if res.get("complete"):
            results[int(res["config"]["seed"])] = res
    return results


def _write_comparison(args, out: str) -> int:
    """DIR/comparison.json and comparison.md over every finished seed directory in ``out`` (atomic writes: the
    processes of other seeds may write them too)."""
    from hyqjax.io.atomic import atomic_write, write_json
    from hyqjax.studies.tune.study import guided as guided_report

    results = finished_seeds(out)
    comp = guided_report.compare(results, args.comparison[0][2].wall_minutes[-1])
    path = os.path.join(out, "comparison.json")
    write_json(path, comp)
    table = guided_report.markdown(comp)
    atomic_write(os.path.join(out, "comparison.md"), lambda f: f.write((table + "\n").encode()))
    print(table)
    print(f"wrote {path} and comparison.md ({len(results)} seeds: {', '.join(map(str, sorted(results)))})")
    return 0


def child_argv(argv: list[str], seeds) -> list[str]:
    """``argv`` (this command's arguments) without ``--gpus`` and ``--seeds``, then ``--seeds`` ``seeds``: the
    command of one GPU's process."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in ("--gpus", "--seeds"):
            skip = True
            continue
        if a.startswith(("--gpus=", "--seeds=")):
            continue
        out.append(a)
    return out + ["--seeds", ",".join(map(str, seeds))]


def _spread_over_gpus(args) -> int:
    """``--gpus K``: the seeds dealt round-robin to ``K`` processes of this command, each on a GPU of its own
    (``CUDA_VISIBLE_DEVICES``); waits for all of them. Exit status: a failed process's, else 75 when one stopped
    after its segment (the same command goes on), else 0."""
    import sys
    import time

    from experiments.gpu_slots import gpu_slots

    seeds = [s for s, _, _ in args.comparison]
    k = min(args.gpus, len(seeds))
    procs = []
    for slot, group in zip(gpu_slots(k), [seeds[i::k] for i in range(k)]):
        cmd = [sys.executable, "-m", "experiments.tune_study", *child_argv(args.raw_argv, group)]
        log_path = os.path.join(args.out, f"gpu{slot}.log")
        os.makedirs(args.out, exist_ok=True)
        log = open(log_path, "a")
        print(f"[{time.strftime('%H:%M:%S')}] seeds {','.join(map(str, group))} on GPU {slot} (log {log_path})",
              flush=True)
        procs.append((slot, group, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                                    env=dict(os.environ, CUDA_VISIBLE_DEVICES=slot)), log))
    codes = []
    for slot, group, proc, log in procs:
        codes.append(proc.wait())
        log.close()
        print(f"[{time.strftime('%H:%M:%S')}] GPU {slot} (seeds {','.join(map(str, group))}): exit status "
              f"{codes[-1]}", flush=True)
    failed = [c for c in codes if c not in (0, 75)]
    return failed[0] if failed else (75 if 75 in codes else 0)


def run(args) -> int:
    if not getattr(args, "options_checked", False) and not getattr(args, "comparison", None):
        validate(args)
    from hyqjax.cli import tune_wallclock
    from hyqjax.io.lock import DirLock

    if args.guided_comparison:
        return _run_comparison(args)
    with DirLock(args.out, wait=args.wait, what="tune study"):
        if args.gradient_study:
            return _run_gradient_study(args)
        return tune_wallclock.run(args)


def main(argv=None) -> int:
    from hyqjax.cli.app import main as app_main

    import sys

    parser = build_parser()
    parser.set_defaults(raw_argv=list(sys.argv[1:] if argv is None else argv))
    return app_main(None if argv is None else list(argv), parser=parser)


if __name__ == "__main__":
    raise SystemExit(main())
