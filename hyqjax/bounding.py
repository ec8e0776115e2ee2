"""HyQ's bounding gait with speed, turning and centrifugal control (Orsolino et al., "Turning maneuvers
strategy for quadrupedal bounding gait").

The controller is a :class:`hyqjax.sim.Controller`; it sees only :class:`hyqjax.sim.Observation`
(joint states and torques, IMU orientation and angular rate, foot forces, time). Base height and
linear velocity are **estimated** (leg odometry, Section "State estimation" below); no ground truth
reaches the controller (the only exception: :func:`hyqjax.bounding_cycle.return_map` starts the estimator at
the true apex state, as the return map is a function of that state).

Defaults: period 0.4 s, duty 0.4 per pair (hind stance at phases 0.05-0.45, front at 0.55-0.95, two
0.04 s flights), base height 0.6 m, feet 0.10 m inside the hips. Simulation: MJX, 2 ms step, 500 Hz
control, flat ground (:func:`hyqjax.bounding_cycle._model` switches off the flush platform's collisions).

Gait baseline (Section II of the paper, Park & Kim's impulses)
---------------------------------------------------------------
The legs work in pairs, front (LF, RF) and hind (LH, RH). A clock of period ``T`` gives the phase
``phi = (t / T) mod 1``; pair ``p`` is in stance while ``(phi - phi_p) mod 1 < d_p`` (touchdown
phase ``phi_p``, duty ``d_p``), with stance progress ``s = ((phi - phi_p) mod 1) / d_p``. During
stance each leg ``i`` pushes with the feed-forward ground-reaction force (horizontal frame ``H``)

.. math:: {}_h f_i(t) = \\beta(s)\\, \\mathbf a_i, \\qquad \\mathbf a_i = [a_{i,x}, a_{i,y}, a_{i,z}]^T   \\qquad (B1)

with the impulse profile ``beta`` a half sine ``sin(pi s)`` or a Bezier curve
``sum_k c_k B_k^n(s)`` (``c_0 = c_n = 0``). Its impulse is ``a_i d_p T kappa`` with
``kappa = 2 / pi`` (half sine) or ``kappa = mean(c)`` (Bezier). Park & Kim's vertical impulse
balance over one period (weight carried, zero net pitch moment about the CoM at ``x_c``) gives the
initial guess :func:`impulse_guess`:

.. math:: 2\\kappa (a_{f,z} d_f + a_{h,z} d_h) T = m g T, \\qquad
          a_{f,z} d_f (x_f - x_c) + a_{h,z} d_h (x_h - x_c) = 0.                      \\qquad (B2)

The exact periodic amplitudes ``a*`` come from :mod:`hyqjax.bounding_cycle` (return-map
optimisation through MJX); the stored cycle is :mod:`hyqjax.bounding_defaults`. The force reaches
the joints through the leg Jacobian (the ground
pushes the foot with ``f``, the leg must push the ground with ``-f``):

.. math:: \\tau_{ff,i} = -J_i(q)^T\\, {}_bR_h\\, {}_h f_i, \\qquad {}_bR_h = (R_y(\\theta) R_x(\\phi))^T. \\qquad (B3)

Joint impedance (:func:`hyqjax.impedance.joint_impedance`) tracks the foot references below,
with separate stance and swing gains: ``tau = Kp (q^d - q) + Kd (qd^d - qd) + tau_ff``.

Stabilising state feedback
--------------------------
Phase 0 is the middle of the flight before the hind stance: the apex. The feed-forward cycle alone
is unstable (return-map eigenvalues up to ~3.4, see :mod:`hyqjax.bounding_cycle`); three feedbacks
stabilise it, all zero on the limit cycle (so the cycle is the same with and without them):

*Stance PD on the cycle reference* (continuous, Park & Kim's attitude control). ``params.reference``
holds the cycle's ``(z, theta, zdot, thetadot)`` against phase (recorded from the optimised cycle);
during stance each leg adds ``beta(s)/2`` times

.. math:: \Delta f_z = k_{sz} (z^{ref} - z) + k_{s\dot z} (\dot z^{ref} - \dot z), \qquad
          \Delta f_x = [k_{s\theta} (\theta - \theta^{ref}) + k_{s\dot\theta} (\dot\theta - \dot\theta^{ref})] / h
          \qquad (B7)

(a forward push at the foot, ``h`` below the CoM, pitches the trunk nose-up: ``tau_y = -h f_x``).

*Apex impulse scaling* (per cycle, Park & Kim's vertical impulse scaling). At every apex ``k`` the
controller samples ``s_k = (z, theta, xdot, zdot, thetadot)`` (estimated height and velocities, IMU
pitch and pitch rate), integrates the errors ``I_k = I_{k-1} + (z* - z_k, theta_k - theta*, ...)``
and scales this cycle's vertical impulses:

.. math::
    \alpha_k = 1 + k_z (z^* - z_k) + k_{\dot z} (\dot z^* - \dot z_k) + k_{zI} I_{z,k}, \qquad
    \Delta_k = k_\theta (\theta_k - \theta^*) + k_{\dot\theta} (\dot\theta_k - \dot\theta^*) + k_{\theta I} I_{\theta,k},

.. math:: a_{f,z} = a^*_{f,z}\, \alpha_k (1 + \Delta_k), \qquad a_{h,z} = a^*_{h,z}\, \alpha_k (1 - \Delta_k).  \qquad (B4)

(``theta > 0`` is nose down; the front push pitches the nose up.)

*Foot placement* (Raibert): the touchdown target is the neutral point of the stride for the estimated
speed plus a correction on the apex speed error, Eq. B8 (:func:`touchdown_target`). Without the
neutral point, forward speed shifts the vertical forces' moment arms and feeds the pitch loop.

Speed and turning control (Section IV)
--------------------------------------
Per cycle, from the apex sample of the estimated velocity in ``H`` (``xdot*`` the cycle's apex speed):

.. math:: a_{i,x} = a^*_{i,x} + K_{d,\dot x} (\dot x^d + \dot x^* - \dot x) + K_{I} I_{\dot x}, \qquad
          a_{i,y} = a^*_{i,y} + K_{d,\dot y} (\dot y^d - \dot y) + K_I I_{\dot y}              \qquad (B5)

(the paper's law is the ``K_d`` term; ``K_I`` defaults to 0). The switch ``apex_feedback`` gates all
per-cycle terms (B4, B5 and the correction of B8). Continuously, from the gyro (``x_{f,i}`` the
nominal foot x in ``B``; ``f_y x_f`` is a yaw moment):

.. math:: a_{i,y} \mathrel{+}= \big[K_{d,\psi} (\dot\psi^d - \dot\psi) + K_{p,\psi} (\psi^d - \psi)\big] / x_{f,i}. \qquad (B6)

``K_{p,psi}`` (yaw-angle feedback) is **not** in the paper, whose law has the rate term only. With the
rate term alone the yaw angle lags the integrated command by a steady 4-6 deg in our simulation; the
default ``K_{p,psi} = 200 N m/rad`` keeps it below ~2.5 deg (set ``k_yaw=0`` for the paper's law).
``psi^d`` integrates the (ramped) yaw-rate command from the initial heading.
Roll is held by a stance PD that shifts vertical force from one side to the other,
``a_{i,z} += -sgn(y_i) [K_\phi (\phi - \phi^d) + K_{\dot\phi} \dot\phi] / (2 |y_f|)``.

Centrifugal compensation (Eqs. 3-4)
-----------------------------------
With ``r = xdot / psidot^d``, ``a_cf = xdot^2 / r = xdot psidot^d`` (Eq. 3, the lateral
acceleration ``a_y`` of the turn). The feet move outward by ``Delta y_f = -h a_y / g`` so the
leg axes align with the resultant of gravity and the centripetal force, the trunk is rolled by
the lean angle ``phi^d = atan(Delta y_f / h)`` (Eq. 4; into the turn), and the stance legs add the
matching lateral feed-forward ``a_{i,y} += a_{i,z} a_y / g``.

Kinematic adjustment (Section III, Eqs. 1-2)
--------------------------------------------
Foot references are planned in a yaw-fixed odometry world frame ``W`` whose horizontal origin is
reset at every apex (the paper's "reset the world frame at every cycle"; we keep ``W``'s yaw, a
rotation that leaves the relative quantities unchanged). A stance foot stays where it touched
down, ``w_x_f^d = p_td``; a swing foot moves in ``H`` from lift-off to the next touchdown target
with a ``clearance * sin(pi s)`` lift above the ground. *Linear* adjustment (Eq. 1):

.. math:: {}_h x_f^d = R_z(\\psi)^T ({}_w x_f^d - {}_w x_b), \\qquad {}_h \\dot x_f^d = R_z(\\psi)^T ({}_w \\dot x_f^d - {}_w \\dot x_b) \\qquad (1)

uses the *estimated actual* base position / velocity; switched off, the *desired* base motion
(height ``h``, velocity ``xdot^d`` since touchdown) replaces it. *Angular* adjustment (Eq. 2):
``b_x_f^d = bR_h(phi, theta) h_x_f^d`` with the *actual* roll and pitch; switched off, the desired
ones (``phi^d``, 0). Then the analytic IK gives ``q^d`` and ``qd^d = J^{-1} b_xdot_f^d``.

State estimation
----------------
Leg odometry: a stance foot is static, so each stance leg measures the base velocity
``v_i = -W_R_B (J_i qd_i + omega x B_x_i)`` and height ``z_i = -(W_R_B B_x_i)_z + r_foot``. The
estimate predicts with the commanded forces, ``v+ = v + dt (sum_i W_f_i / m - g e_z)``, and blends
the leg measurements weighted by the stance profile ``beta(s_i)`` with time constant ``tau_est``.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax import impedance, kinematics, robot, sim, spatial

FRONT, HIND = 0, 1
#: Pair index of each leg (LF, RF, LH, RH).
LEG_PAIR = np.array([FRONT, FRONT, HIND, HIND])
#: +1 for left legs, -1 for right legs.
LEG_SIDE = np.array([1.0, -1.0, 1.0, -1.0])
#: Indices into the apex state vector ``s = (z, theta, xdot, zdot, thetadot)``.
APEX_NAMES = ("z", "pitch", "vx", "vz", "pitch_rate")
N_APEX = 5
PROFILES = ("half_sine", "bezier")
#: Nominal foot positions in ``H`` relative to the base: 0.10 m inside the hips in x (HyQ's
#: knees then share the vertical load with the HFE joints, raising the vertical force limit from
#: ~680 N to ~920 N per leg at h = 0.6 m), 0.30 m from the sagittal plane.
NOMINAL_FOOT_XY = np.array([[0.2735, 0.30], [0.2735, -0.30], [-0.2735, 0.30], [-0.2735, -0.30]])


def _f32(x):
    return jnp.asarray(x, jnp.float32)


def _dc(cls):
    return jax.tree_util.register_dataclass(dataclasses.dataclass(frozen=True)(cls))


def _check(name, value, lo, hi, lo_open=False, hi_open=False):
    v = np.asarray(value, np.float64)
    bad = np.any(~np.isfinite(v)) or np.any(v < lo) or np.any(v > hi)
    bad = bad or (lo_open and np.any(v <= lo)) or (hi_open and np.any(v >= hi))
    if bad:
        lb = "(" if lo_open else "["
        rb = ")" if hi_open else "]"
        raise ValueError(f"{name} must be finite and in {lb}{lo}, {hi}{rb}, got {v.tolist()}")
    return v


# ----------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------


@_dc
class GaitParams:
    """Timing and geometry of the bound (every number a PyTree leaf).

    Attributes:
      period: gait period ``T`` (s).
      duty: (2,) stance fraction ``d_p`` of the front and hind pairs.
      touchdown_phase: (2,) phase ``phi_p`` of the front and hind touchdowns (apex at phase 0).
      height: nominal base height above the ground ``h`` (m), used for the foot lift and when the
        linear kinematic adjustment is off.
      foot_xy: (4, 2) nominal foot positions in ``H`` relative to the base (m).
      clearance: swing foot lift (m).
      bezier: (n,) Bezier control points of the impulse profile (used when ``profile == 'bezier'``).
      profile: ``'half_sine'`` or ``'bezier'`` (static).
    """

    period: jax.Array
    duty: jax.Array
    touchdown_phase: jax.Array
    height: jax.Array
    foot_xy: jax.Array
    clearance: jax.Array
    bezier: jax.Array
    profile: str = dataclasses.field(default="half_sine", metadata=dict(static=True))

    @staticmethod
    def make(period=0.4, duty=(0.4, 0.4), touchdown_phase=(0.55, 0.05), height=0.6, foot_xy=None,
             clearance=0.08, bezier=(0.0, 0.8, 1.0, 1.0, 0.8, 0.0), profile="half_sine") -> "GaitParams":
        _check("period", period, 0.15, 1.5)
        duty = np.broadcast_to(_check("duty", duty, 0.1, 0.9), (2,))
        td = np.broadcast_to(_check("touchdown_phase", touchdown_phase, 0.0, 1.0, hi_open=True), (2,))
        _check("height", height, 0.4, 0.7)
        fxy = NOMINAL_FOOT_XY if foot_xy is None else np.asarray(foot_xy, np.float64)
        if fxy.shape != (4, 2):
            raise ValueError(f"foot_xy must have shape (4, 2), got {fxy.shape}")
        _check("foot_xy", np.abs(fxy), 0.05, 0.6)
        _check("clearance", clearance, 0.0, 0.2)
        bz = np.atleast_1d(np.asarray(bezier, np.float64))
        if bz.ndim != 1 or bz.shape[0] < 3 or bz[0] != 0 or bz[-1] != 0 or np.any(bz < 0) or bz.max() <= 0:
            raise ValueError(f"bezier must be >= 3 non-negative control points starting and ending at 0, got {bz}")
        if profile not in PROFILES:
            raise ValueError(f"profile must be one of {PROFILES}, got {profile!r}")
        # The apex (phase 0) must fall in a flight phase of both pairs, or the per-cycle reset would
        # move a stance foot.
        for p, name in ((FRONT, "front"), (HIND, "hind")):
            end = td[p] + duty[p]
            if end > 1.0 and not np.isclose(end, 1.0):
                raise ValueError(f"touchdown_phase + duty of the {name} pair must be <= 1 (apex at phase 0 "
                                 f"must be in flight), got {td[p]} + {duty[p]}")
        return GaitParams(_f32(period), _f32(duty), _f32(td), _f32(height), _f32(fxy), _f32(clearance), _f32(bz),
                          profile)

    @property
    def kappa(self):
        """Impulse of the unit profile per unit stance time: ``2/pi`` or ``mean(c)``."""
        return jnp.mean(self.bezier) if self.profile == "bezier" else jnp.asarray(2.0 / math.pi, jnp.float32)


@_dc
class BoundingGains:
    """Feedback gains (all leaves; see the module docstring for the equations).

    Attributes:
      stance, swing: joint impedance in stance and in swing.
      k_height, k_height_rate: impulse scaling per apex height error (1/m) and vertical speed error (s/m), Eq. B4.
      k_pitch, k_pitch_rate: front/hind impulse shift per apex pitch error (1/rad) and pitch-rate error (s/rad).
      k_height_int, k_pitch_int: integral of the apex height / pitch errors (per m, per rad, per cycle), Eq. B4.
      k_speed, k_lateral: ``K_{d,xdot}``, ``K_{d,ydot}`` (N s/m), Eq. B5.  k_speed_int: integral (N s/m per cycle).
      k_yaw_rate: ``K_{d,psi}`` (N m s/rad), Eq. B6.  k_yaw: yaw-angle gain ``K_{p,psi}`` (N m/rad), ours.
      k_roll, k_roll_rate: stance roll PD (N m/rad, N m s/rad).
      k_stance_z, k_stance_zdot: stance height PD on the cycle reference (N/m, N s/m), Eq. B7.
      k_stance_pitch, k_stance_pitch_rate: stance pitch PD on the cycle reference (N m/rad, N m s/rad), Eq. B7.
      k_foot: Raibert foot-placement gain on the velocity error (s), Eq. B8.
      tau_est: leg-odometry blending time constant (s).
    """

    stance: impedance.ImpedanceGains
    swing: impedance.ImpedanceGains
    k_height: jax.Array
    k_height_rate: jax.Array
    k_pitch: jax.Array
    k_pitch_rate: jax.Array
    k_height_int: jax.Array
    k_pitch_int: jax.Array
    k_speed: jax.Array
    k_lateral: jax.Array
    k_speed_int: jax.Array
    k_yaw_rate: jax.Array
    k_yaw: jax.Array
    k_roll: jax.Array
    k_roll_rate: jax.Array
    k_stance_z: jax.Array
    k_stance_zdot: jax.Array
    k_stance_pitch: jax.Array
    k_stance_pitch_rate: jax.Array
    k_foot: jax.Array
    tau_est: jax.Array

    @staticmethod
    def make(stance=None, swing=None, k_height=0.0, k_height_rate=0.0, k_pitch=0.0, k_pitch_rate=0.0,
             k_height_int=0.0, k_pitch_int=0.0, k_speed=0.0, k_lateral=0.0, k_speed_int=0.0, k_yaw_rate=0.0,
             k_yaw=0.0, k_roll=0.0, k_roll_rate=0.0,
             k_stance_z=0.0, k_stance_zdot=0.0, k_stance_pitch=0.0, k_stance_pitch_rate=0.0, k_foot=0.0,
             tau_est=0.01) -> "BoundingGains":
        for name, v, lo, hi in (("k_height", k_height, -50, 50), ("k_height_rate", k_height_rate, -10, 10),
                                ("k_pitch", k_pitch, -20, 20), ("k_pitch_rate", k_pitch_rate, -5, 5),
                                ("k_height_int", k_height_int, 0, 10), ("k_pitch_int", k_pitch_int, 0, 10),
                                ("k_speed", k_speed, 0, 2000), ("k_lateral", k_lateral, 0, 2000),
                                ("k_speed_int", k_speed_int, 0, 500),
                                ("k_yaw_rate", k_yaw_rate, 0, 2000), ("k_yaw", k_yaw, 0, 2000),
                                ("k_roll", k_roll, 0, 5000), ("k_roll_rate", k_roll_rate, 0, 500),
                                ("k_stance_z", k_stance_z, 0, 50000), ("k_stance_zdot", k_stance_zdot, 0, 5000),
                                ("k_stance_pitch", k_stance_pitch, 0, 20000),
                                ("k_stance_pitch_rate", k_stance_pitch_rate, 0, 2000),
                                ("k_foot", k_foot, 0, 0.5)):
            _check(name, v, lo, hi)
        _check("tau_est", tau_est, 0.0, 1.0, lo_open=True)
        stance = stance or impedance.ImpedanceGains.make(kp=(300.0, 150.0, 150.0), kd=(8.0, 6.0, 6.0))
        swing = swing or impedance.ImpedanceGains.make(kp=(300.0, 300.0, 300.0), kd=(8.0, 8.0, 6.0))
        vals = dict(k_height=k_height, k_height_rate=k_height_rate, k_pitch=k_pitch, k_pitch_rate=k_pitch_rate,
                    k_height_int=k_height_int, k_pitch_int=k_pitch_int, k_speed=k_speed, k_lateral=k_lateral,
                    k_speed_int=k_speed_int, k_yaw_rate=k_yaw_rate, k_yaw=k_yaw, k_roll=k_roll, k_roll_rate=k_roll_rate,
                    k_stance_z=k_stance_z, k_stance_zdot=k_stance_zdot, k_stance_pitch=k_stance_pitch,
                    k_stance_pitch_rate=k_stance_pitch_rate, k_foot=k_foot, tau_est=tau_est)
        return BoundingGains(stance=stance, swing=swing, **{k: _f32(v) for k, v in vals.items()})


@_dc
class Switches:
    """On/off switches as 0./1. leaves (so the four ablation combinations share one compiled rollout).

    Attributes:
      kinematic_linear: linear kinematic adjustment, Eq. 1.
      kinematic_angular: angular kinematic adjustment, Eq. 2.
      centrifugal: centrifugal compensation, Eqs. 3-4.
      apex_feedback: all per-cycle (apex-sampled) feedback: impulse scaling Eq. B4, speed control Eq. B5 and the
        foot-placement correction of Eq. B8.
      stance_feedback: the stance height / pitch PD on the cycle reference, Eq. B7.
      (Both off: the open-loop, feed-forward limit cycle.)
    """

    kinematic_linear: jax.Array
    kinematic_angular: jax.Array
    centrifugal: jax.Array
    apex_feedback: jax.Array
    stance_feedback: jax.Array

    @staticmethod
    def make(kinematic_adjustment=True, centrifugal=True, apex_feedback=True, stance_feedback=True,
             kinematic_linear=None, kinematic_angular=None) -> "Switches":
        lin = kinematic_adjustment if kinematic_linear is None else kinematic_linear
        ang = kinematic_adjustment if kinematic_angular is None else kinematic_angular
        return Switches(*(_f32(1.0 if bool(v) else 0.0)
                          for v in (lin, ang, centrifugal, apex_feedback, stance_feedback)))


@_dc
class BoundingCommand:
    """Operator command (per instance under ``vmap``).

    Attributes:
      velocity: (2,) desired forward / lateral speed in ``H`` (m/s).
      yaw_rate: desired yaw rate (rad/s, positive turns left).
      ramp_time: the command ramps linearly from 0 over this time (s).
    """

    velocity: jax.Array
    yaw_rate: jax.Array
    ramp_time: jax.Array

    @staticmethod
    def make(speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0) -> "BoundingCommand":
        _check("speed", speed, -1.5, 1.5)
        _check("lateral_speed", lateral_speed, -0.5, 0.5)
        _check("yaw_rate", yaw_rate, -1.5, 1.5)
        _check("ramp_time", ramp_time, 0.0, 10.0)
        speed = np.asarray(speed, np.float64)
        vel = np.stack(np.broadcast_arrays(speed, np.asarray(lateral_speed, np.float64)), -1)
        return BoundingCommand(_f32(vel), _f32(yaw_rate), _f32(ramp_time))


@_dc
class BoundingParams:
    """Everything the bounding controller needs; a PyTree whose leaves all ``vmap``/``jacfwd``.

    Attributes:
      gait: timing and geometry.
      amplitudes: (4, 3) optimal impulse amplitudes ``a*_i = [a_x, a_y, a_z]`` per leg (N), in ``H``.
      apex_ref: (5,) apex state of the limit cycle ``s* = (z, theta, xdot, zdot, thetadot)``.
      reference: (N, 4) the cycle's ``(z, theta, zdot, thetadot)`` at phases ``k / N`` (Eq. B7).
      gains: feedback gains.  switches: module switches.  command: operator command.
      init_estimate: (4,) initial estimate ``(z, vx, vy, vz)`` of base height and velocity.
      mass: robot mass the estimator assumes (kg).
    """

    gait: GaitParams
    amplitudes: jax.Array
    apex_ref: jax.Array
    reference: jax.Array
    gains: BoundingGains
    switches: Switches
    command: BoundingCommand
    init_estimate: jax.Array
    mass: jax.Array

    def replace(self, **kw) -> "BoundingParams":
        return dataclasses.replace(self, **kw)


def pair_amplitudes(a_front, a_hind) -> jax.Array:
    """(4, 3) per-leg amplitudes from pair values ``[a_x, a_y, a_z]`` (``a_y`` mirrored left/right)."""
    af, ah = jnp.asarray(a_front, jnp.float32), jnp.asarray(a_hind, jnp.float32)
    mirror = jnp.array([1.0, -1.0, 1.0], jnp.float32)
    return jnp.stack([af, af * mirror, ah, ah * mirror])


def impulse_guess(gait: GaitParams, mass: float = robot.TOTAL_MASS, com_x: float = 0.007) -> np.ndarray:
    """Park & Kim's vertical impulse balance (Eq. B2): ``(a_{f,z}, a_{h,z})`` per leg (N)."""
    kappa = float(gait.kappa)
    d = np.asarray(gait.duty, np.float64)
    xf, xh = float(gait.foot_xy[0, 0]), float(gait.foot_xy[2, 0])
    w = mass * robot.GRAVITY / (2.0 * kappa)  # sum_p a_p d_p
    af = w * (com_x - xh) / (xf - xh) / d[FRONT]
    ah = w * (xf - com_x) / (xf - xh) / d[HIND]
    return np.array([af, ah])


