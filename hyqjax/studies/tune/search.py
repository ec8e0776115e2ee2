"""Tuning methods under a wall-clock budget: success-driven search (CMA-ES, SNES, OpenES, random search), the
closed-loop gradient, and the hybrid (search, then gradient polish).

Every method runs against a :class:`Clock` and returns, for each checkpoint ``c`` (seconds), the iterate it would
hand back had it been stopped at ``c``: the last iterate it had finished by then (the start point if it had
finished none, e.g. while compiling), or with a :class:`Selection` the best of the iterates it had validated by
then on a fixed validation batch (closed-loop clean success; the validations paid from its clock). The clock
counts everything a stand-alone run would pay: the compile of each program the method uses (:class:`Charges`,
measured once per process and *charged* to every method that uses the program, so that a method run after
another does not profit from its compile), the snapshot windows of the gradient, every evaluation and every
optimiser update. Physics steps are counted next to it (tangents of
forward-mode derivatives included).

Success-driven methods (:func:`run_search`) maximise the fitness of :mod:`.forward` (clean success plus
``w_c`` times completed, on ``M`` training scenarios per generation, the same for every member: common random
numbers). Per generation the population and one extra member, the iterate the method would return, run in one
batch (``N = popsize + 1``), so the returned iterate's fitness is logged on the same scenarios:

* ``cma_es``, ``snes``, ``open_es``: ``evosax`` 0.3.2 (jitted ``ask`` / ``tell``; ``tell`` minimises, so it gets
  ``-F``); the iterate is the search distribution's mean;
* ``ipop_cma_es``, ``bipop_cma_es``: CMA-ES with restarts (:mod:`.restarts`: the restart controller around
  evosax's CMA-ES; a larger population runs in chunks of the first one's batch shape);
* ``random_search``: candidates ``theta_0 + sigma z`` around the start; the iterate is the incumbent, replaced
  by a generation's best candidate when that candidate's fitness exceeds the incumbent's on the same scenarios.

The gradient (:func:`run_gradient`) is Adam with the batched line search of :mod:`.optimize` on the closed-loop
window objective of :mod:`.objective` (``jax.jacfwd`` on MJX-JAX; snapshot windows at the start point). The
hybrid (:func:`run_hybrid`) runs CMA-ES for ``split`` of the budget and then the gradient from its mean.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.studies.tune.names import (ANTITHETIC, BLEND_METHODS, GRADIENT_METHODS, GUIDED_METHODS, METHODS,  # noqa: F401
                                       RESTART_METHODS, SEARCH_METHODS, STUDY_METHODS, USES_GRADIENT)
from hyqjax.studies.tune.resume import tree_like


class Clock:
    """Wall seconds since ``start()`` plus the compile time charged so far (:class:`Charges`)."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.charged = 0.0
        self.physics_steps = 0

    def charge(self, seconds: float) -> None:
        self.charged += float(seconds)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0 + self.charged

    def state(self) -> dict:
        return dict(elapsed=self.elapsed(), charged=self.charged, physics_steps=int(self.physics_steps))

    def restore(self, state: dict) -> None:
        """Go on from a stored :meth:`state` (:mod:`.resume`): :meth:`elapsed` continues from its seconds."""
        self.charged, self.physics_steps = float(state["charged"]), int(state["physics_steps"])
        self.t0 = time.perf_counter() - (float(state["elapsed"]) - self.charged)

    @contextlib.contextmanager
    def paused(self):
        """Time inside the block is not counted (a resumed run compiling again what it paid for once)."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.t0 += time.perf_counter() - t


#: JAX's compile events (tracing, lowering to MLIR, XLA's backend compile) that :class:`Charges` adds up.
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
_TRACKING: list = []


def _on_event(name, secs, **_):
    if name in COMPILE_EVENTS:
        for acc in _TRACKING:
            acc[0] += secs


jax.monitoring.register_event_duration_secs_listener(_on_event)


class Charges:
    """Compile seconds per program name: :meth:`track` adds up JAX's compile events (:data:`COMPILE_EVENTS`;
    tracing of nested functions counts once per level) during a program's first use in this process, so no run
    is spent on measuring; :meth:`one_off` keeps the whole time of a one-off setup (e.g. the gradient's snapshot
    windows: compile and forward run)."""

    def __init__(self, known: dict | None = None):
        self.seconds: dict[str, float] = dict(known or {})

    @contextlib.contextmanager
    def track(self, name: str):
        if name in self.seconds:
            yield
            return
        acc = [0.0]
        _TRACKING.append(acc)
        try:
            yield
        finally:
            _TRACKING.remove(acc)
        self.seconds[name] = acc[0]

    def one_off(self, name: str, fn: Callable):
        t = time.perf_counter()
        out = fn()
        self.seconds.setdefault(name, time.perf_counter() - t)
        return out


class Selection:
    """Closed-loop validation selection: the iterate a method returns is the best, by clean success on a FIXED
    validation batch, of the iterates it has validated so far (the start point first).

    ``evaluate(thetas (1, P)) -> dict(clean (1, V), completed (1, V), physics_steps)`` runs one iterate on the
    ``V`` validation scenarios (the forward program of :mod:`.forward`; the study draws them like the training
    scenarios from a seed of their own, never the held-out set). An iterate is validated when it is *due*:
    ``every`` iterations (0: not by iterations) or ``every_s`` seconds of the method's clock (0: not by time) have
    passed since the last validation, and it differs from the last validated iterate (an unchanged incumbent of
    random search is not run again; it stays due until it changes). Its wall time runs on the method's clock and
    its physics steps are added to the clock's, so the selection is paid from the method's budget.

    Score: (clean rate, completed rate) on the validation batch; an iterate replaces the selected one when its
    score is at least as high (ties go to the later iterate, the one with more optimisation behind it)."""

    def __init__(self, evaluate: Callable, every: int = 5, every_s: float = 0.0, keep: int = 1):
        if every <= 0 and every_s <= 0:
            raise ValueError("a selection needs every > 0 iterations or every_s > 0 seconds")
        self.evaluate, self.every, self.every_s = evaluate, int(every), float(every_s)
        #: the ``keep`` best validated iterates, best first: ``[score, iteration, theta]`` (a final re-evaluation
        #: of the top candidates chooses among them, :func:`final_choice`)
        self.keep, self.top = int(keep), []
        self.log: list = []
        self.best: tuple | None = None  # (score, theta)
        self._since, self._t_last, self._theta_last = 0, -math.inf, None

    def due(self, clock: Clock, theta) -> bool:
        self._since += 1
        if self._theta_last is not None and np.array_equal(np.asarray(theta, np.float64), self._theta_last):
            return False
        return bool((self.every > 0 and self._since >= self.every)
                    or (self.every_s > 0 and clock.elapsed() - self._t_last >= self.every_s))

    def validate(self, clock: Clock, theta, iteration: int) -> bool:
        """Run ``theta`` on the validation batch (on ``clock``); True when it becomes the selected iterate."""
        theta = np.asarray(theta, np.float64).copy()
        t0, s0 = clock.elapsed(), clock.physics_steps
        r = self.evaluate(theta[None])
        clock.physics_steps += int(r["physics_steps"])
        score = (float(np.mean(r["clean"][0])), float(np.mean(r["completed"][0])))
        better = self.best is None or score >= self.best[0]
        if better:
            self.best = (score, theta)
        self.top = sorted(self.top + [[list(score), int(iteration), theta]],
                          key=lambda t: (t[0][0], t[0][1], t[1]), reverse=True)[:self.keep]
        self._since, self._t_last, self._theta_last = 0, clock.elapsed(), theta
        self.log.append(dict(iteration=int(iteration), wall_s=round(clock.elapsed(), 3),
                             physics_steps=int(clock.physics_steps), clean=score[0], completed=score[1],
                             selected=bool(better), wall_s_run=round(clock.elapsed() - t0, 3),
                             physics_steps_run=int(clock.physics_steps - s0)))
        return better

    def state(self) -> dict:
        return dict(log=self.log, best=None if self.best is None else [list(self.best[0]), self.best[1]],
                    since=self._since, t_last=self._t_last, theta_last=self._theta_last, top=self.top)

    def restore(self, s: dict) -> None:
        self.top = [[list(t[0]), int(t[1]), np.asarray(t[2], np.float64)] for t in s.get("top", [])]
        self.log = list(s["log"])
        self.best = None if s["best"] is None else (tuple(s["best"][0]), np.asarray(s["best"][1], np.float64))
        self._since, self._t_last = int(s["since"]), float(s["t_last"])
        self._theta_last = None if s["theta_last"] is None else np.asarray(s["theta_last"], np.float64)


@dataclasses.dataclass
class Trace:
    """What a method did: per generation / step a log row; per checkpoint the iterate it would return (with the
    physics steps spent by the last work finished before the checkpoint). With a :class:`Selection`, the iterate
    it would return is the selected one (:meth:`begin` validates the start point)."""

    checkpoints: tuple
    theta0: np.ndarray
    select: Selection | None = None
    log: list = dataclasses.field(default_factory=list)
    points: list = dataclasses.field(default_factory=list)
    _last: tuple = None

    def __post_init__(self):
        self._last = (np.asarray(self.theta0, np.float64).copy(), None)
        self._spent, self._iterations = 0, 0

    def done(self, clock: Clock) -> bool:
        return clock.elapsed() >= self.checkpoints[-1]

    def _pass(self, clock: Clock) -> None:
        """Checkpoints that passed during the work just finished get the iterate from before it."""
        now = clock.elapsed()
        for c in self.checkpoints[len(self.points):]:
            if now < c:
                break
            pt = dict(seconds=float(c), theta=self._last[0].tolist(), physics_steps=int(self._spent))
            pt.update(self._last[1] or {})
            self.points.append(pt)
        self._spent = int(clock.physics_steps)

    def _validate(self, clock: Clock, theta, iteration: int) -> None:
        better = self.select.validate(clock, theta, iteration)
        self._pass(clock)  # checkpoints passed while validating get the iterate selected before
        if better:
            row = self.select.log[-1]
            self._last = (np.asarray(theta, np.float64).copy(),
                          dict(selected_iteration=iteration, validation_clean=row["clean"],
                               validation_completed=row["completed"]))

    @property
    def returned(self) -> np.ndarray:
        """The iterate the method would return now."""
        return self._last[0].copy()

    def begin(self, clock: Clock) -> None:
        """With a selection: validate the start point (on ``clock``), so that an iterate is returned only when it
        validates at least as well as the start. Without one: nothing."""
        if self.select is not None and self.select.best is None:
            self._validate(clock, self.theta0, 0)

    def advance(self, clock: Clock, theta, row: dict | None = None) -> None:
        """Record that ``theta`` is the iterate after the work just finished (``clock`` now); checkpoints that
        passed during that work get the iterate from before it. With a selection, ``theta`` becomes the returned
        iterate only once validated (when due) at least as well as the selected one."""
        self._pass(clock)
        self._iterations += 1
        if row is not None:
            row.update(wall_s=round(clock.elapsed(), 3), physics_steps=int(clock.physics_steps))
            self.log.append(row)
        if self.select is None:
            self._last = (np.asarray(theta, np.float64).copy(), None)
        elif self.select.due(clock, theta):
            self._validate(clock, theta, self._iterations)

    def state(self) -> dict:
        """Everything :meth:`restore` needs to go on as if never stopped (:mod:`.resume`)."""
        return dict(checkpoints=list(self.checkpoints), log=self.log, points=self.points, last=list(self._last),
                    spent=self._spent, iterations=self._iterations,
                    select=None if self.select is None else self.select.state())

    def restore(self, s: dict) -> None:
        if [float(c) for c in s["checkpoints"]] != [float(c) for c in self.checkpoints]:
            raise ValueError(f"stored checkpoints {s['checkpoints']} differ from {list(self.checkpoints)}")
        if (s["select"] is None) != (self.select is None):
            raise ValueError("stored run and this one differ in their selection")
        self.log, self.points = list(s["log"]), list(s["points"])
        self._last = (np.asarray(s["last"][0], np.float64), s["last"][1])
        self._spent, self._iterations = int(s["spent"]), int(s["iterations"])
        if self.select is not None:
            self.select.restore(s["select"])

    def finish(self, clock: Clock) -> list:
        """Checkpoints not reached (the budget ran out at the last one): the iterate returned at the end."""
        for c in self.checkpoints[len(self.points):]:
            pt = dict(seconds=float(c), theta=self._last[0].tolist(), physics_steps=int(self._spent))
            pt.update(self._last[1] or {})
            self.points.append(pt)
        return self.points


def final_choice(top: list, validation_n: int, evaluate: Callable) -> dict:
    """The final re-evaluation of the top candidates of a selection (``top``: ``[score, iteration, theta]``, best
    first, ``score[0]`` the clean rate on ``validation_n`` validation runs): ``evaluate(thetas (K, P)) ->
    dict(clean (K, F), completed (K, F), physics_steps)`` runs them all on ``F`` further scenarios, and the one with
    the best clean rate pooled over both batches (``(n_v c_v + F c_f) / (n_v + F)``, completed breaking ties, then
    the earlier rank) is chosen: a larger validation set than the selection's, so that the returned set is less
    the luck of one batch. Returns ``chosen`` (its index in ``top``), ``theta``, per candidate the rates, and the
    physics steps spent."""
    thetas = np.stack([np.asarray(t[2], np.float64) for t in top])
    r = evaluate(thetas)
    f_clean = np.asarray(r["clean"], np.float64).mean(axis=1)
    f_done = np.asarray(r["completed"], np.float64).mean(axis=1)
    n_f = np.asarray(r["clean"]).shape[1]
    rows = []
    for i, t in enumerate(top):
        pooled = (validation_n * t[0][0] + n_f * f_clean[i]) / (validation_n + n_f)
        pooled_c = (validation_n * t[0][1] + n_f * f_done[i]) / (validation_n + n_f)
        rows.append(dict(iteration=int(t[1]), validation_clean=float(t[0][0]), final_clean=float(f_clean[i]),
                         final_completed=float(f_done[i]), pooled_clean=float(pooled), pooled_completed=float(pooled_c)))
    chosen = max(range(len(rows)), key=lambda i: (rows[i]["pooled_clean"], rows[i]["pooled_completed"], -i))
    return dict(chosen=int(chosen), theta=thetas[chosen], candidates=rows, instances=int(n_f),
                physics_steps=int(r["physics_steps"]))


def make_strategy(method: str, size: int, popsize: int, sigma: float, lr: float = 0.05):
    """An ``evosax`` strategy and its parameters (``std_init`` / ``std_schedule`` = ``sigma``)."""
    import optax
    from evosax.algorithms import CMA_ES, SNES, Open_ES

    sol = jnp.zeros(size, jnp.float32)
    if method == "cma_es":
        es = CMA_ES(population_size=popsize, solution=sol)
        params = es.default_params.replace(std_init=sigma)
    elif method == "snes":
        es = SNES(population_size=popsize, solution=sol)
        params = es.default_params.replace(std_init=sigma)
    elif method == "open_es":
        es = Open_ES(population_size=popsize, solution=sol, optimizer=optax.adam(lr),
                     std_schedule=optax.constant_schedule(sigma))
        params = es.default_params
    else:
        raise ValueError(f"method must be one of {list(SEARCH_METHODS)}, got {method!r}")
    return es, params


def run_search(method: str, f_gen: Callable, theta0, popsize: int, sigma: float, clock: Clock, trace: Trace,
               seed: int = 0, generation0: int = 0, progress: Callable | None = None, stop_at: float | None = None,
               resume: dict | None = None, checkpoint: Callable | None = None, restart_stall: int = 0):
    """Maximise ``f_gen(thetas (N, P), generation) -> dict(fitness (N,), clean, completed, physics_steps)`` with
    ``method`` until ``clock`` passes ``stop_at`` (default the last checkpoint). Returns the final iterate.
    ``checkpoint(state_fn)`` is called after every generation; ``state_fn()`` is the method's state then, which
    ``resume`` takes back (:mod:`.resume`; the clock and trace are the caller's). ``restart_stall``: the restart
    methods' stagnation length (:class:`.restarts.Controller`'s ``stall_generations``)."""
    if method in RESTART_METHODS:
        from hyqjax.studies.tune import restarts

        return restarts.run_restarts(method, f_gen, theta0, popsize, sigma, clock, trace, seed=seed,
                                     progress=progress, stop_at=stop_at, resume=resume, checkpoint=checkpoint,
                                     stall_generations=restart_stall)
    theta0 = np.asarray(theta0, np.float64)
    stop_at = trace.checkpoints[-1] if stop_at is None else stop_at
    key = jax.random.key(seed)
    gen = generation0 if resume is None else int(resume["gen"])
    if method == "random_search":
        rng = np.random.default_rng(seed)
        inc, inc_fit = theta0.copy(), -math.inf
        if resume is not None:
            rng.bit_generator.state, inc, inc_fit = resume["rng"], np.asarray(resume["inc"]), float(resume["inc_fit"])
        while clock.elapsed() < stop_at:
            cand = theta0 + sigma * rng.standard_normal((popsize, theta0.size))
            r = f_gen(np.concatenate([inc[None], cand]), gen)
            clock.physics_steps += r["physics_steps"]
            fit = np.asarray(r["fitness"])
            inc_fit = fit[0]
            i = int(np.argmax(fit[1:]))
            if fit[1 + i] > inc_fit:
                inc, inc_fit = cand[i].copy(), float(fit[1 + i])
            trace.advance(clock, inc, dict(generation=gen, iterate_fitness=float(fit[0]),
                                           iterate_clean=float(np.mean(r["clean"][0])), best_fitness=float(fit.max()),
                                           mean_fitness=float(fit[1:].mean())))
            gen += 1
            if progress:
                progress(clock, trace)
            if checkpoint:
                checkpoint(lambda: dict(gen=gen, rng=rng.bit_generator.state, inc=inc, inc_fit=inc_fit))
        return inc
    es, params = make_strategy(method, theta0.size, popsize, sigma)
    key, k0 = jax.random.split(key)
    state = es.init(k0, jnp.asarray(theta0, jnp.float32), params)
    ask, tell = jax.jit(es.ask), jax.jit(es.tell)
    if resume is not None:
        key, state = jax.random.wrap_key_data(jnp.asarray(resume["key"])), tree_like(state, resume["state"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            pop, _ = ask(key, state, params)
            tell(key, pop, jnp.zeros(popsize, jnp.float32), state, params)
    while clock.elapsed() < stop_at:
        key, ka, kt = jax.random.split(key, 3)
        pop, state = ask(ka, state, params)
        mean = np.asarray(state.mean, np.float64)
        r, fit = evaluate_generation(f_gen, mean, pop, gen, clock)
        state, new_mean = tell_generation(tell, kt, pop, fit, state, params, method, gen)
        # the returned iterate after this generation is the new mean (its fitness is measured next generation)
        trace.advance(clock, new_mean, dict(generation=gen, iterate_fitness=float(fit[0]),
                                            iterate_clean=float(np.mean(r["clean"][0])),
                                            best_fitness=float(fit[1:].max()), mean_fitness=float(fit[1:].mean()),
                                            std=float(np.mean(np.asarray(state.std)))))
        gen += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(gen=gen, key=jax.random.key_data(key), state=jax.tree.leaves(state)))
    return np.asarray(state.mean, np.float64)


def run_gradient(step_fn: Callable, evaluate: Callable, theta0, clock: Clock, trace: Trace, lr: float = 0.1,
                 clip: float = 1.0, line_search=(0.125, 0.25, 0.5, 1.0, 2.0), step_cost: int = 0,
                 progress: Callable | None = None, resume: dict | None = None, checkpoint: Callable | None = None):
    """Adam + batched line search (:mod:`.optimize`'s step) on ``step_fn(theta) -> dict(loss, grad)`` until the
    clock passes the last checkpoint; ``evaluate(thetas (K, P)) -> (K,)`` scores the line-search candidates
    together with ``theta`` itself (``c = 0``, so acceptance compares values of one program). ``step_cost``:
    physics steps of one step (tangents and line search included). ``checkpoint`` and ``resume``: as in
    :func:`run_search` (the iterate, Adam's state and the step count)."""
    from hyqjax.studies.tune import optimize

    opt = optimize.make_optimizer(optimize.AdamConfig(lr=lr, clip=clip))
    theta = jnp.asarray(theta0, jnp.float32)
    state = opt.init(theta)
    update = jax.jit(lambda g, s, th: opt.update(g, s, th))
    scales = jnp.asarray((0.0,) + tuple(line_search), jnp.float32)
    step = 0
    if resume is not None:
        theta, step = jnp.asarray(resume["theta"], jnp.float32), int(resume["step"])
        state = tree_like(state, resume["opt"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            update(jnp.zeros_like(theta), state, theta)
    while not trace.done(clock):
        r = step_fn(theta)
        g = jnp.asarray(r["grad"], jnp.float32)
        upd, state = update(g, state, theta)
        cands = theta[None] + scales[:, None] * jnp.asarray(upd, jnp.float32)[None]
        vals = np.asarray(evaluate(cands), np.float64)
        vals = np.where(np.isfinite(vals), vals, np.inf)
        i = int(np.argmin(vals))
        theta = cands[i]
        clock.physics_steps += step_cost
        trace.advance(clock, np.asarray(theta), dict(step=step, loss=float(r["loss"]), loss_at_theta=float(vals[0]),
                                                     grad_norm=float(jnp.linalg.norm(g)),
                                                     chosen=float(scales[i]), best_loss=float(vals[i])))
        step += 1
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(step=step, theta=theta, opt=jax.tree.leaves(state)))
    return np.asarray(theta, np.float64)



def evaluate_generation(f_gen, mean: np.ndarray, pop, gen: int, clock) -> tuple[dict, np.ndarray]:
    """One generation's closed-loop runs: the mean (row 0, the iterate the search returns) and the population, in
    one batch; their physics charged to ``clock``. Returns ``f_gen``'s result and the fitness (maximised)."""
    r = f_gen(np.concatenate([mean[None], np.asarray(pop, np.float64)]), gen)
    clock.physics_steps += r["physics_steps"]
    return r, np.asarray(r["fitness"], np.float64)


def tell_generation(tell, key, pop, fit: np.ndarray, state, params, method: str, gen: int):
    """evosax's ``tell`` with the population's fitness (negated: evosax minimises); the new state and its mean, a
    ``FloatingPointError`` when the mean is no longer finite."""
    state, _ = tell(key, pop, jnp.asarray(-fit[1:], jnp.float32), state, params)
    new_mean = np.asarray(state.mean, np.float64)
    if not np.all(np.isfinite(new_mean)):
        raise FloatingPointError(f"{method}: the search mean became non-finite at generation {gen}")
    return state, new_mean
