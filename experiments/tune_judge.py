"""Finished tuning studies judged together: the seed directories of several ``tune_study --guided-comparison`` runs
(the same settings but their seeds and methods, on the same held-out set) merged seed by seed, with the mean and
t-interval over seeds per method and Welch's differences (:func:`hyqjax.studies.tune.study.guided.compare`).

    python -m experiments.tune_judge --out DIR SOURCE [SOURCE ...]
    python -m experiments.tune_judge --out docs/results/tune_guided_matched_h200x2_3min_56 \\
        docs/results/tune_guided_h200x2_3min:snes,cma_es \\
        docs/results/tune_guided_matched_h200x2_3min_56/guided_es docs/results/tune_guided_matched_h200x2_3min_56/open_es

A SOURCE is a study directory (its ``seed<N>/results.json``), optionally ``:`` and the methods taken from it
(comma-separated; all by default). Runs of other settings or on another held-out set are refused in one line
(:func:`hyqjax.studies.tune.study.repeats.check_comparable`; a setting only some methods read, such as the
surrogate's windows, must agree only between runs judged for such a method), and so is one method of one seed given
by two sources. The budget judged is the largest ``--wall-minutes`` every run recorded (a run with further
checkpoints is judged at that one). Writes ``DIR/comparison.json`` and ``DIR/comparison.md``, which also name each
member's settings that only its method reads where they are not the defaults (the windows of guided ES's
surrogate, say); runs nothing.
"""
from __future__ import annotations

import copy
import sys
import warnings

from hyqjax.cli.common import UsageError


