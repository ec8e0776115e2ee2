"""Restarts of CMA-ES (IPOP / BIPOP, :mod:`hyqjax.studies.tune.restarts`) and Suh et al.'s alpha-order blend of
first- and zeroth-order gradients (:mod:`hyqjax.studies.tune.blend`): analytic objectives with known answers, exact
resumes, the tuner's refusals, and a tiny closed-loop IPOP run that resumes after its process is killed (the blend's
closed-loop run shares guided ES's in tests/test_guided_es.py: one compile of the gradient programs)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from hyqjax.studies.tune import blend, restarts, resume, search
from hyqjax.studies.tune.study import analytic

_EvalClock, _rows, _rastrigin = analytic.EvalClock, analytic.rows, analytic.rastrigin
P, SIG = analytic.P, analytic.SIG


# ------------------------------------------------------------------ the alpha-order estimator


def test_alpha_order_weights_by_inverse_variance_and_guards_the_bias():
    """Suh et al.'s rules on hand-made samples: with agreeing estimates alpha is ``s0^2 / (s0^2 + s1^2)`` and the
    blend is the weighted mean; a first-order mean far from the zeroth-order one is cut to ``(gamma - eps) / |g1 -
    g0|``; a zeroth-order estimate too noisy to check the first-order one (``eps >= gamma``) gives alpha 0."""
    rng = np.random.default_rng(0)
    g = np.array([1.0, -2.0, 0.5])
    g1s = g + 0.1 * rng.standard_normal((50, 3))
    g0s = g + 0.3 * rng.standard_normal((200, 3))
    b = blend.alpha_order(g1s, g0s, gamma=10.0)
    v1 = np.sum(np.var(g1s, 0, ddof=1)) / 50
    v0 = np.sum(np.var(g0s, 0, ddof=1)) / 200
    assert b["alpha"] == pytest.approx(v0 / (v0 + v1)) and not b["guard"]
    np.testing.assert_allclose(b["grad"], b["alpha"] * g1s.mean(0) + (1 - b["alpha"]) * g0s.mean(0))
    assert b["cos"] > 0.99 and b["eps"] == pytest.approx(1.96 * math.sqrt(v0))
    biased = blend.alpha_order(g1s + np.array([5.0, 0, 0]), g0s, gamma=1.0)
    assert biased["guard"] and biased["alpha"] == pytest.approx((1.0 - biased["eps"]) / biased["bias"])
    # the blend stays within gamma - eps of the zero-order estimate
    assert np.linalg.norm(biased["grad"] - g0s.mean(0)) == pytest.approx(1.0 - biased["eps"])
    assert blend.alpha_order(g1s, g0s, gamma=0.5 * b["eps"])["alpha"] == 0.0


def test_blend_alpha_falls_at_a_hidden_step_and_beats_the_first_order_gradient():
    """A step of height 10 at ``x_0 = 0`` in a quadratic whose minimum (``x_0 = 0.5``) lies past it: the pathwise
    gradient does not see the step and leads over it; the zeroth-order estimate of the smoothed objective does.
    At the step the bias guard drives alpha to 0 (the first-order mean is far outside the zeroth-order confidence
    radius), and the blend ends on the step's low side with a smoothed objective far below the first-order
    gradient's (Adam, same learning rate and steps, same first-order samples)."""
    x0 = np.full(P, 0.1)
    th, log = analytic.blend_run(10.0, False, x0)
    alphas = [r["alpha"] for r in log]
    assert max(alphas[:5]) < 0.05 and all(r["guard"] for r in log[:5])
    assert all(r["bias"] > 3 * r["eps"] for r in log[:5])
    x = analytic.first_order_run(10.0, False, x0)  # the first-order gradient alone
    assert x[0] > 0.3 and th[0] < -0.2
    assert analytic.smoothed_step(10.0, th) < analytic.smoothed_step(10.0, x) - 5.0


def test_blend_alpha_goes_towards_one_on_a_smooth_function():
    """Without a discontinuity the first- and zeroth-order estimates agree (cosine near 1, bias within the
    zeroth-order noise), and the pathwise samples are the less noisy ones: alpha follows the variances, near 1 while
    the gradient is large (far from the minimum; near it the antithetic pairs of a nearly quadratic function become
    noise-free and alpha falls, as inverse-variance weighting says it should)."""
    th, log = analytic.blend_run(0.0, True, np.full(P, 2.5), steps=20)
    first = log[:10]
    assert np.median([r["alpha"] for r in first]) > 0.9
    assert all(r["cos"] > 0.8 and r["var1"] < r["var0"] for r in first)
    assert not any(r["guard"] for r in first)
    f, _ = analytic.problem(0.0, True)
    assert f(th)[0] < f(np.full(P, 2.5))[0] - 2.0


