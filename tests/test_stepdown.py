"""The step-down experiment (Focchi et al. 2017, Section IV) at CPU size: the paper's qualitative result, and the
same outcomes on MJX-JAX.

One batch: a 16 cm and a 24 cm platform, the reflex off and on, one instance each (the same randomised instance for
every pair), 24 s of closed-loop crawling at 0.1 m/s on C MuJoCo (what ``impl="auto"`` runs on a CPU); the batch
again on MJX-JAX, where every instance must end with the same outcome.
"""
from __future__ import annotations

import numpy as np
import pytest

from hyqjax.core import robot
from hyqjax.crawl import controller as crawl
from hyqjax.studies import stepdown

HEIGHTS = (0.16, 0.24)
PARAMS = crawl.CrawlParams.make(forward_velocity=0.1)


@pytest.fixture(scope="module")
def scenario():
    """The batch and its table of inputs."""
    return stepdown.make_scenarios(HEIGHTS, [False, True], 1, seed=0, params=PARAMS)


@pytest.fixture(scope="module")
def stepdown_run(scenario):
    batch, table = scenario
    out, _ = stepdown.run_batch(batch, stepdown.StepdownConfig(duration=24.0, impl="c"))
    return table, out


def _row(table, out, height, reflex):
    i = int(np.nonzero((table["height"] == height) & (table["reflex"] == reflex))[0][0])
    return {k: v[i] for k, v in out.items()}


@pytest.mark.slow
def test_reflex_is_needed_at_24_cm(stepdown_run):
    table, out = stepdown_run
    off, on = _row(table, out, 0.24, False), _row(table, out, 0.24, True)
    # Without the reflex a swing leg stretches to its workspace limit before finding the ground: stance is
    # triggered with the foot in the air (the paper's failure mode).
    assert not off["completed"] and not off["clean"] and off["lost_foothold"]
    assert off["lost_footholds"] >= 1 and off["n_limit_stops"] >= 1
    # With it, the stance legs take over part of the searching motion and every foot finds the ground.
    # The one failure the reflex does not address is a front shin resting on the edge when a foot lands
    # just past it (blind crawl; 42% of runs at 24 cm on a GPU, docs/stepdown.md): allowed here, nothing else is.
    assert on["completed"], stepdown.failure_labels(on)
    assert stepdown.failure_labels(on) in ([], ["shin strike"]), stepdown.failure_labels(on)
    assert on["lost_footholds"] == 0 and on["n_limit_stops"] == 0
    assert np.isfinite(on["time_all_down"])
    assert on["min_swing_mobility"] > off["min_swing_mobility"] + 0.01


@pytest.mark.slow
def test_16_cm_every_foot_finds_the_ground_with_the_reflex(stepdown_run):
    table, out = stepdown_run
    on = _row(table, out, 0.16, True)
    assert on["completed"], stepdown.failure_labels(on)
    assert stepdown.failure_labels(on) in ([], ["shin strike"]), stepdown.failure_labels(on)
    assert on["clean"] == (not on["shin_strike"])
    assert on["lost_footholds"] == 0 and np.isfinite(on["time_all_down"])
    assert on["peak_pitch"] < 0.4 and on["peak_roll"] < 0.4


@pytest.mark.slow
def test_no_instance_diverges_and_metrics_are_finite(stepdown_run):
    _, out = stepdown_run
    assert not np.any(out["diverged"])
    for k in ("peak_pitch", "peak_roll", "mean_mobility", "min_swing_mobility", "progress"):
        assert np.all(np.isfinite(out[k])), k
    assert np.all(out["progress"] > 0.5)


@pytest.mark.slow
def test_c_and_mjx_step_down_outcomes_agree(scenario, stepdown_run, monkeypatch):
    """The batch on MJX-JAX (float32) ends like on C MuJoCo (float64): every instance has the same outcome (completed,
    clean, each failure reason). MJX-JAX runs it in chunks of 0.6 s (bitwise the one-scan run, tests/test_sim.py):
    the chunk program (batch 4, 300 ticks) of tests/test_cpu_backend.py's trajectory agreement, compiled once in the
    session."""
    from conftest import compiled_for_long_runs
    from hyqjax.studies import stepdown_outcome as so

    _, c_cols = stepdown_run
    ro = compiled_for_long_runs(stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=24.0, impl="jax")),
                                monkeypatch)
    out, _ = ro.run(scenario[0], chunk_seconds=0.6)
    jax_cols = so.to_columns(out)
    for k in ("completed", "clean", *so.FAILURE_REASONS):
        np.testing.assert_array_equal(c_cols[k], jax_cols[k], err_msg=k)
    assert c_cols["completed"].any() and not c_cols["completed"].all()  # both kinds of outcome occur


