"""Robustness sweeps of the step-down experiment (Focchi et al. 2017, Section IV) over a declarative grid.

The package, one concept per module:

* :mod:`~hyqjax.studies.sweep.spec`: the axes, their ranges, and :class:`SweepSpec` (validation, instance
  inputs deterministic in the seed and the instance index);
* :mod:`~hyqjax.studies.sweep.scenario`: input rows as step-down scenarios, sensor noise and latency;
* :mod:`~hyqjax.studies.sweep.runner`: the compiled chunk runner and :func:`run_sweep` (local executor);
* :mod:`~hyqjax.studies.sweep.cluster`: the Ray executor (``hyqjax sweep --executor ray``);
* :mod:`~hyqjax.studies.sweep.store`: the locked, verified Parquet store and its manifest;
  :mod:`~hyqjax.studies.sweep.legacy`: stores of the first format (read as they are, converted on request);
* :mod:`~hyqjax.studies.sweep.outcomes`, :mod:`~hyqjax.studies.sweep.summary`,
  :mod:`~hyqjax.studies.sweep.plots`: failures with reasons, Wilson maps, largest safe height, figures.
"""
from hyqjax.studies.sweep.legacy import convert_v1
from hyqjax.studies.sweep.outcomes import CRITICAL_METRICS, count_outcomes
from hyqjax.studies.sweep.plots import plot_height_curves, plot_maps
from hyqjax.studies.sweep.runner import (LocalExecutor, compute_chunk, default_chunk_size, device_layout, run_rows,
                                         run_sweep)
from hyqjax.studies.sweep.scenario import SensedParams, SensedState, SensorParams, build_scenario, sensed_controller
from hyqjax.studies.sweep.spec import AXES, Axis, SpecError, SweepSpec, load_spec, load_spec_dict
from hyqjax.studies.sweep.store import (SCHEMA, StoreBusy, StoreCorrupt, StoreMismatch, SweepStore, open_store,
                                        parquet_to_rows, rows_to_parquet)
from hyqjax.studies.sweep.summary import format_summary, logistic_h95, summarize_sweep, write_outputs

__all__ = ["AXES", "Axis", "CRITICAL_METRICS", "LocalExecutor", "SCHEMA", "SensedParams", "SensedState",
           "SensorParams", "SpecError", "StoreBusy", "StoreCorrupt", "StoreMismatch", "SweepSpec", "SweepStore",
           "build_scenario", "compute_chunk", "convert_v1", "count_outcomes", "default_chunk_size", "device_layout",
           "format_summary", "load_spec", "load_spec_dict", "logistic_h95", "open_store", "parquet_to_rows", "plot_height_curves",
           "plot_maps", "rows_to_parquet", "run_rows", "run_sweep", "sensed_controller", "summarize_sweep",
           "write_outputs"]
