"""Shape checks of array arguments against patterns, as ``chex.assert_shape`` writes them.

A pattern is a tuple of ints (that size), ``None`` (any size) and at most one ``...`` (any number of axes):
``(..., 4, 3)`` is the feet of any batch. :func:`check_shape` runs on static shapes (free inside ``jit``) and
raises :class:`hyqjax.core.params.ParameterError` naming the argument and the shapes it allows; the kinematics
and the reflex check their inputs with it. (A parameter field's allowed trailing shapes are declared with it
instead: :func:`hyqjax.core.params.param_field`.)
"""
from __future__ import annotations

import jax.numpy as jnp

from hyqjax.core.params import ParameterError

__all__ = ["check_shape", "shape_matches"]


def shape_matches(shape: tuple, pattern: tuple) -> bool:
    """Whether ``shape`` matches ``pattern``: a tuple of ints (that size), ``None`` (any size) and at most one
    ``...`` (any number of leading, inner or trailing axes), as in ``chex.assert_shape``'s patterns."""
    shape = tuple(int(d) for d in shape)
    if Ellipsis in pattern:
        i = pattern.index(Ellipsis)
        head, tail = pattern[:i], pattern[i + 1:]
        if len(shape) < len(head) + len(tail):
            return False
        return (shape_matches(shape[:len(head)], head)
                and shape_matches(shape[len(shape) - len(tail):], tail))
    return len(shape) == len(pattern) and all(p is None or p == d for d, p in zip(shape, pattern))


def check_shape(x, shapes, owner: str, name: str):
    """``x`` as an array, after checking (:func:`shape_matches`) that its shape is one of ``shapes``.

    ``shapes`` are shape patterns, e.g. ``((..., 12), (..., 4, 3))``. Runs on static shapes, so it is free
    inside ``jit``. Raises :class:`ParameterError` naming ``owner.name`` and the allowed shapes.
    """
    x = jnp.asarray(x) if not hasattr(x, "shape") else x
    if any(shape_matches(x.shape, shape) for shape in shapes):
        return x
    def show(s):
        return "(" + ", ".join("..." if d is Ellipsis else str(d) for d in s) + ("," if len(s) == 1 else "") + ")"

    raise ParameterError(owner, name, f"array of shape {tuple(x.shape)}",
                         f"of shape {' or '.join(show(s) for s in shapes)}", problem="has a wrong shape")
