"""A simulated task, and the one generic rollout that runs every task on every backend.

A **task** (:class:`Task`) is what is particular to an experiment: its model and simulator (:meth:`Task.setup`),
its controller, its device metrics (with the episode end, ``Metrics.terminal``), its trace sample, its outcome of
one instance's :class:`hyqjax.sim.rollout.RolloutResult`, and how one instance and one batch of its inputs become
a simulator's model and initial data. The step-down (:class:`hyqjax.studies.stepdown.StepdownTask`) and bounding
(:class:`hyqjax.bounding.rollout.BoundingTask`) are tasks; :mod:`hyqjax.studies.tasks` names them.

The **rollout** (:class:`Rollout`) is everything else, the same for every task:

* ``rollout(params, instance) -> (outcome, final data)``: ONE instance, pure JAX (:func:`hyqjax.sim.rollout.rollout`:
  ``lax.scan`` over control ticks), so ``jax.jit``, ``jax.vmap`` and, on MJX-JAX, ``jax.jacfwd`` reach every leaf
  of ``params`` and ``instance``; a derivative through a forward-only backend is a ``ValueError``
  (``backend.forbid_derivatives``);
* ``rollout.run(batch) -> (outcomes, RolloutResult)``: a batch through the backend's batch runner
  (``backend.make_runner``: jitted, compiled once per batch shape and mesh, sharded over a mesh, chunked in
  simulated time with progress; C MuJoCo's runner steps ``MjData`` in C), one runner kept per mesh;
* the divergence and termination policy (:mod:`hyqjax.sim.rollout`): a non-finite or runaway instance is frozen
  at its last finite tick and flagged; one whose metrics meet ``Metrics.terminal`` ends its episode there.

A batch is any PyTree with ``params`` (the controller's parameters, a leading batch axis) and ``push`` (a
:class:`hyqjax.core.types.Push` per instance) fields; what else it holds is the task's business
(:meth:`Task.batch_inputs`). An instance is whatever :meth:`Task.instance_inputs` takes.

Nothing here names a simulator: a task's setup holds the backend object (:func:`hyqjax.sim.backend.get`) that
its model was made for, and the rollout only asks it.
"""
from __future__ import annotations

import abc
import dataclasses
from typing import Any, Callable, Protocol

import jax
import numpy as np

from hyqjax.core.types import Controller, Metrics
from hyqjax.sim import rollout as sim


class TaskSetup(Protocol):
    """A task's compiled model: ``m`` (C MuJoCo), ``mx`` (the model of the simulator that runs it), ``ids``,
    ``impl`` (the resolved simulator) and ``backend`` (its object, :func:`hyqjax.sim.backend.get`)."""

    m: Any
    mx: Any
    ids: Any
    impl: str

    @property
    def backend(self) -> Any: ...


class Task(abc.ABC):
    """What a simulated task supplies to :class:`Rollout` (see the module docstring).

    Attributes (set by the subclass):
      cfg: the task's static configuration (hashable; changing it recompiles).
      sim_config: rates and horizon (:class:`hyqjax.sim.rollout.SimConfig`).
      controller: the closed loop's controller (:class:`hyqjax.core.types.Controller`).
      metrics: device metrics accumulated every tick (:class:`hyqjax.core.types.Metrics`; ``terminal`` ends an
        instance's episode).
      record: ``record(d, obs, info)``, one trace sample, or None (no trace).
      one_instance_on_every_backend: the one-instance rollout runs on the task's own simulator where that has one
        (``backend.one_instance_error`` is None; a forward run under Warp included). False, or on a simulator
        without one (C MuJoCo), it runs on ``setup(differentiable=True)``'s (``auto``: MJX-JAX), and a request for
        a simulator without one is a ``ValueError``.
    """

    cfg: Any
    sim_config: sim.SimConfig
    controller: Controller
    metrics: Metrics
    record: Callable | None = None
    one_instance_on_every_backend: bool = False

    @abc.abstractmethod
    def setup(self, differentiable: bool = False) -> TaskSetup:
        """The model and simulator of the task's configuration; ``differentiable``: for the pure JAX one-instance
        rollout (where ``impl="auto"`` resolves to ``jax``)."""

    @abc.abstractmethod
    def outcome(self, res: sim.RolloutResult) -> Any:
        """The outcome of ONE instance's rollout result (pure JAX; the rollout ``vmap`` s it over a batch)."""

    @abc.abstractmethod
    def instance_inputs(self, st: TaskSetup, params: Any, instance: Any) -> tuple[Any, Any, Any]:
        """``(model, initial data, push)`` of ONE instance on ``st``'s simulator (pure JAX)."""

    @abc.abstractmethod
    def batch_inputs(self, st: TaskSetup, batch: Any) -> tuple[Any, Any]:
        """``(batched model, batched initial data)`` of a batch on ``st``'s simulator: what its runner takes."""

    def check_batch(self, batch: Any) -> None:
        """Refuse a batch the task cannot run (one clear ``ValueError``) before anything compiles."""

    def check_instance(self, params: Any, instance: Any) -> None:
        """Refuse an instance the task cannot run, where its values are concrete."""


