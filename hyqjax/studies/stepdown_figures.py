"""Figures of the step-down experiment: the paper's Fig. 9, 10 and 11 from recorded traces."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hyqjax.core import robot  # noqa: E402

LEG_LABELS = tuple(leg.upper() for leg in robot.LEG_NAMES)
JOINT_LABELS = [f"{leg}_{j}".upper() for leg in robot.LEG_NAMES for j in robot.JOINT_NAMES]


def _first_reflex_window(tr, k, pad=0.3):
    """Ticks around the longest reflex activation of instance ``k`` (the swing stepping off the platform:
    the haptic search past the edge is the longest downward swing)."""
    t = tr["time"][k]
    act = tr["reflex_active"][k].astype(bool)
    if not act.any():
        act = tr["swing_down"][k].astype(bool)
    if not act.any():
        return 0, len(t)
    edges = np.diff(np.concatenate([[0], act.astype(np.int8), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    j = int(np.argmax(ends - starts))
    i0, i1 = int(starts[j]), int(ends[j])
    dt = t[1] - t[0]
    n = int(pad / dt)
    return max(0, i0 - n), min(len(t), i1 + n)


def fig9_reflex(tr, k, path, title=""):
    """Fig. 9: reflex activation, damping schedule vs swing mobility, swing foot and stance feet trajectories."""
    i0, i1 = _first_reflex_window(tr, k)
    t = tr["time"][k][i0:i1]
    leg = int(np.bincount(tr["swing_leg"][k][i0:i1][tr["swing_down"][k][i0:i1].astype(bool)]).argmax()) if tr["swing_down"][k][i0:i1].any() else 1
    fig, ax = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    ax[0].plot(t, tr["reflex_active"][k][i0:i1].astype(float), "k")
    ax[0].set_ylabel("reflex active")
    damp = tr["damping"][k][i0:i1]
    ax[1].plot(t, damp[:, 3 * leg], label=f"swing ({LEG_LABELS[leg]})")
    stance = int(robot.STANCE_LEGS[leg][0])
    ax[1].plot(t, damp[:, 3 * stance], label="stance")
    ax[1].set_ylabel("damping [Nms/rad]")
    ax[1].set_yscale("log")
    axm = ax[1].twinx()
    axm.plot(t, tr["mobility"][k][i0:i1, leg], "g--", label="swing mobility m")
    axm.set_ylabel("m [m]")
    ax[1].legend(loc="upper left", fontsize=8)
    axm.legend(loc="upper right", fontsize=8)
    ax[2].plot(t, tr["x_plan_b"][k][i0:i1, leg, 2], "--", label="planned $x^d$")
    ax[2].plot(t, tr["x_cmd_b"][k][i0:i1, leg, 2], label="reflex $x^r$")
    ax[2].set_ylabel(f"{LEG_LABELS[leg]} foot z (base) [m]")
    ax[2].legend(fontsize=8)
    for j in robot.STANCE_LEGS[leg].tolist():
        ax[3].plot(t, tr["x_cmd_b"][k][i0:i1, j, 2], label=f"{LEG_LABELS[j]} $x^r$")
        ax[3].plot(t, tr["x_plan_b"][k][i0:i1, j, 2], ":", color=ax[3].lines[-1].get_color())
    ax[3].set_ylabel("stance feet z (base) [m]")
    ax[3].set_xlabel("time [s]")
    ax[3].legend(fontsize=8, ncol=3)
    fig.suptitle(title or "Height reflex in action (cf. Fig. 9)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig10_end_stop(tr, k, path, title=""):
    """Fig. 10: the joint that comes closest to its limit: position, velocity and corrected foot trajectory."""
    q = tr["q_cmd"][k]
    margin = np.minimum(q - robot.Q_MIN, robot.Q_MAX - q)
    j = int(np.argmin(margin.min(0)))
    leg = j // 3
    t = tr["time"][k]
    i = int(np.argmin(margin[:, j]))
    dt = t[1] - t[0]
    n = int(1.5 / dt)
    i0, i1 = max(0, i - n), min(len(t), i + n)
    fig, ax = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    tt = t[i0:i1]
    ax[0].plot(tt, tr["q_cmd"][k][i0:i1, j], label="reference $q^r$")
    ax[0].plot(tt, tr["q"][k][i0:i1, j], label="measured $q$")
    lim = robot.Q_MAX[j] if robot.Q_MAX[j] - q[i, j] < q[i, j] - robot.Q_MIN[j] else robot.Q_MIN[j]
    ax[0].axhline(lim, color="r", label="limit")
    delta = 0.05
    ax[0].axhspan(min(lim, lim - np.sign(lim - q[i, j]) * delta), max(lim, lim - np.sign(lim - q[i, j]) * delta),
                  color="r", alpha=0.15, label="end-stop spring active (Δ)")
    ax[0].set_ylabel(f"{JOINT_LABELS[j]} [rad]")
    ax[0].legend(fontsize=8)
    ax[1].plot(tt, np.gradient(tr["q_cmd"][k][i0:i1, j], dt), label="reference velocity")
    ax[1].plot(tt, tr["qd"][k][i0:i1, j], label="measured velocity")
    ax[1].set_ylabel("[rad/s]")
    ax[1].legend(fontsize=8)
    ax[2].plot(tt, tr["x_plan_b"][k][i0:i1, leg, 2], "--", label="planned z")
    ax[2].plot(tt, tr["x_cmd_b"][k][i0:i1, leg, 2], label="corrected z")
    ax[2].plot(tt, tr["x_plan_b"][k][i0:i1, leg, 0], "--", label="planned x")
    ax[2].plot(tt, tr["x_cmd_b"][k][i0:i1, leg, 0], label="corrected x")
    ax[2].set_ylabel(f"{LEG_LABELS[leg]} foot (base) [m]")
    ax[2].set_xlabel("time [s]")
    ax[2].legend(fontsize=8, ncol=2)
    fig.suptitle(title or f"Joint approaching its end-stop: {JOINT_LABELS[j]} (cf. Fig. 10)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return JOINT_LABELS[j], float(margin[:, j].min())


def fig11_pitch(traces, path, title=""):
    """Fig. 11: trunk pitch over the whole experiment, one line per (height, reflex) trace."""
    fig, ax = plt.subplots(figsize=(8, 3.5))
    _draw_pitch(ax, traces, title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _draw_pitch(ax, traces, title=""):
    for label, (tr, k) in traces.items():
        ax.plot(tr["time"][k], np.degrees(tr["rpy"][k][:, 1]), label=label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("pitch [deg] (nose down > 0)")
    ax.legend(fontsize=8)
    ax.set_title(title or "Trunk pitch while stepping down (cf. Fig. 11)")


def success_bars(rows, path):
    """Clean success rate (``clean``: completed and no shin strike) with 95% intervals per height, reflex on vs
    off."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    _draw_success(ax, rows)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def overview(rows, traces, path):
    """Success bars beside the pitch traces: the picture of the experiment at a glance."""
    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 3.8), gridspec_kw=dict(width_ratios=[1, 1.7]))
    _draw_success(a, rows)
    _draw_pitch(b, traces)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _draw_success(ax, rows):
    heights = sorted({r["height"] for r in rows})
    w = 0.35
    for off, reflex, color in [(-w / 2, False, "tab:gray"), (w / 2, True, "tab:blue")]:
        xs, ys, lo, hi = [], [], [], []
        for i, h in enumerate(heights):
            r = [r for r in rows if r["height"] == h and r["reflex"] == reflex]
            if not r:
                continue
            r = r[0]
            xs.append(i + off)
            ys.append(r["success_rate"])
            lo.append(r["success_rate"] - r["success_ci95"][0])
            hi.append(r["success_ci95"][1] - r["success_rate"])
        ax.bar(xs, ys, w, yerr=[lo, hi], capsize=3, color=color, label=f"reflex {'on' if reflex else 'off'}")
    ax.set_xticks(range(len(heights)), [f"{h * 100:.0f} cm" for h in heights])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("clean success rate")
    ax.legend()
    ax.set_title("Step-down clean success: completed, no shin strike (95% Wilson)", fontsize=10)


def all_figures(out_dir, table, out, rows, trace):
    os.makedirs(out_dir, exist_ok=True)
    success_bars(rows, os.path.join(out_dir, "success.png"))
    figs = {}
    if trace is None:
        return figs
    h = table["height"]
    r = table["reflex"].astype(bool)
    top = h.max()
    on = np.nonzero((h == top) & r)[0]
    off = np.nonzero((h == top) & ~r)[0]
    if len(on):
        fig9_reflex(trace, on[0], os.path.join(out_dir, "fig9_reflex.png"),
                    f"Height reflex stepping down {top * 100:.0f} cm (cf. Fig. 9)")
        figs["fig10_joint"] = fig10_end_stop(trace, on[0], os.path.join(out_dir, "fig10_end_stop.png"))
    lines = {}
    for hh in sorted(set(h.tolist())):
        for rr in (False, True):
            idx = np.nonzero((h == hh) & (r == rr))[0]
            if len(idx):
                lines[f"{hh * 100:.0f} cm, reflex {'on' if rr else 'off'}"] = (trace, idx[0])
    fig11_pitch(lines, os.path.join(out_dir, "fig11_pitch.png"))
    overview(rows, lines, os.path.join(out_dir, "overview.png"))
    del off
    return figs
