"""The ``hyqjax`` command line: one subcommand per experiment.

Each command module in :mod:`hyqjax.cli` defines ``NAME``, ``HELP``, ``add_arguments(parser)``, optionally
``validate(args)`` (option checks and output directories, before JAX is imported or anything compiled)
and ``run(args) -> int``; this file collects them.

Import hygiene: this module, the command modules at import, their ``add_arguments`` and the option checks of
their ``validate`` import nothing heavy (no JAX, MuJoCo, pyarrow or matplotlib; the compilation cache is set
through JAX's environment variables until JAX is imported), so a usage error is printed a fraction of a
second after the start (``benchmarks/bench_cli_refusal.py``). Checks that need a declaration made in JAX
(parameter ranges of a sweep spec or of tuned groups) import JAX's parameter classes, never MJX; heavy
imports are in ``run``.

Exit status: 0 done, 2 a user error (one line naming the option and what is allowed, no traceback; the
parser's own errors too), 1 any other error (one line; ``--debug`` shows the traceback), 130 interrupted.
Every command takes ``--debug`` and ``--no-cache`` (JAX's persistent compilation cache is on by default in
``~/.cache/hyqjax/jax``, see :func:`hyqjax.cli.common.cache_dir`; with it, the bogus XLA:CPU log lines about
loading cached programs are dropped from stderr, :class:`hyqjax.io.cache.StderrFilter`, unless ``--debug``).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import pkgutil
import sys
from typing import NoReturn

# XLA's C++ log lines (e.g. one "Assume version compatibility" warning per program loaded from the
# persistent compilation cache) are not for users of the command line; errors still show.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

import hyqjax  # noqa: E402
from hyqjax.cli.common import (  # noqa: E402
    USAGE_EXIT, HelpFormatter, UsageError, apply_devices, discard_created_out, enable_compilation_cache)
from hyqjax.io.cache import StderrFilter  # noqa: E402


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``hyqjax sweep: argument --seed: invalid int value: 'x'``)."""

    def error(self, message: str):
        self.exit(USAGE_EXIT, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _command_modules():
    """The command modules beside this file (the package's directory, found without importing the package that
    imports this module)."""
    mods = []
    for info in sorted(pkgutil.iter_modules([os.path.dirname(os.path.abspath(__file__))]), key=lambda i: i.name):
        if info.name.startswith("_") or info.name in ("app", "common"):
            continue
        mod = importlib.import_module(f"hyqjax.cli.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return sorted(mods, key=lambda m: getattr(m, "ORDER", 100))


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="hyqjax",
        description="HyQ's height reflex, crawl and bounding gaits on MuJoCo MJX. "
        "stepdown, sweep, tune and bound run batched experiments: each prints a summary and writes results.json "
        "plus PNG figures; render, view and report show what an experiment recorded.",
    )
    parser.add_argument("--version", action="version", version=f"hyqjax {hyqjax.__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", help="show the traceback of an error")
    common.add_argument("--no-cache", action="store_true",
                        help="do not use JAX's persistent compilation cache (default: on, in ~/.cache/hyqjax/jax "
                             "or $HYQJAX_CACHE_DIR, a subdirectory per host CPU)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for mod in _command_modules():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.__doc__, parents=[common],
                           formatter_class=HelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(run_command=mod.run, validate_command=getattr(mod, "validate", None))
    return parser


def _user_errors() -> tuple:
    """Exception types that are the user's to fix (bad spec, busy or foreign store or run directory, a resume with
    other settings), besides UsageError; from the modules loaded only (one not loaded raised nothing)."""
    from hyqjax.io.fingerprint import SettingsMismatch
    from hyqjax.io.lock import Busy

    errs = [UsageError, Busy, SettingsMismatch]
    if "hyqjax.studies.sweep.axes" in sys.modules:
        errs.append(sys.modules["hyqjax.studies.sweep.axes"].SpecError)
    if "hyqjax.studies.sweep.manifest" in sys.modules:
        manifest = sys.modules["hyqjax.studies.sweep.manifest"]
        errs += [manifest.StoreMismatch, manifest.StoreCorrupt]
    return tuple(errs)


def main(argv: list[str] | None = None, parser: argparse.ArgumentParser | None = None) -> int:
    """Parse ``argv``, check the options (``validate_command``) and run the command (``run_command``), with the
    exit statuses of the module docstring. ``parser``: another program's parser with the same contract (its
    ``--debug`` and ``--no-cache``, and ``run_command`` / ``validate_command`` defaults; e.g.
    ``python -m experiments.tune_study``); default the ``hyqjax`` command line."""
    from hyqjax.io import phases

    # The command's clock (hyqjax.io.phases): from the process's start on the command line, from now in-process.
    phases.start(process=argv is None)
    parser = build_parser() if parser is None else parser
    args = parser.parse_args(argv)
    if not getattr(args, "run_command", None):
        parser.print_help()
        return USAGE_EXIT
    prog = f"hyqjax {args.command}" if getattr(args, "command", None) else parser.prog
    debug = args.debug or os.environ.get("HYQJAX_DEBUG") == "1"
    noise = None
    try:
        if args.validate_command is not None:
            try:
                args.validate_command(args)
            except ValueError as e:  # raised while checking options: the user's to fix
                raise UsageError(str(e)) from e
        try:
            apply_devices(args)  # --devices, where the command has it: checked before anything compiles
        except UsageError:
            discard_created_out()  # the command's checks created --out; a refused command leaves nothing
            raise
        if not args.no_cache:
            enable_compilation_cache()
            # The command line itself (not main([...]) inside another program), not with Ray's processes.
            if argv is None and not debug and getattr(args, "executor", "local") != "ray":
                noise = StderrFilter().start()
        return int(args.run_command(args) or 0)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    except SystemExit as e:
        if isinstance(e.code, str):
            print(f"{prog}: {e.code}", file=sys.stderr)
            return USAGE_EXIT
        raise
    except _user_errors() as e:
        if debug:
            raise
        print(f"{prog}: {e}", file=sys.stderr)
        return USAGE_EXIT
    except Exception as e:
        if debug:
            raise
        print(f"{prog}: error: {type(e).__name__}: {e} (run again with --debug for the traceback)",
              file=sys.stderr)
        return 1
    finally:
        if noise is not None:
            noise.stop()


def console_main() -> NoReturn:
    """The ``hyqjax`` executable (and ``python -m hyqjax.cli``): :func:`main` on the command line, then the process
    ends at once.

    When :func:`main` returns, every file a command writes is written and closed, so the interpreter's teardown
    (about 0.5 s of a 2-core machine once JAX has run: its backends, thread pools and thousands of modules released
    one by one) is skipped: standard output and error are flushed, logging is shut down and the process exits with
    ``os._exit``. A process that loaded Ray (``--executor ray``) exits normally, through Ray's own exit handlers."""
    rc = main()
    if "ray" in sys.modules:
        sys.exit(rc)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):  # a closed pipe (``hyqjax ... | head``) has nothing left to flush
            stream.flush()
    logging.shutdown()
    os._exit(rc)


if __name__ == "__main__":
    console_main()
