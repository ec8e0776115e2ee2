"""False alarms and power of the CI gate (``hyqjax compare`` / ``hyqjax sweep --baseline``) over many seeds.

For each seed ``s`` of ``--seeds`` (the CI spec, ``hyqjax/studies/sweep/specs/ci.toml``, with ``seed = s``,
optionally cut down with ``--heights`` / ``--reflex`` / ``--samples`` / ``--duration``), sweeps are run into
stores and compared as CI compares them (:func:`hyqjax.studies.sweep.compare.compare_stores`, Holm at
``--alpha``):

* ``base``: the controller as it is (Table I), on C MuJoCo (``--impl``, default ``c``);
* arm ``planted``: a planted regression, ``--planted`` (default: Table I's reflex damping bounds doubled,
  ``reflex_d_st_min/max`` 50/1000 -> 100/2000, ``reflex_d_sw_min/max`` 5/100 -> 10/200, set as [fixed] axes and
  allowed to differ; halving them is no regression: measured, it raised clean success, and ``d_sw_min`` = 2.5 is
  below the reflex's stability bound of 4 at dt = 2 ms), same simulator; the gate must flag it (power);
* arm ``unchanged``: the same sweep run again (same simulator): the gate must not flag it (identical outcomes);
* arm ``rounding``: the same controller on another simulator (``--rounding-impl``, default ``jax``: MJX-JAX), a
  change of float rounding only: the gate should not flag it.

Writes ``OUT/results_ARMS.json`` (per seed and arm: the verdict, the tests, the discordant pairs) and prints a table:
per arm, how many seeds were flagged (regressed, improved), and per cell of the planted arm the effect measured on
all seeds' instances together (the pooled paired difference with Newcombe's interval): the effect "at scale".

One H200 host (16 CPU cores; the GPU for MJX-JAX), the shipped CI spec (2 cells x 64 instances) over 20 seeds, every
arm, in 7 minutes (2026-11-29; docs/ci.md has the table):

    python benchmarks/ci_gate_power.py --out out/ci_power --arms planted,unchanged,rounding --jobs 8 --cores-per-job 2

CPU, cut down (one cell, 20 seeds; the 2-core VM: 8-18 minutes per 10 seeds):

    python benchmarks/ci_gate_power.py --out out/ci_power --heights 0.24 --samples 16 --arms planted,unchanged

The C arms run in ``--jobs`` worker processes on the CPU (``JAX_PLATFORMS=cpu``; a worker steps its batch on every
core it may use: ``--cores-per-job`` gives each its own), the rounding arm in the main process (the GPU when there
is one) while they run; its comparisons wait for their base stores. A rerun on the same ``--out`` resumes: complete
stores are not simulated again.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

DAMPING_DOUBLED = "reflex_d_st_min=100,reflex_d_st_max=2000,reflex_d_sw_min=10,reflex_d_sw_max=200"
ARMS = ("planted", "unchanged", "rounding")


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="results directory (stores under OUT/stores)")
    p.add_argument("--seeds", type=int, default=20, help="number of seeds (sweep seeds 0 .. N-1 from --seed0)")
    p.add_argument("--seed0", type=int, default=0)
    p.add_argument("--samples", type=int, default=None, help="instances per grid cell (default: the CI spec's)")
    p.add_argument("--heights", default=None, help="comma-separated heights (default: the CI spec's)")
    p.add_argument("--reflex", default=None, help="on, off or on,off (default: the CI spec's)")
    p.add_argument("--duration", type=float, default=None, help="seconds per instance (default: the CI spec's)")
    p.add_argument("--arms", default="planted,unchanged", help=f"comma-separated arms of {list(ARMS)}")
    p.add_argument("--planted", default=DAMPING_DOUBLED, help="the planted change, AXIS=VALUE,... ([fixed] axes)")
    p.add_argument("--impl", default="c", help="simulator of base, planted and unchanged")
    p.add_argument("--rounding-impl", default="jax", help="simulator of the rounding arm")
    p.add_argument("--alpha", type=float, default=0.05)
    p.add_argument("--ci-family", type=int, default=None,
                   help="tests in the full CI sweep's Holm family (default: the shipped CI spec's, its cells x 2 levels + "
                        "2 pooled): a seed also counts as flagged 'at CI size' when its smallest p-value of a "
                        "regression is below alpha / this")
    p.add_argument("--jobs", type=int, default=1, help="processes over seeds for the --impl arms")
    p.add_argument("--cores-per-job", type=int, default=0,
                   help="pin each --jobs process to its own N cores (C MuJoCo steps a batch on the cores a process "
                        "may use; 0: no pinning, every process on every core)")
    a = p.parse_args(argv)
    arms = [x for x in a.arms.split(",") if x]
    bad = [x for x in arms if x not in ARMS]
    if bad or not arms:
        p.error(f"--arms: unknown {bad}; allowed {list(ARMS)}")
    if not 1 <= a.seeds <= 1000 or a.jobs < 1:
        p.error("--seeds must be in [1, 1000], --jobs >= 1")
    if not 0 <= a.cores_per_job <= (os.cpu_count() or 1):
        p.error(f"--cores-per-job must be in [0, {os.cpu_count() or 1}] (the cores of this machine), got {a.cores_per_job}")
    a.arm_list = arms
    if a.ci_family is None:
        a.ci_family = ci_family()
    return a


def ci_family() -> int:
    """The number of tests in the shipped CI sweep's Holm family: its grid cells x 2 levels + the 2 pooled tests."""
    import tomllib

    from hyqjax.cli.sweep import CI_SPEC

    with open(CI_SPEC, "rb") as f:
        grid = tomllib.load(f)["grid"]
    cells = 1
    for v in grid.values():
        cells *= len(v)
    return 2 * cells + (2 if cells > 1 else 0)


