"""The step-down experiment of Focchi et al. (2017), Section IV: HyQ crawls off a platform.

HyQ starts on a platform of height ``h`` (front feet ``start_distance`` before the edge) and crawls
forward; the experiment runs the same batch with the height reflex on and off. Per instance it reports
(:class:`StepdownMetrics`, accumulated on the device, so a sweep keeps only these):

* ``success``: all four feet reached the lower ground and stay past the edge, no trunk or shin strike
  (a contact pressing harder than ``strike_force``), ``|roll|`` and
  ``|pitch|`` below ``max_tilt``, forward progress, no lost foothold (a swing that ended by a limit
  with the foot off the ground) and no divergence;
* ``joint_range_crossed``: a measured joint went past its range by more than 0.01 rad;
* ``min_swing_mobility``: the smallest velocity transformation ratio of the swinging leg in the
  downward part of its swings (Eq. 12);
* ``mean_mobility``: the overall mobility of footnote 8, ``sum_k sum_i c_sd(k) m_i(k)``, divided by the
  number of swing-down ticks so runs of different length compare;
* ``peak_pitch``, ``peak_roll``, ``time_all_down`` (s), counts of touchdowns and limit stops.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hyqjax import crawl, model as hmodel, robot, sim, spatial


@dataclasses.dataclass(frozen=True)
class StepdownConfig:
    """Static settings of a step-down batch (changing them recompiles).

    Attributes:
      duration: simulated time (s).
      control_dt: controller period (s).
      record_every: trace decimation in ticks (0: no traces).
      max_tilt: success bound on |roll| and |pitch| (rad).
      min_progress: success needs the trunk to advance at least this far (m).
      strike_force: a shin or trunk contact pressing on the terrain harder than this (N) is a strike.
      layout: terrain structure (rough blocks).
    """

    duration: float = 24.0
    control_dt: float = 0.002
    record_every: int = 0
    max_tilt: float = 0.4
    min_progress: float = 0.5
    strike_force: float = 100.0
    layout: hmodel.TerrainLayout = hmodel.TerrainLayout()

    def sim_config(self) -> sim.SimConfig:
        return sim.SimConfig(control_dt=self.control_dt, duration=self.duration, record_every=self.record_every)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scenario:
    """Per-instance inputs (every field has a leading batch axis).

    Attributes:
      terrain: platform height, friction, payload, blocks.
      start_distance: distance of the front feet from the platform edge at the start (m).
      lateral_offset: initial lateral offset of the trunk (m).
      yaw: initial heading (rad).
      params: crawl parameters (with ``use_reflex`` and the reflex parameters).
      push: lateral push on the trunk.
    """

    terrain: hmodel.InstanceTerrain
    start_distance: jax.Array
    lateral_offset: jax.Array
    yaw: jax.Array
    params: crawl.CrawlParams
    push: sim.Push

    @property
    def batch_size(self) -> int:
        return int(self.start_distance.shape[0])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StepdownMetrics:
    peak_roll: jax.Array
    peak_pitch: jax.Array
    trunk_strike: jax.Array
    shin_strike: jax.Array
    shin_contact: jax.Array
    peak_shin_force: jax.Array
    peak_trunk_force: jax.Array
    joint_range_crossed: jax.Array
    min_swing_mobility: jax.Array
    mobility_sum: jax.Array
    swing_down_ticks: jax.Array
    lost_footholds: jax.Array
    time_all_down: jax.Array
    x_start: jax.Array


class ContactSlots(NamedTuple):
    """MJX contact slots (static indices) that pair a shin, the trunk or each foot with terrain."""

    shin: np.ndarray
    trunk: np.ndarray
    feet: list


def _contact_slots(m: mujoco.MjModel, mx: mjx.Model, ids: hmodel.ModelIds) -> ContactSlots:
    """Indices of MJX contact slots that pair a shin, the trunk or a foot with terrain."""
    d = jax.jit(mjx.forward)(mx, mjx.make_data(mx))
    geom = np.asarray(d._impl.contact.geom)
    shin = np.isin(geom, ids.shin_geoms).any(1)
    trunk = np.isin(geom, [ids.trunk_geom]).any(1)
    feet = np.stack([np.isin(geom, [g]).any(1) for g in ids.foot_geoms])
    return ContactSlots(np.nonzero(shin)[0], np.nonzero(trunk)[0], [np.nonzero(f)[0] for f in feet])


def contact_normal_forces(d: mjx.Data, slots: np.ndarray) -> jax.Array:
    """Normal force (N) of each contact slot in ``slots`` (0 where the pair is not touching).

    MuJoCo's default pyramidal friction cone stores ``2 (condim - 1)`` edge forces per contact; the
    normal force is their sum (every edge carries the normal direction with weight 1). hyqjax's
    terrain contacts have ``condim = 3``: four edges.
    """
    if len(slots) == 0:
        return jnp.zeros((0,), d.qpos.dtype)
    c = d._impl.contact
    adr = c.efc_address[slots]
    edges = d._impl.efc_force[jnp.maximum(adr, 0)[:, None] + jnp.arange(4)]
    return jnp.where(adr >= 0, jnp.sum(edges, -1), 0.0)


def make_metrics(ids: hmodel.ModelIds, slots: ContactSlots, cfg: StepdownConfig) -> sim.Metrics:
    """Step-down metrics accumulated on the device (see :class:`StepdownMetrics`).

    A *strike* is a shin or trunk contact with the terrain whose normal force exceeds
    ``cfg.strike_force``: a shin resting lightly on the platform edge while its foot stands below
    is recorded (``shin_contact``, ``peak_shin_force``) but is not a strike.
    """
    shin_slots, trunk_slots, foot_slots = slots
    sites = np.asarray(ids.foot_sites)
    qadr = np.asarray(ids.qpos_joints)

    def init(d):
        f = jnp.asarray(0.0, d.qpos.dtype)
        return StepdownMetrics(peak_roll=f, peak_pitch=f, trunk_strike=jnp.array(False), shin_strike=jnp.array(False),
                               shin_contact=jnp.array(False), peak_shin_force=f, peak_trunk_force=f,
                               joint_range_crossed=jnp.array(False), min_swing_mobility=f + 10.0, mobility_sum=f,
                               swing_down_ticks=jnp.asarray(0), lost_footholds=jnp.asarray(0),
                               time_all_down=f - 1.0, x_start=d.qpos[0])

    def update(ms: StepdownMetrics, d, obs, info: crawl.CrawlInfo):
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[3:7]))
        dist = d._impl.contact.dist
        shin_touch = jnp.any(dist[shin_slots] < 0.0) if len(shin_slots) else jnp.array(False)
        f_shin = jnp.max(contact_normal_forces(d, shin_slots), initial=0.0)
        f_trunk = jnp.max(contact_normal_forces(d, trunk_slots), initial=0.0)
        foot_contact = jnp.stack([jnp.any(dist[s] < 0.005) for s in foot_slots])
        q = d.qpos[qadr]
        crossed = jnp.any((q < robot.Q_MIN - 0.01) | (q > robot.Q_MAX + 0.01))
        sd = info.swing_down
        m_sw = info.mobility[info.swing_leg]
        lost = info.limit_stop & ~foot_contact[info.swing_leg]
        feet = d.site_xpos[sites]
        all_down = jnp.all((feet[:, 0] > 0.02) & (feet[:, 2] < 0.06))
        t_down = jnp.where((ms.time_all_down < 0) & all_down, d.time, ms.time_all_down)
        return StepdownMetrics(
            peak_roll=jnp.maximum(ms.peak_roll, jnp.abs(rpy[0])),
            peak_pitch=jnp.maximum(ms.peak_pitch, jnp.abs(rpy[1])),
            trunk_strike=ms.trunk_strike | (f_trunk > cfg.strike_force),
            shin_strike=ms.shin_strike | (f_shin > cfg.strike_force),
            shin_contact=ms.shin_contact | shin_touch,
            peak_shin_force=jnp.maximum(ms.peak_shin_force, f_shin),
            peak_trunk_force=jnp.maximum(ms.peak_trunk_force, f_trunk),
            joint_range_crossed=ms.joint_range_crossed | crossed,
            min_swing_mobility=jnp.where(sd, jnp.minimum(ms.min_swing_mobility, m_sw), ms.min_swing_mobility),
            mobility_sum=ms.mobility_sum + jnp.where(sd, jnp.sum(info.mobility), 0.0),
            swing_down_ticks=ms.swing_down_ticks + sd.astype(jnp.int32),
            lost_footholds=ms.lost_footholds + lost.astype(jnp.int32),
            time_all_down=t_down,
            x_start=ms.x_start,
        )

    return sim.Metrics(init, update)


def record_trace(d, obs: sim.Observation, info: crawl.CrawlInfo, sites=None):
    """What figures need: trunk pose, joints, commanded/planned feet, reflex activity, damping, mobility."""
    return dict(time=d.time, base_pos=d.qpos[0:3], rpy=spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[3:7])),
                q=obs.q, qd=obs.qd, q_cmd=info.q_cmd, x_plan_b=info.x_plan_b, x_cmd_b=info.x_cmd_b,
                reflex_active=info.reflex_active, swing_down=info.swing_down, swing_leg=info.swing_leg,
                phase=info.phase, damping=info.damping, mobility=info.mobility, foot_force=obs.foot_force,
                feet_world=d.site_xpos[sites] if sites is not None else d.site_xpos, qpos=d.qpos)


@functools.lru_cache(maxsize=4)
def _setup(layout: hmodel.TerrainLayout, control_dt: float):
    m = hmodel.load_model(layout, timestep=control_dt)
    ids = hmodel.model_ids(m)
    mx = mjx.put_model(m)
    slots = _contact_slots(m, mx, ids)
    return m, mx, ids, slots


def initial_qpos(m: mujoco.MjModel, scenario: Scenario) -> np.ndarray:
    """Standing keyframe on the platform, front feet ``start_distance`` before the edge."""
    front_x = float(robot.B_P_HIP[0, 0])
    q = np.tile(hmodel.standing_qpos(m), (scenario.batch_size, 1))
    h = np.asarray(scenario.terrain.platform_height)
    yaw = np.asarray(scenario.yaw)
    q[:, 0] = -np.asarray(scenario.start_distance) - front_x
    q[:, 1] = np.asarray(scenario.lateral_offset)
    q[:, 2] = robot.STANDING_BASE_Z + h
    q[:, 3] = np.cos(yaw / 2)
    q[:, 6] = np.sin(yaw / 2)
    return q


def run_batch(scenario: Scenario, cfg: StepdownConfig = StepdownConfig(), mesh=None):
    """Run one batch of step-down instances; returns ``(metrics dict of numpy arrays, trace or None)``."""
    m, mx, ids, slots = _setup(cfg.layout, cfg.control_dt)
    scfg = cfg.sim_config()
    b = scenario.batch_size
    mb = hmodel.batch_model(mx, ids, scenario.terrain)
    d0 = sim.initial_data(mx, initial_qpos(m, scenario), b)
    metrics = make_metrics(ids, slots, cfg)
    sites = np.asarray(ids.foot_sites)
    record = (lambda d, o, i: record_trace(d, o, i, sites)) if cfg.record_every else None
    res = sim.batch_rollout(mb, ids, d0, crawl.crawl_controller(scfg.control_dt), scenario.params, scfg,
                            metrics=metrics, record=record, params_axes=0, mesh=mesh, push=scenario.push)
    out = summarize_instances(res, scenario, cfg, ids)
    trace = jax.tree_util.tree_map(np.asarray, res.trace) if cfg.record_every else None
    return out, trace


def summarize_instances(res: sim.RolloutResult, scenario: Scenario, cfg: StepdownConfig, ids) -> dict[str, np.ndarray]:
    ms = jax.tree_util.tree_map(np.asarray, res.metrics)
    cs = res.ctrl_state
    d = res.data
    feet = np.asarray(d.site_xpos[:, np.asarray(ids.foot_sites)])
    # All four feet reached the lower ground (at one instant) and none is back on the platform at the end
    # (the last instant may fall in a swing, so the final check is on x only).
    all_down = (ms.time_all_down >= 0) & np.all(feet[..., 0] > 0.02, axis=1)
    progress = np.asarray(d.qpos[:, 0]) - ms.x_start
    diverged = np.asarray(res.diverged)
    tilt_ok = (ms.peak_roll < cfg.max_tilt) & (ms.peak_pitch < cfg.max_tilt)
    success = (all_down & ~ms.trunk_strike & ~ms.shin_strike & tilt_ok & (progress > cfg.min_progress)
               & (ms.lost_footholds == 0) & ~diverged)
    sd = np.maximum(ms.swing_down_ticks, 1)
    reason = np.full(success.shape, "", dtype=object)
    for mask, why in [(~all_down, "feet not all down"), (progress <= cfg.min_progress, "no progress"),
                      (ms.lost_footholds > 0, "lost foothold"), (~tilt_ok, "tilt"), (ms.shin_strike, "shin strike"),
                      (ms.trunk_strike, "trunk strike"), (diverged, "diverged")]:
        reason = np.where(mask, np.where(reason == "", why, reason + "; " + why), reason)
    return dict(
        success=success, failure_reason=reason, all_feet_down=all_down, diverged=diverged,
        diverged_tick=np.asarray(res.diverged_tick),
        trunk_strike=ms.trunk_strike, shin_strike=ms.shin_strike, shin_contact=ms.shin_contact,
        peak_shin_force=ms.peak_shin_force, peak_trunk_force=ms.peak_trunk_force, joint_range_crossed=ms.joint_range_crossed,
        lost_footholds=ms.lost_footholds, peak_roll=ms.peak_roll, peak_pitch=ms.peak_pitch,
        min_swing_mobility=np.where(ms.swing_down_ticks > 0, ms.min_swing_mobility, np.nan),
        mean_mobility=ms.mobility_sum / sd, mobility_sum=ms.mobility_sum, swing_down_ticks=ms.swing_down_ticks,
        time_all_down=np.where(ms.time_all_down >= 0, ms.time_all_down, np.nan), progress=progress,
        n_steps=np.asarray(cs.n_steps), n_touchdowns=np.asarray(cs.n_touchdowns),
        n_limit_stops=np.asarray(cs.n_limit_stops),
    )


def make_scenarios(heights, reflex_modes, instances: int, seed: int, *, friction=(0.7, 1.0), payload=(0.0, 10.0),
                   start_distance=(0.0, 0.04), lateral=(-0.03, 0.03), yaw=(-0.05, 0.05), params: crawl.CrawlParams | None = None,
                   n_blocks: int = 0) -> tuple[Scenario, dict[str, np.ndarray]]:
    """A batch over ``heights x reflex_modes x instances`` with per-instance randomisation from ``seed``.

    The same seed gives every (height, reflex) pair the same randomised instances, so reflex on and off
    are compared on identical scenarios. Returns the scenario and a table of the inputs.
    """
    heights = [float(h) for h in heights]
    modes = [bool(r) for r in reflex_modes]
    if instances < 1:
        raise ValueError(f"instances must be >= 1, got {instances}")
    rng = np.random.default_rng(seed)
    n = instances
    inst = dict(
        friction=rng.uniform(*friction, n), payload_mass=rng.uniform(*payload, n),
        payload_com=np.stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.05, 0.05, n), np.zeros(n)], -1),
        start_distance=rng.uniform(*start_distance, n), lateral_offset=rng.uniform(*lateral, n),
        yaw=rng.uniform(*yaw, n),
    )
    rows = {k: [] for k in ["height", "reflex", "instance", *inst]}
    for h in heights:
        for r in modes:
            for i in range(n):
                rows["height"].append(h)
                rows["reflex"].append(r)
                rows["instance"].append(i)
                for k, v in inst.items():
                    rows[k].append(v[i])
    table = {k: np.asarray(v) for k, v in rows.items()}
    base = params or crawl.CrawlParams.make()
    b = len(table["height"])
    terrain = hmodel.InstanceTerrain.make(table["height"], table["friction"], table["payload_mass"],
                                          table["payload_com"], n_blocks=n_blocks)
    bparams = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + jnp.shape(x)), base)
    bparams = dataclasses.replace(bparams, use_reflex=jnp.asarray(table["reflex"], jnp.float32))
    scenario = Scenario(terrain=terrain, start_distance=jnp.asarray(table["start_distance"]),
                        lateral_offset=jnp.asarray(table["lateral_offset"]), yaw=jnp.asarray(table["yaw"]),
                        params=bparams,
                        push=jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), sim.Push.none()))
    return scenario, table


def summarize(table: dict[str, np.ndarray], out: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """One row per (height, reflex): success rate with a Wilson 95% interval, mobility, pitch, time."""
    rows = []
    for h in sorted(set(table["height"].tolist())):
        for r in [False, True]:
            mask = (table["height"] == h) & (table["reflex"] == r)
            if not mask.any():
                continue
            k, n = int(out["success"][mask].sum()), int(mask.sum())
            lo, hi = wilson_interval(k, n)
            rows.append(dict(
                height=h, reflex=r, n=n, successes=k, success_rate=k / n, success_ci95=(lo, hi),
                all_feet_down=float(np.mean(out["all_feet_down"][mask])),
                lost_footholds=float(np.mean(out["lost_footholds"][mask])),
                joint_range_crossed=float(np.mean(out["joint_range_crossed"][mask])),
                min_swing_mobility=float(np.nanmin(out["min_swing_mobility"][mask])) if np.isfinite(out["min_swing_mobility"][mask]).any() else float("nan"),
                mean_mobility=float(np.mean(out["mean_mobility"][mask])),
                peak_pitch=float(np.mean(out["peak_pitch"][mask])),
                time_all_down=float(np.nanmean(out["time_all_down"][mask])) if np.isfinite(out["time_all_down"][mask]).any() else float("nan"),
                diverged=int(out["diverged"][mask].sum()),
            ))
    return rows


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``k / n``."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


def format_table(rows: list[dict[str, Any]]) -> str:
    head = (f"{'height':>7} {'reflex':>6} {'success':>13} {'95% CI':>13} {'feet down':>9} {'lost fh':>7} "
            f"{'jnt range':>9} {'min m_sw':>8} {'mean m':>7} {'pitch':>6} {'t_down':>6}")
    lines = [head, "-" * len(head)]
    for r in rows:
        lo, hi = r["success_ci95"]
        lines.append(
            f"{r['height']:7.2f} {('on' if r['reflex'] else 'off'):>6} {r['successes']:>5d}/{r['n']:<3d} ({r['success_rate']:4.0%})"
            f" [{lo:4.2f},{hi:4.2f}] {r['all_feet_down']:9.0%} {r['lost_footholds']:7.2f} {r['joint_range_crossed']:9.0%}"
            f" {r['min_swing_mobility']:8.3f} {r['mean_mobility']:7.3f} {r['peak_pitch']:6.3f} {r['time_all_down']:6.1f}")
    return "\n".join(lines)
