"""Robust bounding baseline: the impulses and every feedback gain optimised jointly over a batch of commands,
frictions and payloads, by gradient through multi-cycle MJX rollouts (forward mode) or by CMA-ES.

Orsolino et al. optimise the feed-forward impulses of ONE command's limit cycle offline (Section II; here
:mod:`hyqjax.bounding.cycle`, which stays the reference). This module optimises one parameter set for the
whole command envelope instead:

* the decision vector ``theta`` (:class:`RobustSpace`, :data:`COORDS`): the four cycle amplitudes
  ``(a_fz, a_hz, a_fx, a_hx)`` (Eq. B1), the apex feedback (B4), the speed and lateral gains and integrator
  (B5), the yaw gains (B6), the roll PD, the stance PD (B7) and the foot-placement gain (B8). Coordinate ``i``
  is ``p_i = clip(p_i^0 + s_i theta_i, lo_i, hi_i)``: ``theta = 0`` is the default controller, one unit is a
  step of natural size ``s_i``, and every ``theta`` gives parameters inside their declared ranges. The cycle
  reference (apex state, stance reference table) stays that of the stored cycle, so changed impulses act as
  a new feed-forward that the feedback regulates around the stored cycle.
* the objective: the mean over a training batch of :func:`hyqjax.bounding.tracking.total_cost` (yaw error,
  its excess over 3 deg, filtered speed errors, apex height, fall margins, falls) of multi-cycle closed-loop
  runs from randomised apex states, with the command ramped in.
* the gradient (:func:`make_value_and_jac`): ``jax.jacfwd`` of the per-instance costs with respect to
  ``theta`` (``P`` tangents carried with one primal run through ``mjx.step``; reverse mode would need MJX's
  solver as a fixed-length loop, :mod:`hyqjax.sim.reverse_mode`, not used here), under MJX's JAX implementation; Adam with a batched line search
  (:func:`hyqjax.studies.tune.optimize.run_adam`). It is the pathwise gradient of the current contact
  sequence: it does not see how ``theta`` moves a touchdown in time, nor a fall (a step; the margins are its
  smooth surrogate).
* CMA-ES (:func:`cma_es`): evosax's ``CMA_ES`` (jitted ask / tell) on the same ``theta`` and the same training
  batch, every candidate judged by the same cost from forward runs (any simulator), stopped at a
  wall-clock limit (equal wall-clock comparison).

The optimised parameters are stored as JSON (:mod:`hyqjax.bounding.robust_params`: :func:`save_params`, :func:`load_params`);
``params_from_values(load_params(path), speed=...)`` rebuilds the controller. :data:`PRESETS` names the sets
shipped with the package: ``"robust"`` is the gradient's result of the study on one H100 recorded in
``docs/bounding.md`` (``preset_params("robust", speed=0.8, yaw_rate=0.5)``; preset ``bound_robust_grad``),
``"robust_8s"`` CMA-ES's result of the study trained on 8 s rollouts, the one with no held-out fall (preset
``bound_robust_8s``; refined at the fast corners of the command box by ``experiments.bounding_refine`` it is
preset ``bound_robust``, which :func:`hyqjax.bounding.params.default_params` runs); the study starts from and compares
with the paper's reference cycle and hand-set gains (:func:`hyqjax.bounding.params.paper_params`, preset
``bound_paper``).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import cycle as bc
from hyqjax.bounding import batch as bbatch
from hyqjax.bounding import tracking
from hyqjax.bounding.params import BoundingParams, paper_params
from hyqjax.bounding.robust_params import (  # noqa: F401  (their home; the names stay reachable here)
    AMPLITUDE_NAMES, COORDS, FORMAT, PRESETS, load_params, params_from_values, preset_params, preset_path, save_params)
from hyqjax.core.batching import vmap_unless_one


@dataclasses.dataclass(frozen=True)
class RobustSpace:
    """The optimised coordinates (a static, hashable subset of :data:`COORDS`, in that order) and the start
    point ``p^0`` (the values at ``theta = 0``)."""

    names: tuple
    start: tuple

    @staticmethod
    def make(base: BoundingParams | None = None, names=None) -> "RobustSpace":
        """The space around ``base`` (default: the paper's gains, :func:`hyqjax.bounding.params.paper_params`, the
        study's start point) over ``names`` (default: all of COORDS)."""
        base = base or paper_params()
        known = [c[0] for c in COORDS]
        names = tuple(known if names is None else names)
        bad = [n for n in names if n not in known]
        if bad or not names:
            raise ValueError(f"names must be a non-empty subset of {known}, got {list(names)}")
        names = tuple(n for n in known if n in names)
        start = tuple(float(value_of(base, n)) for n in names)
        return RobustSpace(names, start)

    @property
    def size(self) -> int:
        return len(self.names)

    def _arrays(self):
        c = {k[0]: k for k in COORDS}
        scale = np.array([c[n][1] for n in self.names])
        lo = np.array([c[n][2] for n in self.names])
        hi = np.array([c[n][3] for n in self.names])
        return scale, lo, hi

    def values(self, theta, xp=jnp):
        """``p = clip(p^0 + s theta, lo, hi)`` (``(..., P)``; traceable with ``xp = jnp``)."""
        scale, lo, hi = self._arrays()
        theta = xp.asarray(theta)
        return xp.clip(xp.asarray(self.start, theta.dtype) + xp.asarray(scale, theta.dtype) * theta, lo, hi)

    def theta_of(self, values: dict) -> np.ndarray:
        """``theta`` reproducing ``values`` (a dict by name; missing names stay at the start)."""
        scale, _, _ = self._arrays()
        return np.array([(float(values.get(n, s0)) - s0) / s for n, s0, s in zip(self.names, self.start, scale)])

    def apply(self, theta, params: BoundingParams) -> BoundingParams:
        """``params`` (one instance) with the coordinates of ``theta`` (traceable, differentiable)."""
        v = self.values(theta)
        amp = params.amplitudes
        cols = dict(a_fz=(slice(0, 2), 2), a_hz=(slice(2, 4), 2), a_fx=(slice(0, 2), 0), a_hx=(slice(2, 4), 0))
        gains = {}
        for i, n in enumerate(self.names):
            if n in cols:
                rows, col = cols[n]
                amp = amp.at[rows, col].set(v[i].astype(amp.dtype))
            else:
                gains[n] = v[i].astype(jnp.float32)
        return params.replace(amplitudes=amp, gains=dataclasses.replace(params.gains, **gains))

    def describe(self, theta) -> dict[str, float]:
        """The parameter values of a concrete ``theta``."""
        return {n: float(x) for n, x in zip(self.names, self.values(np.asarray(theta, np.float64), np))}


def value_of(params: BoundingParams, name: str) -> float:
    """The value of coordinate ``name`` in ``params`` (one instance)."""
    amp = np.asarray(params.amplitudes)
    i = dict(a_fz=(0, 2), a_hz=(2, 2), a_fx=(0, 0), a_hx=(2, 0)).get(name)
    return float(amp[i]) if i is not None else float(getattr(params.gains, name))


# ----------------------------------------------------------------------------------------------
# Instances: training and held-out draws
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Draw:
    """A distribution of instances: commands uniform in the boxes ``speed``, ``yaw_rate``, ``lateral`` (lo, hi),
    friction and payload uniform (:class:`hyqjax.bounding.batch.Randomisation`), ``ramp_time`` s of ramp."""

    speed: tuple = (0.0, 1.0)
    yaw_rate: tuple = (-0.8, 0.8)
    lateral: tuple = (0.0, 0.0)
    friction: tuple = (0.5, 1.0)
    payload: tuple = (0.0, 10.0)
    ramp_time: float = 1.0

    def __post_init__(self):
        for k, lim in (("speed", 1.5), ("yaw_rate", 1.5), ("lateral", 0.5)):
            lo, hi = (float(x) for x in getattr(self, k))
            if not (np.isfinite(lo) and np.isfinite(hi) and -lim <= lo <= hi <= lim):
                raise bbatch.SettingError(
                    k, f"{k} must be LO HI with -{lim:g} <= LO <= HI <= {lim:g}, got {lo:g} {hi:g}")
        bbatch.Randomisation(friction=self.friction, payload=self.payload)
        if not (0.0 <= self.ramp_time <= 10.0):
            raise bbatch.SettingError("ramp_time", f"ramp_time must be in [0, 10] s, got {self.ramp_time}")

    def commands(self, n: int, seed: int) -> np.ndarray:
        """``(n, 3)`` commands (speed, yaw rate, lateral speed) from ``seed``."""
        rng = np.random.default_rng([seed, 1])
        return np.stack([rng.uniform(*self.speed, n), rng.uniform(*self.yaw_rate, n), rng.uniform(*self.lateral, n)],
                        -1)

    def batch(self, n: int, seed: int, base: BoundingParams | None = None) -> bbatch.Batch:
        """``n`` instances of ``base`` (default: the paper's gains, the study's reference) with commands, initial
        perturbations, friction and payload from ``seed``."""
        base = base or paper_params()
        p = bbatch.command_params(base, self.commands(n, seed), self.ramp_time)
        return bbatch.make_batch(p, seed=seed, rand=bbatch.Randomisation(friction=self.friction, payload=self.payload))


# ----------------------------------------------------------------------------------------------
# The objective: forward (a population of theta) and its forward-mode Jacobian
# ----------------------------------------------------------------------------------------------


def population_batch(space: RobustSpace, thetas, batch: bbatch.Batch) -> bbatch.Batch:
    """Every candidate of ``thetas`` (C, P) on every instance of ``batch`` (B): C x B instances, candidate-major."""
    thetas = jnp.asarray(thetas, jnp.float32)
    c, b = thetas.shape[0], int(np.shape(batch.apex0)[0])
    params = jax.jit(jax.vmap(jax.vmap(space.apply, in_axes=(None, 0)), in_axes=(0, None)))(thetas, batch.params)
    params = jax.tree_util.tree_map(lambda x: x.reshape((c * b,) + x.shape[2:]), params)
    rep = lambda x: (np.tile(x, (c,) + (1,) * (np.ndim(x) - 1)) if isinstance(x, np.ndarray)  # noqa: E731
                     else jnp.tile(jnp.asarray(x), (c,) + (1,) * (jnp.ndim(x) - 1)))
    rest = jax.tree_util.tree_map(rep, batch._replace(params=None))
    return rest._replace(params=params)


def population_cost(space: RobustSpace, thetas, batch: bbatch.Batch, duration: float, impl: str = "auto",
                    spec: tracking.CostSpec = tracking.CostSpec(), max_batch: int = 16384) -> tuple[np.ndarray, dict]:
    """Mean cost over ``batch`` of every candidate of ``thetas`` (C, P) from forward runs (``impl``): ``(C,)``
    and the per-instance columns (C x B rows). A diverged instance's cost is its frozen state's (finite); its
    ``diverged`` flag is counted."""
    thetas = np.atleast_2d(np.asarray(thetas, np.float64))
    cols = tracking.run_batch(population_batch(space, thetas, batch), duration, impl, spec, max_batch)
    cost = cols["cost"].reshape(thetas.shape[0], -1)
    cost = np.where(np.isfinite(cost), cost, np.inf)
    return cost.mean(1), cols


def make_instance_cost(space: RobustSpace, duration: float, spec: tracking.CostSpec = tracking.CostSpec(),
                       control_dt: float = 0.002) -> Callable:
    """``f(theta, params, terrain, apex0, roll0, yaw_rate0) -> (L, TrackingMetrics, diverged)`` of ONE instance
    under MJX's JAX implementation (pure; ``vmap`` over instances, ``jacfwd`` over ``theta``)."""
    from hyqjax.bounding import rollout as brollout
    from hyqjax.sim import model as hmodel
    from hyqjax.sim import rollout as sim

    st = brollout.setup(control_dt, "jax")
    cfg = sim.SimConfig(control_dt=control_dt, duration=float(duration), record_every=0)
    metrics = tracking.tracking_metrics(spec, control_dt)

    def f(theta, params, terrain, apex0, roll0, yaw_rate0):
        p = space.apply(theta, params)
        mx1 = hmodel.instance_model(st.mx, st.ids, terrain)
        d0 = bc.apex_data(st.mx_jax, st.m, p, apex0, roll=roll0, yaw_rate=yaw_rate0)
        res = sim.rollout(mx1, st.ids, d0, bc.DIFFERENTIATED_CONTROLLER, p, cfg, metrics)
        return tracking.total_cost(res.metrics, spec), res.metrics, res.diverged

    return f


def make_value_and_jac(space: RobustSpace, duration: float, spec: tracking.CostSpec = tracking.CostSpec(),
                       control_dt: float = 0.002, clip_factor: float = 3.0) -> Callable:
    """A jitted ``g(theta, batch_args) -> dict(loss, grad, per_instance_loss, per_instance_grad, ok, terms, ...)``:
    one ``jax.jacfwd`` over ``theta`` of the per-instance costs (``vmap`` over the instances of
    ``batch_args = instance_args(batch)``; none for one instance, :func:`hyqjax.core.batching.vmap_unless_one`).
    ``loss`` and ``grad`` are means over the instances whose cost and gradient are finite and that did not diverge
    (``ok``); the others are counted (``ok``, ``diverged``), not averaged. In ``grad`` each instance's gradient is
    capped at ``clip_factor`` times the median norm (``clipped`` counts the capped ones; ``grad_unclipped`` is the
    plain mean)."""
    if not clip_factor > 0:
        raise ValueError(f"clip_factor must be > 0, got {clip_factor}")
    f = make_instance_cost(space, duration, spec, control_dt)

    def g(theta, args):
        def per_instance(th):
            loss, ms, div = vmap_unless_one(lambda *a: f(th, *a))(*args)  # one instance: no batching to trace
            return loss, (loss, ms, div)

        jac, (loss, ms, div) = jax.jacfwd(per_instance, has_aux=True)(theta)
        ok = jnp.isfinite(loss) & jnp.all(jnp.isfinite(jac), -1) & ~div
        w = ok.astype(loss.dtype)
        nw = jnp.maximum(jnp.sum(w), 1.0)
        jac = jnp.where(ok[:, None], jac, 0.0)
        lz = jnp.where(ok, loss, 0.0)
        # Robust mean: an instance's gradient is capped at `clip_factor` x the median norm (a contact-rich rollout
        # can have a pathwise gradient orders of magnitude above the others, which would dominate the mean).
        norm = jnp.linalg.norm(jac, axis=-1)
        cap = clip_factor * jnp.nanmedian(jnp.where(ok, norm, jnp.nan))
        scale = jnp.where(norm > cap, cap / jnp.maximum(norm, 1e-30), 1.0)
        terms = {k: jnp.sum(w * jnp.where(ok, v, 0.0)) / nw for k, v in tracking.cost_terms(ms, spec).items()}
        return dict(loss=jnp.sum(w * lz) / nw, grad=jnp.sum((w * scale)[:, None] * jac, 0) / nw,
                    grad_unclipped=jnp.sum(w[:, None] * jac, 0) / nw, per_instance_loss=loss, per_instance_grad=jac,
                    ok=ok, clipped=jnp.sum(ok & (norm > cap)), terms=terms, falls=jnp.sum(ms.fall.fall_tick >= 0),
                    diverged=jnp.sum(div))

    return jax.jit(g)


def instance_args(batch: bbatch.Batch) -> tuple:
    """``(params, terrain, apex0, roll0, yaw_rate0)`` of a batch as JAX arrays (the per-instance arguments of
    :func:`make_instance_cost`)."""
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return batch.params, batch.terrain, f32(batch.apex0), f32(batch.roll0), f32(batch.yaw_rate0)


def physics_steps(instances: int, duration: float, tangents: int = 0, control_dt: float = 0.002) -> int:
    """Simulation budget: ``instances x ticks x (1 + tangents)`` physics steps."""
    return int(instances) * int(round(duration / control_dt)) * (1 + int(tangents))


# ----------------------------------------------------------------------------------------------
# CMA-ES (evosax), stopped at a wall-clock limit
# ----------------------------------------------------------------------------------------------


def cma_es(f_pop: Callable[[np.ndarray], np.ndarray], theta0: np.ndarray, max_wall_s: float, popsize: int,
           sigma: float = 0.3, seed: int = 0, max_generations: int = 100000, cost_per_candidate: int = 0,
           log: Callable | None = None) -> dict:
    """Minimise ``f_pop(thetas (popsize, P)) -> (popsize,)`` by evosax's ``CMA_ES`` (ask / tell jitted) from
    ``theta0`` with step size ``sigma``, until ``max_wall_s`` s have passed (a generation started before the
    limit finishes). Every generation is recorded (``history``: wall time, physics steps, best value so far
    and its ``theta``). Non-finite values rank last."""
    from evosax.algorithms import CMA_ES

    theta0 = jnp.asarray(theta0, jnp.float32)
    es = CMA_ES(population_size=int(popsize), solution=theta0)
    params = es.default_params.replace(std_init=float(sigma))
    key = jax.random.key(seed)
    key, k0 = jax.random.split(key)
    state = es.init(k0, theta0, params)
    ask, tell = jax.jit(es.ask), jax.jit(es.tell)
    t0 = time.time()
    best, best_theta, hist, spent = np.inf, np.asarray(theta0, np.float64), [], 0
    gen = 0
    while gen < max_generations and time.time() - t0 < max_wall_s:
        key, ka, kt = jax.random.split(key, 3)
        xs, state = ask(ka, state, params)
        vals = np.asarray(f_pop(np.asarray(xs, np.float64)), np.float64)
        vals = np.where(np.isfinite(vals), vals, np.inf)
        spent += popsize * cost_per_candidate
        i = int(np.argmin(vals))
        if vals[i] < best:
            best, best_theta = float(vals[i]), np.asarray(xs[i], np.float64)
        state, _ = tell(kt, xs, jnp.asarray(np.where(np.isfinite(vals), vals, 1e9), jnp.float32), state, params)
        gen += 1
        hist.append(dict(generation=gen, wall_s=round(time.time() - t0, 3), budget=spent, best=best,
                         generation_best=float(vals[i]), theta=best_theta.tolist()))
        if log is not None:
            log(f"cma-es generation {gen}: best {best:.4f} (this generation {vals[i]:.4f}), "
                f"{time.time() - t0:.0f} s")
    return dict(theta=best_theta, value=best, mean=np.asarray(state.mean, np.float64), history=hist,
                generations=gen, popsize=int(popsize), wall_s=time.time() - t0, budget_spent=spent)