def base_spec(a, seed: int) -> dict:
    import tomllib

    from hyqjax.cli.sweep import CI_SPEC
    from hyqjax.studies.sweep.expect import split_spec_dict

    with open(CI_SPEC, "rb") as f:
        d, _ = split_spec_dict(tomllib.load(f))
    d["seed"] = seed
    if a.samples:
        d["samples"] = a.samples
    if a.duration:
        d["duration"] = a.duration
    if a.heights:
        d["grid"]["height"] = [float(x) for x in a.heights.split(",")]
    if a.reflex:
        d["grid"]["reflex"] = [x.strip() in ("on", "true") for x in a.reflex.split(",")]
    return d


def planted_changes(a) -> dict:
    out = {}
    for item in a.planted.split(","):
        k, v = item.split("=")
        out[k.strip()] = float(v)
    return out


def run_store(d: dict, path: str, impl: str, chunk_size: int | None = None) -> float:
    from hyqjax.studies import sweep

    spec = sweep.SweepSpec.from_dict(d)
    t0 = time.time()
    sweep.run_sweep(spec, path, chunk_size=chunk_size, progress=False, executor=sweep.LocalExecutor(impl=impl))
    return time.time() - t0


def pin_worker(counter, cores_per_job: int) -> None:
    """Pool initializer: the i-th worker process runs on cores [i * n, (i + 1) * n) (wrapping round)."""
    with counter.get_lock():
        i = counter.value
        counter.value += 1
    ncpu = os.cpu_count() or 1
    os.sched_setaffinity(0, {(i * cores_per_job + k) % ncpu for k in range(cores_per_job)})


def seed_job(payload) -> dict:
    """The --impl arms of one seed (a worker process): base, planted, unchanged; their comparisons."""
    a, seed = payload
    os.environ.setdefault("JAX_PLATFORMS", "cpu")  # a worker process (main): C MuJoCo's controller on the CPU
    from hyqjax.io.cache import enable_compilation_cache

    enable_compilation_cache()
    from hyqjax.studies.sweep.compare import compare_stores

    root = os.path.join(a.out, "stores", f"seed{seed:03d}")
    d = base_spec(a, seed)
    n = 1
    for k in ("height", "reflex"):
        n *= len(d["grid"][k])
    chunk = n * d["samples"]  # one chunk per store: one compile per shape in this process
    res = dict(seed=seed, wall_s={})
    res["wall_s"]["base"] = run_store(d, os.path.join(root, "base"), a.impl, chunk)
    if "planted" in a.arm_list:
        dp = json.loads(json.dumps(d))
        dp.setdefault("fixed", {}).update(planted_changes(a))
        res["wall_s"]["planted"] = run_store(dp, os.path.join(root, "planted"), a.impl, chunk)
        res["planted"] = compare_stores(os.path.join(root, "base"), os.path.join(root, "planted"), alpha=a.alpha,
                                        allow_change=tuple(planted_changes(a))).to_dict()
    if "unchanged" in a.arm_list:
        res["wall_s"]["unchanged"] = run_store(d, os.path.join(root, "unchanged"), a.impl, chunk)
        res["unchanged"] = compare_stores(os.path.join(root, "base"), os.path.join(root, "unchanged"),
                                          alpha=a.alpha).to_dict()
    return res


