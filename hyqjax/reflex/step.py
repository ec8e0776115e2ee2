"""Height reflex of Focchi et al. (2017), Section III: viscosity-based replanning of the feet.

M. Focchi, R. Featherstone, R. Orsolino, D. G. Caldwell, C. Semini, "Viscosity-based Height
Reflex for Workspace Augmentation for Quadrupedal Locomotion on Rough Terrain", IROS 2017.

While a leg swings down searching for a foothold, the reflex replaces the planned feet
positions ``x^d`` (base frame) by corrected ones ``x^r``. It integrates a massless model of the
robot with virtual viscous joints (Eq. 1, 10): a spring pulls the swing foot toward its plan
(Eq. 2); the vertical part of that force is balanced by stance-foot forces that keep the stance
feet distances (Eq. 3-6); joint dampings are scheduled on the swing leg's mobility (Section
III-E, Eq. 12) so that, when the swing leg stretches, the motion moves to the stance legs, which
retract: the trunk lowers ("squats") and the swing foot reaches further down in the world. Joint
end-stop springs (Eq. 9) keep the joints inside their range.

Public API (all pure, float32/float64, ``jit``/``vmap``/``grad``-able; single robot per call,
use ``jax.vmap`` for batches):

* :class:`ReflexParams` (Table I), :class:`ReflexState`, :class:`ReflexInputs`, :class:`ReflexOutput`
* :func:`reflex_init`, :func:`reflex_step` (one control tick, Eq. 10-11), :func:`reflex_rollout`
* building blocks: :func:`virtual_spring_force` (Eq. 2), :func:`distribute_virtual_forces`
  (Eq. 3-6), :func:`eq6_system`, :func:`relative_distance_jacobian` (Eq. 4),
  :func:`terrain_normal` (Eq. 7), :func:`orientation_error` (Eq. 8), :func:`end_stop_torques`
  (Eq. 9), :func:`damping_schedule` and :func:`damping_matrix_diag` (Fig. 7),
  :func:`velocity_transformation_ratio` (Eq. 12), :func:`planned_terrain_normal`.

Deviations from the paper (all documented where they occur):

* End-stop sign: ``qd = D^-1 (J^T f + tau_kl)`` with ``tau_kl`` of Eq. 9 as printed, so the
  springs repel (the printed minus in Eq. 10 would attract; see :func:`end_stop_torques`).
* Stance constraints include the end-stop torques: ``J~ D^-1 (J_st^T f_st + tau_kl) = 0``, so
  Eq. 4 holds also while a stance joint is in its end-stop band (Eq. 5 is the case ``tau_kl=0``).
* The search direction for the mobility ``m`` is the current terrain normal ``n_t`` (Eq. 7 on the
  reflex stance feet), i.e. the normal of the stance plane seen from the (possibly rotated) base.
* Degenerate / invalid inputs have defined, flagged outcomes (see :func:`reflex_step`).

Behaviour to be aware of (as in the paper): the swing spring (Eq. 2) acts in the base frame, so
the reflex only ends when the swing foot reaches ``x^d`` *in the base frame* or the swing ends
(touchdown, end stops). Motion given to the stance legs lowers the trunk and thereby moves the
swing foot further down in the world than the plan: with a plan that stops at a reachable depth
the swing foot ends ``x^d`` below the trunk *and* the trunk lower. With the haptic search of
Section II (stop at touchdown) this is the intended "aid to the searching motion".
"""
from __future__ import annotations


import jax
import jax.numpy as jnp

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core.shapes import check_shape
from hyqjax.reflex.forces import (
    COLLINEAR_TOL,
    SCHEDULE_SHAPES,
    damping_matrix_diag,
    damping_schedule,
    distribute_virtual_forces,
    effective_k_x,
    end_stop_torques,
    eq6_system,
    leg_compliances,
    virtual_spring_force,
)
from hyqjax.reflex.geometry import (
    MOBILITY_FLOOR,
    MOBILITY_RIDGE,
    STANCE_LEGS,
    STANCE_PAIRS,
    orientation_error,
    relative_distance_jacobian,
    safe_normalize,
    select_legs,
    stance_feet,
    stance_selector,
    swing_one_hot,
    terrain_normal,
    transmission_ratio,
    usum,
    velocity_transformation_ratio,
)
from hyqjax.reflex.params import ReflexParams, check_dt, params_finite, stability_number
from hyqjax.reflex.types import ReflexInputs, ReflexOutput, ReflexState, check_shapes, planned_terrain_normal

