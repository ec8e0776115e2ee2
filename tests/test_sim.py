"""Closed-loop batched simulation (hyqjax.sim.rollout) with the standing controller, in float32 MJX.

One 2 s scenario (:func:`run_scenario`, batch 4 on flat ground, :data:`DURATION`) serves most tests: instances
0-2 stand under joint PD (``hyqjax.control.stand``) on three friction values; instance 3 gets a 1 MN push at
t = 0.5 s and must be flagged as diverged. The same scenario runs sharded over a 1-device mesh
here and over a 2-device mesh in a subprocess (``--xla_force_host_platform_device_count=2``), and in chunks. The
controller's long-horizon property, standing for 10 s, is checked on the C MuJoCo backend (:func:`run_scenario_c`):
a property of the controller, not of MJX, in about a second of simulation instead of MJX's half minute.
The CPU deadlock regression runs in a subprocess with a timeout so a hang fails instead of blocking CI.
"""
from __future__ import annotations

import copy

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import start_python, user_xla_flags
from mujoco import mjx

from hyqjax.sim import backend, compile_phase
from hyqjax.sim import model as hmodel
from hyqjax.core import robot
from hyqjax.sim import rollout as sim
from hyqjax.sim import runner as runner_mod
from hyqjax.core import spatial
from hyqjax.control import stand

BATCH = 4
PUSHED = 3
PUSH_T0 = 0.5
FRICTION = (0.8, 0.6, 1.0, 0.8)
WEIGHT = robot.TOTAL_MASS * robot.GRAVITY
SUBPROCESS_TIMEOUT = 300.0
#: Simulated seconds of the MJX scenario (the runner's properties: sharding, chunks, padding, divergence; the
#: standing robot is settled, |qvel| about 2e-3, by then).
DURATION = 2.0
#: Simulated seconds of the stand on C MuJoCo.
LONG_STAND = 10.0


# ---------------------------------------------------------------- the shared scenario


def scenario(m, ids, duration=DURATION):
    """Batched model, initial data, pushes and config of the standing scenario."""
    mxb = hmodel.batch_model(mjx.put_model(m), ids, terrain())
    # x = 1 m: all four feet on the floor, clear of the platform (its front edge is at x = 0).
    d0 = sim.initial_data(mxb, hmodel.standing_qpos(m, base_xy=(1.0, 0.0)), batch=BATCH)
    force = np.zeros((BATCH, 3), np.float32)
    force[PUSHED] = (1e6, 0.0, 0.0)
    push = sim.Push(jnp.asarray(force), jnp.full((BATCH,), PUSH_T0, jnp.float32), jnp.full((BATCH,), 0.1, jnp.float32))
    cfg = sim.SimConfig(duration=duration, record_every=50)
    return mxb, d0, push, cfg


def terrain():
    """Flat ground under the scenario's four instances, each with its friction."""
    return hmodel.InstanceTerrain.make(np.zeros(BATCH), friction=FRICTION)


def height_metrics() -> sim.Metrics:
    """Largest deviation of the trunk height from its start, and the largest |qvel|, over all ticks."""
    def init(d):
        return dict(z0=d.qpos[2], max_dz=jnp.zeros((), d.qpos.dtype), max_qvel=jnp.zeros((), d.qpos.dtype))

    def update(ms, d, obs, info):
        return dict(z0=ms["z0"], max_dz=jnp.maximum(ms["max_dz"], jnp.abs(d.qpos[2] - ms["z0"])),
                    max_qvel=jnp.maximum(ms["max_qvel"], jnp.max(jnp.abs(d.qvel))))

    return sim.Metrics(init, update)


def record(d, obs, info):
    return dict(qpos=d.qpos, foot_force=obs.foot_force, quat=obs.quat, tau=obs.tau)


def run_scenario(m, ids, mesh=None, duration=DURATION, runner=None) -> dict:
    """Run the scenario (through ``runner`` if given, else a new one); returns numpy arrays."""
    mxb, d0, push, cfg = scenario(m, ids, duration)
    if runner is None:
        runner = runner_mod.make_batch_runner(ids, stand.stand_controller, cfg, height_metrics(), record,
                                              params_axes=None, mesh=mesh)
    return _arrays(jax.block_until_ready(runner(mxb, d0, stand.StandParams.make(), push)))


