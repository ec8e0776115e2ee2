"""The window objective's pathwise gradient, with and without contacts from distance, against the zero-order
gradient of the smoothed objective (hyqjax.studies.tune.study.bias; docs/tuning.md).

    python -m experiments.tune_gradient_bias --out bias.json                       # CPU size: 4 windows of 150 ticks
    python -m experiments.tune_gradient_bias --train-per-height 2 --windows-per-scenario 2 --window-ticks 500 \\
        --pairs 256 --out bias.json                                              # the study's 16 windows of 500 ticks

At the start point of the default tuner (Table I and the shin remedy, the 14 shared coordinates), on the snapshot
windows of the equal-wall-clock study (MJX-JAX): the exact ``jacfwd`` gradient of the window objective, the same
with the backward-only virtual springs of each ``--stiffness``, and the zero-order randomised-smoothing estimate
at each ``--sigma`` (theta units) from ``--pairs`` antithetic pairs; prints their cosines and SNRs, writes JSON.
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.tune_gradient_bias", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--train-per-height", type=int, default=1, help="snapshot scenarios per training height")
    p.add_argument("--windows-per-scenario", type=int, default=1, help="windows per scenario (legs over the edge)")
    p.add_argument("--window-ticks", type=int, default=150, help="window length (control ticks of 2 ms)")
    p.add_argument("--stiffness", type=float, nargs="*", default=[2000.0, 10000.0],
                   help="virtual spring stiffnesses (N/m) of the contacts-from-distance variants")
    p.add_argument("--reach", type=float, default=0.02, help="the virtual springs' reach (m)")
    p.add_argument("--sigma", type=float, nargs="+", default=[0.03, 0.1], help="smoothing scales (theta units)")
    p.add_argument("--pairs", type=int, default=32, help="antithetic pairs of the zero-order estimate")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="")
    a = p.parse_args(argv)
    bad = [(n, v) for n, v, lo, hi in (("--train-per-height", a.train_per_height, 1, 64),
                                       ("--windows-per-scenario", a.windows_per_scenario, 1, 8),
                                       ("--window-ticks", a.window_ticks, 1, 5000), ("--pairs", a.pairs, 2, 4096))
           if not lo <= v <= hi]
    bad += [("--stiffness", s) for s in a.stiffness if not 0.0 < s <= 1e6]
    bad += [("--sigma", s) for s in a.sigma if not 0.0 < s <= 2.0]
    if bad:
        print(f"tune_gradient_bias: {bad[0][0]} out of range: {bad[0][1]}", file=sys.stderr)
        return 2
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hyqjax.io import atomic
    from hyqjax.sim.contacts_from_distance import ContactsFromDistance
    from hyqjax.studies.tune import gradient_programs, objective, schedule, search, wallclock
    from hyqjax.studies.tune.study import bias

    t0 = time.perf_counter()
    cfg = wallclock.WallClockConfig(methods=("gradient",), dims=("shared",), grad_train_per_height=a.train_per_height,
                                    windows_per_scenario=a.windows_per_scenario, window_ticks=a.window_ticks,
                                    seed=a.seed)
    base = wallclock.start_params(cfg)
    grad = gradient_programs.GradientPrograms(cfg, base, search.Charges(), print)
    param = schedule.make("shared", cfg.groups)
    theta = np.asarray(param.theta_of(base), np.float64)
    th32 = jnp.asarray(theta, jnp.float32)
    variants = {"plain": ContactsFromDistance()}
    variants.update({f"contacts from distance, k {s:g}": ContactsFromDistance(stiffness=s, reach=a.reach)
                     for s in a.stiffness})
    pathwise, timing = {}, {}
    for name, cfd in variants.items():
        obj = objective.ClosedLoopObjective(ticks=a.window_ticks, contacts_from_distance=cfd)
        fn = objective.make_value_and_jac(grad.win, base, param, obj, grad.su)
        t = time.perf_counter()
        r = jax.block_until_ready(fn(th32, grad.win))
        timing[name] = time.perf_counter() - t
        pathwise[name] = jax.tree_util.tree_map(np.asarray, r)
        print(f"{name}: loss {float(r['loss']):.4f}, |grad| {float(jnp.linalg.norm(r['grad'])):.4g} "
              f"({timing[name]:.1f} s incl. compile)", flush=True)
    value = objective.make_value(base, param, grad.obj, grad.su)
    zero_order = {}
    for k, s in enumerate(a.sigma):
        t = time.perf_counter()
        zero_order[s] = bias.smoothed_gradient(lambda ts: value(ts, grad.win), theta, s, a.pairs,
                                               jax.random.key(a.seed + 100 + k))
        print(f"zero-order, sigma {s:g}: |g| {np.linalg.norm(zero_order[s]['grad']):.4g}, "
              f"{zero_order[s]['non_finite']} non-finite pairs ({time.perf_counter() - t:.1f} s)", flush=True)
    res = bias.compare(pathwise, zero_order, grad.obj.lengths, param.names)
    print(bias.table(res))
    res.update(date=datetime.date.today().isoformat(), device=str(jax.devices()[0].device_kind), jax=jax.__version__,
               python=platform.python_version(), settings=vars(a), windows=int(grad.win.size),
               windows_valid=int(np.asarray(grad.win.valid).sum()), seconds=timing,
               wall_s=time.perf_counter() - t0, theta=theta.tolist(), names=list(param.names),
               gradients={n: np.asarray(r["grad"]).tolist() for n, r in pathwise.items()},
               zero_order_gradients={str(s): np.asarray(z["grad"]).tolist() for s, z in zero_order.items()})
    if a.out:
        atomic.write_json(a.out, json.loads(json.dumps(res, default=float)))
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
