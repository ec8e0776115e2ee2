"""The sweep results store: ``DIR/manifest.json`` + one Parquet file per chunk, locked and verified.

``DIR`` holds ``manifest.json`` (schema, canonical spec and its SHA-256, chunk size, device layout, the
columns, and per chunk its file, row range ``[start, stop)``, size, SHA-256 and wall time),
``chunks/NNNNN.parquet`` (a chunk's input and outcome columns, with the spec hash, chunk number, row range
and layout in the file's metadata) and ``.lock``. ``pandas.read_parquet("DIR/chunks")``,
``polars.read_parquet("DIR/chunks/*.parquet")`` or DuckDB's ``SELECT * FROM 'DIR/chunks/*.parquet'`` read
the whole sweep as one table (``index`` is the instance number).

Guarantees:

* **One writer.** A writer holds ``DIR/.lock`` (:class:`hyqjax.io.lock.DirLock`) for its whole run; a
  second one is refused with the holder's pid and host, or waits (``wait=True``, ``--wait``). The kernel
  drops the lock when its holder dies. The manifest is re-read and merged under the lock before every
  write, and a chunk already recorded with a valid file is never written again.
* **Atomic files.** Chunk and manifest are written to a temporary and renamed; a kill at any point leaves
  the old or the new file. The next writer removes dead writers' temporaries and adopts a chunk file
  written but not yet recorded once its content checksum, metadata and row range check out.
* **Chunks that check themselves.** Every chunk file carries a SHA-256 of its own contents in its metadata
  (:mod:`hyqjax.studies.sweep.chunkfile`), checked whenever it is read, so damage is caught with or without
  the manifest. A chunk file written by an earlier hyqjax has no such checksum: it is trusted only while
  the manifest records it with a matching SHA-256 of the whole file (:attr:`SweepStore.unchecked` lists
  those chunks); without the manifest its contents cannot be verified, so it is never adopted but
  recomputed.
* **Verified on load.** Each recorded chunk's size and SHA-256 must match the manifest, its content its
  checksum, its metadata must name this sweep and chunk, its ``index`` column must be its row range and its
  columns the store's (another hyqjax version's rows never mix in: :meth:`SweepStore.write_chunk` refuses
  them). A chunk that fails is named in :attr:`SweepStore.problems` and left out of :meth:`SweepStore.load`;
  a writer moves its file to ``DIR/damaged/`` (so ``DIR/chunks`` read with pandas or DuckDB holds no damaged
  rows) and recomputes it.
* **Strict JSON** (no bare NaN). A corrupt or missing manifest is named, set aside and rebuilt by a writer
  from the chunk files whose content checksums verify, keeping their chunk size and layout; chunk files of
  another sweep are refused.
* **Device layout.** An instance's result depends on the batch shape each device compiles for (XLA's
  vectorisation and fusion), not on which rows share a chunk. The layout (platform, device kind, devices
  per program, chunk size) is recorded, and a resume with another one is refused (:class:`StoreMismatch`).

Stores of schema ``hyqjax.sweep/1`` are read as they are, never resumed (:mod:`hyqjax.studies.sweep.legacy`).
The manifest's schema, records and checks are :mod:`hyqjax.studies.sweep.manifest`; what a writer repairs on
opening the store (temporaries, a missing or corrupt manifest, unrecorded and damaged chunk files) is
:mod:`hyqjax.studies.sweep.recovery`.
"""
from __future__ import annotations

import os

import numpy as np

from hyqjax.io.atomic import atomic_write, write_json
from hyqjax.io.lock import Busy, DirLock
from hyqjax.studies.sweep import legacy
from hyqjax.studies.sweep.chunkfile import CHECKSUM, ChunkDamaged, parquet_to_rows, rows_to_parquet
from hyqjax.studies.sweep.legacy import OLD_SCHEMAS
from hyqjax.studies.sweep.manifest import (MANIFEST, SCHEMA, StoreCorrupt, StoreMismatch, check_manifest,
                                           check_preset_values, chunk_entry, new_manifest, read_manifest,
                                           sha256_bytes)