def parse(argv=None):
    from hyqjax.cli.app import Parser
    from hyqjax.cli.common import HelpFormatter

    ap = Parser(prog="python -m experiments.tune_judge", description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--out", required=True, help="directory for comparison.json and comparison.md")
    ap.add_argument("sources", nargs="+", metavar="SOURCE", help="DIR or DIR:method,method (module docstring)")
    return ap.parse_args(argv)


def split_source(source: str) -> tuple[str, tuple[str, ...] | None]:
    """``DIR`` or ``DIR:m1,m2`` -> (DIR, methods or None for all)."""
    if ":" not in source:
        return source, None
    path, _, methods = source.rpartition(":")
    names = tuple(m.strip() for m in methods.split(",") if m.strip())
    if not names:
        raise UsageError(f"SOURCE {source!r}: name at least one method after ':'")
    return path, names


def common_budget(sources: list[tuple[str, dict, tuple[str, ...] | None]]) -> float:
    """The largest ``--wall-minutes`` budget every run of every source recorded; ValueError without one."""
    budgets = None
    for _, results, _ in sources:
        for res in results.values():
            b = {float(m) for m in res["config"]["wall_minutes"]}
            budgets = b if budgets is None else budgets & b
    if not budgets:
        raise ValueError("the sources share no --wall-minutes budget to judge them at")
    return max(budgets)


def merge(sources: list[tuple[str, dict, tuple[str, ...] | None]], minutes: float) -> dict:
    """``(name, {seed: results.json}, methods)`` per source -> seed -> one results dict holding the chosen runs of
    every source and their held-out entries at ``minutes`` (with ``start`` and ``table1`` from the first), its
    ``wall_minutes`` that budget alone. Raises ValueError on runs that are not comparable (but for their seeds,
    methods and further budgets) or a run given twice."""
    from hyqjax.studies.tune.study import repeats
    from hyqjax.studies.tune.wallclock_config import SETTING_READERS, WallClockConfig
    from hyqjax.studies.tune.wallclock_results import member_key

    defaults = WallClockConfig.defaults()

    free = tuple(repeats.FREE_SETTINGS) + ("wall_minutes",)
    taken: list[tuple[str, int, dict, dict]] = []  # every run judged: name, seed, results, the runs judged of it
    for name, results, methods in sources:
        held = {r["method"] for res in results.values() for r in res.get("runs", {}).values()}
        missing = sorted(set(methods or ()) - held)
        if missing:
            raise ValueError(f"SOURCE {name} holds no run of {', '.join(missing)} (it has {', '.join(sorted(held))})")
        for seed, res in sorted(results.items()):
            runs = {k: r for k, r in res.get("runs", {}).items() if methods is None or r["method"] in methods}
            if methods is None or runs:
                taken.append((name, seed, res, runs))
    repeats.check_comparable([t[2] for t in taken], [f"{t[0]}/seed{t[1]}" for t in taken], free,
                             [{r["method"] for r in t[3].values()} for t in taken])
    merged: dict[int, dict] = {}
    for name, seed, res, runs in taken:
        if seed not in merged:
            merged[seed] = dict(copy.deepcopy({k: v for k, v in res.items() if k != "runs"}), runs={})
            merged[seed]["config"]["wall_minutes"] = [minutes]
        base = merged[seed]
        for key, run in runs.items():
            if key in base["runs"]:
                raise ValueError(f"{key} of seed {seed} is given by two sources ({name} and an earlier one)")
            base["runs"][key] = run
            mk = member_key(run["method"], run["dim"], minutes * 60.0)
            if mk in res["heldout"]:
                base["heldout"][mk] = res["heldout"][mk]
        # the merged seed's config tells the truth about its runs: their methods, and each setting only some methods
        # read as the runs that read it had it (they agree: checked above; one their study predates at its default)
        base["config"]["methods"] = sorted({r["method"] for r in base["runs"].values()})
        for k, readers in SETTING_READERS.items():
            if any(r["method"] in readers for r in runs.values()):
                base["config"][k] = copy.deepcopy(res["config"].get(k, defaults[k]))
    return merged


def member_settings(merged: dict) -> dict[str, dict]:
    """Per member judged (``method/dim``) of :func:`merge`'s seeds, the settings only some methods read
    (:data:`hyqjax.studies.tune.wallclock_config.SETTING_READERS`) that its method reads and its runs set away from
    their defaults, e.g. ``{"guided_es/per_leg": {"windows_per_scenario": 4, "window_lead": 16.0}}``; members with
    none are left out. A merged seed's config holds them as its runs had them."""
    from hyqjax.studies.tune.wallclock_config import SETTING_READERS, WallClockConfig

    defaults = WallClockConfig.defaults()
    out: dict[str, dict] = {}
    for res in merged.values():
        for run in res["runs"].values():
            own = {k: res["config"][k] for k, readers in SETTING_READERS.items()
                   if run["method"] in readers and res["config"].get(k, defaults[k]) != defaults[k]}
            if own:
                out[f"{run['method']}/{run['dim']}"] = own
    return out


def main(argv=None) -> int:
    try:
        a = parse(argv)
        parsed = [split_source(s) for s in a.sources]
    except UsageError as e:
        print(f"tune_judge: {e}", file=sys.stderr)
        return 2
    import os

    from experiments.tune_study import finished_seeds

    sources = []
    for path, methods in parsed:
        if not os.path.isdir(path):
            print(f"tune_judge: SOURCE {path} is not a directory", file=sys.stderr)
            return 2
        results = finished_seeds(path)
        if not results:
            print(f"tune_judge: SOURCE {path} holds no finished seed<N>/results.json", file=sys.stderr)
            return 2
        sources.append((path, results, methods))
    try:
        minutes = common_budget(sources)
        merged = merge(sources, minutes)
    except ValueError as e:
        print(f"tune_judge: {e}", file=sys.stderr)
        return 2
    from hyqjax.io.atomic import atomic_write, write_json
    from hyqjax.studies.tune.study import guided as guided_report

    with warnings.catch_warnings():  # Welch's test of a member whose runs all returned the same set
        warnings.simplefilter("ignore", RuntimeWarning)
        try:
            comp = guided_report.compare(merged, minutes)
        except ValueError as e:
            print(f"tune_judge: {e}", file=sys.stderr)
            return 2
        table = guided_report.markdown(comp)
    comp["sources"] = list(a.sources)
    comp["member_settings"] = member_settings(merged)
    if comp["member_settings"]:
        table += "\n\nsettings only some methods read, away from their defaults:\n" + "\n".join(
            f"- {m}: " + ", ".join(f"{k} {v}" for k, v in sorted(own.items()))
            for m, own in sorted(comp["member_settings"].items()))
    os.makedirs(a.out, exist_ok=True)
    write_json(os.path.join(a.out, "comparison.json"), comp)
    atomic_write(os.path.join(a.out, "comparison.md"), lambda f: f.write((table + "\n").encode()))
    print(table)
    print(f"wrote {a.out}/comparison.json and comparison.md ({len(merged)} seeds)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
