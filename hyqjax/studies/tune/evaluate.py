"""Closed-loop evaluation of parameter sets on step-down scenarios (``stepdown.run_batch``, reflex on).

Held-out scenarios (:func:`heldout_scenarios`) come from a seed never used for training and cover heights
14-30 cm in 2 cm steps (the training heights are a subset; the others are never trained on), friction
0.4-1.0, payload 0-15 kg at a random CoM offset, start 0-15 cm before the edge, +-5 cm lateral offset and
+-0.1 rad yaw. Every method runs on the same instances (common random numbers), all methods in one batch.

Per method and per height (the per-height curves are ``statistics.success_curve``'s, Wilson 95% intervals):

* **completed** and **clean** as ``hyqjax.studies.stepdown_outcome`` defines them (completed: no failure
  reason but a shin strike; clean: completed without a shin strike), with every failure reason counted;
* the counts of ``diverged`` (simulator blow-ups) and ``terminated`` (runs that fell: their episode ended at the
  failure tick) runs, kept apart;
* the shin-strike share, and the largest height with >= 90% completion and with >= 95% clean success
  (point estimates; every height up to it must pass too).
"""
from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.studies import stepdown
from hyqjax.studies import statistics
from hyqjax.studies import stepdown_outcome as so

HELDOUT_HEIGHTS = tuple(round(0.14 + 0.02 * i, 2) for i in range(9))
TRAIN_HEIGHTS = (0.16, 0.20, 0.24, 0.28)
RANGES = dict(friction=(0.4, 1.0), payload=(0.0, 15.0), start_distance=(0.0, 0.15), lateral=(-0.05, 0.05),
              yaw=(-0.1, 0.1))


def scenarios(heights, per_height: int, seed: int, params: crawl.CrawlParams | None = None):
    """``stepdown.make_scenarios`` over ``heights x per_height`` with the tuning ranges (reflex on)."""
    return stepdown.make_scenarios(heights, [True], per_height, seed, params=params, **RANGES)


def heldout_scenarios(n: int, seed: int = 7777, heights=HELDOUT_HEIGHTS):
    """At least ``n`` held-out instances spread evenly over ``heights``."""
    per = -(-int(n) // len(heights))
    return scenarios(heights, per, seed)


def with_params_list(scenarios: list[stepdown.Scenario], params: list[crawl.CrawlParams]) -> stepdown.Scenario:
    """One batch: ``scenarios[i]`` run with ``params[i]`` (float32 leaves), concatenated."""
    parts = []
    for sc, p in zip(scenarios, params):
        b = sc.batch_size
        bp = jax.tree_util.tree_map(lambda x, b=b: jnp.broadcast_to(jnp.asarray(x, jnp.asarray(x).dtype if
                                    not jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else jnp.float32),
                                    (b,) + jnp.shape(x)), p)
        bp = dataclasses.replace(bp, use_reflex=sc.params.use_reflex)
        parts.append(dataclasses.replace(sc, params=bp))
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, 0), *parts)


def run(scenario: stepdown.Scenario, params: list[crawl.CrawlParams], duration: float = 24.0,
        counts: list[int] | None = None, impl: str = "auto") -> tuple[dict, float]:
    """Run parameter set ``i`` on the first ``counts[i]`` instances of ``scenario`` (all by default), every
    set in one batch (``stepdown.make_stepdown_rollout(...).run``: compiled once per batch shape; the Warp
    backend where installed with ``impl="auto"``); returns (outcome columns, one ``(counts[i],)`` array per
    set and column, wall s)."""
    counts = counts or [scenario.batch_size] * len(params)
    parts = [jax.tree_util.tree_map(lambda x, c=c: x[:c], scenario) for c in counts]
    full = with_params_list(parts, params)
    rollout = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=duration, impl=impl))
    t0 = time.time()
    out, _ = rollout.run(full)
    cols = so.to_columns(jax.block_until_ready(out))
    wall = time.time() - t0
    keep = {k: cols[k] for k in ("clean", "completed", "mean_mobility", "terminated", *so.FAILURE_REASONS)}
    edges = np.cumsum([0, *counts])
    return {k: [np.asarray(v)[a:b] for a, b in zip(edges[:-1], edges[1:])] for k, v in keep.items()}, wall


