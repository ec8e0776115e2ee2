"""The C MuJoCo backend (``impl="c"``): many simulations stepped in C on all CPU cores, the controller in JAX.

MJX compiled for a CPU spends most of its time in XLA's generic code for the physics (minutes of compile, a
few thousand env-steps per second for HyQ); C MuJoCo steps HyQ in about 20 us per instance and step with no
compile. This backend runs the closed loop as ONE jitted ``lax.scan`` over control ticks, in which

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
loads it instead of compiling. Per-instance terrain, friction and payload live in one
``mujoco.MjModel`` per instance (:func:`batch_models`), written by the same function that writes them into a
batched ``mjx.Model`` (:func:`hyqjax.sim.model.instance_model`), evaluated in float64. The midphase (bounding
volume hierarchy of the static terrain, computed when the model is compiled) is switched off so that a
platform moved per instance collides where it is; the broad and narrow phases are unchanged. MuJoCo's
automatic reset of an unstable instance is switched off as well: its non-finite state is counted as a
divergence instead of restarting the run silently. Warnings MuJoCo prints for such an instance go to the
``hyqjax.sim.cpu_backend`` logger (debug level) while a batch runs, not to ``MUJOCO_LOG.TXT``.

**Shards.** A batch runs as contiguous shards, one per CPU core (:meth:`CBatchRunner.shard_bounds`; at least
:data:`MIN_SHARD_ROWS` rows each, so a small batch runs as one), each with its own batch of simulations stepped on
one thread and its own copy of the compiled chunk program, executed at once from one host thread per shard. A tick
of one shard is its controller (compiled JAX) and then its physics (C MuJoCo); with one shard the two run one after
the other, the core that is not stepping physics waiting for the controller. With two, one shard's controller runs
while the other's physics steps (JAX and MuJoCo both release the GIL). Every shard is padded to the bucket of the
largest, so all run one compiled program. Each instance's computation is the same whatever the sharding, and so are its
results, bit for bit (tested).

Forward only: a derivative through this backend is a ``ValueError`` naming ``impl`` (gradients need
``impl="jax"``), and there is no one-instance rollout outside a batch.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import functools
import logging
import threading
import time
import types
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hyqjax.core import robot
from hyqjax.core.types import Controller, Metrics, Push
from hyqjax.sim import host_call
from hyqjax.sim import impls as _impls
from hyqjax.sim import model as hmodel
from hyqjax.sim import observe as hobs
from hyqjax.sim import runner as hrunner
from hyqjax.sim.compile_phase import AheadOfTime, notify
from hyqjax.sim.cpu_physics import CPhysics, default_threads, push_rows, unpack

log = logging.getLogger(__name__)

#: XLA options of the programs this backend compiles (the controller and metrics, on the CPU): XLA:CPU's
#: elemental emitters instead of its fusion emitters compile the crawl's closed loop in about half the time
#: (5 instead of 9.5 s of CPU for 18 instances) and run its ticks as fast (benchmarks/bench_cpu_backend.py); the
#: controller's small matrix products in Eigen's single-threaded kernels (each shard is one thread already) take
#: 12-15% off a tick of the controller, bitwise the same (benchmarks/RESULTS.md).
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_multi_thread_eigen": False}


@functools.lru_cache(maxsize=None)
def host_sharding():
    """The host CPU device as a sharding: the controller and metrics of this backend run there (its physics is a
    host call registered for the CPU), also in a process whose default device is a GPU."""
    return jax.sharding.SingleDeviceSharding(jax.devices("cpu")[0])


def host_jit(fn, **kw):
    """``jax.jit`` of ``fn`` on the host CPU (:func:`host_sharding`) with :func:`compiler_options`."""
    return jax.jit(fn, in_shardings=host_sharding(), out_shardings=host_sharding(),
                   compiler_options=compiler_options(), **kw)


@functools.lru_cache(maxsize=None)
def compiler_options() -> dict:
    """The entries of :data:`COMPILER_OPTIONS` that this process's XLA knows: each tried once on a one-op program
    (the XLA of jax 0.11 has no ``xla_cpu_use_fusion_emitters`` and refuses a program that names it)."""
    known = {}
    for k, v in COMPILER_OPTIONS.items():
        try:
            jax.jit(lambda x: x + 1, compiler_options={k: v}).lower(jax.ShapeDtypeStruct((), np.float32, sharding=host_sharding())).compile()
        except Exception:  # noqa: BLE001 - XLA's error for an unknown option is a JaxRuntimeError or a ValueError
            continue
        known[k] = v
    return known

#: The fewest rows a shard of a batch has (a smaller batch runs as fewer shards, down to one).
MIN_SHARD_ROWS = 8

_MODEL_FIELDS = ("geom_pos", "geom_friction", "body_mass", "body_ipos", "body_inertia")


def prepare_model(m: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of ``m`` for per-instance edits: midphase and automatic reset off (module docstring)."""
    mc = copy.copy(m)
    mc.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_MIDPHASE) | int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
    return mc


