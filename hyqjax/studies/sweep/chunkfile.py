"""A chunk's rows as one Parquet file (pyarrow, zstd) with the sweep's metadata in the file's key-value metadata.

1-D columns map to Arrow columns of their dtype (strings as UTF-8); a 2-D column (``block_heights``) is a
list per row (Arrow's fixed-size lists cannot be empty, and a sweep without rough terrain has width 0).
"""
from __future__ import annotations

import json

import numpy as np

META_KEY = b"hyqjax.sweep"


def rows_to_parquet(rows: dict[str, np.ndarray], meta: dict) -> bytes:
    """Parquet bytes of ``rows`` (1-D columns; 2-D ones as fixed-size lists) with ``meta`` as file metadata."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {}
    for k, v in rows.items():
        v = np.asarray(v)
        if v.ndim == 2:  # a list per row (Arrow's fixed-size lists cannot have width 0)
            offsets = pa.array(np.arange(v.shape[0] + 1, dtype=np.int32) * v.shape[1])
            cols[k] = pa.ListArray.from_arrays(offsets, pa.array(v.reshape(-1)))
        elif v.dtype.kind in "US":
            cols[k] = pa.array(v.astype(str).tolist(), pa.string())
        else:
            cols[k] = pa.array(v)
    table = pa.table(cols).replace_schema_metadata({META_KEY: json.dumps(meta).encode()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def parquet_to_rows(data: bytes) -> tuple[dict[str, np.ndarray], dict]:
    """Inverse of :func:`rows_to_parquet`: ``(columns as NumPy arrays, metadata)``."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(pa.BufferReader(data))
    meta = json.loads((table.schema.metadata or {}).get(META_KEY, b"{}"))
    rows = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type):
            flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False))
            rows[name] = flat.reshape(len(col), flat.size // max(len(col), 1))
        elif pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            rows[name] = np.asarray(col.to_pylist(), dtype=str) if len(col) else np.zeros(0, str)
        else:
            rows[name] = np.asarray(col.to_numpy(zero_copy_only=False))
    return rows, meta


def read_meta(path: str) -> dict | None:
    """The metadata embedded in the chunk file ``path`` (read from its footer only), or None if unreadable."""
    import pyarrow.parquet as pq

    try:
        meta = json.loads((pq.read_schema(path).metadata or {}).get(META_KEY, b"{}"))
    except Exception:  # pyarrow raises several types for a damaged file
        return None
    return meta if isinstance(meta, dict) and meta else None


def chunk_metas(chunks_dir: str) -> dict[int, dict]:
    """``{chunk: metadata}`` of the readable chunk files ``NNNNN.parquet`` in ``chunks_dir``."""
    import os

    out = {}
    names = os.listdir(chunks_dir) if os.path.isdir(chunks_dir) else []
    for name in sorted(names):
        if name.endswith(".parquet") and name[:-8].isdigit():
            meta = read_meta(os.path.join(chunks_dir, name))
            if meta is not None:
                out[int(name[:-8])] = meta
    return out


def chunk_size_of(metas: dict[int, dict], n_instances: int) -> int | None:
    """The chunk size the files of ``metas`` were written with (None if they do not tell)."""
    for c, m in sorted(metas.items()):
        start, stop = m.get("start"), m.get("stop")
        if not (isinstance(start, int) and isinstance(stop, int)):
            continue
        if c > 0 and start % c == 0:
            return start // c
        if c == 0 and stop < n_instances:
            return stop - start
    return None
