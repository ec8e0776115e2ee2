"""The compile phase of the batch runners: programs compiled ahead of time, timed and announced.

:class:`AheadOfTime` compiles each program once per shape (``jit(...).lower(...).compile()``), so compiling and
simulating are timed apart (``last_timing``), and announces the phase to the listeners of
:func:`compile_listener` (the command line's :data:`COMPILE_LABEL` line with its elapsed time).
:func:`compile_lowered` tells a program JAX loaded from its persistent compilation cache from one XLA compiled
(``jax.monitoring``'s cache-hit event), so the command line says "compiling" only for a real compile. Both
runners build on it: :class:`hyqjax.sim.runner.BatchRunner` (MJX) and the C MuJoCo backend's runner.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import threading
import time
from typing import Any, Callable

import jax

#: Label of the compile phase, as the command line shows it.
COMPILE_LABEL = "compiling (first run of this shape; cached afterwards)"

_LISTENERS: list = []


@contextlib.contextmanager
def compile_listener(listener: Callable[[str, dict], None]):
    """While the context is open, every batch runner that compiles calls ``listener(event, info)``:
    ``("start", {"batch": size})`` before it traces its first program of a call (a program already compiled in this
    process is neither traced nor announced); ``("compile", {"program": name})`` before XLA compiles a traced
    program or loads it from the persistent compilation cache, and ``("compiled", {"program": name, "from_cache":
    bool})`` after; ``("end", {"batch": size, "seconds": s, "from_cache": bool})`` once its programs are ready
    (``from_cache``: every program of the phase was loaded from the persistent cache, none compiled); and
    ``("done", last_timing)`` after every run (:attr:`hyqjax.sim.runner.BatchRunner.last_timing`)."""
    _LISTENERS.append(listener)
    try:
        yield listener
    finally:
        _LISTENERS.remove(listener)


def notify(event: str, **info) -> None:
    for fn in list(_LISTENERS):
        fn(event, info)


_cache_hits = threading.local()
_monitoring_installed = False


def _count_cache_hit(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":  # fired in the thread that asked for the program
        _cache_hits.n = getattr(_cache_hits, "n", 0) + 1


def compile_lowered(lowered, compiler_options: dict | None = None) -> tuple[Any, bool]:
    """``(executable, from_cache)``: ``lowered.compile(compiler_options)`` (XLA options added to those of the jit,
    None: none), and whether JAX loaded the program from its persistent compilation cache instead of compiling it
    (``jax.monitoring``'s ``/jax/compilation_cache/cache_hits`` event, fired in this thread while it compiles)."""
    global _monitoring_installed
    if not _monitoring_installed:
        jax.monitoring.register_event_listener(_count_cache_hit)
        _monitoring_installed = True
    before = getattr(_cache_hits, "n", 0)
    exe = lowered.compile(compiler_options=dict(compiler_options) if compiler_options else None)
    return exe, getattr(_cache_hits, "n", 0) > before


_COUNT_LOCK = threading.Lock()


@functools.cache
def _background() -> concurrent.futures.ThreadPoolExecutor:
    """The one thread in which :meth:`AheadOfTime._executable_in_background` compiles (made on first use)."""
    return concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="hyqjax-compile")


