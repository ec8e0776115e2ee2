"""``python -m hyqjax.studies.sweep.convert DIR``: convert a ``hyqjax.sweep/1`` store (``.npz`` chunks) in place to
Parquet chunks with hashes (:func:`hyqjax.studies.sweep.legacy.convert_v1`; rows kept, the store stays read-only)."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python -m hyqjax.studies.sweep.convert DIR  (converts a hyqjax.sweep/1 store to Parquet)",
              file=sys.stderr)
        return 2
    from hyqjax.studies.sweep.legacy import convert_v1
    from hyqjax.studies.sweep.store import StoreCorrupt, StoreMismatch

    try:
        convert_v1(argv[0])
    except (StoreMismatch, StoreCorrupt, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
