"""The restart rules and the alpha-order blend on analytic objectives with known answers
(hyqjax.studies.tune.study.analytic; a CPU, one to three minutes):

    python -m experiments.tune_restarts_analytic --out out/tune_analytic.json

CMA-ES, IPOP-CMA-ES and BIPOP-CMA-ES on Rastrigin at equal evaluations over seeds (the lowest value each reached),
and the blend against the first-order gradient alone on a quadratic with a hidden step and on a smooth function
(alpha per step, the smoothed objective reached). Prints the tables and writes the JSON.
"""
from __future__ import annotations

import argparse
import os
import sys


def main(argv=None) -> int:
    from hyqjax.cli.app import Parser  # errors in one line

    p = Parser(prog="python -m experiments.tune_restarts_analytic", description=__doc__,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default=None, help="JSON file of the results")
    p.add_argument("--seeds", default="0,1,2,3", help="Rastrigin seeds, comma-separated")
    p.add_argument("--dim", type=int, default=10, help="Rastrigin dimension")
    p.add_argument("--evaluations", type=int, default=20000, help="evaluations per method and seed")
    args = p.parse_args(argv)
    from hyqjax.cli.common import check_range
    from hyqjax.io import atomic

    try:
        seeds = tuple(int(s) for s in args.seeds.split(",") if s.strip())
    except ValueError:
        print(f"tune_restarts_analytic: --seeds must be integers separated by commas, got {args.seeds}",
              file=sys.stderr)
        return 2
    try:
        check_range("--dim", args.dim, 2, 100, integer=True)
        check_range("--evaluations", args.evaluations, 100, 10**7, integer=True)
        if not seeds:
            raise ValueError("--seeds must name at least one seed")
        if args.out:
            atomic.check_writable_dir(os.path.dirname(args.out) or ".", "--out")
    except ValueError as e:
        print(f"tune_restarts_analytic: {e}", file=sys.stderr)
        return 2
    from hyqjax.studies.tune.study import analytic

    rc = analytic.restart_comparison(seeds, args.dim, args.evaluations)
    bc = analytic.blend_comparison()
    print(analytic.markdown(rc, bc))
    if args.out:
        atomic.write_json(args.out, dict(restarts=rc, blend=bc))
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
