"""The crawl's pieces without physics: joint velocity references, planned feet velocities, the shin-strike remedy."""
import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

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


def test_quintic_is_rest_to_rest_and_the_swing_rises_to_its_apex_and_back():
    """``s(0) = 0``, ``s(1) = 1``, increasing, with zero first and second derivatives at both ends (forward-mode
    derivatives, as the controller takes them); the swing's offset along the normal is 0 at lift-off and
    touchdown and ``step_height`` at mid-swing, its highest point, where its rate is 0 from both sides."""
    from hyqjax.control import trajectories

    ds = jax.jacfwd(trajectories.quintic)
    dds = jax.jacfwd(ds)
    assert float(trajectories.quintic(0.0)) == 0.0 and float(trajectories.quintic(1.0)) == 1.0
    for t in (0.0, 1.0):
        assert float(ds(t)) == 0.0 and float(dds(t)) == 0.0
    grid = np.linspace(0.0, 1.0, 201)
    s = np.asarray(trajectories.quintic(jnp.asarray(grid)))
    assert np.all(np.diff(s) > 0)
    h = 0.1
    tan, z = (np.asarray(a) for a in trajectories.swing_profile(jnp.asarray(grid), h))
    np.testing.assert_array_equal(tan, s)
    assert z[0] == 0.0 and z[-1] == 0.0 and z[100] == pytest.approx(h) and z.max() == pytest.approx(h)
    dz = jax.jacfwd(lambda t: trajectories.swing_profile(t, h)[1])
    for t in (0.5 - 1e-4, 0.5 + 1e-4):
        assert abs(float(dz(t))) < 1e-3


@pytest.mark.slow
def test_planned_feet_velocities_are_the_time_derivative_of_the_plan():
    p = CrawlParams.make()
    st = jax.jit(crawl_state.crawl_init)(p, _obs())
    swing_state = jax.jit(crawl_state.start_swing_phase)(p, st, crawl_state.measure(_obs()))
    level = jnp.eye(3)  # hR_b of a level trunk
    planned = jax.jit(lambda p, s, h_r_b, rate: swing.planned_feet(p, s, h_r_b, rate)[:2])
    for phase_start, t in ((None, 0.13), ("swing", 0.2), ("swing", 0.31), ("search", 0.6)):
        s = st
        if phase_start is not None:
            s = swing_state
        rate = jnp.asarray(p.search_speed if phase_start == "search" else 0.0, jnp.float32)
        depth = 0.05 if phase_start == "search" else 0.0
        s = dataclasses.replace(s, t_phase=jnp.asarray(t, jnp.float32), search_depth=jnp.asarray(depth, jnp.float32))
        x, xd = planned(p, s, level, rate)
        eps = 1e-3
        xp = planned(p, dataclasses.replace(s, t_phase=s.t_phase + eps, search_depth=s.search_depth + rate * eps),
                     level, rate)[0]
        xm = planned(p, dataclasses.replace(s, t_phase=s.t_phase - eps, search_depth=s.search_depth - rate * eps),
                     level, rate)[0]
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


def test_speed_limit_removes_driving_torque_past_the_limit_and_never_braking_torque():
    from hyqjax.crawl.controller import speed_limited_torques
    from hyqjax.crawl.params import JOINT_SPEED_BAND

    lim = robot.VELOCITY_LIMIT
    qd = jnp.asarray([0.0, 5.0, -11.9, lim + 0.5 * JOINT_SPEED_BAND, -(lim + 0.5 * JOINT_SPEED_BAND),
                      lim + JOINT_SPEED_BAND, 40.0, 40.0, -40.0, 100.0, 3.0, -3.0], jnp.float32)
    tau = jnp.asarray([150.0, -150.0, -150.0, 100.0, -100.0, 150.0, 150.0, -150.0, 150.0, -80.0, 7.0, 7.0], jnp.float32)
    out = np.asarray(speed_limited_torques(tau, qd, jnp.float32(lim)))
    # Below the limit the torques are exactly the commanded ones.
    assert np.array_equal(out[[0, 1, 2, 10, 11]], np.asarray(tau)[[0, 1, 2, 10, 11]])
    # In the band a torque along the motion is scaled linearly; at its end and beyond it is zero.
    np.testing.assert_allclose(out[[3, 4]], [50.0, -50.0], rtol=1e-6)
    assert out[5] == 0.0 and out[6] == 0.0
    # A torque against the motion (braking) is never limited, at any speed.
    assert out[7] == -150.0 and out[8] == 150.0 and out[9] == -80.0


