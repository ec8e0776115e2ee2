"""Leg kinematics (hyqjax.core.kinematics) against MuJoCo's own kinematics of the MJCF, in float64.

Random configurations are drawn uniformly inside the joint ranges (robot.Q_MIN/Q_MAX); the
ranges fix the knee direction (front KFE < 0, hind KFE > 0), so every sample has the right one.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hyqjax.core import kinematics
from hyqjax.core import robot

N_SAMPLES = 300


def random_q(rng, n):
    """(n, 12) joint vectors uniform in the joint ranges."""
    return rng.uniform(robot.Q_MIN, robot.Q_MAX, size=(n, robot.N_JOINTS))


def random_quat(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def mujoco_feet(m, ids, qpos):
    """MuJoCo's foot sites and per-leg 3x3 site Jacobians, expressed in the trunk frame."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)  # mj_jacSite needs the com-based quantities
    w_r_b = d.xmat[ids.trunk_body].reshape(3, 3)
    p_b = d.xpos[ids.trunk_body]
    pos = np.zeros((4, 3))
    jac = np.zeros((4, 3, 3))
    jacp = np.zeros((3, m.nv))
    dofs = np.asarray(ids.dof_joints).reshape(4, 3)
    for leg, site in enumerate(ids.foot_sites):
        pos[leg] = w_r_b.T @ (d.site_xpos[site] - p_b)
        mujoco.mj_jacSite(m, d, jacp, None, site)
        jac[leg] = w_r_b.T @ jacp[:, dofs[leg]]
    return pos, jac


def test_joint_order_matches_mjcf(hyq):
    m, ids = hyq
    names = [m.joint(int(m.dof_jntid[a])).name for a in ids.dof_joints]
    assert names == [f"{leg}_{j}" for leg in robot.LEG_NAMES for j in robot.JOINT_NAMES]
    assert list(ids.qpos_joints) == list(range(7, 19))
    assert list(ids.dof_joints) == list(range(6, 18))


@pytest.mark.parametrize("random_base", [False, True], ids=["trunk_identity", "trunk_random_pose"])
def test_fk_and_jacobians_match_mujoco(hyq, rng, x64, random_base):
    m, ids = hyq
    qs = random_q(rng, N_SAMPLES)
    fk = jax.jit(jax.vmap(kinematics.foot_positions))
    jf = jax.jit(jax.vmap(kinematics.foot_jacobians))
    pos = np.asarray(fk(jnp.asarray(qs)))
    jac = np.asarray(jf(jnp.asarray(qs)))
    assert pos.dtype == np.float64 and jac.dtype == np.float64
    err_p = err_j = 0.0
    for i, q in enumerate(qs):
        qpos = m.key("standing").qpos.copy()
        if random_base:
            qpos[0:3] = rng.uniform(-2.0, 2.0, 3)
            qpos[3:7] = random_quat(rng)
        else:
            qpos[0:3] = 0.0
            qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        qpos[7:] = q
        p_ref, j_ref = mujoco_feet(m, ids, qpos)
        err_p = max(err_p, np.abs(pos[i] - p_ref).max())
        err_j = max(err_j, np.abs(jac[i] - j_ref).max())
    assert err_p < 1e-6, f"FK differs from mj_kinematics by {err_p:.3g} m"
    assert err_j < 1e-6, f"foot Jacobians differ from mj_jacSite by {err_j:.3g}"


def test_standing_pose_height(x64):
    """The standing pose's foot centres are STANDING_HEIGHT below the trunk, and the keyframe's
    trunk height puts the foot spheres on the ground."""
    x = np.asarray(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING)))
    # FK gives 0.573924 m; robot.STANDING_HEIGHT says 0.573883 m (41 um less): agree to 0.1 mm.
    np.testing.assert_allclose(-x[:, 2], robot.STANDING_HEIGHT, atol=1e-4)
    clearance = robot.STANDING_BASE_Z + x[:, 2] - robot.FOOT_RADIUS
    assert np.all((clearance >= 0.0) & (clearance < 1e-4)), clearance
    # Left/right symmetric, front/hind symmetric in x.
    np.testing.assert_allclose(x[0], x[1] * [1, -1, 1], atol=1e-6)
    np.testing.assert_allclose(x[0], x[2] * [-1, 1, 1], atol=1e-6)


