"""The equal-wall-clock tuning study: every method, every parameterisation, the same wall-clock budget on one GPU.

:func:`run_wallclock_study` (``hyqjax tune`` with one method, ``python -m experiments.tune_study``):

1. **compile charges** (:class:`.clock.Charges`): the forward success program (population ``N = popsize + 1``
   members x ``M`` training scenarios, :class:`.forward.SuccessEvaluator`, ``impl`` warp on a GPU) compiles in the
   first search method's clock (JAX's compile events are added up); the gradient's snapshot windows (compile and
   forward run), its ``jacfwd`` step and forward window program (MJX-JAX) are built before a gradient method's
   clock starts and timed; every method's clock then starts with the charges of the programs it uses and did not
   compile itself, so every method pays its compile as a stand-alone run would, whichever ran first;
2. **runs**: for every parameterisation in ``dims`` (:mod:`.schedule`) and every method in ``methods``
   (:mod:`.search`: ``cma_es``, ``snes``, ``open_es``, ``random_search`` maximise clean success on training
   scenarios, common random numbers per generation; ``gradient`` is Adam + line search on the closed-loop window
   objective; ``hybrid`` is CMA-ES for ``hybrid_split`` of the budget, then the gradient from its mean) until its
   clock reaches the last of ``wall_minutes``; at every checkpoint the iterate it would return is kept with the
   physics steps spent by then (tangents of the ``jacfwd`` counted). With ``select_instances > 0`` (the
   default) every method returns the best of its validated iterates (:class:`.selection.Selection`: the start
   point, then the iterate every ``select_every`` iterations / ``select_every_s`` seconds, by clean success on
   one fixed batch of ``select_instances`` validation scenarios drawn like training from ``select_seed``, on the
   forward program), the validations paid from its clock and physics steps; the hybrid's gradient starts from
   the selected iterate;
3. **held-out evaluation** of Table I (the paper's crawl), the start point and every (method, dim, checkpoint)
   iterate on the same ``>= heldout`` instances drawn wider than training (:func:`.forward.heldout_scenarios`:
   heights 14-30 cm, of which 14, 18, 22, 26, 30 cm never trained on; start 0-15 cm, friction 0.4-1.0, payload
   0-15 kg; another seed), 24 s each, in chunks of ``heldout_chunk`` members;
4. ``results.json`` (every iterate's ``theta``, so that any other held-out set can re-evaluate it; each run's
   validations under ``selection``), the budget curves (held-out clean and completed success against wall-clock
   and against physics steps) and the figure;
5. gradient diagnostics (outside every clock), per parameterisation with a gradient-method run: SNR at the start,
   the window objective's rank correlation with held-out success, and the step's cost in forward windows
   (``step_cost``: one ``jacfwd`` step and one forward evaluation of the same windows for one candidate, timed
   after their compiles).

Resuming: ``results.json`` is written after every run and every held-out chunk, and a run's state every
``checkpoint_every_s`` seconds (:mod:`.resume`); the same command on the same directory keeps every finished run
and every finished held-out member, and goes on with a run cut off by a kill from its last stored state, its
clock from the seconds it had then (its compiles in the new process not counted again). With
``segment_minutes`` a study stops by itself after that long and stores where it was, so that a budget longer
than one machine lease runs in segments. Another configuration in the directory is refused, except
for ``methods``: one process per method (each with ``cold_compile``, so that none loads another's compiled
programs) composes into one results file.
"""
from __future__ import annotations

import json
import os
import time

import jax
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.io.atomic import provenance, write_json
from hyqjax.studies.stepdown import START_POSE, recorded_start_pose
from hyqjax.studies.tune import forward, resume, schedule, search
from hyqjax.studies.tune.wallclock_run import heartbeat, run_key, run_method
from hyqjax.studies.tune.gradient_programs import (GradientPrograms,
                                                  diagnostic_iterates, gradient_diagnostics)
from hyqjax.studies.tune.wallclock_config import (WallClockConfig, is_per_leg, start_point, start_settings,  # noqa: F401
                                                   start_theta)
from hyqjax.studies.tune.wallclock_results import budget_curves, member_key, step_cost_line, summarize

