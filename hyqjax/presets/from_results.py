"""Presets from result files: the values, provenance and figures of a tuning run's returned set, or of a bounding
parameter file, in the registry's format (:data:`hyqjax.presets.registry.FORMAT`).

One home for reading a preset out of a result file: ``python -m experiments.build_presets`` writes the shipped
presets with it, ``hyqjax presets save NAME --from RESULTS.json[:METHOD/DIM]`` a user's own.

* :func:`crawl_values`: the values of a run of a ``hyqjax tune`` (or ``python -m experiments.tune_study``)
  ``results.json``: its returned set (shared, per-leg or conditioned) over the run's start point
  (``start_base``: a start preset's edge probe, say), exactly as :func:`hyqjax.studies.tune.tuned.crawl_params`
  reads it back; :func:`tuned_shared`, :func:`tuned_per_leg` and :func:`tuned_conditioned` are its three cases;
* :func:`provenance` and :func:`heldout_figure`: a run's command, seed, device, date and version, and its held-out
  clean success with its interval and the held-out set;
* :func:`crawl_preset` and :func:`bound_preset`: a user's preset file's contents (name, kind, description, values,
  provenance with the source file's absolute path and SHA-256, figures);
* :func:`write`: the file in the user's preset directory, written atomically (never half a file; without
  ``force`` a second writer of the same name is refused, not overwritten).

Refusals are one-line :class:`hyqjax.presets.registry.PresetError` s: a name that is not allowed, a shipped
preset's name, an existing name without ``force``, a missing or foreign file, a run not in the file, a run
without a returned set.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import os

import numpy as np

from hyqjax.presets.registry import FORMAT, PresetError, name_problem, user_dir


def _read(path: str) -> dict:
    from hyqjax.studies.tune import tuned

    return tuned.read(path)


def _crawl_diff(cp, base) -> tuple[dict, dict]:
    """(``CrawlParams.make`` settings, ``ReflexParams`` fields) of ``cp`` that differ from ``base`` (scalars of
    declared range)."""
    from hyqjax.core.params import param_ranges

    crawl, reflex = {}, {}
    for name in param_ranges(type(cp)):
        a, b = np.asarray(getattr(cp, name)), np.asarray(getattr(base, name))
        if a.shape == () and a != b:
            crawl[name] = float(a)
    for name in param_ranges(type(cp.reflex)):
        a, b = np.asarray(getattr(cp.reflex, name)), np.asarray(getattr(base.reflex, name))
        if a.shape == () and a != b:
            reflex[name] = float(a)
    return crawl, reflex


def _start(res: dict) -> tuple[dict, dict]:
    """The ``CrawlParams.make`` settings and reflex values the run mapped its ``theta`` on: its remedy setting and
    its start point (:func:`hyqjax.studies.tune.tuned.start_base`), in the order ``crawl_params`` applies them."""
    from hyqjax.studies.tune import tuned

    start = tuned.start_base(res)
    return ({"shin_remedy": bool(res["config"].get("remedy", False)), **start.get("crawl", {})},
            dict(start.get("reflex", {})))


def tuned_shared(path: str, run: str | None = None) -> tuple[dict, dict, dict]:
    """``(crawl settings, reflex values, results)`` of a ``shared`` run: the start point's settings and every
    scalar field the returned ``CrawlParams`` sets otherwise."""
    from hyqjax.crawl.params import CrawlParams
    from hyqjax.reflex.params import ReflexParams
    from hyqjax.studies.tune import tuned

    res = _read(path)
    cp = tuned.crawl_params(path, run)
    crawl, reflex = _start(res)
    base = CrawlParams.make(**crawl, reflex_params=ReflexParams.make(**reflex) if reflex else None)
    dc, dr = _crawl_diff(cp, base)
    return {**crawl, **dc}, {**reflex, **dr}, res


def tuned_per_leg(path: str, key: str | None = None) -> tuple[dict, dict, dict, dict]:
    """``(crawl settings, reflex values, per-leg values, results)`` of a ``per_leg`` run: the start point and
    ``{field: {LF: v, RF: v, LH: v, RH: v}}`` (``reflex.<field>`` for a reflex field)."""
    from hyqjax.crawl.scheduled import LEGS
    from hyqjax.studies.tune import tuned

    res = _read(path)
    pl = tuned.crawl_params(path, key)
    crawl, reflex = _start(res)
    per_leg = {k: {leg: float(np.asarray(v)[i]) for i, leg in enumerate(LEGS)} for k, v in pl.legs.items()}
    return crawl, reflex, per_leg, res


def tuned_conditioned(path: str, key: str | None = None) -> tuple[dict, dict, dict, dict]:
    """``(crawl settings, reflex values, conditioned set, results)`` of a conditioned run (``per_leg_cond``,
    ``per_leg_cond_all``): the start point and the run's parameterisation, groups, ``theta``, the fields it chooses
    per tick and their values for reading."""
    from hyqjax.studies.tune import tuned

    res = _read(path)
    key = tuned.pick_run(res, key, path)
    run = res["runs"][key]
    cs = tuned.crawl_params(path, key)
    crawl, reflex = _start(res)
    cond = dict(parameterisation=run["dim"], groups=list(res["config"]["groups"]),
                theta=[float(x) for x in run["theta"]], fields=list(cs.fields),
                values={k: round(float(v), 6) for k, v in cs.describe().items()})
    return crawl, reflex, cond, res


def run_key(path: str, run: str | None = None) -> str:
    """The run of ``results.json`` at ``path`` that ``run`` names (``METHOD/DIM``, or ``METHOD`` when it has one
    run of it; None: the only run), refused in one line when it is not in the file or returned no set."""
    from hyqjax.studies.tune import tuned

    try:
        at_checkpoint = tuned.split_checkpoint(run)[1] is not None
    except ValueError as e:
        raise PresetError(str(e)) from None
    if at_checkpoint:
        raise PresetError(f"run {run} of {path}: a preset keeps the set a run returned, not the iterate it held at a "
                          f"checkpoint (run that one with `hyqjax stepdown --params {path}:{run}`)")
    res = _read(path)
    runs = res.get("runs") if isinstance(res.get("runs"), dict) else {}
    if run and isinstance(runs.get(run), dict) and "theta" not in runs[run]:
        raise PresetError(f"run {run} of {path} has no returned set (no theta: it stopped before its first "
                          f"checkpoint)")
    try:
        return tuned.pick_run(res, run, path)
    except ValueError as e:
        raise PresetError(str(e)) from None


def crawl_values(path: str, run: str | None = None) -> tuple[dict, dict, str]:
    """``(values, results, run key)``: the preset values of run ``run`` (:func:`run_key`) of the tuning results at
    ``path``: ``crawl`` and ``reflex``, and ``per_leg`` or ``conditioned`` for a per-leg or conditioned run;
    :func:`hyqjax.presets.load` of them equals :func:`hyqjax.studies.tune.tuned.crawl_params` of the run."""
    from hyqjax.studies.tune import schedule

    key = run_key(path, run)
    dim = key.rpartition("/")[2]
    try:
        if dim == "per_leg":
            crawl, reflex, per_leg, res = tuned_per_leg(path, key)
            return dict(crawl=crawl, reflex=reflex, per_leg=per_leg), res, key
        if dim in schedule.NAMES and dim != "shared":
            crawl, reflex, cond, res = tuned_conditioned(path, key)
            return dict(crawl=crawl, reflex=reflex, conditioned=cond), res, key
        crawl, reflex, res = tuned_shared(path, key)
    except PresetError:
        raise
    except ValueError as e:
        raise PresetError(str(e).splitlines()[0]) from None
    return dict(crawl=crawl, reflex=reflex), res, key


def command_of(res: dict) -> str:
    """The run's command as typed (``hyqjax tune`` stored its command without the subcommand before it stored
    it with it)."""
    cmd = res["provenance"]["command"]
    if cmd.startswith("hyqjax --"):
        cmd = "hyqjax tune " + cmd[len("hyqjax "):]
    return cmd


def provenance(res: dict, source: str, **extra) -> dict:
    """The run's command, seed, device, date (day), hyqjax version and ``source``, then ``extra``."""
    p = res["provenance"]
    dev = res.get("device") or ", ".join(p.get("devices", []))
    return dict(command=command_of(res), seed=p.get("seed"), device=dev, date=p["date"][:10], hyqjax=p.get("hyqjax"),
                source=source, **extra)


