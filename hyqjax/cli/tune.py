"""Tune the height reflex and the crawl for the step-down (hyqjax.studies.tune, docs/tuning.md).

One search method on one parameterisation for ``--wall-minutes`` (the last value is the budget; compile
included), then the held-out evaluation of what it returns next to the start point's and Table I's, and the
budget-curve figure (DIR/results.json, DIR/tuning.png). ``--quick`` is a small version for a CPU (a few
minutes; it checks the pipeline, its numbers mean little). ``--objective reach`` trains at heights 24-30 cm (the
reach), ``clean`` at 16-28 cm, both on the wide spread of the held-out sets. ``--start-from`` warm-starts from
an earlier run's results.json.

A killed run resumes: the same command on the same --out goes on from the running method's stored state (every
30 s) and keeps finished held-out chunks; ``--segment-minutes`` stops on purpose (exit status 75) so a long
budget runs in segments. One run at a time holds DIR/.lock (--wait queues behind it); a resume with other
settings is refused in one line, before anything is compiled.

The equal-wall-clock method study and the gradient study at equal physics budget are experiments:
``python -m experiments.tune_study`` (every option of the study, docs/tuning.md).
"""
from __future__ import annotations

import argparse

from hyqjax.cli.common import split_names

NAME = "tune"
HELP = "tune the height reflex and crawl on the closed-loop step-down (CMA-ES, SNES, guided ES, ...)"
ORDER = 30


def floats(s):
    return tuple(float(x) for x in s.split(",") if x.strip())


def ints(s):
    return tuple(int(x) for x in s.split(",") if x.strip())


#: Settings of ``--quick`` (a CPU-sized default run; every value can still be given explicitly).
QUICK = dict(wall_minutes=(1.5, 2.5), popsize=4, train_instances=4, heldout=4, heldout_chunk=4, window_ticks=100,
             grad_train_per_height=1)

#: Training heights and spread per ``--objective`` (an explicit ``--train-spread``, and ``--train-heights`` of
#: ``python -m experiments.tune_study``, win). Both train on the wide spread (friction 0.4-1.0, payload 0-15 kg,
#: start 0-15 cm before the edge): five default runs trained on the narrower training spread (start 0-10 cm)
#: returned sets that validated above their start and fell to 0.17-0.43 clean at starts of 10-15 cm on held-out
#: step-downs, against the start's 0.68 (docs/results/tune_default_repeats_h200); trained on the wide spread, the
#: five returned 0.838 [0.810, 0.867] clean over runs against the start's 0.814 (tune_default_repeats_wide_h200).
OBJECTIVES = {"clean": ((0.16, 0.20, 0.24, 0.28), "wide"), "reach": ((0.24, 0.26, 0.28, 0.30), "wide")}
#: The training spread of the equal-wall-clock study per ``--objective`` when none is given: the one every stored
#: study ran (``python -m experiments.tune_study``).
STUDY_SPREADS = {"clean": "train", "reach": "wide"}