#: What ``hyqjax tune`` runs by default (declared in :mod:`hyqjax.studies.tune.names`, where the measurement behind
#: the choice is stated).
from hyqjax.studies.tune.names import DEFAULT_DIM, DEFAULT_METHOD  # noqa: E402,F401


def start_params(cfg: WallClockConfig) -> crawl.CrawlParams:
    """The crawl every ``theta`` is mapped on (the values of the coordinates a run does not tune): the start
    preset's crawl (a per-leg or conditioned set's ``base``) when ``cfg.start_preset`` names one, else Table I and
    the default crawl with the shin-strike remedy if ``cfg.remedy``."""
    start = start_point(cfg)
    return start.base if is_per_leg(start) else start


def start_evaluator(cfg: WallClockConfig, duration: float | None = None):
    """``(param, theta0, evaluator)`` of ``cfg``'s first parameterisation: its start point's ``theta`` and the
    tuner's forward evaluator (:class:`forward.SuccessEvaluator`) on the start crawl (:func:`start_params`),
    ``duration`` seconds a step-down (default ``cfg.train_duration``)."""
    param = schedule.make(cfg.dims[0], cfg.groups)
    theta0 = start_theta(param, start_point(cfg))
    evaluator = forward.SuccessEvaluator(param, start_params(cfg), cfg.train_duration if duration is None else duration,
                                         cfg.impl, cfg.completed_weight)
    return param, theta0, evaluator


def previous(out_dir: str, cfg: WallClockConfig) -> dict | None:
    """``results.json`` of an earlier run of the same configuration (None if none or unreadable); another
    configuration there is refused."""
    path = os.path.join(out_dir, "results.json")
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            prev = json.load(f)
    except (OSError, ValueError):
        return None
    old, new = _fingerprint(prev.get("config", {})), _fingerprint(_config(cfg))
    if prev.get("kind") == "wallclock" and old["start_pose"] != new["start_pose"]:
        raise RuntimeError(f"{out_dir} holds a tuning study run with the {old['start_pose']!r} step-down start "
                           f"(this hyqjax starts with {new['start_pose']!r}: hyqjax.studies.stepdown.start_qpos), so "
                           f"it is not resumed; use another --out or remove it")
    if prev.get("kind") != "wallclock" or old != new:
        raise RuntimeError(f"{out_dir} holds a tuning study of another configuration; use another --out or remove it")
    return prev


def _config(cfg: WallClockConfig) -> dict:
    """What ``results.json`` stores as ``config``: the settings and the step-down's start pose."""
    return dict(cfg.to_dict(), start_pose=START_POSE)


def _fingerprint(config: dict) -> dict:
    """The settings that must agree for runs to share one results file: all but ``methods`` (one process per
    method composes into one study; each run is stored under its own method's key), and the step-down's start pose
    (``hip-line`` for a study that predates it). A setting a stored study predates counts at its default."""
    fp = {k: v for k, v in {**WallClockConfig.defaults(), **config}.items() if k != "methods"}
    return dict(fp, start_pose=recorded_start_pose(config))


def _run_fingerprint(cfg: WallClockConfig, method: str) -> dict:
    """What a run's stored mid-budget state must agree with: the study's fingerprint and, for guided ES, its sampling
    scale (:func:`.guided.sampling_std`: ``--sigma`` per coordinate since 2026-11-30; a state stored before starts
    over)."""
    fp = _fingerprint(_config(cfg))
    return dict(fp, guided_std="sigma sqrt(P)") if method in search.GUIDED_METHODS else fp


def _methods_union(*lists) -> list:
    seen = [m for ms in lists for m in ms]
    return [m for m in search.METHODS if m in seen]


def record_charges(res: dict, measured: dict) -> None:
    """Keep in ``res["charges"]`` each program's compile seconds as first measured: what the runs that started in that
    process were charged (a run's own charge is its ``charged_s``). A later process of a resumed study compiles the
    programs again, mostly from JAX's persistent cache, in a fraction of the time; its measurements go to
    ``res["charges_remeasured"]`` (the latest process's) instead of replacing the first ones."""
    for name, seconds in measured.items():
        if name not in res["charges"]:
            res["charges"][name] = float(seconds)
        elif float(seconds) != res["charges"][name]:
            res.setdefault("charges_remeasured", {})[name] = float(seconds)


