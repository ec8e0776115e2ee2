"""The sweep store's guarantees, without simulating: lock, verification, repair, conversion, kills, two writers.

The rows written here are the sweep's real input rows (``SweepSpec.instance_inputs``) plus an outcome
column derived from them by :func:`inputs_outcome`; what is tested is the store's bookkeeping, which
does not look at what the columns mean. The end-to-end runs with MJX are in test_sweep.py.
"""
from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from hyqjax.io.lock import Busy, DirLock
from hyqjax.studies import sweep

SPEC = dict(seed=5, samples=3, grid=dict(height=[0.1, 0.2, 0.3], reflex=[False, True]),
            random=dict(friction=[0.5, 1.0], payload_mass=[0.0, 10.0]))
LAYOUT = dict(platform="cpu", device_kind="cpu", devices=1)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def inputs_outcome(spec, start, stop):
    rows = spec.instance_inputs(start, stop)
    ok = rows["friction"] * (1 + rows["height"]) > 0.8
    out = dict(success=ok, failure_reason=np.where(ok, "", "tilt"), diverged=rows["payload_mass"] > 9.5,
               peak_pitch=np.where(ok, rows["payload_mass"] / 100, np.nan), mean_mobility=rows["friction"] / 2)
    return {**rows, **sweep.count_outcomes(out)}


def fill(out, spec, chunk_size=5, chunks=None):
    with sweep.SweepStore(str(out), spec, chunk_size, LAYOUT, writer=True) as st:
        for c in (st.todo() if chunks is None else chunks):
            st.write_chunk(c, inputs_outcome(spec, *st.chunk_range(c)), 0.1)
    return st


def same_rows(a, b):
    assert sorted(a) == sorted(b)
    for k in a:
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert (a[k] == b[k]).all(), k


@pytest.fixture
def spec():
    return sweep.SweepSpec.from_dict(SPEC)


def test_parquet_chunks_open_as_one_table_and_round_trip(tmp_path, spec):
    import pyarrow.dataset as ds

    st = fill(tmp_path, spec)
    assert st.n_chunks == 4 and st.done() == {0, 1, 2, 3}
    table = ds.dataset(str(tmp_path / "chunks"), format="parquet").to_table().sort_by("index")
    assert table.num_rows == spec.n_instances == 18
    assert table.column("index").to_pylist() == list(range(18))
    rows = sweep.SweepStore(str(tmp_path), spec).load()
    same_rows(rows, inputs_outcome(spec, 0, 18))
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["schema"] == sweep.SCHEMA and man["layout"] == dict(LAYOUT, chunk_size=5)
    assert [man["chunks"][str(c)]["start"] for c in range(4)] == [0, 5, 10, 15]
    assert all(len(e["sha256"]) == 64 for e in man["chunks"].values())


def test_second_writer_refused_or_waits(tmp_path, spec):
    st = sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True)
    with pytest.raises(Busy, match=f"pid {os.getpid()}.*--wait"):
        sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True)
    got = {}

    def second():
        with sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True, wait=True) as s2:
            got["done"] = s2.done()

    th = threading.Thread(target=second)
    th.start()
    time.sleep(0.5)
    assert "done" not in got  # still waiting
    st.write_chunk(0, inputs_outcome(spec, *st.chunk_range(0)), 0.1)
    st.close()
    th.join(10)
    assert got["done"] == {0}


def test_chunk_lands_once(tmp_path, spec):
    with sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True) as st:
        rows = inputs_outcome(spec, *st.chunk_range(1))
        assert st.write_chunk(1, rows, 0.1) is True
        sha = st.manifest["chunks"]["1"]["sha256"]
        assert st.write_chunk(1, rows, 0.1) is False
        assert st.manifest["chunks"]["1"]["sha256"] == sha
        with pytest.raises(ValueError, match="row range"):
            st.write_chunk(2, rows, 0.1)  # rows of chunk 1 offered as chunk 2


