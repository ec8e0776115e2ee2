"""The CI gate's options, shared by ``hyqjax sweep`` and ``hyqjax compare`` (no command of its own).

``--expect EXPR`` (repeatable; :mod:`hyqjax.studies.sweep.expect`), ``--inconclusive fail|pass|report``, the
baseline comparison's ``--alpha`` and ``--allow-change`` (:mod:`hyqjax.studies.sweep.compare`) and the reports
``--junit PATH``, ``--markdown PATH`` (also appended to ``$GITHUB_STEP_SUMMARY`` when set) and ``--json PATH``
(:mod:`hyqjax.studies.sweep.gate`). Exit status of a gated run: 0 passed, 1 failed or regressed, 3 inconclusive.
Imports nothing heavy (checks run before anything compiles).
"""
from __future__ import annotations

import os

INCONCLUSIVE = ("report", "fail", "pass")


def add_gate_arguments(p, expect: bool = True) -> None:
    g = p.add_argument_group("CI gate (docs/ci.md; exit status 0 passed, 1 failed or regressed, 3 inconclusive)")
    if expect:
        g.add_argument("--expect", action="append", default=[], metavar="EXPR",
                       help="an expectation on the outcome rates, e.g. 'clean >= 0.85' or 'completed >= 0.95 where "
                            "height <= 0.21' (repeatable; also a spec file's expect list): fails when the Wilson 95%% "
                            "interval lies below it, inconclusive when it straddles it")
        g.add_argument("--inconclusive", choices=INCONCLUSIVE, default="report",
                       help="an inconclusive expectation: report it and exit 3 (if nothing failed), fail (exit 1) or "
                            "pass (exit 0)")
    g.add_argument("--alpha", type=float, default=0.05,
                   help="family-wise error rate of the baseline comparison (Holm-corrected McNemar / Fisher tests)")
    g.add_argument("--allow-change", action="append", default=[], metavar="AXIS",
                   help="[fixed] axes (or 'seed') that may differ between the baseline and this sweep, e.g. a gain under test "
                        "(repeatable or comma-separated)")
    g.add_argument("--junit", metavar="PATH", help="write a JUnit XML report (one test case per expectation or cell)")
    g.add_argument("--markdown", metavar="PATH", help="write a Markdown summary (also appended to "
                                                      "$GITHUB_STEP_SUMMARY when set)")
    g.add_argument("--json", dest="json_out", metavar="PATH", help="write the verdict as JSON")


def check_report_path(option: str, path: str | None) -> None:
    if not path:
        return
    if os.path.isdir(path):
        raise ValueError(f"{option} {path} is a directory; give a file path")
    from hyqjax.cli.common import check_out_free

    check_out_free(os.path.dirname(os.path.abspath(path)), option)


def validate_gate(args, spec_expect=()) -> None:
    """Parse the expectations (the spec file's, then ``--expect``'s) into ``args.expectations`` and check the
    gate's options; a bad one raises a one-line error naming it."""
    from hyqjax.cli.common import check_range

    check_range("--alpha", args.alpha, 0.0, 0.5, lo_open=True)
    from hyqjax.studies.sweep.compare import check_allow_change

    args.allow_change = list(check_allow_change(args.allow_change))
    if hasattr(args, "expect"):
        from hyqjax.studies.sweep import expect

        args.expectations = list(spec_expect) + expect.parse_all(args.expect)
    else:
        args.expectations = []
    for opt, path in (("--junit", args.junit), ("--markdown", args.markdown), ("--json", args.json_out)):
        check_report_path(opt, path)


def gate_requested(args) -> bool:
    return bool(getattr(args, "expectations", None) or getattr(args, "baseline", None) or args.junit
                or args.markdown or args.json_out)


def finish(args, verdict) -> int:
    """Print the verdict, write the reports, return the exit status."""
    from hyqjax.studies.sweep.gate import write_reports

    print("\n".join(verdict.lines()), flush=True)
    written = write_reports(verdict, args.junit, args.markdown, args.json_out)
    if written:
        print("wrote " + ", ".join(written))
    return verdict.exit_status()