def run_wallclock_study(cfg: WallClockConfig, out_dir: str, log=print, checkpoint_every_s: float = 30.0,
                        segment_minutes: float | None = None) -> dict:
    """Run (or resume) the study into ``out_dir`` (module docstring); returns the results dict.

    Each run's state is stored every ``checkpoint_every_s`` seconds (:mod:`.resume`), so that a kill loses at
    most that much of it. ``segment_minutes``: after that many minutes of this process, the run under way stores
    its state and the study stops before starting anything new (``results.json`` then has ``paused``: the
    run's key or ``"held-out"``); the same command goes on from there."""
    t_start, t_process = time.time(), time.perf_counter()
    segment_s = None if segment_minutes is None else 60.0 * float(segment_minutes)
    os.makedirs(out_dir, exist_ok=True)
    prev = previous(out_dir, cfg) or {}
    if cfg.cold_compile:
        from hyqjax.io.cache import use_cold_caches

        log(f"cold compile: JAX's persistent cache and Warp's kernel cache in {use_cold_caches()} (empty)")
    config = dict(_config(cfg), methods=_methods_union(prev.get("config", {}).get("methods", []), cfg.methods))
    res = dict(kind="wallclock", complete=False, provenance=provenance(seed=cfg.seed),
               device=str(jax.devices()[0].device_kind), config=config,
               charges=dict(prev.get("charges", {})), runs=dict(prev.get("runs", {})),
               heldout=dict(prev.get("heldout", {})))
    if "charges_remeasured" in prev:
        res["charges_remeasured"] = dict(prev["charges_remeasured"])

    def save():
        res["wall_s"] = time.time() - t_start + prev.get("wall_s", 0.0)
        write_json(os.path.join(out_dir, "results.json"), res)

    base = start_params(cfg)
    params = {d: schedule.make(d, cfg.groups) for d in cfg.dims}
    evaluator = forward.SuccessEvaluator(params[cfg.dims[0]], base, cfg.train_duration, cfg.impl, cfg.completed_weight)
    res["start_base"] = start_settings(cfg.start_preset)
    res["impl"] = evaluator.setup.impl  # the simulator the forward runs use (cfg.impl resolved by their setup)
    # compile charges are re-measured in every process (a resumed study's programs compile again); the stored ones
    # stay as first measured (record_charges)
    charges = search.Charges()
    n_members = cfg.popsize + 1
    todo = [(m, d) for d in cfg.dims for m in cfg.methods if run_key(m, d) not in res["runs"]]
    for key in res["runs"]:  # a stored state left by a kill between a run's results.json and its removal
        resume.RunCheckpoint(out_dir, key, {}).remove()
    log(f"forward success program: {n_members} members x {cfg.train_instances} scenarios x {cfg.train_duration:g} s "
        f"per generation, impl {res['impl']}; it compiles in the first search method's clock and is charged to the "
        f"others")
    grad = None
    if any(m in search.USES_GRADIENT for m, _ in todo):
        log("snapshot windows for the gradient (MJX-JAX) ...")
        with heartbeat(log, lambda t0=time.perf_counter(): f"  snapshot windows: {time.perf_counter() - t0:.0f} s"):
            grad = GradientPrograms(cfg, base, charges, log)
    res.pop("paused", None)

    def pause(what):
        res["paused"] = what
        record_charges(res, charges.seconds)
        save()
        log(f"paused after {(time.perf_counter() - t_process) / 60:.1f} min (--segment-minutes {segment_minutes:g}) "
            f"at {what}: the same command goes on from there")
        return res

    for m, d in todo:
        store = resume.RunCheckpoint(out_dir, run_key(m, d), _run_fingerprint(cfg, m), checkpoint_every_s,
                                     segment_s, log, t_process)
        if resume.segment_over(segment_s, t_process):
            return pause(run_key(m, d))
        log(f"{run_key(m, d)} ({params[d].size} parameters): {cfg.wall_minutes} min budget")
        try:
            r = run_method(m, params[d], cfg, evaluator, charges, grad, base, log, store)
        except resume.Paused:
            return pause(run_key(m, d))
        res["runs"][run_key(m, d)] = r
        record_charges(res, charges.seconds)
        save()
        store.remove()
        log(f"{run_key(m, d)}: done, {r['physics_steps']:,} physics steps, {len(r['log'])} iterations, "
            f"{r['charged_s']:.1f} s charged compile"
            + (f", MuJoCo Warp's kernel build {r['kernel_build_s']:.1f} s (not in the budget)"
               if r["kernel_build_s"] >= 0.05 else ""))
    record_charges(res, charges.seconds)
    save()
    # ---- held-out
    members = heldout_members(cfg, res, params, base)
    left = [k for k in members if k not in res["heldout"]]
    sc, heights = forward.heldout_scenarios(cfg.heldout, cfg.heldout_seed)
    res["heldout_set"] = dict(instances=sc.batch_size, seed=cfg.heldout_seed, duration=cfg.heldout_duration,
                              heights=[float(h) for h in forward.HELDOUT_HEIGHTS], ranges=forward.HELDOUT_RANGES,
                              trained_heights=[float(h) for h in cfg.train_heights],
                              train_ranges=forward.SPREADS[cfg.train_spread])
    if left and resume.segment_over(segment_s, t_process):
        return pause("held-out")
    if left:
        log(f"held-out: {len(left)} parameter sets x {sc.batch_size} instances x {cfg.heldout_duration:g} s "
            f"({len(left) * sc.batch_size * round(cfg.heldout_duration / 0.002):,} physics steps) ...")
        # the training program serves the held-out runs when they have its duration and batch shape
        same = (cfg.heldout_duration == cfg.train_duration
                and cfg.heldout_chunk * sc.batch_size == (cfg.popsize + 1) * cfg.train_instances)
        hev = evaluator if same else forward.SuccessEvaluator(params[cfg.dims[0]], base, cfg.heldout_duration, cfg.impl)
        t = time.perf_counter()

        def done(i, cols):
            res["heldout"][left[i]] = summarize(heights, cols)
            save()

        with heartbeat(log, lambda: f"  held-out: {len(res['heldout'])} of {len(members)} sets done, "
                       f"{time.perf_counter() - t:.0f} s"):
            forward.evaluate_sets(
                hev, [members[k] for k in left], sc, cfg.heldout_chunk, done=done,
                progress=lambda a, n, w: log(f"  held-out {a}/{n} sets ({time.perf_counter() - t:.1f} s)"))
    res["budget_curves"] = budget_curves(res)
    # ---- gradient diagnostics (outside every method's clock): for every parameterisation with a gradient-method
    # run whose diagnostics are missing or cover fewer evaluated iterates than there are now
    res["diagnostics"] = dict(prev.get("diagnostics", {}))
    due = [d for d in cfg.dims if any(r["dim"] == d and r["method"] in search.GRADIENT_METHODS
                                      for r in res["runs"].values())
           and res["diagnostics"].get(d, {}).get("iterates") != diagnostic_iterates(res, members, d)]
    if due:
        if grad is None:
            log("snapshot windows for the gradient diagnostics (MJX-JAX) ...")
            grad = GradientPrograms(cfg, base, search.Charges(), log)
        for d in due:
            with heartbeat(log, lambda t0=time.perf_counter(), d=d: f"  gradient diagnostics on {d}: "
                           f"{time.perf_counter() - t0:.0f} s"):
                grad.programs(params[d])
                diag = gradient_diagnostics(cfg, res, {d: params[d]}, base, grad, members)[d]
                diag["step_cost"] = grad.step_cost(params[d])
            res["diagnostics"][d] = diag
            log(step_cost_line(d, diag["step_cost"], cfg.grad_mode))
            save()
    res["complete"] = True
    save()
    return res


def heldout_members(cfg: WallClockConfig, res: dict, params: dict, base) -> dict:
    """Name -> (parameterisation, theta, base CrawlParams) of every set the held-out evaluation runs."""
    p0 = params[cfg.dims[0]]
    # Table I as every study ran it (the tuned coordinates of the default crawl's start, the paper's crawl around)
    t1 = p0.theta_of(crawl.CrawlParams.make(shin_remedy=cfg.remedy))
    out = {"table1": (p0, t1, crawl.CrawlParams.make()), "start": (p0, start_theta(p0, start_point(cfg)), base)}
    for key, r in res["runs"].items():
        for pt in r["points"]:
            out[member_key(r["method"], r["dim"], pt["seconds"])] = (params[r["dim"]], np.asarray(pt["theta"]), base)
    return out


