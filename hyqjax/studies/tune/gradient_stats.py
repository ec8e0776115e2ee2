"""Statistics of the window objective's per-window gradients: how far the windows agree on a gradient.

:func:`gradient_stats` takes the per-window gradients of every window prefix length (the ``per_window_prefix_grad``
of :func:`hyqjax.studies.tune.objective.make_value_and_jac`'s step) and reports, per parameter and length, the
mean and standard deviation across the ``W`` windows and the signal-to-noise ratio
``|mean| / (std / sqrt(W))``, and per length the median and largest gradient norm: their growth with the window
length is the closed loop's sensitivity (a chaos horizon shows as exponential growth). A study records it in
``results.json`` (``gradient_stats``); :mod:`.bias` and :mod:`.gradient_programs` compare gradient variants with it.
"""
from __future__ import annotations

import numpy as np


def gradient_stats(r: dict, lengths, names) -> dict:
    """Across-window mean, standard deviation and signal-to-noise ratio ``|mean| / (std / sqrt(W))`` of the
    gradient per parameter and window length, and the median gradient norm per length (its growth with the
    length is the closed loop's sensitivity: a chaos horizon shows as exponential growth)."""
    ok = np.asarray(r["ok"], bool)
    g = np.asarray(r["per_window_prefix_grad"], np.float64)[ok]  # (W, L, P)
    out = dict(windows=int(ok.sum()), lengths=list(lengths), names=names, per_length=[])
    for i, n in enumerate(lengths):
        gi = g[:, i]
        mean, std = gi.mean(0), gi.std(0, ddof=1) if len(gi) > 1 else np.zeros(gi.shape[1])
        # undefined with one window (no spread across scenarios): NaN, written as null
        snr = (np.abs(mean) / np.maximum(std / np.sqrt(len(gi)), 1e-30) if len(gi) > 1
               else np.full(gi.shape[1], np.nan))
        out["per_length"].append(dict(ticks=int(n), mean=mean.tolist(), std=std.tolist(), snr=snr.tolist(),
                                      median_norm=float(np.median(np.linalg.norm(gi, axis=1))),
                                      max_norm=float(np.max(np.linalg.norm(gi, axis=1)))))
    return out
