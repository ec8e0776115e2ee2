"""A chunk's rows as one Parquet file (pyarrow, zstd) with the sweep's metadata and a content checksum in the
file's key-value metadata.

1-D columns map to Arrow columns of their dtype (strings as UTF-8); a 2-D column (``block_heights``) is a
list per row (Arrow's fixed-size lists cannot be empty, and a sweep without rough terrain has width 0).

**Content checksum.** Parquet and zstd do not detect most damage: a flipped bit in a data page, a
dictionary or the footer often still parses, with other values. So the writer stores
``content_sha256`` in the chunk's own metadata (:data:`META_KEY`), independent of the store's manifest: the
SHA-256 of a canonical serialisation (:func:`content_sha256`) of the metadata without the checksum and of
every column as Arrow reads it back (name, type, length, nulls, and the values: raw bytes of numbers and
booleans, UTF-8 of strings with their lengths, the lengths and flattened values of lists). Reading a chunk
(:func:`parquet_to_rows`) recomputes it and raises :class:`ChunkDamaged` on a mismatch, so a chunk whose
values or metadata changed after it was written is never read as data, with or without the manifest.
Chunks written before the checksum existed have none: :func:`parquet_to_rows` reads them, and their metadata
lacks :data:`CHECKSUM`, so the store decides (it trusts them only when the manifest's SHA-256 of the whole
file matches; see :mod:`hyqjax.studies.sweep.store`).
"""
from __future__ import annotations

import hashlib
import json
import struct

import numpy as np

META_KEY = b"hyqjax.sweep"
#: The key of the content checksum inside a chunk's metadata.
CHECKSUM = "content_sha256"
_DOMAIN = b"hyqjax.sweep.chunk-content/1\0"


class ChunkDamaged(ValueError):
    """A chunk file cannot be read as data: not a readable Parquet file, or its content checksum does not match."""


def _feed(h, b: bytes) -> None:
    h.update(struct.pack("<q", len(b)))
    h.update(b)


def _type_key(t) -> str:
    """The Arrow type as the checksum sees it: list and string types without the names and offset widths that
    a Parquet round trip may change (``list<item: double>`` reads back as ``list<element: double>``)."""
    import pyarrow as pa

    if pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        return f"list<{_type_key(t.value_type)}>"
    if pa.types.is_string(t) or pa.types.is_large_string(t):
        return "string"
    if pa.types.is_binary(t) or pa.types.is_large_binary(t):
        return "binary"
    return str(t)


def _feed_array(h, arr) -> None:
    import pyarrow as pa
    import pyarrow.compute as pc

    _feed(h, _type_key(arr.type).encode())
    h.update(struct.pack("<qq", len(arr), arr.null_count))
    t = arr.type
    if arr.null_count:  # the writer never writes nulls: any is damage, hashed in a form that cannot collide
        _feed(h, json.dumps(arr.to_pylist(), default=repr).encode())
    elif pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        _feed(h, np.asarray(pc.list_value_length(arr).to_numpy(zero_copy_only=False), np.int64).tobytes())
        _feed_array(h, arr.flatten())
    elif pa.types.is_string(t) or pa.types.is_large_string(t) or pa.types.is_binary(t) or pa.types.is_large_binary(t):
        for s in arr.to_pylist():
            _feed(h, s.encode() if isinstance(s, str) else bytes(s))
    elif pa.types.is_primitive(t):  # numbers and booleans: their exact bits (NaN payloads included)
        _feed(h, np.ascontiguousarray(arr.to_numpy(zero_copy_only=False)).tobytes())
    else:
        _feed(h, json.dumps(arr.to_pylist(), default=repr).encode())


def content_sha256(table, meta: dict) -> str:
    """SHA-256 (hex) of ``meta`` without :data:`CHECKSUM` (canonical JSON) and every column of the Arrow
    ``table`` in order (see the module docstring)."""
    h = hashlib.sha256(_DOMAIN)
    _feed(h, json.dumps({k: v for k, v in meta.items() if k != CHECKSUM}, sort_keys=True,
                        separators=(",", ":")).encode())
    h.update(struct.pack("<q", table.num_columns))
    for name in table.column_names:
        _feed(h, name.encode())
        _feed_array(h, table.column(name).combine_chunks())
    return h.hexdigest()


def rows_to_parquet(rows: dict[str, np.ndarray], meta: dict) -> bytes:
    """Parquet bytes of ``rows`` (1-D columns; 2-D ones as lists) with ``meta`` and its content checksum
    (:data:`CHECKSUM`) as file metadata."""
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
    table = pa.table(cols)
    meta = {k: v for k, v in meta.items() if k != CHECKSUM}
    meta[CHECKSUM] = content_sha256(table, meta)
    table = table.replace_schema_metadata({META_KEY: json.dumps(meta).encode()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def read_table(data: bytes):
    """``(Arrow table, metadata)`` of chunk bytes whose content checksum matches (or that have none: an earlier
    hyqjax's); raises :class:`ChunkDamaged` naming what is wrong otherwise."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        # The file alone (no dataset discovery), on this thread: a chunk is small, and Arrow's thread pool left
        # running can abort the interpreter at exit ("terminate called without an active exception", apache/arrow
        # issue 34314), which would turn a finished sweep or a one-line refusal into exit code -6.
        table = pq.ParquetFile(pa.BufferReader(data)).read(use_threads=False)
        meta = json.loads((table.schema.metadata or {}).get(META_KEY, b"{}"))
        if not isinstance(meta, dict):
            raise ValueError("metadata is not a JSON object")
    except Exception as e:  # pyarrow and json raise several types for a damaged file
        raise ChunkDamaged(f"not a readable Parquet chunk ({type(e).__name__})") from None
    try:
        matches = CHECKSUM not in meta or content_sha256(table, meta) == meta[CHECKSUM]
    except Exception as e:  # a damaged file can make Arrow fail on names or values it has read
        raise ChunkDamaged(f"not a readable Parquet chunk ({type(e).__name__})") from None
    if not matches:
        raise ChunkDamaged("its contents do not match the content checksum in its metadata (damaged after it "
                           "was written)")
    return table, meta


def table_to_rows(table) -> dict[str, np.ndarray]:
    """The columns of an Arrow table as NumPy arrays (lists as 2-D arrays, strings as ``str`` arrays)."""
    import pyarrow as pa

    rows = {}
    for name in table.column_names:
        col = table.column(name).combine_chunks()
        if pa.types.is_list(col.type) or pa.types.is_large_list(col.type) or pa.types.is_fixed_size_list(col.type):
            flat = np.asarray(col.flatten().to_numpy(zero_copy_only=False))
            rows[name] = flat.reshape(len(col), flat.size // max(len(col), 1))
        elif pa.types.is_string(col.type) or pa.types.is_large_string(col.type):
            rows[name] = np.asarray(col.to_pylist(), dtype=str) if len(col) else np.zeros(0, str)
        else:
            rows[name] = np.asarray(col.to_numpy(zero_copy_only=False))
    return rows


def parquet_to_rows(data: bytes) -> tuple[dict[str, np.ndarray], dict]:
    """Inverse of :func:`rows_to_parquet`: ``(columns as NumPy arrays, metadata)``, the content checksum
    checked (:func:`read_table`; :class:`ChunkDamaged` if it does not match). ``CHECKSUM in metadata`` tells
    whether the chunk had one."""
    table, meta = read_table(data)
    try:
        rows = table_to_rows(table)
    except Exception as e:  # a list column whose lengths do not fit a 2-D array, ...
        raise ChunkDamaged(f"not a readable chunk ({type(e).__name__})") from None
    return rows, meta


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
