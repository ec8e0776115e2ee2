"""Closed-loop step-down throughput at scale: env-steps/s, controller overhead, sharding, gradients, memory,
NaN rate, in one run.

Sections (each compiled ahead with ``jit(...).lower(...).compile()``, run once untimed, then timed
``--repeats`` times with ``jax.block_until_ready``; the median is reported):

  throughput  per batch size, side by side on the same host:
                physics   bare MJX: ``jit`` of a ``lax.scan`` of ``--steps`` ``vmap(mjx.step)`` on the *same*
                          batched step-down model and initial state as the closed loop, open loop (constant
                          standing torques);
                closed    the step-down closed loop as ``stepdown.run_batch`` runs it (crawl + height reflex +
                          joint impedance + MJX, step-down metrics, divergence checks, no traces), built by
                          ``sim.batch_rollout_fn``, ``--steps`` control ticks of one 2 ms physics step;
                mujoco_c  C MuJoCo (float64) ``mujoco.rollout`` with all host threads, per-instance platform
                          height, the same initial states and open-loop torques.
              overhead = physics rate / closed rate (1.0 = the controller is free).
  stages      at one batch: observation alone, observation + crawl controller + metrics (no physics; the
              joints are nudged every tick so nothing is loop-invariant), to split the closed loop's time.
  memory      bytes per instance of the rollout state (Data + controller state + metrics, from the shapes),
              XLA's memory analysis of the closed loop at the largest batch for ``--steps`` ticks and for
              ``--long-duration`` s (compiled, not run: the scan keeps only its carry, so the two should
              match), and the device's peak memory (``memory_stats``) after the runs.
  nan         a step-down sweep (heights x reflex on/off) of ``--nan-batch`` instances, float32, timestep
              2 ms, Newton iterations 4 / ls_iterations 8: divergence and non-finite rates and success rate.
              The duration is ``--nan-duration`` s, or (default) what ``--nan-seconds`` of run time allow at the
              measured closed-loop rate, capped at the experiment's 18 s.
  grad        ``jax.jacfwd`` of a tuning objective (mean over the batch of the integral of trunk roll^2 +
              pitch^2) w.r.t. ``--grad-fields`` ReflexParams fields through ``--grad-duration`` s of the
              closed loop, against the forward objective alone: time ratio and memory.
  scaling     with more than one local device: the closed loop on one device at batch B and on the 1-D
              ``sim.batch_mesh`` of all devices at n x B (same batch per device), ratio of env-steps/s.

Writes JSON (``--out``, rewritten after every measurement, so a killed run keeps what it measured) and
a PNG plot of env-steps/s against batch size (``--plot``); prints a markdown summary last.

Usage::

    PYTHONPATH=. python benchmarks/bench_closed_loop.py --tiny --out out/closed_loop_cpu.json --plot out/cl.png
    python benchmarks/bench_closed_loop.py --out $OUT/closed_loop.json --plot $OUT/closed_loop.png --budget-s 480
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import hyqjax  # noqa: E402,F401  (sets the XLA:CPU flags before jax is imported)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import mujoco.rollout  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import mjx  # noqa: E402

from hyqjax.crawl import controller as crawl  # noqa: E402
from hyqjax.io import atomic as hio
from hyqjax.sim import model as hmodel
from hyqjax.core import robot
from hyqjax.sim import rollout as sim
from hyqjax.sim import runner as srunner
from hyqjax.core import spatial
from hyqjax.control import stand
from hyqjax.studies import stepdown

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_physics import host_info  # noqa: E402  (the same host / version record in every benchmark)
import mjx_impl  # noqa: E402

GPU_BATCHES = (4096, 16384, 65536)
GPU_C_BATCHES = (4096, 16384)
CPU_BATCHES = (8, 32)
HEIGHTS = (0.05, 0.10, 0.15, 0.20)  # x reflex off/on: batches are multiples of 8
SECTIONS = ("throughput", "memory", "stages", "nan", "grad", "scaling")


# ----------------------------------------------------------------------------------------------- setup


def scenario(batch: int, seed: int = 0):
    """A step-down batch: HEIGHTS x reflex off/on x batch/8 randomised instances (``stepdown.make_scenarios``)."""
    per = len(HEIGHTS) * 2
    if batch % per:
        raise ValueError(f"batch must be a multiple of {per}, got {batch}")
    scen, table = stepdown.make_scenarios(HEIGHTS, [False, True], batch // per, seed)
    return scen, table


def closed_loop_fn(scen, cfg: stepdown.StepdownConfig, mesh=None, metrics=None, params=None):
    """What ``stepdown.run_batch`` builds (no traces): the jitted batch rollout and its arguments."""
    st = stepdown.setup(cfg)
    mx, ids = st.mx, st.ids
    scfg = cfg.sim_config()
    mb = hmodel.batch_model(mx, ids, scen.terrain)
    d0 = stepdown.initial_batch_data(st, mb, scen)  # under warp: terrain poses in the data
    metrics = metrics or stepdown.make_metrics(ids, cfg)
    fn, args = srunner.batch_rollout_fn(mb, ids, d0, crawl.crawl_controller(scfg.control_dt),
                                        scen.params if params is None else params, scfg, metrics=metrics,
                                        record=None, params_axes=0, mesh=mesh, push=scen.push)
    if mesh is None:
        args = jax.device_put(args, jax.devices()[0])  # committed: every call runs the one executable
    return fn, args


def standing_torques() -> np.ndarray:
    tau = stand.weight_feedforward(jnp.asarray(robot.Q_STANDING, jnp.float32), jnp.array([1.0, 0, 0, 0], jnp.float32))
    return np.clip(np.asarray(tau, np.float64), -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)


def compile_timed(jitted, args):
    t = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    return compiled, time.perf_counter() - t


def time_compiled(compiled, args, repeats: int):
    out = jax.block_until_ready(compiled(*args))  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t)
    return times, out


def memory_analysis(compiled) -> dict | None:
    try:
        ma = compiled.memory_analysis()
    except Exception:  # pragma: no cover
        return None
    if ma is None:
        return None
    keys = ("argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes", "alias_size_in_bytes",
            "generated_code_size_in_bytes")
    return {k: int(getattr(ma, k)) for k in keys if hasattr(ma, k)}


def device_peak() -> dict | None:
    try:
        st = jax.devices()[0].memory_stats()
    except Exception:  # pragma: no cover
        return None
    if not st:
        return None
    return {k: int(st[k]) for k in ("peak_bytes_in_use", "bytes_in_use", "bytes_limit") if k in st}


def _warp_version() -> str | None:
    try:
        import warp

        return warp.__version__
    except ImportError:
        return None


def tree_bytes(tree) -> int:
    return int(sum(np.prod(x.shape) * np.dtype(x.dtype).itemsize for x in jax.tree_util.tree_leaves(tree)))


# ------------------------------------------------------------------------------------------ measurements


def bench_physics(batch: int, steps: int, repeats: int, cfg, impl: str = "jax") -> dict:
    scen, _ = scenario(batch)
    st = stepdown.setup(cfg)
    m, ids = st.m, st.ids
    mx = mjx_impl.put_model(m, impl)
    mb = hmodel.batch_model(mx, ids, scen.terrain)
    d0 = mjx_impl.batch_data(m, mb, stepdown.initial_qpos(m, scen), impl)
    d0 = d0.replace(ctrl=jnp.broadcast_to(jnp.asarray(standing_torques(), d0.ctrl.dtype), d0.ctrl.shape))
    m_axes = hmodel.model_in_axes(mb)

    def run(mb, d):
        step = jax.vmap(mjx.step, in_axes=(m_axes, 0))
        d, _ = jax.lax.scan(lambda dd, _: (step(mb, dd), None), d, None, length=steps)
        return d

    args = jax.device_put((mb, d0), jax.devices()[0])
    compiled, compile_s = compile_timed(jax.jit(run), args)
    times, out = time_compiled(compiled, args, repeats)
    return dict(compile_s=compile_s, times_s=times, memory=memory_analysis(compiled),
                finite=bool(np.all(np.isfinite(np.asarray(out.qpos)))), overflow=mjx_impl.overflow_count(out),
                state_bytes_per_instance=tree_bytes(out) // batch,
                final_trunk_z=float(np.mean(np.asarray(out.qpos[:, 2]) - np.asarray(scen.terrain.platform_height))))


def bench_closed(batch: int, steps: int, repeats: int, cfg, mesh=None, impl: str | None = None) -> dict:
    scen, _ = scenario(batch)
    cfg = dataclasses.replace(cfg, duration=steps * cfg.control_dt, record_every=0, impl=impl or cfg.impl)
    fn, args = closed_loop_fn(scen, cfg, mesh=mesh)
    compiled, compile_s = compile_timed(fn, args)
    times, out = time_compiled(compiled, args, repeats)
    return dict(compile_s=compile_s, times_s=times, memory=memory_analysis(compiled),
                finite=bool(np.all(np.isfinite(np.asarray(out.data.qpos)))),
                diverged=int(np.asarray(out.diverged).sum()),
                state_bytes_per_instance=dict(
                    data=tree_bytes(out.data) // batch, ctrl_state=tree_bytes(out.ctrl_state) // batch,
                    metrics=tree_bytes(out.metrics) // batch, model_batched=tree_bytes(
                        [x for x, ax in zip(jax.tree_util.tree_leaves(args[0]),
                                            jax.tree_util.tree_leaves(hmodel.model_in_axes(args[0]),
                                                                      is_leaf=lambda a: a is None))
                         if ax == 0]) // batch,
                    params=tree_bytes(args[2]) // batch))


def bench_mujoco_c(batch: int, steps: int, repeats: int, nthread: int, cfg, chunk: int = 4096) -> dict:
    """C MuJoCo rollouts of the same instances (platform height per instance; payload and friction not set)."""
    scen, _ = scenario(batch)
    st = stepdown.setup(cfg)
    m, ids = st.m, st.ids
    qpos = stepdown.initial_qpos(m, scen)
    heights = np.asarray(scen.terrain.platform_height)
    models = {}
    for h in np.unique(heights):
        mh = _copy_model(m)
        mh.geom_pos[ids.platform_geom, 2] = h - hmodel.PLATFORM_HALF_SIZE[2]
        models[float(h)] = mh
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m, spec)
    d = mujoco.MjData(m)
    init = np.zeros((batch, nstate))
    for i in range(batch):
        d.qpos[:] = qpos[i]
        d.qvel[:] = 0
        mujoco.mj_getState(m, d, init[i], spec)
    n = min(batch, chunk)
    ctrl = np.tile(standing_torques(), (n, steps, 1))
    out_state = np.zeros((n, steps, nstate))
    datas = [mujoco.MjData(m) for _ in range(max(nthread, 1))]
    mlist = [models[float(h)] for h in heights]

    with mujoco.rollout.Rollout(nthread=nthread) as r:
        def run_all():
            done, finite = 0, True
            while done < batch:
                k = min(n, batch - done)
                r.rollout(mlist[done:done + k], datas, init[done:done + k], ctrl[:k], nstep=steps,
                          state=out_state[:k])
                finite &= bool(np.all(np.isfinite(out_state[:k])))
                done += k
            return finite

        t = time.perf_counter()
        run_all()
        warm = time.perf_counter() - t
        times, finite = [], True
        for _ in range(repeats):
            t = time.perf_counter()
            finite = run_all()
            times.append(time.perf_counter() - t)
    return dict(compile_s=warm, times_s=times, finite=finite, nthread=nthread)


def _copy_model(m):
    import copy

    return copy.copy(m)


def bench_stages(batch: int, steps: int, repeats: int, cfg) -> dict:
    """Observation alone and observation + crawl controller + metrics, without physics, at one batch."""
    scen, _ = scenario(batch)
    st = stepdown.setup(cfg)
    m, mx, ids = st.m, st.mx, st.ids
    d0 = sim.initial_data(mx, stepdown.initial_qpos(m, scen), batch)
    # Contact and kinematic fields the controller and metrics read: one forward pass.
    mb = hmodel.batch_model(mx, ids, scen.terrain)
    m_axes = hmodel.model_in_axes(mb)
    d0 = jax.jit(jax.vmap(mjx.forward, in_axes=(m_axes, 0)))(mb, d0)
    ctrl = crawl.crawl_controller(cfg.control_dt)
    metrics = stepdown.make_metrics(ids, cfg)
    qadr = np.asarray(ids.qpos_joints)

    def nudge(d, tau):  # joints move a little every tick (so XLA cannot hoist the work out of the loop)
        return d.replace(qpos=d.qpos.at[qadr].add(1e-7 * tau), time=d.time + cfg.control_dt)

    def observe_only(d):
        def one(d):
            def tick(c, _):
                d, tau = c
                obs = sim.observe(ids, d, tau)
                tau = tau + 1e-3 * obs.foot_force.reshape(12)
                return (nudge(d, tau), tau), None
            (d, tau), _ = jax.lax.scan(tick, (d, jnp.zeros(12, d.qpos.dtype)), None, length=steps)
            return tau
        return jax.vmap(one)(d)

    def control(d, p):
        def one(d, p):
            obs0 = sim.observe(ids, d, jnp.zeros(12, d.qpos.dtype))
            cs0 = ctrl.init(p, obs0)

            def tick(c, _):
                d, cs, ms, tau = c
                obs = sim.observe(ids, d, tau)
                cs, tau, info = ctrl.step(p, cs, obs)
                tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
                ms = metrics.update(ms, d, obs, info)
                return (nudge(d, tau), cs, ms, tau), None
            c, _ = jax.lax.scan(tick, (d, cs0, metrics.init(d), jnp.zeros(12, d.qpos.dtype)), None, length=steps)
            return c[1], c[2], c[3]
        return jax.vmap(one)(d, p)

    out = {}
    dev = jax.devices()[0]
    for name, fn, args in (("observe", observe_only, (d0,)), ("observe+controller+metrics", control, (d0, scen.params))):
        args = jax.device_put(args, dev)
        compiled, compile_s = compile_timed(jax.jit(fn), args)
        times, _ = time_compiled(compiled, args, repeats)
        med = float(np.median(times))
        out[name] = dict(compile_s=compile_s, times_s=times, median_s=med, env_steps_per_s=batch * steps / med)
    return out


def bench_memory_long(batch: int, duration: float, cfg) -> dict:
    """Compile (not run) the closed loop for ``duration`` s and read XLA's memory analysis."""
    scen, _ = scenario(batch)
    c = dataclasses.replace(cfg, duration=duration, record_every=0)
    fn, args = closed_loop_fn(scen, c)
    compiled, compile_s = compile_timed(fn, args)
    return dict(batch=batch, duration=duration, compile_s=compile_s, memory=memory_analysis(compiled))


