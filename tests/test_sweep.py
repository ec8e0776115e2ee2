"""Robustness sweeps (hyqjax.studies.sweep): spec validation, results store, resume, determinism, outcome counting.

One tiny step-down sweep (8 instances, 0.3 s each, chunks of 4) is compiled once per module and run
twice: uninterrupted, and interrupted after its first chunk then resumed.
"""
from __future__ import annotations

import hashlib
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.sim import rollout as sim
from hyqjax.studies import sweep

SPEC = dict(seed=3, samples=2, duration=0.3,
            grid=dict(height=[0.16, 0.24], reflex=[False, True]),
            random=dict(friction=[0.6, 1.0], payload_mass=[0.0, 8.0]),
            maps=[["height", "friction"], ["height", "payload_mass"]], bins=2)


def _sha(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    spec = sweep.SweepSpec.from_dict(SPEC)
    full = str(tmp_path_factory.mktemp("full"))
    part = str(tmp_path_factory.mktemp("part"))
    sweep.run_sweep(spec, full, chunk_size=4, progress=False)
    store = sweep.run_sweep(spec, part, chunk_size=4, max_chunks=1, progress=False)
    assert store.done() == {0}
    c0 = store.chunk_file(0)
    before = dict(sha=_sha(c0), mtime=os.stat(c0).st_mtime_ns, ino=os.stat(c0).st_ino,
                  entry=dict(store.manifest["chunks"]["0"]))
    sweep.run_sweep(spec, part, chunk_size=4, progress=False)
    return spec, full, part, before


@pytest.mark.slow
def test_store_schema(swept):
    spec, full, _, _ = swept
    with open(os.path.join(full, "manifest.json")) as f:
        man = json.load(f)
    assert man["schema"] == sweep.SCHEMA
    assert man["spec_hash"] == spec.spec_hash
    assert man["spec"] == spec.to_dict()
    assert man["n_instances"] == 8 and man["chunk_size"] == 4 and man["n_chunks"] == 2
    assert sorted(man["chunks"]) == ["0", "1"]
    assert [man["chunks"][c]["start"] for c in ("0", "1")] == [0, 4]
    for col in ("index", "height", "reflex", "friction", "payload_mass", "reflex_k_base", "success",
                "failure_reason", "diverged", "mean_mobility", "peak_pitch", "progress"):
        assert col in man["columns"], col
    rows = sweep.SweepStore(full, spec).load()
    assert rows["index"].tolist() == list(range(8))
    assert all(v.shape[0] == 8 for v in rows.values())
    assert not [f for f in os.listdir(full) if ".tmp" in f]
    assert not [f for f in os.listdir(os.path.join(full, "chunks")) if ".tmp" in f]
    check = sweep.verify_store(full)  # the simulated rows (every dtype the runner writes) carry checksums that verify
    assert check.ok and check.unchecked == [] and len(check.files) == 2, check.lines()


@pytest.mark.slow
def test_resume_equals_uninterrupted_without_recompute(swept):
    spec, full, part, before = swept
    a = sweep.SweepStore(full, spec).load()
    b_store = sweep.SweepStore(part, spec)
    b = b_store.load()
    assert sorted(a) == sorted(b)
    for k in a:
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert (a[k] == b[k]).all(), k
    c0 = b_store.chunk_file(0)
    assert _sha(c0) == before["sha"]
    assert os.stat(c0).st_mtime_ns == before["mtime"] and os.stat(c0).st_ino == before["ino"]
    assert b_store.manifest["chunks"]["0"] == before["entry"]
    # Running again has nothing to do and touches nothing.
    sweep.run_sweep(spec, part, chunk_size=4, progress=False)
    assert os.stat(c0).st_mtime_ns == before["mtime"]


@pytest.mark.slow
def test_rows_independent_of_their_neighbours_and_padding(swept):
    """One compiled program per chunk shape: a row's result does not depend on the other rows of its batch or
    on the padding of a short last chunk (so it does not depend on how the sweep is split into chunks)."""
    spec = swept[0]
    rows = spec.instance_inputs(0, 8)
    pick = lambda idx: {k: v[idx] for k, v in rows.items()}  # noqa: E731
    a = sweep.run_rows(pick([0, 1, 2, 3]), spec, 4)
    b = sweep.run_rows(pick([5, 2, 7]), spec, 4)  # row 2 in another position, padded with row 7
    for k in a:
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k][2], b[k][1], err_msg=k)
        else:
            assert a[k][2] == b[k][1], k


