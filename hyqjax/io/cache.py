"""JAX's persistent compilation cache for hyqjax: a program compiled once is loaded by later runs.

Every ``hyqjax`` command turns it on (``--no-cache`` to skip), and so does every Ray worker of a sweep, in
:func:`cache_dir`: ``$HYQJAX_CACHE_DIR``, else ``$JAX_COMPILATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/hyqjax/jax``
(``~/.cache/hyqjax/jax``), in a subdirectory per host CPU (:func:`host_cpu_key`) but for JAX's own variable.
JAX keys each entry by the program, the compile options, the backend and the JAX version, so a changed
model, batch shape or installation compiles anew. Every program is cached (minimum compile time 0 s),
including the small ones around the rollout.

:class:`StderrFilter` (installed by the command line with the cache, not with ``--debug``) drops the two
bogus ERROR lines XLA:CPU logs for every program it loads from the cache on some hosts.
"""
from __future__ import annotations

import atexit
import os
import re
import select
import sys
import threading


def host_cpu_key() -> str:
    """A short key of this host's CPU (architecture and instruction-set flags: ``/proc/cpuinfo``'s ``flags``
    line on Linux, else ``platform.processor()``). JAX's cache key holds the program, the compile options, the
    backend and the device kind ("cpu"), not the CPU's instruction set, so XLA:CPU code compiled on one host would
    be loaded on another with other instructions (XLA only warns that this "could lead to execution errors such
    as SIGILL"): on a cluster whose nodes share a home directory, each kind of CPU gets its own cache."""
    import hashlib
    import platform

    features = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    features = " ".join(sorted(line.split(":", 1)[1].split()))
                    break
    except OSError:
        pass
    ident = f"{platform.machine()}|{features or platform.processor()}"
    return f"{platform.machine() or 'cpu'}-{hashlib.sha256(ident.encode()).hexdigest()[:12]}"


