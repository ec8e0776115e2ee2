"""The reach map: how tall a step each crawl steps down, on the README's narrow scenario spread and on a wide one.

    python -m experiments.reach_map --out DIR --impl warp --instances 1024                 # GPU: the full map
    python -m experiments.reach_map --out DIR --impl warp --instances 1024 --spread wide --preset paper reach
    python -m experiments.reach_map --out DIR --impl jax --instances 1 --heights 0.16 --duration 2 \\
        --variants default --spread narrow                                                    # CPU check

For every *variant* (a crawl: :data:`VARIANTS`, ``--custom``), *spread* and height (default 14-30 cm in 2 cm
steps) it runs ``--instances`` randomised step-downs of ``--duration`` seconds and reports

* per height: completed and clean (``hyqjax.studies.stepdown_outcome``) with Wilson 95% intervals
  (``statistics.success_curve``), the share of every failure reason, the counts of ``diverged`` (simulator
  blow-ups) and ``terminated`` (runs that fell and were ended at their failure tick) instances, and
  ``by_factor``: the outcome shares per third of the spread's range of start distance, friction and payload;
* ``h90``: the tallest height with >= 90% completed, every height below it too (point estimates), and
  ``h90_wilson``: the same with the Wilson lower bound >= 0.90 (``statistics.h95_wilson`` at 0.90);
* ``h85_clean`` and ``h85_clean_wilson``: the same for >= 85% clean.

Spreads (``--spread``): ``narrow`` is the README's (friction 0.7-1.0, payload 0-10 kg, start 0-4 cm before the
edge, +-3 cm lateral, +-0.05 rad yaw); ``wide`` is the tuner's held-out one (friction 0.4-1.0, payload 0-15 kg,
start 0-15 cm, +-5 cm lateral, +-0.1 rad yaw; ``hyqjax.studies.tune.evaluate.RANGES``). Every variant of a
(spread, height) cell runs the same instances (common random numbers) drawn from ``--seed`` (4242 by default: no
part of the tuner saw it; it trained on seeds 0-2 and was evaluated on 7777).

Variants: ``paper_off`` (the no-reflex baseline), ``default`` (``CrawlParams.make()``), ``remedy`` (``hyqjax
stepdown --remedy``: shin remedy, trunk at 80% of the feet plane), ``start`` (the tuner's start point: Table I and
the shin remedy at 30%), ``tuned`` (the parameters a tuning study selected, from ``--tuned`` results.json and
``--tuned-method``), and options to push the reach (``hyqjax.crawl.params``; defaults off): ``remedy_fwd_0.10``
(the forward search saturating 10 cm ahead), ``remedy_lower_0.05`` (the trunk 5 cm lower while a step down is under
way), ``adaptive`` (the shin remedy with the trunk at 30% of the feet plane, 80% while a step down is under way),
``remedy_all`` (the three together), ``remedy_probe`` (a probing step for the edge, ``hyqjax.crawl.edge``, and the
trunk at 30% of the feet plane until the front hips pass it) and ``remedy_probe2`` (the same with the trunk 1 cm
lower until then). ``--custom NAME:field=value,...`` adds any ``CrawlParams.make`` setting.

Runs in chunks of ``--chunk`` instances (one compiled program: the last chunk is padded), each written to
``DIR/chunks/NNNNN.npz`` as it finishes; the same command resumes after a kill or a time limit (a directory of
another configuration is refused). Writes ``DIR/reach_map.json`` and ``DIR/reach_map.png``.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import sys
import time

import numpy as np

from hyqjax.cli.common import add_devices_argument, apply_devices
from hyqjax.crawl import presets

HEIGHTS = tuple(round(0.14 + 0.02 * i, 2) for i in range(9))
SPREADS = {
    "narrow": dict(friction=(0.7, 1.0), payload=(0.0, 10.0), start_distance=(0.0, 0.04), lateral=(-0.03, 0.03),
                   yaw=(-0.05, 0.05)),
    "wide": dict(friction=(0.4, 1.0), payload=(0.0, 15.0), start_distance=(0.0, 0.15), lateral=(-0.05, 0.05),
                 yaw=(-0.1, 0.1)),
}
#: name -> (CrawlParams.make overrides, description): the hand-set presets (``hyqjax.crawl.presets``) and ``tuned``,
#: built from a tuning study's results.json.
VARIANTS = {**presets.HAND_SET, "tuned": (None, "the tuning study's selected parameters (--tuned, --tuned-method)")}
DEFAULT_VARIANTS = ("paper_off", "default", "remedy", "start", "tuned", "remedy_fwd_0.10", "remedy_lower_0.05",
                    "adaptive", "remedy_all")
DEFAULT_TUNED = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "results",
                             "tune_remedy_h100", "results.json")
#: Levels of the reach: (key, outcome column, target rate).
REACH_LEVELS = (("h90", "completed", 0.90), ("h85_clean", "clean", 0.85))


class UsageError(Exception):
    """A bad option: one line naming it and its allowed values."""


def parse_custom(text: str) -> tuple[str, dict]:
    """``NAME:field=value,...`` -> (NAME, overrides of ``CrawlParams.make``: :func:`hyqjax.crawl.params.parse_settings`)."""
    from hyqjax.crawl.params import parse_settings

    name, sep, body = text.partition(":")
    if not sep or not name:
        raise UsageError(f"--custom {text!r}: expected NAME:field=value,...")
    try:
        return name, parse_settings(body, f"--custom {name}")
    except ValueError as e:
        raise UsageError(str(e)) from None


def tuned_params(path: str, method: str, option: str = "", settings: dict | None = None):
    """The ``CrawlParams`` a tuning study (``hyqjax tune``) selected: ``method``'s ``theta`` on the study's
    ``ParamSpace`` and start point (:func:`hyqjax.studies.tune.tuned.crawl_params`; both layouts, ``method`` a
    method, ``cma_es``, or a run, ``cma_es/shared``), over ``CrawlParams.make`` ``settings`` of fields the run did
    not tune; a problem is one line starting with ``option``."""
    from hyqjax.studies.tune import tuned

    try:
        return tuned.crawl_params(path, method, **(settings or {}))
    except ValueError as e:
        raise UsageError(f"{option or f'--tuned-method {method!r}'}: {e}") from None


def parse_tuned_run(text: str) -> tuple[str, tuple[str, str, dict]]:
    """``NAME:PATH:METHOD[:field=value,...]`` of ``--tuned-run`` -> ``(NAME, (PATH, METHOD, settings))``: the
    optional settings are ``CrawlParams.make`` settings under the tuned values (fields the run did not tune)."""
    parts = text.split(":", 3)
    if len(parts) not in (3, 4) or not all(parts) or parts[0] in VARIANTS:
        raise UsageError(f"--tuned-run {text!r}: must be NAME:PATH:METHOD[:field=value,...] with a new variant name")
    from hyqjax.crawl.params import parse_settings

    try:
        settings = parse_settings(parts[3], f"--tuned-run {parts[0]}") if len(parts) == 4 else {}
    except ValueError as e:
        raise UsageError(str(e)) from None
    return parts[0], (parts[1], parts[2], settings)


def check_presets(names) -> list[str]:
    """The crawl presets of ``--preset`` (one line naming the known ones for an unknown or bounding preset)."""
    from hyqjax import presets as registry

    for n in names:
        try:
            registry.check_kind(n, "crawl")
        except ValueError as e:
            raise UsageError(str(e)) from None
    if len(set(names)) != len(names):
        raise UsageError("--preset: a preset is named twice")
    return list(names)


def variant_params(names, custom: dict, tuned_path: str, tuned_method: str, tuned_runs: dict | None = None,
                   preset_names=()) -> dict:
    """Crawl parameters of every variant (validated before anything compiles); ``tuned_runs`` maps further variant
    names to a tuning study's ``(results.json, method)``; ``preset_names`` are registry presets
    (:mod:`hyqjax.presets`; a per-leg one gives a per-leg set)."""
    from hyqjax import presets as registry
    from hyqjax.core.params import ParameterError
    from hyqjax.crawl import controller as crawl

    tuned_runs = tuned_runs or {}
    out = {}
    for name in names:
        try:
            if name in preset_names:
                out[name] = registry.load(name)
            elif name in tuned_runs:
                path, method, settings = tuned_runs[name]
                out[name] = tuned_params(path, method, option=f"--tuned-run {name}", settings=settings)
            elif name == "tuned":
                out[name] = tuned_params(tuned_path, tuned_method)
            else:
                out[name] = crawl.CrawlParams.make(**(custom[name] if name in custom else VARIANTS[name][0]))
        except (ParameterError, ValueError, TypeError) as e:
            raise UsageError(f"variant {name}: {e}") from None
    return out


def draws(spread: str, heights, instances: int, seed: int):
    """Per (height, draw) the randomised inputs of ``spread`` (``stepdown.make_scenarios``' draws: every height gets
    the same ``instances`` draws of ``seed``), as a table of numpy columns."""
    from hyqjax.studies import stepdown

    _, table = stepdown.make_scenarios(heights, [True], instances, seed, **SPREADS[spread])
    return table


def build_rows(variants, spreads, heights, instances: int, seed: int) -> dict[str, np.ndarray]:
    """Every instance of the map in run order (variant-major within a spread), as numpy columns."""
    cols: dict[str, list] = {}
    for spread in spreads:
        t = draws(spread, heights, instances, seed)
        for v in variants:
            n = len(t["height"])
            for k, x in (("variant", np.full(n, v)), ("spread", np.full(n, spread)), *t.items()):
                cols.setdefault(k, []).append(np.asarray(x))
    return {k: np.concatenate(v) for k, v in cols.items()}


def row_keys(table: dict, idx) -> list[tuple]:
    """The step-down of each of rows ``idx`` of a map's rows (reach_instances.npz's columns): ``(spread, height,
    instance)``, the same for every variant that ran it (common random numbers)."""
    return list(zip(table["spread"][idx], np.round(table["height"][idx], 6), table["instance"][idx]))


def write_map(out_dir: str, columns: dict, record: dict) -> None:
    """A finished map: ``columns`` (each row's scenario and, as ``out_*``, its outcome) to ``reach_instances.npz``,
    then ``record`` to ``reach_map.json``, whose presence says the map is whole; each written whole or not at all."""
    from hyqjax.io import atomic

    atomic.atomic_write(os.path.join(out_dir, "reach_instances.npz"),
                        lambda f: np.savez_compressed(f, **{k: np.asarray(v) for k, v in columns.items()}))
    atomic.write_json(os.path.join(out_dir, "reach_map.json"), record)


def scenario_of(rows: dict, idx: np.ndarray, params: dict):
    """The ``stepdown.Scenario`` of rows ``idx`` with each row's variant parameters (float32 leaves)."""
    import jax
    import jax.numpy as jnp

    from hyqjax.sim import model as hmodel
    from hyqjax.sim import rollout as sim
    from hyqjax.studies import stepdown

    b = len(idx)
    terrain = hmodel.InstanceTerrain.make(rows["height"][idx], rows["friction"][idx], rows["payload_mass"][idx],
                                          rows["payload_com"][idx])
    names = list(params)
    which = np.asarray([names.index(v) for v in rows["variant"][idx]])
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *[params[k] for k in names])
    bparams = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[which], stacked)
    bparams = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, bparams)
    push = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,) + x.shape), sim.Push.none())
    return stepdown.Scenario(terrain=terrain, start_distance=jnp.asarray(rows["start_distance"][idx], jnp.float32),
                             lateral_offset=jnp.asarray(rows["lateral_offset"][idx], jnp.float32),
                             yaw=jnp.asarray(rows["yaw"][idx], jnp.float32), params=bparams, push=push)


