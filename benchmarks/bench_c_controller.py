"""The C MuJoCo backend's compiled controller and metrics alone: one chunk program of the step-down's closed loop
with the physics host call replaced by a constant view, timed per tick at several batch sizes (how much of a tick
is the controller, and how its cost grows with the rows).

Usage::

    PYTHONPATH=. taskset -c 0,1 python benchmarks/bench_c_controller.py --per-cell 1 3 11
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from hyqjax.sim import cpu_backend, host_call  # noqa: E402
from hyqjax.studies import stepdown  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-cell", type=int, nargs="+", default=[1, 3, 11],
                    help="instances per cell (3 heights x reflex off / on); the batch is padded to its bucket")
    ap.add_argument("--ticks", type=int, default=500, help="ticks of the timed program")
    args = ap.parse_args(argv)
    if min(args.per_cell) < 1 or args.ticks < 1:
        ap.error("--per-cell and --ticks must be >= 1")
    ro = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.2, impl="c"))
    seen = {}
    executable = cpu_backend.CBatchRunner._executable

    def spy(self, name, fn, fargs, static=(), batch=None):  # the concrete arguments of the chunk program
        if name == "advance":
            seen.setdefault("args", (self,) + tuple(fargs))
        return executable(self, name, fn, fargs, static, batch)

    cpu_backend.CBatchRunner._executable = spy
    call = host_call.call
    for per in args.per_cell:
        seen.clear()
        scen, _ = stepdown.make_scenarios([0.16, 0.21, 0.24], [False, True], per, 0)
        ro.run(scen)
        runner, carry, params, handle = seen["args"]
        view = jnp.zeros((carry.data.qpos.shape[0], runner._width), carry.data.qpos.dtype)
        host_call.call = lambda name, shape, h, a: view + 0.0 * jnp.sum(a)  # noqa: E731  (no physics)
        try:
            fn = jax.jit(lambda c, p, h: cpu_backend.CBatchRunner._advance_fn(runner, c, p, h, args.ticks))
            t = time.perf_counter()
            prog = fn.lower(carry, params, handle).compile()
            t_compile = time.perf_counter() - t
            jax.block_until_ready(prog(carry, params, handle))
            best = min(_timed(prog, carry, params, handle) for _ in range(3))
        finally:
            host_call.call = call
        print(f"{scen.batch_size} instances ({carry.data.qpos.shape[0]} rows): controller and metrics "
              f"{1e3 * best / args.ticks:.3f} ms a tick without physics (compiled in {t_compile:.1f} s)")
    return 0


def _timed(prog, *a) -> float:
    t = time.perf_counter()
    jax.block_until_ready(prog(*a))
    return time.perf_counter() - t


if __name__ == "__main__":
    raise SystemExit(main())
