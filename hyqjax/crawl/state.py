"""The crawl state machine (Section II, Fig. 2): its memory, its diagnostics and its two phase starts.

A state machine alternates two phases:

* **body motion** (``PHASE_BODY``): the trunk moves, on a quintic of duration ``t_body``, so that the
  centre of mass enters the future support triangle, its height above the feet returns to ``body_height``
  and its roll and pitch follow the plane of the feet (:mod:`hyqjax.crawl.footholds`). Targets are
  recomputed at the start of every phase from the *actual* state, so slips and reflex motions do not
  accumulate.
* **swing** (``PHASE_SWING``): one leg, in the order ``sequence``, follows a quintic in the terrain frame to
  a foothold one step ahead, then searches until a haptic touchdown or a limit (:mod:`hyqjax.crawl.swing`).

Frames: the plan lives in ``H0``, the horizontal frame at the start of the current phase. Stance feet are
fixed in ``H0``; the desired trunk pose relative to ``H0`` is ``(p_des(t), R_des(t))``.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.core import spatial
from hyqjax.crawl import edge
from hyqjax.crawl import footholds
from hyqjax.crawl import remedy
from hyqjax.crawl.params import COM_OFFSET_B, CrawlParams
from hyqjax.reflex import step as reflex
from hyqjax.core.types import Observation

PHASE_BODY = 0
PHASE_SWING = 1

#: Why a swing ended without touchdown (``CrawlInfo.limit_kind``).
LIMIT_NONE, LIMIT_EXTENSION, LIMIT_END_STOP, LIMIT_DEPTH = 0, 1, 2, 3


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CrawlState:
    """The crawl state machine's memory (one instance)."""

    phase: jax.Array  # PHASE_BODY or PHASE_SWING
    seq_index: jax.Array  # index into `sequence` of the current / next swing leg
    sequence: jax.Array  # (4,) leg order (foot_sequence; the remedy may swap entries)
    t_phase: jax.Array  # time in the current phase (s)
    feet_h0: jax.Array  # (4, 3) feet in H0 at the phase start (stance feet stay there)
    body_delta: jax.Array  # (3,) trunk displacement target of the body phase, in H0
    rp_start: jax.Array  # (2,) roll, pitch at the phase start (actual)
    rp_target: jax.Array  # (2,) roll, pitch target of the body phase
    swing_target: jax.Array  # (3,) nominal foothold of the swing foot in H0
    normal_h0: jax.Array  # (3,) terrain normal in H0 sampled at the swing start (Eq. 7)
    search_dir: jax.Array  # (3,) the search moves the foot along -search_dir per metre of depth (H0)
    search_fwd: jax.Array  # (3,) unit of the remedy's forward search (H0; zero where it does not apply)
    search_forward_left: jax.Array  # forward search still allowed this swing before it saturates (m)
    search_depth: jax.Array  # depth searched past the nominal foothold (m)
    stance: jax.Array  # (4,) 1.0 for stance legs
    loaded: jax.Array  # (4,) bool: the foot has pressed above stance_min_force since its last touchdown
    deep: jax.Array  # (4,) bool: the leg's last swing searched deeper than deep_search (a step down)
    edge_lo: jax.Array  # bounds on the step-down edge's x in H0 (hyqjax.crawl.edge; +-EDGE_UNKNOWN: none yet)
    edge_hi: jax.Array
    probe_leg: jax.Array  # the leg whose next swing probes for the edge (-1: none)
    probing: jax.Array  # bool: the current swing is the probe
    step_back: jax.Array  # the next swing's step is this much shorter (m): a probe that missed went this far
    edge_depth: jax.Array  # the step's depth measured by the front foot that found it (m; 0 before)
    reflex: reflex.ReflexState
    q_cmd: jax.Array  # (12,) last joint reference
    n_steps: jax.Array  # completed swings
    n_touchdowns: jax.Array  # swings ended by haptic touchdown
    n_limit_stops: jax.Array  # swings ended by a workspace / end-stop / depth limit


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CrawlInfo:
    """Per-tick diagnostics (for metrics and figures)."""

    phase: jax.Array
    swing_leg: jax.Array
    swing_down: jax.Array  # c_sd of footnote 8: swing leg in the downward part of its swing
    reflex_active: jax.Array
    reflex_failed: jax.Array  # the reflex's internal failure (ReflexOutput.failed) while the reflex is on
    mobility: jax.Array  # (4,) velocity transformation ratio of each leg along the terrain normal
    x_plan_b: jax.Array  # (4, 3) planned feet (trunk frame)
    x_cmd_b: jax.Array  # (4, 3) commanded feet after the reflex (trunk frame)
    q_cmd: jax.Array  # (12,) joint references
    qd_cmd: jax.Array  # (12,) joint velocity references
    damping: jax.Array  # (12,) reflex damping diagonal
    touchdown: jax.Array  # a touchdown happened this tick
    limit_stop: jax.Array  # stance was triggered by a limit this tick
    limit_kind: jax.Array  # LIMIT_* of that stop (LIMIT_NONE otherwise)
    search_depth: jax.Array  # depth searched below the nominal foothold (m)
    tilt_rp: jax.Array  # (2,) measured roll, pitch


