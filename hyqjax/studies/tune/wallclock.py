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
import dataclasses
import json
import os
import threading
import time

import jax
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.io.atomic import provenance, write_json
from hyqjax.sim import backend
from hyqjax.studies.tune import forward, schedule, search
from hyqjax.studies.tune.gradient_programs import (WINDOW_SEED_OFFSET, GradientPrograms,
                                                  diagnostic_iterates, gradient_diagnostics)
from hyqjax.studies.tune.wallclock_results import budget_curves, member_key, summarize
from hyqjax.studies.tune import space as spmod

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


def generation_seed(seed: int, dim: str) -> int:
    """The seed of the training scenarios of the search methods on parameterisation ``dim``."""
    return seed + 1 + 1000 * list(schedule.NAMES).index(dim)


def training_seeds(seed: int) -> tuple:
    """Every seed the training draws of a study with ``seed`` use (the validation seed must be none of them)."""
    return (seed, seed + WINDOW_SEED_OFFSET) + tuple(generation_seed(seed, d) for d in schedule.NAMES)


def run_key(method: str, dim: str) -> str:
    return f"{method}/{dim}"


@dataclasses.dataclass(frozen=True)
class WallClockConfig:
    """Settings of the study (module docstring); every field is checked at construction (one line naming it)."""

    methods: tuple = search.METHODS
    dims: tuple = ("shared", "per_leg_cond")
    wall_minutes: tuple = (1.0, 3.0, 10.0)
    groups: tuple = spmod.DEFAULT_GROUPS
    remedy: bool = True
    seed: int = 0
    # success-driven search
    popsize: int = 16
    train_instances: int = 32
    train_duration: float = 24.0
    sigma: float = 0.3
    completed_weight: float = 0.1
    # gradient (MJX-JAX)
    grad_train_per_height: int = 2
    windows_per_scenario: int = 2
    window_lead: float = 10.0
    window_ticks: int = 500
    lr: float = 0.1
    #: tangents of the tuning step: 0 = exact ``jacfwd`` (``P``); ``K > 0`` = the forward-gradient estimate from
    #: ``K`` random directions (:func:`.objective.make_value_and_forward_gradient`, unbiased, ``(P + 1) / K``
    #: times the variance of one window's gradient)
    grad_directions: int = 0
    hybrid_split: float = 0.5
    #: the hybrid re-takes the gradient's snapshot windows under the iterate its gradient starts from (in its
    #: clock: the capture's compile and forward run), instead of descending from the start point's gait
    retake_windows: bool = False
    # held-out
    heldout: int = 2000
    heldout_seed: int = 7777
    heldout_duration: float = 24.0
    heldout_chunk: int = 8
    #: MJX implementation of the forward runs (search, held-out); the gradient always runs under impl jax
    impl: str = "auto"
    #: warm starts: ``(("method/dim", theta), ...)``, the start of that method on that parameterisation
    start_from: tuple = ()
    #: charge each method the compile of its programs (False: only what it runs; e.g. with a warm compile cache)
    charge_compile: bool = True
    #: compile every program cold: JAX's persistent compilation cache and Warp's kernel cache in fresh empty
    #: directories of this process (:func:`hyqjax.io.cache.use_cold_caches`), so no process profits from another's
    cold_compile: bool = False
    #: closed-loop validation selection (:class:`.search.Selection`): every method returns its best iterate by
    #: clean success on ``select_instances`` fixed validation scenarios (drawn like training from ``select_seed``),
    #: validated every ``select_every`` iterations and / or ``select_every_s`` seconds, paid from its clock.
    #: The default, (16 + 1) x 32 = 544, is the rows of a default generation: the selection runs on the forward
    #: program the search already compiled. 0: no selection (the last iterate is returned)
    select_instances: int = 544
    select_every: int = 5
    select_every_s: float = 0.0
    select_seed: int = 5555

    def __post_init__(self):
        backend.validate_impl(self.impl)
        bad = [m for m in self.methods if m not in search.METHODS]
        if bad or not self.methods or len(set(self.methods)) != len(self.methods):
            raise ValueError(f"methods must be distinct names among {list(search.METHODS)}, got {list(self.methods)}")
        bad = [d for d in self.dims if d not in schedule.NAMES]
        if bad or not self.dims or len(set(self.dims)) != len(self.dims):
            raise ValueError(f"dims must be distinct names among {list(schedule.NAMES)}, got {list(self.dims)}")
        spmod.ParamSpace.make(self.groups)
        wm = tuple(self.wall_minutes)
        if not wm or any(not (0.0 < float(x) <= 600.0) for x in wm) or list(wm) != sorted(set(wm)):
            raise ValueError(f"wall_minutes must be increasing values in (0, 600] minutes, got {list(wm)}")
        for k, lo, hi in (("popsize", 2, 4096), ("train_instances", 4, 100000), ("grad_train_per_height", 1, 1000),
                          ("windows_per_scenario", 1, 8), ("window_ticks", 1, 20000), ("heldout", 1, 10**6),
                          ("grad_directions", 0, 4096),
                          ("heldout_chunk", 1, 4096), ("seed", 0, 2**31 - 1), ("heldout_seed", 0, 2**31 - 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if "open_es" in self.methods and self.popsize % 2:
            raise ValueError(f"popsize must be even with open_es (it samples antithetic pairs), got {self.popsize}")
        for k in ("charge_compile", "cold_compile", "retake_windows"):
            if not isinstance(getattr(self, k), bool):
                raise ValueError(f"{k} must be True or False, got {getattr(self, k)!r}")
        for k, lo, hi in (("select_instances", 0, 10**6), ("select_every", 0, 10**5), ("select_seed", 0, 2**31 - 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if not 0.0 <= float(self.select_every_s) <= 3600.0:
            raise ValueError(f"select_every_s must be in [0, 3600] s, got {self.select_every_s}")
        if self.select_instances % len(forward.TRAIN_HEIGHTS):
            raise ValueError(f"select_instances must be a multiple of {len(forward.TRAIN_HEIGHTS)} (one share per "
                             f"training height; 0: no selection), got {self.select_instances}")
        if self.select_instances and not (self.select_every > 0 or self.select_every_s > 0):
            raise ValueError("select_every (iterations) or select_every_s (seconds) must be > 0 with "
                             f"select_instances {self.select_instances}")
        if self.select_seed in training_seeds(self.seed) or self.select_seed == self.heldout_seed:
            raise ValueError(f"select_seed must differ from heldout_seed ({self.heldout_seed}) and the training "
                             f"draws' seeds ({', '.join(map(str, training_seeds(self.seed)))}), got {self.select_seed}")
        if self.train_instances % len(forward.TRAIN_HEIGHTS):
            raise ValueError(f"train_instances must be a multiple of {len(forward.TRAIN_HEIGHTS)} (one share per "
                             f"training height), got {self.train_instances}")
        if self.heldout_seed == self.seed:
            raise ValueError(f"heldout_seed must differ from seed (held-out scenarios), got {self.heldout_seed}")
        for k, lo, hi in (("train_duration", 0.1, 120.0), ("heldout_duration", 0.1, 120.0), ("window_lead", 0.1, 60.0)):
            if not (lo <= float(getattr(self, k)) <= hi):
                raise ValueError(f"{k} must be in [{lo}, {hi}] s, got {getattr(self, k)}")
        for k, lo, hi in (("sigma", 0.0, 5.0), ("lr", 0.0, 1.0), ("hybrid_split", 0.0, 1.0)):
            if not (lo < float(getattr(self, k)) < hi or (k != "hybrid_split" and float(getattr(self, k)) == hi)):
                end = ")" if k == "hybrid_split" else "]"
                raise ValueError(f"{k} must be in ({lo}, {hi}{end}, got {getattr(self, k)}")
        if not (0.0 <= self.completed_weight <= 10.0):
            raise ValueError(f"completed_weight must be in [0, 10], got {self.completed_weight}")
        if not isinstance(self.remedy, bool):
            raise ValueError(f"remedy must be True or False, got {self.remedy!r}")
        for key, theta in self.start_from:
            m, _, d = str(key).partition("/")
            if m not in self.methods or d not in self.dims:
                raise ValueError(f"start_from names {key!r}, not a run of this study ({list(self.methods)} on "
                                 f"{list(self.dims)})")
            size = schedule.make(d, self.groups).size
            if len(theta) != size or not np.all(np.isfinite(np.asarray(theta, float))):
                raise ValueError(f"start_from {key!r} must be {size} finite numbers, got {len(theta)}")

    @property
    def checkpoints_s(self) -> tuple:
        return tuple(60.0 * float(m) for m in self.wall_minutes)

    def to_dict(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), default=list))

    @staticmethod
    def defaults() -> dict:
        """Every setting's default, as :meth:`to_dict` writes it (no checks run)."""
        fields = {f.name: f.default for f in dataclasses.fields(WallClockConfig)}
        return json.loads(json.dumps(fields, default=list))


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
            return evaluator(thetas, forward.train_scenarios(cfg.train_instances, gen_seed, g), param=param)

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
    heights and ranges) from ``select_seed``; never the held-out set."""
    return forward.train_scenarios(cfg.select_instances, cfg.select_seed, 0)


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
                              trained_heights=list(forward.TRAIN_HEIGHTS), train_ranges=forward.TRAIN_RANGES)
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
            sc_ = diag["step_cost"]
            log(f"gradient on {d}: one jacfwd step {sc_['jacfwd_s']:.3f} s = {sc_['jacfwd_over_value']:.1f} forward "
                f"windows ({sc_['window_value_s']:.3f} s, one candidate, MJX-JAX)"
                + (f"; forward gradient ({sc_['forward_gradient_directions']} directions) "
                   f"{sc_['forward_gradient_s']:.3f} s = {sc_['forward_gradient_over_value']:.1f}"
                   if "forward_gradient_s" in sc_ else ""))
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