def test_saturating_forward_search_is_the_linear_one_below_its_limit_and_straight_down_beyond():
    p = CrawlParams.make(shin_remedy=True, search_forward=0.5)
    n = jnp.asarray([0.0, 0.0, 1.0])
    step = jnp.asarray([0.3, 0.0, 0.0])
    assert np.asarray(remedy.search_forward_unit(p, 1, n, step)).tolist() == [1.0, 0.0, 0.0]
    assert np.asarray(remedy.search_forward_unit(p, 3, n, step)).tolist() == [0.0, 0.0, 0.0]  # hind leg
    # the default never saturates
    assert float(remedy.search_forward_excess(p, jnp.float32(0.4), p.search_forward_limit)) == 0.0
    sat = p.replace(search_forward_limit=jnp.float32(0.1))
    d, u = remedy.search_direction(sat, 1, n, step), remedy.search_forward_unit(sat, 1, n, step)

    def foot(s):  # the search's foot offset from the foothold at depth s, as crawl.swing plans it
        return np.asarray(-s * d - remedy.search_forward_excess(sat, jnp.float32(s), sat.search_forward_limit) * u)

    np.testing.assert_allclose(foot(0.1), [0.05, 0.0, -0.1], atol=1e-6)  # linear: 0.5 m forward per m
    np.testing.assert_allclose(foot(0.3), [0.10, 0.0, -0.3], atol=1e-6)  # saturated at 10 cm ahead
    np.testing.assert_allclose(foot(0.5), [0.10, 0.0, -0.5], atol=1e-6)


def test_forward_search_counting_the_drop_below_lift_off_keeps_the_total_offset_under_the_limit():
    """With ``search_forward_lift = w`` a nominal foothold ``drop`` below the lift-off is moved ``w * 0.5 * drop``
    forward before the search; the search's own forward part then saturates so that the two together stay at
    ``search_forward_limit`` ahead of the nominal foothold. At ``w = 0`` the offset is exactly 0."""
    p = CrawlParams.make(shin_remedy=True, search_forward=0.5, search_forward_limit=0.1)
    lift, target = jnp.asarray([0.0, 0.1, 0.0]), jnp.asarray([0.3, 0.1, -0.08])
    assert float(remedy.lift_drop_offset(p, lift, target)) == 0.0
    q = p.replace(search_forward_lift=jnp.float32(1.0))
    off = float(remedy.lift_drop_offset(q, lift, target))
    np.testing.assert_allclose(off, 0.04, atol=1e-7)
    assert float(remedy.lift_drop_offset(q, lift, jnp.asarray([0.3, 0.1, 0.05]))) == 0.0  # a foothold above: none
    left = q.search_forward_limit - off
    for s, fwd in ((0.05, 0.025), (0.12, 0.06), (0.4, 0.06)):  # searched depth -> the search's forward part
        part = 0.5 * s - float(remedy.search_forward_excess(q, jnp.float32(s), left))
        np.testing.assert_allclose(part, fwd, atol=1e-6)
        assert off + part <= 0.1 + 1e-6
    deep = float(remedy.lift_drop_offset(q, lift, jnp.asarray([0.3, 0.1, -0.5])))  # 0.25 m asked, 0.1 allowed
    np.testing.assert_allclose(deep, 0.1, atol=1e-7)