#: Default gains that are not part of the generated cycle data (hand-tuned; see docs/bounding.md).
DEFAULT_GAINS = dict(k_foot=0.05, k_lateral=150.0, k_yaw_rate=100.0, k_yaw=200.0, k_roll=600.0, k_roll_rate=60.0,
                     k_stance_z=8000.0, k_stance_zdot=300.0, k_stance_pitch=3000.0, k_stance_pitch_rate=300.0)


def default_params(speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0, kinematic_adjustment=True,
                   centrifugal=True, apex_feedback=True, stance_feedback=True, gait: GaitParams | None = None,
                   cycle_amplitudes=None, cycle_apex=None, reference=None, **gain_overrides) -> BoundingParams:
    """The default bound: the stored limit cycle (:mod:`hyqjax.bounding_defaults`), default gains, the command.

    ``cycle_amplitudes`` (4,) = ``(a_fz, a_hz, a_fx, a_hx)``, ``cycle_apex`` (5,) and ``reference`` (N, 4)
    override the stored cycle. Other keyword arguments override :class:`BoundingGains` fields.
    """
    from hyqjax import bounding_defaults as bdef

    gait = gait or GaitParams.make()
    amp = np.asarray(bdef.CYCLE_AMPLITUDES if cycle_amplitudes is None else cycle_amplitudes, np.float64)
    apex = np.asarray(bdef.CYCLE_APEX if cycle_apex is None else cycle_apex, np.float64)
    ref = np.asarray(bdef.CYCLE_REFERENCE if reference is None else reference, np.float64)
    if amp.shape != (4,):
        raise ValueError(f"cycle_amplitudes must have shape (4,), got {amp.shape}")
    if apex.shape != (N_APEX,):
        raise ValueError(f"cycle_apex must have shape ({N_APEX},), got {apex.shape}")
    if ref.ndim != 2 or ref.shape[1] != 4 or ref.shape[0] < 2 or np.any(~np.isfinite(ref)):
        raise ValueError(f"reference must be a finite (N >= 2, 4) table, got shape {ref.shape}")
    _check("cycle_amplitudes[:2] (vertical)", amp[:2], 0.0, 1500.0)
    _check("cycle_amplitudes[2:] (horizontal)", amp[2:], -500.0, 500.0)
    _check("cycle_apex z", apex[0], 0.35, 0.8)
    gkw = dict(bdef.APEX_GAINS, **DEFAULT_GAINS)
    gkw.update(gain_overrides)
    a = pair_amplitudes([amp[2], 0.0, amp[0]], [amp[3], 0.0, amp[1]])
    return BoundingParams(
        gait=gait, amplitudes=a, apex_ref=_f32(apex), reference=_f32(ref), gains=BoundingGains.make(**gkw),
        switches=Switches.make(kinematic_adjustment, centrifugal, apex_feedback, stance_feedback),
        command=BoundingCommand.make(speed, yaw_rate, lateral_speed, ramp_time),
        init_estimate=_f32([apex[0], apex[2], 0.0, apex[3]]), mass=_f32(robot.TOTAL_MASS))


