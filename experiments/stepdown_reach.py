"""How deep the crawl's front foot can search without the height reflex: reachable step-down depth against trunk
height and step length, from the kinematics alone.

    python -m experiments.stepdown_reach --out DIR

The crawl's geometry is replayed without dynamics on flat ground (:mod:`hyqjax.crawl.footholds`): HyQ stands in
the SRDF pose lowered or raised to ``body_height``, the body phase moves the centre of mass into the shrunk
support triangle of the first swing leg (RH), RH steps one step length, the next body phase moves it into the
triangle of RF, and RF's foothold is planned one step ahead of its lift-off point (shortened when out of reach).
Without the reflex the trunk holds still while RF searches straight down (the terrain normal of the flat
stance feet) from that foothold; the search ends at the first of: the leg's extension ``max_leg_extension``,
a joint within 0.01 rad of its end stop (the crawl's stance triggers, Section IV). The depth reached there is
the deepest step the crawl can step down without losing the foothold; the binding limit is recorded.

Writes ``DIR/reach.json`` (the grid, the depth and binding limit per point, the foothold relative to the HFE
joint at the nominal setting) and ``DIR/reach.png``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.crawl import footholds
from hyqjax.crawl.params import COM_OFFSET_B, CrawlParams

RF, RH = robot.RF, robot.RH
LIMIT_NAMES = ("leg extension", "HAA end stop", "HFE end stop", "KFE end stop", "none within 0.5 m")


def standing_feet(body_height: float) -> np.ndarray:
    """SRDF standing feet's x, y with the trunk ``body_height`` above them, (4, 3) in the trunk frame."""
    x = np.asarray(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING)), np.float64)
    x[:, 2] = -body_height
    return x


def first_front_foothold(p: CrawlParams, body_height: float, step: float) -> np.ndarray:
    """RF's planned foothold in the trunk frame after the body phases and RH's step of the crawl's start."""
    feet_w = standing_feet(body_height)  # world = trunk frame at the start, trunk at the origin
    trunk = np.zeros(3)
    com_h = jnp.asarray(COM_OFFSET_B)
    up = jnp.array([0.0, 0.0, 1.0])
    for leg in (RH, RF):
        feet_h = jnp.asarray(feet_w - trunk)
        delta = np.asarray(footholds.body_target(feet_h, leg, com_h, p.stability_margin, body_height))
        trunk = trunk + delta
        feet_h = jnp.asarray(feet_w - trunk)
        nominal = jnp.asarray(standing_feet(body_height)[leg])
        target = footholds.swing_foothold(feet_h[leg], nominal, step, 0.0, up)
        target = np.asarray(footholds.reachable_foothold(p.step_height, p.max_leg_extension, leg, feet_h[leg],
                                                         target, up, jnp.zeros(2)))
        if leg == RF:
            return target
        feet_w[leg] = target + trunk
    raise AssertionError("unreachable")


