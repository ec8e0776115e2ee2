"""Guided evolution strategies inside the tuner (:func:`hyqjax.studies.tune.guided.run_guided`, evosax GuidedES):
on a smooth function with a known gradient the surrogate-guided search beats isotropic antithetic ES at equal
evaluations, and the per-generation agreement it records reads "the surrogate points the right way" for the true
gradient and "no better than chance" for a random one; on the step-down a tiny CPU run records finite agreement
data in the study's results."""
from __future__ import annotations

import json

import numpy as np
import pytest

from hyqjax.studies.tune import guided, search

P = 20
W = np.linspace(1.0, 10.0, P)


def quad(th):
    return ((np.asarray(th) - 1.0) ** 2 * W).sum(-1)


def true_grad(th):
    return 2.0 * W * (np.asarray(th) - 1.0)


def f_gen(th, gen):
    n = len(th)
    return dict(fitness=-quad(th), clean=np.zeros((n, 1)), completed=np.zeros((n, 1)), physics_steps=0)


def _run(seed, alpha, surrogate, generations=30):
    means = []

    def grad_fn(th):
        means.append(np.asarray(th, np.float64))
        return dict(loss=quad(th), grad=surrogate(th))

    trace = search.Trace((1e9,), np.zeros(P))
    m = guided.run_guided(f_gen, grad_fn, np.zeros(P), 8, 0.1, search.Clock(), trace, seed=seed, alpha=alpha,
                          lr=0.05, generations=generations)
    # descent_slope / |true gradient at the generation's mean| = cos(surrogate, true gradient), measured
    ratio = [r["descent_slope"] / np.linalg.norm(true_grad(x)) for r, x in zip(trace.log, means)]
    return quad(m), float(np.median(ratio)), float(np.median([r["cos_search"] for r in trace.log])), trace


def test_guided_es_with_the_true_gradient_beats_isotropic_es_at_equal_evaluations():
    """Same code path, same population (8 = 4 antithetic pairs), step, Adam rate and 30 generations: alpha 0.5
    (half the variance in the gradient's direction) against alpha 1 (isotropic antithetic ES), three seeds each.
    The true gradient's recorded agreement: the population's slope along it over |grad f| (the cosine) is 1 and the
    search direction's cosine is high; a random surrogate's is near 0."""
    start = quad(np.zeros(P))
    for seed in range(3):
        f_guided, ratio, cos_s, trace = _run(seed, 0.5, true_grad)
        f_iso, ratio_iso, _, _ = _run(seed, 1.0, true_grad)
        assert f_guided < 0.2 * f_iso < 0.2 * start, (seed, f_guided, f_iso)
        assert 0.9 < ratio < 1.1 and cos_s > 0.8, (ratio, cos_s)
        assert 0.9 < ratio_iso < 1.1  # the slope along the true gradient is measured with isotropic samples too
        rows = trace.log
        assert len(rows) == 30 and all(r["new_gradient"] for r in rows)
        assert all(np.isfinite([r["descent_slope"], r["cos_search"], r["cos_zero_order"]]).all() for r in rows)
    rng = np.random.default_rng(0)
    _, ratio_rand, cos_rand, _ = _run(0, 0.5, lambda th: rng.standard_normal(P), generations=20)
    assert abs(ratio_rand) < 0.3 and abs(cos_rand) < 0.6, (ratio_rand, cos_rand)


def test_guided_es_explores_as_far_per_coordinate_as_the_other_searches():
    """``--sigma`` is the first step per coordinate for every method: guided ES's perturbations have the total
    variance ``sigma^2 P`` of OpenES's (``theta + sigma z``), and with ``alpha = 1`` each coordinate's spread is
    ``sigma`` like OpenES's, measured on the populations both draw (40 generations of 8 pairs in 30 coordinates);
    with ``alpha = 0.5`` half that variance lies along the surrogate."""
    import jax
    import jax.numpy as jnp

    p, sigma, gens = 30, 0.2, 40
    g_dir = np.zeros(p)
    g_dir[0] = 1.0
    pops = {}
    for alpha in (1.0, 0.5):
        seen = []

        def f_rec(th, gen):
            seen.append(np.asarray(th[1:], np.float64))  # row 0 is the mean
            return dict(fitness=-(np.asarray(th) ** 2).sum(-1), clean=np.zeros((len(th), 1)),
                        completed=np.zeros((len(th), 1)), physics_steps=0)

        trace = search.Trace((1e9,), np.zeros(p))
        guided.run_guided(f_rec, lambda th: dict(loss=0.0, grad=g_dir), np.zeros(p), 16, sigma, search.Clock(),
                          trace, alpha=alpha, lr=1e-9, generations=gens)
        pops[alpha] = np.concatenate(seen)  # around the mean, which stays at 0 (Adam at 1e-9)
    es, params = search.make_strategy("open_es", p, 16, sigma)
    state, key, open_pops = es.init(jax.random.key(1), jnp.zeros(p), params), jax.random.key(2), []
    for _ in range(gens):
        key, k = jax.random.split(key)
        pop, state = es.ask(k, state, params)
        open_pops.append(np.asarray(pop, np.float64))
    open_pops = np.concatenate(open_pops)
    for z in (pops[1.0], pops[0.5], open_pops):  # total variance sigma^2 P within the sampling error (~3 %)
        assert abs(np.mean((z ** 2).sum(1)) / (sigma**2 * p) - 1.0) < 0.1
    per_coord_iso, per_coord_open = pops[1.0][:, 1:].std(0), open_pops[:, 1:].std(0)
    assert abs(per_coord_iso.mean() / sigma - 1.0) < 0.05 and abs(per_coord_open.mean() / sigma - 1.0) < 0.05
    along = np.mean(pops[0.5][:, 0] ** 2) / (sigma**2 * p)  # the share of the variance along the surrogate
    assert 0.4 < along < 0.6, along
    assert abs(pops[0.5][:, 1:].std(0).mean() / (sigma * np.sqrt(0.5)) - 1.0) < 0.05


