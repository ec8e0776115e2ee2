"""What MJX's Warp backend (``mjx.put_model(m, impl="warp")``) does with hyqjax's HyQ model, section by section.

Sections (``--sections``; each one records its answer or the error it raised, then the next one runs):

  sensors     touch sensors on foot / shin / trunk zone sites, ``contact`` sensors (geom1 = a foot, shin or
              the trunk; found + force with reduce maxforce, found + force with reduce netforce, found + dist
              with reduce mindist) and a ``force`` sensor at a knee, added to a copy of the step-down
              model. States are taken from C MuJoCo (float64) runs of HyQ standing and of HyQ collapsing
              onto its shins and trunk; each state is put into MJX (impl jax and impl warp), ``mjx.forward``
              computes the sensors, and each sensor is compared with C MuJoCo's ``mj_forward`` value.
  overflow    the contact and constraint counters of Warp data (``nacon``, ``ncollision``, ``naconmax``,
              ``njmax``, ``nefc``, the per-world ``overflow`` bitmask) for a standing batch, and what a too
              small ``naconmax`` / ``njmax`` does to them and to the state.
  batched     ``jax.vmap(mjx.step)`` over a model batched per instance by ``hyqjax.sim.model.batch_model``
              (platform height, friction, payload): impl jax against impl warp over ``--steps`` steps,
              trunk height and qpos differences.
  rollout     what hyqjax's rollout needs from a Data beyond ``mjx.step``: ``mjx.mul_m``, ``qfrc_bias``,
              ``qacc``, a per-instance ``jnp.where`` merge (tree_map) against ``Data.where``, and
              ``hyqjax.sim.rollout.initial_data``'s broadcast of every field.
  sharding    ``jit(vmap(mjx.step))`` with ``in_shardings`` / ``out_shardings`` over a 1-D mesh of all local
              devices (force several host devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``).
  throughput  bare ``lax.scan`` of ``vmap(mjx.step)`` env-steps/s, impl jax against impl warp, per batch.

Usage (GPU or CPU; warp-lang must be importable)::

    PYTHONPATH=. python benchmarks/probe_warp.py --out out/probe_warp.json
    PYTHONPATH=. python benchmarks/probe_warp.py --sections throughput --batches 16384 65536 --steps 200
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402
from mujoco import mjx  # noqa: E402

from hyqjax.control import stand  # noqa: E402
from hyqjax.core import robot  # noqa: E402
from hyqjax.sim import model as hmodel  # noqa: E402
from hyqjax.sim import rollout as sim  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import mjx_impl  # noqa: E402

SECTIONS = ("sensors", "overflow", "batched", "rollout", "sharding", "throughput")
LEGS = robot.LEG_NAMES
OVERFLOW_BITS = mjx_impl.OVERFLOW_BITS


# ----------------------------------------------------------------------------------------------- models


SENSOR_GROUPS = ("touch", "contact_maxforce", "contact_netforce", "contact_mindist", "force")


def sensor_lines(group: str) -> list[str]:
    """MJCF ``<sensor>`` children of one probed group."""
    if group == "touch":
        return [f'<touch name="{leg}_{z}_touch" site="{leg}_{z}_zone"/>' for leg in LEGS for z in ("foot", "shin")] + [
            '<touch name="trunk_touch" site="trunk_zone"/>']
    if group == "contact_maxforce":
        geoms = [f"{leg}_{z}" for leg in LEGS for z in ("foot", "shin")] + ["trunk"]
        return [f'<contact name="{g}_maxforce" geom1="{g}" data="found force" reduce="maxforce" num="1"/>'
                for g in geoms]
    if group == "contact_netforce":
        return [f'<contact name="{leg}_foot_netforce" geom1="{leg}_foot" data="found force" reduce="netforce" '
                'num="1"/>' for leg in LEGS]
    if group == "contact_mindist":
        return [f'<contact name="{leg}_foot_mindist" geom1="{leg}_foot" data="found dist" reduce="mindist" num="1"/>'
                for leg in LEGS]
    if group == "force":
        return ['<force name="lf_knee_force" site="lf_foot_zone"/>']
    raise ValueError(f"sensor group must be one of {SENSOR_GROUPS}, got {group!r}")


def sensor_model(groups=SENSOR_GROUPS) -> mujoco.MjModel:
    """The step-down model (``load_model()``) with zone sites and the sensors of ``groups``.

    ``load_model()``'s spec is not public, so the copy is made from HyQ's asset with the same terrain (floor,
    platform with its top at 0, payload body) and checked against ``load_model()`` field by field.
    Zone sites: a 4 cm sphere around each foot, a 4 cm capsule along each shin, a 14 cm capsule along the trunk.
    """
    ref = hmodel.load_model()
    spec = mujoco.MjSpec.from_file(hmodel.asset_path())
    spec.stat.extent = 3.0
    terrain = dict(contype=1, conaffinity=2, condim=3, friction=[0.8, 0.02, 0.01])
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05], **terrain)
    hx, hy, hz = hmodel.PLATFORM_HALF_SIZE
    spec.worldbody.add_geom(name="platform", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, hz], pos=[-hx, 0, -hz],
                            **terrain)
    payload = spec.body("trunk").add_body(name="payload", pos=[0, 0, 0.1])
    payload.mass, payload.inertia, payload.explicitinertial = 0.0, [0.0, 0.0, 0.0], True
    spec.option.timestep = ref.opt.timestep
    spec.option.iterations = ref.opt.iterations
    spec.option.ls_iterations = ref.opt.ls_iterations
    cap = mujoco.mjtGeom.mjGEOM_CAPSULE
    for leg in LEGS:
        body = spec.body(f"{leg}_lowerleg")
        body.add_site(name=f"{leg}_foot_zone", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.04, 0, 0],
                      pos=[0, 0, -0.341])
        body.add_site(name=f"{leg}_shin_zone", type=cap, size=[0.04, 0.1364, 0], pos=[0, 0, -0.1364])
    s = 2 ** -0.5
    spec.body("trunk").add_site(name="trunk_zone", type=cap, size=[0.14, 0.35, 0], quat=[s, 0, s, 0])
    lines = [ln for g in groups for ln in sensor_lines(g)]
    xml = spec.to_xml().replace("</mujoco>", "<sensor>\n" + "\n".join(lines) + "\n</sensor>\n</mujoco>")
    m = mujoco.MjModel.from_xml_string(xml)
    for f in ("nq", "nv", "nu", "nbody", "ngeom"):
        assert getattr(m, f) == getattr(ref, f), f
    for f in ("body_mass", "geom_size", "geom_pos", "geom_friction", "actuator_gear", "jnt_range"):
        np.testing.assert_allclose(getattr(m, f), getattr(ref, f), atol=1e-5, err_msg=f)  # MJCF text keeps 6 digits
    return m


def sensor_slices(m: mujoco.MjModel) -> dict[str, slice]:
    return {m.sensor(i).name: slice(int(m.sensor_adr[i]), int(m.sensor_adr[i] + m.sensor_dim[i]))
            for i in range(m.nsensor)}


def c_states(m: mujoco.MjModel) -> list[tuple[str, mujoco.MjData]]:
    """C MuJoCo states: HyQ standing (holding torques) and HyQ collapsing (no torques) onto shins and trunk."""
    out = []
    tau = np.zeros(robot.N_JOINTS)
    for name, qpos, ctrl, steps in (
        ("standing", hmodel.standing_qpos(m), None, (50, 250)),
        ("collapse", hmodel.standing_qpos(m), tau, (150, 300, 450, 600)),
    ):
        d = mujoco.MjData(m)
        d.qpos[:] = qpos
        if name == "collapse":
            d.qpos[robot.QPOS_BASE_QUAT] = [np.cos(0.15), np.sin(0.15), 0, 0]  # rolled 0.3 rad
        k = 0
        for n in steps:
            while k < n:
                if ctrl is None:  # joint PD around the keyframe (what stand.stand_controller does, simplified)
                    q, q_key = d.qpos[robot.QPOS_JOINTS], m.key("standing").qpos[robot.QPOS_JOINTS]
                    d.ctrl[:] = np.clip(d.qfrc_bias[robot.QVEL_JOINTS] + 300.0 * (q_key - q)
                                        - 10.0 * d.qvel[robot.QVEL_JOINTS], -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
                else:
                    d.ctrl[:] = ctrl
                mujoco.mj_step(m, d)
                k += 1
            snap = mujoco.MjData(m)
            snap.qpos[:], snap.qvel[:], snap.ctrl[:], snap.time = d.qpos, d.qvel, d.ctrl, d.time
            snap.qacc_warmstart[:] = d.qacc_warmstart
            mujoco.mj_forward(m, snap)
            out.append((f"{name}@{n}", snap))
    return out


# ------------------------------------------------------------------------------------------------ sections


def probe_sensors(args) -> dict:
    full = sensor_model()
    states = c_states(full)  # C MuJoCo states (sensors do not change the dynamics)
    res = dict(groups={}, states={})
    per_impl = {}
    for impl in ("jax", "warp"):
        ok = []
        for g in SENSOR_GROUPS:
            try:
                mjx.put_model(sensor_model([g]), impl=impl)
                ok.append(g)
                res["groups"][f"{g}/{impl}"] = "put_model ok"
            except Exception as e:  # noqa: BLE001
                res["groups"][f"{g}/{impl}"] = f"{type(e).__name__}: {e}"[:500]
        per_impl[impl] = ok
        print(f"[sensors] {impl}: put_model accepts {ok}; {res['groups']}", flush=True)
    c_sl = sensor_slices(full)
    for label, _ in states:
        res["states"][label] = {}
    for impl, groups in per_impl.items():
        m = sensor_model(groups)
        sl = sensor_slices(m)
        mx = mjx.put_model(m, impl=impl)
        f = jax.jit(mjx.forward)
        for label, dc_full in states:
            row = res["states"][label]
            if "c" not in row:
                row["ncon_c"] = int(dc_full.ncon)
                row["contacts_c"] = sorted({(full.geom(c.geom1).name, full.geom(c.geom2).name)
                                            for c in dc_full.contact[:dc_full.ncon]})
                row["c"] = {n: np.asarray(dc_full.sensordata[s]).tolist() for n, s in c_sl.items()}
            dc = mujoco.MjData(m)
            dc.qpos[:], dc.qvel[:], dc.ctrl[:], dc.time = dc_full.qpos, dc_full.qvel, dc_full.ctrl, dc_full.time
            dc.qacc_warmstart[:] = dc_full.qacc_warmstart
            mujoco.mj_forward(m, dc)
            try:
                kw = dict(naconmax=64, njmax=128) if impl == "warp" else {}
                dx = f(mx, mjx.put_data(m, dc, impl=impl, **kw))
                sd = np.asarray(dx.sensordata, np.float64)
                vals = {n: sd[s].tolist() for n, s in sl.items()}
                row[impl] = vals
                row[f"maxabs_{impl}_vs_c"] = {n: float(np.max(np.abs(np.asarray(vals[n]) - np.asarray(row["c"][n]))))
                                              for n in sl}
            except Exception as e:  # noqa: BLE001
                row[f"error_{impl}"] = f"{type(e).__name__}: {e}"[:2000]
                print(f"[sensors] {impl} {label}: {row[f'error_{impl}']}", flush=True)
    for label, row in res["states"].items():
        print(f"[sensors] {label}: C contacts {row['contacts_c']}", flush=True)
        for n, v in row["c"].items():
            print(f"   {n:22s} C {np.round(v, 2)}  jax {np.round(row.get('jax', {}).get(n, []), 2)}  "
                  f"warp {np.round(row.get('warp', {}).get(n, []), 2)}", flush=True)
    return res


def _standing_batch(mx, m, batch: int, impl: str, naconmax=None, njmax=None, heights=None):
    """A batch of HyQ standing on the platform (per-instance height, friction, payload) as impl ``impl``."""
    ids = hmodel.model_ids(m)
    rng = np.random.default_rng(0)
    h = np.full(batch, 0.1) if heights is None else np.asarray(heights)
    terr = hmodel.InstanceTerrain.make(h, rng.uniform(0.7, 1.0, batch), rng.uniform(0, 10, batch),
                                       np.c_[rng.uniform(-0.1, 0.1, (batch, 2)), np.zeros(batch)])
    mb = hmodel.batch_model(mx, ids, terr)
    qpos = np.stack([hmodel.standing_qpos(m, base_xy=(-0.5, 0.0), ground_height=hh) for hh in h])
    kw = {} if impl == "jax" else dict(naconmax=naconmax, njmax=njmax)

    def one(q):
        d = mjx.make_data(m, impl=impl, **kw)
        return d.replace(qpos=jnp.asarray(q, jnp.float32))

    d0 = jax.jit(jax.vmap(one))(qpos)
    if impl == "warp":  # world-body geoms are static under warp: their pose is taken from Data, not the Model
        static = mjx_impl.static_geoms(m)
        d0 = d0.replace(geom_xpos=d0.geom_xpos.at[:, static].set(mb.geom_pos[:, static]))
    return mb, hmodel.model_in_axes(mb), d0


def _hold_torques(m) -> np.ndarray:
    """The standing keyframe's weight feed-forward torques (what bench_physics holds open loop)."""
    tau = stand.weight_feedforward(jnp.asarray(robot.Q_STANDING, jnp.float32), jnp.array([1.0, 0, 0, 0], jnp.float32))
    return np.clip(np.asarray(tau), -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT).astype(np.float32)


