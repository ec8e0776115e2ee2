"""The HyQ MJCF and the per-instance terrain batching of hyqjax.sim.model."""
from __future__ import annotations


import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from hyqjax.sim import model as hmodel
from hyqjax.core import robot
from hyqjax.control import stand


# ---------------------------------------------------------------- the URDF's numbers


def test_masses(hyq):
    m, ids = hyq
    assert m.body("trunk").mass[0] == pytest.approx(58.96, abs=1e-9)
    for leg in robot.LEG_NAMES:
        assert m.body(f"{leg}_hipassembly").mass[0] == pytest.approx(2.93, abs=1e-9)
        assert m.body(f"{leg}_upperleg").mass[0] == pytest.approx(2.638, abs=1e-9)
        assert m.body(f"{leg}_lowerleg").mass[0] == pytest.approx(0.881, abs=1e-9)
    assert m.body_mass[ids.payload_body] == 0.0
    assert m.body_mass.sum() == pytest.approx(84.756, abs=1e-9)
    assert m.body_subtreemass[ids.trunk_body] == pytest.approx(robot.TOTAL_MASS, abs=1e-9)


def test_leg_geometry(hyq):
    m, _ = hyq
    for leg, hip in zip(robot.LEG_NAMES, robot.B_P_HIP):
        np.testing.assert_allclose(m.body(f"{leg}_hipassembly").pos, hip, atol=1e-12)
        np.testing.assert_allclose(np.abs(hip), (0.3735, 0.207, 0.0), atol=1e-12)
        np.testing.assert_allclose(m.body(f"{leg}_upperleg").pos, (0, 0, -robot.L_HAA_HFE), atol=1e-12)
        np.testing.assert_allclose(m.body(f"{leg}_lowerleg").pos, (0, 0, -robot.L_UPPER), atol=1e-12)
        np.testing.assert_allclose(m.site(f"{leg}_foot").pos, (0, 0, -robot.L_LOWER), atol=1e-12)
        foot = m.geom(f"{leg}_foot")
        assert foot.type[0] == mujoco.mjtGeom.mjGEOM_SPHERE
        np.testing.assert_allclose(foot.pos, (0, 0, -robot.L_LOWER), atol=1e-12)
        assert foot.size[0] == pytest.approx(robot.FOOT_RADIUS, abs=1e-12)
    assert (robot.L_HAA_HFE, robot.L_UPPER, robot.L_LOWER, robot.FOOT_RADIUS) == (0.08, 0.35, 0.341, 0.02175)
    # Sides: left hips at +y, front at +x; HAA axes along -+x as robot.HAA_AXIS_SIGN says, HFE/KFE along +y.
    for i, leg in enumerate(robot.LEG_NAMES):
        np.testing.assert_allclose(m.joint(f"{leg}_haa").axis, (robot.HAA_AXIS_SIGN[i], 0, 0), atol=1e-12)
        np.testing.assert_allclose(m.joint(f"{leg}_hfe").axis, (0, 1, 0), atol=1e-12)
        np.testing.assert_allclose(m.joint(f"{leg}_kfe").axis, (0, 1, 0), atol=1e-12)


def test_joint_ranges_and_actuators(hyq):
    m, ids = hyq
    jids = [m.joint(f"{leg}_{j}").id for leg in robot.LEG_NAMES for j in robot.JOINT_NAMES]
    assert all(m.jnt_limited[j] for j in jids)
    rng = m.jnt_range[jids]
    np.testing.assert_allclose(rng[:, 0], robot.Q_MIN, atol=1e-9)
    np.testing.assert_allclose(rng[:, 1], robot.Q_MAX, atol=1e-9)
    # Front and hind ranges differ (HFE and KFE), HAA is the same on all legs.
    assert not np.allclose(robot.Q_MIN_LEG[robot.LF, 1:], robot.Q_MIN_LEG[robot.LH, 1:])
    assert not np.allclose(robot.Q_MAX_LEG[robot.LF, 1:], robot.Q_MAX_LEG[robot.LH, 1:])
    np.testing.assert_allclose(robot.Q_MIN_LEG[robot.LF], robot.Q_MIN_LEG[robot.RF])
    np.testing.assert_allclose(robot.Q_MIN_LEG[robot.LH], robot.Q_MIN_LEG[robot.RH])
    np.testing.assert_allclose(robot.Q_MIN_LEG[:, 0], robot.Q_MIN_LEG[0, 0])
    # Knee direction of the ranges is robot.KNEE_SIGN.
    assert np.all(np.sign(robot.Q_MIN_LEG[:, 2] + robot.Q_MAX_LEG[:, 2]) == robot.KNEE_SIGN)
    # 12 motors in joint order, +-150 N m, gear 1.
    assert m.nu == 12
    assert list(m.actuator_trnid[:, 0]) == jids
    assert np.all(m.actuator_ctrllimited == 1)
    np.testing.assert_array_equal(m.actuator_ctrlrange, np.tile([-150.0, 150.0], (12, 1)))
    assert robot.TORQUE_LIMIT == 150.0
    np.testing.assert_array_equal(m.actuator_gear[:, 0], 1.0)


