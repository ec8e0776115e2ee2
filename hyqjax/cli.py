"""The ``hyqjax`` command line: one subcommand per experiment.

Each module in :mod:`hyqjax.commands` defines ``NAME``, ``HELP`` and ``add_arguments(parser)`` and
``run(args) -> int``; this file collects them.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import hyqjax
import hyqjax.commands as _commands


def _command_modules():
    mods = []
    for info in sorted(pkgutil.iter_modules(_commands.__path__), key=lambda i: i.name):
        if info.name.startswith("_"):
            continue
        mods.append(importlib.import_module(f"hyqjax.commands.{info.name}"))
    return sorted(mods, key=lambda m: getattr(m, "ORDER", 100))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hyqjax",
        description="HyQ's height reflex, crawl and bounding gaits on MuJoCo MJX. "
        "stepdown, sweep, tune and bound run batched experiments: each prints a summary and writes results.json "
        "plus PNG figures; render, view and report show what an experiment recorded.",
    )
    parser.add_argument("--version", action="version", version=f"hyqjax {hyqjax.__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.__doc__,
                           formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    return int(args._run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