def heldout_figure(res: dict, key: str, what: str, source: str, command: str) -> dict:
    """The held-out clean success ``res["heldout"][key]`` with its 95% interval, the held-out set it was measured
    on (instances, seed, duration, heights, ranges), ``command``, device, date and ``source``."""
    h = res["heldout"][key]
    hs = res["heldout_set"]
    r = hs["ranges"]
    return dict(what=what, value=round(h["clean"], 3), unit="share", interval=[round(x, 3) for x in h["clean_ci95"]],
                heldout=(f"{hs['instances']} step-downs, seed {hs['seed']}, {hs['duration']:g} s, heights "
                         f"{hs['heights'][0]:g}-{hs['heights'][-1]:g} m, friction {r['friction'][0]:g}-"
                         f"{r['friction'][1]:g}, payload {r['payload'][0]:g}-{r['payload'][1]:g} kg, start "
                         f"{r['start_distance'][0]:g}-{r['start_distance'][1]:g} m"),
                command=command, device=res["device"], date=res["provenance"]["date"][:10], source=source)


def returned_heldout_key(res: dict, key: str) -> str | None:
    """The held-out evaluation of the set run ``key`` returned (its last checkpoint, ``KEY@<minutes>min``), or
    None when the run has none (``--heldout 0``, an unfinished run, the gradient study's layout)."""
    minutes = (res.get("config") or {}).get("wall_minutes") or []
    held = res.get("heldout") if isinstance(res.get("heldout"), dict) else {}
    if not minutes or not res.get("complete", False):
        return None
    k = f"{key}@{float(minutes[-1]):g}min"
    h = held.get(k)
    return k if isinstance(h, dict) and "clean" in h and "clean_ci95" in h and "heldout_set" in res else None


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _today() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def crawl_preset(name: str, path: str, run: str | None = None, description: str | None = None) -> dict:
    """The preset file of the set run ``run`` of the tuning results at ``path`` returned (module docstring):
    values (:func:`crawl_values`), provenance (the run's command, seed, device, date, version, start pose, the
    file's absolute path and SHA-256) and the run's held-out clean success when it measured one."""
    import hyqjax

    path = os.path.abspath(path)
    values, res, key = crawl_values(path, run)
    cfg = res["config"]
    extra = dict(run=key, sha256=sha256_file(path), complete=bool(res.get("complete", False)),
                 start_preset=cfg.get("start_preset") or None, saved=_today(), saved_by=hyqjax.__version__)
    if cfg.get("start_pose"):
        extra["start_pose"] = cfg["start_pose"]
    prov = provenance(res, path, **extra)
    hk = returned_heldout_key(res, key)
    figures = [heldout_figure(res, hk, "clean success, held-out step-downs", path, prov["command"])] if hk else []
    kind = {"per_leg": "per-leg", "shared": "shared"}.get(key.rpartition("/")[2], "conditioned")
    desc = description or (f"the {kind} set run {key} returned ({prov['command']}, {prov['date']}, "
                           f"{prov['device']})")
    return dict(format=FORMAT, name=name, kind="crawl", description=desc, aliases=[], values=values,
                provenance=prov, figures=figures)