def rounding_simulate(a, seeds) -> float:
    """The rounding arm of every seed in one batch on ``--rounding-impl`` (one compile, the GPU filled), each seed's
    rows written to its own store (one chunk); returns the batch's wall time. Needs no base store, so it runs while
    the worker processes compute those; a seed whose rounding store is complete is not simulated again."""
    import numpy as np

    from hyqjax.studies import sweep
    from hyqjax.studies.sweep.runner import device_layout, run_rows

    specs = {s: sweep.SweepSpec.from_dict(base_spec(a, s)) for s in seeds}
    paths = {s: os.path.join(a.out, "stores", f"seed{s:03d}", "rounding") for s in seeds}
    def finished(s):
        if not os.path.exists(os.path.join(paths[s], "manifest.json")):
            return False
        with sweep.SweepStore(paths[s], specs[s], specs[s].n_instances) as st:
            return not st.todo()

    todo = [s for s in seeds if not finished(s)]
    if not todo:
        return 0.0
    rows = [specs[s].instance_inputs(0, specs[s].n_instances) for s in todo]
    allrows = {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}
    total = len(allrows["index"])
    t0 = time.time()
    out = run_rows(allrows, specs[todo[0]], total, impl=a.rounding_impl)
    wall = time.time() - t0
    layout = dict(device_layout(impl=a.rounding_impl), batch=total)
    off = 0
    for s, r in zip(todo, rows):
        n = len(r["index"])
        chunk = {**r, **{k: np.asarray(v)[off:off + n] for k, v in out.items()}}
        off += n
        os.makedirs(os.path.dirname(paths[s]), exist_ok=True)
        with sweep.SweepStore(paths[s], specs[s], n, layout, writer=True) as st:
            st.write_chunk(0, chunk, wall * n / total)
    print(f"rounding arm: {total} instances of {len(todo)} seeds on {a.rounding_impl} in {wall:.0f} s", flush=True)
    return wall


def rounding_compare(a, seeds) -> dict:
    """Each seed's rounding store compared with its base store."""
    from hyqjax.studies.sweep.compare import compare_stores

    res = {}
    for s in seeds:
        root = os.path.join(a.out, "stores", f"seed{s:03d}")
        res[s] = compare_stores(os.path.join(root, "base"), os.path.join(root, "rounding"), alpha=a.alpha).to_dict()
    return res


def pooled_effect(results, arm: str) -> list[dict]:
    """Per cell and level, the paired difference over every seed's instances together, Newcombe's interval."""
    from hyqjax.studies.sweep.compare import mcnemar_exact, newcombe_interval

    acc = {}
    for r in results:
        if arm not in r:
            continue
        for t in r[arm]["tests"]:
            e = acc.setdefault((t["cell"], t["level"]), dict(kb=0, kn=0, n=0, b=0, c=0))
            e["kb"] += t["k_base"]
            e["kn"] += t["k_new"]
            e["n"] += t["n_base"]
            e["b"] += t["b"] or 0
            e["c"] += t["c"] or 0
    out = []
    for (cell, level), e in acc.items():
        lo, hi = newcombe_interval(e["kn"], e["n"], e["kb"], e["n"])
        out.append(dict(cell=cell, level=level, n=e["n"], base_rate=e["kb"] / e["n"], new_rate=e["kn"] / e["n"],
                        diff=(e["kn"] - e["kb"]) / e["n"], ci=[lo, hi], b=e["b"], c=e["c"],
                        p_mcnemar=mcnemar_exact(e["b"], e["c"])))
    return out


def projected_power(pb: float, pc: float, n: int, threshold: float) -> float:
    """Probability that a paired cell of ``n`` instances is flagged as regressed (McNemar exact p below ``threshold``,
    more instances worse than better) when each instance independently gets worse with probability ``pb`` and better
    with ``pc`` (the discordant rates measured over all seeds): exact enumeration over the multinomial (b, c)."""
    import numpy as np
    from scipy.stats import binom, multinomial

    b, c = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    ok = b + c <= n
    m = b + c
    p = np.minimum(1.0, 2.0 * binom.cdf(np.minimum(b, c), np.maximum(m, 1), 0.5))
    p[m == 0] = 1.0
    flagged = ok & (p < threshold) & (b > c)
    if not flagged.any():
        return 0.0
    x = np.stack([b[flagged], c[flagged], n - b[flagged] - c[flagged]], 1)
    return float(multinomial.pmf(x, n, [pb, pc, max(0.0, 1.0 - pb - pc)]).sum())


