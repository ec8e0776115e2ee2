"""HyQ + terrain as a MuJoCo / MJX model, and per-instance batching of that model.

:func:`load_model` builds the :class:`mujoco.MjModel` of HyQ (``assets/hyq.xml``) standing on a
terrain: a ground plane at ``z = 0`` and a step-down platform (a box whose top is at height
``h`` and whose front edge is at ``x = 0``; the robot walks along ``+x`` and steps off it).
Optional rough-terrain blocks are laid on both levels.

The platform height, ground friction, payload and block heights are per-instance: they are
fields of the ``mjx.Model`` (``geom_pos``, ``geom_size``, ``geom_friction``, ``body_mass``,
``body_ipos``) which :func:`batch_model` stacks along a leading batch axis, so one compiled
rollout covers many heights without recompiling. :func:`model_in_axes` gives the matching
``vmap`` axes.

Collision filtering (see the MJCF header): robot geoms ``contype=2, conaffinity=1``, terrain
geoms ``contype=1, conaffinity=2``: the robot collides with the terrain only.
"""
from __future__ import annotations

import dataclasses
import functools
import importlib.resources
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot
from hyqjax.sim import contacts

if TYPE_CHECKING:  # MuJoCo and MJX are imported where used: importing this module (e.g. for a sweep's ranges)
    import mujoco  # loads neither
    from mujoco import mjx

#: Half sizes (m) of the platform box. Its top is at ``h`` and its bottom at ``h - 2 * 0.25``.
PLATFORM_HALF_SIZE = (2.0, 2.0, 0.25)
#: Allowed platform heights (m): the box must reach the ground (``h <= 0.5``); HyQ's legs bound it
#: well below that.
MAX_PLATFORM_HEIGHT = 0.45
#: Default rough-terrain block layout: a grid of boxes on the platform and on the ground.
BLOCK_HALF_XY = 0.1
BLOCK_HALF_Z = 0.05


@dataclasses.dataclass(frozen=True)
class TerrainLayout:
    """Static terrain structure (changing it recompiles; per-instance values do not).

    Attributes:
      n_blocks_x, n_blocks_y: rough-terrain block grid per level (0 disables blocks).
      block_x_range: x extent (m) covered by blocks on each level, ``((x0, x1) platform, (x0, x1) ground)``.
    """

    n_blocks_x: int = 0
    n_blocks_y: int = 0
    block_x_range: tuple[tuple[float, float], tuple[float, float]] = ((-1.2, -0.1), (0.1, 1.2))

    @property
    def n_blocks(self) -> int:
        return 2 * self.n_blocks_x * self.n_blocks_y


@dataclasses.dataclass(frozen=True)
class ModelIds:
    """Ids looked up by name once, kept as named constants."""

    trunk_body: int
    payload_body: int
    floor_geom: int
    platform_geom: int
    foot_geoms: tuple[int, ...]
    shin_geoms: tuple[int, ...]
    trunk_geom: int
    foot_sites: tuple[int, ...]
    block_geoms: tuple[int, ...]
    qpos_joints: tuple[int, ...]  # qpos addresses of the 12 leg joints
    dof_joints: tuple[int, ...]  # dof addresses of the 12 leg joints
    contacts: contacts.ContactIds  # contact sensors and terrain geometry (hyqjax.sim.contacts)


def asset_path(name: str = "hyq.xml") -> str:
    return str(importlib.resources.files("hyqjax") / "assets" / name)


def model_spec(layout: TerrainLayout = TerrainLayout(), platform_height: float = 0.0) -> mujoco.MjSpec:
    """The :class:`mujoco.MjSpec` of HyQ on the terrain, with contact sensors (:func:`hyqjax.sim.contacts.add_sensors`).

    ``platform_height`` is compiled into the model (for C MuJoCo, whose collision bounding volumes of the
    static terrain are computed at compile time); MJX batches set it per instance (:func:`batch_model`).
    """
    if not 0.0 <= platform_height <= MAX_PLATFORM_HEIGHT:
        raise ValueError(f"platform_height must be in [0, {MAX_PLATFORM_HEIGHT}] m, got {platform_height}")
    import mujoco

    spec = mujoco.MjSpec.from_file(asset_path())
    spec.stat.extent = 3.0
    tex = spec.add_texture(name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D,
                           builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, width=256, height=256,
                           rgb1=[0.82, 0.84, 0.86], rgb2=[0.7, 0.72, 0.75])
    del tex
    mat = spec.add_material(name="grid", texrepeat=[8, 8], reflectance=0.1)
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     width=64, height=64, rgb1=[0.55, 0.7, 0.9], rgb2=[0.1, 0.15, 0.25])
    world = spec.worldbody
    world.add_light(pos=[0, 0, 4], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8], castshadow=True)
    terrain = dict(contype=1, conaffinity=2, condim=3, friction=[0.8, 0.02, 0.01])
    world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], material="grid", **terrain)
    hx, hy, hz = PLATFORM_HALF_SIZE
    world.add_geom(name="platform", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz], pos=[-hx, 0, platform_height - hz],
                   rgba=[0.55, 0.42, 0.3, 1], **terrain)
    for level, (x0, x1) in enumerate(layout.block_x_range):
        for i in range(layout.n_blocks_x):
            for j in range(layout.n_blocks_y):
                x = x0 + (i + 0.5) * (x1 - x0) / max(layout.n_blocks_x, 1)
                y = -0.6 + (j + 0.5) * 1.2 / max(layout.n_blocks_y, 1)
                world.add_geom(name=f"block_{level}_{i}_{j}", type=mujoco.mjtGeom.mjGEOM_BOX,
                               size=[BLOCK_HALF_XY, BLOCK_HALF_XY, BLOCK_HALF_Z], pos=[x, y, -1.0],
                               rgba=[0.45, 0.45, 0.4, 1], **terrain)
    trunk = spec.body("trunk")
    payload = trunk.add_body(name="payload", pos=[0, 0, 0.1])
    payload.mass = 0.0
    payload.inertia = [0.0, 0.0, 0.0]
    payload.explicitinertial = True
    contacts.add_sensors(spec)
    return spec


