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
import sys
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
    an on/off flag (default off), an unset (None) default or an empty list (a repeatable option)."""

    def _get_help_string(self, action):
        text = action.help or ""
        if ("default" in text.lower() or any(action.default is v for v in (None, False, argparse.SUPPRESS))
                or action.default == []
                or isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))):
            return text
        return super()._get_help_string(action)


def use_help_formatter(p: argparse.ArgumentParser) -> None:
    """Give a command's parser :class:`HelpFormatter` (called first in each command's ``add_arguments``)."""
    p.formatter_class = HelpFormatter


def _compile_line(prefix: str, label: str | None = None):
    from hyqjax.sim.compile_phase import COMPILE_LABEL

    label = COMPILE_LABEL if label is None else label
    return f"{prefix}: {label}" if prefix else label


#: Label of the part of a compile phase before XLA compiles: tracing and lowering the programs (every new process
#: pays it; the persistent cache holds compiled programs, not traces), or loading them from the cache.
PREPARE_LABEL = "preparing the simulation program"
#: Seconds an XLA compile request may take before the line says "compiling": a program loaded from the
#: persistent cache returns well within it (tens of milliseconds), a real compile takes seconds to minutes.
COMPILE_AFTER_S = 0.5


class CompileStatus:
    """Listens to the batch runners (:func:`hyqjax.sim.compile_phase.compile_listener`) and shows their compile phase on
    stderr with its elapsed time: ``PREFIX: preparing the simulation program 0:01`` while the programs are traced
    (and loaded from the persistent compilation cache), ``PREFIX: compiling (first run of this shape; cached
    afterwards) 0:42`` once XLA compiles (a compile request not answered from the cache within
    :data:`COMPILE_AFTER_S`, or answered by a compile). Afterwards one line says how long it took: "compiled in
    ... s (first run of this batch shape; cached afterwards)", or "compiled program loaded from the cache in ... s"
    when no program needed a compile. A program compiled earlier in the same process shows nothing. Sums
    ``compile_s`` and ``simulate_s`` over the runs it saw, so a command prints its throughput without the
    compile."""

    def __init__(self, prefix: str = "", disable: bool = False, on_end=None):
        self.prefix, self.disable, self.on_end = prefix, disable, on_end
        self.compile_s = self.simulate_s = 0.0
        self.compiles = 0
        self.timings: list[dict] = []
        self._bar = None
        self._stop = threading.Event()
        self._thread = None
        self._request_t0: float | None = None  # an XLA compile request in flight since
        self.compiling = False  # this phase compiles (a request went past COMPILE_AFTER_S or compiled)
        # MuJoCo Warp's kernel modules loaded (built, or read from Warp's cache) while listening
        # (hyqjax.sim.warp_kernels), and the part of it inside a compile phase
        self.kernel_s = self.kernel_in_compile_s = 0.0
        self.kernels_compiled = self.kernels_loaded = 0
        self._in_compile = False
        self._kernel_bar = None
        self._kernel_cache = ""

    @property
    def xla_compile_s(self) -> float:
        """The compile phases' seconds less the Warp kernel loads inside them."""
        return max(self.compile_s - self.kernel_in_compile_s, 0.0)

    @property
    def pure_simulate_s(self) -> float:
        """The runs' simulating seconds less the Warp kernel loads inside them (a first run's build)."""
        return max(self.simulate_s - (self.kernel_s - self.kernel_in_compile_s), 0.0)

    def __call__(self, event: str, info: dict) -> None:
        if event == "kernels_start":
            self._kernel_cache = info.get("cache") or self._kernel_cache
            self._open_kernel_bar()
            return
        if event == "kernels":
            self.kernel_s += info["seconds"]
            self.kernel_in_compile_s += info["seconds"] if self._in_compile else 0.0
            self.kernels_loaded += 1
            self.kernels_compiled += int(bool(info.get("compiled")))
            return
        if event == "start":
            self._in_compile = True
            self.compiling = False
            self._request_t0 = None
            self._open()
        elif event == "compile":
            import time

            self._request_t0 = time.perf_counter()
        elif event == "compiled":
            self._request_t0 = None
            if not info.get("from_cache", False):
                self._show_compiling()
        elif event == "end":
            self._in_compile = False
            self._request_t0 = None
            self.compile_s += info["seconds"]
            self.compiles += 1
            self._close(info["seconds"], bool(info.get("from_cache", False)))
            if self.on_end is not None:
                self.on_end()
        elif event == "done":
            self.kernels_done()
            self.simulate_s += info["simulate_s"]
            self.timings.append(dict(info))

    def _open_kernel_bar(self) -> None:
        """``PREFIX: building MuJoCo Warp kernels (first run on this machine; cached in DIR) 0:42`` on stderr
        until :meth:`kernels_done`."""
        if self.disable or self._kernel_bar is not None:
            return
        from tqdm import tqdm

        head = self.prefix + ": " if self.prefix else ""
        where = f"cached in {self._kernel_cache}" if self._kernel_cache else "cached afterwards"
        self._kernel_bar = tqdm(total=None, desc=f"{head}building MuJoCo Warp kernels (first run on this machine; "
                                                 f"{where})", bar_format="{desc} {elapsed}", leave=False,
                                dynamic_ncols=True, mininterval=1.0)
        stop = threading.Event()

        def tick(bar=self._kernel_bar):
            while not stop.wait(0.5):
                bar.refresh()

        self._kernel_stop = stop
        threading.Thread(target=tick, daemon=True, name="hyqjax-kernel-status").start()

    def kernels_done(self) -> None:
        """Close the kernel build's line (the first chunk came back) with one line saying what it took."""
        if self._kernel_bar is None:
            return
        self._kernel_stop.set()
        self._kernel_bar.close()
        self._kernel_bar = None
        from tqdm import tqdm

        head = self.prefix + ": " if self.prefix else ""
        where = f" into {self._kernel_cache}" if self._kernel_cache else ""
        cached = self.kernels_loaded - self.kernels_compiled
        tqdm.write(f"{head}built MuJoCo Warp kernels{where} in {self.kernel_s:.1f} s ({self.kernels_compiled} "
                   f"modules built, {cached} read from the cache; counted as kernel build, not simulation; later runs "
                   f"read them from the cache)", file=sys.stderr)

    def _show_compiling(self) -> None:
        self.compiling = True
        if self._bar is not None:
            self._bar.set_description_str(_compile_line(self.prefix), refresh=True)

    def _open(self) -> None:
        if self.disable:
            return
        import time

        from tqdm import tqdm

        self._bar = tqdm(total=None, desc=_compile_line(self.prefix, PREPARE_LABEL), bar_format="{desc} {elapsed}",
                         leave=False, dynamic_ncols=True)
        self._stop.clear()

        def tick():
            while not self._stop.wait(0.25):
                t0 = self._request_t0
                if not self.compiling and t0 is not None and time.perf_counter() - t0 >= COMPILE_AFTER_S:
                    self._show_compiling()
                self._bar.refresh()

        self._thread = threading.Thread(target=tick, daemon=True)
        self._thread.start()

    def _close(self, seconds: float, from_cache: bool) -> None:
        if self._bar is None:
            return
        self._stop.set()
        self._thread.join()
        self._bar.close()
        self._bar = None
        from tqdm import tqdm

        head = self.prefix + ": " if self.prefix else ""
        if from_cache:
            tqdm.write(f"{head}compiled program loaded from the cache in {seconds:.1f} s", file=sys.stderr)
        else:
            tqdm.write(f"{head}compiled in {seconds:.1f} s (first run of this batch shape; cached afterwards)",
                       file=sys.stderr)

    def close(self) -> None:
        self.kernels_done()
        if self._bar is not None:
            self._stop.set()
            self._thread.join()
            self._bar.close()
            self._bar = None

    def throughput_text(self, instances: int, ticks: int) -> str:
        """``simulated ... env-steps/s (compile ... s besides)``: the rate over simulating time only."""
        sim = self.pure_simulate_s
        rate = instances * ticks / sim if sim > 0 else float("nan")
        pad = ""
        if self.timings:
            t = self.timings[-1]
            extra = t["passes"] * t["batch"] - t["instances"]
            shards = t.get("shards", 1)  # C MuJoCo: the batch's rows in shards, one program (hyqjax.sim.cpu_backend)
            if extra or t["passes"] > 1 or shards > 1:
                pad = (f"; {shards} shards of {t['batch'] // shards} rows" if shards > 1 else
                       f"; batches of {t['batch']}" + (f" x {t['passes']} passes" if t["passes"] > 1 else ""))
                pad += f", {extra} padded rows not counted" if extra else ""
        kernels = f", Warp kernel build {self.kernel_s:.1f} s" if self.kernels_loaded else ""
        return (f"simulating {sim:.1f} s: {rate:,.0f} env-steps/s of {instances} instances; compile "
                f"{self.xla_compile_s:.1f} s{kernels} besides{pad}")


