"""MJX solver settings for HyQ: speed against stability and accuracy, standing and under a push.

For each setting (``timestep``, ``iterations``, ``ls_iterations``) a batch of HyQ instances runs
``--duration`` s of closed loop from the standing keyframe (flat ground, x = 1 m) under
``hyqjax.control.stand.stand_controller`` at a fixed 250 Hz control rate (zero-order hold, so the controller
is the same for every timestep; ``control_dt / timestep`` physics steps per tick), float32 MJX.
Half of the instances only stand; the other half get a horizontal push at t = 0.5 s for 0.1 s,
200 to 800 N in directions spread around the compass (the feet slip; HyQ slides and recovers).

Reported per setting:
  env-steps/s      batch x physics steps / wall time of the jitted rollout (after compile);
  sim-s/s          batch x simulated seconds / wall time (the cost measure that compares timesteps);
  diverged         fraction of instances with a non-finite state or |qvel| > 100 (hyqjax.sim.rollout's test);
  fell             fraction with the trunk below 0.35 m at the end;
  height drift     max over time of |z(t) - z(0)| of the standing instances (mm);
  error vs ref     final-state error against a high-accuracy C MuJoCo reference (float64, default
                   Newton solver: iterations 100, ls_iterations 50, timestep 0.5 ms, same controller
                   and pushes): trunk position (mm), trunk orientation (deg), joints (max, rad); the
                   mean over the standing reference instance and the pushed ones is given separately.

``iterations``/``ls_iterations`` are static in MJX (one compile per pair); the timestep is passed at run
time, so one compiled program serves the three timesteps. "default" means MuJoCo's defaults (100, 50).
The project's setting is timestep 0.002, iterations 4, ls_iterations 8 (``hyqjax.sim.model.load_model``).

Usage::

    python benchmarks/bench_settings.py --out out/bench_settings.json
    python benchmarks/bench_settings.py --grid short --batch 4096 --budget-s 150
"""
from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from bench_physics import host_info  # noqa: E402
from hyqjax.io import atomic as hio  # noqa: E402
from hyqjax.sim import model as hmodel  # noqa: E402
from hyqjax.core import robot  # noqa: E402
from hyqjax.sim import rollout as sim
from hyqjax.control import stand

DEFAULT_ITERATIONS, DEFAULT_LS_ITERATIONS = 100, 50  # MuJoCo's defaults
ITERATIONS = (1, 2, 4, DEFAULT_ITERATIONS)
LS_ITERATIONS = (4, 8, DEFAULT_LS_ITERATIONS)
TIMESTEPS = (0.001, 0.002, 0.004)
CHOSEN = (0.002, 4, 8)
CONTROL_DT = 0.004
PUSH_T0, PUSH_DURATION = 0.5, 0.1
REF_TIMESTEP = 0.0005
BASE_XY = (1.0, 0.0)
MAX_SPEED = sim.SimConfig().max_speed
FELL_Z = 0.35

# Ordered by priority (a budget cuts the tail): the project's choice, MuJoCo's defaults, then the rest.
SHORT_GRID = [(4, 8), (DEFAULT_ITERATIONS, DEFAULT_LS_ITERATIONS), (1, 4), (2, 8), (4, 4), (1, 8)]


