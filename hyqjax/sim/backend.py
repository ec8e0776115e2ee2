"""Which simulator steps the physics: ``impl`` = ``"auto" | "jax" | "warp" | "c"``, and the one object per
implementation that the rest of hyqjax talks to (:func:`get`).

* ``jax``: MJX's pure-JAX physics. Differentiable (forward mode, see README), runs everywhere.
* ``warp``: MuJoCo Warp kernels called from JAX (``mjx.put_model(m, impl="warp")``), several times faster
  on a GPU, forward only. Needs ``warp-lang`` (``pip install "hyqjax[warp]"``). Its contacts live in one
  buffer of ``naconmax`` contacts shared by all worlds of a batch and at most ``njmax`` constraint rows per
  world; :func:`warp_capacity` sizes both from the batch and the model, and a full buffer is reported per
  run (:func:`hyqjax.sim.contacts.overflow`), never silent.
* ``c``: C MuJoCo in float64, one ``MjData`` per instance stepped on all CPU cores, the controller in JAX
  (:mod:`hyqjax.sim.cpu_backend`). Forward only, batches only, no compile of the physics: on a CPU it runs the
  step-down several times faster than MJX-JAX. Tasks that run on it list it in their supported implementations
  (the step-down and its sweeps; bounding runs on ``jax`` and ``warp``).
* ``auto``: ``warp`` when a CUDA device and warp-lang are both available; else ``c`` on a machine without an
  accelerator when the task supports it; else ``jax``. For a pure JAX function of one instance (gradients, a
  jitted single rollout) ``auto`` is ``jax`` (``resolve_impl(..., differentiable=True)``).

:func:`get` returns the backend object of a resolved ``impl``: ``put_model``, ``batch_model``, ``initial_data``,
``make_runner``, ``forbid_derivatives``, ``supports_gradients`` and ``one_instance_error`` (why a one-instance
rollout outside a batch is refused, or ``None``). Code above ``hyqjax.sim`` asks these, never compares ``impl``
names. Asking for a derivative through a forward-only backend raises a ``ValueError`` naming ``impl``
(:func:`forbid_derivatives`), instead of silently falling back.

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
import sys

IMPLS = ("auto", "jax", "warp", "c")
#: The MJX implementations (every task runs on both).
MJX_IMPLS = ("jax", "warp")
#: Every simulator (what the step-down supports).
ALL_IMPLS = ("jax", "warp", "c")
#: Why a forward-only implementation refuses a derivative.
_NOT_DIFFERENTIABLE = {"warp": "MuJoCo Warp is forward only", "c": "C MuJoCo runs outside JAX"}
#: Contacts per instance that the Warp contact buffer holds: each foot on two terrain geoms at once
#: (a platform edge and the ground: 8), up to about 18 with shins and trunk down (benchmarks/probe_warp.py),
#: with margin. A run needing more is flagged (contact_overflow), never silent.
CONTACTS_PER_INSTANCE = 24
#: mujoco_warp's overflow bits that mean a buffer was full (contacts or constraint rows dropped); the
#: higher bits (ITERATIONS, LS_ITERATIONS, ...) only say that the solver used all its iterations.
BUFFER_OVERFLOW_MASK = (1 << 9) - 1
#: Overflow bits that mujoco_warp should not print every step: the solver's iteration limits (bits 9, 10),
#: routine with hyqjax's Newton 4 / 8 settings.
_QUIET_OVERFLOW = 0xFFF & ~((1 << 9) | (1 << 10))
#: Constraint rows per contact of a pyramidal friction cone with condim 3: 2 (condim - 1).
ROWS_PER_CONTACT = 4


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


def check_available(impl: str) -> None:
    """A ``ValueError`` when ``impl`` needs a package that is not installed (warp-lang for ``warp``)."""
    validate_impl(impl)
    if impl == "warp" and not warp_installed():
        raise ValueError("impl='warp' needs warp-lang, which is not installed: pip install \"hyqjax[warp]\" "
                         "(or choose impl='jax')")


_BACKENDS: dict = {}


def get(impl: str):
    """The backend object of a resolved ``impl`` (``jax``, ``warp`` or ``c``; :func:`resolve_impl`), one per
    implementation: :class:`hyqjax.sim.mjx_backend.MJXBackend` or :class:`hyqjax.sim.cpu_backend.CBackend`."""
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


def warp_capacity(njnt_limited: int, batch: int, contacts_per_instance: int = CONTACTS_PER_INSTANCE) -> tuple[int, int]:
    """``(naconmax, njmax)`` for a Warp batch: ``naconmax = batch * contacts_per_instance`` contacts shared by
    all worlds; ``njmax = ROWS_PER_CONTACT * contacts_per_instance + njnt_limited`` rows per world (every
    contact plus every joint-limit row active at once)."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if contacts_per_instance < 1:
        raise ValueError(f"contacts_per_instance must be >= 1, got {contacts_per_instance}")
    return batch * contacts_per_instance, ROWS_PER_CONTACT * contacts_per_instance + njnt_limited


def put_model(m, impl: str):
    """``mjx.put_model(m, impl=...)`` for a resolved ``impl`` (``"jax"`` or ``"warp"``)."""
    from mujoco import mjx

    if impl not in ("jax", "warp"):
        raise ValueError(f"put_model needs a resolved impl ('jax' or 'warp'), got {impl!r}; see resolve_impl")
    mx = mjx.put_model(m, impl=impl)
    if impl == "warp":  # keep the buffer-overflow warnings, drop the per-step iteration-limit printout
        mx = mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=_QUIET_OVERFLOW)))
    return mx


def supports_gradients(impl: str) -> bool:
    return impl not in _NOT_DIFFERENTIABLE


def forbid_derivatives(tree, impl: str):
    """Identity on ``tree``; under a forward-only ``impl`` (``warp``, ``c``) a derivative (``jax.jvp``,
    ``jacfwd``, ``grad``) through it raises ``ValueError`` naming ``impl``."""
    if supports_gradients(impl):
        return tree
    import jax

    why = _NOT_DIFFERENTIABLE[impl]

    @jax.custom_jvp
    def guard(x):
        return x

    @guard.defjvp
    def _jvp(primals, tangents):
        raise ValueError(f"impl='{impl}' is not differentiable ({why}); use impl='jax' for gradients")

    return guard(tree)


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


def model_impl(mx) -> str:
    """The MJX implementation (``"jax"`` or ``"warp"``) of an ``mjx.Model``."""
    return "warp" if is_warp_model(mx) else "jax"


def is_warp_model(mx) -> bool:
    """``mx`` is an ``mjx.Model`` of the Warp implementation."""
    return str(getattr(mx, "impl", "")).lower().endswith("warp")
