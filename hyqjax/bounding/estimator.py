"""What the bounding controller knows of its trunk: IMU attitude and rates, leg-odometry height and velocity.

IMU
---
``W_R_B`` from the IMU quaternion, roll / pitch / yaw ``(phi, theta, psi)`` (ZYX) and the Euler-angle
rates from the body angular velocity ``omega_B`` (:func:`hyqjax.core.spatial.euler_rates`):

.. math:: \\dot\\psi = \\frac{\\sin\\phi\\, \\omega_y + \\cos\\phi\\, \\omega_z}{\\cos\\theta}, \\quad
          \\dot\\theta = \\cos\\phi\\, \\omega_y - \\sin\\phi\\, \\omega_z, \\quad
          \\dot\\phi = \\omega_x + \\sin\\theta\\, \\dot\\psi.

The horizontal frame ``H`` is the trunk frame with roll and pitch removed:
``hR_b = R_y(theta) R_x(phi)`` (:func:`hyqjax.core.spatial.roll_pitch_to_rot`), ``W`` and ``H`` differ by ``R_z(psi)``
(:func:`hyqjax.core.spatial.rot_z`).

Leg odometry
------------
A stance foot is static, so each stance leg measures the base velocity and height

.. math:: v_i = -{}_W R_B\\, (J_i \\dot q_i + \\omega \\times {}_B x_i), \\qquad
          z_i = -({}_W R_B\\, {}_B x_i)_z + r_{foot}.

The estimate predicts with the commanded ground forces, ``v+ = v + dt (sum_i W_f_i / m - g e_z)``,
``p+ = p + dt v``, and blends the leg measurements weighted by the stance profile ``beta(s_i)`` with
time constant ``tau_est``: ``v = v+ + alpha (v_meas - v+)``, ``alpha = clip(sum_i beta_i dt / tau_est, 0, 1)``
(:func:`leg_odometry`). No ground truth reaches the controller.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.core.types import Observation


class Imu(NamedTuple):
    """Attitude from the IMU: ``w_r_b`` (3, 3), ``rpy`` (3,) roll / pitch / yaw, ``rates`` (3,) Euler-angle rates."""

    w_r_b: jax.Array
    rpy: jax.Array
    rates: jax.Array


def imu(obs: Observation) -> Imu:
    """Rotation, roll / pitch / yaw and Euler-angle rates from the IMU quaternion and gyro."""
    w_r_b = spatial.quat_to_rot(obs.quat)
    rpy = spatial.rot_to_rpy(w_r_b)
    return Imu(w_r_b, rpy, spatial.euler_rates(rpy, obs.gyro))


def leg_odometry(obs: Observation, att: Imu, b_feet, jac, weight, pos, vel, force_w, dt, mass, tau_est):
    """One estimator tick: ``(pos, vel)`` in ``W`` (z above the ground) from the previous estimate.

    Args:
      b_feet: (4, 3) foot positions in ``B``; jac: (4, 3, 3) foot Jacobians at ``obs.q``.
      weight: (4,) stance weights ``beta(s_i)`` (0 in swing).  force_w: (3,) last commanded ground force in ``W``.
      dt: time since the previous tick.  mass: mass the prediction assumes.  tau_est: blending time constant.
    """
    b_vfeet = jnp.einsum("lij,lj->li", jac, obs.qd.reshape(4, 3))
    rel_w = b_feet @ att.w_r_b.T
    relv_w = (b_vfeet + jnp.cross(obs.gyro[None, :], b_feet)) @ att.w_r_b.T
    wsum = jnp.sum(weight)
    v_meas = -jnp.sum(weight[:, None] * relv_w, 0) / jnp.maximum(wsum, 1e-6)
    z_meas = -jnp.sum(weight * rel_w[:, 2]) / jnp.maximum(wsum, 1e-6) + robot.FOOT_RADIUS
    grav = jnp.array([0.0, 0.0, robot.GRAVITY], obs.q.dtype)
    vel_pred = vel + dt * (force_w / mass - grav)
    pos_pred = pos + dt * vel
    alpha = jnp.clip(wsum * dt / tau_est, 0.0, 1.0)
    vel_new = vel_pred + alpha * (v_meas - vel_pred)
    pos_new = pos_pred.at[2].set(pos_pred[2] + alpha * (z_meas - pos_pred[2]))
    return pos_new, vel_new
