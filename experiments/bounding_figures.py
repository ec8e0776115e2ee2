"""Regenerate the bounding figures and the numbers behind them (Orsolino et al., turning while bounding), with the
paper's gains (preset ``bound_paper``, :func:`hyqjax.bounding.params.paper_params`) so the tables stay the paper's.

    python -m experiments.bounding_figures FIGURE [--out docs/results] [options]

One command per figure / table; each writes ``OUT/bounding_FIGURE.json`` (the numbers, with the command,
device, versions, seed, batch and wall time) and its PNG figures ``OUT/bounding_FIGURE*.png``:

  optimise    cycle optimisation (Eq. C2) from --guesses initial guesses at once (vmap, forward-mode
              Jacobians, optimistix Levenberg-Marquardt): convergence figure, best residual. With
              --write-cycle PATH also writes the best cycle as a cycle file (hyqjax.bounding.defaults).
  gradient    forward-mode Jacobian of the residual vs central finite differences at the stored cycle.
  eigen       linearised apex return map of the stored cycle: eigenvalues without feedback, with the stance
              feedback (Eq. B7), with stance + apex feedback (Eqs. B4, B5, B8), and with the integrators.
  turning     turning at --turn-speed / --turn-rate: the four kinematic-adjustment / centrifugal on-off
              combinations (ablation), the linear / angular adjustment off one at a time and the paper's
              rate-only yaw law, both turn directions, one compiled batch.
  speed       speed sweep 0 (in place) to 1 m/s, straight.
  robustness  0.5 m/s with lateral pushes, low friction, 10-15 kg payload.
  all         all of the above.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

FIGURES = ("optimise", "gradient", "eigen", "turning", "speed", "robustness")


def _eig_list(e):
    return [[float(np.real(v)), float(np.imag(v))] for v in e]


def optimise(args) -> dict:
    from hyqjax.bounding import cycle as bc
    from hyqjax.bounding import defaults as bdef
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import plots
    from hyqjax.bounding import stability as bst

    params = bp.paper_params(apex_feedback=False, stance_feedback=False)
    u0 = bc.initial_guesses(params, args.guesses, seed=args.seed)
    t0 = time.time()
    res = bc.optimise_cycle(params, u0, iterations=args.iterations)
    wall = time.time() - t0
    best = res.best
    fig = plots.convergence_figure(res.history, res.residual_history,
                                   os.path.join(args.out, f"bounding_cycle_convergence{args.suffix}.png"))
    out = dict(method="optimistix.LevenbergMarquardt (jac='fwd': one jax.jacfwd per step), vmap over guesses",
               guesses=args.guesses, steps=args.iterations, wall_time_s=wall,
               initial_residual_norm=res.residual_history[0].tolist(), final_residual_norm=res.residual_norm.tolist(),
               steps_before_termination=res.steps.tolist(), residual_norm_history=res.residual_history.tolist(),
               loss_history=res.history.tolist(),
               converged_below_0_01=int(np.sum(res.residual_norm < 0.01)),
               best=dict(u=dict(zip(bc.DECISION_NAMES, map(float, res.u[best]))), residual=res.residual[best].tolist(),
                         residual_norm=float(res.residual_norm[best])),
               stored_cycle=dict(u=dict(zip(bc.DECISION_NAMES, map(float, bc.stored_cycle()))),
                                 distance_to_best_scaled=float(np.linalg.norm(
                                     (res.u[best] - bc.stored_cycle()) / bc.DECISION_SCALE))),
               figures=[fig])
    if args.write_cycle:
        ub = res.u[best]
        pc = bc.with_cycle(params, jnp.asarray(ub, jnp.float32))
        table = bst.reference_table(pc, np.asarray(bc.apex_state(jnp.asarray(ub, jnp.float32))))
        bdef.save(args.write_cycle, ub, table, bdef.stored().apex_gains,
                  dict(optimiser=out["method"], guesses=args.guesses, steps=args.iterations, seed=args.seed,
                       residual_norm=float(res.residual_norm[best])))
        out["wrote_cycle"] = args.write_cycle
    return out


def gradient(args) -> dict:
    from hyqjax.bounding import cycle as bc
    from hyqjax.bounding import params as bp

    params = bp.paper_params(apex_feedback=False, stance_feedback=False)
    idx, eps = (0, 1, 2, 3, 4, 6), (2.0, 2.0, 2.0, 2.0, 0.002, 0.02)
    t0 = time.time()
    r0, j_fwd, j_fd = bc.gradient_check(params, bc.stored_cycle(), indices=idx, eps=eps)
    rel = [float(np.linalg.norm(j_fwd[:, k] - j_fd[:, k]) / max(np.linalg.norm(j_fd[:, k]), 1e-12))
           for k in range(len(idx))]
    return dict(at="stored cycle (feedback off)", residual=r0.tolist(), residual_norm=float(np.linalg.norm(r0)),
                variables=[bc.DECISION_NAMES[i] for i in idx], eps=list(eps), wall_time_s=time.time() - t0,
                jacobian_forward=j_fwd.tolist(), jacobian_central_differences=j_fd.tolist(), relative_error=rel)


def eigen(args) -> dict:
    from hyqjax.bounding import cycle as bc
    from hyqjax.bounding import batch as bbatch
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import plots
    from hyqjax.bounding import stability as bst

    u = bc.stored_cycle()
    pf = bc.with_cycle(bp.paper_params(), jnp.asarray(u, jnp.float32))
    s = np.asarray(bc.apex_state(jnp.asarray(u, jnp.float32)))
    configs = dict(none=bst.with_feedback(pf, False), stance=bst.with_feedback(pf, False, True), stance_apex=pf)
    t0 = time.time()
    p_out, a_all, b_all = jax.jit(jax.vmap(lambda q: bst.linearise(q, jnp.asarray(s), period=0.4)))(
        bbatch.stack_params(list(configs.values())))
    wall = time.time() - t0
    a_all, b_all, p_out = np.asarray(a_all), np.asarray(b_all), np.asarray(p_out)
    eigs = {k: np.linalg.eigvals(a) for k, a in zip(configs, a_all)}
    # Linear model of the apex impulse terms only (the B8 placement correction is not an amplitude, so
    # A_stance + B K differs from the direct Jacobian with the apex feedback on).
    kp = bst.feedback_matrix(pf)
    pred = np.linalg.eigvals(a_all[1] + b_all[1] @ kp)
    eigs_aug = np.linalg.eigvals(bst.augmented_matrix(a_all[2], b_all[2], pf))
    names = dict(none="no feedback (feed-forward impulses)", stance="stance PD (Eq. B7)",
                 stance_apex="stance PD + apex feedback (B4, B5, B8)")
    fig = plots.eigenvalue_figure({names[k]: v for k, v in eigs.items()} | {"+ integrators (augmented)": eigs_aug},
                                  os.path.join(args.out, f"bounding_eigenvalues{args.suffix}.png"))
    return dict(state=list(bp.APEX_NAMES), s_star=s.tolist(), wall_time_s=wall,
                fixed_point_residual={k: ((p_out[i] - s) / bc.RESIDUAL_SCALE).tolist() for i, k in enumerate(configs)},
                eigenvalues={k: _eig_list(v) for k, v in eigs.items()},
                spectral_radius={k: float(np.max(np.abs(v))) for k, v in eigs.items()},
                eigenvalues_A_stance_plus_BK_impulse_terms_only=_eig_list(pred),
                spectral_radius_A_stance_plus_BK_impulse_terms_only=float(np.max(np.abs(pred))),
                eigenvalues_with_integrators=_eig_list(eigs_aug),
                spectral_radius_with_integrators=float(np.max(np.abs(eigs_aug))),
                A=a_all.tolist(), B=b_all.tolist(), feedback_matrix=kp.tolist(), figures=[fig])


def _closed_loop(args, groups_spec: list) -> tuple[dict, dict, dict]:
    """Run ``[(name, plist, make_batch kwargs)]`` as one compiled batch; per-group aggregates and instances."""
    from hyqjax.bounding import batch as bbatch
    from hyqjax.bounding import rollout as brollout
    from hyqjax.bounding import summary as bs

    batches, idx = [], {}
    for name, plist, kw in groups_spec:
        start = sum(len(b.apex0) for b in batches)
        batches.append(bbatch.make_batch(plist, seed=args.seed, **kw))
        idx[name] = list(range(start, start + len(plist)))
    batch = bbatch.concat_batches(batches)
    t0 = time.time()
    res, trace = brollout.run(batch, duration=args.duration)
    wall = time.time() - t0
    inst = bs.summarise(res, trace, batch).instances
    agg = {g: bs.aggregate([inst[i] for i in ii]) for g, ii in idx.items()}
    run = dict(duration=args.duration, instances_per_group=args.instances, batch=len(inst), wall_time_s=wall,
               instances={g: [inst[i].to_dict() for i in ii] for g, ii in idx.items()})
    return agg, run, dict(trace=trace, idx=idx, inst=inst)


def turning(args) -> dict:
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import plots
    from hyqjax.bounding import summary as bs

    n, v, w = args.instances, args.turn_speed, args.turn_rate
    abl = (("full", True, True), ("no_kinematic_adjustment", False, True), ("no_centrifugal", True, False),
           ("neither", False, False))
    spec = []
    for sgn, side in ((1, "L"), (-1, "R")):
        for name, kin, cf in abl:
            spec.append((f"turn{side}_{name}", [bp.paper_params(speed=v, yaw_rate=sgn * w, kinematic_adjustment=kin,
                                                                  centrifugal=cf)] * n, {}))
        for name, lin, ang in (("no_kinematic_linear", False, True), ("no_kinematic_angular", True, False)):
            p = bp.paper_params(speed=v, yaw_rate=sgn * w)
            p = p.replace(switches=bp.Switches.make(kinematic_linear=lin, kinematic_angular=ang))
            spec.append((f"turn{side}_{name}", [p] * n, {}))
        spec.append((f"turn{side}_rate_only_paper", [bp.paper_params(speed=v, yaw_rate=sgn * w, k_yaw=0.0)] * n, {}))
    agg, run, raw = _closed_loop(args, spec)
    inst, idx = raw["inst"], raw["idx"]
    names = [a[0] for a in abl] + ["no_kinematic_linear", "no_kinematic_angular", "rate_only_paper"]
    both = {k: bs.aggregate([inst[i] for s in "LR" for i in idx[f"turn{s}_{k}"]]) for k in names}
    contrib = bs.contributions({k: dict(aggregate=both[k]) for k, _, _ in abl})
    f = plots.tracking_figures(raw["trace"], {"turn L, full": idx["turnL_full"], "turn R, full": idx["turnR_full"],
                                              "turn L, neither": idx["turnL_neither"]}, args.out,
                               prefix=f"bounding_turning{args.suffix}_")
    labels = [a[0] for a in abl]
    x10 = lambda k, key: None if both[k][key] is None else 10 * both[k][key]  # noqa: E731
    fig = plots.bar_figure(
        labels, {"yaw error max [deg]": [both[k]["yaw_error_max_deg_mean"] for k in labels],
                 "yaw-rate err rms x10 [rad/s]": [x10(k, "yaw_rate_error_rms_mean") for k in labels],
                 "speed err rms x10 [m/s]": [x10(k, "speed_error_rms_mean") for k in labels],
                 "side slip x10 [m/s]": [x10(k, "side_slip_mean") for k in labels],
                 "falls": [both[k]["falls"] for k in labels]},
        "value", os.path.join(args.out, f"bounding_turning{args.suffix}_ablation.png"),
        f"Turning at {v} m/s, +-{w} rad/s: contribution of each part")
    return dict(turn=dict(speed=v, yaw_rate=w), both_directions=both, contributions=contrib, groups=agg, run=run,
                figures=[f["yaw_tracking"], f["speed_tracking"], fig])


def speed(args) -> dict:
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import plots

    speeds = (0.0, 0.25, 0.5, 0.75, 1.0)
    spec = [(f"speed_{v:g}", [bp.paper_params(speed=v)] * args.instances, {}) for v in speeds]
    agg, run, raw = _closed_loop(args, spec)
    f = plots.tracking_figures(raw["trace"], {f"{v:g} m/s": raw["idx"][f"speed_{v:g}"] for v in speeds}, args.out,
                               prefix=f"bounding_speed{args.suffix}_")
    measured = {g: [p["speed_mean"] for p in run["instances"][g]] for g in agg}
    return dict(groups=agg, speed_mean=measured, run=run, figures=[f["speed_tracking"], f["yaw_tracking"]])


def robustness(args) -> dict:
    from hyqjax.bounding import batch as bbatch
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import plots

    n, p = args.instances, bp.paper_params(speed=0.5)
    pushes = (0.0, 150.0, 300.0, 450.0)
    spec = [(f"push_{f:g}N", [p] * n, dict(push_force=f, push_time=3.0, push_duration=0.1)) for f in pushes]
    spec += [("friction_0.4-0.5", [p] * n, dict(rand=bbatch.Randomisation(friction=(0.4, 0.5)))),
             ("payload_10-15kg", [p] * n, dict(rand=bbatch.Randomisation(payload=(10.0, 15.0))))]
    agg, run, _ = _closed_loop(args, spec)
    rob = list(agg)
    x10 = lambda g: None if agg[g]["speed_error_rms_mean"] is None else 10 * agg[g]["speed_error_rms_mean"]  # noqa
    fig = plots.bar_figure(rob, {"falls": [agg[g]["falls"] for g in rob],
                                 "yaw error max [deg]": [agg[g]["yaw_error_max_deg_mean"] for g in rob],
                                 "speed err rms x10 [m/s]": [x10(g) for g in rob]},
                           "value", os.path.join(args.out, f"bounding_robustness{args.suffix}.png"),
                           "Robustness at 0.5 m/s (lateral push at t = 3 s for 0.1 s)")
    return dict(groups=agg, run=run, figures=[fig])


def _host() -> dict:
    import platform

    cpu = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return dict(cpu=cpu, cpu_count=os.cpu_count(), load_average=list(os.getloadavg()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.bounding_figures", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("figure", choices=FIGURES + ("all",))
    ap.add_argument("--out", default="docs/results", help="output directory (default: docs/results)")
    ap.add_argument("--guesses", type=int, default=8, help="optimise: initial guesses")
    ap.add_argument("--iterations", type=int, default=11, help="optimise: Levenberg-Marquardt steps")
    ap.add_argument("--write-cycle", metavar="PATH", help="optimise: write the best cycle to this cycle file")
    ap.add_argument("--instances", type=int, default=3, help="closed loop: instances per group")
    ap.add_argument("--duration", type=float, default=6.0, help="closed loop: simulated time (s)")
    ap.add_argument("--turn-speed", type=float, default=0.9)
    ap.add_argument("--turn-rate", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--suffix", default="", help="appended to the output names (e.g. _fast for a second turning run)")
    args = ap.parse_args(argv)
    try:
        from hyqjax.bounding import batch as bbatch

        bbatch.validate_run(speed=args.turn_speed, yaw_rate=args.turn_rate, instances=args.instances,
                            duration=args.duration, seed=args.seed)
        if not (1 <= args.guesses <= 4096 and 1 <= args.iterations <= 10000):
            raise ValueError("--guesses must be in [1, 4096] and --iterations in [1, 10000]")
        if not all(c.isalnum() or c in "._-" for c in args.suffix):
            raise ValueError(f"--suffix may hold letters, digits, '.', '_' and '-' only, got {args.suffix!r}")
    except ValueError as e:
        name = getattr(e, "name", None)
        opt = dict(speed="turn-speed", yaw_rate="turn-rate").get(name, (name or "").replace("_", "-"))
        print(f"error: --{opt}: {e}" if name else f"error: {e}", file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    from hyqjax.io import atomic as io

    for name in FIGURES if args.figure == "all" else (args.figure,):
        t0 = time.time()
        out = globals()[name](args)
        prov = io.provenance(seed=args.seed) | dict(host=_host())
        prov["command"] = " ".join(["python -m experiments.bounding_figures", name] +
                                   [a for a in (argv if argv is not None else sys.argv[1:]) if a not in FIGURES + ("all",)])
        out = dict(provenance=prov, args={k: v for k, v in vars(args).items() if k != "figure"},
                   total_wall_time_s=time.time() - t0, **out)
        path = os.path.join(args.out, f"bounding_{name}{args.suffix}.json")
        io.write_json(path, out)
        print(f"{name}: wrote {path} ({out['total_wall_time_s']:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