def test_corrupt_truncated_and_foreign_chunks_named_and_recomputed(tmp_path, spec):
    fill(tmp_path, spec)
    ch = tmp_path / "chunks"
    (ch / "00001.parquet").write_bytes((ch / "00001.parquet").read_bytes()[:200])  # truncated
    (ch / "00002.parquet").write_bytes((ch / "00000.parquet").read_bytes())  # a copy of another chunk
    other = sweep.SweepSpec.from_dict({**SPEC, "seed": 6})
    fill(tmp_path / "o", other)
    (ch / "00003.parquet").write_bytes((tmp_path / "o" / "chunks" / "00003.parquet").read_bytes())  # other sweep
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert set(ro.problems) == {1, 2, 3}
    assert "00001.parquet" in ro.problems[1] and "00002.parquet" in ro.problems[2]
    assert ro.load()["index"].tolist() == list(range(5))  # only the verified chunk
    st = fill(tmp_path, spec)
    assert st.problems == {} and st.done() == {0, 1, 2, 3}
    same_rows(sweep.SweepStore(str(tmp_path), spec).load(), inputs_outcome(spec, 0, 18))


def test_foreign_chunk_with_matching_hash_still_refused(tmp_path, spec):
    """A chunk file and its manifest entry both copied from another chunk: the embedded metadata and the
    row range give it away."""
    fill(tmp_path, spec)
    man = json.loads((tmp_path / "manifest.json").read_text())
    (tmp_path / "chunks" / "00002.parquet").write_bytes((tmp_path / "chunks" / "00001.parquet").read_bytes())
    man["chunks"]["2"].update({k: man["chunks"]["1"][k] for k in ("sha256", "bytes")})
    (tmp_path / "manifest.json").write_text(json.dumps(man))
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert set(ro.problems) == {2} and "chunk" in ro.problems[2]


def test_stale_temporaries_removed_and_unrecorded_chunk_adopted(tmp_path, spec):
    fill(tmp_path, spec, chunks=[0])
    (tmp_path / "chunks" / ".00001.parquet.tmp-999999-abcd").write_bytes(b"partial")
    (tmp_path / ".manifest.json.tmp-999999-abcd").write_bytes(b"{")
    # Chunk 2 written, the writer killed before the manifest's rename.
    data = sweep.rows_to_parquet(inputs_outcome(spec, 10, 15), dict(
        schema=sweep.SCHEMA, spec_hash=spec.spec_hash, chunk=2, start=10, stop=15))
    (tmp_path / "chunks" / "00002.parquet").write_bytes(data)
    st = sweep.SweepStore(str(tmp_path), spec, None, LAYOUT, writer=True)
    st.close()
    assert st.done() == {0, 2}
    assert not [f for d in (tmp_path, tmp_path / "chunks") for f in os.listdir(d) if ".tmp" in f]


def test_corrupt_manifest_named_then_rebuilt(tmp_path, spec):
    fill(tmp_path, spec)
    (tmp_path / "manifest.json").write_text('{"schema": "hyqjax.sweep/2", "chunks": {')
    with pytest.raises(sweep.StoreCorrupt, match="manifest.json is corrupt"):
        sweep.SweepStore(str(tmp_path), spec)
    st = sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True)
    st.close()
    assert st.done() == {0, 1, 2, 3}
    assert [f for f in os.listdir(tmp_path) if f.startswith("manifest.json.corrupt-")]


def test_lost_manifest_rebuilt_with_the_files_chunk_size_and_layout_other_sweep_refused(tmp_path, spec):
    """Without a readable manifest a writer rebuilds it from the chunk files' metadata: their chunk size and
    layout are kept (a resume with another layout is still refused), and chunk files of another sweep make
    it refuse the directory instead of overwriting them."""
    fill(tmp_path, spec, chunk_size=4, chunks=[0, 2])
    chunk_files = _files(tmp_path / "chunks")
    (tmp_path / "manifest.json").write_text("{")  # corrupt
    with pytest.raises(sweep.StoreMismatch, match="1 x cpu.*2 x cpu"):
        sweep.SweepStore(str(tmp_path), spec, None, dict(LAYOUT, devices=2), writer=True)
    assert (tmp_path / "manifest.json").read_text() == "{"  # refused: nothing moved or rewritten
    os.remove(tmp_path / "manifest.json")  # lost
    with sweep.SweepStore(str(tmp_path), spec, None, LAYOUT, writer=True, default_chunk_size=32) as st:
        assert st.chunk_size == 4 and st.done() == {0, 2} and st.layout == dict(LAYOUT, chunk_size=4)
    assert _files(tmp_path / "chunks") == chunk_files
    other = sweep.SweepSpec.from_dict({**SPEC, "seed": 6})
    (tmp_path / "manifest.json").write_text("not json")
    with pytest.raises(sweep.StoreMismatch, match="chunk files hold a different sweep"):
        sweep.SweepStore(str(tmp_path), other, 4, LAYOUT, writer=True)
    assert _files(tmp_path / "chunks") == chunk_files and (tmp_path / "manifest.json").read_text() == "not json"


