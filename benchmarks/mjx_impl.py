"""MJX model and batched data for ``impl`` "jax" or "warp", as the benchmarks build them.

Three things differ under MuJoCo Warp (measured in ``probe_warp.py``, see ``docs/warp.md``):

* ``mjx.make_data`` for warp takes the ``mujoco.MjModel`` and the contact / constraint capacities:
  ``naconmax`` contacts in total over the batch (one buffer shared by all instances) and ``njmax``
  constraint rows per instance. It is ``vmap``-ed over the batch so those buffers stay unbatched.
* Geoms welded to the world (floor, platform, blocks) are static in mujoco_warp: their ``geom_xpos`` is
  computed once in ``make_data`` and never from ``Model.geom_pos`` again, so the per-instance terrain of
  ``hyqjax.sim.model.batch_model`` only takes effect once it is written into the data's ``geom_xpos``.
* mujoco_warp prints one line per instance and step when the solver uses all its iterations (routine
  with Newton 4 / 8); that warning is switched off, the overflow warnings are kept.

The library does all three (``hyqjax.sim.impls.put_model``, ``hyqjax.sim.rollout.initial_data``); this
module adapts them to the benchmarks' (model, batched model, qpos, impl) calls.
"""
from __future__ import annotations

import mujoco
import numpy as np
from mujoco import mjx

from hyqjax.sim import backend
from hyqjax.sim import impls
from hyqjax.sim import rollout as sim

IMPLS = ("jax", "warp")
#: mujoco_warp's OverflowType bits. ITERATIONS and LS_ITERATIONS only say that the solver used all its
#: iterations; the others mean that a buffer was too small and contacts or constraints were dropped.
OVERFLOW_BITS = dict(NEFC=1 << 0, NJMAX_NNZ=1 << 1, BROADPHASE=1 << 2, NARROWPHASE=1 << 3, CCD=1 << 4,
                     HFIELD=1 << 5, CONTACT_MATCH=1 << 6, NVMAX=1 << 7, EPA_HORIZON=1 << 8, ITERATIONS=1 << 9,
                     LS_ITERATIONS=1 << 10, TACTILE=1 << 11)


def warp_available() -> bool:
    return backend.warp_installed()


def put_model(m: mujoco.MjModel, impl: str) -> mjx.Model:
    """``mjx.put_model(m, impl=impl)``; under warp without the iteration-limit printout
    (``hyqjax.sim.impls.put_model``)."""
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    return impls.put_model(m, impl)


def static_geoms(m: mujoco.MjModel) -> np.ndarray:
    """Ids of the geoms welded to the world body (their pose lives in the data under warp)."""
    return np.array([g for g in range(m.ngeom) if m.body_weldid[m.geom_bodyid[g]] == 0], dtype=int)


def batch_data(m: mujoco.MjModel, mx_batched: mjx.Model, qpos: np.ndarray, impl: str) -> mjx.Data:
    """Batched initial data at ``qpos`` (B, nq), zero velocity, on the per-instance terrain of ``mx_batched``
    (``hyqjax.sim.rollout.initial_data``: under warp made from ``m`` in a ``vmap``, with
    ``impls.CONTACTS_PER_INSTANCE`` contacts per instance and the terrain poses written into ``geom_xpos``)."""
    qpos = np.asarray(qpos)
    if impl == "warp":
        return sim.initial_data(mx_batched, qpos, qpos.shape[0], m=m)
    return sim.initial_data(put_model(m, "jax"), qpos, qpos.shape[0])


def overflow_count(d: mjx.Data) -> int:
    """Instances whose contact or constraint buffers overflowed (0 under impl jax, which has none)."""
    flag = getattr(getattr(d, "_impl", None), "overflow", None)
    if flag is None:
        return 0
    return int(np.sum((np.asarray(flag).reshape(-1) & impls.BUFFER_OVERFLOW_MASK) != 0))
