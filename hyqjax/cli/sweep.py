"""Robustness sweep of the step-down experiment over a declarative grid / random sample (hyqjax.studies.sweep).

The sweep is described by a TOML or JSON file (SPEC) and/or the flags --grid, --random, --fixed
(AXIS=v1,v2,...; AXIS=lo,hi; AXIS=v), which override the file's entries; with neither, a CPU-sized
default (3 heights x reflex on/off x 2 random draws of friction and payload, 12 instances). Axes:
`hyqjax sweep --list-axes`. Instances run in chunks (--chunk-size; default 32 per CPU device, 4096
per GPU) sharded over all local devices, or as Ray tasks over a cluster (--executor ray, see
docs/cluster.md). Every finished chunk is stored in DIR/chunks/NNNNN.parquet and recorded with its
SHA-256 in DIR/manifest.json, so running the same command again resumes where it stopped; one writer
at a time holds DIR/.lock (--wait queues behind it). Writes DIR/instances.csv, DIR/summary.json,
success_maps.png and success_height.png; DIR/chunks opens as one table in pandas, polars or DuckDB.
The summary gives both outcome levels of every instance (completed: the paper's criterion; clean: completed
and no shin strike; `hyqjax stepdown --help`) and the failure reasons of the runs that are not clean. A
duration too short for any run to get all four feet down is refused, one shorter than a typical run needs
gets a warning (hyqjax/studies/stepdown_duration.py).

Examples:

    hyqjax sweep --dry-run                                  # the default sweep's size, nothing run
    hyqjax sweep --out out/sweep                            # the default sweep (12 instances)
    hyqjax sweep --grid height=0.16,0.24 --grid reflex=true,false --random friction=0.4,1.0 --samples 8
    hyqjax sweep spec.toml --out out/big --max-chunks 2     # two chunks now, resume later
    hyqjax sweep --ci --impl c --out out/ci --baseline out/ci_base --junit out/ci.xml   # the CI gate (docs/ci.md)
    hyqjax sweep spec.toml --expect "clean >= 0.85" --expect "completed >= 0.95 where height <= 0.21"

CI gate (docs/ci.md): --expect checks an outcome rate (with the spec file's `expect` list) on its Wilson 95%
interval: met, failed (interval wholly below) or inconclusive (straddling; --inconclusive says whether that
fails). --baseline DIR compares the finished store with a baseline store of the same spec as `hyqjax compare`
does. --junit / --markdown / --json write reports. Exit status 0 passed, 1 failed or regressed, 3 inconclusive.
--ci runs the sweep shipped for CI (hyqjax/studies/sweep/specs/ci.toml, with its expectations).

Example spec (TOML):

    seed = 0
    samples = 4            # random draws per grid point
    duration = 18.0        # simulated seconds per instance
    blocks = [0, 0]        # rough-terrain block grid per level (needed for roughness > 0)
    maps = [["height", "friction"], ["height", "payload_mass"]]
    [grid]
    height = [0.16, 0.21, 0.24]
    reflex = [false, true]
    [random]
    friction = [0.5, 1.0]
    payload_mass = [0.0, 10.0]
    [fixed]
    speed = 0.1
"""
from __future__ import annotations

import argparse
import os
import sys

NAME = "sweep"
HELP = "robustness sweep of the step-down (grid / random over terrain, payload, gains, pushes, reflex parameters)"
ORDER = 20

