"""Joint impedance: PD on joint references plus a feed-forward torque.

.. math:: \\tau^d = K_p (q^d - q) + K_d (\\dot q^d - \\dot q) + \\tau_{ff}

(Fig. 2 of Focchi et al. 2017: the joint-level PD is HyQ's impedance controller and the trunk
controller's feed-forward ``tau_ff`` is added to it). Gains are PyTree leaves so ``grad`` and
``vmap`` reach them.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot
from hyqjax.core.params import ParameterError, param_field, params_dataclass


@params_dataclass
class ImpedanceGains:
    """Joint PD gains per joint type, broadcast to the 12 joints.

    Attributes:
      kp: (3,) stiffness for HAA, HFE, KFE (N m/rad), each in ``(0, 5000]``.
      kd: (3,) damping (N m s/rad), each in ``(0, 200]``.
    Leading batch axes are allowed (one set of gains per instance); every element is validated.
    """

    kp: jax.Array = param_field((300.0, 300.0, 300.0), 0.0, 5000.0, "N m/rad",
                                "joint PD stiffness (HAA, HFE, KFE)", lo_open=True, shapes=((3,),))
    kd: jax.Array = param_field((8.0, 8.0, 6.0), 0.0, 200.0, "N m s/rad",
                                "joint PD damping (HAA, HFE, KFE)", lo_open=True, shapes=((3,),))

    @staticmethod
    def make(kp=(300.0, 300.0, 300.0), kd=(8.0, 8.0, 6.0)) -> "ImpedanceGains":
        """Gains from scalars or ``(3,)`` values (broadcast to the three joint types), as float32."""
        out = {}
        for name, v in (("kp", kp), ("kd", kd)):
            try:
                out[name] = np.broadcast_to(np.asarray(v, np.float64), (3,))
            except ValueError as e:
                raise ParameterError("ImpedanceGains", name, f"array of shape {np.shape(v)}",
                                     "a scalar or of shape (3,)", problem="has a wrong shape") from e
        ImpedanceGains(**out)  # range check on the float64 values
        return ImpedanceGains(jnp.asarray(out["kp"].astype(np.float32)), jnp.asarray(out["kd"].astype(np.float32)))

    def per_joint(self):
        return jnp.tile(self.kp, 4), jnp.tile(self.kd, 4)


def joint_impedance(gains: ImpedanceGains, q_des, qd_des, q, qd, tau_ff):
    """``tau = Kp (q_des - q) + Kd (qd_des - qd) + tau_ff``, clipped to the 150 N m limit."""
    kp, kd = gains.per_joint()
    tau = kp * (q_des - q) + kd * (qd_des - qd) + tau_ff
    return jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
