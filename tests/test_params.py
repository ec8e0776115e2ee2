"""Parameter declarations (hyqjax.core.params): one definition per parameter, validated wherever built."""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hyqjax.control.impedance import ImpedanceGains
from hyqjax.core import kinematics
from hyqjax.core.params import ParameterError, batch_params, param_orderings, param_ranges
from hyqjax.reflex.params import ReflexParams

SPECS = param_ranges(ReflexParams)


def _in_range(spec, u):
    """A value inside ``spec``'s range from ``u`` in [0, 1] (log scale where declared)."""
    lo = max(spec.lo, 1e-9) if spec.lo_open else spec.lo
    hi = spec.hi * (1 - 1e-9) if spec.hi_open else spec.hi
    if spec.scale == "log":
        return float(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))
    return float(lo + u * (hi - lo))


def _satisfies_declaration(values):
    ok = all(SPECS[n].in_range(np.asarray(v)).all() for n, v in values.items())
    for o in param_orderings(ReflexParams):
        a, b = values[o.lhs], values[o.rhs]
        ok &= bool(a < b) if o.op == "<" else bool(a <= b)
    return ok


field_values = st.fixed_dictionaries({
    n: st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                 st.floats(0, 1).map(lambda u, s=s: _in_range(s, u)))
    for n, s in SPECS.items()
})


@settings(max_examples=300, deadline=None)
@given(field_values)
def test_construction_accepts_exactly_the_declared_set(values):
    """``ReflexParams(**v)`` succeeds iff every field is in its declared range and every ordering holds;
    a refusal is one line that names a field that violates its declaration."""
    expected = _satisfies_declaration(values)
    try:
        p = ReflexParams(**values)
    except ParameterError as e:
        assert not expected, str(e)
        assert "\n" not in str(e) and str(e).startswith(f"ReflexParams.{e.param}=")
        assert e.param in SPECS
        return
    assert expected
    assert p.validate() is p


@settings(max_examples=50, deadline=None)
@given(st.integers(1, 6), st.integers(0, 5), st.floats(0.0, 1.0))
def test_batched_validation_checks_every_element(n, bad_index, u):
    """A batch is refused iff one element is out of range, and the message shows that element."""
    good = np.full(n, 1e-3 + u * 99.0)  # in range and below d_sw_max = 100
    batch = batch_params(ReflexParams(), n, d_sw_min=good)
    assert batch.d_sw_min.shape == (n,) and batch.k_x.shape == (n,)
    assert batch.validate() is batch
    if bad_index < n:
        bad = good.copy()
        bad[bad_index] = -5.0
        with pytest.raises(ParameterError, match=r"ReflexParams\.d_sw_min=-5 out of range: must be in \[0\.001"):
            batch_params(ReflexParams(), n, d_sw_min=bad)


def test_issue_examples_refused():
    cases = [
        (lambda: ReflexParams(d_sw_min=-5),
         "ReflexParams.d_sw_min=-5 out of range: must be in [0.001, 100000] N m s/rad"),
        (lambda: ReflexParams().replace(m_min=0.5), "ReflexParams.m_min=0.5 out of range: must be < m_max=0.21"),
        (lambda: ImpedanceGains(kp=-300), "ImpedanceGains.kp=-300 out of range: must be in (0, 5000] N m/rad"),
        (lambda: ImpedanceGains.make(kd=(1.0, 2.0)), "ImpedanceGains.kd=array of shape (2,) has a wrong shape"),
    ]
    for build, message in cases:
        with pytest.raises(ParameterError) as e:
            build()
        assert str(e.value).startswith(message), str(e.value)
    for shape in ((5,), (13,), (4, 4)):
        with pytest.raises(ParameterError, match=r"kinematics\.foot_positions\.q=array of shape .* must be of shape "
                                                 r"\(\.\.\., 12\) or \(\.\.\., 4, 3\)"):
            kinematics.foot_positions(jnp.zeros(shape))
    with pytest.raises(ParameterError, match=r"kinematics\.foot_velocities\.jac=array of shape \(4, 3\) .* must be of "
                                             r"shape \(\.\.\., 4, 3, 3\)"):
        kinematics.foot_velocities(jnp.zeros(12), jnp.zeros(12), jac=jnp.zeros((4, 3)))
    with pytest.raises(ParameterError, match=r"kinematics\.inverse_kinematics\.x_feet"):
        kinematics.inverse_kinematics(jnp.zeros((3, 3)))


