"""The crawl parameters a tuning run returned, read back from its ``results.json`` as ``CrawlParams``.

Both layouts ``hyqjax tune`` writes are read:

* the default tuner and the equal-wall-clock study (``python -m experiments.tune_study``):
  ``res["runs"]["<method>/<dim>"]["theta"]``, the iterate the run returned at its last checkpoint (:mod:`.wallclock`);
* the gradient study (``python -m experiments.tune_study --gradient-study``): ``res["<method>"]["theta"]``
  (:mod:`.study.gradient`).

A ``shared`` run (:class:`.space.ParamSpace` over the run's ``groups``) gives one ``CrawlParams``; a ``per_leg``
run (:class:`.schedule.Parameterisation`: one row per swing leg) gives a per-leg set,
:class:`hyqjax.crawl.scheduled.PerLegCrawlParams`; a conditioned run (``per_leg_cond``, ``per_leg_cond_all``: the
rows also move with features the controller measures) gives a
:class:`hyqjax.studies.tune.schedule.ConditionedCrawlParams`. The crawl runs each wherever it runs a
``CrawlParams``.

A run named with a checkpoint, ``cma_es/per_leg@10min``, gives the iterate the run held at that checkpoint of its
budget (``res["runs"][run]["points"]``: ``hyqjax tune``'s default records 3, 10 and 30 minutes), the set its held-out
evaluation at that checkpoint ran (``res["heldout"]["cma_es/per_leg@10min"]``); without one, the set the run
returned at its end (after the final re-evaluation).

``theta`` is mapped on a base crawl: the run's start point (``shin_remedy`` as the run had it; a start preset's
values of the fields the run did not tune, such as an edge probe: :func:`start_base`) with the caller's other
settings (speed, fields the run did not tune); a setting that the run tuned is refused, since the tuned value
would silently replace it.
"""
from __future__ import annotations

import json

import numpy as np

#: The parameterisation whose ``theta`` is one ``CrawlParams``.
SHARED = "shared"
#: The parameterisation whose ``theta`` is one ``CrawlParams`` row per swing leg (a per-leg set).
PER_LEG = "per_leg"
RUNNABLE = (SHARED, PER_LEG, "per_leg_cond", "per_leg_cond_all")


def runs_of(res: dict) -> dict:
    """``{run name: theta}`` of every run in ``res`` whose ``theta`` runs outside the tuner: one ``CrawlParams``
    (``shared``) or a per-leg set (``per_leg``); both layouts."""
    out = {}
    runs = res.get("runs") if isinstance(res.get("runs"), dict) else {}
    for key, r in runs.items():
        if isinstance(r, dict) and "theta" in r and key.rpartition("/")[2] in RUNNABLE:
            out[key] = r["theta"]
    for key, r in res.items():
        if key != "runs" and isinstance(r, dict) and "theta" in r:
            out[key] = r["theta"]
    return out


def read(path: str) -> dict:
    """``results.json`` at ``path``; a ``ValueError`` naming it when it cannot be read or is not a tuning run's."""
    try:
        with open(path) as f:
            res = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read a tuning results.json at {path} ({e})") from None
    if not isinstance(res, dict) or not isinstance(res.get("config"), dict) or "groups" not in res["config"]:
        raise ValueError(f"{path} is not the results.json of `hyqjax tune` (no config with tuned groups)")
    return res


def pick_run(res: dict, run: str | None, path: str = "results.json") -> str:
    """The run to take: ``run`` (``cma_es`` means the one ``cma_es`` run, else ``cma_es/shared``), or the only one
    ``res`` has."""
    found = runs_of(res)
    if run:
        same = [k for k in found if k.split("/")[0] == run]
        key = run if run in found or "/" in run else (same[0] if len(same) == 1 else f"{run}/{SHARED}")
        if key not in found:
            other = sorted(k for k in (res.get("runs") or {}) if k not in found)
            raise ValueError(f"run {run!r} is not a run of {path} (runs: {', '.join(sorted(found)) or 'none'}"
                             + (f"; of no known parameterisation: {', '.join(other)}" if other else "") + ")")
        return key
    if not found:
        other = sorted(res.get("runs") or {})
        raise ValueError(f"{path} has no run of a known parameterisation ({', '.join(RUNNABLE)})"
                         + (f"; its runs: {', '.join(other)}" if other else ""))
    if len(found) != 1:
        raise ValueError(f"{path} has {len(found)} runs ({', '.join(sorted(found)) or 'none'}): "
                         f"name one as PATH:RUN")
    return next(iter(found))


def split_checkpoint(run: str | None) -> tuple[str | None, float | None]:
    """``"cma_es/per_leg@10min"`` -> ``("cma_es/per_leg", 10.0)`` (``@10`` too); a run without ``@`` -> ``(run,
    None)``. A ``ValueError`` for a checkpoint that is not a positive number of minutes."""
    if not run or "@" not in run:
        return run, None
    name, _, at = run.rpartition("@")
    try:
        minutes = float(at.removesuffix("min"))
    except ValueError:
        minutes = float("nan")
    if not (minutes > 0 and np.isfinite(minutes)):
        raise ValueError(f"run {run!r}: the checkpoint after '@' must be minutes > 0, e.g. {name or 'cma_es'}@10min")
    return name or None, minutes


def _points(res: dict, key: str) -> list[dict]:
    """The checkpoint records of run ``key`` of ``res`` (``seconds``, ``theta``, ...), in order."""
    points = ((res.get("runs") or {}).get(key) or {}).get("points") or []
    return [p for p in points if isinstance(p, dict) and "seconds" in p]