def test_layout_recorded_and_other_layout_refused(tmp_path, spec):
    fill(tmp_path, spec, chunks=[0])
    with pytest.raises(sweep.StoreMismatch, match="1 x cpu.*2 x cpu"):
        sweep.SweepStore(str(tmp_path), spec, None, dict(LAYOUT, devices=2), writer=True)
    assert not os.path.exists(tmp_path / ".lock") or DirLock(str(tmp_path)).acquire().release() is None


def test_store_of_another_start_pose_read_but_never_resumed(tmp_path, spec):
    """A store written before the step-down's start pose was recorded (``hip-line``: a heading could put a front foot
    over the edge) reads as it is; a writer is refused in one message naming both poses."""
    from hyqjax.studies.stepdown import START_POSE

    fill(tmp_path / "s", spec, chunks=[0])
    path = tmp_path / "s" / "manifest.json"
    man = json.loads(path.read_text())
    assert man["start_pose"] == START_POSE == "leading-foot"
    del man["start_pose"]
    path.write_text(json.dumps(man))
    with sweep.SweepStore(str(tmp_path / "s"), spec) as st:
        assert len(st.load()["index"]) == 5
    with pytest.raises(sweep.StoreMismatch, match="'hip-line' start pose .* 'leading-foot'"):
        sweep.SweepStore(str(tmp_path / "s"), spec, 5, LAYOUT, writer=True)


def test_strict_json_summary(tmp_path, spec):
    st = fill(tmp_path, spec)
    s = sweep.write_outputs(st)
    text = (tmp_path / "summary.json").read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in summary.json"))
    assert s["complete"] and "NaN" not in text


def _v1_store(path, spec, chunks=(0, 1)):
    """A store of the first format (.npz chunks, no hashes), as the earlier hyqjax wrote it."""
    os.makedirs(path / "chunks")
    man = dict(schema="hyqjax.sweep/1", spec_hash=spec.spec_hash, spec=spec.to_dict(), n_instances=spec.n_instances,
               chunk_size=5, n_chunks=-(-spec.n_instances // 5), chunks={})
    for c in chunks:
        rows = inputs_outcome(spec, c * 5, min(c * 5 + 5, spec.n_instances))
        np.savez(path / "chunks" / f"{c:05d}.npz", **rows)
        man["chunks"][str(c)] = dict(file=f"chunks/{c:05d}.npz", start=c * 5, stop=c * 5 + 5, wall_s=1.0)
        man["columns"] = sorted(rows)
    (path / "manifest.json").write_text(json.dumps(man))


def _files(path):
    out = {}
    for d, _, fs in os.walk(path):
        for f in fs:
            if f != ".lock":
                with open(os.path.join(d, f), "rb") as fh:
                    out[os.path.relpath(os.path.join(d, f), path)] = fh.read()
    return out


def test_schema_1_store_read_as_is_never_resumed_converted_on_request(tmp_path, spec, capsys):
    """A store of the first format is read as it is; a writer is refused with how to convert it (its rows are an
    earlier version's outcomes, so adding this version's rows would mix them); the conversion keeps every row
    and gives a Parquet table, read-only as well."""
    _v1_store(tmp_path, spec)
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert ro.done() == {0, 1} and ro.problems == {}
    same_rows(ro.load(), inputs_outcome(spec, 0, 10))
    before = _files(tmp_path)
    for attempt in (lambda: sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True), ro.check_resumable):
        with pytest.raises(sweep.StoreMismatch, match="hyqjax.sweep/1.*python -m hyqjax.studies.sweep.convert"):
            attempt()
    assert _files(tmp_path) == before  # nothing converted or written by the refused writer
    # A first-format store of another spec is another sweep, for readers too.
    with pytest.raises(sweep.StoreMismatch, match="different sweep"):
        sweep.SweepStore(str(tmp_path), sweep.SweepSpec.from_dict({**SPEC, "seed": 6}))

    st = sweep.convert_v1(str(tmp_path))
    assert "converted" in capsys.readouterr().out
    assert sorted(os.listdir(tmp_path / "chunks")) == ["00000.parquet", "00001.parquet"]
    assert st.done() == {0, 1} and st.problems == {}
    same_rows(sweep.open_store(str(tmp_path)).load(), inputs_outcome(spec, 0, 10))
    import pyarrow.dataset as ds

    table = ds.dataset(str(tmp_path / "chunks"), format="parquet").to_table().sort_by("index")
    assert table.column("index").to_pylist() == list(range(10))
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["schema"] == sweep.SCHEMA and man["converted_from"] == "hyqjax.sweep/1"
    with pytest.raises(sweep.StoreMismatch, match="converted from schema hyqjax.sweep/1"):
        sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True)
    from hyqjax.studies.sweep import convert

    capsys.readouterr()
    assert convert.main([str(tmp_path)]) == 2 and "nothing to convert" in capsys.readouterr().err
    assert convert.main([]) == 2 and "usage" in capsys.readouterr().err


