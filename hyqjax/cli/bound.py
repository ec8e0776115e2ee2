"""Bounding in place, forward and turning (Orsolino et al.): a batch of randomised instances with the
impulse-based bound, apex and stance feedback, speed / yaw control, kinematic adjustment and
centrifugal compensation. Prints a summary table and writes DIR/results.json, DIR/yaw_tracking.png
(the paper's Fig. 4), DIR/speed_tracking.png and DIR/traces.npz, the traces of --record-instances (by default
a few of each configuration and its first failures; format: hyqjax/io/recording.py).

Each instance gets a small random perturbation of the initial apex state, a friction coefficient and a
payload from --seed. A fall (trunk below 0.35 m, |roll| or |pitch| above 0.7 rad) or a diverged
simulation is counted as a failure with its reason; failed instances are never dropped.

Base height and velocity are estimated by the controller (leg odometry + IMU); the metrics use the
simulator's ground truth. --ablation runs all four on/off combinations of the kinematic adjustment and
the centrifugal compensation on the same instances (one compiled rollout) and reports each part's
contribution.

The gains are the preset bound_robust's (`hyqjax presets bound_robust`) unless --preset or --params names others;
--preset bound_paper runs the paper's.

Examples:
  hyqjax bound --out out/bound                             # forward 0.5 m/s, turning 0.3 rad/s, 8 instances
  hyqjax bound --preset bound_paper                        # the paper's gains on the same instances
  hyqjax bound --speed 0.9 --yaw-rate 0.5 --ablation       # each part's contribution, same instances
  hyqjax bound --duration 2.4 --instances 2                # a quick run (tracking errors need cycles after 2 s)
"""
from __future__ import annotations

import argparse
import os

from hyqjax.presets.registry import BOUND_ALIASES
from hyqjax.studies import tasks


NAME = "bound"
#: The task this command runs (:mod:`hyqjax.studies.tasks`; reading it imports nothing heavy).
TASK = tasks.get("bound")
HELP = "bounding gait: in place, forward, turning; yaw / speed tracking, falls, ablation"
ORDER = 40

ABLATION = (("full", True, True), ("no_kinematic_adjustment", False, True), ("no_centrifugal", True, False),
            ("neither", False, False))


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import add_impl_argument, use_help_formatter

    use_help_formatter(p)
    p.add_argument("--speed", type=float, default=0.5, help="desired forward speed (m/s), in [-1.5, 1.5]")
    p.add_argument("--yaw-rate", type=float, default=0.3, help="desired yaw rate (rad/s, + = left), in [-1.5, 1.5]")
    p.add_argument("--lateral-speed", type=float, default=0.0, help="desired lateral speed (m/s), in [-0.5, 0.5]")
    p.add_argument("--duration", type=float, default=6.0, help="simulated time (s); a multiple of the 0.4 s period")
    p.add_argument("--instances", type=int, default=8, help="instances per configuration")
    p.add_argument("--seed", type=int, default=0, help="seed of the per-instance randomisation")
    p.add_argument("--out", default="out/bound", help="output directory")
    p.add_argument("--ramp-time", type=float, default=1.0, help="command ramp time (s)")
    p.add_argument("--no-kinematic-adjustment", action="store_true", help="disable the kinematic adjustment (Eqs. 1-2)")
    p.add_argument("--no-centrifugal", action="store_true", help="disable the centrifugal compensation (Eqs. 3-4)")
    p.add_argument("--ablation", action="store_true",
                   help="run all four kinematic-adjustment / centrifugal on-off combinations on the same instances")
    p.add_argument("--push", type=float, default=0.0, metavar="N",
                   help="lateral push on the trunk (N), sign alternating over instances")
    p.add_argument("--push-time", type=float, default=3.0, help="push start (s)")
    p.add_argument("--push-duration", type=float, default=0.1, help="push duration (s)")
    p.add_argument("--friction", type=float, nargs=2, default=(0.7, 1.0), metavar=("LO", "HI"),
                   help="ground friction range")
    p.add_argument("--payload", type=float, default=5.0, metavar="KG", help="payload mass range [0, KG]")
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="a bounding preset (`hyqjax presets --kind bound`): bound_robust (the default: CMA-ES's "
                        "impulses and gains over commands, friction and payload, refined at the fast corners; no "
                        "fall in 4,096 held-out runs nor in 5,120 at friction 0.5-0.6 with 10 kg), bound_robust_8s "
                        "(its start), bound_paper (the paper's gains), bound_robust_grad (the gradient's)")
    p.add_argument("--params", metavar="FILE", default=None,
                   help="impulse amplitudes and gains from a file of hyqjax.bounding.robust.save_params (your own "
                        "optimisation, docs/bounding.md); the old names 'robust_8s' and 'robust' are aliases of "
                        "--preset bound_robust_8s and --preset bound_robust_grad")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--record-instances", default="few", metavar="SPEC",
                   help="instances written to traces.npz: 'few' (the first 3 of each configuration and its first 3 "
                        "failures), 'all', 'none' or indices like 0,3,5-7 (in results.json's order); the file "
                        "format is in hyqjax/io/recording.py")
    add_impl_argument(p, TASK.impls)