def run_scenario_c(m, ids, duration=LONG_STAND) -> dict:
    """The scenario on the C MuJoCo backend (``impl="c"``: float64 physics, the controller compiled in JAX), the
    same instances, pushes, metrics and record; returns numpy arrays."""
    c = backend.get("c")
    models = c.batch_model(c.put_model(m), ids, terrain())
    d0 = c.initial_data(None, models, np.broadcast_to(hmodel.standing_qpos(m, base_xy=(1.0, 0.0)), (BATCH, 19)), m)
    _, _, push, cfg = scenario(m, ids, duration)
    runner = c.make_runner(ids, stand.stand_controller, cfg, height_metrics(), record, params_axes=None)
    return _arrays(runner(models, d0, stand.StandParams.make(), push))


def _arrays(res) -> dict:
    """A result's final state (with MJX's bias forces where the data has them), flags, metrics and trace."""
    out = dict(qpos=res.data.qpos, qvel=res.data.qvel, diverged=res.diverged, diverged_tick=res.diverged_tick,
               max_dz=res.metrics["max_dz"], max_qvel=res.metrics["max_qvel"],
               **{f"trace_{k}": v for k, v in res.trace.items()})
    if hasattr(res.data, "qfrc_bias"):
        out["qfrc_bias"] = res.data.qfrc_bias
    return {k: np.asarray(v) for k, v in out.items()}


_TWO_DEVICE_CODE = """
import sys, time
import numpy as np
sys.path.insert(0, "tests")
import hyqjax, jax
from hyqjax.sim import model as hmodel
from hyqjax.sim import runner
from test_sim import height_metrics, record, run_scenario, scenario, stand
assert jax.device_count() == 2, jax.devices()
m = hmodel.load_model(); ids = hmodel.model_ids(m)
mesh = runner.batch_mesh()
# One runner called twice in a row (the second call of the same compiled programs must work too).
r = runner.make_batch_runner(ids, stand.stand_controller, scenario(m, ids)[3], height_metrics(), record,
                             params_axes=None, mesh=mesh)
outs = []
for call in range(2):
    t = time.time()
    outs.append(run_scenario(m, ids, mesh=mesh, runner=r))
    print(f"call {call}: {time.time() - t:.1f} s", flush=True)
for k in outs[0]:
    assert np.array_equal(outs[0][k], outs[1][k]), k
np.savez(sys.argv[1] if len(sys.argv) > 1 else "{out}", **outs[0])
print("OK")
"""

_DEADLOCK_CODE = """
import os, time
import hyqjax  # sets the XLA:CPU flags before jax is imported
import jax, numpy as np
from mujoco import mjx
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim
print("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""), flush=True)
m = hmodel.load_model()
mx = mjx.put_model(m)
# Committed to the device, so that both calls run the same executable (uncommitted inputs recompile
# on the second call).
d = jax.device_put(sim.initial_data(mx, hmodel.standing_qpos(m, base_xy=(1.0, 0.0)), batch=512), jax.devices()[0])
step = jax.jit(jax.vmap(mjx.step, in_axes=(None, 0)))
for call in range(2):
    t = time.time()
    d = jax.block_until_ready(step(mx, d))
    print(f"call {call}: {time.time() - t:.1f} s", flush=True)
assert np.all(np.isfinite(np.asarray(d.qpos))), "non-finite state"
print("OK")
"""


@pytest.fixture(scope="module")
def two_device_job(tmp_path_factory):
    """The scenario sharded over a 2-device CPU mesh, twice, in a background subprocess with a user's XLA flags
    (XLA's default code generator: compared with this session's run, it checks the session's option as well)."""
    out = str(tmp_path_factory.mktemp("two_device") / "result.npz")
    env = {"XLA_FLAGS": (user_xla_flags() + " --xla_force_host_platform_device_count=2").strip()}
    proc = start_python(_TWO_DEVICE_CODE.replace("{out}", out), env=env)
    yield proc, out
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def deadlock_job():
    """``jax.jit(jax.vmap(mjx.step))`` at batch 512, called twice, in a background subprocess with a user's XLA
    flags (hyqjax's, without the test session's code generator option)."""
    proc = start_python(_DEADLOCK_CODE, env={"XLA_FLAGS": user_xla_flags()})
    yield proc
    if proc.poll() is None:
        proc.kill()
        proc.communicate()