def _largest(curve, key, level):
    best = None
    for c in curve:
        if c[key] < level:
            break
        best = c["height"]
    return best


def summarize(heights: np.ndarray, res: dict, i: int) -> dict:
    """Summary of parameter set ``i`` of :func:`run`'s output (see the module docstring)."""
    s, c, sh = res["clean"][i], res["completed"][i], res["shin_strike"][i]
    heights = np.asarray(heights)[: s.size]
    curves = [statistics.success_curve(heights, v) for v in (s, c, sh)]
    curve = [dict(height=a["height"], n=a["n"], clean=a["rate"], clean_ci95=a["ci95"], completed=b["rate"],
                  completed_ci95=b["ci95"], shin_strike=x["rate"]) for a, b, x in zip(*curves)]
    n = int(s.size)
    reasons = {k: int(np.sum(res[k][i])) for k in so.FAILURE_REASONS}
    return dict(n=n, clean=float(s.mean()), clean_ci95=list(stepdown.wilson_interval(int(s.sum()), n)),
                completed=float(c.mean()), completed_ci95=list(stepdown.wilson_interval(int(c.sum()), n)),
                shin_strike=float(sh.mean()), lost_foothold=float(res["lost_foothold"][i].mean()),
                diverged=int(res["diverged"][i].sum()), terminated=int(res["terminated"][i].sum()),
                mean_mobility=float(np.mean(res["mean_mobility"][i])),
                failure_counts=reasons, per_height=curve,
                largest_h_completed_90=_largest(curve, "completed", 0.90),
                largest_h_clean_95=_largest(curve, "clean", 0.95))


def evaluate(methods: dict[str, crawl.CrawlParams], n: int, seed: int = 7777, heights=HELDOUT_HEIGHTS,
             duration: float = 24.0, extra: dict[str, crawl.CrawlParams] | None = None, n_extra: int = 0,
             impl: str = "auto") -> dict:
    """Held-out evaluation of every method on the same ``>= n`` instances, and of the ``extra`` sets (the
    budget curve) on a subset of ``n_extra`` of them spread over all heights; one batch, one compile.
    The instances are ordered round-robin over heights, so every prefix covers all heights evenly."""
    sc, table = heldout_scenarios(n, seed, heights)
    order = np.argsort(table["instance"] * len(heights) + np.searchsorted(heights, table["height"]), kind="stable")
    sc = jax.tree_util.tree_map(lambda x: x[order], sc)
    h = table["height"][order]
    extra = extra or {}
    names, enames = list(methods), list(extra)
    counts = [sc.batch_size] * len(names) + [min(n_extra, sc.batch_size)] * len(enames)
    res, wall = run(sc, [methods[k] for k in names] + [extra[k] for k in enames], duration, counts, impl)
    out = dict(seed=seed, heights=[float(x) for x in heights], instances=sc.batch_size, duration=duration,
               wall_s=wall, physics_steps=int(sum(counts) * round(duration / 0.002)),
               methods={k: summarize(h, res, i) for i, k in enumerate(names)},
               extra={k: summarize(h, res, len(names) + i) for i, k in enumerate(enames)})
    return out


def success_objective(thetas: np.ndarray, space, base: crawl.CrawlParams, scenario: stepdown.Scenario,
                      duration: float, impl: str = "auto") -> np.ndarray:
    """Closed-loop clean-success rate of every candidate ``theta`` (rows) on ``scenario`` (for the
    gradient-free baselines given success directly). Cost: ``len(thetas) x B x duration / dt`` steps."""
    params = [space.concrete(t, base) for t in np.asarray(thetas)]
    res, _ = run(scenario, params, duration, impl=impl)
    return np.asarray([s.mean() for s in res["clean"]])
