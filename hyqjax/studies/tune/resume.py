"""A run of the equal-wall-clock study (:mod:`.wallclock`) stored in the middle of its budget, so that a study cut
off by a kill or by the end of a segment (``--segment-minutes``) resumes the run where it was instead of from its
start.

What a method's run is at an iteration boundary, and all that is stored:

* its :class:`.clock.Clock` (seconds elapsed, compile charged, physics steps);
* its :class:`.trace.Trace` (checkpoints passed with their iterates, the log, the iterate it would return) and
  :class:`.selection.Selection` (the validations, the selected iterate);
* the method's own state: the ``evosax`` strategy's state and random key, or random search's generator state and
  incumbent, or the gradient's iterate and Adam state, and the hybrid's phase.

Resuming restores all of it exactly (arrays bit for bit, the generator's state, the key), so a resumed run takes
the same iterates as an uninterrupted one given the same evaluations. Its clock goes on from the stored seconds:
the work done after the last checkpoint file and before the kill is lost and done again, uncounted; compiling the
programs again in the new process runs with the clock paused (:meth:`.clock.Clock.paused`), since the run paid
its compile once already.

The file, ``DIR/partial/<method>__<dim>.json``, is written atomically (:func:`hyqjax.io.atomic.atomic_write`)
every ``every_s`` seconds of the run and at a segment's end, with a SHA-256 of its payload and the study's
configuration: a file that is unreadable, altered or of another configuration is reported in one line and the run
starts over. It is removed when the run finishes (the run is then in ``results.json``).

Arrays are stored as their raw bytes (base64) with dtype and shape, and non-finite floats as tagged strings, so
that every value comes back exactly, ``inf`` and ``nan`` included.
"""
from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import time

import jax
import numpy as np

from hyqjax.io.atomic import atomic_write

FORMAT = 1


class Paused(Exception):
    """The segment ended: the run's state is stored and the same command resumes it."""


def pack(o):
    """``o`` (dicts, lists, tuples, NumPy and JAX arrays, floats) as JSON values that :func:`unpack` restores exactly."""
    if isinstance(o, dict):
        return {str(k): pack(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [pack(v) for v in o]
    if isinstance(o, np.generic):
        return pack(o.item())
    if isinstance(o, (np.ndarray, jax.Array)):
        a = np.asarray(o)  # tobytes() is C order; ascontiguousarray would make a 0-d array 1-d
        return {"__array__": a.dtype.str, "shape": list(a.shape), "data": base64.b64encode(a.tobytes()).decode()}
    if isinstance(o, float) and not math.isfinite(o):
        return {"__float__": repr(o)}
    return o


def unpack(o):
    """The inverse of :func:`pack` (arrays come back as NumPy arrays, tuples as lists)."""
    if isinstance(o, dict):
        if "__array__" in o:
            raw = base64.b64decode(o["data"])
            return np.frombuffer(raw, np.dtype(o["__array__"])).reshape(o["shape"]).copy()
        if "__float__" in o:
            return float(o["__float__"])
        return {k: unpack(v) for k, v in o.items()}
    if isinstance(o, list):
        return [unpack(v) for v in o]
    return o


def tree_like(template, leaves: list):
    """A PyTree of ``template``'s structure with ``leaves`` (``jax.tree.leaves`` of a stored state, through
    :func:`pack` / :func:`unpack`), each leaf checked against the template's dtype and shape."""
    ref, treedef = jax.tree.flatten(template)
    if len(ref) != len(leaves):
        raise ValueError(f"stored state has {len(leaves)} leaves, this method's has {len(ref)}")
    out = []
    for r, x in zip(ref, leaves):
        x = np.asarray(x)
        if x.shape != np.shape(r) or x.dtype != np.asarray(r).dtype:
            raise ValueError(f"stored leaf {x.dtype}{list(x.shape)} differs from {np.asarray(r).dtype}{list(np.shape(r))}")
        out.append(jax.numpy.asarray(x))
    return jax.tree.unflatten(treedef, out)


def segment_over(segment_s: float | None, t_start: float) -> bool:
    """Whether a segment of ``segment_s`` seconds of the process (None: no segment end), counted from the
    ``time.perf_counter()`` reading ``t_start``, is over (``--segment-minutes``)."""
    return segment_s is not None and time.perf_counter() - t_start >= segment_s


class RunCheckpoint:
    """The stored mid-budget state of one run (module docstring).

    ``every_s``: seconds of the process between two stores; ``segment_s``: seconds of the process after which the
    run stores its state and stops (:class:`Paused`; None: no segment end). Both are counted from this object's
    creation, and neither changes what the run computes."""

    def __init__(self, out_dir: str, key: str, fingerprint: dict, every_s: float = 30.0,
                 segment_s: float | None = None, log=print, t_start: float | None = None):
        self.path = os.path.join(out_dir, "partial", key.replace("/", "__") + ".json")
        self.key, self.fingerprint, self.every_s, self.segment_s, self.log = key, fingerprint, every_s, segment_s, log
        self.t_start = time.perf_counter() if t_start is None else t_start
        self._t_saved = time.perf_counter()

    def load(self) -> dict | None:
        """The stored state, or None (no file; or one unreadable, altered or of another run: reported, ignored)."""
        if not os.path.exists(self.path):
            return None
        try:
            with open(self.path) as f:
                doc = json.load(f)
            payload = doc["payload"]
            if hashlib.sha256(payload.encode()).hexdigest() != doc["sha256"]:
                raise ValueError("its checksum does not match")
            state = json.loads(payload)
            if state.get("format") != FORMAT or state.get("key") != self.key:
                raise ValueError("it is of another format or run")
            if state.get("fingerprint") != json.loads(json.dumps(self.fingerprint)):
                raise ValueError("it is of another configuration")
        except (OSError, ValueError, KeyError, TypeError) as e:
            self.log(f"  {self.key}: ignoring the stored mid-budget state {self.path} ({e}); the run starts over")
            return None
        return unpack(state["state"])

    def due(self) -> bool:
        now = time.perf_counter()
        return now - self._t_saved >= self.every_s or self.segment_over()

    def segment_over(self) -> bool:
        return segment_over(self.segment_s, self.t_start)

    def save(self, state: dict) -> None:
        payload = json.dumps(dict(format=FORMAT, key=self.key, fingerprint=self.fingerprint, state=pack(state)),
                             allow_nan=False)
        text = json.dumps(dict(sha256=hashlib.sha256(payload.encode()).hexdigest(), payload=payload)).encode()
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        atomic_write(self.path, lambda f: f.write(text))
        self._t_saved = time.perf_counter()

    def remove(self) -> None:
        if os.path.exists(self.path):
            os.remove(self.path)
