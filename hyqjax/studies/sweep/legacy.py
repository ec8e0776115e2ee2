"""Sweep stores of the first format, ``hyqjax.sweep/1``: read as they are, converted to Parquet on request.

A ``hyqjax.sweep/1`` directory (``manifest.json`` + ``chunks/NNNNN.npz``, no hashes) was written by an earlier
hyqjax whose outcome columns and definitions differ from this version's (e.g. ``success`` before
``completed`` / ``clean``). Its rows are read as they are (:func:`hyqjax.studies.sweep.store.open_store`,
``hyqjax report``), each chunk's ``index`` column checked against its row range. A writer never resumes
it, since its rows and new ones would mix two versions' outcomes; it is refused with
:func:`read_only_message`. :func:`convert_v1` (``python -m hyqjax.studies.sweep.convert DIR``) converts it in
place to Parquet chunks with hashes (rows kept, ``.npz`` files removed) so that pandas, polars or DuckDB
open it as one table; the converted store records ``converted_from`` and stays read-only.
"""
from __future__ import annotations

import os

import numpy as np

SCHEMA = "hyqjax.sweep/2"
OLD_SCHEMAS = ("hyqjax.sweep/1",)


def read_only_message(out_dir: str, schema: str, converted: bool = False) -> str:
    """Why a writer is refused on an old (or converted) store, and what to do."""
    what = f"converted from schema {schema}" if converted else f"of schema {schema}"
    how = "" if converted else (f" To open it as one Parquet table (pandas, polars, DuckDB), convert it: "
                                f"python -m hyqjax.studies.sweep.convert {out_dir}.")
    return (f"{out_dir} holds a sweep {what}, written by an earlier hyqjax (other outcome columns), so this "
            f"version does not add to it (a store never mixes two versions' rows); its rows are read as they are "
            f"(hyqjax report {out_dir}).{how} To run the sweep with this version, use another --out directory")


def check_v1(store, man: dict) -> None:
    """Refuse a v1 store of another spec (raises StoreMismatch), and a writer on any v1 store."""
    from hyqjax.studies.sweep.spec import SpecError, SweepSpec
    from hyqjax.studies.sweep.store import StoreMismatch

    try:
        stored = SweepSpec.from_dict(man.get("spec")).spec_hash
    except SpecError:
        stored = man.get("spec_hash")
    if stored != store.spec.spec_hash:
        raise StoreMismatch(
            f"{store.dir} holds a different sweep (schema {man.get('schema')}, spec hash {str(stored)[:12]}, this "
            f"spec {store.spec.spec_hash[:12]}); use another --out directory")
    if store._writer:
        raise StoreMismatch(read_only_message(store.dir, man.get("schema")))


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


def convert_v1(out_dir: str):
    """Convert the v1 store in ``out_dir`` in place to Parquet chunks (under its lock; rows kept, ``.npz``
    files removed). Unreadable chunks are left out and named. Returns the converted (read-only) store."""
    from hyqjax.io.atomic import atomic_write, write_json
    from hyqjax.io.lock import DirLock
    from hyqjax.studies.sweep.chunkfile import rows_to_parquet
    from hyqjax.studies.sweep.store import StoreMismatch, SweepStore, open_store

    with DirLock(out_dir, what="conversion"):
        old = open_store(out_dir)
        schema = old.manifest.get("schema")
        if schema not in OLD_SCHEMAS:
            raise StoreMismatch(f"{out_dir} is a {schema} store: nothing to convert")
        for c, why in sorted(old.problems.items()):
            print(f"note: chunk {c} left out: {why}")
        rows_of, entries = dict(old._verified), old.manifest["chunks"]
        man = dict(old.manifest, schema=SCHEMA, spec_hash=old.spec.spec_hash, converted_from=schema, chunks={})
        old.manifest = man  # chunk files, metadata and entries of the new schema from here on
        os.makedirs(old.chunks_dir, exist_ok=True)
        for c in sorted(rows_of):
            wall = entries[str(c)].get("wall_s")
            data = rows_to_parquet(rows_of[c], dict(old._meta(c), wall_s=wall))
            atomic_write(old.chunk_file(c), lambda f, d=data: f.write(d))
            man["chunks"][str(c)] = old._entry(c, data, wall)
            man["columns"] = sorted(rows_of[c])
        write_json(old.path, man)
        for name in os.listdir(old.chunks_dir):
            if name.endswith(".npz"):
                os.remove(os.path.join(old.chunks_dir, name))
    store = SweepStore(out_dir, old.spec)
    print(f"converted {out_dir} from {schema} (.npz chunks) to {SCHEMA} (Parquet chunks): {len(store.done())} of "
          f"{store.n_chunks} chunks; read-only")
    return store
