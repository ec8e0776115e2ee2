"""A reader's check of a sweep directory: every chunk file verified, with or without the manifest.

:func:`verify_store` (``hyqjax verify DIR``; ``hyqjax report`` runs it on every sweep it shows) opens the
store read-only and reports, per chunk, whether its rows can be trusted:

* with a readable ``manifest.json``: each recorded chunk as :class:`~hyqjax.studies.sweep.store.SweepStore`
  verifies it (size and SHA-256 against the manifest, content checksum, this sweep's chunk and row range,
  the store's columns), and each file in ``chunks/`` that the manifest does not list (it would be read by
  ``pandas.read_parquet("DIR/chunks")`` or DuckDB all the same): kept by the next run if it verifies, named
  as damaged if it does not or cannot be verified (no content checksum);
* without one (missing or corrupt): each chunk file by its own content checksum, metadata and row range;
  the store is reported damaged (``hyqjax sweep`` with the same spec rebuilds the manifest).

It also says when ``summary.json`` or ``instances.csv`` do not cover the verified rows (an interrupted run
wrote the chunks after them). Nothing is written. :attr:`StoreCheck.files` are the verified chunk files:
the ones to give pandas or DuckDB (``pandas.concat(map(pandas.read_parquet, check.files))``,
``SELECT * FROM read_parquet([...])``).
"""
from __future__ import annotations

import dataclasses
import json
import os

from hyqjax.studies.sweep.chunkfile import CHECKSUM, ChunkDamaged, parquet_to_rows