def cycle_reference(params: BoundingParams, phase):
    """The cycle's ``(z, theta, zdot, thetadot)`` at ``phase`` (periodic linear interpolation of ``params.reference``)."""
    tab = params.reference
    n = tab.shape[0]
    x = jnp.mod(phase, 1.0) * n
    i0 = jnp.floor(x).astype(jnp.int32) % n
    w = x - jnp.floor(x)
    return (1.0 - w) * tab[i0] + w * tab[(i0 + 1) % n]


# ----------------------------------------------------------------------------------------------
# Pure building blocks
# ----------------------------------------------------------------------------------------------


def profile(gait: GaitParams, s: jax.Array) -> jax.Array:
    """Unit impulse profile ``beta(s)`` on ``s in [0, 1]``, 0 outside (Eq. B1)."""
    inside = (s >= 0.0) & (s <= 1.0)
    sc = jnp.clip(s, 0.0, 1.0)
    if gait.profile == "bezier":
        c = gait.bezier
        n = c.shape[0] - 1
        k = jnp.arange(n + 1, dtype=sc.dtype)
        binom = jnp.asarray([math.comb(n, int(i)) for i in range(n + 1)], sc.dtype)
        basis = binom * sc[..., None] ** k * (1.0 - sc[..., None]) ** (n - k)
        val = jnp.sum(basis * c, -1)
    else:
        val = jnp.sin(jnp.pi * sc)
    return jnp.where(inside, val, 0.0)