#: Every setting of the tuner that ``hyqjax tune`` does not show, at the value it runs with (the options of
#: ``python -m experiments.tune_study`` that set them take these as their defaults).
HIDDEN = dict(
    study=False, gradient_study=False, train_duration=24.0, completed_weight=0.1, hybrid_split=0.5,
    heldout_chunk=8, no_compile_charge=False, cold_compile=False, state_every_s=30.0, retake_windows=False,
    select_every_s=0.0, select_seed=5555, grad_directions=0, grad_mode="jacfwd", contacts_from_distance=0.0,
    train_spread=None, train_heights=None, paper_crawl=False, lr=0.1, train_per_height=2, windows_per_scenario=2,
    lead=10.0, window_ticks=None, heldout_seed=7777, heldout_duration=24.0, select_instances=None,
    select_every=5, train_instances=32, guided_alpha=0.5, guided_subspace=1, guided_lr=0.05, guided_grad_every=1,
    blend_gamma=2.0, blend_lr=0.05, restart_stall=25, surrogate_weights=(),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.studies.tune import names

    p.add_argument("--out", default="out/tune", help="run directory (the same command resumes from it)")
    p.add_argument("--method", "--methods", dest="methods", type=split_names, default=None,
                   help=f"search method, one of {', '.join(names.METHODS)} (default: {names.DEFAULT_METHOD}; "
                        "guided_es, with MJX-JAX gradients inside the search, loses to the gradient-free searches at "
                        "equal wall-clock on the step-down: docs/tuning.md)")
    p.add_argument("--dim", "--dims", dest="dims", type=split_names, default=None,
                   help="parameterisation: shared (14 coordinates), per_leg (56), per_leg_cond (68), "
                        f"per_leg_cond_all (98) (default: {names.DEFAULT_DIM})")
    p.add_argument("--wall-minutes", type=float, nargs="+", default=None,
                   help="wall-clock checkpoints (minutes, increasing; the last is the budget; compile included). "
                        f"Default {' '.join(f'{m:g}' for m in names.DEFAULT_WALL_MINUTES)}: from clean, five runs "
                        "returned +0.014 clean success above it on held-out step-downs at 30 minutes, their 3- and "
                        "10-minute iterates none (docs/tuning.md)")
    p.add_argument("--objective", default="clean", choices=sorted(OBJECTIVES),
                   help="clean: clean success at 16-28 cm; reach: clean success at 24-30 cm (both on the wide "
                        "spread: friction 0.4-1.0, payload 0-15 kg, start 0-15 cm before the edge)")
    p.add_argument("--preset", default=None,
                   help="start point: a crawl preset of hyqjax.presets (hyqjax presets lists them), or none for "
                        "Table I with the shin remedy; default: the preset the default was measured from, "
                        + ", ".join(sorted(set(names.DEFAULT_PRESETS.values())))
                        + " (a per-leg parameterisation starts from it on every leg; its values of the coordinates "
                          "no parameterisation tunes, such as an edge probe, stay fixed)")
    p.add_argument("--start-from", default="",
                   help="warm start: a results.json of an earlier run; its last iterate of the same method and "
                        "parameterisation is the start")
    p.add_argument("--groups", default="k_base,damping,mobility,k_x,delta,body_height,step_length,step_height,"
                                       "search_forward,terrain_adaptation",
                   help="tuned groups, comma-separated, from k_base, damping, mobility, k_x, delta, k_kl, "
                        "body_height, step_length, step_height, search_speed, search_forward, terrain_adaptation, "
                        "edge_probe (the probe's step and depth), edge_gate (the depth gate's tilts, margin and "
                        "lowering); the edge groups need a start with the edge probe on, such as --preset clean")
    p.add_argument("--popsize", type=int, default=16, help="population per generation")
    p.add_argument("--sigma", type=float, default=None,
                   help="the search's first step in the tuner's normalised coordinates (default: 0.1 from a tuned "
                        "start, a preset or --start-from; 0.3 from Table I, --preset none, and in "
                        "python -m experiments.tune_study; its --gradient-study: 0.5). Around a tuned set a step of "
                        "0.3 leaves no sample of the first generation as clean as the start, 0.1 a third "
                        "(python -m experiments.tune_step_size, docs/tuning.md)")
    p.add_argument("--heldout", type=int, default=None,
                   help="held-out closed-loop instances per parameter set (default 2000)")
    p.add_argument("--final-instances", type=int, default=None,
                   help="after the budget, the 3 best validated iterates (and the start point when it is not one of "
                        "them) run on this many further scenarios and the best over both validation batches is returned (0: off; default twice the validation batch, "
                        "1,088 runs; python -m experiments.tune_study: 0)")
    p.add_argument("--seed", type=int, default=0, help="training seed")
    p.add_argument("--quick", action="store_true",
                   help="a small version for a CPU: %s" % ", ".join(
                       f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, tuple) else v}"
                       for k, v in QUICK.items() if k != "grad_train_per_height"))
    p.add_argument("--segment-minutes", type=float, default=None,
                   help="stop after this many minutes of this process, storing the running method's state, and "
                        "exit with status 75; the same command goes on from there (default: no stop)")
    p.add_argument("--wait", action="store_true", help="if another run is writing DIR, wait for it instead of stopping")
    from hyqjax.cli.common import add_impl_argument

    add_impl_argument(p)  # the forward-only runs; the gradient always runs under impl jax


def _fill_hidden(args) -> None:
    for k, v in HIDDEN.items():
        if not hasattr(args, k):
            setattr(args, k, v)


def validate(args) -> None:
    """Every option checked, the configuration built and the run directory probed before anything is compiled
    or written (a refused command leaves nothing behind)."""
    _fill_hidden(args)
    from hyqjax.cli.common import UsageError

    if args.quick and (args.study or args.gradient_study):
        raise UsageError("--quick is a small version of the tuner; it does not combine with a study")
    return validate_wallclock(args)


def default_config(out: str, impl: str = "auto"):
    """The configuration (``WallClockConfig``) of ``hyqjax tune --out OUT --impl IMPL`` with every other option at
    its default, as the command builds it."""
    from hyqjax.cli.app import build_parser

    args = build_parser().parse_args(["tune", "--out", out, "--impl", impl])
    validate(args)
    return args.wallclock_config


