"""The named parameter sets of hyqjax (hyqjax.presets): the crawl's and the bounding gait's, shipped and your own.

Lists every preset with its kind, a one-line description and its headline figures, the shipped ones first, then
your own (files in $HYQJAX_PRESETS_DIR, else $XDG_DATA_HOME/hyqjax/presets, else ~/.local/share/hyqjax/presets);
with a NAME, shows that preset's values, provenance (command, seed, device, date, version, source result file)
and every figure with the held-out set it was measured on and the command that measured it. Commands take a
preset with --preset NAME (stepdown, sweep, tune and the reach map a crawl preset; bound a bounding preset); the
library loads one with hyqjax.presets.load(NAME).

`hyqjax presets save NAME --from RESULTS.json[:METHOD/DIM]` saves the set a `hyqjax tune` run returned as your
preset NAME (its values, the run's provenance and the held-out figure it measured); `--from PARAMS.json` a
bounding parameter file (`hyqjax bound --params FILE`'s format) as a bounding preset.

Examples:
  hyqjax presets                         # every preset, its kind and headline figures
  hyqjax presets reach                   # one preset: values, provenance, figures with their commands
  hyqjax presets --kind bound            # the bounding presets only
  hyqjax stepdown --preset reach         # run one
  hyqjax presets save mine --from out/tune/results.json   # a tuning run's returned set as preset mine
"""
from __future__ import annotations

import argparse

NAME = "presets"
HELP = "list the named parameter sets (crawl and bounding) with their figures and provenance"
ORDER = 5


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter
    from hyqjax.presets.registry import NAME_RULE

    use_help_formatter(p)
    p.usage = ("hyqjax presets [NAME] [--kind {crawl,bound}] [--json]\n       hyqjax presets save NAME --from "
               "RESULTS.json[:METHOD/DIM] [--force] [--description TEXT]")
    p.add_argument("name", nargs="?", default=None, metavar="NAME",
                   help="show this preset in full; the word save saves a new preset: save NEW_NAME --from FILE")
    p.add_argument("save_name", nargs="?", default=None, metavar="NEW_NAME",
                   help="after save: the name of your new preset (" + NAME_RULE + ")")
    p.add_argument("--kind", choices=["crawl", "bound"], default=None, help="list the presets of one kind")
    p.add_argument("--json", action="store_true", help="print the registry entries as JSON")
    p.add_argument("--from", dest="source", default=None, metavar="RESULTS.json[:METHOD/DIM]",
                   help="with `save`: a `hyqjax tune` results.json (and with several runs the one to take, e.g. "
                        "results.json:cma_es/per_leg), or a bounding parameter file (`hyqjax bound --params FILE`)")
    p.add_argument("--force", action="store_true", help="with `save`: replace your preset of that name")
    p.add_argument("--description", default=None, metavar="TEXT",
                   help="with `save`: the preset's one-line description (default: the run, its command and date)")



def validate(args) -> None:
    from hyqjax import presets

    if args.name == "save":
        _validate_save(args)
        return
    if args.save_name is not None:
        raise ValueError(f"unexpected argument {args.save_name!r}: give one NAME, or `save NAME --from FILE`")
    for opt, v in (("--from", args.source), ("--force", args.force), ("--description", args.description)):
        if v:
            raise ValueError(f"{opt} belongs to `hyqjax presets save NAME --from FILE`")
    if args.name is not None:
        presets.get(args.name, "NAME")
        if args.kind is not None:
            presets.check_kind(args.name, args.kind, "NAME")


