"""The simulator implementations (``impl``): their names, which of them pass derivatives, and MJX's model
under each.

The vocabulary below every other module of :mod:`hyqjax.sim`: it imports nothing of hyqjax (and no JAX or MuJoCo
at import time). Which implementation runs a task, and the object a task talks to, are :mod:`hyqjax.sim.backend`'s
(:func:`hyqjax.sim.backend.resolve_impl`, :func:`hyqjax.sim.backend.get`), built on this module.

* :data:`MJX_IMPLS` (``jax``, ``warp``) and :data:`ALL_IMPLS` (those and ``c``, C MuJoCo) name them;
  :func:`supports_gradients` and :func:`forbid_derivatives` say which pass a derivative (``jax`` only).
* :func:`put_model` puts a ``mujoco.MjModel`` on MJX under ``jax`` or ``warp``; :func:`is_warp_model` and
  :func:`model_impl` tell the two ``mjx.Model`` kinds apart (code in :mod:`hyqjax.sim` that differs between them).
* MuJoCo Warp keeps the contacts of a whole batch in one buffer of ``naconmax`` contacts and at most ``njmax``
  constraint rows per world: :func:`warp_capacity` sizes both from the batch and the model, and
  :data:`BUFFER_OVERFLOW_MASK` selects the overflow flags that mean a full buffer
  (:func:`hyqjax.sim.contacts.overflow`), so a dropped contact is reported per run, never silent.
"""
from __future__ import annotations

#: What a caller may ask for: ``auto`` (:func:`hyqjax.sim.backend.resolve_impl` picks) or an implementation.
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


def supports_gradients(impl: str) -> bool:
    """A derivative passes through the resolved ``impl`` (MJX-JAX only)."""
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
        raise ValueError(f"put_model needs a resolved impl ('jax' or 'warp'), got {impl!r}; see hyqjax.sim.backend.resolve_impl")
    if impl == "warp":  # its kernel build timed and announced (hyqjax.sim.warp_kernels), not taken for simulation
        from hyqjax.sim import warp_kernels

        warp_kernels.install()
    mx = mjx.put_model(m, impl=impl)
    if impl == "warp":  # keep the buffer-overflow warnings, drop the per-step iteration-limit printout
        mx = mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=_QUIET_OVERFLOW)))
    return mx


def model_impl(mx) -> str:
    """The MJX implementation (``"jax"`` or ``"warp"``) of an ``mjx.Model``."""
    return "warp" if is_warp_model(mx) else "jax"


def is_warp_model(mx) -> bool:
    """``mx`` is an ``mjx.Model`` of the Warp implementation."""
    return str(getattr(mx, "impl", "")).lower().endswith("warp")
