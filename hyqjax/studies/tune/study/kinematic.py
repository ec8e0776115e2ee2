"""The kinematic surrogate of the step-down (Focchi et al. 2017, Section III): an option of ``hyqjax tune``
and a warm start for the closed-loop tuner.

**What is differentiated.** ``lax.scan`` of :func:`hyqjax.reflex.step.reflex_step` (Eq. 1-12) over one
downward haptic search (Section II). A scenario (:class:`KinematicScenarios`) has a swing leg, a standing
pose with the feet perturbed (randomised stance layout), a step depth ``h`` below the stance plane and a
search speed. The plan lifts the swing foot by ``lift`` over ``t_lift`` (reflex inactive), then moves it
down at ``speed`` to ``max_depth`` (active; ``c_sd = 1``). The base is fixed; trunk lowering shows as the
stance feet rising in the base frame. Gradients are reverse mode through the scan. No physics: the
surrogate cannot see the shin striking the edge, the reason it lost in the closed loop (docs/sweeps.md).

**Objective** (per scenario, then the batch mean). With the depth of the swing foot below the stance
plane ``d_k = -n_t . (x_sw - mean(x_st))`` (Eq. 7 on the corrected feet ``x^r``), a soft "still
searching" weight ``w_k = sigmoid((h - d_k) / s)`` and ``c_k = c_sd(k) w_k``, the weighted means
``<y> = sum_k c_k y_k / sum_k c_k`` of: ``mobility`` ``m_bar = sum_i m_i(k)`` (Eq. 12, footnote 8, rewarded);
``lowering``, the mean rise of the stance feet in the base frame (rewarded); ``tilt`` ``|e_b|^2`` (Eq. 8);
``joint_limits`` ``sum_j s softplus((q_j - (q_max - margin)) / s) + s softplus(((q_min + margin) - q_j) / s)``;
``drift`` ``sum_st |x_st,xy - x_st,xy(0)|^2``; plus ``reach = sum_k c_k dt / T_search``, ``shortfall =
relu(h - max_k d_k)`` and a stability penalty ``relu(sigma - 0.9)^2`` with ``sigma`` the reflex's
explicit-integration stability number (``reflex.params.stability_number``, stable below 1). ``loss = sum_term weight_term * term`` (:class:`Objective`).
Only the reflex coordinates of a :class:`.space.ParamSpace` act here; crawl coordinates get zero gradient.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics, robot
from hyqjax.crawl import controller as crawl
from hyqjax.reflex import params as rparams
from hyqjax.reflex import step as hreflex
from hyqjax.studies.tune.space import ParamSpace


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class KinematicScenarios:
    """A batch of kinematic step-down searches (leading batch axis on every field).

    Attributes:
      x0: (B, 4, 3) initial feet in the base frame (standing pose with perturbed feet).
      swing_leg: (B,) int.
      depth: (B,) step depth h below the stance plane (m).
      speed: (B,) search speed (m/s).
    """

    x0: jax.Array
    swing_leg: jax.Array
    depth: jax.Array
    speed: jax.Array

    @property
    def batch_size(self) -> int:
        return int(self.depth.shape[0])


def make_scenarios(n: int, seed: int, depth=(0.12, 0.26), speed=(0.18, 0.3), feet_jitter=0.03,
                   dtype=jnp.float32) -> KinematicScenarios:
    """``n`` randomised searches: swing leg uniform, ``h ~ U(depth)``, speed ``~ U(speed)``, every foot of the
    standing pose moved by ``U(-feet_jitter, feet_jitter)`` per axis (a randomised stance layout / pose)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if not (0.0 < depth[0] <= depth[1] <= 0.45):
        raise ValueError(f"depth must be (lo, hi) with 0 < lo <= hi <= 0.45 m, got {depth}")
    if not (0.0 < speed[0] <= speed[1] <= 1.0):
        raise ValueError(f"speed must be (lo, hi) with 0 < lo <= hi <= 1 m/s, got {speed}")
    if not (0.0 <= feet_jitter <= 0.08):
        raise ValueError(f"feet_jitter must be in [0, 0.08] m, got {feet_jitter}")
    rng = np.random.default_rng(seed)
    x_stand = np.asarray(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, dtype)), np.float64)
    x0 = x_stand[None] + rng.uniform(-feet_jitter, feet_jitter, (n, 4, 3))
    return KinematicScenarios(x0=jnp.asarray(x0, dtype), swing_leg=jnp.asarray(rng.integers(0, 4, n), jnp.int32),
                              depth=jnp.asarray(rng.uniform(*depth, n), dtype),
                              speed=jnp.asarray(rng.uniform(*speed, n), dtype))


