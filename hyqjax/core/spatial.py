"""Rotations: quaternions (MuJoCo's ``w, x, y, z``), rotation matrices ``W_R_B`` and ZYX roll-pitch-yaw.

Every function broadcasts over leading axes, is pure, and works in float32 and float64. The one place in
the package for these conversions (round trips are tested against each other and against MuJoCo).
"""
from __future__ import annotations

import jax.numpy as jnp


def quat_to_rot(q):
    """Rotation matrix ``W_R_B`` of a unit quaternion ``(w, x, y, z)``; works on ``(..., 4)``."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rot_to_rpy(r):
    """Roll, pitch, yaw (ZYX convention) of ``W_R_B``; ``(..., 3)``."""
    roll = jnp.arctan2(r[..., 2, 1], r[..., 2, 2])
    pitch = -jnp.arcsin(jnp.clip(r[..., 2, 0], -1.0, 1.0))
    yaw = jnp.arctan2(r[..., 1, 0], r[..., 0, 0])
    return jnp.stack([roll, pitch, yaw], -1)


def rpy_to_rot(rpy):
    """``R_z(yaw) R_y(pitch) R_x(roll)``."""
    r, p, y = rpy[..., 0], rpy[..., 1], rpy[..., 2]
    cr, sr, cp, sp, cy, sy = jnp.cos(r), jnp.sin(r), jnp.cos(p), jnp.sin(p), jnp.cos(y), jnp.sin(y)
    return jnp.stack(
        [
            jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            jnp.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def roll_pitch_to_rot(roll, pitch):
    """``R_y(pitch) R_x(roll)``: ZYX with the yaw removed, the trunk's orientation in the horizontal frame
    ``H`` (``h_x = hR_b b_x``); broadcasts over ``roll`` and ``pitch``.

    Entry for entry the arithmetic of :func:`rpy_to_rot` at yaw 0, so bitwise its result: its factors
    ``cos 0 = 1`` are left out, its terms in ``sin 0 = 0`` kept (they set the signs of exact zeros and flush
    denormals as it does)."""
    cr, sr, cp, sp = jnp.cos(roll), jnp.sin(roll), jnp.cos(pitch), jnp.sin(pitch)
    z = jnp.zeros_like(cr)  # sin 0
    return jnp.stack(
        [
            jnp.stack([cp, sp * sr - z * cr, sp * cr + z * sr], -1),
            jnp.stack([z * cp, z * sp * sr + cr, z * sp * cr - sr], -1),
            jnp.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )


def euler_rates(rpy, omega_b):
    """ZYX Euler-angle rates ``(phidot, thetadot, psidot)`` of roll / pitch / yaw ``rpy`` from the body angular
    velocity ``omega_b``; ``(..., 3)``. ``cos(pitch)`` is floored at ``1e-3`` (the gimbal lock at 90 deg pitch).

    ``psidot = (sin(phi) w_y + cos(phi) w_z) / cos(theta)``, ``thetadot = cos(phi) w_y - sin(phi) w_z``,
    ``phidot = w_x + sin(theta) psidot``.
    """
    r, p = rpy[..., 0], rpy[..., 1]
    wx, wy, wz = omega_b[..., 0], omega_b[..., 1], omega_b[..., 2]
    cr, sr, cp = jnp.cos(r), jnp.sin(r), jnp.maximum(jnp.cos(p), 1e-3)
    psid = (sr * wy + cr * wz) / cp
    return jnp.stack([wx + jnp.sin(p) * psid, cr * wy - sr * wz, psid], -1)


def skew(v):
    """``[v]_x`` such that ``[v]_x w = v x w``; ``(..., 3) -> (..., 3, 3)``."""
    z = jnp.zeros_like(v[..., 0])
    return jnp.stack(
        [
            jnp.stack([z, -v[..., 2], v[..., 1]], -1),
            jnp.stack([v[..., 2], z, -v[..., 0]], -1),
            jnp.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def rot_x(phi):
    """``R_x(phi)``, ``(...) -> (..., 3, 3)``."""
    c, s = jnp.cos(phi), jnp.sin(phi)
    one, zero = jnp.ones_like(phi), jnp.zeros_like(phi)
    return jnp.stack(
        [jnp.stack([one, zero, zero], -1), jnp.stack([zero, c, -s], -1), jnp.stack([zero, s, c], -1)], -2
    )


def rot_y(theta):
    """``R_y(theta)``, ``(...) -> (..., 3, 3)``."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    one, zero = jnp.ones_like(theta), jnp.zeros_like(theta)
    return jnp.stack(
        [jnp.stack([c, zero, s], -1), jnp.stack([zero, one, zero], -1), jnp.stack([-s, zero, c], -1)], -2
    )