@pytest.fixture(scope="module")
def standing_run(hyq, deadlock_job, two_device_job):
    """The scenario, unsharded (the subprocesses are started first so that they overlap with it)."""
    m, ids = hyq
    return run_scenario(m, ids)


# ---------------------------------------------------------------- standing


STANDING = [i for i in range(BATCH) if i != PUSHED]


def _assert_stands(r, seconds):
    """Instances 0-2 of result ``r`` stood for ``seconds``: never diverged, trunk height within 1 cm of its start at
    every tick and at the end, upright, in place, at rest, joints at the standing posture."""
    assert not r["diverged"][STANDING].any()
    assert np.all(np.isfinite(r["qpos"])) and np.all(np.isfinite(r["qvel"]))
    assert np.all(np.isfinite(r["trace_qpos"]))
    assert r["trace_qpos"].shape[1] == int(round(seconds / 0.002)) // 50  # every 50th of the run's ticks recorded
    # Trunk height within 1 cm of its start over all ticks, and at the end.
    assert np.all(r["max_dz"][STANDING] < 0.01), r["max_dz"]
    z0 = robot.STANDING_BASE_Z
    assert np.all(np.abs(r["qpos"][STANDING, 2] - z0) < 0.01)
    # Upright, in place, and at rest at the end.
    rpy = np.asarray(spatial.rot_to_rpy(spatial.quat_to_rot(jnp.asarray(r["qpos"][STANDING, 3:7], jnp.float32))))
    assert np.all(np.abs(rpy) < 0.02), rpy
    assert np.all(np.abs(r["qpos"][STANDING, :2] - (1.0, 0.0)) < 0.01)
    assert np.all(np.abs(r["qvel"][STANDING]) < 0.01)
    np.testing.assert_allclose(r["qpos"][STANDING, 7:], np.broadcast_to(robot.Q_STANDING, (3, 12)), atol=0.05)


@pytest.mark.slow
def test_stands_on_mjx_through_the_run(standing_run):
    """MJX (float32): the three unpushed instances stand through the scenario's :data:`DURATION`."""
    assert standing_run["qpos"].dtype == np.float32
    _assert_stands(standing_run, DURATION)


@pytest.mark.slow
def test_stands_for_10_s_on_c_mujoco(hyq):
    """The stand controller holds HyQ for 10 s (C MuJoCo's float64 physics, the controller compiled in JAX), and
    the pushed instance is flagged diverged there too."""
    m, ids = hyq
    r = run_scenario_c(m, ids)
    _assert_stands(r, LONG_STAND)
    np.testing.assert_array_equal(r["diverged"], np.arange(BATCH) == PUSHED)


@pytest.mark.slow
def test_estimated_foot_forces_sum_to_the_weight(standing_run):
    r = standing_run
    for b in STANDING:
        f_b = r["trace_foot_force"][b, -1]  # (4, 3) in the trunk frame, the last recorded tick
        w_r_b = np.asarray(spatial.quat_to_rot(jnp.asarray(r["trace_quat"][b, -1])))
        f_w = f_b @ w_r_b.T
        total = f_w.sum(0)
        assert total[2] == pytest.approx(WEIGHT, rel=0.05), total
        assert np.all(np.abs(total[:2]) < 0.02 * WEIGHT), total
        assert np.all((f_w[:, 2] > 0.15 * WEIGHT) & (f_w[:, 2] < 0.35 * WEIGHT)), f_w  # each foot ~ 1/4


FORCE_TOL = 2.0  # N per component, 1 % of a foot's ~208 N load


