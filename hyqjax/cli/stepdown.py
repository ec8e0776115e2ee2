"""Step-down comparison (Focchi et al. 2017, Section IV): HyQ crawls off a platform with the height reflex
on and off, batched over instances with per-instance height, friction, payload, start position and seed.

Outcome of a run, two levels:
  completed  the paper's criterion: all four feet on the lower ground past the edge, forward progress, no lost
             foothold, no joint past its range, no trunk strike, no tilt, no reflex failure, finite
  clean      completed and no shin contact above the strike force (100 N)
A run that is not clean has its failure reasons (feet_not_down, no_progress, lost_foothold, joint_past_range,
tilt, trunk_strike, shin_strike, diverged, reflex_failure, contact_overflow); the table prints, per height and
reflex setting, both levels with Wilson 95% intervals and the runs per failure reason.

Writes DIR/results.json (one row per instance plus a summary per height and reflex setting), the figures
success.png, fig9_reflex.png, fig10_end_stop.png, fig11_pitch.png, and the traces of the --record-instances
every --record-every ticks to DIR/traces.npz (format: hyqjax/io/recording.py; `hyqjax render DIR` makes a video
of one). A --duration too short for any run to get all four feet down (from the crawl's gait timing) is refused;
one shorter than a typical run needs gets a warning.

Examples:
  hyqjax stepdown --instances 3 --out out/stepdown        # the paper's table at CPU size
  hyqjax stepdown --heights 0.24 --reflex on --preset remedy  # one height, the shin-strike remedy
  hyqjax stepdown --preset reach --heights 0.27 --reflex on   # the configuration that reaches furthest
  hyqjax stepdown --preset tuned_per_leg --instances 1     # a per-leg tuned set
  hyqjax stepdown --params out/tune/results.json           # the crawl and reflex gains `hyqjax tune` returned
  hyqjax render out/stepdown --where height=0.24 reflex=on # a video of one recorded run
"""
from __future__ import annotations

import argparse
import os
import sys
import time

from hyqjax.studies import tasks

NAME = "stepdown"
#: The task this command runs (:mod:`hyqjax.studies.tasks`; reading it imports nothing heavy).
TASK = tasks.get("stepdown")
HELP = "step down from a platform with the height reflex on and off (the paper's headline experiment)"
ORDER = 10


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import add_impl_argument, use_help_formatter

    use_help_formatter(p)
    p.add_argument("--heights", type=float, nargs="+", default=[0.16, 0.21, 0.24], help="platform heights (m)")
    p.add_argument("--reflex", nargs="+", choices=["on", "off"], default=["off", "on"], help="reflex settings")
    p.add_argument("--instances", type=int, default=1, help="randomised instances per height and reflex setting")
    p.add_argument("--seed", type=int, default=0, help="seed of the per-instance randomisation")
    p.add_argument("--duration", type=float, default=24.0, help="simulated seconds per instance")
    p.add_argument("--speed", type=float, default=0.1, help="desired forward velocity (m/s)")
    from hyqjax.presets import registry

    p.add_argument("--preset", default=None, metavar="NAME",
                   help="a crawl preset (`hyqjax presets --kind crawl`): " + ", ".join(registry.names("crawl")) +
                        "; default: paper (Table I, the paper's crawl); reach reaches furthest")
    p.add_argument("--remedy", action="store_true",
                   help="alias of --preset remedy: the shin-strike remedy with the trunk following 80%% of the feet "
                        "plane's tilt (docs/stepdown.md)")
    p.add_argument("--crawl", default="", metavar="FIELD=VALUE,...",
                   help="more CrawlParams.make settings over the preset's, e.g. 'search_forward_limit=0.10,"
                        "stance_min_force=1' (the saturating search and the slip-aware trunk load, docs/stepdown.md); "
                        "forward_velocity is --speed")
    p.add_argument("--params", default="", metavar="RESULTS[:RUN]",
                   help="run the crawl and reflex parameters a tuning run returned: its results.json (`hyqjax tune "
                        "--out DIR` writes DIR/results.json), and with several runs the one to take, e.g. "
                        "results.json:snes/shared (a per_leg run runs as a per-leg set); the run's remedy setting is "
                        "kept (no --preset), --crawl may set only fields it did not tune")
    p.add_argument("--no-figures", action="store_true", help="skip traces and figures (less memory)")
    p.add_argument("--record-every", type=int, default=10, metavar="TICKS",
                   help="trace decimation in control ticks (2 ms each); must divide the number of ticks")
    p.add_argument("--record-instances", default="few", metavar="SPEC",
                   help="instances written to traces.npz: 'few' (the first 3 of each height and reflex setting and "
                        "its first 3 runs that are not clean), 'all', 'none' or indices like 0,3,5-7 (rows of "
                        "results.json); the file format is in hyqjax/io/recording.py")
    p.add_argument("--out", default="out/stepdown", help="output directory")
    add_impl_argument(p, TASK.impls)


