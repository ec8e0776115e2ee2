"""The statically stable crawl of Focchi et al. (2017), Section II, as a pure JAX controller.

A state machine alternates two phases (Fig. 2):

* **body motion** (``PHASE_BODY``): the trunk moves, on a quintic of duration ``t_body``, so that the
  centre of mass (CoM) enters the future support triangle (the three feet opposite the next swing
  leg, shrunk by ``stability_margin``), its height above the feet returns to ``body_height`` and its
  roll and pitch follow the plane of the feet (terrain adaptation). Targets are recomputed at the
  start of every phase from the *actual* state, so slips and reflex motions do not accumulate.
* **swing** (``PHASE_SWING``): one leg, in the order ``foot_sequence``, follows a quintic in the
  terrain frame (normal = plane of the three stance feet, Eq. 7) to a foothold ``step_length`` ahead.
  After the nominal ``t_swing`` the foot keeps *searching* along the terrain normal at
  ``search_speed`` until the estimated ground reaction force along the normal exceeds
  ``touchdown_force`` (haptic touchdown, footnote 1: 30 N), or a workspace / end-stop limit or
  ``max_search_depth`` is reached, in which case stance is triggered anyway so the machine never gets stuck.
  While the height reflex is active its end-stop springs keep the joints off their limits, so only the
  leg-extension and depth limits end its search. A step whose foothold or apex would leave the leg's
  workspace is shortened at planning time (:func:`_reachable_foothold`).

Frames: the plan lives in ``H0``, the horizontal frame at the start of the current phase. Stance feet
are fixed in ``H0``; the desired trunk pose relative to ``H0`` is ``(p_des(t), R_des(t))`` and the desired
feet in the trunk frame are ``B_x = R_des^T (H0_x - p_des)``. No world position is needed.

The **height reflex** (:mod:`hyqjax.reflex`) is hooked in as in Fig. 2/3: during the downward part of
the swing its corrected feet ``x_f^r`` replace the plan ``x_f^d`` before inverse kinematics.

The output torque is the joint impedance (:mod:`hyqjax.impedance`) on the IK references plus the
trunk controller's feed-forward (:mod:`hyqjax.trunk_control`).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import impedance, kinematics, reflex, robot, sim, spatial, trajectories, trunk_control

PHASE_BODY = 0
PHASE_SWING = 1

#: Foot sequences (leg indices LF=0, RF=1, LH=2, RH=3). Hind-then-front on each side, the usual crawl.
FOOT_SEQUENCES = {
    "rh-rf-lh-lf": (3, 1, 2, 0),
    "lh-lf-rh-rf": (2, 0, 3, 1),
    "rf-lh-lf-rh": (1, 2, 0, 3),
    "lf-rh-rf-lh": (0, 3, 1, 2),
}

#: The trunk-frame CoM offset in the standing pose (m), from the MJCF's masses.
COM_OFFSET_B = np.array([0.00696, 0.0, -0.0426])


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CrawlParams:
    """Crawl parameters; every field is a PyTree leaf (vmap/grad reach it), except ``foot_sequence``
    and ``use_reflex`` given per instance as arrays too.

    Attributes:
      forward_velocity: desired forward speed ``v_f`` (m/s); the step length is
        ``clip(v_f * T_cycle, 0, max_step_length)`` with ``T_cycle = 4 (t_body + t_swing)``.
      heading_velocity: desired yaw rate ``v_h`` (rad/s); footholds rotate by ``v_h T_cycle``.
      t_body, t_swing: nominal phase durations (s).
      step_height: swing apex along the terrain normal (m).
      body_height: trunk height above the mean foot height (m).
      stability_margin: the support triangle is shrunk by this much (m).
      touchdown_force: haptic touchdown threshold on the estimated force along the normal (N).
      search_speed: speed of the searching motion after the nominal swing (m/s).
      max_search_depth: search stops this far below the nominal foothold (m).
      max_leg_extension: HFE-to-foot distance at which the leg counts as at its workspace limit (m).
      terrain_adaptation: 0..1, fraction of the feet plane's roll/pitch the trunk follows.
      max_tilt: bound on the trunk roll/pitch targets (rad).
      mu: friction coefficient assumed by the trunk controller.
      k_com, d_com: trunk position stiffness (N/m) and damping (N s/m) of the trunk controller.
      k_rot, d_rot: trunk orientation stiffness (N m/rad) and damping (N m s/rad).
      mass: mass the trunk controller supports (kg).
      foot_sequence: (4,) int leg order.
      use_reflex: 0/1, height reflex on or off.
      gains: joint impedance gains.
      reflex: height reflex parameters (Table I by default).
    """

    forward_velocity: jax.Array
    heading_velocity: jax.Array
    t_body: jax.Array
    t_swing: jax.Array
    step_height: jax.Array
    max_step_length: jax.Array
    body_height: jax.Array
    stability_margin: jax.Array
    touchdown_force: jax.Array
    search_speed: jax.Array
    max_search_depth: jax.Array
    max_leg_extension: jax.Array
    terrain_adaptation: jax.Array
    max_tilt: jax.Array
    mu: jax.Array
    k_com: jax.Array
    d_com: jax.Array
    k_rot: jax.Array
    d_rot: jax.Array
    mass: jax.Array
    foot_sequence: jax.Array
    use_reflex: jax.Array
    gains: impedance.ImpedanceGains
    reflex: reflex.ReflexParams

    @staticmethod
    def make(forward_velocity=0.1, heading_velocity=0.0, t_body=0.4, t_swing=0.45, step_height=0.1,
             max_step_length=0.3, body_height=0.56, stability_margin=0.07, touchdown_force=30.0,
             search_speed=0.15, max_search_depth=0.4, max_leg_extension=0.678, terrain_adaptation=0.3,
             max_tilt=0.35, mu=0.7, k_com=3000.0, d_com=600.0, k_rot=1500.0, d_rot=150.0, mass=robot.TOTAL_MASS, foot_sequence="rh-rf-lh-lf", use_reflex=True,
             gains: impedance.ImpedanceGains | None = None,
             reflex_params: reflex.ReflexParams | None = None) -> "CrawlParams":
        """Validated constructor (runs outside jit; errors name the parameter and its range)."""
        checks = {
            "forward_velocity": (forward_velocity, -0.3, 0.3),
            "heading_velocity": (heading_velocity, -0.5, 0.5),
            "t_body": (t_body, 0.1, 5.0),
            "t_swing": (t_swing, 0.1, 5.0),
            "step_height": (step_height, 0.0, 0.25),
            "max_step_length": (max_step_length, 0.0, 0.4),
            "body_height": (body_height, 0.3, 0.68),
            "stability_margin": (stability_margin, 0.0, 0.15),
            "touchdown_force": (touchdown_force, 1.0, 500.0),
            "search_speed": (search_speed, 0.01, 1.0),
            "max_search_depth": (max_search_depth, 0.0, 0.6),
            "max_leg_extension": (max_leg_extension, 0.4, 0.69),
            "terrain_adaptation": (terrain_adaptation, 0.0, 1.0),
            "max_tilt": (max_tilt, 0.0, 0.6),
            "mu": (mu, 0.05, 2.0),
            "k_com": (k_com, 0.0, 2e4),
            "d_com": (d_com, 0.0, 5e3),
            "k_rot": (k_rot, 0.0, 1e4),
            "d_rot": (d_rot, 0.0, 2e3),
            "mass": (mass, 10.0, 300.0),
        }
        vals = {}
        for name, (v, lo, hi) in checks.items():
            arr = np.asarray(v, np.float64)
            if arr.shape != () or not np.isfinite(arr) or not (lo <= arr <= hi):
                raise ValueError(f"{name} must be a finite scalar in [{lo}, {hi}], got {v!r}")
            vals[name] = jnp.asarray(arr, jnp.float32)
        if isinstance(foot_sequence, str):
            if foot_sequence not in FOOT_SEQUENCES:
                raise ValueError(f"foot_sequence must be one of {sorted(FOOT_SEQUENCES)}, got {foot_sequence!r}")
            seq = FOOT_SEQUENCES[foot_sequence]
        else:
            seq = tuple(int(i) for i in foot_sequence)
            if sorted(seq) != [0, 1, 2, 3]:
                raise ValueError(f"foot_sequence must be a permutation of (0, 1, 2, 3), got {foot_sequence!r}")
        return CrawlParams(**vals, foot_sequence=jnp.asarray(seq, jnp.int32),
                           use_reflex=jnp.asarray(1.0 if use_reflex else 0.0, jnp.float32),
                           gains=gains or impedance.ImpedanceGains.make(),
                           reflex=reflex_params or reflex.ReflexParams.table1())

    def replace(self, **kw) -> "CrawlParams":
        return dataclasses.replace(self, **kw)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CrawlState:
    """The crawl state machine's memory (one instance)."""

    phase: jax.Array  # PHASE_BODY or PHASE_SWING
    seq_index: jax.Array  # index into foot_sequence of the current / next swing leg
    t_phase: jax.Array  # time in the current phase (s)
    feet_h0: jax.Array  # (4, 3) feet in H0 at the phase start (stance feet stay there)
    body_delta: jax.Array  # (3,) trunk displacement target of the body phase, in H0
    rp_start: jax.Array  # (2,) roll, pitch at the phase start (actual)
    rp_target: jax.Array  # (2,) roll, pitch target of the body phase
    swing_target: jax.Array  # (3,) nominal foothold of the swing foot in H0
    normal_h0: jax.Array  # (3,) terrain normal in H0 sampled at the swing start (Eq. 7)
    search_depth: jax.Array  # depth searched past the nominal foothold (m)
    stance: jax.Array  # (4,) 1.0 for stance legs
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
    mobility: jax.Array  # (4,) velocity transformation ratio of each leg along the terrain normal
    x_plan_b: jax.Array  # (4, 3) planned feet (trunk frame)
    x_cmd_b: jax.Array  # (4, 3) commanded feet after the reflex (trunk frame)
    q_cmd: jax.Array  # (12,) joint references
    damping: jax.Array  # (12,) reflex damping diagonal
    touchdown: jax.Array  # a touchdown happened this tick
    limit_stop: jax.Array  # stance was triggered by a limit this tick
    tilt_rp: jax.Array  # (2,) measured roll, pitch


