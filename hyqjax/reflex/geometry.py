"""Geometry of the height reflex: stance-leg selection, terrain normal, orientation error and
leg mobility (Focchi et al. 2017, Section III-B Eq. 4, 7, 8 and Section III-F Eq. 12).

Conventions (shared by all ``hyqjax.reflex.step*`` modules):

* Everything is expressed in the trunk (base) frame ``B``; legs are ordered LF, RF, LH, RH
  (``robot.LF ... robot.RH``), joints leg-major ``(HAA, HFE, KFE)``.
* The swing leg is a (possibly traced) integer ``0..3``. Its three stance legs are taken from the
  static table :data:`STANCE_LEGS` (the other legs in increasing index order) and gathered with
  one-hot matrices, so no Python branching ever depends on a traced value.
* Every function is pure, works in float32 and float64, and composes with ``jit``, ``vmap`` and
  ``grad``. Functions marked "broadcasts" accept arbitrary leading batch dimensions; the others
  are single-instance and are batched with ``jax.vmap``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot
from hyqjax.core.smallmat import adj3, cofactors3, det3  # noqa: F401  (re-exported: Eq. 6's closed form uses them)

#: ``STANCE_LEGS[s]`` are the stance legs (in the order 1, 2, 3 of Eq. 4-6) when leg ``s`` swings
#: (:data:`hyqjax.core.robot.STANCE_LEGS`).
STANCE_LEGS: np.ndarray = robot.STANCE_LEGS
#: Relative regulariser of the leg mobility metrics: ``J J^T`` is replaced by
#: ``J J^T + MOBILITY_RIDGE * tr(J J^T)/3 * I`` (a Tikhonov ridge), see
#: :func:`velocity_transformation_ratio`. It changes ``m`` by a relative ~1e-10 away from
#: singularity and keeps it positive, finite and differentiable at a singular Jacobian.
MOBILITY_RIDGE = 1e-10
#: Absolute floor (m/rad) under ``m`` and ``w``: ``m = sqrt(m^2 + MOBILITY_FLOOR^2)``.
MOBILITY_FLOOR = 1e-9


# Small dense products (3x3, 3x4) are written as broadcast-multiply-and-sum instead of ``dot``:
# XLA fuses them with their neighbours, whereas every ``dot`` is a separate kernel launch, and
# launches dominate the latency of one reflex tick on CPU.
def usum(x, axis):
    """Sum over a short axis (kept as a named helper so the products below read as algebra)."""
    return jnp.sum(x, axis=axis)


def dot_last(a, b):
    """``sum(a * b, -1)`` over a short last axis."""
    return usum(a * b, -1)


def matvec(a, v):
    """``a @ v`` for ``a`` ``(..., m, n)`` and ``v`` ``(..., n)``."""
    return usum(a * v[..., None, :], -1)


def select_legs(p, x):
    """``sum_l p[k, l] x[l, ...]``: apply a ``(k, 4)`` one-hot selector to a per-leg array."""
    p = p.reshape(p.shape + (1,) * (x.ndim - 1))
    return usum(p * x[None], 1)


def _tiny(dtype):
    """A positive number far below any physical quantity but representable in ``dtype``."""
    return jnp.asarray(1e-30, dtype)


def safe_norm(v: jax.Array, eps: float | None = None) -> jax.Array:
    """``|v|`` along the last axis with a finite gradient at ``v = 0`` (where it returns 0).

    Uses the double-``where`` pattern: the square root is never evaluated at 0, so neither the
    value nor the gradient is NaN. Broadcasts.
    """
    v = jnp.asarray(v)
    n2 = dot_last(v, v)
    eps2 = _tiny(v.dtype) if eps is None else jnp.asarray(eps, v.dtype) ** 2
    small = n2 <= eps2
    return jnp.where(small, 0.0, jnp.sqrt(jnp.where(small, 1.0, n2)))


def safe_normalize(v: jax.Array, fallback: jax.Array | None = None, eps: float | None = None) -> jax.Array:
    """``v / |v|`` along the last axis; returns ``fallback`` (default: 0) where ``|v| <= eps``.

    Gradients are finite everywhere (double-``where``). Broadcasts.
    """
    v = jnp.asarray(v)
    n2 = dot_last(v, v)[..., None]
    eps2 = _tiny(v.dtype) if eps is None else jnp.asarray(eps, v.dtype) ** 2
    small = n2 <= eps2
    unit = v / jnp.sqrt(jnp.where(small, 1.0, n2))
    fb = jnp.zeros_like(v) if fallback is None else jnp.broadcast_to(jnp.asarray(fallback, v.dtype), v.shape)
    return jnp.where(small, fb, unit)


# ---------------------------------------------------------------------------------------------
# Stance-leg selection
# ---------------------------------------------------------------------------------------------


def swing_one_hot(swing_leg: jax.Array, dtype=jnp.float32) -> jax.Array:
    """One-hot ``(4,)`` vector of the swing leg (clipped to ``0..3``). Broadcasts over leading dims."""
    s = jnp.clip(jnp.asarray(swing_leg, jnp.int32), 0, 3)
    return (jnp.arange(4, dtype=jnp.int32) == s[..., None]).astype(dtype)


def stance_selector(swing_leg: jax.Array, dtype=jnp.float32) -> jax.Array:
    """One-hot selection matrix ``P`` of shape ``(3, 4)`` with ``x_st = P @ x_feet``.

    Row ``k`` picks stance foot ``k`` (``STANCE_LEGS[swing_leg, k]``). ``P^T f_st`` scatters
    stance quantities back to the four legs. ``swing_leg`` may be traced (clipped to ``0..3``).
    """
    s = jnp.clip(jnp.asarray(swing_leg, jnp.int32), 0, 3)
    idx = jnp.asarray(STANCE_LEGS)[s]
    return (idx[..., :, None] == jnp.arange(4, dtype=jnp.int32)).astype(dtype)


def stance_feet(x_feet: jax.Array, swing_leg: jax.Array) -> jax.Array:
    """The three stance feet ``(3, 3)`` (order of :data:`STANCE_LEGS`) of ``x_feet`` ``(4, 3)``."""
    x_feet = jnp.asarray(x_feet)
    return select_legs(stance_selector(swing_leg, x_feet.dtype), x_feet)


# ---------------------------------------------------------------------------------------------
# Terrain normal and orientation error (Eq. 7, 8)
# ---------------------------------------------------------------------------------------------


def terrain_normal(x_stance: jax.Array, up: jax.Array | None = None) -> jax.Array:
    """Unit normal of the plane through the three stance feet (Eq. 7), oriented along ``up``.

    .. math:: n_t = \\frac{\\tilde x_1 \\times \\tilde x_2}{|\\tilde x_1 \\times \\tilde x_2|},
       \\qquad \\tilde x_1 = x_1 - x_2,\\; \\tilde x_2 = x_2 - x_3

    and ``n_t`` is flipped if ``n_t . up < 0`` so that it points to the free side of the terrain
    (the order of the stance feet does not matter). Broadcasts.

    Args:
      x_stance: ``(..., 3, 3)`` stance-foot positions (rows are feet).
      up: ``(..., 3)`` up direction (opposite to gravity) in the same frame; default ``+z``.
    Returns:
      ``(..., 3)`` unit normal. For collinear (or coincident) feet the plane is undefined and the
      normalised ``up`` is returned (value and gradient finite).
    """
    with jax.named_scope("terrain_normal"):
        x_stance = jnp.asarray(x_stance)
        dtype = x_stance.dtype
        up = jnp.asarray([0.0, 0.0, 1.0] if up is None else up, dtype)
        up = safe_normalize(up, fallback=jnp.asarray([0.0, 0.0, 1.0], dtype))
        e1 = x_stance[..., 0, :] - x_stance[..., 1, :]
        e2 = x_stance[..., 1, :] - x_stance[..., 2, :]
        c = jnp.cross(e1, e2)
        # Collinearity measured relative to the feet spread, so the test is scale invariant.
        scale2 = jnp.maximum(dot_last(e1, e1), dot_last(e2, e2))
        degenerate = dot_last(c, c) <= (jnp.asarray(1e-12, dtype) * scale2) ** 2 + _tiny(dtype)
        n = safe_normalize(jnp.where(degenerate[..., None], up, c))
        sign = jnp.where(dot_last(n, up) < 0, -1.0, 1.0).astype(dtype)
        return n * sign[..., None]


def orientation_error(n_t: jax.Array, n_t_des: jax.Array) -> jax.Array:
    """Rotation vector ``e_t`` that brings ``n_t`` onto ``n_t_des`` (Eq. 8).

    .. math:: \\hat a_t = \\frac{n_t \\times n_t^d}{|n_t \\times n_t^d|},\\quad
       \\delta = \\operatorname{acos}(n_t^T n_t^d),\\quad e_t = \\delta\\, \\hat a_t

    Both inputs are normalised first. It is evaluated as
    ``e_t = (n_t x n_t^d) * atan2(s, c) / s`` with ``s = |n_t x n_t^d|``, ``c = n_t . n_t^d``,
    which equals Eq. 8 but is accurate for small angles (``acos`` is not), and for ``s`` below
    ``1e-6`` the ratio ``atan2(s, c)/s`` is replaced by its Taylor series ``1/c - s^2/(3 c^3)``,
    so value and gradient are finite and exact at ``delta = 0``. For (nearly) antiparallel
    normals (``c < 0`` and ``s < 1e-6``) the rotation axis is undefined and ``0`` is returned;
    normals oriented with :func:`terrain_normal` are never antiparallel. Broadcasts.

    With ``n_t`` the current terrain normal in the base frame and ``n_t_des`` its value at the
    start of the swing, ``e_t`` is the base rotation since the start of the swing (the terrain
    tilts the opposite way in the base frame); the paper sets ``e_b = -e_t``.
    """
    with jax.named_scope("orientation_error"):
        n_t = jnp.asarray(n_t)
        dtype = jnp.result_type(n_t, jnp.asarray(n_t_des))
        a = safe_normalize(n_t.astype(dtype))
        b = safe_normalize(jnp.asarray(n_t_des, dtype))
        axis = jnp.cross(a, b)
        c = dot_last(a, b)
        s2 = dot_last(axis, axis)
        small = s2 < jnp.asarray(1e-12, dtype)
        s = jnp.sqrt(jnp.where(small, 1.0, s2))
        c_safe = jnp.where(small & (c > 0), c, 1.0)
        series = 1.0 / c_safe - s2 / (3.0 * c_safe**3)
        ratio = jnp.where(small, jnp.where(c > 0, series, 0.0), jnp.arctan2(s, c) / s)
        return axis * ratio[..., None]


# ---------------------------------------------------------------------------------------------
# Mobility metrics (Eq. 12)
# ---------------------------------------------------------------------------------------------


def _regularised_gram(j_foot):
    g = usum(j_foot[..., :, None, :] * j_foot[..., None, :, :], -1)
    tr = g[..., 0, 0] + g[..., 1, 1] + g[..., 2, 2]
    ridge = jnp.asarray(MOBILITY_RIDGE, g.dtype) * tr / 3.0
    return g + ridge[..., None, None] * jnp.eye(3, dtype=g.dtype)


def transmission_ratio(j_foot: jax.Array, direction: jax.Array) -> jax.Array:
    """Only the velocity transformation ratio ``m(v)`` of :func:`velocity_transformation_ratio`.

    Cheaper (no SVD); used by :func:`hyqjax.reflex.step.reflex_step`. Broadcasts.
    """
    with jax.named_scope("transmission_ratio"):
        j_foot = jnp.asarray(j_foot)
        dtype = j_foot.dtype
        v = safe_normalize(jnp.asarray(direction, dtype), fallback=jnp.asarray([0.0, 0.0, 1.0], dtype))
        g = _regularised_gram(j_foot)
        det = jnp.maximum(det3(g), 0.0)
        quad = dot_last(v, matvec(adj3(g), v))
        # v^T G^{-1} v = v^T adj(G) v / det(G)  =>  m^2 = det(G) / (v^T adj(G) v).
        quad = jnp.maximum(quad, _tiny(dtype))
        floor = jnp.asarray(MOBILITY_FLOOR, dtype)
        return jnp.sqrt(det / quad + floor**2)


def velocity_transformation_ratio(j_foot: jax.Array, direction: jax.Array):
    """Leg mobility metrics of Eq. 12 for a ``3 x n`` foot Jacobian ``J_f``.

    .. math::
        m(v) = (v^T (J_f J_f^T)^{-1} v)^{-1/2},\\qquad
        w = \\sqrt{\\det(J_f J_f^T)},\\qquad
        \\kappa^{-1} = \\sigma_{min}(J_f) / \\sigma_{max}(J_f)

    ``m(v)`` is the velocity transformation ratio along the unit direction ``v`` (``direction``
    is normalised here): the distance from the centre to the surface of the velocity ellipsoid
    ``xd^T (J J^T)^{-1} xd = 1`` along ``v`` (m/rad). ``w`` is Yoshikawa's manipulability and
    ``kappa^{-1}`` the inverse condition number.

    Robustness near singularity: ``J J^T`` is replaced by ``G = J J^T + rho I`` with
    ``rho = MOBILITY_RIDGE * tr(J J^T) / 3`` (relative Tikhonov ridge, 1e-10), and ``m`` is
    computed without an inverse as ``m^2 = det(G) / (v^T adj(G) v)``, then
    ``m = sqrt(m^2 + MOBILITY_FLOOR^2)``, ``w = sqrt(det(G) + MOBILITY_FLOOR^2)``. Hence
    ``m, w > 0`` and finite with finite gradients even at an exactly singular ``J``; elsewhere
    the regulariser is invisible at float32 and float64 precision. ``kappa^{-1}`` uses the
    singular values of ``J`` (their derivative ``u_i^T dJ v_i`` is defined even for repeated
    values). Broadcasts.

    Args:
      j_foot: ``(..., 3, n)`` foot Jacobian (``n = 3`` for a HyQ leg).
      direction: ``(..., 3)`` search direction ``v`` (the terrain normal ``n_t`` in the reflex).
    Returns:
      ``(m, w, kappa_inv)``, each of shape ``(...)``.
    """
    with jax.named_scope("velocity_transformation_ratio"):
        j_foot = jnp.asarray(j_foot)
        dtype = j_foot.dtype
        m = transmission_ratio(j_foot, direction)
        g = _regularised_gram(j_foot)
        floor = jnp.asarray(MOBILITY_FLOOR, dtype)
        w = jnp.sqrt(jnp.maximum(det3(g), 0.0) + floor**2)
        sv = jnp.linalg.svd(j_foot, compute_uv=False)
        kappa_inv = sv[..., -1] / jnp.maximum(sv[..., 0], _tiny(dtype))
        return m, w, kappa_inv


# ---------------------------------------------------------------------------------------------
# Relative-distance (stance constraint) Jacobian (Eq. 4)
# ---------------------------------------------------------------------------------------------

#: Pairs ``(i, j)`` of stance feet whose distance is kept (Eq. 4): 1-2, 2-3, 3-1.
STANCE_PAIRS: tuple[tuple[int, int], ...] = ((0, 1), (1, 2), (2, 0))


def stance_edges(x_stance: jax.Array) -> jax.Array:
    """Edge vectors ``x~_k = x_i - x_j`` for the pairs of :data:`STANCE_PAIRS`, ``(..., 3, 3)``."""
    x_stance = jnp.asarray(x_stance)
    return jnp.stack([x_stance[..., i, :] - x_stance[..., j, :] for i, j in STANCE_PAIRS], -2)


def relative_distance_jacobian(x_feet: jax.Array, j_legs: jax.Array, swing_leg: jax.Array) -> jax.Array:
    """The ``3 x 12`` matrix ``J~`` of Eq. 4 (single instance; ``vmap`` for batches).

    .. math:: \\tilde J = \\begin{bmatrix} \\tilde x_1^T (J_1 - J_2) \\\\
       \\tilde x_2^T (J_2 - J_3) \\\\ \\tilde x_3^T (J_3 - J_1) \\end{bmatrix},\\qquad
       \\tilde x_k = x_i - x_j

    where ``J_i`` (``3 x 12``) is the Jacobian of stance foot ``i``. ``J~ qd`` are the rates of
    change of ``|x~_k|^2 / 2``; ``J~ qd = 0`` keeps the stance-feet distances constant.

    Args:
      x_feet: ``(4, 3)`` feet positions. j_legs: ``(4, 3, 3)`` per-leg foot Jacobians.
      swing_leg: integer ``0..3`` (may be traced).
    """
    with jax.named_scope("relative_distance_jacobian"):
        x_feet = jnp.asarray(x_feet)
        dtype = x_feet.dtype
        p = stance_selector(swing_leg, dtype)  # (3, 4)
        # Full 3x12 Jacobian of every foot: block-diagonal, jfull[l] = e_l (x) J_l.
        eye4 = jnp.eye(4, dtype=dtype)
        jfull = jnp.einsum("lm,lij->limj", eye4, jnp.asarray(j_legs, dtype)).reshape(4, 3, 12)
        j_st = jnp.einsum("kl,lij->kij", p, jfull)  # (3, 3, 12)
        edges = stance_edges(p @ x_feet)
        rows = [edges[k] @ (j_st[i] - j_st[j]) for k, (i, j) in enumerate(STANCE_PAIRS)]
        return jnp.stack(rows, 0)