class AheadOfTime:
    """The compile phase of a batch runner: programs compiled ahead of time (``jit(...).lower(...).compile()``),
    once per shape, kept in ``_executables``; the phase announced to :func:`compile_listener` and timed into
    ``last_timing`` (``compile_s``, ``trace_s``; ``compiled`` and ``from_cache``: programs XLA compiled and
    programs loaded from the persistent cache). Shared by :class:`hyqjax.sim.runner.BatchRunner` and the C MuJoCo
    backend's runner.

    ``compiler_options``: XLA options for every program the runner compiles from then on, added to its own and to the
    process's ``XLA_FLAGS`` (None: none), e.g. ``{"xla_backend_optimization_level": 0}``: LLVM at level 0 compiles a
    program faster and runs it slower than XLA's default (level 2). The code generated differs, and results with it in
    their last bits (an MJX-JAX step-down: 3e-6 m in the positions after 300 ticks), which a long closed-loop run
    amplifies (the same step-down's final state after 24 s differs visibly; its outcome did not)."""

    compiler_options: dict | None = None

    def _reset_compile_phase(self) -> None:
        self._compile_t0 = None  # a compile phase left open by a failed call does not carry over
        self._phase_compiled = 0

    def _executable(self, name: str, fn, args: tuple, static: tuple = (), batch: int | None = None):
        """The compiled ``fn`` for the shapes of ``args`` (compiled ahead of time on first use; opens the compile
        phase, see :meth:`_end_compile_phase`)."""
        key, exe = self._cached(name, args, static)
        if exe is None:
            exe = self._compile(key, name, self._lower(name, fn, args, static, batch))
        return exe

    def _executable_in_background(self, name: str, fn, args: tuple, static: tuple = (), batch: int | None = None):
        """``(get, out_info)``: :meth:`_executable` with XLA's compile in a background thread. ``fn`` is traced and
        lowered now; ``get()`` waits for the compiled program; ``out_info`` is the shapes and types of its outputs
        (``jax.ShapeDtypeStruct``), for which the phase's next program can be traced and lowered while XLA compiles
        this one (XLA releases the GIL; tracing is Python)."""
        key, exe = self._cached(name, args, static)
        if exe is not None:
            return (lambda: exe), exe.out_info
        lowered = self._lower(name, fn, args, static, batch)
        future = _background().submit(self._compile, key, name, lowered)
        return future.result, lowered.out_info

    def _cached(self, name: str, args: tuple, static: tuple):
        """``(key, executable or None)``: the program kept for ``name`` at the shapes of ``args``."""
        key = (name, static, signature(args), tuple(sorted((self.compiler_options or {}).items())))
        return key, self._executables.get(key)

    def _lower(self, name: str, fn, args: tuple, static: tuple, batch: int | None):
        if self._compile_t0 is None:
            self._compile_t0 = time.perf_counter()
            self._phase_compiled = 0
            notify("start", batch=batch)
        t0 = time.perf_counter()
        lowered = fn.lower(*args, *static)
        self.last_timing["trace_s"] = self.last_timing.get("trace_s", 0.0) + time.perf_counter() - t0
        return lowered

    def _compile(self, key, name: str, lowered):
        notify("compile", program=name)
        exe, from_cache = compile_lowered(lowered, self.compiler_options)
        with _COUNT_LOCK:
            self._executables[key] = exe
            field = "from_cache" if from_cache else "compiled"
            self.last_timing[field] = self.last_timing.get(field, 0) + 1
            self._phase_compiled += 0 if from_cache else 1
        notify("compiled", program=name, from_cache=from_cache)
        return exe

    def _end_compile_phase(self, batch: int) -> None:
        if self._compile_t0 is not None:
            dt = time.perf_counter() - self._compile_t0
            self._compile_t0 = None
            self.last_timing["compile_s"] += dt
            notify("end", batch=batch, seconds=dt, from_cache=self._phase_compiled == 0)

    def _new_timing(self, plan) -> None:
        """Start ``last_timing`` of a run of ``plan`` (:class:`hyqjax.sim.runner.BatchPlan`)."""
        self._reset_compile_phase()
        self.last_timing = dict(compile_s=0.0, trace_s=0.0, simulate_s=0.0, compiled=0, from_cache=0,
                                batch=plan.size, passes=plan.passes, instances=plan.n)

    def chunk_ticks(self, chunk_seconds: float | None) -> int:
        """Ticks per chunk: the largest divisor of ``cfg.n_ticks`` that is at most ``chunk_seconds`` of simulated
        time and a multiple of ``cfg.record_every`` (all ticks when ``chunk_seconds`` is None). It depends on the
        configuration alone, never on the batch, so every batch size shares the chunk program's length."""
        n, rec = self.cfg.n_ticks, max(self.cfg.record_every, 1) if self.record is not None else 1
        if chunk_seconds is None:
            return n
        if not chunk_seconds > 0:
            raise ValueError(f"chunk_seconds must be > 0 s, got {chunk_seconds}")
        want = max(int(chunk_seconds / self.cfg.control_dt), 1)
        fits = [k for k in range(rec, n + 1, rec) if n % k == 0 and k <= want]
        return max(fits) if fits else rec if n % rec == 0 else n


def signature(args) -> tuple:
    """What a compiled program is kept by: the pytree structure and abstract values of ``args``, and the devices
    it runs on (:func:`placement`: a program compiled for one device does not run on another)."""
    leaves, treedef = jax.tree_util.tree_flatten(args)
    return treedef, tuple(jax.typeof(x) for x in leaves), placement(leaves)


def placement(leaves) -> frozenset:
    """The devices a jitted program of ``leaves`` runs on: those of its first committed array (``jax.device_put``
    to a device or sharding), else the default device (where JAX puts uncommitted inputs)."""
    for x in leaves:
        if getattr(x, "committed", False):
            return frozenset(x.sharding.device_set)
    dev = jax.config.jax_default_device
    if dev is None or isinstance(dev, str):
        dev = jax.devices(dev)[0]
    return frozenset((dev,))
