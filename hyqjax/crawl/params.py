"""Parameters of the crawl (Focchi et al. 2017, Section II) as a frozen PyTree."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.control import impedance
from hyqjax.core import robot
from hyqjax.core.params import ParameterError, check_params, is_concrete, param_field, param_ranges, params_dataclass
from hyqjax.reflex import step as reflex

#: Foot sequences (leg indices LF=0, RF=1, LH=2, RH=3). Hind-then-front on each side, the usual crawl.
FOOT_SEQUENCES = {
    "rh-rf-lh-lf": (3, 1, 2, 0),
    "lh-lf-rh-rf": (2, 0, 3, 1),
    "rf-lh-lf-rh": (1, 2, 0, 3),
    "lf-rh-rf-lh": (0, 3, 1, 2),
}

#: Width (rad/s) of the speed band over which a joint's torque along its motion falls to zero
#: (``CrawlParams.joint_speed_limit``).
JOINT_SPEED_BAND = 4.0

#: The trunk-frame CoM offset in the standing pose (m), from the MJCF's masses.
COM_OFFSET_B = np.array([0.00696, 0.0, -0.0426])


def _as_float(v, name: str) -> np.ndarray:
    try:
        return np.asarray(v, np.float64)
    except (TypeError, ValueError) as e:
        raise ParameterError("CrawlParams", name, v, "a number") from e


@params_dataclass
class CrawlParams:
    """Crawl parameters; every field but ``weight_qp`` is a PyTree leaf (vmap/grad reach it), ``foot_sequence``,
    ``use_reflex`` and ``shin_remedy`` included (given per instance as arrays).

    Attributes:
      forward_velocity: desired forward speed ``v_f`` (m/s); the step length is
        ``clip(v_f * T_cycle, 0, max_step_length)`` with ``T_cycle = 4 (t_body + t_swing)``.
      heading_velocity: desired yaw rate ``v_h`` (rad/s); footholds rotate by ``v_h T_cycle``.
      t_body, t_swing: nominal phase durations (s).
      step_height: swing apex along the terrain normal (m).
      max_step_length: bound on the step length (m).
      body_height: trunk height above the mean foot height (m).
      stability_margin: the support triangle is shrunk by this much (m).
      touchdown_force: haptic touchdown threshold on the estimated force along the normal (N).
      search_speed: speed of the searching motion after the nominal swing (m/s).
      max_search_depth: search stops this far below the nominal foothold (m).
      max_leg_extension: HFE-to-foot distance at which the leg counts as at its workspace limit (m).
      terrain_adaptation: 0..1, fraction of the feet plane's roll/pitch the trunk follows (1: the terrain frame).
      max_tilt: bound on the trunk roll/pitch targets (rad).
      mu: friction coefficient assumed by the trunk controller (friction pyramid of the weight distribution).
      k_com, d_com: trunk position stiffness (N/m) and damping (N s/m) of the trunk controller.
      k_rot, d_rot: trunk orientation stiffness (N m/rad) and damping (N m s/rad).
      mass: mass the trunk controller supports (kg).
      foot_sequence: (4,) int leg order.
      use_reflex: 0/1, height reflex on or off.
      shin_remedy: 0/1, the step-down remedy against shin strikes (:mod:`hyqjax.crawl.remedy`).
      search_forward: with the remedy and the reflex, the search moves the foot this far forward per metre
        searched below the nominal foothold (m/m).
      deep_search: a swing that searched deeper than this (m) below its nominal foothold found a step down.
      search_forward_limit: the remedy's forward search saturates at this many metres ahead of the nominal
        foothold (below that depth the foot searches straight down), so a deep search stays inside the leg's
        workspace; the default (1.5 m) is beyond any search (``search_forward * max_search_depth <= 1.2 m``).
      search_forward_lift: share of the nominal foothold's drop below the foot's lift-off height that the
        remedy's forward search also counts (0: only the depth searched below the nominal foothold, the remedy
        as first built; 1: the whole depth below the lift-off). The second front leg's nominal foothold already
        lies on the feet plane that the first one tilted, so without it that leg lands close to the edge.
      step_down_lowering: while a step down is under way (a leg's last swing found one, ``deep_search``), body
        phases hold the trunk this much lower (m): workspace for the legs that still have to reach down.
      terrain_adaptation_step: while a step down is under way, the trunk follows this extra fraction of the tilt
        that ``terrain_adaptation`` leaves (``a + s (1 - a)`` of the feet plane's roll/pitch).
      edge_probe: after a front swing found a step down, the other front leg's next swing is a probing step this
        long (m) at its lift-off height whose touchdown or miss bounds the edge's position, then a full step
        (:mod:`hyqjax.crawl.edge`; 0: off).
      edge_probe_depth: the probe searches at most this far below its lift-off height (m).
      edge_tilt: with the probe on, the share of the feet plane's roll/pitch a body phase follows while a front
        hip stays behind the edge's far bound plus ``edge_margin`` (instead of ``terrain_adaptation``).
      edge_margin: the front hips count as past the edge this far beyond its far bound (m; negative: before it).
      edge_lowering: with the probe on, body phases after which a front hip stays behind the edge's far bound plus
        ``edge_margin`` hold the trunk this much lower (m; :func:`hyqjax.crawl.edge.lowered`; 0: off).
      edge_deep, edge_tilt_deep: where the step the first front foot found is deeper than ``edge_deep`` (its
        measured drop, m; 1: never), the gate's tilt is ``edge_tilt_deep`` instead of ``edge_tilt``.
      velocity_feedforward: 0..1, gain on the joint velocity references ``qd^d = J^-1 xd`` (0: the PD damps
        toward zero velocity).
      joint_margin: joint references are kept this far inside each joint's range (rad), so that the
        impedance holding a leg against its workspace does not press the joint onto its end stop.
      joint_speed_limit: the actuators' velocity limit (rad/s): the torque a joint gets along its motion falls
        linearly from full at this speed to zero :data:`JOINT_SPEED_BAND` above it, so no torque drives a joint
        faster (:func:`hyqjax.crawl.controller.speed_limited_torques`; braking torque is never limited).
      weight_qp: weight distribution by the friction-pyramid QP (True) or least-norm forces clipped into the
        cones (False), :mod:`hyqjax.control.trunk`. Static (PyTree metadata, shared by a batch): the QP's
        fixed-iteration ADMM costs ten times the rest of the controller, and a per-instance switch would run it
        for every instance under ``vmap``.
      gains: joint impedance gains.
      reflex: height reflex parameters (Table I by default).
    """

    forward_velocity: jax.Array = param_field(0.1, -0.3, 0.3, "m/s", "desired forward speed v_f")
    heading_velocity: jax.Array = param_field(0.0, -0.5, 0.5, "rad/s", "desired yaw rate v_h")
    t_body: jax.Array = param_field(0.4, 0.1, 5.0, "s", "nominal body-phase duration")
    t_swing: jax.Array = param_field(0.45, 0.1, 5.0, "s", "nominal swing duration")
    step_height: jax.Array = param_field(0.1, 0.0, 0.25, "m", "swing apex along the terrain normal")
    max_step_length: jax.Array = param_field(0.3, 0.0, 0.4, "m", "bound on the step length")
    body_height: jax.Array = param_field(0.56, 0.3, 0.68, "m", "trunk height above the mean foot height")
    stability_margin: jax.Array = param_field(0.07, 0.0, 0.15, "m", "support triangle shrunk by this much")
    touchdown_force: jax.Array = param_field(30.0, 1.0, 500.0, "N", "haptic touchdown threshold along the normal")
    search_speed: jax.Array = param_field(0.15, 0.01, 1.0, "m/s", "speed of the search after the nominal swing")
    max_search_depth: jax.Array = param_field(0.4, 0.0, 0.6, "m", "search stops this far below the foothold")
    max_leg_extension: jax.Array = param_field(0.678, 0.4, 0.69, "m", "HFE-to-foot distance of the workspace limit")
    terrain_adaptation: jax.Array = param_field(0.3, 0.0, 1.0, "", "fraction of the feet plane's roll/pitch followed")
    max_tilt: jax.Array = param_field(0.35, 0.0, 0.6, "rad", "bound on the trunk roll/pitch targets")
    mu: jax.Array = param_field(0.7, 0.05, 2.0, "", "friction coefficient of the weight distribution")
    k_com: jax.Array = param_field(3000.0, 0.0, 2e4, "N/m", "trunk position stiffness")
    d_com: jax.Array = param_field(600.0, 0.0, 5e3, "N s/m", "trunk position damping")
    k_rot: jax.Array = param_field(1500.0, 0.0, 1e4, "N m/rad", "trunk orientation stiffness")
    d_rot: jax.Array = param_field(150.0, 0.0, 2e3, "N m s/rad", "trunk orientation damping")
    mass: jax.Array = param_field(robot.TOTAL_MASS, 10.0, 300.0, "kg", "mass the trunk controller supports")
    search_forward: jax.Array = param_field(0.5, 0.0, 2.0, "m/m", "forward search per metre searched (remedy)")
    deep_search: jax.Array = param_field(0.05, 0.0, 0.5, "m", "a swing searching deeper found a step down")
    search_forward_limit: jax.Array = param_field(1.5, 0.0, 1.5, "m", "forward search saturates this far ahead")
    search_forward_lift: jax.Array = param_field(0.0, 0.0, 1.0, "", "share of the foothold's drop below lift-off "
                                                 "counted by the forward search")
    step_down_lowering: jax.Array = param_field(0.0, 0.0, 0.2, "m", "trunk lowered while a step down is under way")
    terrain_adaptation_step: jax.Array = param_field(0.0, 0.0, 1.0, "", "extra tilt followed during a step down")
    edge_probe: jax.Array = param_field(0.0, 0.0, 0.2, "m", "probing step of the second front leg after a step "
                                        "down (0: off)")
    edge_probe_depth: jax.Array = param_field(0.04, 0.0, 0.15, "m", "the probe searches this far below its lift-off")
    edge_tilt: jax.Array = param_field(0.3, 0.0, 1.0, "", "feet plane share followed while a front hip is behind "
                                       "the edge (probe on)")
    edge_margin: jax.Array = param_field(0.0, -0.3, 0.3, "m", "front hips past the edge's far bound by this")
    edge_lowering: jax.Array = param_field(0.0, 0.0, 0.1, "m", "trunk lowered while a front hip is behind the "
                                           "edge (probe on)")
    edge_deep: jax.Array = param_field(1.0, 0.0, 1.0, "m", "step depth above which the gate tilts edge_tilt_deep")
    edge_tilt_deep: jax.Array = param_field(0.3, 0.0, 1.0, "", "the gate's tilt on a step deeper than edge_deep")
    velocity_feedforward: jax.Array = param_field(0.0, 0.0, 1.0, "", "gain on the joint velocity references")
    joint_margin: jax.Array = param_field(0.0, 0.0, 0.2, "rad", "joint references kept this far inside the ranges")
    joint_speed_limit: jax.Array = param_field(robot.VELOCITY_LIMIT, 1.0, 1000.0, "rad/s",
                                               "no torque along a joint's motion beyond this speed (+ band)")
    stance_min_force: jax.Array = param_field(0.0, 0.0, 500.0, "N", "a stance foot that pressed since its "
                                              "touchdown and presses less than this along the vertical (a slip) "
                                              "carries no trunk load (0: off)")
    weight_qp: bool = param_field(False, doc="friction-pyramid QP (True) or clipped least norm (False); static",
                                  static=True)
    foot_sequence: jax.Array = dataclasses.field(
        default_factory=lambda: np.asarray(FOOT_SEQUENCES["rh-rf-lh-lf"], np.int32))
    use_reflex: jax.Array = param_field(1.0, 0.0, 1.0, "", "0/1: height reflex on")
    shin_remedy: jax.Array = param_field(0.0, 0.0, 1.0, "", "0/1: the step-down remedy against shin strikes")
    gains: impedance.ImpedanceGains = dataclasses.field(default_factory=impedance.ImpedanceGains.make)
    reflex: reflex.ReflexParams = dataclasses.field(default_factory=reflex.ReflexParams.table1)

    @staticmethod
    def make(forward_velocity=0.1, heading_velocity=0.0, t_body=0.4, t_swing=0.45, step_height=0.1,
             max_step_length=0.3, body_height=0.56, stability_margin=0.07, touchdown_force=30.0,
             search_speed=0.15, max_search_depth=0.4, max_leg_extension=0.678, terrain_adaptation=0.3,
             max_tilt=0.35, mu=0.7, k_com=3000.0, d_com=600.0, k_rot=1500.0, d_rot=150.0, mass=robot.TOTAL_MASS,
             search_forward=0.5, deep_search=0.05, search_forward_limit=1.5, search_forward_lift=0.0,
             step_down_lowering=0.0,
             terrain_adaptation_step=0.0, edge_probe=0.0, edge_probe_depth=0.04, edge_tilt=0.3, edge_margin=0.0,
             edge_lowering=0.0, edge_deep=1.0, edge_tilt_deep=0.3,
             velocity_feedforward=0.0, joint_margin=0.0,
             joint_speed_limit=robot.VELOCITY_LIMIT, stance_min_force=0.0, weight_qp=False,
             foot_sequence="rh-rf-lh-lf", use_reflex=True, shin_remedy=False,
             gains: impedance.ImpedanceGains | None = None,
             reflex_params: reflex.ReflexParams | None = None) -> "CrawlParams":
        """Validated constructor (runs outside jit; errors name the parameter and its declared range): scalar
        leaves as float32, ``foot_sequence`` a name of :data:`FOOT_SEQUENCES` or a permutation of the legs."""
        given = dict(forward_velocity=forward_velocity, heading_velocity=heading_velocity, t_body=t_body,
                     t_swing=t_swing, step_height=step_height, max_step_length=max_step_length,
                     body_height=body_height, stability_margin=stability_margin, touchdown_force=touchdown_force,
                     search_speed=search_speed, max_search_depth=max_search_depth,
                     max_leg_extension=max_leg_extension, terrain_adaptation=terrain_adaptation, max_tilt=max_tilt,
                     mu=mu, k_com=k_com, d_com=d_com, k_rot=k_rot, d_rot=d_rot, mass=mass,
                     search_forward=search_forward, deep_search=deep_search,
                     search_forward_limit=search_forward_limit, search_forward_lift=search_forward_lift,
                     step_down_lowering=step_down_lowering,
                     terrain_adaptation_step=terrain_adaptation_step, edge_probe=edge_probe,
                     edge_probe_depth=edge_probe_depth, edge_tilt=edge_tilt, edge_margin=edge_margin,
                     edge_lowering=edge_lowering, edge_deep=edge_deep, edge_tilt_deep=edge_tilt_deep,
                     velocity_feedforward=velocity_feedforward, joint_margin=joint_margin,
                     joint_speed_limit=joint_speed_limit, stance_min_force=stance_min_force)
        specs = param_ranges(CrawlParams)
        vals = {}
        for name, v in given.items():
            arr = _as_float(v, name)
            if arr.shape != ():
                raise ParameterError("CrawlParams", name, f"array of shape {arr.shape}", "a scalar",
                                     problem="has a wrong shape")
            specs[name].check(arr, "CrawlParams")
            vals[name] = jnp.asarray(np.asarray(arr, np.float32))  # converted in NumPy: no conversion program
        if isinstance(foot_sequence, str):
            if foot_sequence not in FOOT_SEQUENCES:
                raise ParameterError("CrawlParams", "foot_sequence", foot_sequence,
                                     f"one of {sorted(FOOT_SEQUENCES)}", problem="is unknown")
            seq = FOOT_SEQUENCES[foot_sequence]
        else:
            seq = tuple(int(i) for i in foot_sequence)
            if sorted(seq) != [0, 1, 2, 3]:
                raise ParameterError("CrawlParams", "foot_sequence", repr(foot_sequence),
                                     "a permutation of (0, 1, 2, 3)", problem="is not a leg order")
        return CrawlParams(**vals, foot_sequence=jnp.asarray(np.asarray(seq, np.int32)),
                           use_reflex=jnp.asarray(np.asarray(1.0 if use_reflex else 0.0, np.float32)),
                           shin_remedy=jnp.asarray(np.asarray(1.0 if shin_remedy else 0.0, np.float32)),
                           weight_qp=bool(weight_qp),
                           gains=gains or impedance.ImpedanceGains.make(),
                           reflex=reflex_params or reflex.ReflexParams.table1())

    def __post_init__(self):
        """Construction, ``dataclasses.replace`` and :meth:`replace` check the concrete leaves (ranges: by
        :func:`hyqjax.core.params.check_params` after this), the static ``weight_qp`` and the leg order."""
        if not isinstance(self.weight_qp, (bool, np.bool_)):
            raise ParameterError("CrawlParams", "weight_qp", repr(self.weight_qp), "True or False (static)")
        seq = self.foot_sequence
        if is_concrete(seq):
            seq = np.asarray(seq)
            rows = seq.reshape(-1, seq.shape[-1]) if seq.ndim else seq.reshape(1, 1)
            ok = np.all(np.sort(rows, -1) == np.arange(4), -1) if rows.shape[-1] == 4 else np.zeros(len(rows), bool)
            if not ok.all():
                raise ParameterError("CrawlParams", "foot_sequence", repr(tuple(rows[np.argmin(ok)].tolist())),
                                     "a permutation of (0, 1, 2, 3)", problem="is not a leg order")

    def validate(self) -> "CrawlParams":
        """Check every concrete field (every element of batched leaves), the leg order, the gains and the reflex
        parameters; return ``self``. Raises :class:`hyqjax.core.params.ParameterError` naming the parameter and
        its range. Construction and :meth:`replace` run the same checks on this class's own fields."""
        self.__post_init__()
        check_params(self)
        self.gains.validate()
        self.reflex.validate()
        return self

    def replace(self, **kw) -> "CrawlParams":
        """``dataclasses.replace``, validated (construction checks)."""
        return dataclasses.replace(self, **kw)


#: ``CrawlParams.make`` arguments that take a word instead of a number in :func:`parse_settings`.
BOOLEAN_SETTINGS = ("use_reflex", "shin_remedy", "weight_qp")


def parse_settings(text: str, option: str = "--crawl") -> dict:
    """``field=value,...`` (``CrawlParams.make`` arguments: numbers, ``true``/``false`` for
    :data:`BOOLEAN_SETTINGS`, a name of :data:`FOOT_SEQUENCES` for ``foot_sequence``) as keyword arguments; a
    ``ValueError`` naming ``option``, the item and the allowed fields otherwise. The values' ranges are checked by
    ``CrawlParams.make`` itself."""
    import inspect

    fields = [n for n in inspect.signature(CrawlParams.make).parameters if n not in ("gains", "reflex_params")]
    out = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, eq, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not eq or key not in fields:
            raise ValueError(f"{option}: {item!r} is not field=value with a field of CrawlParams.make "
                             f"({', '.join(sorted(fields))})")
        if key in BOOLEAN_SETTINGS:
            if value.lower() not in ("1", "0", "true", "false", "on", "off"):
                raise ValueError(f"{option}: {key} must be true or false, got {value!r}")
            out[key] = value.lower() in ("1", "true", "on")
        elif key == "foot_sequence":
            out[key] = value
        else:
            try:
                out[key] = float(value)
            except ValueError:
                raise ValueError(f"{option}: {key} must be a number, got {value!r}") from None
    return out

