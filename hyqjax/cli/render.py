"""Render one recorded instance of an experiment to an MP4 or GIF, headless (EGL or OSMesa on CPU, EGL on GPU).

SOURCE is an experiment output directory holding traces.npz (``hyqjax stepdown --out DIR`` writes
one) or a traces .npz file. Pick the instance by its row in results.json (--instance), the first
failed instance (--worst), or by its inputs (--where height=0.24 reflex=on instance=0); by default
the first recorded one. The camera tracks the trunk with the platform (at the instance's height)
in view; red bars show the foot ground reaction forces, an orange border marks the height reflex
being active, and a strip under the frame plots the reflex activation and the foot forces over
the run with a cursor at the current time. One frame per recorded sample (the recording's
decimation), optionally every --stride-th; playback at --speed times real time. --stills N also
writes N PNG stills next to the video (``hyqjax report`` embeds them). See docs/rendering.md.

Examples:
  hyqjax render out/stepdown --where height=0.24 reflex=on   # the first recorded run at 24 cm with the reflex
  hyqjax render out/stepdown --worst --format gif --stills 4  # the first failed run, as a GIF with 4 stills
"""
from __future__ import annotations

import argparse
import os
import time

from hyqjax.cli.common import UsageError

NAME = "render"
HELP = "render a recorded instance to MP4 / GIF (tracking camera, foot forces, reflex strip)"
ORDER = 60

#: GIF viewers clamp very short frame delays; GIFs are decimated to at most this frame rate by default.
GIF_MAX_FPS = 25.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter

    use_help_formatter(p)
    p.add_argument("source", help="experiment output directory with traces.npz, or a traces .npz file")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--instance", type=int, default=None, metavar="K",
                     help="row K of results.json's instances (default: the first recorded instance)")
    sel.add_argument("--worst", action="store_true", help="the first failed instance (needs results.json)")
    sel.add_argument("--where", nargs="+", default=None, metavar="KEY=VALUE",
                     help="the first recorded instance whose inputs match, keys: height, reflex (on/off), instance "
                          "(randomised instance number), friction, payload_mass, start_distance, lateral_offset, yaw")
    p.add_argument("--out", default=None,
                   help="output .mp4 or .gif (default: SOURCE/render/instance_K.mp4, .gif without imageio-ffmpeg)")
    p.add_argument("--format", choices=["mp4", "gif"], default=None, help="video format when --out is not given")
    p.add_argument("--width", type=int, default=640, help="frame width (px), in [16, 4096]")
    p.add_argument("--height", type=int, default=480, help="3D view height (px), in [16, 4096]; the strip is added")
    p.add_argument("--stride", type=int, default=0,
                   help="draw every STRIDE-th recorded sample (0: 1 for MP4, <= 25 fps for GIF)")
    p.add_argument("--speed", type=float, default=1.0, help="playback speed (1: real time), in (0, 100]")
    p.add_argument("--start", type=float, default=None, help="first simulated time to draw (s)")
    p.add_argument("--end", type=float, default=None, help="last simulated time to draw (s)")
    p.add_argument("--camera", type=float, nargs=3, default=(2.4, 120.0, -15.0),
                   metavar=("DIST", "AZIMUTH", "ELEVATION"),
                   help="tracking camera distance (m), azimuth and elevation (deg); azimuth 90 = side view")
    p.add_argument("--force-scale", type=float, default=0.0006, help="foot force bar length per newton (m/N)")
    p.add_argument("--no-forces", action="store_true", help="do not draw the foot forces")
    p.add_argument("--no-strip", action="store_true", help="no reflex / foot force strip under the frame")
    p.add_argument("--shadows", action="store_true", help="draw shadows and reflections (slower on CPU)")
    p.add_argument("--stills", type=int, default=0, metavar="N",
                   help="also write N PNG stills (first reflex activation and evenly spaced), in [0, 100]")


def video_path(args, source_dir: str, instance: int) -> str:
    if args.out:
        return args.out
    from hyqjax.io import render

    fmt = args.format or ("mp4" if render.has_ffmpeg() else "gif")
    return os.path.join(source_dir, "render", f"instance_{instance:03d}.{fmt}")


def validate(args) -> None:
    """Option checks before any heavy import (ValueError naming the option and the allowed range), then the
    trace archive checked (a damaged one is named, not unpickled)."""
    check_options(args)
    check_archive(args.source)
    if args.out:
        from hyqjax.cli.common import prepare_out

        prepare_out(os.path.dirname(os.path.abspath(args.out)), "--out")
    args.options_checked = True


