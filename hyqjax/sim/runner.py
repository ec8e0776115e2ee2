"""The batch runner: ``vmap`` of :func:`hyqjax.sim.rollout.rollout` over instances, jitted once per static
setup, sharded over a 1-D device mesh (axis ``"batch"``), run in chunks of simulated time with a progress
callback. The one jit + sharding runner of hyqjax: the step-down, the sweeps, bounding and the benchmarks
all run batches through :func:`make_batch_runner` (also reachable as ``hyqjax.sim.rollout.make_batch_runner``).
"""
from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from mujoco import mjx

from hyqjax.sim import model as hmodel
from hyqjax.sim.rollout import (Controller, Metrics, Push, RolloutResult, SimConfig, no_metrics, rollout_advance,
                                rollout_init, rollout_result)


Progress = Callable[[float, float], None]


class BatchRunner:
    """``vmap`` of :func:`hyqjax.sim.rollout.rollout` over instances, jitted once and optionally sharded over a device mesh.

    Built by :func:`make_batch_runner`; call ``runner(mx_batched, d0, params, push)``. The static parts
    (ids, controller, config, metrics, record, parameter axes, mesh) are fixed at construction, so a runner
    compiles once per batch shape and is reused across calls with new values. The scan runs in chunks of
    ``chunk_seconds`` of simulated time (one compiled program: the chunk length divides the number of ticks),
    calling ``progress(sim_seconds_done, sim_seconds_total)`` after each; every chunk continues the carry of
    the last, so the result is bitwise identical to one scan over all ticks.
    """

    def __init__(self, ids: hmodel.ModelIds, controller: Controller, cfg: SimConfig, metrics: Metrics = no_metrics(),
                 record=None, params_axes: Any = 0, mesh: Mesh | None = None):
        self.ids, self.controller, self.cfg, self.metrics = ids, controller, cfg, metrics
        self.record = record if cfg.record_every else None
        self.params_axes, self.mesh = params_axes, mesh
        self._init = self._advance = None
        self.n_compiles = 0  # programs traced (for retrace guards)

    def chunk_ticks(self, chunk_seconds: float | None) -> int:
        """Ticks per chunk: the largest divisor of ``cfg.n_ticks`` that is at most ``chunk_seconds`` of simulated
        time and a multiple of ``cfg.record_every`` (all ticks when ``chunk_seconds`` is None)."""
        n, rec = self.cfg.n_ticks, max(self.cfg.record_every, 1) if self.record is not None else 1
        if chunk_seconds is None:
            return n
        if not chunk_seconds > 0:
            raise ValueError(f"chunk_seconds must be > 0 s, got {chunk_seconds}")
        want = max(int(chunk_seconds / self.cfg.control_dt), 1)
        fits = [k for k in range(rec, n + 1, rec) if n % k == 0 and k <= want]
        return max(fits) if fits else rec if n % rec == 0 else n

    def _build(self, mb: mjx.Model, d0: mjx.Data, params, push: Push):
        ids, ctrl, cfg, met, rec, pax = self.ids, self.controller, self.cfg, self.metrics, self.record, self.params_axes
        m_axes = hmodel.model_in_axes(mb)

        def init(mm, dd, pp):
            self.n_compiles += 1
            return jax.vmap(lambda m1, d1, p1: rollout_init(m1, ids, d1, ctrl, p1, met),
                            in_axes=(m_axes, 0, pax))(mm, dd, pp)

        def advance(mm, cc, pp, pu, n_ticks):
            self.n_compiles += 1
            return jax.vmap(lambda m1, c1, p1, u1: rollout_advance(m1, ids, c1, ctrl, p1, cfg, n_ticks, met, rec, u1),
                            in_axes=(m_axes, 0, pax, 0))(mm, cc, pp, pu)

        def whole(mm, dd, pp, pu):
            self.n_compiles += 1
            c = jax.vmap(lambda m1, d1, p1: rollout_init(m1, ids, d1, ctrl, p1, met), in_axes=(m_axes, 0, pax))(mm, dd, pp)
            c, tr = jax.vmap(lambda m1, c1, p1, u1: rollout_advance(m1, ids, c1, ctrl, p1, cfg, cfg.n_ticks, met, rec, u1),
                             in_axes=(m_axes, 0, pax, 0))(mm, c, pp, pu)
            return rollout_result(c, tr)

        if self.mesh is None:
            self._init, self._advance, self._put = jax.jit(init), jax.jit(advance, static_argnums=4), None
            self._whole = jax.jit(whole)
            return
        shard = NamedSharding(self.mesh, PartitionSpec("batch"))
        repl = NamedSharding(self.mesh, PartitionSpec())
        m_sh = jax.tree_util.tree_map(lambda ax: shard if ax == 0 else repl, m_axes,
                                      is_leaf=lambda x: x is None or isinstance(x, int))
        p_sh = jax.tree_util.tree_map(lambda _: shard if pax == 0 else repl, params)
        d_sh = jax.tree_util.tree_map(lambda _: shard, d0)
        u_sh = jax.tree_util.tree_map(lambda _: shard, push)
        self._put = (m_sh, d_sh, p_sh, u_sh)
        self._init = jax.jit(init, in_shardings=(m_sh, d_sh, p_sh), out_shardings=shard)
        self._advance = jax.jit(advance, static_argnums=4, in_shardings=(m_sh, shard, p_sh, u_sh),
                                out_shardings=shard)
        self._whole = jax.jit(whole, in_shardings=self._put, out_shardings=shard)

    def program(self, mx_batched: mjx.Model, d0: mjx.Data, params: Any, push: Push | None = None):
        """``(fn, args)``: the whole run (all ticks) as ONE jitted program and its placed arguments, for
        ahead-of-time compilation and timing (``fn.lower(*args).compile()``); ``fn(*args)`` equals ``self(...)``."""
        if push is None:
            push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (d0.qpos.shape[0],) + x.shape), Push.none())
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        args = (mx_batched, d0, params, push)
        if self._put is not None:
            args = jax.device_put(args, self._put)
        return self._whole, args

    def __call__(self, mx_batched: mjx.Model, d0: mjx.Data, params: Any, push: Push | None = None, *,
                 progress: Progress | None = None, chunk_seconds: float | None = None) -> RolloutResult:
        """Run the batch. ``progress`` without ``chunk_seconds`` reports every simulated second."""
        if push is None:
            push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (d0.qpos.shape[0],) + x.shape), Push.none())
        if progress is not None and chunk_seconds is None:
            chunk_seconds = 1.0
        k = self.chunk_ticks(chunk_seconds)
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        if self._put is not None:  # committed (single-device) inputs move onto the mesh
            mx_batched, d0, params, push = jax.device_put((mx_batched, d0, params, push), self._put)
        carry = self._init(mx_batched, d0, params)
        n, dt, traces = self.cfg.n_ticks, self.cfg.control_dt, []
        for done in range(0, n, k):
            carry, tr = self._advance(mx_batched, carry, params, push, k)
            traces.append(tr)
            if progress is not None:  # dispatch is asynchronous: report a chunk once it has been computed
                jax.block_until_ready(carry.tick)
                progress((done + k) * dt, n * dt)
        trace = None
        if self.record is not None:
            trace = traces[0] if len(traces) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *traces)
        return rollout_result(carry, trace)