@pytest.mark.slow
def test_other_device_layout_refused_in_a_two_device_process(swept):
    """Resuming a store computed on one host device from a process with two is refused before any compile."""
    import subprocess
    import sys

    _, full, _, _ = swept
    code = ("import sys, jax; from hyqjax.studies import sweep; assert len(jax.local_devices()) == 2;"
            f"spec = sweep.SweepSpec.from_dict({SPEC!r});"
            f"sweep.run_sweep(spec, {full!r}, progress=False)")
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
           "PYTHONPATH": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode != 0
    assert "StoreMismatch" in p.stderr and "1 x cpu" in p.stderr and "2 x cpu" in p.stderr, p.stderr[-2000:]


def test_same_seed_same_inputs_independent_of_chunking():
    spec = sweep.SweepSpec.from_dict(SPEC)
    again = sweep.SweepSpec.from_dict(json.loads(json.dumps(SPEC)))
    assert spec.spec_hash == again.spec_hash
    whole = spec.instance_inputs(0, 8)
    parts = [again.instance_inputs(a, b) for a, b in ((0, 3), (3, 5), (5, 8))]
    for k in whole:
        np.testing.assert_array_equal(whole[k], np.concatenate([p[k] for p in parts]), err_msg=k)
    # Paired draws: every grid point sees the same random inputs.
    assert len(set(whole["friction"].tolist())) == 2
    other = sweep.SweepSpec.from_dict({**SPEC, "seed": 4}).instance_inputs(0, 8)
    assert not np.array_equal(other["friction"], whole["friction"])
    unpaired = sweep.SweepSpec.from_dict({**SPEC, "paired": False}).instance_inputs(0, 8)
    assert len(set(unpaired["friction"].tolist())) == 8


@pytest.mark.slow
def test_different_spec_refused(swept):
    _, full, _, _ = swept
    other = sweep.SweepSpec.from_dict({**SPEC, "seed": 99})
    with pytest.raises(sweep.StoreMismatch, match="different sweep"):
        sweep.SweepStore(full, other)


def test_diverged_and_nan_instances_are_failures_with_reason():
    out = dict(success=np.array([True, True, True, False]),
               failure_reason=np.array(["", "", "", "tilt"], dtype=object),
               diverged=np.array([False, True, False, False]),
               peak_roll=np.array([0.1, 0.1, 0.1, 0.5]), peak_pitch=np.array([0.1, 0.2, np.nan, 0.1]),
               progress=np.array([1.0, 1.0, 1.0, 1.0]), mean_mobility=np.array([1.0, 1.0, 1.0, 1.0]))
    c = sweep.count_outcomes(out)
    assert c["success"].tolist() == [True, False, False, False]
    assert c["failure_reason"].tolist() == ["", "diverged", "non-finite metrics", "tilt"]
    spec = sweep.SweepSpec.from_dict(dict(grid=dict(height=[0.2], reflex=[True]), samples=4))
    rows = {**spec.instance_inputs(0, 4), **c}
    s = sweep.summarize_sweep(spec, rows)
    assert s["successes"] == 1 and s["diverged"] == 1
    assert s["failure_reasons"] == {"diverged": 1, "non-finite metrics": 1, "tilt": 1}
    assert s["by_reflex"]["on"]["n"] == 4 and s["by_reflex"]["on"]["successes"] == 1


