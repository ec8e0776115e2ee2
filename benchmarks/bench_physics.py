"""Physics throughput of HyQ standing on flat ground: env-steps/s against batch size.

Three measurements in the same run (same host, same model, same initial state):

  physics   bare MJX: ``jit`` of a ``lax.scan`` of ``--steps`` calls of ``vmap(mjx.step)``, float32.
  rollout   the closed loop of hyqjax: ``vmap(sim.rollout)`` with ``stand.stand_controller`` under ``jit``
            (what ``sim.batch_rollout`` builds, unsharded), ``--steps`` control ticks of one physics step
            each, per-instance terrain (``model.batch_model``), divergence checks included.
  mujoco_c  C MuJoCo (float64) ``mujoco.rollout.Rollout(nthread=threads)``, ``--steps`` steps per instance.

All start from the standing keyframe at x = 1 m (all four feet on the floor, clear of the step). The
open-loop runs (``physics`` and ``mujoco_c``) hold a constant control: the standing controller's torques
at the keyframe (the PD terms vanish there, so it is the weight feed-forward), which keeps HyQ standing
for the 0.2 s measured. Each measurement is compiled (MJX) or warmed up first, then timed ``--repeats``
times from the same initial state with ``jax.block_until_ready``; the median is reported.
``env-steps/s = batch x steps / median wall time``.

Usage::

    python benchmarks/bench_physics.py --out out/bench_physics.json --plot out/bench_physics.png
    python benchmarks/bench_physics.py --batches 1 16 64 --modes physics mujoco_c

Defaults: batches 1 16 64 256 1024 on CPU, 1024 4096 16384 65536 on GPU; C MuJoCo threads = CPU cores.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
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

from hyqjax.io import atomic as hio  # noqa: E402
from hyqjax.sim import model as hmodel  # noqa: E402
from hyqjax.core import robot  # noqa: E402
from hyqjax.sim import rollout as sim
from hyqjax.control import stand

CPU_BATCHES = (1, 16, 64, 256, 1024)
GPU_BATCHES = (1024, 4096, 16384, 65536)
MODES = ("physics", "rollout", "mujoco_c")
BASE_XY = (1.0, 0.0)


def _version(dist: str) -> str:
    try:
        from importlib.metadata import version

        return version(dist)
    except Exception:  # pragma: no cover
        return "unknown"


def host_info() -> dict:
    dev = jax.devices()[0]
    mjx_version = _version("mujoco-mjx")
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "backend": jax.default_backend(),
        "device": f"{dev.platform.upper()}: {getattr(dev, 'device_kind', str(dev))}",
        "n_devices": jax.device_count(),
        "cpu": cpu,
        "cpu_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "loadavg_start": os.getloadavg() if hasattr(os, "getloadavg") else None,
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": _version("jaxlib"),
        "mujoco": mujoco.__version__,
        "mujoco_mjx": mjx_version,
        "hyqjax": hyqjax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def standing_setup():
    """Model, ids, the keyframe qpos at x = 1 m, and the keyframe's standing torques (12,)."""
    m = hmodel.load_model()
    ids = hmodel.model_ids(m)
    qpos0 = hmodel.standing_qpos(m, base_xy=BASE_XY)
    tau = stand.weight_feedforward(jnp.asarray(robot.Q_STANDING, jnp.float32), jnp.array([1.0, 0, 0, 0], jnp.float32))
    tau = np.clip(np.asarray(tau, np.float64), -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
    return m, ids, qpos0, tau


def _time_compiled(fn, args, repeats: int):
    times = []
    out = None
    for _ in range(repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return times, out


def bench_physics(m, qpos0, tau, batch: int, steps: int, repeats: int) -> dict:
    dev = jax.devices()[0]
    mx = jax.device_put(mjx.put_model(m), dev)
    d0 = sim.initial_data(mx, qpos0, batch=batch)
    d0 = d0.replace(ctrl=jnp.broadcast_to(jnp.asarray(tau, d0.ctrl.dtype), d0.ctrl.shape))
    d0 = jax.device_put(d0, dev)  # committed, so that every call runs the one compiled executable

    def run(mx, d):
        step = jax.vmap(mjx.step, in_axes=(None, 0))
        d, _ = jax.lax.scan(lambda dd, _: (step(mx, dd), None), d, None, length=steps)
        return d

    t = time.perf_counter()
    compiled = jax.jit(run).lower(mx, d0).compile()
    compile_s = time.perf_counter() - t
    _time_compiled(compiled, (mx, d0), 1)  # warm-up
    times, out = _time_compiled(compiled, (mx, d0), repeats)
    z = np.asarray(out.qpos[:, 2])
    return dict(compile_s=compile_s, times_s=times, final_z_mean=float(np.nanmean(z)),
                finite=bool(np.all(np.isfinite(np.asarray(out.qpos)))))


def bench_rollout(m, ids, qpos0, batch: int, steps: int, repeats: int) -> dict:
    dev = jax.devices()[0]
    mx = mjx.put_model(m)
    mxb = hmodel.batch_model(mx, ids, hmodel.InstanceTerrain.make(np.zeros(batch)))
    d0 = sim.initial_data(mxb, qpos0, batch=batch)
    params = stand.StandParams.make()
    cfg = sim.SimConfig(control_dt=float(m.opt.timestep), substeps=1, duration=steps * float(m.opt.timestep),
                        record_every=0)
    assert cfg.n_ticks == steps
    push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), sim.Push.none())
    # The function sim.batch_rollout jits (unsharded path), built once so that it can be timed without
    # recompiling: batch_rollout itself jits a new closure, hence recompiles, on every call.
    fn = jax.vmap(lambda mm, dd, pp, pu: sim.rollout(mm, ids, dd, stand.stand_controller, pp, cfg, sim.no_metrics(),
                                                     None, pu),
                  in_axes=(hmodel.model_in_axes(mxb), 0, None, 0))
    args = jax.device_put((mxb, d0, params, push), dev)
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t
    _time_compiled(compiled, args, 1)
    times, out = _time_compiled(compiled, args, repeats)
    z = np.asarray(out.data.qpos[:, 2])
    return dict(compile_s=compile_s, times_s=times, final_z_mean=float(np.nanmean(z)),
                finite=bool(np.all(np.isfinite(np.asarray(out.data.qpos)))),
                diverged=int(np.asarray(out.diverged).sum()))


