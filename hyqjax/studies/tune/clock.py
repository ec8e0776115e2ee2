"""The clock a tuning method runs against under a wall-clock budget (:mod:`.search`), and the compile charges.

:class:`Clock` counts everything a stand-alone run would pay: wall seconds since it started plus the compile time
charged so far. The compile of each program a method uses is measured once per process (:class:`Charges`: JAX's
compile events added up during the program's first use) and *charged* to every method that uses the program, so
that a method run after another does not profit from its compile. Physics steps are counted next to the seconds
(tangents of forward-mode derivatives included).
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable

import jax


class Clock:
    """Wall seconds since ``start()`` plus the compile time charged so far (:class:`Charges`)."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.charged = 0.0
        self.physics_steps = 0

    def charge(self, seconds: float) -> None:
        self.charged += float(seconds)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0 + self.charged

    def state(self) -> dict:
        return dict(elapsed=self.elapsed(), charged=self.charged, physics_steps=int(self.physics_steps))

    def restore(self, state: dict) -> None:
        """Go on from a stored :meth:`state` (:mod:`.resume`): :meth:`elapsed` continues from its seconds."""
        self.charged, self.physics_steps = float(state["charged"]), int(state["physics_steps"])
        self.t0 = time.perf_counter() - (float(state["elapsed"]) - self.charged)

    @contextlib.contextmanager
    def paused(self):
        """Time inside the block is not counted (a resumed run compiling again what it paid for once)."""
        t = time.perf_counter()
        try:
            yield
        finally:
            self.t0 += time.perf_counter() - t


#: JAX's compile events (tracing, lowering to MLIR, XLA's backend compile) that :class:`Charges` adds up.
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
_TRACKING: list = []


def _on_event(name, secs, **_):
    if name in COMPILE_EVENTS:
        for acc in _TRACKING:
            acc[0] += secs


jax.monitoring.register_event_duration_secs_listener(_on_event)


class Charges:
    """Compile seconds per program name: :meth:`track` adds up JAX's compile events (:data:`COMPILE_EVENTS`;
    tracing of nested functions counts once per level) during a program's first use in this process, so no run
    is spent on measuring; :meth:`one_off` keeps the whole time of a one-off setup (e.g. the gradient's snapshot
    windows: compile and forward run)."""

    def __init__(self, known: dict | None = None):
        self.seconds: dict[str, float] = dict(known or {})

    @contextlib.contextmanager
    def track(self, name: str):
        if name in self.seconds:
            yield
            return
        acc = [0.0]
        _TRACKING.append(acc)
        try:
            yield
        finally:
            _TRACKING.remove(acc)
        self.seconds[name] = acc[0]

    def one_off(self, name: str, fn: Callable):
        t = time.perf_counter()
        out = fn()
        self.seconds.setdefault(name, time.perf_counter() - t)
        return out

