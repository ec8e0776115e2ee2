"""The C MuJoCo backend (``impl="c"``, hyqjax.sim.cpu_backend): its per-instance models, its physics batch, the
choice of backend, and its agreement with MJX-JAX over the first 0.6 s of the step-down (the outcomes of the 24 s
runs agree in tests/test_stepdown.py, whose paper results run on C MuJoCo).

The unit tests build no MJX model; the agreement test runs MJX-JAX on the CPU (marked slow) with XLA's own LLVM
optimisation (``conftest.LONG_RUN_OPTIONS``): its MJX-JAX program is the chunk program of tests/test_stepdown.py's
24 s MJX run, compiled once in the session.
"""
from __future__ import annotations

import os
import subprocess
import sys

import jax
import mujoco
import numpy as np
import pytest

from hyqjax.sim import backend
from hyqjax.sim import cpu_backend as cb
from hyqjax.sim import compile_phase, cpu_physics
from hyqjax.sim import model as hmodel


def _stand(m, d, q0, ticks):
    """``ticks`` steps of a joint PD holding the standing keyframe ``q0``."""
    for _ in range(ticks):
        d.ctrl[:] = 300.0 * (q0[7:] - d.qpos[7:]) - 10.0 * d.qvel[6:]
        mujoco.mj_step(m, d)


def test_per_instance_models_hold_the_terrain_and_payload(hyq):
    m, ids = hyq
    terrain = hmodel.InstanceTerrain.make([0.0, 0.21], friction=[0.4, 1.1], payload_mass=[0.0, 8.0],
                                          payload_com=[(0, 0, 0), (0.05, -0.02, 0.0)])
    m0, m1 = cb.batch_models(m, ids, terrain)
    assert m1.geom_pos[ids.platform_geom, 2] == pytest.approx(0.21 - hmodel.PLATFORM_HALF_SIZE[2], abs=1e-7)
    for g in (ids.floor_geom, ids.platform_geom):
        assert m0.geom_friction[g, 0] == pytest.approx(0.4, abs=1e-7)
        assert m1.geom_friction[g, 0] == pytest.approx(1.1, abs=1e-6)
    assert m1.body_mass[ids.payload_body] == pytest.approx(8.0) and m0.body_mass[ids.payload_body] == 0.0
    np.testing.assert_allclose(m1.body_ipos[ids.payload_body], (0.05, -0.02, -0.1), atol=1e-7)
    # The source model is not modified, and every instance has its own arrays.
    assert m.geom_pos[ids.platform_geom, 2] == pytest.approx(-hmodel.PLATFORM_HALF_SIZE[2])
    assert m0.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_MIDPHASE)


def test_a_moved_platform_collides_like_a_compiled_one(hyq):
    """The platform raised per instance (geom_pos, midphase off) carries HyQ exactly as a model compiled with
    the platform at that height: same contacts, same state after 0.2 s of standing on it."""
    m, ids = hyq
    h = 0.24
    compiled = hmodel.model_spec(platform_height=h).compile()
    compiled.opt.timestep, compiled.opt.iterations, compiled.opt.ls_iterations = (m.opt.timestep, m.opt.iterations,
                                                                                  m.opt.ls_iterations)
    (moved,) = cb.batch_models(m, ids, hmodel.InstanceTerrain.make([h]))
    q0 = hmodel.standing_qpos(m, base_xy=(-0.5, 0.0), ground_height=h)
    states = []
    for mm in (compiled, moved):
        d = mujoco.MjData(mm)
        d.qpos[:] = q0
        _stand(mm, d, q0, 100)
        states.append((d.qpos.copy(), d.ncon, d.sensordata.copy()))
    assert states[0][1] == states[1][1] >= 4  # the four feet on the platform
    np.testing.assert_allclose(states[1][0], states[0][0], atol=1e-9)
    np.testing.assert_allclose(states[1][2], states[0][2], atol=1e-6)