def test_standing_keyframe(hyq):
    m, ids = hyq
    key = m.key("standing")
    np.testing.assert_allclose(key.qpos[7:], robot.Q_STANDING, atol=1e-12)
    np.testing.assert_allclose(key.qpos[:7], (0, 0, robot.STANDING_BASE_Z, 1, 0, 0, 0), atol=1e-12)
    np.testing.assert_allclose(hmodel.standing_qpos(m), key.qpos)
    np.testing.assert_allclose(hmodel.standing_qpos(m, (1.0, 2.0), 0.3)[:3], (1.0, 2.0, robot.STANDING_BASE_Z + 0.3))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, key.id)
    mujoco.mj_forward(m, d)
    # The feet are the robot's lowest points and touch the ground (to 0.1 mm).
    bottoms = d.site_xpos[list(ids.foot_sites), 2] - robot.FOOT_RADIUS
    assert np.all(np.abs(bottoms) < 1e-4), bottoms
    # Only the feet touch: every other robot geom is clear of the floor.
    for g in range(m.ngeom):
        if m.geom_bodyid[g] == 0:
            continue
        dist = mujoco.mj_geomDistance(m, d, g, ids.floor_geom, 1.0, None)
        if g in ids.foot_geoms:
            assert 0.0 <= dist < 1e-4, (m.geom(g).name, dist)
        else:
            assert dist > 0.02, (m.geom(g).name, dist)


# ---------------------------------------------------------------- contacts


def _can_collide(m, g1, g2):
    return bool((m.geom_contype[g1] & m.geom_conaffinity[g2]) or (m.geom_contype[g2] & m.geom_conaffinity[g1]))


def test_contact_filtering_masks(hyq):
    m, ids = hyq
    terrain = [g for g in range(m.ngeom) if m.geom_bodyid[g] == 0]
    robot_geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] != 0]
    assert set(terrain) == {ids.floor_geom, ids.platform_geom, *ids.block_geoms}
    assert set(robot_geoms) == {ids.trunk_geom, *ids.foot_geoms, *ids.shin_geoms}
    for g1 in range(m.ngeom):
        for g2 in range(g1 + 1, m.ngeom):
            one_each = (g1 in terrain) != (g2 in terrain)
            assert _can_collide(m, g1, g2) == one_each, (m.geom(g1).name, m.geom(g2).name)
    # Rough-terrain blocks get the terrain masks too.
    mb = hmodel.load_model(hmodel.TerrainLayout(n_blocks_x=2, n_blocks_y=1))
    ib = hmodel.model_ids(mb)
    assert len(ib.block_geoms) == 4
    for b in ib.block_geoms:
        assert _can_collide(mb, b, ib.foot_geoms[0]) and not _can_collide(mb, b, ib.floor_geom)


def test_feet_shins_trunk_touch_the_terrain_and_nothing_else(hyq):
    m, ids = hyq
    d = mujoco.MjData(m)
    # Trunk lowered into the floor with straight legs: feet, shins and trunk all penetrate the
    # terrain, and the legs cross each other's space (HAA at the inner limit) without contacting.
    d.qpos[:] = hmodel.standing_qpos(m, base_xy=(1.5, 0.0))
    d.qpos[2] = 0.05
    q = np.zeros(12)
    q[0::3] = robot.Q_MAX[0::3]  # HAA inward
    d.qpos[7:] = q
    mujoco.mj_forward(m, d)
    pairs = {(int(c.geom1), int(c.geom2)) for c in d.contact[: d.ncon]}
    touched = {g for p in pairs for g in p if m.geom_bodyid[g] != 0}
    assert ids.trunk_geom in touched
    assert set(ids.foot_geoms) <= touched
    assert set(ids.shin_geoms) <= touched
    for g1, g2 in pairs:
        assert (m.geom_bodyid[g1] == 0) != (m.geom_bodyid[g2] == 0), (m.geom(g1).name, m.geom(g2).name)