SEED_MAX = 2**32 - 1


def validate(args) -> None:
    """Every option checked, and the output directory created and probed, before JAX is imported."""
    from hyqjax.cli.common import check_all, check_impl, check_range, prepare_out

    check_all("--heights", args.heights, 0.0, 0.45, "m")
    check_range("--instances", args.instances, 1, 100000, integer=True)
    check_range("--seed", args.seed, 0, SEED_MAX, integer=True)
    check_range("--duration", args.duration, 0.1, 600.0, "s")
    from hyqjax.core.params import param_ranges
    from hyqjax.crawl.params import CrawlParams

    v_f = param_ranges(CrawlParams)["forward_velocity"]  # the one declaration of the speed's range
    check_range("--speed", args.speed, v_f.lo, v_f.hi, v_f.unit)
    if len(set(args.reflex)) != len(args.reflex):
        raise ValueError(f"--reflex lists a setting twice: {args.reflex}")
    args.crawl_settings = _crawl_settings(args)
    args.preset = _preset_name(args)
    args.tuned_params = _tuned_params(args) if args.params else _preset_params(args)
    check_impl(args.impl, supported=TASK.impls)
    args.recorded = _recorded_instances(args)
    args.duration_warning = _check_duration(args)
    prepare_out(args.out)
    args.options_checked = True


def _crawl_settings(args) -> dict:
    """``CrawlParams.make`` settings of ``--remedy`` and ``--crawl`` (the latter wins), checked against the declared
    ranges (JAX's parameter classes only, no MJX)."""
    import numpy as np

    from hyqjax.core.params import ParameterError, param_ranges
    from hyqjax.crawl.params import FOOT_SEQUENCES, CrawlParams, parse_settings

    extra = parse_settings(args.crawl, "--crawl")
    if "forward_velocity" in extra:
        raise ValueError("--crawl: forward_velocity is set by --speed")
    specs = param_ranges(CrawlParams)  # the one declaration of each range, checked in NumPy (nothing compiles)
    for key, value in extra.items():
        if key == "foot_sequence" and value not in FOOT_SEQUENCES:
            raise ValueError(f"--crawl: foot_sequence must be one of {', '.join(sorted(FOOT_SEQUENCES))}, got {value!r}")
        if key in specs and not isinstance(value, bool):
            try:
                specs[key].check(np.asarray(value, np.float64), "CrawlParams")
            except ParameterError as e:
                raise ValueError(f"--crawl: {e}") from None
    return extra


#: The crawl preset the step-down runs without --preset (its table reproduces the paper's).
DEFAULT_PRESET = "paper"
#: The best measured crawl presets the summary's last line names: the one that reaches farthest and the cleanest
#: up to 26 cm (their figures from the registry). ``clean_refined`` is cleaner than ``clean`` on both maps of fresh
#: step-downs that no choice saw, paired instance by instance: +0.011 [+0.005, +0.017] on the confirmation map (seed
#: 31415, MuJoCo Warp) and +0.011 [+0.001, +0.022] on C MuJoCo (seed 90210); docs/presets.md.
REACH_PRESET = "reach"
CLEAN_PRESET = "clean_refined"


def _preset_name(args) -> str | None:
    """The crawl preset of ``--preset`` / ``--remedy`` (its alias), checked by name and kind; None with
    ``--params`` (a tuning run's parameters)."""
    from hyqjax import presets as registry

    if args.remedy and args.preset not in (None, "remedy"):
        raise ValueError(f"--remedy is --preset remedy; give one of --remedy and --preset {args.preset}")
    name = "remedy" if args.remedy else args.preset
    if args.params:
        if name is not None:
            raise ValueError(f"--params runs a tuning run's parameters; give one of --params and "
                             f"{'--remedy' if args.remedy else '--preset'}")
        return None
    name = DEFAULT_PRESET if name is None else name
    registry.check_kind(name, "crawl")
    return name


def _preset_params(args):
    """The crawl parameters of the preset with ``--speed`` and ``--crawl``'s settings, checked before anything
    compiles (a ``CrawlParams``, or a per-leg set: :mod:`hyqjax.crawl.scheduled`)."""
    from hyqjax import presets as registry

    try:
        return registry.load(args.preset, forward_velocity=args.speed, **args.crawl_settings)
    except ValueError as e:
        raise ValueError(f"--preset {args.preset}" + (f" with --crawl {args.crawl}" if args.crawl else "") +
                         f": {e}") from None


