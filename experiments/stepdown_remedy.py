"""The step-down at scale, one compiled batch: the paper's crawl with the reflex off and on, the shin-strike remedy,
the trunk in the full terrain frame, and the no-reflex crawl with shorter steps.

    python -m experiments.stepdown_remedy --instances 1024 --out DIR      # GPU: about 16,000 instances x 24 s
    python -m experiments.stepdown_remedy --instances 1 --duration 4 --out DIR   # CPU check of the pipeline

Variants (``CrawlParams`` overrides; each runs the same ``--instances`` randomised instances per height, from
``--seed``, as ``hyqjax stepdown`` draws them: friction 0.7-1.0, payload 0-10 kg, start 0-4 cm before the edge,
+-3 cm lateral, +-0.05 rad yaw):

* ``paper_off`` / ``paper_on``: the crawl of Section II, height reflex off / on;
* ``remedy``: reflex on and ``shin_remedy`` (:mod:`hyqjax.crawl.remedy`);
* ``terrain_frame``: as ``remedy`` with ``terrain_adaptation = 1`` (the trunk takes the feet plane's roll and
  pitch in full, the terrain frame of Section II) instead of 0.3;
* ``short_step_off``: reflex off with ``max_step_length = 0.15`` m (the kinematic reach of
  ``experiments/stepdown_reach.py``: the 0.3 m step of the default leaves 13.8 cm of search).

Per instance, besides the step-down outcome (:mod:`hyqjax.studies.stepdown_outcome`), it records when the first shin
strike happened and on which leg, when the first front swing found the step (searched deeper than 5 cm), the
first limit that ended a front swing without touchdown, and how far past the edge the front feet landed after the
step. Writes ``DIR/remedy.json``: per variant and height the counts and Wilson 95% intervals of *completed* and
*clean*, the share of runs losing a foothold, past a joint range, with a shin strike, with a shin strike before the
step was found (a foot slipping off the edge it started on), the median per-run minimum swing mobility, the
footnote-8 mobility, the peak pitch, Pearson's r of *clean* against the start distance, friction and payload, and
the largest height with at least 90% completed; ``DIR/remedy_instances.npz`` holds one row per instance
(inputs and outcome columns).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.io import atomic as io
from hyqjax.sim import contacts
from hyqjax.sim import rollout as sim
from hyqjax.sim import runner as srunner
from hyqjax.studies import stepdown
from hyqjax.studies import stepdown_outcome as so
from hyqjax.studies.statistics import wilson_interval

HEIGHTS = (0.16, 0.21, 0.24, 0.27)
VARIANTS = {
    "paper_off": (dict(use_reflex=False), HEIGHTS[:3]),
    "paper_on": (dict(use_reflex=True), HEIGHTS),
    "remedy": (dict(use_reflex=True, shin_remedy=True), HEIGHTS + (0.30,)),
    "terrain_frame": (dict(use_reflex=True, shin_remedy=True, terrain_adaptation=1.0), HEIGHTS),
    "terrain_frame_no_remedy": (dict(use_reflex=True, terrain_adaptation=1.0), HEIGHTS),
    # between the two frames: the remedy with the trunk following 60% / 80% of the feet plane, and in the full
    # terrain frame with its roll/pitch targets bounded at 0.25 rad instead of 0.35 (tilt failures at 24 cm)
    "remedy_adapt_0.6": (dict(use_reflex=True, shin_remedy=True, terrain_adaptation=0.6), HEIGHTS),
    "remedy_adapt_0.8": (dict(use_reflex=True, shin_remedy=True, terrain_adaptation=0.8), HEIGHTS),
    "terrain_frame_tilt_0.25": (dict(use_reflex=True, shin_remedy=True, terrain_adaptation=1.0, max_tilt=0.25),
                                HEIGHTS),
    "short_step_off": (dict(use_reflex=False, max_step_length=0.15), (0.16, 0.21)),
}
#: A front swing ending deeper than this below its nominal foothold found the step (m).
DEEP = 0.05


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Extra:
    t_first_shin_strike: jax.Array  # s, -1 if none
    shin_strike_leg: jax.Array  # leg of the first shin strike, -1 if none
    t_step_found: jax.Array  # s, first front swing ending deeper than DEEP, -1 if none
    first_front_limit: jax.Array  # CrawlInfo.limit_kind of the first front swing ended by a limit, 0 if none
    first_front_limit_depth: jax.Array  # its search depth (m)
    min_front_landing_x: jax.Array  # smallest x past the edge of a front foot at the end of a deep swing (m)


def make_metrics(ids, strike_force: float, terminal_tilt: float | None = None) -> sim.Metrics:
    base = so.make_metrics(ids, strike_force, terminal_tilt)
    ci = ids.contacts
    sites = np.asarray(ids.foot_sites)

    def init(d):
        f = jnp.asarray(-1.0, d.qpos.dtype)
        return base.init(d), Extra(f, jnp.asarray(-1), f, jnp.asarray(0), f * 0.0, f * 0.0 + 9.0)

    def update(ms, d, obs, info):
        b, e = ms
        f_shin = contacts.shin_forces(ci, d)
        strike = jnp.max(f_shin) > strike_force
        first = strike & (e.t_first_shin_strike < 0)
        front = info.swing_leg < 2
        end = info.touchdown | info.limit_stop
        deep_end = end & front & (info.search_depth > DEEP)
        lim = info.limit_stop & front & (e.first_front_limit == 0)
        x_land = d.site_xpos[sites][info.swing_leg, 0]
        e = Extra(
            t_first_shin_strike=jnp.where(first, d.time, e.t_first_shin_strike),
            shin_strike_leg=jnp.where(first, jnp.argmax(f_shin), e.shin_strike_leg),
            t_step_found=jnp.where(deep_end & (e.t_step_found < 0), d.time, e.t_step_found),
            first_front_limit=jnp.where(lim, info.limit_kind, e.first_front_limit),
            first_front_limit_depth=jnp.where(lim, info.search_depth, e.first_front_limit_depth),
            min_front_landing_x=jnp.where(deep_end, jnp.minimum(e.min_front_landing_x, x_land), e.min_front_landing_x),
        )
        return base.update(b, d, obs, info), e

    terminal = None if base.terminal is None else (lambda ms: base.terminal(ms[0]))
    return sim.Metrics(init, update, terminal)


def build(instances: int, seed: int, variants) -> tuple[stepdown.Scenario, dict[str, np.ndarray]]:
    scs, tabs = [], []
    for name in variants:
        over, heights = VARIANTS[name]
        p = crawl.CrawlParams.make(forward_velocity=0.1, **over)
        sc, tab = stepdown.make_scenarios(heights, [bool(over["use_reflex"])], instances, seed, params=p)
        tab["variant"] = np.array([name] * len(tab["height"]))
        scs.append(sc)
        tabs.append(tab)
    sc = jax.tree_util.tree_map(lambda *x: jnp.concatenate(x), *scs)
    table = {k: np.concatenate([t[k] for t in tabs]) for k in tabs[0]}
    return sc, table


def run(sc: stepdown.Scenario, cfg: stepdown.StepdownConfig):
    st = stepdown.setup(cfg)
    runner = srunner.make_batch_runner(st.ids, crawl.crawl_controller(cfg.control_dt), cfg.sim_config(),
                                       make_metrics(st.ids, cfg.strike_force, cfg.max_tilt if cfg.terminate else None),
                                       None, params_axes=0)
    from hyqjax.sim import model as hmodel

    mb = hmodel.batch_model(st.mx, st.ids, sc.terrain)
    d0 = stepdown.initial_batch_data(st, mb, sc)  # under impl jax or warp
    res = runner(mb, d0, sc.params, sc.push)
    outcome = jax.jit(jax.vmap(lambda r: so.outcome(r, st.ids, cfg.max_tilt, cfg.min_progress)))(
        res._replace(metrics=res.metrics[0], trace=None))
    cols = so.to_columns(outcome)
    extra = jax.tree_util.tree_map(np.asarray, res.metrics[1])
    cols.update({f.name: getattr(extra, f.name) for f in dataclasses.fields(Extra)})
    return cols


def _pearson(x, y):
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.std() == 0 or y.std() == 0:
        return None
    return float(np.corrcoef(x, y)[0, 1])


def summarise(table, cols):
    rows = []
    for name in dict.fromkeys(table["variant"].tolist()):
        for h in sorted(set(table["height"][table["variant"] == name].tolist())):
            m = (table["variant"] == name) & (table["height"] == h)
            n = int(m.sum())
            comp, clean = cols["completed"][m], cols["clean"][m]
            shin = cols["shin_strike"][m]
            early = shin & ((cols["t_step_found"][m] < 0) | (cols["t_first_shin_strike"][m] < cols["t_step_found"][m]))
            lims = cols["first_front_limit"][m]
            landing = cols["min_front_landing_x"][m]
            rows.append(dict(
                variant=name, height=h, n=n,
                completed=int(comp.sum()), completed_rate=float(comp.mean()), completed_ci95=wilson_interval(int(comp.sum()), n),
                clean=int(clean.sum()), clean_rate=float(clean.mean()), clean_ci95=wilson_interval(int(clean.sum()), n),
                share_losing_a_foothold=float(cols["lost_foothold"][m].mean()),
                share_joint_past_range=float(cols["joint_past_range"][m].mean()),
                share_shin_strike=float(shin.mean()),
                share_shin_strike_before_the_step_was_found=float(early.mean()),
                shin_strike_legs={str(k): int(v) for k, v in zip(*np.unique(cols["shin_strike_leg"][m][shin], return_counts=True))},
                share_front_swing_ended_by={k: float((lims == v).mean()) for k, v in
                                            (("extension", 1), ("end_stop", 2), ("depth", 3))},
                median_first_front_limit_depth=float(np.median(cols["first_front_limit_depth"][m][lims > 0])) if (lims > 0).any() else None,
                median_front_landing_past_edge=float(np.median(landing[landing < 9])) if (landing < 9).any() else None,
                median_min_swing_mobility=float(np.nanmedian(cols["min_swing_mobility"][m])),
                mean_mobility=float(np.nanmean(cols["mean_mobility"][m])),
                mean_peak_pitch=float(np.mean(cols["peak_pitch"][m])),
                diverged=int(cols["diverged"][m].sum()),
                terminated=int(cols["terminated"][m].sum()),
                r_clean_vs_start_distance=_pearson(table["start_distance"][m], clean),
                r_clean_vs_friction=_pearson(table["friction"][m], clean),
                r_clean_vs_payload=_pearson(table["payload_mass"][m], clean),
            ))
    limits = {}
    for name in dict.fromkeys(r["variant"] for r in rows):
        ok = [r["height"] for r in rows if r["variant"] == name and r["completed_rate"] >= 0.9]
        limits[name] = dict(largest_height_completed_90=max(ok) if ok else None)
    return rows, limits


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/stepdown_remedy")
    ap.add_argument("--instances", type=int, default=1024, help="randomised instances per variant and height")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    args = ap.parse_args(argv)
    if not (1 <= args.instances <= 100000):
        raise SystemExit(f"--instances must be in [1, 100000], got {args.instances}")
    if not (1.0 <= args.duration <= 120.0):
        raise SystemExit(f"--duration must be in [1, 120] s, got {args.duration}")
    os.makedirs(args.out, exist_ok=True)
    sc, table = build(args.instances, args.seed, args.variants)
    cfg = stepdown.StepdownConfig(duration=args.duration)
    print(f"{sc.batch_size} instances x {args.duration:.0f} s on {jax.devices()[0].device_kind}", flush=True)
    t0 = time.time()
    cols = run(sc, cfg)
    wall = time.time() - t0
    rows, limits = summarise(table, cols)
    for r in rows:
        print(f"{r['variant']:>15} {100 * r['height']:4.0f} cm  completed {r['completed']:5d}/{r['n']} "
              f"({r['completed_rate']:6.1%})  clean {r['clean']:5d} ({r['clean_rate']:6.1%})  shin {r['share_shin_strike']:5.1%}"
              f" (early {r['share_shin_strike_before_the_step_was_found']:5.1%})  lost fh {r['share_losing_a_foothold']:5.1%}"
              f"  r(start) {r['r_clean_vs_start_distance']}")
    print(json.dumps(limits))
    print(f"wall {wall:.1f} s (compile included)")
    np.savez_compressed(os.path.join(args.out, "remedy_instances.npz"),
                        **{k: np.asarray(v) for k, v in {**table, **cols}.items()})
    io.write_json(os.path.join(args.out, "remedy.json"), dict(
        provenance=io.provenance(seed=args.seed), config=dict(vars(args), variants_spec={
            k: dict(overrides=VARIANTS[k][0], heights=VARIANTS[k][1]) for k in args.variants}),
        device=jax.devices()[0].device_kind, n_instances=sc.batch_size, wall_time_s=wall,
        summary=rows, limits=limits, instances_file="remedy_instances.npz"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
