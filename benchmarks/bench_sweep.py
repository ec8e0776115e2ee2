"""Step-down sweep throughput: instances per second of ``hyqjax.studies.sweep.run_rows`` (the chunk runner of
``hyqjax sweep``), on one local device and sharded over all of them.

Usage: ``PYTHONPATH=. python benchmarks/bench_sweep.py [--batch 16 32] [--duration 2] [--host-devices N]``.
``--host-devices N`` splits the CPU into N XLA devices (``--xla_force_host_platform_device_count``) so
the sharded path can be measured on a CPU host; on a GPU host every GPU is a device. Each (batch,
devices) point is compiled and warmed up once, then timed ``--repeats`` times (median); instances/s =
batch / median, env-steps/s = batch x ticks / median. Instances are the default sweep's (heights 0.16-0.24,
reflex on/off, random friction and payload).
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, nargs="+", default=[16, 32])
    p.add_argument("--duration", type=float, default=2.0, help="simulated seconds per instance")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--host-devices", type=int, default=0, help="split the CPU into this many XLA devices")
    args = p.parse_args(argv)
    if args.host_devices:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + f" --xla_force_host_platform_device_count={args.host_devices}").strip()
    import hyqjax  # noqa: F401  (XLA:CPU flags)
    import jax
    import mujoco
    import numpy as np

    from hyqjax.studies import sweep

    devs = jax.local_devices()
    try:
        from importlib.metadata import version

        mjx_v = version("mujoco-mjx")
    except Exception:  # pragma: no cover
        mjx_v = "?"
    print(f"# bench_sweep {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}")
    print(f"# devices: {len(devs)} x {devs[0].device_kind} ({devs[0].platform}); host cpus {os.cpu_count()}; "
          f"load {os.getloadavg()[0]:.1f}")
    print(f"# jax {jax.__version__}, mujoco {mujoco.__version__}, mujoco-mjx {mjx_v}, python {platform.python_version()}")
    print(f"# duration {args.duration} s = {int(round(args.duration / 0.002))} ticks of 2 ms per instance")
    print("| batch | devices | compile+first s | median s | instances/s | env-steps/s |")
    print("|---:|---:|---:|---:|---:|---:|")
    ticks = int(round(args.duration / 0.002))
    sets = [devs[:1]] + ([devs] if len(devs) > 1 else [])
    for b in args.batch:
        spec = sweep.SweepSpec.from_dict(dict(samples=max(1, b // 6), duration=args.duration,
                                              grid=dict(height=[0.16, 0.21, 0.24], reflex=[False, True]),
                                              random=dict(friction=[0.6, 1.0], payload_mass=[0.0, 10.0])))
        rows = spec.instance_inputs(0, min(b, spec.n_instances))
        for ds in sets:
            t0 = time.time()
            sweep.run_rows(rows, spec, b, ds)
            first = time.time() - t0
            ts = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                sweep.run_rows(rows, spec, b, ds)
                ts.append(time.perf_counter() - t0)
            med = float(np.median(ts))
            print(f"| {b} | {len(ds)} | {first:.1f} | {med:.2f} | {b / med:.1f} | {b * ticks / med:,.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
