"""The C MuJoCo backend (``impl="c"``): many ``MjData`` stepped in C on all CPU cores, the controller in JAX.

MJX compiled for a CPU spends most of its time in XLA's generic code for the physics (minutes of compile, a
few thousand env-steps per second for HyQ); C MuJoCo steps HyQ in about 20 us per instance and step with no
compile. This backend runs the closed loop as ONE jitted ``lax.scan`` over control ticks, in which

1. the controller (``jax.vmap`` over instances of ``controller.step``) computes the joint torques of the whole
   batch from the :class:`hyqjax.core.types.Observation` of every instance (:func:`hyqjax.sim.observe.observation`,
   the same definition as under MJX);
2. a host callback (``jax.experimental.io_callback``, ordered) hands the torques to :class:`CPhysics`, which
   holds one ``mujoco.MjData`` per instance in float64 and steps them with ``mujoco.mj_step`` on a thread pool
   (MuJoCo releases the GIL while it steps), and returns the data the metrics read as a
   :class:`hyqjax.sim.observe.DataView` (float32 unless ``jax_enable_x64``);
3. divergence, metrics and traces follow the rules of :func:`hyqjax.sim.rollout.rollout_advance`: an instance
   whose state is non-finite or faster than ``SimConfig.max_speed`` is frozen at its last finite tick (its
   ``MjData`` is no longer stepped), its controller state and metrics stop, and ``diverged_tick`` records when.

The controller and metrics are compiled once per batch shape and chunk length (seconds, not the minutes of an
MJX compile); the physics is never compiled. Per-instance terrain, friction and payload live in one
``mujoco.MjModel`` per instance (:func:`batch_models`), written by the same function that writes them into a
batched ``mjx.Model`` (:func:`hyqjax.sim.model.instance_model`), evaluated in float64. The midphase (bounding
volume hierarchy of the static terrain, computed when the model is compiled) is switched off so that a
platform moved per instance collides where it is; the broad and narrow phases are unchanged. MuJoCo's
automatic reset of an unstable instance is switched off as well: its non-finite state is counted as a
divergence instead of restarting the run silently. Warnings MuJoCo prints for such an instance go to the
``hyqjax.sim.cpu_backend`` logger (debug level) while a batch runs, not to ``MUJOCO_LOG.TXT``.

Forward only: a derivative through this backend is a ``ValueError`` naming ``impl`` (gradients need
``impl="jax"``), and there is no one-instance rollout outside a batch.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import copy
import functools
import logging
import os
import time
import types
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.experimental import io_callback

from hyqjax.core import robot
from hyqjax.core.types import Controller, Metrics, Push
from hyqjax.sim import impls as _impls
from hyqjax.sim import model as hmodel
from hyqjax.sim import observe as hobs

log = logging.getLogger(__name__)

#: XLA options of the programs this backend compiles (the controller and metrics, on the CPU): XLA:CPU's
#: elemental emitters instead of its fusion emitters compile the crawl's closed loop in about half the time
#: (5 instead of 9.5 s of CPU for 18 instances) and run its ticks as fast (benchmarks/bench_cpu_backend.py).
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

_MODEL_FIELDS = ("geom_pos", "geom_friction", "body_mass", "body_ipos", "body_inertia")


def default_threads() -> int:
    """Threads that step the batch: the CPU cores this process may run on."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


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


@functools.partial(jax.jit, static_argnums=0, compiler_options=COMPILER_OPTIONS)
def _instance_fields(ids: hmodel.ModelIds, model_fields: dict, terrain: hmodel.InstanceTerrain) -> dict:
    """:func:`hyqjax.sim.model.instance_model`'s fields of every instance (one compiled program, not one per op)."""
    return jax.vmap(lambda t: hmodel._instance_fields(types.SimpleNamespace(**model_fields), ids, t))(terrain)


