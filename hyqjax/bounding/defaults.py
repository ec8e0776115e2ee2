"""The stored default limit cycle, kept as data in ``default_cycle.json`` (package data).

A cycle file holds the amplitudes ``(a_fz, a_hz, a_fx, a_hx)`` (N per leg, Eq. B1), the apex state at
phase 0 (:class:`hyqjax.bounding.params.Apex`), the cycle's ``(z, pitch, vz, pitch_rate)`` at phases
``k / N`` (the stance feedback's reference, Eq. B7), the apex feedback gains (Eqs. B4, B5) and the
provenance of the optimisation. ``python -m experiments.bounding_figures optimise --write-cycle PATH``
writes a new one (:func:`save`); copying it over ``hyqjax/bounding/default_cycle.json`` makes it the default.
"""
from __future__ import annotations

import functools
import json
import os
from importlib import resources
from typing import NamedTuple

import numpy as np

from hyqjax.io import atomic

AMPLITUDE_NAMES = ("a_fz", "a_hz", "a_fx", "a_hx")
APEX_FIELDS = ("z", "pitch", "vx", "vz", "pitch_rate")
REFERENCE_COLUMNS = ("z", "pitch", "vz", "pitch_rate")


class StoredCycle(NamedTuple):
    """A limit cycle read from a cycle file (NumPy, float64)."""

    amplitudes: np.ndarray  # (4,) a_fz, a_hz, a_fx, a_hx
    apex: np.ndarray  # (5,) in APEX_FIELDS order
    reference: np.ndarray  # (N, 4) in REFERENCE_COLUMNS order
    apex_gains: dict
    provenance: dict

    def decision_vector(self) -> np.ndarray:
        """``u = (a_fz, a_hz, a_fx, a_hx, z0, zdot0, thetadot0, xdot0)`` (:mod:`hyqjax.bounding.cycle`)."""
        a, s = self.amplitudes, self.apex
        return np.array([a[0], a[1], a[2], a[3], s[0], s[3], s[4], s[2]])


def load(path: str | os.PathLike | None = None) -> StoredCycle:
    """Read a cycle file (default: the packaged ``default_cycle.json``); ``ValueError`` names a missing or bad entry."""
    if path is None:
        text = resources.files("hyqjax.bounding").joinpath("default_cycle.json").read_text()
        where = "default_cycle.json"
    else:
        with open(path) as f:
            text = f.read()
        where = str(path)
    try:
        d = json.loads(text)
        amp = np.array([float(d["amplitudes"][k]) for k in AMPLITUDE_NAMES])
        apex = np.array([float(d["apex"][k]) for k in APEX_FIELDS])
        cols = tuple(d["reference"]["columns"])
        ref = np.asarray(d["reference"]["rows"], np.float64)
        gains = {k: float(v) for k, v in d["apex_gains"].items()}
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where} is not a bounding cycle file: {e!r}") from None
    if cols != REFERENCE_COLUMNS or ref.ndim != 2 or ref.shape[1] != 4 or ref.shape[0] < 2:
        raise ValueError(f"{where}: reference must have columns {REFERENCE_COLUMNS} and >= 2 rows")
    if not (np.all(np.isfinite(amp)) and np.all(np.isfinite(apex)) and np.all(np.isfinite(ref))):
        raise ValueError(f"{where}: the cycle must be finite")
    return StoredCycle(amp, apex, ref, gains, dict(d.get("provenance", {})))


@functools.lru_cache(maxsize=1)
def stored() -> StoredCycle:
    """The packaged default cycle (read once)."""
    return load()


def save(path: str | os.PathLike, u, reference, apex_gains: dict, provenance: dict | None = None) -> None:
    """Write a cycle file from a decision vector ``u`` (8,), its reference table (N, 4) and apex gains."""
    u = np.asarray(u, np.float64)
    apex = [u[4], 0.0, u[7], u[5], u[6]]
    g = lambda x: float(f"{float(x):.7g}")  # noqa: E731
    d = dict(
        description="A bounding limit cycle of hyqjax.bounding (hyqjax.bounding.defaults reads it).",
        amplitudes={k: g(v) for k, v in zip(AMPLITUDE_NAMES, u[:4])},
        apex={k: g(v) for k, v in zip(APEX_FIELDS, apex)},
        reference=dict(columns=list(REFERENCE_COLUMNS), rows=[[g(x) for x in r] for r in np.asarray(reference)]),
        apex_gains={k: float(v) for k, v in apex_gains.items()},
        provenance=provenance or {})
    text = dumps(d)
    atomic.atomic_write(str(path), lambda f: f.write(text.encode()))


def dumps(d: dict) -> str:
    """A cycle file's text: indented JSON with one line per reference row."""
    rows = d["reference"]["rows"]
    text = json.dumps(dict(d, reference=dict(d["reference"], rows="@ROWS@")), indent=1)
    return text.replace('"@ROWS@"', "[\n" + ",\n".join("   " + json.dumps(r) for r in rows) + "\n  ]") + "\n"