def rot_z(psi):
    """``R_z(psi)``, ``(...) -> (..., 3, 3)``."""
    c, s = jnp.cos(psi), jnp.sin(psi)
    one, zero = jnp.ones_like(psi), jnp.zeros_like(psi)
    return jnp.stack(
        [jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1), jnp.stack([zero, zero, one], -1)], -2
    )


def quat_mul(a, b):
    """Hamilton product ``a (x) b`` of ``(..., 4)`` quaternions: ``R(a b) = R(a) R(b)``."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_conj(q):
    """Conjugate ``(w, -x, -y, -z)`` (the inverse of a unit quaternion)."""
    return q * jnp.asarray([1.0, -1.0, -1.0, -1.0], q.dtype)


def quat_normalize(q):
    """``q / |q|`` along the last axis."""
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def rotvec_to_quat(v):
    """Unit quaternion of the rotation vector ``v`` (axis times angle), ``(..., 3) -> (..., 4)``.

    ``(cos(|v|/2), sin(|v|/2) v/|v|)``, evaluated with ``sinc`` so it is exact and smooth at ``v = 0``.
    """
    angle = jnp.sqrt(jnp.sum(v * v, -1))
    half = 0.5 * jnp.sinc(angle / (2.0 * jnp.pi))  # sin(|v|/2) / |v|
    return jnp.concatenate([jnp.cos(0.5 * angle)[..., None], half[..., None] * v], -1)


def rot_to_quat(r):
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix, ``(..., 3, 3) -> (..., 4)``.

    Shepperd's method: of the four candidate formulas (based on the trace and on each diagonal entry)
    the one with the largest denominator is used, so the result is accurate for every rotation,
    including half turns.
    """
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    tr = r00 + r11 + r22
    cands = jnp.stack([tr, r00, r11, r22], -1)
    k = jnp.argmax(cands, -1)
    d21, d02, d10 = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    s21, s02, s10 = r[..., 2, 1] + r[..., 1, 2], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 0] + r[..., 0, 1]
    t0 = jnp.sqrt(jnp.maximum(1.0 + tr, 1e-30))
    t1 = jnp.sqrt(jnp.maximum(1.0 + r00 - r11 - r22, 1e-30))
    t2 = jnp.sqrt(jnp.maximum(1.0 - r00 + r11 - r22, 1e-30))
    t3 = jnp.sqrt(jnp.maximum(1.0 - r00 - r11 + r22, 1e-30))
    q0 = jnp.stack([t0 * t0, d21, d02, d10], -1) / (2.0 * t0[..., None])
    q1 = jnp.stack([d21, t1 * t1, s10, s02], -1) / (2.0 * t1[..., None])
    q2 = jnp.stack([d02, s10, t2 * t2, s21], -1) / (2.0 * t2[..., None])
    q3 = jnp.stack([d10, s02, s21, t3 * t3], -1) / (2.0 * t3[..., None])
    q = jnp.select([k[..., None] == 0, k[..., None] == 1, k[..., None] == 2], [q0, q1, q2], q3)
    return q * jnp.where(q[..., :1] < 0, -1.0, 1.0).astype(q.dtype)


def rot_to_quat_trace(r):
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix by the trace formula alone, ``(..., 3, 3) -> (..., 4)``.

    Valid only away from half turns (``1 + trace > 0``; every angle below ``pi / 2``, e.g. HyQ in flight).
    :func:`rot_to_quat` (Shepperd's method) is the general one; the two differ in the last bit of float32,
    so the bounding cycle keeps this one and its stored cycle and committed results stay bit-reproducible.
    """
    w = 0.5 * jnp.sqrt(jnp.maximum(1.0 + r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2], 1e-9))
    return jnp.stack([w, (r[..., 2, 1] - r[..., 1, 2]) / (4 * w), (r[..., 0, 2] - r[..., 2, 0]) / (4 * w),
                      (r[..., 1, 0] - r[..., 0, 1]) / (4 * w)], -1)


def rpy_to_quat(rpy):
    """Unit quaternion of ``R_z(yaw) R_y(pitch) R_x(roll)``, ``(..., 3) -> (..., 4)``."""
    h = 0.5 * rpy
    cr, sr, cp, sp, cy, sy = jnp.cos(h[..., 0]), jnp.sin(h[..., 0]), jnp.cos(h[..., 1]), jnp.sin(h[..., 1]), \
        jnp.cos(h[..., 2]), jnp.sin(h[..., 2])
    return jnp.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        -1,
    )


def quat_to_rpy(q):
    """ZYX roll, pitch, yaw of a unit quaternion, ``(..., 4) -> (..., 3)``."""
    return rot_to_rpy(quat_to_rot(q))