def preset_line(preset: str | None) -> str | None:
    """The summary's last line: the best measured crawl presets beside ``preset``, with their registry figures.
    :data:`CLEAN_PRESET` points to ``reach`` for taller steps (completed at 29 cm), ``reach`` to
    :data:`CLEAN_PRESET` for clean success up to 26 cm, any other preset (or ``--params``) to both. None when a
    figure is missing from the registry."""
    from hyqjax import presets as registry

    def fig(name, what):
        f = next((f for f in registry.get(name).figures if f["what"] == what), None)
        if f is None:
            return None
        return f"{f['value']:g} {f['unit']}" if f["unit"] == "cm" else f"{100 * f['value']:.1f}%"

    clean = {n: fig(n, registry.FIGURE_CLEAN) for n in (CLEAN_PRESET, REACH_PRESET)}
    tall = {n: fig(n, registry.FIGURE_TALL) for n in (CLEAN_PRESET, REACH_PRESET)}
    if None in clean.values() or None in tall.values():
        return None
    if preset == CLEAN_PRESET:
        return (f"taller steps: --preset {REACH_PRESET} completes {tall[REACH_PRESET]} of held-out 29 cm step-downs "
                f"against {tall[CLEAN_PRESET]} for {CLEAN_PRESET} (`hyqjax presets {REACH_PRESET}`)")
    if preset == REACH_PRESET:
        return (f"cleaner up to 26 cm: --preset {CLEAN_PRESET}, {clean[CLEAN_PRESET]} clean on held-out step-downs "
                f"against {clean[REACH_PRESET]} for {REACH_PRESET} (`hyqjax presets {CLEAN_PRESET}`)")
    h90 = fig(REACH_PRESET, "h90, wide spread")
    return (f"best measured crawls: --preset {CLEAN_PRESET} ({clean[CLEAN_PRESET]} clean up to 26 cm on held-out "
            f"step-downs) and --preset {REACH_PRESET} (h90 {h90} on the wide spread, {tall[REACH_PRESET]} completed "
            f"at 29 cm); `hyqjax presets`")


def _tuned_params(args):
    """``CrawlParams`` of ``--params RESULTS[:RUN]`` (:func:`hyqjax.studies.tune.tuned.crawl_params`) with
    ``--speed`` and ``--crawl``'s settings, checked before anything compiles."""
    from hyqjax.studies.tune import tuned

    path, run = args.params, None
    if not os.path.exists(path) and ":" in path:
        path, _, run = path.rpartition(":")
    try:
        return tuned.crawl_params(path, run or None, forward_velocity=args.speed, **args.crawl_settings)
    except ValueError as e:
        raise ValueError(f"--params {args.params}: {e}") from None


#: The start distance range of the randomised instances (m), as ``stepdown.make_scenarios`` draws it.
START_DISTANCE = (0.0, 0.04)


def _check_duration(args) -> str | None:
    """Refuse a --duration no run can complete with; a warning line when it is shorter than a typical run needs
    (:mod:`hyqjax.studies.stepdown_duration`, from the crawl's gait timing)."""
    from hyqjax.studies import stepdown_duration as sdd

    timing = sdd.CrawlTiming.from_params(forward_velocity=float(args.speed))
    return sdd.check_duration(args.duration, args.heights, timing, START_DISTANCE)


