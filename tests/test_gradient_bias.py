"""The zero-order reference of the gradient-bias study (hyqjax.studies.tune.study.bias) on functions with known
gradients: it estimates the smoothed objective's gradient without bias, its halves agree as their noise allows,
and a step-function objective (a contact event) has a smoothed gradient where the pathwise one is zero."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.studies.tune.study import bias


def test_smoothed_gradient_of_a_quadratic_is_its_gradient():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(6, 6)), rng.normal(size=6)
    f = lambda ts: jnp.sum((ts @ jnp.asarray(a.T, jnp.float32) - jnp.asarray(b, jnp.float32)) ** 2, -1)  # noqa: E731
    theta = rng.normal(size=6)
    true = 2 * a.T @ (a @ theta - b)
    z = bias.smoothed_gradient(f, theta, 0.1, 4096, jax.random.key(1))
    assert bias.cosine(z["grad"], true) > 0.98
    assert bias.cosine(z["grad_a"], z["grad_b"]) > 0.9
    assert z["non_finite"] == 0


def test_smoothed_gradient_sees_a_step_the_pathwise_gradient_misses():
    """L = 1[theta_0 > 0]: its pathwise gradient is 0 almost everywhere; the smoothed objective's gradient at 0 is
    the Gaussian density 1 / (sigma sqrt(2 pi)) along theta_0."""
    f = lambda ts: (ts[:, 0] > 0).astype(jnp.float32)  # noqa: E731
    s = 0.2
    z = bias.smoothed_gradient(f, np.zeros(3), s, 8192, jax.random.key(2))
    np.testing.assert_allclose(z["grad"][0], 1.0 / (s * np.sqrt(2 * np.pi)), rtol=0.1)
    assert abs(z["grad"][1]) < 0.2 and abs(z["grad"][2]) < 0.2


def test_bad_settings_and_the_comparison_table():
    with pytest.raises(ValueError, match="pairs"):
        bias.smoothed_gradient(lambda ts: ts[:, 0], np.zeros(2), 0.1, 1, jax.random.key(0))
    w = np.array([[1.0, 0.0], [1.2, 0.1], [0.8, -0.1]])
    r = dict(grad=w.mean(0), per_window_prefix_grad=w[:, None, :], ok=np.ones(3, bool), loss=1.0)
    zo = {0.1: dict(grad=np.array([1.0, 0.0]), grad_a=np.array([1.0, 0.1]), grad_b=np.array([1.0, -0.1]),
                    non_finite=0)}
    res = bias.compare({"plain": r}, zo, (10,), ["a", "b"])
    assert res["variants"]["plain"]["cosine"]["0.1"] == pytest.approx(1.0)
    assert res["zero_order"][0.1]["ceiling"] == pytest.approx(bias.cosine([1, 0.1], [1, -0.1]))
    assert "plain" in bias.table(res)
