"""The types shared by the simulation and the controllers, with no MJX import: what a controller sees
(:class:`Observation`), what it is (:class:`Controller`), how metrics accumulate (:class:`Metrics`) and a push on
the trunk (:class:`Push`). :mod:`hyqjax.sim.rollout` re-exports them; a controller imports them from here so that
importing it does not load MuJoCo / MJX.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:  # annotations only: importing this module must not load MJX
    from mujoco import mjx


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Observation:
    """What the robot measures at one control tick (all in the trunk frame ``B`` unless noted).

    Attributes:
      q, qd, tau: joint positions, velocities, applied torques, (12,).
      quat: IMU orientation ``W_q_B`` (w, x, y, z).
      gyro: trunk angular velocity in ``B``, (3,).
      foot_force: ground reaction forces at the feet estimated from joint torques, (4, 3), in ``B``:
        ``f = J_f^{-T} (h - tau)`` per leg with ``h`` the leg's bias torques (gravity, Coriolis).
      time: seconds since the start.
    """

    q: jax.Array
    qd: jax.Array
    tau: jax.Array
    quat: jax.Array
    gyro: jax.Array
    foot_force: jax.Array
    time: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Push:
    """A lateral push on the trunk: ``force`` (3,) N in the world frame, applied at the trunk's
    centre of mass during ``[t_start, t_start + duration)``. Per instance under ``vmap``."""

    force: jax.Array
    t_start: jax.Array
    duration: jax.Array

    @staticmethod
    def none(dtype=jnp.float32) -> "Push":
        zero = np.zeros((), dtype)  # built in NumPy, then put: no program compiled for it
        return Push(jnp.asarray(np.zeros(3, dtype)), jnp.asarray(zero), jnp.asarray(zero))


class Controller(NamedTuple):
    """A controller: ``init(params, obs) -> state`` and ``step(params, state, obs) -> (state, tau, info)``.

    ``tie_rollout_carry``: a rollout ties its scan's initial carry to the parameters
    (:func:`hyqjax.core.scan_carry.tie_carry`; values unchanged, bit for bit), so that ``lax.scan``'s forward-mode
    and batching rules reach their fixed point without transforming the tick again and again. Measured on
    ``jax.jacfwd`` of the crawl's step-down through MJX-JAX (docs/api.md's example, 5 parameters, float64, 1,200
    ticks, 2 cores): tracing and lowering 19.5-24.4 s -> 11.1-12.3 s, the same derivative. Not set for the bound's
    batch runs (their compile phase took 0.2 s longer tied); its differentiated rollouts use it
    (:data:`hyqjax.bounding.cycle.DIFFERENTIATED_CONTROLLER`); never applied on a Warp model (forward only)."""

    init: Callable[[Any, Observation], Any]
    step: Callable[[Any, Any, Observation], tuple[Any, jax.Array, Any]]
    tie_rollout_carry: bool = False


class Metrics(NamedTuple):
    """Metrics accumulated on the device: ``init(d) -> m``, ``update(m, d, obs, info) -> m``, and optionally
    ``terminal(m) -> bool``: the instance has failed past recovery, so its episode ends at this tick
    (:func:`hyqjax.sim.rollout.rollout_advance` freezes it; ``None``: episodes run to the end)."""

    init: Callable[[mjx.Data], Any]
    update: Callable[[Any, mjx.Data, Observation, Any], Any]
    terminal: Callable[[Any], Any] | None = None