DEFAULT_SPEC = dict(
    seed=0, samples=2, duration=18.0,
    grid=dict(height=[0.16, 0.21, 0.24], reflex=[False, True]),
    random=dict(friction=[0.6, 1.0], payload_mass=[0.0, 10.0]),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import add_impl_argument, use_help_formatter

    use_help_formatter(p)
    p.add_argument("spec", nargs="?", help="sweep spec file (.toml or .json); omit for the default or flags only")
    p.add_argument("--ci", action="store_true", help="run the CI sweep shipped with hyqjax "
                                                     "(hyqjax/studies/sweep/specs/ci.toml) instead of SPEC")
    p.add_argument("--baseline", metavar="BASE_DIR", help="compare the finished store with this baseline store of the "
                                                          "same spec (exit status 1 if regressed)")
    p.add_argument("--out", default="out/sweep", help="results directory (resumed if it holds the same sweep)")
    p.add_argument("--grid", action="append", default=[], metavar="AXIS=V1,V2,...", help="grid axis (repeatable)")
    p.add_argument("--random", action="append", default=[], metavar="AXIS=LO,HI",
                   help="random axis, uniform in [LO, HI] (or a list of options for a choice axis)")
    p.add_argument("--fixed", action="append", default=[], metavar="AXIS=V", help="fixed axis value")
    p.add_argument("--samples", type=int, help="random draws per grid point (default: the spec's; 2 in the built-in "
                                                  "default sweep, else 1)")
    p.add_argument("--seed", type=int, help="sweep seed (default: the spec's, else 0)")
    p.add_argument("--duration", type=float, help="simulated seconds per instance (default: the spec's, else 18)")
    p.add_argument("--chunk-size", type=int, help="instances per chunk (default: 32 per CPU device, 4096 per GPU)")
    p.add_argument("--max-chunks", type=int, help="stop after this many new chunks (resume later), >= 0")
    p.add_argument("--wait", action="store_true", help="if another process is writing DIR, wait for it instead of "
                                                       "stopping")
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="run chunks on this process's devices, or as Ray tasks (pip install 'hyqjax[cluster]')")
    p.add_argument("--address", default=None,
                   help="Ray cluster address (with --executor ray; default: $RAY_ADDRESS, else a local Ray instance)")
    p.add_argument("--gpus-per-task", type=float, default=None,
                   help="GPUs per Ray task (with --executor ray; default 1 if the cluster has GPUs, else 0)")
    p.add_argument("--max-retries", type=int, default=3, help="retries of a Ray task whose worker died, in [0, 100]")
    p.add_argument("--dry-run", action="store_true", help="validate and print the sweep's size, run nothing")
    p.add_argument("--list-axes", action="store_true", help="print the axes with ranges and defaults, then exit")
    p.add_argument("--preset", default=None, metavar="NAME",
                   help="the crawl preset every instance runs (`hyqjax presets --kind crawl`; the spec's `preset`, "
                        "else paper); axes override its values")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_impl_argument(p)
    from hyqjax.cli.gate_options import add_gate_arguments

    add_gate_arguments(p)


#: The CI sweep shipped with the package (``hyqjax sweep --ci``).
CI_SPEC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "studies", "sweep", "specs",
                       "ci.toml")


def _parse_value(s: str):
    low = s.strip().lower()
    if low in ("true", "on"):
        return True
    if low in ("false", "off"):
        return False
    try:
        return float(s)
    except ValueError:
        return s.strip()


def _parse_kv(items, what):
    out = {}
    for item in items:
        if "=" not in item or not item.split("=", 1)[0].strip():
            raise ValueError(f"--{what} expects AXIS=VALUES, got {item!r}")
        k, v = item.split("=", 1)
        if k.strip() in out:
            raise ValueError(f"--{what} names axis {k.strip()!r} twice; give it once")
        out[k.strip()] = [_parse_value(x) for x in v.split(",") if x.strip()]
        if not out[k.strip()]:
            raise ValueError(f"--{what} {k.strip()}= needs at least one value")
    return out


