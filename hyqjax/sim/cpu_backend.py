"""The C MuJoCo backend (``impl="c"``): many simulations stepped in C on all CPU cores, the controller in JAX.

MJX compiled for a CPU spends most of its time in XLA's generic code for the physics (minutes of compile, a
few thousand env-steps per second for HyQ); C MuJoCo steps HyQ in about 20 us per instance and step with no
compile. This backend runs the closed loop as ONE jitted ``lax.scan`` over control ticks: per tick the controller
of the whole batch in compiled JAX, then the physics of every instance in one call into C, then the divergence
rule, metrics and traces of :func:`hyqjax.sim.rollout.rollout_advance`. The controller and metrics compile once per
batch bucket; the physics never compiles. Its parts:

* :mod:`hyqjax.sim.cpu_models`: one ``mujoco.MjModel`` per instance (:func:`batch_models`: per-instance terrain,
  friction and payload, midphase and automatic reset off) and the initial state (:class:`CInitialData`);
* :mod:`hyqjax.sim.cpu_runner`: the closed loop of a batch (:class:`CBatchRunner`: the scan, the physics host call,
  the padding to a bucket, the shards, one per CPU core);
* :mod:`hyqjax.sim.cpu_physics`: the instances in one ``mujoco.batch.Batch``, stepped in C;
* :mod:`hyqjax.sim.host_jit`: programs compiled for the host CPU with this backend's XLA options;
* this module: :class:`CBackend`, the object :func:`hyqjax.sim.backend.get` hands out for ``impl="c"``; the names of
  the modules above that callers reach through it (``cpu_backend.batch_models``, ``cpu_backend.CBatchRunner``, ...)
  are importable from here too.

Forward only: a derivative through this backend is a ``ValueError`` naming ``impl`` (gradients need
``impl="jax"``), and there is no one-instance rollout outside a batch.
"""
from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from hyqjax.sim import impls as _impls
from hyqjax.sim import model as hmodel
from hyqjax.sim.cpu_models import CInitialData, batch_models, prepare_model  # noqa: F401  (re-exported)
from hyqjax.sim.cpu_runner import _ACTIVE, MIN_SHARD_ROWS, PHYSICS_TARGET, CBatchRunner  # noqa: F401  (re-exported)
from hyqjax.sim.host_jit import COMPILER_OPTIONS, compiler_options, host_jit, host_sharding  # noqa: F401  (re-exported)


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
