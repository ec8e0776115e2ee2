"""Where the step-down edge is: bounds from the swings that found it and a probing step (beyond the paper).

The blind crawl learns about a step down when a front swing searches past its nominal foothold (``deep_search``).
Where the edge lies is then known only to within a step: the foot stood on the platform at lift-off and found no
ground at its nominal foothold, at the lift-off height. That is 0.3 m, the whole range of start distances that
decides the step down's outcome (docs/notes/stepdown.md, "The start distance decides the wide spread"). This module
keeps bounds ``edge_lo < x_edge < edge_hi`` on the edge's position along ``H0``'s x (the edge taken perpendicular to the
trunk's heading) and narrows them with one probing step.

The rule (``edge_probe = L > 0``; at ``edge_probe = 0`` the crawl's outputs are bitwise those without it):

* **bounds from the step down**: when a front leg's swing ends deep and the other front leg has not stepped down,
  ``edge_lo`` is the rearmost point of the two front feet on the platform (their x less the foot radius: the larger
  of the lift-off and the partner's foot) and ``edge_hi`` the nominal foothold's x plus the foot radius (the foot
  passed it at the lift-off height without touching ground);
* **the probe**: the partner front leg's next swing is a short step ``L`` straight ahead at its lift-off height,
  then a vertical search of at most ``edge_probe_depth``. A touchdown means the platform reaches beyond the probe
  point (``edge_lo`` rises to its x less the foot radius); no ground within the probe depth means it ends before
  (``edge_hi`` falls to the same point). Either way the leg then swings at once from where it is with the normal
  search (:func:`hyqjax.crawl.state.start_swing_phase`): after a touchdown a full step (it lands a step past the
  probe point, beyond the edge's near bound), after a miss a step shortened by the probe (it lands where the
  step from its lift-off would have put it, at least a step less the probe past the edge);
* **the trunk's tilt**: a body phase after which a front hip is still behind ``edge_hi + edge_margin`` has the trunk
  follow ``edge_tilt`` of the feet plane's roll and pitch instead of ``terrain_adaptation`` (a nose kept up while
  the backward-pointing front knees are over the platform); once both front hips pass it, the crawl's own tilt;
* **the trunk's height**: in the same body phases the trunk is ``edge_lowering`` lower (:func:`lowered`).

The bounds live in the current phase's ``H0`` and are carried to the next phase's ``H0`` by leg odometry
(:func:`carry`): the stance feet are fixed in the world, so the new frame's origin moved by their mean displacement
in it. Yaw changes between phases are neglected (a few centimetres over a step down at +-0.1 rad).
"""
from __future__ import annotations

import jax.numpy as jnp

from hyqjax.core import robot
from hyqjax.crawl import remedy
from hyqjax.crawl.params import CrawlParams

#: Bound magnitude (m) standing for "no bound yet": ``edge_hi >= EDGE_UNKNOWN / 2`` means the edge is not known.
EDGE_UNKNOWN = 10.0


def known(edge_hi):
    """Whether a step down has given the edge's bounds."""
    return edge_hi < 0.5 * EDGE_UNKNOWN


def stance_shift(st, feet_new):
    """``(3,)`` mean displacement of ``st``'s stance feet from ``st.feet_h0`` (its ``H0``) to ``feet_new`` (another
    frame's): as they have not moved in the world, how far that frame's origin lies from ``H0``'s, negated."""
    w = st.stance / jnp.sum(st.stance)
    return jnp.sum(w[:, None] * (feet_new - st.feet_h0), 0)


def carry(st, feet_new):
    """``(edge_lo, edge_hi)`` in the ``H0`` of a phase starting with feet ``feet_new`` ``(4, 3)``: the bounds of
    ``st`` (in its ``H0``) shifted by its stance feet's mean displacement along x (:func:`stance_shift`)."""
    shift = stance_shift(st, feet_new)[0]
    on = known(st.edge_hi)
    return jnp.where(on, st.edge_lo + shift, st.edge_lo), jnp.where(on, st.edge_hi + shift, st.edge_hi)


def drop(st, leg, feet_now):
    """How far ``leg``'s foot went down in the world during the swing (m): its height above the stance feet at the
    swing's start (``st.feet_h0``) less the same now (``feet_now``, the current horizontal frame; the stance feet
    have not moved in the world: :func:`stance_shift`)."""
    return st.feet_h0[leg, 2] - feet_now[leg, 2] + stance_shift(st, feet_now)[2]


