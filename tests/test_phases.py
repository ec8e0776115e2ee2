"""A command's clock (hyqjax/io/phases.py): the printed "wall ... in all" covers the whole process, its phases add
up, results.json stores them; MuJoCo Warp's kernel build is counted apart from the simulation; bound records a few
instances by default."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from hyqjax.io import phases, recording

WALL = re.compile(r"^wall ([0-9.]+) s in all \(since the process started\): (.*)$")


def test_laps_carve_their_parts_and_add_up_to_the_wall():
    clock = phases.Clock()
    time.sleep(0.05)
    clock.lap("startup")
    time.sleep(0.2)
    dt = clock.lap("simulation", compile=0.05, kernels=0.03)
    time.sleep(0.02)
    d = clock.to_dict()
    assert d["phases"]["compile"] == pytest.approx(0.05) and d["phases"]["kernels"] == pytest.approx(0.03)
    assert d["phases"]["simulation"] == pytest.approx(dt - 0.08, abs=1e-4)
    assert sum(d["phases"].values()) <= d["wall_s"] <= sum(d["phases"].values()) + d["unattributed_s"] + 0.01
    assert d["unattributed_s"] >= 0.015  # the last 20 ms are in no phase yet
    # A carve larger than the lap is cut to it: the phases never add up to more than the wall.
    clock.lap("summary", figures=10.0)
    assert sum(clock.seconds.values()) <= clock.wall()
    with pytest.raises(ValueError, match="phase must be one of"):
        clock.add("lunch", 1.0)


def test_the_process_clock_starts_before_this_module_was_imported():
    age = phases.process_age()
    if age is None:
        pytest.skip("no /proc/self/stat")
    # pytest and its imports ran before this test: the process is older than this module's import. The clock starts
    # at the process's start unless hyqjax was imported more than EXEC_GAP_S after it (a slow collection counts so).
    import time

    import hyqjax

    assert age > 0.2
    started = time.perf_counter() - age
    c = phases.Clock.from_process_start()
    assert c.since == ("import" if hyqjax._IMPORTED_AT - started > phases.EXEC_GAP_S + 0.05 else "process") \
        or abs(hyqjax._IMPORTED_AT - started - phases.EXEC_GAP_S) < 0.05


def test_compile_status_keeps_the_warp_kernel_build_out_of_compile_and_simulation(monkeypatch):
    from hyqjax.cli.progress import CompileStatus

    s = CompileStatus(disable=True)
    s("start", dict(batch=8))
    s("kernels", dict(module="a", seconds=2.0, compiled=True))  # inside the compile phase
    s("end", dict(batch=8, seconds=5.0, from_cache=False))
    s("kernels_start", dict(module="b", compiling=True, cache="/c"))
    s("kernels", dict(module="b", seconds=3.0, compiled=True))  # inside the first chunk
    s("kernels", dict(module="c", seconds=0.5, compiled=False))  # read from Warp's cache
    s("done", dict(simulate_s=10.0, batch=8, passes=1, instances=8))
    assert s.kernel_s == pytest.approx(5.5) and (s.kernels_compiled, s.kernels_loaded) == (2, 3)
    assert s.xla_compile_s == pytest.approx(3.0) and s.pure_simulate_s == pytest.approx(6.5)
    text = s.throughput_text(8, 100)
    assert "simulating 6.5 s" in text and "compile 3.0 s, Warp kernel build 5.5 s" in text
    assert f"{8 * 100 / 6.5:,.0f} env-steps/s" in text
    from hyqjax.cli.progress import lap_batch_run
    from hyqjax.sim import warp_kernels

    clock = phases.Clock(time.perf_counter() - 20.0)  # a 20 s lap: 5.5 kernels + 3 compile + 11.5 simulation
    monkeypatch.setitem(warp_kernels._STATE, "seconds", warp_kernels.seconds() + 5.5)  # the loads of the lap
    lap_batch_run(clock, s)
    assert clock.seconds["kernels"] == pytest.approx(5.5) and clock.seconds["compile"] == pytest.approx(3.0)
    assert clock.seconds["simulation"] == pytest.approx(11.5, abs=0.01)


def test_few_instances_keeps_the_first_and_the_failed_of_each_configuration():
    groups = np.repeat([0, 1], 10)
    failed = np.zeros(20, bool)
    failed[[5, 6, 7, 8, 19]] = True
    rows = recording.few_instances(groups, failed, per_group=3)
    assert rows.tolist() == [0, 1, 2, 5, 6, 7, 10, 11, 12, 19]
    assert recording.parse_instances("few", 20) is None
    assert recording.parse_instances("all", 4).tolist() == [0, 1, 2, 3]


@pytest.mark.slow
def test_bound_prints_the_process_wall_last_and_records_a_few_instances(tmp_path):
    out = tmp_path / "b"
    env = {**os.environ, "HYQJAX_CACHE_DIR": os.environ.get("HYQJAX_CACHE_DIR", str(tmp_path / "jax"))}
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "hyqjax.cli", "bound", "--instances", "8", "--duration", "0.8",
                        "--impl", "c", "--out", str(out)], capture_output=True, text=True, timeout=600, env=env)
    process_wall = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    last = r.stdout.strip().splitlines()[-1]
    m = WALL.match(last)
    assert m, last  # the wall line is the last line printed
    printed = float(m.group(1))
    # The printed wall is the process's: from its start (not the command's) to its last write.
    assert printed <= process_wall + 0.05
    assert process_wall - printed < 1.0, (process_wall, printed)
    res = json.loads((out / "results.json").read_text())
    ph = res["phases"]
    assert ph["since"] == "process" and set(ph["phases"]) <= set(phases.LABELS)
    assert {"startup", "compile", "simulation", "summary", "traces", "figures"} <= set(ph["phases"])
    assert printed + 0.05 >= sum(ph["phases"].values()) and ph["wall_s"] <= printed + 0.05
    labels = dict(part.rsplit(" ", 2)[0:2] for part in m.group(2).split(", "))
    assert float(labels["imports and device start-up"]) == pytest.approx(ph["phases"]["startup"], abs=0.06)
    # By default a few instances of the configuration (the first 3 and its first 3 failures), not all 8.
    rec = recording.load(str(out))
    assert 3 <= rec.n_recorded <= 6 and rec.instance_index.tolist() == res["recorded_instances"]
    assert rec.instance_index[:3].tolist() == [0, 1, 2]
    rows = recording.result_rows(res)
    failed = [i for i, row in enumerate(rows) if recording.instance_failed(row)]
    assert set(rec.instance_index.tolist()) == {0, 1, 2} | set(failed[:3])


@pytest.mark.slow
def test_first_hour_benchmark_at_its_tiny_size(tmp_path):
    """benchmarks/bench_first_hour.py --size tiny: one short bound on empty caches, then warm; its table and JSON."""
    import importlib.util

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location("bench_first_hour",
                                                  os.path.join(root, "benchmarks", "bench_first_hour.py"))
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--size", "tiny", "--out", str(tmp_path), "--caches", str(tmp_path / "caches")]) == 0
    data = json.loads((tmp_path / "first_hour.json").read_text())
    fresh, warm = data["rows"]
    assert (fresh["round"], warm["round"]) == ("fresh", "warm")
    for r in (fresh, warm):
        assert r["rc"] == 0 and r["printed_wall_s"] is not None
        assert r["printed_wall_s"] <= r["process_wall_s"] + 0.05 and r["process_wall_s"] - r["printed_wall_s"] < 1.0
        # the phases add up to no more than the wall: the wall is printed to 0.1 s (off by up to 0.05) and each
        # phase kept to 0.01 s (up to 0.005 each; five phases once summed to 6.65 against a printed 6.6)
        assert sum(r["phases"].values()) <= r["printed_wall_s"] + 0.05 + 0.005 * len(r["phases"])
    # The fresh run compiled what the warm one loaded from the cache the fresh one filled.
    assert os.listdir(tmp_path / "caches" / "jax")
    assert warm["phases"]["compile"] < fresh["phases"]["compile"]
    md = (tmp_path / "first_hour.md").read_text()
    assert md.count("| `hyqjax bound --instances 2") == 2


def test_report_shows_the_wall_time_by_phase(tmp_path, capsys):
    from hyqjax.cli import app

    d = tmp_path / "exp"
    d.mkdir()
    clock = phases.Clock(time.perf_counter() - 10.0)
    clock.lap("simulation", compile=3.0, kernels=2.0)
    res = dict(provenance=dict(command="hyqjax bound --out exp", seed=0), wall_time_s=10.0, phases=clock.to_dict(),
               groups={})
    (d / "results.json").write_text(json.dumps(res))
    assert app.main(["report", str(d)]) == 0
    page = (d / "report.html").read_text()
    assert "wall time by phase" in page
    assert "kernel build (Warp) 2.0 s, XLA compile 3.0 s, simulation 5.0 s" in page


def test_warp_module_loads_of_any_lap_count_as_kernel_build(monkeypatch):
    """Kernels Warp loads outside a batch run (e.g. while the model is put on the device) are kernel build too."""
    from hyqjax.sim import warp_kernels

    clock = phases.Clock(time.perf_counter() - 4.0)
    monkeypatch.setitem(warp_kernels._STATE, "seconds", warp_kernels.seconds() + 1.5)
    clock.lap("startup")
    assert clock.seconds["kernels"] == pytest.approx(1.5) and clock.seconds["startup"] == pytest.approx(2.5, abs=0.01)
    clock.lap("summary")  # no loads since: nothing more to kernels
    assert clock.seconds["kernels"] == pytest.approx(1.5)


@pytest.mark.slow
def test_a_command_execd_by_a_shell_counts_from_hyqjax_import_not_from_the_shell(tmp_path):
    """A process keeps its start time through ``exec``: the last command of ``bash -c 'sleep 6; ...'`` runs in the
    shell's process, 6 s old when Python starts. Its clock starts at hyqjax's import and says so (the 6 s named as
    another program's); a process that starts Python at once counts from its start."""
    import subprocess
    import sys

    if phases.process_age() is None:
        pytest.skip("no /proc/self/stat")
    code = ("import hyqjax, json; from hyqjax.io import phases; c = phases.Clock.from_process_start(); "
            "print(json.dumps(dict(since=c.since, wall=c.wall(), before=c.before_s, line=c.line())))")
    sleep = phases.EXEC_GAP_S + 1.0
    out = subprocess.run(["bash", "-c", f"sleep {sleep}; exec {sys.executable} -c '{code}'"], capture_output=True,
                         text=True, check=True).stdout
    r = __import__("json").loads(out)
    assert r["since"] == "import" and r["wall"] < 5.0 and r["before"] >= sleep - 0.5
    assert "the process ran another program for" in r["line"]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    r = __import__("json").loads(out)
    assert r["since"] == "process" and r["wall"] < phases.EXEC_GAP_S
