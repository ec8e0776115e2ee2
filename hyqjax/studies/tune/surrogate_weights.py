"""The window objective's terms (:mod:`.objective`) and the weights a user may give them in place of their defaults
(``--surrogate-weights TERM=W``, ``WallClockConfig.surrogate_weights``), checked here without importing JAX or
MuJoCo, so that a bad weight is refused in one line before anything heavy is loaded."""
from __future__ import annotations

TERMS = ("clearance", "joint", "workspace", "foothold", "tilt", "mobility", "progress", "stability")

#: The largest weight a term may be given (:func:`check_weights`).
MAX_WEIGHT = 1000.0


def check_weights(overrides, name: str = "surrogate_weights") -> tuple:
    """``overrides`` (pairs ``(term, w)``) checked: distinct terms of :data:`TERMS`, each ``w`` in [0,
    :data:`MAX_WEIGHT`] (a weight's size; mobility and progress are rewarded, the others penalised, whatever ``w``).
    Returns them as a tuple of ``(str, float)``; raises ``ValueError`` in one line naming ``name`` (the setting) and
    the first bad pair."""
    out = []
    for pair in overrides:
        if isinstance(pair, str) or len(pair) != 2:
            raise ValueError(f"{name} must be (term, weight) pairs, got {pair!r}")
        k, w = pair
        if k not in TERMS:
            raise ValueError(f"{name}: the term must be one of {list(TERMS)}, got {k!r}")
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0.0 <= float(w) <= MAX_WEIGHT:
            raise ValueError(f"{name}: the weight of {k} must be in [0, {MAX_WEIGHT:g}], got {w!r}")
        if k in dict(out):
            raise ValueError(f"{name}: {k} given twice")
        out.append((str(k), float(w)))
    return tuple(out)


def parse_weights(items) -> tuple:
    """Command-line ``TERM=W`` strings as :func:`check_weights`'s pairs (``ValueError`` in one line)."""
    pairs = []
    for s in items:
        k, eq, w = str(s).partition("=")
        try:
            if not eq:
                raise ValueError
            pairs.append((k, float(w)))
        except ValueError:
            raise ValueError(f"--surrogate-weights takes TERM=W with W a number in [0, {MAX_WEIGHT:g}] and TERM one "
                             f"of {list(TERMS)}, got {s!r}") from None
    return check_weights(pairs, "--surrogate-weights")
