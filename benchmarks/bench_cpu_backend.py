"""The step-down closed loop on a CPU: C MuJoCo (``impl="c"``) against MJX-JAX (``impl="jax"``), in one run.

Sections:

  throughput  one batch of exactly ``--batch`` step-down instances (the first ``--batch`` of
              ``stepdown.make_scenarios`` over 3 heights x reflex off/on at ``ceil(batch / 6)`` per cell; no
              traces; a batch of 64 fills the C backend's controller bucket of 64 with no padded row) for ``--duration`` simulated seconds, through
              ``make_stepdown_rollout(cfg).run`` as ``hyqjax stepdown`` runs it, under each simulator: the first
              call (compile included: a fresh process has nothing compiled; the persistent compilation cache is
              off here) and a second call of the same batch (compiled). env-steps/s = batch x ticks / wall, and
              the ratios C / MJX-JAX with and without compile.
  first       (``--first-command``) the README's first command, ``hyqjax stepdown --instances 3 --out DIR``, in a
              fresh Python process with an empty compilation cache (what a user sees right after the install):
              its wall time, and the wall time it prints for the batch itself.

The numbers depend on the load of the machine: both simulators are timed in the same run, one after the other,
so their ratios are comparable. Writes JSON (``--out``, rewritten after each measurement) and prints a summary.

Usage::

    PYTHONPATH=. python benchmarks/bench_cpu_backend.py --batch 64 --duration 24 --first-command --out out/cpu.json
    PYTHONPATH=. python benchmarks/bench_cpu_backend.py --batch 6 --duration 0.2 --out out/cpu_backend_tiny.json
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


def closed_loop(impl: str, scen, duration: float) -> dict:
    """Wall time of the first (compile included) and second run of ``scen`` under ``impl``."""
    cfg = stepdown.StepdownConfig(duration=duration, impl=impl)
    ro = stepdown.make_stepdown_rollout(cfg)
    out = {}
    for name in ("first", "second"):
        t = time.perf_counter()
        o, res = ro.run(scen)
        jax.block_until_ready((o, res))
        out[f"{name}_wall_s"] = time.perf_counter() - t
    n = scen.batch_size * cfg.sim_config().n_ticks
    out.update(env_steps=n, rate_with_compile=n / out["first_wall_s"], rate_compiled=n / out["second_wall_s"],
               clean=float(np.mean(np.asarray(o.clean))), impl=ro.setup.impl)
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
    ap.add_argument("--batch", type=int, default=64, help="instances")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per instance")
    ap.add_argument("--impls", nargs="+", choices=["c", "jax"], default=["c", "jax"])
    ap.add_argument("--first-command", action="store_true", help="also time the README's first command")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.batch < 1 or not args.duration > 0:
        raise SystemExit("--batch must be >= 1 and --duration > 0")
    per_cell = -(-args.batch // 6)
    scen, _ = stepdown.make_scenarios(HEIGHTS, [False, True], per_cell, args.seed)
    scen = jax.tree_util.tree_map(lambda x: x[:args.batch], scen)
    res = dict(info=host_info(), args=vars(args), batch=scen.batch_size, threads=cpu_physics.default_threads(),
               provenance=hio.provenance(argv if argv is not None else sys.argv[1:]), throughput={})
    print(json.dumps({k: res["info"][k] for k in ("date", "device", "jax", "mujoco")}), flush=True)
    for impl in args.impls:
        res["throughput"][impl] = closed_loop(impl, scen, args.duration)
        t = res["throughput"][impl]
        print(f"{impl}: batch {scen.batch_size} x {args.duration:g} s: first {t['first_wall_s']:.1f} s "
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
