"""Which simulator steps the physics: ``impl`` = ``"auto" | "jax" | "warp" | "c"``, and the one object per
implementation that the rest of hyqjax talks to (:func:`get`).

* ``jax``: MJX's pure-JAX physics. Differentiable (forward mode, see docs/architecture.md), runs everywhere.
* ``warp``: MuJoCo Warp kernels called from JAX (``mjx.put_model(m, impl="warp")``), several times faster
  on a GPU, forward only. Needs ``warp-lang`` (``pip install "hyqjax[warp]"``). Its contacts live in one
  buffer of ``naconmax`` contacts shared by all worlds of a batch and at most ``njmax`` constraint rows per
  world; :func:`hyqjax.sim.impls.warp_capacity` sizes both from the batch and the model, and a full buffer is
  reported per run (:func:`hyqjax.sim.contacts.overflow`), never silent.
* ``c``: C MuJoCo in float64, one ``MjData`` per instance stepped on all CPU cores, the controller in JAX
  (:mod:`hyqjax.sim.cpu_backend`). Forward only, batches only, no compile of the physics: on a CPU it runs the
  step-down several times faster than MJX-JAX. Tasks that run on it list it in their supported implementations
  (the step-down and its sweeps, bounding).
* ``auto``: ``warp`` when a CUDA device and warp-lang are both available; else ``c`` on a machine without an
  accelerator when the task supports it; else ``jax``. For a pure JAX function of one instance (gradients, a
  jitted single rollout) ``auto`` is ``jax`` (``resolve_impl(..., differentiable=True)``).

:func:`get` returns the backend object of a resolved ``impl``: ``put_model``, ``batch_model``, ``initial_data``,
``make_runner``, ``forbid_derivatives``, ``supports_gradients``, ``one_instance_error`` (why a one-instance
rollout outside a batch is refused, or ``None``) and ``from_jax_data`` (MJX-JAX data as this implementation's;
C MuJoCo: a batch's). Code above ``hyqjax.sim`` asks these (and :func:`describe` for a help text of the choices),
never compares ``impl`` names. Asking for a derivative through a forward-only backend raises a ``ValueError``
naming ``impl`` (:func:`hyqjax.sim.impls.forbid_derivatives`), instead of silently falling back.

The names of the implementations, which pass derivatives, and MJX's model under each are
:mod:`hyqjax.sim.impls`'s, the module below every other of :mod:`hyqjax.sim`; this one sits above the backend
objects it hands out (:mod:`hyqjax.sim.mjx_backend`, :mod:`hyqjax.sim.cpu_backend`), so nothing they import
imports it.

This module imports no JAX or MuJoCo at import time (``import hyqjax`` stays light), and warp is imported
only when ``warp`` is chosen. :func:`install_lazy_mjx_import` defers MJX itself (and the MuJoCo Warp it
imports) to its first use, so a run on the C MuJoCo backend never loads it. :func:`install_quiet_warp_import`
removes the two lines MJX prints on stdout when warp-lang is absent ("Failed to import warp: No module named
'warp'", the same for mujoco_warp); any other output of that import, and every other warning, passes through.
"""
from __future__ import annotations

import contextlib
import importlib.abc
import importlib.util
import io
import os
import sys

from hyqjax.sim.impls import ALL_IMPLS, IMPLS, MJX_IMPLS

#: What each implementation is, in a phrase (the command line's ``--impl`` help).
DESCRIPTIONS = dict(warp="MuJoCo Warp, several times faster on a CUDA GPU, forward only; pip install 'hyqjax[warp]'",
                    jax="MJX in pure JAX, differentiable",
                    c="C MuJoCo on all CPU cores, the controller in JAX; forward only")


def validate_impl(impl: str, supported: tuple[str, ...] = ALL_IMPLS) -> str:
    """``impl`` itself if it is ``auto`` or one of ``supported``; else a ``ValueError`` naming the choices."""
    if impl != "auto" and impl not in supported:
        choices = ", ".join(("auto",) + tuple(supported))
        extra = "" if impl not in IMPLS else " for this task"
        raise ValueError(f"impl must be one of {choices}{extra}, got {impl!r}")
    return impl


def warp_installed() -> bool:
    """warp-lang can be imported (checked without importing it)."""
    return importlib.util.find_spec("warp") is not None


def point_warp_kernel_cache(path: str) -> None:
    """Make Warp compile its kernels into (and load them from) ``path``: the ``WARP_CACHE_PATH`` a later Warp
    import reads, and, when Warp is imported already, its live ``kernel_cache_dir``. Imports no Warp."""
    os.environ["WARP_CACHE_PATH"] = path
    warp = sys.modules.get("warp")
    if warp is not None:
        warp.config.kernel_cache_dir = path


def cuda_available() -> bool:
    import jax

    try:
        return any(d.platform == "gpu" for d in jax.devices())
    except RuntimeError:
        return False


def accelerator_available() -> bool:
    """JAX sees a device other than the CPU."""
    import jax

    try:
        return any(d.platform != "cpu" for d in jax.devices())
    except RuntimeError:
        return False


