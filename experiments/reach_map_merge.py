"""One reach map from several made in parts: the same step-downs, other variants in each part.

    python -m experiments.reach_map_merge PART [PART ...] --out DIR

A reach map (``python -m experiments.reach_map``) draws its instances from ``--seed``, ``--instances``, the heights
and the spreads alone, so maps of other variants made with the same settings ran the same step-downs: variants run
in separate sessions, on other machines or after a study gained a run can be judged and paired together. Every
part must have the same drawing settings (seed, instances, heights, spreads, duration, episode end, start pose) and
the same simulator, and must have drawn the same scenario for every (spread, height, instance), which is checked row
by row. A variant in several parts must have the same parameters and the same outcome in every run (C MuJoCo
repeats a batch bit for bit; MuJoCo Warp does not promise to, docs/warp.md): it is kept once, and a part that
disagrees is refused, naming the variant and the runs that differ.

Writes ``DIR/reach_map.json`` (the cells recomputed from the merged rows by :func:`reach_map.summarise`, the first
part's configuration with every part's variants, and ``merged_from``: each part's directory, provenance, device, wall
and physics steps; ``wall_s`` and ``physics_steps`` are the parts' sums, what the map cost), ``DIR/reach_instances.npz``
(every row once) and ``DIR/reach_map.png``: the map ``python -m experiments.paired_map DIR`` and
``python -m experiments.tune_default_repeats --judge-only --heldout-dir DIR`` read.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np

from experiments.reach_map import row_keys

#: Configuration keys that decide which step-downs a map runs and how: equal in every part.
DRAW_KEYS = ("start_pose", "instances", "heights", "spreads", "seed", "duration", "terminate")
#: Columns of reach_instances.npz that describe a row's scenario (the rest, ``out_*``, are its outcome).
SCENARIO_KEYS = ("height", "reflex", "friction", "payload_mass", "payload_com", "start_distance", "lateral_offset",
                 "yaw")


class MergeError(ValueError):
    """A part that cannot be merged: one line naming the part and why."""


def load_part(path: str) -> tuple[dict, dict]:
    """A part's ``reach_map.json`` and ``reach_instances.npz`` columns."""
    try:
        with open(os.path.join(path, "reach_map.json")) as f:
            meta = json.load(f)
        with np.load(os.path.join(path, "reach_instances.npz"), allow_pickle=False) as z:
            table = {k: z[k] for k in z.files}
    except (OSError, ValueError) as e:
        raise MergeError(f"{path}: not a finished reach map ({e.__class__.__name__}: {e})") from None
    if "config" not in meta or "variant" not in table:
        raise MergeError(f"{path}: not a finished reach map (no config or no rows)")
    return meta, table


