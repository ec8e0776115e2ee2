"""Verify sweep stores: the manifest, every chunk file's content checksum, metadata and row range.

DIR is a sweep's --out directory or a directory holding several (searched three levels deep). For each
store one line of totals (chunks verified, damaged, not recorded, not computed yet), then one line per
damaged chunk with what is wrong and a note when summary.json or instances.csv are out of date. A
damaged chunk is left out of every summary and recomputed by the next `hyqjax sweep` with the same
spec. --files prints the verified chunk files, the ones to read with pandas, polars or DuckDB
(docs/sweeps.md). Nothing is written. Exit status 0 when every store verifies, 1 when a chunk is
damaged or unverifiable or a manifest is missing or corrupt.
"""
from __future__ import annotations

import argparse
import os
import sys

NAME = "verify"
HELP = "check sweep stores (manifest, chunk content checksums) and name damaged chunks"
ORDER = 75

DAMAGED_EXIT = 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", help="a sweep's --out directory, or a directory holding several")
    p.add_argument("--files", action="store_true", help="also print the verified chunk files, one per line")
    p.add_argument("--json", action="store_true", help="print the checks as JSON instead")


def find_stores(root: str, max_depth: int = 3) -> list[str]:
    """``root`` and its subdirectories down to ``max_depth`` that look like sweep stores (manifest or chunks/)."""
    from hyqjax.studies.sweep.verify import is_sweep_dir

    found = []
    root = os.path.abspath(root)
    for dirpath, dirnames, _ in os.walk(root):
        depth = os.path.relpath(dirpath, root).count(os.sep) + (dirpath != root)
        if is_sweep_dir(dirpath):
            found.append(dirpath)
            dirnames[:] = []
        elif depth >= max_depth:
            dirnames[:] = []
        dirnames.sort()
    return sorted(found)


def validate(args) -> None:
    if not os.path.isdir(args.dir):
        raise ValueError(f"DIR {args.dir} is not a directory (give a sweep's --out directory)")
    if not find_stores(args.dir):
        raise ValueError(f"DIR {args.dir}: no sweep store (manifest.json or chunks/) in it or its subdirectories")
    args.options_checked = True


def check_dirs(dirs) -> dict:
    """``{dir: StoreCheck}`` of the directories among ``dirs`` that are sweep stores."""
    from hyqjax.studies.sweep.verify import is_sweep_dir, verify_store

    return {d: verify_store(d) for d in dirs if is_sweep_dir(d)}


def tell(checks: dict, prog: str = "hyqjax verify") -> int:
    """Print every damaged store's lines (and out-of-date notes) to stderr; :data:`DAMAGED_EXIT` if any is damaged."""
    for chk in checks.values():
        if not chk.ok or chk.notes:
            for line in chk.lines():
                print(f"{prog}: {line.strip()}", file=sys.stderr)
    return DAMAGED_EXIT if any(not c.ok for c in checks.values()) else 0


def sweep_source_problem(source: str) -> str | None:
    """For ``render`` / ``view``: a message when SOURCE is a sweep store (which records no trajectories), naming its
    damaged chunks, else None."""
    from hyqjax.studies.sweep.verify import is_sweep_dir, verify_store

    d = source if os.path.isdir(source) else os.path.dirname(os.path.abspath(source))
    if not is_sweep_dir(d) or os.path.isfile(os.path.join(d, "traces.npz")):
        return None
    chk = verify_store(d)
    state = "verified" if chk.ok else (f"DAMAGED: chunks {sorted(chk.damaged)} (`hyqjax verify {source}` names "
                                       f"them)" if chk.damaged else f"manifest.json {chk.manifest}")
    return (f"SOURCE {source} is a sweep store ({len(chk.verified)} chunks, {state}), and sweeps record no "
            f"trajectories: render a step-down run of the instance instead (hyqjax stepdown --out DIR, its "
            f"inputs from instances.csv)")


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    checks = check_dirs(find_stores(args.dir))
    if args.json:
        import json

        print(json.dumps({d: c.to_dict() for d, c in checks.items()}, indent=1))
    else:
        for chk in checks.values():
            print("\n".join(chk.lines()))
            if args.files:
                print("\n".join(chk.files))
    return DAMAGED_EXIT if any(not c.ok for c in checks.values()) else 0