def resolve_impl(impl: str, supported: tuple[str, ...] = MJX_IMPLS, differentiable: bool = False) -> str:
    """The implementation that runs a request for ``impl`` by a task supporting ``supported`` (module docstring);
    ``differentiable``: the run is a pure JAX function of one instance (derivatives, ``jax.jit`` of a single
    rollout), for which ``auto`` means ``jax``."""
    validate_impl(impl, supported)
    if impl == "auto" and differentiable:
        return "jax"
    if impl == "auto":
        if "warp" in supported and warp_installed() and cuda_available():
            return "warp"
        if "c" in supported and not accelerator_available():
            return "c"
        return "jax"
    check_available(impl)
    return impl


def describe(supported: tuple[str, ...] = ALL_IMPLS) -> str:
    """The choices of a task supporting ``supported``, each in a phrase, ``auto``'s rule (:func:`resolve_impl`) last."""
    auto = "warp when a CUDA GPU and warp-lang are present, else " + (
        "c without an accelerator, else jax" if "c" in supported else "jax")
    return ", ".join(f"'{k}' ({DESCRIPTIONS[k]})" for k in supported) + f", 'auto' ({auto})"


def check_available(impl: str) -> None:
    """A ``ValueError`` when ``impl`` needs a package that is not installed (warp-lang for ``warp``); ``auto``
    always passes (it picks among what is installed)."""
    validate_impl(impl)
    if impl == "warp" and not warp_installed():
        raise ValueError("impl='warp' needs warp-lang, which is not installed: pip install \"hyqjax[warp]\" "
                         "(or choose impl='jax')")


_BACKENDS: dict = {}


def get(impl: str):
    """The backend object of a resolved ``impl`` (``jax``, ``warp`` or ``c``; :func:`resolve_impl`), one per
    implementation: :class:`hyqjax.sim.mjx_backend.MJXBackend` or :class:`hyqjax.sim.cpu_backend.CBackend` (imported
    here on first use: they import the rollout and runner, which import :mod:`hyqjax.sim.impls`, never this module)."""
    if impl not in ALL_IMPLS:
        raise ValueError(f"get needs a resolved impl ({', '.join(ALL_IMPLS)}), got {impl!r}; see resolve_impl")
    if impl not in _BACKENDS:
        if impl == "c":
            from hyqjax.sim.cpu_backend import CBackend

            _BACKENDS[impl] = CBackend()
        else:
            from hyqjax.sim.mjx_backend import MJXBackend

            _BACKENDS[impl] = MJXBackend(impl)
    return _BACKENDS[impl]


def devices_for(impl: str, selection=None) -> list:
    """The devices a batch of a resolved ``impl`` is split over: :func:`hyqjax.sim.devices.resolve`'s for a simulator
    that runs on JAX devices (MJX-JAX, MuJoCo Warp), ``[None]`` for one that runs on the host's cores (C MuJoCo
    shards over threads, :class:`hyqjax.sim.cpu_backend.CBatchRunner`)."""
    from hyqjax.sim import devices

    return devices.resolve(selection) if get(impl).uses_jax_devices else [None]


_WARP_MISSING = ("Failed to import warp: No module named 'warp'",
                 "Failed to import mujoco_warp: No module named 'warp'")


class _QuietLoader(importlib.abc.Loader):
    def __init__(self, inner):
        self.inner = inner

    def create_module(self, spec):
        return self.inner.create_module(spec)

    def exec_module(self, module):
        buf = io.StringIO()
        try:
            with contextlib.redirect_stdout(buf):
                self.inner.exec_module(module)
        finally:
            kept = [ln for ln in buf.getvalue().splitlines(keepends=True) if ln.rstrip("\n") not in _WARP_MISSING]
            sys.stdout.write("".join(kept))


class _QuietFinder(importlib.abc.MetaPathFinder):
    NAME = "mujoco.mjx.warp"

    def find_spec(self, fullname, path, target=None):
        if fullname != self.NAME:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.loader is not None:
                    spec.loader = _QuietLoader(spec.loader)
                return spec
        return None


def install_quiet_warp_import() -> None:
    """Drop MJX's "Failed to import warp" lines (printed when warp-lang is absent) from ``mujoco.mjx.warp``'s
    import; idempotent, and a no-op once that module is imported."""
    if "mujoco.mjx.warp" in sys.modules or any(isinstance(f, _QuietFinder) for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _QuietFinder())


class _LazyMJXFinder(importlib.abc.MetaPathFinder):
    """Finds ``mujoco.mjx`` with the spec of the other finders, its loader wrapped in ``importlib.util.LazyLoader``."""

    NAME = "mujoco.mjx"

    def find_spec(self, fullname, path, target=None):
        if fullname != self.NAME:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                if spec.loader is not None and hasattr(spec.loader, "exec_module"):
                    spec.loader = importlib.util.LazyLoader(spec.loader)
                return spec
        return None


def install_lazy_mjx_import() -> None:
    """Make ``mujoco.mjx`` load on first use instead of at ``from mujoco import mjx``
    (``importlib.util.LazyLoader``): importing MJX imports MuJoCo Warp and warp-lang when they are installed,
    about 3 s of CPU, which a run on the C MuJoCo backend never needs. Modules that use MJX import it at their
    top as before; it loads when one of its attributes is first read. Idempotent; a no-op once MJX is imported."""
    if "mujoco.mjx" in sys.modules or any(isinstance(f, _LazyMJXFinder) for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _LazyMJXFinder())