def _rp_rot(rp):
    """``R_y(pitch) R_x(roll)``: trunk orientation in the horizontal frame."""
    return spatial.rpy_to_rot(jnp.stack([rp[0], rp[1], jnp.zeros_like(rp[0])]))


def _feet_plane(x):
    """Roll and pitch of the least-squares plane ``z = a x + b y + c`` through the feet ``(4, 3)``."""
    a_mat = jnp.stack([x[:, 0], x[:, 1], jnp.ones_like(x[:, 0])], -1)
    coef = jnp.linalg.solve(a_mat.T @ a_mat + 1e-9 * jnp.eye(3, dtype=x.dtype), a_mat.T @ x[:, 2])
    pitch = jnp.arctan(-coef[0])  # feet lower in front -> nose down (positive pitch in ZYX about +y)
    roll = jnp.arctan(coef[1])
    return jnp.stack([roll, pitch])


def _closest_in_triangle(p, a, b, c):
    """Closest point to ``p`` inside the triangle ``abc`` (2-D)."""

    def seg(p, u, v):
        d = v - u
        t = jnp.clip(jnp.dot(p - u, d) / (jnp.dot(d, d) + 1e-12), 0.0, 1.0)
        return u + t * d

    def cross(u, v):
        return u[0] * v[1] - u[1] * v[0]

    s1, s2, s3 = cross(b - a, p - a), cross(c - b, p - b), cross(a - c, p - c)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    cands = jnp.stack([seg(p, a, b), seg(p, b, c), seg(p, c, a)])
    best = cands[jnp.argmin(jnp.sum((cands - p) ** 2, -1))]
    return jnp.where(inside, p, best)


