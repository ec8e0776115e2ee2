"""``python -m experiments.tune_step_size``: the paired loss of a search's first samples around a tuned set."""
import json

import numpy as np
import pytest

from experiments import tune_step_size as ts


def test_samples_share_their_directions_across_step_sizes():
    theta0 = np.linspace(-1, 1, 7)
    pts = ts.sample_points(theta0, [0.1, 0.3], 5, seed=3)
    z1, z3 = (pts[0.1] - theta0) / 0.1, (pts[0.3] - theta0) / 0.3
    np.testing.assert_allclose(z1, z3, atol=1e-12)
    assert z1.shape == (5, 7) and abs(z1.mean()) < 1.0


def test_antithetic_pairs_mirror_the_same_directions_and_the_halves_split_every_height():
    theta0 = np.linspace(-1, 1, 7)
    pts, z = ts.antithetic_points(theta0, [0.028, 0.3], 4, seed=3)
    for s, th in pts.items():
        assert th.shape == (8, 7)
        np.testing.assert_allclose(th[:4] - theta0, s * z, atol=1e-12)
        np.testing.assert_allclose(th[4:] - theta0, -s * z, atol=1e-12)
    half = ts.halves(32, 4)  # height by height, 8 instances each: the first 4 of every height
    assert half.reshape(4, 8)[:, :4].all() and not half.reshape(4, 8)[:, 4:].any()


def test_pair_signal_tells_a_direction_from_outcome_noise():
    """A fitness whose pair differences follow ``z . u`` on every instance correlates across the two halves of the
    instances (and the halves' zero-order estimates point alike); one whose differences are independent noise per
    instance does not."""
    rng = np.random.default_rng(0)
    n, m, p = 64, 32, 10
    z, u = rng.standard_normal((n, p)), rng.standard_normal(p)
    half = ts.halves(m, 4)
    noise = rng.standard_normal((2 * n, m))
    signal = np.concatenate([z @ u, -(z @ u)])[:, None] * np.ones((1, m))
    for f, direction in ((0.3 * signal + noise, True), (noise, False)):
        r = ts.pair_signal(dict(clean=f, completed=np.zeros_like(f)), z, half, 0.1)
        lo, hi = r["split_half_r_ci95"]
        assert r["pairs"] == n and r["pairs_differing"] == n
        if direction:
            assert lo > 0.5 and r["split_half_cos"] > 0.5, r
        else:
            assert lo < 0 < hi and abs(r["split_half_cos"]) < 0.5, r
    same = ts.pair_signal(dict(clean=np.ones((2 * n, m)), completed=np.ones((2 * n, m))), z, half, 0.1)
    assert same["pairs_differing"] == 0 and np.isnan(same["split_half_r"])  # no difference: nothing measured


def test_the_surrogate_agrees_with_pairs_that_measure_its_direction_and_not_with_noise():
    """Pairs on a fitness that rises along ``u``: a surrogate whose descent is ``u`` (the gradient of ``-u . theta``)
    has a positive slope and cosines near 1 with the estimate, each half's and the sampled one; a random surrogate's
    are near 0."""
    rng = np.random.default_rng(1)
    n, m, p, sigma = 64, 32, 12, 0.1
    theta0 = rng.standard_normal(p)
    u = rng.standard_normal(p)
    pts, z = ts.antithetic_points(theta0, [sigma], n, seed=2)
    th = pts[sigma]
    f = ((th - theta0) @ u)[:, None] * np.ones((1, m)) + 0.01 * rng.standard_normal((2 * n, m))
    members = dict(clean=f, completed=np.zeros_like(f))
    half = ts.halves(m, 4)
    right = ts.surrogate_agreement(-u, th, theta0, members, sigma, half, 0.1)
    assert right["descent_slope"] > 0 and right["cos_zero_order"] > 0.9 and right["cos_sampled"] > 0.9
    assert right["cos_half_a"] > 0.9 and right["cos_half_b"] > 0.9
    rand = ts.surrogate_agreement(rng.standard_normal(p), th, theta0, members, sigma, half, 0.1)
    assert abs(rand["cos_zero_order"]) < 0.7 and abs(rand["cos_sampled"]) < 0.7


