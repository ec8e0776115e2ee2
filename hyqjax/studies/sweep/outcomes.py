"""Outcome counting: every failed, diverged or non-finite instance is a failure with its reason, never dropped."""
from __future__ import annotations

import numpy as np

CRITICAL_METRICS = ("peak_roll", "peak_pitch", "progress", "mean_mobility")


def _boolean_reasons() -> tuple[str, ...]:
    """The step-down's failure reasons, each a boolean outcome column (display order)."""
    from hyqjax.studies.stepdown_outcome import FAILURE_REASONS

    return FAILURE_REASONS


def count_outcomes(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Make every diverged or non-finite instance a failure, and give every failure its reasons.

    ``success <- success & ~diverged & all(isfinite(CRITICAL_METRICS))``. ``failure_reason`` (``"; "``-joined)
    lists, for a failed instance, each boolean failure column of the step-down outcome that is set
    (``feet_not_down``, ..., ``reflex_failure``: the reflex's own integration failed, ``contact_overflow``),
    then ``"diverged"`` / ``"non-finite metrics"`` where they apply and are not listed yet. A reason already
    given in ``failure_reason`` is kept. Returns a new dict (``failure_reason`` as str).
    """
    out = dict(out)
    n = np.asarray(out["success"]).shape[0]
    reason = np.asarray(out.get("failure_reason", np.full(n, "")), dtype=object).copy()
    diverged = np.asarray(out.get("diverged", np.zeros(n, bool)), bool)
    finite = np.ones(n, bool)
    for k in CRITICAL_METRICS:
        if k in out:
            finite &= np.isfinite(np.asarray(out[k], np.float64))
    success = np.asarray(out["success"], bool) & ~diverged & finite
    flags = [(np.asarray(out[k], bool), k) for k in _boolean_reasons() if k in out]
    for mask, why in (*flags, (diverged, "diverged"), (~finite, "non-finite metrics")):
        for i in np.nonzero(mask & ~success)[0]:
            have = str(reason[i]).split("; ") if reason[i] else []
            if why not in have:
                reason[i] = "; ".join([*have, why])
    out["success"] = success
    out["failure_reason"] = np.asarray([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return out