def validate_wallclock(args) -> None:
    """The tuner and the equal-wall-clock study (``python -m experiments.tune_study``): every setting checked in one
    line before anything compiles."""
    from hyqjax.cli.common import UsageError, check_all, check_impl, check_out_free, check_range, prepare_out
    from hyqjax.studies.tune import names

    check_impl(args.impl)
    if args.quick:
        defaults = _defaults()
        for k, v in QUICK.items():
            if getattr(args, k, None) in (None, getattr(defaults, k, HIDDEN.get(k))):
                setattr(args, k, v)
    heights, spread = OBJECTIVES[args.objective]
    args.train_heights = heights if args.train_heights is None else args.train_heights
    if args.train_spread is None:
        args.train_spread = STUDY_SPREADS[args.objective] if args.study else spread
    wm = tuple(args.wall_minutes) if args.wall_minutes else (
        names.STUDY_WALL_MINUTES if args.study else names.DEFAULT_WALL_MINUTES)
    check_all("--wall-minutes", wm, 0.0, 600.0, "min", lo_open=True)
    if list(wm) != sorted(set(wm)):
        raise UsageError(f"--wall-minutes must be increasing, got {' '.join(f'{x:g}' for x in wm)}")
    if args.study:
        methods = args.methods if args.methods is not None else names.STUDY_METHODS
        dims = args.dims if args.dims is not None else ("shared", "per_leg_cond")
    else:
        methods = args.methods if args.methods is not None else (names.DEFAULT_METHOD,)
        dims = args.dims if args.dims is not None else (names.DEFAULT_DIM,)
        if len(methods) != 1 or len(dims) != 1:
            raise UsageError(f"--method and --dim take one name each (several: python -m experiments.tune_study), "
                             f"got {','.join(methods)} / {','.join(dims)}")
    for opt, vals, allowed in (("--methods", methods, names.METHODS), ("--dims", dims, names.DIMS)):
        bad = [v for v in vals if v not in allowed]
        if bad or not vals:
            raise UsageError(f"{opt} must be names among {','.join(allowed)}, got {','.join(vals) or 'nothing'}")
        if len(set(vals)) != len(vals):
            raise UsageError(f"{opt} names a method or parameterisation twice: {','.join(vals)}")
    check_range("--popsize", args.popsize, 2, 4096, integer=True)
    check_range("--guided-alpha", args.guided_alpha, 0.0, 1.0)
    check_range("--guided-subspace", args.guided_subspace, 1, 64, integer=True)
    check_range("--guided-lr", args.guided_lr, 0.0, 1.0, lo_open=True)
    check_range("--guided-grad-every", args.guided_grad_every, 1, 10**4, integer=True)
    check_range("--blend-gamma", args.blend_gamma, 0.0, 100.0, lo_open=True)
    check_range("--blend-lr", args.blend_lr, 0.0, 1.0, lo_open=True)
    check_range("--restart-stall", args.restart_stall, 0, 10**5, integer=True)
    check_range("--train-instances", args.train_instances, 4, 100000, integer=True)
    if args.train_instances % 4:
        raise UsageError(f"--train-instances must be a multiple of 4 (one share per training height), "
                         f"got {args.train_instances}")
    check_range("--train-duration", args.train_duration, 0.1, 120.0, "s")
    check_range("--completed-weight", args.completed_weight, 0.0, 10.0)
    check_range("--hybrid-split", args.hybrid_split, 0.0, 1.0, lo_open=True, hi_open=True)
    check_range("--heldout-chunk", args.heldout_chunk, 1, 4096, integer=True)
    args.window_ticks = 500 if args.window_ticks is None else args.window_ticks
    args.heldout = 2000 if args.heldout is None else args.heldout
    check_range("--window-ticks", args.window_ticks, 1, 20000, integer=True)
    from hyqjax.studies.tune.surrogate_weights import parse_weights

    try:
        args.surrogate_weights = parse_weights(args.surrogate_weights)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if args.sigma is not None:
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
    if args.final_instances is None:
        args.final_instances = 0 if args.study else 2 * args.select_instances
    check_range("--final-instances", args.final_instances, 0, 10**6, integer=True)
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
    from hyqjax.cli import tune_start

    preset = tune_start.start_preset(args, methods, dims)
    if args.sigma is None:
        args.sigma = names.default_sigma(tuned_start=bool(preset or args.start_from), study=args.study)
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
            guided_alpha=args.guided_alpha, guided_subspace=args.guided_subspace, guided_lr=args.guided_lr,
            guided_grad_every=args.guided_grad_every, blend_gamma=args.blend_gamma, blend_lr=args.blend_lr,
            restart_stall=args.restart_stall, surrogate_weights=args.surrogate_weights,
            start_preset=preset, final_instances=args.final_instances,
            start_from=tune_start.start_from(args.start_from, methods, dims, groups) if args.start_from else ())
    except ValueError as e:
        msg = str(e)
        opt = msg.split(" ")[0].replace("_", "-")
        raise UsageError(f"--{opt}: {msg}" if not msg.startswith("--") else msg) from None
    check_out_free(args.out)
    try:
        wallclock.previous(args.out, cfg)
    except RuntimeError as e:
        raise UsageError(str(e)) from None
    tune_start.load_preset(preset)
    tune_start.check_edge_start(cfg)
    prepare_out(args.out)
    args.wallclock_config = cfg
    args.options_checked = True


def _defaults():
    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args([])


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    from hyqjax.cli import tune_wallclock
    from hyqjax.io.lock import DirLock

    # The run directory's lock first, before anything heavy is imported: a second run stops (or waits) at once.
    with DirLock(args.out, wait=args.wait, what="tune run"):
        return tune_wallclock.run(args)
