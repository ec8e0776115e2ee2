"""A task's closed loop on a CPU: C MuJoCo (``impl="c"``) against MJX-JAX (``impl="jax"``), in one run.

Sections:

  throughput  one batch of exactly ``--batch`` instances of ``--task``: step-down instances (the first ``--batch`` of
              ``stepdown.make_scenarios`` over 3 heights x reflex off/on at ``ceil(batch / 6)`` per cell; no
              traces; a batch of 64 fills the C backend's controller bucket of 64 with no padded row) for ``--duration`` simulated seconds, through
              ``make_stepdown_rollout(cfg).run`` as ``hyqjax stepdown`` runs it, under each simulator: the first
              call (compile included: a fresh process has nothing compiled; the persistent compilation cache is
              off here) and a second call of the same batch (compiled). env-steps/s = batch x ticks / wall, and
              the ratios C / MJX-JAX with and without compile. ``--task bound``: bounding instances cycling over
              seven commands (in place, 0.5 and 0.8 m/s, +-0.4 rad/s at 0.5 m/s) from randomised apex states,
              through ``make_bounding_rollout(cfg).run`` (``--duration`` a multiple of the 0.4 s gait period);
              the success column is the share that neither fell nor diverged.
  first       (``--first-command``) the README's first command, ``hyqjax stepdown --instances 3 --out DIR``, in a
              fresh Python process with an empty compilation cache (what a user sees right after the install):
              its wall time, and the wall time it prints for the batch itself.

The numbers depend on the load of the machine: both simulators are timed in the same run, one after the other,
so their ratios are comparable. Writes JSON (``--out``, rewritten after each measurement) and prints a summary.

Usage::

    PYTHONPATH=. python benchmarks/bench_cpu_backend.py --batch 64 --duration 24 --first-command --out out/cpu.json
    PYTHONPATH=. python benchmarks/bench_cpu_backend.py --batch 6 --duration 0.2 --out out/cpu_backend_tiny.json
    PYTHONPATH=. python benchmarks/bench_cpu_backend.py --task bound --batch 7 --duration 6 --out out/cpu_bound.json
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import numpy as np  # noqa: E402

from hyqjax.io import atomic as hio  # noqa: E402
from hyqjax.sim import cpu_physics  # noqa: E402
from hyqjax.studies import stepdown  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_physics import host_info  # noqa: E402

HEIGHTS = (0.16, 0.21, 0.24)


#: The bounding commands ``--task bound`` cycles over (tests/test_bounding.py's closed-loop batch).
BOUND_COMMANDS = (dict(), dict(speed=0.5), dict(speed=0.8), dict(speed=0.5, yaw_rate=0.4),
                  dict(speed=0.5, yaw_rate=-0.4))


def workload(task: str, impl: str, batch: int, duration: float, seed: int):
    """``(rollout, batch of exactly `batch` instances)`` of ``task`` under ``impl``."""
    if task == "bound":
        from hyqjax.bounding import batch as bbatch
        from hyqjax.bounding import params as bparams
        from hyqjax.bounding import rollout as brollout

        plist = [bparams.paper_params(**BOUND_COMMANDS[i % len(BOUND_COMMANDS)]) for i in range(batch)]
        ro = brollout.make_bounding_rollout(brollout.BoundingRolloutConfig(duration=duration, impl=impl))
        return ro, bbatch.make_batch(plist, seed=seed)
    scen, _ = stepdown.make_scenarios(HEIGHTS, [False, True], -(-batch // 6), seed)
    ro = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=duration, impl=impl))
    return ro, jax.tree_util.tree_map(lambda x: x[:batch], scen)


def closed_loop(ro, batch) -> dict:
    """Wall time of the first (compile included) and second run of ``batch`` through rollout ``ro``."""
    out = {}
    for name in ("first", "second"):
        t = time.perf_counter()
        o, res = ro.run(batch)
        jax.block_until_ready((o, res))
        out[f"{name}_wall_s"] = time.perf_counter() - t
    n = int(np.shape(res.diverged)[0]) * ro.sim_config.n_ticks
    key = "success" if hasattr(o, "success") else "clean"  # bounding: neither fell nor diverged
    out.update(env_steps=n, rate_with_compile=n / out["first_wall_s"], rate_compiled=n / out["second_wall_s"],
               impl=ro.setup.impl, **{key: float(np.mean(np.asarray(getattr(o, key))))})
    return out


def first_command(out_dir: str) -> dict:
    """``hyqjax stepdown --instances 3 --out DIR`` in a fresh process with an empty compilation cache."""
    with tempfile.TemporaryDirectory(prefix="hyqjax-bench-cache-") as cache:
        env = {**os.environ, "HYQJAX_CACHE_DIR": cache, "PYTHONUNBUFFERED": "1"}
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        t = time.perf_counter()
        r = subprocess.run([sys.executable, "-c", "from hyqjax.cli.app import main; raise SystemExit(main())",
                            "stepdown", "--instances", "3", "--out", out_dir], capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t
    def num(pattern):
        m = re.search(pattern, r.stdout)
        return float(m.group(1)) if m else None

    sim = re.search(r"simulator (\w+)", r.stdout)
    return dict(rc=r.returncode, wall_s=wall, batch_wall_s=num(r"wall ([0-9.]+) s in all"),
                simulate_s=num(r"simulating ([0-9.]+) s"), compile_s=num(r"compile ([0-9.]+) s"),
                simulator=sim.group(1) if sim else None, stderr_tail=r.stderr[-2000:] if r.returncode else "")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", choices=["stepdown", "bound"], default="stepdown")
    ap.add_argument("--batch", type=int, default=64, help="instances")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per instance")
    ap.add_argument("--impls", nargs="+", choices=["c", "jax"], default=["c", "jax"])
    ap.add_argument("--first-command", action="store_true", help="also time the README's first command")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.batch < 1 or not args.duration > 0:
        raise SystemExit("--batch must be >= 1 and --duration > 0")
    res = dict(info=host_info(), args=vars(args), batch=args.batch, threads=cpu_physics.default_threads(),
               provenance=hio.provenance(argv if argv is not None else sys.argv[1:]), throughput={})
    print(json.dumps({k: res["info"][k] for k in ("date", "device", "jax", "mujoco")}), flush=True)
    for impl in args.impls:
        res["throughput"][impl] = closed_loop(*workload(args.task, impl, args.batch, args.duration, args.seed))
        t = res["throughput"][impl]
        print(f"{impl}: {args.task} batch {args.batch} x {args.duration:g} s: first {t['first_wall_s']:.1f} s "
              f"({t['rate_with_compile']:,.0f} env-steps/s with compile), second {t['second_wall_s']:.1f} s "
              f"({t['rate_compiled']:,.0f} env-steps/s)", flush=True)
        if args.out:
            hio.write_json(args.out, res)
    tp = res["throughput"]
    if "c" in tp and "jax" in tp:
        res["ratio_with_compile"] = tp["c"]["rate_with_compile"] / tp["jax"]["rate_with_compile"]
        res["ratio_compiled"] = tp["c"]["rate_compiled"] / tp["jax"]["rate_compiled"]
        print(f"C / MJX-JAX: {res['ratio_with_compile']:.1f}x counting compile, {res['ratio_compiled']:.1f}x compiled")
    if args.first_command:
        with tempfile.TemporaryDirectory(prefix="hyqjax-bench-out-") as d:
            res["first_command"] = first_command(d)
        f = res["first_command"]
        print(f"README first command: {f['wall_s']:.1f} s wall (batch {f['batch_wall_s']} s: simulating "
              f"{f['simulate_s']} s, compile {f['compile_s']} s; simulator {f['simulator']}, exit {f['rc']})")
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    res["loadavg_at_end"] = load
    if args.out:
        hio.write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
