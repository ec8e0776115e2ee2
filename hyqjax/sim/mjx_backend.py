"""The MJX backends (``impl="jax"`` and ``impl="warp"``) behind the interface of :func:`hyqjax.sim.backend.get`.

A backend object answers, for one implementation, what a task needs to run a batch without naming the
implementation: the model (:meth:`MJXBackend.put_model`), its per-instance batch (:meth:`MJXBackend.batch_model`),
the initial data (:meth:`MJXBackend.initial_data`), the batch runner (:meth:`MJXBackend.make_runner`), whether
derivatives pass (``supports_gradients``, :meth:`MJXBackend.forbid_derivatives`) and why a one-instance rollout
is refused (``one_instance_error``). The C MuJoCo backend (:class:`hyqjax.sim.cpu_backend.CBackend`) answers the
same questions.
"""
from __future__ import annotations

from typing import Any

from hyqjax.sim import impls as _impls


class MJXBackend:
    """MJX under ``impl`` (``jax``: pure JAX, differentiable; ``warp``: MuJoCo Warp kernels, forward only)."""

    def __init__(self, impl: str):
        if impl not in _impls.MJX_IMPLS:
            raise ValueError(f"MJXBackend needs impl in {_impls.MJX_IMPLS}, got {impl!r}")
        self.name = impl
        self.supports_gradients = _impls.supports_gradients(impl)
        #: A batch is split over JAX devices (:func:`hyqjax.sim.devices.resolve_for`).
        self.uses_jax_devices = True
        #: Warp shares one contact buffer over a batch: there is no per-instance ``mjx.Data`` outside a batch.
        self.one_instance_error = (None if impl == "jax" else "MuJoCo Warp keeps one contact buffer for a whole batch")

    def __repr__(self) -> str:
        return f"MJXBackend({self.name!r})"

    def put_model(self, m):
        """``mjx.Model`` of the ``mujoco.MjModel`` ``m``."""
        return _impls.put_model(m, self.name)

    def batch_model(self, model, ids, terrain):
        """``model`` with per-instance terrain (:func:`hyqjax.sim.model.batch_model`)."""
        from hyqjax.sim import model as hmodel

        return hmodel.batch_model(model, ids, terrain)

    def initial_data(self, model, batched_model, qpos, m):
        """Batched data at ``qpos`` ``(B, nq)`` with zero velocity (:func:`hyqjax.sim.rollout.initial_data`; under
        Warp made from ``batched_model``, whose terrain poses go into the data)."""
        from hyqjax.sim import rollout as sim

        return sim.initial_data(batched_model if self.name == "warp" else model, qpos, qpos.shape[0], m=m)

    def from_jax_data(self, model, d, m):
        """This implementation's data holding the state (``qpos``, ``qvel``) of MJX-JAX data ``d`` (one instance
        or a batch, per the shape of ``d.qpos``), on ``model`` (batched for a batch)."""
        if self.name == "jax":
            return d
        from hyqjax.sim import rollout as sim

        batch = d.qpos.shape[0] if d.qpos.ndim == 2 else None
        dw = sim.initial_data(model, d.qpos, batch, m=m)
        return dw.replace(qvel=d.qvel.astype(dw.qvel.dtype))

    def make_runner(self, ids, controller, cfg, metrics=None, record=None, params_axes: Any = 0, mesh=None,
                    buckets: bool = True):
        """The jitted, sharded, chunked batch runner (:func:`hyqjax.sim.runner.make_batch_runner`; ``buckets``: CPU
        batch shapes rounded to a few buckets, see :func:`hyqjax.sim.runner.batch_plan`)."""
        from hyqjax.sim import rollout as sim
        from hyqjax.sim import runner

        return runner.make_batch_runner(ids, controller, cfg, metrics if metrics is not None else sim.no_metrics(),
                                        record, params_axes=params_axes, mesh=mesh, buckets=buckets)

    def forbid_derivatives(self, tree):
        """Identity; a derivative through it raises ``ValueError`` unless the backend supports gradients."""
        return _impls.forbid_derivatives(tree, self.name)
