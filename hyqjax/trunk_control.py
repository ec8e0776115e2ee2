"""Trunk controller: distribute the weight among the stance legs within friction cones.

Given stance feet positions relative to the centre of mass ``r_i`` (horizontal frame ``H``), find
ground reaction forces minimising ``sum_i |f_i|^2`` subject to the static wrench balance

.. math:: \\sum_i f_i = m g e_z, \\qquad \\sum_i r_i \\times f_i = 0,

(the 6 x 3n least-norm problem, solved in closed form with a small regulariser so a swing leg,
masked out, carries nothing), then each force is projected into its friction cone
``|f_t| <= mu f_n, f_n >= 0``. The feed-forward joint torques are ``tau_ff = -J_f^T B_R_H f`` per leg
(Section II, "whole body control ... redistribute the weight among the stance legs (c_st) ensuring
that friction constraints (mu) are not violated").
"""
from __future__ import annotations

import jax.numpy as jnp

from hyqjax import kinematics, robot, spatial


def distribute_wrench(r_feet_h, stance, force, torque, mu, up=(0.0, 0.0, 1.0)):
    """Ground reaction forces ``(4, 3)`` in ``H`` that produce the trunk wrench ``(force, torque)``.

    Args:
      r_feet_h: (4, 3) feet relative to the centre of mass in the horizontal frame.
      stance: (4,) booleans or 0/1 weights; swing legs get zero force.
      force, torque: (3,) desired wrench about the centre of mass (``m g e_z`` and 0 for pure weight support).
      mu: friction coefficient used for the cone projection.
      up: unit vector opposite gravity in ``H`` (``e_z``).
    """
    dtype = r_feet_h.dtype
    up = jnp.asarray(up, dtype)
    w = jnp.asarray(stance, dtype)
    a = jnp.concatenate([jnp.tile(jnp.eye(3, dtype=dtype), (1, 4)),
                         jnp.concatenate([spatial.skew(r_feet_h[i]) for i in range(4)], axis=1)], axis=0)
    a = a * jnp.repeat(w, 3)[None, :]
    b = jnp.concatenate([jnp.asarray(force, dtype), jnp.asarray(torque, dtype)])
    # Least-norm solution f = A^T (A A^T + eps I)^-1 b.
    f = a.T @ jnp.linalg.solve(a @ a.T + 1e-6 * jnp.eye(6, dtype=dtype), b)
    f = f.reshape(4, 3) * w[:, None]
    fn = jnp.maximum(f @ up, 0.0)
    ft = f - (f @ up)[:, None] * up
    ft_norm = jnp.sqrt(jnp.sum(ft**2, -1) + 1e-12)
    scale = jnp.minimum(1.0, mu * fn / ft_norm)
    return fn[:, None] * up + ft * scale[:, None]


def distribute_weight(r_feet_h, stance, mass, mu, up=(0.0, 0.0, 1.0)):
    """:func:`distribute_wrench` for the pure weight ``m g e_z`` and no moment."""
    up_v = jnp.asarray(up, r_feet_h.dtype)
    return distribute_wrench(r_feet_h, stance, mass * robot.GRAVITY * up_v, jnp.zeros(3, r_feet_h.dtype), mu, up)


def feedforward_torques(q, b_r_h, f_h):
    """``tau_ff = -J_f(q)^T (B_R_H f)`` per leg, (12,): the torques that make the feet push ``f`` on the ground."""
    f_b = jnp.einsum("ij,lj->li", b_r_h, f_h)
    jac = kinematics.foot_jacobians(q)
    return -jnp.einsum("lij,li->lj", jac, f_b).reshape(robot.N_JOINTS)