class Rollout:
    """The closed loop of a :class:`Task` (module docstring). ``rollout.task``, ``rollout.cfg`` (the task's
    configuration) and ``rollout.setup`` (its model on its simulator) are the task's."""

    def __init__(self, task: Task):
        self.task = task
        self.cfg = task.cfg
        self.setup = task.setup()
        self.sim_config = task.sim_config
        self.controller = task.controller
        self.metrics = task.metrics
        self.record = task.record if task.sim_config.record_every else None
        self._runners: dict = {}
        self._outcomes = jax.jit(jax.vmap(self.outcome))

    def outcome(self, res: sim.RolloutResult) -> Any:
        """The outcome of one instance's rollout result (pure JAX; the trace is not part of it)."""
        return self.task.outcome(res._replace(trace=None))

    def __call__(self, params: Any, instance: Any) -> tuple[Any, Any]:
        """Simulate ONE instance for the task's duration; returns its outcome and final data (pure JAX)."""
        task = self.task
        task.check_instance(params, instance)
        st = self.setup
        if not task.one_instance_on_every_backend or st.backend.one_instance_error is not None:
            st = task.setup(differentiable=True)
        params, instance = st.backend.forbid_derivatives((params, instance))
        if st.backend.one_instance_error is not None:
            raise ValueError(f"the one-instance rollout needs impl='jax' ({st.backend.one_instance_error}); run "
                             f"{st.impl} batches with rollout.run(...)")
        mx1, d0, push = task.instance_inputs(st, params, instance)
        cfg = dataclasses.replace(self.sim_config, record_every=0)
        res = sim.rollout(mx1, st.ids, d0, self.controller, params, cfg, self.metrics, None, push)
        return task.outcome(res), res.data

    def runner(self, mesh=None):
        """The simulator's batch runner for ``mesh`` (None: one device; a ``jax.Device``: the runner of that
        device's slice of a split batch, :func:`hyqjax.sim.runner.run_on`: the one-device runner placed on it,
        :meth:`hyqjax.sim.runner.BatchRunner.placed`, one trace for every device), built once and kept."""
        if mesh is None:
            key = None
        elif hasattr(mesh, "axis_names"):
            key = (tuple(mesh.devices.flat), mesh.axis_names)
        else:
            key = ("device", mesh.id)
        if key not in self._runners:
            if key is not None and key[0] == "device" and hasattr(self.runner(None), "placed"):
                self._runners[key] = self.runner(None).placed(mesh)
            else:
                self._runners[key] = self.setup.backend.make_runner(
                    self.setup.ids, self.controller, self.sim_config, self.metrics, self.record, params_axes=0,
                    mesh=mesh if key is not None and key[0] != "device" else None)
        return self._runners[key]

    def run(self, batch: Any, mesh=None, progress: Callable[[float, float], None] | None = None,
            chunk_seconds: float | None = None, devices=None) -> tuple[Any, sim.RolloutResult]:
        """Run a batch: the outcomes (leading batch axis) and the rollout result (final state, metrics, trace).
        ``progress(done_s, total_s)`` is called between chunks of simulated time (every ``chunk_seconds``).

        Devices: ``mesh`` runs the batch sharded over that mesh; otherwise over ``devices`` (a list of local
        devices, a count or a list of ids; None: the process's selection, every local device unless the command
        line's ``--devices`` chose, :func:`hyqjax.sim.devices.resolve`), in the simulator's layout
        (:func:`hyqjax.sim.runner.run_on`: MJX-JAX one sharded program, MuJoCo Warp one program per device)."""
        from hyqjax.sim import devices as hdevices
        from hyqjax.sim import runner as srunner

        self.task.check_batch(batch)
        if mesh is not None or self.setup.impl == "c":
            mb, d0 = self.task.batch_inputs(self.setup, batch)
            res = self.runner(mesh)(mb, d0, batch.params, batch.push, progress=progress, chunk_seconds=chunk_seconds)
            return self._outcomes(res._replace(trace=None)), res
        traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(batch))
        devs = hdevices.resolve(devices)[:1] if traced else hdevices.resolve(devices)  # under a transformation: one
        n = int(jax.tree_util.tree_leaves(batch.push)[0].shape[0])

        def inputs_of(idx):
            sub = batch if len(idx) == n and np.array_equal(idx, np.arange(n)) else _take(batch, idx)
            mb, d0 = self.task.batch_inputs(self.setup, sub)
            return mb, d0, sub.params, sub.push

        res = srunner.run_on(devs, n, inputs_of, self.runner, self.setup.impl, progress, chunk_seconds)
        return self._outcomes(res._replace(trace=None)), res


def _take(batch: Any, idx) -> Any:
    """Instances ``idx`` (host integers) of every leaf of a batch (each has the leading batch axis)."""
    idx = np.asarray(idx)
    return jax.tree_util.tree_map(lambda x: x[idx] if isinstance(x, np.ndarray) else jax.numpy.asarray(x)[idx], batch)