@functools.lru_cache(maxsize=8)
def load_model(layout: TerrainLayout = TerrainLayout(), timestep: float = 0.002, iterations: int = 4,
               ls_iterations: int = 8) -> mujoco.MjModel:
    """Compile HyQ on the step-down terrain.

    Args:
      layout: static terrain structure.
      timestep: physics step (s); must be in (0, 0.01].
      iterations, ls_iterations: MuJoCo's Newton solver iterations and line-search iterations
        (defaults chosen in docs/architecture.md, "MJX settings": HyQ stands and walks with them in float32).
    """
    if not 0.0 < timestep <= 0.01:
        raise ValueError(f"timestep must be in (0, 0.01] s, got {timestep}")
    if iterations < 1 or ls_iterations < 1:
        raise ValueError(f"iterations and ls_iterations must be >= 1, got {iterations}, {ls_iterations}")
    spec = model_spec(layout)
    spec.option.timestep = timestep
    spec.option.iterations = iterations
    spec.option.ls_iterations = ls_iterations
    return spec.compile()


def model_ids(m: mujoco.MjModel) -> ModelIds:
    import mujoco

    def gid(n):
        return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)

    jnt = [m.joint(f"{leg}_{j}") for leg in robot.LEG_NAMES for j in robot.JOINT_NAMES]
    blocks = tuple(i for i in range(m.ngeom) if (m.geom(i).name or "").startswith("block_"))
    return ModelIds(
        trunk_body=m.body("trunk").id,
        payload_body=m.body("payload").id,
        floor_geom=gid("floor"),
        platform_geom=gid("platform"),
        foot_geoms=tuple(gid(f"{leg}_foot") for leg in robot.LEG_NAMES),
        shin_geoms=tuple(gid(f"{leg}_shin") for leg in robot.LEG_NAMES),
        trunk_geom=gid("trunk"),
        foot_sites=tuple(m.site(f"{leg}_foot").id for leg in robot.LEG_NAMES),
        block_geoms=blocks,
        qpos_joints=tuple(int(m.jnt_qposadr[j.id]) for j in jnt),
        dof_joints=tuple(int(m.jnt_dofadr[j.id]) for j in jnt),
        contacts=contacts.contact_ids(m),
    )


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class InstanceTerrain:
    """Per-instance physical parameters that live in the ``mjx.Model``; every field has a leading batch axis.

    Attributes:
      platform_height: (B,) step height h (m), in [0, MAX_PLATFORM_HEIGHT].
      friction: (B,) sliding friction coefficient of the terrain, > 0.
      payload_mass: (B,) extra mass rigidly attached to the trunk (kg), >= 0.
      payload_com: (B, 3) its centre of mass in the trunk frame (m).
      block_heights: (B, n_blocks) rough-terrain block heights above their level (m), >= 0.
    """

    platform_height: jax.Array
    friction: jax.Array
    payload_mass: jax.Array
    payload_com: jax.Array
    block_heights: jax.Array

    @staticmethod
    def make(platform_height, friction=0.8, payload_mass=0.0, payload_com=(0.0, 0.0, 0.0), block_heights=None,
             n_blocks: int = 0) -> "InstanceTerrain":
        """Broadcast and validate per-instance terrain parameters (before any compile)."""
        h = np.atleast_1d(np.asarray(platform_height, np.float64))
        b = h.shape[0]
        mu = np.broadcast_to(np.asarray(friction, np.float64), (b,)).copy()
        pm = np.broadcast_to(np.asarray(payload_mass, np.float64), (b,)).copy()
        pc = np.broadcast_to(np.asarray(payload_com, np.float64), (b, 3)).copy()
        bh = np.zeros((b, n_blocks)) if block_heights is None else np.broadcast_to(
            np.asarray(block_heights, np.float64), (b, n_blocks)).copy()
        if h.ndim != 1 or np.any(~np.isfinite(h)) or np.any(h < 0) or np.any(h > MAX_PLATFORM_HEIGHT):
            raise ValueError(f"platform_height must be finite and in [0, {MAX_PLATFORM_HEIGHT}] m, got {h}")
        if np.any(~np.isfinite(mu)) or np.any(mu <= 0) or np.any(mu > 5):
            raise ValueError(f"friction must be in (0, 5], got {mu}")
        if np.any(~np.isfinite(pm)) or np.any(pm < 0) or np.any(pm > 100):
            raise ValueError(f"payload_mass must be in [0, 100] kg, got {pm}")
        if np.any(~np.isfinite(pc)) or np.any(np.abs(pc) > 0.5):
            raise ValueError("payload_com must be finite with |component| <= 0.5 m")
        if np.any(~np.isfinite(bh)) or np.any(bh < 0) or np.any(bh > 2 * BLOCK_HALF_Z):
            raise ValueError(f"block_heights must be in [0, {2 * BLOCK_HALF_Z}] m")
        return InstanceTerrain(jnp.asarray(h), jnp.asarray(mu), jnp.asarray(pm), jnp.asarray(pc), jnp.asarray(bh))

    @property
    def batch_size(self) -> int:
        return int(self.platform_height.shape[0])


