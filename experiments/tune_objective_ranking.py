"""How the gradient's window objective ranks the iterates of tuning study runs (hyqjax.studies.tune.study.ranking).

    python -m experiments.tune_objective_ranking DIR [DIR ...] --out ranking.json

Every DIR is an equal-wall-clock study directory with its held-out evaluation. Every held-out-evaluated iterate
(the start point and every checkpoint of every run) is evaluated with the closed-loop window objective on one
fixed set of start-point windows (MJX-JAX, any machine); prints the iterates by held-out clean success with the
objective and its weighted terms, and Spearman's rank correlation of each with held-out clean success (a useful
objective, lower is better, correlates negatively).
"""
from __future__ import annotations

import argparse
import json
import os
import sys


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.tune_objective_ranking", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", help="study directories with a held-out evaluation")
    p.add_argument("--out", default=None, help="JSON file for the result")
    args = p.parse_args(argv)
    from hyqjax.studies.tune.study import handset

    results = []
    for d in args.dirs:
        try:
            with open(os.path.join(d, "results.json")) as f:
                res = json.load(f)
        except (OSError, ValueError) as e:
            print(f"tune_objective_ranking: {d}: no readable results.json ({e})", file=sys.stderr)
            return 2
        try:
            handset.check_study(res)
        except ValueError as e:
            print(f"tune_objective_ranking: {d}: {e}", file=sys.stderr)
            return 2
        results.append(res)
    from hyqjax.io import atomic
    from hyqjax.studies.tune.study import ranking

    out = ranking.rank_iterates(results, list(args.dirs))
    out["dirs"] = list(args.dirs)
    print(ranking.table(out))
    if args.out:
        atomic.write_json(args.out, out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