#: Largest automatic chunk (instances per compiled batch) on a GPU (MuJoCo Warp's closed loop peaks at about 65k on
#: an H100, benchmarks/RESULTS.md) and on a CPU.
MAX_CHUNK_GPU = 65536
MAX_CHUNK_CPU = 32


def balanced_chunk(n: int, largest: int) -> int:
    """The smallest chunk that runs ``n`` instances in as few chunks of at most ``largest`` as possible (so the last
    chunk's padding stays below one instance per chunk)."""
    k = -(-n // largest)
    return -(-n // k)


#: Outcome columns a chunk file keeps.
KEEP = ("completed", "clean", "diverged", "terminated", "terminated_tick", "diverged_tick", "feet_not_down",
        "no_progress", "lost_foothold", "joint_past_range", "tilt", "trunk_strike", "shin_strike", "reflex_failure",
        "contact_overflow", "peak_pitch", "peak_roll", "progress")


def run_chunks(rows, params, cfg, chunk: int, out_dir: str, config_hash: str, log=print) -> dict[str, np.ndarray]:
    """Run every row in chunks of ``chunk`` (the last one padded with copies of its first row); a chunk already in
    ``out_dir/chunks`` with this configuration's hash is read instead. Returns the outcome columns of all rows."""
    import jax

    from hyqjax.io import atomic
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    n = len(rows["height"])
    os.makedirs(os.path.join(out_dir, "chunks"), exist_ok=True)
    ro = stepdown.make_stepdown_rollout(cfg)
    parts = []
    n_chunks = -(-n // chunk)
    t_start = time.time()
    for c in range(n_chunks):
        path = os.path.join(out_dir, "chunks", f"{c:05d}.npz")
        lo, hi = c * chunk, min(n, (c + 1) * chunk)
        if os.path.exists(path):
            try:
                with np.load(path) as f:
                    if str(f["config_hash"]) == config_hash and int(f["lo"]) == lo and int(f["hi"]) == hi:
                        parts.append({k: f[k] for k in KEEP})
                        continue
            except (OSError, ValueError, KeyError):
                pass
            log(f"chunk {c}: {path} does not belong to this run or is damaged: recomputed")
        idx = np.arange(lo, hi)
        idx = np.concatenate([idx, np.full(chunk - len(idx), lo)])  # one program for every chunk
        t0 = time.time()
        out, _ = ro.run(scenario_of(rows, idx, params))
        cols = so.to_columns(jax.block_until_ready(out))
        part = {k: np.asarray(cols[k])[: hi - lo] for k in KEEP}
        atomic.atomic_write(path, lambda f, part=part: np.savez(f, config_hash=config_hash, lo=lo, hi=hi, **part))
        parts.append(part)
        done = hi
        log(f"chunk {c + 1}/{n_chunks}: {hi - lo} instances in {time.time() - t0:.1f} s "
            f"({done}/{n} done, {time.time() - t_start:.0f} s)")
    return {k: np.concatenate([p[k] for p in parts]) for k in KEEP}


def reach(curve: list[dict], target: float) -> tuple[float | None, float | None]:
    """(tallest height with rate >= target at it and every lower height, the same with the Wilson lower bound)."""
    from hyqjax.studies import statistics

    best = None
    for c in sorted(curve, key=lambda c: c["height"]):
        if not c["rate"] >= target:
            break
        best = c["height"]
    return best, statistics.h95_wilson(curve, target)


#: Scenario inputs whose share of each outcome is reported per third of the spread's range (``by_factor``), and the
#: ``SPREADS`` key of each range.
FACTORS = (("start_distance", "start_distance"), ("friction", "friction"), ("payload_mass", "payload"))
#: Outcome columns reported per factor bin (as shares of the bin's runs).
FACTOR_OUTCOMES = ("completed", "clean", "terminated", "lost_foothold", "joint_past_range", "tilt", "shin_strike")


def bin_index(x, edges) -> np.ndarray:
    """The bin of every value of ``x`` among ``edges`` (``[lo, hi)``, the last one closed, values outside in the end
    bins), the edges compared in the inputs' own precision (float32 0.15 is above float64 0.15): no run is
    dropped."""
    x = np.asarray(x)
    return np.searchsorted(np.asarray(edges[1:-1]).astype(x.dtype), x, side="right")


def factor_shares(rows: dict, out: dict, mask: np.ndarray, spread: str, bins: int = 3) -> dict[str, list[dict]]:
    """Per factor of :data:`FACTORS`: the runs of ``mask`` split into ``bins`` equal parts of the spread's range of that
    input (``[lo, hi)``, the last one closed), each with its range, its count ``n`` and the share of each of
    :data:`FACTOR_OUTCOMES` (None for an empty part). Says how start distance, friction and payload contribute to a
    cell's failures."""
    res = {}
    for col, key in FACTORS:
        lo, hi = SPREADS[spread][key]
        x = np.asarray(rows[col])
        edges = np.linspace(lo, hi, bins + 1)
        part = bin_index(x, edges)
        parts = []
        for i in range(bins):
            inside = mask & (part == i)
            n = int(inside.sum())
            parts.append(dict(range=[float(edges[i]), float(edges[i + 1])], n=n,
                              **{k: (float(out[k][inside].mean()) if n else None) for k in FACTOR_OUTCOMES}))
        res[col] = parts
    return res


def summarise(rows: dict, out: dict, variants, spreads) -> list[dict]:
    """One entry per (spread, variant): per-height curves of both levels, reasons, counts, the shares per third of
    each scenario input's range (:func:`factor_shares`) and the reach."""
    from hyqjax.studies import statistics
    from hyqjax.studies import stepdown_outcome as so

    cells = []
    for spread in spreads:
        for v in variants:
            m = (rows["spread"] == spread) & (rows["variant"] == v)
            if not m.any():
                continue
            h = rows["height"][m]
            curves = {lv: statistics.success_curve(h, out[lv][m]) for lv in ("completed", "clean")}
            per_height = []
            for cc, cl in zip(curves["completed"], curves["clean"]):
                hm = m & (rows["height"] == cc["height"])
                per_height.append(dict(
                    height=cc["height"], n=cc["n"], completed=cc["successes"], completed_rate=cc["rate"],
                    completed_ci95=cc["ci95"], clean=cl["successes"], clean_rate=cl["rate"], clean_ci95=cl["ci95"],
                    diverged=int(out["diverged"][hm].sum()), terminated=int(out["terminated"][hm].sum()),
                    reasons={k: float(out[k][hm].mean()) for k in so.FAILURE_REASONS},
                    by_factor=factor_shares(rows, out, hm, spread)))
            entry = dict(spread=spread, variant=v, n=int(m.sum()), diverged=int(out["diverged"][m].sum()),
                         terminated=int(out["terminated"][m].sum()), per_height=per_height)
            for key, level, target in REACH_LEVELS:
                point, wilson = reach(curves[level], target)
                entry[key], entry[f"{key}_wilson"] = point, wilson
                at = next((c for c in per_height if c["height"] == point), None)
                entry[f"{key}_ci95"] = None if at is None else at[f"{level}_ci95"]
            cells.append(entry)
    return cells


def plot(cells, path: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spreads = list(dict.fromkeys(c["spread"] for c in cells))
    fig, axes = plt.subplots(len(spreads), 2, figsize=(13, 4.2 * len(spreads)), squeeze=False)
    for r, spread in enumerate(spreads):
        for col, (level, target) in enumerate((("completed", 0.90), ("clean", 0.85))):
            ax = axes[r, col]
            for c in (c for c in cells if c["spread"] == spread):
                h = np.array([p["height"] for p in c["per_height"]]) * 100
                y = np.array([p[f"{level}_rate"] for p in c["per_height"]])
                lo = y - np.array([p[f"{level}_ci95"][0] for p in c["per_height"]])
                hi = np.array([p[f"{level}_ci95"][1] for p in c["per_height"]]) - y
                ax.errorbar(h, y, yerr=[lo, hi], marker="o", ms=3, capsize=2, label=c["variant"])
            ax.axhline(target, color="k", lw=0.8, ls=":")
            ax.axvline(24, color="tab:red", lw=0.8, ls="--")
            n = min(p["n"] for c in cells for p in c["per_height"])
            ax.set(xlabel="platform height [cm]", ylabel=f"{level} rate", ylim=(-0.02, 1.02),
                   title=f"{spread}: {level} (Wilson 95%, n >= {n}; dashed: HyQ's 24 cm)")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    from hyqjax.io.phases import process_age

    t_process = time.perf_counter() - (process_age() or 0.0)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/reach_map")
    ap.add_argument("--impl", default="auto", help="simulator: auto | jax | warp | c (auto: warp on a CUDA GPU with "
                    "warp-lang, else c without an accelerator, else jax)")
    ap.add_argument("--instances", type=int, default=1024, help="instances per (variant, spread, height) cell")
    ap.add_argument("--heights", type=float, nargs="+", default=list(HEIGHTS), help="platform heights (m)")
    ap.add_argument("--spread", nargs="+", default=["wide", "narrow"], help="wide | narrow (one or both)")
    ap.add_argument("--variants", nargs="+", default=None,
                    help=f"named variants ({', '.join(VARIANTS)}) and the names of --custom ones (default: "
                         f"{' '.join(DEFAULT_VARIANTS)}; with --preset: the presets only)")
    ap.add_argument("--preset", nargs="+", default=[], metavar="NAME",
                    help="crawl presets of hyqjax.presets (`hyqjax presets --kind crawl`) run as variants of their "
                         "own name, e.g. --preset paper reach tuned_per_leg")
    ap.add_argument("--custom", action="append", default=[], metavar="NAME:field=value,...",
                    help="a variant of CrawlParams.make settings (repeatable)")
    ap.add_argument("--tuned", default=DEFAULT_TUNED, help="a tuning study's results.json (variant 'tuned')")
    ap.add_argument("--tuned-method", default="gradient", help="which of its methods (e.g. gradient)")
    ap.add_argument("--tuned-run", action="append", default=[], metavar="NAME:PATH:METHOD[:field=value,...]",
                    help="a further variant NAME: METHOD's parameters from the tuning results.json PATH (METHOD@10min: "
                         "the iterate it held at its 10-minute checkpoint), optionally with CrawlParams.make settings "
                         "of fields it did not tune (repeatable)")
    ap.add_argument("--seed", type=int, default=4242)
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per run")
    ap.add_argument("--chunk", type=int, default=0,
                    help="instances per compiled batch (0: as few chunks of at most 65536 on a GPU, 32 on a CPU)")
    ap.add_argument("--no-terminate", action="store_true", help="run fallen instances to the end (no episode end)")
    add_devices_argument(ap)
    args = ap.parse_args(argv)
    try:
        config = check(args)
        try:
            apply_devices(args)
        except ValueError as e:
            raise UsageError(str(e)) from None
    except UsageError as e:
        print(f"reach_map: {e}", file=sys.stderr)
        return 2
    import jax

    from hyqjax.sim import devices as hdevices

    from hyqjax.io import atomic
    from hyqjax.studies import stepdown

    params = config.pop("_params")
    # A map resumes only on the same kind of device and implementation (float32 results depend on the layout).
    devs = hdevices.resolve()
    config.update(device=devs[0].device_kind,
                  impl_resolved=stepdown.setup(stepdown.StepdownConfig(impl=args.impl)).impl)
    if len(devs) > 1 and config["impl_resolved"] == "warp":  # Warp's rows depend on the per-device slices
        config.update(devices=len(devs))
    os.makedirs(args.out, exist_ok=True)
    config_hash = hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()
    cfg_path = os.path.join(args.out, "config.json")
    if os.path.exists(cfg_path):
        with open(cfg_path) as f:
            old = json.load(f)
        if old.get("config_hash") != config_hash:
            print(f"reach_map: --out {args.out} holds a map of another configuration: use another --out",
                  file=sys.stderr)
            return 2
    else:
        atomic.write_json(cfg_path, dict(config=config, config_hash=config_hash))
    gpu = devs[0].platform == "gpu"
    rows = build_rows(args.variants, args.spread, args.heights, args.instances, args.seed)
    n = len(rows["height"])
    chunk = args.chunk or balanced_chunk(n, (MAX_CHUNK_GPU if gpu else MAX_CHUNK_CPU) * len(devs))
    cfg = stepdown.StepdownConfig(duration=args.duration, impl=args.impl, terminate=not args.no_terminate)
    print(f"{n} instances x {args.duration:g} s in chunks of {min(chunk, n)} on {devs[0].device_kind}, "
          f"{hdevices.describe(devs)} (impl {stepdown.setup(cfg).impl})", flush=True)
    t0 = time.time()
    out = run_chunks(rows, params, cfg, min(chunk, n), args.out, config_hash,
                     log=lambda s: print(s, flush=True))
    wall = time.time() - t0
    cells = summarise(rows, out, args.variants, args.spread)
    fig = plot(cells, os.path.join(args.out, "reach_map.png"))
    write_map(args.out, {**rows, **{f"out_{k}": v for k, v in out.items()}}, dict(
        provenance=atomic.provenance(seed=args.seed), config=config, device=devs[0].device_kind, devices=len(devs),
        impl=stepdown.setup(cfg).impl, n_instances=n, wall_s=wall, chunk=min(chunk, n),
        physics_steps=int(n * round(args.duration / cfg.control_dt)), cells=cells, figure=os.path.basename(fig)))
    print(format_cells(cells))
    print(f"wall {time.perf_counter() - t_process:.1f} s in all (since the process started): the runs {wall:.1f} s "
          f"(compile included); {args.out}/reach_map.json, {fig}")
    return 0


def check(args) -> dict:
    """Validate every option before anything compiles; returns the configuration (hashed for resuming)."""
    from hyqjax.sim import backend
    from hyqjax.sim import model as hmodel
    from hyqjax.studies import stepdown

    try:
        backend.validate_impl(args.impl, stepdown.SUPPORTED_IMPLS)
    except ValueError:
        raise UsageError(f"--impl {args.impl!r}: must be one of auto, {', '.join(stepdown.SUPPORTED_IMPLS)}") from None
    if not 1 <= args.instances <= 1_000_000:
        raise UsageError(f"--instances {args.instances}: must be in [1, 1000000]")
    bad = [h for h in args.heights if not 0.0 <= h <= hmodel.MAX_PLATFORM_HEIGHT]
    if bad:
        raise UsageError(f"--heights {bad[0]}: must be in [0, {hmodel.MAX_PLATFORM_HEIGHT}] m")
    bad = [s for s in args.spread if s not in SPREADS]
    if bad:
        raise UsageError(f"--spread {bad[0]!r}: must be one of {', '.join(SPREADS)}")
    if not 0.1 <= args.duration <= 120.0:
        raise UsageError(f"--duration {args.duration}: must be in [0.1, 120] s")
    if args.chunk < 0:
        raise UsageError(f"--chunk {args.chunk}: must be >= 0 (0: automatic)")
    custom = dict(parse_custom(c) for c in args.custom)
    tuned_runs = dict(parse_tuned_run(t) for t in args.tuned_run)
    preset_names = check_presets(args.preset)
    if args.variants is None:
        args.variants = list(preset_names) if preset_names else list(DEFAULT_VARIANTS)
    else:
        args.variants = list(args.variants) + [n for n in preset_names if n not in args.variants]
    clash = sorted(set(preset_names) & (set(custom) | set(tuned_runs)))
    if clash:
        raise UsageError(f"--preset {clash[0]}: also a --custom or --tuned-run name; give each variant one name")
    both = sorted(set(custom) & set(tuned_runs))
    if both:
        raise UsageError(f"--tuned-run {both[0]!r}: also a --custom name; give each variant one name")
    unknown = [v for v in args.variants if v not in VARIANTS and v not in custom and v not in tuned_runs
               and v not in preset_names]
    if unknown:
        raise UsageError(f"--variants {unknown[0]!r}: not one of {', '.join(VARIANTS)} nor a --custom or "
                         "--tuned-run name")
    if len(set(args.variants)) != len(args.variants):
        raise UsageError("--variants: a variant is named twice")
    params = variant_params(args.variants, custom, args.tuned, args.tuned_method, tuned_runs, preset_names)
    from hyqjax.crawl import scheduled

    described = {}
    for v in args.variants:
        p = scheduled.base_of(params[v])
        described[v] = {f.name: np.asarray(getattr(p, f.name)).tolist() for f in dataclasses.fields(p)
                        if f.name not in ("gains", "reflex")}
        described[v]["reflex"] = {f.name: np.asarray(getattr(p.reflex, f.name)).tolist()
                                  for f in dataclasses.fields(p.reflex)}
        if params[v] is not p:  # a scheduled set: its per-leg (and conditioned) values
            described[v]["scheduled"] = params[v].describe()
    # Variants are stacked into one batch: with a per-leg set among them, every variant becomes one (the same
    # per-leg fields; a CrawlParams's rows all equal, which runs bit for bit as itself).
    try:
        params = scheduled.common_structure(params)
    except ValueError as e:
        raise UsageError(f"--variants: {e}") from None
    from hyqjax.studies.stepdown import START_POSE

    return dict(start_pose=START_POSE, impl=args.impl, instances=args.instances,
                heights=[float(h) for h in args.heights], spreads={s: SPREADS[s] for s in args.spread}, variants=args.variants, params=described,
                seed=args.seed, duration=args.duration, terminate=not args.no_terminate,
                tuned=os.path.abspath(args.tuned) if "tuned" in args.variants else None,
                tuned_method=args.tuned_method if "tuned" in args.variants else None, custom=args.custom,
                tuned_runs=args.tuned_run,
                _params=params)


def format_cells(cells) -> str:
    lines = []
    for c in cells:
        def h(x):
            return "-" if x is None else f"{100 * x:.0f} cm"
        lines.append(f"{c['spread']:>6} {c['variant']:>18}: h90 {h(c['h90'])} (Wilson {h(c['h90_wilson'])}), "
                     f"h85-clean {h(c['h85_clean'])} (Wilson {h(c['h85_clean_wilson'])}), "
                     f"{c['terminated']} terminated, {c['diverged']} diverged of {c['n']}")
        for p in c["per_height"]:
            lines.append(f"{'':>27}{100 * p['height']:4.0f} cm  completed {p['completed_rate']:6.1%} "
                         f"[{p['completed_ci95'][0]:.3f}, {p['completed_ci95'][1]:.3f}]  clean {p['clean_rate']:6.1%} "
                         f"[{p['clean_ci95'][0]:.3f}, {p['clean_ci95'][1]:.3f}]  fell {p['terminated']}  "
                         f"div {p['diverged']}")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
