"""Parameters of the height reflex (Focchi et al. 2017, Table I) and its step-size stability condition.

:class:`ReflexParams` is a frozen dataclass PyTree (:func:`hyqjax.core.params.params_dataclass`): every
field is a leaf, so ``jax.grad`` and ``jax.vmap`` reach all of them. Each field's range, unit and scale
is declared once (:func:`hyqjax.core.params.param_ranges` reads them for sweeps, help and tuning), and
the orderings ``k_x <= k_x_max``, ``d_st_min < d_st_max``, ``d_sw_min < d_sw_max``, ``m_min < m_max``
with them. Construction and :meth:`ReflexParams.replace` validate concrete values (every element of a
batch); :meth:`ReflexParams.validate` with ``dt`` also enforces the stability condition below.

**Step-size stability** (derived from the discretisation of :func:`hyqjax.reflex.step.reflex_step`).
The reflex integrates the damper model ``qd = D_r^{-1} (J^T f^r + tau_kl) =: g(q)`` (Eq. 1, 10) with
the two-step trapezoidal rule ``q_{k+1} = q_k + dt/2 (g(q_{k-1}) + g(q_k))``. Linearised about a rest
point, ``g(q) ~ -A (q - q*)``, and ``A``'s eigenvalues ``lambda`` are real and ``>= 0`` (``A`` is
``D^{-1}`` times a symmetric positive semi-definite stiffness: the swing spring ``J_sw^T K_x J_sw``
(Eq. 2), the end-stop springs ``K_kl`` (Eq. 9) and the base spring ``K_base`` acting through the stance
legs (Eq. 6)). Per mode, ``e_{k+1} = e_k - (h/2)(e_k + e_{k-1})`` with ``h = dt lambda``; its
characteristic polynomial ``z^2 - (1 - h/2) z + h/2`` has both roots inside the unit circle iff

.. math:: 0 < dt\\, \\lambda_{max} < 2 .

``lambda_max`` is bounded from the parameters with two constants of HyQ's legs:

.. math:: \\lambda_{max} \\le \\max\\Big(\\frac{\\sigma^2 \\min(k_x, k_{x,max}) + K_{kl}}{D_{sw,min}},\\;
          \\frac{c_{base} K_{base} + K_{kl}}{D_{st,min}}\\Big)

with ``sigma^2`` (:data:`SWING_COMPLIANCE`) the largest squared singular value of a HyQ foot Jacobian
over all joint angles (0.594 m^2/rad^2, rounded up to 0.6) and ``c_base`` (:data:`BASE_COMPLIANCE`) the
largest eigenvalue of ``A`` per unit ``K_base / D_st`` over stance layouts within 8 cm of the standing
feet (0.854, rounded up to 1.0); the damping schedule (Fig. 7) never goes below ``D_sw,min`` /
``D_st,min``. With Table I at ``dt = 2 ms`` ``dt lambda_max <= 1.6``; ``k_x = k_x_max = 2e4`` needs
``dt < 0.77 ms``. :func:`stability_number` is ``dt lambda_max / 2`` (stable below 1; traceable, e.g.
for a tuner's penalty).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core.params import Ordering, ParameterError, check_params, is_concrete, param_field, \
    param_ranges, params_dataclass

#: Largest squared singular value of a HyQ foot Jacobian over all joint angles (m^2/rad^2), rounded up
#: from 0.594 (a test checks it bounds random configurations).
SWING_COMPLIANCE = 0.6
#: Largest eigenvalue of the linearised reflex map per unit ``K_base / D_st`` over stance layouts within
#: 8 cm of the standing feet, rounded up from 0.854 (dimensionless; a test re-measures it).
BASE_COMPLIANCE = 1.0
#: Control periods the reflex accepts (s).
DT_RANGE = (0.0, 0.02)

_D = dict(lo=1e-3, hi=1e5, unit="N m s/rad", scale="log")


@params_dataclass(orderings=(
    Ordering("k_x", "<=", "k_x_max", "Eq. 2 upper bound"),
    Ordering("d_st_min", "<", "d_st_max", "Fig. 7"),
    Ordering("d_sw_min", "<", "d_sw_max", "Fig. 7"),
    Ordering("m_min", "<", "m_max", "Fig. 7"),
))
class ReflexParams:
    """Height-reflex parameters; defaults are Table I of the paper.

    Attributes:
      k_x: Cartesian stiffness ``K_x`` of the swing-foot virtual spring (Eq. 2), N/m; scalar
        (isotropic) or ``(3,)`` (diagonal, base-frame axes). Table I: ``diag(5000, 5000, 5000)``.
        (Table I prints the unit as Nm/rad; for a Cartesian spring it is N/m.)
      k_x_max: upper bound on ``K_x`` (Eq. 2, "an upper bound is set to avoid numeric
        instability"): the reflex uses ``min(k_x, k_x_max)`` element-wise. Default ``2e4`` N/m.
      k_base: base torsional stiffness ``K_base`` (Eq. 6, ``m = -K_base e_b``), N m/rad; scalar
        or ``(3,)``. Table I: 1500.
      k_kl: end-stop virtual spring stiffness ``K_kl`` (Eq. 9), N m/rad; scalar or ``(12,)``.
        Table I: 1000.
      delta: end-stop influence distance ``Delta`` (Eq. 9), rad; scalar or ``(12,)``. Table I: 0.05.
      d_st_min, d_st_max: stance-leg joint damping range (Section III-E), N m s/rad. 50, 1000.
      d_sw_min, d_sw_max: swing-leg joint damping range, N m s/rad. 5, 100.
      m_min, m_max: velocity-transformation-ratio thresholds of the damping schedule (Fig. 7),
        m/rad. 0.19, 0.21.
    """

    k_x: float | jax.Array = param_field(5000.0, 0.0, 1e5, "N/m", "swing-foot spring K_x (Eq. 2)",
                                         shapes=((), (3,)))
    k_x_max: float | jax.Array = param_field(2.0e4, 0.0, 1e6, "N/m", "upper bound on K_x (Eq. 2)",
                                             shapes=((), (3,)))
    k_base: float | jax.Array = param_field(1500.0, 0.0, 1e5, "N m/rad", "base torsional stiffness K_base (Eq. 6)",
                                            shapes=((), (3,)))
    k_kl: float | jax.Array = param_field(1000.0, 0.0, 1e5, "N m/rad", "end-stop spring K_kl (Eq. 9)",
                                          shapes=((), (12,)))
    delta: float | jax.Array = param_field(0.05, 0.0, 0.5, "rad", "end-stop band Delta (Eq. 9)",
                                           lo_open=True, hi_open=True, shapes=((), (12,)))
    d_st_min: float | jax.Array = param_field(50.0, doc="stance joint damping at low swing mobility (Fig. 7)", **_D)
    d_st_max: float | jax.Array = param_field(1000.0, doc="stance joint damping at high swing mobility (Fig. 7)", **_D)
    d_sw_min: float | jax.Array = param_field(5.0, doc="swing joint damping at high swing mobility (Fig. 7)", **_D)
    d_sw_max: float | jax.Array = param_field(100.0, doc="swing joint damping at low swing mobility (Fig. 7)", **_D)
    m_min: float | jax.Array = param_field(0.19, 0.0, 1.0, "m/rad", "lower mobility threshold (Fig. 7, Eq. 12)",
                                           lo_open=True)
    m_max: float | jax.Array = param_field(0.21, 0.0, 1.0, "m/rad", "upper mobility threshold (Fig. 7, Eq. 12)",
                                           lo_open=True)

    @classmethod
    def table1(cls) -> "ReflexParams":
        """The parameters of Table I of the paper (the defaults), validated."""
        return cls()

    @classmethod
    def make(cls, **kwargs) -> "ReflexParams":
        """Construct from keyword arguments (others default to Table I); unknown names are refused."""
        names = list(param_ranges(cls))
        unknown = sorted(set(kwargs) - set(names))
        if unknown:
            raise ParameterError(cls.__name__, unknown[0], kwargs[unknown[0]], f"one of the fields {names} (unknown)")
        return cls(**kwargs)

    def validate(self, dt: float | None = None) -> "ReflexParams":
        """Check ranges and orderings (every element of batched leaves) and, given the control period
        ``dt`` (s), the step-size stability condition ``dt lambda_max < 2`` (module docstring).

        Must run on concrete values (outside ``jit``). Returns ``self``.

        Raises:
          ParameterError: one line naming the parameter and its allowed range.
        """
        leaves = jax.tree.leaves(self)
        if not all(is_concrete(x) for x in leaves):
            raise ParameterError(type(self).__name__, "validate()", "a traced value",
                                 "called outside jit (on concrete values)")
        check_params(self)
        if dt is not None:
            check_dt(dt)
            lam_sw, lam_st = stability_rates(self, xp=np)
            d_sw, d_st = np.asarray(self.d_sw_min, np.float64), np.asarray(self.d_st_min, np.float64)
            # smallest damping that satisfies dt lambda < 2 for each term
            need_sw, need_st, d_sw, d_st = np.broadcast_arrays(0.5 * dt * lam_sw * d_sw, 0.5 * dt * lam_st * d_st,
                                                               d_sw, d_st)
            bad_sw, bad_st = ~(d_sw > need_sw), ~(d_st > need_st)
            for name, bad, d, need in (("d_sw_min", bad_sw, d_sw, need_sw), ("d_st_min", bad_st, d_st, need_st)):
                if bad.any():
                    i = int(np.argmax(bad.reshape(-1)))
                    raise ParameterError(type(self).__name__, name, float(d.reshape(-1)[i]),
                                         f"> {float(need.reshape(-1)[i]):.4g} N m s/rad for stability at dt={dt:g} s "
                                         f"(dt lambda_max < 2; or lower k_x, k_kl, k_base)")
        return self

    def astype(self, dtype) -> "ReflexParams":
        """All leaves as ``jnp`` arrays of ``dtype`` (used inside the reflex to fix precision)."""
        return jax.tree.map(lambda a: jnp.asarray(a, dtype), self)


def check_dt(dt) -> None:
    """Raise :class:`ParameterError` unless the control period ``dt`` is in ``(0, 0.02]`` s."""
    try:
        v = float(dt)
    except (TypeError, ValueError) as e:
        raise ParameterError("reflex", "dt", dt, "a number in (0, 0.02] s") from e
    if not (np.isfinite(v) and DT_RANGE[0] < v <= DT_RANGE[1]):
        raise ParameterError("reflex", "dt", v, f"in ({DT_RANGE[0]:g}, {DT_RANGE[1]:g}] s (control period)")


def _max_last(x, xp):
    """Largest value over a field's own axis (``(3,)`` or ``(12,)`` fields) keeping batch axes."""
    x = xp.asarray(x)
    return x if x.ndim == 0 else xp.max(x, axis=-1) if x.shape[-1] in (3, 12) else x


def stability_rates(params: ReflexParams, xp=jnp):
    """``(lambda_swing, lambda_stance)`` (1/s): the bounds on the linearised reflex's rates (module doc).

    ``xp`` is ``jnp`` (traceable) or ``np``. Batched leaves give batched rates.
    """
    kx = xp.minimum(xp.asarray(params.k_x), xp.asarray(params.k_x_max))
    kx, kb, kkl = _max_last(kx, xp), _max_last(params.k_base, xp), _max_last(params.k_kl, xp)
    lam_sw = (SWING_COMPLIANCE * kx + kkl) / xp.asarray(params.d_sw_min)
    lam_st = (BASE_COMPLIANCE * kb + kkl) / xp.asarray(params.d_st_min)
    return lam_sw, lam_st


def stability_number(params: ReflexParams, dt, xp=jnp):
    """``dt lambda_max / 2``: the reflex's explicit integration is stable below 1 (module docstring)."""
    lam_sw, lam_st = stability_rates(params, xp)
    return 0.5 * dt * xp.maximum(lam_sw, lam_st)


def params_finite(params: ReflexParams) -> jax.Array:
    """Traced check that every parameter leaf is finite (used by the NaN-input fallback)."""
    leaves = jax.tree.leaves(params)
    ok = jnp.asarray(True)
    for leaf in leaves:
        ok = ok & jnp.all(jnp.isfinite(jnp.asarray(leaf)))
    return ok