def test_guided_cosines_on_a_linear_function():
    """On ``f(x) = c . x`` every antithetic pair measures ``2 z . c`` exactly: the slope along ``c`` is ``|c|``,
    along ``-c`` it is ``-|c|``, and the search direction is parallel to ``c`` for a surrogate equal to ``c``."""
    rng = np.random.default_rng(1)
    c = rng.standard_normal(12)
    mean = rng.standard_normal(12)
    z = rng.standard_normal((6, 12)) * 0.1
    pop = mean + np.concatenate([z, -z])
    f = pop @ c
    sub = c[:, None]
    r = guided.guided_cosines(c, pop, mean, f, 0.1, 0.5, sub)
    assert r["descent_slope"] == pytest.approx(np.linalg.norm(c), rel=1e-9)
    assert guided.guided_cosines(-c, pop, mean, f, 0.1, 0.5, sub)["descent_slope"] == pytest.approx(
        -np.linalg.norm(c), rel=1e-9)
    assert np.isnan(guided.guided_cosines(c, pop, mean, f, 0.1, 0.0, sub)["cos_zero_order"])
    # inside the span of the 6 pairs, the least-squares gradient is c's projection: cosine 1 with fewer pairs than
    # dimensions; a surrogate off c's direction scores less
    assert r["cos_sampled"] == pytest.approx(1.0, abs=1e-9)
    other = c + 2.0 * rng.standard_normal(12)
    assert guided.guided_cosines(other, pop, mean, f, 0.1, 0.5, sub)["cos_sampled"] < 0.99
    assert np.isnan(guided.guided_cosines(c, pop, mean, np.where(np.arange(12) == 0, np.inf, f), 0.1, 0.5, sub)[
        "cos_sampled"])


