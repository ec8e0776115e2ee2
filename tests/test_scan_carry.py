"""hyqjax.core.scan_carry.tie_carry: the carry's values are unchanged bit for bit, its derivative with respect to
the inputs it is tied to is zero, and a scan started from a tied carry has the value and the forward-mode
derivative of the untied one."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core.scan_carry import tie_carry


def test_values_unchanged_bit_for_bit_and_zero_derivative():
    x = jnp.array([-0.0, 0.0, 1.5, -2.25, jnp.inf, -jnp.inf, jnp.nan], jnp.float32)
    carry = dict(x=x, k=jnp.arange(3), flag=jnp.array([True, False]))
    for theta in (jnp.array([0.3, -1.0]), jnp.array([jnp.inf, jnp.nan]), jnp.array([-4.0, 0.0]),
                  [jnp.float32(3e38), jnp.float32(3e38)]):  # the last: a sum that overflows
        out = tie_carry(carry, theta)
        np.testing.assert_array_equal(np.asarray(out["x"]).view(np.uint32), np.asarray(x).view(np.uint32))
        assert out["k"] is carry["k"] and out["flag"] is carry["flag"]
    d = jax.jacfwd(lambda th: tie_carry(jnp.array([1.0, -0.0]), th))(jnp.array([0.3, -1.0]))
    np.testing.assert_array_equal(np.asarray(d), 0.0)


def test_tied_scan_has_the_untied_value_and_derivative():
    """A carry that starts independent of theta (as a rollout from a stored snapshot does) and that the loop
    mixes with theta: value and jacfwd agree with and without the tie, also under vmap over a batch of starts."""
    def run(theta, x0, tie):
        init = (x0, jnp.zeros(2))
        init = tie_carry(init, theta) if tie else init

        def body(c, _):
            x, v = c
            v = 0.9 * v + 0.01 * jnp.sin(x) * theta[0]
            return (x + 0.02 * v + 0.001 * theta[1] * v[::-1], v), None

        (x, v), _ = jax.lax.scan(body, init, None, length=50)
        return jnp.sum(x ** 2) + jnp.sum(v)

    theta = jnp.array([1.3, -0.7])
    x0 = jnp.array([[0.1, -0.2], [0.4, 0.0]])
    for tie in (False, True):
        f = jax.jit(jax.vmap(jax.jacfwd(lambda th, x: run(th, x, tie)), in_axes=(None, 0)))
        g = jax.jit(jax.vmap(lambda th, x: run(th, x, tie), in_axes=(None, 0)))
        if not tie:
            g0, v0 = np.asarray(f(theta, x0)), np.asarray(g(theta, x0))
        else:
            np.testing.assert_array_equal(np.asarray(g(theta, x0)), v0)
            np.testing.assert_allclose(np.asarray(f(theta, x0)), g0, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(g0) > 0)


def _compiled_instructions(n_inputs: int, n_carry: int) -> int:
    """Instructions of the compiled (XLA:CPU) program that ties a batch of ``n_carry`` leaves to ``n_inputs``."""
    theta = [jnp.full((4, 3), float(i)) for i in range(n_inputs)]
    carry = [jnp.full((4, 2), float(i)) for i in range(n_carry)]
    f = jax.jit(jax.vmap(lambda c, th: [x * 2.0 for x in tie_carry(c, th)]))
    text = f.lower(carry, theta).compile().as_text()
    return sum(1 for line in text.splitlines() if " = " in line)


def test_compiled_tie_grows_with_the_leaves_not_their_product():
    """XLA fuses a cheap elementwise producer into each consumer: the sum ``s`` over the inputs is one reduction,
    so 30 more input leaves add about 4 instructions each to the compiled program of 60 tied carry leaves (measured:
    952 -> 1,083), where a chain of scalar additions was copied into every fused carry update (measured: 4,271 ->
    15,101, about 360 each)."""
    n_carry = 60
    per_input = (_compiled_instructions(40, n_carry) - _compiled_instructions(10, n_carry)) / 30
    assert per_input < 20, per_input