# ---------------------------------------------------------------- per-instance terrain in MJX

HEIGHTS = np.array([0.0, 0.15, 0.3])
PAYLOAD = (0.0, 0.0, 15.0)
PAYLOAD_COM = np.array([[0, 0, 0], [0, 0, 0], [0.1, -0.05, 0.05]])


@pytest.fixture(scope="module")
def batched_platform_run(hyq):
    """One jitted, vmapped ``lax.scan`` of ``mjx.step`` over 3 instances with different platform heights
    (and a payload on the last): 0.5 s of HyQ standing on the platform (all feet on it, at x = -1 m,
    started 0.5 mm into it) under joint PD + weight feed-forward.

    Returns the first step's contacts and whole-robot CoM (``mjx.step`` computes them at the state it
    starts from, the initial one) and the final data."""
    m, ids = hyq
    mx = mjx.put_model(m)
    terrain = hmodel.InstanceTerrain.make(HEIGHTS, payload_mass=PAYLOAD, payload_com=PAYLOAD_COM)
    mxb = hmodel.batch_model(mx, ids, terrain)
    qpos0 = np.stack([hmodel.standing_qpos(m, base_xy=(-1.0, 0.0), ground_height=h) for h in HEIGHTS])
    qpos0[:, 2] -= 5e-4
    qadr, vadr = np.asarray(ids.qpos_joints), np.asarray(ids.dof_joints)
    params = stand.StandParams.make()
    kp, kd = params.gains.per_joint()

    def one(mm, qpos):
        d = mjx.make_data(mm).replace(qpos=qpos)

        def body(dd, _):
            q, qd = dd.qpos[qadr], dd.qvel[vadr]
            tau = kp * (params.q_ref - q) - kd * qd + stand.weight_feedforward(q, dd.qpos[3:7])
            dn = mjx.step(mm, dd.replace(ctrl=jnp.clip(tau, -150.0, 150.0)))
            return dn, (dn._impl.contact, dn.subtree_com[ids.trunk_body])

        d_last, (contacts, com) = jax.lax.scan(body, d, None, length=250)
        first = jax.tree_util.tree_map(lambda x: x[0], contacts)
        return first, com[0], d_last

    fn = jax.jit(jax.vmap(one, in_axes=(hmodel.model_in_axes(mxb), 0)))
    first_contact, first_com, d_last = jax.block_until_ready(fn(mxb, jnp.asarray(qpos0, jnp.float32)))
    return m, ids, mxb, qpos0, first_contact, first_com, d_last


@pytest.mark.slow
def test_batched_model_fields(batched_platform_run):
    m, ids, mxb = batched_platform_run[:3]
    hz = hmodel.PLATFORM_HALF_SIZE[2]
    np.testing.assert_allclose(mxb.geom_pos[:, ids.platform_geom, 2], HEIGHTS - hz, atol=1e-6)
    np.testing.assert_allclose(mxb.geom_size[ids.platform_geom], hmodel.PLATFORM_HALF_SIZE, atol=1e-6)
    np.testing.assert_allclose(mxb.body_mass[:, ids.payload_body], PAYLOAD, atol=1e-6)
    axes = hmodel.model_in_axes(mxb)
    assert axes.geom_pos == 0 and axes.body_mass == 0 and axes.geom_size is None


def _foot_contacts(c, ids, b, foot, terrain_geom):
    g1, g2 = np.asarray(c.geom1)[b], np.asarray(c.geom2)[b]
    return np.flatnonzero(((g1 == terrain_geom) & (g2 == foot)) | ((g2 == terrain_geom) & (g1 == foot)))


