"""The equal-wall-clock tuning study: every method, every parameterisation, the same wall-clock budget on one GPU.

:func:`run_wallclock_study` (``hyqjax tune --study``, ``python -m experiments.tune_study``):

1. **compile charges** (:class:`.search.Charges`): the forward success program (population ``N = popsize + 1``
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
   default) every method returns the best of its validated iterates (:class:`.search.Selection`: the start
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

Resuming: ``results.json`` is written after every run and every held-out chunk; the same command on the same
directory keeps every finished run and every finished held-out member (a run cut off by a kill starts over: its
wall-clock budget is measured from its own start). Another configuration in the directory is refused, except
for ``methods``: one process per method (each with ``cold_compile``, so that none loads another's compiled
programs) composes into one results file.
"""
from __future__ import annotations

import contextlib
import json
import os
import threading
import time

import jax
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.io.atomic import provenance, write_json
from hyqjax.studies.tune import forward, schedule, search
from hyqjax.studies.tune.gradient_programs import (GradientPrograms,
                                                  diagnostic_iterates, gradient_diagnostics)
from hyqjax.studies.tune.wallclock_config import WallClockConfig, generation_seed
from hyqjax.studies.tune.wallclock_results import budget_curves, member_key, step_cost_line, summarize

#: What ``hyqjax tune`` runs by default (declared in :mod:`hyqjax.studies.tune.names`, where the measurement behind
#: the choice is stated).
from hyqjax.studies.tune.names import DEFAULT_DIM, DEFAULT_METHOD  # noqa: E402,F401


