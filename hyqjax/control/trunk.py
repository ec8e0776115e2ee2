"""Trunk controller: distribute the trunk wrench among the stance legs inside friction pyramids.

Section II of Focchi et al. (2017): the whole-body controller of [12] (Focchi et al., "High-slope
terrain locomotion for torque-controlled quadruped robots", Auton. Robots 2016) "redistributes the
weight among the stance legs (c_st) ensuring that friction constraints (mu) are not violated". It is
the quadratic programme

.. math::

    \\min_f \\; \\tfrac12 \\lVert A f - w \\rVert_S^2 + \\tfrac{\\lambda}{2} \\lVert f \\rVert^2
    \\quad \\text{s.t.} \\quad f_{i,n} \\ge 0, \\quad |f_{i,t_1}|, |f_{i,t_2}| \\le \\tfrac{\\mu}{\\sqrt2} f_{i,n}
    \\quad (i \\in c_{st}), \\qquad f_i = 0 \\quad (i \\notin c_{st}),

with ``A = [I ... I; [r_1]x ... [r_4]x]`` (6 x 12, ``r_i`` the foot relative to the centre of mass),
``w = (force, torque)`` the desired trunk wrench, ``S`` weighting moments by ``1 / L_MOMENT^2``, a small
regulariser ``lambda`` (least-norm among the wrench-exact solutions) and the friction cone of each foot
linearised as the inscribed pyramid (4 faces) about the terrain normal ``n``.

:func:`solve_wrench_qp` solves it with a fixed number of ADMM iterations in the OSQP form
(Stellato et al. 2020): ``x <- (P + sigma I + C^T R C)^-1 (sigma x - q + C^T (R z - y))``, relaxation ``alpha``,
``z <- clip(alpha C x + (1 - alpha) z + y / rho, l, u)``, ``y <- y + rho (...)``. A fixed iteration count keeps
shapes static and the solver pure: ``jit``, ``vmap``, ``jacfwd`` and ``grad`` go through the unrolled
iterations. It starts from the least-norm solution projected onto the cones (the former distribution), so
few iterations are needed when the cones are inactive. ``tests/test_trunk.py`` checks it against SciPy's SLSQP
on random instances. The feed-forward joint torques are ``tau_ff = -J_f^T B_R_H f`` per leg.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot, smallmat
from hyqjax.core import spatial

#: Lever arm (m) by which the moment rows of the wrench residual are divided (about the hip half-width).
L_MOMENT = 0.4
#: Regulariser ``lambda`` on the (weight-normalised) forces.
REGULARISATION = 1e-2
#: ADMM step ``rho`` (normalised problem), its multiplier on equality rows, ``sigma`` and relaxation ``alpha``.
RHO, RHO_EQ_FACTOR, SIGMA, ALPHA = 0.25, 1e3, 1e-6, 1.6
#: Fixed number of ADMM iterations.
ITERATIONS = 120
#: Pyramid faces per foot: normal >= 0 and +-t1, +-t2 against mu / sqrt(2) times the normal.
ROWS_PER_FOOT = 5


def wrench_matrix(r_feet_h):
    """``A`` (6, 12): stacked ``[I; [r_i]x]`` so that ``A f = (sum f_i, sum r_i x f_i)``."""
    dtype = r_feet_h.dtype
    return jnp.concatenate([jnp.tile(jnp.eye(3, dtype=dtype), (1, 4)),
                            jnp.concatenate([spatial.skew(r_feet_h[i]) for i in range(4)], axis=1)], axis=0)


def _tangents(up):
    """Two unit tangents orthogonal to ``up`` (forming a right-handed frame with it)."""
    ref = jnp.where(jnp.abs(up[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], up.dtype), jnp.array([0.0, 1.0, 0.0], up.dtype))
    t1 = ref - jnp.dot(ref, up) * up
    t1 = t1 / jnp.linalg.norm(t1)
    return t1, jnp.cross(up, t1)


def friction_constraints(stance, mu, up):
    """``(C, l, u)`` with ``l <= C f <= u`` encoding the unilateral and friction-pyramid constraints (20 x 12).

    Per foot: ``n . f in [0, inf)`` for a stance leg and ``[0, 0]`` for a swing leg, and
    ``(+-t_k - mu/sqrt(2) n) . f <= 0`` (which forces the tangential part to zero when the normal part is).
    """
    dtype = up.dtype
    t1, t2 = _tangents(up)
    mu_p = mu / np.sqrt(2.0)
    faces = jnp.stack([up, t1 - mu_p * up, -t1 - mu_p * up, t2 - mu_p * up, -t2 - mu_p * up])  # (5, 3)
    c = jnp.kron(jnp.eye(4, dtype=dtype), faces)  # (20, 12), block-diagonal
    st = jnp.asarray(stance, dtype) > 0.5
    lo = jnp.stack([jnp.zeros(4, dtype)] + [jnp.full(4, -jnp.inf, dtype)] * 4, 1)
    hi = jnp.stack([jnp.where(st, jnp.inf, 0.0).astype(dtype)] + [jnp.zeros(4, dtype)] * 4, 1)
    eq = jnp.stack([~st] + [jnp.zeros(4, bool)] * 4, 1)
    return c, lo.reshape(-1), hi.reshape(-1), eq.reshape(-1)


def least_norm_forces(a, stance, b):
    """``f = A_s^T (A_s A_s^T + eps I)^-1 b`` with swing columns masked out: the unconstrained distribution."""
    dtype = a.dtype
    w = jnp.repeat(jnp.asarray(stance, dtype), 3)
    a_s = a * w[None, :]
    f = a_s.T @ smallmat.spd_solve(a_s @ a_s.T + 1e-6 * jnp.eye(6, dtype=dtype), b)
    return f * w


def project_to_cones(f, mu, up):
    """Each foot's force ``(4, 3)`` projected into its inscribed friction pyramid (normal clipped at 0, tangents scaled)."""
    t1, t2 = _tangents(up)
    fn = jnp.maximum(f @ up, 0.0)
    lim = mu / np.sqrt(2.0) * fn
    c1 = jnp.clip(f @ t1, -lim, lim)
    c2 = jnp.clip(f @ t2, -lim, lim)
    return fn[:, None] * up + c1[:, None] * t1 + c2[:, None] * t2