def _run(mb, axes, d0, steps: int, tau):
    def run(mb, d):
        d = d.replace(ctrl=jnp.broadcast_to(jnp.asarray(tau), d.ctrl.shape))
        step = jax.vmap(mjx.step, in_axes=(axes, 0))
        return jax.lax.scan(lambda dd, _: (step(mb, dd), dd.qpos[:, 2]), d, None, length=steps)

    return jax.jit(run)(mb, d0)


def _warp_counters(d) -> dict:
    impl = d._impl
    out = {}
    for k in ("nacon", "ncollision", "naconmax", "njmax", "nefc", "overflow", "solver_niter"):
        if hasattr(impl, k):
            v = getattr(impl, k)
            a = np.asarray(v)
            out[k] = a.tolist() if a.size <= 8 else dict(min=int(a.min()), max=int(a.max()), shape=list(a.shape))
    if hasattr(impl, "overflow"):
        ov = np.asarray(impl.overflow).reshape(-1)
        out["overflow_worlds"] = {n: int(np.sum((ov & b) != 0)) for n, b in OVERFLOW_BITS.items()}
    return out


def probe_overflow(args) -> dict:
    m = hmodel.load_model()
    mx = mjx_impl.put_model(m, "warp")
    tau = _hold_torques(m)
    b = args.small_batch
    res = {}
    for label, naconmax, njmax in (("default", None, None), ("ample", 16 * b, 64),
                                   ("naconmax=2/instance", 2 * b, 64), ("njmax=8", 16 * b, 8)):
        try:
            mb, axes, d0 = _standing_batch(mx, m, b, "warp", naconmax, njmax)
            row = dict(fields_of_impl=sorted(k for k in type(d0._impl).__annotations__ if not k.startswith(
                ("contact__", "efc__"))) if label == "default" else None)
            row["contact_field_shapes"] = {k: list(np.shape(getattr(d0._impl, k))) for k in (
                "contact__dist", "contact__geom", "contact__worldid", "efc__force") if hasattr(d0._impl, k)}
            d, z = _run(mb, axes, d0, args.steps, tau)
            z = np.asarray(z)
            row.update(_warp_counters(d))
            row["trunk_z_end"] = dict(min=float(z[-1].min()), max=float(z[-1].max()))
            row["finite"] = bool(np.all(np.isfinite(np.asarray(d.qpos))))
            res[label] = row
        except Exception as e:  # noqa: BLE001
            res[label] = dict(error=f"{type(e).__name__}: {e}"[:2000])
        print(f"[overflow] {label}: {json.dumps(res[label], default=str)[:1500]}", flush=True)
    return res


