"""Parameters of the crawl (Focchi et al. 2017, Section II) as a frozen PyTree."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.control import impedance
from hyqjax.core import robot
from hyqjax.reflex import step as reflex

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
    """Crawl parameters; every field is a PyTree leaf (vmap/grad reach it), ``foot_sequence``, ``use_reflex``
    and ``shin_remedy`` included (given per instance as arrays).

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
      velocity_feedforward: 0..1, gain on the joint velocity references ``qd^d = J^-1 xd`` (0: the PD damps
        toward zero velocity).
      joint_margin: joint references are kept this far inside each joint's range (rad), so that the
        impedance holding a leg against its workspace does not press the joint onto its end stop.
      weight_qp: 0/1, weight distribution by the friction-pyramid QP (1) or least-norm forces clipped into the
        cones (0), :mod:`hyqjax.control.trunk`.
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
    search_forward: jax.Array
    deep_search: jax.Array
    velocity_feedforward: jax.Array
    joint_margin: jax.Array
    weight_qp: jax.Array
    foot_sequence: jax.Array
    use_reflex: jax.Array
    shin_remedy: jax.Array
    gains: impedance.ImpedanceGains
    reflex: reflex.ReflexParams

    @staticmethod
    def make(forward_velocity=0.1, heading_velocity=0.0, t_body=0.4, t_swing=0.45, step_height=0.1,
             max_step_length=0.3, body_height=0.56, stability_margin=0.07, touchdown_force=30.0,
             search_speed=0.15, max_search_depth=0.4, max_leg_extension=0.678, terrain_adaptation=0.3,
             max_tilt=0.35, mu=0.7, k_com=3000.0, d_com=600.0, k_rot=1500.0, d_rot=150.0, mass=robot.TOTAL_MASS,
             search_forward=0.5, deep_search=0.05, velocity_feedforward=0.0, joint_margin=0.0, weight_qp=False, foot_sequence="rh-rf-lh-lf", use_reflex=True,
             shin_remedy=False, gains: impedance.ImpedanceGains | None = None,
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
            "search_forward": (search_forward, 0.0, 2.0),
            "deep_search": (deep_search, 0.0, 0.5),
            "velocity_feedforward": (velocity_feedforward, 0.0, 1.0),
            "joint_margin": (joint_margin, 0.0, 0.2),
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
                           shin_remedy=jnp.asarray(1.0 if shin_remedy else 0.0, jnp.float32),
                           weight_qp=jnp.asarray(1.0 if weight_qp else 0.0, jnp.float32),
                           gains=gains or impedance.ImpedanceGains.make(),
                           reflex=reflex_params or reflex.ReflexParams.table1())

    def replace(self, **kw) -> "CrawlParams":
        return dataclasses.replace(self, **kw)