@pytest.mark.slow
def test_scenarios_pair_reflex_on_and_off_on_identical_instances():
    _, table = stepdown.make_scenarios([0.16, 0.21], [False, True], 3, seed=7)
    for k in ("friction", "payload_mass", "start_distance", "lateral_offset", "yaw"):
        v = table[k].reshape(2, 2, 3)
        assert np.array_equal(v[:, 0], v[:, 1]) and np.array_equal(v[0], v[1]), k


def test_instance_is_the_batch_row_and_refuses_an_index_outside_the_batch():
    """``Scenario.instance(i)`` is row ``i`` of every field (negative ``i`` from the end, as NumPy's), gathered in
    one program; an index outside ``[-B, B)`` is one line naming ``i`` and the range."""
    import jax

    scenario, _ = stepdown.make_scenarios(HEIGHTS, [False, True], 2, seed=0)
    b = scenario.batch_size
    for i in (0, 5, -1):
        for got, whole in zip(jax.tree_util.tree_leaves(scenario.instance(i)), jax.tree_util.tree_leaves(scenario)):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(whole)[i])
            assert np.asarray(got).dtype == np.asarray(whole).dtype
    for bad in (b, -b - 1, 1.0):
        with pytest.raises(IndexError, match=rf"i must be an int in \[-{b}, {b}\)"):
            scenario.instance(bad)


def test_bad_height_is_rejected_before_compiling():
    with pytest.raises(ValueError, match="platform_height"):
        stepdown.make_scenarios([0.6], [True], 1, seed=0)


# ---------------------------------------------------------------- outcome hierarchy and table (no MJX compile)


def _fake_result(**metrics):
    """A one-instance rollout result whose metrics are a passing run, with ``metrics`` overriding fields."""
    import types

    import jax.numpy as jnp

    from hyqjax.sim import rollout as sim
    from hyqjax.studies import stepdown_outcome as so

    f, no = jnp.asarray(0.1, jnp.float32), jnp.array(False)
    base = dict(peak_roll=f, peak_pitch=f, trunk_strike=no, shin_strike=no, shin_contact=no, peak_shin_force=f,
                peak_trunk_force=f, joint_past_range=no, min_swing_mobility=f, mobility_sum=f * 100,
                swing_down_ticks=jnp.asarray(100), lost_footholds=jnp.asarray(0), time_all_down=f * 100,
                x_start=jnp.asarray(-0.4, jnp.float32), reflex_failure=no, contact_overflow=no)
    base.update({k: jnp.asarray(v) for k, v in metrics.items()})
    ms = so.StepdownMetrics(**base)
    qpos = jnp.zeros(19, jnp.float32).at[0].set(1.5)
    site_xpos = jnp.zeros((10, 3), jnp.float32).at[:, 0].set(1.0)  # every site (feet too) past the edge
    data = types.SimpleNamespace(qpos=qpos, site_xpos=site_xpos)
    cs = types.SimpleNamespace(n_steps=jnp.asarray(12), n_touchdowns=jnp.asarray(12), n_limit_stops=jnp.asarray(0))
    return sim.RolloutResult(data, cs, ms, jnp.array(False), jnp.asarray(-1), None)


@pytest.mark.parametrize("metrics, reason, completed", [
    ({}, None, True),
    (dict(shin_strike=True), "shin_strike", True),
    (dict(trunk_strike=True), "trunk_strike", False),
    (dict(lost_footholds=2), "lost_foothold", False),
    (dict(joint_past_range=True), "joint_past_range", False),
    (dict(peak_pitch=0.5), "tilt", False),
    (dict(peak_roll=float("nan")), ("tilt", "diverged"), False),  # a NaN angle is no bounded tilt either
    (dict(time_all_down=-1.0), "feet_not_down", False),
    (dict(reflex_failure=True), "reflex_failure", False),
    (dict(contact_overflow=True), "contact_overflow", False),
])
@pytest.mark.slow
def test_outcome_hierarchy(hyq, metrics, reason, completed):
    """completed: the paper's criterion; clean: completed and no shin / trunk strike; one boolean per reason."""
    from hyqjax.studies import stepdown_outcome as so

    _, ids = hyq
    out = so.outcome(_fake_result(**metrics), ids, max_tilt=0.4, min_progress=0.5)
    set_reasons = [k for k in so.FAILURE_REASONS if bool(getattr(out, k))]
    assert set_reasons == ([] if reason is None else [reason] if isinstance(reason, str) else list(reason))
    assert bool(out.completed) == completed
    assert bool(out.clean) == (reason is None)
    assert float(out.progress) == pytest.approx(1.9)


