"""Batch buckets: how a batch of ``n`` instances runs as passes of a few fixed shapes (:func:`batch_plan`), the
bucket of a runner whose physics runs outside the compiled program (:func:`host_physics_plan`, the C MuJoCo
backend), and the rows of a pass (:func:`take_rows`).

On CPU devices a batch of ``n`` instances runs as passes of a few fixed sizes: ``n <= CPU_PASS`` rounds up to a
power of two, a larger ``n`` runs as ``ceil(n / CPU_PASS)`` passes of ``CPU_PASS`` instances. The padding repeats
the last instance; padded rows are dropped from the result, so they are never seen or counted. One compiled program
then serves every batch of 5 to any number of instances, and changing the instance count does not compile again.
Every instance is independent under ``vmap``, so its result does not depend on the bucket (a test checks it row for
row). On accelerators (and under MuJoCo Warp, whose contact buffers are sized for the whole batch) a batch runs at
its own size in one pass. Nothing here traces or compiles; :mod:`hyqjax.sim.runner` and the C MuJoCo backend plan
with it.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

#: Instances per pass on one CPU device (the batch buckets, :func:`batch_plan`). On 2 CPU cores MJX's closed
#: loop saturates at about 10k env-steps/s from batch 16 on (benchmarks/RESULTS.md, bench_physics); 8 trades a
#: little of that for less padding of small batches (at most 7 padded rows, a third of the default step-down's 6).
CPU_PASS = 8


class BatchPlan(NamedTuple):
    """How a batch of ``n`` instances runs: ``passes`` passes of ``size`` instances (the compiled batch shape);
    the ``passes * size - n`` padded rows repeat the last instance and are dropped from the result."""

    n: int
    size: int
    passes: int

    @property
    def padded(self) -> int:
        return self.passes * self.size - self.n


#: The smallest batch bucket of a runner whose physics runs outside the compiled program (the C MuJoCo backend,
#: :func:`host_physics_plan`). Padded rows cost controller and metrics compute, never physics: on 2 CPU cores the
#: step-down's 18 instances in a bucket of 32 (the worst padding of ``--instances`` 3 to 5) ran at 0.8 of the
#: exact batch's env-steps/s, 30 in 32 at no measurable cost (benchmarks/RESULTS.md, bench_c_buckets); 8 puts
#: every batch of up to 8 instances in one bucket.
HOST_PHYSICS_MIN_BUCKET = 8


def bucket(n: int, minimum: int = 1) -> int:
    """The batch bucket of ``n`` instances: the smallest power of two ``>= max(n, minimum)``."""
    return 1 << max(max(int(n), int(minimum)) - 1, 0).bit_length()


def host_physics_plan(n: int) -> BatchPlan:
    """The bucket of a batch of ``n`` whose physics runs outside the compiled program (the C MuJoCo backend): one
    pass of :func:`bucket` ``(n, HOST_PHYSICS_MIN_BUCKET)`` rows. The padded rows repeat the last instance in the
    controller and metrics only (its observation, parameters and controller state); the physics steps the ``n``
    real instances alone, and the padded rows are dropped from the result. One pass, whatever ``n``: the
    physics of every real row runs in parallel each tick, and padding more than doubles no batch."""
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"a batch needs at least one instance, got {n}")
    return BatchPlan(int(n), bucket(n, HOST_PHYSICS_MIN_BUCKET), 1)


def batch_plan(n: int, platform: str = "cpu", n_devices: int = 1, pass_size: int | None = None) -> BatchPlan:
    """The bucket of a batch of ``n`` instances on ``n_devices`` devices of ``platform``.

    CPU: with ``P = pass_size`` (default ``CPU_PASS * n_devices``), ``n <= P`` runs once at the smallest power of
    two ``>= n`` (a multiple of ``n_devices``), a larger ``n`` as ``ceil(n / P)`` passes of ``P``. Other platforms:
    one pass of ``n`` rounded up to a multiple of ``n_devices``.
    """
    if not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"a batch needs at least one instance, got {n}")
    n, nd = int(n), max(int(n_devices), 1)
    if platform != "cpu":
        return BatchPlan(n, pad_batch(n, nd), 1)
    big = pad_batch(pass_size or CPU_PASS * nd, nd)
    if n > big:
        return BatchPlan(n, big, -(-n // big))
    return BatchPlan(n, min(pad_batch(bucket(n), nd), big), 1)


def take_rows(tree, axes, idx: np.ndarray):
    """Rows ``idx`` (host NumPy) of the leaves of ``tree`` whose ``vmap`` axis (``axes``: 0, None, or a pytree
    of them) is 0; other leaves unchanged."""
    if axes is None:
        return tree
    if isinstance(axes, int):
        return jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], tree)
    return jax.tree_util.tree_map(lambda ax, x: x if ax is None else np.asarray(x)[idx], axes, tree,
                                  is_leaf=lambda x: x is None)


def pad_batch(n: int, multiple: int) -> int:
    """Smallest batch size >= n divisible by ``multiple``."""
    return -(-n // multiple) * multiple


__all__ = ["BatchPlan", "CPU_PASS", "HOST_PHYSICS_MIN_BUCKET", "batch_plan", "bucket", "host_physics_plan", "pad_batch",
           "take_rows"]
