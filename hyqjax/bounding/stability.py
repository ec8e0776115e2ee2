"""Stability of the bounding limit cycle: the linearised apex return map and the feedback that stabilises it.

:func:`linearise` gives ``A = dP/ds`` and ``B = dP/da`` at the fixed point ``s*`` of the return map
(Eq. C1, :mod:`hyqjax.bounding.cycle`) by ``jax.jacfwd`` (9 tangents through ``mjx.step``). The
eigenvalues of ``A`` are the multipliers of the sagittal cycle with the configured feedback (switches
``apex_feedback``, ``stance_feedback``); the feedback is zero on the cycle, so all maps share ``s*``.
:func:`feedback_matrix` is the apex feedback's ``K = da/ds`` (Eq. B4; ``A_stance + B K`` predicts
``A_stance+apex`` up to the placement correction of Eq. B8), :func:`augmented_matrix` adds the per-cycle
integrators as states, and :func:`design_feedback` picks apex gains on the linear model.
:func:`reference_table` records the cycle's ``(z, theta, zdot, thetadot)`` against phase: the stance
feedback's reference (Eq. B7).
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import controller as bctrl
from hyqjax.bounding import cycle
from hyqjax.bounding.params import BoundingParams
from hyqjax.sim import rollout as sim


@functools.partial(jax.jit, static_argnames=("period",))
def linearise(params: BoundingParams, s_star: jax.Array, period: float):
    """``(P(s*), A = dP/ds (5, 5), B = dP/da (5, 4))`` at ``s*`` by ``jax.jacfwd`` (9 tangents, one compile).

    ``a = (a_fz, a_hz, a_fx, a_hx)``. ``A`` includes the apex feedback when ``params.switches.apex_feedback``
    is 1 (the feedback reads the apex sample at the start of the period; the estimator starts at the truth).
    """
    m, mx, ids = cycle.model()
    s_star = jnp.asarray(s_star, jnp.float32)

    def f(x):
        out = cycle.return_map(mx, m, ids, cycle.with_amplitudes(params, x[5:]), x[:5], period=period)
        return out, out

    jac, out = jax.jacfwd(f, has_aux=True)(jnp.concatenate([s_star, cycle.cycle_vector(params)]))
    return out, jac[:, :5], jac[:, 5:]


def with_feedback(params: BoundingParams, apex: bool, stance: bool | None = None) -> BoundingParams:
    """``params`` with the apex (Eq. B4) and stance (Eq. B7) feedback switched on / off (stance defaults to apex)."""
    stance = apex if stance is None else stance
    sw = dataclasses.replace(params.switches, apex_feedback=jnp.float32(1.0 if apex else 0.0),
                             stance_feedback=jnp.float32(1.0 if stance else 0.0))
    return params.replace(switches=sw)


def reference_table(params: BoundingParams, s_star, n: int = 40, control_dt: float = 0.002) -> np.ndarray:
    """Record the open-loop cycle from ``s*`` (feedback off): ``(z, theta, zdot, thetadot)`` at phases ``k / n``.

    This is the reference of the stance feedback (Eq. B7), which therefore vanishes on the cycle.
    """
    period = float(params.gait.period)
    ticks = int(round(period / control_dt))
    if not (isinstance(n, int) and n >= 2 and ticks % n == 0):
        raise ValueError(f"n must be an int >= 2 dividing the ticks per period ({ticks}), got {n}")
    m, mx, ids = cycle.model()
    p = with_feedback(params, False)
    s_star = jnp.asarray(s_star, jnp.float32)

    @jax.jit
    def run(p, s):
        p = cycle.with_estimate(p, s)
        d0 = cycle.apex_data(mx, m, p, s)
        cfg = sim.SimConfig(control_dt=control_dt, duration=period, record_every=ticks // n)
        res = sim.rollout(mx, ids, d0, bctrl.bounding_controller, p, cfg,
                          record=lambda d, o, i: cycle.data_apex(d).array())
        return res.trace

    tr = np.asarray(run(p, s_star), np.float64)  # phases 1/n ... 1
    table = np.concatenate([np.asarray(s_star, np.float64)[None], tr[:-1]], 0)
    return table[:, [0, 1, 3, 4]]


def feedback_matrix(params: BoundingParams, gains: dict | None = None) -> np.ndarray:
    """``d a / d s`` (4, 5) of the apex feedback Eq. B4 at the cycle (the ``K`` of ``A + B K``)."""
    g = params.gains if gains is None else gains
    get = (lambda k: float(getattr(g, k))) if gains is None else (lambda k: float(g[k]))
    af, ah = float(params.amplitudes[0, 2]), float(params.amplitudes[2, 2])
    k = np.zeros((4, 5))
    # alpha = 1 + kz (z* - z) + kzd (zd* - zd); delta = kth (th - th*) + kthd (thd - thd*)
    dalpha = np.array([-get("k_height"), 0, 0, -get("k_height_rate"), 0])
    ddelta = np.array([0, get("k_pitch"), 0, 0, get("k_pitch_rate")])
    k[0] = af * (dalpha + ddelta)
    k[1] = ah * (dalpha - ddelta)
    k[2, 2] = k[3, 2] = -get("k_speed")
    return k


def design_feedback(a_mat: np.ndarray, b_mat: np.ndarray, params: BoundingParams, k_speed: float,
                    grid: dict | None = None):
    """Pick the apex gains (k_height, k_height_rate, k_pitch, k_pitch_rate) minimising the spectral radius of
    ``A + B K(gains)`` on a grid (cheap: NumPy on the linearised map). Returns ``(gains, radius)``."""
    grid = grid or dict(k_height=np.linspace(0, 8, 9), k_height_rate=np.linspace(-0.4, 0.4, 9),
                        k_pitch=np.linspace(-1.0, 2.0, 13), k_pitch_rate=np.linspace(-0.2, 0.3, 11))
    best, best_rho = None, np.inf
    for kz in grid["k_height"]:
        for kzd in grid["k_height_rate"]:
            for kt in grid["k_pitch"]:
                for ktd in grid["k_pitch_rate"]:
                    gains = dict(k_height=kz, k_height_rate=kzd, k_pitch=kt, k_pitch_rate=ktd, k_speed=k_speed)
                    k = feedback_matrix(params, gains)
                    rho = np.max(np.abs(np.linalg.eigvals(a_mat + b_mat @ k)))
                    if rho < best_rho - 1e-9:
                        best, best_rho = gains, rho
    return best, best_rho


def augmented_matrix(a_closed: np.ndarray, b_mat: np.ndarray, params: BoundingParams) -> np.ndarray:
    """Linearised return map with the per-cycle integrators of Eqs. B4-B5 as extra states.

    ``a_closed`` is ``dP/ds`` with the apex feedback on (its proportional terms, the speed term and the
    placement correction included) and ``b_mat = dP/da``. State ``(s_k - s*, I_{k-1})``:
    ``I_k = I_{k-1} + C (s_k - s*)``, ``s_{k+1} - s* = A_closed (s_k - s*) + B K_i I_k``. Only integrators with a
    non-zero gain are states (an integrator with zero gain is a decoupled eigenvalue 1).
    """
    g = params.gains
    af, ah = float(params.amplitudes[0, 2]), float(params.amplitudes[2, 2])
    rows, cols = [], []
    if float(g.k_height_int):
        rows.append([-1.0, 0, 0, 0, 0])  # z* - z
        cols.append(np.array([af, ah, 0.0, 0.0]) * float(g.k_height_int))
    if float(g.k_pitch_int):
        rows.append([0, 1.0, 0, 0, 0])  # theta - theta*
        cols.append(np.array([af, -ah, 0.0, 0.0]) * float(g.k_pitch_int))
    if float(g.k_speed_int):
        rows.append([0, 0, -1.0, 0, 0])  # xdot* - xdot
        cols.append(np.array([0.0, 0.0, 1.0, 1.0]) * float(g.k_speed_int))
    if not rows:
        return np.asarray(a_closed)
    c = np.asarray(rows)
    ki = np.stack(cols, 1)
    top = np.concatenate([a_closed + b_mat @ ki @ c, b_mat @ ki], 1)
    bot = np.concatenate([c, np.eye(len(rows))], 1)
    return np.concatenate([top, bot], 0)
