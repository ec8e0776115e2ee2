"""Closed-loop success of a population of parameter vectors in ONE batched forward rollout, with common random
numbers (the success-driven search methods' objective, and the held-out evaluation of the wall-clock study).

:class:`SuccessEvaluator` runs ``N`` parameter vectors ``theta`` (:class:`.schedule.Parameterisation`) on the same
``M`` step-down scenarios: one batch of ``N x M`` full runs of ``duration`` seconds through the one batch runner
of the simulator's backend object (MuJoCo Warp with ``impl="warp"`` on a GPU, MJX-JAX with ``impl="jax"``, C
MuJoCo with ``impl="c"`` on a CPU), compiled once per batch shape. Member ``n`` sees exactly the scenarios member ``n'`` sees
(common random numbers: differences between members are differences of parameters, not of draws). Per member it
returns the clean and completed rates of :mod:`hyqjax.studies.stepdown_outcome` and the fitness

.. math:: F(\\theta) = \\overline{\\text{clean}} + w_c\\, \\overline{\\text{completed}}

(``w_c`` = ``completed_weight``: completion breaks ties between equal clean rates on a small ``M``). Its cost is
``N M duration / dt`` physics steps.

Scenarios: :func:`train_scenarios` draws generation ``g``'s ``M`` training scenarios from ``(seed, g)`` over
:data:`TRAIN_HEIGHTS` with the training ranges :data:`TRAIN_RANGES`; :func:`heldout_scenarios` draws the held-out
set wider (:data:`HELDOUT_RANGES`, heights 14-30 cm of which 14, 18, 22, 26 and 30 cm are never trained on,
another seed), ordered round-robin over heights so that every prefix covers all heights.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.sim import backend as hbackend
from hyqjax.sim import runner as srunner
from hyqjax.studies import stepdown
from hyqjax.studies import stepdown_outcome as so
from hyqjax.studies.tune.schedule import Parameterisation

TRAIN_HEIGHTS = (0.16, 0.20, 0.24, 0.28)
#: What the search methods train on (narrower than the held-out set).
TRAIN_RANGES = dict(friction=(0.5, 1.0), payload=(0.0, 10.0), start_distance=(0.0, 0.10), lateral=(-0.05, 0.05),
                    yaw=(-0.1, 0.1))
HELDOUT_HEIGHTS = tuple(round(0.14 + 0.02 * i, 2) for i in range(9))
#: The held-out set: wider than training in friction, payload and start distance.
HELDOUT_RANGES = dict(friction=(0.4, 1.0), payload=(0.0, 15.0), start_distance=(0.0, 0.15), lateral=(-0.05, 0.05),
                      yaw=(-0.1, 0.1))
#: Scenario ranges a training draw may use (``WallClockConfig.train_spread``): the training ranges, or the wide
#: spread (the held-out ranges, which the reach map's wide spread also uses).
SPREADS = dict(train=TRAIN_RANGES, wide=HELDOUT_RANGES)


def train_scenarios(m: int, seed: int, generation: int, heights=TRAIN_HEIGHTS,
                    spread: str = "train") -> stepdown.Scenario:
    """Generation ``generation``'s ``m`` training scenarios (``m`` a multiple of ``len(heights)``; reflex on), drawn
    with the ranges ``SPREADS[spread]``."""
    per = m // len(heights)
    if per * len(heights) != m or per < 1:
        raise ValueError(f"train instances must be a positive multiple of {len(heights)}, got {m}")
    gen_seed = int(np.random.SeedSequence([seed, generation]).generate_state(1)[0])
    sc, _ = stepdown.make_scenarios(tuple(heights), [True], per, gen_seed, **SPREADS[spread])
    return sc


def heldout_scenarios(n: int, seed: int = 7777, heights=HELDOUT_HEIGHTS) -> tuple[stepdown.Scenario, np.ndarray]:
    """``n`` held-out scenarios, round-robin over ``heights`` (every height ``n / len(heights)`` times, the first
    ``n mod len(heights)`` heights once more); returns (scenario, height per instance)."""
    per = -(-int(n) // len(heights))
    sc, table = stepdown.make_scenarios(heights, [True], per, seed, **HELDOUT_RANGES)
    order = np.argsort(table["instance"] * len(heights) + np.searchsorted(heights, table["height"]), kind="stable")
    order = order[: int(n)]
    return jax.tree_util.tree_map(lambda x: x[order], sc), table["height"][order]


def _tile(tree, n):
    return jax.tree_util.tree_map(lambda x: jnp.tile(x, (n,) + (1,) * (jnp.ndim(x) - 1)), tree)


@functools.lru_cache(maxsize=8)
def _runners(param: Parameterisation, cfg: stepdown.StepdownConfig, x64: bool) -> srunner.RunnersByPlace:
    """The runners (one per placement) of the evaluators of ``param`` under ``cfg`` (``x64``: the setup's float
    width, :func:`hyqjax.studies.stepdown.setup`)."""
    st = stepdown.setup(cfg)
    return srunner.RunnersByPlace(lambda mesh: st.backend.make_runner(
        st.ids, param.controller(cfg.control_dt), cfg.sim_config(), stepdown.make_metrics(st.ids, cfg), None,
        params_axes=0, mesh=mesh))


class SuccessEvaluator:
    """``evaluator(thetas (N, P), scenario (M)) -> dict(clean (N, M), completed (N, M), fitness (N,), ...)``
    (module docstring). ``bases`` (optional, one ``CrawlParams`` per member) replace the common ``base``
    (e.g. the paper's crawl as a reference next to tuned sets)."""

    def __init__(self, param: Parameterisation, base: crawl.CrawlParams, duration: float = 24.0, impl: str = "auto",
                 completed_weight: float = 0.1, devices=None):
        self.param, self.base = param, base
        self.cfg = stepdown.StepdownConfig(duration=duration, impl=impl)
        self.setup = stepdown.setup(self.cfg)
        st = self.setup
        self.ticks = self.cfg.sim_config().n_ticks
        #: where a generation runs (hyqjax.sim.devices.resolve; None: the process's selection, every local device):
        #: its N x M rows split over the devices, one program per device (hyqjax.sim.runner.run_on)
        self.devices = devices
        #: the runners of the evaluator's static setup (its parameterisation and configuration), shared by every
        #: evaluator of the same setup in this process: a second one neither traces nor compiles them again
        self.runners = _runners(param, self.cfg, bool(jax.config.jax_enable_x64))
        self.runner = self.runners(None)
        cfg = self.cfg
        self._outcome = jax.jit(jax.vmap(lambda r: so.outcome(r, st.ids, cfg.max_tilt, cfg.min_progress)))
        self.completed_weight = float(completed_weight)
        self.physics_steps = 0  # counted over every call

    def __call__(self, thetas, scenario: stepdown.Scenario, bases=None, param: Parameterisation | None = None) -> dict:
        """``thetas (N, P)`` of ``param`` (default: the evaluator's; any parameterisation of the same ``ParamSpace``
        runs on the same compiled program) on ``scenario``."""
        param = param or self.param
        if param.space != self.param.space:
            raise ValueError("the evaluator runs parameterisations of its own ParamSpace only")
        table, cond = param.split(jnp.asarray(np.asarray(thetas, np.float32)))
        return self.run(table, cond, scenario, bases)

    def run(self, table, cond, scenario: stepdown.Scenario, bases=None) -> dict:
        """Members given as tables ``(N, 4, P0)`` and conditioning ``(N, F, P0)`` (:class:`.schedule.Scheduled`);
        member ``n`` owns batch rows ``n M ... (n + 1) M - 1``."""
        from hyqjax.studies.tune.schedule import Scheduled

        dtype = jnp.float32
        table, cond = jnp.asarray(table, dtype), jnp.asarray(cond, dtype)
        n, m = table.shape[0], scenario.batch_size
        def f32(x):
            return jnp.asarray(x, dtype) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else jnp.asarray(x)

        bases = bases or [self.base] * n
        base = jax.tree_util.tree_map(lambda *xs: jnp.stack([f32(x) for x in xs]), *bases)  # (N, ...)
        base = jax.tree_util.tree_map(lambda x: jnp.repeat(x, m, axis=0), base)
        base = dataclasses.replace(base, use_reflex=jnp.tile(jnp.asarray(scenario.params.use_reflex, dtype), n))
        sp = Scheduled(base=base, table=jnp.repeat(table, m, axis=0), cond=jnp.repeat(cond, m, axis=0))
        sc = _tile(scenario, n)
        st = self.setup
        t0 = time.perf_counter()
        devs = hbackend.devices_for(st.impl, self.devices)
        res = srunner.run_tree_on(devs, self.runners, st.impl, (sc, sp),
                                  lambda rows: (*stepdown.batch_inputs(st, rows[0]), rows[1], rows[0].push))
        out = self._outcome(res._replace(trace=None))
        cols = so.to_columns(jax.block_until_ready(out))
        wall = time.perf_counter() - t0
        steps = n * m * self.ticks
        self.physics_steps += steps
        clean = cols["clean"].reshape(n, m).astype(bool)
        completed = cols["completed"].reshape(n, m).astype(bool)
        fitness = clean.mean(1) + self.completed_weight * completed.mean(1)
        return dict(clean=clean, completed=completed, fitness=fitness, physics_steps=steps, wall_s=wall,
                    columns={k: v.reshape((n, m) + v.shape[1:]) for k, v in cols.items()})


def evaluate_sets(evaluator: SuccessEvaluator, members: list, scenario: stepdown.Scenario, chunk_members: int = 0,
                  progress=None, done: Callable | None = None) -> list:
    """Held-out evaluation: every member ``(param, theta, base)`` on every instance of ``scenario``,
    ``chunk_members`` members per batch (0: all in one; the last chunk is padded with copies of its last member so
    that one program serves all). ``done(i, columns)`` gets each member's outcome columns ``(M,)`` as soon as its
    chunk is finished (to store it: a killed evaluation keeps its finished chunks). Returns the columns per
    member."""
    n = len(members)
    k = chunk_members or n
    out = []
    for a in range(0, n, k):
        idx = list(range(a, min(a + k, n)))
        pad = idx + [idx[-1]] * (k - len(idx))
        # members of any parameterisation of the evaluator's space, as (table, cond)
        tc = [members[i][0].split(jnp.asarray(np.asarray(members[i][1], np.float32))) for i in pad]
        r = evaluator.run(jnp.stack([t for t, _ in tc]), jnp.stack([c for _, c in tc]), scenario,
                          [members[i][2] for i in pad])
        for j, i in enumerate(idx):
            cols = {c: v[j] for c, v in r["columns"].items()}
            out.append(cols)
            if done is not None:
                done(i, cols)
        if progress is not None:
            progress(min(a + k, n), n, r["wall_s"])
    return out
