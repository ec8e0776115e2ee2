"""The step-down's start pose (:func:`hyqjax.studies.stepdown.start_qpos`): no front foot starts nearer the platform
edge than at zero heading, checked on MuJoCo's own foot sites, and what a foot over the edge did."""
import dataclasses

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hyqjax.core import robot
from hyqjax.sim import model as hmodel
from hyqjax.studies import stepdown


@pytest.fixture(scope="module")
def model():
    return stepdown.setup(stepdown.StepdownConfig(impl="c")).m


def front_feet_x(m, q0):
    """x of the front foot sites (the edge is at x = 0) of every start ``q0``, from MuJoCo's kinematics."""
    d = mujoco.MjData(m)
    sites = np.asarray(hmodel.model_ids(m).foot_sites)[:2]
    out = []
    for q in np.atleast_2d(q0):
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        out.append(d.site_xpos[sites, 0].copy())
    return np.asarray(out)


def test_leading_front_foot_is_as_far_from_the_edge_as_at_zero_heading(model):
    rng = np.random.default_rng(3)
    n = 64
    sd = rng.uniform(0.0, 0.05, n)
    yaw = np.concatenate([rng.uniform(-0.1, 0.1, n - 2), [0.1, -0.1]])
    q0 = stepdown.start_qpos(hmodel.standing_qpos(model), sd, rng.uniform(-0.05, 0.05, n), yaw, np.full(n, 0.2))
    x = front_feet_x(model, q0)
    x_zero = front_feet_x(model, stepdown.start_qpos(hmodel.standing_qpos(model), sd, 0 * sd, 0 * sd, 0.2 + 0 * sd))
    gap = float(robot.B_P_HIP[0, 0]) - stepdown.standing_front_foot()[0]  # foot centres 6.1 mm behind the hips
    assert gap == pytest.approx(0.0061, abs=2e-4)
    np.testing.assert_allclose(x_zero, np.stack([-sd - gap] * 2, -1), atol=1e-6)
    np.testing.assert_allclose(x.max(-1), -sd - gap, atol=1e-6)  # the leading foot: exactly where it is at yaw 0
    assert (x < 0).all()
    # the advance the trunk is moved back by is what the turn alone moves the leading foot forward
    turned = front_feet_x(model, stepdown.start_qpos(hmodel.standing_qpos(model), sd - stepdown.leading_foot_advance(yaw),
                                                     0 * sd, yaw, 0.2 + 0 * sd))
    np.testing.assert_allclose(turned.max(-1) - x_zero.max(-1), stepdown.leading_foot_advance(yaw), atol=1e-6)
    assert stepdown.leading_foot_advance(np.array([0.1]))[0] == pytest.approx(0.0304, abs=5e-4)


def test_zero_heading_start_is_unchanged_bit_for_bit(model):
    sd = np.array([0.0, 0.013, 0.04], np.float32)
    z = np.zeros(3, np.float32)
    q0 = stepdown.start_qpos(hmodel.standing_qpos(model).astype(np.float32), sd, z, z, z + np.float32(0.2))
    assert q0.dtype == np.float32
    assert (q0[:, 0] == -sd - np.float32(robot.B_P_HIP[0, 0])).all()


@pytest.mark.slow
def test_a_foot_over_the_edge_struck_its_shin_and_the_start_pose_prevents_it():
    """Four headings and start distances that put a front foot 1.3-3.0 cm over the edge with the trunk not moved
    back: every run strikes a shin within its first second (C MuJoCo, the ``reach`` preset, 19 cm); with the start
    pose, none does."""
    from hyqjax import presets

    yaw = np.array([0.08, -0.08, 0.06, -0.1])
    sd = np.array([0.003, 0.0, 0.005, 0.01])
    sc, _ = stepdown.make_scenarios([0.19], [True], 4, 0, params=presets.load("reach"))
    cfg = stepdown.StepdownConfig(duration=1.0, impl="c")
    strikes = {}
    for name, s in (("start pose", sd), ("trunk not moved back", sd - stepdown.leading_foot_advance(yaw))):
        run = dataclasses.replace(sc, start_distance=jnp.asarray(s, jnp.float32), yaw=jnp.asarray(yaw, jnp.float32))
        cols, _ = stepdown.run_batch(run, cfg)
        strikes[name] = (cols["shin_strike"], cols["peak_shin_force"])
    assert not strikes["start pose"][0].any() and (strikes["start pose"][1] == 0).all()
    assert strikes["trunk not moved back"][0].all() and (strikes["trunk not moved back"][1] > 300).all()


def test_start_pose_check_refuses_bad_options_in_one_line(capsys):
    from experiments import start_pose_check

    for argv, needle in ((["--instances", "513"], "--instances"), (["--heights", "0.5"], "--heights"),
                         (["--presets", "bound_robust"], "bound_robust"), (["--duration", "1"], "--duration")):
        assert start_pose_check.main(argv + ["--out", "/nonexistent/x"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0], err
