"""A remedy against shin strikes when the blind crawl steps down (beyond the paper).

The crawl is blind (Section II): it learns about a step down only when a swing foot searches past its
nominal foothold. Two shin strikes follow from that in the step-down experiment, both on a front leg:

* **the stance foot on the edge**: the front foot that has not stepped down yet stands within a couple of
  centimetres of the edge; the body phase that follows the other front leg's step down loads it while the
  trunk moves forward and down, it slides off the edge and its shin lands on the edge;
* **the searched foothold close to the edge**: the search runs along the normal of the stance feet's plane
  (Eq. 7), which tilts backward as soon as one foot is below, so the foot lands a few centimetres closer to
  the edge than planned and the backward-pointing front shin rests on the edge while the trunk moves over it.

With ``shin_remedy`` on, still using only proprioception, for the front legs (the hind knees point forward,
their shins do not reach the edge):

* **follow-up** (:func:`follow_up`): when a front swing ends deeper than ``deep_search`` below its nominal
  foothold (a step down was found) and the other front leg has not stepped down, that leg swings next: the
  foot near the edge is lifted before a body phase can load it. The rest of the cycle keeps the order; the
  next cycle returns to ``foot_sequence``;
* **forward search** (:func:`search_direction`, with the height reflex on): below the nominal foothold the
  search moves a front foot ``search_forward`` metres forward (along the step) per metre of depth, vertically
  rather than along the tilted normal, so the foothold lands further past the edge; the reflex's squat gives
  the leg the reach this needs. The forward part saturates at ``search_forward_limit`` metres
  (:func:`search_forward_excess`): deeper, the foot searches straight down, so a deep search does not carry the
  foot out of the leg's workspace (off by default). With ``search_forward_lift = w > 0`` the forward search
  also counts ``w`` times the nominal foothold's drop below the lift-off height (:func:`lift_drop_offset`):
  once one front foot is below, the feet plane tilts and the other front leg's nominal foothold lies below its
  lift-off already, so the depth it searches, and its forward offset, shrink (off by default).
"""
from __future__ import annotations

import jax.numpy as jnp

from hyqjax.crawl.params import CrawlParams


def is_front(leg):
    """LF (0) and RF (1) are the front legs."""
    return leg < 2


def _forward_unit(p: CrawlParams, leg, n, step_vec):
    """``(u, on)``: the horizontal unit step direction (the trunk's x when the step is shorter than 1 cm) and
    whether the remedy's forward search applies to ``leg`` (a front leg, remedy and reflex on)."""
    dtype = n.dtype
    fwd = jnp.stack([step_vec[0], step_vec[1], jnp.zeros((), dtype)])
    norm = jnp.linalg.norm(fwd)
    u = jnp.where(norm > 0.01, fwd / jnp.maximum(norm, 1e-9), jnp.array([1.0, 0.0, 0.0], dtype))
    return u, (p.shin_remedy > 0.5) & (p.use_reflex > 0.5) & is_front(leg)


def search_direction(p: CrawlParams, leg, n, step_vec):
    """Direction ``d`` (H0) with the search at depth ``s`` placing the foot at ``foothold - s d``.

    ``d = n`` (the paper) without the remedy or the reflex and for hind legs; for a front leg with both,
    ``d = e_z - search_forward * u`` with ``u`` the horizontal unit step direction (the trunk's x when the step
    is shorter than 1 cm).
    """
    dtype = n.dtype
    u, on = _forward_unit(p, leg, n, step_vec)
    d_remedy = jnp.array([0.0, 0.0, 1.0], dtype) - p.search_forward * u
    return jnp.where(on, d_remedy, n)


def search_forward_unit(p: CrawlParams, leg, n, step_vec):
    """``u`` of :func:`search_direction` where the forward search applies, zero elsewhere (H0, (3,))."""
    u, on = _forward_unit(p, leg, n, step_vec)
    return jnp.where(on, u, jnp.zeros_like(u))


def lift_drop_offset(p: CrawlParams, lift, target):
    """Forward offset (m) of the nominal foothold for its drop below the lift-off height:
    ``min(search_forward * search_forward_lift * max(z_lift - z_target, 0), search_forward_limit)`` (H0's z is
    vertical). The caller applies it along :func:`search_forward_unit`, zero where the remedy's search does not
    apply; it is exactly 0 at ``search_forward_lift = 0``."""
    drop = jnp.maximum(lift[2] - target[2], 0.0)
    return jnp.minimum(p.search_forward * p.search_forward_lift * drop, p.search_forward_limit)


def search_forward_excess(p: CrawlParams, search, left):
    """How far the linear forward search ``search_forward * s`` has gone past ``left`` at depth ``s`` (m; 0
    below it), ``left`` the forward offset still allowed this swing: ``search_forward_limit`` less the foothold's
    :func:`lift_drop_offset`. The swing takes it back along the forward unit, so the forward offset is
    ``min(search_forward * s, left)``; below it the plan is exactly the linear one."""
    return jnp.maximum(p.search_forward * search - left, 0.0)


def partner(leg):
    """The other leg of the same pair: LF <-> RF, LH <-> RH."""
    return jnp.bitwise_xor(leg, 1)


def follow_up(p: CrawlParams, sequence, seq_index, leg, deep_leg, deep):
    """Sequence after ``leg`` (at ``seq_index``) ended its swing: the other front leg next after a step down.

    Returns the ``(4,)`` sequence for the next swing, ``sequence[(seq_index + 1) % 4]``: ``foot_sequence`` at the
    start of a cycle, the current one with the partner swapped forward after a deep front swing.
    """
    mate = partner(leg)
    nxt = (seq_index + 1) % 4
    at = jnp.argmax(sequence == mate)
    swap = (p.shin_remedy > 0.5) & is_front(leg) & deep_leg & ~deep[mate] & (nxt != 0)
    sequence = jnp.where(nxt == 0, jnp.asarray(p.foot_sequence, sequence.dtype), sequence)
    a, b = sequence[nxt], sequence[at]
    swapped = sequence.at[nxt].set(b).at[at].set(a)
    return jnp.where(swap, swapped, sequence)