def test_damaged_schema_1_chunk_named(tmp_path, spec):
    _v1_store(tmp_path, spec)
    (tmp_path / "chunks" / "00001.npz").write_bytes(b"PK\x03\x04 truncated")
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert ro.done() == {0} and "00001.npz is not readable" in ro.problems[1]


def test_rows_of_another_version_refused_and_such_a_chunk_named(tmp_path, spec):
    """The manifest lists the columns; rows or a chunk file with other columns (computed by another hyqjax
    version) are refused, so a store never mixes two versions' outcomes."""
    fill(tmp_path, spec, chunks=[0, 1])
    with sweep.SweepStore(str(tmp_path), spec, None, LAYOUT, writer=True) as st:
        rows = {**inputs_outcome(spec, *st.chunk_range(2)), "completed": np.ones(5, bool)}
        with pytest.raises(sweep.StoreMismatch, match=r"chunk 2 .*extra \['completed'\]"):
            st.write_chunk(2, rows, 0.1)
        assert not os.path.exists(st.chunk_file(2))
        # A chunk file of another version, recorded with its true hash: named by verification.
        rows = {k: v for k, v in inputs_outcome(spec, *st.chunk_range(1)).items() if k != "mean_mobility"}
        data = sweep.rows_to_parquet(rows, st._meta(1))
        (tmp_path / "chunks" / "00001.parquet").write_bytes(data)
        man = json.loads((tmp_path / "manifest.json").read_text())
        man["chunks"]["1"].update(st._entry(1, data))
        (tmp_path / "manifest.json").write_text(json.dumps(man))
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert set(ro.problems) == {1} and "missing ['mean_mobility']" in ro.problems[1]
    assert ro.load()["index"].tolist() == list(range(5))


# ------------------------------------------------------------------------------------------------
# Content checksums: damage caught with or without the manifest; readers that say what is damaged
# ------------------------------------------------------------------------------------------------