def test_physics_batch_steps_and_packs_the_view(hyq):
    """CPhysics on 2 threads equals a plain mj_step loop; the packed row unpacks into the view's fields, with
    ``qfrc_gen = qfrc_bias + M qacc``; a frozen instance is not stepped. A batch of fewer than 2 x
    ``MIN_ROWS_PER_THREAD`` instances runs on one thread."""
    m, ids = hyq
    n = 2 * cpu_physics.MIN_ROWS_PER_THREAD
    terrain = hmodel.InstanceTerrain.make([0.0] * n, friction=np.linspace(0.5, 1.0, n))
    models = cb.batch_models(m, ids, terrain)
    q0 = hmodel.standing_qpos(m)
    phys = cpu_physics.CPhysics(models, np.broadcast_to(q0, (n, m.nq)), ids.trunk_body, threads=2, dtype=np.float64)
    assert phys.threads == 2
    small = cpu_physics.CPhysics(models[:n - 1], np.broadcast_to(q0, (n - 1, m.nq)), ids.trunk_body, threads=2)
    assert small.threads == 1
    small.close()
    ref = [mujoco.MjData(mm) for mm in models]
    for d in ref:
        d.qpos[:] = q0
    try:
        for _ in range(20):
            tau = np.stack([300.0 * (q0[7:] - d.qpos[7:]) - 10.0 * d.qvel[6:] for d in ref])
            for d, t, mm in zip(ref, tau, models):
                d.ctrl[:] = t
                mujoco.mj_step(mm, d)
            v = phys.unpack(phys.step(tau, np.zeros(n, bool)))
        for i, (d, mm) in enumerate(zip(ref, models)):
            np.testing.assert_array_equal(v.qpos[i], d.qpos)
            np.testing.assert_array_equal(v.qvel[i], d.qvel)
            assert v.time[i] == pytest.approx(d.time)
            np.testing.assert_array_equal(v.sensordata[i], d.sensordata)
            np.testing.assert_array_equal(v.site_xpos[i], d.site_xpos)
            np.testing.assert_array_equal(v.geom_xmat[i], d.geom_xmat.reshape(-1, 3, 3))
            mq = np.zeros(m.nv)
            mujoco.mj_mulM(mm, d, mq, d.qacc)
            np.testing.assert_allclose(v.qfrc_gen[i], d.qfrc_bias + mq, atol=1e-9)
        before = v.qpos[1].copy()
        v = phys.unpack(phys.step(np.zeros((n, 12)), np.arange(n) == 1))
        np.testing.assert_array_equal(v.qpos[1], before)
        assert not np.array_equal(v.qpos[0], ref[0].qpos)
    finally:
        phys.close()


def test_an_instance_in_which_mujoco_raises_reads_nan_and_the_others_go_on(hyq):
    """An instance whose ``mj_step`` raises (here a stack too small for its contacts) keeps its state, reads as NaN
    from then on (the runner's divergence rule counts it) and is not stepped again, while the other instances of the
    batch go on bit for bit as a plain ``mj_step`` loop steps them."""
    m, ids = hyq
    spec = hmodel.model_spec(hmodel.TerrainLayout())
    spec.memory = 15000  # enough for a HyQ in the air, too little for its contacts on the ground
    small = spec.compile()
    q0 = hmodel.standing_qpos(m)
    high = q0.copy()
    high[2] += 2.0  # instance 0 starts 2 m up: no contact within the test's 10 steps
    qpos = np.stack([high, q0])
    phys = cpu_physics.CPhysics([small, small], qpos, ids.trunk_body, threads=1, dtype=np.float64)
    ref = mujoco.MjData(small)
    ref.qpos[:] = high
    try:
        for _ in range(10):
            out = phys.step(np.zeros((2, 12)), np.zeros(2, bool))
            mujoco.mj_step(small, ref)
        v = phys.unpack(out)
        np.testing.assert_array_equal(v.qpos[0], ref.qpos)
        np.testing.assert_array_equal(v.qvel[0], ref.qvel)
        assert np.isfinite(out[0]).all()
        assert np.isnan(out[1]).all()
        held = phys.batch.bind("qpos")[1].copy()  # the failed instance's state, no longer stepped
        for _ in range(3):
            phys.step(np.zeros((2, 12)), np.zeros(2, bool))
        np.testing.assert_array_equal(phys.batch.bind("qpos")[1], held)
    finally:
        phys.close()