def checkpoint_minutes(res: dict, key: str) -> list[float]:
    """The checkpoints (minutes) at which run ``key`` of ``res`` recorded the iterate it held, in order."""
    return [round(float(p["seconds"]) / 60.0, 6) for p in _points(res, key)]


def checkpoint_point(res: dict, key: str, minutes: float | None = None) -> dict | None:
    """The record (``seconds``, ``theta``, ``validation_clean``, ...) run ``key`` of ``res`` stored at its
    checkpoint of ``minutes`` (None: its last, the end of its budget); None where it has none."""
    points = _points(res, key)
    if minutes is None:
        return points[-1] if points else None
    return next((p for p in points if abs(float(p["seconds"]) - 60.0 * minutes) < 1e-6), None)


def checkpoint_theta(res: dict, key: str, minutes: float, path: str = "results.json") -> np.ndarray:
    """``theta`` run ``key`` held at its checkpoint of ``minutes``; a ``ValueError`` naming the checkpoints it has."""
    p = checkpoint_point(res, key, minutes)
    if p is not None and "theta" in p:
        return np.asarray(p["theta"], np.float64)
    have = ", ".join(f"{m:g}" for m in checkpoint_minutes(res, key)) or "none"
    raise ValueError(f"run {key} of {path} has no checkpoint at {minutes:g} min (its checkpoints, minutes: {have})")


def crawl_params(path: str, run: str | None = None, **settings):
    """``CrawlParams`` (a ``shared`` run) or :class:`hyqjax.crawl.scheduled.PerLegCrawlParams` (a ``per_leg``
    run) of ``run`` in the tuning results at ``path`` (module docstring; ``run@10min``: the iterate held at that
    checkpoint): the run's ``theta`` on the
    ``ParamSpace`` of its ``groups`` (per leg: row by row), over ``CrawlParams.make(shin_remedy=<the run's remedy>,
    **settings)``. A ``ValueError`` naming the problem (unreadable file, unknown or ambiguous run, a setting the run
    tuned, a parameter out of its declared range)."""
    from hyqjax.core.params import ParameterError
    from hyqjax.crawl import controller as crawl
    from hyqjax.studies.tune import space as tspace

    res = read(path)
    run, minutes = split_checkpoint(run)
    key = pick_run(res, run, path)
    theta = np.asarray(runs_of(res)[key] if minutes is None else checkpoint_theta(res, key, minutes, path),
                       np.float64)
    cfg = res["config"]
    try:
        space = tspace.ParamSpace.make(cfg["groups"])
    except (ValueError, TypeError) as e:
        raise ValueError(f"{path}: its groups are not tunable groups ({e})") from None
    from hyqjax.studies.tune import schedule

    dim = key.rpartition("/")[2]
    dim = dim if dim in schedule.NAMES else SHARED  # the gradient study's layout: shared runs
    per_leg = dim == PER_LEG
    pz = schedule.make(dim, cfg["groups"])
    size = pz.size
    if theta.shape != (size,) or not np.all(np.isfinite(theta)):
        raise ValueError(f"{path}: run {key} has {theta.size} values, not {size} finite ones for its groups")
    tuned = sorted({c.name for c in space.coords} & set(settings))
    if tuned:
        raise ValueError(f"{', '.join(tuned)}: tuned by run {key} of {path}; leave it out")
    if "shin_remedy" in settings:
        raise ValueError(f"shin_remedy: set by run {key} of {path} (remedy {bool(cfg.get('remedy', False))})")
    start = start_base(res)
    try:
        from hyqjax.reflex.params import ReflexParams

        reflex = ReflexParams.make(**start["reflex"]) if start.get("reflex") else None
        base = crawl.CrawlParams.make(**{"shin_remedy": bool(cfg.get("remedy", False)), **start.get("crawl", {}),
                                         **settings}, reflex_params=reflex)
        if dim not in (SHARED, PER_LEG):
            return schedule.ConditionedCrawlParams.of_theta(pz, theta, base)
        if not per_leg:
            return space.concrete(theta, base)
        return per_leg_params(space, theta.reshape(4, space.size), base)
    except (ParameterError, ValueError, TypeError) as e:
        raise ValueError(f"run {key} of {path}: {e}") from None


def start_base(res: dict) -> dict:
    """The settings of the crawl the run mapped its ``theta`` on, beyond Table I and the default crawl: the start
    preset's ``crawl`` settings and ``reflex`` values (``res["start_base"]``, or the registry's values of
    ``config.start_preset`` for a ``results.json`` written before it was stored; ``{}`` for a run from Table I)."""
    if isinstance(res.get("start_base"), dict):
        return res["start_base"]
    name = res["config"].get("start_preset") or ""
    if not name:
        return {}
    from hyqjax.studies.tune.wallclock_config import start_settings

    try:
        return start_settings(name)
    except ValueError as e:
        raise ValueError(f"the run started from preset {name}, which this installation cannot read ({e})") from None


def per_leg_params(space, rows, base):
    """The :class:`hyqjax.crawl.scheduled.PerLegCrawlParams` of ``(4, P)`` rows of ``theta`` on ``space`` (legs in
    :data:`hyqjax.crawl.scheduled.LEGS` order, the rows of :class:`.schedule.Parameterisation`) over ``base``: each
    leg's values are ``space.concrete(row, base)``'s."""
    from hyqjax.crawl.scheduled import PerLegCrawlParams

    legs: dict = {}
    for i in range(4):
        cp = space.concrete(np.asarray(rows[i], np.float64), base)
        for c in space.coords:
            obj = cp.reflex if c.owner == "reflex" else cp
            legs.setdefault(f"reflex.{c.name}" if c.owner == "reflex" else c.name, []).append(
                float(np.asarray(getattr(obj, c.name))))
    return PerLegCrawlParams.make(base, legs)
