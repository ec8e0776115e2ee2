"""Build one self-contained HTML report from an experiment's output directory (or a sweep of them).

Reads DIR/results.json (and every results.json, or sweep summary.json, in DIR and its
subdirectories) and writes
DIR/report.html: the exact command, seed and versions; the step-down table and failed instances,
the bounding tracking table and ablation contributions, or a sweep's success per reflex setting and
largest safe height; every PNG figure in the directory; and
the stills and videos that ``hyqjax render --stills N`` wrote to DIR/render/. Images are embedded,
so the page is a single file. Run ``hyqjax render DIR --stills 4`` first to include frames.
Every sweep store is verified (``hyqjax verify``): a damaged one is marked on the page and named on
stderr, and the command exits with status 1.

Examples:
  hyqjax report out/stepdown                   # out/stepdown/report.html
  hyqjax report out --out out/all.html         # every experiment under out/ on one page
"""
from __future__ import annotations

import argparse
import os

NAME = "report"
HELP = "one self-contained HTML page from an experiment's output directory (tables, figures, render stills)"
ORDER = 70


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter

    use_help_formatter(p)
    p.add_argument("dir", help="experiment output directory (with results.json) or a directory of them")
    p.add_argument("--out", default=None, help="output HTML file (default: DIR/report.html)")
    p.add_argument("--title", default=None, help="page title (default: 'hyqjax results: DIR')")
    p.add_argument("--max-embed-mb", type=float, default=8.0,
                   help="embed videos up to this size (MB), link larger ones; in [0, 1000]")


def validate(args) -> None:
    """Options checked and every results.json / summary.json read before anything is written: a damaged one is
    named and the command stops (exit status 2) instead of writing a report around it."""
    import json

    from hyqjax.cli.common import check_range, prepare_out

    if not os.path.isdir(args.dir):
        raise ValueError(f"DIR {args.dir} is not a directory (give an experiment's --out directory)")
    check_range("--max-embed-mb", args.max_embed_mb, 0, 1000, "MB")
    if args.out and not args.out.lower().endswith((".html", ".htm")):
        raise ValueError(f"--out must end in .html, got {args.out}")
    from hyqjax.io import report

    dirs = report.find_result_dirs(args.dir)
    if not dirs:
        raise ValueError(f"DIR {args.dir}: no {report.RESULTS_FILE} or {report.SWEEP_FILE} in it or its "
                         f"subdirectories (run an experiment with --out {args.dir})")
    for d in dirs:
        for name in (report.RESULTS_FILE, report.SWEEP_FILE):
            p = os.path.join(d, name)
            if os.path.isfile(p):
                try:
                    with open(p, "rb") as f:
                        obj = json.loads(f.read().decode("utf-8"))
                except (ValueError, UnicodeDecodeError) as e:
                    raise ValueError(f"{p} is not valid JSON ({str(e)[:80]}): damaged or truncated; run the "
                                     f"experiment again to rewrite it") from None
                if not isinstance(obj, dict):
                    raise ValueError(f"{p} is not a hyqjax results file (a JSON object expected)")
    prepare_out(os.path.dirname(os.path.abspath(args.out)) if args.out else args.dir, "--out")
    args.options_checked = True


def run(args) -> int:
    if not getattr(args, "options_checked", False):
        validate(args)
    from hyqjax.cli import verify
    from hyqjax.io import report

    checks = verify.check_dirs(report.find_result_dirs(args.dir))  # every sweep store verified, damage named
    path, dirs = report.build_report(args.dir, args.out, args.title, args.max_embed_mb,
                                     checks={d: (c.ok, c.lines()) for d, c in checks.items()})
    files = [os.path.normpath(os.path.join(d, name)) for d in dirs for name in (report.RESULTS_FILE, report.SWEEP_FILE)
             if os.path.isfile(os.path.join(d, name))]
    print(f"wrote {path} ({os.path.getsize(path) / 1e6:.1f} MB) from {len(files)} result file(s): " + ", ".join(files))
    return verify.tell(checks, "hyqjax report")