def bench_nan(batch: int, duration: float, cfg) -> dict:
    scen, table = scenario(batch, seed=1)
    c = dataclasses.replace(cfg, duration=duration, record_every=0)
    fn, args = closed_loop_fn(scen, c)
    compiled, compile_s = compile_timed(fn, args)
    t = time.perf_counter()
    res = jax.block_until_ready(compiled(*args))
    run_s = time.perf_counter() - t
    out = stepdown.summarize_instances(res, scen, c)
    qpos, qvel = np.asarray(res.data.qpos), np.asarray(res.data.qvel)
    nonfinite = ~(np.all(np.isfinite(qpos), 1) & np.all(np.isfinite(qvel), 1))
    div = np.asarray(res.diverged)
    rows = stepdown.summarize(table, out)
    return dict(batch=batch, duration=duration, ticks=c.sim_config().n_ticks, compile_s=compile_s, run_s=run_s,
                env_steps_per_s=batch * c.sim_config().n_ticks / run_s,
                diverged=int(div.sum()), diverged_rate=float(div.mean()), nonfinite_final=int(nonfinite.sum()),
                max_abs_qvel=float(np.nanmax(np.abs(qvel))), success_rate=float(np.mean(out["success"])),
                rows=[{k: (list(v) if isinstance(v, tuple) else v) for k, v in r.items()} for r in rows],
                diverged_ticks=sorted(int(t) for t in np.asarray(res.diverged_tick)[div])[:50])


