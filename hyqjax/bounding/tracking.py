"""Tracking metrics of a bounding run, accumulated on the device every tick (ground truth), and the smooth
cost the robust baseline optimisation minimises (:mod:`hyqjax.bounding.robust`).

Per control tick ``k`` (``dt`` = 2 ms), with ``psi`` the trunk's yaw, ``psi^d`` the controller's desired yaw
(the integral of the ramped yaw-rate command from the initial heading, as in :mod:`hyqjax.bounding.summary`),
``v_f``, ``v_l`` the trunk's forward and lateral speed in the heading frame and ``v^d`` the ramped command:

* yaw error ``e_k = wrap(psi^d - psi)``: its largest ``|e|`` over the run (the paper's Fig. 4 quantity);
* speed errors filtered over one gait period (the stride's oscillation removed),
  ``eps_{k+1} = eps_k + (dt / T) (v_k - v^d_k - eps_k)``, forward and lateral;
* settled means of ``v_f``, ``v_l`` over the ticks after ``settle`` s;
* apex height: at every apex (the controller's ``new_cycle`` event) ``(z - z^*)^2``;
* fall margins, ``sp_s(x) = s softplus(x / s)`` a smooth ``max(x, 0)``:
  ``M_k = sp(z_0 - z)^2 + sp(|phi| - phi_0)^2 + sp(|theta| - theta_0)^2`` (trunk height, roll, pitch), margins well
  inside the fall thresholds of :mod:`hyqjax.bounding.rollout` (0.35 m, 0.7 rad);
* falls (:class:`hyqjax.bounding.falls.FallMetrics`).

The cost terms accumulate only while the instance has not fallen (a robot on the ground tells nothing about
the gains). The cost of one instance (:func:`cost_terms`, :func:`total_cost`; bars are means over the ticks
before a fall, the apex term's over the apexes before it):

.. math:: L = w_\\psi \\overline{(e / 4^\\circ)^2}
          + w_x \\overline{\\mathrm{sp}_{0.5^\\circ}(|e| - 3^\\circ)^2} / (1^\\circ)^2
          + w_v \\overline{(\\epsilon_f / 0.1)^2} + w_l \\overline{(\\epsilon_l / 0.1)^2}
          + w_z \\overline{((z_a - z^*) / 0.02)^2} + w_M \\overline{M} / 0.02^2 + w_F\\, \\mathbb 1[\\text{fell}]

The fall indicator is a constant of the parameters almost everywhere: it counts in the value (line search,
CMA-ES, the reports) and gives no gradient; the margins are its smooth surrogate.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding import batch as bbatch
from hyqjax.bounding import falls
from hyqjax.bounding import rollout as brollout
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.sim import backend
from hyqjax.sim import rollout as sim

DEG = math.pi / 180.0


@dataclasses.dataclass(frozen=True)
class CostSpec:
    """Margins, softnesses, scales and weights of the tracking cost (see the module docstring); hashable (static)."""

    period: float = 0.4
    settle: float = 2.0
    apex_height: float = 0.6
    z_margin: float = 0.45
    roll_margin: float = 0.3
    pitch_margin: float = 0.5
    margin_soft: float = 0.01
    yaw_scale: float = 4.0 * DEG
    yaw_excess: float = 3.0 * DEG
    yaw_excess_soft: float = 0.5 * DEG
    speed_scale: float = 0.1
    apex_scale: float = 0.02
    margin_scale: float = 0.02
    w_yaw: float = 1.0
    w_yaw_excess: float = 1.0
    w_speed: float = 1.0
    w_lateral: float = 0.5
    w_apex: float = 0.5
    w_margin: float = 10.0
    w_fall: float = 20.0

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v!r}")
        for k in ("period", "margin_soft", "yaw_scale", "yaw_excess_soft", "speed_scale", "apex_scale", "margin_scale"):
            if not getattr(self, k) > 0:
                raise ValueError(f"{k} must be > 0, got {getattr(self, k)}")


TERMS = ("yaw", "yaw_excess", "speed", "lateral", "apex", "margin", "fall")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrackingMetrics:
    """Device accumulators of one instance (see the module docstring).

    Attributes:
      fall: :class:`hyqjax.bounding.falls.FallMetrics`.
      max_yaw_err: largest ``|e|`` (rad) before a fall.
      eps: (2,) filtered forward / lateral speed error (m/s).
      settled_v: (2,) sum of ``v_f``, ``v_l`` over the settled ticks before a fall.  settled_n: their count.
      alive_n: ticks before a fall.  sum_yaw2, sum_yaw_excess2, sum_eps2 (2,), sum_margin: sums of the cost terms
        over those ticks.  apex_n, sum_apex2: apex events and their squared height errors.
    """

    fall: falls.FallMetrics
    max_yaw_err: jax.Array
    eps: jax.Array
    settled_v: jax.Array
    settled_n: jax.Array
    alive_n: jax.Array
    sum_yaw2: jax.Array
    sum_yaw_excess2: jax.Array
    sum_eps2: jax.Array
    sum_margin: jax.Array
    apex_n: jax.Array
    sum_apex2: jax.Array


def _sp(x, s):
    return s * jax.nn.softplus(x / s)


def tracking_metrics(spec: CostSpec = CostSpec(), control_dt: float = 0.002) -> sim.Metrics:
    """:class:`TrackingMetrics` as a :class:`hyqjax.sim.rollout.Metrics` pair (pure JAX; runs under both MJX
    implementations: it reads only ``qpos``, ``qvel`` and the controller's info)."""
    fm = falls.fall_metrics()
    gain = control_dt / spec.period

    def init(d):
        dt = d.qpos.dtype
        z = jnp.zeros((), dt)
        return TrackingMetrics(fall=fm.init(d), max_yaw_err=z, eps=jnp.zeros(2, dt), settled_v=jnp.zeros(2, dt),
                               settled_n=jnp.array(0), alive_n=jnp.array(0), sum_yaw2=z, sum_yaw_excess2=z,
                               sum_eps2=jnp.zeros(2, dt), sum_margin=z, apex_n=jnp.array(0), sum_apex2=z)

    def update(ms: TrackingMetrics, d, obs, info):
        dt = d.qpos.dtype
        alive = ms.fall.fall_tick < 0
        af = alive.astype(dt)
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
        psi = rpy[2]
        e = jnp.arctan2(jnp.sin(info.yaw_des - psi), jnp.cos(info.yaw_des - psi))
        v = d.qvel[robot.QVEL_BASE_LIN]
        c, s = jnp.cos(psi), jnp.sin(psi)
        v_h = jnp.stack([c * v[0] + s * v[1], -s * v[0] + c * v[1]])
        eps = ms.eps + gain * (v_h - info.v_des.astype(dt) - ms.eps)
        z = d.qpos[robot.QPOS_BASE_POS][2]
        margin = (_sp(spec.z_margin - z, spec.margin_soft) ** 2 + _sp(jnp.abs(rpy[0]) - spec.roll_margin,
                                                                       spec.margin_soft) ** 2
                  + _sp(jnp.abs(rpy[1]) - spec.pitch_margin, spec.margin_soft) ** 2)
        settled = alive & (d.time >= spec.settle)
        apex = alive & info.new_cycle
        return TrackingMetrics(
            fall=fm.update(ms.fall, d, obs, info),
            max_yaw_err=jnp.where(alive, jnp.maximum(ms.max_yaw_err, jnp.abs(e)), ms.max_yaw_err),
            eps=eps, settled_v=ms.settled_v + settled.astype(dt) * v_h, settled_n=ms.settled_n + settled,
            alive_n=ms.alive_n + alive, sum_yaw2=ms.sum_yaw2 + af * e * e,
            sum_yaw_excess2=ms.sum_yaw_excess2 + af * _sp(jnp.abs(e) - spec.yaw_excess, spec.yaw_excess_soft) ** 2,
            sum_eps2=ms.sum_eps2 + af * eps * eps, sum_margin=ms.sum_margin + af * margin,
            apex_n=ms.apex_n + apex, sum_apex2=ms.sum_apex2 + apex.astype(dt) * (z - spec.apex_height) ** 2)

    return sim.Metrics(init, update)


def cost_terms(ms: TrackingMetrics, spec: CostSpec = CostSpec(), xp=jnp) -> dict:
    """The weighted terms of :math:`L` (module docstring) of one instance or a batch (``xp``: ``jnp`` or ``np``)."""
    n = xp.maximum(xp.asarray(ms.alive_n), 1)
    na = xp.maximum(xp.asarray(ms.apex_n), 1)
    eps2 = xp.asarray(ms.sum_eps2)
    fell = (xp.asarray(ms.fall.fall_tick) >= 0)
    return dict(
        yaw=spec.w_yaw * xp.asarray(ms.sum_yaw2) / n / spec.yaw_scale ** 2,
        yaw_excess=spec.w_yaw_excess * xp.asarray(ms.sum_yaw_excess2) / n / DEG ** 2,
        speed=spec.w_speed * eps2[..., 0] / n / spec.speed_scale ** 2,
        lateral=spec.w_lateral * eps2[..., 1] / n / spec.speed_scale ** 2,
        apex=spec.w_apex * xp.asarray(ms.sum_apex2) / na / spec.apex_scale ** 2,
        margin=spec.w_margin * xp.asarray(ms.sum_margin) / n / spec.margin_scale ** 2,
        fall=spec.w_fall * fell.astype(eps2.dtype))


def total_cost(ms: TrackingMetrics, spec: CostSpec = CostSpec(), xp=jnp):
    """:math:`L` of one instance or a batch."""
    return sum(cost_terms(ms, spec, xp).values())


def columns(ms: TrackingMetrics, diverged, diverged_tick, control_dt: float = 0.002) -> dict[str, np.ndarray]:
    """Per-instance NumPy columns of a batch: failure flags and reasons (a divergence before or without a fall
    is the reason ``diverged``; at most one reason per instance), fail time, worst yaw error (deg), settled mean
    forward / lateral speed (NaN without a settled tick) and the raw accumulators."""
    f = ms.fall
    fall_tick = np.asarray(f.fall_tick)
    div = np.asarray(diverged, bool)
    div_tick = np.asarray(diverged_tick)
    div_first = div & ((fall_tick < 0) | (div_tick <= fall_tick))
    fell = (fall_tick >= 0) & ~div_first
    sn = np.asarray(ms.settled_n)
    sv = np.asarray(ms.settled_v, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_v = np.where(sn[:, None] > 0, sv / np.maximum(sn, 1)[:, None], np.nan)
    fail_tick = np.where(div_first, div_tick, np.where(fell, fall_tick, -1))
    return dict(success=~(fell | div_first), fell_low_trunk=fell & np.asarray(f.low_trunk),
                fell_roll=fell & np.asarray(f.roll), fell_pitch=fell & np.asarray(f.pitch), diverged=div_first,
                fail_time=np.where(fail_tick >= 0, (fail_tick + 1) * control_dt, np.nan),
                yaw_error_max_deg=np.degrees(np.asarray(ms.max_yaw_err, np.float64)),
                speed_mean=mean_v[:, 0], lateral_speed_mean=mean_v[:, 1],
                min_height=np.asarray(f.min_z, np.float64), max_roll_deg=np.degrees(np.asarray(f.max_roll)),
                max_pitch_deg=np.degrees(np.asarray(f.max_pitch)))


# ----------------------------------------------------------------------------------------------
# Batched forward runs with these metrics
# ----------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=40)
def _runner(sim_cfg: sim.SimConfig, spec: CostSpec, impl: str, where=None):
    """One batch runner per static config, cost spec, simulator and placement (a runner fixes the batched model's
    pytree structure, which differs between the simulators; ``where``: None, a mesh, or one device of a split
    batch, :func:`hyqjax.sim.runner.run_on`)."""
    from hyqjax.bounding import controller as bctrl
    from hyqjax.bounding import cycle as bc

    _, _, ids = bc.model()
    mesh = where if where is not None and hasattr(where, "axis_names") else None
    if where is not None and mesh is None and hasattr(_runner(sim_cfg, spec, impl, None), "placed"):
        return _runner(sim_cfg, spec, impl, None).placed(where)  # the one-device runner there: one trace for all
    return backend.get(impl).make_runner(ids, bctrl.bounding_controller, sim_cfg,
                                         tracking_metrics(spec, sim_cfg.control_dt), None, mesh=mesh)


def take(batch: bbatch.Batch, idx) -> bbatch.Batch:
    """The instances ``idx`` of a batch (NumPy fancy indexing on every leaf)."""
    idx = np.asarray(idx)
    return jax.tree_util.tree_map(lambda x: x[idx] if isinstance(x, np.ndarray) else jnp.asarray(x)[idx], batch)


def run_batch(batch: bbatch.Batch, duration: float, impl: str = "auto", spec: CostSpec = CostSpec(),
              max_batch: int = 16384, control_dt: float = 0.002, progress=None,
              devices=None) -> dict[str, np.ndarray]:
    """Simulate every instance of ``batch`` for ``duration`` s (a whole number of gait periods) with
    :func:`tracking_metrics` and return NumPy columns: :func:`columns`, the cost :math:`L` (``cost``) and its
    terms (``cost_<term>``).

    Instances run in chunks of at most ``max_batch`` (the last padded by repeating its first instance, so one
    program serves every chunk; the padding is dropped). ``impl``: simulator (``auto | jax | warp | c``).
    ``progress(done, total)`` is called after every chunk with the instances done. ``devices``: where each chunk
    runs (:func:`hyqjax.sim.devices.resolve`; None: the process's selection, every local device by default), in
    the simulator's layout (:func:`hyqjax.sim.runner.run_on`); ``max_batch`` counts the instances of a chunk over
    all of them.
    """
    from hyqjax.sim import backend as hbackend
    from hyqjax.sim import runner as srunner

    cfg = brollout.BoundingRolloutConfig(duration=duration, control_dt=control_dt, impl=impl)
    cfg.check_period(batch.params.gait.period)
    if not (isinstance(max_batch, int) and max_batch >= 1):
        raise ValueError(f"max_batch must be an int >= 1, got {max_batch!r}")
    st = brollout.setup(control_dt, impl)
    devs = hbackend.devices_for(st.impl, devices)
    n = int(np.shape(batch.apex0)[0])
    size = -(-n // -(-n // max_batch))  # balanced chunks of at most max_batch
    out: list[dict] = []
    for start in range(0, n, size):
        idx = np.arange(start, min(start + size, n))
        pad = np.concatenate([idx, np.full(size - idx.size, idx[0])])

        def inputs_of(rows, pad=pad):
            b = take(batch, pad[rows])
            mb = st.backend.batch_model(st.mx, st.ids, b.terrain)
            d0 = brollout.apex_initial_data(b, st.m, st.mx_jax)
            d0 = st.backend.from_jax_data(mb, d0, st.m)  # the JAX state as the simulator's data of the batch
            return mb, d0, b.params, b.push

        if devs == [None]:  # C MuJoCo: its own CPU runner
            res = _runner(cfg.sim_config(), spec, st.impl)(*inputs_of(np.arange(size)))
        else:
            res = srunner.run_on(devs, size, inputs_of, lambda where: _runner(cfg.sim_config(), spec, st.impl,
                                                                                   where), st.impl)
        ms = jax.tree_util.tree_map(np.asarray, res.metrics)
        cols = columns(ms, res.diverged, res.diverged_tick, control_dt)
        terms = cost_terms(ms, spec, np)
        cols.update({f"cost_{k}": np.asarray(v, np.float64) for k, v in terms.items()})
        cols["cost"] = np.sum([cols[f"cost_{k}"] for k in terms], 0)
        out.append({k: v[: idx.size] for k, v in cols.items()})
        if progress is not None:
            progress(int(idx[-1]) + 1, n)
    return {k: np.concatenate([o[k] for o in out]) for k in out[0]}
