"""The Ray executor of a sweep: one worker per GPU (a Ray actor), results written by the driver under the store's lock.

``hyqjax sweep SPEC --out DIR --executor ray [--address ADDR]`` (``pip install 'hyqjax[cluster]'``). The
driver (the process running the command) holds ``DIR/.lock``, starts one worker per slot of the cluster (a
:class:`ChunkWorker` actor holding one GPU, or one CPU on a cluster without GPUs: ``ray.init`` of a local
instance counts the host's GPUs, so on one multi-GPU host every GPU gets its worker), hands each worker the chunks
still to do one after another, and writes each result to the store as it arrives. A worker keeps its GPU, its
process and its compiled chunk program for the whole sweep (a task-per-chunk scheme would reuse worker processes
across tasks whose GPU ids may differ, while JAX keeps the GPU it started on). The store lives only on the
driver's file system: workers need no shared file system, only hyqjax installed, and a chunk's rows (a few
hundred bytes per instance) travel back through Ray's object store.

Failures: a worker that dies mid-chunk (killed, out of memory, node lost) is restarted by Ray (``max_restarts``)
and its chunk run again (``max_retries`` times); an exception inside the chunk is not retried (it would fail
again) and stops the run with its message. A driver killed and started again with the same command resumes from
the store: recorded chunks are not recomputed, the chunks that were in flight are. A chunk lands once: the driver
writes it under the lock and :meth:`SweepStore.write_chunk` refuses a second copy.

Numerics: each worker runs the chunk on its devices (one per worker), with the same chunk shape as the local
executor on one device, so a Ray sweep and a local one-device sweep on the same kind of device give identical
rows. Each result carries its worker's device layout, which must match the store's; a cluster mixing device kinds
is refused rather than mixing layouts in one store.
"""
from __future__ import annotations

import os
import socket
import time

from hyqjax.studies.sweep.spec import SweepSpec


def run_chunk(spec_dict: dict, spec_hash: str, start: int, stop: int, chunk_size: int, impl: str = "auto",
              preset_digest: str | None = None) -> tuple:
    """One chunk on this worker's devices: ``(rows, wall_s, worker, layout)`` (the Ray task body). ``preset_digest``:
    the driver's digest of the values of the spec's preset (the worker reads the preset from its own registry,
    a user's preset from its own presets directory); other values there are refused."""
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    spec = SweepSpec.from_dict(spec_dict)
    if spec.spec_hash != spec_hash:
        raise RuntimeError(f"worker rebuilt spec hash {spec.spec_hash[:12]}, driver sent {spec_hash[:12]}: "
                           f"different hyqjax versions on driver and worker")
    if spec.preset and preset_digest:
        from hyqjax.studies.sweep.manifest import preset_digest as digest_of

        here = digest_of(spec.preset)
        if here != preset_digest:
            raise RuntimeError(f"worker {socket.gethostname()} has other values of preset {spec.preset} (values sha256 "
                               f"{here[:16]}, the driver's {preset_digest[:16]}): give every worker the same preset "
                               f"file (its HYQJAX_PRESETS_DIR)")
    from hyqjax.io.cache import enable_compilation_cache

    enable_compilation_cache()
    import jax

    from hyqjax.studies.sweep.runner import compute_chunk, device_layout

    devices = jax.local_devices()
    t0 = time.time()
    rows = compute_chunk(spec, start, stop, chunk_size, devices, impl=impl)
    return rows, time.time() - t0, f"{socket.gethostname()}:{os.getpid()}", device_layout(devices, impl)


def worker_layout(impl: str = "auto") -> dict:
    """The device layout of a worker (a probe task), with the MJX implementation ``impl`` resolves to there."""
    import jax

    from hyqjax.studies.sweep.runner import device_layout

    return device_layout(jax.local_devices(), impl)


class ChunkWorker:
    """One sweep worker (a Ray actor): its devices, its process and its compiled chunk program for the whole
    sweep."""

    def run(self, spec_dict: dict, spec_hash: str, start: int, stop: int, chunk_size: int, impl: str = "auto",
            preset_digest: str | None = None):
        return run_chunk(spec_dict, spec_hash, start, stop, chunk_size, impl, preset_digest)

    def layout(self, impl: str = "auto") -> dict:
        return worker_layout(impl)


