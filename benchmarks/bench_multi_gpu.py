"""Step-down throughput over 1..N GPUs of one host, side by side, and the outcome agreement between layouts.

    python benchmarks/bench_multi_gpu.py --out DIR                     # every GPU: 1 and N GPUs, both layouts
    python benchmarks/bench_multi_gpu.py --out DIR --counts 1 2 4 8    # every count (budget permitting)
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python benchmarks/bench_multi_gpu.py --out DIR \\
        --impl jax --per-device 4 --duration 0.4 --counts 1 2          # CPU check of the script (seconds)

The paper-table step-down (``hyqjax stepdown``'s heights 0.16 / 0.21 / 0.24 m x reflex off / on, the paper's crawl
``CrawlParams.make()``, ``--duration`` 24 s by default) with ``--per-device`` instances per device (65,536 by
default), drawn at random from the table's cells (a fixed permutation of ``--seed``'s instances, so every device's
slice samples every cell). For each device count ``g`` of ``--counts`` (default: 1 and every local device) and
each layout of ``--modes``:

* ``split``: one process, ``hyqjax.sim.runner.run_on`` (what ``hyqjax stepdown`` / ``sweep`` / the reach map do by
  default): the ``g x per-device`` instances in ``g`` slices, one program per device, dispatched in turn;
* ``process``: ``g`` worker processes of this script, one per GPU (``CUDA_VISIBLE_DEVICES``), each running its
  slice of the same instances; the rate counts the span from the first worker's start of simulating to the last
  one's end.

Reported per run: env-steps/s over simulating time (compile excluded; instances x ticks / seconds), the speed-up
over the 1-device run of the same layout, compile and wall seconds; and the agreement of every run's per-instance
``completed`` and ``clean`` with the 1-device run on the instances both ran (the first ``per-device``), with the
per-cell counts of both. MJX-JAX's split layout is bitwise that of one device on host devices; MuJoCo Warp's
contact buffer and atomics make repeated runs agree within the simulator's agreement (counted, not assumed).

Then (``--tune-members``, 0 to skip) one tuning generation, ``--tune-members`` x ``--tune-scenarios`` rows of
``--tune-duration`` s (the tuner's forward objective, ``SuccessEvaluator``), on 1 device and on each further
count: simulating and wall seconds of the same generation and their speed-up.

Stops starting new runs once ``--budget-s`` (default 420 s) would be passed (the estimate: the last run's wall
time, scaled); ``DIR/bench_multi_gpu.json`` is rewritten after every run, so a killed run keeps what was measured.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

HEIGHTS = (0.16, 0.21, 0.24)
REFLEX = (False, True)


def scenario_rows(per_device: int, max_count: int, seed: int):
    """``(scenario, table)`` of ``per_device * max_count`` instances of the paper table, in a fixed random order."""
    from hyqjax.crawl import controller as crawl
    from hyqjax.sim.task import _take
    from hyqjax.studies import stepdown

    total = per_device * max_count
    k = -(-total // (len(HEIGHTS) * len(REFLEX)))
    scen, table = stepdown.make_scenarios(list(HEIGHTS), list(REFLEX), k, seed, params=crawl.CrawlParams.make())
    perm = np.random.default_rng(seed).permutation(scen.batch_size)[:total]
    return _take(scen, perm), {key: np.asarray(v)[perm] for key, v in table.items()}


def run_rows(scen, lo: int, hi: int, impl: str, duration: float, devices) -> dict:
    """Simulate instances ``lo..hi-1`` of ``scen`` over ``devices``; outcome columns and timing."""
    from hyqjax.sim.compile_phase import compile_listener
    from hyqjax.sim.task import _take
    from hyqjax.studies import stepdown, stepdown_outcome

    ro = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=duration, impl=impl, record_every=0))
    done: list = []
    t0 = time.time()
    with compile_listener(lambda ev, info: done.append(dict(info)) if ev == "done" else None):
        out, _ = ro.run(_take(scen, np.arange(lo, hi)), devices=devices)
    cols = stepdown_outcome.to_columns(out)
    t_end = time.time()
    timing = done[-1] if done else {}
    sim_s = float(timing.get("simulate_s", float("nan")))
    return dict(completed=np.asarray(cols["completed"], bool), clean=np.asarray(cols["clean"], bool),
                simulate_s=sim_s, compile_s=float(timing.get("compile_s", float("nan"))), wall_s=t_end - t0,
                sim_start=t_end - sim_s, sim_end=t_end, impl=ro.setup.impl,
                ticks=int(round(duration / ro.cfg.control_dt)))


def worker(args) -> int:
    """One process of the ``process`` layout: its slice on its one visible device; writes ``--worker-out``."""
    import jax

    scen, _ = scenario_rows(args.per_device, args.max_count, args.seed)
    lo = args.worker_index * args.per_device
    r = run_rows(scen, lo, lo + args.per_device, args.impl, args.duration, jax.local_devices()[:1])
    np.savez(args.worker_out, **{k: np.asarray(v) for k, v in r.items()})
    return 0


def agreement(ref: dict, run: dict, table: dict, n: int) -> dict:
    """Per-instance agreement of ``completed`` / ``clean`` on the first ``n`` instances, and per-cell counts."""
    out = {}
    for col in ("completed", "clean"):
        a, b = ref[col][:n], run[col][:n]
        cells = []
        for h in HEIGHTS:
            for rf in REFLEX:
                m = (np.isclose(table["height"][:n], h)) & (table["reflex"][:n] == rf)
                cells.append(dict(height=h, reflex=bool(rf), n=int(m.sum()), one_device=int(a[m].sum()),
                                  this_run=int(b[m].sum())))
        out[col] = dict(agree=int((a == b).sum()), of=int(n), share=float((a == b).mean()),
                        counts_equal_per_cell=all(c["one_device"] == c["this_run"] for c in cells), cells=cells)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="results directory (bench_multi_gpu.json)")
    ap.add_argument("--impl", default="warp", choices=["jax", "warp"], help="simulator")
    ap.add_argument("--per-device", type=int, default=65536, help="instances per device")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per instance")
    ap.add_argument("--counts", type=int, nargs="+", default=None,
                    help="device counts to measure (default: 1 and every local device)")
    ap.add_argument("--modes", nargs="+", default=["split", "process"], choices=["split", "process"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--budget-s", type=float, default=420.0, help="start no run that would end after this")
    ap.add_argument("--tune-members", type=int, default=64,
                    help="tuning generation: members (0: skip the tuning section)")
    ap.add_argument("--tune-scenarios", type=int, default=4096, help="tuning generation: scenarios per member")
    ap.add_argument("--tune-duration", type=float, default=6.0, help="tuning generation: seconds per run")
    ap.add_argument("--worker-index", type=int, default=-1, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", default="", help=argparse.SUPPRESS)
    ap.add_argument("--max-count", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if not (args.per_device >= 1 and 0 < args.duration <= 120):
        print("bench_multi_gpu: --per-device must be >= 1 and --duration in (0, 120] s", file=sys.stderr)
        return 2
    from hyqjax.io.cache import enable_compilation_cache

    enable_compilation_cache()  # devices 1..N-1 (and the worker processes) load device 0's compiled program
    if args.worker_index >= 0:
        return worker(args)
    import jax

    t_start = time.time()
    local = jax.local_devices()
    counts = sorted(set(args.counts or [1, len(local)]))
    if counts[0] < 1 or counts[-1] > len(local):
        print(f"bench_multi_gpu: --counts must be in [1, {len(local)}] (the local devices)", file=sys.stderr)
        return 2
    if 1 not in counts:
        counts = [1] + counts
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "bench_multi_gpu.json")
    scen, table = scenario_rows(args.per_device, counts[-1], args.seed)
    res = dict(command=" ".join(["python benchmarks/bench_multi_gpu.py", *(argv if argv is not None else sys.argv[1:])]),
               devices=[str(d) for d in local], device_kind=local[0].device_kind, jax=jax.__version__,
               impl=args.impl, per_device=args.per_device, duration=args.duration, counts=counts,
               modes=args.modes, runs=[], skipped=[], date=time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()))
    ref = None
    last_wall = None
    plan = [(m, g) for g in counts for m in args.modes if not (m == "process" and g == 1 and "split" in args.modes)]
    for mode, g in plan:
        est = 0.0 if last_wall is None else last_wall * 1.1
        if time.time() - t_start + est > args.budget_s:
            res["skipped"].append(dict(mode=mode, devices=g, why=f"--budget-s {args.budget_s:g} (estimate {est:.0f} s)"))
            continue
        n = g * args.per_device
        t0 = time.time()
        if mode == "split":
            r = run_rows(scen, 0, n, args.impl, args.duration, local[:g])
            span = r["simulate_s"]
        else:
            r = run_processes(args, g, local, counts[-1])
            span = r["sim_end"] - r["sim_start"]
        wall = time.time() - t0
        last_wall = wall
        rate = n * r["ticks"] / span
        if ref is None:
            ref = r
        entry = dict(mode=mode, devices=g, instances=n, env_steps_per_s=rate, simulate_s=span,
                     compile_s=r["compile_s"], wall_s=wall, impl=r["impl"],
                     agreement_with_one_device=agreement(ref, r, table, min(n, args.per_device)))
        one = next((e for e in res["runs"] if e["devices"] == 1), None)
        if one is not None:
            entry["speedup_vs_one_device"] = rate / one["env_steps_per_s"]
        res["runs"].append(entry)
        print(f"{mode:8s} {g} device(s): {n} instances x {args.duration:g} s: {rate:,.0f} env-steps/s"
              + (f" ({entry['speedup_vs_one_device']:.2f}x one device)" if one is not None else "")
              + f", simulate {span:.1f} s, compile {r['compile_s']:.1f} s, wall {wall:.1f} s; completed agree "
              f"{entry['agreement_with_one_device']['completed']['share']:.4f}", flush=True)
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
    if args.tune_members > 0:
        res["tune"] = tune_section(args, local, counts, t_start, res, path)
    with open(path, "w") as f:
        json.dump(res, f, indent=1)
    print(f"wrote {path}")
    return 0


def tune_section(args, local, counts, t_start: float, res: dict, path: str) -> list:
    """One tuning generation (``--tune-members`` x ``--tune-scenarios`` rows, common random numbers) on 1 and on
    each further count of devices: its simulating and wall seconds (``SuccessEvaluator``, the tuner's forward
    objective) and the speed-up of the same generation; the fitness of every member must not depend on the
    devices beyond the simulator's agreement (the largest fitness difference is reported)."""
    from hyqjax.crawl import controller as crawl
    from hyqjax.sim.compile_phase import compile_listener
    from hyqjax.studies.tune import forward, schedule

    p = schedule.make("shared")
    base = crawl.CrawlParams.make()
    rng = np.random.default_rng(args.seed)
    th0 = p.theta_of(base)
    thetas = th0 + 0.2 * rng.standard_normal((args.tune_members, th0.shape[0])).astype(np.float32)
    m = -(-args.tune_scenarios // len(forward.TRAIN_HEIGHTS)) * len(forward.TRAIN_HEIGHTS)
    sc = forward.train_scenarios(m, args.seed, 0)
    out, ref, last = [], None, None
    for g in counts:
        est = 0.0 if last is None else last * 1.1
        if time.time() - t_start + est > args.budget_s:
            res["skipped"].append(dict(mode="tune", devices=g, why=f"--budget-s {args.budget_s:g}"))
            continue
        done: list = []
        t0 = time.time()
        ev = forward.SuccessEvaluator(p, base, args.tune_duration, args.impl, devices=local[:g])
        with compile_listener(lambda e, info: done.append(dict(info)) if e == "done" else None):
            r = ev(thetas, sc)
        wall = time.time() - t0
        last = wall
        t = done[-1] if done else {}
        e = dict(devices=g, rows=int(args.tune_members * m), simulate_s=float(t.get("simulate_s", float("nan"))),
                 compile_s=float(t.get("compile_s", float("nan"))), wall_s=wall)
        if ref is None:
            ref = (e, np.asarray(r["fitness"]))
        else:
            e["speedup_simulate_vs_one_device"] = ref[0]["simulate_s"] / e["simulate_s"]
            e["speedup_wall_vs_one_device"] = ref[0]["wall_s"] / e["wall_s"]
            e["max_fitness_difference"] = float(np.max(np.abs(np.asarray(r["fitness"]) - ref[1])))
        out.append(e)
        print(f"tune     {g} device(s): generation of {e['rows']} rows x {args.tune_duration:g} s: simulate "
              f"{e['simulate_s']:.1f} s, wall {wall:.1f} s"
              + (f" ({e['speedup_simulate_vs_one_device']:.2f}x one device)" if g != ref[0]["devices"] else ""),
              flush=True)
        res["tune"] = out
        with open(path, "w") as f:
            json.dump(res, f, indent=1)
    return out


def run_processes(args, g: int, local, max_count: int) -> dict:
    """``g`` worker processes, one per device; the slices' columns joined, the simulating span of all."""
    import tempfile

    procs, outs = [], []
    tmp = tempfile.mkdtemp(prefix="bench_multi_gpu_")
    for i in range(g):
        env = dict(os.environ)
        if local[0].platform == "gpu":
            env["CUDA_VISIBLE_DEVICES"] = str(local[i].id)
        else:  # host devices: one per worker
            env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split()
                                        if "xla_force_host_platform_device_count" not in f)
        out = os.path.join(tmp, f"w{i}.npz")
        cmd = [sys.executable, os.path.abspath(__file__), "--out", args.out, "--impl", args.impl, "--per-device",
               str(args.per_device), "--duration", str(args.duration), "--seed", str(args.seed), "--worker-index",
               str(i), "--worker-out", out, "--max-count", str(max_count)]
        procs.append(subprocess.Popen(cmd, env=env))
        outs.append(out)
    for p in procs:
        if p.wait() != 0:
            raise RuntimeError(f"a worker process failed (exit {p.returncode})")
    parts = [dict(np.load(o)) for o in outs]
    return dict(completed=np.concatenate([p["completed"] for p in parts]),
                clean=np.concatenate([p["clean"] for p in parts]),
                sim_start=min(float(p["sim_start"]) for p in parts), sim_end=max(float(p["sim_end"]) for p in parts),
                compile_s=max(float(p["compile_s"]) for p in parts), impl=str(parts[0]["impl"]),
                ticks=int(parts[0]["ticks"]))


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    sys.exit(main())
