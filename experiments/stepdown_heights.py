"""Step-down success against platform height, reflex on and off: the largest height each setting steps down.

    python -m experiments.stepdown_heights --instances 200 --out DIR          # simulate, then plot
    python -m experiments.stepdown_heights --from DIR1 [DIR2 ...] --out DIR   # plot existing results

Simulating runs ``hyqjax stepdown`` over ``--heights`` (default 4-34 cm) with ``--instances`` randomised
instances per cell (a GPU does the default 200 per cell, 4,400 instances, in about two minutes; on a CPU
use a few). ``--from`` merges the ``results.json`` of earlier ``hyqjax stepdown`` runs. Writes
``DIR/heights.png`` (success rate with 95% Wilson intervals and the rate of runs that lost a foothold,
against height) and ``DIR/heights.json``: per height and setting the counts, rates, intervals and the
failure reasons, plus the largest height whose success rate is at least 50% / whose Wilson lower bound is
at least 95%, and the largest height with no lost foothold.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys

import numpy as np

DEFAULT_HEIGHTS = (0.04, 0.08, 0.12, 0.14, 0.16, 0.18, 0.21, 0.24, 0.26, 0.28, 0.30, 0.32, 0.34)


def load_instances(dirs):
    rows = []
    for d in dirs:
        with open(os.path.join(d, "results.json")) as f:
            rows += json.load(f)["instances"]
    return rows


def summarise(rows):
    """Per height and reflex setting: counts, success rate and Wilson interval (``statistics.success_curve``),
    the lost-foothold rate and the failure reasons; sorted by (height, reflex)."""
    from hyqjax.studies.statistics import success_curve
    from hyqjax.studies.stepdown import failure_labels

    heights = np.asarray([round(float(r["height"]), 4) for r in rows])
    reflex = np.asarray([bool(r["reflex"]) for r in rows])
    success = np.asarray([bool(r["success"]) for r in rows])
    lost = np.asarray([int(r["lost_footholds"]) > 0 for r in rows])
    table = []
    for mode in sorted(set(reflex.tolist())):
        m = reflex == mode
        for c in success_curve(heights[m], success[m]):
            cell = m & (heights == c["height"])
            reasons = collections.Counter(" + ".join(failure_labels(r)) for r, failed in zip(rows, cell & ~success)
                                          if failed)
            table.append(dict(height=c["height"], reflex=mode, n=c["n"], successes=c["successes"],
                              success_rate=c["rate"], success_ci95=c["ci95"],
                              lost_foothold_rate=int(lost[cell].sum()) / c["n"],
                              failure_reasons=dict(reasons.most_common())))
    table.sort(key=lambda t: (t["height"], t["reflex"]))
    limits = {}
    for reflex in (False, True):
        cell = [t for t in table if t["reflex"] == reflex]
        limits["reflex_on" if reflex else "reflex_off"] = dict(
            largest_height_success_50=max([t["height"] for t in cell if t["success_rate"] >= 0.5], default=None),
            largest_height_success_95_lower_bound=max(
                [t["height"] for t in cell if t["success_ci95"][0] >= 0.95], default=None),
            largest_height_no_lost_foothold=max(
                [t["height"] for t in cell if t["lost_foothold_rate"] == 0.0], default=None),
        )
    return table, limits


def plot(table, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 3.8))
    for reflex, color in ((False, "tab:gray"), (True, "tab:blue")):
        cell = [t for t in table if t["reflex"] == reflex]
        h = np.array([t["height"] for t in cell]) * 100
        p = np.array([t["success_rate"] for t in cell])
        lo = p - np.array([t["success_ci95"][0] for t in cell])
        hi = np.array([t["success_ci95"][1] for t in cell]) - p
        label = f"reflex {'on' if reflex else 'off'}"
        a.errorbar(h, p, yerr=[lo, hi], marker="o", capsize=3, color=color, label=label)
        b.plot(h, [t["lost_foothold_rate"] for t in cell], marker="o", color=color, label=label)
    n = min(t["n"] for t in table)
    a.set(xlabel="platform height [cm]", ylabel="success rate", ylim=(-0.02, 1.02),
          title=f"Step-down success (95% Wilson intervals, >= {n} instances per point)")
    b.set(xlabel="platform height [cm]", ylabel="fraction of runs", ylim=(-0.02, 1.02),
          title="Runs that lost a foothold (swing stopped at a limit in the air)")
    for ax in (a, b):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/stepdown_heights")
    ap.add_argument("--from", dest="sources", nargs="+", help="existing hyqjax stepdown output directories")
    ap.add_argument("--heights", type=float, nargs="+", default=list(DEFAULT_HEIGHTS))
    ap.add_argument("--instances", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    sources = args.sources
    if not sources:
        run_dir = os.path.join(args.out, "run")
        cmd = [sys.executable, "-m", "hyqjax.cli.app", "stepdown", "--heights", *map(str, args.heights),
               "--instances", str(args.instances), "--seed", str(args.seed), "--no-figures", "--out", run_dir]
        print(" ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)
        sources = [run_dir]
    table, limits = summarise(load_instances(sources))
    plot(table, os.path.join(args.out, "heights.png"))
    with open(os.path.join(args.out, "heights.json"), "w") as f:
        json.dump(dict(sources=sources, table=table, limits=limits), f, indent=1)
    for t in table:
        lo, hi = t["success_ci95"]
        print(f"{t['height'] * 100:5.1f} cm  reflex {'on ' if t['reflex'] else 'off'}  {t['successes']:5d}/{t['n']:<5d}"
              f" {t['success_rate']:5.0%} [{lo:.2f}, {hi:.2f}]  lost foothold {t['lost_foothold_rate']:5.0%}")
    print(json.dumps(limits, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
