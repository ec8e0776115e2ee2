"""The batch runner: ``vmap`` of :func:`hyqjax.sim.rollout.rollout` over instances, jitted once per static
setup, sharded over a 1-D device mesh (axis ``"batch"``), run in chunks of simulated time with a progress
callback. The one jit + sharding runner of hyqjax: the step-down, the sweeps, bounding and the benchmarks
all run batches through :func:`make_batch_runner` (``hyqjax.make_batch_runner``).

Compile phase. The runner compiles ahead of time (``jit(...).lower(...).compile()``), once per batch shape,
so compiling and simulating are timed apart (:attr:`BatchRunner.last_timing`) and announced to the
listeners of :func:`hyqjax.sim.compile_phase.compile_listener` (the command line shows a "compiling" line with
its elapsed time).

Batch buckets. On CPU devices a batch of ``n`` instances runs as passes of a few fixed sizes
(:func:`batch_plan`): ``n <= CPU_PASS`` rounds up to a power of two, a larger ``n`` runs as
``ceil(n / CPU_PASS)`` passes of ``CPU_PASS`` instances. The padding repeats the last instance; padded rows are
dropped from the result, so they are never seen or counted. One compiled program then serves every batch of
5 to any number of instances, and changing the instance count does not compile again. Every instance is
independent under ``vmap``, so its result does not depend on the bucket (a test checks it row for row). On
accelerators (and under MuJoCo Warp, whose contact buffers are sized for the whole batch) a batch runs at its
own size in one pass. The C MuJoCo backend, whose physics runs outside the compiled program, pads its controller
batch to one bucket (:func:`host_physics_plan`: the next power of two, at least ``HOST_PHYSICS_MIN_BUCKET``);
its padded rows are never stepped.

Both runners compile through :class:`hyqjax.sim.compile_phase.AheadOfTime`, which also tells a program loaded from JAX's persistent
compilation cache from one XLA compiled (``jax.monitoring``'s cache-hit event), so the command line says
"compiling" only for a real compile.
"""
from __future__ import annotations

import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from mujoco import mjx

from hyqjax.sim import impls
from hyqjax.sim import model as hmodel
# compile_listener is public here (docs/api.md: hyqjax.sim.runner.compile_listener); its home is compile_phase
from hyqjax.sim.compile_phase import AheadOfTime, compile_listener, notify
from hyqjax.sim.rollout import (Controller, Metrics, Push, RolloutResult, SimConfig, no_metrics, rollout_advance,
                                rollout_init, rollout_result)


Progress = Callable[[float, float], None]

#: Instances per pass on one CPU device (the batch buckets, :func:`batch_plan`). On 2 CPU cores MJX's closed
#: loop saturates at about 10k env-steps/s from batch 16 on (benchmarks/RESULTS.md, bench_physics); 8 trades a
#: little of that for less padding of small batches (at most 7 padded rows, a third of the default step-down's 6).
CPU_PASS = 8

class BatchPlan(NamedTuple):
    """How a batch of ``n`` instances runs: ``passes`` passes of ``size`` instances (the compiled batch shape);
    the ``passes * size - n`` padded rows repeat the last instance and are dropped from the result."""

    n: int
    size: int
    passes: int

    @property
    def padded(self) -> int:
        return self.passes * self.size - self.n


#: The smallest batch bucket of a runner whose physics runs outside the compiled program (the C MuJoCo backend,
#: :func:`host_physics_plan`). Padded rows cost controller and metrics compute, never physics: on 2 CPU cores the
#: step-down's 18 instances in a bucket of 32 (the worst padding of ``--instances`` 3 to 5) ran at 0.8 of the
#: exact batch's env-steps/s, 30 in 32 at no measurable cost (benchmarks/RESULTS.md, bench_c_buckets); 8 puts
#: every batch of up to 8 instances in one bucket.
HOST_PHYSICS_MIN_BUCKET = 8


def bucket(n: int, minimum: int = 1) -> int:
    """The batch bucket of ``n`` instances: the smallest power of two ``>= max(n, minimum)``."""
    return 1 << max(max(int(n), int(minimum)) - 1, 0).bit_length()


def host_physics_plan(n: int) -> BatchPlan:
    """The bucket of a batch of ``n`` whose physics runs outside the compiled program (the C MuJoCo backend): one
    pass of :func:`bucket` ``(n, HOST_PHYSICS_MIN_BUCKET)`` rows. The padded rows repeat the last instance in the
    controller and metrics only (its observation, parameters and controller state); the physics steps the ``n``
    real instances alone, and the padded rows are dropped from the result. One pass, whatever ``n``: the
    physics of every real row runs in parallel each tick, and padding more than doubles no batch."""
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"a batch needs at least one instance, got {n}")
    return BatchPlan(int(n), bucket(n, HOST_PHYSICS_MIN_BUCKET), 1)


