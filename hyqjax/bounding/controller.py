"""HyQ's bounding controller: stabilising feedback, speed and turning control, centrifugal compensation
(Orsolino et al., "Turning maneuvers strategy for quadrupedal bounding gait").

The controller is a :class:`hyqjax.core.types.Controller`; it sees only an
:class:`hyqjax.core.types.Observation` (joint states and torques, IMU, foot forces, time). Base height
and velocity are estimated (:mod:`hyqjax.bounding.estimator`); the only exception is
:func:`hyqjax.bounding.cycle.return_map`, which starts the estimator at the true apex state. One tick
(:func:`bounding_step`) is: estimate -> apex event (:func:`apex_update`) -> centrifugal compensation ->
touchdown events and foot references (:mod:`hyqjax.bounding.kinematic`) -> ground forces
(:func:`ground_forces`) -> feed-forward torques (Eq. B3) -> joint impedance
(:func:`hyqjax.control.impedance.joint_impedance`, stance or swing gains per leg).

Defaults: period 0.4 s, duty 0.4 per pair (hind stance at phases 0.05-0.45, front at 0.55-0.95, two
0.04 s flights), base height 0.6 m, feet 0.10 m inside the hips; 500 Hz control on MJX's 2 ms step.

The force reaches the joints through the leg Jacobian (the ground pushes the foot with ``f``, the leg
must push the ground with ``-f``):

.. math:: \\tau_{ff,i} = -J_i(q)^T\\, {}_bR_h\\, {}_h f_i, \\qquad {}_bR_h = (R_y(\\theta) R_x(\\phi))^T. \\qquad (B3)

Stabilising state feedback
--------------------------
Phase 0 is the middle of the flight before the hind stance: the apex. The feed-forward cycle alone
is unstable (return-map eigenvalues up to ~3.5, :mod:`hyqjax.bounding.stability`); three feedbacks
stabilise it, all zero on the limit cycle:

*Stance PD on the cycle reference* (Park & Kim's attitude control). During stance each leg adds
``beta(s)/2`` times (``h`` the foot's depth below the CoM; ``tau_y = -h f_x``)

.. math:: \\Delta f_z = k_{sz} (z^{ref} - z) + k_{s\\dot z} (\\dot z^{ref} - \\dot z), \\qquad
          \\Delta f_x = [k_{s\\theta} (\\theta - \\theta^{ref}) + k_{s\\dot\\theta} (\\dot\\theta - \\dot\\theta^{ref})] / h
          \\qquad (B7)

*Apex impulse scaling* (per cycle). At every apex ``k`` the controller samples ``s_k`` (:class:`Apex`),
integrates the errors ``I_k = I_{k-1} + (z* - z_k, theta_k - theta*, ...)`` (:func:`apex_errors`) and
scales this cycle's vertical impulses (:func:`cycle_amplitudes`):

.. math::
    \\alpha_k = 1 + k_z (z^* - z_k) + k_{\\dot z} (\\dot z^* - \\dot z_k) + k_{zI} I_{z,k}, \\qquad
    \\Delta_k = k_\\theta (\\theta_k - \\theta^*) + k_{\\dot\\theta} (\\dot\\theta_k - \\dot\\theta^*) + k_{\\theta I} I_{\\theta,k},

.. math:: a_{f,z} = a^*_{f,z}\\, \\alpha_k (1 + \\Delta_k), \\qquad a_{h,z} = a^*_{h,z}\\, \\alpha_k (1 - \\Delta_k).  \\qquad (B4)

*Foot placement* (Raibert, Eq. B8, :func:`hyqjax.bounding.kinematic.touchdown_target`).

Speed and turning control (Section IV)
--------------------------------------
Per cycle, from the apex sample of the estimated velocity in ``H`` (``xdot*`` the cycle's apex speed):

.. math:: a_{i,x} = a^*_{i,x} + K_{d,\\dot x} (\\dot x^d + \\dot x^* - \\dot x) + K_{I} I_{\\dot x}, \\qquad
          a_{i,y} = a^*_{i,y} + K_{d,\\dot y} (\\dot y^d - \\dot y) + K_I I_{\\dot y}              \\qquad (B5)

(the paper's law is the ``K_d`` term; ``K_I`` defaults to 0). ``apex_feedback`` gates B4, B5 and the
correction of B8. Continuously, from the gyro (``x_{f,i}`` the nominal foot x; ``f_y x_f`` is a yaw moment):

.. math:: a_{i,y} \\mathrel{+}= \\big[K_{d,\\psi} (\\dot\\psi^d - \\dot\\psi) + K_{p,\\psi} (\\psi^d - \\psi)\\big] / x_{f,i}. \\qquad (B6)

``K_{p,psi}`` (yaw-angle feedback) is **not** in the paper, whose law has the rate term only (``k_yaw=0``).
Roll is held by a stance PD shifting vertical force between the sides,
``a_{i,z} += -sgn(y_i) [K_\\phi (\\phi - \\phi^d) + K_{\\dot\\phi} \\dot\\phi] / (2 |y_f|)``.

Centrifugal compensation (Eqs. 3-4)
-----------------------------------
With ``r = xdot / psidot^d``, ``a_cf = xdot^2 / r = xdot psidot^d`` (Eq. 3). The feet move outward by
``Delta y_f = -h a_y / g``, the trunk is rolled by ``phi^d = atan(Delta y_f / h)`` (Eq. 4; into the
turn), and the stance legs add the matching lateral feed-forward ``a_{i,y} += a_{i,z} a_y / g``
(:func:`centrifugal_compensation`).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import estimator
from hyqjax.bounding import gait as bgait
from hyqjax.bounding import kinematic
from hyqjax.bounding.params import FRONT, LEG_PAIR, LEG_SIDE, Apex, BoundingParams
from hyqjax.bounding.state import BoundingInfo, BoundingState
from hyqjax.control import impedance
from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.core.types import Controller, Observation

#: Bounds of the per-cycle integrators of :func:`apex_errors` (height m, pitch rad, x / y speed m/s).
INTEGRATOR_LIMIT = np.array([0.5, 0.5, 2.0, 2.0])


def apex_errors(params: BoundingParams, apex: Apex, vel_h: jax.Array, v_des: jax.Array) -> jax.Array:
    """Errors integrated per cycle (Eqs. B4-B5 integral terms):
    ``(z* - z_k, theta_k - theta*, xdot^d + xdot* - xdot_k, ydot^d - ydot_k)``."""
    ref = params.apex_ref
    return jnp.stack([ref.z - apex.z, apex.pitch - ref.pitch, v_des[0] + ref.vx - vel_h[0], v_des[1] - vel_h[1]])


def cycle_amplitudes(params: BoundingParams, apex: Apex, vel_h: jax.Array, v_des: jax.Array, integ: jax.Array):
    """Eqs. B4-B5: this cycle's (4, 3) amplitudes from the apex sample and the per-cycle error integrals."""
    g, ref = params.gains, params.apex_ref
    on = params.switches.apex_feedback
    alpha = 1.0 + on * (g.k_height * (ref.z - apex.z) + g.k_height_rate * (ref.vz - apex.vz)
                        + g.k_height_int * integ[0])
    delta = on * (g.k_pitch * (apex.pitch - ref.pitch) + g.k_pitch_rate * (apex.pitch_rate - ref.pitch_rate)
                  + g.k_pitch_int * integ[1])
    alpha = jnp.clip(alpha, 0.5, 1.5)
    delta = jnp.clip(delta, -0.5, 0.5)
    scale_z = alpha * jnp.where(LEG_PAIR == FRONT, 1.0 + delta, 1.0 - delta)
    a = params.amplitudes
    ax = a[:, 0] + on * (g.k_speed * (v_des[0] + ref.vx - vel_h[0]) + g.k_speed_int * integ[2])
    ay = a[:, 1] + on * (g.k_lateral * (v_des[1] - vel_h[1]) + g.k_speed_int * integ[3])
    az = a[:, 2] * scale_z
    return jnp.stack([jnp.clip(ax, -400.0, 400.0), jnp.clip(ay, -300.0, 300.0), az], -1)


