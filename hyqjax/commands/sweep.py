"""Robustness sweep of the step-down experiment over a declarative grid / random sample (hyqjax.sweep).

The sweep is described by a TOML or JSON file (SPEC) and/or the flags --grid, --random, --fixed
(AXIS=v1,v2,...; AXIS=lo,hi; AXIS=v), which override the file's entries; with neither, a CPU-sized
default (3 heights x reflex on/off x 2 random draws of friction and payload, 12 instances). Axes:
`hyqjax sweep --list-axes`. Instances run in chunks (--chunk-size; default 32 per CPU device, 4096
per GPU) sharded over all local devices; every finished chunk is stored in DIR/chunks and recorded
in DIR/manifest.json, so running the same command again resumes where it stopped. Writes
DIR/instances.csv, DIR/summary.json, success_maps.png and success_height.png.

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
import time

NAME = "sweep"
HELP = "robustness sweep of the step-down (grid / random over terrain, payload, gains, pushes, reflex parameters)"
ORDER = 20

DEFAULT_SPEC = dict(
    seed=0, samples=2, duration=18.0,
    grid=dict(height=[0.16, 0.21, 0.24], reflex=[False, True]),
    random=dict(friction=[0.6, 1.0], payload_mass=[0.0, 10.0]),
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("spec", nargs="?", help="sweep spec file (.toml or .json); omit for the default or flags only")
    p.add_argument("--out", default="out/sweep", help="results directory (resumed if it holds the same sweep)")
    p.add_argument("--grid", action="append", default=[], metavar="AXIS=V1,V2,...", help="grid axis (repeatable)")
    p.add_argument("--random", action="append", default=[], metavar="AXIS=LO,HI",
                   help="random axis, uniform in [LO, HI] (or a list of options for a choice axis)")
    p.add_argument("--fixed", action="append", default=[], metavar="AXIS=V", help="fixed axis value")
    p.add_argument("--samples", type=int, help="random draws per grid point")
    p.add_argument("--seed", type=int, help="sweep seed")
    p.add_argument("--duration", type=float, help="simulated seconds per instance")
    p.add_argument("--chunk-size", type=int, help="instances per chunk (default: 32 per CPU device, 4096 per GPU)")
    p.add_argument("--max-chunks", type=int, help="stop after this many new chunks (resume later)")
    p.add_argument("--dry-run", action="store_true", help="validate and print the sweep's size, run nothing")
    p.add_argument("--list-axes", action="store_true", help="print the axes with ranges and defaults, then exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


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
        if "=" not in item:
            raise SystemExit(f"--{what} expects AXIS=VALUES, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = [_parse_value(x) for x in v.split(",") if x.strip()]
    return out


def build_spec_dict(args) -> dict:
    import json

    if args.spec:
        if args.spec.endswith(".toml"):
            import tomllib

            with open(args.spec, "rb") as f:
                d = tomllib.load(f)
        elif args.spec.endswith(".json"):
            with open(args.spec) as f:
                d = json.load(f)
        else:
            raise SystemExit(f"spec file must end in .toml or .json, got {args.spec!r}")
    elif args.grid or args.random or args.fixed:
        d = {}
    else:
        d = json.loads(json.dumps(DEFAULT_SPEC))
    for sec, items in (("grid", args.grid), ("random", args.random), ("fixed", args.fixed)):
        for k, v in _parse_kv(items, sec).items():
            for other in ("grid", "random", "fixed"):
                d.get(other, {}).pop(k, None)
            d.setdefault(sec, {})[k] = v[0] if sec == "fixed" and len(v) == 1 else v
    for k in ("samples", "seed"):
        if getattr(args, k) is not None:
            d[k] = getattr(args, k)
    if args.duration is not None:
        d["duration"] = args.duration
    return d


def run(args) -> int:
    from hyqjax import io, sweep

    if args.list_axes:
        for a in sweep.AXES.values():
            rng = f"one of {list(a.options)}" if a.kind == "choice" else (
                "true/false" if a.kind == "bool" else f"[{a.lo:g}, {a.hi:g}] {a.unit}")
            print(f"{a.name:18s} {rng:34s} default {a.default!r:14s} {a.doc}")
        return 0
    try:
        spec = sweep.SweepSpec.from_dict(build_spec_dict(args))
    except sweep.SpecError as e:
        raise SystemExit(f"invalid sweep spec: {e}") from None
    if args.chunk_size is not None and args.chunk_size < 1:
        raise SystemExit(f"--chunk-size must be >= 1, got {args.chunk_size}")
    import jax

    devs = jax.local_devices()
    print(f"hyqjax sweep: {spec.n_instances} instances (grid {dict((k, len(v)) for k, v in spec.grid)} x "
          f"{spec.samples} samples), {spec.duration:g} s each, spec {spec.spec_hash[:12]}, "
          f"{len(devs)} x {devs[0].platform} device(s)", flush=True)
    if args.dry_run:
        return 0
    try:
        store = sweep.SweepStore(args.out, spec, args.chunk_size)
    except sweep.StoreMismatch as e:
        raise SystemExit(str(e)) from None
    done = len(store.done())
    print(f"chunks of {store.chunk_size}: {done}/{store.n_chunks} done"
          + (", resuming" if done else "") + " (the first chunk compiles, 30-90 s on CPU)", flush=True)
    t0 = time.time()
    # The store run_sweep returns holds the chunks this run added (``store`` above is the state before it).
    store = sweep.run_sweep(spec, args.out, args.chunk_size, args.max_chunks, progress=not args.no_progress)
    wall = time.time() - t0
    summary = sweep.write_outputs(store)
    summary["provenance"] = io.provenance(seed=spec.seed)
    summary["wall_time_s_this_run"] = wall
    io.write_json(os.path.join(args.out, "summary.json"), summary)
    print(sweep.format_summary(summary))
    left = store.n_chunks - len(store.done())
    print(f"wrote {args.out}/summary.json, instances.csv" + (", figures" if summary.get("figures") else "")
          + (f"; {left} chunk(s) left: run the same command again to resume" if left else ""))
    return 0
