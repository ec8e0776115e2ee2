"""Repeated runs of the equal-wall-clock tuning study, compared over runs (hyqjax.studies.tune.study.repeats).

    python -m experiments.tune_repeats out/tune_s0 out/tune_s1 out/tune_s2 --minutes 10 --out out/tune_repeats.json

Each DIR is a study directory (``python -m experiments.tune_study --out DIR --seed S ...``) of one configuration
but for its seed and methods, evaluated on the same held-out set. Prints, per method and parameterisation, the
held-out clean rate of every run, their mean with the 95% Student-t interval over runs, and which members it is
apart from (its interval above theirs); writes the same as JSON.
"""
from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    from hyqjax.cli.app import Parser  # errors in one line

    p = Parser(prog="python -m experiments.tune_repeats", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", help="study directories (one run each, or several methods per directory)")
    p.add_argument("--minutes", type=float, default=10.0, help="the budget (a checkpoint of every run)")
    p.add_argument("--out", default=None, help="JSON file for the summary")
    args = p.parse_args(argv)
    from hyqjax.cli.common import check_range
    from hyqjax.io import atomic
    from hyqjax.studies.tune.study import repeats

    try:
        check_range("--minutes", args.minutes, 0.0, 600.0, "min", lo_open=True)
        results = [repeats.load(d) for d in args.dirs]
        summary = repeats.collect(results, list(args.dirs), args.minutes)
    except ValueError as e:
        print(f"tune_repeats: {e}", file=sys.stderr)
        return 2
    if not summary:
        print(f"tune_repeats: no run has a held-out result at {args.minutes:g} min", file=sys.stderr)
        return 2
    print(repeats.table(summary, args.minutes))
    if args.out:
        atomic.write_json(args.out, dict(minutes=args.minutes, dirs=list(args.dirs), members=summary,
                                         differences=repeats.differences(summary)))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