@pytest.mark.slow
def test_estimated_foot_forces_match_mujoco_contact_forces(hyq, standing_run):
    """``Observation.foot_force`` (J_f^-T (h - tau), from the final MJX data) against C MuJoCo's contact
    forces (``mj_contactForce``, float64) on the same state with the same (controller) torques."""
    m, ids = hyq
    r = standing_run
    d0 = mjx.make_data(mjx.put_model(m))
    params = stand.StandParams.make()

    @jax.jit
    def estimate(d):
        obs = sim.observe(ids, d, jnp.zeros(12, d.qpos.dtype))
        _, tau, _ = stand.stand_controller.step(params, (), obs)
        tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
        return tau, sim.observe(ids, d, tau).foot_force

    for b in STANDING:
        # The final MJX data of instance b (its bias forces are those of its last step, as the controller sees them).
        dd = d0.replace(qpos=r["qpos"][b], qvel=r["qvel"][b], qfrc_bias=r["qfrc_bias"][b])
        tau, f_est = (np.asarray(x, np.float64) for x in estimate(dd))
        mc = copy.deepcopy(m)
        mc.geom_friction[[ids.floor_geom, ids.platform_geom], 0] = FRICTION[b]
        d = mujoco.MjData(mc)
        d.qpos[:] = r["qpos"][b]
        d.qvel[:] = r["qvel"][b]
        d.ctrl[:] = tau
        mujoco.mj_forward(mc, d)
        f_c = _contact_forces_trunk_frame(mc, ids, d)
        err = np.abs(f_est - f_c)
        assert err.max() < FORCE_TOL, f"instance {b}: estimated\n{f_est}\nMuJoCo\n{f_c}"
        assert f_c[:, 2].sum() == pytest.approx(WEIGHT, rel=0.01)


def _contact_forces_trunk_frame(m, ids, d) -> np.ndarray:
    """Sum of the terrain's contact forces on each foot (``mj_contactForce``), in the trunk frame, (4, 3)."""
    w_r_b = d.xmat[ids.trunk_body].reshape(3, 3)
    out = np.zeros((4, 3))
    f6 = np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        mujoco.mj_contactForce(m, d, i, f6)
        f_w = c.frame.reshape(3, 3).T @ f6[:3]  # force of geom1 on geom2, world frame
        if c.geom2 in ids.foot_geoms:
            out[ids.foot_geoms.index(c.geom2)] += f_w
        elif c.geom1 in ids.foot_geoms:
            out[ids.foot_geoms.index(c.geom1)] -= f_w
        else:
            raise AssertionError(f"unexpected contact {m.geom(c.geom1).name} - {m.geom(c.geom2).name}")
    return out @ w_r_b


# ---------------------------------------------------------------- divergence


@pytest.mark.slow
def test_divergence_is_flagged_and_frozen(standing_run):
    r = standing_run
    expected = np.zeros(BATCH, bool)
    expected[PUSHED] = True
    np.testing.assert_array_equal(r["diverged"], expected)
    t0 = int(round(PUSH_T0 / 0.002))
    tick = int(r["diverged_tick"][PUSHED])
    assert t0 <= tick < t0 + 50, tick
    assert np.all(r["diverged_tick"][STANDING] == -1)
    # Frozen at the last finite state: finite, and every trace sample after the flag is that state.
    assert np.all(np.isfinite(r["qpos"][PUSHED])) and np.all(np.isfinite(r["qvel"][PUSHED]))
    assert np.max(np.abs(r["qvel"][PUSHED])) < sim.SimConfig().max_speed
    after = (np.arange(r["trace_qpos"].shape[1]) + 1) * 50 - 1 > tick
    np.testing.assert_array_equal(r["trace_qpos"][PUSHED, after], np.broadcast_to(r["qpos"][PUSHED], (after.sum(), 19)))
    assert r["max_qvel"][PUSHED] < sim.SimConfig().max_speed


# ---------------------------------------------------------------- config validation


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(control_dt=0.0), "control_dt"),
        (dict(control_dt=0.05), "control_dt"),
        (dict(substeps=0), "substeps"),
        (dict(substeps=2.0), "substeps"),
        (dict(substeps=101), "substeps"),
        (dict(duration=0.0), "duration"),
        (dict(duration=601.0), "duration"),
        (dict(record_every=-1), "record_every"),
        (dict(record_every=1.5), "record_every"),
        (dict(duration=1.0, record_every=7), "record_every"),
    ],
)
def test_simconfig_rejects_bad_inputs(kwargs, name):
    with pytest.raises(ValueError, match=name):
        sim.SimConfig(**kwargs)


def test_simconfig_derived_values():
    cfg = sim.SimConfig(control_dt=0.002, substeps=4, duration=1.0, record_every=10)
    assert cfg.physics_dt == pytest.approx(0.0005)
    assert cfg.n_ticks == 500
    assert runner_mod.pad_batch(5, 4) == 8 and runner_mod.pad_batch(8, 4) == 8


