"""Figures of the height reflex (Focchi et al. 2017, Section III): Fig. 6, Fig. 8 and a
kinematic-only version of Fig. 9.

Run ``python -m experiments.reflex_figures --out DIR``; it writes ``fig6_base_spring.png``,
``fig8_mobility.png``, ``fig9_kinematic_demo.png`` and ``reflex_figures.json`` (the numbers
quoted in the captions). The cores of the figures are plain functions returning arrays
(:func:`fig6_forces`, :func:`fig8_curve`, :func:`kinematic_demo`), reusable from tests and
notebooks. Everything is computed in float64.

Setting of all three: HyQ in the SRDF standing pose, the RF leg swinging (as in the paper's
Fig. 6, 9), Table I parameters unless stated, control period 1 ms. The base is fixed (the reflex
works in the base frame); trunk lowering shows as the stance feet moving up.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.reflex import step as R

DT = 1e-3
RF = robot.RF
LEG_LABELS = ("LF", "RF", "LH", "RH")


def _standing_feet():
    return kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float64))


def search_plan(x0, swing_leg, depth, speed, n_steps, lift=0.0, lift_time=0.0, dt=DT):
    """Planned feet for one swing with a haptic downward search (Section II), base frame.

    The swing foot first rises by ``lift`` over ``lift_time`` (upward phase, reflex inactive),
    then descends at ``speed`` until it is ``depth`` below its start (downward phase, active).
    Returns ``(x_des (T, 4, 3), active (T,))``.
    """
    t = np.arange(n_steps) * dt
    up_phase = t < lift_time
    z = np.where(up_phase, lift * np.minimum(t / max(lift_time, 1e-9), 1.0), lift - speed * (t - lift_time))
    z = np.maximum(z, -depth)
    x_des = np.repeat(np.asarray(x0)[None], n_steps, 0)
    x_des[:, swing_leg, 2] += z
    return jnp.asarray(x_des), jnp.asarray(~up_phase)


def _inputs_sequence(x_des, swing_leg, active, n_t_des):
    n = x_des.shape[0]
    return R.ReflexInputs(
        x_des=x_des,
        swing_leg=jnp.full(n, swing_leg, jnp.int32),
        active=active,
        n_t_des=jnp.tile(n_t_des, (n, 1)),
        up=jnp.tile(jnp.asarray([0.0, 0.0, 1.0], x_des.dtype), (n, 1)),
    )


# ---------------------------------------------------------------------------------------------
# Fig. 6: least-squares force solutions for two base spring stiffnesses
# ---------------------------------------------------------------------------------------------


def fig6_forces(k_base: float, depth: float = 0.2, speed: float = 0.1, t_snapshot: float = 2.0, duration: float = 3.0):
    """RF searches downward (``speed`` m/s to ``depth``); returns the state at ``t_snapshot``.

    Returns a dict of NumPy arrays: ``x_r`` (4, 3) feet, ``f_r`` (4, 3) virtual forces (swing row
    = ``f_sw``), ``e_b`` (3,), ``n_t`` (3,) at the snapshot, and time series ``t``, ``dz``
    (T, 4) feet z change in the base frame, ``e_b_norm`` (T,).
    """
    x0 = _standing_feet()
    n = int(round(duration / DT))
    x_des, active = search_plan(x0, RF, depth, speed, n)
    inputs = _inputs_sequence(x_des, RF, active, R.planned_terrain_normal(x0, RF))
    params = R.ReflexParams.make(k_base=float(k_base))
    _, out = jax.jit(lambda s, i, p: R.reflex_rollout(s, i, p, DT))(R.reflex_init(x0), inputs, params)
    k = int(round(t_snapshot / DT))
    return {
        "k_base": float(k_base),
        "x_r": np.asarray(out.x_r[k]),
        "f_r": np.asarray(out.f_r[k]),
        "e_b": np.asarray(out.e_b[k]),
        "n_t": np.asarray(out.n_t[k]),
        "t": np.arange(n) * DT,
        "dz": np.asarray(out.x_r[:, :, 2] - x0[None, :, 2]),
        "e_b_norm": np.linalg.norm(np.asarray(out.e_b), axis=-1),
        "t_snapshot": t_snapshot,
    }


def _plot_fig6(results, path):
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(13, 8.5))
    for col, res in enumerate(results):
        ax = fig.add_subplot(2, 2, col + 1, projection="3d")
        x, f = res["x_r"], res["f_r"]
        st = R.STANCE_LEGS[RF]
        scale = 0.25 / max(np.abs(f).max(), 1e-9)
        ax.scatter(*x.T, color="k", s=25)
        for leg in range(4):
            ax.text(*(x[leg] + [0, 0, -0.05]), LEG_LABELS[leg], fontsize=9)
        ax.quiver(*x[RF], *(scale * f[RF]), color="red", linewidth=2, label="$f_{sw}^r$")
        for leg in st:
            ax.quiver(*x[leg], *(scale * f[leg]), color="blue", linewidth=2)
        ax.plot([], [], color="blue", label="$f_{st}^r$ (stance)")
        tri = x[st]
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        ax.add_collection3d(Poly3DCollection([tri], alpha=0.25, facecolor="lightblue", edgecolor="steelblue"))
        ax.quiver(0, 0, 0, *(res["e_b"] * 0.3), color="grey", linewidth=2, label="$e_b$ (0.3 m per rad)")
        ax.scatter([0], [0], [0], color="grey", marker="s")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        ax.set_xlim(-0.5, 0.5)
        ax.set_ylim(-0.5, 0.5)
        ax.set_zlim(-0.8, 0.1)
        ax.view_init(elev=18, azim=-60)
        ax.set_title(f"(%s) $K_{{base}}$ = {res['k_base']:.0f} Nm/rad, t = {res['t_snapshot']:.1f} s" % "ab"[col])
        ax.legend(loc="upper left", fontsize=8)
    ax = fig.add_subplot(2, 2, 3)
    for res, ls in zip(results, ("--", "-")):
        ax.plot(res["t"], res["dz"][:, robot.LH] * 100, ls, color="C2", label=f"LH, $K_{{base}}$={res['k_base']:.0f}")
        ax.plot(res["t"], res["dz"][:, robot.LF] * 100, ls, color="C0", label=f"LF, $K_{{base}}$={res['k_base']:.0f}")
        ax.plot(res["t"], res["dz"][:, RF] * 100, ls, color="C3", label=f"RF (swing), $K_{{base}}$={res['k_base']:.0f}")
    ax.axvline(results[0]["t_snapshot"], color="k", lw=0.5)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("foot z change in base frame [cm]\n(> 0: leg retracts)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 2, 4)
    for res, ls in zip(results, ("--", "-")):
        ax.plot(res["t"], np.degrees(res["e_b_norm"]), ls, color="grey", label=f"$K_{{base}}$={res['k_base']:.0f}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("$|e_b|$ [deg]")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.suptitle(
        "Fig. 6: virtual forces (LS solution of Eq. 6) with RF swinging; blue: stance, red: swing, grey: $e_b$"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Fig. 8: mobility of the RF leg versus extension
# ---------------------------------------------------------------------------------------------


def fig8_curve(n: int = 200, kfe_range=(-2.2, float(robot.Q_MAX_LEG[RF, 2]))):
    """Mobility metrics of the RF leg (Eq. 12) as the knee extends, foot kept under the hip.

    The HFE angle is ``-KFE/2`` (foot vertically below the HFE joint), HAA as in the standing
    pose; the search direction is the terrain normal of the standing stance feet (``+z``).
    Returns a dict: ``kfe``, ``extension`` (HFE-foot distance, m), ``m`` (m/rad), ``w``,
    ``kappa_inv`` and the extensions where ``m`` crosses Table I's ``m_max`` and ``m_min``.
    """
    kfe = np.linspace(kfe_range[0], kfe_range[1], n)
    q = np.tile(robot.Q_STANDING, (n, 1))
    q[:, 3 * RF + 2] = kfe
    q[:, 3 * RF + 1] = -kfe / 2.0
    q = jnp.asarray(q)
    n_t = R.terrain_normal(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING))[np.asarray(R.STANCE_LEGS[RF])])
    j_rf = kinematics.foot_jacobians(q)[:, RF]
    m, w, kinv = jax.jit(jax.vmap(R.velocity_transformation_ratio, (0, None)))(j_rf, n_t)
    ext = np.asarray(kinematics.leg_extension(q)[:, RF])
    m = np.asarray(m)
    p = R.ReflexParams()

    def crossing(level):
        i = np.where(np.diff(np.sign(m - level)) != 0)[0]
        if i.size == 0:
            return None
        i = i[0]
        return float(np.interp(level, [m[i + 1], m[i]], [ext[i + 1], ext[i]]))

    return {
        "kfe": kfe,
        "extension": ext,
        "m": m,
        "w": np.asarray(w),
        "kappa_inv": np.asarray(kinv),
        "extension_at_m_max": crossing(p.m_max),
        "extension_at_m_min": crossing(p.m_min),
        "standing_extension": float(kinematics.leg_extension(jnp.asarray(robot.Q_STANDING))[RF]),
    }


def _plot_fig8(curve, path):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.5))
    ext = curve["extension"]
    ax.plot(ext, curve["m"], "k", lw=2, label="$m(n_t)$ velocity transformation ratio [m/rad]")
    p = R.ReflexParams()
    ax.axhspan(p.m_min, p.m_max, color="orange", alpha=0.3, label="$[m_{min}, m_{max}]$ (Table I)")
    ax.axvline(curve["standing_extension"], color="grey", ls=":", label="standing pose")
    ax.set_xlabel("RF leg extension (HFE-foot distance) [m]")
    ax.set_ylabel("m [m/rad]")
    ax2 = ax.twinx()
    ax2.plot(ext, curve["w"] / curve["w"].max(), "C0--", label="$w / w_{max}$ (manipulability)")
    ax2.plot(ext, curve["kappa_inv"] / curve["kappa_inv"].max(), "C2-.", label=r"$\kappa^{-1} / \kappa^{-1}_{max}$")
    ax2.set_ylabel("normalised w, $\\kappa^{-1}$")
    ax2.set_ylim(0, 1.05)
    lines = ax.get_legend_handles_labels()
    lines2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + lines2[0], lines[1] + lines2[1], fontsize=8, loc="lower left")
    ax.grid(alpha=0.3)
    ax.set_title("Fig. 8: RF leg mobility vs extension (foot under the hip)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Fig. 9 (kinematic only): stepping down with the reflex on and off
# ---------------------------------------------------------------------------------------------


def kinematic_demo(
    reflex: bool = True,
    step_height: float = 0.21,
    duration: float = 3.0,
    lift: float = 0.05,
    lift_time: float = 0.3,
    speed: float = 0.15,
    depth: float = 0.45,
    params: R.ReflexParams | None = None,
):
    """RF steps down from a platform of ``step_height`` (experiment (b) of the paper: 21 cm).

    The plan lifts the RF foot by ``lift`` (upward phase, reflex inactive), then searches
    downward at ``speed`` (reflex active) up to ``depth`` below the standing height, i.e. past
    the leg's workspace. Touchdown is declared when the foot is ``step_height`` below the plane
    of the three stance feet (the platform top), measured along its normal; after touchdown the
    reflex is deactivated and the plan is frozen at the corrected feet (the caller takes over).

    ``reflex=False`` is plain IK tracking of the plan, clipped to the reach and to the joint
    ranges (``q = clip(IK(x_des), q_min, q_max)``, ``x = K(q)``).

    Returns a dict of time series (NumPy): ``t``, ``active``, ``touched``, ``d_swing``,
    ``d_stance``, ``mobility`` (swing leg, along ``n_t``), ``x`` (T, 4, 3) feet sent to the
    controller, ``x_des`` (the plan), ``depth_below_platform`` (swing foot below the stance
    plane), ``trunk_lowering`` (mean stance-foot rise), and ``touchdown_time`` (NaN if none).
    """
    x0 = _standing_feet()
    n = int(round(duration / DT))
    params = R.ReflexParams.table1() if params is None else params
    x_plan, descending = search_plan(x0, RF, depth, speed, n, lift=lift, lift_time=lift_time)
    n_t_des = R.planned_terrain_normal(x0, RF)
    st_idx = np.asarray(R.STANCE_LEGS[RF])
    up = jnp.asarray([0.0, 0.0, 1.0])
    q_lo, q_hi = jnp.asarray(robot.Q_MIN), jnp.asarray(robot.Q_MAX)

    def depth_below(x):
        n_t = R.terrain_normal(x[st_idx], up)
        return -jnp.dot(n_t, x[RF] - jnp.mean(x[st_idx], axis=0))

    def body(carry, plan):
        state, touched, x_hold = carry
        x_des_k, desc = plan
        x_des_k = jnp.where(touched, x_hold, x_des_k)
        if reflex:
            active = desc & ~touched
            inputs = R.ReflexInputs(x_des=x_des_k, swing_leg=jnp.int32(RF), active=active, n_t_des=n_t_des, up=up)
            state, out = R.reflex_step(state, inputs, params, DT)
            x_cmd, mob, d = out.x_r, out.mobility[RF], out.d_diag
        else:
            active = jnp.asarray(False)
            q = jnp.clip(kinematics.inverse_kinematics(x_des_k).reshape(12), q_lo, q_hi)
            x_cmd = kinematics.foot_positions(q)
            j = kinematics.foot_jacobians(q)
            mob = R.transmission_ratio(j[RF], R.terrain_normal(x_cmd[st_idx], up))
            d = jnp.full(12, jnp.nan)
        h = depth_below(x_cmd)
        new_touch = touched | (desc & (h >= step_height))
        x_hold = jnp.where(new_touch & ~touched, x_cmd, x_hold)
        rec = dict(active=active, touched=new_touch, mobility=mob, d=d, x=x_cmd, x_des=x_des_k, depth=h)
        return (state, new_touch, x_hold), rec

    init = (R.reflex_init(x0), jnp.asarray(False), x0)
    _, rec = jax.jit(lambda c, xs: jax.lax.scan(body, c, xs))(init, (x_plan, descending))
    rec = jax.tree.map(np.asarray, rec)
    t = np.arange(n) * DT
    touched = rec["touched"]
    d = rec["d"].reshape(n, 4, 3)
    return {
        "reflex": reflex,
        "t": t,
        "active": rec["active"],
        "touched": touched,
        "d_swing": d[:, RF, 0],
        "d_stance": d[:, st_idx[0], 0],
        "mobility": rec["mobility"],
        "x": rec["x"],
        "x_des": rec["x_des"],
        "depth_below_platform": rec["depth"],
        "trunk_lowering": rec["x"][:, st_idx, 2].mean(1) - np.asarray(x0)[st_idx, 2].mean(),
        "touchdown_time": float(t[np.argmax(touched)]) if touched.any() else float("nan"),
        "step_height": step_height,
    }


def _plot_fig9(on, off, path):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(6, 1, figsize=(8, 13), sharex=True)
    t = on["t"]
    ax = axes[0]
    ax.plot(t, on["active"].astype(float), "k", label="reflex active (on)")
    ax.plot(t, on["touched"].astype(float) * 0.5, "C3:", label="touchdown (on)")
    ax.set_ylabel("activation")
    ax.legend(fontsize=8, loc="upper left")
    ax = axes[1]
    ax.semilogy(t, on["d_swing"], "C3", label="$D_{sw}$ (RF joints)")
    ax.semilogy(t, on["d_stance"], "C0", label="$D_{st}$ (stance joints)")
    ax.set_ylabel("damping [Nms/rad]")
    ax.legend(fontsize=8, loc="center left")
    ax = axes[2]
    ax.plot(t, on["mobility"], "k", label="reflex on")
    ax.plot(t, off["mobility"], "k--", label="reflex off")
    p = R.ReflexParams()
    ax.axhspan(p.m_min, p.m_max, color="orange", alpha=0.3, label="$[m_{min}, m_{max}]$")
    ax.set_ylabel("RF mobility m [m/rad]")
    ax.legend(fontsize=8)
    ax = axes[3]
    ax.plot(t, on["x_des"][:, RF, 2], "C7", label="plan $x^d_{RF,z}$ (frozen at touchdown)")
    ax.plot(t, on["x"][:, RF, 2], "C3", label="reflex on")
    ax.plot(t, off["x"][:, RF, 2], "C3--", label="reflex off (IK, clipped)")
    ax.set_ylabel("RF foot z,\nbase frame [m]")
    ax.legend(fontsize=8, loc="lower left")
    ax = axes[4]
    ax.plot(t, -on["depth_below_platform"] * 100, "C1", label="reflex on")
    ax.plot(t, -off["depth_below_platform"] * 100, "C1--", label="reflex off")
    ax.axhline(-on["step_height"] * 100, color="k", lw=0.8, label="lower ground (touchdown)")
    ax.set_ylabel("RF foot above\nstance plane [cm]")
    ax.legend(fontsize=8, loc="lower left")
    ax = axes[5]
    for leg, c in zip(R.STANCE_LEGS[RF], ("C0", "C2", "C4")):
        ax.plot(t, on["x"][:, leg, 2], c, label=f"{LEG_LABELS[leg]} z, reflex on")
        ax.plot(t, off["x"][:, leg, 2], c + "--", lw=1)
    ax.set_ylabel("stance feet z [m]\n(dashed: reflex off)")
    ax.set_xlabel("t [s]")
    ax.legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"Fig. 9 (kinematic only): RF stepping down {on['step_height'] * 100:.0f} cm, reflex on vs off")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="reflex_figures_out", help="output directory")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    with jax.enable_x64(True):
        fig6 = [fig6_forces(100.0), fig6_forces(1500.0)]
        curve = fig8_curve()
        on, off = kinematic_demo(reflex=True), kinematic_demo(reflex=False)
        _plot_fig6(fig6, os.path.join(args.out, "fig6_base_spring.png"))
        _plot_fig8(curve, os.path.join(args.out, "fig8_mobility.png"))
        _plot_fig9(on, off, os.path.join(args.out, "fig9_kinematic_demo.png"))
    summary = {
        "fig6": {
            str(int(r["k_base"])): {
                "t_snapshot_s": r["t_snapshot"],
                "lh_dz_at_snapshot_m": float(r["dz"][int(r["t_snapshot"] / DT), robot.LH]),
                "lh_virtual_force_z_N": float(r["f_r"][robot.LH, 2]),
                "f_r_N": r["f_r"].round(2).tolist(),
                "e_b_rad": r["e_b"].round(5).tolist(),
                "max_abs_e_b_deg": float(np.degrees(r["e_b_norm"].max())),
            }
            for r in fig6
        },
        "fig8": {
            "standing_extension_m": curve["standing_extension"],
            "m_standing": float(np.interp(curve["standing_extension"], curve["extension"], curve["m"])),
            "extension_at_m_max_m": curve["extension_at_m_max"],
            "extension_at_m_min_m": curve["extension_at_m_min"],
            "max_extension_m": float(curve["extension"][-1]),
            "m_at_max_extension": float(curve["m"][-1]),
        },
        "fig9": {
            name: {
                "touchdown_time_s": None if np.isnan(r["touchdown_time"]) else r["touchdown_time"],
                "max_depth_below_platform_m": float(r["depth_below_platform"].max()),
                "max_trunk_lowering_m": float(r["trunk_lowering"].max()),
                "min_swing_mobility": float(np.nanmin(r["mobility"])),
                "swing_foot_z_min_base_frame_m": float(r["x"][:, RF, 2].min()),
            }
            for name, r in (("reflex_on", on), ("reflex_off", off))
        },
        "step_height_m": on["step_height"],
        "params": "Table I",
    }
    with open(os.path.join(args.out, "reflex_figures.json"), "w") as f:
        json.dump(summary, f, indent=2)
    print(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    main(sys.argv[1:])