def pushes(batch: int, seed: int = 0) -> np.ndarray:
    """(batch, 3) push forces: zero for the first half, 200-800 N horizontal for the second half (up to
    80 N s: the feet slip and HyQ, under joint PD alone, slides up to ~0.15 m and recovers)."""
    f = np.zeros((batch, 3))
    n = batch - batch // 2
    k = np.arange(n)
    ang = 2 * np.pi * ((k * 0.618034) % 1.0)
    mag = 200.0 + 600.0 * ((k * 0.381966 + 0.5) % 1.0)
    f[batch // 2:, 0] = mag * np.cos(ang)
    f[batch // 2:, 1] = mag * np.sin(ang)
    return f


def make_rollout(m: mujoco.MjModel, ids: hmodel.ModelIds, duration: float):
    """jit(vmap) of the closed loop; args (mx, qpos0 (nq,), forces (B, 3), timestep, substeps)."""
    n_ticks = int(round(duration / CONTROL_DT))
    params = stand.StandParams.make()

    def one(mx, qpos0, force, substeps):
        d = mjx.make_data(mx).replace(qpos=qpos0)
        tau0 = jnp.zeros(robot.N_JOINTS, d.qpos.dtype)
        z0 = qpos0[2]

        def tick(carry, _):
            d, tau_prev, div, max_dz = carry
            obs = sim.observe(ids, d, tau_prev)
            _, tau, _ = stand.stand_controller.step(params, (), obs)
            tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
            on = (d.time >= PUSH_T0 - 1e-6) & (d.time < PUSH_T0 + PUSH_DURATION - 1e-6)
            wrench = jnp.concatenate([jnp.where(on, force, 0.0), jnp.zeros(3, force.dtype)])
            d = d.replace(ctrl=tau, xfrc_applied=d.xfrc_applied.at[ids.trunk_body].set(wrench))
            d = jax.lax.fori_loop(0, substeps, lambda _, dd: mjx.step(mx, dd), d)
            bad = ~(jnp.all(jnp.isfinite(d.qpos)) & jnp.all(jnp.isfinite(d.qvel)) & (jnp.max(jnp.abs(d.qvel)) < MAX_SPEED))
            max_dz = jnp.maximum(max_dz, jnp.where(jnp.isfinite(d.qpos[2]), jnp.abs(d.qpos[2] - z0), jnp.inf))
            return (d, tau, div | bad, max_dz), None

        carry = (d, tau0, jnp.array(False), jnp.zeros((), d.qpos.dtype))
        (d, _, div, max_dz), _ = jax.lax.scan(tick, carry, None, length=n_ticks)
        return d.qpos, div, max_dz

    def run(mx, qpos0, forces, timestep, substeps):
        mx = mx.replace(opt=mx.opt.replace(timestep=timestep))
        return jax.vmap(one, in_axes=(None, None, 0, None))(mx, qpos0, forces, substeps)

    return jax.jit(run), n_ticks


def reference(m_ref: mujoco.MjModel, ids, qpos0, force, duration: float) -> np.ndarray:
    """Final qpos of the C MuJoCo float64 reference (same controller, same push)."""
    params = stand.StandParams.make()
    with jax.enable_x64(True):
        kp, kd = (np.asarray(x, np.float64) for x in params.gains.per_joint())
        ff = jax.jit(stand.weight_feedforward)
        q_ref = np.asarray(robot.Q_STANDING, np.float64)
        d = mujoco.MjData(m_ref)
        d.qpos[:] = qpos0
        mujoco.mj_forward(m_ref, d)
        substeps = int(round(CONTROL_DT / m_ref.opt.timestep))
        qadr, vadr = np.asarray(ids.qpos_joints), np.asarray(ids.dof_joints)
        for _ in range(int(round(duration / CONTROL_DT))):
            q, qd = d.qpos[qadr], d.qvel[vadr]
            tau = kp * (q_ref - q) - kd * qd + np.asarray(ff(jnp.asarray(q), jnp.asarray(d.qpos[robot.QPOS_BASE_QUAT])))
            d.ctrl[:] = np.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
            on = PUSH_T0 - 1e-6 <= d.time < PUSH_T0 + PUSH_DURATION - 1e-6
            d.xfrc_applied[ids.trunk_body, :3] = force if on else 0.0
            mujoco.mj_step(m_ref, d, nstep=substeps)
    return d.qpos.copy()


def state_errors(qpos, qref) -> dict:
    """Final-state errors of (n, nq) against (n, nq): trunk position (mm), orientation (deg), joints (rad)."""
    pos_, quat, joint = robot.QPOS_BASE_POS, robot.QPOS_BASE_QUAT, robot.QPOS_JOINTS
    pos = np.linalg.norm(qpos[:, pos_] - qref[:, pos_], axis=-1) * 1e3
    dot = np.abs(np.sum(qpos[:, quat] / np.linalg.norm(qpos[:, quat], axis=-1, keepdims=True) * qref[:, quat], -1))
    ang = np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))
    joints = np.max(np.abs(qpos[:, joint] - qref[:, joint]), axis=-1)
    return dict(pos_mm=pos, rot_deg=ang, joint_rad=joints)


def _fmt(x, f="{:.2f}"):
    return "–" if x is None or not np.isfinite(x) else f.format(x)


