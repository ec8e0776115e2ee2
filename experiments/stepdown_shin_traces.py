"""Which shin touches the platform edge, when, and where the feet stand then: per-run traces of step-downs.

    python -m experiments.stepdown_shin_traces --height 0.24 --starts 0.01 0.04 --starts 0.11 0.14 \\
        --instances 8 --crawl shin_remedy=True,terrain_adaptation=0.8 --out docs/results/stepdown_shin_traces

For each ``--starts LO HI`` group it runs ``--instances`` step-downs (start distance of the front feet drawn in
``[LO, HI]`` before the edge, friction 0.9-1.0, payload 0-2 kg, no lateral offset or yaw: the start distance is
the only factor that varies) with the trunk pose recorded every 10 ms, replays each recorded ``qpos`` in C
MuJoCo (``mj_forward``) and reports, per run, the first tick at which each shin capsule touches the platform and
the four feet's x (m past the edge, ``x = 0``) at that tick, plus the front feet's x 8 s into the run. Runs on
C MuJoCo (``impl c``) by default. Writes ``OUT/shin_traces.json``.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

LEGS = ("LF", "RF", "LH", "RH")


def _rounded(x) -> list[float]:
    return [round(float(v), 3) for v in np.ravel(x)]


def first_shin_contacts(m, qpos: np.ndarray, time_s: np.ndarray, feet_x: np.ndarray) -> dict:
    """``{leg: (time, feet x)}`` of the first recorded frame at which each shin touches the platform geom."""
    import mujoco

    d = mujoco.MjData(m)
    shins = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{leg.lower()}_shin"): leg for leg in LEGS}
    platform = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "platform")
    first = {}
    for k in range(qpos.shape[0]):
        d.qpos[:] = qpos[k]
        mujoco.mj_forward(m, d)
        for c in d.contact[: d.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            if platform in pair:
                for g, leg in shins.items():
                    if g in pair and leg not in first:
                        first[leg] = dict(time=round(float(time_s[k]), 2), feet_x=_rounded(feet_x[k]))
        if len(first) == 4:
            break
    return dict(sorted(first.items(), key=lambda kv: kv[1]["time"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.stepdown_shin_traces", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--height", type=float, default=0.24, help="platform height (m)")
    ap.add_argument("--starts", type=float, nargs=2, action="append", metavar=("LO", "HI"),
                    help="a group's start distance range (m, front feet before the edge; repeatable)")
    ap.add_argument("--instances", type=int, default=8, help="runs per group")
    ap.add_argument("--crawl", default="shin_remedy=True,terrain_adaptation=0.8",
                    help="CrawlParams.make settings, field=value,...")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per run")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--impl", default="c", help="simulator: c | jax | warp | auto")
    ap.add_argument("--out", default="out/stepdown_shin_traces")
    args = ap.parse_args(argv)
    starts = args.starts or [[0.01, 0.04], [0.11, 0.14]]
    try:
        import hyqjax
        from hyqjax.sim import backend

        backend.validate_impl(args.impl)
        if not 1 <= args.instances <= 256:
            raise ValueError(f"--instances must be in [1, 256], got {args.instances}")
        for lo, hi in starts:
            if not 0.0 <= lo <= hi <= 1.5:
                raise ValueError(f"--starts must satisfy 0 <= LO <= HI <= 1.5 (m), got {lo} {hi}")
        from hyqjax.crawl.params import parse_settings

        params = hyqjax.CrawlParams.make(**parse_settings(args.crawl, "--crawl"))
        cfg = hyqjax.StepdownConfig(duration=args.duration, impl=args.impl, record_every=5)
    except (ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from hyqjax.io import atomic
    from hyqjax.sim import model as hmodel

    m = hmodel.model_spec(platform_height=args.height).compile()
    groups = []
    for lo, hi in starts:
        sc, table = hyqjax.make_scenarios([args.height], [True], instances=args.instances, seed=args.seed,
                                          start_distance=(lo, hi), friction=(0.9, 1.0), payload=(0.0, 2.0),
                                          lateral=(0.0, 0.0), yaw=(0.0, 0.0), params=params)
        out, res = hyqjax.make_stepdown_rollout(cfg).run(sc)
        tr = {k: np.asarray(res.trace[k]) for k in ("qpos", "time", "feet_world")}
        runs = []
        for i in range(args.instances):
            t8 = int(np.searchsorted(tr["time"][i], 8.0))
            runs.append(dict(start_distance=round(float(table["start_distance"][i]), 3),
                             completed=bool(np.asarray(out.completed)[i]), clean=bool(np.asarray(out.clean)[i]),
                             shin_strike=bool(np.asarray(out.shin_strike)[i]),
                             front_feet_x_at_8s=_rounded(tr["feet_world"][i][t8, :2, 0]),
                             first_shin_contacts=first_shin_contacts(m, tr["qpos"][i], tr["time"][i],
                                                                     tr["feet_world"][i][:, :, 0])))
            print(f"start {runs[-1]['start_distance']:.3f}: clean {runs[-1]['clean']}, front feet x at 8 s "
                  f"{runs[-1]['front_feet_x_at_8s']}, first shin contacts {runs[-1]['first_shin_contacts']}",
                  flush=True)
        groups.append(dict(starts=[lo, hi], runs=runs))
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "shin_traces.json")
    atomic.write_json(path, dict(provenance=atomic.provenance(seed=args.seed), height=args.height, crawl=args.crawl,
                                 impl=args.impl, duration=args.duration, groups=groups))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