def run(args) -> int:
    import jax
    import numpy as np

    from hyqjax.cli.common import import_during_batch_run, user_options
    from hyqjax.cli.progress import lap_batch_run, sim_progress
    from hyqjax.io import atomic as io
    from hyqjax.io import phases, recording
    from hyqjax.sim.compile_phase import compile_listener
    from hyqjax.studies import stepdown, stepdown_outcome

    if not getattr(args, "options_checked", False):
        validate(args)
    if getattr(args, "duration_warning", None):
        print(f"hyqjax stepdown: {args.duration_warning}", file=sys.stderr, flush=True)
    recorded = args.recorded
    params = args.tuned_params
    scenario, table = stepdown.make_scenarios(args.heights, [m == "on" for m in args.reflex], args.instances,
                                              args.seed, params=params)
    record_every = 0 if args.no_figures else args.record_every
    cfg = TASK.config(duration=args.duration, record_every=record_every, impl=args.impl)
    n = scenario.batch_size
    n_ticks = cfg.sim_config().n_ticks
    rollout = TASK.rollout(cfg)
    impl = rollout.setup.impl
    from hyqjax.sim import backend as hbackend, devices as hdevices

    devs = hbackend.devices_for(impl)
    where = "" if devs == [None] else f" on {hdevices.describe(devs)}"
    print(f"hyqjax stepdown: {n} instances ({len(args.heights)} heights x {len(args.reflex)} reflex settings x "
          f"{args.instances}), {args.duration:g} s each, {n_ticks} ticks, simulator {impl}{where}", flush=True)
    clock = phases.current()
    clock.lap("startup")
    t0 = time.time()
    with compile_listener(import_during_batch_run("hyqjax.studies.stepdown_figures", bool(record_every))), \
            sim_progress(f"stepdown: {n} instances", args.duration) as progress:
        outcome, res = rollout.run(scenario, progress=progress)
        out = stepdown_outcome.to_columns(outcome)
        trace = jax.tree_util.tree_map(np.asarray, res.trace) if record_every else None
    status = progress.status
    lap_batch_run(clock, status)
    os.makedirs(args.out, exist_ok=True)
    traces_path = os.path.join(args.out, recording.TRACES_FILE)
    if recorded is None:  # --record-instances few: chosen now that the failures are known
        recorded = recording.few_instances(np.arange(n) // args.instances, ~np.asarray(out["clean"], bool))
    # traces.npz is compressed in a background thread (zlib releases the GIL) while the summary and the figures
    # are made; the command waits for it at the end.
    saving = (recording.BackgroundSave(traces_path, trace, table, recorded, record_every, cfg.control_dt)
              if trace is not None and len(recorded) else None)
    rows = stepdown.summarize(table, out)
    print(stepdown.format_table(rows))
    print(status.throughput_text(n, n_ticks), flush=True)
    instances = [{**{k: v[i] for k, v in table.items()}, **{k: v[i] for k, v in out.items()}} for i in range(n)]
    config = user_options(args)
    config.pop("duration_warning", None)
    sim_s = status.pure_simulate_s
    preset = None
    if args.preset:
        from hyqjax import presets as registry

        rec = registry.get(args.preset)
        preset = dict(name=rec.name, description=rec.description, values=rec.values, provenance=rec.provenance)
    timing = dict(compile_s=status.xla_compile_s, kernel_build_s=status.kernel_s, simulate_s=sim_s,
                  env_steps_per_s=n * n_ticks / sim_s if sim_s > 0 else None, batches=status.timings)
    clock.lap("summary")
    from hyqjax.studies import stepdown_figures  # matplotlib, imported once the simulation is done

    figs = stepdown_figures.all_figures(args.out, table, out, rows, trace)
    clock.lap("figures")
    traces_write_s = saving.join() if saving is not None else None  # its error, if any
    clock.lap("traces")
    if saving is None and os.path.exists(traces_path):
        os.remove(traces_path)  # a previous run's traces would not match this results.json
    timing["traces_write_s"] = traces_write_s
    clocked = clock.to_dict()
    timing["wall_s"] = clocked["wall_s"]
    io.write_json(os.path.join(args.out, "results.json"), dict(
        provenance=io.provenance(seed=args.seed), config=config, preset=preset, impl=impl, summary=rows,
        instances=instances, figures=figs, wall_time_s=clocked["wall_s"], timing=timing, phases=clocked,
        recorded_instances=np.asarray(recorded).tolist()))  # the last write
    wrote = ["results.json (summary and one row per instance)"]
    if saving is not None:
        wrote.append(f"{recording.TRACES_FILE} ({len(recorded)} recorded instances, --record-instances "
                     f"{args.record_instances}: `hyqjax render {args.out}` makes a video, `hyqjax view {args.out}` "
                     f"replays one)")
    pngs = sorted(f for f in os.listdir(args.out) if f.endswith(".png")
                  and os.path.getmtime(os.path.join(args.out, f)) >= t0)
    if pngs:
        wrote.append("figures " + ", ".join(pngs))
    print(f"wrote to {args.out}/: " + "; ".join(wrote) + f"; `hyqjax report {args.out}` makes one HTML page")
    line = preset_line(args.preset)
    if line:
        print(line)
    clock.lap("summary")
    print(clock.line(), flush=True)
    return 0


def _recorded_instances(args) -> "np.ndarray":  # noqa: F821
    """Rows to write to traces.npz, checked (with --record-every) before anything is compiled."""
    from hyqjax.io import recording

    n_ticks = int(round(args.duration / 0.002))
    if not args.no_figures and not (1 <= args.record_every <= n_ticks and n_ticks % args.record_every == 0):
        raise ValueError(f"--record-every must divide the number of ticks ({n_ticks} for --duration {args.duration}) "
                         f"and be in [1, {n_ticks}], got {args.record_every}")
    return recording.parse_instances(args.record_instances, len(args.heights) * len(args.reflex) * args.instances)
