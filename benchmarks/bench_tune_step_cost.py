"""Cost of one tuning step of the gradient against one forward evaluation of the same windows (MJX-JAX).

Usage: ``PYTHONPATH=. python benchmarks/bench_tune_step_cost.py [--dims shared,per_leg_cond] [--directions 2]
[--train-per-height 2] [--windows-per-scenario 2] [--window-ticks 500] [--reps 3] [--out step_cost.json]``.

Builds the equal-wall-clock study's gradient programs (:class:`hyqjax.studies.tune.gradient_programs.GradientPrograms`:
snapshot windows at the start point, the exact ``jacfwd`` step with ``P`` tangents, the exact reverse-mode step
with and without the checkpointed scan (:func:`hyqjax.studies.tune.objective.make_value_and_grad_reverse`; without
it, where it does not fit in memory, the reason), the forward-gradient step with ``K = --directions`` tangents, the
forward window value) and reports, after every compile, the median wall time of one step and of one forward
evaluation of the same windows for one candidate, and their ratios (the target: a step at <= 5 forward windows),
and each program's first call (compile and one run). The study stores the same numbers under ``diagnostics/<dim>/step_cost``
of its ``results.json``. Markdown on stdout, JSON with ``--out``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dims", default="shared", help="parameterisations, comma-separated")
    p.add_argument("--directions", type=int, default=2, help="tangents of the forward-gradient step (K >= 1)")
    p.add_argument("--train-per-height", type=int, default=2)
    p.add_argument("--windows-per-scenario", type=int, default=2)
    p.add_argument("--window-ticks", type=int, default=500)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--out", default="")
    a = p.parse_args(argv)
    if a.directions < 1 or a.reps < 1:
        p.error("--directions and --reps must be >= 1")
    import jax

    from hyqjax.studies.tune import gradient_programs, schedule, search, wallclock

    dims = tuple(x for x in a.dims.split(",") if x)
    cfg = wallclock.WallClockConfig(methods=("gradient",), dims=dims, grad_train_per_height=a.train_per_height,
                                    windows_per_scenario=a.windows_per_scenario, window_ticks=a.window_ticks,
                                    grad_directions=a.directions)
    t0 = time.perf_counter()
    grad = gradient_programs.GradientPrograms(cfg, wallclock.start_params(cfg), search.Charges(), print)
    rows = {}
    for d in dims:
        rows[d] = grad.step_cost(schedule.make(d, cfg.groups), reps=a.reps)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    out = dict(date=datetime.date.today().isoformat(), device=str(jax.devices()[0].device_kind),
               jax=jax.__version__, python=platform.python_version(), cpu=platform.processor() or platform.machine(),
               cpu_count=os.cpu_count(), loadavg=load, wall_s=time.perf_counter() - t0, settings=vars(a),
               step_cost=rows)
    num = lambda x, f=".3f": "-" if x is None else format(x, f)  # noqa: E731
    print("| dim | P | windows x ticks | forward window (s) | jacfwd (s) | ratio | reverse (s) | ratio | "
          "reverse, no checkpoint (s) | ratio | forward gradient K (s) | ratio |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for d, r in rows.items():
        print(f"| {d} | {r['tangents']} | {r['windows']} x {r['ticks']} | {r['window_value_s']:.3f} | "
              f"{r['jacfwd_s']:.3f} | {r['jacfwd_over_value']:.1f} | {r['reverse_s']:.3f} | "
              f"{r['reverse_over_value']:.1f} | {num(r['reverse_nocheckpoint_s'])} | "
              f"{num(r['reverse_nocheckpoint_over_value'], '.1f')} | {r['forward_gradient_directions']}: "
              f"{r['forward_gradient_s']:.3f} | {r['forward_gradient_over_value']:.1f} |")
    print()
    progs = ("window_value", "jacfwd", "reverse", "reverse_nocheckpoint", "forward_gradient")
    print("| dim | first call (s): " + ", ".join(progs) + " | reverse vs jacfwd rows (max rel. difference) |")
    print("|---|---|---:|")
    for d, r in rows.items():
        print(f"| {d} | " + ", ".join(num(r["first_call_s"].get(k), ".1f") for k in progs)
              + f" | {num(r['reverse_vs_jacfwd_rel_diff'], '.1e')} |")
        if r.get("reverse_nocheckpoint_error"):
            print(f"\n{d}: reverse without checkpoint: {r['reverse_nocheckpoint_error']}")
    print(f"\nload average {load}, {os.cpu_count()} CPUs, jax {jax.__version__}, {out['device']}, "
          f"{out['wall_s']:.0f} s in all")
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
