"""Sweep input rows as step-down scenarios, and the sensed controller (sensor noise and control latency).

:func:`build_scenario` turns the input rows of :meth:`SweepSpec.instance_inputs` into a batched
:class:`hyqjax.studies.stepdown.Scenario` (terrain, payload, initial pose, per-instance crawl, joint PD
and reflex parameters, push).

Sensor noise and control latency are applied by wrapping the crawl controller (:func:`sensed_controller`):
Gaussian noise on the joint encoders, joint velocities, IMU orientation (a small random rotation
``quat <- quat (x) [1, dphi / 2]``, normalised) and angular rate and the estimated foot forces; a latency
of ``d`` ticks hands the controller the (noisy) observation of ``d`` ticks ago, from a ring buffer in
the controller state. A sweep without those axes runs the crawl controller unwrapped, as
:func:`stepdown.run_batch`. The noise key of instance ``i`` is ``fold_in(PRNGKey(seed), i)``, so it
depends on the instance only, never on the chunk or device that runs it.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.control import impedance
from hyqjax.core import spatial
from hyqjax import presets
from hyqjax.crawl import controller as crawl
from hyqjax.crawl import scheduled
from hyqjax.reflex import step as hreflex
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim
from hyqjax.studies import stepdown
from hyqjax.studies.sweep.spec import SweepSpec


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensorParams:
    """Per-instance sensor model: noise standard deviations, latency in ticks, PRNG key."""

    joint_pos: jax.Array
    joint_vel: jax.Array
    imu: jax.Array
    gyro: jax.Array
    foot_force: jax.Array
    delay: jax.Array  # int, ticks
    key: jax.Array  # (2,) uint32


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensedParams:
    crawl: crawl.CrawlParams  # or a per-leg set (hyqjax.crawl.scheduled)
    sensor: SensorParams


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensedState:
    inner: Any
    buffer: sim.Observation  # leading axis: ticks ago (0 = now)
    key: jax.Array


def _noisy(obs: sim.Observation, sp: SensorParams, key) -> sim.Observation:
    k = jax.random.split(key, 5)
    dt = obs.q.dtype
    q = obs.q + sp.joint_pos * jax.random.normal(k[0], obs.q.shape, dt)
    qd = obs.qd + sp.joint_vel * jax.random.normal(k[1], obs.qd.shape, dt)
    # A small rotation of std ``imu`` per axis: quat <- quat (x) [1, dphi / 2], normalised.
    dphi = sp.imu * jax.random.normal(k[2], (3,), dt)
    quat = spatial.quat_normalize(spatial.quat_mul(obs.quat, jnp.concatenate([jnp.ones(1, dt), 0.5 * dphi])))
    gyro = obs.gyro + sp.gyro * jax.random.normal(k[3], (3,), dt)
    ff = obs.foot_force + sp.foot_force * jax.random.normal(k[4], obs.foot_force.shape, dt)
    return dataclasses.replace(obs, q=q, qd=qd, quat=quat, gyro=gyro, foot_force=ff)


def sensed_controller(inner: sim.Controller, max_delay: int) -> sim.Controller:
    """Wrap ``inner`` (params :class:`SensedParams`) with sensor noise and a latency of ``delay <= max_delay``
    ticks: the controller gets ``obs~(k - delay)`` with ``obs~ = obs + noise`` (independent Gaussian per tick)."""

    def init(p: SensedParams, obs):
        buf = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (max_delay + 1,) + x.shape), obs)
        return SensedState(inner.init(p.crawl, obs), buf, p.sensor.key)

    def step(p: SensedParams, s: SensedState, obs):
        key, sub = jax.random.split(s.key)
        noisy = _noisy(obs, p.sensor, sub)
        buf = jax.tree_util.tree_map(lambda b, x: jnp.concatenate([x[None], b[:-1]], 0), s.buffer, noisy)
        seen = jax.tree_util.tree_map(lambda b: b[jnp.clip(p.sensor.delay, 0, max_delay)], buf)
        cs, tau, info = inner.step(p.crawl, s.inner, seen)
        return SensedState(cs, buf, key), tau, info

    return sim.Controller(init, step, tie_rollout_carry=inner.tie_rollout_carry)


def build_scenario(rows: dict[str, np.ndarray], spec: SweepSpec) -> tuple[stepdown.Scenario, SensorParams | None]:
    """The :class:`stepdown.Scenario` (and sensor parameters if the spec has noise/latency) of input rows."""
    b = rows["index"].shape[0]
    n_blocks = hmodel.TerrainLayout(*spec.blocks).n_blocks
    com = np.stack([rows["payload_com_x"], rows["payload_com_y"], rows["payload_com_z"]], -1)
    terrain = hmodel.InstanceTerrain.make(rows["height"], rows["friction"], rows["payload_mass"], com,
                                          rows["block_heights"], n_blocks=n_blocks)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    loaded = presets.load(spec.preset) if spec.preset else crawl.CrawlParams.make()
    params = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + jnp.shape(x)), loaded)
    seq = np.asarray([crawl.FOOT_SEQUENCES[str(s)] for s in rows["foot_sequence"]], np.int32)
    gains = impedance.ImpedanceGains(
        kp=f32(np.stack([rows["kp_haa"], rows["kp_hfe"], rows["kp_kfe"]], -1)),
        kd=f32(np.stack([rows["kd_haa"], rows["kd_hfe"], rows["kd_kfe"]], -1)))
    # A reflex field no axis names has the preset's value in the rows (SweepSpec.preset_defaults).
    rp = hreflex.ReflexParams(**{f.name: f32(rows[f"reflex_{f.name}"])
                                 for f in dataclasses.fields(hreflex.ReflexParams)})
    params = scheduled.replace_base(params, forward_velocity=f32(rows["speed"]), foot_sequence=jnp.asarray(seq),
                                    use_reflex=f32(rows["reflex"]), gains=gains, reflex=rp)
    force = np.stack([rows["push_force_x"], rows["push_force_y"], np.zeros(b)], -1)
    push = sim.Push(f32(force), f32(rows["push_t_start"]), f32(rows["push_duration"]))
    scenario = stepdown.Scenario(terrain=terrain, start_distance=f32(rows["start_distance"]),
                                 lateral_offset=f32(rows["lateral_offset"]), yaw=f32(rows["yaw"]),
                                 params=params, push=push)
    if not spec.sensed:
        return scenario, None
    keys = jax.vmap(lambda k: jax.random.fold_in(jax.random.PRNGKey(spec.seed), k))(
        jnp.asarray(rows["index"] % (2**31 - 1), jnp.uint32))
    sensor = SensorParams(f32(rows["noise_joint_pos"]), f32(rows["noise_joint_vel"]), f32(rows["noise_imu"]),
                          f32(rows["noise_gyro"]), f32(rows["noise_foot_force"]),
                          jnp.asarray(np.round(rows["latency"] / spec.control_dt), jnp.int32), keys)
    return scenario, sensor


__all__ = ["SensedParams", "SensedState", "SensorParams", "build_scenario", "sensed_controller"]
