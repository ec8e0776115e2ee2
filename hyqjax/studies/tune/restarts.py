"""Restarts of CMA-ES: IPOP-CMA-ES (Auger & Hansen, CEC 2005) and BIPOP-CMA-ES (Hansen, GECCO BBOB 2009).

The strategy itself is ``evosax`` 0.3.2's ``CMA_ES`` (jitted ``ask`` / ``tell``, one compile per population size
in a process); this module is only the restart controller around it (:class:`Controller`) and its loop
(:func:`run_restarts`), which :func:`hyqjax.studies.tune.search.run_search` runs for the methods ``ipop_cma_es``
and ``bipop_cma_es``.

**When a run stops** (:meth:`Controller.observe`; the criteria of the two papers that apply to a noisy,
quantised objective, with ``h = 10 + ceil(30 P / lambda)`` generations, IPOP's history length, and ``G = 120 +
ceil(30 P / lambda)``, Hansen's stagnation length):

* ``tol_fun`` (flat fitness): the range of the best fitness of the last ``h`` generations and of every fitness of
  the current generation is below ``tol_fun`` (IPOP's *TolFun* and *equalfunvalhist*; on a success rate: a run
  whose populations all score alike);
* ``tol_x`` (step-size collapse): ``sigma * max_i sqrt(C_ii) < tol_x * sigma_0`` (*TolX*);
* ``condition``: the covariance's condition number above ``max_condition`` (*ConditionCov*);
* ``stagnation``: the run's best score has not improved for ``G`` generations. The score is the run's own best
  validated clean success when the search has a validation batch (the tuner: a fixed batch, so scores of
  different generations compare; :class:`hyqjax.studies.tune.selection.Selection`), else the run's best training
  fitness (an analytic objective);
* ``non_finite``: the mean or the covariance left the floats (a numerical breakdown ends the run, not the search).

``stall_generations`` replaces ``G`` (and caps ``h``): the papers' lengths are made for cheap functions, and on the
closed-loop tuner they exceed its whole budget (56 coordinates, population 16: ``h = 115``, ``G = 225`` generations,
while CMA-ES ran 51 generations in 10 minutes on one H200, ``docs/results/tune_cells_h200_10min/cma_es_per_leg``), so
with them the restart methods would be CMA-ES itself. The tuner's default is 25 generations (five validations
without a better validated score, at one validation every 5 generations); ``0`` takes the papers' lengths.

**What the next run is.** IPOP: the population doubles at every restart (``lambda_0 2^k``, at most
``max_popsize``), ``sigma_0`` as at the start. BIPOP: after the first run (default population), each restart runs
in the regime that has spent less of the budget so far, the first restart in the large one: the *large* regime
is IPOP's (``lambda_0 2^k`` for its ``k``-th run, ``sigma_0``), the *small* regime draws ``U_1, U_2 ~ U(0, 1)``
and runs ``lambda_s = floor(lambda_0 (lambda_l / (2 lambda_0))^{U_1^2})`` (``lambda_l`` the last large
population) with ``sigma_s = sigma_0 10^{-2 U_2}``. The budget is the method's clock: seconds of the wall-clock
budget each run used (compile and validation included), so the two regimes alternate under the same wall-clock
budget the method has (an analytic test gives evaluations as its cost).

**Where a restart starts: a fresh draw, as in both papers** (each restart is an independent run from a new
initial point drawn like the first one's region, uniform in the search box there), here ``x_0 = theta_0 +
sigma_0 z``, ``z ~ N(0, I)``: the region the user's start point and ``--sigma`` declare. Restarting from the best
point so far would re-enter the basin the stopped run stalled in, which is what the restart is meant to leave;
nothing is lost by drawing afresh, since the iterate the tuner returns is the best *validated* one over every run
(the selection spans the restarts), and the final re-evaluation chooses among the best of all of them.

**One forward program across restarts.** A population larger than the first one is evaluated in chunks of the
first population's size, each with the mean as its first row (:func:`evaluate_chunked`): every chunk has the
batch shape the first generation compiled, so a doubled population costs twice the runs and no compile (on a GPU a
new batch shape would compile the closed-loop program again); all chunks of a generation run on the same training
scenarios (common random numbers), and the mean's repeated rows and a last chunk's padding are paid and counted.

The controller's state is a plain dict (:meth:`Controller.state`), stored with the strategy's state by the
tuner's checkpoints (:mod:`.resume`): a killed run resumes in the middle of a restart with the same population
size, step size, regime budgets and generator state.
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.studies.tune.resume import tree_like

#: The restart rules: ``ipop`` (population doubled at each restart) and ``bipop`` (large and small regimes).
KINDS = ("ipop", "bipop")
#: The tuner's method names of the two rules (:data:`hyqjax.studies.tune.names.RESTART_METHODS`).
METHOD_KIND = {"ipop_cma_es": "ipop", "bipop_cma_es": "bipop"}


def history(size: int, popsize: int) -> int:
    """IPOP's history length ``10 + ceil(30 P / lambda)`` generations (flat fitness)."""
    return 10 + math.ceil(30.0 * size / popsize)


