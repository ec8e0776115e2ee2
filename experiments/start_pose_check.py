"""The held-out instances whose start once put a front foot over the edge, run again with today's start pose.

    python -m experiments.start_pose_check --out out/start_pose_check                   # C MuJoCo, ~4 min on 2 cores
    python -m experiments.start_pose_check --impl warp --instances 512 --out DIR      # every such instance, one GPU

Until the ``leading-foot`` start pose (:data:`hyqjax.studies.stepdown.START_POSE`), :func:`start_qpos` placed the
front hips ``start_distance`` before the edge and then turned the trunk by its heading about its centre, which moved
one front foot forward by :func:`hyqjax.studies.stepdown.leading_foot_advance` (up to 3.0 cm at 0.1 rad). This script
draws the tuner's held-out map (:data:`hyqjax.studies.tune.study.targets.HELDOUT`: the wide spread, seed 60613, the
first ``--instances`` draws), finds the draws whose leading front foot centre was then past the edge (x > 0, from
MuJoCo's kinematics of the old pose), and runs them with the old start and with today's pose for every ``--presets``
set at ``--heights``: per pose, set and height, the number of such draws and how many run clean, complete and strike
a shin. Written to ``DIR/check.json``.
"""
from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from hyqjax.cli.common import HelpFormatter, UsageError


def parse(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m experiments.start_pose_check", description=__doc__,
                                 formatter_class=HelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--impl", default="c", help="simulator: auto | jax | warp | c")
    ap.add_argument("--presets", nargs="+", default=["reach", "tuned_per_leg_reach"], help="crawl presets")
    ap.add_argument("--heights", nargs="+", type=float, default=[0.14, 0.19, 0.23], help="platform heights (m)")
    ap.add_argument("--instances", type=int, default=512, help="draws of the held-out map searched (at most 512)")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per run")
    a = ap.parse_args(argv)
    from hyqjax import presets
    from hyqjax.studies.tune.study import targets

    if a.impl not in ("auto", "jax", "warp", "c"):
        raise UsageError(f"--impl must be auto, jax, warp or c, got {a.impl!r}")
    if not 1 <= a.instances <= targets.HELDOUT["instances"]:
        raise UsageError(f"--instances must be in [1, {targets.HELDOUT['instances']}], got {a.instances}")
    if any(not 0.0 < h <= 0.4 for h in a.heights):
        raise UsageError(f"--heights must be in (0, 0.4] m, got {a.heights}")
    if not 2.0 <= a.duration <= 60.0:
        raise UsageError(f"--duration must be in [2, 60] s, got {a.duration}")
    for p in a.presets:
        presets.check_kind(p, "crawl", "--presets")  # PresetError: a ValueError of one line
    return a


def hip_line_front_feet_x(m, rows) -> np.ndarray:
    """x of the leading front foot centre (edge at 0) of every row under the hip-line start (trunk not moved back
    for the heading), from MuJoCo's kinematics."""
    import mujoco

    from hyqjax.sim import model as hmodel
    from hyqjax.studies import stepdown

    sd = rows["start_distance"] - stepdown.leading_foot_advance(rows["yaw"])  # today's pose of this is the old one
    q0 = stepdown.start_qpos(hmodel.standing_qpos(m), sd, rows["lateral_offset"], rows["yaw"], rows["height"])
    d = mujoco.MjData(m)
    sites = np.asarray(hmodel.model_ids(m).foot_sites)[:2]
    x = np.empty(len(q0))
    for i, q in enumerate(q0):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        x[i] = d.site_xpos[sites, 0].max()
    return x


def main(argv=None) -> int:
    from hyqjax.io import phases

    clock = phases.Clock.from_process_start()
    try:
        a = parse(argv)
    except (UsageError, ValueError) as e:
        print(f"start_pose_check: {e}", file=sys.stderr)
        return 2
    import jax

    from experiments import reach_map
    from hyqjax import presets
    from hyqjax.crawl import scheduled
    from hyqjax.io import atomic
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so
    from hyqjax.studies.tune.study import targets

    draws = reach_map.draws(targets.HELDOUT["spread"], [a.heights[0]], targets.HELDOUT["instances"],
                            targets.HELDOUT["seed"])
    draws = {k: np.asarray(v)[: a.instances] for k, v in draws.items()}
    cfg = stepdown.StepdownConfig(duration=a.duration, impl=a.impl)
    x_old = hip_line_front_feet_x(stepdown.setup(cfg).m, draws)
    over = np.flatnonzero(x_old > 0)
    print(f"{len(over)} of {a.instances} held-out draws had a front foot centre past the edge at the start "
          f"(up to {100 * x_old.max():.1f} cm); running them with that start and with the {stepdown.START_POSE!r} pose", flush=True)
    reps = 2 * len(a.heights) * len(a.presets)
    n = len(over)
    rows = {k: np.concatenate([v[over]] * reps) for k, v in draws.items()}
    rows["pose"] = np.repeat(np.asarray([stepdown.EARLIER_START_POSE, stepdown.START_POSE]), n * len(a.heights) * len(a.presets))
    rows["variant"] = np.tile(np.repeat(np.asarray(a.presets), n * len(a.heights)), 2)
    rows["height"] = np.tile(np.repeat(np.asarray(a.heights, float), n), 2 * len(a.presets))
    old = rows["pose"] == stepdown.EARLIER_START_POSE  # today's pose of a start distance less the advance is the hip-line start
    rows["start_distance"] = np.where(old, rows["start_distance"] - stepdown.leading_foot_advance(rows["yaw"]),
                                      rows["start_distance"])
    params = scheduled.common_structure({p: presets.load(p) for p in a.presets})
    clock.lap("startup")
    out, _ = stepdown.make_stepdown_rollout(cfg).run(reach_map.scenario_of(rows, np.arange(len(rows["height"])),
                                                                          params))
    cols = so.to_columns(jax.block_until_ready(out))
    clock.lap("simulation")  # the C batch's compile included
    cells = []
    for pose in (stepdown.EARLIER_START_POSE, stepdown.START_POSE):
        for p in a.presets:
            for h in a.heights:
                k = (rows["pose"] == pose) & (rows["variant"] == p) & np.isclose(rows["height"], h)
                c = dict(pose=pose, preset=p, height=h, n=int(k.sum()), clean=int(cols["clean"][k].sum()),
                         completed=int(cols["completed"][k].sum()), shin_strike=int(cols["shin_strike"][k].sum()),
                         diverged=int(cols["diverged"][k].sum()))
                cells.append(c)
                print(f"  {pose:12s} {p:22s} {h:.2f} m: clean {c['clean']}/{c['n']}, completed {c['completed']}, "
                      f"shin strike {c['shin_strike']}, diverged {c['diverged']}")
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, "check.json")
    atomic.write_json(path, dict(provenance=atomic.provenance(seed=targets.HELDOUT["seed"]), impl=a.impl,
                                 start_pose=stepdown.START_POSE, heldout=dict(targets.HELDOUT),
                                 instances_searched=a.instances, over_the_edge=over.tolist(),
                                 hip_line_front_foot_x=x_old[over].tolist(), duration=a.duration, cells=cells,
                                 wall_s=clock.wall(), phases=clock.to_dict()))
    clock.lap("summary")
    print(f"wrote {path}")
    print(clock.line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