__all__ = [
    "COLLINEAR_TOL",
    "DIVERGED_MARGIN",
    "MOBILITY_FLOOR",
    "MOBILITY_RIDGE",
    "SCHEDULE_SHAPES",
    "STANCE_LEGS",
    "STANCE_PAIRS",
    "ReflexInputs",
    "ReflexOutput",
    "ReflexParams",
    "ReflexState",
    "damping_matrix_diag",
    "damping_schedule",
    "distribute_virtual_forces",
    "effective_k_x",
    "end_stop_torques",
    "eq6_system",
    "leg_compliances",
    "orientation_error",
    "planned_terrain_normal",
    "reflex_init",
    "reflex_rollout",
    "reflex_step",
    "stability_number",
    "relative_distance_jacobian",
    "stance_feet",
    "stance_selector",
    "swing_one_hot",
    "terrain_normal",
    "transmission_ratio",
    "velocity_transformation_ratio",
    "virtual_spring_force",
]

_UP = (0.0, 0.0, 1.0)
#: A reflex joint this far outside its range (rad) counts as a diverged integration (``failed``). An
#: unstable integration grows geometrically and passes it within tens of ticks; a stable one with weak
#: end-stop springs (small ``K_kl``) may turn a joint past its range, but at a bounded rate.
DIVERGED_MARGIN = 1000.0


def reflex_init(x_des: jax.Array, dtype=None) -> ReflexState:
    """Initial state: ``q^r = IK(x^d)`` (the reflex starts from the plan), ``qd^r = 0``.

    Args:
      x_des: ``(4, 3)`` planned feet positions in the base frame.
      dtype: floating dtype of the state (default: that of ``x_des``, float32 for non-floats).
        The state's dtype sets the precision of :func:`reflex_step`.
    """
    with jax.named_scope("reflex_init"):
        x_des = check_shape(jnp.asarray(x_des), ((4, 3),), "reflex_init", "x_des")
        if dtype is None:
            dtype = x_des.dtype if jnp.issubdtype(x_des.dtype, jnp.floating) else jnp.float32
        q = kinematics.inverse_kinematics(x_des.astype(dtype)).reshape(12)
        return ReflexState(q_r=q, qd_r=jnp.zeros(12, dtype))


def _all_finite(x):
    return jnp.all(jnp.isfinite(x))


def _diverged(q):
    lo = jnp.asarray(robot.Q_MIN, q.dtype) - DIVERGED_MARGIN
    hi = jnp.asarray(robot.Q_MAX, q.dtype) + DIVERGED_MARGIN
    return jnp.any((q < lo) | (q > hi))


def _check_static(params: ReflexParams, dt) -> None:
    """Validate ``dt`` and, with it, ``params`` when they are concrete (Python-level, before tracing)."""
    if isinstance(dt, jax.core.Tracer):
        return
    check_dt(dt)
    if not any(isinstance(x, (jax.core.Tracer, jax.ShapeDtypeStruct)) for x in jax.tree.leaves(params)):
        params.validate(dt=float(dt))


