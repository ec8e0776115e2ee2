"""Quintic polynomial trajectories (Section II: body and swing trajectories are quintics in the
terrain frame).

A rest-to-rest quintic ``s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5`` on ``tau in [0, 1]`` has zero velocity and
acceleration at both ends. Their rates are taken by forward-mode differentiation where they are needed
(:func:`hyqjax.crawl.swing.planned_feet`), so only the positions are written here.
"""
from __future__ import annotations

import jax.numpy as jnp


def quintic(tau):
    """Rest-to-rest quintic blend ``s(tau)``, ``tau`` clipped to [0, 1]."""
    t = jnp.clip(tau, 0.0, 1.0)
    return t**3 * (10.0 - 15.0 * t + 6.0 * t**2)


def swing_profile(tau, step_height):
    """Swing foot offsets in the terrain frame at phase ``tau in [0, 1]``.

    Returns ``(s_tangent, z_normal)``: the tangential progress (a quintic 0 -> 1) and the height along the terrain
    normal, a quintic rise to ``step_height`` over the first half and a quintic descent back to 0 over the second
    half.
    """
    s = quintic(tau)
    up = quintic(2.0 * tau)
    down = quintic(2.0 * tau - 1.0)
    z = jnp.where(tau < 0.5, step_height * up, step_height * (1.0 - down))
    return s, z