def probe_batched(args) -> dict:
    m = hmodel.load_model()
    tau = _hold_torques(m)
    b = args.small_batch
    heights = np.linspace(0.0, 0.3, b)
    out = {}
    for impl in ("jax", "warp"):
        mx = mjx_impl.put_model(m, impl)
        mb, axes, d0 = _standing_batch(mx, m, b, impl, 16 * b if impl == "warp" else None, 64 if impl == "warp"
                                       else None, heights=heights)
        t = time.perf_counter()
        d, z = _run(mb, axes, d0, args.steps, tau)
        jax.block_until_ready(d)
        out[impl] = dict(qpos=np.asarray(d.qpos, np.float64), z=np.asarray(z), s=time.perf_counter() - t)
    dz = np.abs(out["jax"]["z"] - out["warp"]["z"])
    dq = np.abs(out["jax"]["qpos"] - out["warp"]["qpos"])
    res = dict(batch=b, steps=args.steps, heights=heights.tolist(),
               trunk_z_end_jax=out["jax"]["z"][-1].tolist(), trunk_z_end_warp=out["warp"]["z"][-1].tolist(),
               max_trunk_z_diff=float(dz.max()), max_qpos_diff_end=float(dq.max()),
               trunk_above_platform_end=(out["warp"]["z"][-1] - heights).tolist(),
               finite=bool(np.all(np.isfinite(out["warp"]["qpos"]))))
    print(f"[batched] {json.dumps(res)[:1500]}", flush=True)
    return res


