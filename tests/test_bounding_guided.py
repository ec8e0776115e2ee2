"""hyqjax.bounding.guided and ``experiments.bounding_refine --methods``: guided ES on the robust bounding coordinates
against CMA-ES at equal wall-clock. Without physics: the per-generation cosine on a linear function, the clock and
the budget; the option checks; compiled (slow): the surrogate gradient against central differences of its own
value, and a tiny end-to-end comparison on C MuJoCo with the MJX-JAX gradient."""
from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from experiments import bounding_refine as br
from hyqjax.bounding import guided as bg
from hyqjax.bounding import robust as rb


def test_cosine_is_one_on_a_linear_function_with_the_true_gradient():
    """On ``f(x) = c . x`` every antithetic pair measures ``2 z . c`` exactly, so in every generation the cosine of a
    surrogate equal to ``c`` with the pairs' least-squares gradient (inside the span they explored) is 1 and the slope
    along it is ``|c|``; a surrogate unrelated to ``c`` gets cosines spread around 0, not 1."""
    rng = np.random.default_rng(3)
    p = 22
    c = rng.standard_normal(p)

    def f_pop(xs):
        return xs @ c

    out = bg.guided_es(f_pop, lambda th: dict(loss=float(th @ c), grad=c), np.zeros(p), 60.0, 16, sigma=0.7,
                       max_generations=12)
    h = out["history"]
    assert out["generations"] == 12 and all(r["new_gradient"] for r in h)
    np.testing.assert_allclose([r["cos_sampled"] for r in h], 1.0, atol=1e-9)
    np.testing.assert_allclose([r["descent_slope"] for r in h], np.linalg.norm(c), rtol=1e-6)
    assert h[-1]["best"] < h[0]["generation_best"]  # it descends

    wrong = np.random.default_rng(4)
    out = bg.guided_es(f_pop, lambda th: dict(loss=0.0, grad=wrong.standard_normal(p)), np.zeros(p), 60.0, 16,
                       max_generations=40)
    cos = np.array([r["cos_sampled"] for r in out["history"]])
    assert np.all(np.abs(cos) < 1 - 1e-3) and abs(np.median(cos)) < 0.3, cos


def test_cos_sampled_of_an_unrelated_surrogate_scatters_around_zero_with_spread_one_over_sqrt_pairs():
    """The chance level docs/bounding.md states: guided samples (half the variance along the surrogate) on random
    linear costs, the surrogate drawn independently of the cost's gradient: ``cos_sampled`` has mean 0 and standard
    deviation about ``1 / sqrt(pairs)`` (0.35 at population 16)."""
    from hyqjax.studies.tune.guided import guided_cosines

    rng = np.random.default_rng(0)
    p, n, sigma = 22, 8, 0.7
    cs = []
    for _ in range(400):
        c, g = rng.standard_normal(p), rng.standard_normal(p)
        q = g / np.linalg.norm(g)
        z = (sigma * np.sqrt(0.5 / p) * rng.standard_normal((n, p))
             + sigma * np.sqrt(0.5) * rng.standard_normal((n, 1)) * q)
        pop = np.concatenate([z, -z])
        cs.append(guided_cosines(g, pop, np.zeros(p), pop @ c, sigma, 0.5, q[:, None])["cos_sampled"])
    cs = np.asarray(cs)
    assert abs(cs.mean()) < 0.06 and 0.8 / np.sqrt(n) < cs.std() < 1.2 / np.sqrt(n), (cs.mean(), cs.std())


