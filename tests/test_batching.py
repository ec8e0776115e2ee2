"""hyqjax.core.batching: ``vmap`` over a batch, skipped for a batch of one."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core.batching import vmap_unless_one


def _f(x, scale, tag):
    """A function with a scan (whose batching a batch of one skips), a pytree output and a non-array argument."""
    y, ys = jax.lax.scan(lambda c, _: (c * scale + 1.0, c), x, None, length=3)
    return {"y": y, "ys": ys, "n": jnp.sum(x)}, tag


def test_a_batch_of_one_is_the_single_call_with_the_axis_put_back_and_traces_no_batching():
    x = jnp.asarray([[1.0, 2.0]], jnp.float32)
    s = jnp.asarray([0.5], jnp.float32)
    one, tag = vmap_unless_one(lambda a, b: _f(a, b, "t"))(x, s)
    ref, _ = _f(x[0], s[0], "t")
    assert tag == "t"
    for k in ("y", "ys", "n"):
        assert one[k].shape == (1,) + ref[k].shape
        np.testing.assert_array_equal(np.asarray(one[k][0]), np.asarray(ref[k]))
    jaxpr = jax.make_jaxpr(vmap_unless_one(lambda a, b: _f(a, b, "t")[0]))(x, s)
    plain = jax.make_jaxpr(lambda a, b: _f(a[0], b[0], "t")[0])(x, s)
    scans = [e for e in jaxpr.eqns if e.primitive.name == "scan"]
    assert len(scans) == 1 and str(scans[0].params["jaxpr"]) == str(
        next(e for e in plain.eqns if e.primitive.name == "scan").params["jaxpr"])  # the unbatched loop body


def test_a_larger_batch_is_vmap():
    x = jnp.asarray([[1.0, 2.0], [3.0, -1.0], [0.0, 0.5]], jnp.float32)
    s = jnp.asarray([0.5, 2.0, -1.0], jnp.float32)
    got = vmap_unless_one(lambda a, b: _f(a, b, None)[0])(x, s)
    ref = jax.vmap(lambda a, b: _f(a, b, None)[0])(x, s)
    for k in ref:
        np.testing.assert_array_equal(np.asarray(got[k]), np.asarray(ref[k]))
    for i in range(3):  # each row is its own batch of one
        row = vmap_unless_one(lambda a, b: _f(a, b, None)[0])(x[i:i + 1], s[i:i + 1])
        np.testing.assert_allclose(np.asarray(row["y"][0]), np.asarray(ref["y"][i]), rtol=1e-6)


def test_in_axes_with_unmapped_inputs_as_vmap():
    """``in_axes`` with None (an input passed whole) in a pytree, as ``jax.vmap``'s, for a batch of one and of two."""
    def g(p, x):
        return p["w"] * x + p["b"], jnp.sum(p["w"])

    p = {"w": jnp.asarray([[1.0, 2.0]], jnp.float32), "b": jnp.asarray(3.0, jnp.float32)}
    axes = ({"w": 0, "b": None}, 0)
    for x in (jnp.asarray([[0.5, -1.0]], jnp.float32), jnp.asarray([[0.5, -1.0], [2.0, 0.0]], jnp.float32)):
        pw = {"w": jnp.broadcast_to(p["w"], x.shape), "b": p["b"]}
        got = vmap_unless_one(g, in_axes=axes)(pw, x)
        ref = jax.vmap(g, in_axes=axes)(pw, x)
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    try:
        vmap_unless_one(g, in_axes=(1, 0))(p, x)
    except ValueError as e:
        assert "axis 0 or None" in str(e)
    else:
        raise AssertionError("in_axes 1 accepted")