def test_summary_is_the_paired_difference_from_the_start():
    start = dict(clean=np.array([[1, 1, 0, 1]], bool), fitness=np.array([0.8]))
    members = dict(clean=np.array([[1, 1, 0, 1], [0, 1, 0, 0], [1, 1, 1, 1]], bool), fitness=np.array([0.8, 0.3, 1.1]))
    r = ts.summarize(start, members, 0.2)
    assert r["start_clean"] == 0.75 and r["mean_diff"] == pytest.approx((0 - 0.5 + 0.25) / 3)
    assert r["best_diff"] == 0.25 and r["worst_diff"] == -0.5 and r["share_at_least_start"] == pytest.approx(2 / 3)
    assert r["mean_fitness_diff"] == pytest.approx((0 - 0.5 + 0.3) / 3) and r["best_fitness_diff"] == pytest.approx(0.3)
    lo, hi = r["mean_diff_ci95"]
    assert lo < r["mean_diff"] < hi


def test_line_points_run_down_the_surrogate_at_the_given_distances():
    rng = np.random.default_rng(4)
    theta0, g = rng.standard_normal(9), rng.standard_normal(9)
    t = np.array([-0.8, 0.1, 0.4, 1.6])
    pts = ts.line_points(theta0, g, t)
    step = pts - theta0
    np.testing.assert_allclose(np.linalg.norm(step, axis=1), np.abs(t), rtol=1e-12)
    np.testing.assert_allclose(step @ g, -t * np.linalg.norm(g), rtol=1e-12)  # descent for t > 0, ascent below 0


def test_line_summary_is_paired_over_the_same_step_downs():
    """Two points on four step-downs: the differences from the start are taken step-down by step-down (the same
    instances), the fitness is clean + 0.1 x completed, and the outcome counts are the point's own."""
    start = dict(clean=np.array([[1, 0, 1, 0]], bool), completed=np.array([[1, 1, 1, 0]], bool))
    members = dict(clean=np.array([[1, 1, 1, 0], [0, 0, 1, 0]], bool),
                   completed=np.array([[1, 1, 1, 1], [0, 1, 1, 0]], bool),
                   columns=dict(terminated=np.array([[0, 0, 0, 0], [1, 0, 0, 0]], bool),
                                diverged=np.zeros((2, 4), bool)))
    near, far = ts.line_summary(start, members, [0.2, 1.0], 0.1)
    assert near["distance"] == 0.2 and near["clean"] == 0.75 and near["clean_diff"] == pytest.approx(0.25)
    assert near["fitness_diff"] == pytest.approx((1 + 0.1 * 1) / 4 * 1 + 0.1 * 0)  # one clean gained, one completed
    assert far["clean_diff"] == pytest.approx(-0.25) and far["fitness_diff"] == pytest.approx(-1.1 / 4)
    assert far["counts"] == dict(runs=4, not_completed=2, not_clean=3, fell=1, diverged=0)
    lo, hi = far["clean_diff_ci95"]
    assert lo < far["clean_diff"] < hi
    assert "window_loss" not in near
    near_w, far_w = ts.line_summary(start, members, [0.2, 1.0], 0.1, window_loss=np.array([0.5, 0.25]))
    assert (near_w["window_loss"], far_w["window_loss"]) == (0.5, 0.25)
    table = ts.line_markdown([near_w, far_w], 4, dict(grad_norm=1.0, loss=0.75))
    assert "window objective (start 0.75)" in table and "| 0.25 |" in table
    assert "window objective" not in ts.line_markdown([near, far], 4, dict(grad_norm=1.0, loss=0.75))


def test_runs_ended_early_are_those_the_start_completes_with_their_times():
    """A point's early ends are counted only on the step-downs where the start ran to the end, with when they end
    (the failure tick times the control period), and the descent direction lists ``-g``'s largest components."""
    start = dict(clean=np.ones((1, 5), bool), completed=np.ones((1, 5), bool),
                 columns=dict(terminated_tick=np.array([[-1, 5, -1, -1, -1]])))
    members = dict(clean=np.ones((2, 5), bool), completed=np.ones((2, 5), bool),
                   columns=dict(terminated_tick=np.array([[10, 5, -1, 2000, 1000], [-1, 7, -1, -1, -1]])))
    e = ts.ended_early(start, members, 0, 0.002)
    assert e["ended_early_not_at_start"] == 3  # not step-down 1, where the start ended early too
    assert e["ended_early_time_s"] == np.percentile([0.02, 4.0, 2.0], [10, 50, 90]).round(2).tolist()
    assert ts.ended_early(start, members, 1, 0.002) == dict(ended_early_not_at_start=0, ended_early_time_s=None)
    assert ts.ended_early(dict(clean=start["clean"]), members, 0, 0.002) == {}
    d = ts.descent_direction(np.array([0.0, 3.0, -4.0]), ["a", "b", "c"], top=2)
    assert d == [("c", 0.8), ("b", -0.6)]