def _stoppable(run, stop_at=None, stored=None):
    """``run(clock, trace, resume, checkpoint)`` stopped once ``stop_at`` generations are done (its state through
    JSON, as the tuner stores it), or resumed from ``stored``."""
    clk, saved = _EvalClock(), []
    tr = search.Trace((1500.0,), np.zeros(P))
    if stored is not None:
        clk.restore(stored["clock"])
        tr.restore(stored["trace"])

    def checkpoint(state_fn):
        if stop_at is not None and len(tr.log) == stop_at:
            saved.append(resume.unpack(json.loads(json.dumps(resume.pack(
                dict(clock=clk.state(), trace=tr.state(), method=state_fn()))))))
            raise resume.Paused("x")

    try:
        run(clk, tr, None if stored is None else stored["method"], checkpoint)
    except resume.Paused:
        return tr, saved[0]
    return tr, None


@pytest.mark.parametrize("method", ["blend", pytest.param("ipop_cma_es", marks=pytest.mark.slow),
                                    pytest.param("bipop_cma_es", marks=pytest.mark.slow)])
def test_a_stopped_run_resumes_exactly(method):
    """Blend, IPOP and BIPOP stopped mid-budget (for the restart rules: after their first restart, in the middle of
    a later run) and resumed from their stored state take the same iterates and restarts as the uninterrupted
    run. (The restart rules are slow: evosax's CMA-ES compiles once per population size, a few seconds here.)"""
    f, df = analytic.problem(0.0, True)

    def run(clk, tr, state, checkpoint):
        if method == "blend":
            def f_gen(th, g):
                clk.now += th.shape[0]
                return _rows(th, f(th))

            def grad_fn(th):  # deterministic per iterate, as the tuner's windows
                return dict(per_window_grad=df(th[None] + 0.01 * np.arange(4)[:, None]), ok=np.ones(4, bool))

            blend.run_blend(f_gen, grad_fn, np.full(P, 1.0), 16, 0.2, clk, tr, seed=3, resume=state,
                            checkpoint=checkpoint, relative=False, gamma=1.0, generations=40)
        else:
            def f_gen(th, g):
                clk.now += th.shape[0]
                return _rows(th, _rastrigin(th))

            restarts.run_restarts(method, f_gen, np.full(P, 2.0), 6, 1.0, clk, tr, seed=3, resume=state,
                                  checkpoint=checkpoint, cost=lambda s, e: e, tol_x=0.1)

    full, _ = _stoppable(run)
    n_restarts = sum("restart" in r for r in full.log)
    if method != "blend":
        assert n_restarts >= 2, n_restarts
        first = next(i for i, r in enumerate(full.log) if "restart" in r)
        stop = first + 7
    else:
        stop = 17
    part, stored = _stoppable(run, stop_at=stop)
    assert stored is not None and len(part.log) == stop
    rest, _ = _stoppable(run, stored=stored)
    assert json.dumps(rest.log) == json.dumps(full.log)
    np.testing.assert_array_equal(rest.returned, full.returned)


# ------------------------------------------------------------------ the restart rules


