"""Standing: joint impedance to the SRDF ``standing`` pose with a gravity feed-forward.

The feed-forward shares the robot's weight equally among the four feet,
``tau_ff = -J_f^T (B_R_W m g e_z / 4)`` per leg, the simplest trunk controller; the crawl
uses :mod:`hyqjax.control.trunk` instead. Used to check MJX settings (HyQ must stand for 10 s
with no NaN in float32) and as a baseline under pushes.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from hyqjax.control import impedance
from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core.params import param_field, params_dataclass
from hyqjax.core.types import Controller, Observation
from hyqjax.core import spatial


@params_dataclass
class StandParams:
    """Standing controller parameters: joint gains and the ``(12,)`` joint reference (rad)."""

    gains: impedance.ImpedanceGains = dataclasses.field(default_factory=impedance.ImpedanceGains.make)
    q_ref: jax.Array = param_field(tuple(robot.Q_STANDING), -math.pi, math.pi, "rad", "joint reference",
                                   shapes=((12,),))

    @staticmethod
    def make(gains: impedance.ImpedanceGains | None = None) -> "StandParams":
        return StandParams(gains or impedance.ImpedanceGains.make(), jnp.asarray(robot.Q_STANDING, jnp.float32))


def weight_feedforward(q, quat, mass=robot.TOTAL_MASS):
    """``tau_ff`` (12,) that holds the weight equally on four feet."""
    w_r_b = spatial.quat_to_rot(quat)
    f_w = jnp.array([0.0, 0.0, mass * robot.GRAVITY / 4.0], q.dtype)
    f_b = w_r_b.T @ f_w
    jac = kinematics.foot_jacobians(q)
    return -jnp.einsum("lij,i->lj", jac, f_b).reshape(12)


def _init(params: StandParams, obs: Observation):
    return ()


def _step(params: StandParams, state, obs: Observation):
    tau_ff = weight_feedforward(obs.q, obs.quat)
    tau = impedance.joint_impedance(params.gains, params.q_ref, jnp.zeros_like(obs.q), obs.q, obs.qd, tau_ff)
    return state, tau, ()


stand_controller = Controller(_init, _step)
