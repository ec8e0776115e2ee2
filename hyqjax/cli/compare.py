"""Compare two sweep stores of the same spec (a baseline and a new run): did the robot get worse?

Per grid cell and outcome level (completed, clean), and pooled over all cells, the difference of the rates
NEW - BASE with Newcombe's 95% interval and a test: McNemar's exact test on the paired outcomes where the
instances are the same (the same spec and seed give the same instances, common random numbers; checked on the
input columns stored in the rows), Fisher's exact test otherwise. The p-values are Holm-corrected together
(family-wise error rate --alpha), so an unchanged controller fails a build with probability at most --alpha
(and never when its outcomes are identical). Verdict per test, per cell and overall: regressed, improved or no
significant change. Stores of different specs (--allow-change names a [fixed] axis or the seed changed on
purpose), schemas or outcome columns are refused naming the difference; a damaged or incomplete store is refused
naming its chunks (`hyqjax verify`). --expect checks expectations on NEW as `hyqjax sweep --expect` does.

Exit status: 0 no regression (and every expectation met), 1 regressed (or an expectation failed), 3 an
expectation inconclusive, 2 refused. docs/ci.md.

Examples:

    hyqjax compare out/ci_base out/ci_new
    hyqjax compare out/ci_base out/ci_new --junit out/compare.xml --markdown out/compare.md --json out/compare.json
"""
from __future__ import annotations

import argparse
import os

NAME = "compare"
HELP = "compare two sweep stores (paired McNemar / Newcombe per cell, Holm): regressed, improved or no change"
ORDER = 22


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter
    from hyqjax.cli.gate_options import add_gate_arguments

    use_help_formatter(p)
    p.add_argument("base", help="the baseline sweep's --out directory")
    p.add_argument("new", help="the new sweep's --out directory (same spec)")
    add_gate_arguments(p)


def validate(args) -> None:
    from hyqjax.cli.gate_options import validate_gate
    from hyqjax.studies.sweep.verify import is_sweep_dir

    for role, d in (("BASE", args.base), ("NEW", args.new)):
        if not os.path.isdir(d):
            raise ValueError(f"{role} {d} is not a directory (give a sweep's --out directory)")
        if not is_sweep_dir(d):
            raise ValueError(f"{role} {d} holds no sweep (no manifest.json, no chunks/)")
    validate_gate(args)
    args.options_checked = True


def run(args) -> int:
    from hyqjax.cli.gate_options import finish
    from hyqjax.studies.sweep import expect
    from hyqjax.studies.sweep.compare import compare_stores
    from hyqjax.studies.sweep.gate import Verdict
    from hyqjax.studies.sweep.store import open_store

    if not getattr(args, "options_checked", False):
        validate(args)
    cmp = compare_stores(args.base, args.new, alpha=args.alpha, allow_change=args.allow_change)
    checks = []
    if args.expectations:
        st = open_store(args.new)
        expect.check_selects(args.expectations, st.spec)
        checks = expect.evaluate(args.expectations, st.spec, st.load())
    verdict = Verdict(checks, cmp, args.inconclusive, title=f"hyqjax compare {args.base} {args.new}")
    return finish(args, verdict)