class CPhysics:
    """``len(models)`` instances of C MuJoCo in float64, one ``MjData`` each, stepped on ``threads`` threads.

    ``step(tau, frozen)`` sets the controls (and the trunk push of each instance, as
    :func:`hyqjax.sim.rollout._physics` does), calls ``mj_step`` ``substeps`` times on every instance not
    ``frozen``, and returns the batch's :class:`hyqjax.sim.observe.DataView` packed in ONE array ``(B, width)`` of
    ``dtype`` (one host-callback output instead of eight: each costs about 12 us a tick); :meth:`unpack` (pure JAX,
    static slices) makes the view of it. Per instance a row holds ``time, qpos, qvel`` (``mj_getState``),
    ``sensordata``, ``site_xpos``, ``geom_xpos``, ``geom_xmat`` and ``qfrc_gen = qfrc_bias + M qacc``
    (``mj_mulM``), the fields of the view in that order.
    """

    def __init__(self, models: list[mujoco.MjModel], qpos0: np.ndarray, trunk_body: int, substeps: int = 1,
                 push: Push | None = None, threads: int | None = None, dtype=np.float32):
        self.models = list(models)
        b = len(self.models)
        m0 = self.models[0]
        qpos0 = np.broadcast_to(np.asarray(qpos0, np.float64), (b, m0.nq))
        self.datas = [mujoco.MjData(mi) for mi in self.models]
        for d, q in zip(self.datas, qpos0):
            d.qpos[:] = q
        self.b, self.substeps, self.trunk = b, int(substeps), int(trunk_body)
        self.dtype = np.dtype(dtype)
        self.threads = max(1, min(threads or default_threads(), b))
        self._pool = concurrent.futures.ThreadPoolExecutor(self.threads - 1) if self.threads > 1 else None
        bounds = np.linspace(0, b, self.threads + 1).round().astype(int)
        self._slices = [(int(lo), int(hi)) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]
        self.layout = packed_layout(m0)
        self.width = max(hi for _, hi, _ in self.layout.values())
        self._buf = np.zeros((b, self.width))
        self._bias = np.zeros((b, m0.nv))
        lay = self.layout
        st = mujoco.mjtState
        self._state_spec = int(st.mjSTATE_TIME | st.mjSTATE_QPOS | st.mjSTATE_QVEL)
        for i, d in enumerate(self.datas):
            mujoco.mj_getState(self.models[i], d, self._buf[i, slice(*lay["state"][:2])], self._state_spec)
        self._cols = {k: (lo, hi) for k, (lo, hi, _) in lay.items()}
        self._views = [(d.sensordata, d.site_xpos.reshape(-1), d.geom_xpos.reshape(-1), d.geom_xmat.reshape(-1),
                        d.qfrc_bias, d.qacc, d.ctrl, d.xfrc_applied) for d in self.datas]
        self._push = None
        if push is not None:
            f = np.asarray(push.force, np.float64).reshape(b, 3)
            t0 = np.asarray(push.t_start, np.float64).reshape(b)
            dur = np.asarray(push.duration, np.float64).reshape(b)
            has = (dur > 0) & np.any(f != 0, -1)
            if np.any(has):
                self._push = (f, t0, dur, has)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def _run(self, lo: int, hi: int, tau: np.ndarray, frozen: np.ndarray) -> None:
        buf, bias_out, views, push = self._buf, self._bias, self._views, self._push
        c = self._cols
        st, sen, sit, gpo, gma, gen = (slice(*c["state"]), slice(*c["sensordata"]), slice(*c["site_xpos"]),
                                       slice(*c["geom_xpos"]), slice(*c["geom_xmat"]), slice(*c["qfrc_gen"]))
        step, mul_m, get_state, spec = mujoco.mj_step, mujoco.mj_mulM, mujoco.mj_getState, self._state_spec
        for i in range(lo, hi):
            if frozen[i]:
                continue
            m, d = self.models[i], self.datas[i]
            sens, site, gpos, gmat, bias, qacc, ctrl, xfrc = views[i]
            ctrl[:] = tau[i]
            if push is not None and push[3][i]:
                f, t0, dur, _ = push
                on = t0[i] <= d.time < t0[i] + dur[i]
                xfrc[self.trunk, :3] = f[i] if on else 0.0
            for _ in range(self.substeps):
                step(m, d)
            row = buf[i]
            get_state(m, d, row[st], spec)
            row[sen] = sens
            row[sit] = site
            row[gpo] = gpos
            row[gma] = gmat
            bias_out[i] = bias
            mul_m(m, d, row[gen], qacc)

    def step(self, tau, frozen) -> np.ndarray:
        """Step the instances not ``frozen`` ``(B,)`` with joint torques ``tau`` ``(B, nu)``; the packed view."""
        tau = np.asarray(tau, np.float64)
        frozen = np.asarray(frozen, bool)
        if self._pool is None or len(self._slices) == 1:
            self._run(0, self.b, tau, frozen)
        else:
            futs = [self._pool.submit(self._run, lo, hi, tau, frozen) for lo, hi in self._slices[1:]]
            self._run(*self._slices[0], tau, frozen)
            for f in futs:
                f.result()
        return self.packed()

    def packed(self) -> np.ndarray:
        """The batch's current view, packed ``(B, width)`` in ``dtype`` (``qfrc_gen`` with the bias forces added)."""
        out = self._buf.astype(self.dtype)
        lo, hi = self._cols["qfrc_gen"]
        out[:, lo:hi] += self._bias.astype(self.dtype)
        return out

    def unpack(self, flat: jax.Array) -> hobs.DataView:
        """The :class:`hyqjax.sim.observe.DataView` of a packed batch ``(B, width)`` (JAX or NumPy)."""
        return unpack(self.layout, flat)


