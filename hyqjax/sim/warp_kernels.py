"""MuJoCo Warp's kernel build, timed and announced.

MuJoCo Warp compiles its kernels (Warp modules: C++ through LLVM on a CPU, CUDA through NVRTC on a GPU) the first
time a module is launched on a device, and keeps them in Warp's kernel cache (``~/.cache/warp/VERSION``, or
``$WARP_CACHE_PATH/VERSION``); a later process loads them from there. Under MJX the first launch happens inside
the first simulated chunk, so without this module a first run on a machine reports the build as simulation.

:func:`install` wraps Warp's ``Module.load`` (one call per module and device) and ``Module._compile`` (which
builds, or finds the binary in the cache): every load that is not already in memory is timed, and announced to
the listeners of :func:`hyqjax.sim.compile_phase.compile_listener` as ``("kernels", {"module": name, "seconds": s,
"compiled": bool})`` after it, with ``("kernels_start", {"module": name, "compiling": bool, "cache": dir})``
before a build (``compiling``: the module's binary is not in the cache). :func:`seconds` sums the loads of the
process. Where Warp's internals differ from warp-lang 1.18.0's, :func:`install` does nothing (the build is then
counted as simulation, as before).
"""
from __future__ import annotations

import functools
import os
import threading
import time

_LOCK = threading.Lock()
_STATE = dict(installed=False, seconds=0.0, compiled=0, loaded=0)
_LOCAL = threading.local()


def cache_dir() -> str:
    """Warp's kernel cache directory (as Warp resolves it: ``$WARP_CACHE_PATH/VERSION`` or
    ``~/.cache/warp/VERSION``)."""
    import warp

    d = getattr(warp.config, "kernel_cache_dir", None)
    if d:
        return d
    base = os.environ.get("WARP_CACHE_PATH")
    version = getattr(warp.config, "version", "")
    return os.path.join(base, version) if base else os.path.join("~", ".cache", "warp", version)


def short_path(path: str) -> str:
    home = os.path.expanduser("~")
    return "~" + path[len(home):] if path.startswith(home + os.sep) else path


def seconds() -> float:
    """Seconds this process has spent loading (building or reading from the cache) Warp modules since
    :func:`install`."""
    return _STATE["seconds"]


def counts() -> tuple[int, int]:
    """``(compiled, loaded)``: modules built in this process, and modules loaded in all."""
    return _STATE["compiled"], _STATE["loaded"]


def install() -> bool:
    """Wrap Warp's module loading (once per process); False where warp-lang's internals are not the expected
    ones."""
    with _LOCK:
        if _STATE["installed"]:
            return True
        try:
            from warp._src import context
        except ImportError:
            return False
        module = getattr(context, "Module", None)
        load, compile_ = getattr(module, "load", None), getattr(module, "_compile", None)
        if load is None or compile_ is None:
            return False
        module.load = _timed_load(load)
        module._compile = _announced_compile(compile_)
        _STATE["installed"] = True
        return True


def _notify(event: str, **info) -> None:
    from hyqjax.sim import compile_phase

    if event == "kernels_start" and not compile_phase._LISTENERS and not _STATE.get("announced"):
        # Nobody shows it (a build outside a command's batch run): one line, once per process.
        import sys

        _STATE["announced"] = True
        where = f"; cached in {info['cache']}" if info.get("cache") else ""
        print(f"hyqjax: building MuJoCo Warp kernels (first run on this machine{where}); this takes minutes on a "
              f"CPU, about a minute on a GPU", file=sys.stderr, flush=True)
    compile_phase.notify(event, **info)


def _timed_load(load):
    @functools.wraps(load)
    def wrapper(self, device, *args, **kwargs):
        if getattr(_LOCAL, "depth", 0):  # a load inside a load is the outer one's time
            return load(self, device, *args, **kwargs)
        _LOCAL.depth, _LOCAL.compiled = 1, None
        t0 = time.perf_counter()
        try:
            return load(self, device, *args, **kwargs)
        finally:
            dt = time.perf_counter() - t0
            compiled = _LOCAL.compiled
            _LOCAL.depth = 0
            if compiled is not None:  # not already in memory: built or read from the cache
                with _LOCK:
                    _STATE["seconds"] += dt
                    _STATE["loaded"] += 1
                    _STATE["compiled"] += int(bool(compiled))
                _notify("kernels", module=getattr(self, "name", "?"), seconds=dt, compiled=bool(compiled))

    return wrapper


def _announced_compile(compile_):
    @functools.wraps(compile_)
    def wrapper(self, device=None, output_dir=None, output_name=None, *args, **kwargs):
        cached = bool(output_dir and output_name and os.path.exists(os.path.join(output_dir, output_name)))
        if not cached:
            _notify("kernels_start", module=getattr(self, "name", "?"), compiling=True,
                    cache=short_path(os.path.dirname(os.fspath(output_dir))) if output_dir else "")
        compiled = compile_(self, device, output_dir, output_name, *args, **kwargs)
        if getattr(_LOCAL, "depth", 0):
            _LOCAL.compiled = bool(compiled)
        return compiled

    return wrapper
