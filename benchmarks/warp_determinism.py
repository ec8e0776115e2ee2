"""Whether MuJoCo Warp repeats a batch bit for bit, with and without Warp's deterministic execution mode, and at what
cost.

Usage: ``PYTHONPATH=. python benchmarks/warp_determinism.py [--modes not_guaranteed,run_to_run,run_to_run+xla]
[--processes 2] [--reps 2] [--instances 544] [--duration 24] [--impl warp] [--out determinism.json]``.

The batch is the one whose run-to-run differences were measured (benchmarks/RESULTS.md, docs/warp.md): ``hyqjax
tune``'s default start (the preset ``clean``, the 56 per-leg coordinates) on its selection batch (``select_seed``
5555, the training heights, the wide spread; 544 step-downs by default, and ``--instances`` draws a batch of another
size from the same seed, not a subset), through the tuner's own
forward evaluator (:class:`hyqjax.studies.tune.forward.SuccessEvaluator`). For each mode
(``warp.config.deterministic``: ``not_guaranteed``, Warp's default, ``run_to_run`` or ``gpu_to_gpu``), each of
``--processes`` fresh processes sets the mode before MuJoCo Warp's kernels are built (each of Warp's modes with a
kernel cache of its own, so that no kernel built under another mode is reused), then runs the batch ``--reps`` times.
Every run is compared with the mode's first: the step-downs whose ``clean`` or ``completed`` outcome differs, and
those whose outcome columns (tilts, progress, forces, times) differ in any bit. A mode that fails to build or run is
reported with its error. The walls are those of the runs after the first (the first includes the compiles).

The controller, the scenario set-up and the outcome reductions around MuJoCo Warp's step are XLA programs, whose GPU
reductions and scatters may themselves differ from run to run. A mode with the suffix ``+xla`` (``run_to_run+xla``)
also starts its processes with XLA's deterministic GPU operations (``XLA_FLAGS=--xla_gpu_deterministic_ops=true``),
so the modes together tell Warp's share of the differences from XLA's.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

from hyqjax.io.atomic import write_json

MODES = ("not_guaranteed", "run_to_run", "gpu_to_gpu")
XLA_SUFFIX = "+xla"
XLA_DETERMINISTIC = "--xla_gpu_deterministic_ops=true"


def split_mode(mode: str) -> tuple[str, bool]:
    """``"run_to_run+xla"`` -> ``("run_to_run", True)``: Warp's mode, and whether XLA's GPU operations are deterministic
    too (module docstring)."""
    base = mode[: -len(XLA_SUFFIX)] if mode.endswith(XLA_SUFFIX) else mode
    return base, base != mode


def mode_env(mode: str, environ=None) -> dict:
    """The environment of a worker of ``mode``: ``environ`` (default ``os.environ``) with XLA's deterministic GPU
    operations added to ``XLA_FLAGS`` for a ``+xla`` mode."""
    env = dict(os.environ if environ is None else environ)
    if split_mode(mode)[1]:
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " " + XLA_DETERMINISTIC).strip()
    return env


def worker(a) -> dict:
    """One process: set the mode, build the evaluator, run the batch ``a.reps`` times (module docstring)."""
    os.environ["WARP_CACHE_PATH"] = a.kernel_cache
    import warp as wp

    wp.config.kernel_cache_dir = a.kernel_cache
    wp.config.deterministic = wp.DeterministicMode[split_mode(a.mode)[0].upper()]
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hyqjax.cli import tune as tune_cli
    from hyqjax.studies.tune import wallclock, wallclock_run

    cfg = tune_cli.default_config(os.path.join(a.kernel_cache, "tune"), a.impl)
    cfg = dataclasses.replace(cfg, select_instances=a.instances)
    _, theta, ev = wallclock.start_evaluator(cfg, a.duration)
    sc = wallclock_run.validation_scenarios(cfg)
    runs = []
    for _ in range(a.reps):
        t = time.perf_counter()
        r = ev(jnp.asarray(theta[None], jnp.float32), sc)
        wall = time.perf_counter() - t
        cols = {k: np.asarray(v)[0] for k, v in r["columns"].items()}
        runs.append(dict(wall_s=wall, clean=cols["clean"].astype(bool).tolist(),
                         completed=cols["completed"].astype(bool).tolist(),
                         bits={k: v.tobytes().hex() for k, v in cols.items()}))
    return dict(mode=a.mode, device=str(jax.devices()[0].device_kind), impl=ev.setup.impl, warp=wp.__version__,
                xla_flags=os.environ.get("XLA_FLAGS", ""), runs=runs)


def compare(first: dict, run: dict) -> dict:
    """Step-downs of ``run`` whose outcome, or whose outcome columns in any bit, differ from ``first``'s."""
    import numpy as np

    flips = dict(clean=int(np.sum(np.asarray(first["clean"]) != np.asarray(run["clean"]))),
                 completed=int(np.sum(np.asarray(first["completed"]) != np.asarray(run["completed"]))))
    differ = [k for k in first["bits"] if first["bits"][k] != run["bits"].get(k)]
    return dict(flips, columns_differing=differ, identical=not differ)