def batch_plan(n: int, platform: str = "cpu", n_devices: int = 1, pass_size: int | None = None) -> BatchPlan:
    """The bucket of a batch of ``n`` instances on ``n_devices`` devices of ``platform``.

    CPU: with ``P = pass_size`` (default ``CPU_PASS * n_devices``), ``n <= P`` runs once at the smallest power of
    two ``>= n`` (a multiple of ``n_devices``), a larger ``n`` as ``ceil(n / P)`` passes of ``P``. Other platforms:
    one pass of ``n`` rounded up to a multiple of ``n_devices``.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"a batch needs at least one instance, got {n}")
    n, nd = int(n), max(int(n_devices), 1)
    if platform != "cpu":
        return BatchPlan(n, pad_batch(n, nd), 1)
    big = pad_batch(pass_size or CPU_PASS * nd, nd)
    if n > big:
        return BatchPlan(n, big, -(-n // big))
    return BatchPlan(n, min(pad_batch(bucket(n), nd), big), 1)


def _rows(tree, axes, idx: np.ndarray):
    """Rows ``idx`` (host NumPy) of the leaves of ``tree`` whose ``vmap`` axis (``axes``: 0, None, or a pytree
    of them) is 0; other leaves unchanged."""
    if axes is None:
        return tree
    if isinstance(axes, int):
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], tree)
    return jax.tree_util.tree_map(lambda ax, x: x if ax is None else np.asarray(x)[idx], axes, tree,
                                  is_leaf=lambda x: x is None)


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
        self._init = self._advance = None
        self._executables: dict = {}
        self._reset_compile_phase()
        self.n_compiles = 0  # programs traced (for retrace guards)
        self.last_timing: dict = {}

    def plan(self, n: int, mx_batched: mjx.Model | None = None) -> BatchPlan:
        """The :class:`BatchPlan` of a batch of ``n`` (one pass of ``n`` without buckets or under MuJoCo Warp)."""
        devices = list(self.mesh.devices.flat) if self.mesh is not None else jax.devices()[:1]
        if not self.buckets or (mx_batched is not None and impls.is_warp_model(mx_batched)):
            return BatchPlan(int(n), int(n), 1)
        return batch_plan(n, devices[0].platform, len(devices))

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

        self._m_axes = m_axes
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
        ahead-of-time compilation and timing (``fn.lower(*args).compile()``); ``fn(*args)`` equals ``self(...)``
        (the batch at its own size: no buckets)."""
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
            res = self._run_pass(_rows(mx_batched, self._m_axes, idx), _rows(d0, 0, idx),
                                 _rows(params, self.params_axes, idx), _rows(push, 0, idx), k, progress, p,
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


def run_split(runners: list, parts: list, progress: Progress | None = None,
              chunk_seconds: float | None = None) -> RolloutResult:
    """One program per device: ``parts[i] = (mx_batched, d0, params, push)``, committed to device ``i``, runs on
    ``runners[i]`` (a single-device :class:`BatchRunner` of the same static setup, one per device: each keeps the
    programs compiled for its device). Every device's program is compiled first (device 0's by XLA; on a GPU the
    persistent compilation cache then serves the others: its key leaves out the device), then the chunks of
    simulated time are dispatched to every device in turn (asynchronously, so the devices run at once) and the
    results concatenated along the batch axis on the host. ``progress`` as :class:`BatchRunner`'s (device 0's
    chunks; the slices are of equal size). One ``done`` event reports the whole run (``devices``: how many)."""
    if progress is not None and chunk_seconds is None:
        chunk_seconds = 1.0
    r0 = runners[0]
    k = r0.chunk_ticks(chunk_seconds)
    t_start = time.perf_counter()
    states = []
    compile_s = trace_s = 0.0
    compiled = from_cache = 0
    for r, (mb, d0, params, push) in zip(runners, parts):
        b = int(d0.qpos.shape[0])
        r._new_timing(BatchPlan(b, b, 1))
        if r._init is None:
            r._build(mb, d0, params, push)
        init = r._executable("init", r._init, (mb, d0, params), batch=b)
        carry = init(mb, d0, params)
        advance = r._executable("advance", r._advance, (mb, carry, params, push), (k,), batch=b)
        r._end_compile_phase(b)
        t = r.last_timing
        compile_s, trace_s = compile_s + t["compile_s"], trace_s + t["trace_s"]
        compiled, from_cache = compiled + t["compiled"], from_cache + t["from_cache"]
        states.append([advance, carry, []])
    t0 = time.perf_counter()
    cfg = r0.cfg
    n, dt = cfg.n_ticks, cfg.control_dt
    for done in range(0, n, k):
        for st, (mb, _, params, push) in zip(states, parts):
            st[1], tr = st[0](mb, st[1], params, push)
            st[2].append(tr)
        if progress is not None:
            jax.block_until_ready(states[0][1].tick)
            progress((done + k) * dt, n * dt)
    jax.block_until_ready([st[1].tick for st in states])
    simulate_s = time.perf_counter() - t0
    outs = []
    for r, st in zip(runners, states):
        trace = None
        if r.record is not None:
            trace = st[2][0] if len(st[2]) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *st[2])
        outs.append(jax.tree_util.tree_map(np.asarray, rollout_result(st[1], trace)))
    sizes = [int(p[1].qpos.shape[0]) for p in parts]
    total = sum(sizes)

    def cat(*xs):  # batched leaves joined; a leaf without the batch axis (Warp's contact buffer) is device 0's
        if all(np.ndim(x) >= 1 and x.shape[0] == b for x, b in zip(xs, sizes)):
            return np.concatenate(xs, 0)
        return xs[0]

    out = jax.tree_util.tree_map(cat, *outs)
    timing = dict(compile_s=compile_s, trace_s=trace_s, simulate_s=simulate_s, compiled=compiled,
                  from_cache=from_cache, batch=total, passes=1, instances=total, devices=len(runners),
                  wall_s=time.perf_counter() - t_start)
    for r in runners:
        r.last_timing = dict(r.last_timing, simulate_s=simulate_s)
    notify("done", **timing)
    return out


