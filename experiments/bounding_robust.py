"""Robust bounding baseline: envelope before, gradient optimisation, CMA-ES at equal wall-clock, held-out
evaluation, envelope after. One command, every stage written as it finishes:

    python -m experiments.bounding_robust --out docs/results/bounding_robust --impl warp

Stages (``OUT/results.json`` after each; a rerun of the same command on the same directory keeps the finished
stages and reruns the others):

1. ``envelope_before``: the command map (:mod:`experiments.bounding_envelope`) of the paper's gains (preset
   ``bound_paper``, the study's start point);
2. ``gradient``: Adam with a batched line search on the training cost (:mod:`hyqjax.bounding.robust`; forward-mode
   Jacobian through MJX under its JAX implementation) over ``--train`` instances of ``--train-duration`` s, until
   ``--opt-seconds`` of wall-clock have passed (compiles included);
3. ``cma_es``: evosax CMA-ES on the same training instances and cost, forward runs under ``--cma-impl``, for the
   wall-clock the gradient took (compiles included);
4. ``heldout``: the default, the gradient's and CMA-ES's parameters on ``--heldout`` instances (commands and
   seeds not used in optimisation: ``--heldout-seed``), ``--heldout-duration`` s each; and each method's best
   parameters at 25 / 50 / 100% of the wall-clock and CMA-ES's final mean on ``--curve-instances`` other held-out
   instances (the budget curve);
5. ``envelope_after``: the map with the gradient's parameters.

Writes ``OUT/results.json``, ``OUT/params_gradient.json``, ``OUT/params_cma_es.json`` (for ``--params``),
``OUT/envelope_before.{json,png}``, ``OUT/envelope_after.{json,png}``, ``OUT/envelope_before_after.png``,
``OUT/budget_curve.png`` and the Adam log under ``OUT/gradient/``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import time

import numpy as np

STAGES = ("envelope_before", "gradient", "cma_es", "heldout", "envelope_after")
CURVE_FRACTIONS = (0.25, 0.5, 1.0)


def parse(argv):
    from experiments import bounding_envelope as be

    ap = argparse.ArgumentParser(prog="python -m experiments.bounding_robust", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/results/bounding_robust")
    ap.add_argument("--impl", default="auto", help="MJX implementation of the forward maps: auto | jax | warp")
    ap.add_argument("--cma-impl", default=None, help="CMA-ES's forward runs (default: --impl)")
    ap.add_argument("--stages", nargs="+", default=list(STAGES), choices=STAGES)
    ap.add_argument("--seed", type=int, default=0, help="seed of the training instances and the optimisers")
    # training
    ap.add_argument("--train", type=int, default=128, help="training instances")
    ap.add_argument("--train-duration", type=float, default=8.0,
                    help="training rollout (s), a multiple of 0.4 (8 s: as long as the held-out runs; 3.2 s "
                         "overfit the training horizon, docs/bounding.md)")
    ap.add_argument("--train-speed", type=float, nargs=2, default=(0.0, 1.1), metavar=("LO", "HI"))
    ap.add_argument("--train-yaw-rate", type=float, nargs=2, default=(-0.9, 0.9), metavar=("LO", "HI"))
    ap.add_argument("--train-lateral", type=float, nargs=2, default=(-0.2, 0.2), metavar=("LO", "HI"))
    ap.add_argument("--train-friction", type=float, nargs=2, default=(0.4, 1.0), metavar=("LO", "HI"))
    ap.add_argument("--train-payload", type=float, nargs=2, default=(0.0, 12.0), metavar=("LO", "HI"))
    ap.add_argument("--opt-seconds", type=float, default=270.0,
                    help="gradient wall-clock limit (s, compiles included); CMA-ES gets what the gradient took")
    ap.add_argument("--lr", type=float, default=0.15, help="Adam step (theta units: one unit = a coordinate's scale)")
    ap.add_argument("--line-search", type=float, nargs="*", default=(0.5, 1.0, 2.0), help="line-search scales")
    ap.add_argument("--max-steps", type=int, default=500, help="upper bound on gradient steps")
    ap.add_argument("--popsize", type=int, default=32,
                    help="CMA-ES population (x --train instances per generation: 4,096 by default, the held-out shape)")
    ap.add_argument("--sigma", type=float, default=0.3, help="CMA-ES initial step (theta units)")
    # held-out
    ap.add_argument("--heldout", type=int, default=4096, help="held-out instances")
    ap.add_argument("--heldout-seed", type=int, default=7777)
    ap.add_argument("--heldout-duration", type=float, default=8.0)
    ap.add_argument("--heldout-speed", type=float, nargs=2, default=(0.0, 1.0), metavar=("LO", "HI"))
    ap.add_argument("--heldout-yaw-rate", type=float, nargs=2, default=(-0.8, 0.8), metavar=("LO", "HI"))
    ap.add_argument("--heldout-lateral", type=float, nargs=2, default=(0.0, 0.0), metavar=("LO", "HI"))
    ap.add_argument("--heldout-friction", type=float, nargs=2, default=(0.5, 1.0), metavar=("LO", "HI"))
    ap.add_argument("--heldout-payload", type=float, nargs=2, default=(0.0, 10.0), metavar=("LO", "HI"))
    ap.add_argument("--curve-instances", type=int, default=512, help="held-out instances per budget-curve point")
    # envelope
    be.add_arguments(ap)
    ap.set_defaults(lateral_speeds=(-0.3, 0.0, 0.3), instances=64)
    ap.add_argument("--envelope-seed", type=int, default=1)
    return ap.parse_args(argv)


def check(args):
    """Every option checked before anything compiles (ValueError naming the option)."""
    from experiments import bounding_envelope as be
    from hyqjax.bounding import robust
    from hyqjax.bounding.batch import SettingError
    from hyqjax.sim import backend

    args.cma_impl = args.cma_impl or args.impl
    for opt in ("impl", "cma_impl"):
        try:
            backend.validate_impl(getattr(args, opt))
        except ValueError as e:
            raise SettingError(opt, str(e)) from None
    for opt in ("train_duration", "heldout_duration", "duration"):
        try:
            be.check_duration(getattr(args, opt))
        except SettingError as e:
            raise SettingError(opt, str(e).replace("--duration", "--" + opt.replace("_", "-"))) from None
    for opt, lo, hi in (("train", 1, 65536), ("heldout", 1, 1 << 20), ("curve_instances", 1, 1 << 20),
                        ("popsize", 4, 4096), ("max_steps", 1, 100000)):
        v = getattr(args, opt)
        if not lo <= v <= hi:
            raise SettingError(opt, f"--{opt.replace('_', '-')} must be an int in [{lo}, {hi}], got {v}")
    for opt, lo, hi in (("opt_seconds", 1.0, 86400.0), ("lr", 1e-4, 10.0), ("sigma", 1e-3, 10.0)):
        v = getattr(args, opt)
        if not (np.isfinite(v) and lo <= v <= hi):
            raise SettingError(opt, f"--{opt.replace('_', '-')} must be in [{lo:g}, {hi:g}], got {v}")
    if any(not (0 < c <= 10) for c in args.line_search) or len(args.line_search) > 16:
        raise SettingError("line_search", f"--line-search must be at most 16 scales in (0, 10], got {args.line_search}")
    for pre in ("train", "heldout"):
        try:
            draw(args, pre)
        except ValueError as e:
            name = getattr(e, "name", "")
            raise SettingError(f"{pre}_{name}", str(e).replace(name, f"--{pre}-{name.replace('_', '-')}", 1)) from None
    be.spec_of(args)
    robust.RobustSpace.make()


def draw(args, pre):
    from hyqjax.bounding import robust

    g = lambda k: tuple(getattr(args, f"{pre}_{k}"))  # noqa: E731
    return robust.Draw(speed=g("speed"), yaw_rate=g("yaw_rate"), lateral=g("lateral"), friction=g("friction"),
                       payload=g("payload"))


def config_of(args) -> dict:
    d = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items() if k not in ("stages", "out")}
    return json.loads(json.dumps(d))


def save_heldout_instances(path: str, batch, cols: dict) -> str:
    """Every held-out instance of one parameter set, one row each, to ``path`` (NumPy ``.npz``, written
    atomically): its command (``speed_cmd``, ``lateral_cmd``, ``yaw_rate_cmd``), ``friction``, ``payload`` and
    every outcome column of the run (``success``, the fall reasons, ``yaw_error_max_deg``, ``cost``, ...), so a fall
    of the summary can be traced to the instance that fell. Returns the file's name."""
    from hyqjax.io import atomic

    cmd = batch.params.command
    rows = dict(speed_cmd=np.asarray(cmd.velocity)[:, 0], lateral_cmd=np.asarray(cmd.velocity)[:, 1],
                yaw_rate_cmd=np.asarray(cmd.yaw_rate), friction=np.asarray(batch.terrain.friction),
                payload=np.asarray(batch.terrain.payload_mass))
    n = rows["speed_cmd"].shape[0]
    rows.update({k: np.asarray(v) for k, v in cols.items() if np.ndim(v) >= 1 and np.shape(v)[0] == n})
    atomic.atomic_write(path, lambda f: np.savez_compressed(f, **rows))
    return os.path.basename(path)


