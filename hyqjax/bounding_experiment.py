"""Batched bounding experiments: per-instance randomisation, one compiled rollout, tracking / fall metrics.

Every instance of a batch carries its own :class:`hyqjax.bounding.BoundingParams` (command,
switches), terrain (friction, payload) and :class:`hyqjax.sim.Push`, so in-place, forward,
turning and the four ablation combinations share ONE compiled ``sim.batch_rollout``.

Metrics (:func:`summarise`), all on the ground truth of the simulation:

* **yaw error** ``|wrap(psi^d(t) - psi(t))|`` (deg): max and RMS over the whole run, ``psi^d`` the
  integral of the ramped yaw-rate command from the initial heading (the paper's Fig. 4 quantity;
  HyQ: always below 4 deg);
* **speed error**: per gait cycle, the mean forward speed in the heading frame
  (displacement over one period / T) minus the commanded speed; mean |error| and RMS over the
  cycles after ``settle`` seconds;
* **yaw-rate error**: per cycle mean yaw rate minus the command;
* **side slip**: ``|mean lateral speed|`` in the heading frame over the settled cycles (outward drift in a turn);
* **periodicity residual**: ``||W (s_{k+1} - s_k)||`` of consecutive apex states (Eq. C2's scaling),
  median over the settled cycles;
* **falls**: an instance fails if the trunk goes below ``FALL_HEIGHT``, ``|roll|`` or ``|pitch|``
  exceeds ``FALL_ANGLE``, or the simulation diverges (non-finite state / speed limit). Failures are
  counted with their reason and time; they are never dropped from the summary.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import bounding as bd, bounding_cycle as bc, model as hmodel, sim, spatial

FALL_HEIGHT = 0.35
FALL_ANGLE = 0.7
FAIL_REASONS = ("ok", "low_trunk", "roll", "pitch", "diverged")


@dataclasses.dataclass(frozen=True)
class Randomisation:
    """Per-instance randomisation ranges (uniform). Attributes:
      apex: (5,) half-widths on the apex state ``(z, theta, xdot, zdot, thetadot)``.
      roll, yaw_rate: half-widths on the initial roll (rad) and yaw rate (rad/s).
      friction: (lo, hi) ground friction.  payload: (lo, hi) payload mass (kg); payload_com: half-width (m).
    """

    apex: tuple = (0.01, 0.02, 0.05, 0.05, 0.2)
    roll: float = 0.02
    yaw_rate: float = 0.05
    friction: tuple = (0.7, 1.0)
    payload: tuple = (0.0, 5.0)
    payload_com: float = 0.05

    def __post_init__(self):
        if len(self.apex) != 5 or any((not np.isfinite(a)) or a < 0 for a in self.apex):
            raise ValueError(f"apex must be 5 non-negative half-widths, got {self.apex}")
        lo, hi = self.friction
        if not (0 < lo <= hi <= 5):
            raise ValueError(f"friction must satisfy 0 < lo <= hi <= 5, got {self.friction}")
        lo, hi = self.payload
        if not (0 <= lo <= hi <= 100):
            raise ValueError(f"payload must satisfy 0 <= lo <= hi <= 100 kg, got {self.payload}")
        if not (0 <= self.payload_com <= 0.2):
            raise ValueError(f"payload_com must be in [0, 0.2] m, got {self.payload_com}")

    @staticmethod
    def none() -> "Randomisation":
        return Randomisation(apex=(0.0,) * 5, roll=0.0, yaw_rate=0.0, friction=(0.8, 0.8), payload=(0.0, 0.0),
                             payload_com=0.0)


class Batch(NamedTuple):
    params: bd.BoundingParams  # leading batch axis on every leaf
    terrain: hmodel.InstanceTerrain
    apex0: np.ndarray  # (B, 5) initial apex states
    roll0: np.ndarray
    yaw_rate0: np.ndarray
    push: sim.Push


def stack_params(plist: list[bd.BoundingParams]) -> bd.BoundingParams:
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *plist)


def make_batch(plist: list[bd.BoundingParams], seed: int = 0, rand: Randomisation | None = None,
               push_force=0.0, push_time=2.0, push_duration=0.1, n_unique: int | None = None) -> Batch:
    """Instances from per-instance params, with the seed's randomisation of initial state, friction, payload.

    ``push_force``: scalar or (B,) lateral push magnitudes (N); the sign alternates over instances
    (``+y`` for even, ``-y`` for odd instances), applied at the trunk CoM during ``[push_time, push_time + push_duration)``.
    ``n_unique``: draw the randomisation for this many instances and repeat it (``B`` must be a multiple), so
    several configurations (e.g. the ablation) run on identical instances.
    """
    rand = rand or Randomisation()
    b = len(plist)
    if b < 1:
        raise ValueError("plist (instances) must not be empty")
    nu = b if n_unique is None else n_unique
    if not (isinstance(nu, int) and nu >= 1 and b % nu == 0):
        raise ValueError(f"n_unique must be a positive int dividing the batch size {b}, got {n_unique}")
    rng = np.random.default_rng(seed)
    params = stack_params(plist)
    ref = np.asarray(params.apex_ref, np.float64)

    def draw(shape_tail, lo, hi):
        x = rng.uniform(lo, hi, (nu,) + shape_tail)
        return np.tile(x, (b // nu,) + (1,) * len(shape_tail))

    apex0 = ref + draw((5,), -1, 1) * np.asarray(rand.apex)
    roll0 = draw((), -1, 1) * rand.roll
    yr0 = draw((), -1, 1) * rand.yaw_rate
    fr = draw((), rand.friction[0], rand.friction[1])
    pm = draw((), rand.payload[0], rand.payload[1])
    pc = np.concatenate([draw((2,), -1, 1) * rand.payload_com, np.zeros((b, 1))], 1)
    terrain = hmodel.InstanceTerrain.make(np.zeros(b), friction=fr, payload_mass=pm, payload_com=pc)
    pf = np.broadcast_to(np.asarray(push_force, np.float64), (b,))
    if np.any(~np.isfinite(pf)) or np.any(np.abs(pf) > 5000):
        raise ValueError(f"push_force must be finite with |value| <= 5000 N, got {pf}")
    if not (0 <= push_time <= 600 and 0 <= push_duration <= 10):
        raise ValueError(f"push_time must be in [0, 600] s and push_duration in [0, 10] s, got {push_time}, "
                         f"{push_duration}")
    sign = np.where(np.arange(b) % nu % 2 == 0, 1.0, -1.0)
    force = np.stack([np.zeros(b), sign * pf, np.zeros(b)], 1)
    push = sim.Push(jnp.asarray(force, jnp.float32), jnp.full(b, push_time, jnp.float32),
                    jnp.full(b, push_duration, jnp.float32))
    # The estimator starts at the nominal apex (it does not know the perturbation).
    return Batch(params, terrain, apex0, roll0, yr0, push)


def concat_batches(batches: list[Batch]) -> Batch:
    """One batch from several (so differently randomised groups share one compiled rollout)."""
    cat = lambda *xs: jnp.concatenate([jnp.asarray(x) for x in xs])  # noqa: E731
    params = jax.tree_util.tree_map(cat, *[b.params for b in batches])
    terrain = jax.tree_util.tree_map(cat, *[b.terrain for b in batches])
    push = jax.tree_util.tree_map(cat, *[b.push for b in batches])
    return Batch(params, terrain, np.concatenate([b.apex0 for b in batches]),
                 np.concatenate([b.roll0 for b in batches]), np.concatenate([b.yaw_rate0 for b in batches]), push)


def _metrics() -> sim.Metrics:
    """Device metrics: first fall tick and reason, min trunk height, max |roll|, |pitch|."""

    def init(d):
        return dict(fall_tick=jnp.array(-1), reason=jnp.array(0), k=jnp.array(0), min_z=d.qpos[2],
                    max_roll=jnp.zeros((), d.qpos.dtype), max_pitch=jnp.zeros((), d.qpos.dtype))

    def update(ms, d, obs, info):
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[3:7]))
        z = d.qpos[2]
        reason = jnp.where(z < FALL_HEIGHT, 1, jnp.where(jnp.abs(rpy[0]) > FALL_ANGLE, 2,
                                                         jnp.where(jnp.abs(rpy[1]) > FALL_ANGLE, 3, 0)))
        new = (ms["fall_tick"] < 0) & (reason > 0)
        return dict(fall_tick=jnp.where(new, ms["k"], ms["fall_tick"]), reason=jnp.where(new, reason, ms["reason"]),
                    k=ms["k"] + 1, min_z=jnp.minimum(ms["min_z"], z),
                    max_roll=jnp.maximum(ms["max_roll"], jnp.abs(rpy[0])),
                    max_pitch=jnp.maximum(ms["max_pitch"], jnp.abs(rpy[1])))

    return sim.Metrics(init, update)


def _record(d, obs, info):
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[3:7]))
    return dict(t=d.time, pos=d.qpos[:3], vel=d.qvel[:3], rpy=rpy, omega=d.qvel[3:6], apex=bc.data_apex(d),
                yaw_des=info["yaw_des"], v_des=info["v_des"], yaw_rate_des=info["yaw_rate_des"],
                est_vel_h=info["vel_h"], est_z=info["est_pos"][2], roll_des=info["roll_des"],
                qpos=d.qpos, foot_force=obs.foot_force)


def initial_data(batch: Batch, m, mx) -> "jax.Array":
    def one(p, s, roll, yr):
        return bc.apex_data(mx, m, p, s, roll=roll, yaw_rate=yr)

    return jax.vmap(one)(batch.params, jnp.asarray(batch.apex0, jnp.float32), jnp.asarray(batch.roll0, jnp.float32),
                         jnp.asarray(batch.yaw_rate0, jnp.float32))


def run(batch: Batch, duration: float, control_dt: float = 0.002, record_every: int = 10):
    """Simulate the batch (one ``sim.batch_rollout``); returns ``(RolloutResult, trace as numpy dict)``."""
    m, mx, ids = bc._model()
    period = float(np.asarray(batch.params.gait.period).reshape(-1)[0])
    if not np.allclose(np.asarray(batch.params.gait.period), period):
        raise ValueError("all instances must share the gait period")
    n_per = int(round(period / control_dt))
    if abs(n_per * control_dt - period) > 1e-6 or n_per % record_every:
        raise ValueError(f"the gait period ({period}) must be a multiple of record_every * control_dt "
                         f"({record_every} x {control_dt})")
    cfg = sim.SimConfig(control_dt=control_dt, duration=duration, record_every=record_every)
    mxb = hmodel.batch_model(mx, ids, batch.terrain)
    d0 = initial_data(batch, m, mx)
    res = sim.batch_rollout(mxb, ids, d0, bd.bounding_controller, batch.params, cfg, metrics=_metrics(),
                            record=_record, params_axes=0, push=batch.push)
    trace = jax.tree_util.tree_map(np.asarray, res.trace)
    return res, trace


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def summarise(res, trace, batch: Batch, control_dt: float = 0.002, settle: float | None = None) -> dict:
    """Per-instance metrics (lists, one entry per instance) plus aggregate numbers. See the module docstring."""
    period = float(np.asarray(batch.params.gait.period).reshape(-1)[0])
    ramp = np.asarray(batch.params.command.ramp_time, np.float64)
    t = trace["t"]  # (B, N)
    b, n = t.shape
    settle = float(np.max(ramp)) + 1.0 if settle is None else settle
    diverged = np.asarray(res.diverged)
    fall_tick = np.asarray(res.metrics["fall_tick"])
    reason_code = np.asarray(res.metrics["reason"])
    reasons, fail_time = [], []
    for i in range(b):
        if diverged[i] and (fall_tick[i] < 0 or res.diverged_tick[i] <= fall_tick[i]):
            reasons.append("diverged")
            fail_time.append(float(np.asarray(res.diverged_tick)[i] + 1) * control_dt)
        elif fall_tick[i] >= 0:
            reasons.append(FAIL_REASONS[int(reason_code[i])])
            fail_time.append(float(fall_tick[i] + 1) * control_dt)
        else:
            reasons.append("ok")
            fail_time.append(None)
    ok = np.array([r == "ok" for r in reasons])
    yaw = trace["rpy"][..., 2]
    yaw_err = np.degrees(np.abs(_wrap(trace["yaw_des"] - yaw)))
    # Per-cycle quantities from the apex samples (t = k T).
    k_apex = np.round(t[0] / period)
    is_apex = np.abs(t[0] - k_apex * period) < 0.5 * control_dt
    idx = np.nonzero(is_apex)[0]
    pos = trace["pos"][:, idx]
    yaw_a = np.unwrap(yaw[:, idx], axis=1)
    ta = t[0, idx]
    dpos = np.diff(pos, axis=1)
    heading = yaw_a[:, :-1] + 0.5 * np.diff(yaw_a, axis=1)
    v_fwd = (np.cos(heading) * dpos[..., 0] + np.sin(heading) * dpos[..., 1]) / period
    v_lat = (-np.sin(heading) * dpos[..., 0] + np.cos(heading) * dpos[..., 1]) / period
    yaw_rate_c = np.diff(yaw_a, axis=1) / period
    mid = 0.5 * (ta[:-1] + ta[1:])
    vdes = np.stack([np.interp(mid, t[i], trace["v_des"][i, :, 0]) for i in range(b)])
    yrdes = np.stack([np.interp(mid, t[i], trace["yaw_rate_des"][i]) for i in range(b)])
    settled = ta[:-1] >= settle
    apex = trace["apex"][:, idx]
    resid = np.linalg.norm((apex[:, 1:] - apex[:, :-1]) / bc.RESIDUAL_SCALE, axis=-1)
    per = []
    for i in range(b):
        alive = ta[1:] <= (fail_time[i] if fail_time[i] is not None else np.inf)
        sel = settled & alive
        se = v_fwd[i, sel] - vdes[i, sel]
        ye = yaw_rate_c[i, sel] - yrdes[i, sel]
        alive_t = t[i] <= (fail_time[i] if fail_time[i] is not None else np.inf)
        per.append(dict(
            result=reasons[i], fail_time=fail_time[i],
            yaw_error_max_deg=float(np.max(yaw_err[i, alive_t])) if alive_t.any() else None,
            yaw_error_rms_deg=float(np.sqrt(np.mean(yaw_err[i, alive_t] ** 2))) if alive_t.any() else None,
            speed_cmd=float(np.asarray(batch.params.command.velocity)[i, 0]),
            yaw_rate_cmd=float(np.asarray(batch.params.command.yaw_rate)[i]),
            speed_mean=float(np.mean(v_fwd[i, sel])) if sel.any() else None,
            speed_error_mean_abs=float(np.mean(np.abs(se))) if sel.any() else None,
            speed_error_rms=float(np.sqrt(np.mean(se**2))) if sel.any() else None,
            lateral_speed_mean=float(np.mean(v_lat[i, sel])) if sel.any() else None,
            yaw_rate_mean=float(np.mean(yaw_rate_c[i, sel])) if sel.any() else None,
            yaw_rate_error_rms=float(np.sqrt(np.mean(ye**2))) if sel.any() else None,
            periodicity_residual=float(np.median(resid[i, sel])) if sel.any() else None,
            min_height=float(np.asarray(res.metrics["min_z"])[i]),
            max_roll_deg=float(np.degrees(np.asarray(res.metrics["max_roll"])[i])),
            max_pitch_deg=float(np.degrees(np.asarray(res.metrics["max_pitch"])[i])),
            friction=float(np.asarray(batch.terrain.friction)[i]),
            payload=float(np.asarray(batch.terrain.payload_mass)[i]),
            push=float(np.asarray(batch.push.force)[i, 1]),
        ))
    return dict(instances=per, n=b, falls=int((~ok).sum()),
                fail_reasons={r: reasons.count(r) for r in set(reasons) if r != "ok"})


def aggregate(per: list[dict]) -> dict:
    """Aggregate a list of per-instance dicts: worst / mean of the tracking errors over surviving instances."""
    def vals(key):
        return np.array([p[key] for p in per if p[key] is not None and p["result"] == "ok"], np.float64)

    out = dict(n=len(per), falls=sum(p["result"] != "ok" for p in per),
               fail_reasons=sorted({p["result"] for p in per if p["result"] != "ok"}))
    for key in ("yaw_error_max_deg", "yaw_error_rms_deg", "speed_error_mean_abs", "speed_error_rms",
                "yaw_rate_error_rms", "periodicity_residual"):
        v = vals(key)
        out[key + "_mean"] = float(np.mean(v)) if v.size else None
        out[key + "_worst"] = float(np.max(v)) if v.size else None
    # Side slip: |mean lateral speed| in the heading frame (the outward drift the centrifugal compensation removes).
    v = np.abs(vals("lateral_speed_mean"))
    out["side_slip_mean"] = float(np.mean(v)) if v.size else None
    out["side_slip_worst"] = float(np.max(v)) if v.size else None
    return out


def contributions(groups: dict) -> dict:
    """Each part's contribution from the four ablation groups: the change of the worst / mean yaw error, speed
    error and falls when the part is switched off (averaged over the other part's two settings)."""
    def metric(name, key):
        return groups[name]["aggregate"].get(key)

    out = {}
    pairs = dict(kinematic_adjustment=(("full", "no_kinematic_adjustment"), ("no_centrifugal", "neither")),
                 centrifugal=(("full", "no_centrifugal"), ("no_kinematic_adjustment", "neither")))
    for part, pp in pairs.items():
        d = {}
        for key in ("yaw_error_max_deg_mean", "yaw_error_rms_deg_mean", "speed_error_rms_mean",
                    "yaw_rate_error_rms_mean", "side_slip_mean", "falls"):
            diffs = [metric(off, key) - metric(on, key) for on, off in pp
                     if metric(on, key) is not None and metric(off, key) is not None]
            d[key + "_increase_when_off"] = float(np.mean(diffs)) if diffs else None
        out[part] = d
    return out


def _fmt(v, f="{:.2f}"):
    return "-" if v is None else f.format(v)


def format_table(groups: dict) -> str:
    """A plain-text summary table, one row per configuration."""
    head = (f"{'configuration':26s} {'n':>3s} {'falls':>5s} {'yaw err max [deg]':>18s} {'yaw err rms':>11s} "
            f"{'speed err rms [m/s]':>19s} {'yaw-rate err rms':>16s} {'side slip':>9s} {'periodicity':>11s}")
    lines = [head, "-" * len(head)]
    for name, g in groups.items():
        a = g["aggregate"]
        lines.append(f"{name:26s} {a['n']:3d} {a['falls']:5d} "
                     f"{_fmt(a['yaw_error_max_deg_mean']) + ' / ' + _fmt(a['yaw_error_max_deg_worst']):>18s} "
                     f"{_fmt(a['yaw_error_rms_deg_mean']):>11s} "
                     f"{_fmt(a['speed_error_rms_mean'], '{:.3f}') + ' / ' + _fmt(a['speed_error_rms_worst'], '{:.3f}'):>19s} "
                     f"{_fmt(a['yaw_rate_error_rms_mean'], '{:.3f}'):>16s} {_fmt(a.get('side_slip_mean'), '{:.3f}'):>9s} "
                     f"{_fmt(a['periodicity_residual_mean']):>11s}")
    lines.append("(x / y = mean / worst over surviving instances; side slip = |mean lateral speed| [m/s]; periodicity = "
                 "median apex-to-apex residual, Eq. C2 units)")
    return "\n".join(lines)


def format_contributions(c: dict) -> str:
    lines = ["contribution (increase of the metric when the part is switched off):"]
    for part, d in c.items():
        lines.append(f"  {part:22s} yaw err max {_fmt(d['yaw_error_max_deg_mean_increase_when_off'])} deg, "
                     f"speed err rms {_fmt(d['speed_error_rms_mean_increase_when_off'], '{:+.3f}')} m/s, "
                     f"yaw-rate err rms {_fmt(d['yaw_rate_error_rms_mean_increase_when_off'], '{:+.3f}')} rad/s, "
                     f"side slip {_fmt(d['side_slip_mean_increase_when_off'], '{:+.3f}')} m/s, "
                     f"falls {_fmt(d['falls_increase_when_off'], '{:+.1f}')}")
    return "\n".join(lines)


def trace_slice(trace: dict, i: int) -> dict:
    return {k: v[i] for k, v in trace.items()}


def default_instances(n: int, speed: float, yaw_rate: float, **kw) -> list[bd.BoundingParams]:
    if not (isinstance(n, int) and 1 <= n <= 4096):
        raise ValueError(f"instances must be an int in [1, 4096], got {n}")
    return [bd.default_params(speed=speed, yaw_rate=yaw_rate, **kw) for _ in range(n)]