def main(argv=None) -> int:
    a = parse_args(argv)
    os.makedirs(a.out, exist_ok=True)
    import hyqjax
    from hyqjax.io.cache import enable_compilation_cache

    enable_compilation_cache()
    seeds = list(range(a.seed0, a.seed0 + a.seeds))
    t0 = time.time()
    # The --impl arms run in worker processes on the CPU (JAX_PLATFORMS=cpu: C MuJoCo's controller is a CPU program,
    # and on a GPU machine the GPU stays free for the rounding arm of this process); one worker already steps its
    # batch on every core.
    import concurrent.futures as cf
    import multiprocessing as mp

    results = []
    rounding_wall = None
    ctx = mp.get_context("spawn")
    pin = dict(initializer=pin_worker, initargs=(ctx.Value("i", 0), a.cores_per_job)) if a.cores_per_job else {}
    with cf.ProcessPoolExecutor(a.jobs, mp_context=ctx, **pin) as ex:
        futures = [ex.submit(seed_job, (a, s)) for s in seeds]
        if "rounding" in a.arm_list:  # meanwhile, this process simulates the rounding arm (the GPU, if any)
            rounding_wall = rounding_simulate(a, seeds)
        for fut in futures:
            r = fut.result()
            results.append(r)
            print(f"seed {r['seed']}: " + ", ".join(f"{arm} {r[arm]['verdict']}" for arm in ARMS if arm in r),
                  flush=True)
    if "rounding" in a.arm_list:
        rc = rounding_compare(a, seeds)
        for r in results:
            r["rounding"] = rc[r["seed"]]
            print(f"seed {r['seed']}: rounding {r['rounding']['verdict']}", flush=True)
    wall = time.time() - t0
    summary = dict(args={k: v for k, v in vars(a).items()}, hyqjax=hyqjax.__version__, wall_s=wall,
                   load_avg=os.getloadavg(), cpu_count=os.cpu_count(), rounding_batch_wall_s=rounding_wall)
    import jax
    import mujoco

    summary.update(jax=jax.__version__, mujoco=mujoco.__version__, devices=[str(d) for d in jax.devices()])
    print(f"\n{len(seeds)} seeds, {wall:.0f} s (load average now {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    arms = {}
    for arm in a.arm_list:
        vs = [r[arm]["verdict"] for r in results if arm in r]
        ident = sum(bool(r[arm]["identical"]) for r in results if arm in r)
        thr = a.alpha / a.ci_family
        at_ci = sum(any(t["p"] < thr and t["diff"] < 0 for t in r[arm]["tests"]) for r in results if arm in r)
        arms[arm] = dict(seeds=len(vs), regressed=vs.count("regressed"), improved=vs.count("improved"),
                         no_change=vs.count("no significant change"), identical=ident,
                         regressed_at_ci_family=at_ci, ci_family=a.ci_family)
        print(f"{arm:10s}: flagged regressed {vs.count('regressed')}/{len(vs)}, improved {vs.count('improved')}/"
              f"{len(vs)}, identical outcomes {ident}/{len(vs)}; a regression with p < {a.alpha:g}/{a.ci_family} "
              f"(the CI sweep's first Holm step) in {at_ci}/{len(vs)}")
    summary["arms"] = arms
    for arm in a.arm_list:
        if arm == "unchanged":
            continue
        eff = pooled_effect(results, arm)
        summary[f"effect_{arm}"] = eff
        print(f"{arm}: effect over all seeds' instances (paired; NEW - BASE, Newcombe 95%)")
        for e in eff:
            print(f"  {e['cell']:28s} {e['level']:9s} n {e['n']:5d}: {e['base_rate']:.3f} -> {e['new_rate']:.3f}, "
                  f"{e['diff']:+.3f} [{e['ci'][0]:+.3f}, {e['ci'][1]:+.3f}], discordant {e['b']} worse / {e['c']} "
                  f"better, McNemar p {e['p_mcnemar']:.2g}")
    if "planted" in a.arm_list:
        thr = a.alpha / a.ci_family
        proj = []
        print(f"planted: projected power per cell (each instance worse / better with the rates measured over all seeds; "
              f"flagged when McNemar p < {a.alpha:g}/{a.ci_family})")
        for e in summary["effect_planted"]:
            if e["cell"] == "all cells" or not e["n"]:
                continue
            pb, pc = e["b"] / e["n"], e["c"] / e["n"]
            row = dict(cell=e["cell"], level=e["level"], p_worse=pb, p_better=pc,
                       power={n: projected_power(pb, pc, n, thr) for n in (16, 32, 64, 128, 256)})
            proj.append(row)
            print(f"  {e['cell']:28s} {e['level']:9s} worse {pb:.3f} better {pc:.3f}: " +
                  ", ".join(f"n={n} {v:.2f}" for n, v in row["power"].items()))
        summary["projected_power_planted"] = proj
    summary["seeds"] = results
    path = os.path.join(a.out, f"results_{'_'.join(a.arm_list)}.json")
    with open(path, "w") as f:
        json.dump(summary, f, indent=1, default=str)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
