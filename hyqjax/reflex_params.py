"""Parameters of the height reflex (Focchi et al. 2017, Table I).

:class:`ReflexParams` is a frozen dataclass registered as a JAX PyTree: every field is a leaf,
so ``jax.grad`` and ``jax.vmap`` reach all of them (e.g. to tune the reflex by gradient descent or
to sweep a batch of parameter sets). Validation (:meth:`ReflexParams.validate`) runs in plain
Python/NumPy, outside ``jit``; the jitted code never branches on parameter values.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

_FIELDS = (
    "k_x",
    "k_x_max",
    "k_base",
    "k_kl",
    "delta",
    "d_st_min",
    "d_st_max",
    "d_sw_min",
    "d_sw_max",
    "m_min",
    "m_max",
)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
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

    k_x: float | jax.Array = 5000.0
    k_x_max: float | jax.Array = 2.0e4
    k_base: float | jax.Array = 1500.0
    k_kl: float | jax.Array = 1000.0
    delta: float | jax.Array = 0.05
    d_st_min: float | jax.Array = 50.0
    d_st_max: float | jax.Array = 1000.0
    d_sw_min: float | jax.Array = 5.0
    d_sw_max: float | jax.Array = 100.0
    m_min: float | jax.Array = 0.19
    m_max: float | jax.Array = 0.21

    @classmethod
    def table1(cls) -> "ReflexParams":
        """The parameters of Table I of the paper (the defaults), validated."""
        return cls().validate()

    @classmethod
    def make(cls, **kwargs) -> "ReflexParams":
        """Construct from keyword arguments (others default to Table I) and :meth:`validate`."""
        unknown = set(kwargs) - set(_FIELDS)
        if unknown:
            raise ValueError(f"unknown ReflexParams field(s) {sorted(unknown)}; allowed: {list(_FIELDS)}")
        return cls(**kwargs).validate()

    def validate(self) -> "ReflexParams":
        """Check the parameters (outside ``jit``) and return ``self``.

        Raises:
          ValueError: naming the offending parameter and its allowed range, if a value is not
            finite, has a wrong shape, or violates: stiffnesses ``>= 0``; ``k_x <= k_x_max``;
            damping ``> 0`` with ``d_st_min < d_st_max`` and ``d_sw_min < d_sw_max``;
            ``0 < m_min < m_max``; ``0 < delta < 0.5``.
        """
        shapes = {
            "k_x": ((), (3,)),
            "k_x_max": ((), (3,)),
            "k_base": ((), (3,)),
            "k_kl": ((), (12,)),
            "delta": ((), (12,)),
        }
        vals = {}
        for name in _FIELDS:
            value = getattr(self, name)
            try:
                arr = np.asarray(value, dtype=np.float64)
            except (TypeError, jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError) as e:
                raise ValueError(f"ReflexParams.validate() must run outside jit; '{name}' is traced") from e
            allowed = shapes.get(name, ((),))
            if arr.shape not in allowed:
                raise ValueError(f"ReflexParams.{name} must have shape in {allowed}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"ReflexParams.{name} must be finite, got {value!r}")
            vals[name] = arr

        def need(cond, name, rng):
            if not bool(np.all(cond)):
                raise ValueError(f"ReflexParams.{name}={vals[name].tolist()} out of range: must be {rng}")

        for name in ("k_x", "k_x_max", "k_base", "k_kl"):
            need(vals[name] >= 0, name, ">= 0 (stiffness)")
        need(vals["k_x"] <= vals["k_x_max"], "k_x", f"<= k_x_max={vals['k_x_max'].tolist()} (Eq. 2 upper bound)")
        need((vals["delta"] > 0) & (vals["delta"] < 0.5), "delta", "in (0, 0.5) rad")
        for name in ("d_st_min", "d_st_max", "d_sw_min", "d_sw_max"):
            need(vals[name] > 0, name, "> 0 (damping)")
        need(vals["d_st_min"] < vals["d_st_max"], "d_st_min", f"< d_st_max={float(vals['d_st_max'])}")
        need(vals["d_sw_min"] < vals["d_sw_max"], "d_sw_min", f"< d_sw_max={float(vals['d_sw_max'])}")
        need(vals["m_min"] > 0, "m_min", "> 0 (m/rad)")
        need(vals["m_min"] < vals["m_max"], "m_min", f"< m_max={float(vals['m_max'])}")
        return self

    def astype(self, dtype) -> "ReflexParams":
        """All leaves as ``jnp`` arrays of ``dtype`` (used inside the reflex to fix precision)."""
        return jax.tree.map(lambda a: jnp.asarray(a, dtype), self)

    def replace(self, **kwargs) -> "ReflexParams":
        """``dataclasses.replace`` (no validation; call :meth:`validate` if needed)."""
        return dataclasses.replace(self, **kwargs)


def params_finite(params: ReflexParams) -> jax.Array:
    """Traced check that every parameter leaf is finite (used by the NaN-input fallback)."""
    leaves = jax.tree.leaves(params)
    ok = jnp.asarray(True)
    for leaf in leaves:
        ok = ok & jnp.all(jnp.isfinite(jnp.asarray(leaf)))
    return ok

