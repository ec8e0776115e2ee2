"""The bounding controller's state and per-tick output, as typed PyTrees."""
from __future__ import annotations

import dataclasses

import jax

from hyqjax.bounding.params import Apex


def _dc(cls):
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


@_dc
class BoundingState:
    """Controller state carried from tick to tick.

    Attributes:
      t_prev: time of the previous tick.  cycle: index of the current gait cycle.
      pos: (3,) estimated base position in the odometry frame ``W`` (x, y reset at each apex; z above ground).
      vel: (3,) estimated base velocity in ``W``.
      foot_td: (4, 3) touchdown (stance) foot position in ``W``.  base_td: (4, 3) base estimate at touchdown.
      liftoff_h: (4, 3) latest stance reference in ``H`` (start of the next swing).
      stance_prev: (4,) stance flags of the previous tick.
      apex: latest apex sample.  integ: (4,) per-cycle error integrals (:func:`hyqjax.bounding.controller.apex_errors`).
      cycle_amp: (4, 3) this cycle's amplitudes (apex feedback, speed).
      apex_vel: (2,) apex sample of the estimated horizontal velocity in ``H``.
      yaw0: yaw at start.  force_w: (3,) sum of last commanded ground forces in ``W`` (estimator input).
    """

    t_prev: jax.Array
    cycle: jax.Array
    pos: jax.Array
    vel: jax.Array
    foot_td: jax.Array
    base_td: jax.Array
    liftoff_h: jax.Array
    stance_prev: jax.Array
    apex: Apex
    integ: jax.Array
    cycle_amp: jax.Array
    apex_vel: jax.Array
    yaw0: jax.Array
    force_w: jax.Array


@_dc
class BoundingInfo:
    """What one tick reports besides the torques (the third output of the controller's ``step``).

    Attributes:
      est_pos, est_vel: (3,) the estimate in ``W``.  vel_h: (3,) estimated velocity in ``H``.
      apex: the latest apex sample.  new_cycle: an apex event happened this tick.  cycle: gait cycle index.
      stance: (4,) stance flags.  rpy, rates: (3,) IMU roll / pitch / yaw and Euler-angle rates.
      yaw_des, yaw_rate_des: desired yaw and yaw rate.  v_des: (2,) ramped velocity command in ``H``.
      roll_des: lean reference of the centrifugal compensation (Eq. 4).
      force_h: (4, 3) commanded ground forces in ``H``.
    """

    est_pos: jax.Array
    est_vel: jax.Array
    vel_h: jax.Array
    apex: Apex
    new_cycle: jax.Array
    stance: jax.Array
    yaw_des: jax.Array
    yaw_rate_des: jax.Array
    v_des: jax.Array
    roll_des: jax.Array
    rpy: jax.Array
    rates: jax.Array
    force_h: jax.Array
    cycle: jax.Array
