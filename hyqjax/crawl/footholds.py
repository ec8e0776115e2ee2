"""Where the trunk and the swing foot go: support triangles, the feet plane and reachable footholds (Section II).

* The body phase moves the centre of mass into the future support triangle (the three feet opposite the next
  swing leg) shrunk by a stability margin (:func:`shrink_triangle`, :func:`closest_in_triangle`), and
  orients the trunk toward the plane of the feet (:func:`feet_plane`, terrain adaptation).
* The swing foothold is one step ahead of the lift-off point, shortened when the foothold or the swing apex
  would leave the leg's workspace (:func:`reachable_foothold`).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics
from hyqjax.core import robot, smallmat

#: Step fractions tried, longest first, when the full step leaves the leg's workspace.
STEP_FRACTIONS = np.array([1.0, 0.85, 0.7, 0.55, 0.4, 0.25, 0.1])
#: Joint-limit margin (rad) a planned foothold and swing apex must keep.
REACH_MARGIN = 0.08


def feet_plane(x):
    """Roll and pitch of the least-squares plane ``z = a x + b y + c`` through the feet ``(4, 3)``."""
    a_mat = jnp.stack([x[:, 0], x[:, 1], jnp.ones_like(x[:, 0])], -1)
    coef = smallmat.solve3(a_mat.T @ a_mat + 1e-9 * jnp.eye(3, dtype=x.dtype), a_mat.T @ x[:, 2])
    pitch = jnp.arctan(-coef[0])  # feet lower in front -> nose down (positive pitch in ZYX about +y)
    roll = jnp.arctan(coef[1])
    return jnp.stack([roll, pitch])


def closest_in_triangle(p, a, b, c):
    """Closest point to ``p`` inside the triangle ``abc`` (2-D)."""

    def seg(p, u, v):
        d = v - u
        t = jnp.clip(jnp.dot(p - u, d) / (jnp.dot(d, d) + 1e-12), 0.0, 1.0)
        return u + t * d

    def cross(u, v):
        return u[0] * v[1] - u[1] * v[0]

    s1, s2, s3 = cross(b - a, p - a), cross(c - b, p - b), cross(a - c, p - c)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    cands = jnp.stack([seg(p, a, b), seg(p, b, c), seg(p, c, a)])
    best = cands[jnp.argmin(jnp.sum((cands - p) ** 2, -1))]
    return jnp.where(inside, p, best)


def shrink_triangle(a, b, c, margin):
    """Move the vertices toward the incentre so every edge moves inward by ``margin`` (bounded)."""
    la, lb, lc = jnp.linalg.norm(b - c), jnp.linalg.norm(c - a), jnp.linalg.norm(a - b)
    per = la + lb + lc + 1e-9
    centre = (la * a + lb * b + lc * c) / per
    area = 0.5 * jnp.abs((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0])
    r = 2.0 * area / per
    k = jnp.clip((r - margin) / (r + 1e-9), 0.05, 1.0)
    return centre + k * (a - centre), centre + k * (b - centre), centre + k * (c - centre)


def body_target(feet, leg, com_h, margin, body_height):
    """Trunk displacement ``(3,)`` of a body phase before ``leg`` swings (all in the horizontal frame ``H0``).

    The CoM goes to the point of the shrunk support triangle closest to the centre of the four feet (the
    smallest trunk motion that keeps the stability margin and keeps the trunk centred over the feet), and the
    trunk to ``body_height`` above the mean foot height (feet are below the trunk, mean z < 0).
    """
    tri = feet[jnp.asarray(robot.STANCE_LEGS)[leg]]
    a, b, c = shrink_triangle(tri[0, :2], tri[1, :2], tri[2, :2], margin)
    target_xy = closest_in_triangle(jnp.mean(feet[:, :2], 0), a, b, c)
    dz = jnp.mean(feet[:, 2]) + body_height
    return jnp.concatenate([target_xy - com_h[:2], dz[None]])


def reachable_foothold(step_height, max_leg_extension, leg, lift, target, n, h_r_b):
    """Shorten the step so the foothold and the swing apex stay inside the leg's workspace.

    The trunk holds still during a swing (Section II), so the swing foot's path is fixed in the trunk
    frame at planning time. The step ``lift -> target`` is scaled by the largest fraction in
    ``STEP_FRACTIONS`` for which the foothold and the apex (mid-step, ``step_height`` along ``n``) have
    IK solutions within the joint ranges minus ``REACH_MARGIN`` and within ``max_leg_extension``.
    A hind leg folded under a trunk that has lowered over the step cannot reach a full step forward
    (its HFE hits the end stop); without this the swing would stop at the end stop in mid-air.
    ``h_r_b``: ``hR_b`` of the measured roll and pitch (:class:`hyqjax.crawl.state.Measured`).
    """
    r_b = h_r_b.T
    q_min = jnp.asarray(robot.Q_MIN, lift.dtype).reshape(4, 3)[leg]
    q_max = jnp.asarray(robot.Q_MAX, lift.dtype).reshape(4, 3)[leg]
    hip = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, lift.dtype))

    def ok(frac):
        foot = lift + frac * (target - lift)
        apex = 0.5 * (lift + foot) + step_height * n
        pts = jnp.stack([foot, apex]) @ r_b.T  # (2, 3) in the trunk frame
        x = jnp.broadcast_to(hip, (2, 4, 3)).at[:, leg].set(pts)
        q = kinematics.inverse_kinematics(x)[:, leg]
        inside = jnp.all((q > q_min + REACH_MARGIN) & (q < q_max - REACH_MARGIN))
        ext = kinematics.leg_extension(q.reshape(2, 1, 3).repeat(4, 1).reshape(2, 12))[:, leg]
        return inside & jnp.all(ext < max_leg_extension)

    fracs = jnp.asarray(STEP_FRACTIONS, lift.dtype)
    feasible = jax.vmap(ok)(fracs)
    frac = jnp.where(jnp.any(feasible), fracs[jnp.argmax(feasible)], fracs[-1])
    return lift + frac * (target - lift)


def swing_foothold(lift, nominal_h, step, yaw, n):
    """Nominal foothold in ``H0`` before the workspace check.

    Every foot advances by one step length from where it lifts off (so the trunk, centred over the feet,
    advances one step per cycle), laterally back to its nominal distance from the trunk, rotated about the
    trunk by the heading change of one cycle, and at the lift-off height along the terrain normal ``n``
    (expected flat continuation; the haptic search handles the rest).
    """
    target = jnp.stack([lift[0] + step, nominal_h[1], lift[2]])
    c, s_ = jnp.cos(yaw), jnp.sin(yaw)
    target = jnp.stack([c * target[0] - s_ * target[1], s_ * target[0] + c * target[1], target[2]])
    return target - jnp.dot(target - lift, n) * n
