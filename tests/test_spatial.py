"""Rotation helpers of hyqjax.core.spatial: round trips, group properties and MuJoCo (float64)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hyqjax.core import spatial

unit_quats = st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 1e-3).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))
rpys = st.tuples(st.floats(-3.1, 3.1), st.floats(-1.55, 1.55), st.floats(-3.1, 3.1)).map(np.asarray)

f = jax.jit(lambda q, r, v, p: dict(
    R=spatial.quat_to_rot(q), q_back=spatial.rot_to_quat(spatial.quat_to_rot(q)),
    rpy_back=spatial.rot_to_rpy(spatial.rpy_to_rot(r)), q_rpy=spatial.rpy_to_quat(r), R_rpy=spatial.rpy_to_rot(r),
    rpy_q=spatial.quat_to_rpy(spatial.rpy_to_quat(r)), qv=spatial.rotvec_to_quat(v), qp=spatial.quat_mul(q, p),
    Rp=spatial.quat_to_rot(p), Rqp=spatial.quat_to_rot(spatial.quat_mul(q, p)),
    qc=spatial.quat_mul(q, spatial.quat_conj(q)), zyx=spatial.rot_z(r[2]) @ spatial.rot_y(r[1]) @ spatial.rot_x(r[0]),
    skew=spatial.skew(v) @ r, cross=jnp.cross(v, r)))


@settings(max_examples=200, deadline=None)
@given(unit_quats, rpys, st.lists(st.floats(-3, 3), min_size=3, max_size=3).map(np.asarray), unit_quats)
def test_round_trips_and_group_properties(q, rpy, v, p):
    with jax.enable_x64(True):
        o = {k: np.asarray(a) for k, a in f(q, rpy, v, p).items()}
    r = o["R"]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1) < 1e-12
    # q and -q are the same rotation: the round trip returns one of them, with w >= 0.
    assert min(np.abs(o["q_back"] - q).max(), np.abs(o["q_back"] + q).max()) < 1e-9 and o["q_back"][0] >= 0
    np.testing.assert_allclose(o["rpy_back"], rpy, atol=1e-7)
    np.testing.assert_allclose(o["rpy_q"], rpy, atol=1e-7)
    np.testing.assert_allclose(spatial_np_rot(o["q_rpy"]), o["R_rpy"], atol=1e-12)
    np.testing.assert_allclose(o["zyx"], o["R_rpy"], atol=1e-12)
    np.testing.assert_allclose(o["Rqp"], r @ o["Rp"], atol=1e-12)
    np.testing.assert_allclose(o["qc"], [1, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(o["skew"], o["cross"], atol=1e-12)
    # Against MuJoCo: quaternion -> matrix and rotation vector -> quaternion.
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, q)
    np.testing.assert_allclose(r, mat.reshape(3, 3), atol=1e-12)
    qv = np.zeros(4)
    angle = np.linalg.norm(v)
    mujoco.mju_axisAngle2Quat(qv, v / angle if angle > 0 else np.array([1.0, 0, 0]), angle)
    np.testing.assert_allclose(o["qv"], qv, atol=1e-12)


def spatial_np_rot(q):
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(q, np.float64))
    return mat.reshape(3, 3)


def test_rot_to_quat_half_turns_and_batches():
    """Shepperd's branches: half turns about every axis and a batch of random rotations (float32)."""
    rots = np.stack([np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), np.eye(3)])
    q = np.asarray(jax.jit(spatial.rot_to_quat)(jnp.asarray(rots, jnp.float32)))
    np.testing.assert_allclose(np.abs(q), [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [1, 0, 0, 0]], atol=1e-6)
    rng = np.random.default_rng(0)
    qs = rng.normal(size=(256, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    back = np.asarray(jax.jit(lambda a: spatial.rot_to_quat(spatial.quat_to_rot(a)))(jnp.asarray(qs, jnp.float32)))
    np.testing.assert_allclose(back, qs * np.sign(qs[:, :1]), atol=2e-6)


small_rpys = st.tuples(st.floats(-1.2, 1.2), st.floats(-1.2, 1.2), st.floats(-1.2, 1.2)).map(np.asarray)
vecs = st.lists(st.floats(-3, 3), min_size=3, max_size=3).map(np.asarray)
H = 1e-6


@jax.jit
def _euler_case(rpy, omega):
    r = spatial.rpy_to_rot(rpy)
    step = spatial.quat_to_rot(spatial.rotvec_to_quat(H * omega))  # exp(h [omega]_x)
    batch = jnp.stack([rpy, -rpy])
    return dict(rates=spatial.euler_rates(rpy, omega),
                fd=(spatial.rot_to_rpy(r @ step) - spatial.rot_to_rpy(r @ step.T)) / (2 * H),
                q_trace=spatial.rot_to_quat_trace(r), q=spatial.rot_to_quat(r),
                rp=spatial.roll_pitch_to_rot(rpy[0], rpy[1]),
                rp_ref=spatial.rpy_to_rot(jnp.stack([rpy[0], rpy[1], 0.0])),
                rp_batch=spatial.roll_pitch_to_rot(batch[:, 0], batch[:, 1]),
                rp_neg=spatial.rpy_to_rot(jnp.stack([-rpy[0], -rpy[1], 0.0])),
                rates_batch=spatial.euler_rates(batch, jnp.stack([omega, omega])))


@settings(max_examples=60, deadline=None)
@given(small_rpys, vecs)
def test_euler_rates_trace_quat_and_roll_pitch_frame(rpy, omega):
    """``euler_rates`` is the time derivative of roll / pitch / yaw under the body rate ``omega``
    (``R' = R [omega]_x``, central differences); ``rot_to_quat_trace`` is ``rot_to_quat`` away from half
    turns; ``roll_pitch_to_rot`` is ``rpy_to_rot`` with the yaw removed, for scalars and batches."""
    with jax.enable_x64(True):
        o = {k: np.asarray(v) for k, v in _euler_case(jnp.asarray(rpy), jnp.asarray(omega)).items()}
    np.testing.assert_allclose(o["rates"], o["fd"], atol=1e-6)
    np.testing.assert_allclose(o["q_trace"], o["q"], atol=1e-12)
    np.testing.assert_allclose(o["rp"], o["rp_ref"], atol=0)
    np.testing.assert_allclose(o["rp_batch"][0], o["rp"], atol=0)
    np.testing.assert_allclose(o["rp_batch"][1], o["rp_neg"], atol=0)
    np.testing.assert_allclose(o["rates_batch"][0], o["rates"], atol=0)


# ---------------------------------------------------------------- closed-form small solves (core.smallmat)


@pytest.mark.slow
def test_closed_form_small_solves_match_numpy_in_float64():
    from hyqjax.core import smallmat

    rng = np.random.default_rng(3)
    a3 = rng.normal(size=(64, 3, 3)) + 3.0 * np.eye(3)
    b3 = rng.normal(size=(64, 3))
    m = rng.normal(size=(64, 6, 6))
    a6 = m @ np.swapaxes(m, -1, -2) + 0.5 * np.eye(6)
    b6 = rng.normal(size=(64, 6))
    with jax.enable_x64(True):
        x3 = np.asarray(jax.jit(smallmat.solve3)(jnp.asarray(a3), jnp.asarray(b3)))
        x6 = np.asarray(jax.jit(smallmat.spd_solve)(jnp.asarray(a6), jnp.asarray(b6)))
    np.testing.assert_allclose(x3, np.linalg.solve(a3, b3[..., None])[..., 0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(x6, np.linalg.solve(a6, b6[..., None])[..., 0], rtol=1e-9, atol=1e-11)
    # residuals in float32, the width the controller runs in
    x3f = np.asarray(jax.jit(smallmat.solve3)(jnp.asarray(a3, jnp.float32), jnp.asarray(b3, jnp.float32)))
    assert np.max(np.abs(np.einsum("bij,bj->bi", a3, x3f) - b3)) < 1e-5
    x6f = np.asarray(jax.jit(smallmat.spd_solve)(jnp.asarray(a6, jnp.float32), jnp.asarray(b6, jnp.float32)))
    assert np.max(np.abs(np.einsum("bij,bj->bi", a6, x6f) - b6)) < 1e-4