def leg_phase(gait: GaitParams, t):
    """Per-leg ``(stance, s_stance, s_swing)``: stance flag (4,), stance and swing progress in [0, 1)."""
    phi = jnp.mod(t / gait.period, 1.0)
    td = gait.touchdown_phase[LEG_PAIR]
    duty = gait.duty[LEG_PAIR]
    rel = jnp.mod(phi - td, 1.0)
    stance = rel < duty
    s_st = jnp.where(stance, rel / duty, 0.0)
    s_sw = jnp.where(stance, 0.0, (rel - duty) / (1.0 - duty))
    return stance, s_st, s_sw


def ramped_command(cmd: BoundingCommand, t):
    """Command scaled by ``clip(t / ramp_time, 0, 1)``; returns ``(velocity (2,), yaw_rate, desired yaw offset)``."""
    ramp = jnp.maximum(cmd.ramp_time, 1e-6)
    g = jnp.clip(t / ramp, 0.0, 1.0)
    # Desired yaw: integral of the ramped rate.
    yaw = cmd.yaw_rate * jnp.where(t < ramp, 0.5 * t * t / ramp, t - 0.5 * ramp)
    return cmd.velocity * g, cmd.yaw_rate * g, yaw


def centrifugal_compensation(vx, yaw_rate_des, height, on=1.0):
    """Eqs. 3-4: lateral acceleration ``a_y = xdot psidot^d`` (``|a_cf| = xdot^2 / r``, ``r = xdot / psidot^d``),
    foot offset ``Delta y_f = -h a_y / g`` (outward of the turn, clipped to 0.12 m) and lean
    ``phi^d = atan(Delta y_f / h)``. Returns ``(a_y, dy, phi_lean)``, all zero when ``on == 0``."""
    a_y = on * vx * yaw_rate_des
    dy = jnp.clip(-height * a_y / robot.GRAVITY, -0.12, 0.12)
    return a_y, dy, jnp.arctan(dy / height)


