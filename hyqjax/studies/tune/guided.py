"""Guided evolution strategies (Maheswaranathan et al., ICML 2019; evosax ``GuidedES``) inside the tuner: antithetic
search whose perturbations mix the isotropic search with the subspace of recent surrogate gradients (the MJX-JAX
window gradient of :mod:`.objective`), run under the tuner's clock like the other searches (:mod:`.search`), and the
per-generation agreement of that gradient with the population's own estimate (:func:`guided_cosines`)."""
from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.studies.tune.resume import tree_like
from hyqjax.studies.tune.search import Clock, Trace, evaluate_generation, tell_generation


@np.errstate(invalid="ignore")  # a non-finite fitness gives NaN cosines, documented below
def guided_cosines(g, pop, mean, fitness_min, sigma: float, alpha: float, subspace) -> dict:
    """How far the surrogate gradient ``g`` agrees with what the population itself measured, on the same
    antithetic population (``pop`` (N, P), pairs ``i`` and ``i + N/2``; ``fitness_min`` (N,) the minimised
    objective ``f``; ``g`` the gradient of the surrogate that is minimised):

    * ``descent_slope``: how fast ``f`` falls along the surrogate's descent direction ``-g / |g|``, from the pairs'
      differences ``(f_i+ - f_i-) ~ 2 u_i (g_hat . grad f)`` with ``u_i = z_i . g_hat`` (least squares): positive
      when the surrogate points the right way; it equals ``|grad f| cos(g, grad f)``, so on a function with a
      known gradient ``descent_slope / |grad f|`` is the cosine itself. The samples' large component along
      ``g_hat`` makes it the well-measured one with a small population.
    * ``cos_search``: cosine of ``g`` with ``sum_i (f_i+ - f_i-) z_i``, the direction guided ES's ``tell`` moves
      the mean against (it leans towards ``g`` by design: near 1 when the surrogate is right, near 0 when it is
      orthogonal to the true gradient);
    * ``cos_zero_order``: cosine of ``g`` with the unbiased zero-order estimate ``Sigma^-1 sum_i (f_i+ - f_i-)
      z_i`` (``Sigma = a^2 I + c^2 Q Q^T`` the sampling covariance, ``a^2 = sigma^2 alpha / P``, ``c^2 = sigma^2
      (1 - alpha) / k`` with ``sigma`` GuidedES's ``std`` (:func:`sampling_std`), ``Q`` an orthonormal basis of
      ``subspace`` (P, k)); unbiased but noisy unless the population is large against ``P``. NaN when ``alpha`` is
      0 or a vector is zero;
    * ``cos_sampled``: the same comparison inside the directions the population explored: the least-squares
      (minimum-norm) zero-order gradient ``h`` with ``z_i . h = (f_i+ - f_i-) / 2`` against ``g`` projected onto the
      span of the ``z_i``. For a linear ``f`` ``h`` is exactly the projection of ``grad f``, so it is 1 when ``g`` is
      the true gradient, whatever the population size (the other two cosines need many samples to get near 1); NaN
      when a difference is not finite or a vector is zero;
    * ``pairs_differing``: the antithetic pairs whose two members scored differently. With none (a population all
      of whose runs end alike, e.g. on a small training batch of a success rate) the population measured no
      gradient: the slope is 0 and the cosines NaN."""
    g = np.asarray(g, np.float64)
    z = np.asarray(pop, np.float64) - np.asarray(mean, np.float64)[None]
    n = z.shape[0] // 2
    f = np.asarray(fitness_min, np.float64)
    d = f[:n] - f[n:]
    est = d @ z[:n]
    p, k = z.shape[1], int(np.shape(subspace)[1])
    q, _ = np.linalg.qr(np.asarray(subspace, np.float64))
    a2, c2 = sigma**2 * alpha / p, sigma**2 * (1.0 - alpha) / k
    par = q @ (q.T @ est)
    white = (est - par) / a2 + par / (a2 + c2) if a2 > 0 else np.full_like(est, np.nan)
    gn = np.linalg.norm(g)
    u = z[:n] @ (g / gn) if gn > 0 else np.zeros(n)
    slope = float(d @ u / (2.0 * (u @ u))) if gn > 0 and u @ u > 0 else float("nan")  # how fast f falls along -g

    def cos(a, b):
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        return float(a @ b / (na * nb)) if na > 0 and nb > 0 and np.isfinite(na * nb) else float("nan")

    if np.all(np.isfinite(d)):
        zp = np.linalg.pinv(z[:n])  # (P, n): the sampled span's least squares
        sampled = cos(zp @ (z[:n] @ g), zp @ (d / 2.0))
    else:
        sampled = float("nan")
    return dict(descent_slope=slope, cos_search=cos(g, est), cos_zero_order=cos(g, white), cos_sampled=sampled,
                pairs_differing=int(np.sum(d != 0.0)))


def sampling_std(sigma: float, size: int) -> float:
    """GuidedES's ``std`` (the perturbations' expected norm) for a first step ``sigma`` per coordinate over ``size``
    coordinates: ``sigma sqrt(size)`` (:func:`run_guided`)."""
    return float(sigma) * float(np.sqrt(size))


