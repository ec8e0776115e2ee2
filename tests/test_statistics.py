"""hyqjax.studies.statistics against independent references (closed forms, brute-force likelihood)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hyqjax.studies import statistics as S


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 5000).flatmap(lambda n: st.tuples(st.integers(0, n), st.just(n))))
def test_wilson_matches_scipy(kn):
    """The closed form against SciPy's Wilson interval (``binomtest(k, n).proportion_ci(method="wilson")``)."""
    from scipy import stats

    k, n = kn
    ref = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    lo, hi = S.wilson_interval(k, n)
    assert lo == pytest.approx(max(0.0, ref.low), abs=1e-12)
    assert hi == pytest.approx(min(1.0, ref.high), abs=1e-12)
    assert lo <= k / n <= hi
    lo99, hi99 = S.wilson_interval(k, n, confidence=0.99)
    ref99 = stats.binomtest(k, n).proportion_ci(confidence_level=0.99, method="wilson")
    assert (lo99, hi99) == pytest.approx((max(0.0, ref99.low), min(1.0, ref99.high)), abs=1e-12)


def test_wilson_edge_cases():
    assert all(math.isnan(v) for v in S.wilson_interval(0, 0))
    with pytest.raises(ValueError, match="k=3"):
        S.wilson_interval(3, 2)


def test_success_curve_and_h95_wilson():
    h = np.repeat([0.16, 0.08, 0.24], 400)
    s = np.concatenate([np.arange(400) < 396, np.ones(400, bool), np.arange(400) < 200])
    curve = S.success_curve(h, s)
    assert [c["height"] for c in curve] == [0.08, 0.16, 0.24]
    assert [c["successes"] for c in curve] == [400, 396, 200]
    # 400/400 and 396/400 have Wilson lower bounds 0.9905 and 0.9746; 200/400 fails.
    assert S.h95_wilson(curve) == 0.16
    assert S.h95_wilson(curve[1:]) == 0.16
    assert S.h95_wilson([dict(height=0.1, n=10, successes=5, rate=0.5, ci95=[0.2, 0.8])]) is None
    levels = np.repeat([2, 0, 1], 400)
    assert [c["n"] for c in S.success_curve(h, s, levels=levels)] == [400, 400, 400]


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_logistic_fit_is_the_likelihood_maximum(seed):
    """The fit is a stationary point of the likelihood and no point of a grid around it is better."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 300))
    x = rng.choice(np.linspace(0.04, 0.34, 7), n)
    y = (rng.uniform(size=n) < 1 / (1 + np.exp(-(rng.uniform(2, 10) - rng.uniform(10, 50) * x)))).astype(float)
    fit = S.logistic_fit(x, y)
    if y.all() or not y.any():
        assert fit is None
        return
    a, b = fit

    def nll(a, b):
        z = a + b * x
        return np.sum(np.logaddexp(0.0, z) - y * z) + 0.5e-6 * (a * a + b * b)

    best = nll(a, b)
    for da in np.linspace(-1e-3, 1e-3, 5) * max(1, abs(a)):
        for db in np.linspace(-1e-3, 1e-3, 5) * max(1, abs(b)):
            assert nll(a + da, b + db) >= best - 1e-9 * max(1.0, best)
    h = S.h95_logistic(x, y)
    crossing = (math.log(19.0) - a) / b if b < 0 else None
    if crossing is not None and x.min() <= crossing <= x.max():
        assert 1 / (1 + math.exp(-(a + b * h))) == pytest.approx(0.95, abs=1e-9)
    else:  # no fit, b >= 0, or a crossing outside the measured heights (no extrapolation)
        assert h is None


def test_height_summary_keys():
    x = np.repeat([0.1, 0.2, 0.3], 100)  # 100/100: Wilson lower bound 0.963
    s = np.concatenate([np.ones(100, bool), np.arange(100) < 80, np.arange(100) < 10])
    out = S.height_summary(x, s)
    assert set(out) == {"height_curve", "h95_wilson", "h95_logistic"}
    assert out["h95_wilson"] == 0.1 and 0.1 < out["h95_logistic"] < 0.2


def test_mean_interval():
    v = np.random.default_rng(0).normal(2.0, 1.0, 10000)
    lo, hi = S.mean_interval(v)
    assert lo < v.mean() < hi and hi - lo == pytest.approx(2 * 1.959964 * v.std(ddof=1) / 100, rel=1e-6)


def test_h95_logistic_does_not_extrapolate_a_flat_fit():
    from hyqjax.studies import statistics

    rng = np.random.default_rng(0)
    x = np.repeat([0.12, 0.16, 0.20, 0.24], 200)
    y = (rng.random(x.size) < 0.6).astype(float)  # flat at 60%: the 95% crossing is not in the data
    assert statistics.h95_logistic(x, y) is None
    y2 = (rng.random(x.size) < 1 / (1 + np.exp(-(12 - 60 * x)))).astype(float)  # crosses 95% near 0.15 m
    h = statistics.h95_logistic(x, y2)
    assert h is not None and 0.12 <= h <= 0.24
