"""The crawl's pieces without physics: joint velocity references, planned feet velocities, the shin-strike remedy."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics
from hyqjax.core import robot
from hyqjax.crawl import remedy
from hyqjax.crawl import state as crawl_state
from hyqjax.crawl import swing
from hyqjax.crawl.params import CrawlParams
from hyqjax.sim import rollout as sim


def _obs(q=robot.Q_STANDING):
    q = jnp.asarray(q, jnp.float32)
    z = jnp.zeros(12, jnp.float32)
    return sim.Observation(q=q, qd=z, tau=z, quat=jnp.array([1.0, 0, 0, 0]), gyro=jnp.zeros(3),
                           foot_force=jnp.zeros((4, 3)), time=jnp.zeros(()))


def test_joint_velocities_invert_the_foot_jacobian():
    q = jnp.asarray(robot.Q_STANDING, jnp.float32)
    xd = jnp.asarray(np.random.default_rng(0).normal(0, 0.3, (4, 3)), jnp.float32)
    qd = swing.joint_velocities(q, xd)
    np.testing.assert_allclose(np.asarray(kinematics.foot_velocities(q, qd)), np.asarray(xd), atol=2e-3)


def test_planned_feet_velocities_are_the_time_derivative_of_the_plan():
    p = CrawlParams.make()
    st = crawl_state.crawl_init(p, _obs())
    rp = jnp.zeros(2)
    for phase_start, t in ((None, 0.13), ("swing", 0.2), ("swing", 0.31), ("search", 0.6)):
        s = st
        if phase_start is not None:
            s = crawl_state.start_swing_phase(p, st, _obs())
        rate = p.search_speed if phase_start == "search" else 0.0
        depth = 0.05 if phase_start == "search" else 0.0
        s = dataclasses.replace(s, t_phase=jnp.asarray(t, jnp.float32), search_depth=jnp.asarray(depth, jnp.float32))
        x, xd = swing.planned_feet(p, s, rp, rate)[:2]
        eps = 1e-3
        xp = swing.planned_feet(p, dataclasses.replace(s, t_phase=s.t_phase + eps, search_depth=s.search_depth
                                                       + rate * eps), rp, rate)[0]
        xm = swing.planned_feet(p, dataclasses.replace(s, t_phase=s.t_phase - eps, search_depth=s.search_depth
                                                       - rate * eps), rp, rate)[0]
        fd = (np.asarray(xp) - np.asarray(xm)) / (2 * eps)
        np.testing.assert_allclose(np.asarray(xd), fd, atol=5e-3)
        assert np.abs(np.asarray(xd)).max() > 0.01  # something moves in each case


def test_follow_up_brings_the_other_front_leg_forward_for_the_rest_of_the_cycle():
    p = CrawlParams.make(shin_remedy=True)  # rh-rf-lh-lf = (3, 1, 2, 0)
    seq = jnp.asarray(p.foot_sequence)
    no = jnp.zeros(4, bool)
    # RF (index 1) found a step down: LF swings next, LH after it.
    out = remedy.follow_up(p, seq, jnp.asarray(1), jnp.asarray(1), jnp.asarray(True), no)
    assert out.tolist() == [3, 1, 0, 2]
    # At the end of the cycle the order returns to foot_sequence.
    assert remedy.follow_up(p, out, jnp.asarray(3), jnp.asarray(2), jnp.asarray(False), no).tolist() == [3, 1, 2, 0]
    # Not after a shallow swing, a hind leg's step down, a partner already down, or with the remedy off.
    assert remedy.follow_up(p, seq, jnp.asarray(1), jnp.asarray(1), jnp.asarray(False), no).tolist() == [3, 1, 2, 0]
    assert remedy.follow_up(p, seq, jnp.asarray(0), jnp.asarray(3), jnp.asarray(True), no).tolist() == [3, 1, 2, 0]
    assert remedy.follow_up(p, seq, jnp.asarray(1), jnp.asarray(1), jnp.asarray(True),
                            no.at[0].set(True)).tolist() == [3, 1, 2, 0]
    off = CrawlParams.make()
    assert remedy.follow_up(off, seq, jnp.asarray(1), jnp.asarray(1), jnp.asarray(True), no).tolist() == [3, 1, 2, 0]


def test_forward_search_only_for_front_legs_with_the_remedy_and_the_reflex():
    n = jnp.asarray([0.3, 0.0, 0.954])
    step = jnp.asarray([0.3, 0.0, 0.0])
    on = CrawlParams.make(shin_remedy=True, search_forward=0.5)
    np.testing.assert_allclose(remedy.search_direction(on, 1, n, step), [-0.5, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(remedy.search_direction(on, 3, n, step), n)
    np.testing.assert_allclose(remedy.search_direction(CrawlParams.make(), 1, n, step), n)
    np.testing.assert_allclose(remedy.search_direction(on.replace(use_reflex=jnp.asarray(0.0)), 1, n, step), n)


def test_crawl_params_reject_bad_values_with_the_parameter_name():
    import pytest

    with pytest.raises(ValueError, match="search_forward"):
        CrawlParams.make(search_forward=-1.0)
    with pytest.raises(ValueError, match="deep_search"):
        CrawlParams.make(deep_search=float("nan"))


def test_crawl_step_is_jittable_and_differentiable_in_a_gain():
    from hyqjax.crawl import controller

    p = CrawlParams.make()
    st = controller.crawl_init(p, _obs())

    def tau_of(k):
        return controller.crawl_step(p.replace(k_com=k), st, _obs(), 0.002)[1]

    j = jax.jit(jax.jacfwd(tau_of))(jnp.asarray(3000.0))
    assert np.all(np.isfinite(np.asarray(j)))