def probe_rollout(args) -> dict:
    m = hmodel.load_model()
    ids = hmodel.model_ids(m)
    mx = mjx_impl.put_model(m, "warp")
    b = args.small_batch
    res = {}
    mb, axes, d0 = _standing_batch(mx, m, b, "warp", 16 * b, 64)
    step = jax.jit(jax.vmap(mjx.step, in_axes=(axes, 0)))
    d1 = step(mb, d0)
    for name, fn in (
        ("mul_m", lambda mm, dd: jax.vmap(lambda a, c: mjx.mul_m(a, c, c.qacc), in_axes=(axes, 0))(mm, dd)),
        ("bias_plus_Mqacc_from_forces", lambda mm, dd: dd.qfrc_bias + dd.qfrc_smooth + dd.qfrc_constraint),
        ("observe", lambda mm, dd: jax.vmap(lambda a, c: sim.observe(ids, c, jnp.zeros(12), a).foot_force,
                                            in_axes=(axes, 0))(mm, dd)),
        ("tree_map_where", lambda mm, dd: jax.vmap(
            lambda a, c, e: step(mb, jax.tree_util.tree_map(lambda x, y: jnp.where(a, x, y), c, e)).qpos,
            in_axes=(0, 0, 0))(jnp.arange(b) % 2 == 0, dd, d0)),
        ("Data.where", lambda mm, dd: step(mb, jax.vmap(lambda a, c, e: c.where(a, e))(jnp.arange(b) % 2 == 0, dd,
                                                                                     d0)).qpos),
        ("initial_data", lambda mm, dd: step(mb, sim.initial_data(mx, jnp.asarray(dd.qpos), b)).qpos),
    ):
        try:
            v = np.asarray(jax.jit(fn)(mb, d1))
            res[name] = dict(ok=True, shape=list(v.shape), finite=bool(np.all(np.isfinite(v))))
        except Exception as e:  # noqa: BLE001
            res[name] = dict(ok=False, error=f"{type(e).__name__}: {e}"[:1500])
        print(f"[rollout] {name}: {json.dumps(res[name])[:1500]}", flush=True)
    # qfrc_bias + M qacc (what observe's foot-force estimate needs) from public force fields, against C MuJoCo
    try:
        mxj = mjx.put_model(m, impl="jax")
        dc = mujoco.MjData(m)
        dc.qpos[:] = hmodel.standing_qpos(m)
        dc.ctrl[:] = _hold_torques(m)
        for _ in range(50):
            mujoco.mj_step(m, dc)
        mujoco.mj_forward(m, dc)
        mq = np.zeros(m.nv)
        mujoco.mj_mulM(m, dc, mq, dc.qacc)
        ref = dc.qfrc_bias + mq
        out = {}
        for impl, mm in (("jax", mxj), ("warp", mx)):
            kw = dict(naconmax=16, njmax=64) if impl == "warp" else {}
            dd = jax.jit(mjx.forward)(mm, mjx.put_data(m, dc, impl=impl, **kw))
            ident = np.asarray(dd.qfrc_bias + dd.qfrc_smooth + dd.qfrc_constraint, np.float64)
            out[impl] = dict(maxabs=float(np.max(np.abs(ident - ref))), scale=float(np.max(np.abs(ref))))
        res["bias_plus_Mqacc_vs_c"] = out
        print(f"[rollout] qfrc_bias + qfrc_smooth + qfrc_constraint vs C qfrc_bias + M qacc: {out}", flush=True)
    except Exception as e:  # noqa: BLE001
        res["bias_plus_Mqacc_vs_c"] = f"{type(e).__name__}: {e}"[:1500]
    return res


