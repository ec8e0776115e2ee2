"""Figures of a sweep summary, both outcome levels: completed and clean probability maps, and both against height
(matplotlib, Agg)."""
from __future__ import annotations

import numpy as np

from hyqjax.studies.sweep.outcomes import KEYS, LEVELS
from hyqjax.studies.sweep.spec import AXES


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_map(ax, m: dict, level: str) -> object:
    """One map's ``level`` probability as a heat map (cell text: rate, Wilson 95% interval, n)."""
    keys = KEYS[level]
    rate = np.asarray(m[keys["rate"]], float).T
    im = ax.imshow(rate, origin="lower", vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
    lo, hi = np.asarray(m[keys["ci95_lo"]], float).T, np.asarray(m[keys["ci95_hi"]], float).T
    nn = np.asarray(m["n"]).T
    for yy in range(rate.shape[0]):
        for xx in range(rate.shape[1]):
            if nn[yy, xx]:
                ax.text(xx, yy, f"{rate[yy, xx]:.2f}\n[{lo[yy, xx]:.2f},{hi[yy, xx]:.2f}]\nn={nn[yy, xx]}",
                        ha="center", va="center", fontsize=7)
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
    ax.set_xticks(range(len(m["x_levels"])), [fmt(v) for v in m["x_levels"]], fontsize=8)
    ax.set_yticks(range(len(m["y_levels"])), [fmt(v) for v in m["y_levels"]], fontsize=8)
    ax.set_xlabel(f"{m['x']} [{AXES[m['x']].unit}]")
    ax.set_ylabel(f"{m['y']} [{AXES[m['y']].unit}]")
    ax.set_title(f"{level}, reflex {'on' if m['reflex'] else 'off'}")
    return im


def plot_maps(summary: dict, path: str) -> str | None:
    """Heat maps of the completed and the clean probability: per map pair one row per level (completed, then
    clean; a level absent from the summary is left out), one column per reflex setting."""
    maps = summary.get("maps", [])
    if not maps:
        return None
    plt = pyplot()
    pairs = sorted({(m["x"], m["y"]) for m in maps}, key=lambda p: [(mm["x"], mm["y"]) for mm in maps].index(p))
    modes = sorted({m["reflex"] for m in maps})
    levels = [lv for lv in LEVELS if any(m.get(KEYS[lv]["rate"]) is not None for m in maps)]
    rows = [(p, lv) for p in pairs for lv in levels]
    fig, axes = plt.subplots(len(rows), len(modes), figsize=(4.8 * len(modes) + 1, 3.8 * len(rows)),
                             squeeze=False, layout="constrained")
    im = None
    for i, (p, lv) in enumerate(rows):
        for j, r in enumerate(modes):
            mm = [m for m in maps if (m["x"], m["y"]) == p and m["reflex"] == r]
            if mm:
                im = draw_map(axes[i, j], mm[0], lv)
            else:
                axes[i, j].axis("off")
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.8, label="probability")
    fig.suptitle(f"Step-down {' / '.join(levels)} probability (Wilson 95% intervals)")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_height_curves(summary: dict, path: str) -> str | None:
    """Completed (solid) and clean (dashed) probability against height, one colour per reflex setting, with
    Wilson 95% intervals."""
    br = summary.get("by_reflex")
    if not br:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for ci, (name, r) in enumerate(br.items()):
        c = r["height_curve"]
        if not c:
            continue
        h = np.asarray([x["height"] for x in c], float) * 100
        dx = 0.006 * (float(np.ptp(h)) or 1.0)  # the two levels side by side, their intervals apart
        for li, lv in enumerate(LEVELS):
            keys = KEYS[lv]
            if any(x.get(keys["rate"]) is None for x in c):
                continue
            p = np.asarray([x[keys["rate"]] for x in c], float)
            lo = np.asarray([x[keys["ci95"]][0] for x in c], float)
            hi = np.asarray([x[keys["ci95"]][1] for x in c], float)
            ax.errorbar(h + dx * (2 * li - 1), p, yerr=[p - lo, hi - p], color=f"C{ci}",
                        ls="-" if lv == "completed" else "--", marker="o" if lv == "completed" else "s",
                        mfc="none" if lv == "clean" else None, capsize=3, label=f"reflex {name}, {lv}")
    ax.axhline(0.95, color="k", lw=0.6, ls=":")
    ax.set_xlabel("step height [cm]")
    ax.set_ylabel("probability (completed / clean)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