@pytest.mark.slow
def test_step_down_options_lower_and_tilt_the_trunk_only_while_a_step_down_is_under_way():
    # The trunk pitched 0.2 rad on a flat stance: in the horizontal frame the feet plane pitches by as much.
    obs = dataclasses.replace(_obs(), quat=jnp.asarray([np.cos(0.1), 0.0, np.sin(0.1), 0.0], jnp.float32))
    p0 = CrawlParams.make(shin_remedy=True)
    p1 = p0.replace(step_down_lowering=jnp.float32(0.05), terrain_adaptation_step=jnp.float32(0.5))
    st = crawl_state.crawl_init(p0, obs)
    st = dataclasses.replace(st, seq_index=jnp.asarray(2))
    start = jax.jit(crawl_state.start_body_phase)
    measured = crawl_state.measure(obs)
    for deep in (False, True):
        s = dataclasses.replace(st, deep=jnp.zeros(4, bool).at[1].set(deep))
        a, b = start(p0, s, measured), start(p1, s, measured)
        if not deep:  # no step down under way: exactly the default plan
            assert np.array_equal(np.asarray(a.body_delta), np.asarray(b.body_delta))
            assert np.array_equal(np.asarray(a.rp_target), np.asarray(b.rp_target))
        else:
            np.testing.assert_allclose(float(b.body_delta[2] - a.body_delta[2]), -0.05, atol=1e-5)
            adapt0, adapt1 = 0.3, 0.3 + 0.5 * 0.7
            assert abs(float(a.rp_target[1])) > 0.05
            np.testing.assert_allclose(np.asarray(b.rp_target) * adapt0, np.asarray(a.rp_target) * adapt1, atol=1e-6)


def test_crawl_params_reject_bad_values_with_the_parameter_name():
    with pytest.raises(ValueError, match="search_forward"):
        CrawlParams.make(search_forward=-1.0)
    with pytest.raises(ValueError, match="deep_search"):
        CrawlParams.make(deep_search=float("nan"))


@pytest.mark.slow
def test_crawl_step_is_jittable_and_differentiable_in_a_gain():
    from hyqjax.crawl import controller

    p = CrawlParams.make()
    st = jax.jit(controller.crawl_init)(p, _obs())

    def tau_of(k):
        return controller.crawl_step(p.replace(k_com=k), st, _obs(), 0.002)[1]

    j = jax.jit(jax.jacfwd(tau_of))(jnp.asarray(3000.0))
    assert np.all(np.isfinite(np.asarray(j)))


# ------------------------------------------------------------------- the planner: support triangle, feet plane, footholds
from hyqjax.core import spatial  # noqa: E402
from hyqjax.crawl import footholds  # noqa: E402

X_STAND = np.asarray(kinematics.foot_positions(jnp.asarray(robot.Q_STANDING, jnp.float32)))


def _point_to_segment(p, a, b):
    d = b - a
    t = np.clip(np.dot(p - a, d) / np.dot(d, d), 0.0, 1.0)
    return np.linalg.norm(p - (a + t * d))


def test_body_target_puts_the_com_inside_the_shrunk_support_triangle():
    """The body phase's target: the CoM lands in the support triangle of the three other legs, at least the
    stability margin from every edge, the trunk ``body_height`` above the mean foot height; a CoM already deep
    inside the triangle stays where it is."""
    target = jax.jit(footholds.body_target)
    rng = np.random.default_rng(0)
    margin, height = 0.05, 0.56
    for _ in range(12):
        feet = X_STAND + rng.uniform(-0.04, 0.04, (4, 3))
        leg = int(rng.integers(4))
        com = np.r_[rng.uniform(-0.05, 0.05, 2), 0.0]
        delta = np.asarray(target(jnp.asarray(feet), leg, jnp.asarray(com), margin, height))
        tri = feet[robot.STANCE_LEGS[leg], :2]
        c = com[:2] + delta[:2]
        area = [np.cross(tri[(k + 1) % 3] - tri[k], c - tri[k]) for k in range(3)]
        assert np.all(np.sign(area) == np.sign(area[0])), (leg, c, tri)  # inside
        assert min(_point_to_segment(c, tri[k], tri[(k + 1) % 3]) for k in range(3)) >= margin - 1e-5
        assert delta[2] == pytest.approx(np.mean(feet[:, 2]) + height, abs=1e-6)
    # The incentre of the triangle (deep inside) is a fixed point of the CoM placement.
    feet = X_STAND
    tri = feet[robot.STANCE_LEGS[0], :2]
    la, lb, lc = (np.linalg.norm(tri[1] - tri[2]), np.linalg.norm(tri[2] - tri[0]), np.linalg.norm(tri[0] - tri[1]))
    incentre = (la * tri[0] + lb * tri[1] + lc * tri[2]) / (la + lb + lc)
    np.testing.assert_allclose(np.asarray(footholds.closest_in_triangle(jnp.asarray(incentre), *map(jnp.asarray, tri))),
                               incentre, atol=1e-7)


