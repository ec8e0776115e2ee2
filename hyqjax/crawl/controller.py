"""The statically stable crawl of Focchi et al. (2017), Section II, as a pure JAX controller.

One control tick (:func:`crawl_step`), following Fig. 2:

1. **plan** (:mod:`hyqjax.crawl.swing`): the desired feet ``x_f^d`` and velocities ``xd_f^d`` in the trunk
   frame from the body / swing quintics of the current phase (:mod:`hyqjax.crawl.state`);
2. **height reflex** (:mod:`hyqjax.reflex.step`, Fig. 3): during the downward part of the swing its corrected
   feet ``x_f^r`` and velocities ``xd_f^r`` (Eq. 11) replace the plan;
3. **inverse kinematics**: ``q^d = IK(x_f)`` (the reflex's own ``q^r`` while it is active) and
   ``qd^d = J^-1 xd_f`` (:func:`hyqjax.crawl.swing.joint_velocities`);
4. **trunk control** (:mod:`hyqjax.control.trunk`): a PD wrench on the trunk pose relative to ``H0`` (by leg
   odometry), distributed over the stance feet by the friction-constrained QP; ``tau_ff = -J^T f``;
5. **joint impedance** (:mod:`hyqjax.control.impedance`): ``tau = Kp (q^d - q) + Kd (qd^d - qd) + tau_ff``,
   within the actuators' velocity limit (:func:`speed_limited_torques`, ``joint_speed_limit``);
6. **phase logic**: after the nominal ``t_swing`` the foot keeps *searching* at ``search_speed`` until the
   estimated ground reaction force along the normal exceeds ``touchdown_force`` (haptic touchdown, footnote 1:
   30 N) or a limit is reached — the leg's extension ``max_leg_extension``, an end stop of the swing leg's
   joints (only without the reflex: with it the end-stop springs of Eq. 9 keep the joints off their limits and
   hand the motion to the stance legs) or ``max_search_depth`` — and stance is triggered anyway so the machine
   never gets stuck (Section IV). With ``shin_remedy`` the next swing leg and the search direction follow
   :mod:`hyqjax.crawl.remedy`.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hyqjax.control import impedance
from hyqjax.control import trunk as trunk_control
from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.crawl import edge
from hyqjax.crawl import remedy
from hyqjax.crawl import scheduled
from hyqjax.crawl import swing
from hyqjax.crawl.params import COM_OFFSET_B, FOOT_SEQUENCES, JOINT_SPEED_BAND, CrawlParams  # noqa: F401
from hyqjax.crawl.state import (  # noqa: F401  (re-exported)
    LIMIT_DEPTH, LIMIT_END_STOP, LIMIT_EXTENSION, LIMIT_NONE, PHASE_BODY, PHASE_SWING,
    CrawlInfo, CrawlState, Measured, crawl_init, measure, start_body_phase, start_swing_phase,
)
from hyqjax.reflex import step as reflex
from hyqjax.core.types import Controller, Observation


def pressing_feet(p: CrawlParams, foot_force_b, h_r_b):
    """``(4,)`` bool: the feet whose estimated ground reaction force along the vertical exceeds
    ``p.stance_min_force``."""
    up_b = h_r_b.T @ jnp.array([0.0, 0.0, 1.0], h_r_b.dtype)
    return (foot_force_b @ up_b) > p.stance_min_force


def loaded_stance(p: CrawlParams, stance, loaded, pressing):
    """The stance legs that carry the trunk: ``stance`` without the feet that pressed on the ground since their
    touchdown (``loaded``) and press no more (``~pressing``): a foot that slipped off an edge. Loading it anyway
    drives its leg at the torque the trunk's weight asks for (docs/notes/stepdown.md, "Divergences"). A foot that has
    not pressed yet (a swing that ended at a limit with its foot in the air) keeps its share, which pushes it down onto
    the ground. At least two legs carry the trunk (else every stance leg, as with ``stance_min_force`` 0: off)."""
    gated = stance * (~(loaded & ~pressing)).astype(stance.dtype)
    return jnp.where((p.stance_min_force > 0) & (jnp.sum(gated) >= 2), gated, stance)


def trunk_feedforward(p: CrawlParams, st: CrawlState, obs: Observation, m: Measured, p_des, v_des, rp_des, pressing):
    """Trunk PD wrench relative to ``H0`` (leg odometry), distributed by the QP over the loaded stance feet
    (:func:`loaded_stance`), as joint torques ``(12,)``; ``m``: the tick's measured kinematics."""
    dtype = p_des.dtype
    h_r_b, x_meas_b, rp_meas = m.h_r_b, m.x_b, m.rp
    r_h = jnp.einsum("ij,lj->li", h_r_b, x_meas_b - jnp.asarray(COM_OFFSET_B, dtype))
    # Trunk pose relative to H0 by leg odometry: stance feet are fixed in H0.
    feet_now_h = jnp.einsum("ij,lj->li", h_r_b, x_meas_b)
    w = st.stance / jnp.sum(st.stance)
    p_meas = jnp.sum(w[:, None] * (st.feet_h0 - feet_now_h), 0)
    v_feet_b = kinematics.foot_velocities(obs.q, obs.qd, jac=m.jac)
    v_meas = -jnp.sum(w[:, None] * jnp.einsum("ij,lj->li", h_r_b, v_feet_b + jnp.cross(obs.gyro, x_meas_b)), 0)
    up_h = jnp.array([0.0, 0.0, 1.0], dtype)
    force = p.mass * robot.GRAVITY * up_h + p.k_com * (p_des - p_meas) + p.d_com * (v_des - v_meas)
    rp_err = jnp.concatenate([rp_des - rp_meas, jnp.zeros(1, dtype)])
    torque = p.k_rot * rp_err - p.d_rot * (h_r_b @ obs.gyro)
    distribute = trunk_control.distribute_wrench if p.weight_qp else trunk_control.clipped_least_norm  # static
    f_h = distribute(r_h, loaded_stance(p, st.stance, st.loaded, pressing), force, torque, p.mu)
    return trunk_control.feedforward_torques(m.jac, h_r_b.T, f_h)


