"""How long a step-down must run for all four feet to reach the lower ground, from the crawl's gait timing.

The crawl (Section II) alternates a body phase of ``t_body`` and a swing of ``t_swing`` per leg, the legs in the
order of ``foot_sequence``, so a leg swings once per cycle ``T_cycle = 4 (t_body + t_swing)``. A swing moves its
foot at most one step ``s = clip(v_f T_cycle, 0, max_step_length)`` forward of where it lifted off
(:func:`hyqjax.crawl.footholds.swing_foothold`; the workspace check only shortens it). The step-down's
*completed* criterion needs every foot on the lower ground past the edge (``x > EDGE_CLEARANCE``;
:func:`hyqjax.studies.stepdown_outcome.outcome`). HyQ starts standing with its front feet ``start_distance``
before the edge, so foot ``i`` starts ``d_i`` behind that line (the standing pose's foot ``x``,
:data:`hyqjax.core.robot.Q_STANDING`) and needs ``k_i = ceil(d_i / s)`` swings. With ``p_i`` its place in the
sequence, its ``k_i``-th swing starts at the earliest at

    t_i = (k_i - 1) T_cycle + p_i (t_body + t_swing) + t_body,

so no run shorter than ``max_i t_i`` (:func:`shortest_duration`) can complete: every one fails with
``feet_not_down``. A run of typical length also needs the last swing (``t_swing``) and, for each of the four
feet stepping down a step of height ``h``, the haptic search below the nominal foothold at ``search_speed``
(``h / search_speed`` each, one after the other): :func:`expected_duration`, below which most runs fail.

Measured on an H100 (1,024 instances per cell, docs/results/stepdown_default_h100/): the completed runs got all
four feet down after 11.8-15.0 s at 16 cm without the reflex and 12.3-23.8 s at 16-24 cm with it, against
``shortest_duration`` 8.9 s and ``expected_duration`` 13.6 s (16 cm) / 15.8 s (24 cm) at the defaults.

NumPy arithmetic only (nothing compiled), so the command line checks ``--duration`` before any compile.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hyqjax.core import robot

#: A foot counts as past the edge beyond this x (m): the completed criterion's margin
#: (:func:`hyqjax.studies.stepdown_outcome.outcome`).
EDGE_CLEARANCE = 0.02


class CrawlTiming(NamedTuple):
    """The crawl parameters that set its pace (:class:`hyqjax.crawl.params.CrawlParams` fields;
    :meth:`from_params` reads them from the declaration or from concrete parameters)."""

    forward_velocity: float
    t_body: float
    t_swing: float
    max_step_length: float
    search_speed: float
    foot_sequence: tuple

    @staticmethod
    def from_params(params=None, **overrides) -> "CrawlTiming":
        """From concrete (unbatched) ``CrawlParams``, or the declared defaults when None; ``overrides`` replace
        fields (e.g. ``forward_velocity``). Imports no JAX program, compiles nothing."""
        from hyqjax.core.params import param_ranges
        from hyqjax.crawl.params import FOOT_SEQUENCES, CrawlParams

        specs = param_ranges(CrawlParams)
        names = ("forward_velocity", "t_body", "t_swing", "max_step_length", "search_speed")
        vals = {k: float(np.asarray(getattr(params, k)) if params is not None else specs[k].default) for k in names}
        seq = (tuple(int(i) for i in np.asarray(params.foot_sequence)) if params is not None
               else FOOT_SEQUENCES["rh-rf-lh-lf"])
        return CrawlTiming(**{**vals, "foot_sequence": seq, **overrides})

    @property
    def cycle(self) -> float:
        return 4.0 * (self.t_body + self.t_swing)

    @property
    def step_length(self) -> float:
        return float(np.clip(self.forward_velocity * self.cycle, 0.0, self.max_step_length))


def standing_feet_x() -> np.ndarray:
    """Foot x in the trunk frame in the standing pose, legs LF, RF, LH, RH (the sagittal forward kinematics of
    :func:`hyqjax.core.kinematics.foot_positions`: the HAA rotation leaves x unchanged)."""
    q = robot.Q_STANDING.reshape(4, 3)
    return robot.B_P_HIP[:, 0] - robot.L_UPPER * np.sin(q[:, 1]) - robot.L_LOWER * np.sin(q[:, 1] + q[:, 2])


def swings_needed(timing: CrawlTiming, start_distance: float) -> np.ndarray:
    """Swings each leg needs to get its foot past the edge (``inf`` if the crawl makes no forward steps)."""
    feet = standing_feet_x()
    x0 = -start_distance - robot.B_P_HIP[0, 0] + feet  # the front hips start start_distance before the edge
    d = np.maximum(EDGE_CLEARANCE - x0, 0.0)
    s = timing.step_length
    if s <= 0:
        return np.where(d > 0, np.inf, 0.0)
    return np.ceil(d / s - 1e-9)


def _last_swing_start(timing: CrawlTiming, start_distance: float) -> float:
    k = swings_needed(timing, start_distance)
    if not np.all(np.isfinite(k)):
        return math.inf
    place = np.argsort(np.asarray(timing.foot_sequence))  # place[leg]: the leg's position in the sequence
    slot = timing.t_body + timing.t_swing
    return float(np.max(np.where(k > 0, (k - 1) * timing.cycle + place * slot + timing.t_body, 0.0)))


def shortest_duration(timing: CrawlTiming, start_distance: float = 0.0) -> float:
    """Simulated time (s) below which no step-down run can complete (module docstring); ``inf`` without forward
    steps."""
    return _last_swing_start(timing, start_distance)


def expected_duration(timing: CrawlTiming, height: float = 0.21, start_distance: float = 0.04) -> float:
    """Simulated time (s) a typical run needs to get all four feet down a step of ``height`` (module docstring):
    the last swing start, its nominal swing and four searches of ``height`` at ``search_speed``."""
    return _last_swing_start(timing, start_distance) + timing.t_swing + 4.0 * max(height, 0.0) / timing.search_speed


def check_duration(duration: float, heights, timing: CrawlTiming, start_distance=(0.0, 0.04),
                   option: str = "--duration") -> str | None:
    """Refuse a duration no run can complete with (``ValueError`` naming ``option`` and the shortest possible one);
    return a one-line warning when it is shorter than a typical run needs at the highest of ``heights``, else None.
    ``start_distance``: the (lowest, highest) start distance of the batch (m)."""
    if timing.step_length <= 0:
        return (f"warning: with forward velocity {timing.forward_velocity:g} m/s the crawl makes no forward steps, so "
                f"every run fails with feet_not_down")
    lo = shortest_duration(timing, start_distance[0])
    if duration < lo:
        raise ValueError(f"{option} must be at least {lo:.1f} s for the step-down to be possible (the hind feet need "
                         f"{int(np.max(swings_needed(timing, start_distance[0])))} steps of {timing.step_length:.2f} m "
                         f"at {timing.cycle:.1f} s per crawl cycle to pass the edge), got {duration:g}")
    h = max(float(x) for x in heights)
    typical = expected_duration(timing, h, start_distance[1])
    if duration < typical:
        return (f"warning: {option} {duration:g} s is shorter than the {typical:.1f} s a typical run needs to bring all "
                f"four feet down a {h:.2f} m step (crawl cycles of {timing.cycle:.1f} s plus four searches at "
                f"{timing.search_speed:g} m/s): expect feet_not_down failures")
    return None


__all__ = ["EDGE_CLEARANCE", "CrawlTiming", "check_duration", "expected_duration", "shortest_duration",
           "standing_feet_x", "swings_needed"]
