"""Clean success of the step-down against the start distance, and what happens at the far starts.

    python -m experiments.start_distance_profile --out DIR                            # the profile (seconds)
    python -m experiments.start_distance_profile --out DIR --bin-width 0.02 --max-height 0.26 \\
        docs/results/tune_default_repeats_leading_foot_h200/confirm_31415/reach_instances.npz
    python -m experiments.start_distance_profile --mode mechanism --out DIR         # C MuJoCo, a CPU half-minute

``--mode profile`` (the default) reads a stored reach map's per-instance outcomes (``reach_instances.npz``, written
by ``experiments.tune_default_repeats``: one row per run with its variant, height, start distance, ... and its
``out_*`` outcome columns), pools the heights in ``[--min-height, --max-height]`` and splits the runs of every
variant into bins of ``--bin-width`` of the start distance (from 0 to the top of the map's spread, read from its
``config.json``; ``[lo, hi)``, the last bin closed, the edges compared in the inputs' precision as
``experiments.reach_map.factor_shares`` does), and with ``--split-yaw N`` every bin into N equal bins of the
spread's heading range. Per variant and bin: ``n``, clean runs and rate with its Wilson 95% interval
(``hyqjax.studies.statistics.wilson_interval``), the shares of shin strikes and of completed runs. Writes
``DIR/profile.json``, ``DIR/profile.md`` (one row per bin, one column pair per variant) and ``DIR/profile.png``
(clean rate against start distance per variant, Wilson band; shaded: the starts of the tuner's ``train`` spread,
0-10 cm, which ``experiments.tune_study`` trains on by default; ``hyqjax tune`` trains on the wide spread's 0-15 cm).

``--mode mechanism`` runs the step-down of one crawl preset (``--preset``, ``reach`` by default; or a tuning
study's set, ``--tuned-run NAME:PATH:METHOD``) on C MuJoCo (about 30 s on 2 cores for the default 30 runs) at each
of ``--heights`` for start distances ``--starts FROM TO STEP`` (8-15 cm in 0.5 cm steps by default) with heading
``--yaw`` (0), no lateral offset, friction ``--friction`` (0.7) and payload ``--payload`` (0 kg); it records every
control tick (2 ms) the feet, the joint positions, the shins' contact forces and the crawl's swing, touchdown,
limit and edge-probe state, and reports per run: clean, shin strike, the legs whose shin force passed the strike
threshold (100 N), when and with which peak force, for each FRONT foot its swings up to the first strike (lift-off
and end tick, how each ended: touchdown, limit, probe; the foot's x past the edge, the edge at x = 0, and its height
above the platform's top at the end) and the tick its centre first crossed the edge, and each front shin's smallest
distance from the platform up to the first strike (MuJoCo's ``mj_geomDistance`` on the recorded poses), when, and
where the front feet stood then. Writes ``DIR/mechanism.json`` and ``DIR/mechanism.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from hyqjax.cli.common import HelpFormatter, UsageError

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DEFAULT_NPZ = os.path.join("docs", "results", "tune_default_repeats_leading_foot_h200", "confirm_31415",
                           "reach_instances.npz")
#: Columns a ``reach_instances.npz`` must have for the profile.
REQUIRED = ("variant", "height", "start_distance", "out_clean", "out_shin_strike", "out_completed")
#: The start distances (m) of the tuner's ``train`` spread (``hyqjax.studies.tune.forward.TRAIN_RANGES``), the
#: default of ``experiments.tune_study``; ``hyqjax tune`` trains on the wide spread (0-15 cm) by default.
TRAIN_SPREAD_STARTS = (0.0, 0.10)
LEGS = ("LF", "RF", "LH", "RH")


def parse(argv=None) -> argparse.Namespace:
    from hyqjax.cli.app import Parser

    ap = Parser(prog="python -m experiments.start_distance_profile", description=__doc__,
                                 formatter_class=HelpFormatter)
    ap.add_argument("instances", nargs="?", default=DEFAULT_NPZ,
                    help="profile: a reach map's reach_instances.npz (its config.json beside it gives the spread)")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--mode", default="profile", help="profile | mechanism")
    ap.add_argument("--bin-width", type=float, default=0.01, help="profile: start-distance bin width (m)")
    ap.add_argument("--min-height", type=float, default=0.0, help="profile: lowest height pooled (m)")
    ap.add_argument("--max-height", type=float, default=0.26, help="profile: tallest height pooled (m)")
    ap.add_argument("--variants", nargs="+", default=None, help="profile: the map's variants shown (default all)")
    ap.add_argument("--split-yaw", type=int, default=0, metavar="N",
                    help="profile: also split every bin into N equal bins of the spread's heading range (0: no split)")
    ap.add_argument("--preset", default="reach", help="mechanism: the crawl preset")
    ap.add_argument("--tuned-run", default=None, metavar="NAME:PATH:METHOD",
                    help="mechanism: run a tuning study's set instead of --preset (results.json and method, as "
                         "experiments.reach_map's --tuned-run, e.g. run_1:docs/results/tune_default_repeats_leading_"
                         "foot_h200/run_1/results.json:cma_es/per_leg)")
    ap.add_argument("--heights", nargs="+", type=float, default=[0.18, 0.23], help="mechanism: platform heights (m)")
    ap.add_argument("--starts", nargs=3, type=float, default=[0.08, 0.15, 0.005], metavar=("FROM", "TO", "STEP"),
                    help="mechanism: start distances (m), FROM to TO inclusive in steps of STEP")
    ap.add_argument("--friction", type=float, default=0.7, help="mechanism: friction coefficient")
    ap.add_argument("--yaw", type=float, default=0.0, help="mechanism: heading (rad; the leading-foot start pose)")
    ap.add_argument("--payload", type=float, default=0.0, help="mechanism: payload mass (kg, at the trunk's centre)")
    ap.add_argument("--duration", type=float, default=24.0, help="mechanism: simulated seconds per run")
    return ap.parse_args(argv)


def check(a: argparse.Namespace) -> None:
    """Refuse bad input with one :class:`UsageError` line, before anything is simulated or written."""
    if a.mode not in ("profile", "mechanism"):
        raise UsageError(f"--mode must be profile or mechanism, got {a.mode!r}")
    if a.mode == "profile":
        if a.instances == DEFAULT_NPZ and not os.path.isfile(a.instances):  # run from outside the repository
            a.instances = os.path.join(HERE, DEFAULT_NPZ)
        if not os.path.isfile(a.instances):
            raise UsageError(f"instances: no such file {a.instances!r} (a reach map's reach_instances.npz)")
        if not (np.isfinite(a.bin_width) and 0.001 <= a.bin_width <= 0.15):
            raise UsageError(f"--bin-width must be in [0.001, 0.15] m, got {a.bin_width}")
        if a.split_yaw not in (0, *range(2, 9)):
            raise UsageError(f"--split-yaw must be 0 (no split) or 2-8 heading bins, got {a.split_yaw}")
        if not (0.0 <= a.min_height <= a.max_height <= 0.4):
            raise UsageError(f"--min-height and --max-height must satisfy 0 <= MIN <= MAX <= 0.4 (m), got "
                             f"{a.min_height} {a.max_height}")
        return
    from hyqjax import presets

    presets.check_kind(a.preset, "crawl", "--preset")  # a PresetError: one ValueError line
    a.variant, a.params = a.preset, None
    if a.tuned_run is not None:
        from experiments import reach_map

        try:
            name, (path, method, settings) = reach_map.parse_tuned_run(a.tuned_run)
            a.variant, a.params = name, reach_map.tuned_params(path, method, "--tuned-run", settings)
        except reach_map.UsageError as e:
            raise UsageError(str(e)) from None
    if any(not 0.0 < h <= 0.4 for h in a.heights):
        raise UsageError(f"--heights must be in (0, 0.4] m, got {a.heights}")
    lo, hi, step = a.starts
    if not (0.0 <= lo <= hi <= 1.0 and 0.001 <= step <= 0.5 and (hi - lo) / step <= 200):
        raise UsageError(f"--starts FROM TO STEP must satisfy 0 <= FROM <= TO <= 1 m, 0.001 <= STEP <= 0.5 m and at "
                         f"most 200 steps, got {lo} {hi} {step}")
    if not 0.1 <= a.friction <= 2.0:
        raise UsageError(f"--friction must be in [0.1, 2], got {a.friction}")
    if not -0.2 <= a.yaw <= 0.2:
        raise UsageError(f"--yaw must be in [-0.2, 0.2] rad, got {a.yaw}")
    if not 0.0 <= a.payload <= 20.0:
        raise UsageError(f"--payload must be in [0, 20] kg, got {a.payload}")
    if not 2.0 <= a.duration <= 60.0:
        raise UsageError(f"--duration must be in [2, 60] s, got {a.duration}")
    from hyqjax.studies import stepdown

    try:
        a.cfg = stepdown.StepdownConfig(duration=a.duration, impl="c", record_every=1)
    except ValueError as e:
        raise UsageError(f"--duration: {e}") from None
    from hyqjax.io import atomic

    atomic.check_writable_dir(a.out)  # a ValueError naming --out


# ----------------------------------------------------------------------------------------------------- profile


def load_instances(path: str) -> dict[str, np.ndarray]:
    """The columns of a ``reach_instances.npz``; a :class:`UsageError` naming the file for an unreadable one or one
    without :data:`REQUIRED`."""
    try:
        with np.load(path, allow_pickle=False) as f:
            cols = {k: f[k] for k in f.files}
    except (OSError, ValueError) as e:
        raise UsageError(f"instances: {path!r} is not a readable .npz ({type(e).__name__})") from None
    missing = [k for k in REQUIRED if k not in cols]
    if missing:
        raise UsageError(f"instances: {path!r} lacks the columns {', '.join(missing)} (a reach map's "
                         f"reach_instances.npz has {', '.join(REQUIRED)})")
    return cols


def spread_range(path: str, inst: dict, key: str = "start_distance") -> tuple[float, float]:
    """The range of the map's spread of ``key`` (``start_distance`` or ``yaw``): its ``config.json`` beside the npz (the
    spread of its rows), else 0 (the smallest heading) to the largest value."""
    cfg = os.path.join(os.path.dirname(path), "config.json")
    if os.path.isfile(cfg):
        with open(cfg, encoding="utf-8") as f:
            spreads = json.load(f).get("config", {}).get("spreads", {})
        names = set(np.asarray(inst["spread"]).tolist()) if "spread" in inst else set(spreads)
        ranges = {tuple(spreads[s][key]) for s in names if s in spreads and key in spreads[s]}
        if len(ranges) == 1:
            lo, hi = ranges.pop()
            return float(lo), float(hi)
    x = np.asarray(inst[key])
    return (0.0 if key == "start_distance" else float(np.min(x))), float(np.max(x))


def bin_edges(lo: float, hi: float, width: float) -> np.ndarray:
    """Edges from ``lo`` in steps of ``width``, the last one ``hi`` (a narrower last bin where ``width`` does not
    divide the range). Where it divides it, ``np.linspace`` (the edges of ``experiments.reach_map.factor_shares``)."""
    k = (hi - lo) / width
    if abs(k - round(k)) < 1e-6:
        return np.linspace(lo, hi, round(k) + 1)
    return np.append(lo + width * np.arange(int(np.floor(k)) + 1), hi)


def profile(inst: dict, edges: np.ndarray, min_height: float, max_height: float, variants=None,
            yaw_edges=None) -> list[dict]:
    """Per variant (map order) and start-distance bin of ``edges`` (and, with ``yaw_edges``, per heading bin within
    it: ``yaw_lo``, ``yaw_hi``): ``n``, clean runs, clean rate and its Wilson 95% interval, shin strike and completed
    shares, over the runs with ``min_height <= height <= max_height``."""
    from experiments.reach_map import bin_index
    from hyqjax.studies import statistics

    part = bin_index(inst["start_distance"], edges)
    h = np.asarray(inst["height"])
    in_h = (h >= min_height - 1e-9) & (h <= max_height + 1e-9)
    if yaw_edges is None:
        yaw_bins, ypart = [None], np.zeros(len(h), int)
    else:
        yaw_bins, ypart = list(range(len(yaw_edges) - 1)), bin_index(inst["yaw"], yaw_edges)
    names = list(dict.fromkeys(np.asarray(inst["variant"]).tolist()))
    rows = []
    for v in (variants or names):
        for i in range(len(edges) - 1):
            for j in yaw_bins:
                m = in_h & (inst["variant"] == v) & (part == i) & (ypart == (0 if j is None else j))
                n, k = int(m.sum()), int(inst["out_clean"][m].sum())
                ci = statistics.wilson_interval(k, n)
                row = dict(variant=v, lo=float(edges[i]), hi=float(edges[i + 1]))
                if j is not None:
                    row.update(yaw_lo=float(yaw_edges[j]), yaw_hi=float(yaw_edges[j + 1]))
                rows.append(dict(row, n=n, clean=k, clean_rate=(k / n if n else None),
                                 clean_ci95=([ci[0], ci[1]] if n else None),
                                 shin_strike=int(inst["out_shin_strike"][m].sum()),
                                 shin_strike_rate=(float(inst["out_shin_strike"][m].mean()) if n else None),
                                 completed_rate=(float(inst["out_completed"][m].mean()) if n else None)))
    return rows


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.0f}"


def profile_markdown(rows: list[dict], heights: list[float]) -> str:
    """One row per bin: the start distance (cm), ``n`` (per variant where they differ), then per variant its clean
    rate with the Wilson interval and its shin-strike share (%)."""
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    split = "yaw_lo" in rows[0]
    bins = sorted({(r["lo"], r["hi"], r.get("yaw_lo"), r.get("yaw_hi")) for r in rows})
    by = {(r["variant"], r["lo"], r.get("yaw_lo")): r for r in rows}
    same_n = all(len({by[(v, lo, ylo)]["n"] for v in variants}) == 1 for lo, _, ylo, _ in bins)
    head = (["start (cm)"] + (["heading (rad)"] if split else []) + (["n"] if same_n else [])
            + [c for v in variants for c in (f"`{v}` clean % [95%]", "shin %")])
    lines = [f"Heights pooled: {', '.join(f'{100 * x:g}' for x in heights)} cm.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for lo, hi, ylo, yhi in bins:
        cells = ([f"{100 * lo:.3g}-{100 * hi:.3g}"] + ([f"{ylo:+.3g} to {yhi:+.3g}"] if split else [])
                 + ([str(by[(variants[0], lo, ylo)]["n"])] if same_n else []))
        for v in variants:
            r = by[(v, lo, ylo)]
            ci = "" if r["clean_ci95"] is None else f" [{_pct(r['clean_ci95'][0])}, {_pct(r['clean_ci95'][1])}]"
            cells += [("" if same_n else f"n {r['n']}: ") + _pct(r["clean_rate"]) + ci, _pct(r["shin_strike_rate"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def profile_figure(rows: list[dict], path: str, title: str) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = list(dict.fromkeys(r["variant"] for r in rows))
    split = "yaw_lo" in rows[0]
    # one panel for every variant split by heading (a line per heading bin), else one panel (a line per variant)
    panels = variants if split else [None]
    fig, axes = plt.subplots(1, len(panels), figsize=(7.5 if not split else 4.0 * len(panels), 4.2), squeeze=False,
                             sharey=True)
    for ax, pv in zip(axes[0], panels):
        ax.axvspan(100 * TRAIN_SPREAD_STARTS[0], 100 * TRAIN_SPREAD_STARTS[1], color="0.9",
                   label="starts of the tuner's train spread")
        if split:
            lines = [(f"heading {ylo:+.3g} to {yhi:+.3g} rad", [r for r in rows if r["variant"] == pv
                                                                and r["yaw_lo"] == ylo and r["n"]])
                     for ylo, yhi in sorted({(r["yaw_lo"], r["yaw_hi"]) for r in rows})]
            ax.set_title(pv, fontsize=9)
        else:
            lines = [(v, [r for r in rows if r["variant"] == v and r["n"]]) for v in variants]
            ax.set_title(title, fontsize=9)
        for label, rr in lines:
            x = np.asarray([50 * (r["lo"] + r["hi"]) for r in rr])
            ax.plot(x, [r["clean_rate"] for r in rr], "o-", ms=3, label=label)
            ax.fill_between(x, [r["clean_ci95"][0] for r in rr], [r["clean_ci95"][1] for r in rr], alpha=0.15)
        ax.set_xlabel("start distance of the front feet before the edge (cm)", fontsize=8 if split else 10)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7 if split else 8, loc="lower left")
    axes[0, 0].set_ylabel("clean success (Wilson 95%)")
    if split:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def run_profile(a: argparse.Namespace) -> int:
    from hyqjax.io import atomic

    inst = load_instances(a.instances)
    names = list(dict.fromkeys(np.asarray(inst["variant"]).tolist()))
    if a.variants:
        bad = [v for v in a.variants if v not in names]
        if bad:
            raise UsageError(f"--variants must be among the map's variants {', '.join(names)}, got {', '.join(bad)}")
    h = np.asarray(inst["height"])
    heights = sorted({round(float(x), 4) for x in h[(h >= a.min_height - 1e-9) & (h <= a.max_height + 1e-9)]})
    if not heights:
        raise UsageError(f"--min-height/--max-height select none of the map's heights "
                         f"{sorted({round(float(x), 4) for x in h})} (m)")
    lo, hi = spread_range(a.instances, inst)
    if a.bin_width > hi - lo:
        raise UsageError(f"--bin-width must be at most the spread's range of start distances, {hi - lo:g} m, "
                         f"got {a.bin_width}")
    edges = bin_edges(lo, hi, a.bin_width)
    yaw_edges = None
    if a.split_yaw:
        if "yaw" not in inst:
            raise UsageError(f"--split-yaw: {a.instances!r} has no yaw column")
        ylo, yhi = spread_range(a.instances, inst, "yaw")
        yaw_edges = np.linspace(ylo, yhi, a.split_yaw + 1)
    rows = profile(inst, edges, a.min_height, a.max_height, a.variants, yaw_edges)
    atomic.check_writable_dir(a.out)  # a ValueError naming --out
    src = {}
    rm = os.path.join(os.path.dirname(a.instances), "reach_map.json")
    if os.path.isfile(rm):
        with open(rm, encoding="utf-8") as f:
            src = json.load(f).get("provenance", {})
    md = profile_markdown(rows, heights)
    atomic.atomic_write(os.path.join(a.out, "profile.md"), lambda f: f.write(md.encode()))
    png = profile_figure(rows, os.path.join(a.out, "profile.png"),
                         f"{os.path.relpath(a.instances)}\nheights {100 * heights[0]:g}-{100 * heights[-1]:g} cm "
                         f"pooled, bins of {100 * a.bin_width:g} cm"
                         + (f", {a.split_yaw} heading bins" if a.split_yaw else ""))
    atomic.write_json(os.path.join(a.out, "profile.json"), dict(
        provenance=atomic.provenance(), instances=os.path.relpath(a.instances), source_provenance=src,
        bin_width=a.bin_width, edges=edges.tolist(), yaw_edges=(None if yaw_edges is None else yaw_edges.tolist()),
        heights=heights, train_spread_starts=list(TRAIN_SPREAD_STARTS),
        rows=rows, figure=os.path.basename(png)))
    print(md)
    print(f"wrote {os.path.join(a.out, 'profile.json')}, profile.md, profile.png")
    return 0


# --------------------------------------------------------------------------------------------------- mechanism


def probe_task(cfg):
    """The step-down task of ``cfg`` whose trace holds, every ``cfg.record_every`` ticks, the feet (world), the four
    shins' and feet's contact forces, the crawl's phase, swing leg, touchdown, limit stop and search depth, and the
    edge probe's state at the tick's start (``probing``, ``probe_leg``, the bounds ``edge_lo``/``edge_hi`` in the
    phase's frame): the crawl's own step with its state's edge fields copied into the info (outputs unchanged)."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from hyqjax.core.types import Controller
    from hyqjax.crawl.state import CrawlInfo
    from hyqjax.sim import contacts
    from hyqjax.studies import stepdown

    @jax.tree_util.register_dataclass
    @dataclasses.dataclass(frozen=True)
    class EdgeInfo(CrawlInfo):
        probing: jax.Array = None
        probe_leg: jax.Array = None
        edge_lo: jax.Array = None
        edge_hi: jax.Array = None

    class EdgeTraceTask(stepdown.StepdownTask):
        def __init__(self, cfg):
            super().__init__(cfg)
            crawl_ctrl = self.controller

            def step(p, st, obs):
                st1, tau, info = crawl_ctrl.step(p, st, obs)
                fields = {f.name: getattr(info, f.name) for f in dataclasses.fields(CrawlInfo)}
                return st1, tau, EdgeInfo(**fields, probing=st.probing, probe_leg=st.probe_leg, edge_lo=st.edge_lo,
                                          edge_hi=st.edge_hi)

            self.controller = Controller(crawl_ctrl.init, step, crawl_ctrl.tie_rollout_carry)
            ci, sites = self.ids.contacts, np.asarray(self.ids.foot_sites)
            self.record = lambda d, obs, info: dict(
                time=d.time, feet=d.site_xpos[sites], shin_force=contacts.shin_forces(ci, d),
                foot_force=contacts.foot_forces(ci, d), qpos=d.qpos, phase=info.phase, swing_leg=info.swing_leg,
                touchdown=info.touchdown, limit_stop=info.limit_stop, limit_kind=info.limit_kind,
                search_depth=info.search_depth, probing=info.probing, probe_leg=info.probe_leg,
                edge_lo=jnp.asarray(info.edge_lo), edge_hi=jnp.asarray(info.edge_hi))

    return EdgeTraceTask(cfg)


LIMIT_NAMES = {0: "none", 1: "extension", 2: "end stop", 3: "depth"}


def swings(tr: dict, height: float) -> list[dict]:
    """Every swing of one run's per-tick trace ``tr`` (numpy, ticks first): a run of consecutive swing ticks of one
    leg with one ``probing`` flag (a probe and the swing that follows it at once are two). Each with its leg, first
    and last tick, how it ended (``touchdown``, ``limit: KIND``, ``probe: touchdown`` / ``probe: no ground``, or
    ``running`` at the end of the trace), the foot's x at lift-off and at the end (m past the edge) and its height
    above the platform's top at the end (m)."""
    from hyqjax.crawl.state import PHASE_SWING

    sw = (tr["phase"] == PHASE_SWING)
    key = np.where(sw, tr["swing_leg"] * 2 + tr["probing"].astype(int), -1)
    out = []
    t = 0
    n = len(key)
    while t < n:
        if key[t] < 0:
            t += 1
            continue
        e = t
        while e + 1 < n and key[e + 1] == key[t]:
            e += 1
        leg, probe = int(tr["swing_leg"][t]), bool(tr["probing"][t])
        if e == n - 1 and not (tr["touchdown"][e] or tr["limit_stop"][e]):
            how = "running"
        elif probe:
            how = "probe: touchdown" if tr["touchdown"][e] else "probe: no ground"
        elif tr["touchdown"][e]:
            how = "touchdown"
        elif tr["limit_stop"][e]:
            how = f"limit: {LIMIT_NAMES.get(int(tr['limit_kind'][e]), '?')}"
        else:
            how = "ended"
        out.append(dict(leg=LEGS[leg], first_tick=int(t), last_tick=int(e),
                        end_time=round(float(tr["time"][e]), 3), end=how, x_lift=round(float(tr["feet"][t, leg, 0]), 4),
                        x_end=round(float(tr["feet"][e, leg, 0]), 4),
                        z_end=round(float(tr["feet"][e, leg, 2] - height), 4),
                        search_depth=round(float(tr["search_depth"][e]), 4)))
        t = e + 1
    return out


def shin_clearance(m, qpos: np.ndarray, ticks: np.ndarray) -> np.ndarray:
    """``(len(ticks), 2)``: the distance (m) of the LF and RF shin capsules from the platform box (the edge's corner
    where they are near it; negative: penetrating) at the recorded ``qpos`` of ``ticks``, from MuJoCo's kinematics
    and ``mj_geomDistance`` on ``m`` (the terrain of the run's height)."""
    import mujoco

    d = mujoco.MjData(m)
    gid = lambda name: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
    shins, platform = [gid("lf_shin"), gid("rf_shin")], gid("platform")
    fromto = np.zeros(6)
    out = np.empty((len(ticks), 2))
    for j, k in enumerate(ticks):
        d.qpos[:] = qpos[k]
        mujoco.mj_kinematics(m, d)
        for i, g in enumerate(shins):
            out[j, i] = mujoco.mj_geomDistance(m, d, g, platform, 0.5, fromto)
    return out


def analyse_run(tr: dict, height: float, strike_force: float, m=None, every: int = 2) -> dict:
    """What one run's trace says about its front feet and shins (see the module docstring); with ``m`` (the model
    of the run's terrain), also each front shin's smallest clearance from the platform (:func:`shin_clearance`,
    every ``every`` ticks) up to the first strike (the whole run without one), when, and the front feet's x then."""
    strikes, contacts_first = {}, {}
    for i, leg in enumerate(LEGS):
        k = np.flatnonzero(tr["shin_force"][:, i] > strike_force)
        if len(k):
            strikes[leg] = dict(tick=int(k[0]), time=round(float(tr["time"][k[0]]), 3),
                                peak_force=round(float(tr["shin_force"][:, i].max()), 1),
                                feet_x=[round(float(x), 4) for x in tr["feet"][k[0], :, 0]],
                                feet_z=[round(float(z - height), 4) for z in tr["feet"][k[0], :, 2]])
        c = np.flatnonzero(tr["shin_force"][:, i] > 0)
        if len(c):
            contacts_first[leg] = round(float(tr["time"][c[0]]), 3)
    first_strike = min((s["tick"] for s in strikes.values()), default=None)
    all_swings = swings(tr, height)
    front = [s for s in all_swings if s["leg"] in ("LF", "RF")]
    upto = first_strike if first_strike is not None else len(tr["time"])
    front_shown = [s for s in front if s["first_tick"] <= upto][:6]
    crossing = {}
    for i, leg in enumerate(LEGS[:2]):
        k = np.flatnonzero(tr["feet"][:, i, 0] > 0)
        if len(k):
            crossing[leg] = dict(tick=int(k[0]), time=round(float(tr["time"][k[0]]), 3),
                                 z=round(float(tr["feet"][k[0], i, 2] - height), 4))
    clearance = {}
    if m is not None:
        ticks = np.arange(0, min(upto + 1, len(tr["time"])), every)
        if first_strike is not None:
            ticks = np.append(ticks, first_strike)
        c = shin_clearance(m, tr["qpos"], ticks)
        for i, leg in enumerate(LEGS[:2]):
            j = int(np.argmin(c[:, i]))
            clearance[leg] = dict(min=round(float(c[j, i]), 4), time=round(float(tr["time"][ticks[j]]), 3),
                                  feet_x=[round(float(x), 4) for x in tr["feet"][ticks[j], :2, 0]])
    return dict(strikes=dict(sorted(strikes.items(), key=lambda kv: kv[1]["tick"])),
                first_shin_contact=contacts_first, front_swings=front_shown, first_crossing=crossing,
                probe_ran=bool(tr["probing"].any()), first_strike_tick=first_strike, shin_clearance=clearance)


def _swing_text(s: dict) -> str:
    return (f"{s['leg']} {100 * s['x_lift']:+.1f} -> {100 * s['x_end']:+.1f} cm, z {100 * s['z_end']:+.1f} "
            f"({s['end']}, {s['end_time']:.2f} s)")


def _short_swing(s: dict) -> str:
    how = {"touchdown": "", "probe: touchdown": " probe, ground", "probe: no ground": " probe, no ground"}.get(
        s["end"], f" {s['end']}")
    return f"{s['leg']} {100 * s['x_end']:+.1f}{how}"


def mechanism_markdown(runs: list[dict], preset: str, friction: float, yaw: float, payload: float) -> str:
    lines = [(f"`{preset}`, C MuJoCo, heading {yaw:g} rad, no lateral offset, friction {friction:g}, payload "
              f"{payload:g} kg. Front swings: where the first three front swings ended, the foot's x in cm past the "
              "edge (negative: before it; a probe that found ground stands on the platform). Shin clearance: the "
              "smallest distance of each front shin from the platform up to the first strike (the whole run "
              "without one), when, and the RF foot's x then."), "",
             ("| height (cm) | start (cm) | clean | shin strike (leg, s, peak N) | first front swings (cm past the "
              "edge) | LF shin clearance (cm) | RF shin clearance (cm, s, RF foot x cm) |"),
             "|---|---|---|---|---|---|---|"]
    for r in runs:
        st = "; ".join(f"{leg} {s['time']:.2f} s, {s['peak_force']:.0f} N" for leg, s in r["strikes"].items()) or "–"
        fs = ", ".join(_short_swing(s) for s in r["front_swings"][:3])
        c = r.get("shin_clearance") or {}
        lf = f"{100 * c['LF']['min']:.2f}" if "LF" in c else "–"
        rf = (f"{100 * c['RF']['min']:.2f} at {c['RF']['time']:.2f} s, {100 * c['RF']['feet_x'][1]:+.1f}"
              if "RF" in c else "–")
        lines.append(f"| {100 * r['height']:g} | {100 * r['start_distance']:.1f} | {'yes' if r['clean'] else 'no'} | "
                     f"{st} | {fs} | {lf} | {rf} |")
    return "\n".join(lines) + "\n"


def run_mechanism(a: argparse.Namespace) -> int:
    from hyqjax.io import phases

    clock = phases.Clock.from_process_start()
    import jax

    from experiments import reach_map
    from hyqjax import presets
    from hyqjax.io import atomic
    from hyqjax.sim import model as hmodel
    from hyqjax.sim import task as simtask
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    lo, hi, step = a.starts
    starts = np.round(lo + step * np.arange(int(np.floor((hi - lo) / step + 1e-6)) + 1), 6)
    heights = np.asarray(a.heights, float)
    n = len(starts) * len(heights)
    rows = dict(variant=np.full(n, a.variant), height=np.repeat(heights, len(starts)),
                start_distance=np.tile(starts, len(heights)), friction=np.full(n, a.friction),
                payload_mass=np.full(n, a.payload), payload_com=np.zeros((n, 3)), lateral_offset=np.zeros(n),
                yaw=np.full(n, a.yaw))
    cfg = a.cfg
    ro = simtask.Rollout(probe_task(cfg))
    clock.lap("startup")
    print(f"{n} step-downs of {a.duration:g} s with {a.variant!r} on C MuJoCo (heights {list(heights)} m, starts "
          f"{100 * starts[0]:g}-{100 * starts[-1]:g} cm)", flush=True)
    params = a.params if a.params is not None else presets.load(a.preset)
    out, res = ro.run(reach_map.scenario_of(rows, np.arange(n), {a.variant: params}))
    cols = so.to_columns(jax.block_until_ready(out))
    trace = jax.tree_util.tree_map(np.asarray, res.trace)
    clock.lap("simulation")  # the C batch's compile included
    models = {float(h): hmodel.model_spec(cfg.layout, platform_height=float(h)).compile() for h in heights}
    runs = []
    for i in range(n):
        tr = {k: v[i] for k, v in trace.items()}
        r = dict(height=float(rows["height"][i]), start_distance=float(rows["start_distance"][i]),
                 clean=bool(cols["clean"][i]), completed=bool(cols["completed"][i]),
                 shin_strike=bool(cols["shin_strike"][i]), terminated=bool(cols["terminated"][i]),
                 diverged=bool(cols["diverged"][i]), peak_shin_force=round(float(cols["peak_shin_force"][i]), 1),
                 **analyse_run(tr, float(rows["height"][i]), cfg.strike_force, models[float(rows["height"][i])]))
        runs.append(r)
        print(f"  {100 * r['height']:g} cm, start {100 * r['start_distance']:.1f} cm: clean {r['clean']}, shin strike "
              f"{r['shin_strike']} {list(r['strikes'])}; " + "; ".join(_swing_text(s) for s in r["front_swings"]),
              flush=True)
    md = mechanism_markdown(runs, a.variant, a.friction, a.yaw, a.payload)
    atomic.atomic_write(os.path.join(a.out, "mechanism.md"), lambda f: f.write(md.encode()))
    path = os.path.join(a.out, "mechanism.json")
    atomic.write_json(path, dict(provenance=atomic.provenance(), impl="c", start_pose=stepdown.START_POSE,
                                 preset=None if a.tuned_run else a.preset, tuned_run=a.tuned_run,
                                 heights=heights.tolist(), starts=starts.tolist(),
                                 friction=a.friction, yaw=a.yaw, payload=a.payload, duration=a.duration,
                                 strike_force=cfg.strike_force,
                                 control_dt=cfg.control_dt, runs=runs, wall_s=clock.wall(), phases=clock.to_dict()))
    clock.lap("summary")
    print(f"wrote {path} and mechanism.md")
    print(clock.line())
    return 0


def main(argv=None) -> int:
    a = parse(argv)
    try:
        check(a)  # a preset's PresetError is a ValueError of one line
        if a.mode == "profile":
            return run_profile(a)  # its input errors are UsageErrors, raised before anything is written
    except (UsageError, ValueError) as e:
        print(f"start_distance_profile: {e}", file=sys.stderr)
        return 2
    return run_mechanism(a)


if __name__ == "__main__":
    sys.exit(main())
