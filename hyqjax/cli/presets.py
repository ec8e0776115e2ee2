"""The named parameter sets shipped with hyqjax (hyqjax.presets): the crawl's and the bounding gait's.

Lists every preset with its kind, a one-line description and its headline figures; with a NAME, shows that
preset's values, provenance (command, seed, device, date, version, source result file) and every figure with
the held-out set it was measured on and the command that measured it. Commands take a preset with
--preset NAME (stepdown, sweep and the reach map a crawl preset; bound a bounding preset); the library loads one
with hyqjax.presets.load(NAME).

Examples:
  hyqjax presets                         # every preset, its kind and headline figures
  hyqjax presets reach                   # one preset: values, provenance, figures with their commands
  hyqjax presets --kind bound            # the bounding presets only
  hyqjax stepdown --preset reach         # run one
"""
from __future__ import annotations

import argparse

NAME = "presets"
HELP = "list the named parameter sets (crawl and bounding) with their figures and provenance"
ORDER = 5


def add_arguments(p: argparse.ArgumentParser) -> None:
    from hyqjax.cli.common import use_help_formatter

    use_help_formatter(p)
    p.add_argument("name", nargs="?", default=None, help="show this preset in full")
    p.add_argument("--kind", choices=["crawl", "bound"], default=None, help="list the presets of one kind")
    p.add_argument("--json", action="store_true", help="print the registry entries as JSON")


def validate(args) -> None:
    from hyqjax import presets

    if args.name is not None:
        presets.get(args.name, "NAME")
        if args.kind is not None:
            presets.check_kind(args.name, args.kind, "NAME")


def run(args) -> int:
    import dataclasses
    import json

    from hyqjax import presets

    if args.json:
        names = [args.name] if args.name else presets.names(args.kind)
        print(json.dumps([dataclasses.asdict(presets.get(n)) for n in names], indent=1))
        return 0
    if args.name:
        print(presets.describe(presets.get(args.name)))
        return 0
    rows = []
    for n in presets.names(args.kind):
        p = presets.get(n)
        figs = "; ".join(presets.format_figure(f) for f in p.figures[:2])
        rows.append((n, p.kind, p.description, figs))
    w = max(len(r[0]) for r in rows)
    for n, kind, desc, figs in rows:
        print(f"{n:<{w}}  {kind:<5}  {desc}")
        if figs:
            print(f"{'':<{w}}         {figs}")
    print("\n`hyqjax presets NAME` shows one with its provenance and the command of every figure; "
          "`--preset NAME` runs one (stepdown, sweep: crawl presets; bound: bounding presets)")
    return 0
