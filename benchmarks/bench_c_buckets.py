"""The cost of the C MuJoCo backend's batch buckets: the same step-down batch run padded to its bucket and at its
exact size, side by side in one process.

For each ``--batches`` size ``n`` (the step-down's 3 heights x reflex off/on, ``n`` a multiple of 6, no traces),
the batch runs ``--repeats`` times through the bucketed runner (``hyqjax.sim.runner.host_physics_plan``: the
controller and metrics at the bucket's size, C MuJoCo stepping the ``n`` real instances) and through a runner
without buckets (every array at ``n``), alternating so that a change of the machine's load hits both alike. Each
runner compiles once per shape before the timed calls (the compile is not timed). Reported per run: the
simulating seconds and env-steps/s of the ``n`` real instances (``n x ticks / simulate_s``), and env-steps per
CPU-second of the process over the call (steadier than wall time on a loaded machine); per size: the medians
and their ratios (bucketed / exact). Writes JSON (``--out``) and prints a summary.

Usage::

    PYTHONPATH=. python benchmarks/bench_c_buckets.py --batches 18 30 --duration 4 --out out/c_buckets.json
    PYTHONPATH=. python benchmarks/bench_c_buckets.py --batches 6 --duration 0.2 --repeats 1 --out out/tiny.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import numpy as np  # noqa: E402

from hyqjax.studies import stepdown  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_physics import host_info  # noqa: E402

HEIGHTS = (0.16, 0.21, 0.24)


def timed(runner, st, scen, chunk_seconds: float) -> dict:
    """One run's ``last_timing`` plus ``cpu_s``: the CPU seconds of this process (all threads) over the call."""
    mb, d0 = stepdown.batch_inputs(st, scen)
    c0 = time.process_time()
    res = runner(mb, d0, scen.params, scen.push, chunk_seconds=chunk_seconds)
    jax.block_until_ready(res)
    return dict(runner.last_timing, cpu_s=time.process_time() - c0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[18], help="real instances per batch (multiples of 6)")
    ap.add_argument("--duration", type=float, default=4.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each runner per batch size")
    ap.add_argument("--out", required=True, help="output JSON")
    args = ap.parse_args(argv)
    cfg = stepdown.StepdownConfig(duration=args.duration, impl="c")
    ro = stepdown.make_stepdown_rollout(cfg)
    st = ro.setup
    n_ticks = cfg.sim_config().n_ticks
    chunk = 1.0
    bucketed = ro.runner()
    rows = []
    for n in args.batches:
        scen, _ = stepdown.make_scenarios(HEIGHTS, [False, True], -(-n // 6), seed=0)
        exact = st.backend.make_runner(st.ids, ro.controller, ro.sim_config, ro.metrics, ro.record, buckets=False)
        compile_s = {name: timed(r, st, scen, chunk)["compile_s"] for name, r in (("bucketed", bucketed),
                                                                                  ("exact", exact))}
        runs = {"bucketed": [], "exact": []}
        for _ in range(args.repeats):
            for name, r in (("exact", exact), ("bucketed", bucketed)):
                t = timed(r, st, scen, chunk)
                assert t["compile_s"] == 0.0, "a timed run compiled"
                steps = scen.batch_size * n_ticks
                runs[name].append(dict(simulate_s=t["simulate_s"], cpu_s=t["cpu_s"], batch=t["batch"],
                                       env_steps_per_s=steps / t["simulate_s"], env_steps_per_cpu_s=steps / t["cpu_s"],
                                       load_1min=os.getloadavg()[0]))
        med = {k: float(np.median([r["env_steps_per_s"] for r in v])) for k, v in runs.items()}
        med_cpu = {k: float(np.median([r["env_steps_per_cpu_s"] for r in v])) for k, v in runs.items()}
        rows.append(dict(instances=scen.batch_size, bucket=runs["bucketed"][0]["batch"], runs=runs,
                         compile_s_first=compile_s, median_env_steps_per_s=med, median_env_steps_per_cpu_s=med_cpu,
                         ratio_bucketed_over_exact=med["bucketed"] / med["exact"],
                         cpu_ratio_bucketed_over_exact=med_cpu["bucketed"] / med_cpu["exact"]))
        r = rows[-1]
        print(f"{scen.batch_size} instances: bucket of {r['bucket']}: {med['bucketed']:,.0f} env-steps/s "
              f"({med_cpu['bucketed']:,.0f} per CPU-s), exact: {med['exact']:,.0f} env-steps/s "
              f"({med_cpu['exact']:,.0f} per CPU-s); bucketed / exact {r['ratio_bucketed_over_exact']:.3f} wall, "
              f"{r['cpu_ratio_bucketed_over_exact']:.3f} CPU (median of {args.repeats}; load "
              f"{os.getloadavg()[0]:.2f})", flush=True)
    result = dict(benchmark="bench_c_buckets", date=time.strftime("%Y-%m-%d %H:%M:%S"), host=host_info(),
                  versions=dict(jax=jax.__version__, mujoco=__import__("mujoco").__version__),
                  duration=args.duration, ticks=n_ticks, chunk_seconds=chunk, rows=rows)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
