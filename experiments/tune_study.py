"""The equal-wall-clock tuning study (``hyqjax tune --study``; hyqjax.studies.tune.wallclock, docs/tuning.md).

    python -m experiments.tune_study --out out/tune_study --impl warp --wall-minutes 0.25 0.5   # ~12 min, one H100
    python -m experiments.tune_study --out out/tune_study --impl warp --wall-minutes 1 3 10     # the full curves

Every option of ``hyqjax tune`` applies (``--methods``, ``--dims``, ``--popsize``, ``--train-instances``,
``--heldout``, ...); bad settings are refused in one line before anything compiles, and the same command on the
same ``--out`` resumes without losing finished runs or held-out chunks.
"""
from __future__ import annotations

import sys


def main(argv=None) -> int:
    from hyqjax.cli.app import main as hyqjax_main

    return hyqjax_main(["tune", "--study", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