def test_padded_rows_are_never_stepped_and_copy_the_last_real_row(hyq):
    """The host call of a batch padded to a bucket (CPhysics.step_padded): the real rows are stepped exactly as an
    unpadded batch (torques of the padded rows, NaN here, never reach C MuJoCo), the padded rows are a copy of the
    last real row, and the physics holds the real instances only."""
    m, ids = hyq
    models = cb.batch_models(m, ids, hmodel.InstanceTerrain.make([0.0, 0.1, 0.2]))
    q0 = np.broadcast_to(hmodel.standing_qpos(m), (3, m.nq))
    padded = cpu_physics.CPhysics(models, q0, ids.trunk_body, threads=2)
    exact = cpu_physics.CPhysics(cb.batch_models(m, ids, hmodel.InstanceTerrain.make([0.0, 0.1, 0.2])), q0, ids.trunk_body,
                        threads=2)
    try:
        assert padded.b == padded.batch.nsim == 3
        rng = np.random.default_rng(0)
        out = np.empty((8, padded.width), np.float32)
        for _ in range(10):
            tau = rng.normal(0.0, 20.0, (3, 12))
            frozen = np.array([False, True, False])
            rows = np.full((8, 13), np.nan, np.float32)  # padded rows: garbage the physics must not read
            rows[:3, :12], rows[:3, 12] = tau, frozen
            padded.step_padded(rows, out)
            want = exact.step(tau.astype(np.float32), frozen)
        np.testing.assert_array_equal(out[:3], want)
        np.testing.assert_array_equal(out[3:], np.broadcast_to(out[2], (5, padded.width)))
        assert np.isfinite(out).all()
    finally:
        padded.close()
        exact.close()


def test_host_call_runs_python_in_a_jitted_scan_and_reports_its_errors():
    """hyqjax.sim.host_call: a Python function as an FFI target inside a jitted scan (results written in place,
    called once per tick, in order); an exception in it fills the results with NaN and is raised afterwards."""
    import jax.numpy as jnp

    from hyqjax.sim import host_call

    calls = []

    def target(args, results):
        (k, x), (y,) = args, results
        calls.append(float(x[0, 0]))
        if int(k) < 0:
            raise RuntimeError("negative k")
        y[...] = 2.0 * x + int(k)

    host_call.register("hyqjax_test_double", target)
    shape = jax.ShapeDtypeStruct((2, 3), jnp.float32)

    @jax.jit
    def run(k, x):
        return jax.lax.scan(lambda c, _: (host_call.call("hyqjax_test_double", shape, k, c) * 0.5, None), x, None,
                            length=4)[0]

    x0 = jnp.ones((2, 3), jnp.float32)
    np.testing.assert_allclose(np.asarray(run(jnp.int32(1), x0)), 3.0)  # x -> x + 1/2, four times
    assert calls == [1.0, 1.5, 2.0, 2.5]
    host_call.raise_pending("hyqjax_test_double")  # nothing pending
    y = np.asarray(run(jnp.int32(-1), x0))
    assert np.isnan(y).all()
    with pytest.raises(RuntimeError, match="negative k"):
        host_call.raise_pending("hyqjax_test_double")


