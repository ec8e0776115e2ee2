"""The parameter classes of the bound: gait timing and geometry (:class:`GaitParams`), feedback gains
(:class:`BoundingGains`), module switches (:class:`Switches`), the operator command (:class:`BoundingCommand`) and
all of them with the stored limit cycle (:class:`BoundingParams`), as frozen dataclass PyTrees (every number a leaf,
so ``vmap`` gives each instance its own value and ``jacfwd`` reaches every gain). :mod:`hyqjax.bounding.params`
re-exports them beside the parameter sets it builds.

Ranges, units and shapes are declared once, as field metadata (:func:`hyqjax.core.params.param_field`),
and checked at construction and in ``replace`` on concrete values, batched leaves included (tracers are
skipped; JAX's own rebuilding of the PyTree for gradients or tangents does not validate). A bad value
raises :class:`hyqjax.core.params.ParameterError` (a ``ValueError``), one line naming the field and its
range. The ``make`` constructors add defaults, broadcasting, float32 leaves and the cross-field checks
(shapes, the apex in a flight phase).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.bounding.apex import Apex
from hyqjax.control import impedance
from hyqjax.core import robot
from hyqjax.core.params import ParameterError, param_field, param_ranges, params_dataclass

FRONT, HIND = 0, 1
#: Pair index of each leg (LF, RF, LH, RH).
LEG_PAIR = np.array([FRONT, FRONT, HIND, HIND])
#: +1 for left legs, -1 for right legs.
LEG_SIDE = np.array([1.0, -1.0, 1.0, -1.0])
PROFILES = ("half_sine", "bezier")
#: Nominal foot positions in ``H`` relative to the base: 0.10 m inside the hips in x (HyQ's
#: knees then share the vertical load with the HFE joints, raising the vertical force limit from
#: ~680 N to ~920 N per leg at h = 0.6 m), 0.30 m from the sagittal plane.
NOMINAL_FOOT_XY = np.array([[0.2735, 0.30], [0.2735, -0.30], [-0.2735, 0.30], [-0.2735, -0.30]])


def _f32(x):
    return jnp.asarray(x, jnp.float32)


def check_range(owner, name, value, lo, hi) -> np.ndarray:
    """``value`` as float64 if finite and in ``[lo, hi]``, else :class:`ParameterError` naming ``name``."""
    v = np.asarray(value, np.float64)
    if not (np.all(np.isfinite(v)) and np.all(v >= lo) and np.all(v <= hi)):
        bad = v[~(np.isfinite(v) & (v >= lo) & (v <= hi))].reshape(-1)[0] if v.ndim else float(v)
        raise ParameterError(owner, name, float(bad), f"in [{lo:g}, {hi:g}]")
    return v


def check_field(cls, name, value, as_name=None) -> np.ndarray:
    """``value`` checked against the declared range of ``cls.name`` (reported as ``as_name``)."""
    spec = param_ranges(cls)[name]
    v = np.asarray(value, np.float64)
    if not np.all(spec.in_range(v)):
        bad = v[~spec.in_range(v)].reshape(-1)[0] if v.ndim else float(v)
        raise ParameterError(cls.__name__, as_name or name, float(bad), spec.range_text)
    return v



#: Bezier profiles may have 3 to 32 control points.
_BEZIER_SHAPES = tuple((k,) for k in range(3, 33))
#: Largest |lateral speed| command (m/s); the forward command's range is the velocity field's.
LATERAL_SPEED_LIMIT = 0.5


@params_dataclass
class GaitParams:
    """Timing and geometry of the bound.

    Attributes:
      period: gait period ``T`` (s).  duty: (2,) stance fraction ``d_p`` of the front and hind pairs.
      touchdown_phase: (2,) phase ``phi_p`` of the front and hind touchdowns (apex at phase 0).
      height: nominal base height ``h`` (m), for the foot lift and when the linear adjustment is off.
      foot_xy: (4, 2) nominal foot positions in ``H`` relative to the base (m).
      clearance: swing foot lift (m).
      bezier: (n,) Bezier control points of the impulse profile (``profile == 'bezier'``).
      profile: ``'half_sine'`` or ``'bezier'`` (static).
    """

    period: jax.Array = param_field(0.4, 0.15, 1.5, "s", "gait period T")
    duty: jax.Array = param_field((0.4, 0.4), 0.1, 0.9, "", "stance fraction of the front, hind pair",
                                  shapes=((2,),))
    touchdown_phase: jax.Array = param_field((0.55, 0.05), 0.0, 1.0, "", "touchdown phase of the front, hind pair",
                                             hi_open=True, shapes=((2,),))
    height: jax.Array = param_field(0.6, 0.4, 0.7, "m", "nominal base height")
    foot_xy: jax.Array = param_field(tuple(map(tuple, NOMINAL_FOOT_XY)), -0.6, 0.6, "m",
                                     "nominal foot positions in H relative to the base", shapes=((4, 2),))
    clearance: jax.Array = param_field(0.08, 0.0, 0.2, "m", "swing foot lift")
    bezier: jax.Array = param_field((0.0, 0.8, 1.0, 1.0, 0.8, 0.0), 0.0, 1e6, "", "Bezier control points",
                                    shapes=_BEZIER_SHAPES)
    profile: str = param_field("half_sine", static=True, doc="impulse profile: half_sine or bezier")

    def __post_init__(self):
        if self.profile not in PROFILES:
            raise ParameterError("GaitParams", "profile", self.profile, f"one of {PROFILES}")

    @staticmethod
    def make(period=0.4, duty=(0.4, 0.4), touchdown_phase=(0.55, 0.05), height=0.6, foot_xy=None,
             clearance=0.08, bezier=(0.0, 0.8, 1.0, 1.0, 0.8, 0.0), profile="half_sine") -> "GaitParams":
        """Validated, float32 gait parameters; ``duty`` and ``touchdown_phase`` may be scalars (both pairs)."""
        duty = np.broadcast_to(check_field(GaitParams, "duty", duty), (2,))
        td = np.broadcast_to(check_field(GaitParams, "touchdown_phase", touchdown_phase), (2,))
        fxy = NOMINAL_FOOT_XY if foot_xy is None else np.asarray(foot_xy, np.float64)
        if fxy.shape != (4, 2):
            raise ParameterError("GaitParams", "foot_xy", f"array of shape {fxy.shape}", "of shape (4, 2)",
                                 problem="has a wrong shape")
        check_range("GaitParams", "|foot_xy|", np.abs(fxy), 0.05, 0.6)
        bz = np.atleast_1d(np.asarray(bezier, np.float64))
        if bz.ndim != 1 or bz.shape[0] < 3 or bz[0] != 0 or bz[-1] != 0 or np.any(bz < 0) or bz.max() <= 0:
            raise ParameterError("GaitParams", "bezier", bz,
                                 ">= 3 non-negative control points starting and ending at 0")
        # The apex (phase 0) must fall in a flight phase of both pairs, or the per-cycle reset would
        # move a stance foot.
        for p, name in ((FRONT, "front"), (HIND, "hind")):
            end = td[p] + duty[p]
            if end > 1.0 and not np.isclose(end, 1.0):
                raise ParameterError("GaitParams", "touchdown_phase", float(td[p]),
                                     f"<= 1 - duty of the {name} pair ({1 - duty[p]:g}; the apex at phase 0 "
                                     "must be in flight)")
        check_field(GaitParams, "period", period)
        return GaitParams(_f32(period), _f32(duty), _f32(td), _f32(height), _f32(fxy), _f32(clearance), _f32(bz),
                          profile)

    @property
    def kappa(self):
        """Impulse of the unit profile per unit stance time: ``2/pi`` or ``mean(c)``."""
        return jnp.mean(self.bezier) if self.profile == "bezier" else jnp.asarray(2.0 / math.pi, jnp.float32)


def _stance_gains():
    return impedance.ImpedanceGains.make(kp=(300.0, 150.0, 150.0), kd=(8.0, 6.0, 6.0))


def _swing_gains():
    return impedance.ImpedanceGains.make(kp=(300.0, 300.0, 300.0), kd=(8.0, 8.0, 6.0))


@params_dataclass
class BoundingGains:
    """Feedback gains (equations in :mod:`hyqjax.bounding.controller` and :mod:`hyqjax.bounding.kinematic`).

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

    stance: impedance.ImpedanceGains = dataclasses.field(default_factory=_stance_gains)
    swing: impedance.ImpedanceGains = dataclasses.field(default_factory=_swing_gains)
    k_height: jax.Array = param_field(0.0, -50.0, 50.0, "1/m", "apex impulse scaling per height error (B4)")
    k_height_rate: jax.Array = param_field(0.0, -10.0, 10.0, "s/m", "apex impulse scaling per vertical speed error")
    k_pitch: jax.Array = param_field(0.0, -20.0, 20.0, "1/rad", "front/hind impulse shift per apex pitch error")
    k_pitch_rate: jax.Array = param_field(0.0, -5.0, 5.0, "s/rad", "front/hind shift per apex pitch-rate error")
    k_height_int: jax.Array = param_field(0.0, 0.0, 10.0, "1/m", "integral of the apex height error (B4)")
    k_pitch_int: jax.Array = param_field(0.0, 0.0, 10.0, "1/rad", "integral of the apex pitch error (B4)")
    k_speed: jax.Array = param_field(0.0, 0.0, 2000.0, "N s/m", "forward speed gain K_d,xdot (B5)")
    k_lateral: jax.Array = param_field(0.0, 0.0, 2000.0, "N s/m", "lateral speed gain K_d,ydot (B5)")
    k_speed_int: jax.Array = param_field(0.0, 0.0, 500.0, "N s/m", "integral of the speed errors (B5)")
    k_yaw_rate: jax.Array = param_field(0.0, 0.0, 2000.0, "N m s/rad", "yaw-rate gain K_d,psi (B6)")
    k_yaw: jax.Array = param_field(0.0, 0.0, 2000.0, "N m/rad", "yaw-angle gain K_p,psi (ours, B6)")
    k_roll: jax.Array = param_field(0.0, 0.0, 5000.0, "N m/rad", "stance roll stiffness")
    k_roll_rate: jax.Array = param_field(0.0, 0.0, 500.0, "N m s/rad", "stance roll damping")
    k_stance_z: jax.Array = param_field(0.0, 0.0, 50000.0, "N/m", "stance height stiffness (B7)")
    k_stance_zdot: jax.Array = param_field(0.0, 0.0, 5000.0, "N s/m", "stance height damping (B7)")
    k_stance_pitch: jax.Array = param_field(0.0, 0.0, 20000.0, "N m/rad", "stance pitch stiffness (B7)")
    k_stance_pitch_rate: jax.Array = param_field(0.0, 0.0, 2000.0, "N m s/rad", "stance pitch damping (B7)")
    k_foot: jax.Array = param_field(0.0, 0.0, 0.5, "s", "Raibert foot-placement gain (B8)")
    tau_est: jax.Array = param_field(0.01, 0.0, 1.0, "s", "leg-odometry time constant", lo_open=True)

    @staticmethod
    def make(stance=None, swing=None, **gains) -> "BoundingGains":
        """Validated float32 gains from keyword values (the declared default for an omitted gain) and the default
        stance / swing impedance."""
        specs = param_ranges(BoundingGains)
        unknown = sorted(set(gains) - set(specs))
        if unknown:
            raise ParameterError("BoundingGains", unknown[0], gains[unknown[0]], f"one of {sorted(specs)}")
        vals = {k: gains.get(k, spec.default) for k, spec in specs.items()}
        BoundingGains(**vals)  # range check on the values as given
        return BoundingGains(stance=stance or _stance_gains(), swing=swing or _swing_gains(),
                             **{k: _f32(v) for k, v in vals.items()})


