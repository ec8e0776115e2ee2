"""``python -m hyqjax.studies.sweep.convert DIR``: convert a ``hyqjax.sweep/1`` store (``.npz`` chunks) in place to
Parquet chunks with hashes (:func:`convert_v1`; rows kept, the store stays read-only). The first format is
:mod:`hyqjax.studies.sweep.legacy`'s, the store it becomes :mod:`hyqjax.studies.sweep.store`'s."""
from __future__ import annotations

import os
import sys

from hyqjax.io.atomic import atomic_write, write_json
from hyqjax.io.lock import DirLock
from hyqjax.studies.sweep.chunkfile import rows_to_parquet
from hyqjax.studies.sweep.legacy import OLD_SCHEMAS
from hyqjax.studies.sweep.manifest import SCHEMA, StoreCorrupt, StoreMismatch
from hyqjax.studies.sweep.store import SweepStore, open_store


def convert_v1(out_dir: str):
    """Convert the v1 store in ``out_dir`` in place to Parquet chunks (under its lock; rows kept, ``.npz``
    files removed). Unreadable chunks are left out and named. Returns the converted (read-only) store."""
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



def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python -m hyqjax.studies.sweep.convert DIR  (converts a hyqjax.sweep/1 store to Parquet)",
              file=sys.stderr)
        return 2
    try:
        convert_v1(argv[0])
    except (StoreMismatch, StoreCorrupt, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
