"""``vmap`` over a batch, skipped for a batch of one.

Under ``jax.vmap`` a derivative program through an MJX rollout is traced once more by the batching rules of its
loops: ``scan``'s rule batches the loop body again until the batching of its carries settles, and so does every
loop nested in it. For the bound's cycle optimisation and its robust study that trace is 5-20 s on a CPU
(benchmarks/RESULTS.md). A batch of one gains nothing from it, so :func:`vmap_unless_one` calls the function on
the one row instead and puts the batch axis back; the values are those of the ``vmap`` program up to rounding (the
two programs are compiled separately).
"""
from __future__ import annotations

from typing import Callable

import jax
import numpy as np

__all__ = ["vmap_unless_one"]


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray))


def vmap_unless_one(fn: Callable, vmap: Callable = jax.vmap) -> Callable:
    """``vmap(fn)`` (``jax.vmap`` or e.g. ``equinox.filter_vmap``, mapping over the leading axis of every array
    input), except for a batch of one (the leading axis of the first array input, a static shape): then ``fn`` on
    every array input's first row, with a leading axis of one put on every array output. Inputs and outputs that
    are not arrays pass through unchanged."""

    def batched(*args):
        first = next((x for x in jax.tree_util.tree_leaves(args) if _is_array(x)), None)
        if first is None or np.ndim(first) == 0 or first.shape[0] != 1:
            return vmap(fn)(*args)
        out = fn(*jax.tree_util.tree_map(lambda x: x[0] if _is_array(x) else x, args))
        return jax.tree_util.tree_map(lambda x: x[None] if _is_array(x) else x, out)

    return batched