@pytest.mark.slow
def test_summary_maps_and_outputs(swept):
    spec, full, _, _ = swept
    store = sweep.SweepStore(full, spec)
    s = sweep.write_outputs(store)
    assert s["complete"] and s["n_instances"] == 8
    # Both outcome levels from the real outcome columns: clean implies completed, per reflex setting and cell.
    assert s["completed"] is not None and s["completed"] >= s["successes"] and "notes" not in s
    assert all(r["completed"] >= r["successes"] for r in s["by_reflex"].values())
    assert {(m["x"], m["y"], m["reflex"]) for m in s["maps"]} == {
        ("height", "friction", False), ("height", "friction", True),
        ("height", "payload_mass", False), ("height", "payload_mass", True)}
    for m in s["maps"]:
        n = np.asarray(m["n"])
        assert n.sum() == 4
        lo, hi = np.asarray(m["ci95_lo"]), np.asarray(m["ci95_hi"])
        assert np.all(lo[n > 0] <= hi[n > 0]) and np.all(np.isnan(lo[n == 0]))
        assert np.all(np.asarray(m["completed"]) >= np.asarray(m["successes"]))
    for name in ("summary.json", "instances.csv", "success_maps.png", "success_height.png"):
        assert os.path.exists(os.path.join(full, name)), name
    with open(os.path.join(full, "instances.csv")) as f:
        assert len(f.read().strip().splitlines()) == 9


def test_failure_reasons_come_from_the_outcome_columns():
    """A sweep chunk's outcome columns are the step-down's boolean failure reasons (no failure_reason column):
    every failed row is labelled with the reasons set in it, an internal reflex failure as its own reason, and
    the summary counts them instead of calling them "unspecified"."""
    from hyqjax.studies.stepdown_outcome import FAILURE_REASONS

    n = 5
    out = {k: np.zeros(n, bool) for k in FAILURE_REASONS}
    out.update(success=np.array([True, False, False, False, False]), peak_pitch=np.array([0.1] * 4 + [np.nan]),
               mean_mobility=np.ones(n), diverged=np.array([False, False, False, True, False]))
    out["reflex_failure"][1] = True
    out["feet_not_down"][2] = out["no_progress"][2] = True
    out["shin_strike"][3] = True
    c = sweep.count_outcomes(out)
    assert c["success"].tolist() == [True, False, False, False, False]
    assert c["failure_reason"].tolist() == ["", "reflex_failure", "feet_not_down; no_progress",
                                            "shin_strike; diverged", "non-finite metrics"]
    spec = sweep.SweepSpec.from_dict(dict(grid=dict(height=[0.2], reflex=[True]), samples=n))
    s = sweep.summarize_sweep(spec, {**spec.instance_inputs(0, n), **c})
    assert s["failure_reasons"] == {"reflex_failure": 1, "feet_not_down": 1, "no_progress": 1, "shin_strike": 1,
                                    "diverged": 1, "non-finite metrics": 1}


def test_h95_definitions():
    spec = sweep.SweepSpec.from_dict(dict(grid=dict(height=[0.1, 0.2, 0.3], reflex=[True]), samples=80))
    rows = spec.instance_inputs(0, spec.n_instances)
    h = rows["height"]
    succ = (h < 0.25) | (rows["sample"] < 10)
    n = h.size
    rows.update(success=succ, failure_reason=np.where(succ, "", "tilt"), diverged=np.zeros(n, bool),
                mean_mobility=np.ones(n))
    r = sweep.summarize_sweep(spec, rows)["by_reflex"]["on"]
    assert r["h95_wilson"] == pytest.approx(0.2)
    assert 0.2 < r["h95_logistic"] < 0.3


@pytest.mark.parametrize("bad, match", [
    (dict(grid=dict(height=[0.6])), r"height=0.6 out of range: must be in \[0.0, 0.45\] m"),
    (dict(grid=dict(hieght=[0.1])), "unknown axis 'hieght'"),
    (dict(random=dict(friction=[1.0, 0.5])), "lo=1.0 must be <= hi=0.5"),
    (dict(random=dict(reflex=[0, 1])), "bool axis cannot be random"),
    (dict(grid=dict(friction=[0.8]), fixed=dict(friction=0.9)), "appears in both"),
    (dict(fixed=dict(reflex_m_min=0.3)), "reflex_m_min must be < reflex_m_max"),
    (dict(fixed=dict(foot_sequence="lf-lf-rh-rf")), "foot_sequence must be one of"),
    (dict(samples=0), r"samples=0 out of range: must be in \[1, "),
    (dict(random=dict(roughness=[0.0, 0.05])), "roughness > 0 needs rough-terrain blocks"),
    (dict(fixed=dict(latency=0.5)), "latency=0.5 out of range"),
    (dict(duration=-1), "duration=-1 out of range"),
    (dict(chunks=3), "unknown sweep spec key"),
    (dict(grid=dict(height=[])), "non-empty list"),
])
def test_spec_validation_errors(bad, match):
    with pytest.raises(sweep.SpecError, match=match):
        sweep.SweepSpec.from_dict(bad)