def search_depth(p: CrawlParams, foothold_b: np.ndarray, leg: int = RF, step: float = 5e-4, max_depth: float = 0.5):
    """Depth (m) the foot searches straight down from ``foothold_b`` before a limit, and the limit's index."""
    depths = np.arange(0.0, max_depth, step)
    x = np.broadcast_to(standing_feet(float(-foothold_b[2])), (len(depths), 4, 3)).copy()
    x[:, leg] = foothold_b - depths[:, None] * np.array([0.0, 0.0, 1.0])
    q = np.asarray(kinematics.inverse_kinematics(jnp.asarray(x)))[:, leg]
    ext = np.asarray(kinematics.leg_extension(jnp.asarray(np.tile(q, (1, 4)))))[:, leg]
    lo, hi = robot.Q_MIN_LEG[leg], robot.Q_MAX_LEG[leg]
    stops = (q - lo < 0.01) | (hi - q < 0.01)
    bad = np.c_[ext > float(p.max_leg_extension), stops]
    first = np.argmax(bad.any(1)) if bad.any() else len(depths)
    if first == len(depths):
        return max_depth, 4
    return float(depths[first]), int(np.argmax(bad[first]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/stepdown_reach")
    ap.add_argument("--heights", type=float, nargs=2, default=(0.46, 0.66), metavar=("MIN", "MAX"),
                    help="range of trunk heights above the feet (m)")
    ap.add_argument("--steps", type=float, nargs="+", default=(0.1, 0.15, 0.2, 0.25, 0.3), help="step lengths (m)")
    args = ap.parse_args(argv)
    if not (0.35 <= args.heights[0] < args.heights[1] <= 0.68):
        raise SystemExit(f"--heights must satisfy 0.35 <= MIN < MAX <= 0.68, got {args.heights}")
    if any(not (0.0 <= s <= 0.4) for s in args.steps):
        raise SystemExit(f"--steps must be in [0, 0.4] m, got {args.steps}")
    os.makedirs(args.out, exist_ok=True)
    p = CrawlParams.make()
    heights = np.round(np.arange(args.heights[0], args.heights[1] + 1e-9, 0.005), 4)
    grid = []
    for step in args.steps:
        for h in heights:
            fh = first_front_foothold(p, float(h), float(step))
            d, lim = search_depth(p, fh)
            grid.append(dict(step_length=float(step), body_height=float(h), depth=d, limit=LIMIT_NAMES[lim],
                             foothold_b=fh.tolist(), foothold_from_haa=(fh - robot.B_P_HIP[RF]).tolist()))
    nominal = dict(body_height=float(p.body_height), step_length=float(min(0.1 * 4 * (0.4 + 0.45), 0.3)))
    fh = first_front_foothold(p, nominal["body_height"], nominal["step_length"])
    d, lim = search_depth(p, fh)
    nominal.update(depth=d, limit=LIMIT_NAMES[lim], foothold_from_haa=(fh - robot.B_P_HIP[RF]).tolist())
    need = {}
    for step in args.steps:
        ok = [g["body_height"] for g in grid if g["step_length"] == step and g["depth"] >= 0.16]
        need[str(step)] = dict(max_body_height_for_16cm=max(ok) if ok else None)
    with open(os.path.join(args.out, "reach.json"), "w") as f:
        json.dump(dict(nominal=nominal, reach_16cm=need, grid=grid, max_leg_extension=float(p.max_leg_extension),
                       stability_margin=float(p.stability_margin)), f, indent=1)
    _plot(grid, nominal, args.steps, os.path.join(args.out, "reach.png"))
    print(f"nominal crawl (trunk {nominal['body_height']:.2f} m above the feet, step {nominal['step_length']:.2f} m): "
          f"RF foothold {np.round(nominal['foothold_from_haa'], 3)} m from its HAA joint, reaches "
          f"{100 * nominal['depth']:.1f} cm down before the {nominal['limit']}")
    for step, v in need.items():
        print(f"step {float(step):.2f} m: 16 cm reachable up to a trunk height of {v['max_body_height_for_16cm']}")
    return 0


def _plot(grid, nominal, steps, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    for step in steps:
        g = [x for x in grid if x["step_length"] == step]
        ax.plot([x["body_height"] for x in g], [100 * x["depth"] for x in g], label=f"step {100 * step:.0f} cm")
    for h in (16, 21, 24):
        ax.axhline(h, color="gray", lw=0.8, ls="--")
        ax.text(0.465, h + 0.3, f"{h} cm", color="gray", fontsize=8)
    ax.plot(nominal["body_height"], 100 * nominal["depth"], "ko", label="the crawl's default")
    ax.axvline(robot.STANDING_HEIGHT, color="k", lw=0.8, ls=":", label="SRDF standing height")
    ax.set(xlabel="trunk height above the feet [m]", ylabel="reachable step-down depth [cm]",
           title="Front foot's search without the reflex: depth before a limit")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