def probe_sharding(args) -> dict:
    m = hmodel.load_model()
    mx = mjx_impl.put_model(m, "warp")
    tau = _hold_torques(m)
    devs = jax.local_devices()
    b = args.small_batch * len(devs)
    mb, axes, d0 = _standing_batch(mx, m, b, "warp", 16 * b, 64)
    mesh = Mesh(np.asarray(devs), ("batch",))
    shard, repl = NamedSharding(mesh, PartitionSpec("batch")), NamedSharding(mesh, PartitionSpec())
    m_sh = jax.tree_util.tree_map(lambda ax: shard if ax == 0 else repl, axes,
                                  is_leaf=lambda x: x is None or isinstance(x, int))

    def d_spec(path, x):
        batched = np.ndim(x) > 0 and x.shape[0] == b
        return shard if batched else repl

    d_sh = jax.tree_util.tree_map_with_path(d_spec, d0)

    def run(mb, d):
        d = d.replace(ctrl=jnp.broadcast_to(jnp.asarray(tau), d.ctrl.shape))
        step = jax.vmap(mjx.step, in_axes=(axes, 0))
        d, _ = jax.lax.scan(lambda dd, _: (step(mb, dd), None), d, None, length=args.steps)
        return d

    res = dict(devices=[str(x) for x in devs], graph_mode=str(getattr(mx.opt._impl, "graph_mode", None)))
    try:
        out_sh = jax.tree_util.tree_map_with_path(d_spec, jax.eval_shape(run, mb, d0))
        f = jax.jit(run, in_shardings=(m_sh, d_sh), out_shardings=out_sh)
        a = jax.device_put((mb, d0), (m_sh, d_sh))
        t = time.perf_counter()
        c = f.lower(*a).compile()
        res["compile_s"] = time.perf_counter() - t
        d = jax.block_until_ready(c(*a))
        ref, _ = _run(mb, axes, d0, args.steps, tau)
        res["max_qpos_diff_vs_unsharded"] = float(np.max(np.abs(np.asarray(d.qpos) - np.asarray(ref.qpos))))
        res["qpos_sharding"] = str(d.qpos.sharding)
        res["ok"] = True
    except Exception as e:  # noqa: BLE001
        res["ok"] = False
        res["error"] = f"{type(e).__name__}: {e}"[:3000]
        res["trace"] = traceback.format_exc()[-3000:]
    print(f"[sharding] {json.dumps(res, default=str)[:3000]}", flush=True)
    return res