def test_closest_in_triangle_is_the_nearest_point_of_the_triangle():
    closest = jax.jit(footholds.closest_in_triangle)
    rng = np.random.default_rng(1)
    a, b, c = np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.2, 0.8])
    u, v = np.meshgrid(np.linspace(0, 1, 201), np.linspace(0, 1, 201))
    keep = u + v <= 1
    grid = a + u[keep, None] * (b - a) + v[keep, None] * (c - a)  # dense samples of the triangle
    for p in rng.uniform(-1.0, 2.0, (20, 2)):
        q = np.asarray(closest(jnp.asarray(p), jnp.asarray(a), jnp.asarray(b), jnp.asarray(c)))
        best = np.min(np.linalg.norm(grid - p, axis=1))
        assert np.linalg.norm(q - p) <= best + 1e-6
        assert np.linalg.norm(q - p) >= best - 0.01  # within the sampling resolution


def test_feet_plane_recovers_the_trunk_pitch_and_roll_of_a_flat_stance():
    """Feet of the standing pose seen from a trunk pitched (or rolled) by ``a`` relative to the horizontal
    frame, ``R_y(pitch) R_x(roll) x_b``: the fitted plane gives that pitch (or roll) back: the plane fit and the
    frame convention of the crawl agree."""
    plane = jax.jit(footholds.feet_plane)
    for a in (-0.25, -0.1, 0.0, 0.15, 0.3):
        pitched = np.asarray(X_STAND @ np.asarray(spatial.roll_pitch_to_rot(0.0, a)).T)
        rolled = np.asarray(X_STAND @ np.asarray(spatial.roll_pitch_to_rot(a, 0.0)).T)
        np.testing.assert_allclose(np.asarray(plane(jnp.asarray(pitched))), [0.0, a], atol=1e-5)
        np.testing.assert_allclose(np.asarray(plane(jnp.asarray(rolled))), [a, 0.0], atol=1e-5)


