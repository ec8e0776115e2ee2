"""Robustness sweeps of the step-down experiment (Focchi et al. 2017, Section IV) over a declarative grid.

The package, one concept per module:

* :mod:`~hyqjax.studies.sweep.spec`: the axes, their ranges, and :class:`SweepSpec` (validation, instance
  inputs deterministic in the seed and the instance index);
* :mod:`~hyqjax.studies.sweep.scenario`: input rows as step-down scenarios, sensor noise and latency;
* :mod:`~hyqjax.studies.sweep.runner`: the compiled chunk runner and :func:`run_sweep` (local executor);
* :mod:`~hyqjax.studies.sweep.cluster`: the Ray executor (``hyqjax sweep --executor ray``);
* :mod:`~hyqjax.studies.sweep.store`: the locked, verified Parquet store;
  :mod:`~hyqjax.studies.sweep.manifest`: its manifest (schema, records, checks) and the store's errors;
  :mod:`~hyqjax.studies.sweep.recovery`: what a writer repairs on opening it (temporaries, a lost manifest,
  unrecorded and damaged chunk files);
  :mod:`~hyqjax.studies.sweep.chunkfile`: a chunk file and its content checksum;
  :mod:`~hyqjax.studies.sweep.verify`: a reader's check of a whole sweep directory (``hyqjax verify``);
  :mod:`~hyqjax.studies.sweep.legacy`: stores of the first format (read as they are);
  :mod:`~hyqjax.studies.sweep.convert`: their conversion to the current format, on request;
* :mod:`~hyqjax.studies.sweep.outcomes`, :mod:`~hyqjax.studies.sweep.summary`,
  :mod:`~hyqjax.studies.sweep.plots`: failures with reasons, Wilson maps, largest safe height, figures;
* the CI gate (docs/ci.md): :mod:`~hyqjax.studies.sweep.expect` (expectations on the rates, decided on Wilson
  intervals), :mod:`~hyqjax.studies.sweep.compare` (two stores of one sweep: Newcombe, paired McNemar, Holm),
  :mod:`~hyqjax.studies.sweep.gate` (the verdict, JUnit / Markdown / JSON reports).

Names are imported on first use (``from hyqjax.studies import sweep`` loads neither JAX nor MuJoCo; the spec
loads JAX's parameter declarations, the runner MJX).
"""
from __future__ import annotations

_PUBLIC = {
    "convert_v1": "convert",
    "CRITICAL_METRICS": "outcomes", "count_outcomes": "outcomes",
    "plot_height_curves": "plots", "plot_maps": "plots",
    "LocalExecutor": "runner", "compute_chunk": "runner", "device_layout": "runner", "run_rows": "runner",
    "run_sweep": "runner",
    "SensedParams": "scenario", "SensedState": "scenario", "SensorParams": "scenario", "build_scenario": "scenario",
    "sensed_controller": "scenario",
    "AXES": "spec", "Axis": "spec", "SpecError": "spec", "SweepSpec": "spec", "load_spec": "spec",
    "load_spec_dict": "spec",
    "SCHEMA": "manifest", "StoreCorrupt": "manifest", "StoreMismatch": "manifest",
    "StoreBusy": "store", "SweepStore": "store",
    "default_chunk_size": "store", "open_store": "store",
    "CHECKSUM": "chunkfile", "ChunkDamaged": "chunkfile", "parquet_to_rows": "chunkfile", "rows_to_parquet": "chunkfile",
    "StoreCheck": "verify", "verify_store": "verify",
    "Comparison": "compare", "compare_stores": "compare",
    "Expectation": "expect", "parse_expectation": "expect",
    "Verdict": "gate",
    "format_summary": "summary", "logistic_h95": "summary", "summarize_sweep": "summary", "write_outputs": "summary",
}
_MODULES = ("axes", "chunkfile", "cluster", "compare", "convert", "expect", "gate", "legacy", "manifest", "outcomes",
            "plots", "recovery", "runner", "scenario", "spec", "store", "summary", "verify")
__all__ = sorted(_PUBLIC)


def __getattr__(name):
    if name in _PUBLIC:
        import importlib

        value = getattr(importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
        globals()[name] = value
        return value
    if name in _MODULES:  # ``sweep.store`` etc. without importing the submodule first
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
