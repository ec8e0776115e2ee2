"""One method's run in the equal-wall-clock study (:mod:`.wallclock`): its clock, trace and selection, the
hybrid's two phases, the compile charges it pays, and the storing and resuming of its state in the middle of its
budget (:mod:`.resume`)."""
from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from hyqjax.studies.tune import forward, guided, resume, schedule, search
from hyqjax.studies.tune.gradient_programs import GradientPrograms
from hyqjax.studies.tune.names import NO_LINE_SEARCH
from hyqjax.studies.tune.wallclock_config import WallClockConfig, generation_seed, start_point, start_theta


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

def run_method(method: str, param: schedule.Parameterisation, cfg: WallClockConfig, evaluator: forward.SuccessEvaluator,
               charges: search.Charges, grad: GradientPrograms | None, base, log=print,
               store: resume.RunCheckpoint | None = None) -> dict:
    """One method on one parameterisation under the wall-clock budget: its checkpoints and log. With ``store``,
    the run's state is stored as it goes and a stored state is resumed (:mod:`.resume`); at the end of a
    segment :class:`.resume.Paused` is raised."""
    theta0 = dict(cfg.start_from).get(run_key(method, param.name))
    theta0 = start_theta(param, start_point(cfg)) if theta0 is None else np.asarray(theta0, np.float64)
    if method in search.USES_GRADIENT:  # compiled (and charged) before the clock starts
        with heartbeat(log, lambda t0=time.perf_counter(): f"  compiling the gradient programs for {param.name} "
                       f"({param.size} tangents): {time.perf_counter() - t0:.0f} s"):
            grad.programs(param, line_search=method not in NO_LINE_SEARCH)
    clock = search.Clock()
    selection = None
    if cfg.select_instances:
        sel_sc = validation_scenarios(cfg)

        def f_select(thetas):
            with charges.track(selection_program(cfg)):  # compiles in this clock unless an earlier method did
                return evaluator(thetas, sel_sc, param=param)

        selection = search.Selection(f_select, cfg.select_every, cfg.select_every_s,
                                     keep=cfg.final_candidates if cfg.final_instances else 1)
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

    t_wall, stored = time.perf_counter(), (store.load() if store is not None else None)
    wall_before = 0.0 if stored is None else float(stored["wall_s"])
    segment = 1 if stored is None else int(stored["segments"]) + 1
    if stored is not None:
        clock.restore(stored["clock"])
        trace.restore(stored["trace"])
        log(f"  {run_key(method, param.name)}: resuming at {clock.elapsed():.1f} s of its budget, iteration "
            f"{len(trace.log)} (its programs compile again with the clock stopped)")
        with clock.paused():
            _warm_up(method, param, cfg, evaluator, charges, theta0, stored["phase"])

    def hook(phase):
        def checkpoint(method_state):
            if store is not None and store.due():
                store.save(dict(clock=clock.state(), trace=trace.state(), phase=phase, method=method_state(),
                                wall_s=wall_before + time.perf_counter() - t_wall, segments=segment))
                if store.segment_over():
                    raise resume.Paused(run_key(method, param.name))
        return checkpoint

    beat = heartbeat(log, lambda: f"  {run_key(method, param.name)}: {clock.elapsed():7.1f} / "
                     f"{cfg.checkpoints_s[-1]:.0f} s (charged compile {clock.charged:.1f} s), "
                     f"{clock.physics_steps:,} physics steps, {len(trace.log)} iterations"
                     + ("" if trace.log else " (the first one compiles its programs unless an earlier run did)"))
    with beat:
        _run(method, param, cfg, charges, grad, clock, trace, theta0, f_gen, progress, log, stored, hook)
    points = trace.finish(clock)
    final = None
    cands = selection.candidates() if selection is not None and cfg.final_instances else []
    if len(cands) > 1:
        t0, s0 = time.perf_counter(), clock.physics_steps
        sc = forward.train_scenarios(cfg.final_instances, cfg.select_seed, 1, cfg.train_heights, cfg.train_spread)
        extra = len(cands) - len(selection.top)
        log(f"  {run_key(method, param.name)}: final re-evaluation of the {len(selection.top)} best validated "
            f"iterates" + (" and the start point" if extra else "") + f" on {cfg.final_instances} further "
            f"scenarios (after the budget)")
        with charges.track(f"forward/final_{len(cands)}x{cfg.final_instances}"):
            final = search.final_choice(cands, cfg.select_instances, lambda th: evaluator(th, sc, param=param))
        final.update(wall_s=time.perf_counter() - t0, after_budget=True)
        clock.physics_steps = s0 + final["physics_steps"]
        row = final["candidates"][final["chosen"]]
        points[-1].update(theta=np.asarray(final.pop("theta")).tolist(), selected_iteration=row["iteration"],
                          validation_clean=row["pooled_clean"], validation_completed=row["pooled_completed"])
    return dict(method=method, dim=param.name, size=param.size, points=points, log=trace.log,
                selection=None if selection is None else dict(
                    instances=cfg.select_instances, seed=cfg.select_seed, every=cfg.select_every,
                    every_s=cfg.select_every_s, log=selection.log,
                    physics_steps=int(sum(r["physics_steps_run"] for r in selection.log)),
                    wall_s=float(sum(r["wall_s_run"] for r in selection.log))),
                final_reevaluation=final,
                charged_s=clock.charged, wall_s=wall_before + time.perf_counter() - t_wall, elapsed_s=clock.elapsed(),
                kernel_build_s=clock.kernel_build(),
                segments=segment,
                physics_steps=int(clock.physics_steps), theta=points[-1]["theta"],
                params=describe(param, np.asarray(points[-1]["theta"])),
                **({"guided_std": guided.sampling_std(cfg.sigma, param.size)} if method in search.GUIDED_METHODS
                   else {}))