def bench_grad(batch: int, duration: float, fields: list[str], repeats: int, cfg) -> dict:
    """``jacfwd`` of a tuning objective w.r.t. ReflexParams fields through the closed loop vs the objective."""
    scen, _ = scenario(batch, seed=2)
    c = dataclasses.replace(cfg, duration=duration, record_every=0)
    dt = c.control_dt

    def cost_init(d):
        return jnp.zeros((), d.qpos.dtype)

    def cost_update(acc, d, obs, info):
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d.qpos[robot.QPOS_BASE_QUAT]))
        return acc + dt * (rpy[0] ** 2 + rpy[1] ** 2)

    metrics = sim.Metrics(cost_init, cost_update)
    fn, args = closed_loop_fn(scen, c, metrics=metrics)
    mb, d0, params, push = args
    theta0 = jnp.stack([jnp.asarray(getattr(params.reflex, f)).reshape(batch, -1)[0, 0] for f in fields])

    def objective(theta, mb, d0, params, push):
        rp = params.reflex.replace(**{f: jnp.broadcast_to(theta[i], jnp.shape(getattr(params.reflex, f)))
                                      for i, f in enumerate(fields)})
        res = fn(mb, d0, dataclasses.replace(params, reflex=rp), push)
        return jnp.mean(res.metrics)

    out = {}
    a = (theta0, mb, d0, params, push)
    for name, f in (("forward", objective), ("jacfwd", jax.jacfwd(objective))):
        compiled, compile_s = compile_timed(jax.jit(f), a)
        times, val = time_compiled(compiled, a, repeats)
        med = float(np.median(times))
        out[name] = dict(compile_s=compile_s, times_s=times, median_s=med, memory=memory_analysis(compiled),
                         value=np.asarray(val).tolist(), peak_after=device_peak())
    out["ratio_jacfwd_over_forward"] = out["jacfwd"]["median_s"] / out["forward"]["median_s"]
    out.update(batch=batch, duration=duration, ticks=c.sim_config().n_ticks, fields=fields,
               theta0=np.asarray(theta0).tolist())
    return out