def speed_limited_torques(tau, qd, limit):
    """Joint torques within the actuators' velocity limit: ``tau_i`` where it brakes joint ``i`` (``tau_i qd_i <=
    0``), else ``tau_i clip((limit + JOINT_SPEED_BAND - |qd_i|) / JOINT_SPEED_BAND, 0, 1)``: full up to ``limit``,
    none from ``limit + JOINT_SPEED_BAND`` on, so no torque drives a joint past it. Below ``limit`` the torques
    are exactly ``tau``.

    Without it an ideal torque source spins an unloaded lower leg (about 0.036 kg m^2 about the knee, armature
    included) at 150 N m / 0.036 kg m^2 = 4,000 rad/s^2: a stance foot that has slipped off the edge, or every leg
    of a robot that has fallen over while the trunk controller still distributes its weight over them, reaches
    100 rad/s in about 12 ticks (docs/notes/stepdown.md, "Divergences")."""
    scale = jnp.clip((limit + JOINT_SPEED_BAND - jnp.abs(qd)) / JOINT_SPEED_BAND, 0.0, 1.0)
    return jnp.where((tau * qd > 0) & (scale < 1.0), tau * scale, tau)


def crawl_step(p: CrawlParams, st: CrawlState, obs: Observation, dt: float):
    """One control tick: plan, reflex, IK, joint impedance + feed-forward, phase transitions."""
    m = measure(obs)  # the measured kinematics (once a tick)
    feet_meas, rp_meas = m.feet, m.rp
    in_swing = st.phase == PHASE_SWING
    searching = in_swing & (st.t_phase >= p.t_swing)
    x_plan, xd_plan, swing_down, leg, p_des, v_des, rp_des, r_des = swing.planned_feet(
        p, st, m.h_r_b, jnp.where(searching, p.search_speed, 0.0))
    # --- height reflex (Fig. 2/3): active in the downward part of the swing.
    up_b = r_des.T @ jnp.array([0.0, 0.0, 1.0], x_plan.dtype)
    normal_b = r_des.T @ st.normal_h0
    active = swing_down & (p.use_reflex > 0.5)
    rin = reflex.ReflexInputs(x_des=x_plan, swing_leg=leg, active=active, n_t_des=normal_b, up=up_b)
    rstate, rout = reflex.reflex_step(st.reflex, rin, p.reflex, dt)
    x_cmd = jnp.where(active, rout.x_r, x_plan)
    xd_cmd = jnp.where(active, rout.xd_r, xd_plan)
    q_ik = kinematics.inverse_kinematics(x_cmd).reshape(12)
    q_min, q_max = jnp.asarray(robot.Q_MIN, q_ik.dtype), jnp.asarray(robot.Q_MAX, q_ik.dtype)
    q_cmd = jnp.clip(jnp.where(active, rout.q_r, q_ik), q_min + p.joint_margin, q_max - p.joint_margin)
    qd_cmd = p.velocity_feedforward * swing.joint_velocities(q_cmd, xd_cmd)
    # A reference held at a joint limit does not move further out.
    qd_cmd = jnp.where(((q_cmd <= q_min + p.joint_margin) & (qd_cmd < 0))
                       | ((q_cmd >= q_max - p.joint_margin) & (qd_cmd > 0)), 0.0, qd_cmd)
    pressing = pressing_feet(p, obs.foot_force, m.h_r_b)
    st = dataclasses.replace(st, loaded=st.loaded | (pressing & (st.stance > 0)))
    tau_ff = trunk_feedforward(p, st, obs, m, p_des, v_des, rp_des, pressing)
    tau = impedance.joint_impedance(p.gains, q_cmd, qd_cmd, obs.q, obs.qd, tau_ff)
    tau = speed_limited_torques(tau, obs.qd, p.joint_speed_limit)

    # --- mobility of every leg along the terrain normal (Eq. 12), at the measured configuration.
    mob = jax.vmap(lambda j: reflex.transmission_ratio(j, normal_b))(m.jac)  # m of Eq. 12 (no SVD)

    # --- phase logic.
    t_new = st.t_phase + dt
    nominal_done = t_new >= p.t_swing
    search_depth = jnp.where(in_swing & nominal_done, st.search_depth + p.search_speed * dt, st.search_depth)
    force_n = jnp.dot(obs.foot_force[leg], normal_b)
    touchdown = in_swing & (t_new >= 0.5 * p.t_swing) & (force_n > p.touchdown_force)
    ext_limit = kinematics.leg_extension(q_cmd)[leg] > p.max_leg_extension
    q_leg = jax.lax.dynamic_slice(q_cmd, (3 * leg,), (3,))
    lo = jax.lax.dynamic_slice(q_min, (3 * leg,), (3,))
    hi = jax.lax.dynamic_slice(q_max, (3 * leg,), (3,))
    # While the reflex is active its end-stop springs (Eq. 9) keep the swing joints off their limits and hand
    # the motion to the stance legs, so the search goes on; without it, an end stop ends the swing (Section IV).
    near = p.joint_margin + 0.01  # the reference is held joint_margin inside the range
    end_stop = jnp.any((q_leg - lo < near) | (hi - q_leg < near)) & ~active
    depth_limit = search_depth > edge.max_depth(p, st)
    limit = in_swing & nominal_done & (ext_limit | end_stop | depth_limit)
    limit_kind = jnp.where(ext_limit, LIMIT_EXTENSION, jnp.where(end_stop, LIMIT_END_STOP, LIMIT_DEPTH))
    stop = limit & ~touchdown & ~st.probing  # a probe's end triggers no stance (hyqjax.crawl.edge)
    limit_kind = jnp.where(stop, limit_kind, LIMIT_NONE)
    swing_end = touchdown | limit
    body_end = (~in_swing) & (t_new >= p.t_body)

    st1 = dataclasses.replace(st, t_phase=t_new, search_depth=search_depth, reflex=rstate, q_cmd=q_cmd)
    # After a swing: next leg (the remedy may bring the partner forward), body phase from the actual state.
    deep_leg = search_depth > p.deep_search
    sequence = remedy.follow_up(p, st.sequence, st.seq_index, leg, deep_leg, st.deep)
    st_after_swing = dataclasses.replace(st1, seq_index=(st.seq_index + 1) % 4, sequence=sequence,
                                         deep=st.deep.at[leg].set(deep_leg), n_steps=st.n_steps + 1,
                                         n_touchdowns=st.n_touchdowns + touchdown.astype(jnp.int32),
                                         n_limit_stops=st.n_limit_stops + (limit & ~touchdown).astype(jnp.int32))
    edge_lo, edge_hi, probe_leg, edge_depth = edge.after_swing(p, st, leg, deep_leg, touchdown, feet_meas)
    st_after_swing = dataclasses.replace(st_after_swing, edge_lo=edge_lo, edge_hi=edge_hi, probe_leg=probe_leg,
                                         edge_depth=edge_depth)
    # A new swing starts after a probe's end (touchdown or its depth: the leg's full swing from where it is,
    # hyqjax.crawl.edge) or after a body phase. The two never end on one tick, so one swing start a tick is computed,
    # from the state of whichever ended.
    after_probe = dataclasses.replace(st1, edge_lo=edge_lo, edge_hi=edge_hi, probe_leg=probe_leg,
                                      edge_depth=edge_depth, probing=False, step_back=edge.step_back(p, touchdown))
    swing_from = jax.tree_util.tree_map(lambda a, b: jnp.where(swing_end, a, b), after_probe, st1)
    st_swing = start_swing_phase(p, swing_from, m)
    st_after_swing = start_body_phase(p, st_after_swing, m)
    # The next state, one selection a leaf: the new swing after a probe's end or a body phase's end, the body phase
    # after any other swing's end, else the tick's own state.
    case = jnp.where(swing_end, jnp.where(st.probing, 1, 2), jnp.where(body_end, 1, 0)).astype(jnp.int32)
    st_next = jax.tree_util.tree_map(lambda a, b, c: jax.lax.select_n(case, a, b, c), st1, st_swing, st_after_swing)
    reflex_failed = (p.use_reflex > 0.5) & rout.failed
    info = CrawlInfo(phase=st.phase, swing_leg=leg, swing_down=swing_down, reflex_active=active, reflex_failed=reflex_failed,
                     mobility=mob, x_plan_b=x_plan, x_cmd_b=x_cmd, q_cmd=q_cmd, qd_cmd=qd_cmd, damping=rout.d_diag,
                     touchdown=touchdown, limit_stop=stop, limit_kind=limit_kind,
                     search_depth=search_depth, tilt_rp=rp_meas)
    return st_next, tau, info


def crawl_controller(dt: float) -> Controller:
    """The crawl as a :class:`hyqjax.core.types.Controller` ticking every ``dt`` seconds. Its parameters are a
    ``CrawlParams`` or a scheduled set (a per-leg set, :class:`hyqjax.crawl.scheduled.PerLegCrawlParams`, or a
    conditioned one), whose choice for the tick runs (:func:`hyqjax.crawl.scheduled.at_tick`; a ``CrawlParams``
    runs as itself)."""
    def init(p, obs):
        return crawl_init(scheduled.at_tick(p, None, obs), obs)

    def step(p, st, obs):
        return crawl_step(scheduled.at_tick(p, st, obs), st, obs, dt)

    return Controller(init, step, tie_rollout_carry=True)
