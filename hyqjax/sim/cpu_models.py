"""The per-instance models and initial data of the C MuJoCo backend (:mod:`hyqjax.sim.cpu_backend`).

Per-instance terrain, friction and payload live in one ``mujoco.MjModel`` per instance (:func:`batch_models`),
written by the same function that writes them into a batched ``mjx.Model``
(:func:`hyqjax.sim.model.instance_model`), evaluated in float64. The midphase (bounding volume hierarchy of the
static terrain, computed when the model is compiled) is switched off so that a platform moved per instance collides
where it is; the broad and narrow phases are unchanged. MuJoCo's automatic reset of an unstable instance is switched
off as well: its non-finite state is counted as a divergence instead of restarting the run silently.
"""
from __future__ import annotations

import copy
import functools
import types
from typing import NamedTuple

import jax
import mujoco
import numpy as np

from hyqjax.sim import model as hmodel
from hyqjax.sim.host_jit import host_jit

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


class CInitialData(NamedTuple):
    """Initial state of a C MuJoCo batch at time 0: ``qpos`` ``(B, nq)`` and ``qvel`` ``(B, nv)`` in float64 (None:
    zero velocity, what :func:`hyqjax.sim.rollout.initial_data` makes for MJX)."""

    qpos: np.ndarray
    qvel: np.ndarray | None = None
