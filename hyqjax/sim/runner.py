"""The batch runner: ``vmap`` of :func:`hyqjax.sim.rollout.rollout` over instances, jitted once per static
setup, sharded over a 1-D device mesh (axis ``"batch"``), run in chunks of simulated time with a progress
callback. The one jit + sharding runner of hyqjax: the step-down, the sweeps, bounding and the benchmarks
all run batches through :func:`make_batch_runner` (``hyqjax.make_batch_runner``).

Compile phase. The runner compiles ahead of time (``jit(...).lower(...).compile()``), once per batch shape,
so compiling and simulating are timed apart (:attr:`BatchRunner.last_timing`) and announced to the
listeners of :func:`hyqjax.sim.compile_phase.compile_listener` (the command line shows a "compiling" line with
its elapsed time).

Batch buckets. On CPU devices a batch of ``n`` instances runs as passes of a few fixed sizes
(:mod:`hyqjax.sim.buckets`: :func:`batch_plan`), so one compiled program serves every batch of 5 to any number of
instances; the padded rows repeat the last instance and are dropped from the result. On accelerators (and under
MuJoCo Warp) a batch runs at its own size in one pass. The C MuJoCo backend pads its controller batch to one bucket
(:func:`host_physics_plan`); its padded rows are never stepped.

Devices. A batch over several devices of one host (:func:`run_on`, :class:`RunnersByPlace`, :func:`batch_mesh`)
lives in :mod:`hyqjax.sim.multidevice`; the runner of a device's slice is this runner placed on that device
(:meth:`BatchRunner.placed`), which shares its jitted and compiled programs. Every name of both modules is
importable from here as well.

Both runners compile through :class:`hyqjax.sim.compile_phase.AheadOfTime`, which also tells a program loaded from JAX's persistent
compilation cache from one XLA compiled (``jax.monitoring``'s cache-hit event), so the command line says
"compiling" only for a real compile.
"""
from __future__ import annotations

import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from mujoco import mjx

from hyqjax.sim import impls
from hyqjax.sim import model as hmodel
# The bucket rules and the multi-device helpers have their own modules; their names stay importable from here
# (hyqjax.sim.runner.run_on, .batch_mesh, .host_physics_plan, ... in the docs, tests and the C MuJoCo backend).
from hyqjax.sim.buckets import (CPU_PASS, HOST_PHYSICS_MIN_BUCKET, BatchPlan, batch_plan, bucket,
                                host_physics_plan, pad_batch, take_rows)
# compile_listener is public here (docs/api.md: hyqjax.sim.runner.compile_listener); its home is compile_phase
from hyqjax.sim.compile_phase import AheadOfTime, compile_listener, notify
from hyqjax.sim.multidevice import (Progress, RunnersByPlace, batch_mesh, run_on, run_split,
                                    run_tree_on)
from hyqjax.sim.rollout import (Controller, Metrics, Push, RolloutResult, SimConfig, no_metrics, rollout_advance,
                                rollout_init, rollout_result)

_rows = take_rows  # the C MuJoCo backend's name for it


class _Programs:
    """The jitted functions of one static setup (traced once per batch shape, whatever the device) and the programs
    compiled from them, kept per device (:func:`hyqjax.sim.compile_phase.signature`): shared by a
    :class:`BatchRunner` and the runners placed from it (:meth:`BatchRunner.placed`)."""

    def __init__(self):
        self.init = self.advance = self.whole = self.put = self.m_axes = None
        self.executables: dict = {}
        self.traces = 0  # functions traced (a Python side effect of tracing: the retrace guards' count)


