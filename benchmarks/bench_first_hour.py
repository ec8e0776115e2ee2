"""A user's first hour on a machine: each command once on empty caches, then once warm; process wall against the
phases each command printed and stored.

Round 1 ("fresh") starts with an empty JAX compilation cache (``HYQJAX_CACHE_DIR``) and an empty MuJoCo Warp kernel
cache (``WARP_CACHE_PATH``), both under ``--caches`` (default: a temporary directory, removed at the end with the
runs' output directories), as on a new machine; its commands share them in order, as a user's would. Round 2
("warm") runs the same commands again on the caches round 1 filled. Every run is a fresh process with its own
output directory (a sweep is never resumed); its process wall is measured from before the process is started to its
exit, and compared with the wall it printed last (``wall X s in all``) and the phases it stored
(``results.json``'s ``phases``, a sweep's ``summary.json``'s ``phases_this_run``).

Sizes: ``--size gpu`` (the default; meant for one H200 with warp: ``--budget-s 400`` starts nothing new after
400 s and ``--grace-s 60`` stops a command 60 s after that, so it ends within 8 minutes), ``--size cpu`` (C MuJoCo,
small batches: a few minutes on 2 cores), ``--size tiny`` (one short bound, for the test).

    python benchmarks/bench_first_hour.py --out out/first_hour            # one GPU
    python benchmarks/bench_first_hour.py --size cpu --out out/first_hour_cpu

Writes OUT/first_hour.json and OUT/first_hour.md (a Markdown table, also printed).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time

SIZES = {
    "gpu": [
        "stepdown --instances 3",
        "stepdown --instances 1700",
        "bound --instances 1024 --duration 8",
        "sweep --grid height=0.16,0.24 --grid reflex=false,true --random friction=0.5,1.0 --samples 256",
    ],
    "cpu": [
        "stepdown --instances 1 --duration 10 --impl c",
        "bound --instances 8 --duration 0.8 --impl c",
        "sweep --grid height=0.16 --grid reflex=true --random friction=0.6,1.0 --samples 2 --duration 10 "
        "--impl c",
    ],
    "tiny": ["bound --instances 2 --duration 0.4 --impl c --no-figures"],
}
PHASES = ("startup", "kernels", "compile", "simulation", "summary", "traces", "figures")
WALL = re.compile(r"wall ([0-9.]+) s in all")


def run_one(command: str, out: str, caches: str, timeout: float) -> dict:
    """One command in a fresh process with OUT's caches; its walls and phases."""
    env = {**os.environ, "HYQJAX_CACHE_DIR": os.path.join(caches, "jax"),
           "WARP_CACHE_PATH": os.path.join(caches, "warp")}
    argv = [sys.executable, "-m", "hyqjax.cli", *shlex.split(command), "--out", out]
    t0 = time.perf_counter()
    try:
        r = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=timeout)
        rc, stdout, stderr = r.returncode, r.stdout, r.stderr
    except subprocess.TimeoutExpired as e:
        rc, stdout, stderr = "timeout", (e.stdout or b"").decode(errors="replace"), (e.stderr or b"").decode(
            errors="replace")
    wall = time.perf_counter() - t0
    printed = [float(x) for x in WALL.findall(stdout)]
    phases = {}
    for name, key in (("results.json", "phases"), ("summary.json", "phases_this_run")):
        p = os.path.join(out, name)
        if os.path.exists(p):
            with open(p) as f:
                phases = (json.load(f).get(key) or {}).get("phases", {})
            break
    kernel_line = next((ln for ln in stderr.replace("\r", "\n").splitlines() if "built MuJoCo Warp kernels" in ln),
                       "")
    return dict(command=command, rc=rc, process_wall_s=round(wall, 2), printed_wall_s=printed[-1] if printed else None,
                phases={k: round(v, 2) for k, v in phases.items()}, kernel_build_line=kernel_line.strip(),
                last_lines=stdout.strip().splitlines()[-3:],
                stderr_tail=stderr[-600:] if rc != 0 else "")