def _rot_z(psi):
    c, s = jnp.cos(psi), jnp.sin(psi)
    z, o = jnp.zeros_like(psi), jnp.ones_like(psi)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def horizontal_to_base(roll, pitch):
    """``hR_b = R_y(theta) R_x(phi)`` (ZYX with the yaw removed): ``h_x = hR_b b_x``."""
    return spatial.rpy_to_rot(jnp.stack([roll, pitch, jnp.zeros_like(roll)]))


def euler_rates(rpy, omega_b):
    """ZYX Euler-angle rates ``(phidot, thetadot, psidot)`` from the body angular velocity."""
    r, p = rpy[0], rpy[1]
    wx, wy, wz = omega_b[0], omega_b[1], omega_b[2]
    cr, sr, cp = jnp.cos(r), jnp.sin(r), jnp.maximum(jnp.cos(p), 1e-3)
    psid = (sr * wy + cr * wz) / cp
    return jnp.stack([wx + jnp.sin(p) * psid, cr * wy - sr * wz, psid])


def _min_jerk(s):
    return s**3 * (10.0 - 15.0 * s + 6.0 * s * s), 30.0 * s * s * (1.0 - s) ** 2


def _solve3(jac, v):
    reg = 1e-4 * jnp.eye(3, dtype=jac.dtype)
    return jnp.linalg.solve(jac + reg, v[..., None])[..., 0]


