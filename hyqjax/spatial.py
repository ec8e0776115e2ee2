"""Small rotation helpers (quaternions are MuJoCo's ``w, x, y, z``)."""
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
