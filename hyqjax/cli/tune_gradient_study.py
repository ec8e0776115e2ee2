"""``hyqjax tune --gradient-study``: the gradient study at equal physics budget (:mod:`hyqjax.studies.tune.study`):
its option checks, its configuration and its run. The default tuner and ``--study`` live in :mod:`hyqjax.cli.tune`,
which defines every option of the command (their run: :mod:`hyqjax.cli.tune_wallclock`)."""
from __future__ import annotations

import os

#: Baselines of the gradient study (``--baselines``: the names of :data:`hyqjax.studies.tune.study.METHODS` after
#: the gradient), checked before anything heavy is imported.
BASELINES = ("cma_es", "random_search", "cma_es_success", "random_search_success")


def split_names(s: str) -> tuple:
    """``"a, b,"`` -> ``("a", "b")``."""
    return tuple(x.strip() for x in s.split(",") if x.strip())


def validate(args, wallclock_defaults: dict) -> None:
    """Every option of ``--gradient-study`` checked in one line before anything compiles; an option of the default
    tuner and ``--study`` (``wallclock_defaults``: option -> default) given a value is refused."""
    from hyqjax.cli.common import UsageError, check_all, check_impl, check_out_free, check_range, prepare_out

    for opt, val in (("--methods", args.methods), ("--dims", args.dims), ("--wall-minutes", args.wall_minutes),
                     ("--start-from", args.start_from or None)):
        if val is not None:
            raise UsageError(f"{opt} belongs to the default tuner and --study, not to --gradient-study")
    args.window_ticks = 750 if args.window_ticks is None else args.window_ticks
    args.sigma = 0.5 if args.sigma is None else args.sigma
    args.heldout = 36 if args.heldout is None else args.heldout
    args.select_instances = 16 if args.select_instances is None else args.select_instances
    check_impl(args.impl)
    for k, default in wallclock_defaults.items():
        if getattr(args, k) != default:
            raise UsageError(f"--{k.replace('_', '-')} belongs to the default tuner and --study, not to "
                             f"--gradient-study")

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
    bad = [b for b in split_names(args.baselines) if b not in BASELINES]
    if bad:
        raise ValueError(f"--baselines must be a subset of {list(BASELINES)}, got {bad}")
    from hyqjax.studies.tune import space  # the groups' declarations (JAX's parameter classes, no MJX)

    try:
        space.ParamSpace.make(split_names(args.groups))
    except ValueError as e:
        raise ValueError(f"--groups: {e}") from None
    check_out_free(args.out)
    prepare_out(args.out)
    args.options_checked = True


def config(args):
    """The study configuration; its own checks (groups, baselines, ...) name the option that was given."""
    from hyqjax.studies.tune import objective, optimize, study, windows

    groups, base_list = split_names(args.groups), split_names(args.baselines)
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
    """The gradient study (options checked by :func:`validate`; the run directory locked by the caller)."""
    from hyqjax.cli.common import UsageError

    try:
        cfg = args.study_config = config(args)
    except ValueError as e:
        raise UsageError(str(e)) from None
    groups, base_list = cfg.groups, cfg.baselines
    from hyqjax.studies.tune import figure, study

    print(f"hyqjax tune: {cfg.objective} objective, {cfg.adam.steps} steps, groups {list(groups)}, "
          f"baselines {list(base_list)}, out {args.out}", flush=True)
    res = study.run_study(cfg, args.out, progress=not args.no_progress, log=lambda s: print(s, flush=True),
                          locked=True)
    fig = figure.plot_study(res, os.path.join(args.out, "tuning.png"))
    print(figure.summary_markdown(res))
    print(f"wrote {args.out}/results.json and {fig} ({res['wall_s']:.0f} s)")
    return 0