@dataclasses.dataclass
class StoreCheck:
    """What :func:`verify_store` found in ``dir``."""

    dir: str
    #: "ok", "missing" or "corrupt" (then nothing vouches for the chunks but their own checksums)
    manifest: str
    n_chunks: int | None = None
    #: chunks whose rows are verified (in the store)
    verified: list[int] = dataclasses.field(default_factory=list)
    #: chunk -> why its file cannot be trusted (recorded or not, in ``chunks/``)
    damaged: dict[int, str] = dataclasses.field(default_factory=dict)
    #: verified chunks without a content checksum (an earlier hyqjax's), vouched for by the manifest's SHA-256
    unchecked: list[int] = dataclasses.field(default_factory=list)
    #: chunk files not in the manifest that verify (the next run records them)
    unrecorded: list[int] = dataclasses.field(default_factory=list)
    #: chunks not computed yet (no file)
    missing: list[int] = dataclasses.field(default_factory=list)
    #: verified rows, and remarks (stale summary.json / instances.csv)
    n_rows: int = 0
    notes: list[str] = dataclasses.field(default_factory=list)
    #: the verified chunk files (the ones to read with pandas, polars or DuckDB)
    files: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when the manifest is readable and no chunk file is damaged or unverifiable."""
        return self.manifest == "ok" and not self.damaged

    def lines(self) -> list[str]:
        """The check as text: one line of totals, then one line per damaged chunk and per note."""
        total = "?" if self.n_chunks is None else self.n_chunks
        head = f"{self.dir}: " + ("ok" if self.ok else "DAMAGED") + f": {len(self.verified)} of {total} chunks verified"
        head += f" ({self.n_rows} instances)"
        if self.manifest != "ok":
            head += (f"; manifest.json {self.manifest} (chunks checked by their own content checksums; run the same "
                     f"`hyqjax sweep` command to rebuild it)")
        if self.damaged:
            head += f"; {len(self.damaged)} damaged (left out; the next run recomputes them)"
        if self.unrecorded:
            head += f"; {len(self.unrecorded)} written but not recorded (the next run records them)"
        if self.unchecked:
            head += f"; {len(self.unchecked)} without a content checksum (an earlier hyqjax's), vouched for by the manifest"
        if self.missing:
            head += f"; {len(self.missing)} not computed yet"
        return [head] + [f"  chunk {c}: {why}" for c, why in sorted(self.damaged.items())] + \
            [f"  note: {n}" for n in self.notes]

    def to_dict(self) -> dict:
        return dict(dataclasses.asdict(self), ok=self.ok)


def is_sweep_dir(path: str) -> bool:
    """Whether ``path`` looks like a sweep store (a manifest or a chunks directory)."""
    return os.path.isfile(os.path.join(path, "manifest.json")) or os.path.isdir(os.path.join(path, "chunks"))


def verify_store(out_dir: str) -> StoreCheck:
    """Check the sweep in ``out_dir`` (module docstring); raises :class:`~hyqjax.studies.sweep.manifest.StoreCorrupt`
    if it is no sweep directory, :class:`~hyqjax.studies.sweep.manifest.StoreMismatch` for an unknown schema."""
    from hyqjax.studies.sweep.manifest import MANIFEST, StoreCorrupt
    from hyqjax.studies.sweep.store import open_store

    if not is_sweep_dir(out_dir):
        raise StoreCorrupt(f"{out_dir} holds no sweep (no {MANIFEST}, no chunks/)")
    try:
        st = open_store(out_dir)
    except StoreCorrupt as e:
        state = "missing" if not os.path.exists(os.path.join(out_dir, MANIFEST)) else "corrupt"
        chk = _files_only(out_dir, state)
        if state == "corrupt":
            chk.notes.insert(0, str(e))
        return chk
    chk = StoreCheck(out_dir, "ok", st.n_chunks, verified=sorted(st.done()), damaged=dict(st.problems),
                     unchecked=sorted(st.unchecked))
    listed = {int(k) for k in st.manifest["chunks"]}
    for c, path in _chunk_files(st.chunks_dir).items():
        if c in listed:
            continue
        if not 0 <= c < st.n_chunks:
            chk.damaged[c] = f"{path}: chunk {c} is outside the sweep's {st.n_chunks} chunks"
            continue
        why, rows, meta = _read(path)
        if why is None and CHECKSUM not in meta:
            why = f"{path} is not in the manifest and has no content checksum: its contents cannot be verified"
        elif why is None:
            why = st._check_rows(c, rows, meta) or st._check_columns(rows)
            why = why and f"{path} (not in the manifest): {why}"
        if why:
            chk.damaged[c] = why
        else:
            chk.unrecorded.append(c)
    chk.missing = [c for c in range(st.n_chunks) if c not in listed and c not in chk.unrecorded
                   and c not in chk.damaged]
    chk.files = [st.chunk_file(c) for c in chk.verified]
    chk.n_rows = sum(st.chunk_range(c)[1] - st.chunk_range(c)[0] for c in chk.verified)
    chk.notes += _output_notes(out_dir, st.spec.spec_hash, chk.n_rows)
    return chk


def _chunk_files(chunks_dir: str) -> dict[int, str]:
    names = os.listdir(chunks_dir) if os.path.isdir(chunks_dir) else []
    return {int(n[:-8]): os.path.join(chunks_dir, n) for n in sorted(names) if n.endswith(".parquet")
            and n[:-8].isdigit()}


def _read(path: str) -> tuple[str | None, dict | None, dict | None]:
    try:
        with open(path, "rb") as f:
            rows, meta = parquet_to_rows(f.read())
    except OSError as e:
        return f"{path} is not readable ({e.strerror})", None, None
    except ChunkDamaged as e:
        return f"{path}: {e}", None, None
    return None, rows, meta


def _files_only(out_dir: str, state: str) -> StoreCheck:
    """Without a manifest: each chunk file by its content checksum, and its index column against the row range
    in its (checksummed) metadata."""
    import numpy as np

    chk = StoreCheck(out_dir, state)
    hashes = {}
    for c, path in _chunk_files(os.path.join(out_dir, "chunks")).items():
        why, rows, meta = _read(path)
        if why is None and CHECKSUM not in meta:
            why = f"{path} has no content checksum (an earlier hyqjax's) and the manifest is {state}: unverifiable"
        elif why is None:
            start, stop = meta.get("start"), meta.get("stop")
            if meta.get("chunk") != c or not isinstance(start, int) or not isinstance(stop, int) or \
                    not np.array_equal(rows.get("index"), np.arange(start, stop)):
                why = f"{path}: its metadata or index column is not chunk {c}'s"
        if why:
            chk.damaged[c] = why
            continue
        chk.verified.append(c)
        chk.files.append(path)
        chk.n_rows += len(rows["index"])
        hashes.setdefault(str(meta.get("spec_hash")), []).append(c)
    if len(hashes) > 1:
        chk.notes.append("the chunk files belong to " + ", ".join(f"spec {h[:12]} (chunks {cs})" for h, cs in
                                                                   hashes.items()))
    return chk


def _output_notes(out_dir: str, spec_hash: str, n_rows: int) -> list[str]:
    """Remarks when summary.json or instances.csv do not cover exactly the verified rows."""
    notes = []
    p = os.path.join(out_dir, "summary.json")
    if os.path.isfile(p):
        try:
            with open(p, "rb") as f:
                s = json.loads(f.read().decode("utf-8"))
            n, h = s.get("n_instances"), s.get("spec_hash")
            if h != spec_hash or n != n_rows:
                notes.append(f"{p} covers {n} instances of spec {str(h)[:12]}, the verified chunks {n_rows} of spec "
                             f"{spec_hash[:12]}: it is out of date (run the same `hyqjax sweep` command to rewrite it)")
        except (OSError, ValueError, UnicodeDecodeError, AttributeError):
            notes.append(f"{p} is not readable JSON (run the same `hyqjax sweep` command to rewrite it)")
    p = os.path.join(out_dir, "instances.csv")
    if os.path.isfile(p):
        with open(p, "rb") as f:
            n = max(sum(1 for line in f if line.strip()) - 1, 0)
        if n != n_rows:
            notes.append(f"{p} has {n} rows, the verified chunks {n_rows}: it is out of date (run the same "
                         f"`hyqjax sweep` command to rewrite it)")
    return notes


__all__ = ["StoreCheck", "is_sweep_dir", "verify_store"]