class BatchRunner(AheadOfTime):
    """``vmap`` of :func:`hyqjax.sim.rollout.rollout` over instances, jitted once and optionally sharded over a device mesh.

    Built by :func:`make_batch_runner`; call ``runner(mx_batched, d0, params, push)``. The static parts
    (ids, controller, config, metrics, record, parameter axes, mesh) are fixed at construction, so a runner
    compiles once per batch shape (ahead of time, announced to :func:`compile_listener`) and is reused across
    calls with new values. With ``buckets`` (the default) a batch runs as the passes of :func:`batch_plan`, so
    the batch shape is one of a few buckets whatever the instance count. The scan runs in chunks of
    ``chunk_seconds`` of simulated time (one compiled program: the chunk length divides the number of ticks),
    calling ``progress(sim_seconds_done, sim_seconds_total)`` after each (over several passes both count every
    pass); every chunk continues the carry of the last, so the result is bitwise identical to one scan over all
    ticks. :attr:`last_timing` holds the last call's ``compile_s`` (the compile phase: tracing, lowering, and
    compiling the programs or loading them from the persistent cache), ``trace_s`` (its tracing and lowering
    part, paid by every new process: the persistent cache holds compiled programs, not traces), ``simulate_s``
    (running them), ``compiled`` and ``from_cache`` (programs XLA compiled, programs loaded from the persistent
    cache), ``batch`` (the compiled batch size), ``passes`` and ``instances``.
    """

    def __init__(self, ids: hmodel.ModelIds, controller: Controller, cfg: SimConfig, metrics: Metrics = no_metrics(),
                 record=None, params_axes: Any = 0, mesh: Mesh | None = None, buckets: bool = True):
        self.ids, self.controller, self.cfg, self.metrics = ids, controller, cfg, metrics
        self.record = record if cfg.record_every else None
        self.params_axes, self.mesh, self.buckets = params_axes, mesh, buckets
        #: the device this runner's inputs are placed on (:meth:`placed`; None: where they are)
        self.device = None
        self._base, self._placed, self._options = None, {}, None
        self._programs = _Programs()
        self._executables = self._programs.executables
        self._reset_compile_phase()
        self.last_timing: dict = {}

    def placed(self, device) -> "BatchRunner":
        """The runner of ``device``'s slice of a split batch (:func:`hyqjax.sim.multidevice.run_on`): this runner's
        static setup with its inputs placed on ``device``, built on first use and kept. It shares this runner's
        jitted functions, so a program is traced once for every device (each device lowers and compiles it for
        itself), and its compiled programs, kept per device: the program this runner compiled for the default
        device serves the runner placed there, and the other way round. Its :attr:`compiler_options` are this
        runner's. A runner sharded over a mesh is not placed (``ValueError``)."""
        if self._base is not None:
            return self._base.placed(device)
        if self.mesh is not None:
            raise ValueError("a runner sharded over a mesh runs on the mesh's devices; place a one-device runner")
        if device not in self._placed:
            r = BatchRunner(self.ids, self.controller, self.cfg, self.metrics, self.record, self.params_axes, None,
                            self.buckets)
            r._base, r.device, r._programs, r._executables = self, device, self._programs, self._programs.executables
            self._placed[device] = r
        return self._placed[device]

    @property
    def compiler_options(self) -> dict | None:  # AheadOfTime.compiler_options; a placed runner: its base runner's
        return self._options if self._base is None else self._base.compiler_options

    @compiler_options.setter
    def compiler_options(self, value: dict | None) -> None:
        if self._base is None:
            self._options = value
        else:
            self._base.compiler_options = value

    @property
    def n_compiles(self) -> int:
        """Functions traced for this runner's static setup (the runners placed from one runner count together: they
        share one trace); a retrace guard compares it before and after."""
        return self._programs.traces

    # the jitted functions of the static setup (_Programs), shared with the placed runners
    _init = property(lambda self: self._programs.init)
    _advance = property(lambda self: self._programs.advance)
    _whole = property(lambda self: self._programs.whole)
    _put = property(lambda self: self._programs.put)
    _m_axes = property(lambda self: self._programs.m_axes)

    def plan(self, n: int, mx_batched: mjx.Model | None = None) -> BatchPlan:
        """The :class:`BatchPlan` of a batch of ``n`` (one pass of ``n`` without buckets or under MuJoCo Warp)."""
        devices = (list(self.mesh.devices.flat) if self.mesh is not None
                   else [self.device] if self.device is not None else jax.devices()[:1])
        if not self.buckets or (mx_batched is not None and impls.is_warp_model(mx_batched)):
            return BatchPlan(int(n), int(n), 1)
        return batch_plan(n, devices[0].platform, len(devices))

    def _build(self, mb: mjx.Model, d0: mjx.Data, params, push: Push):
        ids, ctrl, cfg, met, rec, pax = self.ids, self.controller, self.cfg, self.metrics, self.record, self.params_axes
        m_axes = hmodel.model_in_axes(mb)
        progs = self._programs

        def init(mm, dd, pp):
            progs.traces += 1
            return jax.vmap(lambda m1, d1, p1: rollout_init(m1, ids, d1, ctrl, p1, met),
                            in_axes=(m_axes, 0, pax))(mm, dd, pp)

        def advance(mm, cc, pp, pu, n_ticks):
            progs.traces += 1
            return jax.vmap(lambda m1, c1, p1, u1: rollout_advance(m1, ids, c1, ctrl, p1, cfg, n_ticks, met, rec, u1),
                            in_axes=(m_axes, 0, pax, 0))(mm, cc, pp, pu)

        def whole(mm, dd, pp, pu):
            progs.traces += 1
            c = jax.vmap(lambda m1, d1, p1: rollout_init(m1, ids, d1, ctrl, p1, met), in_axes=(m_axes, 0, pax))(mm, dd, pp)
            c, tr = jax.vmap(lambda m1, c1, p1, u1: rollout_advance(m1, ids, c1, ctrl, p1, cfg, cfg.n_ticks, met, rec, u1),
                             in_axes=(m_axes, 0, pax, 0))(mm, c, pp, pu)
            return rollout_result(c, tr)

        progs.m_axes = m_axes
        if self.mesh is None:
            progs.init, progs.advance, progs.put = jax.jit(init), jax.jit(advance, static_argnums=4), None
            progs.whole = jax.jit(whole)
            return
        shard = NamedSharding(self.mesh, PartitionSpec("batch"))
        repl = NamedSharding(self.mesh, PartitionSpec())
        m_sh = jax.tree_util.tree_map(lambda ax: shard if ax == 0 else repl, m_axes,
                                      is_leaf=lambda x: x is None or isinstance(x, int))
        p_sh = jax.tree_util.tree_map(lambda _: shard if pax == 0 else repl, params)
        d_sh = jax.tree_util.tree_map(lambda _: shard, d0)
        u_sh = jax.tree_util.tree_map(lambda _: shard, push)
        progs.put = (m_sh, d_sh, p_sh, u_sh)
        progs.init = jax.jit(init, in_shardings=(m_sh, d_sh, p_sh), out_shardings=shard)
        progs.advance = jax.jit(advance, static_argnums=4, in_shardings=(m_sh, shard, p_sh, u_sh),
                                out_shardings=shard)
        progs.whole = jax.jit(whole, in_shardings=progs.put, out_shardings=shard)

    def program(self, mx_batched: mjx.Model, d0: mjx.Data, params: Any, push: Push | None = None):
        """``(fn, args)``: the whole run (all ticks) as ONE jitted program and its placed arguments, for
        ahead-of-time compilation and timing (``fn.lower(*args).compile()``); ``fn(*args)`` equals ``self(...)``
        (the batch at its own size: no buckets)."""
        if push is None:
            push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (d0.qpos.shape[0],) + x.shape), Push.none())
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        args = (mx_batched, d0, params, push)
        if self._put is not None:
            args = jax.device_put(args, self._put)
        elif self.device is not None:
            args = jax.device_put(args, self.device)
        return self._whole, args

    def __call__(self, mx_batched: mjx.Model, d0: mjx.Data, params: Any, push: Push | None = None, *,
                 progress: Progress | None = None, chunk_seconds: float | None = None) -> RolloutResult:
        """Run the batch. ``progress`` without ``chunk_seconds`` reports every simulated second."""
        n = int(d0.qpos.shape[0])
        if push is None:
            push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (n,) + x.shape), Push.none())
        if progress is not None and chunk_seconds is None:
            chunk_seconds = 1.0
        k = self.chunk_ticks(chunk_seconds)
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((mx_batched, d0, params, push))):
            return self._traced(mx_batched, d0, params, push, k)
        plan = self.plan(n, mx_batched)
        self._new_timing(plan)
        if plan.passes == 1 and plan.size == n:
            out = self._run_pass(mx_batched, d0, params, push, k, progress, 0, 1)
            notify("done", **self.last_timing)
            return out
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        parts = []
        for p in range(plan.passes):  # rows of this pass, the last instance repeated past the end
            idx = np.minimum(np.arange(p * plan.size, (p + 1) * plan.size), n - 1)
            res = self._run_pass(take_rows(mx_batched, self._m_axes, idx), take_rows(d0, 0, idx),
                                 take_rows(params, self.params_axes, idx), take_rows(push, 0, idx), k, progress, p,
                                 plan.passes)
            parts.append(jax.tree_util.tree_map(np.asarray, res))
        out = jax.device_put(jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, 0)[:n], *parts))
        notify("done", **self.last_timing)
        return out

    def _traced(self, mx_batched, d0, params, push, k: int) -> RolloutResult:
        """Under a JAX transformation (the inputs are tracers): the jitted programs inlined into the caller's
        trace, at the batch's own size, without progress or timing."""
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        carry, traces = self._init(mx_batched, d0, params), []
        for _ in range(0, self.cfg.n_ticks, k):
            carry, tr = self._advance(mx_batched, carry, params, push, k)
            traces.append(tr)
        trace = None
        if self.record is not None:
            trace = traces[0] if len(traces) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *traces)
        return rollout_result(carry, trace)

    def _run_pass(self, mx_batched, d0, params, push, k: int, progress, pass_index: int, passes: int) -> RolloutResult:
        if self._init is None:
            self._build(mx_batched, d0, params, push)
        if self._put is not None:  # committed (single-device) inputs move onto the mesh
            mx_batched, d0, params, push = jax.device_put((mx_batched, d0, params, push), self._put)
        elif self.device is not None:  # a placed runner's inputs onto its device
            mx_batched, d0, params, push = jax.device_put((mx_batched, d0, params, push), self.device)
        batch = int(d0.qpos.shape[0])
        init = self._executable("init", self._init, (mx_batched, d0, params), batch=batch)
        carry = init(mx_batched, d0, params)
        advance = self._executable("advance", self._advance, (mx_batched, carry, params, push), (k,), batch=batch)
        self._end_compile_phase(batch)
        t0 = time.perf_counter()
        n, dt, traces = self.cfg.n_ticks, self.cfg.control_dt, []
        for done in range(0, n, k):
            carry, tr = advance(mx_batched, carry, params, push)
            traces.append(tr)
            if progress is not None:  # dispatch is asynchronous: report a chunk once it has been computed
                jax.block_until_ready(carry.tick)
                progress((pass_index * n + done + k) * dt, passes * n * dt)
        jax.block_until_ready(carry.tick)
        self.last_timing["simulate_s"] += time.perf_counter() - t0
        trace = None
        if self.record is not None:
            trace = traces[0] if len(traces) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *traces)
        return rollout_result(carry, trace)