def test_footholds_one_step_ahead_on_the_terrain_plane_and_shortened_to_the_workspace():
    """The nominal foothold is one step ahead along x (rotated by the heading change) in the plane through the
    lift-off point normal to ``n``; ``reachable_foothold`` keeps a reachable step, and shortens one that leaves
    the workspace to a point of the same segment whose joints stay ``REACH_MARGIN`` inside their ranges."""
    swing_target = jax.jit(footholds.swing_foothold)
    reach = jax.jit(footholds.reachable_foothold)
    leg = robot.LF
    lift = jnp.asarray(X_STAND[leg])
    up = jnp.asarray([0.0, 0.0, 1.0])
    t = np.asarray(swing_target(lift, lift, 0.1, 0.0, up))
    np.testing.assert_allclose(t, np.asarray(lift) + [0.1, 0.0, 0.0], atol=1e-7)
    n = jnp.asarray([0.2, -0.1, 0.97]) / np.linalg.norm([0.2, -0.1, 0.97])
    for yaw in (0.0, 0.2):
        t = np.asarray(swing_target(lift, lift + jnp.asarray([0.0, 0.03, 0.0]), 0.12, yaw, n))
        assert abs(np.dot(t - np.asarray(lift), np.asarray(n))) < 1e-6  # on the terrain plane through lift-off
    level = jnp.eye(3)  # hR_b of a level trunk
    easy = lift + jnp.asarray([0.08, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(reach(0.1, 0.75, leg, lift, easy, up, level)), np.asarray(easy), atol=1e-7)
    far = lift + jnp.asarray([0.6, 0.0, 0.0])
    got = np.asarray(reach(0.1, 0.75, leg, lift, far, up, level))
    frac = (got[0] - float(lift[0])) / 0.6
    assert frac < 1.0 and np.any(np.isclose(frac, footholds.STEP_FRACTIONS, atol=1e-5))
    np.testing.assert_allclose(got[1:], np.asarray(lift)[1:], atol=1e-7)  # on the segment lift -> target
    x = jnp.asarray(X_STAND).at[leg].set(jnp.asarray(got))
    q = np.asarray(kinematics.inverse_kinematics(x)).reshape(4, 3)[leg]
    assert np.all(q > robot.Q_MIN.reshape(4, 3)[leg] + footholds.REACH_MARGIN - 1e-6)
    assert np.all(q < robot.Q_MAX.reshape(4, 3)[leg] - footholds.REACH_MARGIN + 1e-6)


# ------------------------------------------------------------------- one declaration of every crawl parameter
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from hyqjax.core.params import ParameterError, batch_params, param_ranges  # noqa: E402

CRAWL_SPECS = param_ranges(CrawlParams)


def _around(name):
    """Values around the declared range of ``name`` (about a third inside), its ends, and non-finite values."""
    s = CRAWL_SPECS[name]
    w = s.hi - s.lo
    return st.tuples(st.just(name), st.floats(s.lo - w, s.hi + w) | st.sampled_from([s.lo, s.hi, float("nan"),
                                                                                      float("-inf")]))


FLAGS = ("use_reflex", "shin_remedy", "weight_qp")  # make() takes booleans for these


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(k for k in CRAWL_SPECS if k not in FLAGS)).flatmap(_around))
def test_make_accepts_exactly_the_declared_range(case):
    """``CrawlParams.make`` accepts a value iff it lies in the range the field declares; a refusal names the field
    and that range; accepted values are float32 leaves and pass ``validate``."""
    name, value = case
    spec = CRAWL_SPECS[name]
    ok = bool(spec.in_range(np.asarray(value)))
    try:
        p = CrawlParams.make(**{name: value})
    except ParameterError as e:
        assert not ok and e.param == name and spec.range_text in str(e), str(e)
        return
    assert ok
    assert getattr(p, name).dtype == jnp.float32 and p.validate() is p


def test_batched_crawl_params_validate_every_element_and_the_sweep_axis_uses_the_declaration():
    from hyqjax.studies.sweep.axes import AXES

    spec = CRAWL_SPECS["forward_velocity"]
    speed = AXES["speed"]
    assert (speed.lo, speed.hi, speed.unit, speed.default) == (spec.lo, spec.hi, spec.unit, spec.default)
    p = CrawlParams.make(forward_velocity=spec.hi)  # an end of the range survives float32
    assert p.validate() is p
    good = batch_params(p, 3, forward_velocity=np.array([spec.lo, 0.0, spec.hi]))
    assert good.validate() is good and good.forward_velocity.shape == (3,)
    with pytest.raises(ParameterError, match=r"CrawlParams\.forward_velocity=0\.31 out of range: must be in "
                                             r"\[-0\.3, 0\.3\] m/s"):
        batch_params(p, 3, forward_velocity=np.array([0.0, 0.31, 0.1])).validate()
    with pytest.raises(ParameterError, match=r"foot_sequence=\(0, 0, 2, 3\) is not a leg order"):
        batch_params(p, 2, foot_sequence=np.array([[3, 1, 2, 0], [0, 0, 2, 3]])).validate()
    with pytest.raises(ParameterError, match=r"ReflexParams\.k_base"):
        batch_params(p, 2, reflex=dict(k_base=np.array([1500.0, -1.0])))


