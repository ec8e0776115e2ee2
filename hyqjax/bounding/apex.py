"""The sagittal apex state of the bound: the Poincare section at gait phase 0, mid-flight before the hind stance,
as the named tuple :class:`Apex` ``(z, pitch, vx, vz, pitch_rate)``: the state of the apex return map
(:mod:`hyqjax.bounding.cycle`), of the limit cycle's reference apex (``BoundingParams.apex_ref``) and of the apex
the controller samples each cycle (:mod:`hyqjax.bounding.state`).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class Apex(NamedTuple):
    """Sagittal apex state ``s = (z, theta, xdot, zdot, thetadot)``: trunk height (m), pitch (rad, > 0
    nose down), forward and vertical speed (m/s), pitch rate (rad/s). Leaves may carry batch axes."""

    z: jax.Array
    pitch: jax.Array
    vx: jax.Array
    vz: jax.Array
    pitch_rate: jax.Array

    def array(self) -> jax.Array:
        """``(..., 5)`` in field order (for the linearised return map)."""
        return jnp.stack([jnp.asarray(v) for v in self], -1)

    @staticmethod
    def of(x) -> "Apex":
        """From a ``(..., 5)`` array in field order."""
        return Apex(*(x[..., k] for k in range(5)))


APEX_NAMES = Apex._fields
N_APEX = len(APEX_NAMES)
