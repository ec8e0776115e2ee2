"""The Ray executor (`hyqjax sweep --executor ray`): a local Ray cluster of two CPU workers, one worker killed
mid-chunk, the store compared row for row with the local executor's; the command's driver killed and restarted,
the store then verified by `hyqjax verify` and compared row for row.

The command and a killed worker are covered apart, each once (every Ray run starts a Ray instance and worker
processes that import hyqjax): the command with ``--executor ray`` by the driver test (the executor the command
builds is :class:`~hyqjax.studies.sweep.cluster.RayExecutor`, run by the same ``run_sweep``), a worker killed
mid-chunk by the executor test.

The local run goes first, in a subprocess with a fresh persistent compilation cache, so the MJX program is
compiled once; the Ray workers load it from that cache (`HYQJAX_CACHE_DIR` travels to them).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

ray = pytest.importorskip("ray")

from hyqjax.studies import sweep  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SPEC = dict(seed=11, samples=2, duration=0.3, grid=dict(height=[0.16, 0.24], reflex=[False, True]),
            random=dict(friction=[0.6, 1.0], payload_mass=[0.0, 8.0]))
CHUNK = 2


def _cli(args, env):
    return [sys.executable, "-m", "hyqjax.cli.app", "sweep", *args, "--chunk-size", str(CHUNK), "--no-progress"]


@pytest.fixture(scope="module")
def local(tmp_path_factory):
    """The sweep by the local executor (and the filled compilation cache)."""
    tmp = tmp_path_factory.mktemp("cluster")
    spec_file = tmp / "spec.json"
    spec_file.write_text(json.dumps(SPEC))
    env = {**os.environ, "HYQJAX_CACHE_DIR": str(tmp / "cache"), "PYTHONPATH": ROOT}
    out = tmp / "local"
    r = subprocess.run(_cli([str(spec_file), "--out", str(out)], env), env=env, capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return tmp, spec_file, env, sweep.SweepSpec.from_dict(SPEC)


def _same_rows(a, b):
    assert sorted(a) == sorted(b)
    for k in a:
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert (a[k] == b[k]).all(), k


def _running_chunk_pids():
    """Pids of Ray workers executing a chunk (Ray titles a worker ``ray::ChunkWorker.run`` while it runs one)."""
    pids = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/cmdline", "rb") as f:
                    if f.read().startswith((b"ray::ChunkWorker.run", b"ray::run_chunk")):
                        pids.append(int(d))
            except OSError:
                pass
    return pids


def _kill_one_worker_mid_chunk(killed: list, stop: threading.Event, after_s: float = 2.0) -> None:
    """Kill the first worker seen running a chunk, ``after_s`` seconds into it (if it still runs one)."""
    while not stop.is_set():
        pids = _running_chunk_pids()
        if pids:
            time.sleep(after_s)
            if pids[0] in _running_chunk_pids():
                os.kill(pids[0], signal.SIGKILL)
                killed.append(pids[0])
                return
        time.sleep(0.1)


@pytest.mark.slow
def test_two_workers_one_killed_mid_chunk_identical_to_local(local, monkeypatch):
    tmp, _, env, spec = local
    monkeypatch.setenv("HYQJAX_CACHE_DIR", env["HYQJAX_CACHE_DIR"])
    monkeypatch.setenv("PYTHONPATH", ROOT)
    killed = []
    stop = threading.Event()

    from hyqjax.studies.sweep import cluster

    th = threading.Thread(target=_kill_one_worker_mid_chunk, args=(killed, stop), daemon=True)
    ex = cluster.RayExecutor(num_cpus=2, max_retries=3)
    assert ex.slots == 2
    th.start()
    try:
        store = sweep.run_sweep(spec, str(tmp / "ray"), CHUNK, progress=False, executor=ex)
    finally:
        stop.set()
        ex.close()
    assert killed, "no worker was killed mid-chunk"
    assert store.done() == set(range(spec.n_instances // CHUNK)) and store.problems == {}
    workers = [e["worker"] for e in store.manifest["chunks"].values()]
    assert not any(w.endswith(f":{killed[0]}") for w in workers)  # its chunk was run again by another worker
    assert store.layout == sweep.SweepStore(str(tmp / "local"), spec).layout
    _same_rows(sweep.SweepStore(str(tmp / "ray"), spec).load(), sweep.SweepStore(str(tmp / "local"), spec).load())


@pytest.mark.slow
def test_driver_killed_and_restarted_resumes_without_recomputing(local):
    tmp, spec_file, env, spec = local
    out = tmp / "ray_driver"
    cmd = _cli([str(spec_file), "--out", str(out), "--executor", "ray"], env)
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    man = out / "manifest.json"
    deadline = time.time() + 600
    while time.time() < deadline and p.poll() is None:
        if man.exists() and json.loads(man.read_text() or "{}").get("chunks"):
            break
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)  # the driver and the Ray instance it started
    p.wait()
    first = json.loads(man.read_text())["chunks"]
    assert 0 < len(first) < spec.n_instances // CHUNK
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    # one worker per slot of the local Ray instance (here its CPUs; on a GPU host its GPUs)
    assert "worker(s) of 1 CPU each" in r.stdout, r.stdout[-2000:]
    final = json.loads(man.read_text())["chunks"]
    assert len(final) == spec.n_instances // CHUNK
    for c, e in first.items():
        assert final[c] == e  # recorded chunks kept, not recomputed
    v = subprocess.run([sys.executable, "-m", "hyqjax.cli.app", "verify", str(out)], env=env, capture_output=True,
                       text=True, timeout=300)
    assert v.returncode == 0, v.stdout + v.stderr
    store = sweep.SweepStore(str(out), spec)
    assert store.problems == {} and store.layout == sweep.SweepStore(str(tmp / "local"), spec).layout
    _same_rows(store.load(), sweep.SweepStore(str(tmp / "local"), spec).load())