def _flip(data: bytes, bit: int) -> bytes:
    d = bytearray(data)
    d[bit // 8] ^= 1 << (bit % 8)
    return bytes(d)


def _same_bits(a, b) -> bool:
    return sorted(a) == sorted(b) and all(a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes() for k in a)


def _without_checksum(rows, meta) -> bytes:
    """A chunk file as hyqjax wrote it before chunks carried a content checksum."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from hyqjax.studies.sweep import chunkfile

    table = pa.table({k: pa.array(v.astype(str).tolist()) if v.dtype.kind in "US" else
                      (pa.ListArray.from_arrays(pa.array(np.arange(len(v) + 1, dtype=np.int32) * v.shape[1]),
                                                pa.array(v.reshape(-1))) if v.ndim == 2 else pa.array(v))
                      for k, v in rows.items()})
    table = table.replace_schema_metadata({chunkfile.META_KEY: json.dumps(meta).encode()})
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


def test_bit_flips_never_reach_the_store_with_or_without_the_manifest(tmp_path, spec, capsys):
    """Single-bit flips of one chunk file (benchmarks/bitflip_store.py flips every bit): with the manifest a
    reader names the chunk; without it the rebuilding writer adopts the file only when what it reads is bitwise
    the original, so no changed value reaches the store (and hence the summary or a report). The sample holds
    flips that Parquet still reads with other values, which only the content checksum catches."""
    from hyqjax.studies.sweep import chunkfile

    fill(tmp_path, spec, chunks=[1])
    path = tmp_path / "chunks" / "00001.parquet"
    pristine, manifest = path.read_bytes(), (tmp_path / "manifest.json").read_bytes()
    want = sweep.SweepStore(str(tmp_path), spec).load()
    rng = random.Random(3)
    kinds: dict[str, list[int]] = {"checksum": [], "unreadable": [], "unchanged": []}
    for bit in rng.sample(range(len(pristine) * 8), 250):  # classified by the chunk reader alone (fast)
        try:
            chunkfile.parquet_to_rows(_flip(pristine, bit))
            kind = "unchanged"
        except chunkfile.ChunkDamaged as e:
            kind = "checksum" if "checksum" in str(e) else "unreadable"
        kinds[kind].append(bit)
    assert kinds["checksum"], "no flip in the sample parses with other values: the sample misses the point"
    bits = kinds["checksum"][:6] + kinds["unreadable"][:4] + kinds["unchanged"][:4]
    for bit in bits:
        path.write_bytes(_flip(pristine, bit))
        (tmp_path / "manifest.json").write_bytes(manifest)
        ro = sweep.SweepStore(str(tmp_path), spec)
        assert 1 in ro.problems and ro.load() == {}, bit  # with the manifest: named, nothing read
        chk = sweep.verify_store(str(tmp_path))
        assert not chk.ok and 1 in chk.damaged and not chk.files, bit
        os.remove(tmp_path / "manifest.json")
        with sweep.SweepStore(str(tmp_path), spec, None, LAYOUT, writer=True) as st:
            adopted = 1 in st.done()
        rows = sweep.SweepStore(str(tmp_path), spec).load()
        if adopted:
            assert bit in kinds["unchanged"] and _same_bits(rows, want), bit
        else:
            assert rows == {} and not path.exists() and os.listdir(tmp_path / "damaged"), bit  # set aside
            shutil.rmtree(tmp_path / "damaged")
    out = capsys.readouterr().out
    assert "not adopted" in out and "writer stopped" not in out


def test_written_chunk_carries_a_checksum_that_covers_rows_and_metadata(spec):
    from hyqjax.studies.sweep import chunkfile

    rows = inputs_outcome(spec, 0, 5)
    meta = dict(schema=sweep.SCHEMA, spec_hash=spec.spec_hash, chunk=0, start=0, stop=5, wall_s=1.5)
    back, m = chunkfile.parquet_to_rows(chunkfile.rows_to_parquet(rows, meta))
    assert len(m[chunkfile.CHECKSUM]) == 64 and {k: v for k, v in m.items() if k != chunkfile.CHECKSUM} == meta
    same_rows(back, rows)
    import pyarrow as pa

    table, _ = chunkfile.read_table(chunkfile.rows_to_parquet(rows, meta))
    assert chunkfile.content_sha256(table, m) == m[chunkfile.CHECKSUM]
    assert chunkfile.content_sha256(table, dict(m, wall_s=1.6)) != m[chunkfile.CHECKSUM]  # metadata covered
    t2 = table.set_column(table.column_names.index("peak_pitch"), "peak_pitch",
                          pa.array(np.nextafter(rows["peak_pitch"], 1.0)))
    assert chunkfile.content_sha256(t2, m) != m[chunkfile.CHECKSUM]  # one ulp of one column


CHUNK_THREADS = textwrap.dedent("""
    import os, sys
    sys.path.insert(0, {root!r})
    import numpy as np
    from hyqjax.studies.sweep import chunkfile
    data = chunkfile.rows_to_parquet(dict(x=np.arange(500.0), h=np.ones((500, 3)), s=np.array(["ok"] * 500)),
                                     dict(chunk=0))
    before = len(os.listdir("/proc/self/task"))
    for _ in range(20):
        chunkfile.parquet_to_rows(chunkfile.rows_to_parquet(*chunkfile.parquet_to_rows(data)))
    print(before, len(os.listdir("/proc/self/task")))
""")


@pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="counts threads through Linux's /proc")
def test_chunk_io_starts_no_native_threads():
    """Reading and writing chunks stays on the calling thread: Arrow's thread pool, once started, can abort the
    interpreter at exit (SIGABRT, "terminate called without an active exception"), which turned a writer's
    one-line refusal into exit code -6 about once in ten runs."""
    out = subprocess.run([sys.executable, "-c", CHUNK_THREADS.format(root=ROOT)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    before, after = map(int, out.stdout.split())
    assert after == before

def test_chunks_without_a_checksum_trusted_only_through_the_manifest(tmp_path, spec, capsys):
    """Policy for chunk files of an earlier hyqjax (no content checksum): recorded in the manifest with a matching
    SHA-256 they are verified (and listed as such); without the manifest nothing vouches for their contents, so
    they are named and recomputed, never adopted."""
    with sweep.SweepStore(str(tmp_path), spec, 5, LAYOUT, writer=True) as st:
        for c in (0, 1):
            data = _without_checksum(inputs_outcome(spec, *st.chunk_range(c)), dict(st._meta(c), layout=st.layout))
            (tmp_path / "chunks" / f"{c:05d}.parquet").write_bytes(data)
            st.manifest["chunks"][str(c)] = st._entry(c, data)
            st.manifest["columns"] = sorted(inputs_outcome(spec, 0, 1))
        from hyqjax.io.atomic import write_json

        write_json(st.path, st.manifest)
    ro = sweep.SweepStore(str(tmp_path), spec)
    assert ro.done() == {0, 1} and ro.unchecked == {0, 1} and ro.problems == {}
    chk = sweep.verify_store(str(tmp_path))
    assert chk.ok and chk.unchecked == [0, 1] and "without a content checksum" in chk.lines()[0]
    os.remove(tmp_path / "manifest.json")
    chk = sweep.verify_store(str(tmp_path))
    assert not chk.ok and chk.manifest == "missing" and set(chk.damaged) == {0, 1}
    assert "no content checksum" in chk.damaged[0]
    capsys.readouterr()
    st = fill(tmp_path, spec)  # rebuilds the manifest: both recomputed, with checksums
    out = capsys.readouterr().out
    assert out.count("no content checksum") == 2 and "not adopted" in out
    assert st.done() == {0, 1, 2, 3} and st.unchecked == set()
    same_rows(sweep.SweepStore(str(tmp_path), spec).load(), inputs_outcome(spec, 0, 18))


def test_rebuild_and_adoption_messages_say_what_happened(tmp_path, spec, capsys):
    fill(tmp_path, spec, chunks=[0, 1])
    capsys.readouterr()
    os.remove(tmp_path / "manifest.json")
    fill(tmp_path, spec, chunks=[])
    out = capsys.readouterr().out
    assert "manifest.json was missing: rebuilding it from the chunk files whose content checksums verify" in out
    assert "rebuilt with 2 chunk file(s)" in out and "writer stopped" not in out
    # A chunk written, then its writer killed before the manifest's rename (the manifest is intact).
    data = sweep.rows_to_parquet(inputs_outcome(spec, 10, 15), dict(
        schema=sweep.SCHEMA, spec_hash=spec.spec_hash, chunk=2, start=10, stop=15))
    (tmp_path / "chunks" / "00002.parquet").write_bytes(data)
    st = fill(tmp_path, spec, chunks=[])
    out = capsys.readouterr().out
    assert "00002.parquet was written but not recorded in the manifest (its writer stopped in between)" in out
    assert st.done() == {0, 1, 2}


def test_damaged_store_named_by_verify_report_render_and_the_summary(tmp_path, spec, capsys):
    from hyqjax.cli import app

    out = tmp_path / "sw"
    st = fill(out, spec)
    sweep.summary.write_json(str(out / "summary.json"), sweep.summarize_sweep(spec, st.load()))
    assert app.main(["verify", str(out)]) == 0 and "ok: 4 of 4 chunks verified" in capsys.readouterr().out
    assert app.main(["report", str(out), "--no-cache"]) == 0
    capsys.readouterr()
    path = out / "chunks" / "00002.parquet"
    data = path.read_bytes()
    path.write_bytes(data[:-9] + bytes([data[-9] ^ 1]) + data[-8:])  # one flipped bit in the footer
    assert app.main(["verify", str(out)]) == 1
    text = capsys.readouterr().out
    assert "DAMAGED: 3 of 4 chunks verified" in text and "chunk 2:" in text and "00002.parquet" in text
    assert app.main(["report", str(out), "--no-cache"]) == 1  # the old summary is not shown silently
    io = capsys.readouterr()
    assert "chunk 2:" in io.err and "summary.json covers 18 instances" in io.err
    assert "Store damaged" in (out / "report.html").read_text()
    assert app.main(["render", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sweep store" in err[0] and "DAMAGED: chunks [2]" in err[0]
    summary = sweep.write_outputs(sweep.open_store(str(out)))
    assert summary["n_instances"] == 13 and set(summary["damaged_chunks"]) == {"2"}
    assert any("damaged chunk" in n for n in summary["notes"])


# ------------------------------------------------------------------------------------------------
# Processes: kills at random points (including mid-write), two writers
# ------------------------------------------------------------------------------------------------

WRITER = textwrap.dedent("""
    import os, sys, time
    sys.path.insert(0, {root!r}); sys.path.insert(0, {tests!r})
    from test_store import inputs_outcome, LAYOUT
    from hyqjax.studies import sweep
    import hyqjax.io.atomic as atomic
    spec = sweep.SweepSpec.from_dict({spec!r})
    slow = float(os.environ.get("SLOW_RENAME", "0"))
    if slow:
        real = atomic.os.replace
        def replace(a, b):  # widen the window between writing a temporary and renaming it
            time.sleep(slow); real(a, b)
        atomic.os.replace = replace
    with sweep.SweepStore(sys.argv[1], spec, int(sys.argv[2]), LAYOUT, writer=True, wait=True) as st:
        for c in st.todo():
            st.write_chunk(c, inputs_outcome(spec, *st.chunk_range(c)), 0.0, worker=str(os.getpid()))
    print("done", flush=True)
""")


def _writer(tmp_path, spec_dict, out, chunk_size=1, env=None):
    script = tmp_path / f"writer_{sweep.SweepSpec.from_dict(spec_dict).spec_hash[:8]}.py"
    script.write_text(WRITER.format(root=ROOT, tests=os.path.join(ROOT, "tests"), spec=spec_dict))
    return subprocess.Popen([sys.executable, str(script), str(out), str(chunk_size)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, **(env or {})})


@pytest.mark.slow  # subprocesses killed and resumed: seconds, not the unit lane
def test_sigkill_at_random_points_then_resume_is_identical(tmp_path, spec):
    ref = tmp_path / "ref"
    fill(ref, spec, chunk_size=1)
    out = tmp_path / "out"
    rng = random.Random(0)
    for trial in range(6):
        env = {"SLOW_RENAME": "0.3"} if trial % 2 else {}  # odd trials: kill inside the write window
        p = _writer(tmp_path, SPEC, out, env=env)
        time.sleep(rng.uniform(1.0, 3.0))
        p.send_signal(signal.SIGKILL)
        p.wait()
    p = _writer(tmp_path, SPEC, out)
    assert p.wait(120) == 0, p.stderr.read()
    st = sweep.SweepStore(str(out), spec)
    assert st.problems == {} and st.done() == set(range(18))
    same_rows(st.load(), sweep.SweepStore(str(ref), spec).load())
    assert not [f for d in (out, out / "chunks") for f in os.listdir(d) if ".tmp" in f]


@pytest.mark.slow  # subprocesses killed and resumed: seconds, not the unit lane
def test_two_writers_no_lost_records(tmp_path, spec):
    out = tmp_path / "out"
    ps = [_writer(tmp_path, SPEC, out, env={"SLOW_RENAME": "0.05"}) for _ in range(2)]
    for p in ps:
        assert p.wait(120) == 0, p.stderr.read()
    st = sweep.SweepStore(str(out), spec)
    assert st.done() == set(range(18)) and st.problems == {}
    workers = {e["worker"] for e in st.manifest["chunks"].values()}
    assert len(workers) == 1  # the second writer waited, then found every chunk done: nothing computed twice
    same_rows(st.load(), inputs_outcome(spec, 0, 18))


@pytest.mark.slow
def test_two_specs_started_together_never_mix(tmp_path):
    other = {**SPEC, "seed": 77}
    for trial in range(4):
        out = tmp_path / f"t{trial}"
        ps = [_writer(tmp_path, s, out) for s in (SPEC, other)]
        codes = [p.wait(120) for p in ps]
        errs = [p.stderr.read() for p in ps]
        assert sorted(codes) == [0, 1], errs
        assert "different sweep" in errs[codes.index(1)]
        man = json.loads((out / "manifest.json").read_text())
        winner = sweep.SweepSpec.from_dict(SPEC if codes[0] == 0 else other)
        assert man["spec_hash"] == winner.spec_hash
        st = sweep.SweepStore(str(out), winner)
        assert st.problems == {} and st.done() == set(range(18))
        same_rows(st.load(), inputs_outcome(winner, 0, 18))
