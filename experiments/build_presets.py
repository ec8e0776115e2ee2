"""Write the preset registry's files (``hyqjax/presets/<name>.json``) from the stored results they come from.

    python -m experiments.build_presets            # rewrite every preset file
    python -m experiments.build_presets --check    # exit 1 if a file differs from what the results give

Every value is read from a stored result file (``docs/results/...``): the tuned crawl gains from a tuning run's
``results.json`` (its returned iterate, mapped on its parameter space exactly as ``hyqjax tune`` reported it),
the bounding gains from the robust study's ``params_*.json``; every figure from a stored result file with the
command in its provenance, or from the held-out evaluation of 2026-11-29 (one H200, MuJoCo Warp) whose result
file is not in the repository, marked as such with the command that re-measures it.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

from hyqjax.presets import from_results, registry

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "hyqjax", "presets")
R = "docs/results"
FORMAT = "hyqjax.presets/1"

#: The recommended step-down configuration's edge probe (hyqjax.crawl.presets.PROBE_DEEP).
PROBE = dict(edge_probe=0.1, edge_tilt=0.3, edge_margin=0.1, edge_lowering=0.01, edge_deep=0.255, edge_tilt_deep=0.5)
REACH_SRC = f"{R}/tune_reach_h200_10min/snes/results.json"
PER_LEG_SRC = f"{R}/tune_cells_h200_30min/cma_es_per_leg_30min/results.json"
REACH_MAP = f"{R}/reach_recommended_h200/warp_wide/reach_map.json"
HELDOUT_0129 = ("2,400 held-out step-downs of 2026-11-29 (heights between the trained ones, another seed, the wide "
                "spread: friction 0.4-1.0, payload 0-15 kg, start 0-15 cm)")
NEW_HELDOUT_SOURCE = "held-out evaluation on one H200, MuJoCo Warp, 2026-11-29 (its result file is not stored)"
REACH_WIDE_1024 = ("wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm), 1,024 runs per height, held-out "
                   "seed")
BOUND_ENV = ("five commands of the bounding command envelope at low friction and a 10 kg payload: friction "
             "0.5-0.6, payload 10 kg, 1,024 x 8 s per command")
#: The command field of a figure of the 2026-11-29 evaluation, whose command was not recorded.
UNRECORDED = "unrecorded: held-out evaluation of 2026-11-29 on one H200, MuJoCo Warp (no result file in the repository)"
BOUND_PRESETS_CMD = "python -m experiments.bounding_presets --impl warp --instances 1024 --out out/bounding_presets"


def rel(path):
    return os.path.relpath(path, ROOT)


def read(path):
    with open(os.path.join(ROOT, path)) as f:
        return json.load(f)


def prov_of(res: dict, source: str, **extra) -> dict:
    return from_results.provenance(res, source, **extra)


def tuned_shared(path: str, run: str):
    return from_results.tuned_shared(os.path.join(ROOT, path), run)


def tuned_per_leg(path: str, key: str):
    """``(crawl settings, reflex values, per-leg values, results)``
    (:func:`hyqjax.presets.from_results.tuned_per_leg`)."""
    return from_results.tuned_per_leg(os.path.join(ROOT, path), key)


def tuned_conditioned(path: str, key: str):
    return from_results.tuned_conditioned(os.path.join(ROOT, path), key)


heldout_fig = from_results.heldout_figure


def map_command(recorded: str) -> str:
    """A reach map's recorded command as typed: maps stored before 2026-11-30 recorded it as ``hyqjax ARGS``,
    later ones as ``python -m experiments.reach_map ARGS``."""
    old = "hyqjax "
    args = recorded[len(old):] if recorded.startswith(old) else recorded.split(" ", 3)[3]
    return "python -m experiments.reach_map " + args


def reach_fig(variant: str):
    res = read(REACH_MAP)
    cell = next(c for c in res["cells"] if c["variant"] == variant)
    n = cell["per_height"][0]["n"]
    return dict(what="h90, wide spread", value=round(100 * cell["h90"]), unit="cm", interval=None,
                heldout=f"wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm), {n} runs per height at "
                        f"14-30 cm, seed {res['provenance']['seed']}",
                command=map_command(res["provenance"]["command"]),
                device=res["device"], date=res["provenance"]["date"][:10], source=REACH_MAP)


def reach_fig_0129(value_cm: int, variant_cmd: str):
    return dict(what="h90, wide spread (independent held-out set)", value=value_cm, unit="cm", interval=None,
                heldout=REACH_WIDE_1024, device="NVIDIA H200, MuJoCo Warp", date="2026-11-29",
                source=NEW_HELDOUT_SOURCE, command=UNRECORDED,
                remeasure=f"python -m experiments.reach_map --impl warp --instances 1024 --spread wide --seed 20261129 "
                          f"--heights 0.14 0.16 0.18 0.20 0.22 0.24 0.26 0.27 0.28 0.30 {variant_cmd}")


def clean_fig_0129(value: float, preset: str):  # noqa: ARG001
    return dict(what="clean success, held-out step-downs", value=value, unit="share", interval=None,
                heldout=HELDOUT_0129, device="NVIDIA H200, MuJoCo Warp", date="2026-11-29",
                source=NEW_HELDOUT_SOURCE, command=UNRECORDED)


TARGETS = f"{R}/tune_default_repeats_h200"
#: The five default runs trained with the leading-foot start (``hyqjax.studies.stepdown.START_POSE``), their
#: targets map (seed 60613) and a confirmation map of four sets on fresh instances (seed 31415).
TARGETS_LF = f"{R}/tune_default_repeats_leading_foot_h200"
CONFIRM_LF = f"{TARGETS_LF}/confirm_31415/reach_map.json"
#: Five default runs from ``clean`` at the first step 0.1 (two H200s), their targets map (seed 27182) and a
#: confirmation of four of them against ``clean`` on fresh instances on C MuJoCo (seed 90210).
TARGETS_S01 = f"{R}/tune_default_repeats_clean_sigma01_h200x2"
CONFIRM_C = f"{TARGETS_S01}/confirm_c_90210"
#: ``clean_refined`` and ``clean`` run again on the confirmation map's instances (seed 31415; two H200s, MuJoCo Warp),
#: with the instances kept for the paired comparison.
CONFIRM_S01 = f"{TARGETS_S01}/confirm_31415"
#: The start pose of each stored targets map (``experiments/start_pose_check.py``, docs/stepdown.md).
POSE = {TARGETS: "the earlier hip-line start", TARGETS_LF: "the leading-foot start",
        TARGETS_S01: "the leading-foot start"}


def targets_figs(variant: str, chosen_on_it: bool = False, root: str = TARGETS) -> list[dict]:
    """Figures of ``variant`` on a default tuner's held-out targets map (``experiments/tune_default_repeats.py``,
    :data:`hyqjax.studies.tune.study.targets.HELDOUT`) stored under ``root``: clean success pooled up to 26 cm and h90
    on the wide spread (with the map's start pose named). ``chosen_on_it``: the set was picked as the best run on
    this very map (its figure is optimistic)."""
    t = read(f"{root}/targets.json")
    m = read(f"{root}/heldout/reach_map.json")
    v = t["variants"][variant]
    h = t["heldout"]
    held = (f"wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm), seed {h['seed']}, "
            f"{h['instances']} runs per height at {', '.join(f'{100 * x:g}' for x in h['heights'])} cm (no "
            f"training height), {POSE[root]}" + ("; this set was chosen as the best of five runs on this map, so the "
                                                 "figure is optimistic" if chosen_on_it else ""))
    base = dict(heldout=held, command=t["reach_map_command"].replace("/tmp/tdr/", "out/tdr/").replace("/tmp/s01/",
                                                                                                     "out/tdr/"),
                device=f"{m['device']}, MuJoCo Warp", date=m["provenance"]["date"][:10],
                source=f"{root}/targets.json")
    return [dict(what="clean success up to 26 cm, held-out step-downs", value=round(v["clean"], 3), unit="share",
                 interval=[round(x, 3) for x in v["clean_ci95"]], **base),
            dict(what="h90, wide spread", value=round(100 * v["h90"]), unit="cm", interval=None, **base)]


def confirm_figs(variant: str, path: str = CONFIRM_LF) -> list[dict]:
    """Figures of ``variant`` on the confirmation map ``path`` (:data:`CONFIRM_LF`, or its instances run again:
    fresh instances, seed 31415; the leading-foot start; no part of any tuner or of the choice of the ``clean`` and
    ``clean_refined`` presets saw it): clean success pooled up to 26 cm, the worst clean rate at a height up to 24
    cm, clean at the farthest starts (10-15 cm), h90 and completed at 29 cm."""
    from hyqjax.studies import statistics
    from hyqjax.studies.tune.study import targets

    m = read(path)
    s = targets.variant_summary(next(c for c in m["cells"] if c["variant"] == variant))
    n = s["per_height"][0]["n"]
    hs = ", ".join(f"{100 * p['height']:g}" for p in s["per_height"])
    base = dict(heldout=(f"wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm), seed "
                         f"{m['provenance']['seed']}, {n} runs per height at {hs} cm, the leading-foot start; "
                         f"{s['diverged']} diverged of {s['n']:,}"),
                command=(map_command(m["provenance"]["command"]).replace("/root/out/", "out/").replace(
                             "/tmp/m/c31415", "out/confirm")),
                device=f"{m['device']}, MuJoCo Warp", date=m["provenance"]["date"][:10], source=path)
    w, far = s["worst_low"], s["far_start"]
    tall = next(p for p in s["per_height"] if abs(p["height"] - 0.29) < 1e-9)
    return [dict(what=registry.FIGURE_CLEAN, value=round(s["clean"], 3),
                 unit="share", interval=[round(x, 3) for x in s["clean_ci95"]], **base),
            dict(what=f"worst clean success at a height up to 24 cm ({100 * w['height']:g} cm)",
                 value=round(w["clean"], 3), unit="share", interval=None, **base),
            dict(what="clean success from the farthest starts (10-15 cm before the edge)",
                 value=round(far["clean"], 3), unit=f"share of {far['n']:,}", interval=None, **base),
            dict(what="h90, wide spread", value=round(100 * s["h90"]), unit="cm", interval=None, **base),
            dict(what=registry.FIGURE_TALL, value=round(tall["completed"], 3),
                 unit="share", interval=[round(x, 3) for x in statistics.wilson_interval(
                     int(round(tall["completed"] * tall["n"])), int(tall["n"]))], **base)]


def chosen_run(root: str, key: str, label: str, command: tuple[str, str]) -> tuple[str, str]:
    """The run of a default tuner's repeats under ``root`` with the highest ``key`` of the tuner's own selection
    (``targets.json``'s ``returned``), and the provenance line saying how it was chosen (``command``: the repeats
    command and its runs; ``label``: what ``key`` is)."""
    returned = read(f"{root}/targets.json")["returned"]
    chosen = max(sorted(returned), key=lambda v: returned[v][key])
    others = ", ".join(f"{returned[v][key]:.3f}" for v in sorted(returned) if v != chosen)
    return chosen, (f"the run of the five of `{command[0]}` ({command[1]}) with the highest {label} of the tuner "
                    f"itself ({returned[chosen][key]:.3f}; the others {others}); no held-out map took part in the "
                    f"choice")


def confirm_c_figs(variant: str, reference: str = "clean") -> list[dict]:
    """Figures of ``variant`` on the C MuJoCo confirmation :data:`CONFIRM_C` (fresh instances, seed 90210, 15-25
    cm; no run, study or choice saw them): its clean success pooled over the map with the Wilson interval, and its
    difference from ``reference`` paired on the same instances (``python -m experiments.paired_map``)."""
    from hyqjax.studies import statistics

    m = read(f"{CONFIRM_C}/reach_map.json")
    paired = read(f"{CONFIRM_C}/paired_{reference}.json")["variants"][variant]["clean"]["pooled"]
    cell = next(c for c in m["cells"] if c["variant"] == variant)
    hs = ", ".join(f"{100 * p['height']:g}" for p in cell["per_height"])
    n_h = cell["per_height"][0]["n"]
    base = dict(heldout=(f"wide spread (friction 0.4-1.0, payload 0-15 kg, start 0-15 cm), seed "
                         f"{m['provenance']['seed']}, {n_h} runs per height at {hs} cm, the leading-foot start, C "
                         f"MuJoCo; {cell['diverged']} diverged of {cell['n']:,}"),
                command=map_command(m["provenance"]["command"]),
                device=f"{m['device']} (C MuJoCo)", date=m["provenance"]["date"][:10], source=f"{CONFIRM_C}/reach_map.json")
    k = int(round(paired["variant"] * paired["n"]))
    first = dict(what="clean success at 15-25 cm, held-out step-downs (C MuJoCo confirmation)",
                 value=round(paired["variant"], 3), unit="share",
                 interval=[round(x, 3) for x in statistics.wilson_interval(k, paired["n"])], **base)
    return [first, paired_fig(CONFIRM_C, variant, reference, first,
                              what=f"clean success minus {reference}'s on the same step-downs (paired)")]


def paired_fig(map_dir: str, variant: str, reference: str, figure: dict, what: str | None = None) -> dict:
    """``variant``'s clean success minus ``reference``'s on the same step-downs of the reach map ``map_dir`` up to
    26 cm (``python -m experiments.paired_map``'s stored result), with the provenance of ``figure`` (one of the
    map's figures); ``what`` names it (default: the step-downs up to 26 cm)."""
    paired = read(f"{map_dir}/paired_{reference}.json")["variants"][variant]["clean"]["pooled"]
    return dict(what=what or f"clean success minus {reference}'s on the same step-downs up to 26 cm (paired)",
                value=round(paired["d"], 3), unit="share", interval=[round(x, 3) for x in paired["ci95"]],
                heldout=figure["heldout"], command=figure["command"] + f"; python -m experiments.paired_map "
                                                                         f"{map_dir} --reference {reference}",
                device=figure["device"], date=figure["date"], source=f"{map_dir}/paired_{reference}.json")


def bound_file(path: str):
    d = read(path)
    return d["amplitudes"], d["gains"], d.get("provenance", {})


def bound_heldout_fig(method: str, what_prefix=""):
    path = f"{R}/bounding_robust_h100_8s/results.json"
    res = read(path)
    h = res["heldout"]
    m = h["methods"][method]
    d = h["draw"]
    held = (f"{h['instances']:,} runs x {h['duration']:g} s, seed {h['seed']}: speed {d['speed'][0]:g}-"
            f"{d['speed'][1]:g}"
            f" m/s, yaw rate +-{d['yaw_rate'][1]:g} rad/s, friction {d['friction'][0]:g}-{d['friction'][1]:g}, "
            f"payload {d['payload'][0]:g}-{d['payload'][1]:g} kg")
    common = dict(heldout=held, command="python -m experiments.bounding_robust " + res["provenance"]["command"].split(
        "experiments.bounding_robust ", 1)[1], device=res["device"], date=res["provenance"]["date"][:10], source=path)
    return [dict(what="falls, held-out bounding runs", value=m["failures"], unit=f"of {m['n']:,}", interval=None,
                 **common),
            dict(what="worst yaw error, held-out bounding runs", value=round(m["yaw_error_worst_deg"], 2), unit="deg",
                 interval=None, **common)]


def bound_envelope_figs(falls: str, yaw: str, nominal: dict | None):
    out = [dict(what="runs that fall, envelope commands at friction 0.5-0.6, 10 kg (per command)", value=falls,
                unit="", interval=None, heldout=BOUND_ENV, device="NVIDIA H200, MuJoCo Warp", date="2026-11-29",
                source=NEW_HELDOUT_SOURCE, command=UNRECORDED, remeasure=BOUND_PRESETS_CMD),
           dict(what="worst yaw error there", value=yaw, unit="deg", interval=None, heldout=BOUND_ENV,
                device="NVIDIA H200, MuJoCo Warp", date="2026-11-29", source=NEW_HELDOUT_SOURCE,
                command=UNRECORDED, remeasure=BOUND_PRESETS_CMD)]
    if nominal:
        for what, v, unit in (("yaw rms at (0.5 m/s, 0.3 rad/s)", nominal["yaw"], "deg"),
                              ("speed rms at (0.5 m/s, 0.3 rad/s)", nominal["speed"], "m/s")):
            out.append(dict(what=what, value=v, unit=unit, interval=None,
                            heldout="the nominal command (0.5 m/s, 0.3 rad/s)", device="NVIDIA H200, MuJoCo Warp",
                            date="2026-11-29",
                            source=NEW_HELDOUT_SOURCE, command=UNRECORDED, remeasure=BOUND_PRESETS_CMD))
    return out


BOUND_PRESETS_H200 = f"{R}/bounding_presets_h200/bounding_presets.json"


BOUND_PRESETS_H200_5151 = f"{R}/bounding_presets_h200_seed5151/bounding_presets.json"


def bound_presets_figs(preset: str, source: str = BOUND_PRESETS_H200) -> list[dict]:
    """Figures of ``preset`` from the presets-on-the-same-instances run (``experiments/bounding_presets.py``, stored in
    :data:`BOUND_PRESETS_H200`): falls and worst yaw error at friction 0.5-0.6 with 10 kg (the nominal command and the
    four corners of the command box, 1,024 runs each), the speed error at the nominal command."""
    d = read(source)
    rows = [r for r in d["rows"] if r["preset"] == preset]
    low = [r for r in rows if r["condition"] != "nominal"]
    nom = next(r for r in rows if r["condition"] == "nominal")
    prov = d["provenance"]
    cmd = prov["command"].replace("/root/out/", "out/")
    common = dict(heldout=(f"seed {prov['seed']}: the nominal command (0.5 m/s, 0.3 rad/s) and the corners of the command "
                           "box (0 and 1.0 m/s x -0.8 and +0.8 rad/s) at friction 0.5-0.6 with a 10 kg payload, "
                           f"{nom['n']:,} runs x {d['duration']:g} s each"),
                  command=cmd, device="NVIDIA H200, MuJoCo Warp", date=prov["date"][:10], source=source)
    return low_friction_figs(low, nom, common)


def low_friction_figs(low: list[dict], nom: dict, common: dict) -> list[dict]:
    """Falls and the worst yaw error over the low-friction, 10 kg rows ``low`` (the nominal command and the four
    corners), the speed error of the nominal row ``nom``; ``common``: the figures' held-out set and provenance."""
    per = ", ".join(f"{r['failures']}" for r in low)
    return [dict(what="runs that fall at friction 0.5-0.6, 10 kg (nominal command, then the four corners)",
                 value=sum(r["failures"] for r in low), unit=f"of {sum(r['n'] for r in low):,} ({per})",
                 interval=None, **common),
            dict(what="worst yaw error there", value=round(max(r["yaw_error_worst_deg"] for r in low), 2), unit="deg",
                 interval=None, **common),
            dict(what="mean absolute speed error at the nominal command", value=round(nom["speed_error_mean_abs"], 3),
                 unit="m/s", interval=None, **common)]


BOUND_REFINE = f"{R}/bounding_refine_h200/results.json"


def bound_refine_figs(set_name: str) -> list[dict]:
    """Figures of ``set_name`` (``refined`` or the start preset) from the refinement run at the fast corners
    (``experiments/bounding_refine.py``, stored in :data:`BOUND_REFINE`): falls and worst yaw error at friction
    0.5-0.6 with 10 kg (the nominal command and the four corners of the command box, 1,024 runs each, seed 2911: the
    instances of ``experiments.bounding_presets``), the speed error at the nominal command, and falls and worst yaw
    on the broad held-out envelope (4,096 runs, seed 7777)."""
    d = read(BOUND_REFINE)
    h = d["heldout"]
    prov = d["provenance"]
    cmd = prov["command"].replace("/root/out/", "out/")
    base = dict(command=cmd, device=f"{d['device']}, MuJoCo Warp", date=prov["date"][:10], source=BOUND_REFINE)
    rows = [r for r in h["conditions"]["rows"] if r["set"] == set_name]
    low = [r for r in rows if r["condition"] != "nominal"]
    nom = next(r for r in rows if r["condition"] == "nominal")
    cond = dict(base, heldout=(f"seed {h['conditions']['seed']}: the nominal command (0.5 m/s, 0.3 rad/s) and the "
                               "corners of the command box (0 and 1.0 m/s x -0.8 and +0.8 rad/s) at friction 0.5-0.6 "
                               f"with a 10 kg payload, {nom['n']:,} runs x {h['conditions']['duration']:g} s each"))
    b = next(x for x in h["broad"]["sets"] if x["set"] == set_name)
    dr = h["broad"]["draw"]
    broad = dict(base, heldout=(f"{b['n']:,} runs x {h['broad']['duration']:g} s, seed {h['broad']['seed']}: speed "
                                f"{dr['speed'][0]:g}-{dr['speed'][1]:g} m/s, yaw rate +-{dr['yaw_rate'][1]:g} rad/s, "
                                f"friction {dr['friction'][0]:g}-{dr['friction'][1]:g}, payload "
                                f"{dr['payload'][0]:g}-{dr['payload'][1]:g} kg"))
    return low_friction_figs(low, nom, cond) + [
            dict(what="falls, held-out bounding runs", value=b["failures"], unit=f"of {b['n']:,}", interval=None,
                 **broad),
            dict(what="worst yaw error, held-out bounding runs", value=round(b["yaw_error_worst_deg"], 2), unit="deg",
                 interval=None, **broad)]


def build() -> dict[str, dict]:
    import hyqjax

    presets = {}

    def add(name, kind, description, values, provenance, figures, aliases=()):
        provenance.setdefault("hyqjax", hyqjax.__version__)
        presets[name] = dict(format=FORMAT, name=name, kind=kind, description=description, aliases=list(aliases),
                             values=values, provenance=provenance, figures=figures)

    # ---- crawl ----
    rm = read(REACH_MAP)
    rm_prov = dict(command=map_command(rm["provenance"]["command"]),
                   seed=rm["provenance"]["seed"], device=rm["device"], date=rm["provenance"]["date"][:10],
                   hyqjax=rm["provenance"]["hyqjax"], source=REACH_MAP)
    add("paper", "crawl", "the paper's crawl and Table I reflex (CrawlParams.make()); the step-down default",
        dict(crawl={}, reflex={}),
        dict(rm_prov, command="CrawlParams.make() (Focchi et al. 2017, Table I)", seed=None,
             source="hyqjax/crawl/params.py, hyqjax/reflex/params.py"),
        [reach_fig("default"), reach_fig_0129(21, "--variants default")])
    add("remedy", "crawl", "shin-strike remedy with the trunk at 80% of the feet plane (old --remedy)",
        dict(crawl=dict(shin_remedy=True, terrain_adaptation=0.8), reflex={}),
        dict(rm_prov, command="CrawlParams.make(shin_remedy=True, terrain_adaptation=0.8) (docs/stepdown.md, the "
                              "remedy study)", seed=None, source="hyqjax/crawl/presets.py (REMEDY)"),
        [reach_fig("remedy"), reach_fig_0129(23, "--variants remedy")], aliases=("--remedy",))
    crawl, reflex, res = tuned_shared(REACH_SRC, "snes")
    reach_prov = prov_of(res, REACH_SRC, note="tuned gains of `snes/shared` with the edge probe and depth gate of "
                                               "docs/stepdown.md added")
    add("reach", "crawl", "the recommended reach configuration: reach-trained SNES gains, edge probe and depth gate",
        dict(crawl=dict(crawl, **PROBE), reflex=reflex), reach_prov,
        [reach_fig("snes_reach_probe_deep"), reach_fig_0129(27, "--preset reach"), clean_fig_0129(0.857, "reach")]
        + targets_figs("reach") + targets_figs("reach", root=TARGETS_LF) + confirm_figs("reach"))
    add("tuned_shared", "crawl", "best measured 14-coordinate shared set (SNES, reach-trained, 10 min on one H200)",
        dict(crawl=crawl, reflex=reflex), prov_of(res, REACH_SRC),
        [heldout_fig(res, "snes/shared@10min", "clean success, held-out step-downs", REACH_SRC,
                     prov_of(res, REACH_SRC)["command"])])
    crawl_b, reflex_b, per_leg, res = tuned_per_leg(PER_LEG_SRC, "cma_es/per_leg")
    cmd = prov_of(res, PER_LEG_SRC)["command"]
    add("tuned_per_leg", "crawl", "56-coordinate per-leg set (CMA-ES, 14 coordinates per swing leg, 30 min on one "
        "H200)", dict(crawl=crawl_b, reflex=reflex_b, per_leg=per_leg), prov_of(res, PER_LEG_SRC),
        [clean_fig_0129(0.841, "tuned_per_leg"),
         heldout_fig(res, "cma_es/per_leg@30min", "clean success, held-out step-downs", PER_LEG_SRC, cmd)]
        + targets_figs("tuned_per_leg"))
    src = f"{TARGETS}/run_0/results.json"
    crawl_b, reflex_b, per_leg, res = tuned_per_leg(src, "cma_es/per_leg")
    add("tuned_per_leg_reach", "crawl", "56-coordinate per-leg set: `hyqjax tune` (CMA-ES, 3 min on one H200, "
        "training spread) from `reach`, whose edge probe and depth gate it keeps",
        dict(crawl=crawl_b, reflex=reflex_b, per_leg=per_leg),
        prov_of(res, src), targets_figs("run_0", chosen_on_it=True)
        + [heldout_fig(res, "cma_es/per_leg@3min", "clean success, held-out step-downs", src,
                       prov_of(res, src)["command"])]
        + targets_figs("tuned_per_leg_reach", root=TARGETS_LF) + confirm_figs("tuned_per_leg_reach"))

    src = f"{TARGETS_LF}/run_1/results.json"
    crawl_b, reflex_b, per_leg, res = tuned_per_leg(src, "cma_es/per_leg")
    chosen, selection = chosen_run(TARGETS_LF, "validation_clean", "validation score", (
        "python -m experiments.tune_default_repeats --impl warp --wall-minutes 3 --heldout 256", "seeds 0-4"))
    assert chosen == "run_1", f"the highest validation score is {chosen}'s"
    add("clean", "crawl", "the highest clean success measured: `hyqjax tune` (CMA-ES on 56 per-leg coordinates, 3 min "
        "on one H200, the wide spread, the leading-foot start) from `reach`, whose edge probe and depth gate it keeps",
        dict(crawl=crawl_b, reflex=reflex_b, per_leg=per_leg), prov_of(res, src, selection=selection),
        confirm_figs("run_1") + targets_figs("run_1", root=TARGETS_LF)
        + [heldout_fig(res, "cma_es/per_leg@3min", "clean success, held-out step-downs", src,
                       prov_of(res, src)["command"])])

    src = f"{TARGETS_S01}/run_2/results.json"
    crawl_b, reflex_b, per_leg, res = tuned_per_leg(src, "cma_es/per_leg")
    chosen, selection = chosen_run(TARGETS_S01, "pooled_clean", "pooled validation score", (
        "python -m experiments.tune_default_repeats --impl warp --wall-minutes 3 --heldout 256 --references clean "
        "reach --map-seed 27182 --gpus 2", "seeds 0-4, first step 0.1"))
    assert chosen == "run_2", f"the highest pooled validation score is {chosen}'s"
    refined_confirm = confirm_figs("clean_refined", f"{CONFIRM_S01}/reach_map.json")
    add("clean_refined", "crawl", "`clean` refined by `hyqjax tune`'s default (CMA-ES on 56 per-leg coordinates, "
        "first step 0.1, 3 min on one H200, the wide spread); edge probe and depth gate kept",
        dict(crawl=crawl_b, reflex=reflex_b, per_leg=per_leg), prov_of(res, src, selection=selection),
        refined_confirm + [paired_fig(CONFIRM_S01, "clean_refined", "clean", refined_confirm[0])]
        + targets_figs("run_2", root=TARGETS_S01) + confirm_c_figs("s01_run2")
        + [heldout_fig(res, "cma_es/per_leg@3min", "clean success, held-out step-downs", src,
                       prov_of(res, src)["command"])])

    cond_src = f"{R}/tune_wallclock_h200_10min_68/results.json"
    crawl_c, reflex_c, cond, res = tuned_conditioned(cond_src, "hybrid/per_leg_cond")
    cmd = prov_of(res, cond_src)["command"]
    add("tuned_per_leg_cond", "crawl", "68-coordinate per-leg set conditioned on payload, search depth and steps down "
        "(hybrid search, 10 min on one H200)", dict(crawl=crawl_c, reflex=reflex_c, conditioned=cond),
        prov_of(res, cond_src),
        [heldout_fig(res, "hybrid/per_leg_cond@10min", "clean success, held-out step-downs", cond_src, cmd)])

    # ---- bound ----
    add("bound_paper", "bound", "the paper's bounding gains on the stored limit cycle (the reference cycle's)",
        dict(amplitudes={}, gains={}),
        dict(command="hyqjax.bounding.params.paper_params() (Orsolino et al.; the stored cycle "
                     "hyqjax/bounding/default_cycle.json, hand-set gains DEFAULT_GAINS)", seed=None,
             device=None, date=None, source="hyqjax/bounding/default_cycle.json, hyqjax/bounding/params.py"),
        bound_heldout_fig("default") + bound_presets_figs("bound_paper"))
    refined = f"{R}/bounding_refine_h200/params_refined.json"
    amp, gains, pr = bound_file(refined)
    add("bound_robust", "bound", "bound_robust_8s refined by CMA-ES at the fast corners of the command box with low "
        "friction and a payload; the default of `hyqjax bound`", dict(amplitudes=amp, gains=gains),
        dict(prov_of(read(BOUND_REFINE), refined, method=pr.get("method"),
                     start="bound_robust_8s (the preset's name was bound_robust until this run replaced it)"),
             command=read(BOUND_REFINE)["provenance"]["command"].replace("/root/out/", "out/")),
        bound_refine_figs("refined") + bound_presets_figs("bound_robust", BOUND_PRESETS_H200_5151))
    amp, gains, p8 = bound_file(f"{R}/bounding_robust_h100_8s/params_cma_es.json")
    res8 = read(f"{R}/bounding_robust_h100_8s/results.json")
    add("bound_robust_8s", "bound", "CMA-ES's impulses and gains over commands, friction and payload (8 s training); "
        "bound_robust's start", dict(amplitudes=amp, gains=gains),
        prov_of(res8, f"{R}/bounding_robust_h100_8s/params_cma_es.json", method=p8.get("method")),
        bound_heldout_fig("cma_es") + bound_presets_figs("bound_robust")
        + bound_presets_figs("bound_robust_8s", BOUND_PRESETS_H200_5151),
        aliases=("--params robust_8s",))
    amp, gains, pg = bound_file(f"{R}/bounding_robust_h100/params_gradient.json")
    resg = read(f"{R}/bounding_robust_h100/results.json")
    fg = []
    h = resg["heldout"]
    m = h["methods"]["gradient"]
    d = h["draw"]
    fg.append(dict(what="falls, held-out bounding runs", value=m["failures"], unit=f"of {m['n']:,}", interval=None,
                   heldout=(f"{h['instances']:,} runs x {h['duration']:g} s, seed {h['seed']}: speed "
                            f"{d['speed'][0]:g}-{d['speed'][1]:g} m/s, yaw rate +-{d['yaw_rate'][1]:g} rad/s, friction "
                            f"{d['friction'][0]:g}-{d['friction'][1]:g}, payload {d['payload'][0]:g}-"
                            f"{d['payload'][1]:g} kg"),
                   command="python -m experiments.bounding_robust " + resg["provenance"]["command"].split(
                       "experiments.bounding_robust ", 1)[1], device=resg["device"],
                   date=resg["provenance"]["date"][:10], source=f"{R}/bounding_robust_h100/results.json"))
    add("bound_robust_grad", "bound", "the gradient's (jacfwd + Adam) impulses and gains over commands, friction "
        "and payload (3.2 s training)", dict(amplitudes=amp, gains=gains),
        prov_of(resg, f"{R}/bounding_robust_h100/params_gradient.json", method=pg.get("method")), fg,
        aliases=("--params robust",))
    return presets


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.build_presets", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="compare with the files instead of writing them")
    args = ap.parse_args(argv)
    bad = 0
    for name, d in build().items():
        path = os.path.join(OUT, f"{name}.json")
        text = json.dumps(d, indent=1) + "\n"
        if args.check:
            old = open(path).read() if os.path.exists(path) else None
            if old != text:
                print(f"{rel(path)} differs from the stored results", file=sys.stderr)
                bad = 1
        else:
            with open(path, "w") as f:
                f.write(text)
            print(f"wrote {rel(path)}")
    return bad


if __name__ == "__main__":
    raise SystemExit(main())