@pytest.mark.slow
def test_guided_es_and_the_blend_on_the_step_down_record_finite_agreement(tmp_path):
    """A tiny CPU run of guided ES and of Suh et al.'s blend through ``python -m experiments.tune_study`` (C MuJoCo
    forward runs, the surrogate gradient by jacfwd through MJX-JAX windows, compiled once for both): every guided-ES
    generation's log row carries a fresh surrogate gradient and finite agreement data; every blend step's row the
    surrogate's windows and either the alpha-order diagnostics (alpha in [0, 1], finite variances, a cosine in
    [-1, 1]) or, where every antithetic pair tied, alpha undefined and no step; neither compiles a program it does
    not run (the window value program of the gradient method's line search), and both are held out like any other
    method. (On this CPU size, 0.5 s training runs, every member of a population may score alike: the population
    then measured no gradient, its slope along the surrogate is 0 and the cosines are undefined, stored as null.)
    Budgets of 6 s per method: every row is checked, and a row takes about 2 s after the first generation's
    compile (alone on 2 cores, rows of a 30 s run: 12 guided-ES generations and 15 blend steps, of which 4 and 8
    started within the first 15 s); the compile is not charged (``--no-compile-charge``), so each method's first
    generation starts inside its budget and the row checks hold for any number of rows."""
    from experiments import tune_study

    out = tmp_path / "g"
    code = tune_study.main(["--out", str(out), "--impl", "c", "--methods", "guided_es,blend", "--dims", "shared",
                            "--wall-minutes", "0.1", "--popsize", "4", "--train-instances", "4", "--heldout", "4",
                            "--heldout-chunk", "1", "--train-duration", "0.5", "--heldout-duration", "1",
                            "--window-ticks", "20", "--train-per-height", "1", "--lead", "4", "--select-instances", "0",
                            "--no-compile-charge"])
    assert code == 0
    res = json.loads((out / "results.json").read_text())
    run = res["runs"]["guided_es/shared"]
    rows = run["log"]
    assert rows and all(r["new_gradient"] for r in rows)
    assert rows[0]["surrogate_loss"] == rows[0]["surrogate_loss"]  # a number (the window loss at the mean)
    assert all(np.isfinite(r["surrogate_grad_norm"]) and r["surrogate_grad_norm"] > 0 for r in rows)
    for r in rows:  # the slope is measured every generation; the cosines wherever a pair scored differently
        assert np.isfinite(r["descent_slope"]) and 0 <= r["pairs_differing"] <= 2
        if r["pairs_differing"]:
            assert -1.0 <= r["cos_search"] <= 1.0
        else:
            assert r["descent_slope"] == 0.0 and r["cos_search"] is None  # NaN, stored as null
    from hyqjax.studies.tune.wallclock_results import member_key

    assert run["physics_steps"] > 0
    assert run["guided_std"] == pytest.approx(res["config"]["sigma"] * np.sqrt(run["size"]))  # sigma per coordinate
    # guided ES takes no line search: the windows' value program is not compiled, only the tuning step
    assert {"gradient_windows", "jacfwd/shared"} <= set(res["charges"]), res["charges"]
    assert "window_value/shared" not in res["charges"], res["charges"]
    h = res["heldout"][member_key("guided_es", "shared", 6.0)]
    assert h["n"] == 4 and 0.0 <= h["clean"] <= 1.0
    blend = res["runs"]["blend/shared"]
    assert blend["log"] and all(r["windows"] >= 1 for r in blend["log"])
    for r in blend["log"]:
        if r["pairs_differing"]:
            assert 0.0 <= r["alpha"] <= 1.0 and r["var0"] >= 0 and r["var1"] >= 0 and -1.0 <= r["cos"] <= 1.0
        else:
            assert r["alpha"] is None and r["var0"] == 0.0  # NaN, stored as null
    assert blend["physics_steps"] > 0 and res["heldout"][member_key("blend", "shared", 6.0)]["n"] == 4


def test_the_guided_comparison_summarises_seeds_and_agreement():
    """``--guided-comparison``'s summary (:mod:`hyqjax.studies.tune.study.guided`) of two seeds' results: per
    method the held-out clean of each seed, their mean and t-interval, and per guided-ES run the agreement data
    over its generations (null cosines, generations whose pairs all tied, left out)."""
    from hyqjax.studies.tune.study import guided
    from hyqjax.studies.tune.wallclock import WallClockConfig
    from hyqjax.studies.tune.wallclock_results import member_key

    def res(seed, clean_g, clean_c, cos):
        cfg = WallClockConfig(methods=("guided_es", "cma_es"), dims=("per_leg",), wall_minutes=(1.0,), seed=seed)
        h = lambda c: dict(clean=c, completed=c, clean_ci95=[c - 0.01, c + 0.01], n=100)  # noqa: E731
        log = [dict(cos_search=c, cos_zero_order=c / 2, descent_slope=c) for c in cos] + [
            dict(cos_search=None, cos_zero_order=None, descent_slope=0.0)]
        return dict(kind="wallclock", config=cfg.to_dict(), heldout_set=dict(instances=100, seed=7777),
                    runs={"guided_es/per_leg": dict(method="guided_es", dim="per_leg", log=log),
                          "cma_es/per_leg": dict(method="cma_es", dim="per_leg", log=[])},
                    heldout={member_key("guided_es", "per_leg", 60.0): h(clean_g),
                             member_key("cma_es", "per_leg", 60.0): h(clean_c), "start": h(0.4)})

    comp = guided.compare({0: res(0, 0.6, 0.5, [0.2, 0.4, 0.6]), 1: res(1, 0.8, 0.55, [-0.1, 0.3, 0.5])}, 1.0)
    g = comp["summary"]["guided_es/per_leg"]["clean"]
    assert g["n"] == 2 and g["mean"] == pytest.approx(0.7) and g["ci95"][0] < 0.7 < g["ci95"][1]
    c0 = comp["cosines"]["guided_es/per_leg"]["seed0"]["cos_search"]
    assert c0["n"] == 3 and c0["median"] == pytest.approx(0.4) and c0["share_positive"] == 1.0
    assert comp["cosines"]["guided_es/per_leg"]["seed1"]["cos_search"]["share_positive"] == pytest.approx(2 / 3)
    assert "guided_es/per_leg" in guided.markdown(comp)