def _validate_save(args) -> None:
    """Every refusal of `save` before anything is written: the name, the file, the run; builds the preset
    (``args.preset_file``) and checks its values load."""
    import os

    from hyqjax import presets
    from hyqjax.presets import from_results

    if args.kind is not None or args.json:
        raise ValueError("save takes NAME, --from, --force and --description only")
    if args.save_name is None:
        raise ValueError("save needs a NAME: hyqjax presets save NAME --from RESULTS.json[:METHOD/DIM]")
    name = args.save_name
    try:
        from_results.check_name(name, args.force)
    except ValueError as e:
        raise ValueError(f"NAME: {e}") from None
    if not args.source:
        raise ValueError(f"save {name} needs --from RESULTS.json[:METHOD/DIM] (a `hyqjax tune` results.json) or "
                         f"--from PARAMS.json (a bounding parameter file)")
    path, run = args.source, None
    if not os.path.exists(path) and ":" in path:
        path, _, run = path.rpartition(":")
    if not os.path.isfile(path):
        raise ValueError(f"--from {args.source}: no such file")
    try:
        if from_results.is_bound_file(path):
            if run:
                raise ValueError(f"{path} is a bounding parameter file: it has no runs (leave out :{run})")
            d = from_results.bound_preset(name, path, args.description)
        else:
            d = from_results.crawl_preset(name, path, run or None, args.description)
        rec = presets.registry._record(d, f"{name}.json", presets.user_dir())
        presets.load_preset(rec)
    except ValueError as e:
        raise ValueError(f"--from {args.source}: {e}") from None
    from hyqjax.io.atomic import check_writable_dir

    check_writable_dir(presets.user_dir(), "presets directory (HYQJAX_PRESETS_DIR, else XDG_DATA_HOME/hyqjax/presets)")
    args.preset_file = d


def _save(args) -> int:
    from hyqjax import presets
    from hyqjax.presets import from_results

    d = args.preset_file
    path = from_results.write(d, args.force)
    rec = presets.get(d["name"])
    print(f"saved {rec.kind} preset {rec.name}: {path}")
    if rec.figures:
        print(f"  {presets.format_figure(rec.figures[0])} (held-out set: {rec.figures[0]['heldout']})")
    elif rec.kind == "crawl":
        print("  no figure: the run measured no held-out clean success of the set it returned")
    if rec.provenance.get("complete") is False:
        print("  note: the run was not complete; this is the set it had returned at its last checkpoint")
    cmd = ("hyqjax stepdown --preset {n} --heights 0.24 --instances 4" if rec.kind == "crawl"
           else "hyqjax bound --preset {n}").format(n=rec.name)
    print(f"run it: {cmd}" + ("; in a sweep: preset = \"{n}\" in the spec or hyqjax sweep --preset {n}".format(
        n=rec.name) if rec.kind == "crawl" else "") + f"; show it: hyqjax presets {rec.name}")
    return 0


def run(args) -> int:
    import dataclasses
    import json
    import sys

    from hyqjax import presets

    if args.name == "save":
        if not hasattr(args, "preset_file"):
            _validate_save(args)
        return _save(args)
    if args.json:
        names = [args.name] if args.name else presets.names(args.kind)
        print(json.dumps([dataclasses.asdict(presets.get(n)) for n in names], indent=1))
        return 0
    if args.name:
        print(presets.describe(presets.get(args.name)))
        _problems(sys.stderr, only=args.name)
        return 0
    rows = []
    for n in presets.names(args.kind):
        p = presets.get(n)
        figs = "; ".join(presets.format_figure(f) for f in p.figures[:2])
        rows.append((n, p.kind, p.description, figs, p.user))
    w = max(len(r[0]) for r in rows)
    user_header = False
    for n, kind, desc, figs, user in rows:
        if user and not user_header:
            print(f"\nyour presets ({presets.user_dir()}):")
            user_header = True
        print(f"{n:<{w}}  {kind:<5}  {desc}")
        if figs:
            print(f"{'':<{w}}         {figs}")
    if not user_header:
        print(f"\nyour presets: none in {presets.user_dir()}")
    _problems(sys.stderr)
    print("\n`hyqjax presets NAME` shows one with its provenance and the command of every figure; "
          "`--preset NAME` runs one (stepdown, sweep, tune: crawl presets; bound: bounding presets); "
          "`hyqjax presets save NAME --from RESULTS.json` saves a tuning run's returned set as yours")
    return 0


def _problems(stream, only: str | None = None) -> None:
    """One line per file of the user's preset directory that is not used (``only``: the one of that name)."""
    from hyqjax import presets

    lines = presets.user_problems() if only is None else [presets.registry.user_problem(only)]
    for line in lines:
        if line:
            print(f"note: {line}", file=stream)