def stall(size: int, popsize: int) -> int:
    """Hansen's stagnation length ``120 + ceil(30 P / lambda)`` generations (no improvement of the run's best)."""
    return 120 + math.ceil(30.0 * size / popsize)


class Controller:
    """The restart controller (module docstring): fed one generation at a time (:meth:`observe`), it says when the
    run stops and why, and draws the next run's population size and step size (:meth:`next_run`)."""

    def __init__(self, kind: str, size: int, popsize: int, sigma: float, seed: int = 0, tol_fun: float = 1e-12,
                 tol_x: float = 1e-12, max_condition: float = 1e14, max_popsize: int = 4096, stall_generations: int = 0):
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
        self.kind, self.size, self.popsize0, self.sigma0 = kind, int(size), int(popsize), float(sigma)
        self.tol_fun, self.tol_x, self.max_condition = float(tol_fun), float(tol_x), float(max_condition)
        self.max_popsize = int(max(max_popsize, popsize))
        #: generations without improvement that end a run (0: the papers' ``G``; ``h`` is then at most this too)
        self.stall_generations = int(stall_generations)
        self.rng = np.random.default_rng([int(seed), 0x1905])
        self.s = dict(run=0, popsize=int(popsize), sigma=float(sigma), regime="first", large_runs=0,
                      last_large=int(popsize), budget=dict(large=0.0, small=0.0), run_cost=0.0, gens=0,
                      best_hist=[], best=None, since=0, runs=[])

    # -- what a run is -------------------------------------------------------------------------------------------
    @property
    def popsize(self) -> int:
        return int(self.s["popsize"])

    @property
    def sigma(self) -> float:
        return float(self.s["sigma"])

    @property
    def run(self) -> int:
        return int(self.s["run"])

    def observe(self, fitness, score: float, sigma_max: float, condition: float, finite: bool,
                cost: float) -> str | None:
        """One generation of the current run: ``fitness`` (its population's, maximised), ``score`` (the run's
        best so far by the stagnation criterion's measure), ``sigma_max = sigma max_i sqrt(C_ii)``, the
        covariance's ``condition`` number, whether the state is finite, and the generation's ``cost`` (clock
        seconds or evaluations). Returns the reason the run stops, or None."""
        s = self.s
        s["gens"] += 1
        s["run_cost"] += float(cost)
        fit = np.asarray(fitness, np.float64)
        h, g = self.lengths()
        s["best_hist"] = (s["best_hist"] + [float(np.max(fit))])[-h:]
        if s["best"] is None or score > s["best"]:
            s["best"], s["since"] = float(score), 0
        else:
            s["since"] += 1
        if not finite:
            return "non_finite"
        if len(s["best_hist"]) >= h and (max(max(s["best_hist"]), fit.max()) - min(min(s["best_hist"]), fit.min())
                                         < self.tol_fun):
            return "tol_fun"
        if sigma_max < self.tol_x * self.sigma0:
            return "tol_x"
        if condition > self.max_condition:
            return "condition"
        if s["since"] >= g:
            return "stagnation"
        return None

    def lengths(self) -> tuple[int, int]:
        """``(h, G)`` of the current run: the papers' lengths, or with ``stall_generations`` that many for ``G`` and
        at most that many for ``h``."""
        h, g = history(self.size, self.popsize), stall(self.size, self.popsize)
        if self.stall_generations:
            g = self.stall_generations
            h = min(h, g)
        return h, g

    def next_run(self, reason: str) -> tuple[int, float]:
        """End the current run (``reason``) and start the next: its population size and step size."""
        s = self.s
        s["runs"].append(dict(run=s["run"], regime=s["regime"], popsize=s["popsize"], sigma=s["sigma"],
                              generations=s["gens"], cost=s["run_cost"], best=s["best"], reason=reason))
        if s["regime"] in ("large", "small"):
            s["budget"][s["regime"]] += s["run_cost"]
        if self.kind == "ipop":
            regime = "large"
        else:
            regime = "large" if s["budget"]["large"] <= s["budget"]["small"] else "small"
        if regime == "large":
            s["large_runs"] += 1
            lam = min(self.popsize0 * 2 ** s["large_runs"], self.max_popsize)
            sig, s["last_large"] = self.sigma0, lam
        else:
            u1, u2 = self.rng.uniform(size=2)
            lam = int(math.floor(self.popsize0 * (0.5 * s["last_large"] / self.popsize0) ** (u1 ** 2)))
            lam = max(2, min(lam, self.max_popsize))
            sig = self.sigma0 * 10.0 ** (-2.0 * u2)
        s.update(run=s["run"] + 1, popsize=int(lam), sigma=float(sig), regime=regime, run_cost=0.0, gens=0,
                 best_hist=[], best=None, since=0)
        return int(lam), float(sig)

    def draw(self, theta0) -> np.ndarray:
        """A restart's fresh start point ``theta_0 + sigma_0 z`` (module docstring)."""
        theta0 = np.asarray(theta0, np.float64)
        return theta0 + self.sigma0 * self.rng.standard_normal(theta0.shape)

    def state(self) -> dict:
        return dict(s=self.s, rng=self.rng.bit_generator.state)

    def restore(self, st: dict) -> None:
        self.s = dict(st["s"])
        self.s["budget"] = {k: float(v) for k, v in self.s["budget"].items()}
        self.rng.bit_generator.state = st["rng"]


