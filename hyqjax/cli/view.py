"""Play a recorded instance in MuJoCo's interactive viewer (needs a display).

SOURCE and the instance choice are those of ``hyqjax render`` (--instance, --worst, --where). The
recorded trajectory is replayed kinematically at --speed times real time, looping until the window
is closed, with the platform at the instance's height and the foot ground reaction forces drawn as
red bars. Without a display (neither DISPLAY nor WAYLAND_DISPLAY set on Linux) the command stops
with a message and exit status 3: use ``hyqjax render`` to write a video instead.

Example:
  hyqjax view out/stepdown --where height=0.24 reflex=on
"""
from __future__ import annotations

import argparse
import os
import sys
import time

NAME = "view"
HELP = "play a recorded instance in MuJoCo's interactive viewer (needs a display)"
ORDER = 65

NO_DISPLAY_EXIT = 3


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter

    use_help_formatter(p)
    p.add_argument("source", help="experiment output directory with traces.npz, or a traces .npz file")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--instance", type=int, default=None, metavar="K", help="row K of results.json's instances")
    sel.add_argument("--worst", action="store_true", help="the first failed instance (needs results.json)")
    sel.add_argument("--where", nargs="+", default=None, metavar="KEY=VALUE",
                     help="the first recorded instance whose inputs match (see `hyqjax render --help`)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (1: real time), in (0, 100]")
    p.add_argument("--once", action="store_true", help="play once and keep the last frame instead of looping")
    p.add_argument("--force-scale", type=float, default=0.0006, help="foot force bar length per newton (m/N)")


def display_available() -> bool:
    """Whether a window can be opened: always on macOS and Windows, with DISPLAY or WAYLAND_DISPLAY on Linux."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _check(args) -> None:
    if not (0 < args.speed <= 100):
        raise ValueError(f"--speed must be in (0, 100], got {args.speed}")
    if not (0 < args.force_scale <= 0.1):
        raise ValueError(f"--force-scale must be in (0, 0.1] m/N, got {args.force_scale}")
    if not os.path.exists(args.source):
        raise ValueError(f"SOURCE {args.source} does not exist (an experiment output directory or a traces .npz)")


def validate(args) -> None:
    from hyqjax.cli import render as render_cmd

    _check(args)
    render_cmd.check_archive(args.source)
    args.options_checked = True


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    from hyqjax.cli import render as render_cmd

    rec, row = render_cmd.select(args)
    if not display_available():
        print("hyqjax view: no display (neither DISPLAY nor WAYLAND_DISPLAY is set), so the interactive viewer "
              "cannot open. Run it on a machine with a screen (or over ssh -X), or write a video with "
              f"`hyqjax render {args.source}`.", file=sys.stderr)
        return NO_DISPLAY_EXIT
    return play(rec, row, args.speed, loop=not args.once, force_scale=args.force_scale)


def play(rec, row: int, speed: float, loop: bool, force_scale: float) -> int:
    """Replay row ``row`` of ``rec`` in ``mujoco.viewer.launch_passive`` until the window closes."""
    os.environ.setdefault("MUJOCO_GL", "glfw")
    import mujoco
    import mujoco.viewer
    import numpy as np

    from hyqjax.core import robot
    from hyqjax.io import recording
    from hyqjax.io import render

    inst = rec.instance(row)
    m = render.scene_model(float(inst.get("input_height", 0.0)))
    d = mujoco.MjData(m)
    links = render.LegLinks(m)
    t = np.asarray(inst["time"], np.float64)
    qpos = np.asarray(inst["qpos"], np.float64)
    ff = inst.get("foot_force")
    print(f"hyqjax view: {recording.label(rec, row)}, {t[-1] - t[0]:.1f} s at {speed:g}x; close the window to quit")
    with mujoco.viewer.launch_passive(m, d) as viewer:
        viewer.cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        viewer.cam.trackbodyid = links.trunk
        viewer.cam.distance, viewer.cam.azimuth, viewer.cam.elevation = 2.4, 120.0, -15.0
        while viewer.is_running():
            start = time.perf_counter()
            for i in range(len(t)):
                if not viewer.is_running():
                    break
                d.qpos[:] = qpos[i]
                mujoco.mj_kinematics(m, d)
                mujoco.mj_comPos(m, d)
                with viewer.lock():
                    scn = viewer.user_scn
                    scn.ngeom = 0
                    render.add_leg_links(scn, d, links)
                    if ff is not None:
                        rot = render.quat_to_rot(qpos[i, robot.QPOS_BASE_QUAT])
                        render.add_force_arrows(scn, d.site_xpos[links.feet], np.asarray(ff[i], np.float64) @ rot.T,
                                                force_scale)
                viewer.sync()
                lag = (t[i] - t[0]) / speed - (time.perf_counter() - start)
                if lag > 0:
                    time.sleep(lag)
            if not loop:
                while viewer.is_running():
                    time.sleep(0.05)
    return 0