def merge(parts: list[tuple[str, dict, dict]]) -> tuple[dict, dict, list[str]]:
    """Merge ``(path, meta, table)`` parts (module docstring): the merged configuration, the rows (every variant's
    once) and a line per variant found in several parts. Raises :class:`MergeError`."""
    if len(parts) < 2:
        raise MergeError("give at least two parts")
    path0, meta0, table0 = parts[0]
    cfg0 = meta0["config"]
    # the scenario of each (spread, height, instance), from the first part's first variant
    scen = {}
    for path, meta, table in parts:
        cfg = meta["config"]
        for k in DRAW_KEYS:
            if cfg.get(k) != cfg0.get(k):
                raise MergeError(f"{path}: its {k} ({cfg.get(k)!r}) is not {path0}'s ({cfg0.get(k)!r}); parts must "
                                 "draw the same step-downs")
        if meta.get("impl") != meta0.get("impl"):
            raise MergeError(f"{path}: simulator {meta.get('impl')!r}, {path0}'s is {meta0.get('impl')!r}; parts must "
                             "run on one simulator")
        first = np.flatnonzero(table["variant"] == table["variant"][0])
        for key, i in zip(row_keys(table, first), first):
            row = tuple(np.asarray(table[c][i]).tobytes() for c in SCENARIO_KEYS if c in table)
            if scen.setdefault(key, row) != row:
                raise MergeError(f"{path}: the step-down {key} differs from {path0}'s: parts must draw the same "
                                 "step-downs (another code version?)")
    cols = sorted(table0)
    kept: dict[str, tuple[str, np.ndarray, dict]] = {}  # variant -> (part, its rows, its table)
    notes = []
    params = {}
    for path, meta, table in parts:
        if sorted(table) != cols:
            raise MergeError(f"{path}: its columns differ from {path0}'s (another code version?)")
        for v in dict.fromkeys(table["variant"].tolist()):
            rows = np.flatnonzero(table["variant"] == v)
            p = meta["config"].get("params", {}).get(v)
            if v not in kept:
                kept[v] = (path, rows, table)
                params[v] = p
                continue
            path_k, rows_k, table_k = kept[v]
            if p != params[v]:
                raise MergeError(f"{path}: variant {v} has other parameters than in {path_k}: give it another name")
            order_k = dict(zip(row_keys(table_k, rows_k), rows_k))
            keys = row_keys(table, rows)
            if set(keys) != set(order_k):
                raise MergeError(f"{path}: variant {v} ran other step-downs than in {path_k}")
            mine = np.asarray(rows)
            theirs = np.asarray([order_k[k] for k in keys])
            differ = np.zeros(len(mine), bool)
            for c in cols:
                if c.startswith("out_"):
                    a, b = table[c][mine], table_k[c][theirs]
                    same = (a == b) | (np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f" else (a == b)
                    differ |= ~same.reshape(len(mine), -1).all(axis=1)
            if differ.any():
                flips = int((table["out_clean"][mine] != table_k["out_clean"][theirs]).sum())
                raise MergeError(f"{path}: variant {v} differs from {path_k} in {int(differ.sum())} of {len(mine)} "
                                 f"runs (clean in {flips}): a simulator that does not repeat a batch, or another code "
                                 "version")
            notes.append(f"{v}: in {path_k} and {path}, the same outcome in all {len(mine)} runs (kept once)")
    merged = {c: np.concatenate([t[c][r] for _, r, t in kept.values()]) for c in cols}
    variants = list(kept)
    config = dict(cfg0, variants=variants, params=params,
                  custom=[c for _, m, _ in parts for c in m["config"].get("custom") or []],
                  tuned_runs=[c for _, m, _ in parts for c in m["config"].get("tuned_runs") or []])
    return config, merged, notes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.reach_map_merge", description=__doc__.split("\n\n")[0],
                                 epilog="Details: the module's docstring.")
    ap.add_argument("parts", nargs="+", help="finished reach maps (their --out directories)")
    ap.add_argument("--out", required=True, help="directory of the merged map (not one of the parts)")
    a = ap.parse_args(argv)
    try:
        if any(os.path.abspath(p) == os.path.abspath(a.out) for p in a.parts):
            raise MergeError(f"--out {a.out}: one of the parts; give a new directory")
        parts = [(p, *load_part(p)) for p in a.parts]
        config, rows, notes = merge(parts)
    except MergeError as e:
        print(f"reach_map_merge: {e}", file=sys.stderr)
        return 2
    from experiments import reach_map
    from hyqjax.io import atomic

    out = {k[4:]: v for k, v in rows.items() if k.startswith("out_")}
    scenario = {k: v for k, v in rows.items() if not k.startswith("out_")}
    spreads = list(config["spreads"])
    cells = reach_map.summarise(scenario, out, config["variants"], spreads)
    os.makedirs(a.out, exist_ok=True)
    fig = reach_map.plot(cells, os.path.join(a.out, "reach_map.png"))
    metas = [m for _, m, _ in parts]
    # reach_map resumes a map whose config.json holds its configuration's hash; a merged map has none, so this one
    # makes reach_map refuse --out DIR instead of running the map again over it
    atomic.write_json(os.path.join(a.out, "config.json"), dict(config_hash="merged", merged_from=list(a.parts)))
    reach_map.write_map(a.out, rows, dict(
        provenance=atomic.provenance(seed=config["seed"]), config=config, device=metas[0].get("device"),
        devices=metas[0].get("devices"), impl=metas[0].get("impl"), n_instances=len(rows["variant"]),
        wall_s=sum(m.get("wall_s") or 0.0 for m in metas),
        physics_steps=sum(m.get("physics_steps") or 0 for m in metas),
        merged_from=[dict(dir=p, provenance=m.get("provenance"), device=m.get("device"), wall_s=m.get("wall_s"),
                          physics_steps=m.get("physics_steps"), variants=m["config"].get("variants"))
                     for p, m, _ in parts],
        cells=cells, figure=os.path.basename(fig)))
    for n in notes:
        print(n)
    print(reach_map.format_cells(cells))
    print(f"merged {len(parts)} maps, {len(config['variants'])} variants, {len(rows['variant'])} runs: "
          f"{a.out}/reach_map.json, {fig}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