def test_the_clock_includes_the_gradient_and_stops_like_cma_es():
    """The first generation's recorded time includes the surrogate's compile (here a 0.3 s sleep reported as compile
    time) and every gradient's time; a generation started before ``max_wall_s`` finishes, none starts after it; the
    budget counts forward candidates and gradient calls separately."""
    calls = []

    def grad_fn(th):
        calls.append(time.time())
        time.sleep(0.3 if len(calls) == 1 else 0.05)
        return dict(loss=0.0, grad=np.ones_like(th), compile_s=0.3 if len(calls) == 1 else 0.0)

    def f_pop(xs):
        time.sleep(0.05)
        return np.sum(xs**2, 1)

    # evosax's ask and tell compile once per setting in a process (make_guided's cache): compiled here first, so
    # the timed run's generations are the sleeps above on a loaded machine too (under three xdist workers on two
    # cores the compile inside the first generation once took 2.8 s of the 2.5 s budget)
    bg.guided_es(lambda xs: np.sum(xs**2, 1), lambda th: dict(loss=0.0, grad=np.ones_like(th)), np.ones(5), 10.0,
                 4, max_generations=2)
    out = bg.guided_es(f_pop, grad_fn, np.ones(5), 2.5, 4, cost_per_candidate=10, grad_cost=1000, grad_every=2)
    h = out["history"]
    assert h[0]["grad_compile_s"] == out["grad_compile_s"] == pytest.approx(0.3)
    assert h[0]["wall_s"] >= h[0]["grad_s"] + 0.05 and h[0]["grad_s"] >= h[0]["grad_compile_s"]
    assert len(h) >= 3 and all(r["grad_compile_s"] == 0 for r in h[1:])
    assert h[-1]["wall_s"] >= 2.5 and all(r["wall_s"] < 2.5 for r in h[:-1])  # the stop rule of robust.cma_es
    n = out["generations"]
    assert out["gradients"] == len(calls) == (n + 1) // 2 and [r["new_gradient"] for r in h] == [
        i % 2 == 0 for i in range(n)]
    assert out["budget_forward"] == n * 4 * 10 and out["budget_gradient"] == len(calls) * 1000
    assert out["budget_spent"] == h[-1]["budget"] == out["budget_forward"] + out["budget_gradient"]
    assert out["grad_wall_s"] >= 0.3 + 0.05 * (len(calls) - 1)


def test_spread_subset_keeps_both_parts_of_the_training_batch():
    idx = bg.spread_subset(128, 8)
    assert len(idx) == 8 and idx[0] == 0 and idx[-1] == 127 and np.all(np.diff(idx) > 0)
    assert np.sum(idx < 64) == 4  # half from the envelope part, half from the corners
    assert list(bg.spread_subset(5, 5)) == [0, 1, 2, 3, 4] and list(bg.spread_subset(5, 1)) == [0]
    with pytest.raises(ValueError, match="subset size"):
        bg.spread_subset(4, 5)


