"""A scan's initial carry tied to the inputs a transformation follows, so that ``lax.scan``'s rules iterate less.

``jax.lax.scan``'s forward-mode rule (``jvp``) and its batching rule (``vmap``) each find, by fixed-point iteration,
which parts of the carry have a non-zero tangent and which are batched: they transform the whole loop body, see
which carry outputs came out non-zero / batched, widen the carry's pattern and transform the body again, until it
stops changing. A carry that starts independent of the differentiated or batched inputs (a closed-loop rollout's
state from a stored snapshot, differentiated with respect to controller parameters) becomes dependent on them one
loop-carried hop at a time, so the body (MJX's step with a controller: about 10^5 primitives) is transformed several
times over; under ``jacfwd`` (``vmap`` of ``jvp``) both iterations nest.

:func:`tie_carry` subtracts ``|0 * s|`` from every inexact leaf ``x`` of the carry, with ``s`` a scalar that depends
on every leaf of ``inputs`` (their non-finite values read as 0; one reduction, so that XLA does not copy it into each
fused update of the carry): that is ``x - (+0.0)``, which is ``x`` bit for bit (signed zeros, infinities and NaNs of
``x`` included), and the carry enters the loop with a non-zero tangent and batched wherever ``inputs`` are, the fixed
point the rules reach anyway for a carry that the loop mixes with the inputs, so they iterate less. Measured on the
window objective's per-robot ``jacfwd`` (14 tangents, 2 robots x 260 ticks, float64, one idle CPU core): tracing 45 s
-> 32 s, compiling 47 s -> 42 s, the same values to 1e-17. It is no rule for every scan: tied to the parameters in the
generic rollout (:func:`hyqjax.sim.rollout.rollout_advance`) it made the bounding programs slower to compile (carry
parts that stay unbatched or tangent-free there were forced to be both), so it is used where it was measured to pay:
the window objective, and the generic rollout of a controller that asks for it
(:attr:`hyqjax.core.types.Controller.tie_rollout_carry`: the crawl; ``jax.jacfwd`` of its step-down traced and lowered
in 11.1-12.3 s instead of 19.5-24.4 s; the bound's differentiated rollouts,
:data:`hyqjax.bounding.cycle.DIFFERENTIATED_CONTROLLER`, since the tie is one reduction: its robust cost's ``jacfwd``
traced in 7.1-7.3 s instead of 11.9-12.0 s, XLA unchanged).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def tie_carry(carry, inputs):
    """``carry`` with ``|0 * s|`` subtracted from each inexact leaf, ``s`` the sum of the first element of every
    inexact leaf of ``inputs``, a non-finite one read as 0, and ``s`` itself read as 0 if the sum overflows (module
    docstring). Integer and boolean leaves are returned as they are.

    ``s`` is one reduction over a stacked vector, not a chain of scalar adds: XLA fuses a cheap elementwise producer
    into every consumer, so a chain of additions over the ~50 parameters was copied into each of the ~90 fused
    updates of the carry (14,700 instructions at these lines in a 2-instance step-down program on MJX-JAX, whose
    optimised HLO went from 63,301 to 44,868 lines with the reduction); a reduction is computed once."""
    firsts = [jnp.ravel(x)[0] for x in jax.tree_util.tree_leaves(inputs)
              if jnp.issubdtype(jnp.result_type(x), jnp.inexact) and jnp.size(x) > 0]
    if not firsts:
        return carry
    v = jnp.stack(firsts)  # promoted to their common type
    s = jnp.sum(jnp.where(jnp.isfinite(v), v, 0))
    zero = jnp.abs(0 * jnp.where(jnp.isfinite(s), s, 0))  # +0.0, whatever the inputs hold

    def tie(x):
        if not jnp.issubdtype(jnp.result_type(x), jnp.inexact):
            return x
        return x - zero.astype(jnp.result_type(x))

    return jax.tree_util.tree_map(tie, carry)
