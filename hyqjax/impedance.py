"""Joint impedance: PD on joint references plus a feed-forward torque.

.. math:: \\tau^d = K_p (q^d - q) + K_d (\\dot q^d - \\dot q) + \\tau_{ff}

(Fig. 2 of Focchi et al. 2017: the joint-level PD is HyQ's impedance controller and the trunk
controller's feed-forward ``tau_ff`` is added to it). Gains are PyTree leaves so ``grad`` and
``vmap`` reach them.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import robot


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImpedanceGains:
    """Joint PD gains per joint type, broadcast to the 12 joints.

    Attributes:
      kp: (3,) stiffness for HAA, HFE, KFE (N m/rad).
      kd: (3,) damping (N m s/rad).
    """

    kp: jax.Array
    kd: jax.Array

    @staticmethod
    def make(kp=(300.0, 300.0, 300.0), kd=(8.0, 8.0, 6.0)) -> "ImpedanceGains":
        kp = np.broadcast_to(np.asarray(kp, np.float64), (3,))
        kd = np.broadcast_to(np.asarray(kd, np.float64), (3,))
        if np.any(~np.isfinite(kp)) or np.any(kp <= 0) or np.any(kp > 5000):
            raise ValueError(f"kp must be in (0, 5000] N m/rad, got {kp}")
        if np.any(~np.isfinite(kd)) or np.any(kd <= 0) or np.any(kd > 200):
            raise ValueError(f"kd must be in (0, 200] N m s/rad, got {kd}")
        return ImpedanceGains(jnp.asarray(kp, jnp.float32), jnp.asarray(kd, jnp.float32))

    def per_joint(self):
        return jnp.tile(self.kp, 4), jnp.tile(self.kd, 4)


def joint_impedance(gains: ImpedanceGains, q_des, qd_des, q, qd, tau_ff):
    """``tau = Kp (q_des - q) + Kd (qd_des - qd) + tau_ff``, clipped to the 150 N m limit."""
    kp, kd = gains.per_joint()
    tau = kp * (q_des - q) + kd * (qd_des - qd) + tau_ff
    return jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
