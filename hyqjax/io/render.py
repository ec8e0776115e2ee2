"""Videos and stills of recorded instances with MuJoCo's offscreen renderer, headless on CPU or GPU.

A recorded instance (:mod:`hyqjax.io.recording`) is replayed kinematically: each sample's ``qpos``
is written into an ``MjData`` of the step-down model (:func:`hyqjax.sim.model.load_model`) with the
instance's platform height, and the scene is drawn from a camera that tracks the trunk, so the
platform edge at ``x = 0`` stays in view while HyQ walks off it. Overlays:

* **foot forces**: one red bar per foot along the recorded ground reaction force (``foot_force``,
  rotated from the trunk frame to the world), ``force_scale`` metres per newton (default 0.6 mm/N:
  a stance foot of the crawl carries about 300 N, a bar of about half a shin);
* **legs**: the model has collision geometry only (trunk, shins, feet); the thighs are drawn as
  capsules from hip to knee so the legs read as legs;
* **reflex**: a strip under the frame (matplotlib) plots the height reflex activation and the
  vertical foot forces over the whole run with a cursor at the current time, and the frame gets an
  orange border while the reflex is active (the strip: :mod:`hyqjax.io.strip`).

Frames are written as MP4, GIF or PNG by :mod:`hyqjax.io.video` (``has_ffmpeg``, ``write_video`` and
``write_png`` are also reachable here).

OpenGL backend: MuJoCo picks it from ``MUJOCO_GL`` when ``mujoco`` is imported. Unset, hyqjax uses
``egl``: headless, on NVIDIA GPUs through the driver and on CPU through Mesa's software EGL device
(Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``). ``MUJOCO_GL=osmesa`` (``libosmesa6``)
also works. If ``mujoco`` was already imported with another backend, :func:`make_renderer` creates
the context of the chosen backend itself.
"""
from __future__ import annotations

import dataclasses
import os
import sys
from typing import Iterator

import numpy as np

#: Headless backends MuJoCo can render with, in the order hyqjax tries them.
HEADLESS_BACKENDS = ("egl", "osmesa")
REFLEX_RGB = np.array([255, 140, 0], np.uint8)


def gl_backend() -> str:
    """The OpenGL backend to render with: ``MUJOCO_GL`` if set, else ``egl``."""
    return (os.environ.get("MUJOCO_GL") or "egl").lower().strip()


def _select_backend_before_import() -> None:
    """Set ``MUJOCO_GL`` (and PyOpenGL's platform) before ``mujoco`` is imported, when the user has not."""
    if "mujoco" in sys.modules:
        return
    backend = gl_backend()
    os.environ.setdefault("MUJOCO_GL", backend)
    if backend in HEADLESS_BACKENDS:
        os.environ.setdefault("PYOPENGL_PLATFORM", backend)


_select_backend_before_import()

import mujoco  # noqa: E402

from hyqjax.sim import model as hmodel  # noqa: E402
from hyqjax.core import robot  # noqa: E402
from hyqjax.io import recording  # noqa: E402
from hyqjax.io.strip import reflex_strip  # noqa: E402
from hyqjax.io.video import has_ffmpeg, write_png, write_video  # noqa: E402, F401  (has_ffmpeg: re-exported)


class RenderBackendError(RuntimeError):
    """No OpenGL context could be created for offscreen rendering."""


def _context_class(backend: str):
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        from mujoco.glfw import GLContext
    return GLContext


def _backend_help(backend: str, err: BaseException) -> str:
    return (f"cannot create an OpenGL context with MUJOCO_GL={backend} ({type(err).__name__}: {err}). "
            "Headless rendering needs EGL (Debian: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri; "
            "NVIDIA: the driver's libEGL_nvidia) or OSMesa (apt-get install libosmesa6, then MUJOCO_GL=osmesa). "
            "See docs/rendering.md.")


