"""Guided evolution strategies (Maheswaranathan et al., ICML 2019) on the robust bounding coordinates, stopped at a
wall-clock limit like :func:`hyqjax.bounding.robust.cma_es`, so the two compare at equal wall-clock.

* The search: evosax's ``GuidedES`` as the step-down tuner builds it (:func:`hyqjax.studies.tune.guided.make_guided`:
  antithetic pairs ``mean +- z``, ``z`` from ``sigma^2 (alpha / P I + (1 - alpha) / k Q Q^T)`` with ``Q`` spanning
  the last ``k`` surrogate gradients; the mean moved by Adam along the pairs' own estimate ``sum_i (f_i+ - f_i-)
  z_i``; it minimises). Every candidate is judged by the same ``f_pop`` as CMA-ES (forward runs on any simulator,
  MuJoCo Warp on a GPU).
* The surrogate gradient (:func:`make_surrogate`): :func:`hyqjax.bounding.robust.make_value_and_jac` (``jax.jacfwd``
  through MJX's JAX implementation, every instance's gradient capped at 3 x the median norm) at the current mean, on
  a subset of the training batch (:func:`spread_subset`) and a rollout duration of its own, handed to the search with
  ``state.replace(grad=g)`` before each ``ask``. All of its time, the compile of the first call included, is on
  the method's clock: the clock starts before the first gradient is compiled.
* Recorded per generation (the :func:`~hyqjax.bounding.robust.cma_es` record plus): the gradient's wall time and
  compile time, its loss and norm, and :func:`hyqjax.studies.tune.guided.guided_cosines` of the surrogate gradient
  against what the same generation's antithetic pairs measured (``cos_sampled``: inside the span the pairs
  explored; ``cos_zero_order``, ``cos_search``, ``descent_slope``).
"""
from __future__ import annotations

import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import robust
from hyqjax.bounding import tracking


def spread_subset(n_total: int, n: int) -> np.ndarray:
    """``n`` indices spread evenly over ``range(n_total)`` (first and last included): a subset of a batch that keeps
    the proportions of its consecutive parts (the training batch's envelope and corner instances)."""
    if not 1 <= n <= n_total:
        raise ValueError(f"subset size must be in [1, {n_total}], got {n}")
    return np.unique(np.round(np.linspace(0, n_total - 1, n)).astype(int)) if n > 1 else np.array([0])


def make_surrogate(space: robust.RobustSpace, batch, duration: float,
                   spec: tracking.CostSpec = tracking.CostSpec()) -> Callable:
    """``grad_fn(theta) -> dict(loss, grad, ok, falls, clipped, diverged, wall_s, compile_s)``: the MJX-JAX value and
    clipped mean gradient of :func:`hyqjax.bounding.robust.make_value_and_jac` over ``batch`` (``duration`` s runs)
    at ``theta``. Nothing is built before the first call: that call builds the model, traces and compiles the
    program ahead of time (``compile_s``: all of that, 0 in later calls; ``wall_s``: the whole call's time), so a
    clock started before it charges the gradient's compile to the method."""
    prog = []

    def grad_fn(theta) -> dict:
        t0 = time.time()
        th = jnp.asarray(np.asarray(theta, np.float32))
        compile_s = 0.0
        if not prog:
            args = robust.instance_args(batch)
            prog.append((robust.make_value_and_jac(space, duration, spec).lower(th, args).compile(), args))
            compile_s = time.time() - t0
        r = jax.device_get(prog[0][0](th, prog[0][1]))
        return dict(loss=float(r["loss"]), grad=np.asarray(r["grad"], np.float64), ok=int(np.sum(r["ok"])),
                    falls=int(r["falls"]), clipped=int(r["clipped"]), diverged=int(r["diverged"]),
                    wall_s=time.time() - t0, compile_s=compile_s)

    return grad_fn


