"""The phases of a command's wall time, from the process's start to its last write.

A command's printed ``wall ... in all`` line and its ``results.json`` (``phases``) come from one :class:`Clock`:
started when the process started (Linux: ``/proc/self/stat``'s start time against ``CLOCK_BOOTTIME``, so the
interpreter's start and every import count; elsewhere, or when a command is run in-process through
``hyqjax.cli.app.main([...])``, when the command was called). A process keeps its start time through ``exec``:
when hyqjax was imported more than :data:`EXEC_GAP_S` after the process started, the process ran another program
first (a shell that ran other commands, then ``exec``'d this one, e.g. the last command of ``bash -c``), and the
clock starts at hyqjax's import instead, the line saying so. The wall is divided into named phases by
:meth:`Clock.lap`: each lap gives the time since the previous one to a phase, less the parts carved out for
others (a batch run's XLA compile and MuJoCo Warp kernel build out of its simulation). Phases, in order:

=============  =========================================================================================
key            what it holds
=============  =========================================================================================
``startup``    imports and device start-up: the interpreter, hyqjax, JAX and MuJoCo, the device, the
               model, the instances' batch
``kernels``    kernel build (Warp): MuJoCo Warp building (or loading from ``~/.cache/warp``) its kernels
``compile``    XLA compile: tracing, lowering and compiling the programs, or loading them from the cache
``simulation`` simulating, after the compile and the kernel build
``tuning``     ``hyqjax tune``'s search and held-out evaluation, whose compiles and simulations interleave
               (the tuner's own clock, ``results.json``'s ``wall_s``, divides them by method)
``summary``    the outcome tables, ``results.json`` and the console summary
``traces``     what writing ``traces.npz`` held the command up (it is written in a background thread)
``figures``    the PNG figures
=============  =========================================================================================

The sum of the phases is the wall time at the last lap; :meth:`Clock.wall` is read after it, so the printed
wall is never below the sum. Nothing heavy is imported here.
"""
from __future__ import annotations

import os
import sys
import threading
import time

#: Seconds between a process's start and hyqjax's import beyond which the process ran another program before this
#: interpreter (an ``exec``): the interpreter's start and the imports before hyqjax take well under a second.
EXEC_GAP_S = 5.0

#: Phase keys and their labels, in the order they are printed.
LABELS = {"startup": "imports and device start-up", "kernels": "kernel build (Warp)", "compile": "XLA compile",
          "simulation": "simulation", "tuning": "tuning (search, compiles and held-out evaluation)",
          "summary": "summary", "traces": "traces", "figures": "figures"}