_BATCHED_FIELDS = ("geom_pos", "geom_friction", "body_mass", "body_ipos", "body_inertia")


def batch_model(mx: mjx.Model, ids: ModelIds, terrain: InstanceTerrain) -> mjx.Model:
    """Stack per-instance terrain into the fields of ``mx`` listed in ``_BATCHED_FIELDS``
    (``vmap`` of :func:`instance_model`'s field values; :func:`model_in_axes` gives the matching axes).
    """
    fields = jax.vmap(lambda t: _instance_fields(mx, ids, t))(terrain)
    return mx.tree_replace(fields)


def instance_model(mx: mjx.Model, ids: ModelIds, terrain: InstanceTerrain) -> mjx.Model:
    """``mx`` with ONE instance's terrain (leaves of ``terrain`` without a batch axis); pure, differentiable.

    Block ``k`` sits on the level its x position is on: its top is at that level's height plus
    ``block_heights[k]`` (a block of height 0 is flush with the level and inert).
    """
    return mx.tree_replace(_instance_fields(mx, ids, terrain))


def _instance_fields(mx: mjx.Model, ids: ModelIds, t: InstanceTerrain) -> dict:
    gpos = mx.geom_pos
    hz = PLATFORM_HALF_SIZE[2]
    gpos = gpos.at[ids.platform_geom, 2].set(t.platform_height - hz)
    for k, g in enumerate(ids.block_geoms):
        on_platform = mx.geom_pos[g, 0] < 0.0
        level = jnp.where(on_platform, t.platform_height, 0.0)
        gpos = gpos.at[g, 2].set(level + t.block_heights[k] - BLOCK_HALF_Z)
    fr = mx.geom_friction
    terrain_geoms = [ids.floor_geom, ids.platform_geom, *ids.block_geoms]
    fr = fr.at[jnp.asarray(terrain_geoms), 0].set(t.friction)
    mass = mx.body_mass.at[ids.payload_body].set(t.payload_mass)
    ipos = mx.body_ipos.at[ids.payload_body].set(t.payload_com - jnp.array([0.0, 0.0, 0.1]))
    # A payload is a solid box of 0.3 x 0.2 x 0.1 m.
    box = jnp.array([0.2**2 + 0.1**2, 0.3**2 + 0.1**2, 0.3**2 + 0.2**2]) / 12.0
    inertia = mx.body_inertia.at[ids.payload_body].set(t.payload_mass * box)
    return dict(geom_pos=gpos, geom_friction=fr, body_mass=mass, body_ipos=ipos, body_inertia=inertia)


def map_batched_fields(mb: mjx.Model, fn) -> mjx.Model:
    """``mb`` (made by :func:`batch_model`) with its per-instance fields replaced by ``fn({name: array})`` (one
    call for all of them: ``fn`` may be one jitted program); the fields every instance shares are kept."""
    return mb.tree_replace(fn({f: getattr(mb, f) for f in _BATCHED_FIELDS}))


def model_in_axes(mx: mjx.Model) -> mjx.Model:
    """``vmap`` in_axes for a model made by :func:`batch_model`: 0 on batched fields, None elsewhere."""
    axes = jax.tree_util.tree_map(lambda _: None, mx)
    return axes.tree_replace({f: 0 for f in _BATCHED_FIELDS})


def standing_qpos(m: mujoco.MjModel, base_xy=(0.0, 0.0), ground_height: float = 0.0) -> np.ndarray:
    """The SRDF ``standing`` keyframe with the trunk at ``base_xy`` above ground at ``ground_height``."""
    q = m.key("standing").qpos.copy()
    q[robot.QPOS_BASE_POS] = (*base_xy, robot.STANDING_BASE_Z + ground_height)
    return q