@dataclasses.dataclass(frozen=True)
class Objective:
    """Static settings of the kinematic objective and its term weights (see the module docstring)."""

    dt: float = 0.002
    duration: float = 2.0
    lift: float = 0.04
    t_lift: float = 0.1
    max_depth: float = 0.45
    softness: float = 0.01  # s of the soft touchdown (m)
    joint_margin: float = 0.1  # rad
    joint_softness: float = 0.02  # rad
    w_reach: float = 1.0
    w_shortfall: float = 20.0
    w_mobility: float = -1.0
    w_lowering: float = -5.0
    w_tilt: float = 20.0
    w_joint_limits: float = 10.0
    w_drift: float = 50.0
    w_stability: float = 10.0

    def __post_init__(self):
        if not (0.0 < self.dt <= 0.01):
            raise ValueError(f"dt must be in (0, 0.01] s, got {self.dt}")
        if not (self.t_lift < self.duration <= 20.0):
            raise ValueError(f"duration must be in (t_lift={self.t_lift}, 20] s, got {self.duration}")
        if not (0.0 < self.softness <= 0.1):
            raise ValueError(f"softness must be in (0, 0.1] m, got {self.softness}")

    @property
    def n_ticks(self) -> int:
        return int(round(self.duration / self.dt))

    def weights(self) -> dict[str, float]:
        return dict(reach=self.w_reach, shortfall=self.w_shortfall, mobility=self.w_mobility,
                    lowering=self.w_lowering, tilt=self.w_tilt, joint_limits=self.w_joint_limits,
                    drift=self.w_drift, stability=self.w_stability)


def scenario_terms(p: hreflex.ReflexParams, x0, leg, depth, speed, obj: Objective) -> dict[str, jax.Array]:
    """Objective terms of ONE scenario (``vmap`` for a batch): the reflex rollout over one search."""
    dtype = x0.dtype
    up = jnp.asarray([0.0, 0.0, 1.0], dtype)
    n_t_des = hreflex.planned_terrain_normal(x0, leg, up)
    hot = hreflex.swing_one_hot(leg, dtype)
    stance = 1.0 - hot
    q_lo = jnp.asarray(robot.Q_MIN, dtype) + obj.joint_margin
    q_hi = jnp.asarray(robot.Q_MAX, dtype) - obj.joint_margin
    s_q = obj.joint_softness

    def body(state, k):
        t = k.astype(dtype) * obj.dt
        active = t >= obj.t_lift
        z = jnp.where(active, obj.lift - speed * (t - obj.t_lift), obj.lift * t / obj.t_lift)
        z = jnp.maximum(z, -obj.max_depth)
        x_des = x0 + (hot[:, None] * jnp.asarray([0.0, 0.0, 1.0], dtype)) * z
        inp = hreflex.ReflexInputs(x_des=x_des, swing_leg=leg, active=active, n_t_des=n_t_des, up=up)
        state, out = hreflex.reflex_step(state, inp, p, obj.dt)
        x = out.x_r
        n_t = hreflex.terrain_normal(hreflex.stance_feet(x, leg), up)
        x_sw = jnp.sum(hot[:, None] * x, 0)
        centre = jnp.sum(stance[:, None] * x, 0) / 3.0
        d = -jnp.dot(n_t, x_sw - centre)
        rise = jnp.sum(stance * (x[:, 2] - x0[:, 2])) / 3.0
        drift = jnp.sum(stance * jnp.sum((x[:, :2] - x0[:, :2]) ** 2, -1))
        jl = jnp.sum(s_q * jax.nn.softplus((out.q_r - q_hi) / s_q) + s_q * jax.nn.softplus((q_lo - out.q_r) / s_q))
        rec = dict(d=d, active=active.astype(dtype), mobility=jnp.sum(out.mobility), tilt=jnp.sum(out.e_b ** 2),
                   lowering=rise, drift=drift, joint_limits=jl)
        return state, rec

    _, r = jax.lax.scan(body, hreflex.reflex_init(x0, dtype), jnp.arange(obj.n_ticks))
    w = jax.nn.sigmoid((depth - r["d"]) / obj.softness)
    c = r["active"] * w
    csum = jnp.sum(c) + 1e-6
    mean = lambda y: jnp.sum(c * y) / csum
    t_search = obj.duration - obj.t_lift
    d_max = jnp.max(r["d"])
    stab = jax.nn.relu(rparams.stability_number(p, obj.dt) - 0.9) ** 2
    return dict(reach=jnp.sum(c) * obj.dt / t_search, shortfall=jax.nn.relu(depth - d_max),
                mobility=mean(r["mobility"]), lowering=mean(r["lowering"]), tilt=mean(r["tilt"]),
                joint_limits=mean(r["joint_limits"]), drift=mean(r["drift"]), stability=stab,
                reached=(d_max >= depth).astype(dtype), max_depth=d_max)


def batch_terms(p: hreflex.ReflexParams, sc: KinematicScenarios, obj: Objective) -> dict[str, jax.Array]:
    return jax.vmap(lambda x0, leg, h, v: scenario_terms(p, x0, leg, h, v, obj))(sc.x0, sc.swing_leg, sc.depth,
                                                                                   sc.speed)


def loss_from_terms(terms: dict, obj: Objective) -> jax.Array:
    return sum(w * jnp.mean(terms[k]) for k, w in obj.weights().items())


def make_value_and_grad(space: ParamSpace, sc: KinematicScenarios, obj: Objective, base: crawl.CrawlParams):
    """A jitted ``f(theta) -> dict(loss, grad, terms)`` of the surrogate (reverse mode) on ``sc``."""

    def loss(theta):
        p = space.crawl_params(theta, base).reflex
        terms = batch_terms(p, sc, obj)
        return loss_from_terms(terms, obj), {k: jnp.mean(v) for k, v in terms.items()}

    vg = jax.jit(jax.value_and_grad(loss, has_aux=True))

    def f(theta):
        (val, terms), g = vg(theta)
        return dict(loss=val, grad=g, terms=terms)

    return f