def packed_layout(m: mujoco.MjModel) -> dict[str, tuple[int, int, tuple[int, ...]]]:
    """Columns ``(start, stop, shape per instance)`` of each field in :class:`CPhysics`'s packed rows; ``state``
    is ``time, qpos, qvel``."""
    layout, at = {}, 0
    for name, shape in (("state", (1 + m.nq + m.nv,)), ("sensordata", (m.nsensordata,)), ("site_xpos", (m.nsite, 3)),
                        ("geom_xpos", (m.ngeom, 3)), ("geom_xmat", (m.ngeom, 3, 3)), ("qfrc_gen", (m.nv,))):
        n = int(np.prod(shape))
        layout[name] = (at, at + n, shape)
        at += n
    return layout


def unpack(layout: dict, flat) -> hobs.DataView:
    """:class:`hyqjax.sim.observe.DataView` of packed rows ``flat`` ``(B, width)`` laid out as ``layout``."""
    b = flat.shape[0]
    f = {k: flat[:, lo:hi].reshape((b,) + shape) for k, (lo, hi, shape) in layout.items()}
    nq = (layout["state"][1] - layout["state"][0] - 1 - layout["qfrc_gen"][2][0])
    st = f.pop("state")
    return hobs.DataView(time=st[:, 0], qpos=st[:, 1:1 + nq], qvel=st[:, 1 + nq:], **f)


@contextlib.contextmanager
def _warnings_to_log():
    """MuJoCo's warnings (an unstable instance) go to this module's logger while a batch runs."""
    prev = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(lambda msg: log.debug("MuJoCo: %s", msg))
    try:
        yield
    finally:
        mujoco.set_mju_user_warning(prev)


class CInitialData:
    """Initial state of a C MuJoCo batch: ``qpos`` ``(B, nq)`` in float64, zero velocity, time 0 (what
    :func:`hyqjax.sim.rollout.initial_data` makes for MJX)."""

    def __init__(self, qpos: np.ndarray):
        self.qpos = np.asarray(qpos, np.float64)

    @property
    def batch_size(self) -> int:
        return int(self.qpos.shape[0])


