"""Paired differences of a reach map's variants against one of them, run by run on the same instances.

    python -m experiments.paired_map DIR --reference clean                   # DIR: a reach map's --out
    python -m experiments.paired_map DIR --reference clean --max-height 0.26 --level clean completed

Every variant of a reach map (``python -m experiments.reach_map``) runs the same instances of each (spread, height)
cell (common random numbers), so two variants' outcomes pair up instance by instance. For each variant ``v`` and
outcome level (clean, completed) over the pooled cells up to ``--max-height`` and per height:

* ``d = (b - c) / n``, where of the ``n`` paired instances ``b`` succeed with ``v`` and fail with the reference and
  ``c`` the reverse (the difference of the two success rates);
* its 95% interval by Newcombe's method for paired proportions (Wilson intervals combined through the pairs'
  correlation; :func:`paired_difference`);
* the two-sided exact McNemar p-value of ``b`` and ``c`` (:func:`hyqjax.studies.sweep.compare.mcnemar_exact`).

A paired test sees a difference that two independent intervals hide: most instances succeed or fail with both sets,
and only the discordant ones carry information. Diverged instances count as failures, as everywhere in the map.
Reads ``DIR/reach_instances.npz``; writes ``DIR/paired_<reference>.json`` and ``.md``.
"""
from __future__ import annotations

import math
import os
import sys

import numpy as np

from hyqjax.cli.common import HelpFormatter, UsageError

LEVELS = ("clean", "completed")


