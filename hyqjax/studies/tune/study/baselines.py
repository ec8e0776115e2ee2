"""Gradient-free baselines at equal simulation budget: CMA-ES (``evosax``) and random search.

Both search the same unconstrained ``theta`` (:class:`.space.ParamSpace`) from the same start, on either

* the same closed-loop window objective as the gradient (``f_pop(thetas (N, P)) -> (N,)``, every
  candidate on the same windows), or
* closed-loop clean success directly (``-success_rate`` over full step-down runs), which needs no gradient.

Budget: physics steps, tangents counted. A gradient step through ``W`` windows of ``n`` ticks with ``P``
tangents costs ``W n (1 + P)`` steps, a candidate on the same windows ``W n``: per gradient step a
baseline gets ``1 + P`` candidate evaluations; a candidate judged by success on ``M`` full runs of ``T``
ticks costs ``M T``.

CMA-ES: ``evosax.algorithms.CMA_ES`` from ``theta_0`` with ``std_init = sigma_0`` (jitted ask / tell), population ``lambda`` (default ``4 + 3 ln P``),
generations until the budget is spent; the reported point is the best candidate evaluated (and the final
mean, on request of the caller). Random search: ``theta_0 + sigma N(0, I)``, the best candidate kept.
``max_wall_s`` (> 0) also stops a search at that wall time (the budget spent is returned). Every
evaluation is recorded (``history``: budget spent, best value so far, best ``theta``) for the
success-vs-budget figure.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def _record(hist, spent, best, best_theta, t0):
    hist.append(dict(budget=int(spent), best=float(best), theta=[float(x) for x in best_theta],
                     wall_s=round(time.time() - t0, 3)))


def cma_es(f_pop: Callable[[np.ndarray], np.ndarray], theta0: np.ndarray, budget: int, cost_per_eval: int,
           sigma: float = 0.5, popsize: int | None = None, seed: int = 0, progress=None,
           max_wall_s: float = 0.0) -> dict:
    """Minimise ``f_pop`` by CMA-ES within ``budget`` physics steps (``cost_per_eval`` per candidate)."""
    from hyqjax.studies.tune.search import make_strategy

    theta0 = np.asarray(theta0, np.float64)
    p = theta0.size
    lam = popsize or (4 + int(3 * math.log(p)))
    es, params = make_strategy("cma_es", p, lam, sigma)
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(theta0, jnp.float32), params)
    ask, tell = jax.jit(es.ask), jax.jit(es.tell)
    spent, best, best_theta, hist, t0 = 0, math.inf, theta0.copy(), [], time.time()
    while spent + lam * cost_per_eval <= budget and not (max_wall_s and time.time() - t0 > max_wall_s):
        key, ka, kt = jax.random.split(key, 3)
        pop, state = ask(ka, state, params)
        xs = np.asarray(pop, np.float64)
        vals = np.asarray(f_pop(xs), np.float64)
        vals = np.where(np.isfinite(vals), vals, np.inf)
        spent += lam * cost_per_eval
        i = int(np.argmin(vals))
        if vals[i] < best:
            best, best_theta = float(vals[i]), xs[i].copy()
        state, _ = tell(kt, pop, jnp.asarray(np.where(np.isfinite(vals), vals, 1e9), jnp.float32), state, params)
        _record(hist, spent, best, best_theta, t0)
        if progress is not None:
            progress(spent, best)
    return dict(theta=best_theta, value=best, mean=np.asarray(state.mean, np.float64), history=hist, popsize=lam,
                generations=len(hist), budget_spent=spent)


def random_search(f_pop: Callable[[np.ndarray], np.ndarray], theta0: np.ndarray, budget: int, cost_per_eval: int,
                  sigma: float = 0.5, chunk: int = 16, seed: int = 0, progress=None,
                  max_wall_s: float = 0.0) -> dict:
    """Best of ``theta0`` and ``theta0 + sigma N(0, I)`` candidates within ``budget`` physics steps."""
    rng = np.random.default_rng(seed)
    theta0 = np.asarray(theta0, np.float64)
    n_total = budget // cost_per_eval
    spent, best, best_theta, hist, t0, first = 0, math.inf, theta0.copy(), [], time.time(), True
    while spent + cost_per_eval <= budget and not (max_wall_s and time.time() - t0 > max_wall_s):
        n = int(min(chunk, n_total - spent // cost_per_eval))
        xs = theta0 + sigma * rng.standard_normal((chunk, theta0.size))  # fixed shape: one compile
        if first:
            xs[0] = theta0
            first = False
        vals = np.asarray(f_pop(xs), np.float64)[:n]  # the padding beyond the budget is discarded unseen
        xs = xs[:n]
        vals = np.where(np.isfinite(vals), vals, np.inf)
        spent += n * cost_per_eval
        i = int(np.argmin(vals))
        if vals[i] < best:
            best, best_theta = float(vals[i]), xs[i].copy()
        _record(hist, spent, best, best_theta, t0)
        if progress is not None:
            progress(spent, best)
    return dict(theta=best_theta, value=best, history=hist, evaluations=spent // cost_per_eval, budget_spent=spent)