def _shrink_triangle(a, b, c, margin):
    """Move the vertices toward the incentre so every edge moves inward by ``margin`` (bounded)."""
    la, lb, lc = jnp.linalg.norm(b - c), jnp.linalg.norm(c - a), jnp.linalg.norm(a - b)
    per = la + lb + lc + 1e-9
    centre = (la * a + lb * b + lc * c) / per
    area = 0.5 * jnp.abs((b - a)[0] * (c - a)[1] - (b - a)[1] * (c - a)[0])
    r = 2.0 * area / per
    k = jnp.clip((r - margin) / (r + 1e-9), 0.05, 1.0)
    return centre + k * (a - centre), centre + k * (b - centre), centre + k * (c - centre)


_STANCE_OF = np.array([[j for j in range(4) if j != i] for i in range(4)])


def _feet_h(obs: sim.Observation):
    """Feet in the current horizontal frame from the actual joints and IMU roll/pitch, and that roll/pitch."""
    rpy = spatial.rot_to_rpy(spatial.quat_to_rot(obs.quat))
    rp = rpy[:2]
    x_b = kinematics.foot_positions(obs.q)
    return jnp.einsum("ij,lj->li", _rp_rot(rp), x_b), rp


def _start_body_phase(p: CrawlParams, st: CrawlState, obs: sim.Observation) -> CrawlState:
    feet, rp = _feet_h(obs)
    leg = p.foot_sequence[st.seq_index]
    com = jnp.asarray(COM_OFFSET_B, feet.dtype)
    com_h = _rp_rot(rp) @ com
    tri = feet[jnp.asarray(_STANCE_OF)[leg]]
    a, b, c = _shrink_triangle(tri[0, :2], tri[1, :2], tri[2, :2], p.stability_margin)
    # The CoM goes to the point of the shrunk support triangle closest to the centre of the four feet:
    # the smallest trunk motion that keeps the stability margin and keeps the trunk centred over the feet.
    ref = jnp.mean(feet[:, :2], 0)
    target_xy = _closest_in_triangle(ref, a, b, c)
    # Trunk height: body_height above the mean foot height (feet are below the trunk, mean z < 0).
    dz = jnp.mean(feet[:, 2]) + p.body_height
    delta = jnp.concatenate([target_xy - com_h[:2], dz[None]])
    plane = _feet_plane(feet)
    rp_target = jnp.clip(p.terrain_adaptation * plane, -p.max_tilt, p.max_tilt)
    return dataclasses.replace(st, phase=jnp.asarray(PHASE_BODY), t_phase=jnp.zeros_like(st.t_phase), feet_h0=feet,
                               body_delta=delta, rp_start=rp, rp_target=rp_target, stance=jnp.ones(4, feet.dtype))


