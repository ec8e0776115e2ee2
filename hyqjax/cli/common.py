"""What every command shares: user errors, range checks, output directories, the compilation cache.

A user error is a :class:`UsageError` (or a ``ValueError`` raised while the options are checked): ``main``
prints it as one line, ``hyqjax COMMAND: MESSAGE``, and exits with status 2, without a traceback
(``--debug`` shows it). Every command checks its options and creates and probes its output directory
before anything is imported from JAX or compiled, so a refused command leaves nothing behind and a
run never simulates for minutes and then fails to save.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import threading

from hyqjax.io.cache import cache_dir, enable_compilation_cache  # noqa: F401  (re-exported for the commands)

USAGE_EXIT = 2


class UsageError(ValueError):
    """A bad option or input file; the message names it and what is allowed."""


def split_names(s: str) -> tuple:
    """A comma-separated option: ``"a, b,"`` -> ``("a", "b")``."""
    return tuple(x.strip() for x in s.split(",") if x.strip())


def check_range(option: str, value, lo=None, hi=None, unit: str = "", integer: bool = False,
                lo_open: bool = False, hi_open: bool = False) -> None:
    """Raise :class:`UsageError` unless ``value`` is finite and in the interval (``[lo, hi]``; open ends on request)."""
    u = f" {unit}" if unit else ""
    left, right = "(" if lo_open else "[", ")" if hi_open else "]"
    num = (lambda x: f"{int(x)}") if integer else (lambda x: f"{x:g}")  # noqa: E731
    lo_s = "-inf" if lo is None else num(lo)
    hi_s = "inf" if hi is None else num(hi)
    rng = f"{left}{lo_s}, {hi_s}{right}{u}"
    kind = "an integer" if integer else "a number"
    if value is None or isinstance(value, bool):
        raise UsageError(f"{option} must be {kind} in {rng}, got {value!r}")
    v = float(value)
    ok = math.isfinite(v)
    if ok and lo is not None:
        ok = v > lo if lo_open else v >= lo
    if ok and hi is not None:
        ok = v < hi if hi_open else v <= hi
    if ok and integer:
        ok = v.is_integer()
    if not ok:
        raise UsageError(f"{option} must be {kind} in {rng}, got {value}")


def check_all(option: str, values, lo=None, hi=None, unit: str = "", **kw) -> None:
    """:func:`check_range` for each of ``values`` (which must not be empty)."""
    if not values:
        raise UsageError(f"{option} needs at least one value")
    for v in values:
        check_range(option, v, lo, hi, unit, **kw)


#: Output directories :func:`prepare_out` created in this process (removed again, while empty, by
#: :func:`discard_created_out` when a later check refuses the command).
_CREATED_OUT: list[str] = []


def prepare_out(path: str, option: str = "--out") -> str:
    """Create output directory ``path`` and check it is writable (:func:`hyqjax.io.atomic.check_writable_dir`)."""
    from hyqjax.io.atomic import check_writable_dir

    new = not os.path.exists(path)
    try:
        out = check_writable_dir(path, option)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if new:
        _CREATED_OUT.append(os.path.abspath(path))
    return out


def discard_created_out() -> None:
    """Remove the output directories :func:`prepare_out` created, where still empty: a refusal after the command's
    own checks (``--devices`` against the host's devices) leaves nothing behind."""
    while _CREATED_OUT:
        with contextlib.suppress(OSError):
            os.rmdir(_CREATED_OUT.pop())


def check_out_free(path: str, option: str = "--out") -> None:
    """Refuse an output path that exists and is not a directory, or lies under a file (checked without writing)."""
    p = os.path.abspath(path)
    probe = p
    while not os.path.exists(probe) and os.path.dirname(probe) != probe:
        probe = os.path.dirname(probe)
    if os.path.exists(probe) and not os.path.isdir(probe):
        raise UsageError(f"{option} {path}: {probe} is a file, not a directory; give a directory path")
    if os.path.isdir(probe) and not os.access(probe, os.W_OK | os.X_OK):
        raise UsageError(f"{option} {path}: {probe} is not writable")


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Help as written: the description keeps its line breaks (examples stay readable), and an option's default
    is appended once, only where it says something: not where the help text already names its default, not for
    an on/off flag (default off), an unset (None) default, an empty string or an empty list (a repeatable option)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if ("default" in text.lower() or any(action.default is v for v in (None, False, argparse.SUPPRESS))
                or action.default in ([], "")
                or isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))):
            return text
        return super()._get_help_string(action)


