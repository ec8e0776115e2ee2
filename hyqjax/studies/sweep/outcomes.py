"""Outcome counting (every failed, diverged or non-finite instance is a failure with its reason, never dropped)
and the two outcome levels' columns and summary keys."""
from __future__ import annotations

import numpy as np

CRITICAL_METRICS = ("peak_roll", "peak_pitch", "progress", "mean_mobility")
#: The outcome columns a diverged or non-finite instance fails: ``success`` (= ``clean``, the name older
#: results use), ``clean`` and ``completed`` (each where present).
OUTCOME_COLUMNS = ("success", "clean", "completed")
#: The outcome levels of a summary, in display order (:mod:`hyqjax.studies.stepdown_outcome`).
LEVELS = ("completed", "clean")
#: Summary keys of each level: clean keeps the keys of summaries written before the hierarchy, completed has
#: ``completed``-named keys next to them.
KEYS = {
    "completed": dict(count="completed", rate="completed_rate", ci95="completed_ci95", ci95_lo="completed_ci95_lo",
                      ci95_hi="completed_ci95_hi", h95_wilson="h95_completed_wilson",
                      h95_logistic="h95_completed_logistic"),
    "clean": dict(count="successes", rate="rate", ci95="ci95", ci95_lo="ci95_lo", ci95_hi="ci95_hi",
                  h95_wilson="h95_wilson", h95_logistic="h95_logistic"),
}
#: Why a summary's completed entries are None.
NO_COMPLETED_NOTE = ("completed: absent (these rows have no completed column: written before the completed / clean "
                     "outcome levels); successes, rate, ci95 and h95 are clean (= success)")


def level_columns(rows: dict[str, np.ndarray]) -> dict[str, np.ndarray | None]:
    """Boolean column of each level of :data:`LEVELS`: ``clean`` is ``success`` (``clean`` where rows have no
    ``success``); ``completed`` is None where rows have no ``completed`` column (older stores)."""
    clean = rows["success"] if "success" in rows else rows["clean"]
    completed = rows.get("completed")
    return dict(completed=None if completed is None else np.asarray(completed).astype(bool),
                clean=np.asarray(clean).astype(bool))


def _boolean_reasons() -> tuple[str, ...]:
    """The step-down's failure reasons, each a boolean outcome column (display order)."""
    from hyqjax.studies.stepdown_outcome import FAILURE_REASONS

    return FAILURE_REASONS


def count_outcomes(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Make every diverged or non-finite instance a failure, and give every failure its reasons.

    For each outcome level present (``success``, ``clean``, ``completed``; at least ``success`` or ``clean``):
    ``level <- level & ~diverged & all(isfinite(CRITICAL_METRICS))``, so a diverged instance is a counted
    failure of both levels, never dropped. ``success`` is added as ``clean`` where only ``clean`` is given.
    ``failure_reason`` (``"; "``-joined) lists, for an instance that is not clean (``~success``), each boolean
    failure column of the step-down outcome that is set (``feet_not_down``, ..., ``reflex_failure``: the
    reflex's own integration failed, ``contact_overflow``), then ``"diverged"`` / ``"non-finite metrics"``
    where they apply and are not listed yet. A reason already given in ``failure_reason`` is kept. A *terminated*
    instance (``terminated``: it fell and its episode ended at the failure tick) is a failure through the reasons
    recorded up to that tick (tilt, trunk strike), not a divergence; its flag is kept as it is. Returns a
    new dict (``failure_reason`` as str).
    """
    out = dict(out)
    if "success" not in out:
        out["success"] = out["clean"]
    n = np.asarray(out["success"]).shape[0]
    reason = np.asarray(out.get("failure_reason", np.full(n, "")), dtype=object).copy()
    diverged = np.asarray(out.get("diverged", np.zeros(n, bool)), bool)
    finite = np.ones(n, bool)
    for k in CRITICAL_METRICS:
        if k in out:
            finite &= np.isfinite(np.asarray(out[k], np.float64))
    for k in OUTCOME_COLUMNS:
        if k in out:
            out[k] = np.asarray(out[k], bool) & ~diverged & finite
    success = out["success"]
    flags = [(np.asarray(out[k], bool), k) for k in _boolean_reasons() if k in out]
    for mask, why in (*flags, (diverged, "diverged"), (~finite, "non-finite metrics")):
        for i in np.nonzero(mask & ~success)[0]:
            have = str(reason[i]).split("; ") if reason[i] else []
            if why not in have:
                reason[i] = "; ".join([*have, why])
    out["failure_reason"] = np.asarray([str(r) for r in reason], dtype=str) if n else np.zeros(0, str)
    return out