def test_final_choice_pools_the_validation_and_the_further_scenarios():
    """The final re-evaluation (:func:`search.final_choice`): a selection keeps its best validated iterates (best
    first); re-run on further scenarios, the candidate with the best clean rate pooled over both batches wins, here
    the second of the validation ranking, whose validation lead was luck of one batch."""
    calls = []

    def evaluate(th):  # the validation batch of 4 runs: iterate k scores clean at a fixed per-iterate rate
        calls.append(len(th))
        rate = {0.0: 0.25, 1.0: 0.75, 2.0: 0.5, 3.0: 1.0}[float(th[0][0])]
        return dict(clean=np.array([[1.0] * int(4 * rate) + [0.0] * (4 - int(4 * rate))]),
                    completed=np.ones((1, 4)), physics_steps=4)

    sel = search.Selection(evaluate, every=1, keep=3)
    clock = search.Clock()
    for i, x in enumerate((0.0, 1.0, 2.0, 3.0)):
        sel.validate(clock, np.full(3, x), i)
    assert [t[1] for t in sel.top] == [3, 1, 2] and [t[0][0] for t in sel.top] == [1.0, 0.75, 0.5]
    state = sel.state()
    again = search.Selection(evaluate, every=1, keep=3)
    again.restore(state)
    assert [t[1] for t in again.top] == [3, 1, 2] and np.array_equal(again.top[0][2], sel.top[0][2])

    def further(th):  # 12 further runs: iterate 3 clean in 3, iterate 1 in 11, iterate 2 in 6
        n = {3.0: 3, 1.0: 11, 2.0: 6}
        clean = np.array([[1.0] * n[float(t[0])] + [0.0] * (12 - n[float(t[0])]) for t in th])
        return dict(clean=clean, completed=np.ones_like(clean), physics_steps=12 * len(th))

    out = search.final_choice(sel.top, 4, further)
    assert out["chosen"] == 1 and out["theta"][0] == 1.0 and out["instances"] == 12 and out["physics_steps"] == 36
    pooled = [c["pooled_clean"] for c in out["candidates"]]
    np.testing.assert_allclose(pooled, [(4 * 1.0 + 3) / 16, (4 * 0.75 + 11) / 16, (4 * 0.5 + 6) / 16])


def test_final_choice_weighs_the_start_point_against_lucky_iterates():
    """The start point (the first validated iterate) joins the final re-evaluation when three iterates outrank it
    on the validation batch: here each of them scored above it by the luck of one small batch, the further runs say
    the start is best, and the run returns the start. The start survives a stored state; a state stored before it
    was kept restores without it (no start candidate)."""
    def evaluate(th):  # 8 validation runs: the start 4 clean, the three iterates 5, 6 and 7
        k = {0.0: 4, 1.0: 5, 2.0: 6, 3.0: 7}[float(th[0][0])]
        return dict(clean=np.array([[1.0] * k + [0.0] * (8 - k)]), completed=np.ones((1, 8)), physics_steps=8)

    sel = search.Selection(evaluate, every=1, keep=3)
    clock = search.Clock()
    for i, x in enumerate((0.0, 1.0, 2.0, 3.0)):
        sel.validate(clock, np.full(2, x), i)
    assert [t[1] for t in sel.top] == [3, 2, 1]
    cands = sel.candidates()
    assert [t[1] for t in cands] == [3, 2, 1, 0] and np.array_equal(cands[-1][2], np.zeros(2))

    def further(th):  # 40 further runs: the start 30 clean, the iterates 12, 14 and 16
        n = {0.0: 30, 1.0: 16, 2.0: 14, 3.0: 12}
        clean = np.array([[1.0] * n[float(t[0])] + [0.0] * (40 - n[float(t[0])]) for t in th])
        return dict(clean=clean, completed=np.ones_like(clean), physics_steps=40 * len(th))

    out = search.final_choice(cands, 8, further)
    assert out["candidates"][out["chosen"]]["iteration"] == 0 and np.array_equal(out["theta"], np.zeros(2))
    assert out["candidates"][-1]["pooled_clean"] == pytest.approx((4 + 30) / 48)
    # without the start the best of the three lucky iterates would have been returned
    assert search.final_choice(sel.top, 8, further)["candidates"][0]["iteration"] == 3
    again = search.Selection(evaluate, every=1, keep=3)
    again.restore(sel.state())
    assert [t[1] for t in again.candidates()] == [3, 2, 1, 0]
    old = {k: v for k, v in sel.state().items() if k != "start"}
    again.restore(old)
    assert again.start is None and [t[1] for t in again.candidates()] == [3, 2, 1]
    # a start among the best validated iterates is not added twice
    top = search.Selection(evaluate, every=1, keep=3)
    for i, x in enumerate((3.0, 1.0, 2.0)):
        top.validate(clock, np.full(2, x), i)
    assert [t[1] for t in top.candidates()] == [0, 2, 1]
