"""JAX's persistent compilation cache for hyqjax: a program compiled once is loaded by later runs.

Every ``hyqjax`` command turns it on (``--no-cache`` to skip), and so does every Ray worker of a sweep, in
:func:`cache_dir`: ``$HYQJAX_CACHE_DIR``, else ``$JAX_COMPILATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/hyqjax/jax``
(``~/.cache/hyqjax/jax``).
JAX keys each entry by the program, the compile options, the backend and the JAX version, so a changed
model, batch shape or installation compiles anew. Every program is cached (minimum compile time 0 s),
including the small ones around the rollout.
"""
from __future__ import annotations

import os


def cache_dir() -> str:
    """``$HYQJAX_CACHE_DIR``, else JAX's own ``$JAX_COMPILATION_CACHE_DIR``, else ``$XDG_CACHE_HOME/hyqjax/jax``
    (``~/.cache/hyqjax/jax``)."""
    for var in ("HYQJAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR"):
        if os.environ.get(var):
            return os.environ[var]
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "hyqjax", "jax")


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Turn on JAX's persistent compilation cache in ``path`` (default :func:`cache_dir`). Returns the
    directory, or None when it cannot be created or written (the run then compiles as usual)."""
    path = path or cache_dir()
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    if not os.access(path, os.W_OK):
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