def process_age() -> float | None:
    """Seconds since this process started, from ``/proc/self/stat`` (10 ms resolution), or None where that
    cannot be read (not Linux)."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rpartition(")")[2].split()  # after the command name; fields[0] is field 3 (state)
        start = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22, starttime, in ticks since boot
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - start
    except (OSError, ValueError, IndexError, AttributeError):
        return None
    return age if 0.0 <= age < 10 * 86400 else None


class Clock:
    """Wall time since ``t0`` (a ``time.perf_counter`` value) in named phases (:data:`LABELS`).

    ``since``: ``"process"`` when ``t0`` is the process's start, ``"import"`` when it is hyqjax's import in a
    process that ran another program ``before_s`` seconds before it (:meth:`from_process_start`), ``"call"`` when
    it is the command's call."""

    def __init__(self, t0: float | None = None, since: str = "call", before_s: float = 0.0):
        self.t0 = time.perf_counter() if t0 is None else float(t0)
        self.since = since
        self.before_s = float(before_s)
        self.seconds: dict[str, float] = {}
        self._last = self.t0
        self._kernels_last = _kernel_seconds()
        self._lock = threading.Lock()

    @classmethod
    def from_process_start(cls) -> "Clock":
        """A clock started when this process did (or now, where that cannot be read); at hyqjax's import when the
        process ran another program first (more than :data:`EXEC_GAP_S` between the two)."""
        age = process_age()
        now = time.perf_counter()
        if age is None:
            return cls(now, "call")
        started = now - age
        imported = getattr(sys.modules.get("hyqjax"), "_IMPORTED_AT", None)
        if imported is not None and imported - started > EXEC_GAP_S:
            return cls(imported, "import", before_s=imported - started)
        return cls(started, "process")

    def add(self, phase: str, seconds: float) -> None:
        if phase not in LABELS:
            raise ValueError(f"phase must be one of {', '.join(LABELS)}, got {phase!r}")
        with self._lock:
            self.seconds[phase] = self.seconds.get(phase, 0.0) + max(float(seconds), 0.0)

    def lap(self, phase: str, **carved: float) -> float:
        """Give the time since the last lap to ``phase``, less ``carved`` (phase=seconds, each given to its phase,
        never more in all than the lap); returns the lap's seconds. MuJoCo Warp's module loads during the lap
        (:func:`hyqjax.sim.warp_kernels.seconds`) go to ``kernels`` unless ``carved`` names it."""
        now = time.perf_counter()
        k = _kernel_seconds()
        with self._lock:
            dt, self._last = now - self._last, now
            dk, self._kernels_last = k - self._kernels_last, k
        if "kernels" not in carved and dk > 0:
            carved = {"kernels": dk, **carved}
        left = dt
        for name, s in carved.items():
            s = min(max(float(s or 0.0), 0.0), left)
            if s > 0:
                self.add(name, s)
            left -= s
        self.add(phase, left)
        return dt

    def wall(self) -> float:
        """Seconds since ``t0``, now."""
        return time.perf_counter() - self.t0

    def to_dict(self) -> dict:
        """``{"wall_s": ..., "since": ..., "phases": {key: seconds}, "unattributed_s": ...}`` as of now (the JSON
        form, for ``results.json``)."""
        wall = self.wall()
        phases = {k: round(self.seconds[k], 4) for k in LABELS if k in self.seconds}
        out = dict(wall_s=round(wall, 4), since=self.since, phases=phases,
                   unattributed_s=round(max(wall - sum(self.seconds.values()), 0.0), 4))
        if self.since == "import":
            out["process_before_s"] = round(self.before_s, 2)
        return out

    def line(self) -> str:
        """``wall 23.4 s in all (since the process started): imports and device start-up 5.1 s, ...``: the last
        line a command prints."""
        wall = self.wall()
        parts = [f"{LABELS[k]} {self.seconds[k]:.1f} s" for k in LABELS if self.seconds.get(k, 0.0) >= 0.05]
        rest = wall - sum(self.seconds.values())
        if rest >= 0.05:
            parts.append(f"other {rest:.1f} s")
        since = {"process": "since the process started",
                 "import": f"since hyqjax was imported; the process ran another program for {self.before_s:.1f} s "
                           "before"}.get(self.since, "since the command was called")
        return f"wall {wall:.1f} s in all ({since}): " + ", ".join(parts)


def _kernel_seconds() -> float:
    """Seconds of MuJoCo Warp module loads in this process so far (0 before :mod:`hyqjax.sim.warp_kernels` is
    imported: nothing is imported here)."""
    mod = sys.modules.get("hyqjax.sim.warp_kernels")
    return mod.seconds() if mod is not None else 0.0


_CURRENT: Clock | None = None


def start(process: bool) -> Clock:
    """Start the clock of the command about to run: from the process's start (the command line) or from now (a
    command called in-process)."""
    global _CURRENT
    _CURRENT = Clock.from_process_start() if process else Clock()
    return _CURRENT


def current() -> Clock:
    """The running command's clock (one started now, when a command's ``run`` is called without ``main``)."""
    global _CURRENT
    if _CURRENT is None:
        _CURRENT = Clock()
    return _CURRENT
