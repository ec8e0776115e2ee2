"""Foot references of the bound: touchdown targets, the kinematic adjustment (Section III, Eqs. 1-2) and IK.

Foot references are planned in a yaw-fixed odometry world frame ``W`` whose horizontal origin is
reset at every apex (the paper's "reset the world frame at every cycle"; ``W`` keeps its yaw, a
rotation that leaves the relative quantities unchanged). A stance foot stays where it touched
down, ``w_x_f^d = p_td`` (:func:`touchdown_update`); a swing foot moves in ``H`` from lift-off to
the next touchdown target (:func:`touchdown_target`, Eq. B8) with a ``clearance * sin(pi s)`` lift
above the ground.

*Linear* adjustment (Eq. 1):

.. math:: {}_h x_f^d = R_z(\\psi)^T ({}_w x_f^d - {}_w x_b), \\qquad
          {}_h \\dot x_f^d = R_z(\\psi)^T ({}_w \\dot x_f^d - {}_w \\dot x_b) \\qquad (1)

uses the *estimated actual* base position / velocity; switched off, the *desired* base motion
(height ``h``, velocity ``xdot^d`` since touchdown) replaces it. *Angular* adjustment (Eq. 2):
``b_x_f^d = bR_h(phi, theta) h_x_f^d`` with the *actual* roll and pitch; switched off, the desired
ones (the lean ``phi^d`` of Eq. 4, 0). Then the analytic IK gives ``q^d`` and
``qd^d = J^{-1} b_xdot_f^d`` (:func:`joint_references`).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hyqjax.bounding.params import LEG_PAIR, BoundingParams
from hyqjax.bounding.state import BoundingState
from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core import spatial


def touchdown_target(params: BoundingParams, v_est, v_err_apex, dy):
    """Touchdown foot positions (4, 2) in ``H``: the neutral point of the stride plus a Raibert correction,

    .. math:: {}_h x_{td} = x_{nom} + \\tfrac12 d_p T\\, \\dot x + k_{fp} (\\dot x_k - \\dot x^d), \\qquad
              {}_h y_{td} = y_{nom} + \\tfrac12 d_p T\\, \\dot y + k_{fp} (\\dot y_k - \\dot y^d) + \\Delta y_f   \\qquad (B8)

    ``xdot`` the current velocity estimate in ``H`` (with ``xdot = xdot^d`` the stride is ``D = d_p T xdot^d``,
    Fig. 2), ``xdot_k`` its apex sample minus the cycle's apex speed (so the correction vanishes on the cycle),
    ``Delta y_f`` the centrifugal foot offset (Eq. 4). The stance feet sweep symmetrically under the hips,
    so forward speed does not feed the pitch loop.
    """
    gait, g = params.gait, params.gains
    half = 0.5 * gait.duty[LEG_PAIR] * gait.period
    off = half[:, None] * v_est[None, :2] + params.switches.apex_feedback * g.k_foot * v_err_apex[None, :]
    off = jnp.clip(off, -0.15, 0.15)
    return gait.foot_xy + off + jnp.stack([jnp.zeros(4), jnp.full(4, 1.0) * dy], -1)


def touchdown_update(params: BoundingParams, state: BoundingState, touchdown, target_xy, psi) -> BoundingState:
    """At a leg's touchdown fix its stance foot in ``W`` at the target (``H`` -> ``W``, on the ground) and
    remember the base at that instant (at the nominal height, for the desired base motion of Eq. 1 off)."""
    dtype = state.pos.dtype
    target_h = jnp.concatenate([target_xy, jnp.zeros((4, 1), dtype)], -1)
    td_w = state.pos[None, :] + target_h @ spatial.rot_z(psi).T
    td_w = td_w.at[:, 2].set(robot.FOOT_RADIUS)
    base_now = jnp.broadcast_to(state.pos, (4, 3))
    base_now = base_now.at[:, 2].set(params.gait.height)
    return dataclasses.replace(state, foot_td=jnp.where(touchdown[:, None], td_w, state.foot_td),
                               base_td=jnp.where(touchdown[:, None], base_now, state.base_td))


def min_jerk(s):
    """Minimum-jerk blend ``sigma(s) = s^3 (10 - 15 s + 6 s^2)`` and ``d sigma / ds``."""
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s), 30.0 * s * s * (1.0 - s) ** 2


def foot_references(params: BoundingParams, state: BoundingState, t, rpy, rates, omega_b, stance, s_st, s_sw,
                    v_des, target_xy, dy):
    """Desired foot positions / velocities in ``B`` (4, 3) and the stance references in ``H`` (Eqs. 1-2).

    Returns ``(b_x, b_xd, h_x)``: ``h_x`` is each leg's reference in ``H`` (stance: the foot fixed in ``W``
    seen from the base; swing: the lift-off-to-target trajectory).
    """
    gait, sw = params.gait, params.switches
    psi = rpy[2]
    rz = spatial.rot_z(psi)
    lin, ang = sw.kinematic_linear, sw.kinematic_angular
    foot_z = jnp.asarray(robot.FOOT_RADIUS, t.dtype)
    # --- Stance (Eq. 1): foot fixed at foot_td in W; base actual (lin) or desired (1 - lin).
    t_st = s_st * gait.duty[LEG_PAIR] * gait.period  # time since touchdown
    v_des_w = rz @ jnp.concatenate([v_des, jnp.zeros(1, t.dtype)])
    base_des = state.base_td + t_st[:, None] * v_des_w[None, :]
    base_des = base_des.at[:, 2].set(gait.height)
    vel_des = jnp.broadcast_to(v_des_w.at[2].set(0.0), (4, 3))
    base = lin * state.pos[None, :] + (1.0 - lin) * base_des
    base_v = lin * state.vel[None, :] + (1.0 - lin) * vel_des
    r_st_w = state.foot_td - base
    rd_st_w = -base_v
    # --- Swing in H: min-jerk in x, y from lift-off to the touchdown target; z lifts above the ground.
    duty = gait.duty[LEG_PAIR]
    t_sw = (1.0 - duty) * gait.period
    sig, dsig = min_jerk(s_sw)
    xy = state.liftoff_h[:, :2] + (target_xy - state.liftoff_h[:, :2]) * sig[:, None]
    dxy = (target_xy - state.liftoff_h[:, :2]) * (dsig / t_sw)[:, None]
    base_z = lin * state.pos[2] + (1.0 - lin) * gait.height
    base_vz = lin * state.vel[2]
    lift = gait.clearance * jnp.sin(jnp.pi * s_sw)
    dlift = gait.clearance * jnp.pi * jnp.cos(jnp.pi * s_sw) / t_sw
    z = foot_z + lift - base_z
    dz = dlift - base_vz
    h_sw = jnp.concatenate([xy, z[:, None]], -1)
    hd_sw = jnp.concatenate([dxy, dz[:, None]], -1)
    # H velocity -> W' (yaw-rotating H): r_w = Rz h, rd_w = Rz (hd + psidot e_z x h).
    ez = jnp.array([0.0, 0.0, 1.0], t.dtype)
    r_sw_w = h_sw @ rz.T
    rd_sw_w = (hd_sw + rates[2] * jnp.cross(ez, h_sw)) @ rz.T
    r_w = jnp.where(stance[:, None], r_st_w, r_sw_w)
    rd_w = jnp.where(stance[:, None], rd_st_w, rd_sw_w)
    h_stance = r_st_w @ rz  # stance reference in H (Rz^T r)
    # --- Angular adjustment (Eq. 2): rotate into B with the actual (ang) or desired roll / pitch.
    roll_d = jnp.arctan(dy / gait.height)
    roll = ang * rpy[0] + (1.0 - ang) * roll_d
    pitch = ang * rpy[1]
    w_r_b = rz @ spatial.roll_pitch_to_rot(roll, pitch)
    omega = ang * omega_b + (1.0 - ang) * (w_r_b.T @ (rates[2] * ez))
    b_x = r_w @ w_r_b
    b_xd = rd_w @ w_r_b - jnp.cross(omega[None, :], b_x)
    return b_x, b_xd, jnp.where(stance[:, None], h_stance, h_sw)


def _solve3(jac, v):
    reg = 1e-4 * jnp.eye(3, dtype=jac.dtype)
    return jnp.linalg.solve(jac + reg, v[..., None])[..., 0]


def joint_references(b_x: jax.Array, b_xd: jax.Array):
    """``(q^d, qd^d)`` (12,) from foot references in ``B``: analytic IK (kept 0.02 rad inside the joint range)
    and ``qd^d = (J(q^d) + 1e-4 I)^{-1} b_xdot^d`` per leg, clipped to the velocity limit."""
    q_des = kinematics.inverse_kinematics(b_x).reshape(12)
    q_des = jnp.clip(q_des, robot.Q_MIN + 0.02, robot.Q_MAX - 0.02)
    qd_des = _solve3(kinematics.foot_jacobians(q_des), b_xd).reshape(12)
    return q_des, jnp.clip(qd_des, -robot.VELOCITY_LIMIT, robot.VELOCITY_LIMIT)