#: Step fractions tried, longest first, when the full step leaves the leg's workspace.
_STEP_FRACTIONS = np.array([1.0, 0.85, 0.7, 0.55, 0.4, 0.25, 0.1])
#: Joint-limit margin (rad) a planned foothold and swing apex must keep.
_REACH_MARGIN = 0.08


def _reachable_foothold(p: CrawlParams, leg, lift, target, n, rp):
    """Shorten the step so the foothold and the swing apex stay inside the leg's workspace.

    The trunk holds still during a swing (Section II), so the swing foot's path is fixed in the trunk
    frame at planning time. The step ``lift -> target`` is scaled by the largest fraction in
    ``_STEP_FRACTIONS`` for which the foothold and the apex (mid-step, ``step_height`` along ``n``) have
    IK solutions within the joint ranges minus ``_REACH_MARGIN`` and within ``max_leg_extension``.
    A hind leg folded under a trunk that has lowered over the step cannot reach a full step forward
    (its HFE hits the end stop); without this the swing would stop at the end stop in mid-air.
    """
    r_b = _rp_rot(rp).T
    q_min = jnp.asarray(robot.Q_MIN, lift.dtype).reshape(4, 3)[leg]
    q_max = jnp.asarray(robot.Q_MAX, lift.dtype).reshape(4, 3)[leg]
    hip = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, lift.dtype))

    def ok(frac):
        foot = lift + frac * (target - lift)
        apex = 0.5 * (lift + foot) + p.step_height * n
        pts = jnp.stack([foot, apex]) @ r_b.T  # (2, 3) in the trunk frame
        x = jnp.broadcast_to(hip, (2, 4, 3)).at[:, leg].set(pts)
        q = kinematics.inverse_kinematics(x)[:, leg]
        inside = jnp.all((q > q_min + _REACH_MARGIN) & (q < q_max - _REACH_MARGIN))
        ext = kinematics.leg_extension(q.reshape(2, 1, 3).repeat(4, 1).reshape(2, 12))[:, leg]
        return inside & jnp.all(ext < p.max_leg_extension)

    fracs = jnp.asarray(_STEP_FRACTIONS, lift.dtype)
    feasible = jax.vmap(ok)(fracs)
    frac = jnp.where(jnp.any(feasible), fracs[jnp.argmax(feasible)], fracs[-1])
    return lift + frac * (target - lift)