def main(argv=None) -> int:
    args = parse(argv)
    try:
        check(args)
    except ValueError as e:
        name = getattr(e, "name", None)
        print(f"error: --{name.replace('_', '-')}: {e}" if name else f"error: {e}", file=sys.stderr)
        return 2
    from hyqjax.sim import backend

    args.impl, args.cma_impl = backend.resolve_impl(args.impl), backend.resolve_impl(args.cma_impl)
    os.makedirs(args.out, exist_ok=True)
    run(args)
    return 0


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def run(args) -> dict:
    import jax
    import jax.numpy as jnp

    from experiments import bounding_envelope as be
    from hyqjax.bounding import envelope, robust, tracking
    from hyqjax.io import atomic
    from hyqjax.studies.tune import optimize

    out = args.out
    path = os.path.join(out, "results.json")
    cfg = config_of(args)
    res = {}
    if os.path.exists(path):
        try:
            with open(path) as f:
                prev = json.load(f)
            if prev.get("config") == cfg:
                res = prev
        except (OSError, ValueError):
            pass
    command = " ".join(["python -m experiments.bounding_robust", *sys.argv[1:]])
    res.update(config=cfg, provenance=dict(atomic.provenance(seed=args.seed), command=command),
               device=str(jax.devices()[0].device_kind))
    res.setdefault("stages_done", [])

    def save():
        atomic.write_json(path, res)

    def done(stage):
        if stage not in res["stages_done"]:
            res["stages_done"].append(stage)
        save()

    space = robust.RobustSpace.make()
    spec = be.spec_of(args)
    spec = dataclasses.replace(spec, seed=args.envelope_seed)
    train = draw(args, "train").batch(args.train, seed=args.seed)
    n_tan = space.size
    res["space"] = dict(names=list(space.names), start=list(space.start),
                        scale=[c[1] for c in robust.COORDS if c[0] in space.names])
    res["training"] = dict(instances=args.train, duration=args.train_duration, seed=args.seed,
                           step_physics_steps=robust.physics_steps(args.train, args.train_duration, n_tan)
                           + len(args.line_search) * robust.physics_steps(args.train, args.train_duration),
                           candidate_physics_steps=robust.physics_steps(args.train, args.train_duration))
    save()
    want = set(args.stages)

    # 1. envelope before
    if "envelope_before" in want and "envelope_before" not in res["stages_done"]:
        log("stage envelope_before")
        r = be.run_map(spec, robust.paper_params(), args.impl, args.max_batch, "envelope_before", out, log, command)
        res["envelope_before"] = dict(overall=r["overall"], safe_area=r["safe_area"], wall_time_s=r["wall_time_s"],
                                      file="envelope_before.json")
        done("envelope_before")

    # 2. gradient
    if "gradient" in want and "gradient" not in res["stages_done"]:
        log(f"stage gradient: {args.train} instances x {args.train_duration:g} s, {n_tan} tangents, "
            f"limit {args.opt_seconds:g} s")
        gdir = os.path.join(out, "gradient")
        shutil.rmtree(gdir, ignore_errors=True)  # a stage cut off earlier restarts (its wall-clock is the budget)
        t0 = time.time()
        vj = robust.make_value_and_jac(space, args.train_duration, tracking.CostSpec())
        targs = robust.instance_args(train)

        def step_fn(th):
            r = vj(jnp.asarray(th, jnp.float32), targs)
            loss = np.asarray(r["per_instance_loss"], np.float64)
            return dict(loss=float(np.mean(np.where(np.isfinite(loss), loss, np.inf))), grad=r["grad"],
                        per_window_grad=r["per_instance_grad"], ok=r["ok"],
                        terms=dict({k: float(v) for k, v in r["terms"].items()}, falls=float(r["falls"]),
                                   diverged=float(r["diverged"]), clipped=float(r["clipped"]),
                                   ok=float(np.sum(np.asarray(r["ok"])))))

        def evaluate(ths):
            return robust.population_cost(space, np.asarray(ths), train, args.train_duration, "jax")[0]

        acfg = optimize.AdamConfig(steps=args.max_steps, lr=args.lr, clip=1.0, checkpoint_every=1,
                                   line_search=tuple(args.line_search))
        iterates = [dict(step=0, wall_s=0.0, theta=[0.0] * n_tan)]
        step = 0
        while step < args.max_steps and time.time() - t0 < args.opt_seconds:
            r = optimize.run_adam(step_fn, jnp.zeros(n_tan, jnp.float32), acfg, gdir,
                                  dict(kind="bounding_robust", config=cfg), res["training"]["step_physics_steps"],
                                  space.describe, stop_after=1, progress=False, evaluate=evaluate)
            step = r["step"]
            rec = r["log"][-1]
            ls = rec.get("line_search", {})
            after = min([v for v in ls.get("losses", []) if v is not None] + [rec["loss"]]) if ls.get("chosen") \
                else rec["loss"]
            iterates.append(dict(step=step, wall_s=round(time.time() - t0, 3), theta=np.asarray(r["theta"]).tolist(),
                                 loss_before=rec["loss"], loss_after=after, terms=rec["terms"],
                                 chosen=ls.get("chosen")))
            terms = json.dumps({k: round(v, 3) for k, v in rec["terms"].items()})
            log(f"gradient step {step}: loss {rec['loss']:.4f} -> {after:.4f} (terms {terms}), "
                f"line search {rec.get('line_search', {}).get('chosen')}, {time.time() - t0:.0f} s")
        theta = np.asarray(iterates[-1]["theta"])
        wall = time.time() - t0
        res["gradient"] = dict(theta=theta.tolist(), params=space.describe(theta), steps=step, wall_s=wall,
                               physics_steps=step * res["training"]["step_physics_steps"], iterates=iterates,
                               train_loss=[it.get("loss_before") for it in iterates[1:]])
        robust.save_params(os.path.join(out, "params_gradient.json"), space.describe(theta),
                           dict(method="gradient (jacfwd, Adam + line search)", steps=step, wall_s=wall,
                                command=command))
        done("gradient")

    # 3. CMA-ES at the gradient's wall-clock
    if "cma_es" in want and "cma_es" not in res["stages_done"]:
        wall = res.get("gradient", {}).get("wall_s", args.opt_seconds)
        log(f"stage cma_es: popsize {args.popsize}, impl {args.cma_impl}, wall-clock {wall:.0f} s")
        t0 = time.time()
        cost = robust.physics_steps(args.train, args.train_duration)
        out_c = robust.cma_es(lambda xs: robust.population_cost(space, xs, train, args.train_duration,
                                                                 args.cma_impl, max_batch=args.max_batch)[0],
                              np.zeros(n_tan), wall, args.popsize, args.sigma, args.seed,
                              cost_per_candidate=cost, log=log)
        theta = out_c["theta"]
        res["cma_es"] = dict(theta=np.asarray(theta).tolist(), params=space.describe(theta), value=out_c["value"],
                             mean=np.asarray(out_c["mean"]).tolist(), mean_params=space.describe(out_c["mean"]),
                             generations=out_c["generations"], popsize=args.popsize, impl=args.cma_impl,
                             wall_s=time.time() - t0, physics_steps=out_c["budget_spent"],
                             history=out_c["history"])
        robust.save_params(os.path.join(out, "params_cma_es.json"), space.describe(theta),
                           dict(method=f"CMA-ES (evosax), impl {args.cma_impl}", wall_s=time.time() - t0,
                                command=command))
        done("cma_es")

    # 4. held-out
    if "heldout" in want and "heldout" not in res["stages_done"]:
        log("stage heldout")
        ho_draw = draw(args, "heldout")
        ho = ho_draw.batch(args.heldout, seed=args.heldout_seed)
        methods = {"default": np.zeros(n_tan)}
        for m in ("gradient", "cma_es"):
            if m in res:
                methods[m] = np.asarray(res[m]["theta"])
        t0 = time.time()
        res["heldout"] = dict(instances=args.heldout, seed=args.heldout_seed, duration=args.heldout_duration,
                              draw=dataclasses.asdict(ho_draw), methods={})
        for m, th in methods.items():
            _, cols = robust.population_cost(space, th[None], ho, args.heldout_duration, args.impl,
                                             max_batch=args.max_batch)
            s = envelope.group_summary(dict(cols, speed_cmd=np.asarray(ho.params.command.velocity)[:, 0],
                                            lateral_cmd=np.asarray(ho.params.command.velocity)[:, 1]))
            s["cost_mean"] = float(np.mean(cols["cost"]))
            worst = s["yaw_error_worst_deg"]
            s["target_met"] = bool(s["failures"] == 0 and worst is not None and worst < envelope.YAW_LIMIT_DEG)
            res["heldout"]["methods"][m] = s
            res["heldout"]["methods"][m]["instances_file"] = save_heldout_instances(
                os.path.join(args.out, f"heldout_{m}.npz"), ho, cols)
            log(f"held-out {m}: failures {s['failures']}/{s['n']} {s['reasons']}, worst yaw "
                f"{s['yaw_error_worst_deg']}, "
                f"> 4 deg {s['yaw_over_4deg']}, cost {s['cost_mean']:.3f}")
        # the budget curve: each method's best parameters at fractions of the common wall-clock, on a subset
        curve = []
        if "gradient" in res and "cma_es" in res:
            wall = res["gradient"]["wall_s"]
            pts = [("start", 0.0, np.zeros(n_tan))]
            for f in CURVE_FRACTIONS:
                its = [it for it in res["gradient"]["iterates"] if it["wall_s"] <= f * wall + 1e-6]
                pts.append(("gradient", f, np.asarray(its[-1]["theta"])))
                hs = [h for h in res["cma_es"]["history"] if h["wall_s"] <= f * wall + 1e-6]
                pts.append(("cma_es", f, np.asarray(hs[-1]["theta"]) if hs else np.zeros(n_tan)))
            pts.append(("cma_es_mean", 1.0, np.asarray(res["cma_es"]["mean"])))  # 8 points x 512: the held-out shape
            sub = ho_draw.batch(args.curve_instances, seed=args.heldout_seed + 1)
            _, cols = robust.population_cost(space, np.stack([p[2] for p in pts]), sub, args.heldout_duration,
                                             args.impl, max_batch=args.max_batch)
            k = args.curve_instances
            for i, (m, f, th) in enumerate(pts):
                mask = np.zeros(len(cols["success"]), bool)
                mask[i * k:(i + 1) * k] = True
                s = envelope.group_summary(cols, mask)
                curve.append(dict(method=m, fraction=f, wall_s=f * wall, n=s["n"], failures=s["failures"],
                                  fall_rate_ci95=s["fall_rate_ci95"], yaw_error_worst_deg=s["yaw_error_worst_deg"],
                                  yaw_over_4deg=s["yaw_over_4deg"], cost_mean=float(np.mean(cols["cost"][mask]))))
            res["budget_curve"] = curve
            res["budget_curve_figure"] = budget_figure(res, os.path.join(out, "budget_curve.png"))
        res["heldout"]["wall_s"] = time.time() - t0
        done("heldout")

    # 5. envelope after
    if "envelope_after" in want and "envelope_after" not in res["stages_done"] and "gradient" in res:
        log("stage envelope_after")
        base = robust.params_from_values(res["gradient"]["params"])
        r = be.run_map(spec, base, args.impl, args.max_batch, "envelope_after", out, log, command)
        res["envelope_after"] = dict(overall=r["overall"], safe_area=r["safe_area"], wall_time_s=r["wall_time_s"],
                                     file="envelope_after.json", params="params_gradient.json")
        if os.path.exists(os.path.join(out, "envelope_before.json")):
            with open(os.path.join(out, "envelope_before.json")) as f:
                before = json.load(f)["per_command"]
            res["envelope_figure"] = envelope.figure(spec, {"default": before, "gradient": r["per_command"]},
                                                     os.path.join(out, "envelope_before_after.png"))
        done("envelope_after")
    log(f"done: {path}")
    return res


