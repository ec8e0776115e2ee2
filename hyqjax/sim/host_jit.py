"""Programs of the C MuJoCo backend (:mod:`hyqjax.sim.cpu_backend`) compiled for the host CPU: :func:`host_jit` is
``jax.jit`` placed on the host CPU device (:func:`host_sharding`, also in a process whose default device is a GPU)
with the XLA options of :data:`COMPILER_OPTIONS` that this process's XLA knows (:func:`compiler_options`).
"""
from __future__ import annotations

import functools

import jax
import numpy as np

#: XLA options of the programs this backend compiles (the controller and metrics, on the CPU): XLA:CPU's
#: elemental emitters instead of its fusion emitters compile the crawl's closed loop in about half the time
#: (5 instead of 9.5 s of CPU for 18 instances) and run its ticks as fast (benchmarks/bench_cpu_backend.py); the
#: controller's small matrix products in Eigen's single-threaded kernels (each shard is one thread already) take
#: 12-15% off a tick of the controller, bitwise the same (benchmarks/RESULTS.md).
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_multi_thread_eigen": False}


@functools.lru_cache(maxsize=None)
def host_sharding():
    """The host CPU device as a sharding: the controller and metrics of this backend run there (its physics is a
    host call registered for the CPU), also in a process whose default device is a GPU."""
    return jax.sharding.SingleDeviceSharding(jax.devices("cpu")[0])


def host_jit(fn, **kw):
    """``jax.jit`` of ``fn`` on the host CPU (:func:`host_sharding`) with :func:`compiler_options`."""
    return jax.jit(fn, in_shardings=host_sharding(), out_shardings=host_sharding(),
                   compiler_options=compiler_options(), **kw)


@functools.lru_cache(maxsize=None)
def compiler_options() -> dict:
    """The entries of :data:`COMPILER_OPTIONS` that this process's XLA knows: each tried once on a one-op program
    (the XLA of jax 0.11 has no ``xla_cpu_use_fusion_emitters`` and refuses a program that names it)."""
    known = {}
    for k, v in COMPILER_OPTIONS.items():
        try:
            jax.jit(lambda x: x + 1, compiler_options={k: v}).lower(jax.ShapeDtypeStruct((), np.float32, sharding=host_sharding())).compile()
        except Exception:  # noqa: BLE001 - XLA's error for an unknown option is a JaxRuntimeError or a ValueError
            continue
        known[k] = v
    return known