@functools.lru_cache(maxsize=32)
def make_cma(size: int, popsize: int):
    """evosax's ``CMA_ES`` for ``popsize``, its default parameters and its jitted ``ask`` / ``tell``."""
    from evosax.algorithms import CMA_ES

    es = CMA_ES(population_size=int(popsize), solution=jnp.zeros(int(size), jnp.float32))
    return es, es.default_params, jax.jit(es.ask), jax.jit(es.tell)


def evaluate_chunked(f_gen: Callable, mean: np.ndarray, pop: np.ndarray, gen: int, chunk: int) -> tuple:
    """The population in chunks of ``chunk`` rows, each run as ``[mean, rows...]`` (``chunk + 1`` rows, the batch
    shape of the first population), the last one padded with the mean; every chunk on generation ``gen``'s
    scenarios. Returns ``(row0, fitness (lambda,), physics_steps)``: ``row0`` the mean's ``clean`` / ``completed``
    / ``fitness`` from the first chunk."""
    pop = np.asarray(pop, np.float64)
    lam, fits, steps, row0 = pop.shape[0], [], 0, None
    for a in range(0, lam, chunk):
        rows = pop[a:a + chunk]
        pad = chunk - rows.shape[0]
        batch = np.concatenate([mean[None], rows] + ([np.repeat(mean[None], pad, 0)] if pad else []))
        r = f_gen(batch, gen)
        steps += int(r["physics_steps"])
        fit = np.asarray(r["fitness"], np.float64)
        if row0 is None:
            row0 = dict(fitness=float(fit[0]), clean=float(np.mean(np.asarray(r["clean"])[0])),
                        completed=float(np.mean(np.asarray(r["completed"])[0])))
        fits.append(fit[1:1 + rows.shape[0]])
    return row0, np.concatenate(fits), steps