# ----------------------------------------------------------------------------------------------
# Controller
# ----------------------------------------------------------------------------------------------


@_dc
class BoundingState:
    """Controller state.

    Attributes:
      t_prev: time of the previous tick.  cycle: index of the current gait cycle.
      pos: (3,) estimated base position in the odometry frame ``W`` (x, y reset at each apex; z above ground).
      vel: (3,) estimated base velocity in ``W``.
      foot_td: (4, 3) touchdown (stance) foot position in ``W``.  base_td: (4, 3) base estimate at touchdown.
      liftoff_h: (4, 3) latest stance reference in ``H`` (start of the next swing).
      stance_prev: (4,) stance flags of the previous tick.
      apex: (5,) latest apex sample.  integ: (4,) per-cycle error integrals (:func:`apex_errors`).
      cycle_amp: (4, 3) this cycle's amplitudes (apex feedback, speed).
      apex_vel: (2,) apex sample of the estimated horizontal velocity in ``H``.
      yaw0: yaw at start.  force_w: (3,) sum of last commanded ground forces in ``W`` (estimator input).
    """

    t_prev: jax.Array
    cycle: jax.Array
    pos: jax.Array
    vel: jax.Array
    foot_td: jax.Array
    base_td: jax.Array
    liftoff_h: jax.Array
    stance_prev: jax.Array
    apex: jax.Array
    integ: jax.Array
    cycle_amp: jax.Array
    apex_vel: jax.Array
    yaw0: jax.Array
    force_w: jax.Array


def _imu(obs: sim.Observation):
    w_r_b = spatial.quat_to_rot(obs.quat)
    rpy = spatial.rot_to_rpy(w_r_b)
    rates = euler_rates(rpy, obs.gyro)
    return w_r_b, rpy, rates


INTEGRATOR_LIMIT = np.array([0.5, 0.5, 2.0, 2.0])


def apex_errors(params: BoundingParams, apex: jax.Array, vel_h: jax.Array, v_des: jax.Array) -> jax.Array:
    """Errors integrated per cycle (Eq. B4 integral terms): ``(z* - z_k, theta_k - theta*, xdot^d - xdot_k, ydot^d - ydot_k)``."""
    ref = params.apex_ref
    return jnp.stack([ref[0] - apex[0], apex[1] - ref[1], v_des[0] + ref[2] - vel_h[0], v_des[1] - vel_h[1]])


def _cycle_amplitudes(params: BoundingParams, apex: jax.Array, vel_h: jax.Array, v_des: jax.Array, integ: jax.Array):
    """Eqs. B4-B5: this cycle's (4, 3) amplitudes from the apex sample and the per-cycle error integrals."""
    g, ref = params.gains, params.apex_ref
    on = params.switches.apex_feedback
    alpha = 1.0 + on * (g.k_height * (ref[0] - apex[0]) + g.k_height_rate * (ref[3] - apex[3])
                        + g.k_height_int * integ[0])
    delta = on * (g.k_pitch * (apex[1] - ref[1]) + g.k_pitch_rate * (apex[4] - ref[4]) + g.k_pitch_int * integ[1])
    alpha = jnp.clip(alpha, 0.5, 1.5)
    delta = jnp.clip(delta, -0.5, 0.5)
    scale_z = alpha * jnp.where(LEG_PAIR == FRONT, 1.0 + delta, 1.0 - delta)
    a = params.amplitudes
    ax = a[:, 0] + on * (g.k_speed * (v_des[0] + ref[2] - vel_h[0]) + g.k_speed_int * integ[2])
    ay = a[:, 1] + on * (g.k_lateral * (v_des[1] - vel_h[1]) + g.k_speed_int * integ[3])
    az = a[:, 2] * scale_z
    return jnp.stack([jnp.clip(ax, -400.0, 400.0), jnp.clip(ay, -300.0, 300.0), az], -1)


def _apex_sample(pos, vel, rpy, rates, psi):
    vel_h = _rot_z(psi).T @ vel
    return jnp.stack([pos[2], rpy[1], vel_h[0], vel[2], rates[1]]), vel_h


def bounding_init(params: BoundingParams, obs: sim.Observation) -> BoundingState:
    """Controller state at ``obs.time`` (assumed phase 0, the apex), estimator at ``params.init_estimate``."""
    dt = obs.q.dtype
    _, rpy, rates = _imu(obs)
    est = params.init_estimate.astype(dt)
    pos = jnp.stack([0.0, 0.0, est[0]]).astype(dt)
    vel = est[1:4]
    apex, vel_h = _apex_sample(pos, vel, rpy, rates, rpy[2])
    v_des, _, _ = ramped_command(params.command, obs.time)
    nom = jnp.concatenate([params.gait.foot_xy, jnp.full((4, 1), robot.FOOT_RADIUS - params.gait.height)], -1)
    return BoundingState(
        t_prev=jnp.asarray(obs.time, dt), cycle=jnp.floor(obs.time / params.gait.period + 1e-4).astype(jnp.int32),
        pos=pos, vel=vel, foot_td=jnp.zeros((4, 3), dt), base_td=jnp.zeros((4, 3), dt), liftoff_h=nom.astype(dt),
        stance_prev=jnp.zeros(4, bool), apex=apex, integ=apex_errors(params, apex, vel_h, v_des),
        cycle_amp=_cycle_amplitudes(params, apex, vel_h, v_des, apex_errors(params, apex, vel_h, v_des)),
        apex_vel=vel_h[:2], yaw0=rpy[2], force_w=jnp.zeros(3, dt))


