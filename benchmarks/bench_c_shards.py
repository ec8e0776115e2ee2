"""The C MuJoCo backend with its batch as one shard and as one shard per core, alternated in one process.

One batch of exactly ``--batch`` step-down instances (the first ``--batch`` of ``stepdown.make_scenarios`` over
3 heights x reflex off/on, as ``bench_cpu_backend.py``) for ``--duration`` simulated seconds, run ``--reps`` times
with each sharding in turn (``--shards``; the runner's ``shards``, :meth:`hyqjax.sim.cpu_backend.CBatchRunner.
shard_bounds`). Reports each run's simulating time (compile excluded; the first run of a sharding compiles its
bucket), env-steps/s, the median per sharding, and whether every output is bitwise the same under every sharding.
Alternating in one process is what makes the comparison fair on a machine whose speed drifts.

Usage::

    PYTHONPATH=. taskset -c 0,1 python benchmarks/bench_c_shards.py --batch 64 --duration 24 --reps 3 \\
        --out out/c_shards_b64.json
"""
from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import numpy as np  # noqa: E402

from hyqjax.io import atomic as hio  # noqa: E402
from hyqjax.studies import stepdown  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_cpu_backend import HEIGHTS  # noqa: E402  (the same batch as bench_cpu_backend.py)
from bench_physics import host_info  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=64, help="instances")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per instance")
    ap.add_argument("--shards", type=int, nargs="+", default=[1, 2], help="shardings to alternate")
    ap.add_argument("--reps", type=int, default=3, help="runs of each sharding")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.batch < 1 or args.duration <= 0 or args.reps < 1 or min(args.shards) < 1:
        ap.error("--batch, --reps and --shards must be >= 1 and --duration > 0")
    scen, _ = stepdown.make_scenarios(HEIGHTS, [False, True], -(-args.batch // 6), args.seed)
    scen = jax.tree_util.tree_map(lambda x: x[:args.batch], scen)
    cfg = stepdown.StepdownConfig(duration=args.duration, impl="c")
    ro = stepdown.make_stepdown_rollout(cfg)
    runner = ro.runner()
    ticks = cfg.sim_config().n_ticks
    res = dict(info=host_info(), args=vars(args), batch=scen.batch_size, runs=[])
    first = {}
    same = True
    for rep in range(args.reps):
        for s in args.shards:
            runner.shards = s
            t = time.perf_counter()
            out = ro.run(scen)
            jax.block_until_ready(out)
            wall = time.perf_counter() - t
            sim_s = runner.last_timing["simulate_s"]
            leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(out)]
            if s not in first:
                first[s] = leaves
            same &= all(np.array_equal(a, b, equal_nan=True) for a, b in zip(leaves, first[args.shards[0]]))
            row = dict(rep=rep, shards=runner.last_timing.get("shards", 1), wall_s=wall, simulate_s=sim_s,
                       compile_s=runner.last_timing["compile_s"], rate=scen.batch_size * ticks / sim_s)
            res["runs"].append(row)
            print(f"rep {rep} shards {row['shards']}: simulating {sim_s:.2f} s ({row['rate']:,.0f} env-steps/s), "
                  f"compile {row['compile_s']:.1f} s", flush=True)
    runner.shards = None
    res["median_simulate_s"] = {str(s): float(np.median([r["simulate_s"] for r in res["runs"] if r["shards"] == s]))
                                for s in sorted({r["shards"] for r in res["runs"]})}
    res["bitwise_equal"] = bool(same)
    res["loadavg_at_end"] = list(os.getloadavg())
    print("median simulating time by shards:", res["median_simulate_s"], "| bitwise equal:", same)
    if args.out:
        hio.write_json(args.out, res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