def parse(argv=None):
    from hyqjax.cli.app import Parser

    ap = Parser(prog="python -m experiments.paired_map", description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("map_dir", help="a reach map's output directory (holding reach_instances.npz)")
    ap.add_argument("--reference", required=True, help="the variant every other one is paired against")
    ap.add_argument("--max-height", type=float, default=0.26,
                    help="the pooled row covers heights up to this (m); per-height rows cover every height")
    ap.add_argument("--level", nargs="+", default=list(LEVELS), help="outcome levels: clean, completed")
    args = ap.parse_args(argv)
    if not 0.0 < args.max_height <= 1.0:
        raise UsageError(f"--max-height must be in (0, 1] m, got {args.max_height}")
    bad = [lv for lv in args.level if lv not in LEVELS]
    if bad:
        raise UsageError(f"--level must be among {', '.join(LEVELS)}, got {', '.join(bad)}")
    path = os.path.join(args.map_dir, "reach_instances.npz")
    if not os.path.exists(path):
        raise UsageError(f"map_dir {args.map_dir}: no reach_instances.npz (give a finished reach map's --out)")
    return args


def paired_difference(a, b, confidence: float = 0.95) -> dict:
    """Paired comparison of the boolean outcome arrays ``a`` (the variant) and ``b`` (the reference), aligned
    instance by instance: ``d = mean(a) - mean(b) = (n10 - n01) / n``, its interval by Newcombe's method for paired
    proportions (Newcombe 1998, Stat. Med. 17, method 10: the two Wilson intervals combined with the continuity-
    corrected phi of the 2 x 2 table; it stays within [-1, 1] and keeps its coverage with few discordant pairs, where
    the Wald interval does not), and the exact McNemar p-value of the discordant counts ``n10`` (a only) and ``n01``
    (b only)."""
    from hyqjax.studies.statistics import wilson_interval
    from hyqjax.studies.sweep.compare import mcnemar_exact

    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError(f"paired outcomes need one shape, got {a.shape} and {b.shape}")
    n = int(a.size)
    n11, n10, n01 = int((a & b).sum()), int((a & ~b).sum()), int((~a & b).sum())
    n00 = n - n11 - n10 - n01
    if n == 0:
        return dict(n=0, variant=float("nan"), reference=float("nan"), d=float("nan"), ci95=[float("nan")] * 2,
                    only_variant=0, only_reference=0, p_mcnemar=1.0)
    p1, p2 = (n11 + n10) / n, (n11 + n01) / n
    l1, u1 = wilson_interval(n11 + n10, n, confidence)
    l2, u2 = wilson_interval(n11 + n01, n, confidence)
    den = (n11 + n10) * (n01 + n00) * (n11 + n01) * (n10 + n00)
    num = n11 * n00 - n10 * n01
    if den == 0:
        phi = 0.0
    elif num > 0:
        phi = max(num - n / 2.0, 0.0) / math.sqrt(den)
    else:
        phi = num / math.sqrt(den)
    d = p1 - p2
    lo2 = (p1 - l1) ** 2 - 2.0 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2
    hi2 = (u1 - p1) ** 2 - 2.0 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2
    ci = [max(-1.0, d - math.sqrt(max(lo2, 0.0))), min(1.0, d + math.sqrt(max(hi2, 0.0)))]
    return dict(n=n, variant=p1, reference=p2, d=d, ci95=ci, only_variant=n10, only_reference=n01,
                p_mcnemar=mcnemar_exact(n10, n01))


def aligned(table: dict, variant: str, reference: str):
    """The row indices of ``variant`` and ``reference`` in ``table`` (reach_instances.npz's columns) ordered so that
    row ``i`` of both is the same (spread, height, instance); refuses maps whose two variants ran other instances."""
    from experiments.reach_map import row_keys

    def keyed(name):
        m = np.flatnonzero(table["variant"] == name)
        return dict(zip(row_keys(table, m), m))

    kv, kr = keyed(variant), keyed(reference)
    if set(kv) != set(kr):
        raise ValueError(f"variants {variant} and {reference} ran different instances ({len(kv)} and {len(kr)}); "
                         f"they cannot be paired")
    keys = sorted(kv)
    for col in ("friction", "payload_mass", "start_distance", "lateral_offset", "yaw"):
        if col in table and not np.array_equal(table[col][[kv[k] for k in keys]], table[col][[kr[k] for k in keys]]):
            raise ValueError(f"variants {variant} and {reference} drew different {col} for the same instance")
    return np.array([kv[k] for k in keys], int), np.array([kr[k] for k in keys], int)


def compare(table: dict, reference: str, max_height: float = 0.26, levels=LEVELS) -> dict:
    """Every variant of ``table`` against ``reference``: per level, the pooled row over heights up to
    ``max_height`` and one row per height (:func:`paired_difference`)."""
    variants = [v for v in dict.fromkeys(table["variant"].tolist()) if v != reference]
    if reference not in set(table["variant"].tolist()):
        raise ValueError(f"--reference {reference} is not a variant of this map: "
                         f"{', '.join(dict.fromkeys(table['variant'].tolist()))}")
    out = dict(reference=reference, max_height=max_height, variants={})
    for v in variants:
        iv, ir = aligned(table, v, reference)
        h = np.round(table["height"][iv], 6)
        row = {}
        for lv in levels:
            a, b = table[f"out_{lv}"][iv], table[f"out_{lv}"][ir]
            pool = h <= max_height + 1e-9
            row[lv] = dict(pooled=paired_difference(a[pool], b[pool]),
                           per_height={f"{x:g}": paired_difference(a[h == x], b[h == x]) for x in sorted(set(h))})
        row["diverged"] = int(table["out_diverged"][iv].sum())
        out["variants"][v] = row
    out["reference_diverged"] = int(table["out_diverged"][table["variant"] == reference].sum())
    return out


def markdown(res: dict) -> str:
    """The pooled rows (left out, with a line saying so, when the map has no height up to ``max_height``) and, per
    level, one line per variant with every height's difference."""
    ref, hmax = res["reference"], res["max_height"]
    levels = [lv for lv in LEVELS if any(lv in row for row in res["variants"].values())]
    pooled = [(v, lv, row[lv]["pooled"]) for v, row in res["variants"].items() for lv in levels if lv in row]
    head = (f"paired against `{ref}` on the same instances (d = variant - reference, 95% paired interval; McNemar "
            f"exact p)")
    if any(p["n"] for _, _, p in pooled):
        lines = [f"{head}; heights up to {100 * hmax:g} cm pooled", "",
                 "| variant | level | n | variant | reference | d [95%] | only variant / only reference | p |",
                 "|---|---|---:|---:|---:|---|---|---:|"]
        for v, lv, p in pooled:
            lines.append(f"| {v} | {lv} | {p['n']:,} | {p['variant']:.3f} | {p['reference']:.3f} | {p['d']:+.3f} "
                         f"[{p['ci95'][0]:+.3f}, {p['ci95'][1]:+.3f}] | {p['only_variant']} / "
                         f"{p['only_reference']} | {p['p_mcnemar']:.2g} |")
    else:
        lines = [head, "", f"no height up to {100 * hmax:g} cm in this map: no pooled rows (--max-height)"]
    for lv in levels:
        lines += ["", f"per height ({lv}): variant / reference, d [95%], p", ""]
        for v, row in res["variants"].items():
            if lv not in row:
                continue
            cells = [f"{100 * float(h):g} cm {x['variant']:.3f} / {x['reference']:.3f}, {x['d']:+.3f} "
                     f"[{x['ci95'][0]:+.3f}, {x['ci95'][1]:+.3f}] p {x['p_mcnemar']:.2g}"
                     for h, x in row[lv]["per_height"].items()]
            lines.append(f"- {v}: " + "; ".join(cells))
    lines.append("")
    lines.append(f"diverged: {ref} {res['reference_diverged']}, "
                 + ", ".join(f"{v} {row['diverged']}" for v, row in res["variants"].items()))
    return "\n".join(lines)


def main(argv=None) -> int:
    from hyqjax.io.atomic import atomic_write, write_json

    try:
        args = parse(argv)
        with np.load(os.path.join(args.map_dir, "reach_instances.npz"), allow_pickle=False) as z:
            table = {k: z[k] for k in z.files}
        res = compare(table, args.reference, args.max_height, tuple(args.level))
    except (UsageError, ValueError) as e:
        print(f"paired_map: {e}", file=sys.stderr)
        return 2
    base = os.path.join(args.map_dir, f"paired_{args.reference}")
    write_json(base + ".json", res)
    text = markdown(res)
    atomic_write(base + ".md", lambda f: f.write((text + "\n").encode()))
    print(text)
    print(f"wrote {base}.json and {base}.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