@contextlib.contextmanager
def compile_status(prefix: str = "", disable: bool = False):
    """A :class:`CompileStatus` listening to every batch runner while the context is open."""
    from hyqjax.sim.compile_phase import compile_listener

    status = CompileStatus(prefix, disable)
    try:
        with compile_listener(status):
            yield status
    finally:
        status.close()


class SimProgress:
    """The progress of a batched run on stderr: the compile phase (:class:`CompileStatus`), then a bar over
    simulated seconds with an ETA, fed by the batch runner's ``progress(done_s, total_s)`` between chunks (the
    total counts every pass of a bucketed batch). The bar starts when the simulation does, so its rate and ETA
    exclude the compile; it never passes its total."""

    def __init__(self, desc: str, total_s: float, disable: bool = False):
        self.desc, self.total, self.disable = desc, float(total_s), disable
        self.status = CompileStatus(desc, disable)
        self.bar = None

    def _ensure_bar(self):
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=self.total, desc=self.desc, unit="sim s", disable=self.disable, dynamic_ncols=True,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} sim s "
                                       "[{elapsed}<{remaining}]")
        return self.bar

    def __call__(self, done_s: float, total_s: float) -> None:
        self.status.kernels_done()
        bar = self._ensure_bar()
        total = float(total_s)
        if abs(total - bar.total) > 1e-9:
            bar.total = total
        bar.n = min(max(float(done_s), 0.0), bar.total)
        bar.refresh()
        if bar.n >= bar.total:  # closed now, so its elapsed time is the simulation's, not what follows
            bar.close()

    def close(self) -> None:
        self.status.close()
        if self.bar is not None:
            self.bar.close()


@contextlib.contextmanager
def sim_progress(desc: str, total_s: float, disable: bool = False):
    """A :class:`SimProgress` for one batched run (listening to the runners' compiles); yields it (the
    ``progress`` callback of the runner; ``.status`` holds the compile and simulate seconds)."""
    from hyqjax.sim.compile_phase import compile_listener

    prog = SimProgress(desc, total_s, disable)
    try:
        with compile_listener(prog.status):
            yield prog
    finally:
        prog.close()


def lap_batch_run(clock, status: CompileStatus) -> None:
    """End ``clock``'s lap of a batched run (:class:`hyqjax.io.phases.Clock`): MuJoCo Warp's kernel build (every
    module load of the lap) and the XLA compile that ``status`` saw (less the kernel loads inside it) carved out, the
    rest simulation."""
    clock.lap("simulation", compile=status.xla_compile_s)


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