def bench_scaling(per_device: int, steps: int, repeats: int, cfg) -> dict:
    n = jax.local_device_count()
    one = bench_closed(per_device, steps, repeats, cfg)
    mesh = srunner.batch_mesh()
    many = bench_closed(per_device * n, steps, repeats, cfg, mesh=mesh)
    r1 = per_device * steps / float(np.median(one["times_s"]))
    rn = per_device * n * steps / float(np.median(many["times_s"]))
    return dict(per_device=per_device, n_devices=n, one=dict(env_steps_per_s=r1, compile_s=one["compile_s"],
                                                             times_s=one["times_s"]),
                mesh=dict(env_steps_per_s=rn, compile_s=many["compile_s"], times_s=many["times_s"],
                          diverged=many["diverged"]), speedup=rn / r1, efficiency=rn / r1 / n)


# ------------------------------------------------------------------------------------------------ report


def summary(res: dict) -> str:
    info = res["info"]
    lines = [f"## closed-loop step-down: {info['device']} x{info['n_devices']}, {info['date']}",
             f"jax {info['jax']}, mujoco {info['mujoco']}, mjx {info['mujoco_mjx']}, python {info['python']}, "
             f"{info['cpu_cores']} host cores ({info['cpu']}), {info['steps']} steps per timed call, "
             f"median of {info['repeats']}", ""]
    tp = res.get("throughput", {})
    if tp:
        lines += ["| batch | MJX physics | closed loop (step-down) | C MuJoCo | overhead (physics / closed) "
                  "| closed / C | compile s (physics / closed) | MJX-Warp physics | warp / jax physics "
                  "| closed loop under warp | closed warp / bare warp | closed warp / C |",
                  "|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|"]

        def f(x):
            return "–" if x is None else f"{x:,.0f}"

        for b in sorted(int(k) for k in tp):
            row = tp[str(b)]
            p = row.get("physics", {}).get("env_steps_per_s")
            cl = row.get("closed", {}).get("env_steps_per_s")
            cc = row.get("mujoco_c", {}).get("env_steps_per_s")
            comp = " / ".join(f"{row[k]['compile_s']:.0f}" if "compile_s" in row.get(k, {}) else "–"
                              for k in ("physics", "closed"))
            lines.append(f"| {b:,} | {f(p)} | {f(cl)} | {f(cc)} | {p / cl:.2f}x |" if p and cl else
                         f"| {b:,} | {f(p)} | {f(cl)} | {f(cc)} | – |")
            lines[-1] += (f" {cl / cc:.2f} |" if cl and cc else " – |") + f" {comp} |"
            pw = row.get("physics_warp", {}).get("env_steps_per_s")
            cw = row.get("closed_warp", {}).get("env_steps_per_s")
            lines[-1] += f" {f(pw)} |" + (f" {pw / p:.2f}x |" if pw and p else " – |")
            lines[-1] += f" {f(cw)} |" + (f" {cw / pw:.0%} |" if cw and pw else " – |")
            lines[-1] += f" {cw / cc:.1f}x |" if cw and cc else " – |"
    st = res.get("stages")
    if st:
        lines += ["", f"stages at batch {st['batch']} ({st['steps']} ticks): " + ", ".join(
            f"{k} {v['median_s'] * 1e3:.1f} ms ({v['env_steps_per_s']:,.0f}/s)" for k, v in st["results"].items())]
        if "closed_s" in st:
            lines.append(f"  physics {st['physics_s'] * 1e3:.1f} ms, closed {st['closed_s'] * 1e3:.1f} ms at that batch")
    mem = res.get("memory")
    if mem:
        lines += ["", f"memory: state bytes per instance {mem.get('state_bytes_per_instance')}"]
        for k in ("closed_short", "closed_long"):
            if k in mem:
                lines.append(f"  {k}: {mem[k]}")
        if "peak" in mem:
            lines.append(f"  device peak: {mem['peak']}")
    nan = res.get("nan")
    if nan:
        lines += ["", f"NaN/divergence: {nan['diverged']} of {nan['batch']} diverged ({nan['diverged_rate']:.2%}), "
                      f"{nan['nonfinite_final']} non-finite final states, {nan['duration']} s simulated "
                      f"({nan['ticks']} ticks), success {nan['success_rate']:.1%}, "
                      f"{nan['env_steps_per_s']:,.0f} env-steps/s"]
    g = res.get("grad")
    if g and "ratio_jacfwd_over_forward" in g:
        lines += ["", f"gradient: jacfwd over {g['fields']} through {g['duration']} s at batch {g['batch']}: "
                      f"{g['jacfwd']['median_s'] * 1e3:.1f} ms vs forward {g['forward']['median_s'] * 1e3:.1f} ms "
                      f"= {g['ratio_jacfwd_over_forward']:.2f}x; temp memory {(g['jacfwd']['memory'] or {}).get('temp_size_in_bytes')}"
                      f" vs {(g['forward']['memory'] or {}).get('temp_size_in_bytes')} bytes; grad {g['jacfwd']['value']}"]
    for s in res.get("scaling", []):
        lines += [f"scaling: {s['n_devices']} devices x {s['per_device']:,}: {s['mesh']['env_steps_per_s']:,.0f} vs one "
                  f"device {s['one']['env_steps_per_s']:,.0f} env-steps/s = {s['speedup']:.2f}x "
                  f"(efficiency {s['efficiency']:.0%})"]
    return "\n".join(lines)


