"""Time to start simulating when only the instance count changes: `hyqjax stepdown` runs in a row.

The first run (the first of ``--instances``) compiles the batch shape of its bucket into the persistent compilation
cache (a fresh cache directory unless ``--cache-dir``); the later runs have other instance counts. With the batch
buckets of :mod:`hyqjax.sim.runner` (MJX-JAX on a CPU: a power of two up to 8 instances, then passes of 8; C
MuJoCo: one pass of the next power of two, at least 8) they land on one compiled shape, so they load their
programs from the cache instead of compiling.

For each run the script records, from its own clock: ``to_simulating_s``, the time from starting the process to
the end of the compile phase (the command's "compiled in" or "loaded from the cache" line on stderr, when the
simulation starts; the process start, imports, model setup and the compile or cache load included), and
``cpu_to_simulating_s`` the CPU seconds the process used until then (``/proc``; about what the wait would be on
idle cores, where it runs on one core at a time until the simulation starts, unless XLA compiles), and
``wall_s`` the whole run; from the run's results.json: ``compile_s`` (the compile phase), ``trace_s`` (its tracing
and lowering, which the persistent cache does not spare), ``compiled`` and ``from_cache`` (programs XLA compiled,
programs loaded from the cache), ``simulate_s`` and the batch plan; and the 1-minute load average at the start
of each run. Writes JSON. Run it on idle cores (e.g. ``taskset -c 0,1`` on an idle host) for the target timing.

    python benchmarks/bench_recompile.py --out out/bench_recompile.json           # stepdown --instances 3, 4, 5
    python benchmarks/bench_recompile.py --impl jax --instances 1 2 --duration 9 --no-figures --out out/r.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import select
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MARKS = (b"compiled in ", b"loaded from the cache in ")


def cpu_seconds(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) process ``pid`` has used so far (Linux ``/proc``), else None."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def run_stepdown(instances: int, duration: float, heights: list[float], out_dir: str, cache_dir: str,
                 timeout: float, impl: str = "auto", figures: bool = True) -> dict:
    """One `hyqjax stepdown` in a fresh process; the times seen from outside and its results.json timing."""
    cmd = [sys.executable, "-c", "import sys; from hyqjax.cli import main; sys.exit(main())", "stepdown",
           "--instances", str(instances), "--duration", f"{duration:g}", "--heights", *[f"{h:g}" for h in heights],
           "--impl", impl, "--out", out_dir] + ([] if figures else ["--no-figures"])
    env = dict(os.environ, HYQJAX_CACHE_DIR=cache_dir, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = None
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    seen, err, t_sim, cpu_sim = b"", b"", None, None
    while proc.poll() is None and time.perf_counter() - t0 < timeout:
        ready, _, _ = select.select([proc.stderr], [], [], 0.2)
        if ready:
            chunk = os.read(proc.stderr.fileno(), 65536)
            err += chunk
            seen = (seen + chunk)[-4096:]
            if t_sim is None and any(m in seen for m in MARKS):
                t_sim = time.perf_counter() - t0
                cpu_sim = cpu_seconds(proc.pid)
    if proc.poll() is None:
        proc.kill()
        raise RuntimeError(f"hyqjax stepdown --instances {instances} did not finish within {timeout:g} s")
    out, rest = proc.communicate()
    err += rest
    wall = time.perf_counter() - t0
    if t_sim is None and any(m in err for m in MARKS):  # the line arrived with the last read
        t_sim = wall
    if proc.returncode != 0:
        raise RuntimeError(f"hyqjax stepdown exited {proc.returncode}: {err.decode(errors='replace')[-2000:]}")
    with open(os.path.join(out_dir, "results.json")) as f:
        res = json.load(f)
    timing = res.get("timing", {})
    batches = timing.get("batches") or [{}]
    return dict(instances_per_cell=instances, batch=len(heights) * 2 * instances, impl=res.get("impl"),
                load_average_1min_at_start=load, to_simulating_s=t_sim, cpu_to_simulating_s=cpu_sim, wall_s=wall,
                compile_s=timing.get("compile_s"), trace_s=batches[0].get("trace_s"),
                compiled=batches[0].get("compiled"), from_cache=batches[0].get("from_cache"),
                simulate_s=timing.get("simulate_s"), batches=timing.get("batches"),
                compile_lines=[ln.strip() for ln in err.decode(errors="replace").replace("\r", "\n").splitlines()
                               if any(m.decode() in ln for m in MARKS)],
                stdout_tail=out.decode(errors="replace")[-600:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--instances", type=int, nargs="+", default=[3, 4, 5], help="--instances of the runs, in order")
    ap.add_argument("--heights", type=float, nargs="+", default=[0.16, 0.21, 0.24], help="--heights of every run")
    ap.add_argument("--duration", type=float, default=24.0, help="--duration of every run (s)")
    ap.add_argument("--impl", default="auto", help="--impl of every run")
    ap.add_argument("--no-figures", action="store_true", help="pass --no-figures (default: the figures are made)")
    ap.add_argument("--cache-dir", default=None, help="compilation cache (default: a fresh temporary directory)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="limit per run (s)")
    ap.add_argument("--out", required=True, help="output JSON")
    args = ap.parse_args(argv)
    work = tempfile.mkdtemp(prefix="hyqjax-recompile-")
    cache = args.cache_dir or os.path.join(work, "cache")
    try:
        runs = [run_stepdown(k, args.duration, args.heights, os.path.join(work, f"run{i}"), cache, args.timeout,
                             args.impl, not args.no_figures)
                for i, k in enumerate(args.instances)]
    finally:
        shutil.rmtree(work, ignore_errors=True)
    try:
        load = os.getloadavg()
    except OSError:
        load = None
    result = dict(benchmark="bench_recompile", date=time.strftime("%Y-%m-%d %H:%M:%S"), python=platform.python_version(),
                  cpus=os.cpu_count(), affinity=len(os.sched_getaffinity(0)), load_average=load,
                  duration=args.duration, heights=args.heights, figures=not args.no_figures,
                  fresh_cache=args.cache_dir is None, runs=runs)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    for r in runs:
        cpu = r["cpu_to_simulating_s"]
        print(f"--instances {r['instances_per_cell']} ({r['batch']} instances, {r['impl']}): simulating after "
              f"{r['to_simulating_s']:.1f} s ({'?' if cpu is None else f'{cpu:.1f}'} s of CPU; compile phase "
              f"{r['compile_s']:.1f} s, of which tracing "
              f"{r['trace_s'] or 0:.1f} s; programs compiled {r['compiled']}, from the cache {r['from_cache']}), "
              f"wall {r['wall_s']:.1f} s, load {r['load_average_1min_at_start']}, "
              f"batches {[(b['batch'], b['passes']) for b in r['batches'] or []]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