def probe_throughput(args) -> dict:
    m = hmodel.load_model()
    tau = _hold_torques(m)
    res = {}
    for b in args.batches:
        for impl in ("jax", "warp"):
            mx = mjx_impl.put_model(m, impl)
            mb, axes, d0 = _standing_batch(mx, m, b, impl, args.naconmax_per * b if impl == "warp" else None,
                                           args.njmax if impl == "warp" else None)

            def run(mb, d):
                d = d.replace(ctrl=jnp.broadcast_to(jnp.asarray(tau), d.ctrl.shape))
                step = jax.vmap(mjx.step, in_axes=(axes, 0))
                d, _ = jax.lax.scan(lambda dd, _: (step(mb, dd), None), d, None, length=args.steps)
                return d

            t = time.perf_counter()
            c = jax.jit(run).lower(mb, d0).compile()
            comp = time.perf_counter() - t
            jax.block_until_ready(c(mb, d0))
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                d = jax.block_until_ready(c(mb, d0))
                times.append(time.perf_counter() - t)
            med = float(np.median(times))
            row = dict(compile_s=comp, times_s=times, env_steps_per_s=b * args.steps / med,
                       finite=bool(np.all(np.isfinite(np.asarray(d.qpos)))),
                       trunk_z=dict(min=float(np.min(d.qpos[:, 2])), max=float(np.max(d.qpos[:, 2]))))
            if impl == "warp":
                row.update(_warp_counters(d))
            res[f"{impl}@{b}"] = row
            print(f"[throughput] {impl} batch {b}: {row['env_steps_per_s'] / 1e6:.3f} M env-steps/s "
                  f"(compile {comp:.1f} s) {json.dumps({k: row[k] for k in row if k not in ('times_s',)})[:600]}",
                  flush=True)
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    p.add_argument("--small-batch", type=int, default=8, help="batch of the overflow/batched/rollout sections")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--batches", type=int, nargs="+", default=[64])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--naconmax-per", type=int, default=16, help="throughput: naconmax per instance")
    p.add_argument("--njmax", type=int, default=64, help="throughput: njmax per instance")
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    import warp as wp

    info = dict(jax=jax.__version__, backend=jax.default_backend(), devices=[str(d) for d in jax.devices()],
                mujoco=mujoco.__version__, warp=wp.__version__, date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    res = dict(info=info)
    print(json.dumps(info), flush=True)
    for s in a.sections:
        t = time.perf_counter()
        try:
            res[s] = globals()[f"probe_{s}"](a)
        except Exception as e:  # noqa: BLE001
            res[s] = dict(error=f"{type(e).__name__}: {e}"[:3000], trace=traceback.format_exc()[-3000:])
            print(f"[{s}] FAILED {res[s]['error'][:1500]}", flush=True)
        res[s + "_s"] = time.perf_counter() - t
        if a.out:
            os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
            with open(a.out, "w") as f:
                json.dump(res, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
