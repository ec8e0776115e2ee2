"""Contacts between HyQ and the terrain, read the same way under every MJX implementation (``jax``, ``warp``).

The model carries one MuJoCo *contact sensor* per zone (:func:`add_sensors`, called by
:func:`hyqjax.sim.model.load_model`): each foot, each shin and the trunk, as
``<contact geom1="ZONE" data="found force" reduce="maxforce" num="1"/>``. Its four values are

* ``found``: the number of contacts of that geom with penetration ``dist < 0`` (the robot collides with
  the terrain only, so every contact of the geom is a terrain contact);
* the force of the contact with the largest force magnitude, in that contact's frame: slot 1 is its
  **normal** force ``f_n >= 0`` (N). For MuJoCo's pyramidal friction cone ``f_n`` is the sum of the
  cone's edge forces. The two tangential slots depend on the contact frame's tangent convention, which
  differs between implementations, and are never read.

This module is the only reader of contacts in hyqjax; nothing else touches MJX's backend internals
(``Data._impl``), which differ between implementations (static per-instance contact slots under ``jax``,
one buffer shared by all worlds under ``warp``). The only internal read left is the Warp contact-buffer
overflow flag (:func:`overflow`).

Foot clearance (:func:`foot_clearance`) is geometric: the signed distance from each foot sphere to the
terrain's plane and boxes (platform, blocks), ``min_g sd_g(p) - r`` with ``p`` the sphere centre, ``r`` its
radius, ``sd`` the exact signed distance to a plane (``n . (p - c)``) or a box (``|max(q, 0)| +
min(max_i q_i, 0)`` with ``q = |R^T (p - c)| - half``). It equals the distance MJX's sphere-plane and
sphere-box collision functions compute, without their contact slots.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot
from hyqjax.sim.impls import BUFFER_OVERFLOW_MASK

if TYPE_CHECKING:  # imported where used (a sweep's option checks load no MuJoCo)
    import mujoco

#: ``data="found force"`` (bits 0 and 1 of mjtConDataType), ``reduce="maxforce"``, ``num=1``.
_FOUND_FORCE, _MAXFORCE, _NUM = 3, 2, 1
#: Values per sensor: found, then the 3 force components in the contact frame (normal first).
SENSOR_DIM = 4
ZONES = tuple(f"{leg}_foot" for leg in robot.LEG_NAMES) + tuple(f"{leg}_shin" for leg in robot.LEG_NAMES) + ("trunk",)


def sensor_name(zone: str) -> str:
    return f"{zone}_contact"


def add_sensors(spec: mujoco.MjSpec) -> None:
    """Add the contact sensor of every zone in :data:`ZONES` (a geom of that name) to ``spec``."""
    import mujoco

    for zone in ZONES:
        spec.add_sensor(type=mujoco.mjtSensor.mjSENS_CONTACT, name=sensor_name(zone), objtype=mujoco.mjtObj.mjOBJ_GEOM,
                        objname=zone, intprm=[_FOUND_FORCE, _MAXFORCE, _NUM])


@dataclasses.dataclass(frozen=True)
class ContactIds:
    """Static addresses (into ``sensordata``) and geometry the readers need (hashable: part of static configs).

    Attributes:
      foot_adr, shin_adr: ``sensordata`` address of each leg's foot / shin sensor (LF, RF, LH, RH).
      trunk_adr: address of the trunk sensor.
      foot_geoms, terrain_geoms: geom ids of the feet and of the terrain (floor plane first, then boxes).
      foot_radius: radius of each foot sphere (m).
      box_half_size: half sizes of the terrain boxes (``terrain_geoms[1:]``), which no instance changes (m).
    """

    foot_adr: tuple[int, ...]
    shin_adr: tuple[int, ...]
    trunk_adr: int
    foot_geoms: tuple[int, ...]
    terrain_geoms: tuple[int, ...]
    foot_radius: tuple[float, ...]
    box_half_size: tuple[tuple[float, float, float], ...]


def contact_ids(m: mujoco.MjModel) -> ContactIds:
    """Look up the sensors of :func:`add_sensors` and the terrain geoms in a compiled model."""
    import mujoco

    def adr(zone):
        s = m.sensor(sensor_name(zone))
        if int(m.sensor_dim[s.id]) != SENSOR_DIM:
            raise ValueError(f"sensor {sensor_name(zone)} has dim {int(m.sensor_dim[s.id])}, expected {SENSOR_DIM}")
        return int(m.sensor_adr[s.id])

    def gid(name):
        return int(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name))

    blocks = tuple(i for i in range(m.ngeom) if (m.geom(i).name or "").startswith("block_"))
    feet = tuple(gid(f"{leg}_foot") for leg in robot.LEG_NAMES)
    boxes = (gid("platform"), *blocks)
    return ContactIds(
        foot_adr=tuple(adr(f"{leg}_foot") for leg in robot.LEG_NAMES),
        shin_adr=tuple(adr(f"{leg}_shin") for leg in robot.LEG_NAMES),
        trunk_adr=adr("trunk"),
        foot_geoms=feet,
        terrain_geoms=(gid("floor"), *boxes),
        foot_radius=tuple(float(m.geom_size[g, 0]) for g in feet),
        box_half_size=tuple(tuple(float(x) for x in m.geom_size[g]) for g in boxes),
    )


def _found(sensordata: jax.Array, adr) -> jax.Array:
    return sensordata[np.asarray(adr)]


def _normal(sensordata: jax.Array, adr) -> jax.Array:
    return sensordata[np.asarray(adr) + 1]


def foot_forces(ci: ContactIds, d) -> jax.Array:
    """(4,) normal force (N) of each foot's strongest terrain contact (0 without contact)."""
    return _normal(d.sensordata, ci.foot_adr)


