"""Desired feet of the crawl in the trunk frame: body and swing quintics (Section II) and their velocities.

Body phase: the trunk pose relative to ``H0`` is ``p_des(t) = s(t / t_body) delta`` and
``R_des(t) = R(rp_start + s (rp_target - rp_start))`` with the rest-to-rest quintic ``s``; the stance feet,
fixed in ``H0``, are ``x_i^B = R_des^T (x_i^H0 - p_des)``.

Swing phase: the trunk holds still; the swing foot follows, in the terrain frame (normal ``n`` of Eq. 7),
``x^H0(t) = x_lift + s(tau) (x_target - x_lift) + z(tau) n - d_search(t) d`` with the swing profile of
:func:`hyqjax.control.trajectories.swing_profile` (a quintic apex of ``step_height``), ``tau = t / t_swing``
and, after the nominal swing, the haptic search ``d_search`` growing at ``search_speed`` along ``-d``
(``d = n`` in the paper, :func:`hyqjax.crawl.remedy.search_direction`; the remedy's forward part saturates at
``search_forward_limit``, :func:`hyqjax.crawl.remedy.search_forward_excess`). It is mapped into the trunk frame with
the *measured* roll and pitch (angular kinematic adjustment), so a trunk rotation such as the reflex's squat
does not drag the foot along in the world.

:func:`planned_feet` returns the positions and, by forward-mode differentiation in time, their velocities
``xd^B`` (the quintics' derivatives and the search speed); the controller maps them to joint velocity
references ``qd = J^-1 xd`` (:func:`joint_velocities`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from hyqjax.control import trajectories
from hyqjax.core import kinematics
from hyqjax.core import robot, smallmat
from hyqjax.core import spatial
from hyqjax.crawl import remedy
from hyqjax.crawl.params import CrawlParams
from hyqjax.crawl.state import PHASE_BODY, CrawlState

#: Damping (m) of the damped least-squares inverse ``J^T (J J^T + lambda^2 I)^-1`` near the stretched leg.
JACOBIAN_DAMPING = 0.02


def _feet_at(p: CrawlParams, st: CrawlState, t, search, h_r_b):
    in_body = st.phase == PHASE_BODY
    s_body = trajectories.quintic(t / p.t_body)
    s_body = jnp.where(in_body, s_body, 0.0)
    p_des = s_body * st.body_delta
    rp_des = st.rp_start + s_body * (st.rp_target - st.rp_start)
    r_des = spatial.roll_pitch_to_rot(rp_des[0], rp_des[1])
    leg = st.sequence[st.seq_index]
    s_tan, z_n = trajectories.swing_profile(t / p.t_swing, p.step_height)
    start = st.feet_h0[leg]
    swing_pos = start + s_tan * (st.swing_target - start) + z_n * st.normal_h0 - search * st.search_dir
    # the remedy's saturating forward search
    swing_pos = swing_pos - remedy.search_forward_excess(p, search, st.search_forward_left) * st.search_fwd
    x_b = jnp.einsum("ji,lj->li", r_des, st.feet_h0 - p_des)
    x_sw_b = h_r_b.T @ (swing_pos - p_des)
    x_b = jnp.where((~in_body) & (jnp.arange(4) == leg)[:, None], x_sw_b[None, :], x_b)
    return x_b, (p_des, rp_des, r_des)


def planned_feet(p: CrawlParams, st: CrawlState, h_r_b, search_rate):
    """Planned feet ``(4, 3)`` and velocities ``(4, 3)`` in the trunk frame, plus the body plan.

    Returns ``(x_b, xd_b, swing_down, leg, p_des, v_des, rp_des, r_des)``; ``h_r_b`` is ``hR_b`` of the measured
    roll and pitch (:class:`hyqjax.crawl.state.Measured`), ``search_rate`` the search speed now (0 before the
    nominal swing ends).
    """
    def f(t, s):
        return _feet_at(p, st, t, s, h_r_b)

    (x_b, (p_des, rp_des, r_des)), (xd_b, (v_des, _, _)) = jax.jvp(
        f, (st.t_phase, st.search_depth), (jnp.ones_like(st.t_phase), jnp.asarray(search_rate, st.t_phase.dtype)))
    leg = st.sequence[st.seq_index]
    swing_down = (st.phase != PHASE_BODY) & (st.t_phase / p.t_swing >= 0.5)
    return x_b, xd_b, swing_down, leg, p_des, v_des, rp_des, r_des


def joint_velocities(q, xd_b):
    """``qd = J_f(q)^-1 xd`` per leg ``(12,)`` (damped near the stretched leg), clipped to the velocity limit."""
    jac = kinematics.foot_jacobians(q)
    eye = jnp.eye(3, dtype=jac.dtype)
    qd = jnp.einsum("lji,lj->li", jac, smallmat.solve3(jac @ jnp.swapaxes(jac, -1, -2) + JACOBIAN_DAMPING**2 * eye, xd_b))
    return jnp.clip(qd.reshape(robot.N_JOINTS), -robot.VELOCITY_LIMIT, robot.VELOCITY_LIMIT)