def build_spec_dict(args) -> dict:
    """The spec as a dict: the SPEC file (or the default when neither SPEC nor axis flags are given), then the
    flags. File problems raise ``SpecError`` naming the file."""
    import json

    from hyqjax.studies import sweep

    if args.spec:
        d = sweep.load_spec_dict(args.spec)
        if "expect" in d:  # the CI gate's expectations: not part of the sweep (validate_gate parses them)
            from hyqjax.studies.sweep.expect import split_spec_dict

            d, args.spec_expect = split_spec_dict(d, f"SPEC {args.spec}")
    elif args.grid or args.random or args.fixed:
        d = {}
    else:
        d = json.loads(json.dumps(DEFAULT_SPEC))
    flags = {sec: _parse_kv(items, sec) for sec, items in (("grid", args.grid), ("random", args.random),
                                                            ("fixed", args.fixed))}
    given: dict[str, str] = {}
    for sec, axes in flags.items():  # an axis named by two of the flags: which one was meant is not ours to guess
        for k in axes:
            if k in given:
                raise ValueError(f"--{given[k]} and --{sec} both name axis {k!r}; give it once")
            given[k] = sec
    for sec, axes in flags.items():
        for k, v in axes.items():
            for other in ("grid", "random", "fixed"):
                if isinstance(d.get(other), dict):
                    d[other].pop(k, None)
            d.setdefault(sec, {})[k] = v[0] if sec == "fixed" and len(v) == 1 else v
    if getattr(args, "preset", None) is not None:
        d["preset"] = "" if args.preset == "paper" else args.preset
    for k in ("samples", "seed"):
        if getattr(args, k) is not None:
            d[k] = getattr(args, k)
    if args.duration is not None:
        d["duration"] = args.duration
    return d


def validate(args) -> None:
    """The spec validated, the options checked and the output directory probed before anything compiles."""
    from hyqjax.cli.common import check_impl, check_out_free, check_range, prepare_out
    from hyqjax.studies import sweep

    if args.list_axes:
        return
    check_impl(args.impl)
    if args.chunk_size is not None:
        check_range("--chunk-size", args.chunk_size, 1, 10**7, integer=True)
    if args.max_chunks is not None:
        check_range("--max-chunks", args.max_chunks, 0, 10**9, integer=True)
    check_range("--max-retries", args.max_retries, 0, 100, integer=True)
    if getattr(args, "ci", False):
        if args.spec:
            raise ValueError(f"--ci runs the shipped CI spec: give either --ci or SPEC {args.spec}, not both")
        args.spec = CI_SPEC
    if args.executor != "ray":
        for opt, v in (("--address", args.address), ("--gpus-per-task", args.gpus_per_task)):
            if v is not None:
                raise ValueError(f"{opt} needs --executor ray")
    elif args.gpus_per_task is not None:
        check_range("--gpus-per-task", args.gpus_per_task, 0, 8)
    args.spec_obj = sweep.SweepSpec.from_dict(build_spec_dict(args))
    args.duration_warning = check_spec_duration(args.spec_obj)
    _validate_gate(args)
    check_out_free(args.out)
    if args.dry_run:
        return
    if os.path.exists(os.path.join(args.out, "manifest.json")):
        # A different sweep, or an old store that is read-only, is refused now, not after a compile (read-only,
        # writes nothing). A corrupt manifest is not an error here: the run sets it aside and rebuilds it.
        try:
            sweep.SweepStore(args.out, args.spec_obj).check_resumable()
        except sweep.StoreCorrupt:
            pass
    if args.executor == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ValueError("--executor ray needs Ray: pip install 'hyqjax[cluster]'") from None
    prepare_out(args.out)
    args.options_checked = True


