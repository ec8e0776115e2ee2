"""C MuJoCo's side of the C MuJoCo backend (:mod:`hyqjax.sim.cpu_backend`): a batch of ``MjData`` stepped on a
thread pool, and the one packed array its host call returns.

:class:`CPhysics` holds one ``mujoco.MjData`` per instance in float64 and steps the instances with
``mujoco.mj_step`` on :func:`default_threads` threads (MuJoCo releases the GIL while it steps); per instance it
returns one row of ``time, qpos, qvel`` (``mj_getState``), ``sensordata``, ``site_xpos``, ``geom_xpos``,
``geom_xmat`` and ``qfrc_gen = qfrc_bias + M qacc`` (``mj_mulM``), laid out by :func:`packed_layout`;
:func:`unpack` (pure JAX, static slices) makes the :class:`hyqjax.sim.observe.DataView` of such rows, what the
controllers and metrics read. No JAX program is built here: the backend's runner calls :meth:`CPhysics.step_padded`
from its host call (:mod:`hyqjax.sim.host_call`).
"""
from __future__ import annotations

import concurrent.futures
import os

import jax
import mujoco
import numpy as np

from hyqjax.core.types import Push
from hyqjax.sim import observe as hobs


def default_threads() -> int:
    """Threads that step the batch: the CPU cores this process may run on."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


#: The fewest instances a stepping thread gets: below about 16 instances handing half of them to a second thread
#: costs more than it gains (6 instances: 0.24 ms a step on two threads, 0.17 ms on one; 9: 0.56 against 0.21;
#: 24: 0.46 against 0.77; benchmarks/RESULTS.md).
MIN_ROWS_PER_THREAD = 8


class CPhysics:
    """``len(models)`` instances of C MuJoCo in float64, one ``MjData`` each, stepped on ``threads`` threads (at most
    one per :data:`MIN_ROWS_PER_THREAD` instances).

    ``step(tau, frozen)`` sets the controls (and the trunk push of each instance, as
    :func:`hyqjax.sim.rollout._physics` does), calls ``mj_step`` ``substeps`` times on every instance not
    ``frozen``, and returns the batch's :class:`hyqjax.sim.observe.DataView` packed in ONE array ``(B, width)`` of
    ``dtype`` (one output of the host call instead of eight: as ``io_callback`` outputs each cost about 12 us a
    tick); :meth:`unpack` (pure JAX, static slices) makes the view of it. Per instance a row holds ``time, qpos, qvel`` (``mj_getState``),
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
        self.threads = max(1, min(threads or default_threads(), b // MIN_ROWS_PER_THREAD))
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
            f, t0, dur = push_rows(push, b)
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

    def step(self, tau, frozen, out: np.ndarray | None = None) -> np.ndarray:
        """Step the instances not ``frozen`` ``(B,)`` with joint torques ``tau`` ``(B, nu)``; the packed view (written
        into ``out`` when given)."""
        tau = np.asarray(tau, np.float64)
        frozen = np.asarray(frozen, bool)
        if self._pool is None or len(self._slices) == 1:
            self._run(0, self.b, tau, frozen)
        else:
            futs = [self._pool.submit(self._run, lo, hi, tau, frozen) for lo, hi in self._slices[1:]]
            self._run(*self._slices[0], tau, frozen)
            for f in futs:
                f.result()
        if out is None:
            return self.packed()
        self.pack_into(out)
        return out

    def packed(self) -> np.ndarray:
        """The batch's current view, packed ``(B, width)`` in ``dtype`` (``qfrc_gen`` with the bias forces added)."""
        out = np.empty((self.b, self.width), self.dtype)
        self.pack_into(out)
        return out

    def pack_into(self, out: np.ndarray) -> None:
        """:meth:`packed` written into ``out`` ``(B, width)``."""
        out[...] = self._buf
        lo, hi = self._cols["qfrc_gen"]
        out[:, lo:hi] += self._bias.astype(out.dtype)

    def step_padded(self, tau_frozen: np.ndarray, out: np.ndarray) -> None:
        """The host call of a padded batch: ``tau_frozen`` ``(P, nu + 1)`` (torques, then 1 for a frozen instance)
        of ``P >= B`` rows, of which the first ``B`` are this batch's instances; steps those (:meth:`step`) and
        writes the packed view of all ``P`` rows into ``out``, the rows past ``B`` a copy of row ``B - 1`` (padded
        rows are never stepped)."""
        b = self.b
        tau_frozen = np.asarray(tau_frozen)
        self.step(tau_frozen[:b, :-1], tau_frozen[:b, -1] > 0.5, out=out[:b])
        out[b:] = out[b - 1]

    def unpack(self, flat: jax.Array) -> hobs.DataView:
        """The :class:`hyqjax.sim.observe.DataView` of a packed batch ``(B, width)`` (JAX or NumPy)."""
        return unpack(self.layout, flat)


def push_rows(push: Push | None, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``push`` as per-instance NumPy rows ``(n, 3), (n,), (n,)`` (None without one)."""
    if push is None:
        return None
    return (np.broadcast_to(np.asarray(push.force, np.float64).reshape(-1, 3), (n, 3)),
            np.broadcast_to(np.asarray(push.t_start, np.float64).reshape(-1), (n,)),
            np.broadcast_to(np.asarray(push.duration, np.float64).reshape(-1), (n,)))


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
