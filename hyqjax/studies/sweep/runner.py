"""Running a sweep: one compiled program per (config, chunk size, devices), chunks through an executor.

:func:`run_rows` simulates the input rows of one chunk: padded to the chunk size and to a multiple of
the device count (repeating the last row) so every chunk runs the same compiled program, sharded over
the devices along the ``batch`` axis of :func:`hyqjax.sim.runner.batch_mesh`. :func:`run_sweep` runs
(or resumes) a sweep into its store (:mod:`hyqjax.studies.sweep.store`): it takes the store's lock,
hands the chunks still to do to an executor (:class:`LocalExecutor` here; Ray in
:mod:`hyqjax.studies.sweep.cluster`) and writes each finished chunk, in the driver, under the lock.
"""
from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.sim import backend
from hyqjax.sim import devices as hdevices
from hyqjax.sim import runner as srunner
from hyqjax.studies import stepdown
from hyqjax.studies.sweep.outcomes import count_outcomes
from hyqjax.studies.sweep.scenario import SensedParams, build_scenario, sensed_controller
from hyqjax.studies.sweep.spec import SweepSpec
from hyqjax.studies.sweep.store import SweepStore, default_chunk_size


def device_layout(devices=None, impl: str = "jax") -> dict:
    """What an instance's numerics depend on besides its inputs: platform, device kind, devices per program and
    the simulator (``impl`` resolved: ``jax``, ``warp`` or ``c``)."""
    devices = list(jax.local_devices() if devices is None else devices)
    return dict(platform=devices[0].platform, device_kind=devices[0].device_kind, devices=len(devices),
                impl=backend.resolve_impl(impl, stepdown.SUPPORTED_IMPLS))


_RUNNERS: dict = {}


def _runner(cfg: stepdown.StepdownConfig, sensed: bool, max_delay: int, devices: tuple):
    """The simulator's batch runner of the step-down closed loop (cached: chunks reuse the executable), sharded over
    ``devices`` under MJX; with sensor noise / latency the crawl is wrapped by :func:`sensed_controller`."""
    key = (cfg, sensed, max_delay, devices)
    if key in _RUNNERS:
        return _RUNNERS[key]
    st = stepdown.setup(cfg)
    ctrl = crawl.crawl_controller(cfg.control_dt)
    if sensed:
        ctrl = sensed_controller(ctrl, max_delay)
    # MJX-JAX: one program sharded over the devices; MuJoCo Warp splits the batch, one runner per device (run_rows)
    mesh = srunner.batch_mesh(list(devices)) if hdevices.layout(st.impl, len(devices)) == "mesh" else None
    # buckets=False: a chunk is the sweep's own fixed batch shape (its chunk size, part of the store's layout).
    run = st.backend.make_runner(st.ids, ctrl, cfg.sim_config(), stepdown.make_metrics(st.ids, cfg), mesh=mesh,
                                 buckets=False)
    _RUNNERS[key] = (run, st.m, st.mx, st.ids)
    return _RUNNERS[key]


def run_rows(rows: dict[str, np.ndarray], spec: SweepSpec, pad_to: int, devices=None,
             progress=None, impl: str = "auto") -> dict[str, np.ndarray]:
    """Simulate input rows (padded to ``pad_to`` by repeating the last row); returns the outcome columns.

    The scan always runs in chunks of one simulated second (the batch runner's progress mode, bitwise equal to
    one scan), calling ``progress(done_s, total_s)`` between them when given, so every executor runs the
    same compiled programs."""
    devices = tuple(hdevices.resolve(devices))
    n = rows["index"].shape[0]
    pad_to = srunner.pad_batch(max(pad_to, n), len(devices))
    padded = {k: np.concatenate([v, np.repeat(v[-1:], pad_to - n, 0)], 0) for k, v in rows.items()}
    scenario, sensor = build_scenario(padded, spec)
    cfg = dataclasses.replace(spec.stepdown_config(), impl=impl)
    run, _, _, ids = _runner(cfg, spec.sensed, spec.max_delay, devices)
    st = stepdown.setup(cfg)
    if hdevices.layout(st.impl, len(devices)) == "split":  # MuJoCo Warp: one program per device, equal slices

        def inputs_of(idx):
            sc, se = build_scenario({k: v[idx] for k, v in padded.items()}, spec)
            mb, d0 = stepdown.batch_inputs(st, sc)
            return mb, d0, (sc.params if se is None else SensedParams(sc.params, se)), sc.push

        one = _runner(cfg, spec.sensed, spec.max_delay, devices[:1])[0]  # placed on each device: one trace for all
        res = srunner.run_on(list(devices), pad_to, inputs_of, one.placed, st.impl, progress or _no_progress, 1.0)
    else:
        mb, d0 = stepdown.batch_inputs(st, scenario)
        params = scenario.params if sensor is None else SensedParams(scenario.params, sensor)
        res = run(mb, d0, params, scenario.push, progress=progress or _no_progress, chunk_seconds=1.0)
    if sensor is not None:
        res = res._replace(ctrl_state=res.ctrl_state.inner)
    out = stepdown.summarize_instances(res, scenario, cfg, ids)
    out = count_outcomes({k: np.asarray(v)[:n] for k, v in out.items()})
    return out


