"""State, per-tick inputs and outputs of the height reflex (:func:`hyqjax.reflex.step.reflex_step`), as
PyTree dataclasses of one robot (``vmap`` for batches), and the planned terrain normal of Eq. 7-8.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from hyqjax.core.shapes import check_shape
from hyqjax.reflex.geometry import stance_feet, terrain_normal

_UP = (0.0, 0.0, 1.0)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ReflexState:
    """Reflex state carried between control ticks.

    Attributes:
      q_r: ``(12,)`` reflex joint positions ``q^r`` (Eq. 10). While the reflex is inactive they
        track ``IK(x^d)``, so on activation the reflex starts from the plan.
      qd_r: ``(12,)`` reflex joint velocities of the last tick (needed by the trapezoidal rule);
        zero while inactive.
    """

    q_r: jax.Array
    qd_r: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ReflexInputs:
    """Per-tick inputs of :func:`reflex_step` (all may be traced; batch with ``vmap``).

    Attributes:
      x_des: ``(4, 3)`` planned feet positions ``x_f^d`` in the base frame.
      swing_leg: integer ``0..3`` (LF, RF, LH, RH); values outside are clipped.
      active: bool, True during the downward part of the swing (Section III-E remark).
      n_t_des: ``(3,)`` terrain normal ``n_t^d`` in the base frame sampled at the beginning of the
        swing (Eq. 8); see :func:`planned_terrain_normal`.
      up: ``(3,)`` gravity-up direction ``e_z`` in the base frame (``f_sw^perp``, Eq. 3).
    """

    x_des: jax.Array
    swing_leg: jax.Array
    active: jax.Array
    n_t_des: jax.Array
    up: jax.Array

    @classmethod
    def make(cls, x_des, swing_leg, active=True, n_t_des=None, up=None) -> "ReflexInputs":
        """Convenience constructor; ``n_t_des`` defaults to :func:`planned_terrain_normal`."""
        x_des = check_shape(jnp.asarray(x_des), ((4, 3),), "ReflexInputs.make", "x_des")
        dtype = x_des.dtype if jnp.issubdtype(x_des.dtype, jnp.floating) else jnp.float32
        x_des = x_des.astype(dtype)
        up = jnp.asarray(_UP if up is None else up, dtype)
        if n_t_des is None:
            n_t_des = planned_terrain_normal(x_des, swing_leg, up)
        return cls(
            x_des=x_des,
            swing_leg=jnp.asarray(swing_leg, jnp.int32),
            active=jnp.asarray(active, bool),
            n_t_des=jnp.asarray(n_t_des, dtype),
            up=up,
        )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ReflexOutput:
    """Per-tick outputs of :func:`reflex_step`.

    Attributes:
      x_r: ``(4, 3)`` corrected feet positions ``x_f^r = K(q^r)`` (Eq. 11), to be sent to the
        controller instead of the plan; equal to ``x_des`` while inactive.
      xd_r: ``(4, 3)`` corrected feet velocities ``J(q^r) qd^r`` (Eq. 11); zero while inactive.
      q_r, qd_r: ``(12,)`` the new reflex joint positions / velocities.
      mobility: ``(4,)`` velocity transformation ratio ``m(n_t)`` of every leg (Eq. 12).
      d_diag: ``(12,)`` diagonal of the damping matrix ``D_r`` used (Fig. 7).
      f_r: ``(4, 3)`` virtual feet forces (Eq. 2, 6); zero while inactive.
      e_b: ``(3,)`` base orientation error ``e_b = -e_t`` (Eq. 8).
      n_t: ``(3,)`` current terrain (stance-plane) normal (Eq. 7).
      tau_kl: ``(12,)`` end-stop torques (Eq. 9).
      active: bool, the reflex moved this tick (``inputs.active`` and inputs valid).
      degenerate: bool, Eq. 6 was singular (collinear stance feet or ill-conditioned): stance
        forces were set to zero for this tick.
      input_ok: bool, all inputs (state, plan, normals, params, dt) were finite.
      failed: bool, an internal failure of the reflex this tick: an input was not finite (the
        fallback of :func:`reflex_step` ran), the new state is not finite, or a reflex joint left its
        range by more than :data:`DIVERGED_MARGIN` (the integration diverged). Count it as its own
        failure reason. With parameters accepted by ``ReflexParams.validate(dt=...)`` and finite
        inputs the state stays finite and the fallback never runs; a joint can still be turned far
        past its range if the end-stop springs are weak (``K_kl Delta`` far below the swing spring's
        torque), which this flag reports too.
    """

    x_r: jax.Array
    xd_r: jax.Array
    q_r: jax.Array
    qd_r: jax.Array
    mobility: jax.Array
    d_diag: jax.Array
    f_r: jax.Array
    e_b: jax.Array
    n_t: jax.Array
    tau_kl: jax.Array
    active: jax.Array
    degenerate: jax.Array
    input_ok: jax.Array
    failed: jax.Array


def planned_terrain_normal(x_des: jax.Array, swing_leg: jax.Array, up: jax.Array | None = None) -> jax.Array:
    """Terrain normal ``n_t^d`` of the planned stance feet (Eq. 7), to sample at swing start.

    ``x_des`` ``(4, 3)`` planned feet (base frame); returns the unit normal ``(3,)`` of the plane
    through the three stance feet, oriented along ``up``.
    """
    with jax.named_scope("planned_terrain_normal"):
        x_des = check_shape(jnp.asarray(x_des), ((4, 3),), "planned_terrain_normal", "x_des")
        return terrain_normal(stance_feet(x_des, swing_leg), up)


def check_shapes(state: ReflexState, inputs: ReflexInputs) -> None:
    """Single-instance shapes of the state and inputs (at trace time; ``vmap`` for batches)."""
    for owner, name, x, shape in (("ReflexState", "q_r", state.q_r, (12,)), ("ReflexState", "qd_r", state.qd_r, (12,)),
                                  ("ReflexInputs", "x_des", inputs.x_des, (4, 3)),
                                  ("ReflexInputs", "swing_leg", inputs.swing_leg, ()),
                                  ("ReflexInputs", "active", inputs.active, ()),
                                  ("ReflexInputs", "n_t_des", inputs.n_t_des, (3,)),
                                  ("ReflexInputs", "up", inputs.up, (3,))):
        check_shape(x, (shape,), f"reflex_step: {owner}", name)
