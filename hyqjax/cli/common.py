"""What every command shares: user errors, range checks, output directories, the compilation cache.

A user error is a :class:`UsageError` (or a ``ValueError`` raised while the options are checked): ``main``
prints it as one line, ``hyqjax COMMAND: MESSAGE``, and exits with status 2, without a traceback
(``--debug`` shows it). Every command checks its options and creates and probes its output directory
before anything is imported from JAX or compiled, so a refused command leaves nothing behind and a
run never simulates for minutes and then fails to save.
"""
from __future__ import annotations

import contextlib
import math
import os
import threading

from hyqjax.io.cache import cache_dir, enable_compilation_cache  # noqa: F401  (re-exported for the commands)

USAGE_EXIT = 2


class UsageError(ValueError):
    """A bad option or input file; the message names it and what is allowed."""


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


def prepare_out(path: str, option: str = "--out") -> str:
    """Create output directory ``path`` and check it is writable (:func:`hyqjax.io.atomic.check_writable_dir`)."""
    from hyqjax.io.atomic import check_writable_dir

    try:
        return check_writable_dir(path, option)
    except ValueError as e:
        raise UsageError(str(e)) from None


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


@contextlib.contextmanager
def sim_progress(desc: str, total_s: float, disable: bool = False):
    """A tqdm bar over simulated seconds with an ETA, fed by the batch runner's ``progress(done_s, total_s)``
    callback between chunks of simulated time; yields the callback. The wait before the first update is the
    compile (shown as elapsed time)."""
    from tqdm import tqdm

    bar = tqdm(total=round(total_s, 3), desc=f"{desc} (compiling, then simulating)", unit="sim s",
               bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} sim s [{elapsed}<{remaining}]",
               disable=disable, dynamic_ncols=True)
    stop = threading.Event()

    def tick():
        while not stop.wait(0.5):
            bar.refresh()

    th = threading.Thread(target=tick, daemon=True)
    th.start()

    def progress(done_s, total):
        if bar.n == 0:
            bar.set_description_str(desc)
        bar.update(round(float(done_s) - bar.n, 3))

    try:
        yield progress
    finally:
        stop.set()
        th.join()
        bar.close()


def add_impl_argument(p, supported: tuple[str, ...] | None = None) -> None:
    """``--impl auto|jax|warp|c``: the simulator of a forward-only run (:mod:`hyqjax.sim.backend`); ``supported``
    restricts the choices to a task's simulators (default: all)."""
    from hyqjax.sim import backend

    supported = backend.ALL_IMPLS if supported is None else supported
    helps = dict(warp="'warp' (MuJoCo Warp, several times faster on a CUDA GPU, forward only; pip install "
                      "'hyqjax[warp]')", jax="'jax' (MJX in pure JAX, differentiable)",
                 c="'c' (C MuJoCo on all CPU cores, the controller in JAX; forward only)")
    auto = ("'auto' (warp when a CUDA GPU and warp-lang are present, else c without an accelerator, else jax)"
            if "c" in supported else "'auto' (warp when a CUDA GPU and warp-lang are present, else jax)")
    p.add_argument("--impl", choices=["auto", *supported], default="auto",
                   help="simulator: " + ", ".join(helps[k] for k in supported) + ", " + auto)


def check_impl(impl: str, option: str = "--impl", supported: tuple[str, ...] | None = None) -> None:
    """Refuse an unknown ``impl`` or one whose package is missing (``warp`` without warp-lang), before anything is
    imported from JAX."""
    from hyqjax.sim import backend

    supported = backend.ALL_IMPLS if supported is None else supported
    try:
        backend.validate_impl(impl, supported)
        if impl != "auto":
            backend.check_available(impl)
    except ValueError as e:
        msg = str(e).replace("impl must be", f"{option} must be").replace("impl='warp' needs", f"{option} warp needs")
        raise UsageError(msg.replace("(or choose impl='jax')", f"(or use {option} jax)")) from None


#: Attributes the command line sets on its parsed options for itself (not options a user gave).
INTERNAL_OPTIONS = ("options_checked", "run_command", "validate_command", "study_config", "spec_obj", "recorded")


def user_options(args) -> dict:
    """The options of a parsed command line as a user gave them (for ``results.json``)."""
    return {k: v for k, v in vars(args).items() if k not in INTERNAL_OPTIONS and not callable(v)}