def batch_models(m: mujoco.MjModel, ids: hmodel.ModelIds, terrain: hmodel.InstanceTerrain) -> list[mujoco.MjModel]:
    """One ``MjModel`` per instance of ``terrain``: ``m`` with the fields :func:`hyqjax.sim.model.instance_model`
    writes (platform and block heights, terrain friction, payload mass, centre and inertia), in float64."""
    base = prepare_model(m)
    with jax.enable_x64(True):
        fields = _instance_fields(ids, {f: np.asarray(getattr(base, f), np.float64) for f in _MODEL_FIELDS},
                                  jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), terrain))
        fields = {k: np.asarray(v, np.float64) for k, v in fields.items()}
    models = []
    for i in range(terrain.batch_size):
        mi = copy.copy(base)
        for f in _MODEL_FIELDS:
            getattr(mi, f)[...] = fields[f][i]
        models.append(mi)
    return models


def _instance_fields(ids: hmodel.ModelIds, model_fields: dict, terrain: hmodel.InstanceTerrain) -> dict:
    """:func:`_instance_fields_fn` compiled once with :func:`compiler_options`."""
    return _instance_fields_jit()(ids, model_fields, terrain)


@functools.lru_cache(maxsize=None)
def _instance_fields_jit():
    return host_jit(_instance_fields_fn, static_argnums=0)


def _instance_fields_fn(ids: hmodel.ModelIds, model_fields: dict, terrain: hmodel.InstanceTerrain) -> dict:
    """:func:`hyqjax.sim.model.instance_model`'s fields of every instance (one compiled program, not one per op)."""
    return jax.vmap(lambda t: hmodel._instance_fields(types.SimpleNamespace(**model_fields), ids, t))(terrain)


@contextlib.contextmanager
def _warnings_to_log():
    """MuJoCo's warnings (an unstable instance) go to this module's logger while a batch runs."""
    prev = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda msg: log.debug("MuJoCo: %s", msg))
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(prev)


class CInitialData(NamedTuple):
    """Initial state of a C MuJoCo batch at time 0: ``qpos`` ``(B, nq)`` and ``qvel`` ``(B, nv)`` in float64 (None:
    zero velocity, what :func:`hyqjax.sim.rollout.initial_data` makes for MJX)."""

    qpos: np.ndarray
    qvel: np.ndarray | None = None


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
    :func:`batch_models` and ``d0`` a :class:`CInitialData`; returns a :class:`hyqjax.sim.rollout.RolloutResult`
    whose ``data`` is the final :class:`hyqjax.sim.observe.DataView`. With ``buckets`` (the default) the controller
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


class CBackend:
    """C MuJoCo (``impl="c"``) behind the interface of :func:`hyqjax.sim.backend.get`
    (:class:`hyqjax.sim.mjx_backend.MJXBackend` documents it). Its "model" is the ``mujoco.MjModel`` itself, its
    batch a list of per-instance models, its initial data a :class:`CInitialData`, its runner a
    :class:`CBatchRunner` (which ignores a device mesh: the physics runs on the host's cores)."""

    name = "c"
    supports_gradients = False
    #: The physics runs on the host's cores, sharded over threads, not over JAX devices.
    uses_jax_devices = False
    one_instance_error = "C MuJoCo steps whole batches outside JAX"

    def __repr__(self) -> str:
        return "CBackend()"

    def put_model(self, m: mujoco.MjModel) -> mujoco.MjModel:
        return m

    def batch_model(self, model: mujoco.MjModel, ids: hmodel.ModelIds, terrain: hmodel.InstanceTerrain):
        return batch_models(model, ids, terrain)

    def initial_data(self, model, batched_model, qpos, m) -> CInitialData:
        return CInitialData(np.asarray(qpos, np.float64))

    def from_jax_data(self, models, d, m) -> CInitialData:
        """The state (``qpos``, ``qvel``) of batched MJX-JAX data ``d`` as a batch's initial data."""
        return CInitialData(np.asarray(d.qpos, np.float64), np.asarray(d.qvel, np.float64))

    def make_runner(self, ids, controller, cfg, metrics=None, record=None, params_axes: Any = 0, mesh=None,
                    buckets: bool = True):
        """The C batch runner (``mesh`` is ignored: one thread pool); ``buckets``: pad the controller batch to
        :func:`hyqjax.sim.runner.host_physics_plan`'s bucket (False: every batch at its own size)."""
        return CBatchRunner(ids, controller, cfg, metrics, record, params_axes, buckets=buckets)

    def forbid_derivatives(self, tree):
        return _impls.forbid_derivatives(tree, self.name)
