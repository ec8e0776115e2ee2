"""What every simulation backend hands to the controllers, the metrics and the traces: one definition.

* **The observation** (:class:`hyqjax.core.types.Observation`) the controllers read, from
  :func:`observation`: joint positions and velocities, the applied torques, the IMU's orientation and angular
  velocity (MuJoCo's free-joint angular velocity, which is in the trunk frame), and the foot forces estimated
  from joint-space dynamics, per leg ``tau = M_l qdd + h_l - J_f^T f``, so

      f = J_f^{-T} (g_l - tau),    g = qfrc_bias + M qacc,

  with ``g_l`` the leg rows of the generalized force ``g`` of the last physics step (gravity, Coriolis, and the
  inertial term a robot gets by differentiating its encoder velocities). Without the inertial term a fast
  swing leg reads tens of newtons of phantom contact force. Each backend computes ``g`` its own way
  (:func:`hyqjax.sim.rollout.observe` under MJX, ``mj_mulM`` in C MuJoCo); the formula above is shared.
* **The data the metrics, outcomes and traces read**: the fields of :class:`DataView`, which carry the names and
  meaning of ``mjx.Data``'s fields (``time``, ``qpos``, ``qvel``, ``sensordata`` with the contact sensors of
  :mod:`hyqjax.sim.contacts`, ``site_xpos``, ``geom_xpos``, ``geom_xmat``). MJX hands its ``mjx.Data`` (a
  superset); the C MuJoCo backend (:mod:`hyqjax.sim.cpu_backend`) hands a :class:`DataView` per tick. A metric
  written against these fields runs unchanged on every backend.

Like every ``mjx.step``, one physics step computes the derived fields (sensors, site and geom poses, ``g``) at
the state it starts from and then integrates ``time``, ``qpos`` and ``qvel``: a view after a step holds the new
state and the derived fields of the old one, under every backend.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics, robot, smallmat
from hyqjax.core.types import Observation

#: The fields of the simulated data that metrics, outcomes and traces may read (``mjx.Data`` names).
VIEW_FIELDS = ("time", "qpos", "qvel", "sensordata", "site_xpos", "geom_xpos", "geom_xmat")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class DataView:
    """The simulated data of one instance (leading batch axis in a batch) as a backend without ``mjx.Data``
    hands it over: the :data:`VIEW_FIELDS` of ``mjx.Data``, plus

    Attributes:
      qfrc_gen: ``qfrc_bias + M qacc`` of the last physics step, ``(nv,)`` (the ``g`` of the module docstring).
    """

    time: jax.Array
    qpos: jax.Array
    qvel: jax.Array
    sensordata: jax.Array
    site_xpos: jax.Array
    geom_xpos: jax.Array
    geom_xmat: jax.Array
    qfrc_gen: jax.Array

    def replace(self, **kw) -> "DataView":
        return dataclasses.replace(self, **kw)


def observation(qadr, vadr, qpos: jax.Array, qvel: jax.Array, qfrc_gen: jax.Array, tau: jax.Array,
                time: jax.Array) -> Observation:
    """The :class:`Observation` of one instance from its state (``qpos``, ``qvel``, ``time``), the generalized
    force ``qfrc_gen = qfrc_bias + M qacc`` of the last step and the applied joint torques ``tau`` (12,);
    ``qadr`` / ``vadr``: the qpos / dof addresses of the 12 leg joints (:class:`hyqjax.sim.model.ModelIds`)."""
    qadr, vadr = np.asarray(qadr), np.asarray(vadr)
    q = qpos[qadr]
    qd = qvel[vadr]
    quat = qpos[robot.QPOS_BASE_QUAT]
    gyro = qvel[robot.QVEL_BASE_ANG]  # MuJoCo's free-joint angular velocity is in the body frame.
    bias = qfrc_gen[vadr].reshape(4, 3)
    jac = kinematics.foot_jacobians(q)
    rhs = (bias - tau.reshape(4, 3))[..., None]
    reg = 1e-6 * jnp.eye(3, dtype=q.dtype)
    jt = jnp.swapaxes(jac, -1, -2)
    force = smallmat.solve3(jt + reg, rhs[..., 0])
    return Observation(q=q, qd=qd, tau=tau, quat=quat, gyro=gyro, foot_force=force, time=time)


def observe_view(ids, d: DataView, tau: jax.Array) -> Observation:
    """:func:`observation` of a :class:`DataView` (one instance)."""
    return observation(ids.qpos_joints, ids.dof_joints, d.qpos, d.qvel, d.qfrc_gen, tau, d.time)
