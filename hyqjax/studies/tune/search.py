"""Tuning methods under a wall-clock budget: success-driven search (CMA-ES, SNES, OpenES, random search) and the
closed-loop gradient; the hybrid (search, then gradient polish) runs the two one after the other
(:mod:`.wallclock_run`).

Every method runs against a :class:`.clock.Clock` and records in a :class:`.trace.Trace`, for each checkpoint ``c``
(seconds), the iterate it would hand back had it been stopped at ``c``: the last iterate it had finished by then
(the start point if it had finished none, e.g. while compiling), or with a :class:`.selection.Selection` the best
of the iterates it had validated by then on a fixed validation batch (closed-loop clean success; the validations
paid from its clock). The clock counts everything a stand-alone run would pay: the compile of each program the
method uses (:class:`.clock.Charges`, measured once per process and *charged* to every method that uses the
program), the snapshot windows of the gradient, every evaluation and every optimiser update. Physics steps are
counted next to it (tangents of forward-mode derivatives included).

Success-driven methods (:func:`run_search`) maximise the fitness of :mod:`.forward` (clean success plus
``w_c`` times completed, on ``M`` training scenarios per generation, the same for every member: common random
numbers). Per generation the population and one extra member, the iterate the method would return, run in one
batch (``N = popsize + 1``), so the returned iterate's fitness is logged on the same scenarios:

* ``cma_es``, ``snes``, ``open_es``: ``evosax`` 0.3.2 (jitted ``ask`` / ``tell``; ``tell`` minimises, so it gets
  ``-F``); the iterate is the search distribution's mean;
* ``ipop_cma_es``, ``bipop_cma_es``: CMA-ES with restarts (:mod:`.restarts`: the restart controller around
  evosax's CMA-ES; a larger population runs in chunks of the first one's batch shape);
* ``random_search``: candidates ``theta_0 + sigma z`` around the start; the iterate is the incumbent, replaced
  by a generation's best candidate when that candidate's fitness exceeds the incumbent's on the same scenarios.

The gradient (:func:`run_gradient`) is Adam with the batched line search of :mod:`.optimize` on the closed-loop
window objective of :mod:`.objective` (``jax.jacfwd`` on MJX-JAX; snapshot windows at the start point). The
hybrid runs CMA-ES for ``split`` of the budget and then the gradient from its mean.

The clock, trace and selection are importable from here too (``search.Clock``, ``search.Charges``,
``search.Trace``, ``search.Selection``, ``search.final_choice``): the methods' callers name them with the methods.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.studies.tune.clock import COMPILE_EVENTS, Charges, Clock  # noqa: F401  (re-exported)
from hyqjax.studies.tune.names import (ANTITHETIC, BLEND_METHODS, GRADIENT_METHODS, GUIDED_METHODS, METHODS,  # noqa: F401
                                       RESTART_METHODS, SEARCH_METHODS, STUDY_METHODS, USES_GRADIENT)
from hyqjax.studies.tune.resume import tree_like
from hyqjax.studies.tune.selection import Selection, final_choice  # noqa: F401  (re-exported)
from hyqjax.studies.tune.trace import Trace


def make_strategy(method: str, size: int, popsize: int, sigma: float, lr: float = 0.05):
    """An ``evosax`` strategy and its parameters (``std_init`` / ``std_schedule`` = ``sigma``)."""
    import optax
    from evosax.algorithms import CMA_ES, SNES, Open_ES

    sol = jnp.zeros(size, jnp.float32)
    if method == "cma_es":
        es = CMA_ES(population_size=popsize, solution=sol)
        params = es.default_params.replace(std_init=sigma)
    elif method == "snes":
        es = SNES(population_size=popsize, solution=sol)
        params = es.default_params.replace(std_init=sigma)
    elif method == "open_es":
        es = Open_ES(population_size=popsize, solution=sol, optimizer=optax.adam(lr),
                     std_schedule=optax.constant_schedule(sigma))
        params = es.default_params
    else:
        raise ValueError(f"method must be one of {list(SEARCH_METHODS)}, got {method!r}")
    return es, params


def run_search(method: str, f_gen: Callable, theta0, popsize: int, sigma: float, clock: Clock, trace: Trace,
               seed: int = 0, generation0: int = 0, progress: Callable | None = None, stop_at: float | None = None,
               resume: dict | None = None, checkpoint: Callable | None = None, restart_stall: int = 0):
    """Maximise ``f_gen(thetas (N, P), generation) -> dict(fitness (N,), clean, completed, physics_steps)`` with
    ``method`` until ``clock`` passes ``stop_at`` (default the last checkpoint). Returns the final iterate.
    ``checkpoint(state_fn)`` is called after every generation; ``state_fn()`` is the method's state then, which
    ``resume`` takes back (:mod:`.resume`; the clock and trace are the caller's). ``restart_stall``: the restart
    methods' stagnation length (:class:`.restarts.Controller`'s ``stall_generations``)."""
    if method in RESTART_METHODS:
        from hyqjax.studies.tune import restarts

        return restarts.run_restarts(method, f_gen, theta0, popsize, sigma, clock, trace, seed=seed,
                                     progress=progress, stop_at=stop_at, resume=resume, checkpoint=checkpoint,
                                     stall_generations=restart_stall)
    theta0 = np.asarray(theta0, np.float64)
    stop_at = trace.checkpoints[-1] if stop_at is None else stop_at
    key = jax.random.key(seed)
    gen = generation0 if resume is None else int(resume["gen"])
    if method == "random_search":
        rng = np.random.default_rng(seed)
        inc, inc_fit = theta0.copy(), -math.inf
        if resume is not None:
            rng.bit_generator.state, inc, inc_fit = resume["rng"], np.asarray(resume["inc"]), float(resume["inc_fit"])
        while clock.elapsed() < stop_at:
            cand = theta0 + sigma * rng.standard_normal((popsize, theta0.size))
            r = f_gen(np.concatenate([inc[None], cand]), gen)
            clock.physics_steps += r["physics_steps"]
            fit = np.asarray(r["fitness"])
            inc_fit = fit[0]
            i = int(np.argmax(fit[1:]))
            if fit[1 + i] > inc_fit:
                inc, inc_fit = cand[i].copy(), float(fit[1 + i])
            trace.advance(clock, inc, dict(generation=gen, iterate_fitness=float(fit[0]),
                                           iterate_clean=float(np.mean(r["clean"][0])), best_fitness=float(fit.max()),
                                           mean_fitness=float(fit[1:].mean())))
            gen += 1
            if progress:
                progress(clock, trace)
            if checkpoint:
                checkpoint(lambda: dict(gen=gen, rng=rng.bit_generator.state, inc=inc, inc_fit=inc_fit))
        return inc
    es, params = make_strategy(method, theta0.size, popsize, sigma)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(theta0, jnp.float32), params)
    ask, tell = jax.jit(es.ask), jax.jit(es.tell)
    if resume is not None:
        key, state = jax.random.wrap_key_data(jnp.asarray(resume["key"])), tree_like(state, resume["state"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            pop, _ = ask(key, state, params)
            tell(key, pop, jnp.zeros(popsize, jnp.float32), state, params)
    while clock.elapsed() < stop_at:
        key, ka, kt = jax.random.split(key, 3)
        pop, state = ask(ka, state, params)
        mean = np.asarray(state.mean, np.float64)
        r, fit = evaluate_generation(f_gen, mean, pop, gen, clock)
        state, new_mean = tell_generation(tell, kt, pop, fit, state, params, method, gen)
        # the returned iterate after this generation is the new mean (its fitness is measured next generation)
        trace.advance(clock, new_mean, dict(generation=gen, iterate_fitness=float(fit[0]),
                                            iterate_clean=float(np.mean(r["clean"][0])),
                                            best_fitness=float(fit[1:].max()), mean_fitness=float(fit[1:].mean()),
                                            std=float(np.mean(np.asarray(state.std)))))
        gen += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(gen=gen, key=jax.random.key_data(key), state=jax.tree.leaves(state)))
    return np.asarray(state.mean, np.float64)


def run_gradient(step_fn: Callable, evaluate: Callable, theta0, clock: Clock, trace: Trace, lr: float = 0.1,
                 clip: float = 1.0, line_search=(0.125, 0.25, 0.5, 1.0, 2.0), step_cost: int = 0,
                 progress: Callable | None = None, resume: dict | None = None, checkpoint: Callable | None = None):
    """Adam + batched line search (:mod:`.optimize`'s step) on ``step_fn(theta) -> dict(loss, grad)`` until the
    clock passes the last checkpoint; ``evaluate(thetas (K, P)) -> (K,)`` scores the line-search candidates
    together with ``theta`` itself (``c = 0``, so acceptance compares values of one program). ``step_cost``:
    physics steps of one step (tangents and line search included). ``checkpoint`` and ``resume``: as in
    :func:`run_search` (the iterate, Adam's state and the step count)."""
    from hyqjax.studies.tune import optimize

    opt = optimize.make_optimizer(optimize.AdamConfig(lr=lr, clip=clip))
    theta = jnp.asarray(theta0, jnp.float32)
    state = opt.init(theta)
    update = jax.jit(lambda g, s, th: opt.update(g, s, th))
    scales = jnp.asarray((0.0,) + tuple(line_search), jnp.float32)
    step = 0
    if resume is not None:
        theta, step = jnp.asarray(resume["theta"], jnp.float32), int(resume["step"])
        state = tree_like(state, resume["opt"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            update(jnp.zeros_like(theta), state, theta)
    while not trace.done(clock):
        r = step_fn(theta)
        g = jnp.asarray(r["grad"], jnp.float32)
        upd, state = update(g, state, theta)
        cands = theta[None] + scales[:, None] * jnp.asarray(upd, jnp.float32)[None]
        vals = np.asarray(evaluate(cands), np.float64)
        vals = np.where(np.isfinite(vals), vals, np.inf)
        i = int(np.argmin(vals))
        theta = cands[i]
        clock.physics_steps += step_cost
        trace.advance(clock, np.asarray(theta), dict(step=step, loss=float(r["loss"]), loss_at_theta=float(vals[0]),
                                                     grad_norm=float(jnp.linalg.norm(g)),
                                                     chosen=float(scales[i]), best_loss=float(vals[i])))
        step += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(step=step, theta=theta, opt=jax.tree.leaves(state)))
    return np.asarray(theta, np.float64)



def evaluate_generation(f_gen, mean: np.ndarray, pop, gen: int, clock) -> tuple[dict, np.ndarray]:
    """One generation's closed-loop runs: the mean (row 0, the iterate the search returns) and the population, in
    one batch; their physics charged to ``clock``. Returns ``f_gen``'s result and the fitness (maximised)."""
    r = f_gen(np.concatenate([mean[None], np.asarray(pop, np.float64)]), gen)
    clock.physics_steps += r["physics_steps"]
    return r, np.asarray(r["fitness"], np.float64)


def tell_generation(tell, key, pop, fit: np.ndarray, state, params, method: str, gen: int):
    """evosax's ``tell`` with the population's fitness (negated: evosax minimises); the new state and its mean, a
    ``FloatingPointError`` when the mean is no longer finite."""
    state, _ = tell(key, pop, jnp.asarray(-fit[1:], jnp.float32), state, params)
    new_mean = np.asarray(state.mean, np.float64)
    if not np.all(np.isfinite(new_mean)):
        raise FloatingPointError(f"{method}: the search mean became non-finite at generation {gen}")
    return state, new_mean