def apex_sample(pos, vel, rpy, rates) -> tuple[Apex, jax.Array]:
    """The apex state from the estimate and the IMU, and the estimated velocity in ``H`` (3,)."""
    vel_h = spatial.rot_z(rpy[2]).T @ vel
    return Apex(z=pos[2], pitch=rpy[1], vx=vel_h[0], vz=vel[2], pitch_rate=rates[1]), vel_h


def centrifugal_compensation(vx, yaw_rate_des, height, on=1.0):
    """Eqs. 3-4: lateral acceleration ``a_y = xdot psidot^d`` (``|a_cf| = xdot^2 / r``, ``r = xdot / psidot^d``),
    foot offset ``Delta y_f = -h a_y / g`` (outward of the turn, clipped to 0.12 m) and lean
    ``phi^d = atan(Delta y_f / h)``. Returns ``(a_y, dy, phi_lean)``, all zero when ``on == 0``."""
    a_y = on * vx * yaw_rate_des
    dy = jnp.clip(-height * a_y / robot.GRAVITY, -0.12, 0.12)
    return a_y, dy, jnp.arctan(dy / height)


def bounding_init(params: BoundingParams, obs: Observation) -> BoundingState:
    """Controller state at ``obs.time`` (assumed phase 0, the apex), estimator at ``params.init_estimate``."""
    dt = obs.q.dtype
    att = estimator.imu(obs)
    est = params.init_estimate.astype(dt)
    pos = jnp.stack([0.0, 0.0, est[0]]).astype(dt)
    vel = est[1:4]
    apex, vel_h = apex_sample(pos, vel, att.rpy, att.rates)
    v_des, _, _ = bgait.ramped_command(params.command, obs.time)
    nom = jnp.concatenate([params.gait.foot_xy, jnp.full((4, 1), robot.FOOT_RADIUS - params.gait.height)], -1)
    integ = apex_errors(params, apex, vel_h, v_des)
    return BoundingState(
        t_prev=jnp.asarray(obs.time, dt), cycle=bgait.cycle_index(params.gait, obs.time),
        pos=pos, vel=vel, foot_td=jnp.zeros((4, 3), dt), base_td=jnp.zeros((4, 3), dt), liftoff_h=nom.astype(dt),
        stance_prev=jnp.zeros(4, bool), apex=apex, integ=integ,
        cycle_amp=cycle_amplitudes(params, apex, vel_h, v_des, integ),
        apex_vel=vel_h[:2], yaw0=att.rpy[2], force_w=jnp.zeros(3, dt))