def _foot_below_haa_axis(qs, margin=0.02):
    """True where the foot lies below the HAA axis in the leg plane (HyQ's workspace; IK's branch)."""
    q = qs.reshape(-1, 4, 3)
    vz = -robot.L_HAA_HFE - robot.L_UPPER * np.cos(q[..., 1]) - robot.L_LOWER * np.cos(q[..., 1] + q[..., 2])
    return np.all(vz < -margin, axis=-1)


def test_ik_fk_round_trip(rng, x64):
    qs = random_q(rng, 2 * N_SAMPLES)
    ok = _foot_below_haa_axis(qs)
    qs = qs[ok][:N_SAMPLES]
    assert len(qs) == N_SAMPLES, "too few random samples inside the IK branch's workspace"
    q_legs = jnp.asarray(qs.reshape(-1, 4, 3))
    x = jax.jit(kinematics.foot_positions)(q_legs)
    q_back = np.asarray(jax.jit(kinematics.inverse_kinematics)(x))
    assert q_back.dtype == np.float64
    err = np.abs(q_back - np.asarray(q_legs)).max()
    assert err < 1e-6, f"IK(FK(q)) differs from q by {err:.3g} rad"
    # And FK(IK(x)) = x.
    x_back = np.asarray(kinematics.foot_positions(jnp.asarray(q_back)))
    assert np.abs(x_back - np.asarray(x)).max() < 1e-9


def test_ik_knee_sign_and_unreachable_targets_are_finite(x64):
    q = jnp.asarray(robot.Q_STANDING)
    x = kinematics.foot_positions(q)
    # The other knee solution reaches the same feet.
    q_other = kinematics.inverse_kinematics(x, knee_sign=-robot.KNEE_SIGN)
    assert np.all(np.sign(np.asarray(q_other)[:, 2]) == -robot.KNEE_SIGN)
    np.testing.assert_allclose(kinematics.foot_positions(q_other), x, atol=1e-9)
    # A target 2 m below the hips is out of reach: the leg stretches toward it, finitely.
    far = jnp.asarray(robot.B_P_HIP) + jnp.array([0.0, 0.0, -2.0])
    q_far = np.asarray(kinematics.inverse_kinematics(far))
    assert np.all(np.isfinite(q_far))
    assert np.all(np.abs(q_far[:, 2]) < 1e-3)  # knee straight


def test_foot_jacobians_equal_jacfwd(rng, x64):
    qs = jnp.asarray(random_q(rng, 64))
    jac = jax.jit(jax.vmap(kinematics.foot_jacobians))(qs)  # (n, 4, 3, 3)
    full = jax.jit(jax.vmap(jax.jacfwd(lambda q: kinematics.foot_positions(q))))(qs)  # (n, 4, 3, 12)
    full = np.asarray(full).reshape(-1, 4, 3, 4, 3)
    for leg in range(4):
        np.testing.assert_allclose(full[:, leg, :, leg, :], jac[:, leg], atol=1e-12)
        for other in range(4):
            if other != leg:
                assert np.all(full[:, leg, :, other, :] == 0.0), "a foot moves with another leg's joints"


def test_stacked_jacobian_block_structure(rng, x64):
    qs = jnp.asarray(random_q(rng, 16))
    big = np.asarray(jax.jit(kinematics.stacked_jacobian)(qs))
    jac = np.asarray(kinematics.foot_jacobians(qs))
    assert big.shape == (16, 12, 12)
    for leg in range(4):
        blk = slice(3 * leg, 3 * leg + 3)
        np.testing.assert_allclose(big[:, blk, blk], jac[:, leg], rtol=0, atol=1e-15)
    mask = np.kron(np.eye(4), np.ones((3, 3))).astype(bool)
    assert np.all(big[:, ~mask] == 0.0)
    # dx_f = J dq, the whole robot at once, equals the per-leg velocities.
    qd = jnp.asarray(rng.normal(size=(16, 12)))
    v = np.asarray(kinematics.foot_velocities(qs, qd)).reshape(16, 12)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", big, np.asarray(qd)), v, atol=1e-12)
    # with the Jacobians handed in (a controller that has them already): bit for bit the same
    v_jac = np.asarray(kinematics.foot_velocities(qs, qd, jac=jnp.asarray(jac))).reshape(16, 12)
    assert v_jac.tobytes() == v.tobytes()


