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
"""
from __future__ import annotations

import datetime
import hashlib
import json
import os

import numpy as np

from hyqjax.io.atomic import atomic_write, clean_temporaries, write_json
from hyqjax.io.lock import Busy, DirLock
from hyqjax.studies.sweep import legacy
from hyqjax.studies.sweep.chunkfile import (CHECKSUM, META_KEY, ChunkDamaged, chunk_size_of, parquet_to_rows,
                                            rows_to_parquet)
from hyqjax.studies.sweep.legacy import OLD_SCHEMAS
from hyqjax.studies.sweep.spec import SpecError, SweepSpec

#: The schema this hyqjax writes (Parquet chunks with content checksums); older ones: :data:`OLD_SCHEMAS`.
SCHEMA = "hyqjax.sweep/2"
MANIFEST = "manifest.json"
DAMAGED_DIR = "damaged"


class StoreMismatch(RuntimeError):
    """The output directory holds a sweep of a different specification, schema, layout or version."""


class StoreCorrupt(RuntimeError):
    """A store file cannot be read (the message names it and what to do)."""


StoreBusy = Busy


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def sha256_bytes(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()


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
        self._scan: dict | None = None
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
        cs = int(chunk_size or self._requested["default_chunk_size"] or default_chunk_size())
        return dict(schema=SCHEMA, spec_hash=self.spec.spec_hash, spec=self.spec.to_dict(),
                    n_instances=self.spec.n_instances, chunk_size=cs, n_chunks=-(-self.spec.n_instances // cs),
                    layout=None if layout is None else dict(layout, chunk_size=cs), chunks={}, created=_now())

    def _read_manifest(self) -> dict | None:
        try:
            with open(self.path, "rb") as f:
                man = json.loads(f.read().decode("utf-8"))
            if not isinstance(man, dict) or not isinstance(man.get("chunks"), dict):
                raise ValueError("not a sweep manifest (no 'chunks' table)")
            return man
        except FileNotFoundError:
            return None
        except (ValueError, UnicodeDecodeError) as e:
            raise StoreCorrupt(f"{self.path} is corrupt ({str(e)[:120]}); run the same `hyqjax sweep` command "
                               f"again to rebuild it from the chunk files, or remove {self.dir}") from None

    def _check(self, man: dict, chunk_size, layout) -> None:
        if man.get("schema") in OLD_SCHEMAS:  # same spec, read as is, never resumed
            why = legacy.v1_refusal(self.dir, man, self.spec.spec_hash, self._writer)
            if why:
                raise StoreMismatch(why)
            return
        if man.get("schema") != SCHEMA:
            raise StoreMismatch(f"{self.path} has schema {man.get('schema')!r}, expected {SCHEMA!r}")
        if man.get("spec_hash") != self.spec.spec_hash:
            raise StoreMismatch(
                f"{self.dir} holds a different sweep (spec hash {str(man.get('spec_hash', '?'))[:12]}, this spec "
                f"{self.spec.spec_hash[:12]}); use another --out directory or remove {self.dir}")
        if self._writer and man.get("converted_from"):
            raise StoreMismatch(legacy.read_only_message(self.dir, man["converted_from"], converted=True))
        if chunk_size is not None and chunk_size != man["chunk_size"]:
            print(f"note: resuming with the stored chunk size {man['chunk_size']} (ignoring {chunk_size})")
        stored = man.get("layout")
        if layout is not None and stored is not None:
            want = dict(layout, chunk_size=man["chunk_size"])
            stored = dict(stored, impl=stored.get("impl", "jax"))  # stores written before impl was recorded
            want.setdefault("impl", "jax")
            keys = ("platform", "device_kind", "devices", "chunk_size", "impl")
            if any(stored.get(k) != want.get(k) for k in keys):
                fmt = lambda lo: (f"{lo.get('devices')} x {lo.get('device_kind')} ({lo.get('platform')}), "  # noqa: E731
                                  f"chunks of {lo.get('chunk_size')}, MJX impl {lo.get('impl')}")
                raise StoreMismatch(
                    f"{self.dir} was computed on {fmt(stored)}; this run has {fmt(want)}. An instance's result "
                    f"depends on the batch each device compiles for, so a store never mixes layouts: resume "
                    f"with the same devices (e.g. CUDA_VISIBLE_DEVICES / --executor), or use another --out")

    def check_resumable(self) -> None:
        """Raise :class:`StoreMismatch` if a writer would be refused here (an old or a converted store)."""
        schema = self.manifest.get("schema")
        if schema in OLD_SCHEMAS or self.manifest.get("converted_from"):
            old = self.manifest.get("converted_from") or schema
            raise StoreMismatch(legacy.read_only_message(self.dir, old, converted=schema not in OLD_SCHEMAS))

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

    def _read_file(self, path: str) -> tuple[bytes | None, dict | None, dict | None, str | None]:
        """``(data, rows, meta, None)`` of the chunk file ``path`` if it reads and its content checksum matches (or
        it has none), else ``(data or None, None, None, reason)``."""
        try:
            with open(path, "rb") as f:
                data = f.read()
        except OSError:
            return None, None, None, f"{path} is missing"
        try:
            rows, meta = parquet_to_rows(data)
        except ChunkDamaged as e:
            return data, None, None, f"{path}: {e}"
        return data, rows, meta, None

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
        """Under the lock: remove dead writers' temporaries, read (or rebuild a missing or corrupt) manifest, check
        it, adopt written-but-unrecorded chunks, re-verify, set damaged chunk files aside, write the manifest."""
        for d in (self.dir, self.chunks_dir):
            for p in clean_temporaries(d, all_writers=True):
                print(f"note: removed {p}, the temporary file of a writer that stopped")
        self._scan = None
        try:
            man, state = self._read_manifest(), None
        except StoreCorrupt:
            man, state = None, "corrupt"
        if man is None:
            state = state or ("missing" if self._scan_files() else None)
            man = self._rebuilt_manifest()
        self._check(man, self._requested["chunk_size"], self._requested["layout"])
        if state == "corrupt":
            bad = f"{self.path}.corrupt-{datetime.datetime.now().strftime('%Y%m%dT%H%M%S')}"
            os.replace(self.path, bad)
            print(f"note: {self.path} was corrupt (kept as {bad}): rebuilding it from the chunk files whose "
                  f"content checksums verify")
        elif state == "missing":
            print(f"note: {self.path} was missing: rebuilding it from the chunk files whose content checksums verify")
        if man.get("layout") is None and self._requested["layout"] is not None:
            man["layout"] = dict(self._requested["layout"], chunk_size=man["chunk_size"])
        self.manifest = man
        os.makedirs(self.chunks_dir, exist_ok=True)
        self._adopt_unlisted(rebuilding=state is not None)
        self._scan = None
        self.verify()
        for c, why in sorted(self.problems.items()):
            moved = self._set_aside(self.chunk_file(c)) if 0 <= c < self.n_chunks else ""
            print(f"note: chunk {c} failed verification ({why}): {moved}recomputed")
            self.manifest["chunks"].pop(str(c), None)
        write_json(self.path, self.manifest)

    def _scan_files(self) -> dict[int, tuple]:
        """``{chunk: (path, data, rows, meta, reason)}`` of the files ``chunks/NNNNN.parquet`` (read once while a
        writer opens the store; ``reason`` None when the file reads and its content checksum matches)."""
        if self._scan is None:
            self._scan = {}
            names = os.listdir(self.chunks_dir) if os.path.isdir(self.chunks_dir) else []
            for name in sorted(names):
                if name.endswith(".parquet") and name[:-8].isdigit():
                    path = os.path.join(self.chunks_dir, name)
                    self._scan[int(name[:-8])] = (path, *self._read_file(path))
        return self._scan

    def _rebuilt_manifest(self) -> dict:
        """A manifest for a directory without a readable one, from the metadata of its chunk files whose content
        checksums verify: refused if they are another sweep's (or any file without a checksum is: an earlier
        hyqjax's chunk of another sweep is not overwritten either); their chunk size and device layout kept, so
        the checks still apply. Damaged files tell nothing here."""
        scan = self._scan_files()
        readable = {c: meta for c, (_, _, _, meta, why) in scan.items() if why is None}
        verified = {c: m for c, m in readable.items() if CHECKSUM in m}
        # an earlier hyqjax's chunk (no checksum) counts when it names a sweep; a file without metadata tells nothing
        named = [m for m in readable.values() if CHECKSUM in m or isinstance(m.get("spec_hash"), str)]
        foreign = sorted({str(m.get("spec_hash")) for m in named} - {self.spec.spec_hash})
        if foreign:
            raise StoreMismatch(f"{self.dir} has no readable {MANIFEST} and its chunk files hold a different sweep "
                                f"(spec hash {foreign[0][:12]}); use another --out directory or remove {self.dir}")
        cs = chunk_size_of(verified, self.spec.n_instances) or self._requested["chunk_size"]
        layout = next((m["layout"] for m in verified.values() if isinstance(m.get("layout"), dict)), None)
        return self._new_manifest(cs, layout or self._requested["layout"])

    def _set_aside(self, path: str) -> str:
        """Move a damaged chunk file out of ``chunks/`` into ``DIR/damaged/`` (so that the chunk table read with
        pandas, polars or DuckDB holds no damaged rows); returns the words for the note."""
        if not os.path.isfile(path):
            return ""
        d = os.path.join(self.dir, DAMAGED_DIR)
        os.makedirs(d, exist_ok=True)
        dst = os.path.join(d, f"{os.path.basename(path)}.{datetime.datetime.now().strftime('%Y%m%dT%H%M%S%f')}")
        os.replace(path, dst)
        return f"moved to {dst}, "

    def _adopt_unlisted(self, rebuilding: bool) -> None:
        """Record chunk files not in the manifest whose content checksum, metadata and row range verify: after a
        writer was killed between the chunk's and the manifest's rename, or (``rebuilding``) when the manifest
        was missing or corrupt. A file that does not verify, or has no content checksum (an earlier hyqjax's,
        whose contents nothing else vouches for here), is named, set aside and recomputed: never adopted."""
        kept = []
        for c, (path, data, rows, meta, why) in sorted(self._scan_files().items()):
            if str(c) in self.manifest["chunks"]:
                continue
            if not 0 <= c < self.n_chunks:
                why = f"{path}: chunk {c} is outside the sweep's {self.n_chunks} chunks of {self.chunk_size}"
            elif why is None and CHECKSUM not in meta:
                why = (f"{path} has no content checksum (written by an earlier hyqjax) and is not in the manifest, "
                       f"so its contents cannot be verified")
            elif why is None:
                why = self._check_rows(c, rows, meta) or self._check_columns(rows)
                why = why and f"{path}: {why}"
            if why:
                print(f"note: {why}: not adopted, {self._set_aside(path)}"
                      + ("the chunk is recomputed" if 0 <= c < self.n_chunks else "not part of the store"))
                continue
            self.manifest["chunks"][str(c)] = self._entry(c, data, wall_s=meta.get("wall_s"), adopted=True)
            self.manifest.setdefault("columns", sorted(rows))
            kept.append(c)
            if not rebuilding:
                print(f"note: {path} was written but not recorded in the manifest (its writer stopped in between): "
                      f"content checksum, metadata and row range verified, kept")
        if rebuilding:
            print(f"note: {self.path} rebuilt with {len(kept)} chunk file(s) whose content checksum, metadata and "
                  f"row range verify")

    def _entry(self, c: int, data: bytes, wall_s=None, worker=None, adopted=False) -> dict:
        start, stop = self.chunk_range(c)
        e = dict(file=os.path.relpath(self.chunk_file(c), self.dir), start=start, stop=stop, rows=stop - start,
                 bytes=len(data), sha256=sha256_bytes(data), wall_s=None if wall_s is None else round(wall_s, 3),
                 finished=_now())
        if worker:
            e["worker"] = worker
        if adopted:
            e["adopted"] = True
        return e

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


__all__ = ["CHECKSUM", "ChunkDamaged", "DAMAGED_DIR", "MANIFEST", "META_KEY", "SCHEMA", "StoreBusy", "StoreCorrupt",
           "StoreMismatch", "SweepStore", "default_chunk_size", "open_store", "parquet_to_rows", "rows_to_parquet"]

