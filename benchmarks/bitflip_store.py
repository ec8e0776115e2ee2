"""Every single-bit flip of one sweep chunk file, through the store's readers and writers, with and without the
manifest: does a changed value ever reach the store, the summary or a report?

Usage: ``PYTHONPATH=. python benchmarks/bitflip_store.py [--stride 1] [--limit N] [--workers 2] [--out flips.json]``
(every bit of the file by default: about 133,000 flips, 25 per second with 2 workers on a loaded 2-core VM;
``--workers`` scales with the cores).

A store of one small chunk (5 instances of a sweep of 18, the sweep's real input columns plus outcome
columns from :func:`hyqjax.studies.sweep.count_outcomes`: 50 columns, about 16 kB of Parquet) is written by
the real chunk writer. Then for every bit ``b`` (every ``--stride``-th) of the chunk file, the bit is flipped
and each path a user has to the data is run on the damaged store, which is restored after each:

* ``reader``: ``SweepStore(DIR, spec)`` with the manifest (what ``hyqjax report`` and ``write_outputs`` read);
* ``writer``: ``SweepStore(..., writer=True)`` with the manifest (what ``hyqjax sweep`` does on a resume);
* ``rebuild``: the writer without ``manifest.json`` (rebuilt from the chunk files, the chunk adopted or not),
  then a reader of the rebuilt store;
* ``verify`` / ``verify_no_manifest``: :func:`hyqjax.studies.sweep.verify_store` with and without the manifest,
  the chunk file read with pyarrow when it is among the verified files (the pandas / DuckDB recipe).

Each outcome is ``named`` (the chunk is reported damaged, left out, recomputed by a writer), ``unchanged`` (the
flip changed nothing that is read: the rows and metadata read are bitwise the original ones) or ``SILENT``
(rows that differ from the original reached a reader: the failure this benchmark looks for); ``refused`` (the
writer stopped with an error naming the directory) and ``crash`` (the process died) are counted too.
The summary and the report are functions of the rows a reader loads, so ``unchanged`` everywhere means they
are unchanged too. Workers run in subprocesses (a crash of pyarrow on a damaged file would be counted, not
stop the scan). JSON (``--out``) with the counts per path and every non-``named`` bit's detail.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import random
import shutil
import subprocess
import sys
import tempfile
import time

SPEC = dict(seed=5, samples=3, grid=dict(height=[0.1, 0.2, 0.3], reflex=[False, True]),
            random=dict(friction=[0.5, 1.0], payload_mass=[0.0, 10.0]))
LAYOUT = dict(platform="cpu", device_kind="cpu", devices=1)
CHUNK = 1  # the flipped chunk: instances 5..9 of 18
PATHS = ("reader", "writer", "rebuild", "verify", "verify_no_manifest")


def rows_of(spec, start, stop):
    """The sweep's input rows plus outcome columns derived from them (what the store keeps does not depend on
    what the columns mean)."""
    import numpy as np

    from hyqjax.studies import sweep

    rows = spec.instance_inputs(start, stop)
    ok = rows["friction"] * (1 + rows["height"]) > 0.8
    out = dict(success=ok, failure_reason=np.where(ok, "", "tilt"), diverged=rows["payload_mass"] > 9.5,
               peak_pitch=np.where(ok, rows["payload_mass"] / 100, np.nan), mean_mobility=rows["friction"] / 2)
    return {**rows, **sweep.count_outcomes(out)}


def build(d):
    """A store in ``d`` with chunk CHUNK only; returns (chunk bytes, manifest bytes)."""
    from hyqjax.studies import sweep

    spec = sweep.SweepSpec.from_dict(SPEC)
    with sweep.SweepStore(d, spec, 5, LAYOUT, writer=True) as st:
        st.write_chunk(CHUNK, rows_of(spec, *st.chunk_range(CHUNK)), 0.1)
    with open(st.chunk_file(CHUNK), "rb") as f, open(os.path.join(d, "manifest.json"), "rb") as g:
        return f.read(), g.read()


def _same(a, b) -> bool:
    return sorted(a) == sorted(b) and all(a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
                                          and a[k].tobytes() == b[k].tobytes() for k in a)


def worker(d: str, bits: list[int]) -> None:
    """Flip each bit of ``bits`` in the store ``d``, print ``bit path outcome`` lines (module docstring)."""
    import contextlib
    import io

    import pyarrow.parquet as pq

    from hyqjax.studies import sweep
    from hyqjax.studies.sweep import chunkfile

    spec = sweep.SweepSpec.from_dict(SPEC)
    chunk_path = os.path.join(d, "chunks", f"{CHUNK:05d}.parquet")
    man_path = os.path.join(d, "manifest.json")
    with open(chunk_path, "rb") as f:
        pristine = f.read()
    with open(man_path, "rb") as f:
        manifest = f.read()
    want = chunkfile.parquet_to_rows(pristine)[0]

    def restore(with_manifest: bool):
        shutil.rmtree(os.path.join(d, "damaged"), ignore_errors=True)
        with open(chunk_path, "wb") as f:
            f.write(pristine)
        if with_manifest:
            with open(man_path, "wb") as f:
                f.write(manifest)
        elif os.path.exists(man_path):
            os.remove(man_path)

    def flip(bit):
        data = bytearray(pristine)
        data[bit // 8] ^= 1 << (bit % 8)
        with open(chunk_path, "wb") as f:
            f.write(bytes(data))

    def loaded(st):
        if CHUNK in st.problems or CHUNK not in st.done():
            return "named"
        return "unchanged" if _same(st.load(), want) else "SILENT"

    def via_verify():
        chk = sweep.verify_store(d)
        if chunk_path not in chk.files:
            return "named"
        rows = chunkfile.table_to_rows(pq.read_table(chunk_path))  # what pandas / DuckDB read
        return "unchanged" if _same(rows, want) else "SILENT"

    quiet = contextlib.redirect_stdout(io.StringIO())
    for bit in bits:
        out = {}
        with quiet:
            restore(True)
            flip(bit)
            out["reader"] = loaded(sweep.SweepStore(d, spec))
            out["verify"] = via_verify()
            try:
                with sweep.SweepStore(d, spec, None, LAYOUT, writer=True) as st:
                    out["writer"] = loaded(st)
            except (sweep.StoreMismatch, sweep.StoreCorrupt):
                out["writer"] = "refused"
            restore(False)
            flip(bit)
            out["verify_no_manifest"] = via_verify()
            try:
                with sweep.SweepStore(d, spec, None, LAYOUT, writer=True) as st:
                    w = loaded(st)
                r = loaded(sweep.SweepStore(d, spec))
                out["rebuild"] = "SILENT" if "SILENT" in (w, r) else r
            except (sweep.StoreMismatch, sweep.StoreCorrupt):
                out["rebuild"] = "refused"
        print(bit, json.dumps(out), flush=True)
    restore(True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--stride", type=int, default=1, help="flip every STRIDE-th bit (1: all of them)")
    p.add_argument("--limit", type=int, default=None,
                   help="stop after this many flips (the bits run in a seeded random order, so any number of them "
                        "is a uniform sample of the file)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", default=None, help="JSON results")
    p.add_argument("--worker", nargs=2, metavar=("DIR", "BITS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        worker(args.worker[0], json.loads(args.worker[1]))
        return 0
    import pyarrow

    root = tempfile.mkdtemp(prefix="hyqjax-bitflip-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None)
    try:
        chunk, _ = build(os.path.join(root, "store0"))
        n_bits = len(chunk) * 8
        bits = list(range(0, n_bits, args.stride))
        random.Random(0).shuffle(bits)  # data pages and footer alike in any prefix
        bits = bits[:args.limit]
        parts = [bits[w::args.workers] for w in range(args.workers)]
        for w in range(1, args.workers):
            shutil.copytree(os.path.join(root, "store0"), os.path.join(root, f"store{w}"))
        counts = {k: {} for k in PATHS}
        detail = []
        t0 = time.time()
        todo = {w: list(parts[w]) for w in range(args.workers)}
        while todo:  # all workers at once, each writing to its own file; a dead worker restarts after its bit
            procs = {}
            for w, rest in todo.items():
                lst, log = (os.path.join(root, f"{n}{w}.json") for n in ("bits", "out"))
                with open(lst, "w") as f:
                    json.dump(rest, f)
                with open(log, "w") as f:
                    procs[w] = subprocess.Popen([sys.executable, __file__, "--worker", os.path.join(root, f"store{w}"),
                                                 "@" + lst], stdout=f)
            for w, proc in procs.items():
                rc = proc.wait()
                done = []
                with open(os.path.join(root, f"out{w}.json")) as f:
                    for line in f:
                        bit, res = line.split(" ", 1)
                        res = json.loads(res)
                        done.append(int(bit))
                        for k, v in res.items():
                            counts[k][v] = counts[k].get(v, 0) + 1
                        if any(v != "named" for v in res.values()):
                            detail.append(dict(bit=int(bit), byte=int(bit) // 8, **res))
                rest = todo[w][len(done):]
                if rc != 0 and rest:  # the process died on rest[0]
                    for k in PATHS:
                        counts[k]["crash"] = counts[k].get("crash", 0) + 1
                    detail.append(dict(bit=rest[0], byte=rest[0] // 8, crash=rc))
                    rest = rest[1:]
                if rest:
                    todo[w] = rest
                else:
                    del todo[w]
        wall = time.time() - t0
    finally:
        shutil.rmtree(root, ignore_errors=True)
    silent = sum(c.get("SILENT", 0) for c in counts.values())
    res = dict(date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
               python=platform.python_version(), pyarrow=pyarrow.__version__, chunk_bytes=len(chunk), bits=len(bits),
               file_bits=n_bits, stride=args.stride, limit=args.limit, workers=args.workers, wall_s=round(wall, 1), counts=counts, silent=silent,
               detail=detail)
    print(f"{len(bits)} single-bit flips of a {len(chunk)}-byte chunk ({n_bits} bits, stride {args.stride}"
          f"{'' if args.limit is None else f', limit {args.limit}'}), {wall:.0f} s")
    print("| path | " + " | ".join(("named", "unchanged", "refused", "crash", "SILENT")) + " |")
    print("|---|---|---|---|---|---|")
    for k in PATHS:
        print(f"| {k} | " + " | ".join(str(counts[k].get(v, 0)) for v in ("named", "unchanged", "refused", "crash",
                                                                          "SILENT")) + " |")
    print(f"silent changes: {silent}")
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    return 1 if silent else 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--worker" and sys.argv[3].startswith("@"):
        with open(sys.argv[3][1:]) as f:
            sys.argv[3] = f.read()
    sys.exit(main())