def test_a_runner_placed_on_a_device_shares_its_programs_kept_per_device():
    """The runner of a device's slice of a split batch (BatchRunner.placed) is the one-device runner's static setup on
    that device: kept, with the one-device runner's jitted functions, compiled programs and compiler options; its
    programs are kept by the devices they run on (compile_phase.signature): an uncommitted input's is the default
    device, a committed one's its own. (tests/test_multidevice.py counts the traces and compiles on 2 devices.)"""
    cfg = sim.SimConfig(control_dt=0.002, duration=0.02)
    base = runner_mod.BatchRunner(None, None, cfg)
    dev = jax.devices()[0]
    r = base.placed(dev)
    assert base.placed(dev) is r and r.placed(dev) is r and r.device == dev and base.device is None
    assert r._executables is base._executables and r._programs is base._programs and r.n_compiles == 0
    base.compiler_options = {"xla_backend_optimization_level": 0}
    assert r.compiler_options == {"xla_backend_optimization_level": 0}
    with pytest.raises(ValueError, match="mesh"):
        runner_mod.BatchRunner(None, None, cfg, mesh=runner_mod.batch_mesh(jax.devices()[:1])).placed(dev)
    x = np.zeros(3, np.float32)
    assert compile_phase.placement([x]) == frozenset([dev]) == compile_phase.placement([jax.device_put(x, dev)])
    assert compile_phase.signature((x,))[2] == frozenset([dev])


# ---------------------------------------------------------------- sharding and the CPU traps


@pytest.mark.slow
def test_sharded_one_device_mesh_matches_unsharded(hyq, standing_run):
    m, ids = hyq
    mesh = runner_mod.batch_mesh(jax.local_devices()[:1])
    assert mesh.axis_names == ("batch",) and mesh.devices.size == 1
    r = run_scenario(m, ids, mesh=mesh)
    _assert_same_result(r, standing_run, atol=1e-6)


@pytest.mark.slow
def test_sharded_two_device_mesh_matches_and_runs_twice(standing_run, two_device_job):
    proc, out = two_device_job
    stdout, stderr = proc.communicate(timeout=2 * SUBPROCESS_TIMEOUT)
    assert proc.returncode == 0 and "OK" in stdout, f"stdout:\n{stdout}\nstderr:\n{stderr[-4000:]}"
    with np.load(out) as f:
        r2 = {k: f[k] for k in f.files}
    # The two-device job compiles with a user's XLA options, the session's run with the session's
    # (conftest.SESSION_XLA_FLAGS: other code generator, LLVM at level 0): float32 rounding differs, and over the
    # 1,000 ticks the standing robot's residual joint velocities (~2e-3 rad/s) differ by up to 1.9e-4 (measured;
    # positions 1.7e-6, foot forces 0.03 N).
    _assert_same_result(r2, standing_run, atol=4e-4)


def _assert_same_result(a, b, atol):
    np.testing.assert_array_equal(a["diverged"], b["diverged"])
    np.testing.assert_array_equal(a["diverged_tick"], b["diverged_tick"])
    for k in ("qpos", "qvel", "trace_qpos", "max_dz"):
        np.testing.assert_allclose(a[k][STANDING], b[k][STANDING], atol=atol, rtol=0, err_msg=k)
    # Forces (~200 N) amplify float32 differences, and their inertial term M qdd carries the contact
    # solver's rounding: relative, with an absolute floor of 500 x atol (0.15 N for two devices, far below
    # the 30 N touchdown threshold).
    np.testing.assert_allclose(a["trace_foot_force"][STANDING], b["trace_foot_force"][STANDING],
                               atol=500 * atol, rtol=10 * atol, err_msg="trace_foot_force")
    assert np.all(np.isfinite(a["qpos"]))


@pytest.mark.slow
def test_cpu_batch_512_step_twice_does_not_deadlock(deadlock_job):
    """Regression: jaxlib 0.10.x on CPU hung in ``jax.jit(jax.vmap(mjx.step))`` at batch >= 256 on the
    second call; hyqjax pins jax 0.9.2 and switches the XLA:CPU features involved off at import."""
    try:
        stdout, stderr = deadlock_job.communicate(timeout=SUBPROCESS_TIMEOUT)
    except Exception:
        deadlock_job.kill()
        deadlock_job.communicate()
        pytest.fail(f"jit(vmap(mjx.step)) at batch 512 did not return within {SUBPROCESS_TIMEOUT} s (deadlock?)")
    assert deadlock_job.returncode == 0 and "OK" in stdout, f"stdout:\n{stdout}\nstderr:\n{stderr[-4000:]}"
    assert "call 1" in stdout
    flags = next(line for line in stdout.splitlines() if line.startswith("XLA_FLAGS"))
    assert "concurrency_optimized_scheduler" in flags, flags  # hyqjax's workaround is in place