@params_dataclass
class Switches:
    """On/off switches as 0./1. leaves (so the ablation combinations share one compiled rollout).

    Attributes:
      kinematic_linear: linear kinematic adjustment, Eq. 1.  kinematic_angular: angular, Eq. 2.
      centrifugal: centrifugal compensation, Eqs. 3-4.
      apex_feedback: all per-cycle (apex-sampled) feedback: impulse scaling Eq. B4, speed control Eq. B5 and the
        foot-placement correction of Eq. B8.
      stance_feedback: the stance height / pitch PD on the cycle reference, Eq. B7.
      (Both feedbacks off: the open-loop, feed-forward limit cycle.)
    """

    kinematic_linear: jax.Array = param_field(1.0, 0.0, 1.0, "", "linear kinematic adjustment (Eq. 1) on")
    kinematic_angular: jax.Array = param_field(1.0, 0.0, 1.0, "", "angular kinematic adjustment (Eq. 2) on")
    centrifugal: jax.Array = param_field(1.0, 0.0, 1.0, "", "centrifugal compensation (Eqs. 3-4) on")
    apex_feedback: jax.Array = param_field(1.0, 0.0, 1.0, "", "per-cycle feedback (B4, B5, B8) on")
    stance_feedback: jax.Array = param_field(1.0, 0.0, 1.0, "", "stance PD on the cycle reference (B7) on")

    @staticmethod
    def make(kinematic_adjustment=True, centrifugal=True, apex_feedback=True, stance_feedback=True,
             kinematic_linear=None, kinematic_angular=None) -> "Switches":
        lin = kinematic_adjustment if kinematic_linear is None else kinematic_linear
        ang = kinematic_adjustment if kinematic_angular is None else kinematic_angular
        return Switches(*(_f32(1.0 if bool(v) else 0.0)
                          for v in (lin, ang, centrifugal, apex_feedback, stance_feedback)))