def test_pytree_transformations_do_not_validate_and_work():
    p = ReflexParams()
    assert len(jax.tree.leaves(p)) == len(SPECS)
    # tree.map to any values (here negative) builds without validation: transformations need it.
    neg = jax.tree.map(lambda a: -jnp.asarray(a), p)
    assert float(neg.k_x) == -5000.0
    # grad, vmap and jit through the PyTree; construction inside jit (traced values) is not checked.
    g = jax.grad(lambda q: q.k_x * q.k_base)(p)
    assert float(g.k_x) == 1500.0 and float(g.k_base) == 5000.0
    b = batch_params(p, 3, k_base=[1.0, 2.0, 3.0])
    np.testing.assert_array_equal(jax.vmap(lambda q: 2 * q.k_base)(b), [2.0, 4.0, 6.0])
    assert float(jax.jit(lambda k: ReflexParams(k_x=k, k_x_max=k).k_x)(-1.0)) == -1.0
    assert jax.eval_shape(lambda q: q, p).k_x.shape == ()
    paths = [jax.tree_util.keystr(k) for k, _ in jax.tree_util.tree_flatten_with_path(p)[0]]
    assert paths[:2] == [".k_x", ".k_x_max"]


def test_batch_params_nested_and_dtypes():
    from hyqjax.control.stand import StandParams

    s = StandParams.make()
    b = batch_params(s, 4, gains=dict(kp=np.full((4, 3), 200.0)), **{"gains.kd": [[1.0], [2.0], [3.0], [4.0]]})
    assert b.gains.kp.shape == (4, 3) and b.gains.kp.dtype == jnp.float32 and b.q_ref.shape == (4, 12)
    np.testing.assert_array_equal(b.gains.kd[:, 0], [1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ParameterError, match=r"ImpedanceGains\.kd=0 out of range"):
        batch_params(s, 2, **{"gains.kd": [[1.0], [0.0]]})
    with pytest.raises(ParameterError, match=r"StandParams\.gain="):
        batch_params(s, 2, gain=1.0)


def test_declarations_feed_help_and_reparameterisation():
    """Each declaration gives help text, and constrain/unconstrain is a bijection onto the range."""
    for name, spec in SPECS.items():
        assert spec.unit or name in (), name
        assert spec.range_text in spec.help()
        theta = np.linspace(-8, 8, 9)
        v = np.asarray(spec.constrain(jnp.asarray(theta, jnp.float32)), np.float64)
        assert spec.in_range(v).all() or not spec.hi_open, name
        back = spec.constrain(jnp.asarray(spec.unconstrain(spec.default), jnp.float64)) if jax.config.jax_enable_x64 \
            else None
        if back is not None:
            np.testing.assert_allclose(back, spec.default, rtol=1e-6)
    assert dataclasses.fields(ReflexParams)[0].metadata["param"].unit == "N/m"


def test_reparameterisation_roundtrip_float64(x64):
    for name, spec in SPECS.items():
        back = float(spec.constrain(jnp.asarray(spec.unconstrain(spec.default), jnp.float64)))
        np.testing.assert_allclose(back, spec.default, rtol=1e-6, err_msg=name)


@pytest.mark.parametrize("shape, pattern, ok", [
    ((4, 3), (4, 3), True), ((4, 3), (3, 4), False), ((4, 3), (4,), False), ((4, 3), (None, 3), True),
    ((4, 3), (..., 3), True), ((2, 5, 4, 3), (..., 4, 3), True), ((2, 5, 4, 3), (..., 5, 3), False),
    ((12,), (..., 12), True), ((), (...,), True), ((3,), (..., 4, 3), False), ((7, 1, 12), (7, ..., 12), True),
    ((7, 12), (7, ..., 1, 12), False)])
def test_shape_patterns_match_as_chex_assert_shape(shape, pattern, ok):
    """hyqjax.core.shapes.shape_matches against chex.assert_shape's rule for the same patterns."""
    import chex

    from hyqjax.core.shapes import shape_matches

    try:
        chex.assert_shape(np.zeros(shape), pattern)
        ref = True
    except AssertionError:
        ref = False
    assert shape_matches(shape, pattern) == ref == ok