# ---------------------------------------------------------------- backend choice (impl), on CPU without warp-lang


def test_impl_is_validated_with_a_clear_message():
    from hyqjax.sim import backend

    with pytest.raises(ValueError, match=r"impl must be one of auto, jax, warp, got 'cuda'"):
        backend.resolve_impl("cuda")


@pytest.mark.parametrize("warp, cuda, expected", [(False, False, "jax"), (True, False, "jax"), (False, True, "jax"),
                                                  (True, True, "warp")])
def test_auto_picks_warp_only_with_cuda_and_warp_lang(monkeypatch, warp, cuda, expected):
    from hyqjax.sim import backend

    monkeypatch.setattr(backend, "warp_installed", lambda: warp)
    monkeypatch.setattr(backend, "cuda_available", lambda: cuda)
    assert backend.resolve_impl("auto") == expected
    assert backend.resolve_impl("jax") == "jax"


def test_warp_without_warp_lang_names_the_install_extra(monkeypatch):
    from hyqjax.sim import backend

    monkeypatch.setattr(backend, "warp_installed", lambda: False)
    with pytest.raises(ValueError, match=r"impl='warp' needs warp-lang.*hyqjax\[warp\]"):
        backend.resolve_impl("warp")


def test_warp_capacity_is_sized_from_batch_and_model(hyq):
    from hyqjax.sim import impls

    m, _ = hyq
    n_limited = int(m.jnt_limited.sum())
    assert n_limited == 12  # the leg joints; the free joint has no range
    naconmax, njmax = impls.warp_capacity(n_limited, 4096)
    assert naconmax == 4096 * impls.CONTACTS_PER_INSTANCE
    # Every contact of an instance active (4 pyramid edges with condim 3) plus every joint limit.
    assert njmax == 4 * impls.CONTACTS_PER_INSTANCE + 12
    assert int(m.geom_condim[m.geom("lf_foot").id]) == 3
    with pytest.raises(ValueError, match="batch"):
        impls.warp_capacity(n_limited, 0)


@pytest.mark.slow
def test_a_derivative_through_warp_is_an_error_naming_impl():
    from hyqjax.sim import impls

    def f(x, impl):
        return jnp.sum(impls.forbid_derivatives(x, impl) ** 2)

    x = jnp.arange(3.0)
    assert float(f(x, "warp")) == pytest.approx(5.0)  # forward evaluation is fine
    np.testing.assert_allclose(jax.grad(f)(x, "jax"), 2 * x)
    for diff in (jax.grad, jax.jacfwd):
        with pytest.raises(ValueError, match=r"impl='warp' is not differentiable.*impl='jax'"):
            diff(f)(x, "warp")
    with pytest.raises(ValueError, match="impl='warp'"):
        jax.vmap(jax.jacfwd(f), in_axes=(0, None))(jnp.ones((2, 3)), "warp")