def validate(args) -> None:
    """Every option checked (:func:`check_options`), then the output directory created and probed."""
    from hyqjax.cli.common import prepare_out

    check_options(args)
    prepare_out(args.out)
    args.options_checked = True


def check_options(args) -> None:
    """Every option checked, here and by ``bounding.batch.validate_run``, before anything is compiled;
    raises ValueError naming the option and its allowed range."""
    from hyqjax.cli.common import check_impl, check_out_free, check_range

    check_impl(args.impl, supported=TASK.impls)

    for opt, v, lo, hi, unit in (("--speed", args.speed, -1.5, 1.5, "m/s"), ("--yaw-rate", args.yaw_rate, -1.5, 1.5,
                                                                              "rad/s"),
                                 ("--lateral-speed", args.lateral_speed, -0.5, 0.5, "m/s"),
                                 ("--ramp-time", args.ramp_time, 0.0, 10.0, "s"),
                                 ("--push", args.push, -5000.0, 5000.0, "N"),
                                 ("--push-time", args.push_time, 0.0, 600.0, "s"),
                                 ("--push-duration", args.push_duration, 0.0, 10.0, "s"),
                                 ("--payload", args.payload, 0.0, 100.0, "kg"),
                                 ("--duration", args.duration, 0.4, 600.0, "s")):
        check_range(opt, v, lo, hi, unit)
    check_range("--instances", args.instances, 1, 4096, integer=True)
    check_range("--seed", args.seed, 0, 2**32 - 1, integer=True)
    if abs(args.duration / 0.4 - round(args.duration / 0.4)) > 1e-6:
        raise ValueError(f"--duration must be a multiple of the gait period 0.4 s, got {args.duration}")
    lo, hi = args.friction
    for v in (lo, hi):
        check_range("--friction", v, 0.0, 5.0, lo_open=True)
    if lo > hi:
        raise ValueError(f"--friction LO HI must satisfy 0 < LO <= HI <= 5, got {lo} {hi}")
    check_out_free(args.out)
    args.preset = _preset_name(args)
    from hyqjax.io import recording

    args.recorded = recording.parse_instances(args.record_instances, len(configurations(args)) * args.instances)
    if args.params is not None:
        from hyqjax.bounding import robust as rb

        try:
            rb.params_from_values(rb.load_params(args.params))
        except ValueError as e:
            raise ValueError(f"--params: {e}") from None
    else:
        from hyqjax import presets

        presets.load(args.preset)  # a stored value outside its declared range is refused here
    from hyqjax.bounding import batch as bbatch

    try:
        bbatch.validate_run(speed=args.speed, yaw_rate=args.yaw_rate, lateral_speed=args.lateral_speed,
                            ramp_time=args.ramp_time, instances=args.instances, duration=args.duration,
                            friction=tuple(args.friction), payload=(0.0, args.payload), push=args.push,
                            push_time=args.push_time, push_duration=args.push_duration, seed=args.seed)
    except bbatch.SettingError as e:
        opt = "--" + e.name.replace("_", "-")
        raise ValueError(str(e).replace(e.name, opt, 1) if str(e).startswith(e.name) else f"{opt}: {e}") from None


