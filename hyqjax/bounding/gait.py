"""The bound's clock and feed-forward impulses (Section II of Orsolino et al., Park & Kim's impulses).

The legs work in pairs, front (LF, RF) and hind (LH, RH). A clock of period ``T`` gives the phase
``phi = (t / T) mod 1``; pair ``p`` is in stance while ``(phi - phi_p) mod 1 < d_p`` (touchdown
phase ``phi_p``, duty ``d_p``), with stance progress ``s = ((phi - phi_p) mod 1) / d_p``
(:func:`leg_phase`). During stance each leg ``i`` pushes with the feed-forward ground-reaction force
(horizontal frame ``H``)

.. math:: {}_h f_i(t) = \\beta(s)\\, \\mathbf a_i, \\qquad \\mathbf a_i = [a_{i,x}, a_{i,y}, a_{i,z}]^T   \\qquad (B1)

with the impulse profile ``beta`` (:func:`profile`) a half sine ``sin(pi s)`` or a Bezier curve
``sum_k c_k B_k^n(s)`` (``c_0 = c_n = 0``). Its impulse is ``a_i d_p T kappa`` with
``kappa = 2 / pi`` (half sine) or ``kappa = mean(c)`` (Bezier). Park & Kim's vertical impulse
balance over one period (weight carried, zero net pitch moment about the CoM at ``x_c``) gives the
initial guess :func:`impulse_guess`:

.. math:: 2\\kappa (a_{f,z} d_f + a_{h,z} d_h) T = m g T, \\qquad
          a_{f,z} d_f (x_f - x_c) + a_{h,z} d_h (x_h - x_c) = 0.                      \\qquad (B2)

The exact periodic amplitudes ``a*`` come from :mod:`hyqjax.bounding.cycle`. The operator command
ramps in linearly (:func:`ramped_command`); the stance feedback's reference is the cycle's recorded
state against phase (:func:`cycle_reference`).
"""
from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding.params import FRONT, HIND, LEG_PAIR, BoundingCommand, BoundingParams, GaitParams
from hyqjax.core import robot


def profile(gait: GaitParams, s: jax.Array) -> jax.Array:
    """Unit impulse profile ``beta(s)`` on ``s in [0, 1]``, 0 outside (Eq. B1)."""
    inside = (s >= 0.0) & (s <= 1.0)
    sc = jnp.clip(s, 0.0, 1.0)
    if gait.profile == "bezier":
        c = gait.bezier
        n = c.shape[0] - 1
        k = jnp.arange(n + 1, dtype=sc.dtype)
        binom = jnp.asarray([math.comb(n, int(i)) for i in range(n + 1)], sc.dtype)
        basis = binom * sc[..., None] ** k * (1.0 - sc[..., None]) ** (n - k)
        val = jnp.sum(basis * c, -1)
    else:
        val = jnp.sin(jnp.pi * sc)
    return jnp.where(inside, val, 0.0)


def leg_phase(gait: GaitParams, t):
    """Per-leg ``(stance, s_stance, s_swing)``: stance flag (4,), stance and swing progress in [0, 1)."""
    phi = jnp.mod(t / gait.period, 1.0)
    td = gait.touchdown_phase[LEG_PAIR]
    duty = gait.duty[LEG_PAIR]
    rel = jnp.mod(phi - td, 1.0)
    stance = rel < duty
    s_st = jnp.where(stance, rel / duty, 0.0)
    s_sw = jnp.where(stance, 0.0, (rel - duty) / (1.0 - duty))
    return stance, s_st, s_sw


def cycle_index(gait: GaitParams, t):
    """Index of the gait cycle at time ``t`` (a new cycle starts at every apex, phase 0)."""
    return jnp.floor(t / gait.period + 1e-4).astype(jnp.int32)


def ramped_command(cmd: BoundingCommand, t):
    """Command scaled by ``clip(t / ramp_time, 0, 1)``; returns ``(velocity (2,), yaw_rate, desired yaw offset)``.

    The yaw offset is the integral of the ramped rate, ``psi^d(t) - psi^d(0)``.
    """
    ramp = jnp.maximum(cmd.ramp_time, 1e-6)
    g = jnp.clip(t / ramp, 0.0, 1.0)
    yaw = cmd.yaw_rate * jnp.where(t < ramp, 0.5 * t * t / ramp, t - 0.5 * ramp)
    return cmd.velocity * g, cmd.yaw_rate * g, yaw


def cycle_reference(params: BoundingParams, phase):
    """The cycle's ``(z, theta, zdot, thetadot)`` at ``phase`` (periodic linear interpolation of ``params.reference``)."""
    tab = params.reference
    n = tab.shape[0]
    x = jnp.mod(phase, 1.0) * n
    i0 = jnp.floor(x).astype(jnp.int32) % n
    w = x - jnp.floor(x)
    return (1.0 - w) * tab[i0] + w * tab[(i0 + 1) % n]


def impulse_guess(gait: GaitParams, mass: float = robot.TOTAL_MASS, com_x: float = 0.007) -> np.ndarray:
    """Park & Kim's vertical impulse balance (Eq. B2): ``(a_{f,z}, a_{h,z})`` per leg (N)."""
    kappa = float(gait.kappa)
    d = np.asarray(gait.duty, np.float64)
    xf, xh = float(gait.foot_xy[0, 0]), float(gait.foot_xy[2, 0])
    w = mass * robot.GRAVITY / (2.0 * kappa)  # sum_p a_p d_p
    af = w * (com_x - xh) / (xf - xh) / d[FRONT]
    ah = w * (xf - com_x) / (xf - xh) / d[HIND]
    return np.array([af, ah])