def apex_update(params: BoundingParams, state: BoundingState, pos, vel, att: estimator.Imu, t, v_des):
    """Apex event (a new gait cycle starts at phase 0): sample the apex state, integrate its errors, set this
    cycle's amplitudes (Eqs. B4-B5) and reset the odometry frame's horizontal origin to the base.

    Returns ``(state, new_cycle)`` with the estimate ``pos, vel`` (shifted) in ``state``.
    """
    cycle = bgait.cycle_index(params.gait, t)
    new_cycle = cycle != state.cycle
    apex_now, vel_h = apex_sample(pos, vel, att.rpy, att.rates)
    apex = jax.tree_util.tree_map(lambda a, b: jnp.where(new_cycle, a, b), apex_now, state.apex)
    apex_vel = jnp.where(new_cycle, vel_h[:2], state.apex_vel)
    lim = jnp.asarray(INTEGRATOR_LIMIT, pos.dtype)
    integ = jnp.where(new_cycle, jnp.clip(state.integ + apex_errors(params, apex_now, vel_h, v_des), -lim, lim),
                      state.integ)
    cycle_amp = jnp.where(new_cycle, cycle_amplitudes(params, apex_now, vel_h, v_des, integ), state.cycle_amp)
    shift = jnp.where(new_cycle, jnp.stack([pos[0], pos[1], 0.0]), jnp.zeros(3, pos.dtype))
    state = dataclasses.replace(state, cycle=cycle, pos=pos - shift, vel=vel, foot_td=state.foot_td - shift,
                                base_td=state.base_td - shift, apex=apex, apex_vel=apex_vel, integ=integ,
                                cycle_amp=cycle_amp)
    return state, new_cycle


def ground_forces(params: BoundingParams, state: BoundingState, att: estimator.Imu, beta, t, yaw_rate_des, yaw_err,
                  roll_des, a_cf):
    """Commanded ground forces (4, 3) in ``H``: ``beta(s) a_i`` (Eq. B1) with this cycle's amplitudes (B4, B5),
    the yaw feedback (B6), the stance PD on the cycle reference (B7), the roll PD and the centrifugal
    feed-forward ``a_z a_y / g`` (Eq. 4). Vertical amplitudes are kept >= 0 (a foot cannot pull)."""
    gait, gains = params.gait, params.gains
    rpy, rates = att.rpy, att.rates
    x_f = gait.foot_xy[:, 0]
    y_f = jnp.abs(gait.foot_xy[:, 1])
    yaw_force = (gains.k_yaw_rate * (yaw_rate_des - rates[2]) + gains.k_yaw * yaw_err) / x_f
    roll_moment = gains.k_roll * (rpy[0] - roll_des) + gains.k_roll_rate * rates[0]
    ref = bgait.cycle_reference(params, t / gait.period)
    on_st = params.switches.stance_feedback
    d_fz = on_st * (gains.k_stance_z * (ref[0] - state.pos[2]) + gains.k_stance_zdot * (ref[2] - state.vel[2]))
    d_fx = on_st * (gains.k_stance_pitch * (rpy[1] - ref[1]) + gains.k_stance_pitch_rate * (rates[1] - ref[3]))
    d_fx = d_fx / gait.height
    amp = state.cycle_amp
    az = amp[:, 2] + 0.5 * jnp.clip(d_fz, -600.0, 600.0) - LEG_SIDE * roll_moment / (2.0 * y_f)
    ax = amp[:, 0] + 0.5 * jnp.clip(d_fx, -500.0, 500.0)
    ay = amp[:, 1] + jnp.clip(yaw_force, -300.0, 300.0) + amp[:, 2] * a_cf / robot.GRAVITY
    return beta[:, None] * jnp.stack([ax, ay, jnp.maximum(az, 0.0)], -1)


