"""Paired step-down runs under two simulators: the same instances under ``impl="jax"`` and ``"warp"`` (default), or
any two of ``jax``, ``warp``, ``c`` (``--impls``; e.g. ``--impls c jax`` compares C MuJoCo with MJX-JAX on a CPU).

Measures, on one batch of ``heights x reflex off/on x --instances`` randomised step-down instances
(``stepdown.make_scenarios``, one seed for both implementations):

  outcomes     per-instance agreement of ``completed``, ``clean`` and every boolean failure reason;
               per (height, reflex) cell the ``completed`` and ``clean`` counts and 95% Wilson intervals under each
               implementation, and whether each rate lies inside the other's interval; the disagreeing
               instances with their reasons under each implementation and their start distance from the edge.
  trajectory   a second run of ``--traj-duration`` s with traces every ``--record-every`` ticks: per-instance
               maximum difference of the trunk position (m) and joint angles (rad) between the two
               implementations, and the first time the trunk positions differ by more than 1 mm / 1 cm.
  wall time    of each implementation's full batch, compile included (``stepdown.run_batch``).

Usage (GPU; >= 2,000 instances: 3 heights x 2 x 340)::

    python benchmarks/paired_stepdown.py --instances 340 --out $OUT/paired.json
    # C MuJoCo against MJX-JAX on a CPU (64 instances per cell; the MJX side takes most of the time)
    PYTHONPATH=. python benchmarks/paired_stepdown.py --impls c jax --instances 64 --out out/paired_c_jax.json
    PYTHONPATH=. python benchmarks/paired_stepdown.py --instances 2 --duration 2 --traj-duration 0.2 --out out/p.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import numpy as np  # noqa: E402

from hyqjax.io import atomic as hio  # noqa: E402
from hyqjax.studies import statistics, stepdown  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_physics import host_info  # noqa: E402

IMPLS = ("jax", "warp")


def run(scen, cfg) -> tuple[dict, object, float]:
    t = time.perf_counter()
    cols, trace = stepdown.run_batch(scen, cfg)
    return cols, trace, time.perf_counter() - t


def compare_outcomes(table: dict, cols: dict[str, dict], impls=IMPLS) -> dict:
    a, b = cols[impls[0]], cols[impls[1]]
    keys = ["completed", "clean", *stepdown.FAILURE_REASONS]
    agree = {k: float(np.mean(np.asarray(a[k]) == np.asarray(b[k]))) for k in keys if k in a and k in b}
    cells = []
    for h in sorted(set(np.asarray(table["height"]).tolist())):
        for r in (False, True):
            sel = (np.asarray(table["height"]) == h) & (np.asarray(table["reflex"]) == r)
            n = int(sel.sum())
            row = dict(height=h, reflex=r, n=n)
            for impl in impls:  # clean (the success of older results) and completed
                k = int(np.sum(np.asarray(cols[impl]["clean"])[sel]))
                row[impl] = dict(k=k, rate=k / n if n else float("nan"), ci=statistics.wilson_interval(k, n))
                kc = int(np.sum(np.asarray(cols[impl]["completed"])[sel]))
                row[impl]["completed"] = dict(k=kc, rate=kc / n if n else float("nan"),
                                              ci=statistics.wilson_interval(kc, n))
            ja, wa = row[impls[0]], row[impls[1]]
            row[f"{impls[1]}_rate_in_{impls[0]}_ci"] = bool(ja["ci"][0] <= wa["rate"] <= ja["ci"][1])
            row[f"{impls[0]}_rate_in_{impls[1]}_ci"] = bool(wa["ci"][0] <= ja["rate"] <= wa["ci"][1])
            jc, wc = ja["completed"], wa["completed"]
            row["completed_in_each_others_ci"] = bool(jc["ci"][0] <= wc["rate"] <= jc["ci"][1]
                                                      and wc["ci"][0] <= jc["rate"] <= wc["ci"][1])
            row["clean_in_each_others_ci"] = (row[f"{impls[1]}_rate_in_{impls[0]}_ci"]
                                              and row[f"{impls[0]}_rate_in_{impls[1]}_ci"])
            row["clean_agreement"] = float(np.mean(np.asarray(a["clean"])[sel] == np.asarray(b["clean"])[sel]))
            cells.append(row)
    dis = np.nonzero(np.asarray(a["clean"]) != np.asarray(b["clean"]))[0]
    reasons = lambda c, i: [k for k in stepdown.FAILURE_REASONS if bool(np.asarray(c[k])[i])]  # noqa: E731
    disagreements = [dict(index=int(i), height=float(table["height"][i]), reflex=bool(table["reflex"][i]),
                          start_distance=float(table["start_distance"][i]), first=reasons(a, i), second=reasons(b, i))
                     for i in dis]
    by_reason = {}
    for d in disagreements:
        for k in set(d["first"]) ^ set(d["second"]):
            by_reason[k] = by_reason.get(k, 0) + 1
    sd = np.asarray(table["start_distance"])
    return dict(n=int(len(a["clean"])), agreement=agree, cells=cells, n_disagree=int(len(dis)),
                disagreement_reasons=by_reason,
                start_distance_disagree=dict(mean=float(sd[dis].mean()) if len(dis) else None,
                                             all_mean=float(sd.mean())),
                disagreements=disagreements[:200])


def compare_traces(traces: dict, impls=IMPLS) -> dict:
    a, b = traces[impls[0]], traces[impls[1]]
    pa, pb = np.asarray(a["base_pos"]), np.asarray(b["base_pos"])
    qa, qb = np.asarray(a["q"]), np.asarray(b["q"])
    t = np.asarray(a["time"])  # (B, T)
    dp = np.linalg.norm(pa - pb, axis=-1)  # (B, T)
    dq = np.max(np.abs(qa - qb), axis=-1)

    def first_over(x, thr):
        hit = x > thr
        idx = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)
        return np.where(idx >= 0, t[np.arange(len(idx)), np.maximum(idx, 0)], np.nan)

    pct = lambda x: {p: float(np.nanpercentile(x, p)) for p in (50, 90, 99, 100)}  # noqa: E731
    return dict(samples=int(t.shape[1]), horizon_s=float(t[0, -1]), max_trunk_pos_diff_m=pct(dp.max(axis=1)),
                max_joint_diff_rad=pct(dq.max(axis=1)),
                share_within_1mm=float(np.mean(dp.max(axis=1) <= 1e-3)),
                first_time_over_1mm_s=pct(first_over(dp, 1e-3)), first_time_over_1cm_s=pct(first_over(dp, 1e-2)),
                share_ever_over_1cm=float(np.mean((dp > 1e-2).any(axis=1))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heights", type=float, nargs="+", default=[0.16, 0.21, 0.24])
    ap.add_argument("--instances", type=int, default=340, help="instances per (height, reflex) cell")
    ap.add_argument("--duration", type=float, default=24.0)
    ap.add_argument("--traj-duration", type=float, default=1.0)
    ap.add_argument("--record-every", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--impls", nargs=2, choices=["jax", "warp", "c"], default=list(IMPLS),
                    help="the two simulators compared (default: jax warp)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    impls = tuple(args.impls)
    if impls[0] == impls[1]:
        raise SystemExit("--impls must name two different simulators")
    if args.instances < 1:
        raise SystemExit("--instances must be >= 1")
    info = host_info()
    scen, table = stepdown.make_scenarios(args.heights, [False, True], args.instances, args.seed)
    res = dict(info=info, args=vars(args), provenance=hio.provenance(argv if argv is not None else sys.argv[1:]))
    print(json.dumps({k: info[k] for k in ("date", "device", "jax", "mujoco", "mujoco_mjx")}), flush=True)
    cols, traces, wall = {}, {}, {}
    for impl in impls:
        cfg = stepdown.StepdownConfig(duration=args.duration, impl=impl)
        cols[impl], _, wall[impl] = run(scen, cfg)
        print(f"{impl}: {len(cols[impl]['clean'])} instances x {args.duration} s in {wall[impl]:.1f} s "
              f"(compile included), clean {np.mean(cols[impl]['clean']):.3f}", flush=True)
    res["wall_s"] = wall
    res["outcomes"] = compare_outcomes(table, cols, impls)
    if args.out:
        hio.write_json(args.out, res)
    for impl in impls:
        cfg = stepdown.StepdownConfig(duration=args.traj_duration, record_every=args.record_every, impl=impl)
        _, traces[impl], _ = run(scen, cfg)
    res["trajectory"] = compare_traces(traces, impls)
    if args.out:
        hio.write_json(args.out, res)
    o, tr = res["outcomes"], res["trajectory"]
    print(f"agreement: {json.dumps({k: round(v, 4) for k, v in o['agreement'].items()})}")
    print(f"clean disagreements: {o['n_disagree']} of {o['n']} ({o['disagreement_reasons']})")
    a, b = impls
    for c in o["cells"]:
        print(f"  h={c['height']:.2f} reflex={'on ' if c['reflex'] else 'off'} n={c['n']}: completed {a} "
              f"{c[a]['completed']['k']} {np.round(c[a]['completed']['ci'], 3)} {b} {c[b]['completed']['k']} "
              f"{np.round(c[b]['completed']['ci'], 3)} (in each other's CI: {c['completed_in_each_others_ci']}); "
              f"clean {a} {c[a]['k']} {np.round(c[a]['ci'], 3)} {b} {c[b]['k']} {np.round(c[b]['ci'], 3)} "
              f"(in each other's CI: {c['clean_in_each_others_ci']})")
    print(f"trajectory over {tr['horizon_s']:.2f} s: max trunk position diff {tr['max_trunk_pos_diff_m']}, "
          f"within 1e-3 m: {tr['share_within_1mm']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