def table(rows: list[dict]) -> str:
    head = ("| command | caches | process wall (s) | printed wall (s) | process - printed (s) | "
            + " | ".join(PHASES) + " |")
    lines = [head, "|---|---|" + "---:|" * (3 + len(PHASES))]
    for r in rows:
        if r.get("skipped"):
            lines.append(f"| `hyqjax {r['command']}` | {r['round']} | skipped ({r['skipped']}) |"
                         + " |" * (2 + len(PHASES)))
            continue
        pr = r["printed_wall_s"]
        gap = f"{r['process_wall_s'] - pr:.1f}" if pr is not None else "-"
        ph = " | ".join(f"{r['phases'][k]:.1f}" if k in r["phases"] else "-" for k in PHASES)
        rc = "" if r["rc"] == 0 else f" (exit {r['rc']})"
        lines.append(f"| `hyqjax {r['command']}`{rc} | {r['round']} | {r['process_wall_s']:.1f} | "
                     f"{'-' if pr is None else f'{pr:.1f}'} | {gap} | {ph} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", choices=sorted(SIZES), default="gpu", help="the commands' sizes (default gpu)")
    p.add_argument("--out", required=True, help="results directory (first_hour.json, first_hour.md)")
    p.add_argument("--caches", default=None,
                   help="where the fresh caches go (emptied first; default: a new temporary directory, removed at "
                        "the end: compiled programs and kernels are large, and not results)")
    p.add_argument("--budget-s", type=float, default=400.0,
                   help="start no new command after this many seconds (default 400)")
    p.add_argument("--grace-s", type=float, default=60.0,
                   help="a command started within the budget is stopped this long after it (default 60 s)")
    p.add_argument("--timeout-s", type=float, default=400.0, help="one command's limit (default 400 s)")
    a = p.parse_args(argv)
    out = os.path.abspath(a.out)
    os.makedirs(out, exist_ok=True)
    if a.caches is None:
        import tempfile

        caches = tempfile.mkdtemp(prefix="hyqjax-first-hour-")
    else:
        caches = os.path.abspath(a.caches)
    shutil.rmtree(caches, ignore_errors=True)
    runs = os.path.join(caches, "runs")  # the commands' output directories (a step-down's results.json is large)
    os.makedirs(runs)
    commands = SIZES[a.size]
    t_start = time.perf_counter()
    rows = []
    for rnd in ("fresh", "warm"):
        for i, command in enumerate(commands):
            left = a.budget_s - (time.perf_counter() - t_start)
            if left <= 0:
                rows.append(dict(command=command, round=rnd, skipped=f"--budget-s {a.budget_s:g} spent"))
                continue
            row = run_one(command, os.path.join(runs, f"{rnd}_{i}"), caches, min(a.timeout_s, left + a.grace_s))
            row["round"] = rnd
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "stderr_tail"}), flush=True)
    import platform

    meta = dict(size=a.size, host=platform.node(), python=sys.version.split()[0],
                date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                total_s=round(time.perf_counter() - t_start, 1))
    try:
        import jax

        meta.update(jax=jax.__version__, devices=[str(d) for d in jax.devices()])
    except Exception as e:  # noqa: BLE001  (recorded, not fatal: the runs are the measurement)
        meta["jax_error"] = repr(e)
    meta["cache_bytes"] = {k: sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(os.path.join(caches, k))
                                  for f in fs) for k in ("jax", "warp", "runs")}
    if a.caches is None:
        shutil.rmtree(caches, ignore_errors=True)
    md = table(rows)
    with open(os.path.join(out, "first_hour.json"), "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    with open(os.path.join(out, "first_hour.md"), "w") as f:
        f.write(f"First hour ({meta['date']}, size {a.size}, {meta.get('devices', '?')}):\n\n{md}\n")
    print(md)
    return 0 if all(r.get("rc", 0) == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