def make_batch_runner(ids: hmodel.ModelIds, controller: Controller, cfg: SimConfig, metrics: Metrics = no_metrics(),
                      record=None, params_axes: Any = 0, mesh: Mesh | None = None) -> BatchRunner:
    """The one jit + sharding runner of hyqjax (see :class:`BatchRunner`). Keep it: each new runner compiles anew.

    Args:
      ids: named model ids; controller, metrics, record: as in :func:`rollout`.
      params_axes: ``vmap`` axes of the controller parameters (0: per instance, None: shared).
      mesh: a 1-D ``jax.sharding.Mesh`` with axis ``"batch"`` (:func:`batch_mesh`); the batch must be
        divisible by its size (:func:`pad_batch`). ``None`` runs on the default device.
    """
    return BatchRunner(ids, controller, cfg, metrics, record, params_axes, mesh)


def batch_rollout(mx_batched: mjx.Model, ids: hmodel.ModelIds, d0: mjx.Data, controller: Controller,
                  params: Any, cfg: SimConfig, metrics: Metrics = no_metrics(), record=None,
                  params_axes: Any = 0, mesh: Mesh | None = None, push: Push | None = None) -> RolloutResult:
    """One-off batch run: :func:`make_batch_runner` then call it (compiles on every call; keep a runner to
    run the same static setup repeatedly).

    Args:
      mx_batched: model from :func:`hyqjax.sim.model.batch_model` (leading batch axis on its batched fields).
      d0: batched initial data (leading batch axis on every field).
      params: controller parameters; ``params_axes`` is their ``vmap`` axes (0: per instance, None: shared).
      push: optional per-instance :class:`Push` (leading batch axis).
    """
    return make_batch_runner(ids, controller, cfg, metrics, record, params_axes, mesh)(mx_batched, d0, params, push)


def batch_rollout_fn(mx_batched: mjx.Model, ids: hmodel.ModelIds, d0: mjx.Data, controller: Controller,
                     params: Any, cfg: SimConfig, metrics: Metrics = no_metrics(), record=None,
                     params_axes: Any = 0, mesh: Mesh | None = None, push: Push | None = None):
    """:meth:`BatchRunner.program` of a new runner: the whole batch run as one jitted function and its arguments."""
    return make_batch_runner(ids, controller, cfg, metrics, record, params_axes, mesh).program(mx_batched, d0, params, push)


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all local devices)."""
    devs = np.asarray(jax.local_devices() if devices is None else devices)
    return Mesh(devs, ("batch",))


def pad_batch(n: int, multiple: int) -> int:
    """Smallest batch size >= n divisible by ``multiple``."""
    return -(-n // multiple) * multiple