def touchdown_target(params: BoundingParams, v_est, v_err_apex, dy):
    """Touchdown foot positions (4, 2) in ``H``: the neutral point of the stride plus a Raibert correction,

    .. math:: {}_h x_{td} = x_{nom} + \tfrac12 d_p T\, \dot x + k_{fp} (\dot x_k - \dot x^d), \qquad
              {}_h y_{td} = y_{nom} + \tfrac12 d_p T\, \dot y + k_{fp} (\dot y_k - \dot y^d) + \Delta y_f   \qquad (B8)

    ``xdot`` the current velocity estimate in ``H`` (with ``xdot = xdot^d`` the stride is ``D = d_p T xdot^d``,
    Fig. 2), ``xdot_k`` its apex sample minus the cycle's apex speed (so the correction vanishes on the cycle).
    The stance feet sweep
    symmetrically under the hips, so forward speed does not feed the pitch loop.
    """
    gait, g = params.gait, params.gains
    half = 0.5 * gait.duty[LEG_PAIR] * gait.period
    off = half[:, None] * v_est[None, :2] + params.switches.apex_feedback * g.k_foot * v_err_apex[None, :]
    off = jnp.clip(off, -0.15, 0.15)
    return gait.foot_xy + off + jnp.stack([jnp.zeros(4), jnp.full(4, 1.0) * dy], -1)


def foot_references(params: BoundingParams, state: BoundingState, t, rpy, rates, omega_b, stance, s_st, s_sw,
                    v_des, target_xy, dy):
    """Desired foot positions / velocities in ``B`` (4, 3) and the stance references in ``H`` (kinematic adjustment).

    Returns ``(b_x, b_xd, h_x_stance)``.
    """
    gait, sw = params.gait, params.switches
    psi = rpy[2]
    rz = _rot_z(psi)
    lin, ang = sw.kinematic_linear, sw.kinematic_angular
    foot_z = jnp.asarray(robot.FOOT_RADIUS, t.dtype)
    # --- Stance (Eq. 1): foot fixed at foot_td in W; base actual (lin) or desired (1 - lin).
    t_st = s_st * gait.duty[LEG_PAIR] * gait.period  # time since touchdown
    v_des_w = rz @ jnp.concatenate([v_des, jnp.zeros(1, t.dtype)])
    base_des = state.base_td + t_st[:, None] * v_des_w[None, :]
    base_des = base_des.at[:, 2].set(gait.height)
    vel_des = jnp.broadcast_to(v_des_w.at[2].set(0.0), (4, 3))
    base = lin * state.pos[None, :] + (1.0 - lin) * base_des
    base_v = lin * state.vel[None, :] + (1.0 - lin) * vel_des
    r_st_w = state.foot_td - base
    rd_st_w = -base_v
    # --- Swing in H: min-jerk in x, y from lift-off to the touchdown target; z lifts above the ground.
    duty = gait.duty[LEG_PAIR]
    t_sw = (1.0 - duty) * gait.period
    sig, dsig = _min_jerk(s_sw)
    xy = state.liftoff_h[:, :2] + (target_xy - state.liftoff_h[:, :2]) * sig[:, None]
    dxy = (target_xy - state.liftoff_h[:, :2]) * (dsig / t_sw)[:, None]
    base_z = lin * state.pos[2] + (1.0 - lin) * gait.height
    base_vz = lin * state.vel[2]
    lift = gait.clearance * jnp.sin(jnp.pi * s_sw)
    dlift = gait.clearance * jnp.pi * jnp.cos(jnp.pi * s_sw) / t_sw
    z = foot_z + lift - base_z
    dz = dlift - base_vz
    h_sw = jnp.concatenate([xy, z[:, None]], -1)
    hd_sw = jnp.concatenate([dxy, dz[:, None]], -1)
    # H velocity -> W' (yaw-rotating H): r_w = Rz h, rd_w = Rz (hd + psidot e_z x h).
    ez = jnp.array([0.0, 0.0, 1.0], t.dtype)
    r_sw_w = h_sw @ rz.T
    rd_sw_w = (hd_sw + rates[2] * jnp.cross(ez, h_sw)) @ rz.T
    r_w = jnp.where(stance[:, None], r_st_w, r_sw_w)
    rd_w = jnp.where(stance[:, None], rd_st_w, rd_sw_w)
    h_stance = r_st_w @ rz  # stance reference in H (Rz^T r)
    # --- Angular adjustment (Eq. 2): rotate into B with the actual (ang) or desired roll / pitch.
    roll_d = jnp.arctan(dy / gait.height)
    roll = ang * rpy[0] + (1.0 - ang) * roll_d
    pitch = ang * rpy[1]
    w_r_b = rz @ horizontal_to_base(roll, pitch)
    omega = ang * omega_b + (1.0 - ang) * (w_r_b.T @ (rates[2] * ez))
    b_x = r_w @ w_r_b
    b_xd = rd_w @ w_r_b - jnp.cross(omega[None, :], b_x)
    return b_x, b_xd, jnp.where(stance[:, None], h_stance, h_sw)


