"""Budget curves of several equal-wall-clock study runs in one figure: held-out clean and completed success
against wall-clock minutes and physics steps (:func:`hyqjax.studies.tune.figure.plot_wallclock`), one curve per
(method, parameterisation) of the runs given (one directory or results file each).

    python -m experiments.tune_budget_curves docs/results/tune_cells_h200_30min/cma_es_shared_30min docs/results/tune_cells_h200_30min/random_search_shared_30min docs/results/tune_cells_h200_30min/cma_es_per_leg_30min docs/results/tune_cells_h200_30min/snes_per_leg_30min --figure docs/img/tune_30min_h200.png

The runs must be of one configuration but for seed, methods, parameterisations and gradient mode, on one kind of
device and the same held-out set (as ``experiments.tune_cells`` requires); the Table I and start-point bands are
the first run's (every run evaluates them on the same held-out set). The same (method, parameterisation) given
twice is refused: give one run of each.
"""
from __future__ import annotations

import argparse
import os
import sys


def merge(results: list[dict], names: list[str]) -> dict:
    """One results dict whose ``budget_curves`` are those of every run in ``results`` (checked comparable,
    module docstring), with the first run's held-out Table I and start point."""
    from hyqjax.studies.tune.study import cells, repeats

    repeats.check_comparable(results, names, cells.FREE_SETTINGS)
    cells.check_one_device(results)
    curves, seen = [], {}
    for res, name in zip(results, names):
        for c in res.get("budget_curves", []):
            key = (c["method"], c["dim"])
            if key in seen:
                raise ValueError(f"{name} and {seen[key]} both hold {key[0]} on {key[1]}; give one run of each")
            seen[key] = name
            curves.append(c)
    first = results[0]
    heldout = {k: v for k, v in first.get("heldout", {}).items() if k in ("table1", "start")}
    return dict(device=first.get("device"), impl=first.get("impl"), heldout_set=first.get("heldout_set"),
                heldout=heldout, budget_curves=curves)


def main(argv=None) -> int:
    from hyqjax.cli.app import Parser  # errors in one line

    p = Parser(prog="python -m experiments.tune_budget_curves", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", help="study directories or results files")
    p.add_argument("--figure", required=True, help="PNG of the budget curves")
    args = p.parse_args(argv)
    from hyqjax.io.atomic import check_writable_dir
    from hyqjax.studies.tune import figure
    from hyqjax.studies.tune.study import repeats

    try:
        check_writable_dir(os.path.dirname(args.figure) or ".", "--figure")
        res = merge([repeats.load(d) for d in args.inputs], list(args.inputs))
    except ValueError as e:
        print(f"tune_budget_curves: {e}", file=sys.stderr)
        return 2
    if not res["budget_curves"]:
        print("tune_budget_curves: no run has a held-out budget curve", file=sys.stderr)
        return 2
    print(f"wrote {figure.plot_wallclock(res, args.figure)} ({len(res['budget_curves'])} curves)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
