"""The closed loop of a batch on C MuJoCo (:class:`CBatchRunner`, the runner of :mod:`hyqjax.sim.cpu_backend`).

It runs as ONE jitted ``lax.scan`` over control ticks, in which

1. the controller (``jax.vmap`` over instances of ``controller.step``) computes the joint torques of the whole
   batch from the :class:`hyqjax.core.types.Observation` of every instance (:func:`hyqjax.sim.observe.observation`,
   the same definition as under MJX);
2. a host call (:mod:`hyqjax.sim.host_call`: an XLA FFI target that is a Python function) hands the torques to
   :class:`hyqjax.sim.cpu_physics.CPhysics`, which holds the instances in float64 in one ``mujoco.batch.Batch`` and
   steps them with ``mj_step`` in one call into C (a loop over the instances without the GIL), and returns the data
   the metrics read as a :class:`hyqjax.sim.observe.DataView` (float32 unless ``jax_enable_x64``);
3. divergence, metrics and traces follow the rules of :func:`hyqjax.sim.rollout.rollout_advance`: an instance
   whose state is non-finite or faster than ``SimConfig.max_speed`` is frozen at its last finite tick (its
   simulation is no longer stepped), its controller state and metrics stop, and ``diverged_tick`` records when.

The controller and metrics are compiled once per batch bucket and chunk length (seconds, not the minutes of an
MJX compile); the physics is never compiled. The controller batch is padded to a bucket
(:func:`hyqjax.sim.runner.host_physics_plan`: the next power of two, at least 8), so another instance count in
the same bucket reuses the compiled program: the padded rows repeat the last instance's observation,
parameters and controller state, are never stepped in C MuJoCo (the host call copies the last real row's data
into them) and are dropped from the result. The chunk length depends on the simulated time alone. Because the
physics is an FFI target named by a string (not an ``io_callback``, whose program JAX never caches), the
compiled program goes to the persistent compilation cache, and a new process with a batch in the same bucket
loads it instead of compiling. Warnings MuJoCo prints for an unstable instance go to the
``hyqjax.sim.cpu_backend`` logger (debug level) while a batch runs, not to ``MUJOCO_LOG.TXT``.

**Shards.** A batch runs as contiguous shards, one per CPU core (:meth:`CBatchRunner.shard_bounds`; at least
:data:`MIN_SHARD_ROWS` rows each, so a small batch runs as one), each with its own batch of simulations stepped on
one thread and its own copy of the compiled chunk program, executed at once from one host thread per shard. A tick
of one shard is its controller (compiled JAX) and then its physics (C MuJoCo); with one shard the two run one after
the other, the core that is not stepping physics waiting for the controller. With two, one shard's controller runs
while the other's physics steps (JAX and MuJoCo both release the GIL). Every shard is padded to the bucket of the
largest, so all run one compiled program. Each instance's computation is the same whatever the sharding, and so are its
results, bit for bit (tested).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import logging
import threading
import time
import types
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hyqjax.core import robot
from hyqjax.core.types import Controller, Metrics, Push
from hyqjax.sim import host_call
from hyqjax.sim import model as hmodel
from hyqjax.sim import observe as hobs
from hyqjax.sim import runner as hrunner
from hyqjax.sim.compile_phase import AheadOfTime, notify
from hyqjax.sim.cpu_models import CInitialData
from hyqjax.sim.cpu_physics import CPhysics, default_threads, push_rows, unpack
from hyqjax.sim.host_jit import host_jit

#: MuJoCo's warnings while a batch runs (:func:`_warnings_to_log`), under the backend's name.
log = logging.getLogger("hyqjax.sim.cpu_backend")

#: The fewest rows a shard of a batch has (a smaller batch runs as fewer shards, down to one).
MIN_SHARD_ROWS = 8


@contextlib.contextmanager
def _warnings_to_log():
    """MuJoCo's warnings (an unstable instance) go to this module's logger while a batch runs."""
    prev = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda msg: log.debug("MuJoCo: %s", msg))
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(prev)


#: Name of the FFI target that steps the C MuJoCo batches (:mod:`hyqjax.sim.host_call`).
PHYSICS_TARGET = "hyqjax_c_mujoco_step"
#: The batches being simulated, by the handle their compiled program passes to the physics target.
_ACTIVE: dict[int, CPhysics] = {}
_next_handle = iter(range(1, 2**31 - 1))


def _physics_target(args: list[np.ndarray], results: list[np.ndarray]) -> None:
    handle, tau_frozen = args
    _ACTIVE[int(handle)].step_padded(tau_frozen, results[0])


class CBatchRunner(AheadOfTime):
    """The closed loop of a batch on C MuJoCo (module docstring); the counterpart of
    :class:`hyqjax.sim.runner.BatchRunner` with the same call and result.

    ``runner(models, d0, params, push, progress=..., chunk_seconds=...)`` with ``models`` from
    :func:`hyqjax.sim.cpu_models.batch_models` and ``d0`` a :class:`CInitialData`; returns a
    :class:`hyqjax.sim.rollout.RolloutResult` whose ``data`` is the final :class:`hyqjax.sim.observe.DataView`.
    With ``buckets`` (the default) the controller
    batch is padded to :func:`hyqjax.sim.runner.host_physics_plan`'s bucket, so the controller and metrics are
    compiled once per bucket and chunk length and reused by later calls (and, through the persistent compilation
    cache, by later processes). :attr:`last_timing` as :class:`hyqjax.sim.runner.BatchRunner`'s.
    """

    def __init__(self, ids: hmodel.ModelIds, controller: Controller, cfg, metrics: Metrics | None = None,
                 record=None, params_axes: Any = 0, threads: int | None = None, buckets: bool = True,
                 shards: int | None = None):
        from hyqjax.sim import rollout as sim

        self.ids, self.controller, self.cfg = ids, controller, cfg
        self.metrics = metrics if metrics is not None else sim.no_metrics()
        self.record = record if cfg.record_every else None
        self.params_axes, self.threads, self.buckets, self.shards = params_axes, threads, buckets, shards
        self.n_compiles, self._layout, self._width = 0, None, 0
        self._init = host_jit(self._init_fn)
        self._advance = host_jit(self._advance_fn, static_argnums=3)
        self._executables: dict = {}
        self._reset_compile_phase()
        self.last_timing: dict = {}
        host_call.register(PHYSICS_TARGET, _physics_target)

    def plan(self, n: int) -> hrunner.BatchPlan:
        """The :class:`hyqjax.sim.runner.BatchPlan` of a batch of ``n`` (one pass; padded to a bucket unless
        ``buckets`` is off)."""
        return hrunner.host_physics_plan(n) if self.buckets else hrunner.BatchPlan(int(n), int(n), 1)

    # ------------------------------------------------------------------ the jitted programs
    def _init_fn(self, view0: hobs.DataView, params):
        from hyqjax.sim import rollout as sim

        self.n_compiles += 1
        b = view0.qpos.shape[0]
        tau0 = jnp.zeros((b, robot.N_JOINTS), view0.qpos.dtype)
        obs0 = jax.vmap(lambda v, t: hobs.observe_view(self.ids, v, t))(view0, tau0)
        cs = jax.vmap(self.controller.init, in_axes=(self.params_axes, 0))(params, obs0)
        ms = jax.vmap(self.metrics.init)(view0)
        carry = sim.RolloutCarry(view0, cs, ms, tau0, jnp.zeros(b, bool), jnp.full(b, -1, jnp.int32),
                                 jnp.zeros(b, jnp.int32), jnp.zeros(b, bool), jnp.full(b, -1, jnp.int32))
        return jax.tree_util.tree_map(lambda x: jax.lax.convert_element_type(x, jnp.result_type(x)), carry)

    def _advance_fn(self, carry, params, handle, n_ticks: int):
        from hyqjax.sim import rollout as sim

        self.n_compiles += 1
        ids, ctrl, cfg, met, rec = self.ids, self.controller, self.cfg, self.metrics, self.record
        layout = self._layout
        packed = jax.ShapeDtypeStruct((carry.data.qpos.shape[0], self._width), carry.data.qpos.dtype)
        def control(v, cs, tau_prev, p):
            obs = hobs.observe_view(ids, v, tau_prev)
            cs_new, tau, info = ctrl.step(p, cs, obs)
            return obs, cs_new, jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT), info

        def settle(v, v_new, cs, cs_new, ms, obs, info, tau, tau_prev, div, div_tick, k, term, term_tick):
            # The divergence rule and the episode end, per instance: hyqjax.sim.rollout.settle_tick.
            v_new, cs_new, ms_new, tau, div, div_tick, term, term_tick = sim.settle_tick(
                v_new, v, cs_new, cs, ms, lambda m, vv: met.update(m, vv, obs, info), tau, tau_prev, div, div_tick,
                k, term, term_tick, max_speed=cfg.max_speed, terminal=met.terminal)
            out = rec(v_new, obs, info) if rec is not None else None
            return v_new, cs_new, ms_new, tau, div, div_tick, term, term_tick, out

        def tick(c, _):
            v, cs, ms, tau_prev, div, div_tick, k, term, term_tick = c
            obs, cs_new, tau, info = jax.vmap(control, in_axes=(0, 0, 0, self.params_axes))(v, cs, tau_prev, params)
            frozen = (div | term)[:, None].astype(tau.dtype)  # a frozen instance is not stepped
            args = jnp.concatenate([tau, frozen], axis=1)  # one input array: (B, nu + 1)
            v_new = unpack(layout, host_call.call(PHYSICS_TARGET, packed, handle, args))
            v_new, cs_new, ms_new, tau, div, div_tick, term, term_tick, out = jax.vmap(settle)(
                v, v_new, cs, cs_new, ms, obs, info, tau, tau_prev, div, div_tick, k, term, term_tick)
            return sim.RolloutCarry(v_new, cs_new, ms_new, tau, div, div_tick, k + 1, term, term_tick), out

        if rec is not None:
            def block(c, _):
                c, outs = jax.lax.scan(tick, c, None, length=cfg.record_every)
                return c, jax.tree_util.tree_map(lambda x: x[-1], outs)

            carry, trace = jax.lax.scan(block, carry, None, length=n_ticks // cfg.record_every)
            return carry, jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), trace)  # (B, samples, ...)
        carry, _ = jax.lax.scan(lambda c, x: (tick(c, x)[0], None), carry, None, length=n_ticks)
        return carry, None

    # ------------------------------------------------------------------ running a batch
    def shard_bounds(self, n: int) -> list[tuple[int, int]]:
        """Contiguous row ranges ``[lo, hi)`` of the shards a batch of ``n`` runs as (module docstring, "Shards"):
        ``shards`` of them (at most ``n``; default: one per CPU core this process may use, as many as give each at
        least :data:`MIN_SHARD_ROWS` rows), the larger ones first."""
        want = self.shards if self.shards is not None else min(default_threads(), n // MIN_SHARD_ROWS)
        s = max(1, min(int(want), n))
        edges = np.cumsum([0] + [n // s + (i < n % s) for i in range(s)])  # the larger shards first
        return [(int(lo), int(hi)) for lo, hi in zip(edges[:-1], edges[1:])]

    def __call__(self, models: list[mujoco.MjModel], d0: CInitialData, params: Any, push: Push | None = None, *,
                 progress=None, chunk_seconds: float | None = None):
        from hyqjax.sim import rollout as sim

        if progress is not None and chunk_seconds is None:
            chunk_seconds = 1.0
        k = self.chunk_ticks(chunk_seconds)
        n = len(models)
        bounds = self.shard_bounds(n)
        plan = self.plan(bounds[0][1] - bounds[0][0])  # every shard padded to the largest one's bucket
        dtype = np.dtype(jnp.result_type(float))
        pushes = push_rows(push, n)
        per_shard = max(1, (self.threads or default_threads()) // len(bounds))
        shards = []
        for lo, hi in bounds:
            rows = lo + np.minimum(np.arange(plan.size), hi - lo - 1)  # the padded rows repeat the shard's last
            sp = None if pushes is None else Push(*(x[lo:hi] for x in pushes))
            phys = CPhysics(models[lo:hi], d0.qpos[lo:hi], self.ids.trunk_body, self.cfg.substeps, sp, per_shard,
                            dtype, qvel0=None if d0.qvel is None else d0.qvel[lo:hi])
            shards.append(types.SimpleNamespace(lo=lo, hi=hi, rows=rows, phys=phys, handle=next(_next_handle),
                                                params=hrunner._rows(params, self.params_axes, rows), carry=None,
                                                traces=[], done=0))
        self._layout, self._width = shards[0].phys.layout, shards[0].phys.width
        n_ticks, dt = self.cfg.n_ticks, self.cfg.control_dt
        self._new_timing(hrunner.BatchPlan(n, plan.size * len(shards), 1))
        self.last_timing["shards"] = len(shards)
        for sh in shards:
            _ACTIVE[sh.handle] = sh.phys
        host_call.discard_pending(PHYSICS_TARGET)
        lock, reported = threading.Lock(), [0]

        def chunk_done(sh) -> None:  # progress at the pace of the slowest shard
            with lock:
                sh.done += k
                least = min(x.done for x in shards)
                if progress is not None and least > reported[0]:
                    reported[0] = least
                    progress(least * dt, n_ticks * dt)

        stop = threading.Event()  # set when another shard failed or the caller was interrupted

        def run(sh, advance, h) -> None:
            for _ in range(0, n_ticks, k):
                if stop.is_set():
                    return
                sh.carry, tr = advance(sh.carry, sh.params, h)
                sh.traces.append(tr)
                if progress is not None:
                    jax.block_until_ready(sh.carry.tick)
                    host_call.raise_pending(PHYSICS_TARGET)  # a failed host call stops the run at this chunk
                    chunk_done(sh)
            jax.block_until_ready(sh.carry)

        try:
            with _warnings_to_log():
                # Unpacked in NumPy, then put (slicing JAX arrays would compile a program per field).
                views0 = [jax.tree_util.tree_map(jnp.asarray, unpack(sh.phys.layout, sh.phys.packed()[sh.rows - sh.lo]))
                          for sh in shards]
                # The initial-state program compiles while the chunk program is traced for its output's shapes.
                get_init, carry0 = self._executable_in_background("init", self._init, (views0[0], shards[0].params),
                                                                  batch=plan.size)
                hs = [jnp.asarray(np.asarray(sh.handle, np.int32)) for sh in shards]  # NumPy would compile a conversion
                advance = self._executable("advance", self._advance, (carry0, shards[0].params, hs[0]), (k,),
                                           batch=plan.size)
                init = get_init()
                for sh, view0 in zip(shards, views0):
                    sh.carry = init(view0, sh.params)
                self._end_compile_phase(plan.size)
                t_sim = time.perf_counter()
                if len(shards) == 1:
                    run(shards[0], advance, hs[0])
                else:  # one host thread per shard: while one shard's physics steps, another's controller runs
                    pool = concurrent.futures.ThreadPoolExecutor(len(shards))
                    try:
                        futs = [pool.submit(run, sh, advance, h) for sh, h in zip(shards, hs)]
                        concurrent.futures.wait(futs, return_when=concurrent.futures.FIRST_EXCEPTION)
                        for f in sorted(futs, key=lambda f: not (f.done() and f.exception())):
                            f.result()  # the first failure first
                    except BaseException:  # an interrupt or a failed shard: the others stop at their next chunk
                        stop.set()
                        raise
                    finally:
                        pool.shutdown(wait=True)
                host_call.raise_pending(PHYSICS_TARGET)
                self.last_timing["simulate_s"] = time.perf_counter() - t_sim
        finally:
            self._compile_t0 = None
            for sh in shards:
                if sh.carry is not None:  # a call that failed on the host waits for the chunks it dispatched
                    with contextlib.suppress(Exception):
                        jax.block_until_ready(sh.carry)
                _ACTIVE.pop(sh.handle, None)
                sh.phys.close()
        notify("done", **self.last_timing)
        # The chunks of a trace, the shards and the padded rows joined or dropped in NumPy: slicing or joining JAX
        # arrays compiles a program per shape (0.7 s for the 25 fields of a step-down's trace, after the simulation).
        results = []
        for sh in shards:
            trace = None if self.record is None else jax.tree_util.tree_map(
                lambda *xs: np.concatenate([np.asarray(x) for x in xs], axis=1), *sh.traces)
            results.append((sim.rollout_result(sh.carry, trace), sh.hi - sh.lo))
        if len(results) == 1 and plan.size == n:
            return jax.device_put(results[0][0])
        return jax.device_put(jax.tree_util.tree_map(
            lambda *xs: np.concatenate([np.asarray(x)[:m] for x, (_, m) in zip(xs, results)]),
            *(r for r, _ in results)))