@contextlib.contextmanager
def heartbeat(log, message, every: float = 5.0):
    """Call ``log(message())`` every ``every`` seconds while the block runs (compiles and long batches report
    progress too)."""
    stop = threading.Event()

    def beat():
        while not stop.wait(every):
            log(message())

    th = threading.Thread(target=beat, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join()


def run_key(method: str, dim: str) -> str:
    return f"{method}/{dim}"


def start_params(cfg: WallClockConfig) -> crawl.CrawlParams:
    """Where every method starts: Table I and the default crawl, with the shin-strike remedy if ``cfg.remedy``."""
    return crawl.CrawlParams.make(shin_remedy=cfg.remedy)


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
    if prev.get("kind") != "wallclock" or _fingerprint(prev.get("config", {})) != _fingerprint(cfg.to_dict()):
        raise RuntimeError(f"{out_dir} holds a tuning study of another configuration; use another --out or remove it")
    return prev


def _fingerprint(config: dict) -> dict:
    """The settings that must agree for runs to share one results file: all but ``methods`` (one process per
    method composes into one study; each run is stored under its own method's key)."""
    return {k: v for k, v in config.items() if k != "methods"}


def _methods_union(*lists) -> list:
    seen = [m for ms in lists for m in ms]
    return [m for m in search.METHODS if m in seen]


def run_method(method: str, param: schedule.Parameterisation, cfg: WallClockConfig, evaluator: forward.SuccessEvaluator,
               charges: search.Charges, grad: GradientPrograms | None, base, log=print) -> dict:
    """One method on one parameterisation under the wall-clock budget: its checkpoints and log."""
    theta0 = dict(cfg.start_from).get(run_key(method, param.name))
    theta0 = param.theta_of(base) if theta0 is None else np.asarray(theta0, np.float64)
    if method in search.GRADIENT_METHODS:  # compiled (and charged) before the clock starts
        with heartbeat(log, lambda t0=time.perf_counter(): f"  compiling the gradient programs for {param.name} "
                       f"({param.size} tangents): {time.perf_counter() - t0:.0f} s"):
            grad.programs(param)
    clock = search.Clock()
    selection = None
    if cfg.select_instances:
        sel_sc = validation_scenarios(cfg)

        def f_select(thetas):
            with charges.track(selection_program(cfg)):  # compiles in this clock unless an earlier method did
                return evaluator(thetas, sel_sc, param=param)

        selection = search.Selection(f_select, cfg.select_every, cfg.select_every_s)
    trace = search.Trace(cfg.checkpoints_s, theta0, select=selection)
    gen_seed = generation_seed(cfg.seed, param.name)

    def f_gen(thetas, g):
        with charges.track("forward"):  # the first use in this process compiles, inside this method's clock
            return evaluator(thetas, forward.train_scenarios(cfg.train_instances, gen_seed, g, cfg.train_heights,
                                                            cfg.train_spread), param=param)

    last = [0.0]

    def progress(clk, tr):
        if clk.elapsed() - last[0] >= 5.0 or tr.done(clk):
            last[0] = clk.elapsed()
            row = tr.log[-1] if tr.log else {}
            val = row.get("iterate_fitness", row.get("loss_at_theta"))
            what = "fitness" if "iterate_fitness" in row else "window loss"
            sel = tr.select.best if tr.select is not None else None
            log(f"  {run_key(method, param.name)}: {clk.elapsed():7.1f} / {cfg.checkpoints_s[-1]:.0f} s, "
                f"{clk.physics_steps:,} physics steps, {len(tr.log)} iterations"
                + (f", iterate {what} {val:.3f}" if val is not None else "")
                + (f", selected: validation clean {sel[0][0]:.3f} ({len(tr.select.log)} validations)" if sel else ""))

    t_wall = time.perf_counter()
    beat = heartbeat(log, lambda: f"  {run_key(method, param.name)}: {clock.elapsed():7.1f} / "
                     f"{cfg.checkpoints_s[-1]:.0f} s (charged compile {clock.charged:.1f} s), "
                     f"{clock.physics_steps:,} physics steps, {len(trace.log)} iterations"
                     + ("" if trace.log else " (the first one compiles its programs unless an earlier run did)"))
    with beat:
        _run(method, param, cfg, charges, grad, clock, trace, theta0, f_gen, progress, log)
    points = trace.finish(clock)
    return dict(method=method, dim=param.name, size=param.size, points=points, log=trace.log,
                selection=None if selection is None else dict(
                    instances=cfg.select_instances, seed=cfg.select_seed, every=cfg.select_every,
                    every_s=cfg.select_every_s, log=selection.log,
                    physics_steps=int(sum(r["physics_steps_run"] for r in selection.log)),
                    wall_s=float(sum(r["wall_s_run"] for r in selection.log))),
                charged_s=clock.charged, wall_s=time.perf_counter() - t_wall, elapsed_s=clock.elapsed(),
                physics_steps=int(clock.physics_steps), theta=points[-1]["theta"],
                params=param.describe(np.asarray(points[-1]["theta"])))


def validation_scenarios(cfg: WallClockConfig):
    """The fixed validation batch of the selection: ``select_instances`` scenarios drawn like training (training
    heights and spread) from ``select_seed``; never the held-out set."""
    return forward.train_scenarios(cfg.select_instances, cfg.select_seed, 0, cfg.train_heights, cfg.train_spread)


def selection_program(cfg: WallClockConfig) -> str:
    """The charge name of the selection's forward program: the training program's (``forward``) when it has its
    rows (``select_instances == (popsize + 1) x train_instances``), else a program of its own."""
    rows = cfg.select_instances
    return "forward" if rows == (cfg.popsize + 1) * cfg.train_instances else f"forward/{rows}_rows"


def forward_programs(method: str, cfg: WallClockConfig) -> list:
    """Charge names of the forward (Warp) programs ``method`` runs: training generations and the selection."""
    out = ["forward"] if method in search.SEARCH_METHODS or method == "hybrid" else []
    if cfg.select_instances and selection_program(cfg) not in out:
        out.append(selection_program(cfg))
    return out


def _run(method, param, cfg, charges, grad, clock, trace, theta0, f_gen, progress, log):
    charge = clock.charge if cfg.charge_compile else (lambda s: None)
    for name in forward_programs(method, cfg):
        if name in charges.seconds:
            charge(charges.seconds[name])  # compiled by an earlier method: charged as if compiled here
    trace.begin(clock)  # with a selection: the start point's validation (compiles it here if no method did)
    if method in search.SEARCH_METHODS:
        search.run_search(method, f_gen, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                          progress=progress)
    else:
        theta_start = theta0
        if method == "hybrid":
            mean = search.run_search("cma_es", f_gen, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                                     progress=progress, stop_at=cfg.hybrid_split * cfg.checkpoints_s[-1])
            theta_start = mean if trace.select is None else trace.returned
            log(f"  hybrid: CMA-ES until {clock.elapsed():.1f} s, then the gradient from its "
                + ("mean" if trace.select is None else "selected iterate"))
        step_fn, evaluate, cost = grad.programs(param)
        for name in grad.charge_names(param):
            charge(charges.seconds[name])
        retaken = method == "hybrid" and cfg.retake_windows
        if retaken:
            t = clock.elapsed()
            clock.physics_steps += grad.retake(param, theta_start)
            log(f"  hybrid: windows re-taken at the gradient's start iterate ({clock.elapsed() - t:.1f} s, "
                f"{int(np.asarray(grad.win.valid).sum())} of {grad.win.size} triggered)")
        try:
            search.run_gradient(step_fn, evaluate, theta_start, clock, trace, lr=cfg.lr, step_cost=cost,
                                progress=progress)
        finally:
            if retaken:
                grad.restore()


def run_wallclock_study(cfg: WallClockConfig, out_dir: str, log=print) -> dict:
    """Run (or resume) the study into ``out_dir`` (module docstring); returns the results dict."""
    t_start = time.time()
    os.makedirs(out_dir, exist_ok=True)
    prev = previous(out_dir, cfg) or {}
    if cfg.cold_compile:
        from hyqjax.io.cache import use_cold_caches

        log(f"cold compile: JAX's persistent cache and Warp's kernel cache in {use_cold_caches()} (empty)")
    config = dict(cfg.to_dict(), methods=_methods_union(prev.get("config", {}).get("methods", []), cfg.methods))
    res = dict(kind="wallclock", complete=False, provenance=provenance(seed=cfg.seed),
               device=str(jax.devices()[0].device_kind), config=config,
               charges=dict(prev.get("charges", {})), runs=dict(prev.get("runs", {})),
               heldout=dict(prev.get("heldout", {})))

    def save():
        res["wall_s"] = time.time() - t_start + prev.get("wall_s", 0.0)
        write_json(os.path.join(out_dir, "results.json"), res)

    base = start_params(cfg)
    params = {d: schedule.make(d, cfg.groups) for d in cfg.dims}
    evaluator = forward.SuccessEvaluator(params[cfg.dims[0]], base, cfg.train_duration, cfg.impl, cfg.completed_weight)
    res["impl"] = evaluator.setup.impl  # the simulator the forward runs use (cfg.impl resolved by their setup)
    # compile charges are re-measured in every process (a resumed study's programs compile again)
    charges = search.Charges()
    n_members = cfg.popsize + 1
    todo = [(m, d) for d in cfg.dims for m in cfg.methods if run_key(m, d) not in res["runs"]]
    log(f"forward success program: {n_members} members x {cfg.train_instances} scenarios x {cfg.train_duration:g} s "
        f"per generation, impl {res['impl']}; it compiles in the first search method's clock and is charged to the "
        f"others")
    grad = None
    if any(m in search.GRADIENT_METHODS for m, _ in todo):
        log("snapshot windows for the gradient (MJX-JAX) ...")
        with heartbeat(log, lambda t0=time.perf_counter(): f"  snapshot windows: {time.perf_counter() - t0:.0f} s"):
            grad = GradientPrograms(cfg, base, charges, log)
    for m, d in todo:
        log(f"{run_key(m, d)} ({params[d].size} parameters): {cfg.wall_minutes} min budget")
        r = run_method(m, params[d], cfg, evaluator, charges, grad, base, log)
        res["runs"][run_key(m, d)] = r
        res["charges"].update(charges.seconds)
        save()
        log(f"{run_key(m, d)}: done, {r['physics_steps']:,} physics steps, {len(r['log'])} iterations, "
            f"{r['charged_s']:.1f} s charged compile")
    res["charges"].update(charges.seconds)
    save()
    # ---- held-out
    members = heldout_members(cfg, res, params, base)
    left = [k for k in members if k not in res["heldout"]]
    sc, heights = forward.heldout_scenarios(cfg.heldout, cfg.heldout_seed)
    res["heldout_set"] = dict(instances=sc.batch_size, seed=cfg.heldout_seed, duration=cfg.heldout_duration,
                              heights=[float(h) for h in forward.HELDOUT_HEIGHTS], ranges=forward.HELDOUT_RANGES,
                              trained_heights=[float(h) for h in cfg.train_heights],
                              train_ranges=forward.SPREADS[cfg.train_spread])
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
    out = {"table1": (p0, p0.theta_of(base), crawl.CrawlParams.make()), "start": (p0, p0.theta_of(base), base)}
    for key, r in res["runs"].items():
        for pt in r["points"]:
            out[member_key(r["method"], r["dim"], pt["seconds"])] = (params[r["dim"]], np.asarray(pt["theta"]), base)
    return out