def bounding_step(params: BoundingParams, state: BoundingState, obs: sim.Observation):
    """One control tick: estimate, apex events, kinematic adjustment, impulses, impedance. Returns (state, tau, info)."""
    gait, gains, sw = params.gait, params.gains, params.switches
    t = obs.time
    dtype = obs.q.dtype
    dt = jnp.maximum(t - state.t_prev, 0.0)
    w_r_b, rpy, rates = _imu(obs)
    psi = rpy[2]
    stance, s_st, s_sw = leg_phase(gait, t)
    beta = profile(gait, jnp.where(stance, s_st, -1.0))

    # ---- State estimation (leg odometry + force-driven prediction).
    b_feet = kinematics.foot_positions(obs.q)
    jac = kinematics.foot_jacobians(obs.q)
    b_vfeet = jnp.einsum("lij,lj->li", jac, obs.qd.reshape(4, 3))
    rel_w = b_feet @ w_r_b.T
    relv_w = (b_vfeet + jnp.cross(obs.gyro[None, :], b_feet)) @ w_r_b.T
    w = beta
    wsum = jnp.sum(w)
    v_meas = -jnp.sum(w[:, None] * relv_w, 0) / jnp.maximum(wsum, 1e-6)
    z_meas = -jnp.sum(w * rel_w[:, 2]) / jnp.maximum(wsum, 1e-6) + robot.FOOT_RADIUS
    grav = jnp.array([0.0, 0.0, robot.GRAVITY], dtype)
    vel_pred = state.vel + dt * (state.force_w / params.mass - grav)
    pos_pred = state.pos + dt * state.vel
    alpha = jnp.clip(wsum * dt / gains.tau_est, 0.0, 1.0)
    vel = vel_pred + alpha * (v_meas - vel_pred)
    pos = pos_pred.at[2].set(pos_pred[2] + alpha * (z_meas - pos_pred[2]))

    # ---- Apex event: new cycle -> sample, impulse scaling, world-frame reset.
    cycle = jnp.floor(t / gait.period + 1e-4).astype(jnp.int32)
    new_cycle = cycle != state.cycle
    v_des, yaw_rate_des, yaw_des_off = ramped_command(params.command, t)
    apex_now, vel_h = _apex_sample(pos, vel, rpy, rates, psi)
    apex = jnp.where(new_cycle, apex_now, state.apex)
    apex_vel = jnp.where(new_cycle, vel_h[:2], state.apex_vel)
    lim = jnp.asarray(INTEGRATOR_LIMIT, dtype)
    integ = jnp.where(new_cycle, jnp.clip(state.integ + apex_errors(params, apex_now, vel_h, v_des), -lim, lim),
                      state.integ)
    cycle_amp = jnp.where(new_cycle, _cycle_amplitudes(params, apex_now, vel_h, v_des, integ), state.cycle_amp)
    shift = jnp.where(new_cycle, jnp.stack([pos[0], pos[1], 0.0]), jnp.zeros(3, dtype))
    pos = pos - shift
    foot_td = state.foot_td - shift
    base_td = state.base_td - shift

    # ---- Centrifugal compensation (Eqs. 3-4).
    vel_h_now = _rot_z(psi).T @ vel
    a_cf, dy, roll_lean = centrifugal_compensation(vel_h_now[0], yaw_rate_des, gait.height, sw.centrifugal)

    # ---- Touchdown events: fix the stance foot in W at the end of its swing (target in H).
    touchdown = stance & ~state.stance_prev
    target_xy = touchdown_target(params, vel_h_now, apex_vel - v_des - jnp.stack([params.apex_ref[2], 0.0]), dy)
    target_h = jnp.concatenate([target_xy, jnp.zeros((4, 1), dtype)], -1)
    rz = _rot_z(psi)
    td_w = pos[None, :] + target_h @ rz.T
    td_w = td_w.at[:, 2].set(robot.FOOT_RADIUS)
    base_now = jnp.broadcast_to(pos, (4, 3))
    base_now = base_now.at[:, 2].set(gait.height)
    foot_td = jnp.where(touchdown[:, None], td_w, foot_td)
    base_td = jnp.where(touchdown[:, None], base_now, base_td)
    state_k = dataclasses.replace(state, pos=pos, vel=vel, foot_td=foot_td, base_td=base_td)

    # ---- Foot references with kinematic adjustment (Eqs. 1-2) -> IK.
    b_x, b_xd, h_ref = foot_references(params, state_k, t, rpy, rates, obs.gyro, stance, s_st, s_sw,
                                       v_des, target_xy, dy)
    q_des = kinematics.inverse_kinematics(b_x).reshape(12)
    q_des = jnp.clip(q_des, robot.Q_MIN + 0.02, robot.Q_MAX - 0.02)
    jac_des = kinematics.foot_jacobians(q_des)
    qd_des = _solve3(jac_des, b_xd).reshape(12)
    qd_des = jnp.clip(qd_des, -robot.VELOCITY_LIMIT, robot.VELOCITY_LIMIT)

    # ---- Impulses (Eqs. B1, B5, B6) and roll PD, in H.
    yaw_des = state.yaw0 + yaw_des_off
    yaw_err = jnp.arctan2(jnp.sin(yaw_des - psi), jnp.cos(yaw_des - psi))
    x_f = gait.foot_xy[:, 0]
    y_f = jnp.abs(gait.foot_xy[:, 1])
    yaw_force = (gains.k_yaw_rate * (yaw_rate_des - rates[2]) + gains.k_yaw * yaw_err) / x_f
    roll_d = roll_lean
    roll_moment = gains.k_roll * (rpy[0] - roll_d) + gains.k_roll_rate * rates[0]
    # Stance PD on the cycle reference (Eq. B7): vertical force for height, horizontal for pitch.
    ref = cycle_reference(params, t / gait.period)
    on_st = sw.stance_feedback
    d_fz = on_st * (gains.k_stance_z * (ref[0] - pos[2]) + gains.k_stance_zdot * (ref[2] - vel[2]))
    d_fx = on_st * (gains.k_stance_pitch * (rpy[1] - ref[1]) + gains.k_stance_pitch_rate * (rates[1] - ref[3]))
    d_fx = d_fx / gait.height
    amp = cycle_amp
    az = amp[:, 2] + 0.5 * jnp.clip(d_fz, -600.0, 600.0) - LEG_SIDE * roll_moment / (2.0 * y_f)
    ax = amp[:, 0] + 0.5 * jnp.clip(d_fx, -500.0, 500.0)
    ay = amp[:, 1] + jnp.clip(yaw_force, -300.0, 300.0) + amp[:, 2] * a_cf / robot.GRAVITY
    f_h = beta[:, None] * jnp.stack([ax, ay, jnp.maximum(az, 0.0)], -1)
    h_r_b = horizontal_to_base(rpy[0], rpy[1])
    f_b = f_h @ h_r_b  # (hR_b^T f)^T
    tau_ff = -jnp.einsum("lij,li->lj", jac, f_b).reshape(12)
    f_w = jnp.sum(f_h @ rz.T, 0)

    # ---- Joint impedance, stance / swing gains.
    st12 = jnp.repeat(stance, 3)
    kp = jnp.where(st12, jnp.tile(gains.stance.kp, 4), jnp.tile(gains.swing.kp, 4))
    kd = jnp.where(st12, jnp.tile(gains.stance.kd, 4), jnp.tile(gains.swing.kd, 4))
    tau = kp * (q_des - obs.q) + kd * (qd_des - obs.qd) + tau_ff
    tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)

    liftoff_h = jnp.where(stance[:, None], h_ref, state.liftoff_h)
    new_state = BoundingState(
        t_prev=jnp.asarray(t, dtype), cycle=cycle, pos=pos, vel=vel, foot_td=foot_td, base_td=base_td,
        liftoff_h=liftoff_h, stance_prev=stance, apex=apex, integ=integ, cycle_amp=cycle_amp, apex_vel=apex_vel,
        yaw0=state.yaw0,
        force_w=f_w)
    info = dict(est_pos=pos, est_vel=vel, vel_h=vel_h_now, apex=apex, new_cycle=new_cycle, stance=stance,
                yaw_des=yaw_des, yaw_rate_des=yaw_rate_des, v_des=v_des, roll_des=roll_d, rpy=rpy,
                rates=rates, force_h=f_h, cycle=cycle)
    return new_state, tau, info


bounding_controller = sim.Controller(bounding_init, bounding_step)