class RayExecutor:
    """Chunks on one Ray worker per slot (see the module docstring).

    Args:
      address: Ray cluster address (``ray start --head`` prints it; "auto" finds a local one); None uses
        ``$RAY_ADDRESS`` if set, else starts a local Ray instance with ``num_cpus`` CPUs and every GPU of the host.
      gpus_per_task: GPUs per worker; None: 1 if the cluster has GPUs, else 0 (CPU workers).
      cpus_per_task: CPUs per worker.
      max_retries: how often a chunk whose worker died is run again (on the restarted worker).
      max_in_flight: chunks queued at once on each worker (default 2: the next chunk is there when one ends).
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
        self.per_worker = max(1, int(max_in_flight or 2))
        self.max_in_flight = self.per_worker * self.slots
        self._actor = ray.remote(num_gpus=self.gpus, num_cpus=self.cpus, max_restarts=-1,
                                 max_task_retries=max_retries)(ChunkWorker)
        self._workers: list = []
        self._layout: dict | None = None

    def describe(self) -> str:
        res = self.ray.cluster_resources()
        kind = f"{self.gpus:g} GPU" if self.gpus else f"{self.cpus:g} CPU"
        return (f"Ray cluster of {res.get('CPU', 0):g} CPUs and {res.get('GPU', 0):g} GPUs, {self.slots} worker(s) "
                f"of {kind} each")

    def workers(self) -> list:
        """The workers, one per slot (started on first use)."""
        if not self._workers:
            self._workers = [self._actor.remote() for _ in range(self.slots)]
        return self._workers

    def layout(self) -> dict:
        """The layout of the workers (asked of the first one)."""
        if self._layout is None:
            self._layout = self.ray.get(self.workers()[0].layout.remote(self.impl))
        return self._layout

    def default_chunk_size(self) -> int:
        return 32 if self.layout()["platform"] == "cpu" else 4096

    def run(self, spec: SweepSpec, chunks: list[tuple[int, int, int]], chunk_size: int, progress=None):
        """Yield ``(chunk, rows, wall_s, worker)`` as chunks finish (in any order); each worker has at most
        ``per_worker`` chunks queued, and gets the next one when one of its own ends."""
        ray = self.ray
        want = self.layout()
        workers = self.workers()
        spec_ref = ray.put(spec.to_dict())
        if spec.preset:
            from hyqjax.studies.sweep.manifest import preset_digest

            digest = preset_digest(spec.preset)
        else:
            digest = None
        queue = list(chunks)
        pending: dict = {}  # ref -> (chunk, worker index)
        load = [0] * len(workers)

        def submit(w: int) -> None:
            c, start, stop = queue.pop(0)
            pending[workers[w].run.remote(spec_ref, spec.spec_hash, start, stop, chunk_size, self.impl,
                                          digest)] = (c, w)
            load[w] += 1

        try:
            for w in range(len(workers)):
                for _ in range(self.per_worker):
                    if queue:
                        submit(w)
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    c, w = pending.pop(ref)
                    load[w] -= 1
                    rows, wall, worker, layout = ray.get(ref)
                    if layout != want:
                        raise RuntimeError(f"worker {worker} ran chunk {c} on {layout}, the sweep's layout is "
                                           f"{want}: give the sweep one kind of device (e.g. a Ray custom resource "
                                           f"per GPU model) so that one store never mixes layouts")
                    if queue:
                        submit(w)
                    yield c, rows, wall, worker
        finally:
            for ref in pending:  # stopped early (error, --max-chunks reached, interrupt): drop what is in flight
                try:
                    ray.cancel(ref)
                except Exception:  # noqa: BLE001  (finished meanwhile, or its worker is gone)
                    pass

    def close(self) -> None:
        for w in self._workers:
            try:
                self.ray.kill(w)
            except Exception:  # noqa: BLE001  (already gone)
                pass
        self._workers = []
        if self.started and self.ray.is_initialized():
            self.ray.shutdown()
            self.started = False


__all__ = ["ChunkWorker", "RayExecutor", "run_chunk", "worker_layout"]
