"""Figures of a sweep summary: success probability maps and success against height (matplotlib, Agg)."""
from __future__ import annotations

import numpy as np

from hyqjax.studies.sweep.spec import AXES


def plot_maps(summary: dict, path: str) -> str | None:
    """Heat maps of the success probability (cell text: rate and Wilson 95% interval)."""
    maps = summary.get("maps", [])
    if not maps:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = sorted({(m["x"], m["y"]) for m in maps}, key=lambda p: [(mm["x"], mm["y"]) for mm in maps].index(p))
    modes = sorted({m["reflex"] for m in maps})
    fig, axes = plt.subplots(len(pairs), len(modes), figsize=(4.8 * len(modes), 3.8 * len(pairs)), squeeze=False)
    im = None
    for i, p in enumerate(pairs):
        for j, r in enumerate(modes):
            ax = axes[i, j]
            mm = [m for m in maps if (m["x"], m["y"]) == p and m["reflex"] == r]
            if not mm:
                ax.axis("off")
                continue
            m = mm[0]
            rate = np.asarray(m["rate"], float).T
            im = ax.imshow(rate, origin="lower", vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
            lo, hi, nn = np.asarray(m["ci95_lo"]).T, np.asarray(m["ci95_hi"]).T, np.asarray(m["n"]).T
            for yy in range(rate.shape[0]):
                for xx in range(rate.shape[1]):
                    if nn[yy, xx]:
                        ax.text(xx, yy, f"{rate[yy, xx]:.2f}\n[{lo[yy, xx]:.2f},{hi[yy, xx]:.2f}]\nn={nn[yy, xx]}",
                                ha="center", va="center", fontsize=7)
            fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
            ax.set_xticks(range(len(m["x_levels"])), [fmt(v) for v in m["x_levels"]], fontsize=8)
            ax.set_yticks(range(len(m["y_levels"])), [fmt(v) for v in m["y_levels"]], fontsize=8)
            ax.set_xlabel(f"{p[0]} [{AXES[p[0]].unit}]")
            ax.set_ylabel(f"{p[1]} [{AXES[p[1]].unit}]")
            ax.set_title(f"reflex {'on' if r else 'off'}")
    if im is not None:
        fig.colorbar(im, ax=axes, shrink=0.8, label="success probability")
    fig.suptitle("Step-down success probability (Wilson 95% intervals)")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def plot_height_curves(summary: dict, path: str) -> str | None:
    br = summary.get("by_reflex")
    if not br:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in br.items():
        c = r["height_curve"]
        if not c:
            continue
        h = np.asarray([x["height"] for x in c])
        p = np.asarray([x["rate"] for x in c])
        lo = np.asarray([x["ci95"][0] for x in c])
        hi = np.asarray([x["ci95"][1] for x in c])
        ax.errorbar(h * 100, p, yerr=[p - lo, hi - p], marker="o", capsize=3, label=f"reflex {name}")
    ax.axhline(0.95, color="k", lw=0.6, ls=":")
    ax.set_xlabel("step height [cm]")
    ax.set_ylabel("success probability")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