def bench_mujoco_c(m, qpos0, tau, batch: int, steps: int, repeats: int, nthread: int, chunk: int = 4096) -> dict:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos0
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m, spec)
    state0 = np.zeros(nstate)
    mujoco.mj_getState(m, d, state0, spec)
    n = min(batch, chunk)
    init = np.tile(state0, (n, 1))
    ctrl = np.tile(tau, (n, steps, 1))
    out_state = np.zeros((n, steps, nstate))
    datas = [mujoco.MjData(m) for _ in range(max(nthread, 1))]

    with mujoco.rollout.Rollout(nthread=nthread) as r:
        def run_all():
            done = 0
            while done < batch:
                k = min(n, batch - done)
                r.rollout(m, datas, init[:k], ctrl[:k], nstep=steps, state=out_state[:k])
                done += k
            return out_state

        t = time.perf_counter()
        run_all()  # warm-up (thread pool start, first touch of the buffers)
        warm_s = time.perf_counter() - t
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            run_all()
            times.append(time.perf_counter() - t)
    qpos_final = out_state[:, -1, 1:1 + m.nq]  # FULLPHYSICS: time, qpos, qvel, ...
    return dict(compile_s=warm_s, times_s=times, final_z_mean=float(np.mean(qpos_final[:, 2])),
                finite=bool(np.all(np.isfinite(out_state))), nthread=nthread)


def markdown_table(results: list[dict], steps: int) -> str:
    by = {}
    for r in results:
        by.setdefault(r["batch"], {})[r["mode"]] = r
    lines = [
        "| batch | MJX physics (env-steps/s) | closed-loop rollout (env-steps/s) | C MuJoCo rollout (env-steps/s) "
        "| physics / C | rollout / physics | compile s (physics / rollout) |",
        "|---:|---:|---:|---:|---:|---:|---|",
    ]

    def f(x):
        return "–" if x is None else f"{x:,.0f}"

    for b in sorted(by):
        row = by[b]
        p = row.get("physics", {}).get("env_steps_per_s")
        ro = row.get("rollout", {}).get("env_steps_per_s")
        c = row.get("mujoco_c", {}).get("env_steps_per_s")
        comp = " / ".join(f"{row[k]['compile_s']:.0f}" if k in row else "–" for k in ("physics", "rollout"))
        lines.append(f"| {b:,} | {f(p)} | {f(ro)} | {f(c)} | {p / c:.2f} |" if p and c else
                     f"| {b:,} | {f(p)} | {f(ro)} | {f(c)} | – |")
        lines[-1] += f" {ro / p:.2f} |" if p and ro else " – |"
        lines[-1] += f" {comp} |"
    lines.append(f"\n{steps} steps per instance per timed call; median of the repeats; physics timestep 2 ms.")
    return "\n".join(lines)