def make_renderer(m: mujoco.MjModel, width: int, height: int) -> mujoco.Renderer:
    """A ``mujoco.Renderer`` on the backend of :func:`gl_backend`; raises :class:`RenderBackendError` with
    what to install when no context can be made."""
    backend = gl_backend()
    m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), width)
    m.vis.global_.offheight = max(int(m.vis.global_.offheight), height)
    try:
        from mujoco.rendering.classic import gl_context as glc

        wanted = _context_class(backend)
        saved = glc.GLContext
    except Exception as err:  # noqa: BLE001  (a missing library surfaces as any of several errors)
        raise RenderBackendError(_backend_help(backend, err)) from err
    glc.GLContext = wanted
    try:
        return mujoco.Renderer(m, height=height, width=width)
    except Exception as err:  # noqa: BLE001
        raise RenderBackendError(_backend_help(backend, err)) from err
    finally:
        glc.GLContext = saved


@dataclasses.dataclass(frozen=True)
class RenderOptions:
    """How a recorded instance is drawn.

    Attributes:
      width, height: size of the 3D view (px); the reflex strip is added below it.
      distance, azimuth, elevation: tracking camera (m, deg, deg); azimuth 90 looks along +y
        (side view, HyQ walking to the right).
      forces: draw the foot force arrows.  force_scale: arrow length per newton (m/N).
      strip: add the reflex / foot force strip.  strip_height: its height (px).
      shadows: draw shadows and reflections (slower on CPU).
    """

    width: int = 640
    height: int = 480
    distance: float = 2.4
    azimuth: float = 120.0
    elevation: float = -15.0
    forces: bool = True
    force_scale: float = 0.0006
    strip: bool = True
    strip_height: int = 0
    shadows: bool = False

    def __post_init__(self):
        if not (16 <= self.width <= 4096 and 16 <= self.height <= 4096):
            raise ValueError(f"width and height must be in [16, 4096] px, got {self.width} x {self.height}")
        if not (0.2 <= self.distance <= 50):
            raise ValueError(f"camera distance must be in [0.2, 50] m, got {self.distance}")
        if not (-90 <= self.elevation <= 90):
            raise ValueError(f"camera elevation must be in [-90, 90] deg, got {self.elevation}")
        if not (0 < self.force_scale <= 0.1):
            raise ValueError(f"force_scale must be in (0, 0.1] m/N, got {self.force_scale}")

    @property
    def strip_px(self) -> int:
        return self.strip_height or max(24, self.height // 4)


def scene_model(platform_height: float = 0.0) -> mujoco.MjModel:
    """A private copy of the step-down model with the platform top at ``platform_height`` and a brighter headlight."""
    m = _copy_model(hmodel.load_model())
    ids = hmodel.model_ids(m)
    m.geom_pos[ids.platform_geom, 2] = float(platform_height) - hmodel.PLATFORM_HALF_SIZE[2]
    m.vis.headlight.ambient[:] = 0.35
    m.vis.headlight.diffuse[:] = 0.6
    return m


def _copy_model(m: mujoco.MjModel) -> mujoco.MjModel:
    import copy

    return copy.deepcopy(m)


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a (w, x, y, z) quaternion."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(q, np.float64) / max(np.linalg.norm(q), 1e-12))
    return mat.reshape(3, 3)


class LegLinks:
    """Body ids of the hip (upper-leg origin) and knee (lower-leg origin) of each leg."""

    def __init__(self, m: mujoco.MjModel):
        self.hips = [m.body(f"{leg}_upperleg").id for leg in robot.LEG_NAMES]
        self.knees = [m.body(f"{leg}_lowerleg").id for leg in robot.LEG_NAMES]
        self.trunk = m.body("trunk").id
        self.hip_assemblies = [m.body(f"{leg}_hipassembly").id for leg in robot.LEG_NAMES]
        self.feet = [m.site(f"{leg}_foot").id for leg in robot.LEG_NAMES]


def _add_connector(scn: mujoco.MjvScene, kind: int, width: float, a, b, rgba) -> None:
    if scn.ngeom >= scn.maxgeom:
        return
    g = scn.geoms[scn.ngeom]
    mujoco.mjv_initGeom(g, kind, np.zeros(3), np.zeros(3), np.eye(3).reshape(-1), np.asarray(rgba, np.float32))
    mujoco.mjv_connector(g, kind, width, np.asarray(a, np.float64), np.asarray(b, np.float64))
    scn.ngeom += 1


def add_leg_links(scn: mujoco.MjvScene, d: mujoco.MjData, links: LegLinks) -> None:
    """Thigh capsules hip -> knee and hip-assembly links (the model has no visual geometry for them)."""
    for ha, hip, knee in zip(links.hip_assemblies, links.hips, links.knees):
        _add_connector(scn, mujoco.mjtGeom.mjGEOM_CAPSULE, 0.03, d.xpos[ha], d.xpos[hip], (0.35, 0.4, 0.45, 1))
        _add_connector(scn, mujoco.mjtGeom.mjGEOM_CAPSULE, 0.028, d.xpos[hip], d.xpos[knee], (0.55, 0.58, 0.62, 1))


def add_force_arrows(scn: mujoco.MjvScene, feet: np.ndarray, forces_w: np.ndarray, scale: float) -> None:
    """One red bar per foot from the foot along its ground reaction force (world frame), ``scale`` m/N.

    Drawn as capsules: their length is exactly the scaled force (MuJoCo's arrow geoms render shorter than
    their ``size[2]`` in mujoco 4.0)."""
    for p, f in zip(feet, forces_w):
        if not np.all(np.isfinite(f)) or np.linalg.norm(f) * scale < 0.01:
            continue
        _add_connector(scn, mujoco.mjtGeom.mjGEOM_CAPSULE, 0.012, p, p + scale * f, (0.9, 0.12, 0.08, 1))


class FrameRenderer:
    """Draws qpos samples of one instance: ``render(qpos, foot_force_b=None) -> (H, W, 3) uint8``."""

    def __init__(self, platform_height: float, opts: RenderOptions = RenderOptions()):
        self.opts = opts
        self.model = scene_model(platform_height)
        self.data = mujoco.MjData(self.model)
        self.links = LegLinks(self.model)
        self.renderer = make_renderer(self.model, opts.width, opts.height)
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        self.camera.trackbodyid = self.links.trunk
        self.camera.distance = opts.distance
        self.camera.azimuth = opts.azimuth
        self.camera.elevation = opts.elevation

    def set_state(self, qpos: np.ndarray) -> None:
        if qpos.shape[-1] != self.model.nq:
            raise ValueError(f"qpos has {qpos.shape[-1]} entries, the model needs nq = {self.model.nq}")
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_comPos(self.model, self.data)

    def render(self, qpos: np.ndarray, foot_force_b: np.ndarray | None = None) -> np.ndarray:
        self.set_state(qpos)
        r = self.renderer
        r.update_scene(self.data, self.camera)
        scn = r.scene
        scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.opts.shadows
        scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = self.opts.shadows
        add_leg_links(scn, self.data, self.links)
        if self.opts.forces and foot_force_b is not None:
            rot = quat_to_rot(qpos[robot.QPOS_BASE_QUAT])
            feet = self.data.site_xpos[self.links.feet]
            add_force_arrows(scn, feet, np.asarray(foot_force_b, np.float64) @ rot.T, self.opts.force_scale)
        return r.render().copy()

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def with_border(frame: np.ndarray, rgb: np.ndarray, px: int) -> np.ndarray:
    out = frame.copy()
    out[:px], out[-px:], out[:, :px], out[:, -px:] = rgb, rgb, rgb, rgb
    return out


def sample_indices(time: np.ndarray, stride: int = 1, start: float | None = None,
                   end: float | None = None) -> np.ndarray:
    """Sample indices to draw: every ``stride``-th sample with ``start <= t <= end``."""
    t = np.asarray(time)
    keep = np.ones(t.shape, bool)
    if start is not None:
        keep &= t >= start - 1e-9
    if end is not None:
        keep &= t <= end + 1e-9
    return np.nonzero(keep)[0][::max(int(stride), 1)]


def frames(inst: dict[str, np.ndarray], indices: np.ndarray, opts: RenderOptions = RenderOptions(),
           window: tuple[int, int] | None = None) -> Iterator[np.ndarray]:
    """Composited frames (3D view, orange border while the reflex is active, strip below) of one recorded instance.

    ``window``: the sample range ``[i0, i1]`` the strip covers (default: that of ``indices``).
    """
    if "qpos" not in inst:
        raise ValueError("the trace has no 'qpos' (trunk pose and joint angles): it cannot be drawn")
    t = np.asarray(inst["time"], np.float64)
    act = inst.get("reflex_active")
    ff = inst.get("foot_force")
    i0, i1 = window or (int(np.min(indices)), int(np.max(indices)))
    span = slice(i0, i1 + 1)
    strip = None
    if opts.strip:
        strip = reflex_strip(t[span], opts.width, opts.strip_px, None if act is None else np.asarray(act)[span],
                             None if ff is None else np.asarray(ff)[span])
    border = max(2, opts.width // 100)
    with FrameRenderer(float(inst.get("input_height", 0.0)), opts) as fr:
        for i in indices:
            img = fr.render(np.asarray(inst["qpos"][i], np.float64), None if ff is None else ff[i])
            if act is not None and bool(act[i]):
                img = with_border(img, REFLEX_RGB, border)
            if strip is not None:
                img = np.concatenate([img, strip.at(float(t[i]))], axis=0)
            yield img


def still_indices(inst: dict[str, np.ndarray], indices: np.ndarray, n: int) -> np.ndarray:
    """``n`` samples among ``indices`` for stills: the first reflex activation (when there is one) and evenly
    spaced samples over the run."""
    if n <= 0 or len(indices) == 0:
        return np.zeros(0, np.int64)
    picks = list(np.asarray(indices)[np.linspace(0, len(indices) - 1, n).round().astype(int)])
    act = inst.get("reflex_active")
    if act is not None and np.asarray(act)[indices].any() and n >= 2:
        first = int(np.asarray(indices)[np.argmax(np.asarray(act)[indices])])
        picks[len(picks) // 2] = first
    return np.unique(np.asarray(picks, np.int64))


def render_recording(rec: "recording.Recording", row: int, out_path: str, opts: RenderOptions = RenderOptions(),
                     stride: int = 1, start: float | None = None, end: float | None = None, speed: float = 1.0,
                     stills: int = 0, progress: bool = False) -> dict:
    """Render row ``row`` of a recording to ``out_path`` (and ``stills`` PNGs next to it).

    Playback runs at ``speed`` times real time: one frame per drawn sample, ``fps = speed / (sample_dt * stride)``.
    Returns ``dict(video=..., frames=..., fps=..., stills=[...])``. ``progress``: a tqdm bar over the frames
    with an ETA (on stderr).
    """
    inst = rec.instance(row)
    idx = sample_indices(inst["time"], stride, start, end)
    if len(idx) == 0:
        raise ValueError(f"no samples between --start {start} and --end {end} (recorded "
                         f"{float(inst['time'][0]):.2f}-{float(inst['time'][-1]):.2f} s)")
    fps = speed / (rec.sample_dt * max(stride, 1))
    window = (int(idx[0]), int(idx[-1]))
    images = frames(inst, idx, opts, window)
    if progress:
        from tqdm.auto import tqdm

        images = tqdm(images, total=len(idx), desc=f"render {os.path.basename(out_path)}", unit="frame",
                      dynamic_ncols=True)
    n = write_video(out_path, images, fps)
    still_paths = []
    if stills:
        base = os.path.splitext(out_path)[0]
        pick = still_indices(inst, idx, stills)
        for i, img in zip(pick, frames(inst, pick, opts, window)):
            p = f"{base}_t{float(inst['time'][i]):06.2f}s.png"
            write_png(p, img)
            still_paths.append(p)
    return dict(video=out_path, frames=n, fps=fps, stills=still_paths)