def make_batch_runner(ids: hmodel.ModelIds, controller: Controller, cfg: SimConfig, metrics: Metrics = no_metrics(),
                      record=None, params_axes: Any = 0, mesh: Mesh | None = None, buckets: bool = True) -> BatchRunner:
    """The one jit + sharding runner of hyqjax (see :class:`BatchRunner`). Keep it: each new runner compiles anew.

    Args:
      ids: named model ids; controller, metrics, record: as in :func:`rollout`.
      params_axes: ``vmap`` axes of the controller parameters (0: per instance, None: shared).
      mesh: a 1-D ``jax.sharding.Mesh`` with axis ``"batch"`` (:func:`batch_mesh`); the batch must be
        divisible by its size (:func:`pad_batch`). ``None`` runs on the default device.
      buckets: run a batch as the passes of :func:`batch_plan` (CPU: a few fixed shapes, so a new instance count
        does not compile again); False: at its own size.
    """
    return BatchRunner(ids, controller, cfg, metrics, record, params_axes, mesh, buckets)


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


__all__ = ["BatchPlan", "BatchRunner", "CPU_PASS", "HOST_PHYSICS_MIN_BUCKET", "Progress", "batch_mesh", "batch_plan",
           "batch_rollout", "batch_rollout_fn", "bucket", "compile_listener", "host_physics_plan", "make_batch_runner",
           "pad_batch", "run_on", "run_split", "run_tree_on", "RunnersByPlace"]