def _start_swing_phase(p: CrawlParams, st: CrawlState, obs: sim.Observation) -> CrawlState:
    feet, rp = _feet_h(obs)
    leg = p.foot_sequence[st.seq_index]
    tri = feet[jnp.asarray(_STANCE_OF)[leg]]
    n = reflex.terrain_normal(tri)
    t_cycle = 4.0 * (p.t_body + p.t_swing)
    step = jnp.clip(p.forward_velocity * t_cycle, -p.max_step_length, p.max_step_length)
    yaw = p.heading_velocity * t_cycle
    nominal_b = kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, feet.dtype))[leg]
    nominal_h = _rp_rot(rp) @ nominal_b
    # Foothold: every foot advances by one step length from where it lifts off (so the trunk, centred
    # over the feet, advances one step per cycle), laterally back to its nominal distance from the trunk,
    # rotated about the trunk by the heading change of one cycle, and at the lift-off height along the
    # terrain normal (expected flat continuation; the haptic search handles the rest).
    lift = feet[leg]
    target = jnp.stack([lift[0] + step, nominal_h[1], lift[2]])
    c, s_ = jnp.cos(yaw), jnp.sin(yaw)
    target = jnp.stack([c * target[0] - s_ * target[1], s_ * target[0] + c * target[1], target[2]])
    target = target - jnp.dot(target - lift, n) * n
    target = _reachable_foothold(p, leg, lift, target, n, rp)
    stance = jnp.ones(4, feet.dtype).at[leg].set(0.0)
    return dataclasses.replace(st, phase=jnp.asarray(PHASE_SWING), t_phase=jnp.zeros_like(st.t_phase), feet_h0=feet,
                               body_delta=jnp.zeros(3, feet.dtype), rp_start=rp, rp_target=rp, swing_target=target,
                               normal_h0=n, search_depth=jnp.zeros_like(st.search_depth), stance=stance)


def crawl_init(p: CrawlParams, obs: sim.Observation) -> CrawlState:
    feet, rp = _feet_h(obs)
    dtype = feet.dtype
    z = jnp.zeros((), dtype)
    st = CrawlState(
        phase=jnp.asarray(PHASE_BODY), seq_index=jnp.asarray(0), t_phase=z, feet_h0=feet,
        body_delta=jnp.zeros(3, dtype), rp_start=rp, rp_target=rp, swing_target=feet[0],
        normal_h0=jnp.array([0.0, 0.0, 1.0], dtype), search_depth=z, stance=jnp.ones(4, dtype),
        reflex=reflex.reflex_init(kinematics.foot_positions(obs.q)), q_cmd=obs.q,
        n_steps=jnp.asarray(0), n_touchdowns=jnp.asarray(0), n_limit_stops=jnp.asarray(0),
    )
    return _start_body_phase(p, st, obs)


