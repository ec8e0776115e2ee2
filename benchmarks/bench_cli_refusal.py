"""How fast the command line refuses bad input: wall time of a usage error against ``python -c pass``, in one run.

Usage: ``PYTHONPATH=. python benchmarks/bench_cli_refusal.py [--repeats 7] [--out refusal.json]``.

For each case (a bad option of every command, a parser error, a bad sweep spec value, an unknown tuned group)
the command ``python -m hyqjax.cli ARGS`` is started ``--repeats`` times, interleaved with ``python -c pass``
(the interpreter's own start on this machine, under the same load), and the median wall times are reported
with their ratio (and, as a reference, ``python -c "import jax"``). Each case also runs once in a harness that prints which heavy modules were imported by the
time the refusal came (``jax``, ``mujoco.mjx``, ``pyarrow``, ``matplotlib``). Exit status 2 and one line on
stderr are checked for every case. Markdown table on stdout, JSON with ``--out``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

CASES = [
    ("parser: unknown option", ["sweep", "--sed", "1"]),
    ("parser: bad int", ["tune", "--seed", "x"]),
    ("sweep --chunk-size 0", ["sweep", "--chunk-size", "0"]),
    ("sweep spec value out of range", ["sweep", "--grid", "height=0.6"]),
    ("sweep spec unknown axis", ["sweep", "--grid", "heigth=0.2"]),
    ("tune --popsize 1", ["tune", "--popsize", "1"]),
    ("tune --groups k_base,spring", ["tune", "--groups", "k_base,spring"]),
    ("stepdown --heights 0.9", ["stepdown", "--heights", "0.9"]),
    ("bound --speed 9", ["bound", "--speed", "9"]),
    ("report DIR missing", ["report", "nowhere"]),
    ("render SOURCE missing", ["render", "nowhere"]),
    ("verify DIR missing", ["verify", "nowhere"]),
]
HEAVY = ("jax", "mujoco", "mujoco.mjx", "pyarrow", "matplotlib")
HARNESS = ("import sys\nfrom hyqjax.cli.app import main\ntry:\n    code = main(sys.argv[1:])\n"
           "except SystemExit as e:\n    code = e.code\n"
           "print('MODULES', [m for m in {heavy!r} if m in sys.modules], code)")


def timed(cmd, env, cwd) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    p = subprocess.run(cmd, env=env, cwd=cwd, capture_output=True, text=True)
    return time.perf_counter() - t, p


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cwd = tempfile.mkdtemp(prefix="hyqjax-refusal-")
    rows = []
    for name, case in CASES:
        t_cmd, t_pass = [], []
        for _ in range(args.repeats):
            t, _ = timed([sys.executable, "-c", "pass"], env, cwd)
            t_pass.append(t)
            t, p = timed([sys.executable, "-m", "hyqjax.cli", *case], env, cwd)
            t_cmd.append(t)
            err = [ln for ln in p.stderr.splitlines() if ln.strip()]
            if p.returncode != 2 or len(err) != 1:
                raise SystemExit(f"{case}: exit {p.returncode}, stderr {p.stderr!r}")
        h = subprocess.run([sys.executable, "-c", HARNESS.format(heavy=HEAVY), *case], env=env, cwd=cwd,
                           capture_output=True, text=True)
        mods = h.stdout.split("MODULES", 1)[1].strip().rsplit(" ", 1)[0] if "MODULES" in h.stdout else "?"
        rows.append(dict(case=name, argv=case, median_s=statistics.median(t_cmd), max_s=max(t_cmd),
                         python_pass_s=statistics.median(t_pass), ratio=statistics.median(t_cmd) /
                         statistics.median(t_pass), imported=mods, message=err[0]))
    t_jax, t_pass = [], []
    for _ in range(args.repeats):  # the reference: what importing JAX alone costs here, now
        t_pass.append(timed([sys.executable, "-c", "pass"], env, cwd)[0])
        t_jax.append(timed([sys.executable, "-c", "import jax"], env, cwd)[0])
    rows.append(dict(case="reference: python -c 'import jax'", argv=None, median_s=statistics.median(t_jax),
                     max_s=max(t_jax), python_pass_s=statistics.median(t_pass),
                     ratio=statistics.median(t_jax) / statistics.median(t_pass), imported="['jax']", message=""))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    print(f"usage errors, median of {args.repeats} (python -c pass interleaved), {os.cpu_count()} cores, "
          f"load {load}")
    print("| case | refusal [s] | max [s] | `python -c pass` [s] | ratio | heavy modules imported |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['median_s']:.2f} | {r['max_s']:.2f} | {r['python_pass_s']:.3f} | "
              f"{r['ratio']:.0f} | {r['imported']} |")
    if args.out:
        res = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                   python=platform.python_version(), cores=os.cpu_count(), load=load, repeats=args.repeats, cases=rows)
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