class CBatchRunner:
    """The closed loop of a batch on C MuJoCo (module docstring); the counterpart of
    :class:`hyqjax.sim.runner.BatchRunner` with the same call and result.

    ``runner(models, d0, params, push, progress=..., chunk_seconds=...)`` with ``models`` from
    :func:`batch_models` and ``d0`` a :class:`CInitialData`; returns a :class:`hyqjax.sim.rollout.RolloutResult`
    whose ``data`` is the final :class:`hyqjax.sim.observe.DataView`. The controller and metrics are jitted once
    per batch shape and chunk length and reused by later calls.
    """

    def __init__(self, ids: hmodel.ModelIds, controller: Controller, cfg, metrics: Metrics | None = None,
                 record=None, params_axes: Any = 0, threads: int | None = None):
        from hyqjax.sim import rollout as sim

        self.ids, self.controller, self.cfg = ids, controller, cfg
        self.metrics = metrics if metrics is not None else sim.no_metrics()
        self.record = record if cfg.record_every else None
        self.params_axes, self.threads = params_axes, threads
        self.n_compiles = 0
        self._phys: CPhysics | None = None
        self._init = jax.jit(self._init_fn, compiler_options=COMPILER_OPTIONS)
        self._advance = jax.jit(self._advance_fn, static_argnums=2, compiler_options=COMPILER_OPTIONS)
        self._executables: dict = {}
        self._compile_t0: float | None = None
        self.last_timing: dict = {}

    def _executable(self, name: str, fn, args: tuple, static: tuple = ()):
        """The compiled ``fn`` for the shapes of ``args``, compiled ahead of time on first use; the compile phase is
        announced to :func:`hyqjax.sim.runner.compile_listener` and timed apart from the simulation, as
        :class:`hyqjax.sim.runner.BatchRunner` does."""
        from hyqjax.sim import runner

        key = (name, static, runner._signature(args))
        exe = self._executables.get(key)
        if exe is None:
            if self._compile_t0 is None:
                self._compile_t0 = time.perf_counter()
                runner._notify("start", batch=None)
            t0 = time.perf_counter()
            lowered = fn.lower(*args, *static)
            self.last_timing["trace_s"] += time.perf_counter() - t0
            exe = self._executables[key] = lowered.compile()
        return exe

    def _end_compile_phase(self, batch: int) -> None:
        from hyqjax.sim import runner

        if self._compile_t0 is not None:
            dt = time.perf_counter() - self._compile_t0
            self._compile_t0 = None
            self.last_timing["compile_s"] += dt
            runner._notify("end", batch=batch, seconds=dt)

    def chunk_ticks(self, chunk_seconds: float | None) -> int:
        """Ticks per chunk (:meth:`hyqjax.sim.runner.BatchRunner.chunk_ticks`)."""
        from hyqjax.sim import runner

        return runner.BatchRunner.chunk_ticks(self, chunk_seconds)

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

    def _physics_callback(self, tau_frozen):
        tau_frozen = np.asarray(tau_frozen)
        return self._phys.step(tau_frozen[:, :-1], tau_frozen[:, -1] > 0.5)

    def _advance_fn(self, carry, params, n_ticks: int):
        from hyqjax.sim import rollout as sim

        self.n_compiles += 1
        ids, ctrl, cfg, met, rec = self.ids, self.controller, self.cfg, self.metrics, self.record
        layout = self._phys.layout
        packed = jax.ShapeDtypeStruct((carry.data.qpos.shape[0], self._phys.width), carry.data.qpos.dtype)

        def control(v, cs, tau_prev, p):
            obs = hobs.observe_view(ids, v, tau_prev)
            cs_new, tau, info = ctrl.step(p, cs, obs)
            return obs, cs_new, jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT), info

        def settle(v, v_new, cs, cs_new, ms, obs, info, tau, tau_prev, div, div_tick, k, term, term_tick):
            # The divergence rule and the episode end of hyqjax.sim.rollout.rollout_advance, per instance.
            ok = sim._finite_tree((v_new.qpos, v_new.qvel, tau)) & (jnp.max(jnp.abs(v_new.qvel)) < cfg.max_speed)
            newly = (~div) & (~term) & (~ok)
            div = div | newly
            frozen = div | term
            keep = lambda new, old: jax.tree_util.tree_map(lambda a, b: jnp.where(frozen, b, a), new, old)  # noqa: E731
            v_new = keep(v_new, v)
            cs_new = keep(cs_new, cs)
            tau = jnp.where(frozen, tau_prev, tau)
            ms_new = keep(met.update(ms, v_new, obs, info), ms)
            div_tick = jnp.where(newly, k, div_tick)
            if met.terminal is not None:  # static: the episode ends at the failure tick
                ended = (~frozen) & jnp.asarray(met.terminal(ms_new), bool)
                term = term | ended
                term_tick = jnp.where(ended, k, term_tick)
            out = rec(v_new, obs, info) if rec is not None else None
            return v_new, cs_new, ms_new, tau, div, div_tick, term, term_tick, out

        def tick(c, _):
            v, cs, ms, tau_prev, div, div_tick, k, term, term_tick = c
            obs, cs_new, tau, info = jax.vmap(control, in_axes=(0, 0, 0, self.params_axes))(v, cs, tau_prev, params)
            frozen = (div | term)[:, None].astype(tau.dtype)  # a frozen instance is not stepped
            args = jnp.concatenate([tau, frozen], axis=1)  # one input array: (B, nu + 1)
            v_new = unpack(layout, io_callback(self._physics_callback, packed, args, ordered=True))
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
    def __call__(self, models: list[mujoco.MjModel], d0: CInitialData, params: Any, push: Push | None = None, *,
                 progress=None, chunk_seconds: float | None = None):
        from hyqjax.sim import rollout as sim

        if progress is not None and chunk_seconds is None:
            chunk_seconds = 1.0
        k = self.chunk_ticks(chunk_seconds)
        dtype = np.dtype(jnp.result_type(float))
        phys = CPhysics(models, d0.qpos, self.ids.trunk_body, self.cfg.substeps, push, self.threads, dtype)
        self._phys = phys
        n, dt, traces = self.cfg.n_ticks, self.cfg.control_dt, []
        n_inst = len(models)
        self._compile_t0 = None
        self.last_timing = dict(compile_s=0.0, trace_s=0.0, simulate_s=0.0, batch=n_inst, passes=1, instances=n_inst)
        try:
            with _warnings_to_log():
                view0 = phys.unpack(jnp.asarray(phys.packed()))
                init = self._executable("init", self._init, (view0, params))
                carry = init(view0, params)
                advance = self._executable("advance", self._advance, (carry, params), (k,))
                self._end_compile_phase(n_inst)
                t_sim = time.perf_counter()
                for done in range(0, n, k):
                    carry, tr = advance(carry, params)
                    traces.append(tr)
                    if progress is not None:
                        jax.block_until_ready(carry.tick)
                        progress((done + k) * dt, n * dt)
                jax.block_until_ready(carry)
                self.last_timing["simulate_s"] = time.perf_counter() - t_sim
        finally:
            self._compile_t0 = None
            phys.close()
            self._phys = None
        from hyqjax.sim import runner

        runner._notify("done", **self.last_timing)
        trace = None
        if self.record is not None:
            trace = traces[0] if len(traces) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *traces)
        return sim.rollout_result(carry, trace)


