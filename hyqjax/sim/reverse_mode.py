"""Reverse-mode differentiation through MJX's constraint solver: :func:`fixed_length_solver`.

MJX-JAX finds the constraint forces of ``mjx.step`` with a conjugate-gradient / Newton solver
(``mujoco.mjx._src.solver.solve``) whose outer loop is a ``jax.lax.while_loop``: with ``c`` its condition and
``b`` its body, the solver state after the loop is ``x_* = b^k(x_0)`` with ``k`` the first count for which
``c(b^k(x_0))`` is false. ``c`` is false as soon as ``k >= N = m.opt.iterations`` (or the cost improvement or the
gradient falls below ``m.opt.tolerance``), so ``k <= N``. A ``while_loop`` has a forward-mode rule (``jax.jvp``,
``jax.jacfwd``) but no transpose: its trip count is not known when the program is built, so reverse mode
(``jax.grad``, ``jax.vjp``, ``jax.jacrev``) refuses it. MJX's line search inside the body is already a
fixed-length loop.

While :func:`fixed_length_solver` is active, that one ``while_loop`` is traced as ``N`` steps of a ``lax.scan``,
step ``i`` being

.. math:: x_{i+1} = \\begin{cases} b(x_i) & c(x_i) \\\\ x_i & \\text{otherwise} \\end{cases}
          \\qquad (\\texttt{lax.cond}),

which gives ``x_N = b^k(x_0) = x_*``: the steps after the first false ``c`` return their input unchanged (``c``
stays false on an unchanged state), and ``k <= N`` means no step is missing. The primal is the same computation,
and a ``scan`` of ``cond`` s has a transpose, so the step is reverse-differentiable; the derivative is that of the
branch each step took, exactly what forward mode through the ``while_loop`` computes. The extra cost is at most
``N - k`` predicate evaluations per step of a single system; under ``vmap`` (a batch of systems), where both the
``while_loop`` and the ``cond`` evaluate the body for every system while any one is still iterating, the scan runs
all ``N`` bodies.

Only TRACING is affected: a function traced (``jax.jit``, ``jax.grad``, ...) inside the context keeps the fixed-length
loop in its program, a function traced outside keeps the ``while_loop``; nothing changes for programs already
compiled. How: for the duration of the context, the name ``solve`` of ``mujoco.mjx._src.solver`` (what
``mjx.forward`` calls) is a wrapper that records ``N = m.opt.iterations`` of the model it is given, and the module's
name ``jax`` is a proxy of ``jax`` whose ``lax.while_loop`` is the fixed-length loop above, of that ``N``. The
installed package is not edited; both names are restored when the outermost context exits, also on an exception.
A re-entrant lock is held for the whole context, so two threads never patch or trace through the patched module
at the same time (a thread entering waits), and contexts nest within one thread.
"""
from __future__ import annotations

import contextlib
import threading

import jax

#: Held while a context is active (re-entrant: contexts nest within one thread).
_LOCK = threading.RLock()
#: Nesting depth of active contexts and the names they replaced.
_STATE = {"depth": 0, "saved": None}
#: Per thread: the stack of ``m.opt.iterations`` of the wrapped solves being traced.
_BOUNDS = threading.local()


def bounded_while_loop(cond_fun, body_fun, init_val, max_iter: int):
    """``while cond_fun(x): x = body_fun(x)`` as ``max_iter`` steps of a ``lax.scan``, each a ``lax.cond`` that
    applies ``body_fun`` while ``cond_fun`` holds and returns its input otherwise; equal to the ``while_loop``
    whenever that stops within ``max_iter`` iterations, and reverse-differentiable."""

    def step(x, _):
        return jax.lax.cond(cond_fun(x), body_fun, lambda y: y, x), None

    return jax.lax.scan(step, init_val, None, length=int(max_iter))[0]


def _while_loop(cond_fun, body_fun, init_val):
    """The solver module's ``jax.lax.while_loop`` while patched: fixed length inside a wrapped ``solve``."""
    stack = getattr(_BOUNDS, "stack", None)
    if not stack:  # not the solver's loop (no wrapped solve is being traced): the ordinary loop
        return jax.lax.while_loop(cond_fun, body_fun, init_val)
    return bounded_while_loop(cond_fun, body_fun, init_val, stack[-1])


class _LaxProxy:
    """``jax.lax`` with ``while_loop`` replaced (every other name is ``jax.lax``'s)."""

    while_loop = staticmethod(_while_loop)

    def __getattr__(self, name):
        return getattr(jax.lax, name)


class _JaxProxy:
    """``jax`` with ``lax`` replaced by :class:`_LaxProxy` (every other name is ``jax``'s)."""

    lax = _LaxProxy()

    def __getattr__(self, name):
        return getattr(jax, name)


def _wrap_solve(solve):
    def fixed_length_solve(m, d):
        n = int(m.opt.iterations)
        if not hasattr(_BOUNDS, "stack"):
            _BOUNDS.stack = []
        stack = _BOUNDS.stack
        stack.append(n)
        try:
            return solve(m, d)
        finally:
            stack.pop()

    fixed_length_solve.__wrapped__ = solve
    fixed_length_solve.__name__ = getattr(solve, "__name__", "solve")
    fixed_length_solve.__doc__ = getattr(solve, "__doc__", None)
    return fixed_length_solve


@contextlib.contextmanager
def fixed_length_solver():
    """While active, MJX-JAX's constraint solver loop traces as a fixed-length ``lax.scan`` of at most
    ``m.opt.iterations`` steps with the same early stop, so that reverse mode differentiates ``mjx.step`` (module
    docstring). Trace (``jit``, ``grad``, ``vjp``) inside it; restores MJX on exit."""
    from mujoco.mjx._src import solver

    with _LOCK:
        if _STATE["depth"] == 0:
            _STATE["saved"] = (solver.jax, solver.solve)
            solver.jax, solver.solve = _JaxProxy(), _wrap_solve(solver.solve)
        _STATE["depth"] += 1
        try:
            yield
        finally:
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0:
                solver.jax, solver.solve = _STATE["saved"]
                _STATE["saved"] = None


def is_active() -> bool:
    """Whether a :func:`fixed_length_solver` context is active (in any thread)."""
    return _STATE["depth"] > 0