@pytest.mark.slow
def test_platform_contact_height_per_instance(batched_platform_run):
    m, ids, _, _, c, _, d_last = batched_platform_run
    dist, pos = np.asarray(c.dist), np.asarray(c.pos)
    for b, h in enumerate(HEIGHTS):
        for foot in ids.foot_geoms:
            on_platform = _foot_contacts(c, ids, b, foot, ids.platform_geom)
            on_floor = _foot_contacts(c, ids, b, foot, ids.floor_geom)
            assert len(on_platform) == 1 and len(on_floor) == 1
            # The foot touches the platform top at z = h (0.5 mm into it) ...
            k = on_platform[0]
            assert dist[b, k] == pytest.approx(-5e-4, abs=1e-4), (h, dist[b, k])
            assert pos[b, k, 2] == pytest.approx(h, abs=5e-4), (h, pos[b, k])
            # ... and is h above the floor (the floor plane's contact reports its distance).
            assert dist[b, on_floor[0]] == pytest.approx(h - 5e-4, abs=1e-4)
    # After 0.5 s of standing the feet rest on each instance's platform and the trunk is 0.5957 m above it.
    sites = np.asarray(d_last.site_xpos)[:, list(ids.foot_sites), 2]
    np.testing.assert_allclose(sites, np.broadcast_to(HEIGHTS[:, None] + robot.FOOT_RADIUS, sites.shape), atol=1.5e-3)
    np.testing.assert_allclose(np.asarray(d_last.qpos)[:, 2], HEIGHTS + robot.STANDING_BASE_Z, atol=0.01)
    assert np.all(np.isfinite(np.asarray(d_last.qpos)))
    c_last = d_last._impl.contact
    for b in range(len(HEIGHTS)):
        k = _foot_contacts(c_last, ids, b, ids.foot_geoms[0], ids.platform_geom)[0]
        assert -2e-3 < float(c_last.dist[b, k]) < 0.0  # in contact, still with the platform


@pytest.mark.slow
def test_payload_shifts_mass_and_com(batched_platform_run):
    m, ids, mxb, qpos0, _, com_mjx, _ = batched_platform_run
    com_mjx = np.asarray(com_mjx)
    # Total mass per instance.
    np.testing.assert_allclose(np.asarray(mxb.body_mass).sum(1), robot.TOTAL_MASS + np.asarray(PAYLOAD), atol=1e-4)
    # Whole-robot CoM from MJX (subtree of the trunk) against the bare robot's from C MuJoCo plus the payload.
    for b in range(len(HEIGHTS)):
        d = mujoco.MjData(m)
        d.qpos[:] = qpos0[b]
        mujoco.mj_forward(m, d)
        c0 = d.subtree_com[ids.trunk_body]
        p = d.xpos[ids.trunk_body] + d.xmat[ids.trunk_body].reshape(3, 3) @ PAYLOAD_COM[b]
        expect = (robot.TOTAL_MASS * c0 + PAYLOAD[b] * p) / (robot.TOTAL_MASS + PAYLOAD[b])
        np.testing.assert_allclose(com_mjx[b], expect, atol=2e-5)
    shift = com_mjx[2] - com_mjx[1] - (HEIGHTS[2] - HEIGHTS[1]) * np.array([0, 0, 1])
    assert shift[0] > 0.01 and shift[1] < -0.005  # toward the payload's (+x, -y)
    # Its inertia is that of a solid 0.3 x 0.2 x 0.1 m box.
    box = np.array([0.2**2 + 0.1**2, 0.3**2 + 0.1**2, 0.3**2 + 0.2**2]) / 12.0
    np.testing.assert_allclose(np.asarray(mxb.body_inertia)[2, ids.payload_body], PAYLOAD[2] * box, rtol=1e-5)


@pytest.mark.slow
def test_friction_is_per_instance(hyq):
    m, ids = hyq
    mx = mjx.put_model(m)
    mxb = hmodel.batch_model(mx, ids, hmodel.InstanceTerrain.make([0.0, 0.1], friction=[0.3, 1.2]))
    fr = np.asarray(mxb.geom_friction)
    np.testing.assert_allclose(fr[:, ids.floor_geom, 0], [0.3, 1.2], atol=1e-6)
    np.testing.assert_allclose(fr[:, ids.platform_geom, 0], [0.3, 1.2], atol=1e-6)
    np.testing.assert_allclose(fr[:, ids.foot_geoms[0], 0], 0.8, atol=1e-6)  # the robot's own unchanged


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(platform_height=-0.01), "platform_height"),
        (dict(platform_height=hmodel.MAX_PLATFORM_HEIGHT + 0.01), "platform_height"),
        (dict(platform_height=np.nan), "platform_height"),
        (dict(platform_height=0.1, friction=0.0), "friction"),
        (dict(platform_height=0.1, friction=-1.0), "friction"),
        (dict(platform_height=0.1, friction=np.inf), "friction"),
        (dict(platform_height=0.1, payload_mass=-1.0), "payload_mass"),
        (dict(platform_height=0.1, payload_mass=101.0), "payload_mass"),
        (dict(platform_height=0.1, payload_com=(0.0, 0.0, 0.6)), "payload_com"),
        (dict(platform_height=0.1, block_heights=[0.2], n_blocks=1), "block_heights"),
    ],
)
def test_instance_terrain_rejects_bad_values(kwargs, name):
    with pytest.raises(ValueError, match=name):
        hmodel.InstanceTerrain.make(**kwargs)