def feedforward_torques(jac, f_h, rpy):
    """Eq. B3: ``tau_ff = -J^T bR_h f_h`` (12,) from the ground forces in ``H``."""
    f_b = f_h @ spatial.roll_pitch_to_rot(rpy[0], rpy[1])  # (hR_b^T f)^T
    return -jnp.einsum("lij,li->lj", jac, f_b).reshape(12)


def bounding_step(params: BoundingParams, state: BoundingState, obs: Observation):
    """One control tick (see the module docstring for the order). Returns ``(state, tau (12,), BoundingInfo)``."""
    gait = params.gait
    t = obs.time
    dtype = obs.q.dtype
    dt = jnp.maximum(t - state.t_prev, 0.0)
    att = estimator.imu(obs)
    psi = att.rpy[2]
    stance, s_st, s_sw = bgait.leg_phase(gait, t)
    beta = bgait.profile(gait, jnp.where(stance, s_st, -1.0))

    b_feet = kinematics.foot_positions(obs.q)
    jac = kinematics.foot_jacobians(obs.q)
    pos, vel = estimator.leg_odometry(obs, att, b_feet, jac, beta, state.pos, state.vel, state.force_w, dt,
                                      params.mass, params.gains.tau_est)
    v_des, yaw_rate_des, yaw_des_off = bgait.ramped_command(params.command, t)
    state, new_cycle = apex_update(params, state, pos, vel, att, t, v_des)

    vel_h = spatial.rot_z(psi).T @ state.vel
    a_cf, dy, roll_lean = centrifugal_compensation(vel_h[0], yaw_rate_des, gait.height, params.switches.centrifugal)

    touchdown = stance & ~state.stance_prev
    v_err_apex = state.apex_vel - v_des - jnp.stack([params.apex_ref.vx, 0.0])
    target_xy = kinematic.touchdown_target(params, vel_h, v_err_apex, dy)
    state = kinematic.touchdown_update(params, state, touchdown, target_xy, psi)
    b_x, b_xd, h_ref = kinematic.foot_references(params, state, t, att.rpy, att.rates, obs.gyro, stance, s_st, s_sw,
                                                 v_des, target_xy, dy)
    q_des, qd_des = kinematic.joint_references(b_x, b_xd)

    yaw_des = state.yaw0 + yaw_des_off
    yaw_err = jnp.arctan2(jnp.sin(yaw_des - psi), jnp.cos(yaw_des - psi))
    f_h = ground_forces(params, state, att, beta, t, yaw_rate_des, yaw_err, roll_lean, a_cf)
    tau_ff = feedforward_torques(jac, f_h, att.rpy)
    st12 = jnp.repeat(stance, 3)
    tau = jnp.where(st12, impedance.joint_impedance(params.gains.stance, q_des, qd_des, obs.q, obs.qd, tau_ff),
                    impedance.joint_impedance(params.gains.swing, q_des, qd_des, obs.q, obs.qd, tau_ff))

    new_state = dataclasses.replace(
        state, t_prev=jnp.asarray(t, dtype), liftoff_h=jnp.where(stance[:, None], h_ref, state.liftoff_h),
        stance_prev=stance, force_w=jnp.sum(f_h @ spatial.rot_z(psi).T, 0))
    info = BoundingInfo(est_pos=state.pos, est_vel=state.vel, vel_h=vel_h, apex=state.apex, new_cycle=new_cycle,
                        stance=stance, yaw_des=yaw_des, yaw_rate_des=yaw_rate_des, v_des=v_des, roll_des=roll_lean,
                        rpy=att.rpy, rates=att.rates, force_h=f_h, cycle=state.cycle)
    return new_state, tau, info


bounding_controller = Controller(bounding_init, bounding_step)