def after_swing(p: CrawlParams, st, leg, deep_leg, touchdown, feet_now):
    """``(edge_lo, edge_hi, probe_leg, edge_depth)`` after ``leg``'s swing ends (``st``: the swing's state, its
    ``H0``; ``feet_now`` the feet in the current horizontal frame): the bounds, the leg to probe and the step's
    depth (:func:`drop`, measured by the front swing that found it)."""
    mate = remedy.partner(leg)
    r = jnp.asarray(robot.FOOT_RADIUS, st.edge_hi.dtype)
    first = remedy.is_front(leg) & deep_leg & ~st.deep[mate] & ~known(st.edge_hi) & ~st.probing
    lo_first = jnp.maximum(st.feet_h0[leg, 0], st.feet_h0[mate, 0]) - r
    hi_first = st.swing_target[0] + r
    at = st.swing_target[0] - r  # the probe point's bound: the foot searched straight down there
    lo = jnp.where(first, lo_first, jnp.where(st.probing & touchdown, jnp.maximum(st.edge_lo, at), st.edge_lo))
    hi = jnp.where(first, hi_first, jnp.where(st.probing & ~touchdown, jnp.minimum(st.edge_hi, at), st.edge_hi))
    probe_leg = jnp.where(first & (p.edge_probe > 0), mate, jnp.where(st.probing, -1, st.probe_leg))
    depth = jnp.where(first, drop(st, leg, feet_now), st.edge_depth)
    return lo, hi, probe_leg.astype(st.probe_leg.dtype), depth


def probe_swing(p: CrawlParams, st, leg, lift, target, search_dir, search_fwd):
    """``(probing, target, search_dir, search_fwd)`` of a swing of ``leg`` lifting off at ``lift``: the probe
    (``edge_probe`` straight ahead along ``H0``'s x at the lift-off height, searching vertically) where ``leg`` is
    the leg to probe, else the given plan unchanged."""
    dtype = lift.dtype
    probing = (leg == st.probe_leg) & (p.edge_probe > 0)
    ahead = lift + p.edge_probe * jnp.array([1.0, 0.0, 0.0], dtype)
    up = jnp.array([0.0, 0.0, 1.0], dtype)
    return (probing, jnp.where(probing, ahead, target), jnp.where(probing, up, search_dir),
            jnp.where(probing, jnp.zeros_like(search_fwd), search_fwd))


def step_back(p: CrawlParams, touchdown):
    """How much shorter the full step after a probe is: ``edge_probe`` after a miss (the foot lands where the
    step from its lift-off would have put it, at least a step less the probe past the edge), 0 after a touchdown
    (a full step from the probe point)."""
    return jnp.where(touchdown, 0.0, p.edge_probe)


def max_depth(p: CrawlParams, st):
    """The search depth at which the current swing stops: ``edge_probe_depth`` for a probe."""
    return jnp.where(st.probing, p.edge_probe_depth, p.max_search_depth)


def behind(p: CrawlParams, st, h_r_b, delta):
    """Whether the probe is on, the edge known and a front hip at the end of a body phase (trunk displaced by
    ``delta``, tilted by ``h_r_b = hR_b`` at its start, :func:`hyqjax.core.spatial.roll_pitch_to_rot`) is behind
    ``edge_hi + edge_margin`` (``st`` carries the bounds in this phase's ``H0``)."""
    hips = jnp.asarray(robot.B_P_HIP[:2], delta.dtype) @ h_r_b.T
    hip_x = jnp.min(hips[:, 0]) + delta[0]
    return (p.edge_probe > 0) & known(st.edge_hi) & (hip_x < st.edge_hi + p.edge_margin)


def tilt_share(p: CrawlParams, st, adapt, h_r_b, delta):
    """Share of the feet plane's tilt a body phase follows: ``edge_tilt`` while a front hip is behind the edge
    (:func:`behind`; ``edge_tilt_deep`` where the measured step is deeper than ``edge_deep``), ``adapt``
    otherwise."""
    tilt = jnp.where(st.edge_depth > p.edge_deep, p.edge_tilt_deep, p.edge_tilt)
    return jnp.where(behind(p, st, h_r_b, delta), tilt, adapt)


def lowered(p: CrawlParams, st, h_r_b, delta):
    """The body phase's trunk displacement ``delta`` with the trunk ``edge_lowering`` lower while a front hip is
    behind the edge (:func:`behind`): the legs of a trunk held near level over the step (``edge_tilt``) stand
    stretched down it, and the lower trunk gives them range. ``delta`` itself where the hips are past and at
    ``edge_lowering = 0``."""
    return jnp.where(behind(p, st, h_r_b, delta), delta.at[2].add(-p.edge_lowering), delta)