class CBackend:
    """C MuJoCo (``impl="c"``) behind the interface of :func:`hyqjax.sim.backend.get`
    (:class:`hyqjax.sim.mjx_backend.MJXBackend` documents it). Its "model" is the ``mujoco.MjModel`` itself, its
    batch a list of per-instance models, its initial data a :class:`CInitialData`, its runner a
    :class:`CBatchRunner` (which ignores a device mesh: the physics runs on the host's cores)."""

    name = "c"
    supports_gradients = False
    one_instance_error = "C MuJoCo steps whole batches outside JAX"

    def __repr__(self) -> str:
        return "CBackend()"

    def put_model(self, m: mujoco.MjModel) -> mujoco.MjModel:
        return m

    def batch_model(self, model: mujoco.MjModel, ids: hmodel.ModelIds, terrain: hmodel.InstanceTerrain):
        return batch_models(model, ids, terrain)

    def initial_data(self, model, batched_model, qpos, m) -> CInitialData:
        return CInitialData(np.asarray(qpos, np.float64))

    def make_runner(self, ids, controller, cfg, metrics=None, record=None, params_axes: Any = 0, mesh=None,
                    buckets: bool = True):
        """The C batch runner; ``mesh`` and ``buckets`` are MJX's (one thread pool, every batch at its own size)."""
        return CBatchRunner(ids, controller, cfg, metrics, record, params_axes)

    def forbid_derivatives(self, tree):
        return _impls.forbid_derivatives(tree, self.name)
