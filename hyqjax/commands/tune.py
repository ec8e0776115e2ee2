"""Gradient tuning of the height reflex (K_base, damping bounds, mobility thresholds; optionally K_x, K_kl,
Delta) on randomised kinematic step-down searches (hyqjax.tune), then an evaluation against Table I and
a random-search baseline given the same budget in primal evaluations: held-out kinematic scenarios
(another seed, wider depth range) and the closed-loop MJX step-down with the reflex on.

DIR holds config.json, log.jsonl (loss, terms, grad norm and parameters of every step),
checkpoint.npz (every --checkpoint-every steps, atomic), results.json and tuning.png (loss curves
and parameter trajectories). Running the same command again resumes from the checkpoint; a larger
--steps continues the run.
"""
from __future__ import annotations

import argparse
import math
import os
import time

NAME = "tune"
HELP = "tune the height reflex parameters by gradient descent through the kinematic reflex rollout"
ORDER = 30


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/tune", help="run directory (resumed if it holds the same configuration)")
    p.add_argument("--steps", type=int, default=40, help="optimiser steps (total, across resumes)")
    p.add_argument("--batch", type=int, default=16, help="training scenarios")
    p.add_argument("--seed", type=int, default=0, help="training-set seed")
    p.add_argument("--lr", type=float, default=0.05, help="Adam learning rate (unconstrained parameters)")
    p.add_argument("--groups", default="k_base,damping,mobility",
                   help="tuned groups, comma-separated, from k_base, damping, mobility, k_x, k_kl, delta")
    p.add_argument("--checkpoint-every", type=int, default=5, help="checkpoint period (steps)")
    p.add_argument("--heldout", type=int, default=64, help="held-out kinematic scenarios")
    p.add_argument("--heldout-seed", type=int, default=1000, help="held-out seed (never used for training)")
    p.add_argument("--heldout-depth", type=float, nargs=2, default=[0.08, 0.30], help="held-out step depths (m)")
    p.add_argument("--no-baseline", action="store_true", help="skip the random-search baseline")
    p.add_argument("--mjx-heights", type=float, nargs="+", default=[0.16, 0.21, 0.24],
                   help="closed-loop evaluation heights (m)")
    p.add_argument("--mjx-instances", type=int, default=2,
                   help="closed-loop instances per height and parameter set (0: skip the MJX evaluation)")
    p.add_argument("--mjx-seed", type=int, default=2000, help="closed-loop evaluation seed")
    p.add_argument("--mjx-duration", type=float, default=18.0, help="closed-loop simulated seconds per instance")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args) -> int:
    groups = tuple(g.strip() for g in args.groups.split(",") if g.strip())
    from hyqjax import io, tune
    from hyqjax import reflex as hreflex

    if not (1 <= args.heldout <= 100000):
        raise SystemExit(f"--heldout must be in [1, 100000], got {args.heldout}")
    if not (0 <= args.mjx_instances <= 10000):
        raise SystemExit(f"--mjx-instances must be in [0, 10000], got {args.mjx_instances}")
    if any(not 0.0 <= h <= 0.45 for h in args.mjx_heights):
        raise SystemExit(f"--mjx-heights must be in [0, 0.45] m, got {args.mjx_heights}")
    try:
        cfg = tune.TuneConfig(steps=args.steps, batch=args.batch, seed=args.seed, lr=args.lr, groups=groups,
                              checkpoint_every=args.checkpoint_every)
        heldout = tune.make_scenarios(args.heldout, args.heldout_seed, depth=tuple(args.heldout_depth),
                                      speed=(0.15, 0.35), feet_jitter=0.04)
    except ValueError as e:
        raise SystemExit(f"invalid tuning setting: {e}") from None
    print(f"hyqjax tune: {cfg.steps} steps, {cfg.batch} training scenarios, groups {list(groups)}, out {args.out}",
          flush=True)
    t0 = time.time()
    try:
        res = tune.run_tune(cfg, args.out, progress=not args.no_progress)
    except RuntimeError as e:
        raise SystemExit(str(e)) from None
    t_tune = time.time() - t0
    log = tune.read_log(args.out)
    print(f"tuned in {t_tune:.1f} s: loss {log[0]['loss']:.4f} -> {log[-1]['loss']:.4f}" if log else "no steps")
    table1 = hreflex.ReflexParams.table1()
    params = {"table1": table1, "tuned": res["params"]}
    cost = tune.measure_cost(cfg)
    budget = max(1, math.ceil(cfg.steps * cost["grad_cost"]))
    baseline = None
    if not args.no_baseline:
        print(f"random search with the same budget: {cfg.steps} gradient steps x {cost['grad_cost']:.2f} = "
              f"{budget} primal evaluations", flush=True)
        baseline = tune.random_search(cfg, budget, seed=cfg.seed + 1)
        params["random_search"] = baseline["params"]
    kin = tune.evaluate_kinematic(params, heldout, cfg.objective)
    for name, r in kin.items():
        print(f"held-out kinematic {name:>13}: loss {r['loss']:+.4f}, reach {r['reach_rate']:.2f} "
              f"[{r['reach_ci95'][0]:.2f}, {r['reach_ci95'][1]:.2f}], m_bar {r['m_bar']:.3f} "
              f"[{r['m_bar_ci95'][0]:.3f}, {r['m_bar_ci95'][1]:.3f}], lowering {r['terms']['lowering'] * 100:.1f} cm")
    mjx = None
    if args.mjx_instances:
        print(f"closed-loop MJX step-down: {len(args.mjx_heights)} heights x {args.mjx_instances} instances x "
              f"{len(params)} parameter sets (compiling...)", flush=True)
        mjx = tune.evaluate_mjx(params, args.mjx_heights, args.mjx_instances, args.mjx_seed, args.mjx_duration)
        for name in params:
            r = mjx[name]
            h95 = r["h95_wilson"]
            print(f"MJX {name:>13}: success {r['success']}/{r['n']} [{r['ci95'][0]:.2f}, {r['ci95'][1]:.2f}], "
                  f"mean mobility {r['mean_mobility']:.3f}, h95 {'-' if h95 is None else f'{h95:.2f} m'}")
    fig = tune.plot_run(log, os.path.join(args.out, "tuning.png"), baseline["curve"] if baseline else None,
                        cost["grad_cost"])
    io.write_json(os.path.join(args.out, "results.json"), dict(
        provenance=io.provenance(seed=cfg.seed), config=cfg.to_dict(), tune_wall_s=t_tune, cost=cost,
        budget_primal_evals=budget, final_loss=log[-1]["loss"] if log else None,
        params={k: tune.reflex_values(v) for k, v in params.items()},
        random_search_loss=baseline["loss"] if baseline else None, heldout_kinematic=kin,
        heldout_config=dict(n=args.heldout, seed=args.heldout_seed, depth=args.heldout_depth),
        mjx=mjx, figures=[fig]))
    print(f"wrote {args.out}/results.json, log.jsonl, tuning.png")
    return 0
