"""Sweep stores of the first format, ``hyqjax.sweep/1``: read as they are, converted to Parquet on request.

A ``hyqjax.sweep/1`` directory (``manifest.json`` + ``chunks/NNNNN.npz``, no hashes) was written by an earlier
hyqjax whose outcome columns and definitions differ from this version's (e.g. ``success`` before
``completed`` / ``clean``). Its rows are read as they are (:func:`hyqjax.studies.sweep.store.open_store`,
``hyqjax report``), each chunk's ``index`` column checked against its row range. A writer never resumes
it, since its rows and new ones would mix two versions' outcomes; it is refused with
:func:`read_only_message`. :func:`hyqjax.studies.sweep.convert.convert_v1` (``python -m
hyqjax.studies.sweep.convert DIR``) converts it in place to Parquet chunks with hashes (rows kept, ``.npz`` files
removed) so that pandas, polars or DuckDB open it as one table; the converted store records ``converted_from``
and stays read-only.

This module knows the old format only and sits below :mod:`hyqjax.studies.sweep.store`, which imports it (the
current schema, :data:`hyqjax.studies.sweep.manifest.SCHEMA`, is the store's).
"""
from __future__ import annotations

import os

import numpy as np

#: Schemas of the first format (read as they are, never resumed).
OLD_SCHEMAS = ("hyqjax.sweep/1",)


def read_only_message(out_dir: str, schema: str, converted: bool = False) -> str:
    """Why a writer is refused on an old (or converted) store, and what to do."""
    what = f"converted from schema {schema}" if converted else f"of schema {schema}"
    how = "" if converted else (f" To open it as one Parquet table (pandas, polars, DuckDB), convert it: "
                                f"python -m hyqjax.studies.sweep.convert {out_dir}.")
    return (f"{out_dir} holds a sweep {what}, written by an earlier hyqjax (other outcome columns), so this "
            f"version does not add to it (a store never mixes two versions' rows); its rows are read as they are "
            f"(hyqjax report {out_dir}).{how} To run the sweep with this version, use another --out directory")


def v1_refusal(out_dir: str, man: dict, spec_hash: str, writer: bool) -> str | None:
    """Why the v1 store in ``out_dir`` (manifest ``man``) is refused to a run of the spec ``spec_hash``: another
    spec, or a writer (a v1 store is never resumed); ``None`` when a reader may read it."""
    from hyqjax.studies.sweep.spec import SpecError, SweepSpec

    try:
        stored = SweepSpec.from_dict(man.get("spec")).spec_hash
    except SpecError:
        stored = man.get("spec_hash")
    if stored != spec_hash:
        return (f"{out_dir} holds a different sweep (schema {man.get('schema')}, spec hash {str(stored)[:12]}, this "
                f"spec {spec_hash[:12]}); use another --out directory")
    if writer:
        return read_only_message(out_dir, man.get("schema"))
    return None


def load_v1_chunk(store, c: int, entry: dict) -> tuple[dict | None, str | None]:
    """``(rows, None)`` of a v1 ``.npz`` chunk whose ``index`` is its row range, else ``(None, reason)``."""
    path = os.path.join(store.dir, entry.get("file", f"chunks/{c:05d}.npz"))
    try:
        with np.load(path, allow_pickle=False) as z:
            rows = {k: z[k] for k in z.files}
    except Exception as e:  # missing, truncated, not a zip, object arrays
        return None, f"{path} is not readable ({type(e).__name__})"
    start, stop = store.chunk_range(c)
    if not np.array_equal(rows.get("index"), np.arange(start, stop)):
        return None, f"{path}: its index column is not the row range [{start}, {stop})"
    return rows, None