def _plan(p: CrawlParams, st: CrawlState, dt, rp_meas):
    """Desired feet in the trunk frame ``(4, 3)``, swing-down flag, and the trunk rotation ``R_des``."""
    t = st.t_phase
    in_body = st.phase == PHASE_BODY
    s_body, ds_body, _ = trajectories.quintic(t / p.t_body)
    p_des = jnp.where(in_body, s_body, 0.0) * st.body_delta
    v_des = jnp.where(in_body, ds_body / p.t_body, 0.0) * st.body_delta
    rp_des = st.rp_start + jnp.where(in_body, s_body, 0.0) * (st.rp_target - st.rp_start)
    r_des = _rp_rot(rp_des)
    feet = st.feet_h0
    # Swing foot: quintic in the terrain frame, then a search along -normal.
    leg = p.foot_sequence[st.seq_index]
    tau = t / p.t_swing
    s_tan, z_n, _ = trajectories.swing_profile(tau, p.step_height)
    start = st.feet_h0[leg]
    n = st.normal_h0
    search = st.search_depth
    swing_pos = start + s_tan * (st.swing_target - start) + (z_n - search) * n
    is_swing = (~in_body)
    x_b = jnp.einsum("ji,lj->li", r_des, feet - p_des)
    # Angular kinematic adjustment of the swing foot: its H0 trajectory is mapped into the trunk frame with
    # the *measured* roll and pitch, so a trunk rotation (e.g. the reflex's squat) does not drag the foot
    # along with it in the world.
    x_sw_b = _rp_rot(rp_meas).T @ (swing_pos - p_des)
    x_b = jnp.where(is_swing & (jnp.arange(4) == leg)[:, None], x_sw_b[None, :], x_b)
    swing_down = is_swing & (tau >= 0.5)
    return x_b, swing_down, r_des, leg, p_des, v_des, rp_des