def _validate_gate(args) -> None:
    """The CI gate's options (``hyqjax/cli/gate_options.py``): expectations parsed and checked against the spec, the
    baseline store probed (read-only) for the same spec, the report paths."""
    from hyqjax.cli.gate_options import validate_gate
    from hyqjax.studies.sweep import expect

    validate_gate(args, getattr(args, "spec_expect", ()))
    expect.check_selects(args.expectations, args.spec_obj)
    if args.baseline:
        from hyqjax.studies.sweep.manifest import StoreCorrupt, read_manifest
        from hyqjax.studies.sweep.verify import is_sweep_dir

        if not os.path.isdir(args.baseline) or not is_sweep_dir(args.baseline):
            raise ValueError(f"--baseline {args.baseline} holds no sweep (no manifest.json, no chunks/)")
        if os.path.abspath(args.baseline) == os.path.abspath(args.out):
            raise ValueError(f"--baseline {args.baseline} is the --out directory; give the baseline's own store")
        try:
            man = read_manifest(args.baseline)
        except StoreCorrupt:
            man = None  # named after the run, by the comparison's verification
        if man and man.get("spec_hash") != args.spec_obj.spec_hash and not args.allow_change:
            from hyqjax.studies.sweep.compare import spec_differences

            diffs = spec_differences(man.get("spec") or {}, args.spec_obj.to_dict())
            raise ValueError(f"--baseline {args.baseline} holds a different sweep (BASE vs this spec: "
                             f"{'; '.join(diffs) or 'spec hash ' + str(man.get('spec_hash'))[:12]})")


def _gate(args, store) -> int:
    """Expectations on the finished store and the baseline comparison; reports; the exit status."""
    from hyqjax.cli.gate_options import finish, gate_requested
    from hyqjax.studies.sweep import expect
    from hyqjax.studies.sweep.gate import Verdict

    if not gate_requested(args):
        return 0
    notes = []
    complete = len(store.done()) == store.n_chunks
    checks = expect.evaluate(args.expectations, store.spec, store.load())
    cmp = None
    if args.baseline and complete:
        from hyqjax.studies.sweep.compare import compare_stores

        cmp = compare_stores(args.baseline, args.out, alpha=args.alpha, allow_change=args.allow_change)
    elif args.baseline:
        notes.append("the sweep is not complete: not compared with the baseline (run the same command again)")
    if not complete:
        notes.append(f"the sweep is not complete ({len(store.done())} of {store.n_chunks} chunks): the gate is "
                     f"inconclusive")
    verdict = Verdict(checks, cmp, args.inconclusive, title=f"hyqjax sweep {store.spec.spec_hash[:12]}", notes=notes)
    status = finish(args, verdict)
    return 3 if status == 0 and not complete else status


def _done_chunks(out: str, spec) -> set:
    """Chunks already stored in ``out`` for ``spec`` (read-only; none for a new, foreign or damaged store)."""
    from hyqjax.studies import sweep

    if not os.path.exists(os.path.join(out, "manifest.json")):
        return set()
    try:
        return set(sweep.SweepStore(out, spec).done())
    except Exception:  # the run itself refuses or repairs such a store, with its reason
        return set()


def check_spec_duration(spec) -> str | None:
    """A warning line when no instance can complete within the sweep's duration, or when it is shorter than a
    typical run of its slowest instances needs (:mod:`hyqjax.studies.stepdown_duration`, over the speed,
    foot sequence, start distance and height values the spec can take)."""
    from hyqjax.crawl.params import FOOT_SEQUENCES
    from hyqjax.studies import stepdown_duration as sdd

    speeds = [float(v) for v in spec.axis_values("speed")]
    seqs = [FOOT_SEQUENCES[str(v)] for v in spec.axis_values("foot_sequence")]
    starts = [float(v) for v in spec.axis_values("start_distance")]
    heights = [float(v) for v in spec.axis_values("height")]
    fast = [sdd.CrawlTiming.from_params(forward_velocity=max(speeds), foot_sequence=q) for q in seqs]
    if max(speeds) > 0:
        shortest = min(sdd.shortest_duration(t, min(starts)) for t in fast)
        if spec.duration < shortest:  # a warning, not a refusal: short sweeps test the store and the machinery
            return (f"warning: duration {spec.duration:g} s is below the {shortest:.1f} s any step-down of this sweep "
                    f"needs (the crawl's gait timing at {max(speeds):g} m/s): every instance will fail with "
                    f"feet_not_down")
    slow = [v for v in speeds if v > 0]
    if len(slow) < len(speeds):
        return "warning: speed values <= 0 make no forward steps: those instances fail with feet_not_down"
    notes = [sdd.check_duration(spec.duration, heights, sdd.CrawlTiming.from_params(forward_velocity=min(slow),
                                                                                   foot_sequence=q),
                                (min(starts), max(starts)), option="duration") for q in seqs]
    return next((n for n in notes if n), None)


