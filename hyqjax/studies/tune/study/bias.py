"""Bias and noise of the window objective's pathwise gradient, against a zero-order estimate of the smoothed one.

Through contact the pathwise (first-order) gradient ``\\nabla L(\\theta)`` of a window's loss is biased: it sees the
current contact sequence only, not how ``theta`` moves a touchdown or a strike (Suh et al. 2022). The reference
is the gradient of the Gaussian-smoothed objective, estimated without derivatives (randomised smoothing):

.. math:: L_\\sigma(\\theta) = E_u\\, L(\\theta + \\sigma u),\\qquad
          \\hat g_\\sigma = \\frac{1}{N} \\sum_{k=1}^{N} \\frac{L(\\theta + \\sigma u_k) - L(\\theta - \\sigma u_k)}{2 \\sigma}\\, u_k,
          \\qquad u_k \\sim \\mathcal N(0, I_P)

(antithetic pairs on the same windows: common random numbers). :func:`smoothed_gradient` returns ``g_sigma`` and
the estimates of its two halves; the cosine between the halves is the estimate's own agreement, the ceiling any
other gradient's cosine with ``g_sigma`` can reach at this ``N``. :func:`compare` reports, per pathwise variant
(plain, or with contacts from distance, :mod:`hyqjax.sim.contacts_from_distance`), its cosine with
``g_sigma`` and its signal-to-noise ratio across windows (``|mean| / (std / sqrt(W))`` per coordinate,
:func:`.gradient_stats.gradient_stats`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.studies.tune.gradient_stats import gradient_stats


def cosine(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return float(a @ b / (na * nb)) if na > 0 and nb > 0 else float("nan")


def smoothed_gradient(value_fn, theta, sigma: float, pairs: int, key) -> dict:
    """``g_sigma`` of the module docstring from ``pairs`` antithetic pairs: ``value_fn(thetas (2N, P)) -> (2N,)``
    (one batched evaluation on the same windows). Returns ``grad``, the halves' estimates ``grad_a`` / ``grad_b``
    and the evaluated ``values``."""
    if pairs < 2 or sigma <= 0:
        raise ValueError(f"pairs must be >= 2 and sigma > 0, got {pairs} and {sigma}")
    theta = np.asarray(theta, np.float64)
    u = np.asarray(jax.random.normal(key, (pairs, theta.size)), np.float64)
    thetas = np.concatenate([theta + sigma * u, theta - sigma * u])
    vals = np.asarray(value_fn(jnp.asarray(thetas, jnp.float32)), np.float64)
    diff = (vals[:pairs] - vals[pairs:]) / (2.0 * sigma)
    ok = np.isfinite(diff)
    contrib = diff[:, None] * u
    half = pairs // 2
    mean = lambda rows, m: rows[m].mean(0) if m.any() else np.full(theta.size, np.nan)  # noqa: E731
    idx = np.arange(pairs)
    return dict(grad=mean(contrib, ok), grad_a=mean(contrib, ok & (idx < half)),
                grad_b=mean(contrib, ok & (idx >= half)), values=vals.tolist(), sigma=float(sigma),
                pairs=int(pairs), non_finite=int((~ok).sum()))


def compare(pathwise: dict, zero_order: dict, lengths, names) -> dict:
    """Per pathwise variant (``name -> step dict`` of :func:`.objective.make_value_and_jac`): its mean gradient's
    cosine with each zero-order estimate (``sigma -> smoothed_gradient``), the zero-order halves' cosine (the
    ceiling), and the gradient's SNR across windows at the full window length."""
    zo = {s: dict(ceiling=cosine(z["grad_a"], z["grad_b"]), norm=float(np.linalg.norm(z["grad"])),
                  non_finite=z["non_finite"]) for s, z in zero_order.items()}
    out = dict(zero_order=zo, variants={})
    for name, r in pathwise.items():
        g = np.asarray(r["grad"], np.float64)
        stats = gradient_stats(r, lengths, list(names))["per_length"][-1]
        snr = np.asarray([np.nan if x is None else x for x in stats["snr"]], float)
        out["variants"][name] = dict(
            cosine={str(s): cosine(g, z["grad"]) for s, z in zero_order.items()}, norm=float(np.linalg.norm(g)),
            snr_median=float(np.nanmedian(snr)), snr_above_2=float(np.mean(snr > 2.0)),
            windows=int(np.sum(np.asarray(r["ok"]))), loss=float(r["loss"]))
    return out


def table(res: dict) -> str:
    """Markdown: one row per pathwise variant, a cosine column per smoothing scale, and the ceilings."""
    sig = list(res["zero_order"])
    head = "| gradient | " + " | ".join(f"cos with g_sigma, sigma {s}" for s in sig) + " | SNR median | SNR > 2 |"
    rows = [head, "|---|" + "---:|" * (len(sig) + 2)]
    for name, v in res["variants"].items():
        rows.append(f"| {name} | " + " | ".join(f"{v['cosine'][str(s)]:+.2f}" for s in sig)
                    + f" | {v['snr_median']:.2f} | {v['snr_above_2']:.0%} |")
    rows.append("| zero-order halves (ceiling) | " + " | ".join(f"{res['zero_order'][s]['ceiling']:+.2f}" for s in sig)
                + " | | |")
    return "\n".join(rows)