def test_restart_controller_follows_ipop_and_bipop():
    """IPOP doubles the population at every restart and keeps sigma_0; BIPOP's first restart is large, then each
    restart runs in the regime that has spent less so far: small runs with ``lambda_0 <= lambda_s <= lambda_l / 2``
    and ``sigma_0 / 100 <= sigma_s <= sigma_0``; the stop criteria fire as documented."""
    c = restarts.Controller("ipop", 10, 8, 0.5)
    assert [c.next_run("x") for _ in range(3)] == [(16, 0.5), (32, 0.5), (64, 0.5)]
    b = restarts.Controller("bipop", 10, 8, 0.5, seed=1)
    regimes = []
    for k in range(12):
        for _ in range(3):
            b.observe(np.zeros(b.popsize), 0.0, 1.0, 1.0, True, cost=float(b.popsize))
        lam, sig = b.next_run("x")
        regimes.append(b.s["regime"])
        if b.s["regime"] == "small":
            assert 8 <= lam <= b.s["last_large"] // 2 + 1 and 0.005 - 1e-12 <= sig <= 0.5
        else:
            assert sig == 0.5 and lam == 8 * 2 ** b.s["large_runs"]
        spent = b.s["budget"]
        assert abs(spent["large"] - spent["small"]) <= max(x["cost"] for x in b.s["runs"])
    assert regimes[0] == "large" and "small" in regimes and regimes.count("small") > regimes.count("large")
    # stop criteria (h = 10 + ceil(30 * 10 / 8) = 48; G = 158)
    c = restarts.Controller("ipop", 10, 8, 0.5)
    assert c.observe(np.ones(8), 1.0, 1e-14, 1.0, True, 1.0) == "tol_x"
    assert c.observe(np.ones(8), 1.0, 1.0, 1e15, True, 1.0) == "condition"
    assert c.observe(np.ones(8), 1.0, 1.0, 1.0, False, 1.0) == "non_finite"
    c = restarts.Controller("ipop", 10, 8, 0.5)
    reasons = [c.observe(np.ones(8), 1.0, 1.0, 1.0, True, 1.0) for _ in range(48)]
    assert reasons[-1] == "tol_fun" and set(reasons[:-1]) == {None}
    c = restarts.Controller("ipop", 10, 8, 0.5)
    reasons = [c.observe(np.arange(8.0) + (i % 2), 1.0, 1.0, 1.0, True, 1.0) for i in range(159)]
    assert reasons[-1] == "stagnation" and set(reasons[:-1]) == {None}
    # the tuner's shorter stagnation length (and h capped by it)
    c = restarts.Controller("ipop", 10, 8, 0.5, stall_generations=5)
    assert c.lengths() == (5, 5)
    reasons = [c.observe(np.arange(8.0) + (i % 2), 1.0, 1.0, 1.0, True, 1.0) for i in range(6)]
    assert reasons == [None] * 5 + ["stagnation"]


def test_a_larger_population_runs_in_chunks_of_the_first_batch_shape():
    """A restart's doubled population is evaluated in chunks of the first population's batch shape (the mean first
    in each, the last padded): one compiled forward program; every chunk on the generation's scenarios."""
    shapes, gens = [], []

    def f_gen(th, g):
        shapes.append(th.shape)
        gens.append(g)
        return _rows(th, np.sum(th, -1))

    mean, pop = np.zeros(3), np.arange(30.0).reshape(10, 3)
    row0, fit, steps = restarts.evaluate_chunked(f_gen, mean, pop, 7, 4)
    assert shapes == [(5, 3)] * 3 and gens == [7] * 3 and steps == 15
    np.testing.assert_array_equal(fit, -pop.sum(1)) and row0["fitness"] == 0.0


@pytest.mark.slow
def test_ipop_and_bipop_reach_lower_minima_than_cma_es_on_rastrigin():
    """Rastrigin in 10 dimensions (global minimum 0, about 10^10 local minima), start uniform in [-4, 4]^10, sigma_0
    = 2, 20,000 evaluations each, four seeds: IPOP and BIPOP reach a lower minimum than plain CMA-ES (evosax, same
    first population of 10, which converges to a local minimum and cannot use the rest of its budget) on at least
    three of the four seeds, and lower on average."""
    rc = analytic.restart_comparison(seeds=(0, 1, 2, 3), dim=10, evaluations=20000, popsize=10, sigma=2.0)
    cma = [rc["runs"]["cma_es"][s]["lowest"] for s in range(4)]
    for m in ("ipop_cma_es", "bipop_cma_es"):
        low = [rc["runs"][m][s]["lowest"] for s in range(4)]
        assert rc["summary"][m]["below_cma_es"] >= 3 and np.mean(low) < np.mean(cma), rc["summary"]
        assert all(len(rc["runs"][m][s]["restarts"]) >= 1 for s in range(4))
    assert all(rc["runs"][m][s]["evaluations"] <= 20000 + 400 for m in rc["runs"] for s in range(4))


# ------------------------------------------------------------------ the tuner's settings


@pytest.mark.parametrize("kw, match", [(dict(methods=("blend",), popsize=5), "popsize must be even"),
                                       (dict(methods=("ipop_cma_es",), select_instances=0), "select_instances must"),
                                       (dict(blend_gamma=0.0), "blend_gamma"), (dict(blend_lr=2.0), "blend_lr")])
def test_wallclock_config_refuses_bad_restart_and_blend_settings(kw, match):
    from hyqjax.studies.tune import wallclock

    with pytest.raises(ValueError, match=match):
        wallclock.WallClockConfig(**kw)


@pytest.mark.parametrize("argv, match", [(["--method", "blend", "--popsize", "5"], "--popsize"),
                                         (["--method", "ipop"], "--methods must be names among")])
def test_tune_refuses_in_one_line_before_compiling(argv, match, tmp_path, capsys):
    from hyqjax.cli.app import main

    assert main(["tune", "--out", str(tmp_path / "o"), "--impl", "c"] + argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "o").exists()