def test_instance_terrain_broadcasts():
    t = hmodel.InstanceTerrain.make([0.0, 0.1, 0.2], friction=0.5, payload_mass=3.0, payload_com=(0.1, 0, 0))
    assert t.batch_size == 3
    assert t.friction.shape == (3,) and t.payload_com.shape == (3, 3) and t.block_heights.shape == (3, 0)


def test_load_model_rejects_bad_settings():
    with pytest.raises(ValueError, match="timestep"):
        hmodel.load_model(timestep=0.0)
    with pytest.raises(ValueError, match="iterations"):
        hmodel.load_model(iterations=0)
    m = hmodel.load_model(timestep=0.001, iterations=2, ls_iterations=4)
    assert (m.opt.timestep, m.opt.iterations, m.opt.ls_iterations) == (0.001, 2, 4)
    dflt = hmodel.load_model()
    assert (dflt.opt.timestep, dflt.opt.iterations, dflt.opt.ls_iterations) == (0.002, 4, 8)


# ---------------------------------------------------------------- contacts through sensors (hyqjax.sim.contacts)

SENSOR_FORCE_TOL = 0.1  # N, on forces of 10-1500 N (float32 MJX, 4 Newton iterations, against float64 C)
CLEARANCE_TOL = 1e-5  # m


def _on_platform(height):
    return hmodel.model_spec(platform_height=height).compile()