def run_on(devices: list, n: int, inputs_of: Callable, runner_of: Callable, impl: str,
           progress: Progress | None = None, chunk_seconds: float | None = None,
           how: str | None = None) -> RolloutResult:
    """Run a batch of ``n`` instances over ``devices`` in the layout of the resolved simulator ``impl``
    (:func:`hyqjax.sim.devices.layout`): one device; MJX-JAX's ``mesh`` (one program sharded over
    :func:`batch_mesh`); MuJoCo Warp's ``split`` (:func:`run_split`: equal contiguous slices, the last padded by
    repeating instance ``n - 1``, one program per device).

    ``inputs_of(idx)``: ``(mx_batched, d0, params, push)`` of the instances ``idx`` (a host integer array);
    ``runner_of(where)``: the :class:`BatchRunner` for ``where``, None (one device), a mesh, or a device (one
    runner per device, kept by the caller). ``how`` overrides the layout (``"split"`` under MJX-JAX, to compare
    the layouts). Returns the :class:`RolloutResult` of the ``n`` instances in order."""
    from hyqjax.sim import devices as hdevices

    devices = list(devices)
    how = how or hdevices.layout(impl, len(devices))
    if how != "split":
        runner = runner_of(None if how == "one" else batch_mesh(devices))
        return runner(*inputs_of(np.arange(n)), progress=progress, chunk_seconds=chunk_seconds)
    k = len(devices)
    size = -(-n // k)
    parts = []
    for i, dev in enumerate(devices):
        idx = np.minimum(np.arange(i * size, (i + 1) * size), n - 1)
        parts.append(jax.device_put(inputs_of(idx), dev))
    out = run_split([runner_of(dev) for dev in devices], parts, progress, chunk_seconds)
    return jax.tree_util.tree_map(lambda x: x[:n] if np.ndim(x) >= 1 and x.shape[0] == k * size else x, out)


class RunnersByPlace:
    """The runners of ONE static setup, one per placement, built on first use by ``make(mesh)`` (a
    :class:`BatchRunner` factory) and kept: ``runners(None)`` the one-device runner, ``runners(device)`` the runner
    of that device's slice of a split batch (:func:`run_on`), ``runners(mesh)`` the runner sharded over ``mesh``."""

    def __init__(self, make: Callable[[Mesh | None], Any]):
        self.make, self._kept = make, {}

    def __call__(self, where=None):
        if where is None:
            key, mesh = None, None
        elif hasattr(where, "axis_names"):
            key, mesh = ("mesh", tuple(d.id for d in where.devices.flat), where.axis_names), where
        else:
            key, mesh = ("device", where.id), None
        if key not in self._kept:
            self._kept[key] = self.make(mesh)
        return self._kept[key]


def run_tree_on(devices, runners: Callable, impl: str, tree: Any, inputs_of: Callable,
                progress: Progress | None = None, chunk_seconds: float | None = None) -> RolloutResult:
    """:func:`run_on` of a batch given as a PyTree ``tree`` whose every leaf has the leading batch axis (e.g.
    ``(scenario, params)``): ``inputs_of(rows)`` makes ``(mx_batched, d0, params, push)`` of a PyTree of rows;
    ``runners`` e.g. a :class:`RunnersByPlace`. Each row keeps its inputs whatever device computes it (a
    population's common random numbers stay common)."""
    n = int(jax.tree_util.tree_leaves(tree)[0].shape[0])
    full = np.arange(n)

    def rows(idx):
        if len(idx) == n and np.array_equal(idx, full):
            return inputs_of(tree)
        return inputs_of(jax.tree_util.tree_map(lambda x: x[idx], tree))

    return run_on(list(devices), n, rows, runners, impl, progress, chunk_seconds)


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


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all local devices)."""
    devs = np.asarray(jax.local_devices() if devices is None else devices)
    return Mesh(devs, ("batch",))


def pad_batch(n: int, multiple: int) -> int:
    """Smallest batch size >= n divisible by ``multiple``."""
    return -(-n // multiple) * multiple


__all__ = ["BatchPlan", "BatchRunner", "CPU_PASS", "HOST_PHYSICS_MIN_BUCKET", "Progress", "batch_mesh", "batch_plan",
           "batch_rollout", "batch_rollout_fn", "bucket", "compile_listener", "host_physics_plan", "make_batch_runner",
           "pad_batch", "run_on", "run_split", "run_tree_on", "RunnersByPlace"]