def markdown_table(rows: list[dict], info: dict) -> str:
    out = [
        "| timestep | iterations | ls_iter | env-steps/s | sim-s/s | cost vs chosen | diverged | fell "
        "| stand height drift (mm) | stand err vs ref: pos mm / rot deg / joint rad | push err vs ref: pos mm / rot deg / joint rad |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    chosen = next((r for r in rows if (r["timestep"], r["iterations"], r["ls_iterations"]) == CHOSEN), None)
    for r in rows:
        it = "default (100)" if r["iterations"] == DEFAULT_ITERATIONS else str(r["iterations"])
        ls = "default (50)" if r["ls_iterations"] == DEFAULT_LS_ITERATIONS else str(r["ls_iterations"])
        mark = " **(chosen)**" if (r["timestep"], r["iterations"], r["ls_iterations"]) == CHOSEN else ""
        cost = chosen["sim_s_per_s"] / r["sim_s_per_s"] if chosen else None
        st, pu = r["err_stand"], r["err_push"]
        out.append(
            f"| {r['timestep']}{mark} | {it} | {ls} | {r['env_steps_per_s']:,.0f} | {r['sim_s_per_s']:,.1f} "
            f"| {_fmt(cost, '{:.2f}x')} | {r['diverged_rate']:.0%} | {r['fell_rate']:.0%} | {_fmt(r['stand_height_drift_mm'])} "
            f"| {_fmt(st['pos_mm'])} / {_fmt(st['rot_deg'])} / {_fmt(st['joint_rad'], '{:.3f}')} "
            f"| {_fmt(pu['pos_mm'])} / {_fmt(pu['rot_deg'])} / {_fmt(pu['joint_rad'], '{:.3f}')} |")
    out.append(f"\nbatch {info['batch']} ({info['batch'] // 2} standing, {info['batch'] - info['batch'] // 2} pushed "
               f"200-800 N for {PUSH_DURATION} s at t = {PUSH_T0} s), {info['duration']} s simulated, control at "
               f"{1 / CONTROL_DT:.0f} Hz; reference: C MuJoCo float64, Newton 100/50, timestep {REF_TIMESTEP} s, "
               f"{info['n_ref']} instances (1 standing, {info['n_ref'] - 1} pushed); cost vs chosen = chosen's sim-s/s "
               "over this row's.")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", choices=("full", "short"), default="full",
                    help="full: iterations x ls_iterations = 12 pairs; short: the 6 pairs of SHORT_GRID")
    ap.add_argument("--timesteps", type=float, nargs="+", default=list(TIMESTEPS))
    ap.add_argument("--batch", type=int, default=None, help="instances per setting (default 16 CPU, 4096 GPU)")
    ap.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    ap.add_argument("--repeats", type=int, default=1, help="timed calls per setting (median)")
    ap.add_argument("--n-ref", type=int, default=5, help="reference instances (1 standing + pushed ones)")
    ap.add_argument("--budget-s", type=float, default=None, help="skip the remaining pairs after this many seconds")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    info = host_info()
    gpu = info["backend"] != "cpu"
    batch = args.batch or (4096 if gpu else 16)
    pairs = list(itertools.product(ITERATIONS, LS_ITERATIONS)) if args.grid == "full" else SHORT_GRID
    if args.grid == "full":  # priority order as in the short grid, then the rest
        pairs = [p for p in SHORT_GRID if p in pairs] + [p for p in pairs if p not in SHORT_GRID]
    n_ref = min(args.n_ref, batch // 2 + 1)
    info.update(batch=batch, duration=args.duration, control_dt=CONTROL_DT, grid=args.grid, pairs=pairs,
                timesteps=args.timesteps, n_ref=n_ref, repeats=args.repeats,
                provenance=hio.provenance(argv if argv is not None else sys.argv[1:]))
    print("# bench_settings")
    for k in ("date", "device", "cpu", "cpu_cores", "loadavg_start", "jax", "mujoco", "mujoco_mjx", "batch",
              "duration", "control_dt", "grid", "timesteps", "n_ref"):
        print(f"{k}: {info[k]}")
    sys.stdout.flush()

    m0 = hmodel.load_model()
    ids = hmodel.model_ids(m0)
    qpos0 = hmodel.standing_qpos(m0, base_xy=BASE_XY)
    forces = pushes(batch)
    ref_idx = [0] + list(range(batch // 2, batch // 2 + n_ref - 1))

    t = time.perf_counter()
    m_ref = hmodel.load_model(timestep=REF_TIMESTEP, iterations=DEFAULT_ITERATIONS, ls_iterations=DEFAULT_LS_ITERATIONS)
    q_ref = np.stack([reference(m_ref, ids, qpos0, forces[i], args.duration) for i in ref_idx])
    print(f"reference: {len(ref_idx)} instances in {time.perf_counter() - t:.1f} s; final trunk z "
          f"{np.round(q_ref[:, 2], 4).tolist()}", flush=True)

    rows = []
    t_start = time.perf_counter()

    def save():
        if args.out:
            info["loadavg_end"] = os.getloadavg()
            hio.write_json(args.out, dict(info=info, q_ref=q_ref, ref_index=ref_idx, rows=rows,
                                          table=markdown_table(rows, info) if rows else ""))

    dev = jax.devices()[0]
    for it, ls in pairs:
        if args.budget_s is not None and time.perf_counter() - t_start > args.budget_s:
            print(f"budget of {args.budget_s} s spent: skipping iterations={it}, ls_iterations={ls}", flush=True)
            continue
        m = hmodel.load_model(timestep=0.002, iterations=it, ls_iterations=ls)
        mx = jax.device_put(mjx.put_model(m), dev)
        fn, n_ticks = make_rollout(m, ids, args.duration)
        call_args = lambda dt: jax.device_put(  # noqa: E731
            (mx, jnp.asarray(qpos0, jnp.float32), jnp.asarray(forces, jnp.float32), jnp.float32(dt),
             jnp.int32(int(round(CONTROL_DT / dt)))), dev)
        t = time.perf_counter()
        compiled = fn.lower(*call_args(args.timesteps[0])).compile()
        compile_s = time.perf_counter() - t
        for dt in args.timesteps:
            substeps = int(round(CONTROL_DT / dt))
            a = call_args(dt)
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                qpos, div, max_dz = jax.block_until_ready(compiled(*a))
                times.append(time.perf_counter() - t)
            wall = float(np.median(times))
            qpos, div, max_dz = np.asarray(qpos, np.float64), np.asarray(div), np.asarray(max_dz)
            stand_ids = np.arange(batch // 2)
            fell = ~div & (qpos[:, 2] < FELL_Z)
            err = state_errors(qpos[ref_idx], q_ref)
            ok = ~div[ref_idx]

            def mean_err(sel):
                sel = sel & ok
                return {k: (float(np.mean(v[sel])) if sel.any() else None) for k, v in err.items()}

            is_stand = np.array([i < batch // 2 for i in ref_idx])
            row = dict(timestep=dt, iterations=it, ls_iterations=ls, substeps=substeps, compile_s=compile_s,
                       times_s=times, wall_s=wall, env_steps_per_s=batch * n_ticks * substeps / wall,
                       sim_s_per_s=batch * args.duration / wall, diverged_rate=float(div.mean()),
                       fell_rate=float(fell.mean()),
                       stand_height_drift_mm=float(np.max(max_dz[stand_ids][~div[stand_ids]]) * 1e3)
                       if (~div[stand_ids]).any() else None,
                       err_stand=mean_err(is_stand), err_push=mean_err(~is_stand),
                       err_all={k: v.tolist() for k, v in err.items()})
            rows.append(row)
            print(f"dt {dt:.3f} it {it:3d} ls {ls:2d}: {row['env_steps_per_s']:11,.0f} env-steps/s "
                  f"{row['sim_s_per_s']:8.1f} sim-s/s  diverged {row['diverged_rate']:.0%} fell {row['fell_rate']:.0%} "
                  f"drift {_fmt(row['stand_height_drift_mm'])} mm  err stand {_fmt(row['err_stand']['pos_mm'])} mm "
                  f"push {_fmt(row['err_push']['pos_mm'])} mm  (compile {compile_s:.0f} s, run {wall:.1f} s)", flush=True)
            save()

    rows.sort(key=lambda r: (r["timestep"], r["iterations"], r["ls_iterations"]))
    print()
    print(markdown_table(rows, info))
    save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