def guided_es(f_pop: Callable[[np.ndarray], np.ndarray], grad_fn: Callable[[np.ndarray], dict], theta0: np.ndarray,
              max_wall_s: float, popsize: int, sigma: float = 0.7, seed: int = 0, alpha: float = 0.5,
              subspace: int = 1, lr: float = 0.1, grad_every: int = 1, max_generations: int = 100000,
              cost_per_candidate: int = 0, grad_cost: int = 0, log: Callable | None = None) -> dict:
    """Minimise ``f_pop(thetas (popsize, P)) -> (popsize,)`` by guided ES from ``theta0`` until ``max_wall_s`` s have
    passed (the stop rule of :func:`hyqjax.bounding.robust.cma_es`: a generation started before the limit finishes).
    ``grad_fn(theta) -> dict(loss, grad, ...)`` is the surrogate gradient, evaluated at the mean every ``grad_every``
    generations (the last one again in between) on the same clock (``grad_cost`` physics steps each). ``sigma``: the
    perturbations' scale (their expected norm; evosax's ``std``), ``alpha``: the isotropic share of their variance,
    ``subspace``: the number of recent gradients spanning the guided part, ``lr``: Adam's step on the mean.

    Returns :func:`~hyqjax.bounding.robust.cma_es`'s keys (``theta``: the best candidate, ``value``, ``mean``: the
    final mean, ``history``, ``generations``, ``popsize``, ``wall_s``, ``budget_spent`` = forward + gradient physics
    steps) and ``budget_forward``, ``budget_gradient``, ``gradients`` (calls), ``grad_wall_s`` (their total time),
    ``grad_compile_s``. Each ``history`` row holds cma_es's fields and the gradient's (``new_gradient``, ``grad_s``,
    ``grad_compile_s``, ``surrogate_loss``, ``surrogate_grad_norm``) and the cosines of
    :func:`hyqjax.studies.tune.guided.guided_cosines`. Non-finite values rank last (in ``tell`` they take the
    generation's worst finite value)."""
    from hyqjax.studies.tune.guided import guided_cosines, make_guided

    t0 = time.time()
    theta0 = np.asarray(theta0, np.float64)
    popsize = int(popsize)
    es, params, ask, tell = make_guided(int(theta0.size), popsize, float(sigma), float(alpha), int(subspace),
                                        float(lr))
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(theta0, jnp.float32), params)
    best, best_theta, hist = np.inf, theta0, []
    spent_f = spent_g = calls = 0
    grad_wall = grad_compile = 0.0
    g, loss, gen = None, float("nan"), 0
    while gen < max_generations and time.time() - t0 < max_wall_s:
        key, ka, kt = jax.random.split(key, 3)
        mean = np.asarray(state.mean, np.float64)
        fresh = g is None or gen % int(grad_every) == 0
        gs = gc = 0.0
        if fresh:
            tg = time.time()
            r = grad_fn(mean)
            gs, gc = time.time() - tg, float(r.get("compile_s", 0.0))
            g, loss = np.asarray(r["grad"], np.float64), float(r["loss"])
            if not np.all(np.isfinite(g)):
                g = np.zeros_like(g)  # a non-finite surrogate guides nothing: isotropic this generation
            calls, spent_g, grad_wall, grad_compile = calls + 1, spent_g + int(grad_cost), grad_wall + gs, \
                grad_compile + gc
        xs, state = ask(ka, state.replace(grad=jnp.asarray(g, jnp.float32)), params)
        xs = np.asarray(xs, np.float64)
        vals = np.asarray(f_pop(xs), np.float64)
        vals = np.where(np.isfinite(vals), vals, np.inf)
        spent_f += popsize * int(cost_per_candidate)
        i = int(np.argmin(vals))
        if vals[i] < best:
            best, best_theta = float(vals[i]), xs[i].copy()
        cosines = guided_cosines(g, xs, mean, vals, float(sigma), float(alpha), np.asarray(state.grad_subspace))
        fin = np.isfinite(vals)
        told = np.where(fin, vals, vals[fin].max() if fin.any() else 0.0)
        state, _ = tell(kt, jnp.asarray(xs, jnp.float32), jnp.asarray(told, jnp.float32), state, params)
        gen += 1
        hist.append(dict(generation=gen, wall_s=round(time.time() - t0, 3), budget=spent_f + spent_g, best=best,
                         generation_best=float(vals[i]), theta=best_theta.tolist(), new_gradient=bool(fresh),
                         grad_s=round(gs, 3), grad_compile_s=round(gc, 3), surrogate_loss=loss,
                         surrogate_grad_norm=float(np.linalg.norm(g)), **cosines))
        if log is not None:
            log(f"guided-es generation {gen}: best {best:.4f} (this generation {vals[i]:.4f}), gradient "
                f"{gs:.1f} s{f' ({gc:.1f} s compile)' if gc else ''}, cosine in the sampled span "
                f"{cosines['cos_sampled']:+.2f}, {time.time() - t0:.0f} s")
    mean = np.asarray(state.mean, np.float64)
    if not np.all(np.isfinite(mean)):
        raise FloatingPointError(f"guided ES: the search mean became non-finite at generation {gen}")
    return dict(theta=best_theta, value=best, mean=mean, history=hist, generations=gen, popsize=popsize,
                wall_s=time.time() - t0, budget_spent=spent_f + spent_g, budget_forward=spent_f,
                budget_gradient=spent_g, gradients=calls, grad_wall_s=grad_wall, grad_compile_s=grad_compile)
