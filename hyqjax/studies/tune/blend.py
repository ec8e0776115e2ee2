"""The alpha-order blend of first- and zeroth-order gradient estimates (Suh, Simchowitz, Zhang & Tedrake, "Do
Differentiable Simulators Give Better Policy Gradients?", ICML 2022), as the tuner's method ``blend``.

**The estimator** (:func:`alpha_order`). For the smoothed objective ``F(theta) = E_w f(theta + w)``, with
``g1_i`` first-order samples (pathwise gradients, one per instance) and ``g0_j`` zeroth-order samples (here
antithetic pairs, ``(f(theta + sigma z_j) - f(theta - sigma z_j)) / (2 sigma) z_j``)::

    g1 = mean_i g1_i,   g0 = mean_j g0_j,   s1^2 = tr Cov(g1_i) / m,   s0^2 = tr Cov(g0_j) / n
    alpha_var = s0^2 / (s1^2 + s0^2)                                  (inverse-variance weighting)
    eps = z_delta s0                                                  (confidence radius of g0)
    alpha = alpha_var            if alpha_var |g1 - g0| <= gamma - eps
            (gamma - eps) / |g1 - g0|   otherwise (0 when eps >= gamma)
    g_alpha = alpha g1 + (1 - alpha) g0

The second case is Suh et al.'s bias guard: the blended estimate must stay within ``gamma - eps`` of the
zeroth-order one, since ``|g_alpha - g0| = alpha |g1 - g0|``. Where the pathwise gradient is biased (a
discontinuity it cannot see: a contact made or missed, a foothold lost) ``|g1 - g0|`` exceeds what the zeroth-order
noise explains and ``alpha`` falls towards 0; where both agree ``alpha`` follows the variances, towards 1 when the
pathwise samples are the less noisy ones. When the zeroth-order estimate is too noisy to check the first-order one
(``eps >= gamma``) the guard admits no first-order weight: nothing certifies it. ``eps`` uses the normal
approximation ``E |g0 - grad F|^2 = s0^2`` with ``z_delta = 1.96``.

**Why a method of its own (Adam on ``g_alpha``), not the surrogate fed to guided ES.** Suh et al.'s estimator is a
gradient estimate for a descent step: its ``alpha`` trades the step's variance against its bias. Guided ES
(:func:`.guided.run_guided`) uses its surrogate only for the *subspace* it samples in, and moves its mean by the
population's own zeroth-order estimate, so the blend's variance reduction would never reach the step. Run as a
method, the blend's step is exactly ``g_alpha``: the comparison with guided ES at equal wall-clock then says which
use of the same MJX-JAX gradient pays.

**In the tuner** (:func:`run_blend`). Per step: the population ``theta +- sigma z_j`` (``popsize / 2`` antithetic
pairs) and the mean run in one closed-loop batch on the generation's training scenarios (the forward program of
every search method; the fitness, clean success plus ``w_c`` times completed, is maximised); the first-order
samples are the per-window gradients of the MJX-JAX window objective at the mean (``-dL_w / dtheta`` for the
windows whose rollout is valid; its descent is the fitness's ascent), the instances of Suh's first-order
estimate. The two estimate gradients of *different* objectives (a success rate and a smooth window loss): the
first-order samples are scaled by one number per step so that their mean has the zeroth-order estimate's norm
(``scale = |g0| / |g1|``); the blend then weighs directions, and with equal norms the bias guard is a test of the
angle between them against the zeroth-order noise (``|g1 - g0| = |g0| sqrt(2 - 2 cos)``). ``gamma`` is given
relative to ``|g0|`` for the same reason (``gamma_rel = 2``: with a population whose estimate is all noise,
``eps ~ 1.96 |g0|``, the surrogate gets almost no weight). A step whose antithetic pairs all tied (every member
scored alike, frequent with small training batches of a success rate) measured no gradient: no step, alpha
undefined (NaN, null in ``results.json``). With a single valid window the first-order variance is not measured
(0), so alpha is decided by the guard alone. Every step's log row holds ``alpha``, ``alpha_var``,
both variances, ``eps``, the bias ``|g1 - g0|``, the scale and the cosine between ``g1`` and ``g0``.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hyqjax.studies.statistics import series_summary

Z_DELTA = 1.96


def _cos(a, b) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 and np.isfinite(na * nb) else float("nan")


def _mean_var(samples: np.ndarray) -> tuple[np.ndarray, float]:
    """Mean of the rows and the variance of that mean, ``tr Cov / n`` (0 for one row)."""
    x = np.asarray(samples, np.float64)
    n = x.shape[0]
    if n < 2:
        return x.mean(axis=0), 0.0
    return x.mean(axis=0), float(np.sum(np.var(x, axis=0, ddof=1)) / n)


def alpha_order(g1_samples, g0_samples, gamma: float, z: float = Z_DELTA) -> dict:
    """Suh et al.'s alpha-order estimate (module docstring) from first-order samples ``(m, P)`` and zeroth-order
    samples ``(n, P)`` of the gradient of one objective; ``gamma``: the bias the blend may take (absolute).
    Returns ``grad`` and the diagnostics ``alpha, alpha_var, var1, var0, eps, bias, cos``."""
    g1, v1 = _mean_var(g1_samples)
    g0, v0 = _mean_var(g0_samples)
    alpha_var = v0 / (v0 + v1) if v0 + v1 > 0 else 0.5
    eps = z * np.sqrt(v0)
    bias = float(np.linalg.norm(g1 - g0))
    room = max(float(gamma) - eps, 0.0)
    alpha = alpha_var if alpha_var * bias <= room else room / bias
    alpha = float(np.clip(alpha, 0.0, 1.0))
    return dict(grad=alpha * g1 + (1.0 - alpha) * g0, alpha=alpha, alpha_var=float(alpha_var), var1=float(v1),
                var0=float(v0), eps=float(eps), bias=bias, cos=_cos(g1, g0), guard=bool(alpha < alpha_var))


def zeroth_order_samples(fitness_plus, fitness_minus, z, sigma: float) -> np.ndarray:
    """Antithetic zeroth-order samples ``(f(theta + sigma z_j) - f(theta - sigma z_j)) / (2 sigma) z_j``."""
    d = (np.asarray(fitness_plus, np.float64) - np.asarray(fitness_minus, np.float64)) / (2.0 * sigma)
    return d[:, None] * np.asarray(z, np.float64)


def run_blend(f_gen: Callable, grad_fn: Callable, theta0, popsize: int, sigma: float, clock, trace, seed: int = 0,
              lr: float = 0.05, gamma: float = 2.0, relative: bool = True, grad_cost: int = 0,
              progress: Callable | None = None, resume: dict | None = None, checkpoint: Callable | None = None,
              generations: int | None = None):
    """Maximise ``f_gen(thetas (N, P), generation) -> dict(fitness (N,), clean, completed, physics_steps)`` (as
    :func:`.search.run_search`, ``N = popsize + 1``: the mean and ``popsize / 2`` antithetic pairs) by Adam (``lr``)
    on the alpha-order blend of the population's zeroth-order estimate and the first-order samples of
    ``grad_fn(theta) -> dict(per_window_grad (m, P), ok (m,), loss)``, the gradient of a surrogate that is
    *minimised* (its rows are negated; :mod:`.objective`'s tuning step). ``relative``: the tuner's setting (module
    docstring): the first-order samples scaled to the zeroth-order estimate's norm and ``gamma`` relative to that
    norm; False: Suh's estimator as is (both estimate the same objective, ``gamma`` absolute). ``grad_cost``:
    physics steps of one ``grad_fn`` call. Stops at the trace's last checkpoint or after ``generations``; returns
    the final mean; ``checkpoint`` / ``resume`` as in ``run_search`` (the iterate, Adam's state, the generator)."""
    import jax
    import jax.numpy as jnp
    import optax

    from hyqjax.studies.tune.resume import tree_like

    if popsize % 2:
        raise ValueError(f"popsize must be even (antithetic pairs), got {popsize}")
    theta = np.asarray(theta0, np.float64).copy()
    opt = optax.adam(lr)
    ost = opt.init(jnp.asarray(theta, jnp.float32))
    update = jax.jit(opt.update)
    rng = np.random.default_rng([int(seed), 0x5C4])
    gen, half = 0, popsize // 2
    if resume is not None:
        theta, gen = np.asarray(resume["theta"], np.float64), int(resume["gen"])
        ost = tree_like(ost, resume["opt"])
        rng.bit_generator.state = resume["rng"]
        with clock.paused():  # compiled again in this process; the run paid for it once
            update(jnp.zeros(theta.size, jnp.float32), ost)
    while not trace.done(clock) and (generations is None or gen < generations):
        z = rng.standard_normal((half, theta.size))
        pop = np.concatenate([theta + sigma * z, theta - sigma * z])
        r = f_gen(np.concatenate([theta[None], pop]), gen)
        clock.physics_steps += int(r["physics_steps"])
        fit = np.asarray(r["fitness"], np.float64)
        g0s = zeroth_order_samples(fit[1:1 + half], fit[1 + half:], z, sigma)
        rg = grad_fn(theta)
        clock.physics_steps += int(grad_cost)
        g1s = -np.asarray(rg["per_window_grad"], np.float64)
        ok = np.asarray(rg.get("ok", np.ones(g1s.shape[0], bool)), bool) & np.all(np.isfinite(g1s), axis=1)
        g1s = g1s[ok]
        g0_mean = g0s.mean(axis=0)
        scale, gam = 1.0, float(gamma)
        if relative:
            n1 = float(np.linalg.norm(g1s.mean(axis=0))) if g1s.shape[0] else 0.0
            n0 = float(np.linalg.norm(g0_mean))
            scale = n0 / n1 if n1 > 0 else 0.0
            gam = float(gamma) * n0
        if relative and not np.any(g0_mean):  # every pair tied: the population measured no gradient, and the
            # surrogate's scale and the guard are undefined; no step (alpha recorded as undefined)
            b = dict(grad=np.zeros_like(g0_mean), alpha=float("nan"), alpha_var=float("nan"), var1=float("nan"),
                     var0=0.0, eps=0.0, bias=float("nan"), cos=float("nan"), guard=False)
        elif g1s.shape[0]:
            b = alpha_order(scale * g1s, g0s, gam)
        else:  # no valid window: the zeroth-order estimate alone
            _, v0 = _mean_var(g0s)
            b = dict(grad=g0_mean, alpha=0.0, alpha_var=float("nan"), var1=float("nan"), var0=v0,
                     eps=Z_DELTA * np.sqrt(v0), bias=float("nan"), cos=float("nan"), guard=False)
        upd, ost = update(jnp.asarray(-b["grad"], jnp.float32), ost)  # Adam descends; the fitness is maximised
        theta = theta + np.asarray(upd, np.float64)
        if not np.all(np.isfinite(theta)):
            raise FloatingPointError(f"blend: the iterate became non-finite at generation {gen}")
        trace.advance(clock, theta, dict(
            generation=gen, iterate_fitness=float(fit[0]), iterate_clean=float(np.mean(np.asarray(r["clean"])[0])),
            best_fitness=float(fit[1:].max()), mean_fitness=float(fit[1:].mean()),
            surrogate_loss=float(rg.get("loss", float("nan"))), windows=int(g1s.shape[0]), scale=float(scale),
            gamma=float(gam), pairs_differing=int(np.sum(fit[1:1 + half] != fit[1 + half:])),
            **{k: (float(v) if k != "guard" else bool(v)) for k, v in b.items() if k != "grad"}))
        gen += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(gen=gen, theta=theta, opt=jax.tree.leaves(ost), rng=rng.bit_generator.state))
    return theta


def summary(log: list) -> dict:
    """Per blend run: over its steps, the median and mean of ``alpha`` (and of ``alpha_var``, what the variances
    alone would give), the share of steps the bias guard lowered ``alpha``, and the median ``cos`` between the
    first- and zeroth-order estimates, with the first and last third of steps."""
    out = dict(steps=len(log))
    for k in ("alpha", "alpha_var", "cos", "var0", "var1"):
        out[k] = series_summary([r.get(k, np.nan) for r in log])
    out["guard_share"] = float(np.mean([bool(r.get("guard")) for r in log])) if log else None
    return out