def describe(param: schedule.Parameterisation, theta) -> dict:
    """``param.describe(theta)``, or, for an iterate so far out that a mapped value rounds onto the edge of its
    declared range (a search that drifted where every run scores alike), the reason it cannot be described; the
    run's ``theta`` is kept either way."""
    try:
        return param.describe(theta)
    except ValueError as e:
        return {"not_describable": str(e)}


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
    out = ["forward"] if method in search.SEARCH_METHODS + search.GUIDED_METHODS + search.BLEND_METHODS \
        or method == "hybrid" else []
    if cfg.select_instances and selection_program(cfg) not in out:
        out.append(selection_program(cfg))
    return out


def _warm_up(method, param, cfg, evaluator, charges, theta0, phase) -> None:
    """A resumed run's forward programs compiled again (their outputs dropped), before its clock goes on."""
    if method in search.SEARCH_METHODS + search.GUIDED_METHODS + search.BLEND_METHODS or phase["name"] == "search":
        with charges.track("forward"):
            evaluator(np.repeat(np.asarray(theta0, np.float64)[None], cfg.popsize + 1, 0),
                      forward.train_scenarios(cfg.train_instances, generation_seed(cfg.seed, param.name), 0,
                                              cfg.train_heights, cfg.train_spread), param=param)
    if cfg.select_instances:
        with charges.track(selection_program(cfg)):
            evaluator(np.asarray(theta0, np.float64)[None], validation_scenarios(cfg), param=param)


def _run(method, param, cfg, charges, grad, clock, trace, theta0, f_gen, progress, log, stored=None, hook=None):
    """The method's loop (the hybrid's two phases); ``stored``: a run's state to go on from (:mod:`.resume`);
    ``hook(phase)``: the checkpoint function of a phase: ``{"name": "search"}`` (every run starts in it; a search
    method never leaves it) or ``{"name": "gradient", "theta_start": ...}``. The compile charges of a phase are
    paid when it starts, never again on a resume."""
    phase = {"name": "search"} if stored is None else stored["phase"]
    state = None if stored is None else stored["method"]
    hook = hook or (lambda phase: None)
    charge = clock.charge if cfg.charge_compile else (lambda s: None)
    if stored is None:
        for name in forward_programs(method, cfg):
            if name in charges.seconds:
                charge(charges.seconds[name])  # compiled by an earlier method: charged as if compiled here
        trace.begin(clock)  # with a selection: the start point's validation (compiles it here if no method did)
    if method in search.GUIDED_METHODS + search.BLEND_METHODS:  # the gradient inside a population search
        step_fn, _, _ = grad.programs(param, line_search=False)
        if stored is None:
            for name in grad.charge_names(param)[:2]:  # the windows and the tuning step (no line search)
                charge(charges.seconds[name])
        common = dict(grad_cost=grad.step_costs[param.name], progress=progress, resume=state,
                      checkpoint=hook(phase))
        if method in search.GUIDED_METHODS:
            guided.run_guided(f_gen, step_fn, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                              alpha=cfg.guided_alpha, subspace=cfg.guided_subspace, lr=cfg.guided_lr,
                              grad_every=cfg.guided_grad_every, **common)
        else:
            from hyqjax.studies.tune import blend

            blend.run_blend(f_gen, step_fn, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                            lr=cfg.blend_lr, gamma=cfg.blend_gamma, **common)
        return
    if method in search.SEARCH_METHODS:
        search.run_search(method, f_gen, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                          progress=progress, resume=state, checkpoint=hook(phase), restart_stall=cfg.restart_stall)
        return
    theta_start = theta0
    if method == "hybrid" and phase["name"] == "search":
        mean = search.run_search("cma_es", f_gen, theta0, cfg.popsize, cfg.sigma, clock, trace, seed=cfg.seed,
                                 progress=progress, stop_at=cfg.hybrid_split * cfg.checkpoints_s[-1],
                                 resume=state, checkpoint=hook(phase))
        theta_start, state = (mean if trace.select is None else trace.returned), None
        log(f"  hybrid: CMA-ES until {clock.elapsed():.1f} s, then the gradient from its "
            + ("mean" if trace.select is None else "selected iterate"))
    elif method == "hybrid":
        theta_start = np.asarray(phase["theta_start"], np.float64)
    step_fn, evaluate, cost = grad.programs(param)
    if phase["name"] == "search":  # the gradient phase starts here, not in a stored one
        for name in grad.charge_names(param):
            charge(charges.seconds[name])
    retaken = method == "hybrid" and cfg.retake_windows
    if retaken:
        if state is None:
            t = clock.elapsed()
            clock.physics_steps += grad.retake(param, theta_start)
            log(f"  hybrid: windows re-taken at the gradient's start iterate ({clock.elapsed() - t:.1f} s, "
                f"{int(np.asarray(grad.win.valid).sum())} of {grad.win.size} triggered)")
        else:  # taken and paid for before the stop; taken again with the clock stopped
            with clock.paused():
                grad.retake(param, theta_start)
    try:
        search.run_gradient(step_fn, evaluate, theta_start, clock, trace, lr=cfg.lr, step_cost=cost,
                            progress=progress, resume=state,
                            checkpoint=hook({"name": "gradient", "theta_start": np.asarray(theta_start, np.float64)}))
    finally:
        if retaken:
            grad.restore()