@params_dataclass
class BoundingCommand:
    """Operator command (per instance under ``vmap``).

    Attributes:
      velocity: (2,) desired forward / lateral speed in ``H`` (m/s); the lateral one within
        ``LATERAL_SPEED_LIMIT``.
      yaw_rate: desired yaw rate (rad/s, positive turns left).
      ramp_time: the command ramps linearly from 0 over this time (s).
    """

    velocity: jax.Array = param_field((0.0, 0.0), -1.5, 1.5, "m/s", "desired forward, lateral speed in H",
                                      shapes=((2,),))
    yaw_rate: jax.Array = param_field(0.0, -1.5, 1.5, "rad/s", "desired yaw rate (+ turns left)")
    ramp_time: jax.Array = param_field(1.0, 0.0, 10.0, "s", "command ramp time")

    def __post_init__(self):
        v = self.velocity
        if not isinstance(v, (jax.core.Tracer, jax.ShapeDtypeStruct)) and np.shape(v)[-1:] == (2,):
            check_range("BoundingCommand", "lateral_speed", np.asarray(v, np.float64)[..., 1],
                        -LATERAL_SPEED_LIMIT, LATERAL_SPEED_LIMIT)

    @staticmethod
    def make(speed=0.0, yaw_rate=0.0, lateral_speed=0.0, ramp_time=1.0) -> "BoundingCommand":
        """The command from a forward ``speed`` and a ``lateral_speed`` (m/s), validated, float32."""
        speed = check_field(BoundingCommand, "velocity", speed, "speed")
        lateral_speed = check_range("BoundingCommand", "lateral_speed", lateral_speed, -LATERAL_SPEED_LIMIT,
                                    LATERAL_SPEED_LIMIT)
        check_field(BoundingCommand, "yaw_rate", yaw_rate)
        check_field(BoundingCommand, "ramp_time", ramp_time)
        vel = np.stack(np.broadcast_arrays(speed, lateral_speed), -1)
        return BoundingCommand(_f32(vel), _f32(yaw_rate), _f32(ramp_time))


@params_dataclass
class BoundingParams:
    """Everything the bounding controller needs; a PyTree whose leaves all ``vmap``/``jacfwd``.

    Attributes:
      gait: timing and geometry.
      amplitudes: (4, 3) optimal impulse amplitudes ``a*_i = [a_x, a_y, a_z]`` per leg (N), in ``H``.
      apex_ref: apex state ``s*`` of the limit cycle (:class:`Apex`).
      reference: (N, 4) the cycle's ``(z, theta, zdot, thetadot)`` at phases ``k / N`` (Eq. B7).
      gains: feedback gains.  switches: module switches.  command: operator command.
      init_estimate: (4,) initial estimate ``(z, vx, vy, vz)`` of base height and velocity.
      mass: robot mass the estimator assumes (kg).
    """

    gait: GaitParams
    amplitudes: jax.Array
    apex_ref: Apex
    reference: jax.Array
    gains: BoundingGains
    switches: Switches
    command: BoundingCommand
    init_estimate: jax.Array
    mass: jax.Array = param_field(robot.TOTAL_MASS, 10.0, 500.0, "kg", "mass the estimator assumes")