def budget_figure(res: dict, path: str) -> str:
    """Training cost against wall-clock (gradient iterates, CMA-ES best so far) and held-out cost / failures at
    the curve points."""
    from hyqjax.bounding import plots

    plt = plots._plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    g = res["gradient"]["iterates"]
    ax[0].plot([it["wall_s"] for it in g[1:]], [it["loss_after"] for it in g[1:]], "o-", ms=3,
               label="gradient (after each step)")
    h = res["cma_es"]["history"]
    ax[0].plot([x["wall_s"] for x in h], [x["best"] for x in h], "-", label="CMA-ES (best so far)")
    ax[0].set_xlabel("wall-clock [s] (compiles included)")
    ax[0].set_ylabel("training cost")
    ax[0].set_yscale("log")
    ax[0].legend(fontsize=8)
    for m in ("gradient", "cma_es"):
        pts = [p for p in res["budget_curve"] if p["method"] in (m, "start")]
        ax[1].plot([p["wall_s"] for p in pts], [p["cost_mean"] for p in pts], "o-", label=f"{m}: held-out cost")
    ax[1].set_xlabel("wall-clock [s]")
    ax[1].set_ylabel("held-out cost (subset)")
    ax[1].legend(fontsize=8)
    fig.suptitle("Robust bounding baseline: cost against wall-clock")
    return plots._save(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