@functools.lru_cache(maxsize=16)
def make_guided(size: int, popsize: int, sigma: float, alpha: float = 0.5, subspace: int = 1, lr: float = 0.05):
    """evosax's ``GuidedES`` (antithetic; the mean moved by Adam at ``lr``; constant ``sigma``, the perturbations'
    expected norm: :func:`sampling_std` gives it for a step per coordinate), its parameters and
    its jitted ``ask`` and ``tell`` (one compile per setting in a process); ``alpha = 1`` is isotropic antithetic
    ES on the same code path."""
    import optax
    from evosax.algorithms import GuidedES

    es = GuidedES(population_size=popsize, solution=jnp.zeros(size, jnp.float32),
                  subspace_dims=max(1, min(int(subspace), size - 1)), optimizer=optax.adam(lr),
                  std_schedule=optax.constant_schedule(sigma))
    return es, es.default_params.replace(alpha=float(alpha)), jax.jit(es.ask), jax.jit(es.tell)


def run_guided(f_gen: Callable, grad_fn: Callable, theta0, popsize: int, sigma: float, clock: Clock, trace: Trace,
               seed: int = 0, alpha: float = 0.5, subspace: int = 1, lr: float = 0.05, grad_every: int = 1,
               grad_cost: int = 0, progress: Callable | None = None, resume: dict | None = None,
               checkpoint: Callable | None = None, generations: int | None = None):
    """Guided evolution strategies (Maheswaranathan et al., ICML 2019; evosax ``GuidedES``): maximise
    ``f_gen(thetas (N, P), generation) -> dict(fitness, clean, completed, physics_steps)`` (as :func:`run_search`)
    with antithetic samples from ``s^2 (alpha / P I + (1 - alpha) / k Q Q^T)``, ``Q`` spanning the last ``k =
    subspace`` surrogate gradients and ``s = sigma sqrt(P)``: ``sigma`` is the first step per coordinate, as it is
    for CMA-ES, SNES, OpenES and the blend (their samples ``theta + sigma z``), so every method explores the same
    total variance ``sigma^2 P`` and ``alpha = 1`` samples exactly as OpenES does. (GuidedES's ``std`` is the
    perturbations' expected norm; given ``sigma`` itself, its samples would be ``sqrt(P)`` times smaller per
    coordinate than the other methods' at the same ``--sigma``, as in the tuner's guided-ES measurements of
    2026-11-29 and 2026-11-30.) ``grad_fn(theta) -> dict(loss, grad)`` is the gradient of a surrogate that is
    *minimised* (the window objective of :mod:`.objective` on MJX-JAX), evaluated at the mean every
    ``grad_every`` generations (its wall time on ``clock``, ``grad_cost`` physics steps each) and handed to the
    search with ``state.replace(grad=g)`` before each ``ask`` (the last one again between two). Only the subspace
    of the gradients shapes the samples; the mean moves by the population's own antithetic estimate (Adam).

    Every generation's log row holds :func:`guided_cosines`: the surrogate gradient against what the same
    population measured (the slope along it, the cosines). Returns the final mean; ``checkpoint`` / ``resume`` as in
    :func:`run_search`; ``generations``: also stop after that many (equal-evaluation comparisons)."""
    theta0 = np.asarray(theta0, np.float64)
    std = sampling_std(sigma, theta0.size)
    es, params, ask, tell = make_guided(int(theta0.size), int(popsize), std, float(alpha), int(subspace), float(lr))
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(theta0, jnp.float32), params)
    gen, g, loss = 0, None, float("nan")
    if resume is not None:
        key, state = jax.random.wrap_key_data(jnp.asarray(resume["key"])), tree_like(state, resume["state"])
        gen, g, loss = int(resume["gen"]), np.asarray(resume["g"], np.float64), float(resume["loss"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            pop, _ = ask(key, state.replace(grad=jnp.asarray(g, jnp.float32)), params)
            tell(key, pop, jnp.zeros(popsize, jnp.float32), state, params)
    while not trace.done(clock) and (generations is None or gen < generations):
        key, ka, kt = jax.random.split(key, 3)
        mean = np.asarray(state.mean, np.float64)
        fresh = g is None or gen % grad_every == 0
        if fresh:
            r = grad_fn(mean)
            g, loss = np.asarray(r["grad"], np.float64), float(r["loss"])
            clock.physics_steps += int(grad_cost)
            if not np.all(np.isfinite(g)):
                g = np.zeros_like(g)  # a non-finite surrogate guides nothing: isotropic this generation
        pop, state = ask(ka, state.replace(grad=jnp.asarray(g, jnp.float32)), params)
        r, fit = evaluate_generation(f_gen, mean, pop, gen, clock)
        cosines = guided_cosines(g, np.asarray(pop, np.float64), mean, -fit[1:], std, alpha,
                                 np.asarray(state.grad_subspace))
        state, new_mean = tell_generation(tell, kt, pop, fit, state, params, "guided_es", gen)
        trace.advance(clock, new_mean, dict(generation=gen, iterate_fitness=float(fit[0]),
                                            iterate_clean=float(np.mean(r["clean"][0])),
                                            best_fitness=float(fit[1:].max()), mean_fitness=float(fit[1:].mean()),
                                            surrogate_loss=loss, surrogate_grad_norm=float(np.linalg.norm(g)),
                                            new_gradient=bool(fresh), **cosines))
        gen += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(gen=gen, key=jax.random.key_data(key), state=jax.tree.leaves(state), g=g,
                                    loss=loss))
    return np.asarray(state.mean, np.float64)