@pytest.mark.parametrize("argv, needle", [(["--sigmas", "0"], "--sigmas"), (["--instances", "6"], "--instances"),
                                          (["--samples", "1"], "--samples"), (["--preset", "bound_robust"], "bound"),
                                          (["--dim", "wings"], "--dim"), (["--impl", "gpu"], "--impl"),
                                          (["--spread", "narrow"], "--spread"),
                                          (["--antithetic", "--samples", "9"], "--samples"),
                                          (["--antithetic", "--instances", "12"], "--instances"),
                                          (["--surrogate"], "--surrogate"), (["--window-ticks", "0"], "--window-ticks"),
                                          (["--windows-per-scenario", "9"], "--windows-per-scenario"), (["--lead", "0"], "--lead"),
                                          (["--line", "0.1", "--surrogate-weights", "tilt"], "TERM=W"),
                                          (["--sigmas"], "--sigmas"), (["--line", "11"], "--line")])
def test_bad_input_is_refused_in_one_line(argv, needle, tmp_path, capsys):
    assert ts.main(argv + ["--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_a_vanishing_step_runs_exactly_the_start_and_a_large_one_loses(tmp_path, capsys):
    """On C MuJoCo, samples 1e-7 away from ``clean`` end every one of the same step-downs as ``clean`` does (a
    paired difference of exactly 0), and samples at a step of 2 lose clean success on average."""
    out = tmp_path / "ss"
    assert ts.main(["--out", str(out), "--samples", "2", "--instances", "4", "--sigmas", "1e-7", "2",
                    "--seed", "5"]) == 0, capsys.readouterr().err
    res = json.loads((out / "step_size.json").read_text())
    tiny, big = res["rows"]
    assert res["start"]["clean"] > 0.5 and res["impl"] == "c"
    assert tiny["mean_diff"] == 0.0 and tiny["worst_diff"] == 0.0 and tiny["share_at_least_start"] == 1.0
    assert big["mean_diff"] < 0.0
    assert res["physics_steps"] == (1 + 2 * 2) * 4 * round(24.0 / 0.002)
    assert "| 2 |" in (out / "step_size.md").read_text()


def test_stored_line_down_the_surrogate_at_clean_loses_at_every_distance():
    """The stored C MuJoCo line at ``clean`` (docs/results/tune_surrogate_line_clean_cpu): the report is what the
    stored rows give; every point down the window gradient loses clean success against ``clean`` on the same 256
    step-downs (intervals below 0 at 0.025 and from 0.1 on), the loss grows with the distance from 0.1, and at 0.4
    and 0.8 the ascent side loses more than the descent side, while the window objective falls down the gradient:
    ``clean`` sits on a ridge the surrogate tells apart but cannot climb."""
    root = "docs/results/tune_surrogate_line_clean_cpu"
    with open(f"{root}/step_size.json") as f:
        res = json.load(f)
    with open(f"{root}/step_size.md") as f:
        assert f.read().strip() == ts.line_markdown(res["line"], res["instances"], res["surrogate"]).strip()
    by_t = {x["distance"]: x for x in res["line"]}
    assert res["instances"] == 256 and res["preset"] == "clean" and res["spread"] == "wide"
    assert all(x["counts"]["diverged"] == 0 for x in res["line"])
    down = [by_t[t] for t in sorted(t for t in by_t if t > 0)]
    assert all(x["clean_diff"] < 0 for x in down)
    assert all(by_t[t]["clean_diff_ci95"][1] < 0 for t in (0.025, 0.1, 0.2, 0.4, 0.8, 1.6))
    far = [by_t[t]["clean_diff"] for t in (0.1, 0.2, 0.4, 0.8, 1.6)]
    assert far == sorted(far, reverse=True)
    assert by_t[-0.4]["clean_diff"] < by_t[0.4]["clean_diff"] and by_t[-0.8]["clean_diff"] < by_t[0.8]["clean_diff"]
    loss0 = res["surrogate"]["loss"]  # while its own window objective falls all the way down to 0.8
    losses = [loss0] + [by_t[t]["window_loss"] for t in (0.025, 0.05, 0.1, 0.2, 0.4, 0.8)]
    assert losses == sorted(losses, reverse=True) and by_t[-0.4]["window_loss"] > loss0


def test_stored_line_at_table_i_loses_more_down_the_surrogate_than_up_it():
    """The stored C MuJoCo line at the study's start (Table I with the shin remedy, the study's spread;
    docs/results/tune_surrogate_line_tablei_cpu): the report is what the stored rows give, and at 0.4 and 0.8 the
    full-run clean rate falls further down the window gradient than up it, with more runs ending in a fall, while
    the window objective itself falls down it and rises up it: the gradient is right about its objective, and the
    objective and the full run disagree there."""
    root = "docs/results/tune_surrogate_line_tablei_cpu"
    with open(f"{root}/step_size.json") as f:
        res = json.load(f)
    with open(f"{root}/step_size.md") as f:
        assert f.read().strip() == ts.line_markdown(res["line"], res["instances"], res["surrogate"]).strip()
    assert res["preset"] == "none" and res["spread"] == "train" and res["instances"] == 256
    by_t = {x["distance"]: x for x in res["line"]}
    for t in (0.4, 0.8):
        assert by_t[t]["clean_diff"] < by_t[-t]["clean_diff"] and by_t[t]["clean_diff_ci95"][1] < 0
        assert by_t[t]["counts"]["fell"] > 4 * by_t[-t]["counts"]["fell"]
    assert all(x["counts"]["diverged"] == 0 for x in res["line"])
    loss0 = res["surrogate"]["loss"]  # the gradient descends its own objective: lower down it, higher up it
    assert by_t[0.4]["window_loss"] < by_t[0.2]["window_loss"] < by_t[0.1]["window_loss"] < loss0
    assert loss0 < by_t[-0.4]["window_loss"] < by_t[-0.8]["window_loss"]
    # the runs it ends early (not at the start) end after its windows: nine in ten more than 2.5 s after the last
    end = res["surrogate"]["windows_s"][1]
    for t in (0.1, 0.2, 0.4, 0.8):
        assert by_t[t]["ended_early_not_at_start"] >= 30 and by_t[t]["ended_early_time_s"][0] > end + 2.5
    assert res["surrogate"]["direction"][0][0] == "body_height[RF]" and res["surrogate"]["direction"][0][1] > 0.5


def test_stored_line_with_long_windows_does_not_descend_its_own_objective():
    """The stored C MuJoCo line at Table I with 2,000-tick windows (docs/results/tune_surrogate_line_tablei_w2000_cpu):
    the gradient's norm is thousands of times the 500-tick one's, and a step of 0.1 down it already raises the window
    objective it was taken from (and 0.4 up it lowers it), while the full runs lose at 0.4 down it."""
    with open("docs/results/tune_surrogate_line_tablei_w2000_cpu/step_size.json") as f:
        long = json.load(f)
    with open("docs/results/tune_surrogate_line_tablei_cpu/step_size.json") as f:
        short = json.load(f)
    assert (long["surrogate"]["window_ticks"], short["surrogate"]["window_ticks"]) == (2000, 500)
    assert long["start"] == short["start"] and long["surrogate"]["grad_norm"] > 1000 * short["surrogate"]["grad_norm"]
    by_t = {x["distance"]: x for x in long["line"]}
    loss0 = long["surrogate"]["loss"]
    assert by_t[0.1]["window_loss"] > loss0 and by_t[0.4]["window_loss"] > loss0 > by_t[-0.4]["window_loss"]
    assert by_t[0.4]["clean_diff_ci95"][1] < 0 and all(x["counts"]["diverged"] == 0 for x in long["line"])


def _stored_line(name: str) -> dict:
    """A stored ``--line`` result (``docs/results/NAME/step_size.json``), its report checked to be what its rows give."""
    root = f"docs/results/{name}"
    with open(f"{root}/step_size.json") as f:
        res = json.load(f)
    with open(f"{root}/step_size.md") as f:
        assert f.read().strip() == ts.line_markdown(res["line"], res["instances"], res["surrogate"]).strip()
    return res


def test_stored_margins_line_at_table_i_falls_more_than_the_full_objectives():
    """The stored C MuJoCo line at Table I down the surrogate of the failure margins alone (mobility, progress and
    stability weighed 0; docs/results/tune_surrogate_line_tablei_margins_cpu): its report is what its rows give, it
    was taken with those weights, it descends its own objective, and on the same step-downs as the full objective's
    line HyQ falls at least as often down it at every distance, more at 0.4 and 0.8, and its extra early ends come
    after the windows."""
    res, full = _stored_line("tune_surrogate_line_tablei_margins_cpu"), _stored_line("tune_surrogate_line_tablei_cpu")
    w = res["surrogate"]["weights"]
    assert w["mobility"] == w["progress"] == w["stability"] == 0 and w["clearance"] == 100.0
    assert res["start"] == full["start"] and res["surrogate"]["windows_s"] == full["surrogate"]["windows_s"]
    mine, theirs = ({x["distance"]: x for x in r["line"]} for r in (res, full))
    assert mine[0.4]["window_loss"] < mine[0.1]["window_loss"] < res["surrogate"]["loss"] < mine[-0.4]["window_loss"]
    for t in (0.1, 0.2, 0.4, 0.8):
        assert mine[t]["counts"]["fell"] >= theirs[t]["counts"]["fell"] > res["start"]["counts"]["fell"]
        assert mine[t]["ended_early_time_s"][0] > res["surrogate"]["windows_s"][1] + 2.0
    assert all(mine[t]["counts"]["fell"] > theirs[t]["counts"]["fell"] for t in (0.4, 0.8))
    assert mine[0.4]["clean_diff_ci95"][1] < 0 and all(x["counts"]["diverged"] == 0 for x in res["line"])


def test_stored_line_with_the_hind_legs_windows_cuts_falls_without_more_clean_runs():
    """The stored C MuJoCo line at Table I with the hind legs' windows too (four a scenario;
    docs/results/tune_surrogate_line_tablei_hind_cpu): its report is what its rows give; down its direction HyQ falls
    in fewer than half the start's runs at 0.2 and 0.4 and up it in more, while clean success ties with the start
    there; the gradient, through contacts late in the run, is thousands of times the front legs' and does not descend
    its own window objective."""
    res, front = _stored_line("tune_surrogate_line_tablei_hind_cpu"), _stored_line("tune_surrogate_line_tablei_cpu")
    sur = res["surrogate"]
    assert sur["windows_per_scenario"] == 4 and sur["windows_valid"] > 16 and sur["windows_s"][1] > 8.0
    assert res["start"] == front["start"] and sur["grad_norm"] > 1000 * front["surrogate"]["grad_norm"]
    fell0 = res["start"]["counts"]["fell"]
    by_t = {x["distance"]: x for x in res["line"]}
    assert all(by_t[t]["counts"]["fell"] < fell0 / 2 for t in (0.2, 0.4)) and by_t[-0.4]["counts"]["fell"] > fell0
    for t in (0.1, 0.2, 0.4):
        lo, hi = by_t[t]["clean_diff_ci95"]
        assert lo <= 0 <= hi
    assert by_t[0.4]["window_loss"] > sur["loss"]  # down its gradient, its own objective rises
    assert all(x["counts"]["diverged"] == 0 for x in res["line"])
    # with every hind-leg window (a 16-s snapshot run) the direction and the falls are the same within a few runs
    all32 = _stored_line("tune_surrogate_line_tablei_hind_lead16_cpu")
    assert all32["surrogate"]["windows_valid"] == 32 and all32["surrogate"]["lead_s"] == 16.0
    assert all32["surrogate"]["direction"][:2] == sur["direction"][:2] == [["body_height[RH]", -0.9609],
                                                                            ["terrain_adaptation[RH]", 0.2768]]
    margins = _stored_line("tune_surrogate_line_tablei_hind_margins_cpu")  # the margins alone, the same 32 windows
    assert margins["surrogate"]["weights"]["progress"] == 0 and margins["surrogate"]["windows_valid"] == 32
    assert [k for k, _ in margins["surrogate"]["direction"][:2]] == ["body_height[RH]", "terrain_adaptation[RH]"]
    assert np.allclose([v for _, v in margins["surrogate"]["direction"][:2]], [-0.961, 0.277], atol=0.002)
    for x, y, z in zip(all32["line"], res["line"], margins["line"]):
        assert x["distance"] == y["distance"] == z["distance"]
        assert abs(x["counts"]["fell"] - y["counts"]["fell"]) <= 2 and abs(z["counts"]["fell"] - y["counts"]["fell"]) <= 2
