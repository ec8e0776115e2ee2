"""Reverse mode through MJX (:mod:`hyqjax.sim.reverse_mode`) and the reverse-mode tuning step
(:func:`hyqjax.studies.tune.objective.make_value_and_grad_reverse`): the fixed-length solver loop keeps the primal and
is undone on exit; the reverse-mode window rows equal ``jacfwd``'s, with and without the checkpointed scan."""
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
    context gives the same states bit for bit as traced outside; reverse mode traces inside and is refused outside,
    before and after (MJX's names are back, also after an exception, and nested contexts undo only at the end)."""
    import mujoco
    from mujoco import mjx
    from mujoco.mjx._src import solver

    mx = mjx.put_model(mujoco.MjModel.from_xml_string(XML))
    d0 = mjx.make_data(mx)

    def roll(v):
        d = d0.replace(qvel=d0.qvel.at[0].set(v[0]).at[6].set(v[1]))
        d, _ = jax.lax.scan(lambda d, _: (mjx.step(mx, d), None), d, None, length=30)
        return jnp.concatenate([d.qpos, d.qvel])

    v = jnp.asarray([0.3, -0.2])
    grad = lambda: jax.make_jaxpr(jax.grad(lambda v: jnp.sum(roll(v))))(v)  # noqa: E731 (traced, not compiled)
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


# ------------------------------------------------------------------ the tuning step on step-down windows (slow)

#: The window programs below are compiled at XLA's backend optimisation level 0: the same traced programs (what is
#: compared), about 40 % less compile time on the CPU.
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def _call(fn, *args):
    """``fn(*args)`` of a jitted ``fn``, compiled with :data:`FAST_COMPILE`; numpy leaves."""
    out = fn.lower(*args).compile(compiler_options=FAST_COMPILE)(*args)
    return jax.tree_util.tree_map(np.asarray, out)


@pytest.fixture(scope="module")
def windows64():
    """Float64: both front legs' windows of one 24 cm step-down with the shin-strike remedy, started one tick before
    the leg's body phase (the crawl parameters act at once), 50 ticks (the front feet in contact), a prefix of 25
    ticks, and the ``jacfwd`` step's result (the reference) for 7 parameters."""
    from hyqjax.crawl import controller as crawl
    from hyqjax.studies.tune import evaluate, objective, windows
    from hyqjax.studies.tune import space as spmod

    with jax.enable_x64(True):
        su = windows.setup(dtype="float64")
        start = crawl.CrawlParams.make(shin_remedy=True)
        sc, _ = evaluate.scenarios([0.24], 1, 3, params=start)
        win = windows.make_windows(sc, windows.WindowSpec(per_scenario=2, lead=4.0), su)
        sp = spmod.ParamSpace.make(("damping", "body_height", "step_length", "step_height"))
        base = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(
            jnp.asarray(x).dtype, jnp.floating) else x, start)
        obj = objective.ClosedLoopObjective(ticks=50, prefixes=(25,))
        th = jnp.asarray(sp.theta_of(base))
        ref = _call(objective.make_value_and_jac(win, base, sp, obj, su), th, win)
    return win, sp, base, obj, su, th, ref


def _compare(res, ref, prefixes: bool):
    assert res["ok"].all() and ref["ok"].all()
    np.testing.assert_allclose(res["per_window_loss"], ref["per_window_loss"], rtol=1e-12)
    g, g0 = res["per_window_grad"], ref["per_window_grad"]
    assert np.all(np.abs(g0).max(1) > 1e-6)  # every window's row is not zero (the parameters act)
    np.testing.assert_allclose(g, g0, rtol=1e-6, atol=1e-9 * np.abs(g0).max())
    np.testing.assert_allclose(res["grad"], ref["grad"], rtol=1e-6, atol=1e-9 * np.abs(g0).max())
    np.testing.assert_allclose(res["loss"], ref["loss"], rtol=1e-12)
    for k, v in ref["terms"].items():
        np.testing.assert_allclose(res["terms"][k], v, rtol=1e-10, atol=1e-14)
    if prefixes:  # every prefix's rows, the first (25 ticks) included
        np.testing.assert_allclose(res["per_window_prefix_grad"], ref["per_window_prefix_grad"], rtol=1e-6,
                                   atol=1e-9 * np.abs(ref["per_window_prefix_grad"]).max())
        assert not np.allclose(ref["per_window_prefix_grad"][:, 0], ref["per_window_prefix_grad"][:, 1])


@pytest.mark.slow
def test_reverse_mode_window_rows_equal_jacfwd_with_checkpoint(windows64):
    """The checkpointed reverse-mode step (two prefix lengths: one backward pass each) gives ``jacfwd``'s
    per-window rows of both prefixes, the same losses and terms."""
    from hyqjax.studies.tune import objective

    win, sp, base, obj, su, th, ref = windows64
    with jax.enable_x64(True):
        res = _call(objective.make_value_and_grad_reverse(base, sp, obj, su, checkpoint=True), th, win)
    _compare(res, ref, prefixes=True)