def check_archive(source: str) -> None:
    """Raise ValueError naming ``source`` when its traces.npz (or results.json) is missing or damaged."""
    import json
    import zipfile

    from hyqjax.io import recording

    tp = recording.traces_path(source)
    from hyqjax.cli.verify import sweep_source_problem

    sweep_problem = sweep_source_problem(source)  # a sweep store: verified, its damaged chunks named
    if sweep_problem:
        raise ValueError(sweep_problem)
    if not os.path.isfile(tp):
        raise ValueError(f"SOURCE {source}: no trace archive at {tp} (run e.g. `hyqjax stepdown --out DIR` without "
                         f"--no-figures to record one)")
    if not zipfile.is_zipfile(tp):
        raise ValueError(f"SOURCE {source}: {tp} is not a .npz (zip) archive: damaged or not written by hyqjax; "
                         f"run the experiment again to rewrite it")
    try:
        with zipfile.ZipFile(tp) as z:
            bad = z.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        bad = str(e) or type(e).__name__
    if bad:
        raise ValueError(f"SOURCE {source}: {tp} is damaged ({bad}); run the experiment again to rewrite it")
    res = os.path.join(os.path.dirname(os.path.abspath(tp)), recording.RESULTS_FILE)
    if os.path.isfile(res):
        try:
            with open(res, "rb") as f:
                json.loads(f.read().decode("utf-8"))
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"SOURCE {source}: {res} is not valid JSON ({str(e)[:80]}); run the experiment again "
                             f"to rewrite it") from None


def check_options(args) -> None:
    _check(args)


def _check(args) -> None:
    if not (16 <= args.width <= 4096):
        raise ValueError(f"--width must be in [16, 4096] px, got {args.width}")
    if not (16 <= args.height <= 4096):
        raise ValueError(f"--height must be in [16, 4096] px, got {args.height}")
    if not (0 <= args.stride <= 100000):
        raise ValueError(f"--stride must be in [0, 100000], got {args.stride}")
    if not (0 < args.speed <= 100):
        raise ValueError(f"--speed must be in (0, 100], got {args.speed}")
    if not (0 <= args.stills <= 100):
        raise ValueError(f"--stills must be in [0, 100], got {args.stills}")
    if not (0 < args.force_scale <= 0.1):
        raise ValueError(f"--force-scale must be in (0, 0.1] m/N, got {args.force_scale}")
    dist, _, elev = args.camera
    if not (0.2 <= dist <= 50) or not (-90 <= elev <= 90):
        raise ValueError(f"--camera DIST must be in [0.2, 50] m and ELEVATION in [-90, 90] deg, got {args.camera}")
    if args.start is not None and args.end is not None and args.end < args.start:
        raise ValueError(f"--end ({args.end}) must not be before --start ({args.start})")
    if args.out and os.path.splitext(args.out)[1].lower() not in (".mp4", ".gif"):
        raise ValueError(f"--out must end in .mp4 or .gif, got {args.out}")
    if not os.path.exists(args.source):
        raise ValueError(f"SOURCE {args.source} does not exist (an experiment output directory or a traces .npz)")


def select(args):
    """Load the recording and the row to render; UsageError with the reason on bad input."""
    from hyqjax.io import recording

    try:
        rec = recording.load(args.source)
        where = recording.parse_where(args.where) if args.where else None
        row = recording.choose_row(rec, instance=args.instance, worst=args.worst, where=where)
    except (FileNotFoundError, ValueError) as err:
        raise UsageError(str(err)) from None
    if "qpos" not in rec.arrays:
        raise UsageError(f"{rec.path} has no 'qpos' (trunk pose and joint angles), nothing to draw")
    return rec, row


def stride_for(args, rec, fmt: str) -> int:
    if args.stride:
        return args.stride
    if fmt != "gif":
        return 1
    fps = args.speed / rec.sample_dt
    return max(1, int(-(-fps // GIF_MAX_FPS)))


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    rec, row = select(args)
    from hyqjax.io import recording

    instance = int(rec.instance_index[row])
    out = video_path(args, os.path.dirname(os.path.abspath(rec.path)), instance)
    fmt = os.path.splitext(out)[1].lstrip(".").lower()
    from hyqjax.io import render

    if fmt == "mp4" and not render.has_ffmpeg():
        raise UsageError(".mp4 needs imageio-ffmpeg (pip install 'hyqjax[video]'); use --format gif")
    opts = render.RenderOptions(width=args.width, height=args.height, distance=args.camera[0], azimuth=args.camera[1],
                                elevation=args.camera[2], forces=not args.no_forces, force_scale=args.force_scale,
                                strip=not args.no_strip, shadows=args.shadows)
    stride = stride_for(args, rec, fmt)
    print(f"hyqjax render: {recording.label(rec, row)}; every {stride} of {rec.arrays['time'].shape[1]} samples "
          f"({rec.sample_dt * 1000:.0f} ms apart), {args.width}x{args.height}, MUJOCO_GL={render.gl_backend()}",
          flush=True)
    t0 = time.time()
    try:
        res = render.render_recording(rec, row, out, opts, stride=stride, start=args.start, end=args.end,
                                      speed=args.speed, stills=args.stills, progress=True)
    except render.RenderBackendError as err:
        raise UsageError(str(err)) from None
    except ValueError as err:
        raise UsageError(str(err)) from None
    wall = time.time() - t0
    video_s = res["frames"] / res["fps"] if res["fps"] else 0.0
    print(f"wrote {res['video']}: {res['frames']} frames at {res['fps']:.1f} fps, a {video_s:.1f} s video of "
          f"{video_s * args.speed:.1f} s of simulated time; rendering took {wall:.1f} s (wall time)")
    for p in res["stills"]:
        print(f"wrote {p}")
    return 0