class Measured(NamedTuple):
    """The robot's measured kinematics at one tick, computed once a tick (:func:`measure`) for every part of the
    controller that reads them.

    Attributes:
      feet: ``(4, 3)`` feet in the current horizontal frame ``H``, ``hR_b x_b``.
      rp: ``(2,)`` the IMU's roll and pitch.
      h_r_b: ``(3, 3)`` ``hR_b = R_y(pitch) R_x(roll)`` (:func:`hyqjax.core.spatial.roll_pitch_to_rot`).
      x_b: ``(4, 3)`` feet in the trunk frame from the measured joints, ``K(q)``.
      jac: ``(4, 3, 3)`` the feet's Jacobians ``J_f(q)`` at the measured joints (Eq. 11).
    """

    feet: jax.Array
    rp: jax.Array
    h_r_b: jax.Array
    x_b: jax.Array
    jac: jax.Array


def measure(obs: Observation) -> Measured:
    """:class:`Measured` of an observation: the actual joints and the IMU's roll and pitch."""
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(obs.quat))
    rp = rpy[:2]
    h_r_b = spatial.roll_pitch_to_rot(rp[0], rp[1])
    x_b = kinematics.foot_positions(obs.q)
    return Measured(jnp.einsum("ij,lj->li", h_r_b, x_b), rp, h_r_b, x_b, kinematics.foot_jacobians(obs.q))


def start_body_phase(p: CrawlParams, st: CrawlState, m: Measured) -> CrawlState:
    """Body phase toward the support triangle of the next swing leg, from the actual state ``m``: the feet in the
    horizontal frame and the measured roll and pitch (:func:`measure`)."""
    feet, rp = m.feet, m.rp
    edge_lo, edge_hi = edge.carry(st, feet)
    st = dataclasses.replace(st, edge_lo=edge_lo, edge_hi=edge_hi)
    leg = st.sequence[st.seq_index]
    com_h = m.h_r_b @ jnp.asarray(COM_OFFSET_B, feet.dtype)
    # While a step down is under way (a leg's last swing found one) the options lower the trunk and let it follow
    # more of the feet plane's tilt; at their defaults (0) both terms are exactly zero.
    stepping = jnp.any(st.deep).astype(feet.dtype)
    height = p.body_height - p.step_down_lowering * stepping
    adapt = p.terrain_adaptation + p.terrain_adaptation_step * (1.0 - p.terrain_adaptation) * stepping
    delta = footholds.body_target(feet, leg, com_h, p.stability_margin, height)
    adapt = edge.tilt_share(p, st, adapt, m.h_r_b, delta)  # adapt itself at edge_probe = 0
    delta = edge.lowered(p, st, m.h_r_b, delta)  # delta itself at edge_probe = 0
    rp_target = jnp.clip(adapt * footholds.feet_plane(feet), -p.max_tilt, p.max_tilt)
    return dataclasses.replace(st, phase=jnp.int32(PHASE_BODY), t_phase=jnp.zeros_like(st.t_phase), feet_h0=feet,
                               body_delta=delta, rp_start=rp, rp_target=rp_target, stance=jnp.ones(4, feet.dtype))


