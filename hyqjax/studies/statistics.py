"""Statistics of success/failure experiments: Wilson intervals, success-versus-height curves, the
largest safe height ``h95`` (two definitions) and a maximum-likelihood logistic fit.

Every step-down study (``stepdown``, ``sweep``, ``tune``, ``experiments.stepdown_heights``) summarises
with these functions, so one height curve means the same everywhere:

* :func:`wilson_interval`: the Wilson score interval of a binomial proportion (closed form);
* :func:`success_curve`: per level of ``x`` (e.g. the platform height) ``n``, successes, rate and the
  Wilson interval;
* :func:`h95_wilson` (conservative): the largest level ``h`` such that at every level ``<= h`` the
  Wilson lower bound of the success probability is ``>= target`` (0.95); ``None`` if the first fails;
* :func:`logistic_fit` / :func:`h95_logistic` (point estimate): ``P(success | x) = sigmoid(a + b x)``
  by maximum likelihood (``scipy.optimize``, exact gradient and Hessian, a ``1e-6`` ridge), and the
  ``x`` where it crosses ``target``; ``None`` if the fit does not decrease with ``x`` or all outcomes
  are equal;
* :func:`height_summary`: the three together, as JSON-ready dicts.
"""
from __future__ import annotations

import math
import statistics
from typing import Any

import numpy as np

__all__ = ["h95_logistic", "h95_wilson", "height_summary", "logistic_fit", "mean_interval", "success_curve",
           "wilson_interval"]


