"""Hand-set crawl configurations of the study scripts (the user-facing names are the registry's,
:mod:`hyqjax.presets`: ``paper``, ``remedy``, ``reach``, ...): one home for the named ``CrawlParams.make`` settings
that the CLI's ``--remedy``,
the reach map (``experiments/reach_map.py``) and the tuning study's hand-set comparison
(``experiments/tune_handset.py``) run.

Every preset is a dict of ``CrawlParams.make`` overrides and a one-line description; none is tuned on data: the
shin remedy (``crawl.remedy``) and its trunk at 80% of the feet plane (``terrain_adaptation``) come from the
narrow-spread remedy study (docs/stepdown.md), the other settings are its options (``remedy_probe``: the probing
step of ``crawl.edge``, its tilt and margin picked among eight settings on 96 CPU runs of the reach map's seed 9494;
``remedy_probe2``: the same with the trunk lower while the front hips are behind the edge, picked among five
lowerings on the same runs and confirmed on 256 runs of seed 9696; docs/stepdown.md, "Finding the edge";
``remedy_probe_deep`` and ``start_probe_deep``: the probe settings of the recommended step-down configuration,
:data:`PROBE_DEEP`, on the remedy crawl and on the tuner's start point).
"""
from __future__ import annotations

from hyqjax.presets import registry as _registry

#: ``--remedy`` (preset ``remedy`` of :mod:`hyqjax.presets`, whose file holds the values): the shin-strike remedy
#: with the trunk at 80% of the feet plane.
REMEDY = _registry.crawl_settings("remedy")

#: The edge probe's settings of the recommended step-down configuration (docs/stepdown.md, "The tilt by the measured
#: depth"): a 10 cm probe, the trunk at 30% of the feet plane and 1 cm lower until the front hips are 10 cm past the
#: edge, at 50% where the first front foot measured the step deeper than 25.5 cm.
PROBE_DEEP = dict(edge_probe=0.1, edge_tilt=0.3, edge_margin=0.1, edge_lowering=0.01, edge_deep=0.255,
                  edge_tilt_deep=0.5)

#: name -> (``CrawlParams.make`` overrides, description).
HAND_SET = {
    "paper_off": (dict(use_reflex=False), "reflex off (the no-reflex baseline)"),
    "default": (dict(), "CrawlParams.make(): the reflex, trunk at 30% of the feet plane"),
    "remedy": (REMEDY, "--remedy: shin remedy, trunk at 80% of the feet plane"),
    "start": (dict(shin_remedy=True), "the tuner's start point: Table I, shin remedy, trunk at 30%"),
    "remedy_fwd_0.10": (dict(REMEDY, search_forward_limit=0.10), "remedy, forward search saturating at 10 cm"),
    "remedy_lower_0.05": (dict(REMEDY, step_down_lowering=0.05), "remedy, trunk 5 cm lower during a step down"),
    "adaptive": (dict(shin_remedy=True, terrain_adaptation=0.3, terrain_adaptation_step=5.0 / 7.0),
                 "shin remedy, trunk at 30% of the feet plane, 80% during a step down"),
    "remedy_all": (dict(REMEDY, search_forward_limit=0.10, step_down_lowering=0.05),
                   "remedy, saturating forward search and lower trunk during a step down"),
    "remedy_probe": (dict(REMEDY, edge_probe=0.1, edge_tilt=0.3, edge_margin=0.1),
                     "remedy, a 10 cm probing step for the edge, trunk at 30% until the front hips pass it"),
    "remedy_probe2": (dict(REMEDY, edge_probe=0.1, edge_tilt=0.3, edge_margin=0.1, edge_lowering=0.01),
                      "remedy_probe with the trunk 1 cm lower until the front hips pass the edge"),
    "remedy_probe_deep": (dict(REMEDY, **PROBE_DEEP),
                          "remedy_probe2, the trunk at 50% while the hips pass an edge measured deeper than 25.5 cm"),
    "start_probe_deep": (dict(shin_remedy=True, **PROBE_DEEP),
                         "the tuner's start point with remedy_probe_deep's probe, gate and depth gate"),
}


def make(name: str):
    """``CrawlParams`` of preset ``name`` (a ``ValueError`` naming the presets for any other name)."""
    if name not in HAND_SET:
        raise ValueError(f"preset must be one of {list(HAND_SET)}, got {name!r}")
    from hyqjax.crawl.params import CrawlParams

    return CrawlParams.make(**HAND_SET[name][0])