def start_swing_phase(p: CrawlParams, st: CrawlState, m: Measured) -> CrawlState:
    """Swing of ``sequence[seq_index]`` to a reachable foothold one step ahead, in the terrain frame (Eq. 7), from
    the feet in the horizontal frame and the measured roll and pitch (:func:`measure`)."""
    feet, rp = m.feet, m.rp
    edge_lo, edge_hi = edge.carry(st, feet)
    leg = st.sequence[st.seq_index]
    n = reflex.terrain_normal(feet[jnp.asarray(robot.STANCE_LEGS)[leg]])
    t_cycle = 4.0 * (p.t_body + p.t_swing)
    step = jnp.clip(p.forward_velocity * t_cycle, -p.max_step_length, p.max_step_length)
    nominal_h = m.h_r_b @ kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, feet.dtype))[leg]
    lift = feet[leg]
    target = footholds.swing_foothold(lift, nominal_h, step - st.step_back, p.heading_velocity * t_cycle, n)
    lift_offset = remedy.lift_drop_offset(p, lift, target)
    target = target + lift_offset * remedy.search_forward_unit(p, leg, n, target - lift)
    target = footholds.reachable_foothold(p.step_height, p.max_leg_extension, leg, lift, target, n, m.h_r_b)
    search_dir = remedy.search_direction(p, leg, n, target - lift)
    search_fwd = remedy.search_forward_unit(p, leg, n, target - lift)
    probing, target, search_dir, search_fwd = edge.probe_swing(p, st, leg, lift, target, search_dir, search_fwd)
    lift_offset = jnp.where(probing, 0.0, lift_offset)
    stance = jnp.ones(4, feet.dtype).at[leg].set(0.0)
    return dataclasses.replace(st, loaded=st.loaded.at[leg].set(False), phase=jnp.int32(PHASE_SWING),
                               t_phase=jnp.zeros_like(st.t_phase), feet_h0=feet,
                               body_delta=jnp.zeros(3, feet.dtype), rp_start=rp, rp_target=rp, swing_target=target,
                               normal_h0=n, search_dir=search_dir, search_fwd=search_fwd,
                               search_forward_left=p.search_forward_limit - lift_offset,
                               search_depth=jnp.zeros_like(st.search_depth),
                               stance=stance, edge_lo=edge_lo, edge_hi=edge_hi, probing=probing,
                               step_back=jnp.zeros_like(st.step_back))


def crawl_init(p: CrawlParams, obs: Observation) -> CrawlState:
    """Initial state: a body phase toward the first swing leg's support triangle."""
    m = measure(obs)
    feet, rp = m.feet, m.rp
    dtype = feet.dtype
    z = jnp.zeros((), dtype)
    up = jnp.array([0.0, 0.0, 1.0], dtype)
    st = CrawlState(
        phase=jnp.int32(PHASE_BODY), seq_index=jnp.int32(0), sequence=jnp.asarray(p.foot_sequence, jnp.int32),
        t_phase=z, feet_h0=feet, body_delta=jnp.zeros(3, dtype), rp_start=rp, rp_target=rp, swing_target=feet[0],
        normal_h0=up, search_dir=up, search_fwd=jnp.zeros(3, dtype),
        search_forward_left=jnp.asarray(p.search_forward_limit, dtype), search_depth=z, stance=jnp.ones(4, dtype),
        loaded=jnp.zeros(4, bool), deep=jnp.zeros(4, bool), edge_lo=jnp.asarray(-edge.EDGE_UNKNOWN, dtype),
        edge_hi=jnp.asarray(edge.EDGE_UNKNOWN, dtype), probe_leg=jnp.int32(-1), probing=jnp.asarray(False),
        step_back=z, edge_depth=z,
        reflex=reflex.reflex_init(m.x_b), q_cmd=obs.q,
        n_steps=jnp.int32(0), n_touchdowns=jnp.int32(0), n_limit_stops=jnp.int32(0),
    )
    return start_body_phase(p, st, m)