@pytest.mark.slow
def test_jit_vmap_grad_and_shapes(rng):
    qs = jnp.asarray(random_q(rng, 8), jnp.float32)
    # Batched (..., 12) and (..., 4, 3) inputs agree, with and without jit/vmap.
    a = jax.jit(kinematics.foot_positions)(qs)
    b = jax.vmap(kinematics.foot_positions)(qs.reshape(8, 4, 3))
    assert a.shape == (8, 4, 3)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert jax.jit(kinematics.foot_jacobians)(qs).shape == (8, 4, 3, 3)
    assert jax.jit(kinematics.stacked_jacobian)(qs).shape == (8, 12, 12)
    assert jax.jit(kinematics.leg_extension)(qs).shape == (8, 4)
    # grad of a scalar of the feet equals J^T applied to its gradient.
    w = jnp.asarray(rng.normal(size=(4, 3)), jnp.float32)
    g = jax.jit(jax.vmap(jax.grad(lambda q: jnp.sum(w * kinematics.foot_positions(q)))))(qs)
    jt_w = jnp.einsum("nlij,li->nlj", kinematics.foot_jacobians(qs), w).reshape(8, 12)
    np.testing.assert_allclose(g, jt_w, atol=1e-5)
    # grad through IK is finite inside the workspace.
    x = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float32))
    gi = jax.jit(jax.grad(lambda x: jnp.sum(kinematics.inverse_kinematics(x) ** 2)))(x)
    assert np.all(np.isfinite(gi))


def test_leg_extension_matches_fk(rng, x64):
    qs = random_q(rng, 32)
    q = qs.reshape(-1, 4, 3)
    ext = np.asarray(kinematics.leg_extension(jnp.asarray(qs)))
    # HFE joint position: HAA position + R_x(phi) (0, 0, -l0).
    phi = robot.HAA_AXIS_SIGN * q[..., 0]
    hfe = robot.B_P_HIP + np.stack([0 * phi, robot.L_HAA_HFE * np.sin(phi), -robot.L_HAA_HFE * np.cos(phi)], -1)
    feet = np.asarray(kinematics.foot_positions(jnp.asarray(qs)))
    np.testing.assert_allclose(ext, np.linalg.norm(feet - hfe, axis=-1), atol=1e-12)


@pytest.mark.slow
def test_float32_close_to_float64(rng):
    qs = random_q(rng, N_SAMPLES)
    with jax.enable_x64(True):
        p64 = np.asarray(kinematics.foot_positions(jnp.asarray(qs, jnp.float64)))
        j64 = np.asarray(kinematics.foot_jacobians(jnp.asarray(qs, jnp.float64)))
        x64_ = jnp.asarray(p64)
        i64 = np.asarray(kinematics.inverse_kinematics(x64_))
    q32 = jnp.asarray(qs, jnp.float32)
    p32 = kinematics.foot_positions(q32)
    j32 = kinematics.foot_jacobians(q32)
    i32 = kinematics.inverse_kinematics(jnp.asarray(p64, jnp.float32))
    assert p32.dtype == jnp.float32 and j32.dtype == jnp.float32 and i32.dtype == jnp.float32
    assert np.abs(np.asarray(p32) - p64).max() < 1e-6
    assert np.abs(np.asarray(j32) - j64).max() < 1e-6
    ok = _foot_below_haa_axis(qs)
    assert np.abs(np.asarray(i32) - i64)[ok].max() < 1e-4
