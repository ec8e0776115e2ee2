"""A fall of the bound, as device metrics accumulated every tick on the simulator's ground truth.

:class:`FallMetrics` (one instance): the tick of the first fall and its cause (the trunk below
:data:`FALL_HEIGHT`; ``|roll|`` or ``|pitch|`` above :data:`FALL_ANGLE`, checked in that order), the ticks
simulated, the lowest trunk height and the largest ``|roll|`` and ``|pitch|``. :func:`fall_metrics` is the
:class:`hyqjax.sim.rollout.Metrics` pair the bound's rollout (:mod:`hyqjax.bounding.rollout`) and the tracking
batch (:mod:`hyqjax.bounding.tracking`) accumulate; :class:`hyqjax.bounding.rollout.BoundingOutcome` reports it.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.sim import rollout as sim


#: A fall (:class:`FallMetrics`): the trunk below ``FALL_HEIGHT`` (m), or ``|roll|`` or ``|pitch|`` above
#: ``FALL_ANGLE`` (rad).
FALL_HEIGHT = 0.35
FALL_ANGLE = 0.7


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FallMetrics:
    """Device metrics of one instance (accumulated every tick on the ground truth).

    Attributes:
      fall_tick: tick of the first fall (-1: none).  low_trunk, roll, pitch: the first fall's cause (the trunk
        below ``FALL_HEIGHT``; ``|roll|`` / ``|pitch|`` above ``FALL_ANGLE``; checked in that order, one is set).
      ticks: ticks simulated.  min_z: lowest trunk height.  max_roll, max_pitch: largest ``|roll|``, ``|pitch|``.
    """

    fall_tick: jax.Array
    low_trunk: jax.Array
    roll: jax.Array
    pitch: jax.Array
    ticks: jax.Array
    min_z: jax.Array
    max_roll: jax.Array
    max_pitch: jax.Array


def fall_metrics() -> sim.Metrics:
    """:class:`FallMetrics` as a :class:`hyqjax.sim.rollout.Metrics` pair."""

    def init(d):
        f = jnp.zeros((), bool)
        return FallMetrics(fall_tick=jnp.array(-1), low_trunk=f, roll=f, pitch=f, ticks=jnp.array(0),
                           min_z=d.qpos[robot.QPOS_BASE_POS][2], max_roll=jnp.zeros((), d.qpos.dtype),
                           max_pitch=jnp.zeros((), d.qpos.dtype))

    def update(ms: FallMetrics, d, obs, info):
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
        z = d.qpos[robot.QPOS_BASE_POS][2]
        low = z < FALL_HEIGHT
        roll = ~low & (jnp.abs(rpy[0]) > FALL_ANGLE)
        pitch = ~low & ~roll & (jnp.abs(rpy[1]) > FALL_ANGLE)
        new = (ms.fall_tick < 0) & (low | roll | pitch)
        return FallMetrics(fall_tick=jnp.where(new, ms.ticks, ms.fall_tick), low_trunk=ms.low_trunk | (new & low),
                           roll=ms.roll | (new & roll), pitch=ms.pitch | (new & pitch), ticks=ms.ticks + 1,
                           min_z=jnp.minimum(ms.min_z, z), max_roll=jnp.maximum(ms.max_roll, jnp.abs(rpy[0])),
                           max_pitch=jnp.maximum(ms.max_pitch, jnp.abs(rpy[1])))

    return sim.Metrics(init, update)