def run(args) -> int:
    from hyqjax.io import atomic as io
    from hyqjax.studies import sweep

    if args.list_axes:
        for a in sweep.AXES.values():
            rng = f"one of {list(a.options)}" if a.kind == "choice" else (
                "true/false" if a.kind == "bool" else a.range_text)
            print(f"{a.name:18s} {rng:34s} default {a.default!r:14s} {a.doc}")
        return 0
    if not hasattr(args, "spec_obj"):
        validate(args)
    spec = args.spec_obj
    size = (f"hyqjax sweep: {spec.n_instances} instances (grid {dict((k, len(v)) for k, v in spec.grid)} x "
            f"{spec.samples} samples), {spec.duration:g} s each, spec {spec.spec_hash[:12]}")
    if args.dry_run:
        print(size)
        return 0
    if getattr(args, "duration_warning", None):
        print(f"hyqjax sweep: {args.duration_warning}", file=sys.stderr, flush=True)
    if args.executor == "ray":
        from hyqjax.studies.sweep import cluster

        executor = cluster.RayExecutor(address=args.address, gpus_per_task=args.gpus_per_task,
                                       max_retries=args.max_retries, impl=args.impl)
        where = executor.describe()
    else:

        executor = sweep.LocalExecutor(impl=args.impl)
        devs = executor.devices
        where = (f"{len(devs)} x {devs[0].platform} device(s) (ids {','.join(str(d.id) for d in devs)}), "
                 f"simulator {executor.impl}")
    print(f"{size}, {where}", flush=True)
    from hyqjax.cli.progress import compile_status, lap_batch_run
    from hyqjax.io import phases

    before = _done_chunks(args.out, spec)
    clock = phases.current()
    clock.lap("startup")
    with compile_status("sweep", disable=args.no_progress) as status:
        store = sweep.run_sweep(spec, args.out, args.chunk_size, args.max_chunks, progress=not args.no_progress,
                                wait=args.wait, executor=executor)
    lap_batch_run(clock, status)  # chunks simulated and stored
    summary = sweep.write_outputs(store, clock)
    summary["provenance"] = io.provenance(seed=spec.seed)
    if status.timings:  # chunks simulated in this process (the local executor)
        summary["timing_this_run"] = dict(compile_s=status.xla_compile_s, kernel_build_s=status.kernel_s,
                                          simulate_s=status.pure_simulate_s, batches=status.timings)
    summary["executor"] = args.executor
    print(sweep.format_summary(summary))
    clock.lap("summary")
    summary["phases_this_run"] = clock.to_dict()
    summary["wall_time_s_this_run"] = summary["phases_this_run"]["wall_s"]
    io.write_json(os.path.join(args.out, "summary.json"), summary)  # the last write
    if status.timings:  # instances of the chunks finished now (the chunks' padding rows not counted)
        n_run = sum(store.chunk_range(c)[1] - store.chunk_range(c)[0] for c in store.done() - before)
        print(f"this run: {status.throughput_text(n_run, int(round(spec.duration / spec.control_dt)))}")
    left = store.n_chunks - len(store.done())
    print(f"wrote {args.out}/summary.json, instances.csv" + (", figures" if summary.get("figures") else "")
          + (f"; {left} chunk(s) left: run the same command again to resume" if left else ""))
    clock.lap("summary")
    rc = _gate(args, store)
    print(clock.line(), flush=True)
    return rc
