"""The equal-wall-clock study as one grid of (method, parameterisation) cells at one budget
(hyqjax.studies.tune.study.cells), gathered from the directories (or results files) of the runs that made it.

    python -m experiments.tune_cells docs/results/tune_cells_h200_10min/cma_es_per_leg docs/results/tune_cells_h200_10min/snes_per_leg --minutes 10 --figure out/tune_cells.png

Prints the markdown table (one run per cell: its Wilson interval; several seeds: the interval over runs; not
completed and diverged counts in every cell) and writes the figure and, with ``--out``, the JSON. Inputs of
another configuration (but for seed, methods, parameterisations and gradient mode), device or held-out set are
refused in one line.
"""
from __future__ import annotations

import argparse
import os
import sys


def main(argv=None) -> int:
    from hyqjax.cli.app import Parser  # errors in one line

    p = Parser(prog="python -m experiments.tune_cells", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", help="study directories or results files")
    p.add_argument("--minutes", type=float, default=10.0, help="the budget (a checkpoint of every run)")
    p.add_argument("--figure", default=None, help="PNG of the grid")
    p.add_argument("--out", default=None, help="JSON file for the grid")
    args = p.parse_args(argv)
    from hyqjax.cli.common import check_range
    from hyqjax.io import atomic
    from hyqjax.studies.tune.study import cells, repeats

    try:
        check_range("--minutes", args.minutes, 0.0, 600.0, "min", lo_open=True)
        for option, path in (("--figure", args.figure), ("--out", args.out)):
            if path:
                atomic.check_writable_dir(os.path.dirname(path) or ".", option)
        grid = cells.gather([repeats.load(d) for d in args.inputs], list(args.inputs), args.minutes)
    except ValueError as e:
        print(f"tune_cells: {e}", file=sys.stderr)
        return 2
    if not grid["cells"]:
        print(f"tune_cells: no run has a held-out result at {args.minutes:g} min", file=sys.stderr)
        return 2
    print(cells.markdown(grid))
    if args.figure:
        print(f"wrote {cells.plot(grid, args.figure)}")
    if args.out:
        atomic.write_json(args.out, dict(inputs=list(args.inputs), **grid))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