def test_loaded_stance_drops_a_stance_foot_that_stopped_pressing_and_keeps_two():
    """``stance_min_force``: a stance foot that pressed on the ground since its touchdown and now presses below
    the threshold (along the vertical of the tilted trunk: a foot that slipped off the edge) carries no trunk load;
    a stance foot that has not pressed yet (a swing ended at a limit, its foot in the air) keeps its share; with
    fewer than two carrying feet, or with the option off (0 N, the default), every stance foot carries the trunk."""
    from hyqjax.crawl.controller import loaded_stance, pressing_feet

    pitch = 0.3
    h_r_b = spatial.roll_pitch_to_rot(jnp.float32(0.0), jnp.float32(pitch))
    up_b = np.asarray(h_r_b).T @ np.array([0.0, 0.0, 1.0])
    off, on = CrawlParams.make(), CrawlParams.make(stance_min_force=20.0)
    forces = jnp.asarray(np.array([120.0, 5.0, 90.0, 200.0])[:, None] * up_b)  # RF barely presses
    pressing = pressing_feet(on, forces, h_r_b)
    assert np.asarray(pressing).tolist() == [True, False, True, True]
    sideways = jnp.asarray(np.array([[0.0, 80.0, 0.0]] * 4) @ np.asarray(h_r_b))  # horizontal in H: no vertical load
    assert not np.any(np.asarray(pressing_feet(on, sideways, h_r_b)))
    stance = jnp.array([1.0, 1.0, 1.0, 0.0])  # RH swings
    slipped = jnp.array([True, True, True, False])  # RF pressed earlier in this stance
    never = jnp.array([True, False, True, False])  # RF has not touched down yet
    np.testing.assert_array_equal(loaded_stance(off, stance, slipped, pressing), stance)
    np.testing.assert_array_equal(loaded_stance(on, stance, slipped, pressing), [1.0, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(loaded_stance(on, stance, never, pressing), stance)
    only_one = jnp.array([True, False, False, True])  # two of three stance feet slipped: keep all three
    np.testing.assert_array_equal(loaded_stance(on, stance, jnp.ones(4, bool), only_one), stance)


def test_crawl_state_keeps_its_types_through_a_step_so_a_scan_traces_its_body_once():
    """Under x64 every leaf of the crawl's state, and of the step-down metrics, leaves a step with the type it
    entered with, none weakly typed: ``lax.scan`` traces a rollout's body (MJX and the controller, about 10^5
    primitives) once. A weakly typed integer (``jnp.asarray(0)``, int64 under x64) that the step turns into int32
    makes the scan trace the whole body a second time."""
    from hyqjax.crawl import controller
    from hyqjax.studies import stepdown_outcome

    with jax.enable_x64(True):
        obs = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), _obs())
        p = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(jnp.asarray(x).dtype,
                                   jnp.floating) else x, CrawlParams.make())
        st = jax.eval_shape(controller.crawl_init, p, obs)  # types only (nothing runs)
        traces = []

        def body(s, _):
            traces.append(1)
            return controller.crawl_step(p, s, obs, 0.002)[0], None

        closed = jax.make_jaxpr(lambda s: jax.lax.scan(body, s, None, length=3)[0])(st)
        assert len(traces) == 1
        for a, b in zip(jax.tree_util.tree_leaves(st), closed.out_avals):
            assert (a.shape, a.dtype) == (b.shape, b.dtype) and not a.weak_type
        ids = types.SimpleNamespace(contacts=None, foot_sites=np.zeros(4, int), qpos_joints=np.arange(7, 19))
        init = stepdown_outcome.make_metrics(ids, 100.0).init
        ms = jax.eval_shape(lambda q: init(types.SimpleNamespace(qpos=q)), jnp.zeros(19, jnp.float64))
        assert not [x for x in jax.tree_util.tree_leaves(ms) if x.weak_type]
