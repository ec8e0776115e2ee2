"""Analytic checks of the restart rules and the alpha-order blend, with known answers (``python -m
experiments.tune_restarts_analytic``; ``tests/test_tune_restarts_blend.py`` asserts the same properties).

* :func:`restart_comparison`: CMA-ES, IPOP-CMA-ES and BIPOP-CMA-ES (:mod:`..restarts`, evosax's CMA-ES) on
  Rastrigin, ``f(x) = 10 n + sum x_i^2 - 10 cos(2 pi x_i)`` (global minimum 0 at the origin, a local minimum at
  every integer point), from a start drawn uniformly in ``[-4, 4]^n`` per seed, each with the same number of
  evaluations (a clock that counts evaluated rows): the lowest value each reached.
* :func:`blend_comparison`: the blend (:mod:`..blend`, Suh et al.'s estimator as is: both estimates of one
  objective) against Adam on the first-order (pathwise) gradient alone, on ``f(x) = |x - a|^2 / 2 + H 1[x_0 > 0]``
  (the pathwise gradient does not see the step; its minimum past the step, ``x_0 = 0.5``, is the smoothed
  objective's worst side) and on a smooth function (``+ 0.3 sum sin 3 x_i``, no step): alpha per step and the
  smoothed objective ``F(x) = E f(x + w)``, ``w ~ N(0, sigma^2 I)``, reached.
"""
from __future__ import annotations

import contextlib
import math

import numpy as np

from hyqjax.studies.tune import blend, search

#: The blend problems' dimension, smoothing and quadratic's minimum.
P, SIG, A = 5, 0.2, 0.5


class EvalClock:
    """A method's clock that advances by one per evaluated row (equal evaluations = equal budget)."""

    def __init__(self):
        self.now, self.charged, self.physics_steps = 0.0, 0.0, 0

    def elapsed(self):
        return self.now + self.charged

    def charge(self, s):
        self.charged += s

    def state(self):
        return dict(elapsed=self.elapsed(), charged=self.charged, physics_steps=self.physics_steps)

    def restore(self, st):
        self.now, self.charged, self.physics_steps = st["elapsed"] - st["charged"], st["charged"], st["physics_steps"]

    def paused(self):
        return contextlib.nullcontext()


def rows(th, f) -> dict:
    """``f_gen``'s result for the minimised values ``f`` of the rows ``th`` (fitness ``-f``; no success columns)."""
    z = np.zeros((th.shape[0], 1))
    return dict(fitness=-np.asarray(f, np.float64), clean=z, completed=z, physics_steps=th.shape[0])


def rastrigin(x):
    x = np.atleast_2d(x)
    return 10 * x.shape[-1] + np.sum(x**2 - 10 * np.cos(2 * np.pi * x), -1)


def lowest(method: str, seed: int, dim: int = 10, evaluations: int = 20000, popsize: int = 10,
           sigma: float = 2.0) -> dict:
    """The lowest Rastrigin value ``method`` reached in ``evaluations`` (plain CMA-ES stops early when its float32
    step size underflows after converging: it cannot use the rest), and the restarts it made."""
    clk, low = EvalClock(), [math.inf]

    def f_gen(th, g):
        clk.now += th.shape[0]
        f = rastrigin(th)
        low[0] = min(low[0], float(f.min()))
        return rows(th, f)

    x0 = np.random.default_rng(seed).uniform(-4, 4, dim)
    tr = search.Trace((float(evaluations),), x0)
    try:
        search.run_search(method, f_gen, x0, popsize, sigma, clk, tr, seed=seed)
    except FloatingPointError:
        pass
    return dict(lowest=low[0], evaluations=int(clk.now), generations=len(tr.log),
                restarts=[r["restart"]["reason"] for r in tr.log if "restart" in r])


def restart_comparison(seeds=(0, 1, 2, 3), dim: int = 10, evaluations: int = 20000, popsize: int = 10,
                       sigma: float = 2.0, methods=("cma_es", "ipop_cma_es", "bipop_cma_es")) -> dict:
    runs = {m: {int(s): lowest(m, s, dim, evaluations, popsize, sigma) for s in seeds} for m in methods}
    summary = {m: dict(mean=float(np.mean([r["lowest"] for r in v.values()])),
                       median=float(np.median([r["lowest"] for r in v.values()])),
                       below_cma_es=int(sum(v[s]["lowest"] < runs["cma_es"][s]["lowest"] for s in v)))
               for m, v in runs.items()}
    return dict(dim=dim, evaluations=evaluations, popsize=popsize, sigma=sigma, seeds=[int(s) for s in seeds],
                runs=runs, summary=summary)


def problem(step: float, smooth: bool):
    """``(f, df)``: ``f(x) = |x - a|^2 / 2 (+ 0.3 sum sin 3x) + step 1[x_0 > 0]`` and its pathwise gradient."""
    def f(x):
        x = np.atleast_2d(x)
        v = 0.5 * np.sum((x - A) ** 2, -1) + (0.3 * np.sum(np.sin(3 * x), -1) if smooth else 0.0)
        return v + step * (x[:, 0] > 0)

    def df(x):
        return (x - A) + (0.9 * np.cos(3 * x) if smooth else 0.0)

    return f, df


