"""The plot strip under a rendered frame: reflex activation and the feet's vertical forces over the run.

:func:`reflex_strip` draws it once with matplotlib (Agg) for the whole sample window; :meth:`Strip.at` then
gives the strip of one frame, with a cursor at that frame's time. :mod:`hyqjax.io.render` stacks it under
the 3D view.
"""
from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["Strip", "reflex_strip"]


@dataclasses.dataclass
class Strip:
    """A pre-drawn plot strip and the pixel column of each time."""

    image: np.ndarray  # (h, W, 3) uint8
    t0: float
    t1: float
    x0: float
    x1: float

    def column(self, t: float) -> int:
        f = (t - self.t0) / max(self.t1 - self.t0, 1e-9)
        return int(round(self.x0 + np.clip(f, 0.0, 1.0) * (self.x1 - self.x0)))

    def at(self, t: float) -> np.ndarray:
        img = self.image.copy()
        c = self.column(t)
        img[:, max(c - 1, 0):c + 1] = (20, 20, 20)
        return img


def reflex_strip(time: np.ndarray, width: int, height: int, reflex_active: np.ndarray | None = None,
                 foot_force: np.ndarray | None = None) -> Strip:
    """The strip under the frame: reflex activation (orange band) and each foot's vertical force over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 100
    fig = plt.figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    t = np.asarray(time, np.float64)
    if foot_force is not None:
        fz = np.asarray(foot_force, np.float64)[..., 2]
        top = max(float(np.nanmax(fz)) if np.isfinite(fz).any() else 1.0, 1.0)
        for leg, color in zip(range(fz.shape[1]), ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b")):
            ax.plot(t, np.clip(fz[:, leg], 0, None) / top, color=color, lw=0.8)
    if reflex_active is not None:
        act = np.asarray(reflex_active).astype(bool)
        ax.fill_between(t, 0, 1, where=act, step="mid", color="#ff8c00", alpha=0.55, lw=0)
    ax.set_xlim(t[0], t[-1] if t[-1] > t[0] else t[0] + 1.0)
    ax.set_ylim(-0.05, 1.1)
    ax.set_axis_off()
    if height >= 40:
        ax.text(0.005, 0.97, "reflex active (orange), foot normal forces LF RF LH RH", transform=ax.transAxes,
                fontsize=max(5, min(8, height // 12)), va="top", color="#333")
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    x1 = ax.get_xlim()[1]
    return Strip(image=img, t0=float(t[0]), t1=float(x1), x0=0.0, x1=float(width - 1))
