"""The start point of ``hyqjax tune`` from its command line: the start preset (``--preset``, or the default of
:data:`hyqjax.studies.tune.names.DEFAULT_PRESETS`), its stored values, the edge groups' need of a start with the edge
probe on, and a warm start from an earlier run (``--start-from``); each refused in one line before anything
compiles (:func:`hyqjax.cli.tune.validate_wallclock` calls them)."""
from __future__ import annotations

from hyqjax.cli.common import UsageError, split_names


def start_preset(args, methods, dims) -> str:
    """The start preset's name ('' for Table I with the shin remedy), checked in one line: a known crawl preset
    (its values are checked by :func:`load_preset`), a per-leg set only for per-leg parameterisations, not with
    --start-from. Without --preset: ``hyqjax tune`` starts from :data:`names.DEFAULT_PRESETS` where the registry
    holds it; the studies start from Table I with the shin remedy, as every stored study did."""
    from hyqjax.studies.tune import names

    given = args.preset
    if given is not None and args.start_from:
        raise UsageError(f"--preset {given} and --start-from {args.start_from} are two start points; give one")
    if given is None and (args.study or args.start_from or len(dims) != 1):
        return ""
    if given is not None and given.lower() == "none":
        return ""
    try:
        from hyqjax import presets
    except ImportError:
        if given is None:
            return ""
        raise UsageError(f"--preset {given}: this installation has no preset registry (hyqjax.presets); give "
                         f"--preset none or --start-from") from None
    name = given if given is not None else names.DEFAULT_PRESETS.get((args.objective, dims[0]))
    if name is None:
        return ""
    if given is None and name not in presets.names():
        return ""
    try:
        rec = presets.get(name)
    except ValueError as e:
        raise UsageError(f"--preset: {e}") from None
    if rec.kind != "crawl":
        raise UsageError(f"--preset {name} is a {rec.kind} preset; the tuner starts from a crawl preset: "
                         f"{', '.join(presets.names('crawl'))}")
    cond = (rec.values or {}).get("conditioned")
    groups = list(split_names(args.groups))
    if cond and (list(dims) != [cond.get("parameterisation")] or groups != list(cond.get("groups", ()))):
        raise UsageError(f"--preset {name} is a conditioned set of {cond.get('parameterisation')}: it starts --dim "
                         f"{cond.get('parameterisation')} with --groups {','.join(cond.get('groups', ()))} only")
    if (rec.values or {}).get("per_leg"):
        flat = [d for d in dims if not d.startswith("per_leg")]
        if flat:
            raise UsageError(f"--preset {name} is a per-leg set: it starts per-leg parameterisations only (per_leg, "
                             f"per_leg_cond, per_leg_cond_all), not {','.join(flat)}")
    return name


def load_preset(name: str) -> None:
    """The preset's stored values in their declared ranges (JAX's parameter classes, no MJX): after every other
    check, since it runs JAX operations."""
    if not name:
        return
    from hyqjax import presets

    try:
        presets.load(name)
    except ValueError as e:
        raise UsageError(f"--preset: {e}") from None


def check_edge_start(cfg) -> None:
    """The edge groups (:data:`hyqjax.studies.tune.space.EDGE_GROUPS`) act only with the edge probe on, and a
    ``box`` coordinate cannot hold the probe's ``0`` (off): from a start with the probe off they are refused in one
    line, since their start point would turn the probe on (a step of 0.2 um) instead of running the start."""
    from hyqjax.studies.tune import space, wallclock

    edge = [g for g in cfg.groups if g in space.EDGE_GROUPS]
    if not edge:
        return
    start = wallclock.start_params(cfg)
    if not float(start.edge_probe) > 0.0:
        where = f"the preset {cfg.start_preset}" if cfg.start_preset else "Table I's crawl"
        raise UsageError(f"--groups {','.join(edge)}: the start ({where}) has the edge probe off (edge_probe 0), "
                         f"and these groups act only with it on; start from a preset with the probe on "
                         f"(--preset clean or reach)")


def start_from(path: str, methods, dims, groups) -> tuple:
    """``(("method/dim", theta), ...)`` from an earlier results.json: each run's last iterate, for the runs of the
    same method and parameterisation; refused in one line when absent or of another size."""
    import json
    import os

    from hyqjax.studies.tune import schedule

    if not os.path.isfile(path):
        raise UsageError(f"--start-from {path}: no such file (give a results.json of an earlier run)")
    try:
        with open(path) as f:
            runs = json.load(f).get("runs", {})
    except (OSError, ValueError) as e:
        raise UsageError(f"--start-from {path}: not a readable results.json ({e.__class__.__name__})") from None
    out = []
    for m in methods:
        for d in dims:
            r = runs.get(f"{m}/{d}")
            if r is None:
                continue
            theta = r.get("theta") or []
            size = schedule.make(d, groups).size
            if len(theta) != size:
                raise UsageError(f"--start-from {path}: {m}/{d} has {len(theta)} parameters, the parameterisation "
                                 f"{d} of --groups has {size}")
            out.append((f"{m}/{d}", tuple(float(x) for x in theta)))
    if not out:
        raise UsageError(f"--start-from {path}: no run of {','.join(methods)} on {','.join(dims)} in it "
                         f"(it holds {', '.join(sorted(runs)) or 'none'})")
    return tuple(out)
