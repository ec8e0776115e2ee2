"""Per-instance step-down metrics (accumulated on the device) and outcomes (typed, boolean failure reasons).

Metrics (:class:`StepdownMetrics`, one :class:`hyqjax.sim.rollout.Metrics` pair from :func:`make_metrics`)
are updated every control tick from the simulated state, the contact sensors
(:mod:`hyqjax.sim.contacts`) and the crawl's per-tick info:

* a *strike* is a shin or trunk contact whose normal force exceeds ``strike_force`` (100 N): a shin resting
  lightly on the platform edge while its foot stands below is recorded (``shin_contact``,
  ``peak_shin_force``) but is not a strike;
* a *lost foothold* is a swing ended by a limit (workspace, end stop, search depth) with the swing foot
  more than 5 mm above the terrain (:func:`hyqjax.sim.contacts.foot_clearance`);
* ``joint_past_range``: a measured joint went past its range by more than 0.01 rad;
* ``min_swing_mobility``: the smallest velocity transformation ratio of the swinging leg in the downward
  part of its swings (Eq. 12); ``mean_mobility``: the overall mobility of footnote 8,
  ``sum_k sum_i c_sd(k) m_i(k)``, divided by the number of swing-down ticks so runs of different length compare.

Episode end (:func:`make_metrics` with ``terminal_tilt``, the default of every step-down): a run that tilts past
``terminal_tilt`` (``|roll|`` or ``|pitch|``; the step-down passes its ``max_tilt``) or strikes the trunk has fallen:
neither failure can be undone by a later tick, so its episode ends there. The rollout freezes it at that tick (its
*failure tick*, ``terminated_tick``) and its outcome is the one recorded up to it (``terminated``). A run that
never tilts that far nor strikes the trunk, every completed run among them, runs exactly as without the episode
end. ``terminated`` and ``diverged`` are counted separately: a terminated run is a failure with its reasons (tilt,
trunk strike), not a simulator blow-up.

Outcome hierarchy (:class:`StepdownOutcome`, from :func:`outcome`):

* ``completed`` (the paper's criterion): all four feet reached the lower ground and stay past the edge,
  forward progress, no lost foothold, no joint past its range, no trunk strike, ``|roll|`` and ``|pitch|``
  below ``max_tilt``, a finite, non-diverged simulation, no reflex failure, no contact overflow;
* ``clean``: completed and no shin or trunk contact above ``strike_force``.

Every failure reason is a boolean field; :data:`FAILURE_REASONS` lists them in display order.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot, spatial
from hyqjax.sim import contacts
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim

#: A limit stop with the swing foot farther than this from the terrain is a lost foothold (m).
FOOTHOLD_CLEARANCE = 0.005
#: A joint this far past its range (rad) counts as past its range.
JOINT_RANGE_TOL = 0.01
#: Failure reasons of :class:`StepdownOutcome`, in display order.
FAILURE_REASONS = ("feet_not_down", "no_progress", "lost_foothold", "joint_past_range", "tilt", "trunk_strike",
                   "shin_strike", "diverged", "reflex_failure", "contact_overflow")
#: Reasons that do not prevent ``completed`` (they only make a run not ``clean``).
CLEAN_ONLY_REASONS = ("shin_strike",)


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
    joint_past_range: jax.Array
    min_swing_mobility: jax.Array
    mobility_sum: jax.Array
    swing_down_ticks: jax.Array
    lost_footholds: jax.Array
    time_all_down: jax.Array
    x_start: jax.Array
    reflex_failure: jax.Array
    contact_overflow: jax.Array


def make_metrics(ids: hmodel.ModelIds, strike_force: float, terminal_tilt: float | None = None) -> sim.Metrics:
    """Step-down metrics accumulated on the device (see the module docstring); with ``terminal_tilt`` (rad), their
    ``terminal``: the run has fallen (:func:`fallen`)."""
    ci = ids.contacts
    sites = np.asarray(ids.foot_sites)
    qadr = np.asarray(ids.qpos_joints)

    def init(d):
        f = jnp.asarray(0.0, d.qpos.dtype)
        no = jnp.array(False)
        return StepdownMetrics(peak_roll=f, peak_pitch=f, trunk_strike=no, shin_strike=no, shin_contact=no,
                               peak_shin_force=f, peak_trunk_force=f, joint_past_range=no,
                               min_swing_mobility=f + 10.0, mobility_sum=f, swing_down_ticks=jnp.int32(0),
                               lost_footholds=jnp.int32(0), time_all_down=f - 1.0,
                               x_start=d.qpos[robot.QPOS_BASE_POS][0], reflex_failure=no, contact_overflow=no)

    def update(ms: StepdownMetrics, d, obs, info) -> StepdownMetrics:
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
        f_shin = jnp.max(contacts.shin_forces(ci, d))
        f_trunk = contacts.trunk_force(ci, d)
        foot_contact = contacts.foot_clearance(ci, d) < FOOTHOLD_CLEARANCE
        q = d.qpos[qadr]
        crossed = jnp.any((q < robot.Q_MIN - JOINT_RANGE_TOL) | (q > robot.Q_MAX + JOINT_RANGE_TOL))
        sd = info.swing_down
        m_sw = info.mobility[info.swing_leg]
        lost = info.limit_stop & ~foot_contact[info.swing_leg]
        feet = d.site_xpos[sites]
        all_down = jnp.all((feet[:, 0] > 0.02) & (feet[:, 2] < 0.06))
        t_down = jnp.where((ms.time_all_down < 0) & all_down, d.time, ms.time_all_down)
        # The crawl reports the reflex's internal failure (ReflexOutput.failed) as CrawlInfo.reflex_failed.
        reflex_failed = getattr(info, "reflex_failed", jnp.array(False))
        return StepdownMetrics(
            peak_roll=jnp.maximum(ms.peak_roll, jnp.abs(rpy[0])),
            peak_pitch=jnp.maximum(ms.peak_pitch, jnp.abs(rpy[1])),
            trunk_strike=ms.trunk_strike | (f_trunk > strike_force),
            shin_strike=ms.shin_strike | (f_shin > strike_force),
            shin_contact=ms.shin_contact | jnp.any(contacts.shin_in_contact(ci, d)),
            peak_shin_force=jnp.maximum(ms.peak_shin_force, f_shin),
            peak_trunk_force=jnp.maximum(ms.peak_trunk_force, f_trunk),
            joint_past_range=ms.joint_past_range | crossed,
            min_swing_mobility=jnp.where(sd, jnp.minimum(ms.min_swing_mobility, m_sw), ms.min_swing_mobility),
            mobility_sum=ms.mobility_sum + jnp.where(sd, jnp.sum(info.mobility), 0.0),
            swing_down_ticks=ms.swing_down_ticks + sd.astype(jnp.int32),
            lost_footholds=ms.lost_footholds + lost.astype(jnp.int32),
            time_all_down=t_down,
            x_start=ms.x_start,
            reflex_failure=ms.reflex_failure | reflex_failed,
            contact_overflow=ms.contact_overflow | contacts.overflow(d),
        )

    terminal = None if terminal_tilt is None else (lambda ms: fallen(ms, terminal_tilt))
    return sim.Metrics(init, update, terminal)


def fallen(ms: StepdownMetrics, terminal_tilt: float) -> jax.Array:
    """The episode end of the step-down: ``|roll|`` or ``|pitch|`` has reached ``terminal_tilt`` (rad) or the trunk
    struck the terrain. Both are failures of :func:`outcome` that no later tick undoes (peaks and sticky flags), so
    ending the run there changes no ``completed`` or ``clean`` outcome (with ``terminal_tilt >= max_tilt``)."""
    return ~((ms.peak_roll < terminal_tilt) & (ms.peak_pitch < terminal_tilt)) | ms.trunk_strike


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class StepdownOutcome:
    """One instance's step-down outcome (leaves are scalars; with a leading batch axis after ``vmap``).

    ``completed`` and ``clean`` as in the module docstring; the boolean failure reasons are those of
    :data:`FAILURE_REASONS` (``diverged`` includes non-finite metrics). Measurements: peak shin / trunk
    contact forces (N), ``lost_footholds`` (count), ``peak_roll`` / ``peak_pitch`` (rad), mobility (Eq. 12,
    footnote 8; NaN ``min_swing_mobility`` without a swing-down tick), ``time_all_down`` (s, NaN if never),
    ``progress`` (m), ``diverged_tick`` (-1 if never), ``terminated`` and its failure tick ``terminated_tick`` (-1 if
    never; the episode end of the module docstring: the outcome is the one recorded up to that tick), and the
    crawl's step counts.
    """

    completed: jax.Array
    clean: jax.Array
    feet_not_down: jax.Array
    no_progress: jax.Array
    lost_foothold: jax.Array
    joint_past_range: jax.Array
    tilt: jax.Array
    trunk_strike: jax.Array
    shin_strike: jax.Array
    diverged: jax.Array
    reflex_failure: jax.Array
    contact_overflow: jax.Array
    shin_contact: jax.Array
    peak_shin_force: jax.Array
    peak_trunk_force: jax.Array
    lost_footholds: jax.Array
    peak_roll: jax.Array
    peak_pitch: jax.Array
    min_swing_mobility: jax.Array
    mean_mobility: jax.Array
    mobility_sum: jax.Array
    swing_down_ticks: jax.Array
    time_all_down: jax.Array
    progress: jax.Array
    diverged_tick: jax.Array
    terminated: jax.Array
    terminated_tick: jax.Array
    n_steps: jax.Array
    n_touchdowns: jax.Array
    n_limit_stops: jax.Array


def outcome(res: sim.RolloutResult, ids: hmodel.ModelIds, max_tilt: float, min_progress: float) -> StepdownOutcome:
    """The :class:`StepdownOutcome` of ONE instance's rollout (``vmap`` it for a batch); pure JAX."""
    ms: StepdownMetrics = res.metrics
    d, cs = res.data, res.ctrl_state
    feet = d.site_xpos[np.asarray(ids.foot_sites)]
    # All four feet reached the lower ground (at one instant) and none is back on the platform at the end
    # (the last instant may fall in a swing, so the final check is on x only).
    all_down = (ms.time_all_down >= 0) & jnp.all(feet[:, 0] > 0.02)
    progress = d.qpos[robot.QPOS_BASE_POS][0] - ms.x_start
    sd = jnp.maximum(ms.swing_down_ticks, 1)
    mean_mobility = ms.mobility_sum / sd
    finite = jnp.all(jnp.isfinite(jnp.stack([ms.peak_roll, ms.peak_pitch, progress, mean_mobility])))
    tilt = ~((ms.peak_roll < max_tilt) & (ms.peak_pitch < max_tilt))
    reasons = dict(feet_not_down=~all_down, no_progress=~(progress > min_progress), lost_foothold=ms.lost_footholds > 0,
                   joint_past_range=ms.joint_past_range, tilt=tilt, trunk_strike=ms.trunk_strike,
                   shin_strike=ms.shin_strike, diverged=res.diverged | ~finite, reflex_failure=ms.reflex_failure,
                   contact_overflow=ms.contact_overflow)
    completed = ~jnp.any(jnp.stack([v for k, v in reasons.items() if k not in CLEAN_ONLY_REASONS]))
    clean = completed & ~jnp.any(jnp.stack([reasons[k] for k in CLEAN_ONLY_REASONS]))
    nan = jnp.asarray(jnp.nan, ms.peak_roll.dtype)
    return StepdownOutcome(
        completed=completed, clean=clean, **reasons, shin_contact=ms.shin_contact,
        peak_shin_force=ms.peak_shin_force, peak_trunk_force=ms.peak_trunk_force, lost_footholds=ms.lost_footholds,
        peak_roll=ms.peak_roll, peak_pitch=ms.peak_pitch,
        min_swing_mobility=jnp.where(ms.swing_down_ticks > 0, ms.min_swing_mobility, nan),
        mean_mobility=mean_mobility, mobility_sum=ms.mobility_sum, swing_down_ticks=ms.swing_down_ticks,
        time_all_down=jnp.where(ms.time_all_down >= 0, ms.time_all_down, nan), progress=progress,
        diverged_tick=res.diverged_tick,
        terminated=jnp.asarray(False) if res.terminated is None else res.terminated,
        terminated_tick=jnp.asarray(-1, jnp.int32) if res.terminated_tick is None else res.terminated_tick,
        n_steps=cs.n_steps, n_touchdowns=cs.n_touchdowns,
        n_limit_stops=cs.n_limit_stops)


def to_columns(out: StepdownOutcome) -> dict[str, np.ndarray]:
    """NumPy columns of a batched outcome (one entry per field), plus ``success`` (= ``clean``, the name older
    results use) and ``all_feet_down`` (= ``~feet_not_down``)."""
    cols = {f.name: np.asarray(getattr(out, f.name)) for f in dataclasses.fields(out)}
    cols["success"] = cols["clean"]
    cols["all_feet_down"] = ~cols["feet_not_down"]
    return cols


def failure_labels(row) -> list[str]:
    """Names of the failure reasons set in one instance (a mapping of columns), in display order."""
    return [k.replace("_", " ") for k in FAILURE_REASONS if bool(row.get(k, False))]