def smoothed_step(step: float, x) -> float:
    """``F(x) = E f(x + w)`` of the non-smooth problem, exactly."""
    from scipy.stats import norm

    x = np.asarray(x, np.float64)
    return float(0.5 * np.sum((x - A) ** 2) + 0.5 * P * SIG**2 + step * norm.cdf(x[0] / SIG))


def blend_run(step: float, smooth: bool, x0, steps: int = 60, seed: int = 0, popsize: int = 1024,
              windows: int = 16, lr: float = 0.05, gamma: float = 3.0):
    """The blend on :func:`problem` (Suh's estimator as is: ``relative=False``, absolute ``gamma``); the
    first-order samples are the pathwise gradients at ``theta + w_i``. Returns ``(theta, log)``."""
    f, df = problem(step, smooth)
    rng = np.random.default_rng(seed + 1)
    clk = EvalClock()

    def f_gen(th, g):
        clk.now += th.shape[0]
        return rows(th, f(th))

    def grad_fn(th):
        return dict(per_window_grad=df(th[None] + SIG * rng.standard_normal((windows, P))),
                    ok=np.ones(windows, bool), loss=0.0)

    tr = search.Trace((1e12,), np.asarray(x0, np.float64))
    th = blend.run_blend(f_gen, grad_fn, x0, popsize, SIG, clk, tr, seed=seed, lr=lr, gamma=gamma, relative=False,
                         generations=steps)
    return th, tr.log


def first_order_run(step: float, smooth: bool, x0, steps: int = 60, seed: int = 0, windows: int = 16,
                    lr: float = 0.05):
    """Adam on the mean of the same first-order samples alone (the pathwise gradient)."""
    import optax

    _, df = problem(step, smooth)
    rng = np.random.default_rng(seed + 1)
    opt = optax.adam(lr)
    x = np.asarray(x0, np.float64).copy()
    st = opt.init(x)
    for _ in range(steps):
        g = df(x[None] + SIG * rng.standard_normal((windows, P))).mean(0)
        u, st = opt.update(g, st)
        x = x + np.asarray(u)
    return x


def blend_comparison(steps: int = 60, step: float = 10.0) -> dict:
    out = {}
    x0 = np.full(P, 0.1)
    th, log = blend_run(step, False, x0, steps)
    x = first_order_run(step, False, x0, steps)
    out["hidden_step"] = dict(step=step, x0=x0.tolist(), blend_theta=th.tolist(), first_order_theta=x.tolist(),
                              blend_F=smoothed_step(step, th), first_order_F=smoothed_step(step, x),
                              alpha=[r["alpha"] for r in log], guard=[r["guard"] for r in log],
                              cos=[r["cos"] for r in log])
    x0 = np.full(P, 2.5)
    f, _ = problem(0.0, True)
    th, log = blend_run(0.0, True, x0, 20)
    out["smooth"] = dict(x0=x0.tolist(), blend_theta=th.tolist(), f_start=float(f(x0)[0]), f_end=float(f(th)[0]),
                         alpha=[r["alpha"] for r in log], alpha_var=[r["alpha_var"] for r in log],
                         cos=[r["cos"] for r in log])
    return out


def markdown(rc: dict, bc: dict) -> str:
    lines = [f"Rastrigin, {rc['dim']} dimensions, {rc['evaluations']:,} evaluations each, first population "
             f"{rc['popsize']}, sigma_0 {rc['sigma']:g}: lowest value per seed", "",
             "| method | " + " | ".join(f"seed {s}" for s in rc["seeds"]) + " | mean | below CMA-ES |",
             "|---|" + "---:|" * (len(rc["seeds"]) + 2)]
    for m, v in rc["runs"].items():
        s = rc["summary"][m]
        lines.append(f"| {m} | " + " | ".join(f"{v[k]['lowest']:.3f} ({len(v[k]['restarts'])} restarts)"
                                              for k in rc["seeds"])
                     + f" | {s['mean']:.3f} | {s['below_cma_es'] if m != 'cma_es' else '-'} |")
    h, sm = bc["hidden_step"], bc["smooth"]
    a = np.asarray(h["alpha"], np.float64)
    lines += ["", f"Hidden step (H = {h['step']:g}): alpha over the first 5 steps max {a[:5].max():.3f}, "
                  f"median over all {len(a)} steps {np.median(a):.3f}; smoothed objective reached: blend "
                  f"{h['blend_F']:.3f} (x_0 = {h['blend_theta'][0]:+.3f}), first-order gradient alone "
                  f"{h['first_order_F']:.3f} (x_0 = {h['first_order_theta'][0]:+.3f})",
              f"Smooth function: alpha median over the first 10 steps {np.median(sm['alpha'][:10]):.3f}, cosine of "
              f"the two estimates median {np.median(sm['cos'][:10]):+.3f}; f {sm['f_start']:.3f} -> {sm['f_end']:.3f}"]
    return "\n".join(lines)

