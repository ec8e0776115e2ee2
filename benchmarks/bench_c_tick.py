"""Where a tick of the C MuJoCo backend goes at a small batch: the host call (C MuJoCo stepping the batch and the
Python around it, :meth:`hyqjax.sim.cpu_physics.CPhysics.step_padded`, timed from inside) against the whole tick
(the compiled controller and metrics, the call into the host and back).

Usage::

    PYTHONPATH=. taskset -c 0,1 python benchmarks/bench_c_tick.py --per-cell 1 --duration 4
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)

from hyqjax.sim import cpu_physics  # noqa: E402
from hyqjax.studies import stepdown  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-cell", type=int, default=1, help="instances per cell (3 heights x reflex off / on)")
    ap.add_argument("--duration", type=float, default=4.0, help="simulated seconds")
    ap.add_argument("--reps", type=int, default=2, help="timed runs after the compiling one")
    args = ap.parse_args(argv)
    if args.per_cell < 1 or args.duration <= 0 or args.reps < 1:
        ap.error("--per-cell and --reps must be >= 1 and --duration > 0")
    acc = {"n": 0, "t": 0.0}
    step_padded = cpu_physics.CPhysics.step_padded

    def timed(self, tau_frozen, out):
        t = time.perf_counter()
        step_padded(self, tau_frozen, out)
        acc["t"] += time.perf_counter() - t
        acc["n"] += 1

    cpu_physics.CPhysics.step_padded = timed
    scen, _ = stepdown.make_scenarios([0.16, 0.21, 0.24], [False, True], args.per_cell, 0)
    cfg = stepdown.StepdownConfig(duration=args.duration, impl="c")
    ro = stepdown.make_stepdown_rollout(cfg)
    ro.run(scen)  # compiles
    ticks = round(args.duration / 0.002)
    for _ in range(args.reps):
        acc.update(n=0, t=0.0)
        t = time.perf_counter()
        ro.run(scen)
        w = time.perf_counter() - t
        print(f"{scen.batch_size} instances: {1e3 * w / ticks:.3f} ms a tick, of which the host call "
              f"{1e3 * acc['t'] / max(acc['n'], 1):.3f} ms ({acc['n']} calls)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