def _contact_states(m):
    """C MuJoCo states with terrain contacts of every kind, as ``(model, qpos, qvel)``.

    Standing on the floor (four feet), and HyQ standing with its front feet 5 cm past the edge of a 16 cm
    platform under soft joint PD: it tips forward off the edge, its front feet fall to the floor past the
    edge, and its shins and feet touch the platform's edge.
    """
    states = []
    d = mujoco.MjData(m)
    d.qpos[:] = hmodel.standing_qpos(m, base_xy=(1.0, 0.0))
    states.append((m, d.qpos.copy(), d.qvel.copy()))
    mc = _on_platform(0.16)
    d = mujoco.MjData(mc)
    d.qpos[:] = hmodel.standing_qpos(mc, base_xy=(-float(robot.B_P_HIP[0, 0]) + 0.05, 0.0), ground_height=0.16)
    q0 = d.qpos[7:].copy()
    for k in range(600):
        d.ctrl[:] = np.clip(300.0 * (q0 - d.qpos[7:]) - 10.0 * d.qvel[6:], -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
        mujoco.mj_step(mc, d)
        if k % 100 == 99:
            states.append((mc, d.qpos.copy(), d.qvel.copy()))
    # Standing on the floor with the hind feet pressed against the platform's face: feet on two geoms at once.
    d = mujoco.MjData(mc)
    d.qpos[:] = hmodel.standing_qpos(mc, base_xy=(0.0, 0.0))
    mujoco.mj_kinematics(mc, d)
    hind_x = d.site_xpos[list(ids_of(mc).foot_sites[2:]), 0].max()
    d.qpos[0] += mc.geom_size[ids_of(mc).foot_geoms[2], 0] - 0.003 - hind_x
    for k in range(300):
        d.ctrl[:] = np.clip(3000.0 * (q0 - d.qpos[7:]) - 30.0 * d.qvel[6:], -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
        mujoco.mj_step(mc, d)
        if k % 100 == 99:
            states.append((mc, d.qpos.copy(), d.qvel.copy()))
    return states


def ids_of(m):
    return hmodel.model_ids(m)


def _c_forward(mc, qpos, qvel):
    d = mujoco.MjData(mc)
    d.qpos[:], d.qvel[:] = qpos, qvel
    mujoco.mj_forward(mc, d)
    return d


def _old_max_normal(mc, d, geom) -> float:
    """The previous reader's quantity: the largest normal force over the contacts of ``geom`` (0 if none)."""
    f6, out = np.zeros(6), 0.0
    for i in range(d.ncon):
        c = d.contact[i]
        if geom in (c.geom1, c.geom2) and c.efc_address >= 0:
            mujoco.mj_contactForce(mc, d, i, f6)
            out = max(out, f6[0])
    return out


@pytest.mark.slow
def test_foot_clearance_is_the_geometric_distance_to_the_terrain(hyq):
    from hyqjax.sim import contacts

    m, ids = hyq
    ci = ids.contacts
    n_close = 0
    for mc, qpos, qvel in _contact_states(m):
        d = _c_forward(mc, qpos, qvel)
        got = np.asarray(contacts.foot_clearance(ci, mjx.put_data(mc, d)))
        fromto = np.zeros(6)
        want = [min(mujoco.mj_geomDistance(mc, d, f, g, 1.0, fromto) for g in ci.terrain_geoms) for f in ci.foot_geoms]
        np.testing.assert_allclose(got, want, atol=CLEARANCE_TOL)
        n_close += int(np.sum(np.abs(want) < 0.005))
    assert n_close >= 8  # the 5 mm foothold test is exercised on feet touching the terrain


@pytest.mark.slow
def test_contact_sensors_match_mujoco_c_and_the_previous_reader(hyq):
    """Shin, trunk and foot sensors in MJX (float32) against C MuJoCo's sensors and contact forces (float64)
    on a standing state and the states of a collapse over the platform edge."""
    from hyqjax.sim import contacts

    m, ids = hyq
    ci = ids.contacts
    # mjx.step computes the sensors and contacts at the state it starts from (its forward pass, before it
    # integrates): the program of test_one_mjx_step_matches_mujoco_c below, compiled once for both tests.
    step = jax.jit(mjx.step)
    seen_shin = seen_two = 0
    for mc, qpos, qvel in _contact_states(m):
        dc = _c_forward(mc, qpos, qvel)
        d = mujoco.MjData(mc)
        d.qpos[:], d.qvel[:] = qpos, qvel
        dx = step(mjx.put_model(mc), mjx.put_data(mc, d))  # data placed as the golden test places it
        for read, adr in ((contacts.shin_forces, ci.shin_adr), (contacts.foot_forces, ci.foot_adr)):
            np.testing.assert_allclose(np.asarray(read(ci, dx)), dc.sensordata[np.asarray(adr) + 1],
                                       atol=SENSOR_FORCE_TOL)
        np.testing.assert_array_equal(np.asarray(contacts.shin_in_contact(ci, dx)), dc.sensordata[np.asarray(ci.shin_adr)] > 0)
        np.testing.assert_array_equal(np.asarray(contacts.foot_in_contact(ci, dx)), dc.sensordata[np.asarray(ci.foot_adr)] > 0)
        assert float(contacts.trunk_force(ci, dx)) == pytest.approx(dc.sensordata[ci.trunk_adr + 1], abs=SENSOR_FORCE_TOL)
        # Against the previous reader (the largest normal force over the geom's contacts): equal whenever a
        # geom has one contact; with two (a foot on the floor and the edge) the sensor reports the contact
        # of larger force magnitude, which is also the larger normal force in these states.
        for geoms, read in ((ids.shin_geoms, contacts.shin_forces), (ids.foot_geoms, contacts.foot_forces)):
            old = np.array([_old_max_normal(mc, dc, g) for g in geoms])
            np.testing.assert_allclose(np.asarray(read(ci, dx)), old, atol=SENSOR_FORCE_TOL)
        seen_shin += int(np.any(dc.sensordata[np.asarray(ci.shin_adr) + 1] > 1.0))
        seen_two += int(np.any(dc.sensordata[np.asarray(ci.foot_adr)] >= 2))
    assert seen_shin >= 1 and seen_two >= 1, (seen_shin, seen_two)
    assert contacts.overflow(dx).dtype == bool and not bool(contacts.overflow(dx))


@pytest.mark.slow
def test_one_mjx_step_matches_mujoco_c(hyq):
    """Golden test: one 2 ms step of MJX (float32) from a settled standing state equals C MuJoCo's (float64)."""
    m, ids = hyq
    d = mujoco.MjData(m)
    d.qpos[:] = hmodel.standing_qpos(m, base_xy=(1.0, 0.0))
    q0 = d.qpos[7:].copy()
    for _ in range(250):  # settle under joint PD so the feet carry the weight
        d.ctrl[:] = np.clip(3000.0 * (q0 - d.qpos[7:]) - 30.0 * d.qvel[6:], -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
        mujoco.mj_step(m, d)
    dx = jax.jit(mjx.step)(mjx.put_model(m), mjx.put_data(m, d))  # same state, controls and solver warm start
    mujoco.mj_step(m, d)
    assert d.ncon >= 4
    np.testing.assert_allclose(np.asarray(dx.qpos), d.qpos, atol=2e-6)
    np.testing.assert_allclose(np.asarray(dx.qvel), d.qvel, atol=2e-3)
