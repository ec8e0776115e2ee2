"""Build one self-contained HTML report from an experiment's output directory (or a sweep of them).

Reads DIR/results.json (and every results.json, or sweep summary.json, in DIR and its
subdirectories) and writes
DIR/report.html: the exact command, seed and versions; the step-down table and failed instances,
the bounding tracking table and ablation contributions, or a sweep's success per reflex setting and
largest safe height; every PNG figure in the directory; and
the stills and videos that ``hyqjax render --stills N`` wrote to DIR/render/. Images are embedded,
so the page is a single file. Run ``hyqjax render DIR --stills 4`` first to include frames.
"""
from __future__ import annotations

import argparse
import os

NAME = "report"
HELP = "one self-contained HTML page from an experiment's output directory (tables, figures, render stills)"
ORDER = 70


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", help="experiment output directory (with results.json) or a directory of them")
    p.add_argument("--out", default=None, help="output HTML file (default: DIR/report.html)")
    p.add_argument("--title", default=None, help="page title (default: 'hyqjax results: DIR')")
    p.add_argument("--max-embed-mb", type=float, default=8.0,
                   help="embed videos up to this size (MB), link larger ones; in [0, 1000]")


def run(args) -> int:
    if not os.path.isdir(args.dir):
        raise SystemExit(f"hyqjax {NAME}: DIR {args.dir} is not a directory (give an experiment's --out directory)")
    if not (0 <= args.max_embed_mb <= 1000):
        raise SystemExit(f"hyqjax {NAME}: --max-embed-mb must be in [0, 1000], got {args.max_embed_mb}")
    if args.out and not args.out.lower().endswith((".html", ".htm")):
        raise SystemExit(f"hyqjax {NAME}: --out must end in .html, got {args.out}")
    from hyqjax import report

    try:
        path, dirs = report.build_report(args.dir, args.out, args.title, args.max_embed_mb)
    except FileNotFoundError as err:
        raise SystemExit(f"hyqjax {NAME}: {err}") from None
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.1f} MB) from {len(dirs)} results.json: "
          + ", ".join(os.path.relpath(d, args.dir) for d in dirs))
    return 0