from hyqjax.studies.sweep.recovery import repair
from hyqjax.studies.sweep.spec import SpecError, SweepSpec

#: A writer that finds the lock held (:class:`hyqjax.io.lock.Busy`).
StoreBusy = Busy


def default_chunk_size(devices=None) -> int:
    """Instances per chunk of a new store when none is given: 32 per CPU device, 4096 per accelerator
    (``devices``: default JAX's local devices)."""
    import jax

    devices = jax.local_devices() if devices is None else devices
    per = 32 if devices[0].platform == "cpu" else 4096
    return per * len(devices)


class SweepStore:
    """A sweep's store in ``out_dir`` (see the module docstring).

    A reader (``writer=False``) checks the manifest (spec hash, schema, layout) and verifies every recorded
    chunk, writing nothing; :meth:`load` gives the rows. A writer (``writer=True``) takes the lock, repairs and
    writes the manifest, and records chunks with :meth:`write_chunk`; :meth:`close` releases the lock.

    Args:
      out_dir: the sweep directory.
      spec: the validated spec; None opens the stored spec read-only (``hyqjax report``).
      chunk_size: instances per chunk for a new store (ignored with a note when resuming).
      layout: the device layout of this run (:func:`hyqjax.studies.sweep.runner.device_layout`); a stored
        layout that differs is refused. None: do not check (readers).
    """

    def __init__(self, out_dir: str, spec: SweepSpec | None, chunk_size: int | None = None,
                 layout: dict | None = None, writer: bool = False, wait: bool = False,
                 timeout: float | None = None, default_chunk_size: int | None = None):
        self.dir = out_dir
        self.path = os.path.join(out_dir, MANIFEST)
        self.chunks_dir = os.path.join(out_dir, "chunks")
        self.problems: dict[int, str] = {}
        #: verified chunks without a content checksum (an earlier hyqjax's): trusted through the manifest's SHA-256
        self.unchecked: set[int] = set()
        self._lock: DirLock | None = None
        self._writer = writer
        self._verified: dict[int, dict[str, np.ndarray]] = {}
        self._requested = dict(chunk_size=chunk_size, layout=layout, default_chunk_size=default_chunk_size)
        if chunk_size is not None and chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        if spec is None:
            man = self._read_manifest()
            if man is None:
                raise StoreCorrupt(f"{out_dir} holds no sweep ({MANIFEST} missing)")
            try:
                spec = SweepSpec.from_dict(man.get("spec"))
            except SpecError as e:
                raise StoreCorrupt(f"{self.path}: its spec is not readable by this hyqjax ({e})") from None
            if man.get("schema") not in OLD_SCHEMAS and spec.spec_hash != man.get("spec_hash"):
                raise StoreCorrupt(f"{self.path}: its spec does not match its spec hash (corrupt, or written by another "
                                   f"hyqjax version)")
        self.spec = spec
        if writer:
            self._lock = DirLock(out_dir, wait=wait, timeout=timeout, what=f"sweep {spec.spec_hash[:12]}").acquire()
            try:
                self._refresh()
            except BaseException:
                self.close()
                raise
            return
        man = self._read_manifest()
        if man is None:  # nothing stored yet: an empty store, nothing written
            man = self._new_manifest(chunk_size, layout)
        self._check(man, chunk_size, layout)
        self.manifest = man
        self.verify()

    def close(self) -> None:
        """Release the writer's lock (a reader has none)."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> "SweepStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---------------------------------------------------------------- manifest
    def _new_manifest(self, chunk_size, layout) -> dict:
        cs = chunk_size or self._requested["default_chunk_size"] or default_chunk_size()
        return new_manifest(self.spec, cs, layout)

    def _read_manifest(self) -> dict | None:
        return read_manifest(self.dir)

    def _check(self, man: dict, chunk_size, layout) -> None:
        check_manifest(man, self.dir, self.spec.spec_hash, self._writer, chunk_size, layout)

    def check_resumable(self) -> None:
        """Raise :class:`StoreMismatch` if a writer would be refused here (an old or a converted store, one whose
        spec's preset has other values now: :func:`hyqjax.studies.sweep.manifest.check_preset_values`)."""
        schema = self.manifest.get("schema")
        if schema in OLD_SCHEMAS or self.manifest.get("converted_from"):
            old = self.manifest.get("converted_from") or schema
            raise StoreMismatch(legacy.read_only_message(self.dir, old, converted=schema not in OLD_SCHEMAS))
        check_preset_values(self.manifest, self.dir)

    @property
    def chunk_size(self) -> int:
        return int(self.manifest["chunk_size"])

    @property
    def n_chunks(self) -> int:
        return int(self.manifest["n_chunks"])

    @property
    def layout(self) -> dict | None:
        return self.manifest.get("layout")

    def chunk_range(self, c: int) -> tuple[int, int]:
        return c * self.chunk_size, min((c + 1) * self.chunk_size, self.spec.n_instances)

    def chunk_file(self, c: int) -> str:
        return os.path.join(self.chunks_dir, f"{c:05d}.parquet")

    def done(self) -> set[int]:
        """Recorded chunks whose files passed verification."""
        return set(self._verified)

    def todo(self) -> list[int]:
        return [c for c in range(self.n_chunks) if c not in self._verified]

    # ---------------------------------------------------------------- verification
    def _meta(self, c: int) -> dict:
        start, stop = self.chunk_range(c)
        return dict(schema=SCHEMA, spec_hash=self.spec.spec_hash, chunk=c, start=start, stop=stop)

    def _check_rows(self, c: int, rows: dict, meta: dict) -> str | None:
        want = self._meta(c)
        for k in ("spec_hash", "chunk", "start", "stop"):
            if meta.get(k) != want[k]:
                return f"its metadata has {k}={meta.get(k)!r}, expected {want[k]!r} (a file of another chunk or sweep)"
        idx = rows.get("index")
        if idx is None or not np.array_equal(idx, np.arange(want["start"], want["stop"])):
            return f"its index column is not the row range [{want['start']}, {want['stop']})"
        return None

    def _verify_chunk(self, c: int, entry: dict) -> tuple[dict | None, dict | None, str | None]:
        """``(rows, meta, None)`` of recorded chunk ``c`` if its file matches its manifest entry (size, SHA-256),
        its content checksum, this sweep and chunk, its row range and the store's columns; else
        ``(None, None, reason)``."""
        path = os.path.join(self.dir, entry.get("file", ""))
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError:
            return None, None, f"{path} is missing"
        if entry.get("bytes") is not None and len(data) != entry["bytes"]:
            return None, None, f"{path} has {len(data)} bytes, the manifest {entry['bytes']} (truncated or replaced)"
        if entry.get("sha256") is not None and sha256_bytes(data) != entry["sha256"]:
            return None, None, f"{path} does not match its SHA-256 in the manifest (corrupt or replaced)"
        try:
            rows, meta = parquet_to_rows(data)
        except ChunkDamaged as e:
            return None, None, f"{path}: {e}"
        if CHECKSUM not in meta and entry.get("sha256") is None:
            return None, None, (f"{path} has neither a content checksum nor a SHA-256 in the manifest: its contents "
                                f"cannot be verified")
        why = self._check_rows(c, rows, meta) or self._check_columns(rows)
        return (None, None, f"{path}: {why}") if why else (rows, meta, None)

    def _check_columns(self, rows: dict) -> str | None:
        want = self.manifest.get("columns")
        if want is None or sorted(rows) == sorted(want):
            return None
        extra, missing = sorted(set(rows) - set(want)), sorted(set(want) - set(rows))
        return (f"its columns differ from the store's (another hyqjax version?): extra {extra}, "
                f"missing {missing}")

    def verify(self) -> dict[int, str]:
        """Check every recorded chunk; returns (and keeps in :attr:`problems`) ``{chunk: reason}`` of bad ones."""
        self._verified, self.problems, self.unchecked = {}, {}, set()
        if self.manifest.get("schema") in OLD_SCHEMAS:
            for key, entry in self.manifest["chunks"].items():
                rows, why = legacy.load_v1_chunk(self, int(key), entry)
                if why:
                    self.problems[int(key)] = why
                else:
                    self._verified[int(key)] = rows
                    self.unchecked.add(int(key))
            return self.problems
        for key, entry in sorted(self.manifest["chunks"].items(), key=lambda t: int(t[0])):
            c = int(key)
            if not 0 <= c < self.n_chunks:
                self.problems[c] = f"chunk {c} is outside the sweep's {self.n_chunks} chunks"
                continue
            rows, meta, why = self._verify_chunk(c, entry)
            if why:
                self.problems[c] = why
            else:
                self._verified[c] = rows
                if CHECKSUM not in meta:
                    self.unchecked.add(c)
        return self.problems

    # ---------------------------------------------------------------- writing (under the lock)
    def _refresh(self) -> None:
        """Under the lock: repair what a killed writer left (:func:`hyqjax.studies.sweep.recovery.repair`)."""
        repair(self)

    def _entry(self, c: int, data: bytes, wall_s=None, worker=None, adopted=False) -> dict:
        return chunk_entry(os.path.relpath(self.chunk_file(c), self.dir), *self.chunk_range(c), data, wall_s=wall_s,
                           worker=worker, adopted=adopted)

    def write_chunk(self, c: int, rows: dict[str, np.ndarray], wall_s: float, worker: str | None = None) -> bool:
        """Record chunk ``c`` (its rows must be exactly the chunk's row range). Needs the lock. Returns False,
        writing nothing, when the chunk is already recorded with a valid file (a chunk lands once)."""
        if self._lock is None or not self._lock.held:
            raise RuntimeError("SweepStore.write_chunk needs a writer: SweepStore(..., writer=True)")
        man = self._read_manifest() or self.manifest  # merge what is on disk (under the lock)
        entry = man["chunks"].get(str(c))
        if entry is not None and self._verify_chunk(c, entry)[2] is None:
            self.manifest = man
            return False
        meta = dict(self._meta(c), wall_s=wall_s, layout=man.get("layout"))
        why = self._check_rows(c, rows, meta)
        if why:
            raise ValueError(f"rows given for chunk {c}: {why}")
        self.manifest = man
        check_preset_values(man, self.dir)  # the preset's values changed while the sweep ran: not recorded
        why = self._check_columns(rows)
        if why:
            raise StoreMismatch(f"{self.dir}: the rows computed for chunk {c} do not fit the store: {why}; the "
                                f"store's chunks were computed by another hyqjax version: use another --out directory")
        data = rows_to_parquet(rows, meta)
        back = parquet_to_rows(data)[0]  # read back (content checksum checked) before anything is renamed
        atomic_write(self.chunk_file(c), lambda f: f.write(data))
        man["chunks"][str(c)] = self._entry(c, data, wall_s, worker)
        man["columns"] = sorted(rows)
        write_json(self.path, man)
        self.manifest = man
        self._verified[c] = back
        self.problems.pop(c, None)
        self.unchecked.discard(c)
        return True

    # ---------------------------------------------------------------- reading
    def load(self) -> dict[str, np.ndarray]:
        """All verified rows, in instance order (bad chunks are in :attr:`problems`, not here)."""
        parts = [self._verified[c] for c in sorted(self._verified)]
        for c in sorted(self._verified):
            if sorted(self._verified[c]) != sorted(parts[0]):
                raise StoreCorrupt(f"{self.chunk_file(c)} has other columns than the store's first chunk "
                                   f"(computed by another hyqjax version); remove {self.dir} and run the sweep again")
        return {k: np.concatenate([p[k] for p in parts], 0) for k in parts[0]} if parts else {}


def open_store(out_dir: str) -> SweepStore:
    """Open a sweep directory read-only with its stored spec (for reports and analysis)."""
    return SweepStore(out_dir, None)


__all__ = ["StoreBusy", "SweepStore", "default_chunk_size", "open_store"]

