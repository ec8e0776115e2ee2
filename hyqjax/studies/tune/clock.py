"""The clock a tuning method runs against under a wall-clock budget (:mod:`.search`), and the compile charges.

:class:`Clock` counts everything a stand-alone run would pay on a machine that has run MuJoCo Warp before: wall
seconds since it started, less MuJoCo Warp's kernel build in them, plus the compile time charged so far. The
compile of each program a method uses is measured once per process (:class:`Charges`: JAX's compile events added
up during the program's first use) and *charged* to every method that uses the program, so that a method run
after another does not profit from its compile. Physics steps are counted next to the seconds
(tangents of forward-mode derivatives included).
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable

import jax

from hyqjax.sim import warp_kernels


class Clock:
    """Wall seconds since the clock started, less MuJoCo Warp's kernel build in them, plus the compile time charged
    so far (:class:`Charges`).

    The kernel build (:mod:`hyqjax.sim.warp_kernels`: Warp compiling its kernels the first time a module is
    launched on a machine, or loading them from its cache) is a cost of the machine, paid once, not of a method or
    of a budget: counted, a method that runs first on a fresh machine loses up to a minute of its budget to it (56 s
    on an H200) and a method after it nothing. :meth:`kernel_build` counts it apart, and the command's wall line names
    it. ``timer`` and ``kernel_seconds`` (the process's kernel-build seconds so far) are the sources of time."""

    def __init__(self, timer: Callable[[], float] = time.perf_counter,
                 kernel_seconds: Callable[[], float] = warp_kernels.seconds):
        self._timer, self._kernels = timer, kernel_seconds
        self.t0 = timer()
        self.charged = 0.0
        self.physics_steps = 0
        self.kernels_before = 0.0  # kernel-build seconds left out in earlier segments of a resumed run
        self._k0 = kernel_seconds()

    def charge(self, seconds: float) -> None:
        self.charged += float(seconds)

    def kernel_build(self) -> float:
        """Seconds of MuJoCo Warp's kernel build left out of :meth:`elapsed` (all segments of a resumed run)."""
        return self.kernels_before + self._kernels() - self._k0

    def elapsed(self) -> float:
        return self._timer() - self.t0 - (self._kernels() - self._k0) + self.charged

    def state(self) -> dict:
        return dict(elapsed=self.elapsed(), charged=self.charged, physics_steps=int(self.physics_steps),
                    kernel_build=self.kernel_build())

    def restore(self, state: dict) -> None:
        """Go on from a stored :meth:`state` (:mod:`.resume`): :meth:`elapsed` continues from its seconds."""
        self.charged, self.physics_steps = float(state["charged"]), int(state["physics_steps"])
        self.kernels_before, self._k0 = float(state.get("kernel_build", 0.0)), self._kernels()
        self.t0 = self._timer() - (float(state["elapsed"]) - self.charged)

    @contextlib.contextmanager
    def paused(self):
        """Time inside the block is not counted (a resumed run compiling again what it paid for once); a kernel
        build in it (a resumed run's new process building or loading MuJoCo Warp's kernels) is counted in
        :meth:`kernel_build`, as every segment's is, and stays out of :meth:`elapsed`."""
        t, k = self._timer(), self._kernels()
        try:
            yield
        finally:
            built = self._kernels() - k
            self.t0 += self._timer() - t
            self._k0 += built
            self.kernels_before += built


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