def reflex_step(
    state: ReflexState,
    inputs: ReflexInputs,
    params: ReflexParams,
    dt: float | jax.Array,
    shape: str = "smoothstep",
) -> tuple[ReflexState, ReflexOutput]:
    """One control tick of the height reflex (Eq. 1-12). Single robot; ``vmap`` for batches.

    When ``inputs.active`` (downward part of the swing), at ``q = q^r`` of the previous tick:

    1. ``x = K(q)``, per-leg Jacobians ``J_l(q)``; current terrain normal ``n_t`` of the three
       stance feet (Eq. 7); mobility ``m_l = m(n_t)`` of every leg (Eq. 12).
    2. Damping ``D_r`` from the swing leg's ``m`` (Fig. 7, :func:`damping_matrix_diag`).
    3. ``f_sw = K_x (x_sw^d - x_sw)`` (Eq. 2); ``tau_kl(q)`` (Eq. 9);
       ``e_b = -orientation_error(n_t, n_t^d)`` (Eq. 8); stance forces from Eq. 6.
    4. ``qd_new = D_r^{-1} (J^T f^r + tau_kl)`` (Eq. 10; end-stop sign, see
       :func:`end_stop_torques`).
    5. Trapezoidal rule ``q^r <- q + dt/2 (qd_prev + qd_new)``; ``x^r = K(q^r)``,
       ``xd^r = J(q^r) qd_new`` (Eq. 11).

    The stance-leg plan is ignored while active (the base does not move during the swing phase,
    Section II). When inactive, the reflex passes the plan through: ``q^r = IK(x^d)``,
    ``x^r = x^d``, ``qd^r = 0``, ``f^r = 0``; diagnostics (mobility, damping, ``e_b``,
    ``tau_kl``) are evaluated at ``IK(x^d)``. Hence the reflex always (re)starts from the plan at
    activation, and when it deactivates (touchdown) the caller takes over from ``x^r``.

    Stability: linearised, the integration ``q_{k+1} = q_k + dt/2 (qd_{k-1} + qd_k)`` with
    ``qd = -lambda (q - q*)`` is stable iff ``dt * lambda < 2``. The stiffest rate is about
    ``k_x * sigma_max(J)^2 / d_sw_min`` (``sigma_max ~ 0.59`` m/rad for HyQ) and
    ``k_kl / d_sw_min`` for the end stops: with Table I, ``dt`` below ~5.9 ms at
    ``k_x = 5000`` and ~1.5 ms at ``k_x = k_x_max = 2e4``.

    Degenerate and invalid inputs (never a silent NaN):

    * collinear stance feet / singular Eq. 6: zero stance forces (the motion stays in the swing
      leg), ``degenerate=True`` (see :func:`distribute_virtual_forces`);
    * any non-finite entry in the state, ``x_des``, ``n_t_des``, ``up``, ``params`` or ``dt``:
      ``input_ok=False``, ``active=False``, the previous state is held (``q^r`` unchanged,
      ``qd^r = 0``) and ``x^r = K(q^r)``. If the held ``q^r`` is itself non-finite it is
      replaced by ``IK(x_des)`` (or the standing pose if ``x_des`` is not finite either).

    Args:
      state: :class:`ReflexState` (``(12,)`` fields); its dtype sets the computation precision.
      inputs: :class:`ReflexInputs` of one robot (shapes checked when traced).
      params: :class:`ReflexParams`; if concrete they are checked with ``validate(dt=dt)``.
      dt: control period (s) in ``(0, 0.02]``, e.g. ``1e-3``; checked if concrete.
      shape: damping-schedule blend, ``"smoothstep"`` or ``"linear"`` (static).
    Returns:
      ``(new_state, output)``.
    """
    check_shapes(state, inputs)
    _check_static(params, dt)
    with jax.named_scope("reflex_step"):
        dtype = state.q_r.dtype
        p = params.astype(dtype)
        x_des = jnp.asarray(inputs.x_des, dtype)
        n_des = jnp.asarray(inputs.n_t_des, dtype)
        up = jnp.asarray(inputs.up, dtype)
        swing = jnp.clip(jnp.asarray(inputs.swing_leg, jnp.int32), 0, 3)
        active = jnp.asarray(inputs.active, bool)
        dt = jnp.asarray(dt, dtype)
        z_up = jnp.asarray(_UP, dtype)

        # ---- Validity and sanitisation (so the numerics never see a NaN) ----
        q_ok = _all_finite(state.q_r)
        x_ok = _all_finite(x_des)
        up_ok = _all_finite(up) & (jnp.sum(up * up) > 0)
        n_ok = _all_finite(n_des) & (jnp.sum(n_des * n_des) > 0)
        p_ok = params_finite(p)
        dt_ok = jnp.isfinite(dt)
        ok = q_ok & x_ok & up_ok & n_ok & p_ok & dt_ok & _all_finite(state.qd_r)

        q_stand = jnp.asarray(robot.Q_STANDING, dtype)
        x_safe = jnp.where(x_ok, x_des, kinematics.foot_positions(q_stand))
        q_plan = kinematics.inverse_kinematics(x_safe).reshape(12)
        q_hold = jnp.where(q_ok, state.q_r, jnp.where(x_ok, q_plan, q_stand))
        qd_prev = jnp.where(ok, state.qd_r, 0.0)
        up = safe_normalize(jnp.where(up_ok, up, z_up), fallback=z_up)
        n_des = jnp.where(n_ok, n_des, up)
        defaults = ReflexParams().astype(dtype)
        p = jax.tree.map(lambda a, d: jnp.where(jnp.isfinite(a), a, d), p, defaults)
        dt = jnp.where(dt_ok, dt, 0.0)

        run = active & ok
        q = jnp.where(run, q_hold, q_plan)

        # ---- Eq. 7, 12: geometry and mobility at q ----
        x = kinematics.foot_positions(q)
        j_legs = kinematics.foot_jacobians(q)
        hot = swing_one_hot(swing, dtype)
        n_t = terrain_normal(select_legs(stance_selector(swing, dtype), x), up)
        mobility = transmission_ratio(j_legs, n_t[None, :])
        # ---- Fig. 7: damping schedule on the swing leg's mobility ----
        d_diag = damping_matrix_diag(swing, usum(hot * mobility, 0), p, shape)
        # ---- Eq. 2, 8, 9, 6 ----
        f_sw = virtual_spring_force(select_legs(hot[None], x_safe)[0], select_legs(hot[None], x)[0], p)
        tau_kl = end_stop_torques(q, p)
        e_b = -orientation_error(n_t, n_des)
        f_r, degenerate = distribute_virtual_forces(
            x, f_sw, swing, j_legs, d_diag, e_b, p, up=up, tau_kl=tau_kl, return_degenerate=True
        )
        # ---- Eq. 10: damper model (end-stop torque added, see end_stop_torques) ----
        tau_r = usum(j_legs * f_r[:, :, None], 1).reshape(12) + tau_kl  # J^T f^r
        qd_new = tau_r / d_diag
        # ---- trapezoidal integration ----
        q_next = q_hold + 0.5 * dt * (qd_prev + qd_new)

        q_new = jnp.where(run, q_next, jnp.where(ok, q_plan, q_hold))
        qd_out = jnp.where(run, qd_new, 0.0)
        # ---- Eq. 11 ----
        x_new, xd_r = jax.jvp(kinematics.foot_positions, (q_new,), (qd_out,))  # K(q^r), J(q^r) qd^r
        x_r = jnp.where(ok & ~active, x_safe, x_new)
        out = ReflexOutput(
            x_r=x_r,
            xd_r=xd_r,
            q_r=q_new,
            qd_r=qd_out,
            mobility=mobility,
            d_diag=d_diag,
            f_r=jnp.where(run, f_r, 0.0),
            e_b=e_b,
            n_t=n_t,
            tau_kl=tau_kl,
            active=run,
            degenerate=degenerate & run,
            input_ok=ok,
            failed=~ok | ~(_all_finite(q_new) & _all_finite(qd_out)) | _diverged(q_new),
        )
        return ReflexState(q_r=q_new, qd_r=qd_out), out


def reflex_rollout(
    state: ReflexState,
    inputs: ReflexInputs,
    params: ReflexParams,
    dt: float | jax.Array,
    n_steps: int | None = None,
    shape: str = "smoothstep",
) -> tuple[ReflexState, ReflexOutput]:
    """Run :func:`reflex_step` over time with ``lax.scan``.

    Args:
      inputs: either per-tick inputs with a leading time axis (``n_steps=None``), or constant
        inputs repeated for ``n_steps`` ticks.
    Returns:
      ``(final_state, outputs)`` with a leading time axis on every output field.
    """
    with jax.named_scope("reflex_rollout"):
        if n_steps is not None:
            xs = None
            length = int(n_steps)
        else:
            xs = inputs
            length = None

        def body(carry, inp):
            return reflex_step(carry, inputs if inp is None else inp, params, dt, shape)

        return jax.lax.scan(body, state, xs, length=length)

