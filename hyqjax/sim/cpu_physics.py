"""C MuJoCo's side of the C MuJoCo backend (:mod:`hyqjax.sim.cpu_backend`): a batch of simulations stepped in C on
a thread pool, and the one packed array its host call returns.

:class:`CPhysics` holds the batch in a ``mujoco.batch.Batch`` (MuJoCo's own batch of simulations: one state row per
instance in float64, each instance on its own ``MjModel``, stepped by ``mj_step`` in a C loop over the instances on
``threads`` threads with the GIL released, bit for bit what a loop over one ``MjData`` per instance gives); per
instance it returns one row of ``time, qpos, qvel``, ``sensordata``, ``site_xpos``, ``geom_xpos``, ``geom_xmat`` and
``qfrc_gen = qfrc_bias + M qacc`` (``M`` from the batch's sparse inertia), laid out by :func:`packed_layout`;
:func:`unpack` (pure JAX, static slices) makes the :class:`hyqjax.sim.observe.DataView` of such rows, what the
controllers and metrics read. No JAX program is built here: the backend's runner calls :meth:`CPhysics.step_padded`
from its host call (:mod:`hyqjax.sim.host_call`).
"""
from __future__ import annotations

import os

import jax
import mujoco
import mujoco.batch
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
    """``len(models)`` instances of C MuJoCo in float64 in one ``mujoco.batch.Batch``, each on its own model, stepped
    on ``threads`` threads (at most one per :data:`MIN_ROWS_PER_THREAD` instances), starting at ``qpos0`` with
    velocity ``qvel0`` (None: zero).

    ``step(tau, frozen)`` sets the controls (and the trunk push of each instance, as
    :func:`hyqjax.sim.rollout._physics` does), calls ``mj_step`` ``substeps`` times on every instance not
    ``frozen`` (one call into C for the whole batch), and returns the batch's :class:`hyqjax.sim.observe.DataView`
    packed in ONE array ``(B, width)`` of ``dtype`` (one output of the host call instead of eight: as ``io_callback``
    outputs each cost about 12 us a tick); :meth:`unpack` (pure JAX, static slices) makes the view of it. Per instance
    a row holds ``time, qpos, qvel``, ``sensordata``, ``site_xpos``, ``geom_xpos``, ``geom_xmat`` and
    ``qfrc_gen = qfrc_bias + M qacc``, the fields of the view in that order. As after ``mj_step``, the derived fields
    (all but the state) describe the state before the last substep; before the first step they are zero. An
    instance in which MuJoCo raises an error keeps its state and reads as NaN, so the runner counts it as diverged.
    """

    def __init__(self, models: list[mujoco.MjModel], qpos0: np.ndarray, trunk_body: int, substeps: int = 1,
                 push: Push | None = None, threads: int | None = None, dtype=np.float32,
                 qvel0: np.ndarray | None = None):
        models = list(models)
        b = len(models)
        m0 = models[0]
        self.b, self.substeps, self.trunk = b, int(substeps), int(trunk_body)
        self.dtype = np.dtype(dtype)
        self.threads = max(1, min(threads or default_threads(), b // MIN_ROWS_PER_THREAD))
        self.batch = mujoco.batch.Batch(m0, nsim=b, nthread=self.threads)
        self.batch.set_models(models)  # the batch keeps them alive
        self.batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        bind = self.batch.bind
        self._time, self._qpos, self._qvel, self._ctrl = bind("time"), bind("qpos"), bind("qvel"), bind("ctrl")
        self._qpos[...] = np.broadcast_to(np.asarray(qpos0, np.float64), (b, m0.nq))
        if qvel0 is not None:
            self._qvel[...] = np.broadcast_to(np.asarray(qvel0, np.float64), (b, m0.nv))
        self._derived = [bind(f) for f in ("sensordata", "site_xpos", "geom_xpos", "geom_xmat")]
        self._bias, self._qacc, self._inertia = bind("qfrc_bias"), bind("qacc"), bind("M")
        # M (the lower triangle of the joint-space inertia in MuJoCo's CSR layout) as a dense (nv, nv) gather from
        # its entries and a zero after them (the index of every entry outside the sparsity pattern).
        rows = np.repeat(np.arange(m0.nv), m0.M_rownnz)
        self._dense = np.full((m0.nv, m0.nv), len(rows), np.int64)
        self._inertia_ext = np.zeros((b, len(rows) + 1))
        self._dense[rows, m0.M_colind] = self._dense[m0.M_colind, rows] = np.arange(len(rows))
        self.layout = packed_layout(m0)
        self.width = max(hi for _, hi, _ in self.layout.values())
        self._failed = np.zeros(b, bool)
        self._push = None
        if push is not None:
            f, t0, dur = push_rows(push, b)
            has = (dur > 0) & np.any(f != 0, -1)
            if np.any(has):
                self._push = (f, t0, dur, has, bind("xfrc_applied"))

    def close(self) -> None:
        """Release the batch's thread pool."""
        self.batch = None

    def step(self, tau, frozen, out: np.ndarray | None = None) -> np.ndarray:
        """Step the instances not ``frozen`` ``(B,)`` with joint torques ``tau`` ``(B, nu)``; the packed view (written
        into ``out`` when given)."""
        frozen = np.asarray(frozen, bool) | self._failed
        self._ctrl[...] = tau
        if self._push is not None:
            f, t0, dur, has, xfrc = self._push
            on = (t0 <= self._time) & (self._time < t0 + dur)
            xfrc[has, self.trunk, :3] = np.where(on[has, None], f[has], 0.0)
        ids = None if not frozen.any() else np.flatnonzero(~frozen)
        if ids is None or len(ids):
            try:
                self.batch.step(ids, nstep=self.substeps)
            except mujoco.batch.SimulationError as e:  # those instances kept their state; they read as NaN
                self._failed[np.asarray(e.ids)] = True
        if out is None:
            out = np.empty((self.b, self.width), self.dtype)
        self.pack_into(out)
        return out

    def step_padded(self, tau_frozen: np.ndarray, out: np.ndarray) -> None:
        """The host call of a padded batch: ``tau_frozen`` ``(P, nu + 1)`` (torques, then 1 for a frozen instance)
        of ``P >= B`` rows, of which the first ``B`` are this batch's instances; steps those (:meth:`step`) and
        writes the packed view of all ``P`` rows into ``out``, the rows past ``B`` a copy of row ``B - 1`` (padded
        rows are never stepped)."""
        b = self.b
        tau_frozen = np.asarray(tau_frozen)
        self.step(tau_frozen[:b, :-1], tau_frozen[:b, -1] > 0.5, out=out[:b])
        out[b:] = out[b - 1]

    def packed(self) -> np.ndarray:
        """The batch's current view, packed ``(B, width)`` in ``dtype``."""
        out = np.empty((self.b, self.width), self.dtype)
        self.pack_into(out)
        return out

    def pack_into(self, out: np.ndarray) -> None:
        """:meth:`packed` written into ``out`` ``(B, width)``: ``qfrc_gen`` is ``M qacc`` and ``qfrc_bias``, each
        rounded to ``dtype``, added."""
        b, lay = self.b, self.layout
        lo, hi, _ = lay["state"]
        nq = self._qpos.shape[1]
        out[:, lo] = self._time
        out[:, lo + 1:lo + 1 + nq] = self._qpos
        out[:, lo + 1 + nq:hi] = self._qvel
        for name, field in zip(("sensordata", "site_xpos", "geom_xpos", "geom_xmat"), self._derived):
            out[:, lay[name][0]:lay[name][1]] = field.reshape(b, -1)
        lo, hi, _ = lay["qfrc_gen"]
        self._inertia_ext[:, :-1] = self._inertia
        m_qacc = np.einsum("bij,bj->bi", self._inertia_ext[:, self._dense], self._qacc)
        out[:, lo:hi] = m_qacc
        out[:, lo:hi] += self._bias.astype(out.dtype)
        if self._failed.any():
            out[self._failed] = np.nan

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