def test_spec_files(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('seed = 1\nsamples = 2\n[grid]\nheight = [0.16, 0.21]\nreflex = ["off", "on"]\n'
                 '[random]\nfriction = [0.5, 1.0]\n')
    s = sweep.load_spec(str(p))
    assert s.n_instances == 8 and dict(s.grid)["reflex"] == (False, True)
    q = tmp_path / "s.json"
    q.write_text(json.dumps(s.to_dict()))
    assert sweep.load_spec(str(q)).spec_hash == s.spec_hash
    bad = tmp_path / "b.toml"
    bad.write_text("[grid\n")
    with pytest.raises(sweep.SpecError, match="invalid TOML"):
        sweep.load_spec(str(bad))


def test_cli_validation_before_compile(capsys):
    from hyqjax.cli import app as cli

    assert cli.main(["sweep", "--grid", "height=0.5", "--dry-run"]) == 2
    assert "height=0.5 out of range" in capsys.readouterr().err
    assert cli.main(["sweep", "--grid", "height=0.1,0.2", "--random", "friction=0.5,1", "--samples", "3",
                     "--dry-run", "--no-cache"]) == 0
    assert "6 instances" in capsys.readouterr().out


@pytest.mark.slow
def test_sensed_controller_delay_and_noise():
    """Latency hands the controller the observation of ``delay`` ticks ago; zero noise changes nothing."""
    inner = sim.Controller(lambda p, o: jnp.zeros(()), lambda p, s, o: (s, o.q, dict(seen=o.q[0])))
    ctrl = sweep.sensed_controller(inner, max_delay=3)
    zero = jnp.asarray(0.0)

    def obs(t):
        q = jnp.full(12, t)
        return sim.Observation(q=q, qd=q, tau=q, quat=jnp.array([1.0, 0, 0, 0]), gyro=jnp.zeros(3),
                               foot_force=jnp.zeros((4, 3)), time=jnp.asarray(t))

    def seen(delay, noise):
        sp = sweep.SensorParams(noise, zero, zero, zero, zero, jnp.asarray(delay), jax.random.PRNGKey(0))
        p = sweep.SensedParams(crawl=None, sensor=sp)
        s = ctrl.init(p, obs(0.0))
        out = []
        for t in range(1, 7):
            s, tau, info = ctrl.step(p, s, obs(float(t)))
            out.append(float(info["seen"]))
        return out

    assert seen(0, zero) == [1, 2, 3, 4, 5, 6]
    assert seen(2, zero) == [0, 0, 1, 2, 3, 4]
    noisy = np.asarray(seen(0, jnp.asarray(0.01))) - np.arange(1, 7)
    assert np.all(np.abs(noisy) > 0) and np.all(np.abs(noisy) < 0.1)


@pytest.mark.slow
def test_real_sweep_killed_then_resumed_is_identical(swept, tmp_path):
    """`hyqjax sweep` SIGKILLed at a random point after its first chunk, then run again: the store equals the
    uninterrupted one row for row (the compiled program comes from the persistent cache the first run filled)."""
    import random
    import signal
    import subprocess
    import sys
    import time

    spec, full, _, _ = swept
    path = tmp_path / "spec.json"
    path.write_text(json.dumps(SPEC))
    out = tmp_path / "out"
    env = {**os.environ, "HYQJAX_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
    cmd = [sys.executable, "-m", "hyqjax.cli.app", "sweep", str(path), "--out", str(out), "--chunk-size", "4",
           "--no-progress"]
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    man = out / "manifest.json"
    deadline = time.time() + 600
    while time.time() < deadline and p.poll() is None:
        if man.exists() and '"0"' in man.read_text():
            break
        time.sleep(0.05)
    time.sleep(random.Random(1).uniform(0.0, 1.0))
    p.send_signal(signal.SIGKILL)
    p.wait()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    got = sweep.SweepStore(str(out), spec)
    assert got.problems == {} and got.done() == {0, 1}
    a, b = sweep.SweepStore(full, spec).load(), got.load()
    for k in a:
        if a[k].dtype.kind == "f":
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        else:
            assert (a[k] == b[k]).all(), k
