"""Gradient tuning of the height reflex's K_base, damping bounds and mobility thresholds (Focchi et al. 2017,
Section III, Table I) with optax, and its evaluation against Table I and a gradient-free baseline.

**What is differentiated.** The *kinematic* reflex rollout of Section III: ``lax.scan`` of
:func:`hyqjax.reflex.reflex_step` (Eq. 1-12) over one downward haptic search (Section II), as in
``experiments/reflex_figures.py`` (``kinematic_demo``). A scenario (:class:`KinematicScenarios`) has a
swing leg, a standing pose with the feet perturbed (randomised stance layout), a step depth ``h`` below
the stance plane and a search speed. The plan lifts the swing foot by ``lift`` over ``t_lift`` (reflex
inactive), then moves it down at ``speed`` to ``max_depth`` (active; ``c_sd = 1``). The base is fixed;
trunk lowering shows as the stance feet rising in the base frame. Gradients are reverse mode
(``jax.value_and_grad``) through the scan, reflex planner and kinematics.

No MJX term: reverse mode through ``mjx.step`` needs the constraint solver's ``while_loop`` replaced by
a fixed-length scan, and forward mode (``jax.jacfwd``) costs one tangent rollout per parameter (7-10 x
a 9000-tick closed-loop rollout per step, and contact events make those derivatives uninformative about
success, a step function). The closed loop is used only to *evaluate* (:func:`evaluate_mjx`).

**Objective** (per scenario, then the batch mean). With the depth of the swing foot below the stance
plane ``d_k = -n_t . (x_sw - mean(x_st))`` (Eq. 7 on the corrected feet ``x^r``), a soft "still
searching" weight ``w_k = sigmoid((h - d_k) / s)`` (a smooth surrogate of the haptic touchdown at
``d_k >= h``) and ``c_k = c_sd(k) w_k``, the weighted means ``<y> = sum_k c_k y_k / sum_k c_k`` of:

* ``mobility``: ``m_bar = sum_i m_i(k)`` over the four legs (Eq. 12, footnote 8, as
  ``stepdown``'s ``mean_mobility``), rewarded;
* ``lowering``: trunk lowering, the mean rise of the stance feet in the base frame (m), rewarded;
* ``tilt``: ``|e_b|^2`` (Eq. 8), the base orientation change, penalised;
* ``joint_limits``: ``sum_j s softplus((q_j - (q_max - margin)) / s) + s softplus(((q_min + margin) - q_j) / s)``
  over the reflex joints ``q^r``, penalised (joint-limit proximity);
* ``drift``: ``sum_st |x_st,xy - x_st,xy(0)|^2``, the horizontal stance-feet drift, penalised;

plus ``reach = sum_k c_k dt / T_search`` (normalised time to the soft touchdown; 1 if the foot never gets
there) and ``shortfall = relu(h - max_k d_k)`` (m), both penalised, and a stability penalty
``relu(dt k_x sigma^2 / d_sw_min - 1)^2`` (the explicit-integration bound of ``reflex_step``).
``loss = sum_term weight_term * term`` with :class:`Objective`'s weights (signs: rewards negative).

**Parameters** (:class:`TuneParams`, unconstrained ``theta``; always inside ``ReflexParams.validate``'s
ranges): ``k_base = exp(a)``; ``d_sw_min = exp(b)``, ``d_sw_max = d_sw_min + exp(c)`` (ordered), the same
for ``d_st``; ``m_max = M_NOMINAL sigmoid(e)``, ``m_min = m_max sigmoid(f)`` (below the standing pose's
mobility, see :data:`M_NOMINAL`); optionally ``k_x = k_x_max sigmoid(g)``,
``k_kl = exp(i)``, ``delta = 0.5 sigmoid(j)``. Adam (optax) with global-norm clipping; non-finite
updates are skipped (``optax.apply_if_finite``).

**Evaluation** (:func:`evaluate`): tuned vs Table I on held-out kinematic scenarios (another seed and
wider ranges: reach rate with Wilson 95% intervals, ``m_bar`` with a normal 95% interval, every objective
term) and in the closed-loop MJX step-down (:func:`evaluate_mjx`, ``stepdown.run_batch``): success rate
(Wilson), ``mean_mobility`` and the max safe height (``hyqjax.sweep`` definitions). A random-search
baseline (:func:`random_search`) gets the same budget in *primal evaluations*, a gradient step counted as
its measured cost ``t(value_and_grad) / t(value)`` in primal evaluations.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import kinematics, reflex as hreflex, robot
from hyqjax.io import atomic_write

#: Tunable groups: name -> unconstrained keys.
GROUPS = {
    "k_base": ("log_k_base",),
    "damping": ("log_d_sw_min", "log_d_sw_gap", "log_d_st_min", "log_d_st_gap"),
    "mobility": ("logit_m_max", "logit_m_ratio"),
    "k_x": ("logit_k_x",),
    "k_kl": ("log_k_kl",),
    "delta": ("logit_delta",),
}
DEFAULT_GROUPS = ("k_base", "damping", "mobility")
#: Largest singular value of a HyQ foot Jacobian (m/rad), for the stability bound (reflex_step docstring).
SIGMA_MAX = 0.59
#: Mobility m(e_z) (Eq. 12) of every leg in the SRDF standing pose (m/rad). The damping schedule reacts
#: to a *loss* of mobility: thresholds above this would make every swing on flat ground squat the trunk
#: (Table I's m_max = 0.21 sits just below it), which a step-down search alone cannot penalise. The
#: tuner keeps ``m_max < M_NOMINAL``.
M_NOMINAL = 0.2149


def _logit(p):
    return math.log(p / (1 - p))


def theta_from_reflex(p: hreflex.ReflexParams, groups=DEFAULT_GROUPS) -> dict[str, jax.Array]:
    """Unconstrained parameters that map back to ``p`` (scalar fields) for the tuned ``groups``."""
    v = {f.name: float(np.asarray(getattr(p, f.name)).mean()) for f in dataclasses.fields(p)}
    full = dict(log_k_base=math.log(max(v["k_base"], 1e-6)),
                log_d_sw_min=math.log(v["d_sw_min"]), log_d_sw_gap=math.log(v["d_sw_max"] - v["d_sw_min"]),
                log_d_st_min=math.log(v["d_st_min"]), log_d_st_gap=math.log(v["d_st_max"] - v["d_st_min"]),
                logit_m_max=_logit(min(v["m_max"] / M_NOMINAL, 1 - 1e-6)),
                logit_m_ratio=_logit(min(v["m_min"] / v["m_max"], 1 - 1e-6)),
                logit_k_x=_logit(min(max(v["k_x"] / v["k_x_max"], 1e-6), 1 - 1e-6)),
                log_k_kl=math.log(max(v["k_kl"], 1e-6)), logit_delta=_logit(v["delta"] / 0.5))
    keys = [k for g in groups for k in GROUPS[g]]
    return {k: jnp.asarray(full[k], jnp.float32) for k in keys}


def reflex_from_theta(theta: dict, base: hreflex.ReflexParams = hreflex.ReflexParams()) -> hreflex.ReflexParams:
    """``ReflexParams`` of ``theta`` (fields not in ``theta`` from ``base``). Traceable."""
    kw = {}
    if "log_k_base" in theta:
        kw["k_base"] = jnp.exp(theta["log_k_base"])
    for leg in ("sw", "st"):
        if f"log_d_{leg}_min" in theta:
            lo = jnp.exp(theta[f"log_d_{leg}_min"])
            kw[f"d_{leg}_min"], kw[f"d_{leg}_max"] = lo, lo + jnp.exp(theta[f"log_d_{leg}_gap"])
    if "logit_m_max" in theta:
        kw["m_max"] = M_NOMINAL * jax.nn.sigmoid(theta["logit_m_max"])
        kw["m_min"] = kw["m_max"] * jax.nn.sigmoid(theta["logit_m_ratio"])
    if "logit_k_x" in theta:
        kw["k_x"] = jnp.asarray(base.k_x_max) * jax.nn.sigmoid(theta["logit_k_x"])
    if "log_k_kl" in theta:
        kw["k_kl"] = jnp.exp(theta["log_k_kl"])
    if "logit_delta" in theta:
        kw["delta"] = 0.5 * jax.nn.sigmoid(theta["logit_delta"])
    return dataclasses.replace(base, **kw)


def reflex_values(p: hreflex.ReflexParams) -> dict[str, float]:
    return {f.name: float(np.asarray(getattr(p, f.name)).mean()) for f in dataclasses.fields(p)}


# ------------------------------------------------------------------------------------------------
# Scenarios and objective
# ------------------------------------------------------------------------------------------------


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
    mean = lambda y: jnp.sum(c * y) / csum  # noqa: E731
    t_search = obj.duration - obj.t_lift
    d_max = jnp.max(r["d"])
    k_x = jnp.min(hreflex.effective_k_x(p, dtype))
    stab = jax.nn.relu(obj.dt * k_x * SIGMA_MAX**2 / p.d_sw_min - 1.0) ** 2
    return dict(reach=jnp.sum(c) * obj.dt / t_search, shortfall=jax.nn.relu(depth - d_max),
                mobility=mean(r["mobility"]), lowering=mean(r["lowering"]), tilt=mean(r["tilt"]),
                joint_limits=mean(r["joint_limits"]), drift=mean(r["drift"]), stability=stab,
                reached=(d_max >= depth).astype(dtype), max_depth=d_max)


def batch_terms(p: hreflex.ReflexParams, sc: KinematicScenarios, obj: Objective) -> dict[str, jax.Array]:
    return jax.vmap(lambda x0, leg, h, v: scenario_terms(p, x0, leg, h, v, obj))(sc.x0, sc.swing_leg, sc.depth,
                                                                                   sc.speed)


def loss_from_terms(terms: dict, obj: Objective) -> jax.Array:
    return sum(w * jnp.mean(terms[k]) for k, w in obj.weights().items())


def loss_fn(theta: dict, sc: KinematicScenarios, obj: Objective, base=hreflex.ReflexParams()):
    """``(loss, batch-mean terms)`` of ``theta`` on the scenarios (differentiable in ``theta``)."""
    p = reflex_from_theta(theta, base)
    terms = batch_terms(p, sc, obj)
    return loss_from_terms(terms, obj), {k: jnp.mean(v) for k, v in terms.items()}


# ------------------------------------------------------------------------------------------------
# Tuning run with logging, checkpoints and resume
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """A tuning run (its hash guards resume).

    Attributes:
      steps: optimiser steps.
      batch: training scenarios (a fixed set drawn from ``seed``).
      seed: training-set seed.
      lr: Adam learning rate on ``theta``.
      clip: global-norm gradient clipping.
      groups: tuned parameter groups (:data:`GROUPS`).
      checkpoint_every: checkpoint period (steps).
      depth, speed, feet_jitter: training scenario ranges.
      objective: :class:`Objective`.
    """

    steps: int = 40
    batch: int = 16
    seed: int = 0
    lr: float = 0.05
    clip: float = 1.0
    groups: tuple = DEFAULT_GROUPS
    checkpoint_every: int = 5
    depth: tuple = (0.12, 0.26)
    speed: tuple = (0.18, 0.3)
    feet_jitter: float = 0.03
    objective: Objective = Objective()

    def __post_init__(self):
        checks = dict(steps=(self.steps, 0, 100000), batch=(self.batch, 1, 100000),
                      checkpoint_every=(self.checkpoint_every, 1, 100000))
        for k, (v, lo, hi) in checks.items():
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if not (0.0 < self.lr <= 1.0):
            raise ValueError(f"lr must be in (0, 1], got {self.lr}")
        if not (0.0 < self.clip <= 1e3):
            raise ValueError(f"clip must be in (0, 1000], got {self.clip}")
        bad = [g for g in self.groups if g not in GROUPS]
        if bad or not self.groups:
            raise ValueError(f"groups must be a non-empty subset of {list(GROUPS)}, got {list(self.groups)}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["groups"] = list(self.groups)
        return d

    @property
    def hash(self) -> str:
        d = self.to_dict()
        d.pop("steps")  # more steps continue the same run
        d.pop("checkpoint_every")
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()

    def train_set(self) -> KinematicScenarios:
        return make_scenarios(self.batch, self.seed, self.depth, self.speed, self.feet_jitter)


def make_optimizer(cfg: TuneConfig):
    import optax

    return optax.apply_if_finite(optax.chain(optax.clip_by_global_norm(cfg.clip), optax.adam(cfg.lr)), 10)


_STEP_FNS: dict = {}


def _step_fn(cfg: TuneConfig):
    key = (cfg.objective, cfg.lr, cfg.clip)
    if key not in _STEP_FNS:
        import optax

        opt = make_optimizer(cfg)

        @jax.jit
        def step(theta, opt_state, sc):
            (loss, terms), g = jax.value_and_grad(loss_fn, has_aux=True)(theta, sc, cfg.objective)
            updates, opt_state = opt.update(g, opt_state, theta)
            return optax.apply_updates(theta, updates), opt_state, loss, terms, optax.global_norm(g)

        _STEP_FNS[key] = step
    return _STEP_FNS[key]


def save_checkpoint(path: str, step: int, theta: dict, opt_state, cfg: TuneConfig) -> None:
    """Atomic ``.npz`` of the step, ``theta`` and the optimiser state leaves."""
    leaves = jax.tree_util.tree_leaves(opt_state)
    arrays = {f"theta/{k}": np.asarray(v) for k, v in theta.items()}
    arrays.update({f"opt/{i:04d}": np.asarray(v) for i, v in enumerate(leaves)})
    arrays["step"] = np.asarray(step)
    arrays["config_hash"] = np.asarray(cfg.hash)
    atomic_write(path, lambda f: np.savez(f, **arrays))


def load_checkpoint(path: str, cfg: TuneConfig):
    """``(step, theta, opt_state)`` from :func:`save_checkpoint` (optimiser structure from a fresh init)."""
    with np.load(path) as z:
        if str(z["config_hash"]) != cfg.hash:
            raise RuntimeError(f"{path} belongs to a different tuning configuration; use another --out")
        theta = {k.split("/", 1)[1]: jnp.asarray(z[k]) for k in z.files if k.startswith("theta/")}
        opt_leaves = [jnp.asarray(z[k]) for k in sorted(k for k in z.files if k.startswith("opt/"))]
        step = int(z["step"])
    treedef = jax.tree_util.tree_structure(make_optimizer(cfg).init(theta))
    return step, theta, jax.tree_util.tree_unflatten(treedef, opt_leaves)


def run_tune(cfg: TuneConfig, out_dir: str, stop_after: int | None = None, progress: bool = True,
             base: hreflex.ReflexParams | None = None) -> dict:
    """Tune (or resume tuning) into ``out_dir``: ``config.json``, ``log.jsonl`` (one line per step:
    loss, terms, grad norm, parameters, wall time), ``checkpoint.npz`` (every ``checkpoint_every`` steps and
    at the end, atomically). ``stop_after`` ends this call after that many steps (an interruption).
    Returns ``dict(step, theta, params, losses)``."""
    from tqdm.auto import tqdm

    base = base or hreflex.ReflexParams.table1()
    os.makedirs(out_dir, exist_ok=True)
    cpath, ckpt, lpath = (os.path.join(out_dir, n) for n in ("config.json", "checkpoint.npz", "log.jsonl"))
    if os.path.exists(cpath):
        with open(cpath) as f:
            old = json.load(f)
        if old.get("hash") != cfg.hash:
            raise RuntimeError(f"{out_dir} holds a tuning run of another configuration (hash {old.get('hash', '?')[:12]}"
                               f" != {cfg.hash[:12]}); use another --out or remove it")
    atomic_write(cpath, lambda f: f.write(json.dumps(dict(config=cfg.to_dict(), hash=cfg.hash), indent=1).encode()))
    opt = make_optimizer(cfg)
    if os.path.exists(ckpt):
        step, theta, opt_state = load_checkpoint(ckpt, cfg)
    else:
        step, theta = 0, theta_from_reflex(base, cfg.groups)
        opt_state = opt.init(theta)
    # The log keeps exactly the steps before the checkpoint (steps after it are recomputed).
    lines = []
    if os.path.exists(lpath):
        with open(lpath) as f:
            lines = [ln for ln in f if ln.strip() and json.loads(ln)["step"] < step]
    atomic_write(lpath, lambda f: f.write("".join(lines).encode()))
    sc = cfg.train_set()
    fn = _step_fn(cfg)
    end = cfg.steps if stop_after is None else min(cfg.steps, step + stop_after)
    bar = tqdm(total=cfg.steps, initial=step, unit="step", desc="tune", disable=not progress, dynamic_ncols=True)
    t0 = time.time()
    try:
        with open(lpath, "a") as log:
            while step < end:
                theta_before = theta
                theta, opt_state, loss, terms, gnorm = fn(theta, opt_state, sc)
                rec = dict(step=step, loss=float(loss), grad_norm=float(gnorm),
                           terms={k: float(v) for k, v in terms.items()},
                           params=reflex_values(reflex_from_theta(theta_before, base)),
                           theta={k: float(v) for k, v in theta_before.items()}, wall_s=round(time.time() - t0, 3))
                log.write(json.dumps(rec) + "\n")
                log.flush()
                step += 1
                bar.update(1)
                bar.set_postfix(loss=f"{float(loss):.4f}", gnorm=f"{float(gnorm):.3g}")
                if step % cfg.checkpoint_every == 0 or step == end:
                    save_checkpoint(ckpt, step, theta, opt_state, cfg)
    finally:
        bar.close()
    with open(lpath) as f:
        losses = [json.loads(ln)["loss"] for ln in f if ln.strip()]
    return dict(step=step, theta=theta, params=reflex_from_theta(theta, base), losses=losses)


def read_log(out_dir: str) -> list[dict]:
    with open(os.path.join(out_dir, "log.jsonl")) as f:
        return [json.loads(ln) for ln in f if ln.strip()]


# ------------------------------------------------------------------------------------------------
# Cost model, gradient-free baseline, evaluation
# ------------------------------------------------------------------------------------------------


def measure_cost(cfg: TuneConfig, repeats: int = 3) -> dict[str, float]:
    """Median wall time of one jitted primal evaluation and one ``value_and_grad`` on the training set;
    ``grad_cost`` = their ratio (a gradient step counted in primal evaluations)."""
    sc = cfg.train_set()
    theta = theta_from_reflex(hreflex.ReflexParams.table1(), cfg.groups)
    f = jax.jit(lambda th, s: loss_fn(th, s, cfg.objective)[0])
    g = jax.jit(jax.value_and_grad(lambda th, s: loss_fn(th, s, cfg.objective)[0]))

    def timed(fn):
        jax.block_until_ready(fn(theta, sc))
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(fn(theta, sc))
            ts.append(time.perf_counter() - t)
        return float(np.median(ts))

    tp, tg = timed(f), timed(g)
    return dict(t_primal_s=tp, t_grad_s=tg, grad_cost=tg / tp)


def random_search(cfg: TuneConfig, n_evals: int, sigma: float = 0.5, seed: int = 1, base=None) -> dict:
    """Gradient-free baseline: ``theta_i = theta_Table_I + sigma N(0, I)`` (log / logit space), each candidate
    evaluated once on the training set; returns the best and the best-so-far curve per evaluation."""
    base = base or hreflex.ReflexParams.table1()
    if n_evals < 1:
        raise ValueError(f"n_evals must be >= 1, got {n_evals}")
    sc = cfg.train_set()
    theta0 = theta_from_reflex(base, cfg.groups)
    f = jax.jit(lambda th, s: loss_fn(th, s, cfg.objective, base)[0])
    rng = np.random.default_rng(seed)
    best_theta, best = theta0, float(f(theta0, sc))
    curve = [best]
    for _ in range(n_evals - 1):
        cand = {k: v + jnp.asarray(sigma * rng.standard_normal(), v.dtype) for k, v in theta0.items()}
        val = float(f(cand, sc))
        if np.isfinite(val) and val < best:
            best, best_theta = val, cand
        curve.append(best)
    return dict(theta=best_theta, params=reflex_from_theta(best_theta, base), loss=best, curve=curve)


def evaluate_kinematic(params: dict[str, hreflex.ReflexParams], sc: KinematicScenarios, obj: Objective) -> dict:
    """Per parameter set: the loss, mean terms, reach rate (Wilson 95%) and ``m_bar`` (normal 95%) on ``sc``."""
    from hyqjax.stepdown import wilson_interval

    out = {}
    f = jax.jit(lambda p, s: batch_terms(p, s, obj))
    for name, p in params.items():
        t = {k: np.asarray(v, np.float64) for k, v in f(p, sc).items()}
        k, n = int(t["reached"].sum()), t["reached"].size
        m = t["mobility"]
        half = 1.96 * m.std(ddof=1) / math.sqrt(n) if n > 1 else float("nan")
        out[name] = dict(loss=float(sum(w * t[kk].mean() for kk, w in obj.weights().items())),
                         terms={kk: float(v.mean()) for kk, v in t.items()}, reach_rate=k / n,
                         reach_ci95=list(wilson_interval(k, n)), m_bar=float(m.mean()),
                         m_bar_ci95=[float(m.mean() - half), float(m.mean() + half)], n=n)
    return out


def evaluate_mjx(params: dict[str, hreflex.ReflexParams], heights, instances: int, seed: int,
                 duration: float = 18.0) -> dict:
    """Closed-loop MJX step-down (``stepdown.run_batch``, reflex on) per parameter set, one batch (one
    compile): success rate (Wilson 95%) overall and per height, ``mean_mobility`` (normal 95%), and the
    max safe height (``h95_wilson``, ``h95_logistic`` as in :mod:`hyqjax.sweep`)."""
    from hyqjax import crawl, stepdown, sweep

    names = list(params)
    parts, tables = [], []
    for name in names:
        p = params[name]
        rp = hreflex.ReflexParams(**{k: float(v) for k, v in reflex_values(p).items()}).validate()
        sc, tab = stepdown.make_scenarios(heights, [True], instances, seed,
                                          params=crawl.CrawlParams.make(reflex_params=rp))
        parts.append(sc)
        tables.append(tab)
    scen = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, 0), *parts)
    t0 = time.time()
    out, _ = stepdown.run_batch(scen, stepdown.StepdownConfig(duration=duration))
    wall = time.time() - t0
    out = sweep.count_outcomes(out)
    res = dict(wall_s=wall, heights=list(heights), instances=instances, seed=seed, duration=duration)
    b = len(tables[0]["height"])
    for i, name in enumerate(names):
        sl = slice(i * b, (i + 1) * b)
        h = tables[i]["height"]
        s = out["success"][sl]
        mm = out["mean_mobility"][sl].astype(np.float64)
        curve = []
        for hh in sorted(set(h.tolist())):
            k, n = int(s[h == hh].sum()), int((h == hh).sum())
            curve.append(dict(height=hh, n=n, successes=k, rate=k / n, ci95=list(stepdown.wilson_interval(k, n))))
        h95 = None
        for c in curve:
            if c["ci95"][0] < 0.95:
                break
            h95 = c["height"]
        half = 1.96 * mm.std(ddof=1) / math.sqrt(mm.size) if mm.size > 1 else float("nan")
        res[name] = dict(success=int(s.sum()), n=int(s.size), rate=float(s.mean()),
                         ci95=list(stepdown.wilson_interval(int(s.sum()), int(s.size))),
                         mean_mobility=float(mm.mean()), mean_mobility_ci95=[float(mm.mean() - half),
                                                                              float(mm.mean() + half)],
                         height_curve=curve, h95_wilson=h95,
                         h95_logistic=sweep._logistic_h95(h.astype(float), s.astype(float)),
                         failure_reasons=sorted(set(out["failure_reason"][sl].tolist()) - {""}))
    return res


def plot_run(log: list[dict], path: str, baseline_curve: list[float] | None = None, grad_cost: float | None = None):
    """Loss curve (vs primal-evaluation budget when ``grad_cost`` is given, with the random-search curve)
    and the parameter trajectories relative to Table I."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 4.2))
    steps = np.asarray([r["step"] for r in log])
    loss = np.asarray([r["loss"] for r in log])
    x = steps + 1 if grad_cost is None else (steps + 1) * grad_cost
    a1.plot(x, loss, "C0", label="Adam (gradient)")
    if baseline_curve is not None:
        a1.plot(np.arange(1, len(baseline_curve) + 1), baseline_curve, "C1", label="random search (best so far)")
    a1.set_xlabel("optimizer step" if grad_cost is None else "cost [primal evaluations]")
    a1.set_ylabel("training loss")
    a1.grid(alpha=0.3)
    a1.legend()
    t1 = reflex_values(hreflex.ReflexParams.table1())
    keys = [k for k in ("k_base", "d_sw_min", "d_sw_max", "d_st_min", "d_st_max", "m_min", "m_max", "k_x", "k_kl",
                        "delta") if any(abs(r["params"][k] - t1[k]) > 1e-9 * max(1, abs(t1[k])) for r in log)]
    for k in keys:
        a2.plot(steps, [r["params"][k] / t1[k] for r in log], label=k)
    a2.set_yscale("log")
    a2.set_xlabel("optimizer step")
    a2.set_ylabel("value / Table I")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def default_base() -> hreflex.ReflexParams:
    return hreflex.ReflexParams.table1()


__all__ = ["GROUPS", "KinematicScenarios", "Objective", "TuneConfig", "batch_terms", "evaluate_kinematic",
           "evaluate_mjx", "loss_fn", "make_scenarios", "measure_cost", "plot_run", "random_search",
           "read_log", "reflex_from_theta", "run_tune", "scenario_terms", "theta_from_reflex"]
_ = Any
