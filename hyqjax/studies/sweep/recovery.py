"""What a writer does when it opens a sweep store (under the lock), so that a killed writer leaves nothing wrong.

:func:`repair` removes dead writers' temporaries; rebuilds a missing or corrupt manifest from the chunk files
whose content checksums verify (keeping their chunk size and device layout, refusing chunk files of another
sweep; a corrupt manifest is kept beside it as ``manifest.json.corrupt-TIME``); adopts a chunk file written but
not yet recorded once its content checksum, metadata and row range check out; and moves every chunk file that
fails verification to ``DIR/damaged/`` (:func:`set_aside`), so that ``DIR/chunks`` read with pandas, polars or
DuckDB holds no damaged rows, to be recomputed. The store it repairs is
:class:`hyqjax.studies.sweep.store.SweepStore` (see its module docstring for the guarantees).
"""
from __future__ import annotations

import datetime
import os

from hyqjax.io.atomic import clean_temporaries, write_json
from hyqjax.studies.sweep.chunkfile import CHECKSUM, ChunkDamaged, chunk_size_of, parquet_to_rows
from hyqjax.studies.sweep.manifest import MANIFEST, StoreCorrupt, StoreMismatch, check_manifest, read_manifest

DAMAGED_DIR = "damaged"


def read_chunk_file(path: str) -> tuple[bytes | None, dict | None, dict | None, str | None]:
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


def scan_chunk_files(chunks_dir: str) -> dict[int, tuple]:
    """``{chunk: (path, data, rows, meta, reason)}`` of the files ``chunks/NNNNN.parquet`` (``reason`` None when
    the file reads and its content checksum matches)."""
    scan = {}
    names = os.listdir(chunks_dir) if os.path.isdir(chunks_dir) else []
    for name in sorted(names):
        if name.endswith(".parquet") and name[:-8].isdigit():
            path = os.path.join(chunks_dir, name)
            scan[int(name[:-8])] = (path, *read_chunk_file(path))
    return scan


def set_aside(out_dir: str, path: str) -> str:
    """Move a damaged chunk file out of ``chunks/`` into ``DIR/damaged/`` (so that the chunk table read with
    pandas, polars or DuckDB holds no damaged rows); returns the words for the note."""
    if not os.path.isfile(path):
        return ""
    d = os.path.join(out_dir, DAMAGED_DIR)
    os.makedirs(d, exist_ok=True)
    dst = os.path.join(d, f"{os.path.basename(path)}.{datetime.datetime.now().strftime('%Y%m%dT%H%M%S%f')}")
    os.replace(path, dst)
    return f"moved to {dst}, "


def repair(store) -> None:
    """Under the writer's lock: remove dead writers' temporaries, read (or rebuild a missing or corrupt) manifest,
    check it, adopt written-but-unrecorded chunks, re-verify, set damaged chunk files aside, write the manifest."""
    for d in (store.dir, store.chunks_dir):
        for p in clean_temporaries(d, all_writers=True):
            print(f"note: removed {p}, the temporary file of a writer that stopped")
    scan = scan_chunk_files(store.chunks_dir)  # read once: the rebuild and the adoption both look at it
    try:
        man, state = read_manifest(store.dir), None
    except StoreCorrupt:
        man, state = None, "corrupt"
    if man is None:
        state = state or ("missing" if scan else None)
        man = _rebuilt_manifest(store, scan)
    requested = store._requested
    check_manifest(man, store.dir, store.spec.spec_hash, True, requested["chunk_size"], requested["layout"])
    if state == "corrupt":
        bad = f"{store.path}.corrupt-{datetime.datetime.now().strftime('%Y%m%dT%H%M%S')}"
        os.replace(store.path, bad)
        print(f"note: {store.path} was corrupt (kept as {bad}): rebuilding it from the chunk files whose "
              f"content checksums verify")
    elif state == "missing":
        print(f"note: {store.path} was missing: rebuilding it from the chunk files whose content checksums verify")
    if man.get("layout") is None and requested["layout"] is not None:
        man["layout"] = dict(requested["layout"], chunk_size=man["chunk_size"])
    store.manifest = man
    os.makedirs(store.chunks_dir, exist_ok=True)
    _adopt_unlisted(store, scan, rebuilding=state is not None)
    store.verify()
    for c, why in sorted(store.problems.items()):
        moved = set_aside(store.dir, store.chunk_file(c)) if 0 <= c < store.n_chunks else ""
        print(f"note: chunk {c} failed verification ({why}): {moved}recomputed")
        store.manifest["chunks"].pop(str(c), None)
    write_json(store.path, store.manifest)