def bound_preset(name: str, path: str, description: str | None = None) -> dict:
    """The preset file of a bounding parameter file (``hyqjax bound --params FILE``'s format,
    :func:`hyqjax.bounding.robust_params.save_params`): its amplitudes and gains, checked in their declared
    ranges, with the file's provenance, absolute path and SHA-256."""
    import hyqjax
    from hyqjax.bounding import robust_params as rp

    path = os.path.abspath(path)
    try:
        vals = rp.load_params(path)
        rp.params_from_values(vals)
        with open(path) as f:
            d = json.load(f)
    except (ValueError, TypeError) as e:
        raise PresetError(str(e).splitlines()[0]) from None
    if d.get("format") == FORMAT:
        d = dict(d["values"], provenance=d.get("provenance", {}))
    fp = d.get("provenance") if isinstance(d.get("provenance"), dict) else {}
    amps = {k: vals[k] for k in rp.AMPLITUDE_NAMES if k in vals}
    gains = {k: v for k, v in vals.items() if k not in rp.AMPLITUDE_NAMES}
    prov = dict(command=fp.get("command"), seed=fp.get("seed"), device=fp.get("device") or ", ".join(
        fp.get("devices", []) or []) or None, date=(fp.get("date") or "")[:10] or None, hyqjax=fp.get("hyqjax"),
        source=path, sha256=sha256_file(path), method=fp.get("method"), saved=_today(), saved_by=hyqjax.__version__)
    desc = description or f"bounding amplitudes and gains of {os.path.basename(path)}" + (
        f" ({fp['method']})" if fp.get("method") else "")
    return dict(format=FORMAT, name=name, kind="bound", description=desc, aliases=[],
                values=dict(amplitudes=amps, gains=gains), provenance=prov, figures=[])


def is_bound_file(path: str) -> bool:
    """Whether ``path`` is a bounding parameter file (or a bounding preset file), not a tuning results.json."""
    from hyqjax.bounding.robust_params import FORMAT as BOUND_FORMAT

    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and (d.get("format") == BOUND_FORMAT
                                    or (d.get("format") == FORMAT and d.get("kind") == "bound"))


def check_name(name: str, force: bool = False) -> str:
    """The path of user preset ``name``'s file; a one-line :class:`PresetError` for a name that is not allowed, a
    shipped preset's, or an existing user preset's without ``force``."""
    why = name_problem(name)
    if why:
        raise PresetError(why)
    path = os.path.join(user_dir(), f"{name}.json")
    if os.path.exists(path) and not force:
        raise PresetError(f"{name} exists ({path}); give --force to replace it, or another name")
    return path


def write(d: dict, force: bool = False) -> str:
    """Write preset file ``d`` into the user's preset directory (:func:`hyqjax.presets.registry.user_dir`),
    atomically: a reader sees the old file or the new one, never a part. Without ``force`` an existing file is
    refused (also one a second writer made in between: the new file is linked into place, which fails if the
    name exists). Returns the path."""
    from hyqjax.io import atomic

    path = check_name(d["name"], force)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    text = (json.dumps(atomic.to_jsonable(d), indent=1, allow_nan=False) + "\n").encode()
    if force:
        atomic.atomic_write(path, lambda f: f.write(text))
        return path
    tmp = atomic.temporary_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            raise PresetError(f"{d['name']} exists ({path}); give --force to replace it, or another name") from None
        except OSError:  # a file system without hard links: the rename, after the check above
            os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path
