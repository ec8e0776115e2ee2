"""What a simulating command shows while its batch runs: the compile phase on stderr with its elapsed time
(:class:`CompileStatus`, :func:`compile_status`), the simulation's progress bar (:class:`SimProgress`,
:func:`sim_progress`), and the end of a batched run's lap of the phase clock (:func:`lap_batch_run`)."""
from __future__ import annotations

import contextlib
import sys
import threading


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
