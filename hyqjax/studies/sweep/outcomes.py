"""Outcome counting: every diverged or non-finite instance is a failure with its reason, never dropped."""
from __future__ import annotations

import numpy as np

CRITICAL_METRICS = ("peak_roll", "peak_pitch", "progress", "mean_mobility")


def count_outcomes(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Make every diverged or non-finite instance a failure with a reason.

    ``success <- success & ~diverged & all(isfinite(CRITICAL_METRICS))``; the reason gains
    ``"diverged"`` / ``"non-finite metrics"`` where missing. Returns a new dict (``failure_reason`` as str).
    """
    out = dict(out)
    n = np.asarray(out["success"]).shape[0]
    reason = np.asarray(out.get("failure_reason", np.full(n, "")), dtype=object).copy()
    diverged = np.asarray(out.get("diverged", np.zeros(n, bool)), bool)
    finite = np.ones(n, bool)
    for k in CRITICAL_METRICS:
        if k in out:
            finite &= np.isfinite(np.asarray(out[k], np.float64))
    for mask, why in ((diverged, "diverged"), (~finite, "non-finite metrics")):
        for i in np.nonzero(mask)[0]:
            if why not in str(reason[i]):
                reason[i] = why if not reason[i] else f"{reason[i]}; {why}"
    out["success"] = np.asarray(out["success"], bool) & ~diverged & finite
    out["failure_reason"] = np.asarray([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return out