def test_a_runners_compiler_options_reach_xla_and_key_its_programs():
    """``AheadOfTime.compiler_options`` goes to XLA with every program the runner compiles (an option XLA does not
    know is refused, naming it), and a program compiled under other options is kept apart from the first, each
    compiled once."""
    import jax.numpy as jnp

    class Runner(compile_phase.AheadOfTime):
        def __init__(self):
            self._executables, self.last_timing = {}, {}
            self._reset_compile_phase()

    f = jax.jit(lambda x: jnp.sin(x) * 2.0)
    x = jnp.arange(3.0, dtype=jnp.float32)
    r = Runner()
    plain = r._executable("f", f, (x,))
    r.compiler_options = {"xla_backend_optimization_level": 0}
    level0 = r._executable("f", f, (x,))
    assert level0 is not plain and r._executable("f", f, (x,)) is level0 and len(r._executables) == 2
    r.compiler_options = None
    assert r._executable("f", f, (x,)) is plain
    np.testing.assert_allclose(np.asarray(level0(x)), 2.0 * np.sin(np.arange(3.0)), rtol=1e-6)
    r.compiler_options = {"xla_no_such_option": 1}
    with pytest.raises(Exception, match="xla_no_such_option"):
        r._executable("f", f, (x,))


_CACHED_HOST_CALL = """
import sys, jax, jax.numpy as jnp
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
from hyqjax.sim import compile_phase, host_call
host_call.register("hyqjax_test_add", lambda a, r: r[0].__setitem__(Ellipsis, a[0] + 1.0))
f = jax.jit(lambda x: jax.lax.scan(lambda c, _: (host_call.call("hyqjax_test_add", jax.ShapeDtypeStruct((3,),
    jnp.float32), c) * 2.0, None), x, None, length=3)[0])
exe, from_cache = compile_phase.compile_lowered(f.lower(jnp.zeros(3, jnp.float32)))
print(from_cache, float(exe(jnp.zeros(3, jnp.float32))[0]))
"""


@pytest.mark.slow
def test_a_program_with_a_host_call_is_loaded_from_the_persistent_cache(tmp_path):
    """Unlike an io_callback's, a program calling a host_call target goes to JAX's persistent compilation cache: a
    second process loads it (compile_phase.compile_lowered says so) and it computes the same ((0+1)2+1)2+1)2 = 14."""
    script = tmp_path / "cached.py"
    script.write_text(_CACHED_HOST_CALL)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root)
    outs = [subprocess.run([sys.executable, str(script), str(tmp_path / "cache")], capture_output=True, text=True,
                           env=env, timeout=300) for _ in range(2)]
    for r in outs:
        assert r.returncode == 0, r.stderr[-2000:]
    assert outs[0].stdout.split() == ["False", "14.0"]
    assert outs[1].stdout.split() == ["True", "14.0"]


def test_observation_reads_the_weight_on_the_feet(hyq):
    """The foot forces the controller sees (sim/observe.py, from C MuJoCo's qfrc_bias + M qacc) carry HyQ's weight
    when it stands still: their vertical components sum to m g within 5% (measured: 3.6% high; the estimate
    takes the contact at the foot's centre, the legs' Jacobians from hyqjax.core.kinematics)."""
    m, ids = hyq
    (mm,) = cb.batch_models(m, ids, hmodel.InstanceTerrain.make([0.0]))
    q0 = hmodel.standing_qpos(m)
    phys = cpu_physics.CPhysics([mm], q0[None], ids.trunk_body, threads=1)
    d = mujoco.MjData(mm)
    d.qpos[:] = q0
    for _ in range(300):  # settle under the PD, then read one tick
        tau = 300.0 * (q0[7:] - d.qpos[7:]) - 10.0 * d.qvel[6:]
        d.ctrl[:] = tau
        mujoco.mj_step(mm, d)
        v = phys.unpack(phys.step(tau[None], np.zeros(1, bool)))
        last = tau
    phys.close()
    from hyqjax.sim import observe

    obs = jax.jit(lambda vv, t: observe.observe_view(ids, vv, t))(jax.tree_util.tree_map(lambda x: x[0], v),
                                                                  np.asarray(last, np.float32))
    # foot_force is in the trunk frame; the trunk stands level, so its z is the vertical.
    assert float(np.sum(obs.foot_force[:, 2])) == pytest.approx(float(mm.body_subtreemass[1] * 9.81), rel=0.05)


