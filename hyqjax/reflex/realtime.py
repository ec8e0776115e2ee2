"""The height reflex as one flat-vector function, for a hard real-time control loop.

:func:`hyqjax.reflex.step.reflex_step` takes and returns PyTrees (19 input and 15 output arrays). Called
once per tick from Python, a jitted call of that signature spends most of its time in JAX's dispatch
of the arrays, not in the reflex (see ``benchmarks/RESULTS.md``). A robot's 1 kHz loop calls the
reflex once per tick with fixed parameters, so :func:`make_realtime_reflex` packs everything that
changes per tick into one vector in and one vector out and closes over the parameters:

``packed_in = [q_r (12), qd_r (12), x_des (12), swing_leg, active, n_t_des (3), up (3)]`` (44 values)

``packed_out = [q_r (12), qd_r (12), x_r (12), xd_r (12), mobility (4), d_diag (12), flags (4)]``
(68 values; ``flags = [active, degenerate, input_ok, failed]`` as 0/1). The first 24 output values are the
next tick's state, so a loop feeds ``out[:24]`` back as ``in[:24]``.

The arithmetic is exactly :func:`~hyqjax.reflex.step.reflex_step`'s (a test checks equality).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from hyqjax.reflex import step as reflex
from hyqjax.reflex.params import check_dt

N_IN = 44
N_OUT = 68
#: Slices of the packed output.
OUT_STATE = slice(0, 24)
OUT_X_R = slice(24, 36)
OUT_XD_R = slice(36, 48)
OUT_MOBILITY = slice(48, 52)
OUT_D_DIAG = slice(52, 64)
OUT_FLAGS = slice(64, 68)


def pack_inputs(state: reflex.ReflexState, inputs: reflex.ReflexInputs) -> jax.Array:
    """``(44,)`` vector of the state and the tick's inputs (layout in the module docstring)."""
    dtype = state.q_r.dtype
    return jnp.concatenate([
        state.q_r, state.qd_r, jnp.reshape(inputs.x_des, 12).astype(dtype),
        jnp.asarray(inputs.swing_leg, dtype)[None], jnp.asarray(inputs.active, dtype)[None],
        jnp.asarray(inputs.n_t_des, dtype), jnp.asarray(inputs.up, dtype),
    ])


def unpack_inputs(v: jax.Array) -> tuple[reflex.ReflexState, reflex.ReflexInputs]:
    """Inverse of :func:`pack_inputs`."""
    state = reflex.ReflexState(q_r=v[0:12], qd_r=v[12:24])
    inputs = reflex.ReflexInputs(x_des=v[24:36].reshape(4, 3), swing_leg=jnp.round(v[36]).astype(jnp.int32),
                                 active=v[37] > 0.5, n_t_des=v[38:41], up=v[41:44])
    return state, inputs


def pack_outputs(out: reflex.ReflexOutput) -> jax.Array:
    """``(68,)`` vector of the outputs a controller needs (layout in the module docstring)."""
    dtype = out.q_r.dtype
    flags = jnp.stack([out.active, out.degenerate, out.input_ok, out.failed]).astype(dtype)
    return jnp.concatenate([out.q_r, out.qd_r, out.x_r.reshape(12), out.xd_r.reshape(12), out.mobility,
                            out.d_diag, flags])


def make_realtime_reflex(params: reflex.ReflexParams, dt: float, dtype=jnp.float32):
    """A compiled ``step(packed_in) -> packed_out`` for fixed ``params`` and control period ``dt``.

    Validates ``params`` and ``dt`` here (ranges and the step-size stability condition; clear errors,
    before compiling), then compiles ahead of time for a ``(44,)`` vector of ``dtype`` on the default device.
    """
    check_dt(dt)
    params.validate(dt=float(dt))
    p = jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), params)

    def step(v):
        state, inputs = unpack_inputs(v)
        _, out = reflex.reflex_step(state, inputs, p, dt)
        return pack_outputs(out)

    return jax.jit(step).lower(jax.ShapeDtypeStruct((N_IN,), dtype)).compile()
