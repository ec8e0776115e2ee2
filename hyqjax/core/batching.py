"""``vmap`` over a batch, skipped for a batch of one.

Under ``jax.vmap`` a derivative program through an MJX rollout is traced once more by the batching rules of its
loops: ``scan``'s rule batches the loop body again until the batching of its carries settles, and so does every
loop nested in it. For the bound's cycle optimisation, its robust study and the tuner's windows that trace is 5-20
s on a CPU (benchmarks/RESULTS.md). A batch of one gains nothing from it, so :func:`vmap_unless_one` calls the
function on the one row instead and puts the batch axis back; the values are those of the ``vmap`` program up to
rounding (the two programs are compiled separately).
"""
from __future__ import annotations

from typing import Callable

import jax
import numpy as np

__all__ = ["vmap_unless_one", "take_rows", "row_index"]


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray))


def vmap_unless_one(fn: Callable, vmap: Callable = jax.vmap, in_axes=0) -> Callable:
    """``vmap(fn, in_axes=in_axes)`` (``jax.vmap``, or e.g. ``equinox.filter_vmap`` with the default ``in_axes``),
    except for a batch of one (the leading axis of the first mapped array input, a static shape): then ``fn`` on
    every mapped array input's first row, with a leading axis of one put on every array output. ``in_axes`` as
    ``jax.vmap``'s, 0 or None per input or subtree (None: not mapped, passed whole). Inputs and outputs that are
    not arrays pass through unchanged."""

    if any(ax not in (0, None) for ax in jax.tree_util.tree_leaves(in_axes, is_leaf=lambda x: x is None)):
        raise ValueError(f"vmap_unless_one maps axis 0 or None, got in_axes {in_axes}")

    def per_input(args) -> tuple:
        return tuple(in_axes) if isinstance(in_axes, (tuple, list)) else (in_axes,) * len(args)

    def batched(*args):
        def over_inputs(f):  # f(axis, input subtree) for every input or subtree that in_axes names
            return jax.tree_util.tree_map(f, per_input(args), args, is_leaf=lambda x: x is None)

        mapped = over_inputs(lambda ax, sub: None if ax is None else sub)
        first = next((x for x in jax.tree_util.tree_leaves(mapped) if _is_array(x)), None)
        if first is None or np.ndim(first) == 0 or first.shape[0] != 1:
            return vmap(fn)(*args) if in_axes == 0 else vmap(fn, in_axes=in_axes)(*args)
        first_row = lambda x: x[0] if _is_array(x) else x  # noqa: E731
        rows = over_inputs(lambda ax, sub: sub if ax is None else jax.tree_util.tree_map(first_row, sub))
        out = fn(*rows)
        return jax.tree_util.tree_map(lambda x: x[None] if _is_array(x) else x, out)

    return batched


@jax.jit
def take_rows(tree, idx):
    """Rows ``idx`` (an integer or an integer array, within the leading axis: a traced index is not checked) of
    every leaf of ``tree``, in one jitted gather (one program per structure and shapes; indexing leaf by leaf
    outside ``jit`` compiles a small program per leaf)."""
    return jax.tree_util.tree_map(lambda x: x[idx], tree)


def row_index(idx, size: int, name: str = "idx") -> np.ndarray:
    """``idx`` (an int or integer array, NumPy's negative indices counted from the end) as indices in ``[0, size)``
    for :func:`take_rows`; an index outside ``[-size, size)`` or not an integer is an ``IndexError`` naming ``name``
    and the range (a traced index would be clamped silently)."""
    a = np.asarray(idx)
    if a.dtype.kind not in "iu" or np.any(a < -size) or np.any(a >= size):
        raise IndexError(f"{name} must be an int in [-{size}, {size}) (each of its entries), got {a.tolist()!r}")
    return a % size