def _no_progress(done_s, total_s) -> None:
    pass


def compute_chunk(spec: SweepSpec, start: int, stop: int, chunk_size: int, devices=None,
                  progress=None, impl: str = "auto") -> dict[str, np.ndarray]:
    """Inputs and outcomes of instances ``start..stop-1`` (one chunk), computed on ``devices`` under MJX
    implementation ``impl``."""
    rows = spec.instance_inputs(start, stop)
    return {**rows, **run_rows(rows, spec, chunk_size, devices, progress, impl)}


class LocalExecutor:
    """Chunks one after another on this process's devices (the default executor)."""

    name = "local"

    def __init__(self, devices=None, impl: str = "auto"):
        self.devices = tuple(hdevices.resolve(devices))
        self.impl = backend.resolve_impl(impl, stepdown.SUPPORTED_IMPLS)

    def layout(self) -> dict:
        return device_layout(self.devices, self.impl)

    def default_chunk_size(self) -> int:
        return default_chunk_size(self.devices)

    def run(self, spec: SweepSpec, chunks: list[tuple[int, int, int]], chunk_size: int, progress=None):
        """Yield ``(chunk, rows, wall_s, worker)`` for each ``(chunk, start, stop)`` as it finishes;
        ``progress(chunk, fraction)`` during a chunk's simulation."""
        for c, start, stop in chunks:
            t0 = time.time()
            cb = None if progress is None else (lambda d, t, c=c: progress(c, d / t))
            rows = compute_chunk(spec, start, stop, chunk_size, self.devices, cb, self.impl)
            yield c, rows, time.time() - t0, None

    def close(self) -> None:
        pass


def run_sweep(spec: SweepSpec, out_dir: str, chunk_size: int | None = None, max_chunks: int | None = None,
              devices=None, progress: bool = True, wait: bool = False, executor=None, impl: str = "auto") -> SweepStore:
    """Run (or resume) ``spec`` into ``out_dir``; at most ``max_chunks`` new chunks in this call.

    Holds the store's lock for the whole run (``wait``: queue behind another writer instead of failing with
    :class:`hyqjax.io.lock.Busy`). Returns the store (lock released) with every verified chunk.
    """
    if max_chunks is not None and max_chunks < 0:
        raise ValueError(f"max_chunks must be >= 0, got {max_chunks}")
    executor = executor or LocalExecutor(devices, impl)
    from tqdm.auto import tqdm

    with SweepStore(out_dir, spec, chunk_size, executor.layout(), writer=True, wait=wait,
                    default_chunk_size=executor.default_chunk_size()) as store:
        todo = store.todo()
        if max_chunks is not None:
            todo = todo[:max_chunks]
        if progress:
            print(f"chunks of {store.chunk_size}: {len(store.done())}/{store.n_chunks} done"
                  + (", resuming" if store.done() else "") + f"; {len(todo)} to run now", flush=True)
        done_rows = sum(store.chunk_range(c)[1] - store.chunk_range(c)[0] for c in store.done())
        bar = tqdm(total=spec.n_instances, initial=done_rows, unit="inst", desc="sweep", disable=not progress,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.1f}/{total} inst [{elapsed}<{remaining}{postfix}]",
                   dynamic_ncols=True)
        try:
            jobs = [(c, *store.chunk_range(c)) for c in todo]
            shown: dict[int, float] = {}

            def advance(c, fraction):  # instances of chunk c counted as simulated so far
                start, stop = store.chunk_range(c)
                now = (stop - start) * min(max(fraction, 0.0), 1.0)
                bar.update(now - shown.get(c, 0.0))
                shown[c] = now

            for c, rows, wall, worker in executor.run(spec, jobs, store.chunk_size, progress=advance):
                store.write_chunk(c, rows, wall, worker)
                advance(c, 1.0)
                bar.set_postfix(chunk=f"{c + 1}/{store.n_chunks}", ok=int(np.asarray(rows["success"]).sum()))
        finally:
            bar.close()
            executor.close()
    return store


__all__ = ["LocalExecutor", "compute_chunk", "device_layout", "run_rows", "run_sweep"]