def test_a_resume_with_other_settings_is_refused(tmp_path, capsys):
    """A directory holding runs of ``ipop_cma_es`` and ``blend``: the same command with another blend gamma or
    another first population (the restarts' ``lambda_0``) is refused in one line before anything is compiled."""
    from experiments import tune_study

    out = tmp_path / "o"
    base = ["--out", str(out), "--methods", "ipop_cma_es,blend", "--dims", "shared", "--impl", "c", "--no-cache"]
    args = tune_study.build_parser().parse_args(base)
    args.validate_command(args)
    from hyqjax.studies.tune import wallclock

    (out / "results.json").write_text(json.dumps(dict(kind="wallclock", config=wallclock._config(args.wallclock_config),
                                                      runs={"ipop_cma_es/shared": {}}, heldout={})))
    for change in (["--blend-gamma", "3"], ["--popsize", "8"]):
        assert tune_study.main(base + change) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "another configuration" in lines[0], lines


# ------------------------------------------------------------------ tiny closed-loop runs (CPU, slow)

TINY = ["--impl", "c", "--dims", "shared", "--popsize", "4", "--train-instances", "4", "--heldout", "4",
        "--heldout-chunk", "1", "--train-duration", "0.5", "--heldout-duration", "1", "--window-ticks", "20",
        "--train-per-height", "1", "--lead", "4", "--select-instances", "12", "--select-every", "1",
        "--no-compile-charge", "--state-every-s", "0"]


@pytest.mark.slow
def test_ipop_on_the_step_down_resumes_after_a_kill(tmp_path, capsys):
    """IPOP-CMA-ES through the tuner's study command on the CPU (C MuJoCo, 0.5 s runs), its process killed
    (SIGKILL) in the middle of its budget once its state is stored: the same command goes on from the stored state
    (generations continuing without a gap or a repeat, its clock from the stored seconds, every row with its run,
    regime and population) and completes with the held-out evaluation."""
    import os
    import time

    from conftest import start_python

    from experiments import tune_study

    out = tmp_path / "k"
    argv = ["--out", str(out), "--methods", "ipop_cma_es", "--wall-minutes", "0.4"] + TINY
    log = tmp_path / "killed.log"
    proc = start_python(f"from experiments import tune_study; tune_study.main({argv!r})", log=str(log))
    part = out / "partial" / "ipop_cma_es__shared.json"
    t0 = time.time()
    try:
        while time.time() - t0 < 240 and proc.poll() is None:
            if part.exists() and time.time() - os.path.getmtime(part) < 5 and part.stat().st_size > 0:
                state = json.loads(json.loads(part.read_text())["payload"])
                if len(state["state"]["trace"]["log"]) >= 3:
                    break
            time.sleep(0.2)
        assert proc.poll() is None, log.read_text()[-2000:]
    finally:
        proc.kill()
        proc.wait()
    assert part.exists(), log.read_text()[-2000:]
    if (out / "results.json").exists():
        assert "ipop_cma_es/shared" not in json.loads((out / "results.json").read_text()).get("runs", {})
    stored = resume.unpack(json.loads(json.loads(part.read_text())["payload"])["state"])
    n_before, t_stop = len(stored["trace"]["log"]), stored["clock"]["elapsed"]
    assert stored["method"]["ctl"]["s"]["popsize"] == 4 and 0 < t_stop < 24.0
    assert tune_study.main(argv) == 0
    assert "resuming at" in capsys.readouterr().out
    res = json.loads((out / "results.json").read_text())
    run = res["runs"]["ipop_cma_es/shared"]
    assert res["complete"] and run["segments"] == 2 and not part.exists()
    log = run["log"]
    assert [r["generation"] for r in log] == list(range(len(log))) and len(log) > n_before
    assert log[:n_before] == json.loads(json.dumps(stored["trace"]["log"])) and log[n_before]["wall_s"] >= t_stop
    # every row carries its run, regime and population: the first run at popsize 4, each IPOP restart (a warm
    # process may fit one into the budget) in the large regime at twice the population, runs never going back
    assert all(r["run"] == 0 and r["regime"] == "first" and r["popsize"] == 4 for r in log[:n_before])
    assert all(r["popsize"] == 4 * 2 ** r["run"] and r["regime"] == ("first" if r["run"] == 0 else "large")
               for r in log)
    assert [r["run"] for r in log] == sorted(r["run"] for r in log)
    assert sum(x["generations"] for x in restarts.summary(log)["runs"]) == len(log)
    from hyqjax.studies.tune.wallclock_results import member_key

    assert res["heldout"][member_key("ipop_cma_es", "shared", 24.0)]["n"] == 4
