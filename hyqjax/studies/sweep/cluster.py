"""The Ray executor of a sweep: every chunk a Ray task, results written by the driver under the store's lock.

``hyqjax sweep SPEC --out DIR --executor ray [--address ADDR]`` (``pip install 'hyqjax[cluster]'``). The
driver (the process running the command) holds ``DIR/.lock``, submits the chunks still to do as tasks of
:func:`run_chunk` (one GPU each on a GPU cluster, one CPU otherwise), and writes each result to the store
as it arrives. The store therefore lives only on the driver's file system: workers need no shared file
system, only hyqjax installed, and a chunk's rows (a few hundred bytes per instance) travel back through
Ray's object store.

Failures: a worker that dies mid-chunk (killed, out of memory, node lost) makes Ray run the task again on
another worker, ``max_retries`` times; an exception inside the chunk is not retried (it would fail again)
and stops the run with its message. A driver killed and started again with the same command resumes from
the store: recorded chunks are not recomputed, the chunks that were in flight are. A chunk lands once:
the driver writes it under the lock and :meth:`SweepStore.write_chunk` refuses a second copy.

Numerics: each task runs the chunk on its worker's devices (one per task), with the same chunk shape as
the local executor on one device, so a Ray sweep and a local one-device sweep on the same kind of device
give identical rows. Each result carries its worker's device layout, which must match the store's;
a cluster mixing device kinds is refused rather than mixing layouts in one store.
"""
from __future__ import annotations

import os
import socket
import time

from hyqjax.studies.sweep.spec import SweepSpec


def run_chunk(spec_dict: dict, spec_hash: str, start: int, stop: int, chunk_size: int, impl: str = "auto") -> tuple:
    """One chunk on this worker's devices: ``(rows, wall_s, worker, layout)`` (the Ray task body)."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    from hyqjax.io.cache import enable_compilation_cache

    enable_compilation_cache()
    import jax

    from hyqjax.studies.sweep.runner import compute_chunk, device_layout

    spec = SweepSpec.from_dict(spec_dict)
    if spec.spec_hash != spec_hash:
        raise RuntimeError(f"worker rebuilt spec hash {spec.spec_hash[:12]}, driver sent {spec_hash[:12]}: "
                           f"different hyqjax versions on driver and worker")
    devices = jax.local_devices()
    t0 = time.time()
    rows = compute_chunk(spec, start, stop, chunk_size, devices, impl=impl)
    return rows, time.time() - t0, f"{socket.gethostname()}:{os.getpid()}", device_layout(devices, impl)


def worker_layout(impl: str = "auto") -> dict:
    """The device layout of a worker (a probe task), with the MJX implementation ``impl`` resolves to there."""
    import jax

    from hyqjax.studies.sweep.runner import device_layout

    return device_layout(jax.local_devices(), impl)


class RayExecutor:
    """Chunks as Ray tasks (see the module docstring).

    Args:
      address: Ray cluster address (``ray start --head`` prints it; "auto" finds a local one); None uses
        ``$RAY_ADDRESS`` if set, else starts a local Ray instance with ``num_cpus`` CPUs.
      gpus_per_task: GPUs per task; None: 1 if the cluster has GPUs, else 0 (CPU workers).
      cpus_per_task: CPUs per task.
      max_retries: how often a task whose worker died is run again.
      max_in_flight: tasks submitted at once (default: twice the workers the cluster can run at a time).
      num_cpus: CPUs of a local instance started here (None: all).
      impl: MJX implementation of the workers (``auto | jax | warp``, resolved on each worker).
    """

    name = "ray"

    def __init__(self, address: str | None = None, gpus_per_task: float | None = None, cpus_per_task: float = 1,
                 max_retries: int = 3, max_in_flight: int | None = None, num_cpus: int | None = None,
                 impl: str = "auto"):
        import ray

        self.impl = impl
        self.ray = ray
        self.started = not ray.is_initialized()
        if self.started:
            address = address or os.environ.get("RAY_ADDRESS") or None
            kw = dict(include_dashboard=False, log_to_driver=True)
            if address is None and num_cpus is not None:
                kw["num_cpus"] = num_cpus
            env = {k: os.environ[k] for k in ("PYTHONPATH", "HYQJAX_CACHE_DIR", "XLA_FLAGS") if k in os.environ}
            ray.init(address=address, runtime_env={"env_vars": env} if env else None, **kw)
        res = ray.cluster_resources()
        self.gpus = float(gpus_per_task if gpus_per_task is not None else (1 if res.get("GPU", 0) >= 1 else 0))
        self.cpus = float(cpus_per_task)
        slots = res.get("GPU", 0) / self.gpus if self.gpus else res.get("CPU", 1) / self.cpus
        self.slots = max(1, int(slots))
        self.max_in_flight = max_in_flight or 2 * self.slots
        opts = dict(num_gpus=self.gpus, num_cpus=self.cpus)
        self._task = ray.remote(max_retries=max_retries, retry_exceptions=False, **opts)(run_chunk)
        self._probe = ray.remote(**opts)(worker_layout)
        self._layout: dict | None = None

    def describe(self) -> str:
        res = self.ray.cluster_resources()
        kind = f"{self.gpus:g} GPU" if self.gpus else f"{self.cpus:g} CPU"
        return (f"Ray cluster of {res.get('CPU', 0):g} CPUs and {res.get('GPU', 0):g} GPUs, {kind} per task, "
                f"{self.slots} task(s) at a time")

    def layout(self) -> dict:
        """The layout of the workers (asked of one by a probe task)."""
        if self._layout is None:
            self._layout = self.ray.get(self._probe.remote(self.impl))
        return self._layout

    def default_chunk_size(self) -> int:
        return 32 if self.layout()["platform"] == "cpu" else 4096

    def run(self, spec: SweepSpec, chunks: list[tuple[int, int, int]], chunk_size: int, progress=None):
        """Yield ``(chunk, rows, wall_s, worker)`` as tasks finish (in any order); progress is per chunk."""
        ray = self.ray
        want = self.layout()
        spec_ref = ray.put(spec.to_dict())
        queue = list(chunks)
        pending: dict = {}
        try:
            while queue or pending:
                while queue and len(pending) < self.max_in_flight:
                    c, start, stop = queue.pop(0)
                    pending[self._task.remote(spec_ref, spec.spec_hash, start, stop, chunk_size, self.impl)] = c
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    c = pending.pop(ref)
                    rows, wall, worker, layout = ray.get(ref)
                    if layout != want:
                        raise RuntimeError(f"worker {worker} ran chunk {c} on {layout}, the sweep's layout is "
                                           f"{want}: give the sweep one kind of device (e.g. a Ray custom resource "
                                           f"per GPU model) so that one store never mixes layouts")
                    yield c, rows, wall, worker
        finally:
            for ref in pending:  # stopped early (error, --max-chunks reached, interrupt): drop what is in flight
                ray.cancel(ref, force=True)

    def close(self) -> None:
        if self.started and self.ray.is_initialized():
            self.ray.shutdown()
            self.started = False


__all__ = ["RayExecutor", "run_chunk", "worker_layout"]