def run_restarts(method: str, f_gen: Callable, theta0, popsize: int, sigma: float, clock, trace, seed: int = 0,
                 progress: Callable | None = None, stop_at: float | None = None, resume: dict | None = None,
                 checkpoint: Callable | None = None, cost: Callable | None = None,
                 generations: int | None = None, **controller_kw):
    """IPOP- or BIPOP-CMA-ES (``method`` ``ipop_cma_es`` / ``bipop_cma_es``) maximising ``f_gen(thetas (N, P),
    generation) -> dict(fitness (N,), clean, completed, physics_steps)`` (as
    :func:`hyqjax.studies.tune.search.run_search`, ``N = popsize + 1``) until ``clock`` passes ``stop_at``
    (default the last checkpoint) or after ``generations``. ``cost(seconds, evaluations)`` is a generation's cost
    for BIPOP's budgets (default: the clock's seconds). Every generation's log row holds the run, its regime,
    population and step size; a restart's row holds ``restart`` (why the run ended). Returns the final mean;
    ``checkpoint`` / ``resume`` as in ``run_search`` (the strategy's state, the key and the controller's)."""
    theta0 = np.asarray(theta0, np.float64)
    stop_at = trace.checkpoints[-1] if stop_at is None else stop_at
    cost = cost or (lambda seconds, evaluations: seconds)
    ctl = Controller(METHOD_KIND[method], theta0.size, popsize, sigma, seed=seed, **controller_kw)
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)

    def start(x0, k):
        es, params, ask, tell = make_cma(theta0.size, ctl.popsize)
        params = params.replace(std_init=ctl.sigma)
        return es, params, ask, tell, es.init(k, jnp.asarray(x0, jnp.float32), params)

    es, params, ask, tell, state = start(theta0, k0)
    gen, sel0 = 0, 0  # the first run's validations include the start point's
    if resume is not None:
        ctl.restore(resume["ctl"])
        es, params, ask, tell, state = start(theta0, k0)
        key, state = jax.random.wrap_key_data(jnp.asarray(resume["key"])), tree_like(state, resume["state"])
        gen, sel0 = int(resume["gen"]), int(resume["sel0"])
        with clock.paused():  # compiled again in this process; the run paid for it once
            pop, _ = ask(key, state, params)
            tell(key, pop, jnp.zeros(ctl.popsize, jnp.float32), state, params)
    while clock.elapsed() < stop_at and (generations is None or gen < generations):
        t0 = clock.elapsed()
        key, ka, kt = jax.random.split(key, 3)
        pop, state = ask(ka, state, params)
        mean = np.asarray(state.mean, np.float64)
        row0, fit, steps = evaluate_chunked(f_gen, mean, np.asarray(pop), gen, popsize)
        clock.physics_steps += steps
        state, _ = tell(kt, pop, jnp.asarray(-fit, jnp.float32), state, params)
        new_mean = np.asarray(state.mean, np.float64)
        finite = bool(np.all(np.isfinite(new_mean)) and np.all(np.isfinite(np.asarray(state.C))))
        row = dict(generation=gen, iterate_fitness=row0["fitness"], iterate_clean=row0["clean"],
                   best_fitness=float(fit.max()), mean_fitness=float(fit.mean()), std=float(state.std),
                   run=ctl.run, regime=ctl.s["regime"], popsize=ctl.popsize, sigma0_run=ctl.sigma)
        if finite:
            trace.advance(clock, new_mean, row)
        else:
            trace.advance(clock, trace.returned, row)
        score = float(fit.max()) if trace.select is None else _validated(trace, sel0)
        d = np.asarray(state.D, np.float64)
        cond = float((d.max() / d.min()) ** 2) if finite and d.min() > 0 else math.inf
        sig_max = float(state.std) * float(np.sqrt(np.max(np.diag(np.asarray(state.C, np.float64))))) if finite \
            else 0.0
        reason = ctl.observe(fit, score, sig_max, cond, finite, cost(clock.elapsed() - t0, fit.size))
        gen += 1
        if reason is not None:
            lam, sig = ctl.next_run(reason)
            row["restart"] = dict(reason=reason, next_popsize=lam, next_sigma=sig, next_regime=ctl.s["regime"])
            key, k0 = jax.random.split(key)
            es, params, ask, tell, state = start(ctl.draw(theta0), k0)
            sel0 = _validated_count(trace)
        if progress:
            progress(clock, trace)
        if checkpoint:
            checkpoint(lambda: dict(gen=gen, key=jax.random.key_data(key), state=jax.tree.leaves(state),
                                    ctl=ctl.state(), sel0=sel0))
    return np.asarray(state.mean, np.float64)


def _validated_count(trace) -> int:
    return 0 if trace.select is None else len(trace.select.log)


def _validated(trace, since: int = 0) -> float:
    """The best validation score (clean, completed as a tie-break) among the validations since row ``since`` of
    the selection's log; ``-inf`` while the run has none (its generations before its first validation count as
    not improving)."""
    rows = trace.select.log[since:]
    if not rows:
        return -math.inf
    return max(r["clean"] + 1e-6 * r["completed"] for r in rows)


def summary(log: list) -> dict:
    """Per restart run (:func:`run_restarts`'s log): the runs it made, each with its regime, population, step size,
    generations and why it ended (the last one: still running at the end of the budget)."""
    runs, cur = [], None
    for r in log:
        if cur is None or r.get("run") != cur["run"]:
            cur = dict(run=r.get("run"), regime=r.get("regime"), popsize=r.get("popsize"),
                       sigma=r.get("sigma0_run"), generations=0, ended="budget")
            runs.append(cur)
        cur["generations"] += 1
        if "restart" in r:
            cur["ended"] = r["restart"]["reason"]
    return dict(runs=runs, restarts=sum(1 for r in log if "restart" in r))
