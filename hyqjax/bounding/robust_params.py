"""The robust bounding study's coordinates and its stored parameter sets.

:data:`COORDS` declares every coordinate :class:`hyqjax.bounding.robust.RobustSpace` optimises (name, natural step
size ``s_i`` and bounds ``lo_i, hi_i``); :func:`save_params` and :func:`load_params` write and read an optimised set
as JSON (amplitudes of Eq. B1 in N per leg and the feedback gains of
:class:`hyqjax.bounding.params.BoundingGains`, with provenance); :data:`PRESETS`, :func:`preset_path` and
:func:`preset_params` reach the sets shipped with the package (:mod:`hyqjax.presets`). Imported by
:mod:`hyqjax.bounding.robust`, which keeps every name.
"""
from __future__ import annotations

import json
import os

import numpy as np

from hyqjax.bounding.params import BoundingGains, BoundingParams, params_of_values
from hyqjax.core.params import param_ranges
from hyqjax.io import atomic
from hyqjax.presets.registry import BOUND_ALIASES

#: ``(name, scale s_i, lo, hi)``: the four amplitudes (N per leg) and the gains (units of
#: :class:`hyqjax.bounding.params.BoundingGains`). ``lo, hi`` lie inside the declared ranges.
COORDS: tuple = (
    ("a_fz", 40.0, 650.0, 1000.0), ("a_hz", 40.0, 600.0, 950.0), ("a_fx", 40.0, -150.0, 150.0),
    ("a_hx", 40.0, -150.0, 150.0),
    ("k_height", 2.0, -10.0, 20.0), ("k_height_rate", 0.3, -2.0, 2.0), ("k_pitch", 0.5, -2.0, 4.0),
    ("k_pitch_rate", 0.1, -0.5, 0.5), ("k_height_int", 0.5, 0.0, 5.0), ("k_pitch_int", 0.3, 0.0, 3.0),
    ("k_speed", 100.0, 0.0, 1000.0), ("k_speed_int", 50.0, 0.0, 300.0), ("k_lateral", 100.0, 0.0, 800.0),
    ("k_yaw_rate", 100.0, 0.0, 800.0), ("k_yaw", 150.0, 0.0, 1200.0),
    ("k_roll", 300.0, 0.0, 3000.0), ("k_roll_rate", 40.0, 0.0, 400.0),
    ("k_stance_z", 3000.0, 0.0, 30000.0), ("k_stance_zdot", 200.0, 0.0, 2000.0),
    ("k_stance_pitch", 1500.0, 0.0, 15000.0), ("k_stance_pitch_rate", 150.0, 0.0, 1500.0),
    ("k_foot", 0.05, 0.0, 0.3),
)
AMPLITUDE_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx")
FORMAT = "hyqjax.bounding.robust/1"
#: The old names of the shipped parameter sets: aliases of the bounding presets of :mod:`hyqjax.presets`
#: (``hyqjax/presets/<name>.json``; :func:`load_params` takes either name in place of a path). ``robust``: the
#: gradient's parameters of ``experiments.bounding_robust`` on one H100
#: (2026-11-25; ``docs/results/bounding_robust_h100/params_gradient.json``): 10 falls in 4,096 held-out
#: instances against 692 with the paper's gains. ``robust_8s``: CMA-ES's parameters of the same study trained on
#: 8 s rollouts (2026-11-26; ``docs/results/bounding_robust_h100_8s/params_cma_es.json``): 0 falls in the same
#: 4,096 held-out instances (the paper's gains: 708), worst yaw error 3.24 deg.
PRESETS = BOUND_ALIASES


def save_params(path: str | os.PathLike, values: dict, provenance: dict | None = None) -> None:
    """Write optimised parameters (amplitudes and gains by name) as JSON, atomically."""
    known = {c[0] for c in COORDS}
    bad = sorted(set(values) - known)
    if bad:
        raise ValueError(f"unknown parameter {bad[0]!r}: must be one of {sorted(known)}")
    d = dict(format=FORMAT, description="Bounding amplitudes (N per leg, Eq. B1) and feedback gains "
                                        "(hyqjax.bounding.params.BoundingGains) from hyqjax.bounding.robust.",
             amplitudes={k: float(values[k]) for k in AMPLITUDE_NAMES if k in values},
             gains={k: float(v) for k, v in values.items() if k not in AMPLITUDE_NAMES},
             provenance=provenance or {})
    atomic.write_json(str(path), d)


def preset_path(name: str) -> str:
    """The registry file of the parameter set ``name`` (a key of :data:`PRESETS` or a bounding preset of
    :mod:`hyqjax.presets`, shipped or the user's)."""
    from hyqjax.presets import registry as presets

    reg = PRESETS.get(name, name)
    if reg not in presets.names("bound"):
        raise ValueError(f"preset must be one of {sorted(set(PRESETS) | set(presets.names('bound')))}, got {name!r}")
    return presets.get(reg).path


def load_params(path: str | os.PathLike) -> dict:
    """The parameter values of a file written by :func:`save_params` (by name), of a bounding preset file of
    :mod:`hyqjax.presets`, or of the shipped set named ``path`` (a key of :data:`PRESETS` or a bounding preset's
    name, which take precedence over a file of that name); ``ValueError`` naming the file and the bad entry (an
    unknown name, a value outside the declared range, not such a file)."""
    from hyqjax.presets import registry as presets

    if isinstance(path, str) and (path in PRESETS or path in presets.names("bound")):
        path = preset_path(path)
    try:
        with open(path) as f:
            d = json.load(f)
        if d.get("format") == presets.FORMAT and d.get("kind") == "bound":
            d = d["values"]
        elif d.get("format") != FORMAT:
            raise ValueError(f"format is {d.get('format')!r}, expected {FORMAT!r}")
        vals = {k: float(v) for k, v in dict(d["amplitudes"], **d["gains"]).items()}
    except (OSError, KeyError, TypeError, ValueError, AttributeError) as e:
        raise ValueError(f"{path} is not a bounding parameter file: {e}") from None
    known = {c[0] for c in COORDS} | set(param_ranges(BoundingGains))
    for k, v in vals.items():
        if k not in known or not np.isfinite(v):
            raise ValueError(f"{path}: parameter {k!r}={v} is unknown or not finite")
    return vals


def params_from_values(values: dict, **kw) -> BoundingParams:
    """:func:`hyqjax.bounding.params.params_of_values`: :func:`hyqjax.bounding.params.paper_params` (``kw``:
    command, switches) with the stored amplitudes and gains of ``values`` (validated by the parameter classes'
    declared ranges)."""
    return params_of_values(values, **kw)


def preset_params(name: str = "robust", **kw) -> BoundingParams:
    """:func:`params_from_values` of the shipped parameter set ``name`` (:data:`PRESETS` or a bounding preset of
    :mod:`hyqjax.presets`); ``kw`` as for :func:`hyqjax.bounding.params.paper_params` (command, switches)."""
    return params_from_values(load_params(preset_path(name)), **kw)
