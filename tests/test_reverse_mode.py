"""Reverse mode through MJX (:mod:`hyqjax.sim.reverse_mode`): the fixed-length solver loop keeps the primal, has a
reverse derivative and is undone on exit. The reverse-mode tuning step's rows against ``jacfwd``'s on step-down
windows are tested with the tuner's float64 windows (``tests/test_tune.py``)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.sim import reverse_mode


def test_bounded_while_loop_equals_the_while_loop_and_has_a_reverse_derivative():
    """Pure JAX (unit lane): the fixed-length loop stops where the ``while_loop`` stops (later steps are no-ops),
    whatever the bound above the trip count, and reverse mode through it equals forward mode."""
    def cond(c):
        i, x = c
        return (i < 5) & (x < 3.0)

    def body(c):
        i, x = c
        return i + 1, x * x + 0.5

    def run(loop, x):
        return loop((jnp.int32(0), x))[1]

    wl = lambda c: jax.lax.while_loop(cond, body, c)  # noqa: E731
    for x0 in (0.1, 1.2, 5.0):  # 5, 2 and 0 iterations
        ref = run(wl, jnp.float32(x0))
        for bound in (5, 9):
            fixed = lambda c, b=bound: reverse_mode.bounded_while_loop(cond, body, c, b)  # noqa: E731
            assert float(run(fixed, jnp.float32(x0))) == float(ref)
            g = jax.grad(lambda x: run(fixed, x))(jnp.float32(x0))
            assert float(g) == pytest.approx(float(jax.jacfwd(lambda x: run(wl, x))(jnp.float32(x0))), rel=1e-6)
    with pytest.raises(ValueError, match="Reverse-mode"):
        jax.grad(lambda x: run(wl, x))(jnp.float32(1.2))


XML = """<mujoco><option timestep="0.005" iterations="4"/>
<worldbody><geom type="plane" size="2 2 0.1"/>
<body pos="0 0 0.1"><freejoint/><geom type="box" size="0.1 0.1 0.1" mass="1"/></body>
<body pos="0.4 0 0.15"><freejoint/><geom type="sphere" size="0.1" mass="1"/></body>
</worldbody></mujoco>"""


@pytest.mark.slow
def test_fixed_length_solver_keeps_the_primal_and_restores_mjx():
    """A box resting on a plane and a falling ball (contacts, the solver iterates): ``mjx.step`` traced inside the
    context gives the same states bit for bit over 30 steps as traced outside; reverse mode through a step traces
    inside and is refused outside, before and after (MJX's names are back, also after an exception, and nested
    contexts undo only at the end)."""
    import mujoco
    from mujoco import mjx
    from mujoco.mjx._src import solver

    mx = mjx.put_model(mujoco.MjModel.from_xml_string(XML))
    d0 = mjx.make_data(mx)

    def start(v):  # the box's and the ball's initial x velocities
        return d0.replace(qvel=d0.qvel.at[0].set(v[0]).at[6].set(v[1]))

    def roll(v):
        d, _ = jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), start(v), None, length=30)
        return jnp.concatenate([d.qpos, d.qvel])

    def step(v):  # one step: its solver loop is the one every step of ``roll`` runs
        return jnp.sum(mjx.step(mx, start(v)).qvel)

    v = jnp.asarray([0.3, -0.2])
    grad = lambda: jax.make_jaxpr(jax.grad(step))(v)  # noqa: E731 (traced, not compiled)
    names = (solver.jax, solver.solve)
    out = np.asarray(jax.jit(roll)(v))
    with reverse_mode.fixed_length_solver():
        assert reverse_mode.is_active() and solver.solve is not names[1]
        inside = np.asarray(jax.jit(roll)(v))
        with reverse_mode.fixed_length_solver():
            pass
        assert grad().eqns  # reverse mode traces (after the nested context's exit too)
    assert (solver.jax, solver.solve) == names and solver.jax is jax and not reverse_mode.is_active()
    np.testing.assert_array_equal(inside, out)
    assert abs(out[2] - 0.1) < 0.01 and abs(out[9] - 0.1) < 0.01  # the box rests, the ball has landed
    with pytest.raises(ValueError, match="Reverse-mode"):
        grad()
    with pytest.raises(RuntimeError, match="inside"):
        with reverse_mode.fixed_length_solver():
            raise RuntimeError("inside")
    assert (solver.jax, solver.solve) == names and not reverse_mode.is_active()
