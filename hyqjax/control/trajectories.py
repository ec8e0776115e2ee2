"""Quintic polynomial trajectories (Section II: body and swing trajectories are quintics in the
terrain frame).

A rest-to-rest quintic ``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` on ``tau in [0, 1]`` has zero velocity and
acceleration at both ends; :func:`quintic` returns ``s``, ``ds/dtau`` and ``d2s/dtau2``.
"""
from __future__ import annotations

import jax.numpy as jnp


def quintic(tau):
    """Rest-to-rest quintic blend and its derivatives w.r.t. ``tau`` (clipped to [0, 1])."""
    t = jnp.clip(tau, 0.0, 1.0)
    s = t**3 * (10.0 - 15.0 * t + 6.0 * t**2)
    ds = 30.0 * t**2 * (1.0 - t) ** 2
    dds = 60.0 * t * (1.0 - t) * (1.0 - 2.0 * t)
    return s, ds, dds


def swing_profile(tau, step_height):
    """Swing foot offsets in the terrain frame at phase ``tau in [0, 1]``.

    Returns ``(s_tangent, z_normal, dz_normal/dtau)``: the tangential progress (a quintic 0 -> 1) and the
    height along the terrain normal, a quintic rise to ``step_height`` over the first half and a quintic
    descent back to 0 over the second half.
    """
    s, _, _ = quintic(tau)
    up, dup, _ = quintic(2.0 * tau)
    down, ddown, _ = quintic(2.0 * tau - 1.0)
    first = tau < 0.5
    z = jnp.where(first, step_height * up, step_height * (1.0 - down))
    dz = jnp.where(first, 2.0 * step_height * dup, -2.0 * step_height * ddown)
    return s, z, dz