@pytest.mark.slow
def test_importing_hyqjax_prints_no_warp_import_failure():
    from conftest import run_python

    code = """
    import hyqjax
    import mujoco.mjx
    from hyqjax.sim import rollout
    print("still printed")
    """
    r = run_python(code, timeout=SUBPROCESS_TIMEOUT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "Failed to import" not in r.stdout + r.stderr
    assert "still printed" in r.stdout


# ---------------------------------------------------------------- the batch runner: chunks, progress, retrace guard


#: Seconds per chunk of the chunked run: four chunks.
CHUNK = DURATION / 4


@pytest.fixture(scope="module")
def chunked_run(hyq):
    """The scenario through a kept runner in chunks of :data:`CHUNK` s (progress reported after each): the runner, its
    inputs, the progress reports, the result (a batch of 4 at its own size, unpadded) and the programs it traced. Its
    batched inputs are host (NumPy) arrays, the form in which the runner hands a padded pass its rows, so that the
    padded batch below runs the same program (an input on the device is declared with its sharding in the lowered
    program, a host array is not: the two would be two entries of the persistent compilation cache)."""
    m, ids = hyq
    mxb, d0, push, cfg = scenario(m, ids)
    mxb = jax.tree_util.tree_map(lambda ax, x: x if ax is None else np.asarray(x), hmodel.model_in_axes(mxb), mxb,
                                 is_leaf=lambda x: x is None)
    d0, push = jax.tree_util.tree_map(np.asarray, (d0, push))
    runner = runner_mod.make_batch_runner(ids, stand.stand_controller, cfg, height_metrics(), record, params_axes=None)
    seen = []
    res = runner(mxb, d0, stand.StandParams.make(), push, progress=lambda done, total: seen.append((done, total)),
                 chunk_seconds=CHUNK)
    return runner, (mxb, d0, push), seen, jax.block_until_ready(res), runner.n_compiles


@pytest.mark.slow
def test_chunked_run_is_bitwise_the_unchunked_one_and_compiles_once(standing_run, chunked_run):
    """The runner in chunks of :data:`CHUNK` s (progress reported after each) gives exactly the one-scan result; a
    second call with new values (another push) reuses the compiled programs."""
    runner, (mxb, d0, push), seen, res, compiled = chunked_run
    assert seen == [pytest.approx((CHUNK * (k + 1), DURATION)) for k in range(4)]
    r = dict(qpos=res.data.qpos, qvel=res.data.qvel, diverged_tick=res.diverged_tick, max_dz=res.metrics["max_dz"],
             **{f"trace_{k}": v for k, v in res.trace.items()})
    for k, v in r.items():
        np.testing.assert_array_equal(np.asarray(v), standing_run[k], err_msg=k)
    assert compiled == 2  # the initial carry and one chunk program
    push2 = sim.Push(push.force * 0.5, push.t_start + 0.1, push.duration)
    res2 = runner(mxb, d0, stand.StandParams.make(), push2, chunk_seconds=CHUNK)
    assert runner.n_compiles == compiled
    assert not np.array_equal(np.asarray(res2.data.qpos)[PUSHED], standing_run["qpos"][PUSHED])
    np.testing.assert_array_equal(np.asarray(res2.data.qpos)[STANDING], standing_run["qpos"][STANDING])


@pytest.mark.slow
def test_padded_batch_rows_equal_the_unpadded_ones(chunked_run):
    """Three instances run in the bucket of four (the last one repeated, then dropped) give bitwise the rows of the
    same instances in an unpadded batch (the batch of four of the chunked run above, at its own size); the compile
    of the new runner is announced and timed apart from the simulation. (Its programs are those of the chunked
    run's runner, the same static setup: loaded from the session's cache, not compiled again.)"""
    runner, (mxb, d0, push), _, full, _ = chunked_run
    assert runner.plan(4).size == 4 and runner.plan(4).passes == 1  # the reference batch ran unpadded
    params = stand.StandParams.make()
    three = jax.tree_util.tree_map(lambda x: x[:3], (d0, push))
    mx3 = jax.tree_util.tree_map(lambda ax, x: x if ax is None else x[:3], hmodel.model_in_axes(mxb), mxb,
                                 is_leaf=lambda x: x is None)
    bucketed = runner_mod.make_batch_runner(runner.ids, stand.stand_controller, runner.cfg, height_metrics(), record,
                                            params_axes=None)
    events = []
    with compile_phase.compile_listener(lambda e, info: events.append(e)):
        res = bucketed(mx3, three[0], params, three[1], chunk_seconds=CHUNK)
    assert bucketed.last_timing["batch"] == 4 and bucketed.last_timing["instances"] == 3
    assert events == ["start", "compile", "compiled", "compile", "compiled", "end", "done"]
    assert bucketed.last_timing["compile_s"] > 0
    got = jax.tree_util.tree_leaves(res)
    want = jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda x: np.asarray(x)[:3], full))
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.shape == w.shape
        np.testing.assert_array_equal(np.asarray(g), w)


@pytest.mark.slow
def test_chunk_length_divides_the_run_and_the_trace_decimation():
    cfg = sim.SimConfig(duration=24.0, record_every=10)
    runner = runner_mod.make_batch_runner(None, stand.stand_controller, cfg, record=record)
    assert runner.chunk_ticks(None) == 12000
    assert runner.chunk_ticks(1.0) == 500
    k = runner.chunk_ticks(0.37)
    assert 12000 % k == 0 and k % 10 == 0 and k * 0.002 <= 0.37
    with pytest.raises(ValueError, match="chunk_seconds"):
        runner.chunk_ticks(0.0)