def crawl_step(p: CrawlParams, st: CrawlState, obs: sim.Observation, dt: float):
    """One control tick: plan, reflex, IK, joint impedance + feed-forward, phase transitions."""
    rp_meas = spatial.rot_to_rpy(spatial.quat_to_rot(obs.quat))[:2]
    x_plan, swing_down, r_des, leg, p_des, v_des, rp_des = _plan(p, st, dt, rp_meas)
    in_swing = st.phase == PHASE_SWING
    # --- height reflex (Fig. 2/3): active in the downward part of the swing.
    up_b = r_des.T @ jnp.array([0.0, 0.0, 1.0], x_plan.dtype)
    normal_b = r_des.T @ st.normal_h0
    active = swing_down & (p.use_reflex > 0.5)
    rin = reflex.ReflexInputs(x_des=x_plan, swing_leg=leg, active=active, n_t_des=normal_b, up=up_b)
    rstate, rout = reflex.reflex_step(st.reflex, rin, p.reflex, dt)
    x_cmd = jnp.where(active, rout.x_r, x_plan)
    q_ik = kinematics.inverse_kinematics(x_cmd).reshape(12)
    q_min, q_max = jnp.asarray(robot.Q_MIN, q_ik.dtype), jnp.asarray(robot.Q_MAX, q_ik.dtype)
    q_cmd = jnp.clip(jnp.where(active, rout.q_r, q_ik), q_min, q_max)
    # --- trunk controller feed-forward on the stance legs.
    h_r_b = _rp_rot(rp_meas)
    x_meas_b = kinematics.foot_positions(obs.q)
    com_b = jnp.asarray(COM_OFFSET_B, x_plan.dtype)
    r_h = jnp.einsum("ij,lj->li", h_r_b, x_meas_b - com_b)
    # Trunk pose relative to H0 by leg odometry: stance feet are fixed in H0.
    feet_now_h = jnp.einsum("ij,lj->li", h_r_b, x_meas_b)
    w = st.stance / jnp.sum(st.stance)
    p_meas = jnp.sum(w[:, None] * (st.feet_h0 - feet_now_h), 0)
    v_feet_b = kinematics.foot_velocities(obs.q, obs.qd)
    v_meas = -jnp.sum(w[:, None] * jnp.einsum("ij,lj->li", h_r_b, v_feet_b + jnp.cross(obs.gyro, x_meas_b)), 0)
    up_h = jnp.array([0.0, 0.0, 1.0], x_plan.dtype)
    force = p.mass * robot.GRAVITY * up_h + p.k_com * (p_des - p_meas) + p.d_com * (v_des - v_meas)
    omega_h = h_r_b @ obs.gyro
    rp_err = jnp.concatenate([rp_des - rp_meas, jnp.zeros(1, x_plan.dtype)])
    torque = p.k_rot * rp_err - p.d_rot * omega_h
    f_h = trunk_control.distribute_wrench(r_h, st.stance, force, torque, p.mu)
    tau_ff = trunk_control.feedforward_torques(obs.q, h_r_b.T, f_h)
    tau = impedance.joint_impedance(p.gains, q_cmd, jnp.zeros_like(q_cmd), obs.q, obs.qd, tau_ff)

    # --- mobility of every leg along the terrain normal (Eq. 12), at the measured configuration.
    jac = kinematics.foot_jacobians(obs.q)
    mob = jax.vmap(lambda j: reflex.velocity_transformation_ratio(j, normal_b)[0])(jac)

    # --- phase logic.
    t_new = st.t_phase + dt
    nominal_done = t_new >= p.t_swing
    search_depth = jnp.where(in_swing & nominal_done, st.search_depth + p.search_speed * dt, st.search_depth)
    force_n = jnp.dot(obs.foot_force[leg], normal_b)
    touchdown = in_swing & (t_new >= 0.5 * p.t_swing) & (force_n > p.touchdown_force)
    ext = kinematics.leg_extension(q_cmd)[leg]
    q_leg = jax.lax.dynamic_slice(q_cmd, (3 * leg,), (3,))
    lo = jax.lax.dynamic_slice(q_min, (3 * leg,), (3,))
    hi = jax.lax.dynamic_slice(q_max, (3 * leg,), (3,))
    at_end_stop = jnp.any((q_leg - lo < 0.01) | (hi - q_leg < 0.01))
    # While the reflex is active its end-stop springs (Eq. 9) keep the swing joints off their limits and hand
    # the motion to the stance legs, so the search goes on; without it, an end stop ends the swing (Section IV).
    limit = in_swing & nominal_done & ((ext > p.max_leg_extension) | (at_end_stop & ~active)
                                       | (search_depth > p.max_search_depth))
    swing_end = touchdown | limit
    body_end = (~in_swing) & (t_new >= p.t_body)

    st1 = dataclasses.replace(st, t_phase=t_new, search_depth=search_depth, reflex=rstate, q_cmd=q_cmd)
    # After a swing: next leg, body phase from the actual state. After a body phase: swing.
    st_after_swing = dataclasses.replace(st1, seq_index=(st.seq_index + 1) % 4, n_steps=st.n_steps + 1,
                                         n_touchdowns=st.n_touchdowns + touchdown.astype(jnp.int32),
                                         n_limit_stops=st.n_limit_stops + (limit & ~touchdown).astype(jnp.int32))
    st_after_swing = _start_body_phase(p, st_after_swing, obs)
    st_after_body = _start_swing_phase(p, st1, obs)
    pick = lambda c, a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)  # noqa: E731
    st_next = pick(swing_end, st_after_swing, pick(body_end, st_after_body, st1))
    # The reflex tracks the plan again from the new phase's start.
    info = CrawlInfo(phase=st.phase, swing_leg=leg, swing_down=swing_down, reflex_active=active, mobility=mob,
                     x_plan_b=x_plan, x_cmd_b=x_cmd, q_cmd=q_cmd, damping=rout.d_diag, touchdown=touchdown,
                     limit_stop=limit & ~touchdown, tilt_rp=rp_meas)
    return st_next, tau, info


def crawl_controller(dt: float) -> sim.Controller:
    """The crawl as a :class:`hyqjax.sim.Controller` ticking every ``dt`` seconds."""
    return sim.Controller(crawl_init, lambda p, s, o: crawl_step(p, s, o, dt))