def summarise_mode(procs: list[dict], wall_s: float) -> dict:
    """One mode's record from its processes so far: each run compared with the mode's first (:func:`compare`), the
    first run's counts, the walls of the runs after each process's first, and the first error."""
    ok = [q for q in procs if "error" not in q]
    runs = [r for q in ok for r in q["runs"]]
    first = ok[0] if ok else {}
    return dict(processes=len(ok), error=next((q["error"] for q in procs if "error" in q), None),
                device=first.get("device"), impl=first.get("impl"), warp=first.get("warp"),
                xla_flags=first.get("xla_flags"), comparisons=[compare(runs[0], r) for r in runs[1:]] if runs else [],
                first_clean=int(sum(runs[0]["clean"])) if runs else None,
                first_completed=int(sum(runs[0]["completed"])) if runs else None,
                wall_s_after_first=[r["wall_s"] for q in ok for r in q["runs"][1:]], mode_wall_s=wall_s)


def table_row(mode: str, r: dict, reps: int) -> str:
    """A mode's row of the summary table (``main``'s header)."""
    if r["error"]:
        last = r["error"].strip().splitlines()[-1] if r["error"].strip() else r["error"]
        return f"| {mode} | failed: {last} | | | | |"
    cmp = r["comparisons"]
    same = sum(c["identical"] for c in cmp)
    flips = (max((c["clean"] for c in cmp), default=0), max((c["completed"] for c in cmp), default=0))
    walls = r["wall_s_after_first"]
    wall = f"{sorted(walls)[len(walls) // 2]:.2f}" if walls else "-"
    return (f"| {mode} | {r['processes']} x {reps} | {r['first_clean']} / {r['first_completed']} | "
            f"{same} of {len(cmp)} | {flips[0]} / {flips[1]} | {wall} |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--modes", default="not_guaranteed,run_to_run,run_to_run+xla",
                   help=f"comma-separated, from {', '.join(MODES)}, each optionally with {XLA_SUFFIX} (XLA's "
                        "deterministic GPU operations too)")
    p.add_argument("--processes", type=int, default=2, help="fresh processes per mode")
    p.add_argument("--reps", type=int, default=2, help="runs of the batch per process")
    p.add_argument("--instances", type=int, default=544, help="step-downs of the batch (a multiple of 4)")
    p.add_argument("--duration", type=float, default=24.0, help="seconds of each step-down")
    p.add_argument("--impl", default="warp")
    p.add_argument("--out", default="")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="not_guaranteed", help=argparse.SUPPRESS)
    p.add_argument("--kernel-cache", default="", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    modes = [m for m in a.modes.split(",") if m]
    bad = [m for m in modes if split_mode(m)[0] not in MODES]
    if bad or not modes:
        p.error(f"--modes must name some of {', '.join(MODES)} (each optionally with {XLA_SUFFIX}), got {a.modes!r}")
    if a.processes < 1 or a.reps < 1 or a.instances < 4 or a.instances % 4:
        p.error("--processes and --reps must be >= 1, --instances a positive multiple of 4")
    if a.worker:
        print(json.dumps(worker(a)))
        return 0
    from hyqjax.io.phases import process_age

    t0 = time.perf_counter() - (process_age() or 0.0)  # the clock starts with the process
    root = tempfile.mkdtemp(prefix="hyqjax-warp-determinism-")
    settings = {k: v for k, v in vars(a).items() if k not in ("worker", "mode", "kernel_cache")}
    results = {}
    for mode in modes:
        t_mode = time.perf_counter()
        cache = os.path.join(root, split_mode(mode)[0])  # XLA's flags do not change Warp's kernels
        os.makedirs(cache, exist_ok=True)
        procs = []
        for i in range(a.processes):
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", "--mode", mode, "--kernel-cache", cache,
                   "--reps", str(a.reps), "--instances", str(a.instances), "--duration", str(a.duration),
                   "--impl", a.impl]
            with tempfile.TemporaryFile("w+") as err:
                c = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=mode_env(mode))
                err.seek(0)
                tail = err.read()[-1500:]
            procs.append(dict(error=f"exit {c.returncode}: {tail}") if c.returncode != 0
                         else json.loads(c.stdout.strip().splitlines()[-1]))
            results[mode] = summarise_mode(procs, time.perf_counter() - t_mode)
            # Every finished process is on disk and on the console at once: a run stopped by a time limit keeps them.
            print(f"{mode}: process {i + 1} of {a.processes} done ({time.perf_counter() - t0:.0f} s since the process "
                  f"started): {table_row(mode, results[mode], a.reps)}", flush=True)
            if a.out:
                write_json(a.out, dict(date=datetime.date.today().isoformat(), python=platform.python_version(),
                                       settings=settings, wall_s=time.perf_counter() - t0, modes=results,
                                       complete=False))
            if "error" in procs[-1]:
                break
    import jax

    out = dict(date=datetime.date.today().isoformat(), jax=jax.__version__, python=platform.python_version(),
               settings=settings, wall_s=time.perf_counter() - t0, modes=results, complete=True)
    print(f"| mode | processes x runs | clean / completed of {a.instances} (first run) | runs identical to the first "
          "| largest clean / completed flips | wall of a later run (s) |")
    print("|---|---|---|---|---|---|")
    for mode, r in results.items():
        print(table_row(mode, r, a.reps))
    if a.out:
        write_json(a.out, out)
    each = ", ".join(f"{m} {r['mode_wall_s']:.1f} s" for m, r in results.items())
    print(f"device {next((r['device'] for r in results.values() if r['device']), '-')}; wall "
          f"{time.perf_counter() - t0:.1f} s in all (since the process started): the modes' processes ({each}: "
          f"imports, MuJoCo Warp's kernel build and the XLA compile in each process's first run, then the runs), "
          f"the rest imports and this summary")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