_validate = check_options

#: The old shipped-set names of --params: aliases of presets (the registry's table).
PARAMS_ALIASES = BOUND_ALIASES


def _preset_name(args) -> str | None:
    """The bounding preset to run (``--preset``, an alias given to ``--params``, else the default gains'
    preset, ``hyqjax.bounding.params.DEFAULT_PRESET``), checked by name and kind; None when ``--params`` names a
    file."""
    from hyqjax import presets
    from hyqjax.bounding.params import DEFAULT_PRESET

    if args.params in PARAMS_ALIASES:  # the old shipped names take precedence over a file of that name, as before
        alias = PARAMS_ALIASES[args.params]
        if args.preset not in (None, alias):
            raise ValueError(f"--params {args.params} is --preset {alias}; give one of them")
        args.params = None
        args.preset = alias
    if args.params is not None:
        if args.preset is not None:
            raise ValueError("--params runs the parameters of a file; give one of --params and --preset")
        return None
    name = DEFAULT_PRESET if args.preset is None else args.preset
    presets.check_kind(name, "bound")
    return name


def configurations(args) -> list[tuple[str, bool, bool]]:
    if args.ablation:
        return list(ABLATION)
    return [("run", not args.no_kinematic_adjustment, not args.no_centrifugal)]


def run(args) -> int:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hyqjax.bounding import batch as bbatch
    from hyqjax.bounding import params as bd
    from hyqjax.bounding import summary as bs
    from hyqjax.cli.common import user_options
    from hyqjax.io import atomic as io

    if not getattr(args, "options_checked", False):
        validate(args)
    configs = configurations(args)
    n = args.instances
    values = None
    if args.params is None:
        from hyqjax import presets

        preset = presets.get(args.preset)
        values = dict(preset.values.get("amplitudes", {}), **preset.values.get("gains", {}))
        make = lambda **kw: bd.params_of_values(values, **kw)  # noqa: E731
    else:
        from hyqjax.bounding import robust as rb

        values = rb.load_params(args.params)
        make = lambda **kw: rb.params_from_values(values, **kw)  # noqa: E731
    # One parameter set per configuration, repeated for its n instances (the same leaves, types and values as n
    # calls each and a stack, without their cost: about 28 ms per instance on 2 cores).
    per_config = [make(speed=args.speed, yaw_rate=args.yaw_rate, lateral_speed=args.lateral_speed,
                       ramp_time=args.ramp_time, kinematic_adjustment=kin, centrifugal=cf) for _, kin, cf in configs]
    params = jax.tree_util.tree_map(
        lambda *xs: jnp.concatenate([jnp.broadcast_to(jnp.asarray(x), (n,) + jnp.shape(x)) for x in xs]), *per_config)
    n_total = len(configs) * n
    rand = bbatch.Randomisation(friction=tuple(args.friction), payload=(0.0, args.payload))
    batch = bbatch.make_batch(params, seed=args.seed, rand=rand, push_force=args.push, push_time=args.push_time,
                              push_duration=args.push_duration, n_unique=n)
    from hyqjax.cli.progress import lap_batch_run, sim_progress
    from hyqjax.io import phases, recording

    clock = phases.current()
    rollout = TASK.rollout(TASK.config(duration=args.duration, record_every=10, impl=args.impl))
    print(f"hyqjax bound: {n_total} instances ({len(configs)} configuration(s) x {n}), {args.duration:g} s each, "
          f"{int(round(args.duration / 0.002))} ticks, simulator {rollout.setup.impl}", flush=True)
    clock.lap("startup")
    from hyqjax.cli.common import import_during_batch_run
    from hyqjax.sim.compile_phase import compile_listener

    with compile_listener(import_during_batch_run("hyqjax.bounding.plots", not args.no_figures)), \
            sim_progress(f"bound: {n_total} instances", args.duration) as progress:
        _, res = rollout.run(batch, progress=progress)
        trace = jax.tree_util.tree_map(np.asarray, res.trace)
    status = progress.status
    lap_batch_run(clock, status)
    summary = bs.summarise(res, trace, batch)
    failed = np.array([not p.success for p in summary.instances])
    group = np.repeat(np.arange(len(configs)), n)
    recorded = recording.few_instances(group, failed) if args.recorded is None else args.recorded
    traces_path = os.path.join(args.out, recording.TRACES_FILE)
    os.makedirs(args.out, exist_ok=True)
    saving = None
    if len(recorded):  # hyqjax.io.recording's format, for `hyqjax render` / `hyqjax view`, written meanwhile
        inputs = dict(friction=np.asarray(batch.terrain.friction),
                      payload_mass=np.asarray(batch.terrain.payload_mass), group=group)
        saving = recording.BackgroundSave(traces_path, trace, inputs, recorded, record_every=10, control_dt=0.002)
    elif os.path.exists(traces_path):
        os.remove(traces_path)  # a previous run's traces would not match this results.json
    groups = {}
    for g, (name, kin, cf) in enumerate(configs):
        per = summary.instances[g * n:(g + 1) * n]
        groups[name] = dict(kinematic_adjustment=kin, centrifugal=cf, aggregate=bs.aggregate(per),
                            instances=[p.to_dict() for p in per])
    opts = user_options(args)
    n_ticks = int(round(args.duration / 0.002))
    sim_s = status.pure_simulate_s
    out = dict(provenance=io.provenance(seed=args.seed), args=opts, impl=rollout.setup.impl,
               compile_s=status.xla_compile_s, kernel_build_s=status.kernel_s, simulate_s=sim_s,
               env_steps_per_s=n_total * n_ticks / sim_s if sim_s > 0 else None,
               batches=status.timings, groups=groups, recorded_instances=recorded.tolist())
    if values is not None:
        out["params"] = dict(source=args.params or f"preset {args.preset}", preset=args.preset, values=values)
    if args.ablation:
        out["contributions"] = bs.contributions(groups)
    print(bs.format_table(groups, settle=args.ramp_time + 1.0, duration=args.duration))
    if args.ablation:
        print(bs.format_contributions(out["contributions"]))
    print(status.throughput_text(n_total, n_ticks), flush=True)
    clock.lap("summary")
    if not args.no_figures:
        from hyqjax.bounding import plots as bp

        idx = {name: list(range(g * n, (g + 1) * n)) for g, (name, _, _) in enumerate(configs)}
        out["figures"] = bp.tracking_figures(trace, idx, args.out)
        clock.lap("figures")
    if saving is not None:
        out["traces_write_s"] = saving.join()  # its error, if any
        clock.lap("traces")
    out["phases"] = clock.to_dict()
    out["wall_time_s"] = out["phases"]["wall_s"]
    io.write_json(os.path.join(args.out, "results.json"), out)  # the last write
    figs = ", ".join(os.path.basename(p) for p in (out.get("figures") or {}).values()) if isinstance(
        out.get("figures"), dict) else ""
    wrote = ["results.json (per instance and per configuration)"]
    if saving is not None:
        wrote.append(f"{recording.TRACES_FILE} ({len(recorded)} recorded instances, --record-instances "
                     f"{args.record_instances}: `hyqjax render {args.out}` makes a video)")
    print(f"wrote to {args.out}/: " + ", ".join(wrote) + (f", {figs}" if figs else ""))
    clock.lap("summary")
    print(clock.line(), flush=True)
    return 0
