"""Process wall against printed wall of `hyqjax bound`, two code trees side by side.

Runs ``python -m hyqjax.cli bound --instances N --duration D --out DIR`` with ``PYTHONPATH`` set to each tree in
turn (alternating, ``--pairs`` times: a drift of the machine's load hits both alike), each in a fresh process, and
reports per run: the process wall (from before the process is started to its exit), the wall the command printed
(``wall X s in all``, its last one) and the size of the ``traces.npz`` it wrote. The persistent compilation cache
is shared and warmed by one run of each tree first (not reported), so every reported run loads its programs.

    python benchmarks/bench_bound_wall.py --trees /path/to/old /path/to/new --instances 256 --duration 4 \\
        --out out/bench_bound_wall

Writes OUT/bench_bound_wall.json and prints a Markdown table.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time


def run_once(tree: str, args, out: str) -> dict:
    env = {**os.environ, "PYTHONPATH": tree}
    cmd = [sys.executable, "-m", "hyqjax.cli", "bound", "--instances", str(args.instances), "--duration",
           str(args.duration), "--out", out]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tree)
    wall = time.perf_counter() - t0
    printed = [float(x) for x in re.findall(r"wall ([0-9.]+) s in all", r.stdout)]
    traces = os.path.join(out, "traces.npz")
    return dict(tree=tree, rc=r.returncode, process_wall_s=round(wall, 2),
                printed_wall_s=printed[-1] if printed else None,
                ratio=round(wall / printed[-1], 3) if printed else None,
                traces_bytes=os.path.getsize(traces) if os.path.exists(traces) else 0,
                stderr_tail=r.stderr[-400:] if r.returncode else "")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trees", nargs=2, required=True, metavar=("OLD", "NEW"), help="two hyqjax checkouts")
    p.add_argument("--instances", type=int, default=256)
    p.add_argument("--duration", type=float, default=4.0)
    p.add_argument("--pairs", type=int, default=2)
    p.add_argument("--out", default="out/bench_bound_wall")
    p.add_argument("--no-warm-up", action="store_true", help="skip the unreported first run of each tree (the "
                                                              "compilation cache is warm already)")
    a = p.parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    trees = [os.path.abspath(t) for t in a.trees]
    for k, tree in enumerate([] if a.no_warm_up else trees):  # warm the compilation cache (not reported)
        run_once(tree, a, os.path.join(os.path.abspath(a.out), f"warm{k}"))
    rows = []
    for i in range(a.pairs):
        for k, tree in enumerate(trees):
            row = run_once(tree, a, os.path.join(os.path.abspath(a.out), f"pair{i}_tree{k}"))
            row.update(pair=i, which=("old", "new")[k])
            rows.append(row)
            print(json.dumps(row), flush=True)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    with open(os.path.join(a.out, "bench_bound_wall.json"), "w") as f:
        json.dump(dict(instances=a.instances, duration=a.duration, rows=rows, loadavg_at_end=load), f, indent=1)
    print("\n| pair | code | process wall (s) | printed wall (s) | process / printed | traces.npz (bytes) |")
    print("|---:|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['pair']} | {r['which']} | {r['process_wall_s']:.1f} | {r['printed_wall_s']} | {r['ratio']} | "
              f"{r['traces_bytes']:,} |")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
