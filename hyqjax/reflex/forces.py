"""Virtual forces, damping schedule and end-stop springs of the height reflex
(Focchi et al. 2017, Section III-B Eq. 2-6, III-C Eq. 9, III-E Fig. 7).

The reflex moves a massless model of the robot with viscous joints, ``tau = D_r qd`` (Eq. 1),
under virtual forces at the feet: a spring pulls the swing foot toward its plan (Eq. 2), the
vertical part of that force is balanced by stance-foot forces (Eq. 3, 6) chosen such that the
stance feet keep their mutual distances (Eq. 4, 5), and joint-limit springs repel the joints
from their end stops (Eq. 9). See :mod:`hyqjax.reflex.geometry` for the frame and leg-order
conventions.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from hyqjax.core import robot
from hyqjax.reflex.geometry import (
    cofactors3,
    det3,
    dot_last,
    matvec,
    select_legs,
    usum,
    safe_normalize,
    stance_edges,
    stance_selector,
    swing_one_hot,
)
from hyqjax.reflex.params import ReflexParams
from hyqjax.core.spatial import skew

#: Stance triangles thinner than this are treated as collinear (Eq. 6 singular): the measure is
#: ``|x~_1 x x~_2| / max_k |x~_k|^2`` (twice the area over the longest edge squared; about the
#: smallest angle of the triangle in rad). HyQ's crawl triangles are around 0.8.
COLLINEAR_TOL = 1e-3
#: Edge-foot incidence of the stance triangle for the pairs 1-2, 2-3, 3-1 of Eq. 4:
#: ``x~ = _INCIDENCE @ x_st``.
_INCIDENCE = ((1.0, -1.0, 0.0), (0.0, 1.0, -1.0), (-1.0, 0.0, 1.0))
#: Damping schedule shapes accepted by :func:`damping_schedule`.
SCHEDULE_SHAPES = ("smoothstep", "linear")


def _vec3(x, dtype):
    return jnp.broadcast_to(jnp.asarray(x, dtype), (3,))


# ---------------------------------------------------------------------------------------------
# Eq. 2: swing-foot virtual spring
# ---------------------------------------------------------------------------------------------


def effective_k_x(params: ReflexParams, dtype=jnp.float32) -> jax.Array:
    """Diagonal of ``K_x`` actually used: ``min(k_x, k_x_max)`` element-wise, shape ``(3,)``."""
    with jax.named_scope("effective_k_x"):
        return jnp.minimum(_vec3(params.k_x, dtype), _vec3(params.k_x_max, dtype))


def virtual_spring_force(x_des_sw: jax.Array, x_r_sw: jax.Array, params: ReflexParams) -> jax.Array:
    """Swing-foot virtual force ``f_sw = K_x (x_sw^d - x_sw^r)`` (Eq. 2). Broadcasts.

    ``K_x = diag(min(k_x, k_x_max))``: the upper bound ``k_x_max`` keeps the explicit integration
    of :func:`hyqjax.reflex.step.reflex_step` stable. Units: m -> N.
    """
    with jax.named_scope("virtual_spring_force"):
        x_r_sw = jnp.asarray(x_r_sw)
        dtype = jnp.result_type(x_r_sw, jnp.asarray(x_des_sw))
        return effective_k_x(params, dtype) * (jnp.asarray(x_des_sw, dtype) - x_r_sw.astype(dtype))


# ---------------------------------------------------------------------------------------------
# Section III-E: damping schedule
# ---------------------------------------------------------------------------------------------


def damping_schedule(mobility: jax.Array, params: ReflexParams, shape: str = "smoothstep"):
    """Swing and stance joint damping as a function of the swing-leg mobility (Fig. 7).

    With ``u = clip((m - m_min) / (m_max - m_min), 0, 1)`` and a blend ``s(u)``:

    .. math:: D_{sw} = D_{sw,max} + (D_{sw,min} - D_{sw,max})\\, s(u),\\qquad
              D_{st} = D_{st,min} + (D_{st,max} - D_{st,min})\\, s(u)

    so for ``m >= m_max`` the swing leg has ``D_sw_min`` and the stance legs ``D_st_max`` (the
    swing leg does all the motion, as in normal operation) and for ``m <= m_min`` the swing leg
    has ``D_sw_max`` and the stance legs ``D_st_min`` (motion goes to the stance legs, the trunk
    lowers). The paper does not specify the curve between the thresholds; ``shape`` selects it:

    * ``"smoothstep"`` (default): ``s = 3u^2 - 2u^3``, continuous with a continuous derivative
      (C^1), so the damping has no kinks at ``m_min``/``m_max``;
    * ``"linear"``: ``s = u``, continuous, piecewise linear (kinks at the thresholds).

    Differentiable in ``mobility`` and in every parameter it uses. Broadcasts over ``mobility``.

    Returns:
      ``(d_swing, d_stance)``, each with the shape of ``mobility`` (N m s/rad).
    """
    if shape not in SCHEDULE_SHAPES:
        raise ValueError(f"damping_schedule shape must be one of {SCHEDULE_SHAPES}, got {shape!r}")
    with jax.named_scope("damping_schedule"):
        m = jnp.asarray(mobility)
        dtype = m.dtype if jnp.issubdtype(m.dtype, jnp.floating) else jnp.float32
        m = m.astype(dtype)
        p = params.astype(dtype)
        u = jnp.clip((m - p.m_min) / (p.m_max - p.m_min), 0.0, 1.0)
        s = u * u * (3.0 - 2.0 * u) if shape == "smoothstep" else u
        d_sw = p.d_sw_max + (p.d_sw_min - p.d_sw_max) * s
        d_st = p.d_st_min + (p.d_st_max - p.d_st_min) * s
        return d_sw, d_st


def damping_matrix_diag(
    swing_leg: jax.Array, mobility: jax.Array, params: ReflexParams, shape: str = "smoothstep"
) -> jax.Array:
    """Diagonal ``(12,)`` of the virtual damping matrix ``D_r`` (Eq. 1, Section III-E).

    The three joints of the swing leg get ``d_swing`` and the nine stance joints ``d_stance``
    from :func:`damping_schedule` evaluated at ``mobility`` (the swing leg's velocity
    transformation ratio, a scalar). ``swing_leg`` may be traced: a one-hot mask is used.
    """
    with jax.named_scope("damping_matrix_diag"):
        m = jnp.asarray(mobility)
        dtype = m.dtype if jnp.issubdtype(m.dtype, jnp.floating) else jnp.float32
        d_sw, d_st = damping_schedule(m.astype(dtype), params, shape)
        hot = swing_one_hot(swing_leg, dtype)
        per_leg = hot * d_sw + (1.0 - hot) * d_st
        return jnp.repeat(per_leg, 3, axis=-1)


# ---------------------------------------------------------------------------------------------
# Eq. 9: end-stop springs
# ---------------------------------------------------------------------------------------------


def end_stop_torques(q: jax.Array, params: ReflexParams, q_min=robot.Q_MIN, q_max=robot.Q_MAX) -> jax.Array:
    """Virtual end-stop spring torques (Eq. 9), ``(..., 12)``.

    .. math:: \\tau_{kl} = \\mathbf 1(q > q_{max} - \\Delta)\\, K_{kl}\\,(q_{max} - \\Delta - q)
              + \\mathbf 1(q < q_{min} + \\Delta)\\, K_{kl}\\,(q_{min} + \\Delta - q)

    exactly as printed: ``tau_kl`` is zero outside the band of width ``Delta`` next to each limit
    and, inside it, is the *restoring* torque of a spring anchored at the threshold: negative
    near ``q_max`` and positive near ``q_min``, i.e. pointing away from the end stop.

    Sign convention (deviation from the printed Eq. 10): the paper writes
    ``qd = D^-1 (J^T f - tau_kl)``; with Eq. 9's sign that would *attract* the joint into the
    end stop, contradicting the text ("a virtual strip that pulls the joint away"). The reflex
    therefore *adds* this torque, ``qd = D^-1 (J^T f + tau_kl)``
    (:func:`hyqjax.reflex.step.reflex_step`), so the net effect repels. Equivalently, Eq. 10 holds as
    printed for ``-tau_kl``.

    The joint settles where ``K_kl (q - q_th)`` balances the virtual-force torque, so it stops
    before the limit iff that torque is below ``K_kl * Delta`` (50 N m with Table I).

    Args:
      q: joint angles ``(..., 12)``.
      params: uses ``k_kl`` and ``delta`` (scalars or ``(12,)``).
      q_min, q_max: joint ranges ``(12,)``; default HyQ's (``robot.Q_MIN``, ``robot.Q_MAX``).
    """
    with jax.named_scope("end_stop_torques"):
        q = jnp.asarray(q)
        dtype = q.dtype
        k = jnp.asarray(params.k_kl, dtype)
        delta = jnp.asarray(params.delta, dtype)
        hi = jnp.asarray(q_max, dtype) - delta
        lo = jnp.asarray(q_min, dtype) + delta
        return jnp.where(q > hi, k * (hi - q), 0.0) + jnp.where(q < lo, k * (lo - q), 0.0)


# ---------------------------------------------------------------------------------------------
# Eq. 3-6: distribution of the swing force to the stance feet
# ---------------------------------------------------------------------------------------------


def leg_compliances(j_legs: jax.Array, d_diag: jax.Array) -> jax.Array:
    """Per-leg Cartesian mobility ``C_l = J_l D_l^{-1} J_l^T`` ``(4, 3, 3)``: ``xd_l = C_l f_l``.

    This is the foot-velocity response of the damper model (Eq. 1, 10) to a foot force; the
    stance block of ``J D_r^{-1} J^T``.
    """
    with jax.named_scope("leg_compliances"):
        d_leg = jnp.asarray(d_diag).reshape(jnp.shape(d_diag)[:-1] + (4, 3))
        jd = j_legs / d_leg[..., None, :]
        return usum(jd[..., :, None, :] * j_legs[..., None, :, :], -1)


def eq6_system(
    x_feet: jax.Array,
    f_sw: jax.Array,
    swing_leg: jax.Array,
    j_legs: jax.Array,
    d_diag: jax.Array,
    e_b: jax.Array,
    params: ReflexParams,
    up: jax.Array | None = None,
    tau_kl: jax.Array | None = None,
):
    """The literal ``9 x 9`` linear system ``A f_st = b`` of Eq. 6 (reference / diagnostics).

    .. math::
        A = \\begin{bmatrix} I & I & I \\\\
            [x_1 - x_{sw}]_\\times & [x_2 - x_{sw}]_\\times & [x_3 - x_{sw}]_\\times \\\\
            & \\tilde J D_r^{-1} J_{st}^T & \\end{bmatrix},\\qquad
        b = \\begin{bmatrix} -f_{sw}^\\perp \\\\ -K_{base} e_b \\\\ -\\tilde J D_r^{-1}\\tau_{kl} \\end{bmatrix}

    with ``f_sw^perp = e_z e_z^T f_sw`` (``e_z = up``), ``J~`` of Eq. 4 and ``J_st`` the
    ``9 x 12`` stance Jacobian. The last block of ``b`` is zero in the paper; it is
    ``-J~ D^-1 tau_kl`` here so that the stance distances stay constant also while end-stop
    springs act on stance joints (identical to the paper when ``tau_kl`` is zero on the stance
    joints or not given). :func:`distribute_virtual_forces` solves this system in closed form.

    Returns:
      ``(A, b)`` of shapes ``(9, 9)`` and ``(9,)`` (single instance).
    """
    with jax.named_scope("eq6_system"):
        return _eq6_system(x_feet, f_sw, swing_leg, j_legs, d_diag, e_b, params, up, tau_kl)


def _eq6_system(x_feet, f_sw, swing_leg, j_legs, d_diag, e_b, params, up, tau_kl):
    from hyqjax.reflex.geometry import relative_distance_jacobian

    x_feet = jnp.asarray(x_feet)
    dtype = x_feet.dtype
    p = stance_selector(swing_leg, dtype)
    hot = swing_one_hot(swing_leg, dtype)
    x_st = p @ x_feet
    x_sw = hot @ x_feet
    e_z = safe_normalize(jnp.asarray([0.0, 0.0, 1.0] if up is None else up, dtype))
    f_perp = e_z * jnp.dot(e_z, jnp.asarray(f_sw, dtype))
    j_tilde = relative_distance_jacobian(x_feet, j_legs, swing_leg)  # (3, 12)
    eye4 = jnp.eye(4, dtype=dtype)
    jfull = jnp.einsum("lm,lij->limj", eye4, jnp.asarray(j_legs, dtype)).reshape(4, 3, 12)
    j_st = jnp.einsum("kl,lij->kij", p, jfull).reshape(9, 12)
    dinv = 1.0 / jnp.asarray(d_diag, dtype)
    a = jnp.concatenate(
        [
            jnp.tile(jnp.eye(3, dtype=dtype), (1, 3)),
            jnp.concatenate([skew(x_st[i] - x_sw) for i in range(3)], axis=1),
            (j_tilde * dinv) @ j_st.T,
        ],
        axis=0,
    )
    tau = jnp.zeros(12, dtype) if tau_kl is None else jnp.asarray(tau_kl, dtype)
    moment = -_vec3(params.k_base, dtype) * jnp.asarray(e_b, dtype)
    b = jnp.concatenate([-f_perp, moment, -(j_tilde * dinv) @ tau])
    return a, b


def _inv3(m):
    cof = cofactors3(m)
    det = dot_last(m[..., 0, :], cof[..., 0, :])
    return jnp.swapaxes(cof, -1, -2) / det[..., None, None], det


def distribute_virtual_forces(
    x_feet: jax.Array,
    f_sw: jax.Array,
    swing_leg: jax.Array,
    j_legs: jax.Array,
    d_diag: jax.Array,
    e_b: jax.Array,
    params: ReflexParams,
    up: jax.Array | None = None,
    tau_kl: jax.Array | None = None,
    return_degenerate: bool = False,
):
    """All four virtual foot forces ``f^r`` ``(4, 3)``: Eq. 2-6 (single instance; ``vmap``).

    The swing row is ``f_sw`` itself (it drives the swing leg). The stance rows are the unique
    solution ``f_st = A^{-1} b`` of Eq. 6 (see :func:`eq6_system`):

    * force balance (Eq. 3): ``sum_i f_i = -f_sw^perp`` with ``f_sw^perp = e_z e_z^T f_sw`` and
      ``e_z = up`` the gravity-up direction in the base frame; only the vertical part of the
      swing force is mapped to the stance legs, so the reflex moves the trunk only vertically;
    * moment balance about the swing foot (Eq. 3): ``sum_i (x_i - x_sw) x f_i = m`` with the
      base-spring moment ``m = -K_base e_b`` (Eq. 6);
    * stance constraints (Eq. 4, 5): ``J~ D_r^{-1} (J_st^T f_st + tau_kl) = 0``, i.e. the
      distances between the stance feet (pairs 1-2, 2-3, 3-1) do not change. (The paper's
      Eq. 5 has no ``tau_kl``; see :func:`eq6_system`.)

    Closed-form solution (exactly ``A^{-1} b``, with only 3x3 inverses; fast when batched):
    the six balance equations are satisfied by the minimum-norm particular solution
    ``f_i^p = F/3 + y x rho_i`` (``rho_i`` the feet relative to their centroid ``c``,
    ``F = -f_sw^perp``, ``y = K^{-1} (m - (c - x_sw) x F)``, ``K = sum_i |rho_i|^2 I - rho_i rho_i^T``);
    the remaining three unknowns are the internal (squeezing) forces ``t_k`` along the edges
    ``x~_k``, which carry no net force or moment; the stance constraints then read
    ``H t = -g(f^p)`` with ``H = J~ D_r^{-1} J~^T`` (3x3, symmetric positive definite unless
    degenerate).

    Degenerate case (documented fallback, never NaN): if the stance feet are (nearly) collinear
    (measure below :data:`COLLINEAR_TOL`), if ``H`` is numerically singular
    (``det(H)/(tr(H)/3)^3`` below ``1e3 * eps(dtype)``, at least ``1e-9``), or if the solution is
    not finite, the stance forces are set to zero (all motion stays in the swing leg) and the
    degenerate flag is raised. Value and gradient stay finite in both branches.

    Args:
      x_feet: ``(4, 3)`` reflex feet positions ``x^r`` in the base frame.
      f_sw: ``(3,)`` swing-foot virtual force (Eq. 2, :func:`virtual_spring_force`).
      swing_leg: integer ``0..3``, may be traced.
      j_legs: ``(4, 3, 3)`` per-leg foot Jacobians at ``q^r``.
      d_diag: ``(12,)`` diagonal of ``D_r`` (:func:`damping_matrix_diag`).
      e_b: ``(3,)`` base orientation error (``e_b = -e_t``, Eq. 8).
      params: uses ``k_base``.
      up: ``(3,)`` gravity-up direction ``e_z`` in the base frame (default ``+z``).
      tau_kl: optional ``(12,)`` end-stop torques (Eq. 9) entering the stance constraints.
      return_degenerate: if True return ``(f_r, degenerate)``.
    Returns:
      ``f_r`` ``(4, 3)``, or ``(f_r, degenerate)`` with a boolean scalar flag.
    """
    with jax.named_scope("distribute_virtual_forces"):
        x_feet = jnp.asarray(x_feet)
        dtype = x_feet.dtype
        f_sw = jnp.asarray(f_sw, dtype)
        j_legs = jnp.asarray(j_legs, dtype)
        d_diag = jnp.asarray(d_diag, dtype)
        p = stance_selector(swing_leg, dtype)  # (3, 4)
        hot = swing_one_hot(swing_leg, dtype)  # (4,)
        x_st = select_legs(p, x_feet)
        x_sw = usum(hot[:, None] * x_feet, 0)
        e_z = safe_normalize(
            jnp.asarray([0.0, 0.0, 1.0] if up is None else up, dtype), fallback=jnp.asarray([0.0, 0.0, 1.0], dtype)
        )
        force = -e_z * dot_last(e_z, f_sw)  # F = -f_sw^perp
        moment = -_vec3(params.k_base, dtype) * jnp.asarray(e_b, dtype)  # m = -K_base e_b

        # Foot-velocity response of each stance leg: xd_i = C_i f_i + u_i (Eq. 1, 10).
        comp = leg_compliances(j_legs, d_diag)
        c_st = select_legs(p, comp)
        if tau_kl is None:
            u_st = jnp.zeros((3, 3), dtype)
        else:
            tau_leg = jnp.asarray(tau_kl, dtype).reshape(4, 3) / d_diag.reshape(4, 3)
            u_st = select_legs(p, matvec(j_legs, tau_leg))

        # Degeneracy of the stance triangle.
        edges = stance_edges(x_st)  # (3, 3): x~_1, x~_2, x~_3
        area2 = jnp.cross(edges[0], edges[1])
        len2 = dot_last(edges, edges)
        longest2 = jnp.maximum(jnp.maximum(len2[0], len2[1]), len2[2])
        tri = jnp.sqrt(dot_last(area2, area2)) / jnp.maximum(longest2, jnp.asarray(1e-30, dtype))
        collinear = ~(tri > COLLINEAR_TOL)  # also catches NaN

        # Particular solution of the 6 balance equations (minimum norm).
        centroid = usum(x_st, 0) / 3.0
        rho = x_st - centroid
        kmat = usum(dot_last(rho, rho), 0) * jnp.eye(3, dtype=dtype) - usum(rho[:, :, None] * rho[:, None, :], 0)
        kmat = jnp.where(collinear, jnp.eye(3, dtype=dtype), kmat)
        kinv, _ = _inv3(kmat)
        moment_c = moment - jnp.cross(centroid - x_sw, force)
        y = matvec(kinv, moment_c)
        f_p = force / 3.0 + jnp.cross(y[None, :], rho)

        # Internal (squeezing) forces: a tension t_l on edge l adds +t_l x~_l to its first foot and
        # -t_l x~_l to its second, i.e. f_int = INC^T diag(t) X~ with the edge-foot incidence INC.
        inc = jnp.asarray(_INCIDENCE, dtype)  # (3 edges, 3 feet)
        # Stance constraint rates (Eq. 4): r_k = x~_k . sum_i INC[k, i] xd_i with xd_i = C_i f_i + u_i.
        vel_p = matvec(c_st, f_p) + u_st
        g0 = dot_last(edges, select_legs(inc, vel_p))
        # H[k, l] = sum_i INC[k, i] INC[l, i] x~_k^T C_i x~_l  (= J~ D^-1 J~^T, symmetric PSD).
        c_e = matvec(c_st[:, None], edges[None, :])  # (foot i, edge l, 3): C_i x~_l
        q = dot_last(edges[:, None, None, :], c_e[None])  # (edge k, foot i, edge l)
        h = usum(inc[:, :, None] * inc.T[None, :, :] * q, 1)
        h = 0.5 * (h + h.T)
        tr = h[0, 0] + h[1, 1] + h[2, 2]
        det = det3(h)
        h_tol = max(1e-9, 1e3 * float(jnp.finfo(dtype).eps))
        ill = ~(det > h_tol * (tr / 3.0) ** 3) | ~(tr > 0)
        degenerate = collinear | ill
        h = jnp.where(degenerate, jnp.eye(3, dtype=dtype), h)
        hinv, _ = _inv3(h)
        t = -matvec(hinv, g0)
        f_st = f_p + select_legs(inc.T, t[:, None] * edges)
        degenerate = degenerate | ~jnp.isfinite(usum(usum(f_st, 0), 0))
        f_st = jnp.where(degenerate, 0.0, f_st)
        f_r = select_legs(p.T, f_st) + hot[:, None] * f_sw[None, :]
        if return_degenerate:
            return f_r, degenerate
        return f_r
