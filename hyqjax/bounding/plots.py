"""Figures of the bounding experiments (matplotlib, Agg backend)."""
from __future__ import annotations

import os

import numpy as np

from hyqjax.bounding.summary import per_cycle, wrap_angle


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str) -> str:
    """Lay out, write (120 dpi) and close ``fig``; return ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    _plt().close(fig)
    return path


def cycle_speeds(trace: dict, i: int, period: float = 0.4, control_dt: float = 0.002):
    """Per-cycle mean forward speed (heading frame) and yaw rate of instance ``i``: ``(t_mid, v, psidot)``."""
    idx, v, _, yr = per_cycle(trace, period, control_dt)
    t = trace["t"][i, idx]
    return 0.5 * (t[:-1] + t[1:]), v[i], yr[i]


def _lines(ax, xs, ys, color, label=None, marker=False, **kw):
    """One ``LineCollection`` of the rows of ``xs`` / ``ys`` (each row a line, drawn as separate paths: the same
    picture as one ``plot`` call per row, in one artist), with ``marker`` dots in one scatter."""
    from matplotlib.collections import LineCollection

    xs, ys = np.broadcast_arrays(np.asarray(xs, float), np.asarray(ys, float))
    if xs.size == 0:
        return
    ax.add_collection(LineCollection(np.stack([xs, ys], axis=-1), colors=color, label=label, **kw))
    if marker:
        ax.scatter(xs.ravel(), ys.ravel(), s=3, color=color, alpha=kw.get("alpha"), linewidths=0)
    ax.autoscale_view()


#: Instances drawn per group in :func:`tracking_figures` at most (evenly spaced over the group; more lines only
#: darken the same band, and Agg's time grows with each: 1,024 lines of 400 samples take seconds per panel).
MAX_LINES = 128


def _shown(idx) -> tuple[list[int], str]:
    """At most :data:`MAX_LINES` of ``idx``, evenly spaced (first and last kept), and a legend note."""
    idx = list(idx)
    if len(idx) <= MAX_LINES:
        return idx, ""
    keep = np.unique(np.linspace(0, len(idx) - 1, MAX_LINES).round().astype(int))
    return [idx[k] for k in keep], f" ({len(keep)} of {len(idx)} shown)"


def tracking_figures(trace: dict, groups: dict[str, list[int]], outdir: str, prefix: str = "") -> dict:
    """``PREFIXyaw_tracking.png`` (desired vs actual yaw and the yaw error, as the paper's Fig. 4) and
    ``PREFIXspeed_tracking.png`` (per-cycle forward speed vs command) for every group of instances (at most
    :data:`MAX_LINES` of a group, evenly spaced, the legend saying so; each group drawn as one collection of
    lines)."""
    plt = _plt()
    os.makedirs(outdir, exist_ok=True)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    for g, (name, idx) in enumerate(groups.items()):
        c = colors[g % len(colors)]
        idx, note = _shown(idx)
        name = name + note
        if not idx:
            continue
        t = trace["t"][idx]
        yaw = np.degrees(np.unwrap(trace["rpy"][idx, :, 2], axis=1))
        yd = np.degrees(trace["yaw_des"][idx])
        yaw = yaw + 360.0 * np.round((yd[:, :1] - yaw[:, :1]) / 360.0)
        _lines(ax[0], t, yaw, c, label=f"{name}: actual", lw=0.8, alpha=0.8)
        ax[0].plot(t[0], yd[0], color=c, lw=1.5, ls="--", label=f"{name}: desired")
        err = np.degrees(np.abs(wrap_angle(trace["yaw_des"][idx] - trace["rpy"][idx, :, 2])))
        _lines(ax[1], t, err, c, lw=0.8, alpha=0.8)
    ax[1].axhline(4.0, color="k", ls=":", lw=1, label="4 deg (HyQ, paper Fig. 4)")
    ax[0].set_ylabel("yaw [deg]")
    ax[1].set_ylabel("|yaw error| [deg]")
    ax[1].set_xlabel("time [s]")
    ax[0].legend(fontsize=7, ncol=2)
    ax[1].legend(fontsize=7)
    ax[0].set_title("Yaw tracking while bounding")
    f_yaw = _save(fig, os.path.join(outdir, prefix + "yaw_tracking.png"))

    fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    cyc, v_all, _, yr_all = per_cycle(trace, 0.4)  # every instance at once (one call, not one per instance)
    for g, (name, idx) in enumerate(groups.items()):
        c = colors[g % len(colors)]
        idx, note = _shown(idx)
        name = name + note
        if not idx:
            continue
        tc = trace["t"][idx][:, cyc]
        tm = 0.5 * (tc[:, :-1] + tc[:, 1:])
        _lines(ax[0], tm, v_all[idx], c, label=name, marker=True, lw=0.8, alpha=0.8)
        _lines(ax[1], tm, yr_all[idx], c, marker=True, lw=0.8, alpha=0.8)
        i = idx[0]
        ax[0].plot(trace["t"][i], trace["v_des"][i, :, 0], color=c, ls="--", lw=1.5)
        ax[1].plot(trace["t"][i], trace["yaw_rate_des"][i], color=c, ls="--", lw=1.5)
    ax[0].set_ylabel("forward speed [m/s]\n(per cycle)")
    ax[1].set_ylabel("yaw rate [rad/s]\n(per cycle)")
    ax[1].set_xlabel("time [s]")
    ax[0].legend(fontsize=7)
    ax[0].set_title("Speed and yaw-rate tracking (dashed: command)")
    f_speed = _save(fig, os.path.join(outdir, prefix + "speed_tracking.png"))
    return dict(yaw_tracking=f_yaw, speed_tracking=f_speed)


def convergence_figure(history: np.ndarray, residual_history: np.ndarray, path: str, title: str = "") -> str:
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    it = np.arange(1, history.shape[0] + 1)
    for b in range(history.shape[1]):
        ax[0].semilogy(it, np.maximum(history[:, b], 1e-12), lw=0.8)
        ax[1].semilogy(it, np.maximum(residual_history[:, b], 1e-12), lw=0.8)
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("loss (Eq. C2)")
    ax[1].set_xlabel("iteration")
    ax[1].set_ylabel("||r|| (scaled return-map residual)")
    fig.suptitle(title or "Cycle optimisation from many initial guesses (vmap, forward-mode Jacobians)")
    return _save(fig, path)


def eigenvalue_figure(eigs: dict[str, np.ndarray], path: str) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 5))
    th = np.linspace(0, 2 * np.pi, 200)
    ax.plot(np.cos(th), np.sin(th), "k:", lw=1)
    for (name, e), m in zip(eigs.items(), "oxs^v"):
        ax.plot(np.real(e), np.imag(e), m, ms=7, mfc="none", label=f"{name}: max|lambda| = {np.max(np.abs(e)):.2f}")
    ax.set_aspect("equal")
    ax.set_xlabel("Re")
    ax.set_ylabel("Im")
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title("Linearised apex return map: eigenvalues")
    lim = max(1.2, max(np.max(np.abs(e)) for e in eigs.values()) * 1.1)
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    return _save(fig, path)


def bar_figure(labels: list[str], series: dict[str, list[float]], ylabel: str, path: str, title: str = "") -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    x = np.arange(len(labels))
    w = 0.8 / max(len(series), 1)
    for k, (name, vals) in enumerate(series.items()):
        v = [np.nan if a is None else a for a in vals]
        ax.bar(x + (k - (len(series) - 1) / 2) * w, v, w, label=name)
    ax.set_xticks(x)
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7)
    ax.set_title(title)
    return _save(fig, path)