def wilson_interval(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of the proportion ``p = k / n``; NaNs for ``n = 0``.

    With ``z`` the normal quantile of ``(1 + confidence) / 2``: centre ``(p + z^2 / 2n) / (1 + z^2 / n)``, half-width
    ``z sqrt(p (1 - p) / n + z^2 / 4n^2) / (1 + z^2 / n)`` (the interval of ``scipy.stats.binomtest(k, n)
    .proportion_ci(method="wilson")``, computed here without importing ``scipy.stats``, which costs about 1 s).
    """
    k, n = int(k), int(n)
    if n == 0:
        return (float("nan"), float("nan"))
    if not 0 <= k <= n:
        raise ValueError(f"successes k={k} must be in [0, n={n}]")
    z = _normal_quantile(0.5 + confidence / 2)
    p, z2 = k / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    # At k = 0 (k = n) the lower (upper) bound is exactly 0 (1); the two terms cancel only up to rounding.
    return (0.0 if k == 0 else max(0.0, centre - half), 1.0 if k == n else min(1.0, centre + half))


def _normal_quantile(q: float) -> float:
    """The standard normal quantile (``statistics.NormalDist``: no SciPy import)."""
    return statistics.NormalDist().inv_cdf(q)


def mean_interval(values, confidence: float = 0.95) -> tuple[float, float]:
    """Normal-approximation interval of the mean, ``mean +- z s / sqrt(n)``; NaNs for fewer than 2 values."""
    v = np.asarray(values, np.float64)
    if v.size < 2:
        return (float("nan"), float("nan"))
    half = _normal_quantile(0.5 + confidence / 2) * float(v.std(ddof=1)) / math.sqrt(v.size)
    return (float(v.mean()) - half, float(v.mean()) + half)


def series_summary(values, share_positive: bool = False) -> dict[str, Any] | None:
    """Over the finite entries of a per-step series (in order): their count ``n``, ``median``, ``mean`` (and the
    ``share_positive`` > 0 when asked), and the mean of the first and last third (``first_third``, ``last_third``:
    does the quantity drift over a run?); None without a finite entry."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return None
    t = max(1, v.size // 3)
    out = dict(n=int(v.size), median=float(np.median(v)), mean=float(v.mean()))
    if share_positive:
        out["share_positive"] = float(np.mean(v > 0))
    return dict(out, first_third=float(v[:t].mean()), last_third=float(v[-t:].mean()))


def success_curve(x, success, levels=None, confidence: float = 0.95, key: str = "height") -> list[dict[str, Any]]:
    """Per level of ``x`` (sorted), ``{key, n, successes, rate, ci95}``.

    Args:
      x: ``(N,)`` level of each instance (e.g. the platform height, m).
      success: ``(N,)`` booleans.
      levels: optional ``(N,)`` integer level index with ``x`` giving the label per index (for binned
        continuous axes); by default every distinct value of ``x`` is a level.
    """
    x = np.asarray(x, np.float64)
    s = np.asarray(success).astype(bool)
    if x.shape != s.shape:
        raise ValueError(f"x and success must have the same shape, got {x.shape} and {s.shape}")
    idx = np.unique(x, return_inverse=True)[1].reshape(x.shape) if levels is None else np.asarray(levels)
    out = []
    for i in np.unique(idx):
        m = idx == i
        k, n = int(s[m].sum()), int(m.sum())
        out.append({key: float(x[m][0]), "n": n, "successes": k, "rate": k / n,
                    "ci95": list(wilson_interval(k, n, confidence))})
    out.sort(key=lambda c: c[key])
    return out


def h95_wilson(curve: list[dict[str, Any]], target: float = 0.95, key: str = "height") -> float | None:
    """Largest level whose Wilson lower bound, and that of every lower level, is ``>= target``."""
    best = None
    for c in sorted(curve, key=lambda c: c[key]):
        if c["n"] == 0 or not c["ci95"][0] >= target:
            break
        best = c[key]
    return best


def logistic_fit(x, y, ridge: float = 1e-6) -> tuple[float, float] | None:
    """Maximum-likelihood ``(a, b)`` of ``P(y = 1 | x) = sigmoid(a + b x)``; ``None`` without a fit.

    Minimises ``-sum(y log p + (1 - y) log(1 - p)) + ridge/2 |w|^2`` with ``scipy.optimize.minimize``
    (Newton-CG), then polishes the stationary point with ``scipy.optimize.root``; exact gradient
    ``X^T (p - y) + ridge w`` and Hessian ``X^T diag(p(1-p)) X + ridge I``. ``None`` if fewer than two
    distinct ``x``, all outcomes equal, or the gradient at the result is not below ``1e-6 n``.
    """
    from scipy import optimize, special

    x = np.asarray(x, np.float64).reshape(-1)
    y = np.asarray(y, np.float64).reshape(-1)
    if len(np.unique(x)) < 2 or y.all() or not y.any():
        return None
    xm = np.stack([np.ones_like(x), x], 1)

    def nll(w):
        z = xm @ w
        return float(np.sum(np.logaddexp(0.0, z) - y * z) + 0.5 * ridge * w @ w)

    def grad(w):
        return xm.T @ (special.expit(xm @ w) - y) + ridge * w

    def hess(w):
        p = special.expit(xm @ w)
        return (xm * (p * (1 - p))[:, None]).T @ xm + ridge * np.eye(2)

    res = optimize.minimize(nll, np.zeros(2), jac=grad, hess=hess, method="Newton-CG",
                            options=dict(xtol=1e-12, maxiter=1000))
    # The objective is strictly convex: polish the stationary point to full precision (MINPACK hybrd).
    root = optimize.root(grad, res.x, jac=hess, method="hybr", options=dict(xtol=1e-14))
    w = root.x if np.all(np.isfinite(root.x)) and np.linalg.norm(grad(root.x)) <= np.linalg.norm(grad(res.x)) else res.x
    if not np.all(np.isfinite(w)) or not np.linalg.norm(grad(w)) < 1e-6 * max(1, x.size):
        return None
    return float(w[0]), float(w[1])


def h95_logistic(x, y, target: float = 0.95) -> float | None:
    """``x`` where the logistic fit (:func:`logistic_fit`) equals ``target``; ``None`` if ``b >= 0``, no fit, or
    the crossing lies outside the measured ``[min x, max x]`` (an extrapolation the data do not support: a nearly
    flat fit crosses the target arbitrarily far away)."""
    fit = logistic_fit(x, y)
    if fit is None:
        return None
    a, b = fit
    if not b < 0:
        return None
    h = float((math.log(target / (1 - target)) - a) / b)
    x = np.asarray(x, np.float64)
    return h if x.min() <= h <= x.max() else None


def height_summary(x, success, levels=None, target: float = 0.95) -> dict[str, Any]:
    """``{height_curve, h95_wilson, h95_logistic}`` of instances at levels ``x`` with outcomes ``success``."""
    curve = success_curve(x, success, levels)
    return dict(height_curve=curve, h95_wilson=h95_wilson(curve, target),
                h95_logistic=h95_logistic(np.asarray(x, np.float64), np.asarray(success, np.float64), target))
