"""Contacts from distance (hyqjax.sim.contacts_from_distance): a backward-only virtual spring under each foot.

The forward value of a step is MJX's exactly; its derivative gains exactly the derivative of the virtual spring's
velocity change, whose sign pushes a foot away from the ground it approaches; nothing changes with the spring off
or with the feet far from the ground; the spring's direction is the terrain's outward normal (the floor's up, the
platform's side face beside it).
"""
from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hyqjax.sim import contacts
from hyqjax.sim import contacts_from_distance as cfdm
from hyqjax.sim import model as hmodel


def test_settings_are_checked_and_off_is_the_identity():
    for kw, name in ((dict(stiffness=-1.0), "stiffness"), (dict(reach=0.5), "reach"), (dict(softness=0.0), "softness")):
        with pytest.raises(ValueError, match=name):
            cfdm.ContactsFromDistance(**kw)
    d = object()
    assert cfdm.apply(cfdm.ContactsFromDistance(), None, None, (), d, 0.002) is d


def test_virtual_force_follows_the_terrain_normal_and_fades_with_clearance():
    """Synthetic kinematics: the floor at z = 0 and the platform box of the model raised to a 24 cm step; feet above
    the floor (force up, larger when closer), one beside the platform's front face (force horizontal, away from the
    face), one touching (no force: the real contact acts)."""
    m = hmodel.load_model()
    ci = contacts.contact_ids(m)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    plat = ci.terrain_geoms[1]
    px, hx = float(d.geom_xpos[plat][0]), ci.box_half_size[0][0]
    r = ci.foot_radius[0]
    xpos = np.array(d.geom_xpos, np.float64)
    hz = ci.box_half_size[0][2]
    far_x = px + hx + 0.5  # past the platform's front face: over the floor
    feet = np.array([[far_x, 0.0, r + 0.005],            # 5 mm above the floor
                     [far_x, 0.3, r + 0.015],            # 15 mm above the floor
                     [px + hx + r + 0.01, 0.0, 0.12],    # 1 cm before the platform's front face, halfway up
                     [far_x, -0.3, r - 0.002]])          # touching the floor
    xpos[np.asarray(ci.foot_geoms)] = feet
    xpos[ci.terrain_geoms[0]] = 0.0
    xpos[plat] = [px, 0.0, 0.24 - hz]  # the platform's top at 24 cm
    cfd = cfdm.ContactsFromDistance(stiffness=1000.0, reach=0.02, softness=0.005)
    with jax.enable_x64(True):
        view = types.SimpleNamespace(geom_xpos=jnp.asarray(xpos),
                                     geom_xmat=jnp.asarray(np.array(d.geom_xmat).reshape(-1, 3, 3)))
        f, c = cfdm.virtual_forces(cfd, ci, view)
    f, c = np.asarray(f), np.asarray(c)
    np.testing.assert_allclose(c[:3], [0.005, 0.015, 0.01], atol=1e-9)
    assert f[0, 2] > f[1, 2] > 0 and np.allclose(f[:2, :2], 0.0, atol=1e-9)
    s = cfd.softness
    np.testing.assert_allclose(f[0, 2], cfd.stiffness * s * np.log1p(np.exp((cfd.reach - c[0]) / s)), rtol=1e-9)
    assert f[2, 0] > 0 and abs(f[2, 2]) < 1e-9 * abs(f[2, 0])  # pushed along +x, away from the front face
    np.testing.assert_allclose(f[3], 0.0)


@pytest.mark.slow
def test_one_step_value_unchanged_derivative_gains_the_spring():
    """HyQ with straight legs 1 cm and 20 cm above the floor, one ``mjx.step`` in float64: the next velocity is
    bitwise MJX's; its derivative along the trunk height gains exactly the derivative of the spring's velocity
    change (negative: lower means a stronger push up), and nothing measurable 20 cm up."""
    from mujoco import mjx

    m = hmodel.load_model()
    ci = hmodel.model_ids(m).contacts
    bodies = cfdm.foot_bodies(m, ci)
    dt = float(m.opt.timestep)
    cfd = cfdm.ContactsFromDistance(stiffness=5000.0, reach=0.02, softness=0.005)
    dc = mujoco.MjData(m)
    mujoco.mj_forward(m, dc)  # C MuJoCo: how far the straight legs reach below qpos0's trunk (no MJX compile)
    view = types.SimpleNamespace(geom_xpos=np.asarray(dc.geom_xpos),
                                 geom_xmat=np.asarray(dc.geom_xmat).reshape(-1, 3, 3))
    straight = float(-np.min(np.asarray(contacts.foot_clearance(ci, view))))
    with jax.enable_x64(True):
        mx = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64) if hasattr(x, "dtype") and
                                    jnp.issubdtype(x.dtype, jnp.floating) else x, mjx.put_model(m))
        d0 = mjx.make_data(mx)

        @jax.jit
        def run(q):
            d = d0.replace(qpos=q)

            def hard_and_soft(q):
                # MJX's step, traced once: its next velocity (hard) and the same step with the spring applied
                # (soft); the two share the step, so what differs between them is ``cfdm.apply`` alone.
                stepped = mjx.step(mx, d.replace(qpos=q))
                return stepped.qvel, cfdm.apply(cfd, mx, ci, bodies, stepped, dt).qvel

            dv = lambda q: cfdm.velocity_change(cfd, mx, ci, bodies, mjx.forward(mx, d.replace(qpos=q)), dt)  # noqa: E731
            e = jnp.zeros_like(q).at[2].set(1.0)
            (vh, vs), (th, ts) = jax.jvp(hard_and_soft, (q,), (e,))
            return (vh, th), (vs, ts), jax.jvp(dv, (q,), (e,))[1]

        q0 = jnp.asarray(m.qpos0, jnp.float64)
        # One program for both heights, compiled at XLA's backend optimisation level 0 (it runs two steps; the
        # compile is the test's cost).
        step = run.lower(q0).compile(compiler_options={"xla_backend_optimization_level": 0})
        for lift, near in ((0.01, True), (0.2, False)):
            (vh, th), (vs, ts), tdv = step(q0.at[2].add(straight + lift))
            assert bool(jnp.all(vh == vs))
            np.testing.assert_allclose(np.asarray(ts - th), np.asarray(tdv), rtol=1e-9, atol=1e-12)
            if near:
                assert float(ts[2] - th[2]) < -0.1  # d(v_z)/dz: a spring pushing the trunk up, weaker higher
            else:
                assert abs(float(ts[2] - th[2])) < 1e-9
