"""Regenerate the bounding figures and tables (Orsolino et al., turning while bounding).

    python -m experiments.bounding_figures --out DIR [--quick] [--write-defaults]

1. Cycle optimisation (Eq. C2) from ``--guesses`` initial guesses at once (vmap, forward-mode Jacobians,
   Levenberg-Marquardt through optax): convergence figure, best residual. Forward-mode Jacobian of the
   residual vs central finite differences at the stored cycle.
2. Linearised apex return map of the stored cycle: eigenvalues without feedback, with the stance
   feedback (Eq. B7), with stance + apex feedback (Eqs. B4, B5, B8), and with the per-cycle integrators.
3. Closed loop, one compiled batch: turning at speed with all four kinematic-adjustment /
   centrifugal on-off combinations (ablation), the linear / angular adjustment off one at a time, the
   paper's rate-only yaw law, a speed sweep (0 = in place), and a robustness set (lateral pushes, low
   friction, payload).
Writes DIR/results.json, DIR/tables.md and the PNG figures. ``--write-defaults`` replaces
``hyqjax/bounding_defaults.py`` by the newly optimised cycle (its reference table and the current apex gains).
CPU time with the defaults: about 15-20 minutes on 2 cores (most of it XLA compiles); ``--quick`` ~8 minutes.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np


def _eig_list(e):
    return [[float(np.real(v)), float(np.imag(v))] for v in e]


def optimisation(args, out: dict, figs: dict):
    from hyqjax import bounding as bd, bounding_cycle as bc, bounding_plots as bp

    params = bd.default_params(apex_feedback=False, stance_feedback=False)
    u0 = bc.initial_guesses(params, args.guesses, seed=args.seed)
    t0 = time.time()
    res = bc.optimise_cycle(params, u0, iterations=args.iterations, method="lm")
    wall = time.time() - t0
    best = res.best
    figs["convergence"] = bp.convergence_figure(res.history, res.residual_history,
                                                os.path.join(args.out, "cycle_convergence.png"))
    out["optimisation"] = dict(
        method="Levenberg-Marquardt direction through optax.sgd; forward-mode (jacfwd) Jacobians; vmap over guesses",
        guesses=args.guesses, iterations=args.iterations, wall_time_s=wall,
        initial_residual_norm=[float(v) for v in res.residual_history[0]],
        final_residual_norm=[float(v) for v in res.residual_norm],
        converged_below_0_01=int(np.sum(res.residual_norm < 0.01)),
        best=dict(u=dict(zip(bc.DECISION_NAMES, map(float, res.u[best]))), residual=res.residual[best].tolist(),
                  residual_norm=float(res.residual_norm[best])))
    return params, res


def gradient_check(args, out: dict):
    """Forward-mode Jacobian of the residual vs central finite differences at the stored cycle (one vmap of jvp)."""
    from hyqjax import bounding as bd, bounding_cycle as bc

    params = bd.default_params(apex_feedback=False, stance_feedback=False)
    u = bc.stored_cycle()
    idx = (0, 1, 2, 3, 4, 6)
    eps = (2.0, 2.0, 2.0, 2.0, 0.002, 0.02)
    t0 = time.time()
    r0, j_fwd, j_fd = bc.gradient_check(params, u, indices=idx, eps=eps)
    wall = time.time() - t0
    rel = [float(np.linalg.norm(j_fwd[:, k] - j_fd[:, k]) / max(np.linalg.norm(j_fd[:, k]), 1e-12))
           for k in range(len(idx))]
    out["gradient_check"] = dict(
        at="stored cycle (feedback off)", residual=r0.tolist(), residual_norm=float(np.linalg.norm(r0)),
        variables=[bc.DECISION_NAMES[i] for i in idx], eps=list(eps), wall_time_s=wall,
        jacobian_forward=j_fwd.tolist(), jacobian_central_differences=j_fd.tolist(), relative_error=rel)


def linear_analysis(args, out: dict, figs: dict):
    from hyqjax import bounding as bd, bounding_cycle as bc, bounding_experiment as bx, bounding_plots as bp

    u = bc.stored_cycle()
    pf = bc.with_cycle(bd.default_params(), jnp.asarray(u, jnp.float32))
    s = np.asarray(bc.apex_state(jnp.asarray(u, jnp.float32)))
    configs = dict(none=bc.with_feedback(pf, False), stance=bc.with_feedback(pf, False, True), stance_apex=pf)
    stacked = bx.stack_params(list(configs.values()))
    t0 = time.time()
    p_out, a_all, b_all = jax.jit(jax.vmap(lambda q: bc.linearise(q, jnp.asarray(s), period=0.4)))(stacked)
    wall = time.time() - t0
    a_all, b_all, p_out = np.asarray(a_all), np.asarray(b_all), np.asarray(p_out)
    eigs = {k: np.linalg.eigvals(a) for k, a in zip(configs, a_all)}
    # Linear model of the apex impulse terms only (the B8 placement correction is not an amplitude, so
    # A_stance + B K differs from the direct Jacobian with the apex feedback on).
    kp = bc.feedback_matrix(pf)
    pred = np.linalg.eigvals(a_all[1] + b_all[1] @ kp)
    aug = bc.augmented_matrix(a_all[2], b_all[2], pf)
    eigs_aug = np.linalg.eigvals(aug)
    names = dict(none="no feedback (feed-forward impulses)", stance="stance PD (Eq. B7)",
                 stance_apex="stance PD + apex feedback (B4, B5, B8)")
    figs["eigenvalues"] = bp.eigenvalue_figure({names[k]: v for k, v in eigs.items()} |
                                               {"+ integrators (augmented)": eigs_aug},
                                               os.path.join(args.out, "return_map_eigenvalues.png"))
    out["return_map"] = dict(
        state=["z", "theta", "xdot", "zdot", "thetadot"], s_star=s.tolist(), wall_time_s=wall,
        fixed_point_residual={k: ((p_out[i] - s) / bc.RESIDUAL_SCALE).tolist() for i, k in enumerate(configs)},
        eigenvalues={k: _eig_list(v) for k, v in eigs.items()},
        spectral_radius={k: float(np.max(np.abs(v))) for k, v in eigs.items()},
        eigenvalues_A_stance_plus_BK_impulse_terms_only=_eig_list(pred),
        spectral_radius_A_stance_plus_BK_impulse_terms_only=float(np.max(np.abs(pred))),
        eigenvalues_with_integrators=_eig_list(eigs_aug),
        spectral_radius_with_integrators=float(np.max(np.abs(eigs_aug))),
        A=a_all.tolist(), B=b_all.tolist(), feedback_matrix=kp.tolist())


def write_defaults(args, params, res, out):
    from hyqjax import bounding_cycle as bc, bounding_defaults as bdef

    ub = res.u[res.best]
    pc = bc.with_cycle(params, jnp.asarray(ub, jnp.float32))
    table = bc.reference_table(pc, np.asarray(bc.apex_state(jnp.asarray(ub, jnp.float32))))
    path = os.path.join(os.path.dirname(bdef.__file__), "bounding_defaults.py")
    with open(path, "w") as f:
        f.write(bc.defaults_source(ub, table, dict(bdef.APEX_GAINS)))
    importlib.reload(bdef)
    out["wrote_defaults"] = path


def closed_loop(args, out: dict, figs: dict):
    from hyqjax import bounding as bd, bounding_experiment as bx, bounding_plots as bp

    n = args.instances
    v_turn, w_turn = args.turn_speed, args.turn_rate
    batches, groups = [], {}

    def add(name, plist, **kw):
        start = sum(len(b.apex0) for b in batches)
        batches.append(bx.make_batch(plist, seed=args.seed, **kw))
        groups[name] = list(range(start, start + len(plist)))

    abl = (("full", True, True), ("no_kinematic_adjustment", False, True), ("no_centrifugal", True, False),
           ("neither", False, False))
    for name, kin, cf in abl:
        for sgn in (1, -1):
            add(f"turn{'L' if sgn > 0 else 'R'}_{name}",
                [bd.default_params(speed=v_turn, yaw_rate=sgn * w_turn, kinematic_adjustment=kin, centrifugal=cf)] * n)
    # Linear (Eq. 1) and angular (Eq. 2) kinematic adjustment switched off one at a time (centrifugal on).
    for name, lin, ang in (("no_kinematic_linear", False, True), ("no_kinematic_angular", True, False)):
        for sgn in (1, -1):
            p = bd.default_params(speed=v_turn, yaw_rate=sgn * w_turn)
            p = p.replace(switches=bd.Switches.make(kinematic_linear=lin, kinematic_angular=ang))
            add(f"turn{'L' if sgn > 0 else 'R'}_{name}", [p] * n)
    # The paper's turning law uses the yaw-rate term only (K_p,psi = 0).
    for sgn in (1, -1):
        add(f"turn{'L' if sgn > 0 else 'R'}_rate_only_paper",
            [bd.default_params(speed=v_turn, yaw_rate=sgn * w_turn, k_yaw=0.0)] * n)
    speeds = (0.0, 0.25, 0.5, 0.75, 1.0)
    for v in speeds:
        add(f"speed_{v:g}", [bd.default_params(speed=v)] * n)
    pushes = (0.0, 150.0, 300.0, 450.0)
    for f in pushes:
        add(f"push_{f:g}N", [bd.default_params(speed=0.5)] * n, push_force=f, push_time=3.0, push_duration=0.1)
    add("friction_0.4-0.5", [bd.default_params(speed=0.5)] * n, rand=bx.Randomisation(friction=(0.4, 0.5)))
    add("payload_10-15kg", [bd.default_params(speed=0.5)] * n, rand=bx.Randomisation(payload=(10.0, 15.0)))
    batch = bx.concat_batches(batches)
    t0 = time.time()
    res, trace = bx.run(batch, duration=args.duration)
    wall = time.time() - t0
    summary = bx.summarise(res, trace, batch)
    inst = summary["instances"]
    agg = {g: bx.aggregate([inst[i] for i in idx]) for g, idx in groups.items()}
    # Ablation over both turn directions.
    abl_groups = {name: dict(aggregate=bx.aggregate([inst[i] for s in "LR" for i in groups[f"turn{s}_{name}"]]))
                  for name, _, _ in abl}
    split = {name: bx.aggregate([inst[i] for s in "LR" for i in groups[f"turn{s}_{name}"]])
             for name in ("no_kinematic_linear", "no_kinematic_angular", "rate_only_paper")}
    out["closed_loop"] = dict(
        duration=args.duration, instances_per_group=n, wall_time_s=wall,
        env_steps_per_s=len(inst) * args.duration / 0.002 / wall, turn=dict(speed=v_turn, yaw_rate=w_turn),
        groups=agg, ablation=dict(groups={k: v["aggregate"] for k, v in abl_groups.items()} | split,
                                  contributions=bx.contributions(abl_groups)),
        instances={g: [inst[i] for i in idx] for g, idx in groups.items()})
    os.makedirs(args.out, exist_ok=True)
    f1 = bp.tracking_figures(trace, {"turn L, full": groups["turnL_full"], "turn R, full": groups["turnR_full"],
                                     "turn L, neither": groups["turnL_neither"]}, os.path.join(args.out, "turning"))
    f2 = bp.tracking_figures(trace, {f"{v:g} m/s": groups[f"speed_{v:g}"] for v in speeds},
                             os.path.join(args.out, "speed"))
    figs["yaw_tracking"], figs["speed_tracking"] = f1["yaw_tracking"], f2["speed_tracking"]
    figs["turn_speed_tracking"], figs["sweep_yaw"] = f1["speed_tracking"], f2["yaw_tracking"]
    labels = [a[0] for a in abl]
    figs["ablation"] = bp.bar_figure(
        labels, {"yaw error max [deg]": [abl_groups[k]["aggregate"]["yaw_error_max_deg_mean"] for k in labels],
                 "yaw-rate err rms x10 [rad/s]": [None if abl_groups[k]["aggregate"]["yaw_rate_error_rms_mean"] is None
                                                  else 10 * abl_groups[k]["aggregate"]["yaw_rate_error_rms_mean"]
                                                  for k in labels],
                 "speed err rms x10 [m/s]": [None if abl_groups[k]["aggregate"]["speed_error_rms_mean"] is None
                                             else 10 * abl_groups[k]["aggregate"]["speed_error_rms_mean"] for k in labels],
                 "falls": [abl_groups[k]["aggregate"]["falls"] for k in labels]},
        "value", os.path.join(args.out, "ablation.png"),
        f"Turning at {v_turn} m/s, +-{w_turn} rad/s: contribution of each part")
    rob = [f"push_{f:g}N" for f in pushes] + ["friction_0.4-0.5", "payload_10-15kg"]
    figs["robustness"] = bp.bar_figure(
        rob, {"falls": [agg[g]["falls"] for g in rob],
              "yaw error max [deg]": [agg[g]["yaw_error_max_deg_mean"] for g in rob],
              "speed err rms x10 [m/s]": [None if agg[g]["speed_error_rms_mean"] is None
                                          else 10 * agg[g]["speed_error_rms_mean"] for g in rob]},
        "value", os.path.join(args.out, "robustness.png"), "Robustness at 0.5 m/s (lateral push at t = 3 s for 0.1 s)")
    return agg, abl_groups


def tables_md(out: dict) -> str:
    from hyqjax import bounding_experiment as bx

    lines = ["# Bounding: results", ""]
    if "optimisation" in out:
        o = out["optimisation"]
        lines += ["## Cycle optimisation", "",
                  f"{o['guesses']} guesses x {o['iterations']} iterations ({o['wall_time_s']:.0f} s); "
                  f"{o['converged_below_0_01']} reached ||r|| < 0.01; best ||r|| = {o['best']['residual_norm']:.2e}", "",
                  "| " + " | ".join(o["best"]["u"]) + " |", "|" + "---|" * len(o["best"]["u"]),
                  "| " + " | ".join(f"{v:.4g}" for v in o["best"]["u"].values()) + " |", ""]
    if "gradient_check" in out:
        gc = out["gradient_check"]
        lines += ["## Forward-mode Jacobian vs central differences (stored cycle)", "",
                  f"||r(u*)|| = {gc['residual_norm']:.2e}", "", "| variable | eps | relative error |", "|---|---|---|"]
        lines += [f"| {v} | {e:g} | {x:.1e} |" for v, e, x in zip(gc["variables"], gc["eps"], gc["relative_error"])]
        lines.append("")
    if "return_map" in out:
        r = out["return_map"]
        lines += ["## Linearised apex return map (stored cycle)", "", "| feedback | spectral radius | eigenvalues |",
                  "|---|---|---|"]
        for k, e in r["eigenvalues"].items():
            lines.append(f"| {k} | {r['spectral_radius'][k]:.3f} | "
                         + ", ".join(f"{a:.3f}{b:+.3f}j" for a, b in e) + " |")
        lines.append(f"| stance + apex + per-cycle integrators (augmented) | "
                     f"{r['spectral_radius_with_integrators']:.3f} | "
                     + ", ".join(f"{a:.3f}{b:+.3f}j" for a, b in r["eigenvalues_with_integrators"]) + " |")
        lines.append("")
    if "closed_loop" in out:
        c = out["closed_loop"]
        groups = {k: dict(aggregate=v) for k, v in c["groups"].items()}
        lines += ["## Closed loop", "", "```", bx.format_table(groups), "```", "", "### Ablation (turning)", "", "```",
                  bx.format_table({k: dict(aggregate=v) for k, v in c["ablation"]["groups"].items()}),
                  bx.format_contributions(c["ablation"]["contributions"]), "```", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.bounding_figures", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="results/bounding_figures")
    ap.add_argument("--guesses", type=int, default=8, help="initial guesses of the cycle optimisation")
    ap.add_argument("--iterations", type=int, default=10, help="optimiser iterations")
    ap.add_argument("--instances", type=int, default=3, help="instances per closed-loop group")
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--turn-speed", type=float, default=0.9)
    ap.add_argument("--turn-rate", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="4 guesses x 6 iterations, 2 instances per group")
    ap.add_argument("--skip-optimisation", action="store_true")
    ap.add_argument("--skip-gradient-check", action="store_true")
    ap.add_argument("--write-defaults", action="store_true",
                    help="write the optimised cycle to hyqjax/bounding_defaults.py")
    args = ap.parse_args(argv)
    if args.quick:
        args.guesses, args.iterations, args.instances = 4, 6, 2
    if args.guesses < 1 or args.iterations < 1 or args.instances < 1:
        raise ValueError("--guesses, --iterations and --instances must be >= 1")
    os.makedirs(args.out, exist_ok=True)
    from hyqjax import io

    out: dict = dict(provenance=io.provenance(argv=sys.argv[1:], seed=args.seed), args=vars(args))
    out["provenance"]["command"] = " ".join(["python -m experiments.bounding_figures", *sys.argv[1:]])
    figs: dict = {}
    t0 = time.time()
    if not args.skip_optimisation:
        params, res = optimisation(args, out, figs)
        if args.write_defaults:
            write_defaults(args, params, res, out)
    if not args.skip_gradient_check:
        gradient_check(args, out)
    linear_analysis(args, out, figs)
    closed_loop(args, out, figs)
    out["figures"] = figs
    out["wall_time_s"] = time.time() - t0
    io.write_json(os.path.join(args.out, "results.json"), out)
    md = tables_md(out)
    with open(os.path.join(args.out, "tables.md"), "w") as f:
        f.write(md + "\n")
    print(md)
    print(json.dumps(figs, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