def cache_dir() -> str:
    """``$HYQJAX_CACHE_DIR/<host CPU>``, else JAX's own ``$JAX_COMPILATION_CACHE_DIR`` (as given), else
    ``$XDG_CACHE_HOME/hyqjax/jax/<host CPU>`` (``~/.cache/hyqjax/jax/<host CPU>``); ``<host CPU>`` is
    :func:`host_cpu_key`, so hosts with different instruction sets never load each other's programs."""
    if os.environ.get("HYQJAX_CACHE_DIR"):
        return os.path.join(os.environ["HYQJAX_CACHE_DIR"], host_cpu_key())
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "hyqjax", "jax", host_cpu_key())


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`cache_dir`). Returns the
    directory, or None when it cannot be created or written (the run then compiles as usual).

    Before JAX is imported this only sets the environment variables JAX reads its configuration from when it
    is imported (so a command that never needs JAX, or is refused first, does not pay for importing it);
    after, it updates ``jax.config``."""
    path = path or cache_dir()
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    if not os.access(path, os.W_OK):
        return None
    if "jax" not in sys.modules:
        os.environ.update(JAX_COMPILATION_CACHE_DIR=path, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                          JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
        return path
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def use_cold_caches(path: str | None = None) -> str:
    """Compile everything of this process cold: JAX's persistent compilation cache and Warp's kernel cache in
    ``path`` (default: a fresh empty temporary directory, removed at exit), so that no program or kernel is
    loaded from an earlier process (a compile time measured now is what a first run on a fresh machine pays).
    Call it before the first compile (JAX) and before Warp is initialised (its kernel cache is fixed then).
    Returns the directory."""
    import tempfile

    if path is None:
        import shutil

        path = tempfile.mkdtemp(prefix="hyqjax-cold-")
        atexit.register(shutil.rmtree, path, True)
    jax_dir, warp_dir = os.path.join(path, "jax"), os.path.join(path, "warp")
    os.makedirs(jax_dir, exist_ok=True)
    os.makedirs(warp_dir, exist_ok=True)
    from hyqjax.sim.backend import point_warp_kernel_cache

    point_warp_kernel_cache(warp_dir)
    os.environ.pop("HYQJAX_CACHE_DIR", None)
    enable_compilation_cache(jax_dir)
    if "jax" in sys.modules:  # a cache JAX opened already is closed, so the next compile opens the new one
        from jax._src import compilation_cache

        compilation_cache.reset_cache()
    return path


# XLA:CPU logs two ERROR lines (thousands of characters each) for every program it loads from the persistent
# cache on hosts whose LLVM target features include the tuning flags +prefer-no-gather / +prefer-no-scatter
# ("Target machine feature ... is not supported on the host machine"); the program loads and runs correctly
# (openxla/xla#44565, jax-ml/jax#38445). StderrFilter drops exactly those lines.
_NOISE = re.compile(rb"[IWEF]\d{4} \d\d:\d\d:\d\d\.\d+ +\d+ cpu_aot_loader\.cc:\d+\] Loading XLA:CPU AOT result\."
                    rb"[^\n]*\n")
_LOG_START = re.compile(rb"[IWEF](\d{0,4}|\d{4} [^\n]*)$")  # a log line begun but not ended yet
_HOLD_MAX = 1 << 20


def filter_log_noise(buf: bytes, quiet: bool = False, final: bool = False) -> tuple[bytes, bytes]:
    """``(to_write, held)``: ``buf`` without the XLA:CPU cache-load lines; a tail that may be the start of one is
    held back, unless nothing more came for a while (``quiet``) and it is not one, or at the end (``final``)."""
    out = []
    while (m := _NOISE.search(buf)) is not None:
        out.append(buf[:m.start()])
        buf = buf[m.end():]
    p = None if final else _LOG_START.search(buf)
    if p is not None and len(buf) - p.start() < _HOLD_MAX:
        tail = buf[p.start():]
        if not quiet or b"cpu_aot_loader.cc" in tail:
            out.append(buf[:p.start()])
            return b"".join(out), tail
    out.append(buf)
    return b"".join(out), b""


def _write_all(fd: int, data: bytes) -> None:
    try:
        while data:
            data = data[os.write(fd, data):]
    except OSError:
        pass


class StderrFilter:
    """File descriptor 2 (XLA's C++ logging) through a pipe and a thread that writes everything to the real stderr
    except the lines :func:`filter_log_noise` drops; Python's ``sys.stderr`` (progress bars, messages) writes to
    the real stderr directly, so it stays in order with stdout. :meth:`stop` (also at exit) restores both."""

    def __init__(self):
        self._orig = None

    def start(self) -> "StderrFilter":
        if self._orig is not None:
            return self
        try:
            sys.stderr.flush()
            orig = os.dup(2)
            r, w = os.pipe()
            os.dup2(w, 2)
            os.close(w)
        except OSError:
            return self
        self._orig, self._r, self._py = orig, r, sys.stderr
        sys.stderr = open(orig, "w", buffering=1, encoding=getattr(self._py, "encoding", None) or "utf-8",
                          errors="backslashreplace", closefd=False)
        self._thread = threading.Thread(target=self._pump, name="hyqjax-stderr-filter", daemon=True)
        self._thread.start()
        atexit.register(self.stop)
        return self

    def _pump(self) -> None:
        held = b""
        while True:
            if select.select([self._r], [], [], 0.2)[0]:
                chunk = os.read(self._r, 1 << 16)
                if not chunk:
                    break
                out, held = filter_log_noise(held + chunk)
            elif held:
                out, held = filter_log_noise(held, quiet=True)
            else:
                continue
            _write_all(self._orig, out)
        _write_all(self._orig, filter_log_noise(held, final=True)[0])
        os.close(self._r)

    def stop(self, timeout: float = 1.0) -> None:
        """Restore fd 2 and wait (``timeout`` s at most) until everything written before is out."""
        if self._orig is None:
            return
        try:
            sys.stderr.flush()
        except (OSError, ValueError):
            pass
        sys.stderr = self._py
        os.dup2(self._orig, 2)  # closes this process's write end of the pipe: the pump reads to the end
        self._thread.join(timeout)
        self._orig = None
