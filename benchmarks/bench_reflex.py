"""Benchmark of the height reflex tick (:func:`hyqjax.reflex.step.reflex_step`).

* Latency: one jitted ``reflex_step`` call for one robot (float32), median over many calls,
  each blocking on all outputs (``jax.block_until_ready``). This includes JAX's dispatch of a
  call with 19 input and 15 output arrays; the "dispatch floor" row times a jitted function of
  the same signature that does no reflex arithmetic.
* Amortised per-tick cost for one robot inside a jitted ``lax.scan`` of 1000 ticks (what a
  jitted controller loop pays).
* Throughput: robot-ticks/s of ``jit(vmap(scan(reflex_step)))`` for batches of robots, each
  with its own swing leg and plan. The scan carries the reflex state and an accumulator of the
  corrected feet ``x_r`` (so the outputs are really computed), not the per-tick outputs.

Usage::

    PYTHONPATH=. python benchmarks/bench_reflex.py                 # print the table
    PYTHONPATH=. python benchmarks/bench_reflex.py --append benchmarks/RESULTS.md

Batches 1k, 10k, 100k on every device; 1M as well when the device is a GPU.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import time

import hyqjax  # noqa: F401  (first: the package sets its XLA:CPU flags before jax is imported)
import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.reflex import step as R

DT = 1e-3
SECTION_TITLE = "## Height reflex step (reflex_step)"


def _inputs(batch: int | None, seed: int = 0):
    """Active reflex inputs: every swing leg, plans 0-25 cm below the standing feet."""
    x0 = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float32))
    if batch is None:
        return R.ReflexInputs.make(x0.at[robot.RF, 2].add(-0.1), robot.RF)
    rng = np.random.default_rng(seed)
    swing = jnp.asarray(rng.integers(0, 4, batch), jnp.int32)
    drop = jnp.asarray(rng.uniform(0.0, 0.25, batch), jnp.float32)
    return jax.vmap(lambda s, d: R.ReflexInputs.make(x0.at[s, 2].add(-d), s))(swing, drop)


def _state(inputs, batch: int | None):
    if batch is None:
        return R.reflex_init(inputs.x_des)
    return jax.vmap(R.reflex_init)(inputs.x_des)


def _time(fn, *args, repeats: int) -> list[float]:
    out = fn(*args)
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    return times


def bench_latency(device, n_calls: int = 5000) -> dict:
    params = jax.device_put(jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), R.ReflexParams()), device)
    inputs = jax.device_put(_inputs(None), device)
    state = jax.device_put(_state(inputs, None), device)
    dt = jax.device_put(jnp.float32(DT), device)
    step = jax.jit(R.reflex_step)
    times = _time(step, state, inputs, params, dt, repeats=n_calls)

    # Dispatch floor: a jitted function with the same inputs and outputs as reflex_step that
    # computes (almost) nothing; what one call costs before any reflex arithmetic.
    out_struct = jax.eval_shape(R.reflex_step, state, inputs, params, dt)

    def same_signature(s, i, p, d):
        seed = s.q_r[0] + i.x_des[0, 0] + p.k_x + d
        return jax.tree.map(lambda sd: jnp.full(sd.shape, seed).astype(sd.dtype), out_struct)

    floor = _time(jax.jit(same_signature), state, inputs, params, dt, repeats=n_calls)

    # The packed real-time entry point: one (44,) vector in, one (67,) out, parameters closed over.
    from hyqjax.reflex import realtime as RT

    with jax.default_device(device):
        packed_step = RT.make_realtime_reflex(R.ReflexParams(), DT)
        v = jax.device_put(RT.pack_inputs(state, inputs), device)
        packed = _time(packed_step, v, repeats=n_calls)

    scan = jax.jit(lambda s, i, p: R.reflex_rollout(s, i, p, DT, n_steps=1000)[0])
    scan_times = _time(scan, state, inputs, params, repeats=max(20, n_calls // 250))
    return {
        "median_us": statistics.median(times) * 1e6,
        "p10_us": float(np.percentile(times, 10) * 1e6),
        "p90_us": float(np.percentile(times, 90) * 1e6),
        "scan_per_tick_us": statistics.median(scan_times) / 1000 * 1e6,
        "dispatch_floor_us": statistics.median(floor) * 1e6,
        "packed_median_us": statistics.median(packed) * 1e6,
        "packed_p10_us": float(np.percentile(packed, 10) * 1e6),
        "packed_p90_us": float(np.percentile(packed, 90) * 1e6),
        "n_calls": n_calls,
    }


def bench_throughput(device, batch: int, target_ticks: float, repeats: int = 3) -> dict:
    n_steps = int(max(10, min(1000, target_ticks // batch)))
    params = R.ReflexParams()
    inputs = jax.device_put(_inputs(batch), device)
    state = jax.device_put(_state(inputs, batch), device)

    def one_robot(s, inp):
        def body(carry, _):
            st, acc = carry
            st, out = R.reflex_step(st, inp, params, DT)
            return (st, acc + out.x_r), None

        (s, acc), _ = jax.lax.scan(body, (s, jnp.zeros((4, 3), jnp.float32)), None, length=n_steps)
        return s, acc

    fn = jax.jit(jax.vmap(one_robot))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(state, inputs))
    compile_s = time.perf_counter() - t0
    times = _time(fn, state, inputs, repeats=repeats)
    t = statistics.median(times)
    return {
        "batch": batch,
        "n_steps": n_steps,
        "seconds": t,
        "robot_ticks_per_s": batch * n_steps / t,
        "ns_per_robot_tick": t / (batch * n_steps) * 1e9,
        "first_call_s": compile_s,
    }


def _device_label(device) -> str:
    if device.platform == "cpu":
        return f"CPU, {os.cpu_count()} cores ({platform.processor() or platform.machine()})"
    return f"{device.platform.upper()}: {getattr(device, 'device_kind', str(device))}"


def run(devices, batches, cpu_target_ticks, gpu_target_ticks, n_calls, date) -> str:
    lines = [SECTION_TITLE, ""]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines.append(
        f"Date {date}; jax {jax.__version__}, jaxlib {jax.lib.__version__ if hasattr(jax.lib, '__version__') else ''}"
        f"; Python {platform.python_version()}; float32; dt = 1 ms; Table I parameters; "
        f"host load average at start {load:.1f}; XLA_FLAGS=`{os.environ.get('XLA_FLAGS', '')}` "
        "(set by `import hyqjax`). Command: `PYTHONPATH=. python benchmarks/bench_reflex.py`."
    )
    lines.append("")
    for device in devices:
        label = _device_label(device)
        print(f"# device: {label}", flush=True)
        lat = bench_latency(device, n_calls)
        print(f"latency: {lat}", flush=True)
        lines += [
            f"### {label}",
            "",
            "| one robot | value |",
            "| --- | --- |",
            f"| `jit(reflex_step)` latency, median (p10-p90) over {lat['n_calls']} calls | "
            f"{lat['median_us']:.1f} us ({lat['p10_us']:.1f}-{lat['p90_us']:.1f}) |",
            "| dispatch floor: jitted no-op with the same 19 inputs / 15 outputs | "
            f"{lat['dispatch_floor_us']:.1f} us |",
            f"| `reflex_realtime.make_realtime_reflex` (one packed vector in and out), median (p10-p90) | "
            f"{lat['packed_median_us']:.1f} us ({lat['packed_p10_us']:.1f}-{lat['packed_p90_us']:.1f}) |",
            f"| per tick inside a jitted `lax.scan` of 1000 ticks | {lat['scan_per_tick_us']:.2f} us |",
            "",
            "| batch (robots) | ticks per call | time per call | robot-ticks/s | ns per robot-tick |",
            "| ---: | ---: | ---: | ---: | ---: |",
        ]
        dev_batches = list(batches) + ([1_000_000] if device.platform == "gpu" and 1_000_000 not in batches else [])
        target = gpu_target_ticks if device.platform == "gpu" else cpu_target_ticks
        for b in dev_batches:
            res = bench_throughput(device, b, target)
            print(f"batch {b}: {res}", flush=True)
            lines.append(
                f"| {b:,} | {res['n_steps']} | {res['seconds'] * 1e3:.1f} ms | {res['robot_ticks_per_s']:.3g} | "
                f"{res['ns_per_robot_tick']:.1f} |"
            )
        lines.append("")
    return "\n".join(lines) + "\n"


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description="Benchmark hyqjax.reflex.step.reflex_step")
    parser.add_argument("--batches", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--cpu-target-ticks", type=float, default=2e6, help="robot-ticks per timed call on CPU")
    parser.add_argument("--gpu-target-ticks", type=float, default=2e8, help="robot-ticks per timed call on GPU")
    parser.add_argument("--calls", type=int, default=5000, help="calls for the latency median")
    parser.add_argument("--cpu-only", action="store_true", help="benchmark only the CPU even if a GPU is present")
    parser.add_argument("--date", default=datetime.date.today().isoformat())
    parser.add_argument("--append", default=None, help="append the markdown section to this file")
    args = parser.parse_args(argv)

    devices = [jax.devices("cpu")[0]]
    if not args.cpu_only:
        try:
            devices += jax.devices("gpu")[:1]
        except RuntimeError:
            pass
    print(f"jax {jax.__version__}, devices {[str(d) for d in devices]}, batches {args.batches}", flush=True)
    section = run(devices, args.batches, args.cpu_target_ticks, args.gpu_target_ticks, args.calls, args.date)
    print(section)
    if args.append:
        new = not os.path.exists(args.append)
        with open(args.append, "a") as f:
            if new:
                f.write("# Benchmark results\n\n")
            f.write(section if new else "\n" + section)
    return section


if __name__ == "__main__":
    main(sys.argv[1:])