def foot_in_contact(ci: ContactIds, d) -> jax.Array:
    """(4,) bool: the foot penetrates the terrain (a contact with ``dist < 0``)."""
    return _found(d.sensordata, ci.foot_adr) > 0


def shin_forces(ci: ContactIds, d) -> jax.Array:
    """(4,) normal force (N) of each shin's strongest terrain contact (0 without contact)."""
    return _normal(d.sensordata, ci.shin_adr)


def shin_in_contact(ci: ContactIds, d) -> jax.Array:
    """(4,) bool: the shin penetrates the terrain."""
    return _found(d.sensordata, ci.shin_adr) > 0


def trunk_force(ci: ContactIds, d) -> jax.Array:
    """Normal force (N) of the trunk's strongest terrain contact (0 without contact)."""
    return d.sensordata[ci.trunk_adr + 1]


def foot_clearance(ci: ContactIds, d) -> jax.Array:
    """(4,) signed distance (m) from each foot sphere to the nearest terrain geom (negative: penetration).

    Terrain geoms are the floor plane and boxes (platform, blocks), placed per instance (``d.geom_xpos``).
    """
    return clearance_of_points(ci, d.geom_xpos[np.asarray(ci.foot_geoms)], d)


def clearance_of_points(ci: ContactIds, feet: jax.Array, d) -> jax.Array:
    """(4,) :func:`foot_clearance` of foot spheres centred at ``feet`` (4, 3) instead of where ``d`` has them
    (differentiable in ``feet``: its gradient is each foot's outward terrain normal)."""
    terr = np.asarray(ci.terrain_geoms)
    c, rot = d.geom_xpos[terr], d.geom_xmat[terr]  # (G, 3), (G, 3, 3)
    local = jnp.einsum("gji,fgj->fgi", rot, feet[:, None, :] - c[None])  # R^T (p - c), (4, G, 3)
    plane = local[:, 0, 2]  # the floor: distance along its normal
    q = jnp.abs(local[:, 1:]) - jnp.asarray(ci.box_half_size, local.dtype)[None]
    s2 = jnp.sum(jnp.square(jnp.maximum(q, 0.0)), -1)
    outside = jnp.where(s2 > 0, jnp.sqrt(jnp.where(s2 > 0, s2, 1.0)), 0.0)  # finite derivative at 0
    box = outside + jnp.minimum(jnp.max(q, -1), 0.0)
    sd = jnp.minimum(plane, jnp.min(box, -1))
    return sd - jnp.asarray(ci.foot_radius, sd.dtype)


def overflow(d) -> jax.Array:
    """True where MJX's Warp implementation dropped contacts or constraints because a buffer (``naconmax``
    contacts, ``njmax`` rows, broad/narrow phase) was full: the buffer bits of mujoco_warp's overflow flags
    (:data:`hyqjax.sim.impls.BUFFER_OVERFLOW_MASK`; the solver's iteration-limit bits are not failures).
    Always False under the JAX implementation (static contact slots)."""
    impl = getattr(d, "_impl", None)
    flag = getattr(impl, "overflow", None)
    if flag is None:
        return jnp.array(False)
    return jnp.any((jnp.asarray(flag) & BUFFER_OVERFLOW_MASK) != 0)


def slot_geoms(d) -> np.ndarray:
    """``(ncon, 2)`` geom ids of MJX-JAX's static contact slots (the candidate pairs, one row per slot, in a
    fixed order), for code that needs a per-pair signed distance (:func:`slot_distances`). MJX-JAX only: MuJoCo
    Warp keeps no per-instance contact slots (its contacts are read through the sensors above)."""
    contact = getattr(getattr(d, "_impl", None), "contact", None)
    if contact is None or not hasattr(contact, "geom"):
        raise ValueError("contact slots exist only under impl='jax' (MuJoCo Warp shares one contact buffer)")
    return np.asarray(contact.geom)


def slot_distances(d) -> jax.Array:
    """``(ncon,)`` signed distance of every static contact slot (negative: penetration), MJX-JAX only; a smooth
    function of the state, which the tuner's clearance and foothold terms differentiate."""
    contact = getattr(getattr(d, "_impl", None), "contact", None)
    if contact is None or not hasattr(contact, "dist"):
        raise ValueError("contact slots exist only under impl='jax' (MuJoCo Warp shares one contact buffer)")
    return contact.dist