def test_auto_picks_c_without_an_accelerator_for_forward_runs(monkeypatch):
    monkeypatch.setattr(backend, "accelerator_available", lambda: False)
    monkeypatch.setattr(backend, "warp_installed", lambda: False)
    assert backend.resolve_impl("auto", backend.ALL_IMPLS) == "c"
    assert backend.resolve_impl("auto", backend.ALL_IMPLS, differentiable=True) == "jax"
    assert backend.resolve_impl("auto") == "jax"  # a task on MJX only (bounding)
    with pytest.raises(ValueError, match="impl must be one of auto, jax, warp for this task, got 'c'"):
        backend.resolve_impl("c")
    monkeypatch.setattr(backend, "accelerator_available", lambda: True)
    assert backend.resolve_impl("auto", backend.ALL_IMPLS) == "jax"
    c = backend.get("c")
    assert not c.supports_gradients and c.one_instance_error and backend.get("c") is c


def test_a_derivative_through_c_is_an_error_naming_impl():
    import jax.numpy as jnp

    f = lambda x: jnp.sum(backend.get("c").forbid_derivatives(x) ** 2)  # noqa: E731
    assert float(f(jnp.arange(3.0))) == pytest.approx(5.0)
    with pytest.raises(ValueError, match=r"impl='c' is not differentiable.*impl='jax'"):
        jax.grad(f)(jnp.arange(3.0))


# ---------------------------------------------------------------- agreement with MJX-JAX (MJX compiles: slow)

@pytest.mark.slow
def test_c_follows_mjx_over_the_first_300_ticks(monkeypatch):
    """Two step-down instances (16 and 24 cm, reflex on) for 0.6 s on C MuJoCo (float64) and MJX-JAX (float32):
    the final states agree to a tenth of a millimetre and a milliradian (measured: about 1e-6), the crawl's
    progress to 0.1 mm, and the strike and contact flags are equal."""
    from conftest import compiled_for_long_runs
    from hyqjax.studies import stepdown

    sc, _ = stepdown.make_scenarios([0.16, 0.24], [True], 2, seed=0)
    runs = {}
    for impl in ("c", "jax"):  # the jax chunk program is the one tests/test_stepdown.py's 24 s MJX run is made of
        cfg = stepdown.StepdownConfig(duration=0.6, impl=impl)
        ro = compiled_for_long_runs(stepdown.make_stepdown_rollout(cfg), monkeypatch)
        out, res = ro.run(sc)
        runs[impl] = (jax.tree_util.tree_map(np.asarray, out), np.asarray(res.data.qpos), np.asarray(res.data.qvel))
    (oc, qc, vc), (oj, qj, vj) = runs["c"], runs["jax"]
    np.testing.assert_allclose(qc[:, :3], qj[:, :3], atol=1e-4)
    np.testing.assert_allclose(qc[:, 3:], qj[:, 3:], atol=1e-3)
    np.testing.assert_allclose(vc, vj, atol=2e-2)
    np.testing.assert_allclose(oc.progress, oj.progress, atol=1e-4)
    for k in ("shin_contact", "trunk_strike", "diverged", "lost_footholds", "n_steps"):
        np.testing.assert_array_equal(getattr(oc, k), getattr(oj, k), err_msg=k)