def plot(res: dict, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    info = res["info"]
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    labels = {"physics": "bare MJX physics", "physics_warp": "bare MJX-Warp physics",
              "closed": "closed loop (crawl + reflex + MJX)", "closed_warp": "closed loop, MJX-Warp",
              "mujoco_c": f"C MuJoCo ({info.get('c_threads')} threads)"}
    tp = res.get("throughput", {})
    for mode, lab in labels.items():
        pts = sorted((int(b), r[mode]["env_steps_per_s"]) for b, r in tp.items() if "env_steps_per_s" in r.get(mode, {}))
        if pts:
            ax.plot(*zip(*pts), marker="o", label=lab)
    sc = res.get("scaling", [])
    if sc:
        pts = sorted((s["per_device"] * s["n_devices"], s["mesh"]["env_steps_per_s"]) for s in sc)
        ax.plot(*zip(*pts), marker="s", ls="--", label=f"closed loop, {sc[0]['n_devices']}-device mesh")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("batch size (instances)")
    ax.set_ylabel("env-steps / s")
    ax.set_title(f"HyQ step-down, {info['device']}, {info['date'][:10]}\njax {info['jax']}, mujoco {info['mujoco']}, "
                 f"mjx {info['mujoco_mjx']}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiny", action="store_true", help="CPU smoke run: tiny batches and horizons")
    ap.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS)
    ap.add_argument("--batches", type=int, nargs="+", default=None)
    ap.add_argument("--c-batches", type=int, nargs="+", default=None)
    ap.add_argument("--steps", type=int, default=None, help="control ticks (= 2 ms physics steps) per timed call")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None, help="C MuJoCo threads (default: host cores)")
    ap.add_argument("--stage-batch", type=int, default=None)
    ap.add_argument("--long-duration", type=float, default=20.0, help="duration (s) of the memory-analysis compile")
    ap.add_argument("--nan-batch", type=int, default=None)
    ap.add_argument("--nan-duration", type=float, default=None)
    ap.add_argument("--nan-seconds", type=float, default=30.0, help="run-time budget of the NaN sweep")
    ap.add_argument("--grad-batch", type=int, default=None)
    ap.add_argument("--grad-duration", type=float, default=None)
    ap.add_argument("--grad-fields", nargs="+", default=["k_x", "k_base", "d_sw_max"])
    ap.add_argument("--scaling-batches", type=int, nargs="+", default=None, help="batch per device")
    ap.add_argument("--budget-s", type=float, default=None, help="start nothing new after this many seconds")
    ap.add_argument("--impls", nargs="+", default=None, choices=mjx_impl.IMPLS,
                    help="MJX implementations of the bare-physics column (default: jax, and warp when installed)")
    ap.add_argument("--modes", nargs="+", default=["physics", "closed", "mujoco_c"],
                    choices=["physics", "closed", "mujoco_c"], help="throughput columns to measure")
    ap.add_argument("--out", default=None)
    ap.add_argument("--plot", default=None)
    args = ap.parse_args(argv)
    impls = args.impls or (["jax", "warp"] if mjx_impl.warp_available() else ["jax"])

    info = host_info()
    gpu = info["backend"] != "cpu"
    tiny = args.tiny or not gpu
    batches = args.batches or list(CPU_BATCHES if tiny else GPU_BATCHES)
    c_batches = args.c_batches or (batches if tiny else list(GPU_C_BATCHES))
    steps = args.steps or (20 if tiny else 100)
    repeats = args.repeats or (2 if tiny else 3)
    threads = args.threads or info["cpu_cores"]
    stage_batch = args.stage_batch or (8 if tiny else 16384)
    nan_batch = args.nan_batch or (16 if tiny else 8192)
    grad_batch = args.grad_batch or (8 if tiny else 4096)
    grad_duration = args.grad_duration or (0.1 if tiny else 0.8)
    long_batch = max(batches)
    scaling_batches = args.scaling_batches or ([8] if tiny else [16384, 32768])
    cfg = stepdown.StepdownConfig(record_every=0, impl="jax")  # the other implementations: *_warp columns
    info.update(impls=impls, warp=_warp_version(), batches=batches, c_batches=c_batches, steps=steps,
                repeats=repeats, c_threads=threads,
                heights=list(HEIGHTS), timestep=cfg.control_dt, dtype="float32",
                solver="Newton, iterations=4, ls_iterations=8 (hyqjax.sim.model.load_model defaults)",
                provenance=hio.provenance(argv if argv is not None else sys.argv[1:]))
    print("# bench_closed_loop")
    for k in ("date", "device", "n_devices", "cpu", "cpu_cores", "loadavg_start", "python", "jax", "jaxlib",
              "mujoco", "mujoco_mjx", "hyqjax", "batches", "c_batches", "steps", "repeats", "c_threads"):
        print(f"{k}: {info[k]}")
    sys.stdout.flush()

    res: dict = {"info": info}
    t0 = time.perf_counter()

    def save():
        info["loadavg_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
        info["elapsed_s"] = time.perf_counter() - t0
        if args.out:
            hio.write_json(args.out, res)

    def over_budget(what: str) -> bool:
        if args.budget_s is not None and time.perf_counter() - t0 > args.budget_s:
            print(f"budget of {args.budget_s} s spent: skipping {what}", flush=True)
            res.setdefault("skipped", []).append(what)
            return True
        return False

    def attempt(what: str, fn):
        if over_budget(what):
            return None
        t = time.perf_counter()
        try:
            r = fn()
        except Exception as e:  # e.g. out of memory: record and go on
            msg = f"{type(e).__name__}: {str(e)[:400]}"
            print(f"{what}: FAILED {msg}", flush=True)
            res.setdefault("errors", {})[what] = msg
            save()
            return None
        print(f"[{time.perf_counter() - t0:6.0f} s] {what} done in {time.perf_counter() - t:.1f} s", flush=True)
        return r

    # ---- throughput
    if "throughput" in args.sections:
        tp = res.setdefault("throughput", {})
        for b in sorted(set(batches) | set(c_batches)):
            row = tp.setdefault(str(b), {})
            others = [i for i in impls if i != "jax"]
            for mode in ([f"physics_{i}" for i in others] + ["physics"] + [f"closed_{i}" for i in others]
                         + ["closed", "mujoco_c"]):
                if mode.split("_")[0] not in args.modes and mode not in args.modes:
                    continue
                if mode == "mujoco_c" and b not in c_batches:
                    continue
                if mode != "mujoco_c" and b not in batches:
                    continue
                if mode.startswith("physics_"):
                    r = attempt(f"{mode} {b}", lambda: bench_physics(b, steps, repeats, cfg, mode.split("_", 1)[1]))
                elif mode.startswith("closed_"):
                    r = attempt(f"{mode} {b}", lambda: bench_closed(b, steps, repeats, cfg, impl=mode.split("_", 1)[1]))
                elif mode == "physics":
                    r = attempt(f"physics {b}", lambda: bench_physics(b, steps, repeats, cfg))
                elif mode == "closed":
                    r = attempt(f"closed {b}", lambda: bench_closed(b, steps, repeats, cfg))
                else:
                    r = attempt(f"mujoco_c {b}", lambda: bench_mujoco_c(b, steps, repeats, threads, cfg))
                if r is None:
                    continue
                med = float(np.median(r["times_s"]))
                r.update(median_s=med, env_steps_per_s=b * steps / med)
                row[mode] = r
                print(f"  {mode:9s} batch {b:6d}: {r['env_steps_per_s']:12,.0f} env-steps/s (median {med * 1e3:.1f} ms, "
                      f"compile {r['compile_s']:.1f} s, finite {r['finite']})", flush=True)
                save()
        res["peak_after_throughput"] = device_peak()

    # ---- memory
    if "memory" in args.sections:
        mem = res.setdefault("memory", {})
        tp = res.get("throughput", {})
        lb = str(long_batch)
        if lb in tp and "closed" in tp[lb]:
            mem["state_bytes_per_instance"] = tp[lb]["closed"]["state_bytes_per_instance"]
            mem["closed_short"] = dict(batch=long_batch, duration=steps * cfg.control_dt, memory=tp[lb]["closed"]["memory"])
        r = attempt(f"memory compile {long_batch} x {args.long_duration} s",
                    lambda: bench_memory_long(long_batch, args.long_duration, cfg))
        if r:
            mem["closed_long"] = r
        mem["peak"] = device_peak()
        save()

    # ---- stages
    if "stages" in args.sections:
        r = attempt(f"stages {stage_batch}", lambda: bench_stages(stage_batch, steps, repeats, cfg))
        if r:
            st = dict(batch=stage_batch, steps=steps, results=r)
            row = res.get("throughput", {}).get(str(stage_batch), {})
            if "physics" in row and "closed" in row:
                st.update(physics_s=row["physics"]["median_s"], closed_s=row["closed"]["median_s"])
            res["stages"] = st
            save()

    # ---- NaN sweep
    if "nan" in args.sections:
        dur = args.nan_duration
        if dur is None:
            rate = None
            for b, row in sorted(res.get("throughput", {}).items(), key=lambda kv: abs(int(kv[0]) - nan_batch)):
                if "closed" in row:
                    rate = row["closed"]["env_steps_per_s"]
                    break
            ticks = int(rate * args.nan_seconds / nan_batch) if rate else int(0.2 / cfg.control_dt)
            dur = float(min(18.0, max(0.2, round(ticks * cfg.control_dt, 1))))
            if tiny:
                dur = min(dur, 0.2)
        r = attempt(f"nan {nan_batch} x {dur} s", lambda: bench_nan(nan_batch, dur, cfg))
        if r:
            res["nan"] = r
            print(f"  NaN sweep: {r['diverged']} / {r['batch']} diverged, {r['nonfinite_final']} non-finite, "
                  f"{dur} s, success {r['success_rate']:.1%}", flush=True)
            save()

    # ---- gradient
    if "grad" in args.sections:
        r = attempt(f"grad {grad_batch} x {grad_duration} s",
                    lambda: bench_grad(grad_batch, grad_duration, args.grad_fields, repeats, cfg))
        if r:
            res["grad"] = r
            print(f"  grad: jacfwd / forward = {r['ratio_jacfwd_over_forward']:.2f}", flush=True)
            save()

    # ---- scaling over local devices
    if "scaling" in args.sections:
        if jax.local_device_count() < 2:
            res["scaling_note"] = "one local device: no scaling measured"
        else:
            for pb in scaling_batches:
                r = attempt(f"scaling {pb}/device", lambda: bench_scaling(pb, steps, repeats, cfg))
                if r:
                    res.setdefault("scaling", []).append(r)
                    print(f"  scaling {pb}/device: {r['speedup']:.2f}x on {r['n_devices']} devices", flush=True)
                    save()

    res["peak_end"] = device_peak()
    save()
    print()
    print(summary(res))
    if args.plot and res.get("throughput"):
        plot(res, args.plot)
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
