"""Leg kinematics of HyQ in the trunk frame: FK, foot Jacobians and analytic IK.

Each leg is a HAA joint about ``s_l * x_B`` (``s_l = HAA_AXIS_SIGN``) at ``B_p_HAA``, then a
planar HFE-KFE chain about the HAA-rotated ``y`` axis. With ``phi = s_l q_HAA``,

.. math::
    B\\_x_{foot} = B\\_p_{HAA} + R_x(\\phi)\\, v(q_{HFE}, q_{KFE}), \\qquad
    v = \\begin{bmatrix} -L_1 \\sin q_1 - L_2 \\sin(q_1+q_2) \\\\ 0 \\\\
        -l_0 - L_1 \\cos q_1 - L_2 \\cos(q_1+q_2) \\end{bmatrix}

with ``l_0 = 0.08`` (HAA to HFE), ``L_1 = 0.35``, ``L_2 = 0.341``. This is the map
``\\mathbb{K}(q)`` of Eq. 11 of Focchi et al. (2017) and its Jacobian ``J_f``.

All functions are pure, work for float32 and float64, and compose with ``jit``, ``vmap`` and
``grad``. Leg arrays are ``(4, 3)`` (legs LF, RF, LH, RH); joint vectors ``(12,)`` or ``(4, 3)``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from hyqjax.core import robot
from hyqjax.core.shapes import check_shape
from hyqjax.core.spatial import rot_x

_Q_SHAPES = ((..., 12), (..., 4, 3))


def _leg_consts(dtype):
    return (
        jnp.asarray(robot.B_P_HIP, dtype),
        jnp.asarray(robot.HAA_AXIS_SIGN, dtype),
    )


def _sagittal(q1, q2):
    """Foot position in the HAA-rotated leg plane relative to the HAA joint, and its partials."""
    l0, l1, l2 = robot.L_HAA_HFE, robot.L_UPPER, robot.L_LOWER
    s1, c1 = jnp.sin(q1), jnp.cos(q1)
    s12, c12 = jnp.sin(q1 + q2), jnp.cos(q1 + q2)
    zero = jnp.zeros_like(q1)
    v = jnp.stack([-l1 * s1 - l2 * s12, zero, -l0 - l1 * c1 - l2 * c12], -1)
    dv1 = jnp.stack([-l1 * c1 - l2 * c12, zero, l1 * s1 + l2 * s12], -1)
    dv2 = jnp.stack([-l2 * c12, zero, l2 * s12], -1)
    return v, dv1, dv2


def _as_legs(q, owner: str, name: str = "q"):
    """``q`` as ``(..., 4, 3)``; a shape other than ``(..., 12)`` / ``(..., 4, 3)`` is refused by name."""
    q = check_shape(jnp.asarray(q), _Q_SHAPES, f"kinematics.{owner}", name)
    return q.reshape(q.shape[:-1] + (4, 3)) if q.shape[-1] == 12 else q


def foot_positions(q: jax.Array) -> jax.Array:
    """Foot-centre positions in the trunk frame, ``B_x_feet``.

    Args:
      q: joint angles, shape ``(..., 12)`` or ``(..., 4, 3)``.
    Returns:
      ``(..., 4, 3)`` foot positions (m), legs LF, RF, LH, RH.
    """
    q = _as_legs(q, "foot_positions")
    hip, sign = _leg_consts(q.dtype)
    v, _, _ = _sagittal(q[..., 1], q[..., 2])
    rot = rot_x(sign * q[..., 0])
    return hip + jnp.einsum("...ij,...j->...i", rot, v)


def foot_jacobians(q: jax.Array) -> jax.Array:
    """Per-leg 3x3 foot Jacobians ``J_f = d B_x_foot / d q_leg`` (Eq. 11, Eq. 12).

    Args:
      q: joint angles, ``(..., 12)`` or ``(..., 4, 3)``.
    Returns:
      ``(..., 4, 3, 3)``; ``J[..., l, :, k]`` is the foot-l velocity per unit rate of joint k of leg l.
    """
    q = _as_legs(q, "foot_jacobians")
    _, sign = _leg_consts(q.dtype)
    v, dv1, dv2 = _sagittal(q[..., 1], q[..., 2])
    phi = sign * q[..., 0]
    rot = rot_x(phi)
    c, s = jnp.cos(phi), jnp.sin(phi)
    # d/dphi R_x(phi) v with v_y = 0: (0, -v_z c, -v_z s).
    d0 = sign[..., None] * jnp.stack([jnp.zeros_like(c), -v[..., 2] * c, -v[..., 2] * s], -1)
    d1 = jnp.einsum("...ij,...j->...i", rot, dv1)
    d2 = jnp.einsum("...ij,...j->...i", rot, dv2)
    return jnp.stack([d0, d1, d2], -1)


def stacked_jacobian(q: jax.Array) -> jax.Array:
    """The 12x12 block-diagonal Jacobian ``J`` of all feet (Eq. 10), ``dx_f = J dq``."""
    jl = foot_jacobians(q)
    out = jnp.zeros(jl.shape[:-3] + (12, 12), jl.dtype)
    for leg in range(4):
        out = out.at[..., 3 * leg : 3 * leg + 3, 3 * leg : 3 * leg + 3].set(jl[..., leg, :, :])
    return out


def foot_velocities(q: jax.Array, qd: jax.Array, jac: jax.Array | None = None) -> jax.Array:
    """Foot velocities in the trunk frame, ``J_f(q) qd`` per leg (Eq. 11); ``(..., 4, 3)``. ``jac``: ``J_f(q)``
    where the caller has it already (:func:`foot_jacobians` of the same ``q``)."""
    if jac is None:
        jac = foot_jacobians(q)
    else:
        jac = check_shape(jac, ((..., 4, 3, 3),), "kinematics.foot_velocities", "jac")
    return jnp.einsum("...lij,...lj->...li", jac, _as_legs(qd, "foot_velocities", "qd"))


def inverse_kinematics(x_feet: jax.Array, knee_sign: jax.Array | None = None) -> jax.Array:
    """Analytic inverse kinematics of the four legs.

    Args:
      x_feet: desired foot positions in the trunk frame, ``(..., 4, 3)``.
      knee_sign: sign of the KFE solution per leg, default ``robot.KNEE_SIGN`` (front knees
        negative, hind positive, as HyQ's joint ranges require).
    Returns:
      joint angles ``(..., 4, 3)``. Targets beyond reach are projected onto the reachable
      sphere (the leg stretches toward them), so the result is always finite.

    The HAA angle is ``phi = atan2(d_y, -d_z)`` (``d`` the foot relative to the hip, ``phi = s q_HAA``);
    the sagittal 2R problem uses ``cos q2 = (D - L1^2 - L2^2) / (2 L1 L2)``.
    """
    x_feet = check_shape(jnp.asarray(x_feet), ((..., 4, 3),), "kinematics.inverse_kinematics", "x_feet")
    dtype = x_feet.dtype
    hip, sign = _leg_consts(dtype)
    ks = jnp.asarray(robot.KNEE_SIGN if knee_sign is None else knee_sign, dtype)
    l0, l1, l2 = robot.L_HAA_HFE, robot.L_UPPER, robot.L_LOWER
    d = x_feet - hip
    phi = jnp.arctan2(d[..., 1], -d[..., 2])
    r = jnp.sqrt(d[..., 1] ** 2 + d[..., 2] ** 2)
    x = d[..., 0]
    z = -(r - l0)
    dist2 = x**2 + z**2
    c2 = jnp.clip((dist2 - l1**2 - l2**2) / (2 * l1 * l2), -1.0 + 1e-7, 1.0 - 1e-7)
    q2 = ks * jnp.arccos(c2)
    q1 = jnp.arctan2(-x, -z) - jnp.arctan2(l2 * jnp.sin(q2), l1 + l2 * jnp.cos(q2))
    return jnp.stack([phi * sign, q1, q2], -1)


def leg_extension(q: jax.Array) -> jax.Array:
    """Hip(HFE)-to-foot distance per leg (m), ``(..., 4)``: the leg length used in Fig. 8."""
    q = _as_legs(q, "leg_extension")
    l1, l2 = robot.L_UPPER, robot.L_LOWER
    return jnp.sqrt(l1**2 + l2**2 + 2 * l1 * l2 * jnp.cos(q[..., 2]))