@pytest.mark.slow
def test_padded_c_batch_equals_the_exact_batch_and_one_bucket_compiles_once():
    """Five step-down instances in the bucket of 8 give the outcomes, final state, metrics and traces of the same
    five in a batch of exactly 5 (the padded rows never stepped, dropped from the result); a batch of 6 then runs
    in the same bucket without tracing or compiling again (counted by the runner's compile listener and its trace
    counter, not by wall time)."""
    from hyqjax.studies import stepdown

    cfg = stepdown.StepdownConfig(duration=0.6, record_every=10, impl="c")
    ro = stepdown.make_stepdown_rollout(cfg)
    six, _ = stepdown.make_scenarios([0.16, 0.21, 0.24], [False, True], 1, seed=3)
    five = jax.tree_util.tree_map(lambda x: x[:5], six)
    st = ro.setup
    exact = st.backend.make_runner(st.ids, ro.controller, ro.sim_config, ro.metrics, ro.record, buckets=False)
    bucketed = ro.runner()

    def run(runner, sc):
        mb, d0 = stepdown.batch_inputs(st, sc)
        res = runner(mb, d0, sc.params, sc.push, chunk_seconds=0.2)
        return jax.tree_util.tree_map(np.asarray, (ro._outcomes(res._replace(trace=None)), res))

    want = run(exact, five)
    assert exact.last_timing["batch"] == 5
    events = []
    with compile_phase.compile_listener(lambda e, info: events.append(e)):
        got = run(bucketed, five)
        assert bucketed.last_timing["batch"] == 8 and bucketed.last_timing["instances"] == 5
        assert events.count("compile") == 2  # the initial carry and the chunk program (compiled or cache-loaded)
        traced, n_events = bucketed.n_compiles, len(events)
        got6 = run(bucketed, six)
    assert bucketed.last_timing["batch"] == 8 and bucketed.last_timing["instances"] == 6
    assert bucketed.n_compiles == traced and events[n_events:] == ["done"]  # no start, compile or end
    assert bucketed.last_timing["compile_s"] == 0.0
    g, w = jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)
    assert len(g) == len(w)
    for a, b in zip(g, w):
        assert a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree_util.tree_leaves(got6), g):  # the five shared instances, again in a batch of 6
        np.testing.assert_array_equal(a[:5], b)
    # Shards, one host thread each, run at once: 13 instances as 7 + 6 rows, each padded to the same bucket of 8
    # (no new program), give every instance the result of the unsharded runs of the same rows.
    thirteen = jax.tree_util.tree_map(lambda x: x[:13], stepdown.make_scenarios([0.16, 0.21, 0.24], [False, True], 3,
                                                                                 seed=3)[0])
    bucketed.shards = 2
    assert bucketed.shard_bounds(13) == [(0, 7), (7, 13)]
    both = run(bucketed, thirteen)
    assert bucketed.last_timing["shards"] == 2 and bucketed.last_timing["compile_s"] == 0.0
    assert bucketed.n_compiles == traced
    bucketed.shards = 1
    parts = [run(bucketed, jax.tree_util.tree_map(lambda x: x[lo:hi], thirteen)) for lo, hi in ((0, 7), (7, 13))]
    for a, b, c in zip(jax.tree_util.tree_leaves(both), *(jax.tree_util.tree_leaves(p) for p in parts)):
        np.testing.assert_array_equal(a, np.concatenate([b, c]))
    # An interrupt in one shard's thread (here from the progress callback, at the first chunk both shards finished)
    # stops the other at its next chunk and reaches the caller; nothing of the batch stays registered.
    bucketed.shards = 2
    calls = []

    def interrupt(done_s, total_s):
        calls.append(done_s)
        raise KeyboardInterrupt

    mb, d0 = stepdown.batch_inputs(st, thirteen)
    with pytest.raises(KeyboardInterrupt):
        bucketed(mb, d0, thirteen.params, thirteen.push, progress=interrupt, chunk_seconds=0.2)
    assert calls == [pytest.approx(0.2)] and not cb._ACTIVE
    bucketed.shards = None  # the cached runner back to its default