@pytest.mark.parametrize("argv, needle", [
    (["--methods", "cma_es", "adam"], "--methods must be distinct names of cma_es, guided_es"),
    (["--methods", "cma_es", "cma_es"], "--methods must be distinct"),
    (["--methods", "guided_es", "--popsize", "5"], "--popsize must be even for guided_es"),
    (["--alpha", "0"], "--alpha must be in (0, 1]"),
    (["--subspace", "22"], "--subspace must be an int in [1, 21]"),
    (["--methods", "guided_es", "--grad-instances", "129"], "--grad-instances must be an int in [1, 128]"),
    (["--grad-duration", "1.0"], "--grad-duration must be a positive multiple"),
    (["--methods", "guided_es", "--grad-duration", "8.4"], "--grad-duration must be <= --train-duration"),
    (["--guided-lr", "0"], "--guided-lr must be in"),
    (["--guided-sigma", "nan"], "--guided-sigma must be in"),
    (["--grad-every", "0"], "--grad-every must be an int"),
])
def test_bad_guided_options_are_refused_in_one_line_before_anything_is_written(tmp_path, capsys, argv, needle):
    out = str(tmp_path / "out")
    assert br.main(argv + ["--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err
    assert not os.path.exists(out)


TINY = ["--impl", "c", "--popsize", "4", "--train-envelope", "2", "--train-corners", "2", "--train-duration", "0.8",
        "--duration", "0.8", "--instances", "1", "--broad", "4", "--grad-instances", "1", "--grad-duration", "0.4"]


@pytest.mark.slow
def test_surrogate_matches_central_differences_and_methods_compare_at_equal_wall_clock(tmp_path, monkeypatch):
    """(1) The guided loop's surrogate (MJX-JAX jacfwd of the mean training cost over a subset of the training batch,
    0.4 s, all 22 coordinates, at the warm start) along a direction against central differences of its own value;
    the first call reports its compile, the later ones none. (2) ``--methods cma_es guided_es`` on a tiny CPU size,
    with that surrogate (the program the command builds: the same subset and duration) already compiled, so its
    compile is charged once in this test: both methods train from the same start at the same limit; results.json
    holds each method's per-generation record (guided ES's with the surrogate's time and the cosines), its budget
    split into forward and gradient physics steps, every set's held-out rows on the same instances, and the
    comparison. Each method's limit is 4 s (the checks hold per generation, whatever their number): a
    generation started before the limit is finished, so each method runs at least one. (That a first call's
    compile lands in the first generation's time is checked without physics in
    ``test_the_clock_includes_the_gradient_and_stops_like_cma_es``.)"""
    args = br.parse(TINY)
    train, labels = br.training_batch(args)
    space = rb.RobustSpace.make()
    theta0 = space.theta_of(rb.load_params(args.start_preset))
    from hyqjax.bounding import tracking

    grad_fn = bg.make_surrogate(space, tracking.take(train, bg.spread_subset(len(labels), 1)), 0.4)
    v = np.zeros(space.size)
    for name, x in (("a_fz", 1.0), ("a_hz", -1.0), ("k_yaw", 0.5), ("k_stance_pitch", 0.5)):
        v[space.names.index(name)] = x
    eps = 0.05
    r0 = grad_fn(theta0)
    rp, rm = grad_fn(theta0 + eps * v), grad_fn(theta0 - eps * v)
    assert r0["compile_s"] > 0 and rp["compile_s"] == rm["compile_s"] == 0.0 and r0["wall_s"] >= r0["compile_s"]
    assert r0["ok"] == 1 and r0["falls"] == 0 and r0["clipped"] == 0
    der = float(r0["grad"] @ v)
    fd = (rp["loss"] - rm["loss"]) / (2 * eps)
    assert r0["loss"] > 0 and abs(der) > 1e-3 * r0["loss"]
    assert der == pytest.approx(fd, rel=0.05), (r0["loss"], der, fd)

    built = []
    monkeypatch.setattr(bg, "make_surrogate", lambda *a, **k: built.append(a) or grad_fn)
    out = tmp_path / "cmp"
    assert br.main(TINY + ["--methods", "cma_es", "guided_es", "--max-wall", "4", "--out", str(out)]) == 0
    assert len(built) == 1 and len(built[0][1].apex0) == 1 and built[0][2] == 0.4  # the command's surrogate
    res = json.load(open(out / "results.json"))
    tr = res["training"]
    assert set(tr["methods"]) == {"cma_es", "guided_es"} and "history" not in tr  # no default-run fields
    g, c = tr["methods"]["guided_es"], tr["methods"]["cma_es"]
    for m in (g, c):
        assert m["generations"] >= 1 and m["wall_s"] >= 4.0 and len(m["history"]) == m["generations"]
    h0 = g["history"][0]
    assert h0["new_gradient"] and h0["grad_compile_s"] == 0.0 and g["grad_compile_s"] == 0.0  # compiled above
    assert h0["wall_s"] >= h0["grad_s"] > 0
    for r in g["history"]:
        for k in ("cos_sampled", "cos_zero_order", "cos_search", "descent_slope", "pairs_differing"):
            assert k in r
        assert r["cos_sampled"] is None or -1 - 1e-9 <= r["cos_sampled"] <= 1 + 1e-9
    steps = rb.physics_steps(1, 0.4, tangents=22)
    assert g["grad_physics_steps_each"] == steps and g["physics_steps_gradient"] == g["gradients"] * steps
    assert g["physics_steps_forward"] == g["generations"] * 4 * rb.physics_steps(4, 0.8)
    assert g["physics_steps"] == g["physics_steps_forward"] + g["physics_steps_gradient"]
    assert c["physics_steps"] == c["generations"] * 4 * rb.physics_steps(4, 0.8)
    names = {"bound_robust_8s", "cma_es", "cma_es_mean", "guided_es", "guided_es_mean"}
    broad = {r["set"]: r for r in res["heldout"]["broad"]["sets"]}
    assert set(broad) == names and all(r["n"] == 4 for r in broad.values())
    assert {r["set"] for r in res["heldout"]["conditions"]["rows"]} == names
    comp = res["comparison"]
    assert set(comp) == {"cma_es", "guided_es"}
    assert comp["guided_es"]["best"]["falls"] == broad["guided_es"]["failures"]
    assert comp["guided_es"]["cosines"]["generations"] == g["generations"]
    assert comp["cma_es"]["physics_steps_gradient"] == 0
    for n in ("cma_es", "cma_es_mean", "guided_es", "guided_es_mean"):
        vals = rb.load_params(str(out / f"params_{n}.json"))
        assert set(vals) == set(rb.RobustSpace.make().names)
    md = open(out / "refine.md").read()
    rows = [ln for ln in md.splitlines() if ln.startswith("| `cma_es` |") or ln.startswith("| `guided_es` |")]
    assert any(f"| {g['generations']} |" in ln for ln in rows if ln.startswith("| `guided_es`"))
    assert "`cos_sampled`: " in md
