"""Gradient tuning of the height reflex (hyqjax.tune): gradients, optimisation, checkpoint/resume."""
from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax import reflex as hreflex, tune

SMALL_OBJ = tune.Objective(duration=0.5, t_lift=0.05, lift=0.02)


def small_cfg(**kw):
    return tune.TuneConfig(**{**dict(steps=4, batch=3, seed=0, lr=0.1, checkpoint_every=2, depth=(0.02, 0.06),
                                     objective=SMALL_OBJ), **kw})


def test_gradient_matches_central_differences(x64):
    sc = tune.make_scenarios(2, 5, depth=(0.02, 0.05), dtype=jnp.float64)
    groups = ("k_base", "damping", "mobility", "k_x", "k_kl", "delta")
    theta = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64),
                                   tune.theta_from_reflex(hreflex.ReflexParams.table1(), groups))
    # Start off Table I, inside the schedule's transition band, so every parameter matters.
    theta = {**theta, "logit_m_max": theta["logit_m_max"] - 0.3}
    f = jax.jit(lambda th: tune.loss_fn(th, sc, SMALL_OBJ)[0])
    g = jax.jit(jax.grad(lambda th: tune.loss_fn(th, sc, SMALL_OBJ)[0]))(theta)
    assert all(np.isfinite(float(v)) for v in g.values())
    assert any(abs(float(v)) > 0 for v in g.values())
    rng = np.random.default_rng(0)
    for _ in range(2):
        v = {k: jnp.asarray(rng.standard_normal(), jnp.float64) for k in theta}
        eps = 1e-5
        fd = (float(f({k: theta[k] + eps * v[k] for k in theta})) -
              float(f({k: theta[k] - eps * v[k] for k in theta}))) / (2 * eps)
        ad = sum(float(g[k] * v[k]) for k in theta)
        assert ad == pytest.approx(fd, rel=1e-4, abs=1e-8)


def test_reparameterisation_stays_valid():
    rng = np.random.default_rng(1)
    groups = tuple(tune.GROUPS)
    base = tune.theta_from_reflex(hreflex.ReflexParams.table1(), groups)
    back = tune.reflex_values(tune.reflex_from_theta(base))
    for k, v in tune.reflex_values(hreflex.ReflexParams.table1()).items():
        assert back[k] == pytest.approx(v, rel=1e-5), k
    for _ in range(20):
        th = {k: v + 3.0 * rng.standard_normal() for k, v in base.items()}
        vals = tune.reflex_values(tune.reflex_from_theta(th))
        hreflex.ReflexParams(**vals).validate()  # raises if out of range


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    cfg = small_cfg()
    full = str(tmp_path_factory.mktemp("tune_full"))
    part = str(tmp_path_factory.mktemp("tune_part"))
    r_full = tune.run_tune(cfg, full, progress=False)
    r_part = tune.run_tune(cfg, part, stop_after=2, progress=False)
    assert r_part["step"] == 2
    r_resumed = tune.run_tune(cfg, part, progress=False)
    return cfg, full, part, r_full, r_resumed


def test_loss_decreases_and_log(runs):
    cfg, full, _, r_full, _ = runs
    log = tune.read_log(full)
    assert [r["step"] for r in log] == [0, 1, 2, 3]
    assert log[-1]["loss"] < log[0]["loss"]
    for r in log:
        assert np.isfinite(r["loss"]) and np.isfinite(r["grad_norm"]) and r["grad_norm"] > 0
        assert set(r["params"]) >= {"k_base", "d_sw_min", "d_sw_max", "d_st_min", "d_st_max", "m_min", "m_max"}
        assert r["params"]["m_min"] < r["params"]["m_max"]
    assert log[0]["params"]["k_base"] == pytest.approx(1500.0, rel=1e-5)
    assert os.path.exists(os.path.join(full, "checkpoint.npz"))
    with open(os.path.join(full, "config.json")) as f:
        assert json.load(f)["hash"] == cfg.hash


def test_resume_continues_and_matches_uninterrupted(runs):
    cfg, full, part, r_full, r_resumed = runs
    assert r_resumed["step"] == 4
    for k in r_full["theta"]:
        np.testing.assert_allclose(np.asarray(r_resumed["theta"][k]), np.asarray(r_full["theta"][k]), rtol=1e-6)
    assert [r["step"] for r in tune.read_log(part)] == [0, 1, 2, 3]
    np.testing.assert_allclose([r["loss"] for r in tune.read_log(part)],
                               [r["loss"] for r in tune.read_log(full)], rtol=1e-6)
    # Further steps continue the counter; another configuration is refused.
    r6 = tune.run_tune(small_cfg(steps=6), part, progress=False)
    assert r6["step"] == 6 and [r["step"] for r in tune.read_log(part)] == list(range(6))
    with pytest.raises(RuntimeError, match="another configuration"):
        tune.run_tune(small_cfg(lr=0.2), part, progress=False)


def test_random_search_budget():
    cfg = small_cfg()
    rs = tune.random_search(cfg, 5, seed=3)
    assert len(rs["curve"]) == 5
    assert all(b <= a for a, b in zip(rs["curve"], rs["curve"][1:]))
    hreflex.ReflexParams(**tune.reflex_values(rs["params"])).validate()


@pytest.mark.parametrize("kw, match", [(dict(steps=-1), "steps must be"), (dict(lr=0.0), "lr must be"),
                                       (dict(groups=("k_base", "spring")), "groups must be")])
def test_config_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        small_cfg(**kw)