def _rebuilt_manifest(store, scan: dict[int, tuple]) -> dict:
    """A manifest for a directory without a readable one, from the metadata of its chunk files whose content
    checksums verify: refused if they are another sweep's (or any file without a checksum is: an earlier
    hyqjax's chunk of another sweep is not overwritten either); their chunk size and device layout kept, so
    the checks still apply. Damaged files tell nothing here."""
    readable = {c: meta for c, (_, _, _, meta, why) in scan.items() if why is None}
    verified = {c: m for c, m in readable.items() if CHECKSUM in m}
    # an earlier hyqjax's chunk (no checksum) counts when it names a sweep; a file without metadata tells nothing
    named = [m for m in readable.values() if CHECKSUM in m or isinstance(m.get("spec_hash"), str)]
    foreign = sorted({str(m.get("spec_hash")) for m in named} - {store.spec.spec_hash})
    if foreign:
        raise StoreMismatch(f"{store.dir} has no readable {MANIFEST} and its chunk files hold a different sweep "
                            f"(spec hash {foreign[0][:12]}); use another --out directory or remove {store.dir}")
    cs = chunk_size_of(verified, store.spec.n_instances) or store._requested["chunk_size"]
    layout = next((m["layout"] for m in verified.values() if isinstance(m.get("layout"), dict)), None)
    return store._new_manifest(cs, layout or store._requested["layout"])


def _adopt_unlisted(store, scan: dict[int, tuple], rebuilding: bool) -> None:
    """Record chunk files not in the manifest whose content checksum, metadata and row range verify: after a
    writer was killed between the chunk's and the manifest's rename, or (``rebuilding``) when the manifest
    was missing or corrupt. A file that does not verify, or has no content checksum (an earlier hyqjax's,
    whose contents nothing else vouches for here), is named, set aside and recomputed: never adopted."""
    kept = []
    for c, (path, data, rows, meta, why) in sorted(scan.items()):
        if str(c) in store.manifest["chunks"]:
            continue
        if not 0 <= c < store.n_chunks:
            why = f"{path}: chunk {c} is outside the sweep's {store.n_chunks} chunks of {store.chunk_size}"
        elif why is None and CHECKSUM not in meta:
            why = (f"{path} has no content checksum (written by an earlier hyqjax) and is not in the manifest, "
                   f"so its contents cannot be verified")
        elif why is None:
            why = store._check_rows(c, rows, meta) or store._check_columns(rows)
            why = why and f"{path}: {why}"
        if why:
            print(f"note: {why}: not adopted, {set_aside(store.dir, path)}"
                  + ("the chunk is recomputed" if 0 <= c < store.n_chunks else "not part of the store"))
            continue
        store.manifest["chunks"][str(c)] = store._entry(c, data, wall_s=meta.get("wall_s"), adopted=True)
        store.manifest.setdefault("columns", sorted(rows))
        kept.append(c)
        if not rebuilding:
            print(f"note: {path} was written but not recorded in the manifest (its writer stopped in between): "
                  f"content checksum, metadata and row range verified, kept")
    if rebuilding:
        print(f"note: {store.path} rebuilt with {len(kept)} chunk file(s) whose content checksum, metadata and "
              f"row range verify")