def solve_wrench_qp(r_feet_h, stance, force, torque, mu, up=(0.0, 0.0, 1.0), weight=None,
                    iterations: int = ITERATIONS):
    """Feet forces ``(4, 3)`` of the friction-constrained QP (module docstring), by fixed-iteration ADMM.

    Args:
      r_feet_h: (4, 3) feet relative to the centre of mass (horizontal frame ``H``).
      stance: (4,) 0/1; swing legs get zero force.
      force, torque: (3,) desired wrench about the centre of mass.
      mu: friction coefficient (the pyramid's faces use ``mu / sqrt(2)``).
      up: terrain normal in ``H``.
      weight: force scale (N) normalising the problem (default ``|force|``); any positive value gives the
        same solution, it only conditions the iterations.
      iterations: ADMM iterations (static).
    Returns:
      (4, 3) forces; swing legs exactly zero.
    """
    dtype = r_feet_h.dtype
    up = jnp.asarray(up, dtype)
    up = up / jnp.linalg.norm(up)
    stance = jnp.asarray(stance, dtype)
    b = jnp.concatenate([jnp.asarray(force, dtype), jnp.asarray(torque, dtype)])
    scale = jnp.maximum(jnp.linalg.norm(b[:3]) if weight is None else jnp.asarray(weight, dtype), 1.0)
    a = wrench_matrix(r_feet_h)
    s = jnp.concatenate([jnp.ones(3, dtype), jnp.full(3, 1.0 / L_MOMENT**2, dtype)])
    bn = b / scale
    p_mat = a.T @ (s[:, None] * a) + REGULARISATION * jnp.eye(12, dtype=dtype)
    q_vec = -a.T @ (s * bn)
    c, lo, hi, eq = friction_constraints(stance, mu, up)
    rho = jnp.where(eq, RHO * RHO_EQ_FACTOR, RHO).astype(dtype)
    k_mat = p_mat + SIGMA * jnp.eye(12, dtype=dtype) + c.T @ (rho[:, None] * c)
    chol = jax.scipy.linalg.cho_factor(k_mat)
    x0 = project_to_cones(least_norm_forces(a, stance, bn).reshape(4, 3), mu, up).reshape(12)
    x0 = x0 * jnp.repeat(stance, 3)
    z0 = jnp.clip(c @ x0, lo, hi)
    y0 = jnp.zeros_like(z0)

    def body(_, carry):
        x, z, y = carry
        x_t = jax.scipy.linalg.cho_solve(chol, SIGMA * x - q_vec + c.T @ (rho * z - y))
        z_t = c @ x_t
        x = ALPHA * x_t + (1.0 - ALPHA) * x
        z_r = ALPHA * z_t + (1.0 - ALPHA) * z
        z_new = jnp.clip(z_r + y / rho, lo, hi)
        y = y + rho * (z_r - z_new)
        return x, z_new, y

    x, _, _ = jax.lax.fori_loop(0, iterations, body, (x0, z0, y0))
    # Clean up the O(ADMM tolerance) constraint residual: exact cones, swing legs exactly zero.
    f = project_to_cones(x.reshape(4, 3), mu, up) * stance[:, None]
    return f * scale


def distribute_wrench(r_feet_h, stance, force, torque, mu, up=(0.0, 0.0, 1.0)):
    """Ground reaction forces ``(4, 3)`` in ``H`` that produce the trunk wrench ``(force, torque)`` (the QP)."""
    return solve_wrench_qp(r_feet_h, stance, force, torque, mu, up)


def clipped_least_norm(r_feet_h, stance, force, torque, mu, up=(0.0, 0.0, 1.0)):
    """The least-norm forces meeting the wrench, each projected into its pyramid afterwards (no longer meets the
    wrench once a projection acts): the distribution before the QP, kept for ablation."""
    dtype = r_feet_h.dtype
    up = jnp.asarray(up, dtype)
    b = jnp.concatenate([jnp.asarray(force, dtype), jnp.asarray(torque, dtype)])
    f = least_norm_forces(wrench_matrix(r_feet_h), stance, b).reshape(4, 3)
    return project_to_cones(f, mu, up) * jnp.asarray(stance, dtype)[:, None]


def distribute_weight(r_feet_h, stance, mass, mu, up=(0.0, 0.0, 1.0)):
    """:func:`distribute_wrench` for the pure weight ``m g e_z`` and no moment."""
    up_v = jnp.asarray(up, r_feet_h.dtype)
    return distribute_wrench(r_feet_h, stance, mass * robot.GRAVITY * up_v, jnp.zeros(3, r_feet_h.dtype), mu, up)


def feedforward_torques(jac, b_r_h, f_h):
    """``tau_ff = -J_f(q)^T (B_R_H f)`` per leg, (12,): the torques that make the feet push ``f`` on the ground;
    ``jac``: the feet's Jacobians ``J_f(q)``, ``(4, 3, 3)`` (:func:`hyqjax.core.kinematics.foot_jacobians`)."""
    f_b = jnp.einsum("ij,lj->li", b_r_h, f_h)
    return -jnp.einsum("lij,li->lj", jac, f_b).reshape(robot.N_JOINTS)