@pytest.mark.parametrize("metrics, fell", [
    ({}, False), (dict(shin_strike=True), False), (dict(lost_footholds=2), False),
    (dict(joint_past_range=True), False), (dict(peak_pitch=0.39), False), (dict(time_all_down=-1.0), False),
    (dict(peak_pitch=0.4), True), (dict(peak_roll=3.0), True), (dict(trunk_strike=True), True),
    (dict(peak_roll=float("nan")), True),
])
def test_episode_ends_only_at_failures_no_later_tick_undoes(metrics, fell):
    """The step-down's episode end (a fall: tilt past max_tilt or a trunk strike) is a failure of the outcome that
    no later tick can undo, so it never ends a run that would complete; the outcome carries the flag and tick."""
    import jax.numpy as jnp

    from hyqjax.studies import stepdown_outcome as so

    res = _fake_result(**metrics)
    assert bool(so.fallen(res.metrics, 0.4)) == fell
    ids = type("Ids", (), dict(foot_sites=(0, 1, 2, 3)))()
    out = so.outcome(res, ids, max_tilt=0.4, min_progress=0.5)
    if fell:
        assert not bool(out.completed) and not bool(out.clean)
    assert not bool(out.terminated) and int(out.terminated_tick) == -1  # a result without the flags
    out = so.outcome(res._replace(terminated=jnp.array(fell), terminated_tick=jnp.asarray(7 if fell else -1)), ids,
                     max_tilt=0.4, min_progress=0.5)
    assert bool(out.terminated) == fell and int(out.terminated_tick) == (7 if fell else -1)
    assert not bool(out.diverged) or metrics.get("peak_roll") != 3.0


def test_summary_reports_completed_clean_with_wilson_and_share_of_runs():
    table = dict(height=np.full(4, 0.16), reflex=np.ones(4, bool))
    n = 4
    out = dict(completed=np.array([1, 1, 1, 0], bool), clean=np.array([1, 0, 1, 0], bool),
               feet_not_down=np.zeros(n, bool), lost_foothold=np.array([0, 0, 0, 1], bool),
               lost_footholds=np.array([0, 0, 0, 3]), joint_past_range=np.zeros(n, bool),
               shin_strike=np.array([0, 1, 0, 0], bool), min_swing_mobility=np.full(n, 0.1),
               mean_mobility=np.full(n, 0.8), peak_pitch=np.full(n, 0.1), time_all_down=np.full(n, 10.0),
               diverged=np.zeros(n, bool), terminated=np.array([0, 0, 0, 1], bool))
    (row,) = stepdown.summarize(table, out)
    assert (row["terminated"], row["diverged"]) == (1, 0)
    assert (row["completed"], row["clean"], row["n"]) == (3, 2, 4)
    assert row["completed_ci95"] == pytest.approx(stepdown.wilson_interval(3, 4))
    assert row["clean_ci95"] == pytest.approx(stepdown.wilson_interval(2, 4))
    assert row["lost_foothold_share"] == pytest.approx(0.25)  # a share of runs, not the mean count (0.75)
    assert row["mean_lost_footholds"] == pytest.approx(0.75)
    text = stepdown.format_table([row])
    assert "completed" in text and "clean" in text and "share of runs" in text


def test_wilson_interval_matches_the_closed_form():
    lo, hi = stepdown.wilson_interval(0, 1700)
    assert lo == 0.0 and hi == pytest.approx(0.00226, abs=1e-4)
    lo, hi = stepdown.wilson_interval(1404, 1700)
    assert (lo, hi) == pytest.approx((0.807, 0.843), abs=1e-3)


def test_config_rejects_bad_impl_and_values():
    with pytest.raises(ValueError, match="impl"):
        stepdown.StepdownConfig(impl="cuda")
    with pytest.raises(ValueError, match="strike_force"):
        stepdown.StepdownConfig(strike_force=-1.0)
    with pytest.raises(ValueError, match="duration"):
        stepdown.StepdownConfig(duration=0.0)


@pytest.mark.slow
def test_start_qpos_numpy_and_jax_agree(hyq):
    import jax.numpy as jnp

    from hyqjax.sim import model as hmodel

    m, _ = hyq
    sc, _ = stepdown.make_scenarios([0.16, 0.24], [True], 3, seed=1)
    q_np = stepdown.initial_qpos(m, sc)
    q_j = stepdown.start_qpos(jnp.asarray(hmodel.standing_qpos(m)), sc.start_distance, sc.lateral_offset, sc.yaw,
                              sc.terrain.platform_height, xp=jnp)
    np.testing.assert_allclose(np.asarray(q_j), q_np, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q_np[:, 3:7], axis=1), 1.0, atol=1e-6)
    # the front hips' line at zero heading, moved back by the leading front foot's advance under the heading
    # (tests/test_start_pose.py checks the feet themselves on MuJoCo's kinematics)
    front_line_x = q_np[:, 0] + float(robot.B_P_HIP[0, 0]) + stepdown.leading_foot_advance(np.asarray(sc.yaw))
    np.testing.assert_allclose(front_line_x, -np.asarray(sc.start_distance), atol=1e-6)