def use_help_formatter(p: argparse.ArgumentParser) -> None:
    """Give a command's parser :class:`HelpFormatter` (called first in each command's ``add_arguments``)."""
    p.formatter_class = HelpFormatter


def add_impl_argument(p, supported: tuple[str, ...] | None = None) -> None:
    """``--impl auto|jax|warp|c``: the simulator of a forward-only run (:mod:`hyqjax.sim.backend`); ``supported``
    restricts the choices to a task's simulators (default: all)."""
    from hyqjax.sim import backend

    supported = backend.ALL_IMPLS if supported is None else supported
    p.add_argument("--impl", choices=["auto", *supported], default="auto",
                   help="simulator: " + backend.describe(supported))
    add_devices_argument(p)


def add_devices_argument(p) -> None:
    """``--devices all|N|ID,ID,...``: the local devices a batch runs over (:mod:`hyqjax.sim.devices`); checked and
    made the process's selection by :func:`apply_devices` (``hyqjax``'s ``main`` calls it for every command)."""
    from hyqjax.sim.devices import DEVICES_HELP

    p.add_argument("--devices", default="all", metavar="all|N|IDS",
                   help=f"devices the batch runs over: {DEVICES_HELP} (default: all; one program per device, the "
                        "batch split between them; C MuJoCo ignores it)")


def apply_devices(args) -> None:
    """Check ``args.devices`` (its form first, without JAX; then against the host's devices) and make it the
    process's device selection (:func:`hyqjax.sim.devices.select`). A bad value is a :class:`UsageError` naming
    ``--devices`` and what is allowed. Does nothing for a command without the option."""
    if getattr(args, "devices", None) is None:
        return
    from hyqjax.sim import devices

    try:
        sel = devices.parse(args.devices)
        if sel is not None or devices.selected() is not None:
            devices.select(sel)
    except ValueError as e:
        raise UsageError(str(e)) from None


def check_impl(impl: str, option: str = "--impl", supported: tuple[str, ...] | None = None) -> None:
    """Refuse an unknown ``impl`` or one whose package is missing (``warp`` without warp-lang), before anything is
    imported from JAX."""
    from hyqjax.sim import backend

    supported = backend.ALL_IMPLS if supported is None else supported
    try:
        backend.validate_impl(impl, supported)
        backend.check_available(impl)
    except ValueError as e:
        msg = str(e).replace("impl must be", f"{option} must be").replace("impl='warp' needs", f"{option} warp needs")
        raise UsageError(msg.replace("(or choose impl='jax')", f"(or use {option} jax)")) from None


#: Attributes the command line sets on its parsed options for itself (not options a user gave).
INTERNAL_OPTIONS = ("options_checked", "run_command", "validate_command", "study_config", "spec_obj", "recorded",
                    "tuned_params")


def user_options(args) -> dict:
    """The options of a parsed command line as a user gave them (for ``results.json``)."""
    return {k: v for k, v in vars(args).items() if k not in INTERNAL_OPTIONS and not callable(v)}


def import_during_batch_run(module: str, enabled: bool = True):
    """A compile listener (:func:`hyqjax.sim.compile_phase.compile_listener`) that imports ``module`` (a figure
    module: matplotlib takes 0.5-1.5 s) in a background thread while the batch runs, instead of after it: from the
    moment XLA compiles the chunk program (a compile releases the GIL and uses about one core) or, when the program is
    loaded from the cache, from the end of the compile phase (the simulation then runs on a GPU or in C, with the
    GIL released). A failed import is left to the import after the run, which raises it."""
    import importlib

    started = []

    def quietly() -> None:
        try:
            importlib.import_module(module)
        except Exception:  # noqa: BLE001  (raised again by the import that needs the module)
            pass

    def listener(event: str, info: dict) -> None:
        if not enabled or started:
            return
        if (event == "compile" and info.get("program") == "advance") or event == "end":
            started.append(threading.Thread(target=quietly, daemon=True, name=f"hyqjax-import-{module}"))
            started[0].start()

    return listener