def plot(results: list[dict], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    labels = {"physics": "MJX physics (jit vmap mjx.step)", "rollout": "hyqjax closed-loop rollout",
              "mujoco_c": "C MuJoCo rollout (threads)"}
    for mode in MODES:
        pts = sorted((r["batch"], r["env_steps_per_s"]) for r in results if r["mode"] == mode)
        if pts:
            ax.plot(*zip(*pts), marker="o", label=labels[mode])
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("batch size (instances)")
    ax.set_ylabel("env-steps / s")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="batch sizes (default: by backend)")
    ap.add_argument("--c-batches", type=int, nargs="+", default=None, help="batch sizes for C MuJoCo (default: --batches)")
    ap.add_argument("--steps", type=int, default=100, help="physics steps per instance per timed call")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--threads", type=int, default=None, help="C MuJoCo threads (default: CPU cores)")
    ap.add_argument("--budget-s", type=float, default=None, help="skip what is left after this many seconds")
    ap.add_argument("--out", default=None, help="JSON output path")
    ap.add_argument("--plot", default=None, help="PNG output path")
    args = ap.parse_args(argv)

    info = host_info()
    gpu = info["backend"] not in ("cpu",)
    batches = args.batches or list(GPU_BATCHES if gpu else CPU_BATCHES)
    c_batches = args.c_batches or batches
    threads = args.threads or info["cpu_cores"]
    info.update(batches=batches, c_batches=c_batches, steps=args.steps, repeats=args.repeats, c_threads=threads,
                timestep=0.002, solver="Newton, iterations=4, ls_iterations=8 (hyqjax.sim.model.load_model defaults)",
                provenance=hio.provenance(argv if argv is not None else sys.argv[1:]))
    print("# bench_physics")
    for k in ("date", "device", "n_devices", "cpu", "cpu_cores", "loadavg_start", "python", "jax", "mujoco",
              "mujoco_mjx", "hyqjax", "batches", "c_batches", "steps", "repeats", "c_threads"):
        print(f"{k}: {info[k]}")
    sys.stdout.flush()

    m, ids, qpos0, tau = standing_setup()
    results = []
    t_start = time.perf_counter()

    def save():
        if args.out:
            info["loadavg_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
            hio.write_json(args.out, dict(info=info, results=results, table=markdown_table(results, args.steps)))

    for batch in sorted(set(batches) | set(c_batches if "mujoco_c" in args.modes else [])):
        for mode in args.modes:
            if mode == "mujoco_c" and batch not in c_batches or mode != "mujoco_c" and batch not in batches:
                continue
            if args.budget_s is not None and time.perf_counter() - t_start > args.budget_s:
                print(f"budget of {args.budget_s} s spent: skipping {mode} at batch {batch}", flush=True)
                continue
            try:
                if mode == "physics":
                    r = bench_physics(m, qpos0, tau, batch, args.steps, args.repeats)
                elif mode == "rollout":
                    r = bench_rollout(m, ids, qpos0, batch, args.steps, args.repeats)
                else:
                    r = bench_mujoco_c(m, qpos0, tau, batch, args.steps, args.repeats, threads)
            except Exception as e:  # e.g. out of memory at the largest batch: record and go on
                print(f"{mode} batch {batch}: FAILED {type(e).__name__}: {str(e)[:300]}", flush=True)
                results.append(dict(mode=mode, batch=batch, error=f"{type(e).__name__}: {str(e)[:300]}"))
                save()
                continue
            med = float(np.median(r["times_s"]))
            r.update(mode=mode, batch=batch, steps=args.steps, median_s=med, env_steps_per_s=batch * args.steps / med)
            results.append(r)
            print(f"{mode:9s} batch {batch:6d}: {r['env_steps_per_s']:12,.0f} env-steps/s  (median {med * 1e3:.1f} ms, "
                  f"compile/warm-up {r['compile_s']:.1f} s, final z {r['final_z_mean']:.4f} m, finite {r['finite']})",
                  flush=True)
            save()

    ok = [r for r in results if "error" not in r]
    table = markdown_table(ok, args.steps)
    print()
    print(table)
    save()
    if args.plot and ok:
        plot(ok, args.plot, f"HyQ standing, {info['device']}, {info['date'][:10]}\n"
                            f"jax {info['jax']}, mujoco {info['mujoco']}, mjx {info['mujoco_mjx']}, C threads {threads}")
        print(f"plot: {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
