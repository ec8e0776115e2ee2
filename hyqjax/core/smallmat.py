"""Closed-form linear algebra of the tiny systems in one control tick (3x3 and 6x6).

``jnp.linalg.solve`` factorises with LU (a LAPACK call on the CPU, cuBLAS / cuSOLVER on a GPU) and then
runs two triangular solves: kernels of their own that XLA cannot fuse with the arithmetic around them.
Under ``vmap`` over tens of thousands of robots, the per-tick 3x3 and 6x6 systems of the controller are
cheaper as a few dozen fused multiply-adds:

* 3x3 (:func:`solve3`): Cramer's rule, ``x = adj(A) b / det(A)`` with ``adj(A)`` the transposed cofactor
  matrix (row ``i`` of the cofactors is ``r_{i+1} x r_{i+2}`` of the rows ``r`` of ``A``).
* symmetric positive definite ``n x n`` (:func:`spd_solve`): Cholesky ``A = L L^T`` unrolled over the static
  ``n``, ``L_jj = sqrt(A_jj - sum_k L_jk^2)``, ``L_ij = (A_ij - sum_k L_ik L_jk) / L_jj``, then forward and
  back substitution.

Both are exact in exact arithmetic; for the regularised, well-conditioned systems they are used on they
agree with ``numpy.linalg.solve`` in float64 to rounding (``tests/test_spatial.py``). Neither pivots: a
singular ``A`` gives non-finite results, as LU without regularisation would.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def cofactors3(m: jax.Array) -> jax.Array:
    """Cofactor matrix of a 3x3 matrix ``(..., 3, 3)``: row ``i`` is ``r_{i+1} x r_{i+2}`` of the rows ``r``."""
    return jnp.cross(jnp.roll(m, -1, axis=-2), jnp.roll(m, -2, axis=-2))


def det3(m: jax.Array) -> jax.Array:
    """Determinant of a 3x3 matrix ``(..., 3, 3)``, ``r_0 . (r_1 x r_2)``."""
    return jnp.sum(m[..., 0, :] * jnp.cross(m[..., 1, :], m[..., 2, :]), -1)


def adj3(m: jax.Array) -> jax.Array:
    """Adjugate (transposed cofactor matrix) of a 3x3 matrix: ``m @ adj(m) = det(m) I``."""
    return jnp.swapaxes(cofactors3(m), -1, -2)


def solve3(a: jax.Array, b: jax.Array) -> jax.Array:
    """``x = A^-1 b`` for ``A`` ``(..., 3, 3)`` and ``b`` ``(..., 3)``, by Cramer's rule (module docstring)."""
    x = jnp.sum(adj3(a) * b[..., None, :], -1)
    return x / det3(a)[..., None]


def spd_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """``x = A^-1 b`` for a symmetric positive definite ``A`` ``(..., n, n)`` and ``b`` ``(..., n)`` by an
    unrolled Cholesky factorisation (module docstring); ``n`` is static and small (the loops are unrolled)."""
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        d = a[..., j, j] - sum((low[j][k] ** 2 for k in range(j)), jnp.zeros_like(a[..., j, j]))
        low[j][j] = jnp.sqrt(d)
        for i in range(j + 1, n):
            s = a[..., i, j] - sum((low[i][k] * low[j][k] for k in range(j)), jnp.zeros_like(a[..., i, j]))
            low[i][j] = s / low[j][j]
    y = [None] * n
    for i in range(n):  # L y = b
        y[i] = (b[..., i] - sum((low[i][k] * y[k] for k in range(i)), jnp.zeros_like(b[..., i]))) / low[i][i]
    x = [None] * n
    for i in reversed(range(n)):  # L^T x = y
        x[i] = (y[i] - sum((low[k][i] * x[k] for k in range(i + 1, n)), jnp.zeros_like(y[i]))) / low[i][i]
    return jnp.stack(x, -1)
