"""hyqjax: IIT HyQ's height reflex, crawl and bounding gaits as pure, batched, differentiable JAX on MJX.

Subpackages by concept (docs/architecture.md draws the layers):
  core      robot constants, spatial algebra, kinematics, parameter declarations
  sim       HyQ + terrain model, contacts (sensors), backend choice (impl), rollout, batch runner
  control   joint impedance, trunk control, trajectories, standing
  reflex    the height reflex (Focchi et al. 2017, Section III, Eqs. 2-12)
  crawl     the statically stable crawl (Section II) with the reflex hooked in
  bounding  impulse-based bounding and turning (Orsolino et al.)
  studies   the step-down experiment (Section IV), sweeps, tuning, statistics
  io, cli   results, recordings, rendering, reports; the command line

The public API is re-exported here and imported on first use (``import hyqjax`` loads no JAX):
``StepdownConfig``, ``Scenario``, ``make_scenarios``, ``make_stepdown_rollout``, ``StepdownOutcome``,
``run_batch``, ``summarize``, ``format_table``; ``CrawlParams``, ``PerLegCrawlParams``, ``ReflexParams``,
``batch_params``;
``Observation``, ``Controller``, ``Metrics``, ``Push`` (MJX-free, :mod:`hyqjax.core.types`);
``SimConfig``, ``make_batch_runner``, ``rollout``, ``batch_mesh``; ``load_model``, ``model_ids``,
``InstanceTerrain``, ``batch_model``; ``resolve_impl``; the bound: ``BoundingRolloutConfig``,
``make_bounding_rollout``, ``BoundingRollout``, ``BoundingOutcome``, ``BoundingParams`` (batches from
``hyqjax.bounding.make_batch``). Named parameter sets: ``hyqjax.presets`` (``load``, ``get``, ``names``).
"""
from __future__ import annotations

import os as _os
import sys as _sys
import time as _time

#: When this package was first imported (``time.perf_counter``): a command's clock (:mod:`hyqjax.io.phases`) starts at
#: its process's start unless that process ran another program before this interpreter (a shell's ``exec``).
_IMPORTED_AT = _time.perf_counter()

__version__ = "0.1.0"

# jaxlib 0.10.x on CPU deadlocks jit(vmap(mjx.step)) at batch >= 256. hyqjax pins jax 0.9.2; if a
# newer jax is installed and not yet imported, switch off the two XLA:CPU features involved.
if "jax" not in _sys.modules:
    _flags = _os.environ.get("XLA_FLAGS", "")
    if "concurrency_optimized_scheduler" not in _flags:
        _os.environ["XLA_FLAGS"] = (
            _flags + " --xla_cpu_enable_concurrency_optimized_scheduler=false"
            " --xla_cpu_experimental_ynn_fusion_type="
        ).strip()

from hyqjax.sim import backend as _backend  # noqa: E402  (stdlib only: no JAX at import)

_backend.install_quiet_warp_import()
_backend.install_lazy_mjx_import()

_PUBLIC = {
    "StepdownConfig": "hyqjax.studies.stepdown", "Scenario": "hyqjax.studies.stepdown",
    "make_scenarios": "hyqjax.studies.stepdown", "make_stepdown_rollout": "hyqjax.studies.stepdown",
    "StepdownRollout": "hyqjax.studies.stepdown", "run_batch": "hyqjax.studies.stepdown",
    "StepdownOutcome": "hyqjax.studies.stepdown_outcome", "FAILURE_REASONS": "hyqjax.studies.stepdown_outcome",
    "summarize": "hyqjax.studies.stepdown_table", "format_table": "hyqjax.studies.stepdown_table",
    "CrawlParams": "hyqjax.crawl.controller", "ReflexParams": "hyqjax.reflex.params",
    "PerLegCrawlParams": "hyqjax.crawl.scheduled",
    "batch_params": "hyqjax.core.params",
    "SimConfig": "hyqjax.sim.rollout", "rollout": "hyqjax.sim.rollout", "Observation": "hyqjax.core.types",
    "Controller": "hyqjax.core.types", "Metrics": "hyqjax.core.types", "Push": "hyqjax.core.types",
    "make_batch_runner": "hyqjax.sim.runner", "batch_mesh": "hyqjax.sim.runner",
    "load_model": "hyqjax.sim.model", "model_ids": "hyqjax.sim.model", "InstanceTerrain": "hyqjax.sim.model",
    "batch_model": "hyqjax.sim.model", "resolve_impl": "hyqjax.sim.backend",
    "BoundingRolloutConfig": "hyqjax.bounding.rollout", "make_bounding_rollout": "hyqjax.bounding.rollout",
    "BoundingRollout": "hyqjax.bounding.rollout", "BoundingOutcome": "hyqjax.bounding.rollout",
    "BoundingParams": "hyqjax.bounding.params",
}
__all__ = sorted(_PUBLIC)


def __getattr__(name):
    if name in _PUBLIC:
        import importlib

        value = getattr(importlib.import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'hyqjax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
