"""A batch over several devices of one host: :func:`run_on` runs a batch of ``n`` instances over a list of devices in
the layout of its simulator (:func:`hyqjax.sim.devices.layout`), as one program per device (:func:`run_split`,
the devices running at once) or one program sharded over a 1-D mesh (:func:`batch_mesh`, axis ``"batch"``).
:class:`RunnersByPlace` keeps the runners of one static setup per placement.

One trace for every device. The runner of a device's slice is the one-device runner placed on that device
(:meth:`hyqjax.sim.runner.BatchRunner.placed`): it shares the one-device runner's jitted functions, so a program
is traced once for every device (a device's compile still lowers and compiles it for that device; on a CPU XLA
compiles per device), and its compiled programs, kept per device, so the default device's program serves the
one-device run and device 0's slice of a split alike (``tests/test_sim.py`` counts the traces and programs).
"""
from __future__ import annotations

import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from hyqjax.sim import model as hmodel
from hyqjax.sim.buckets import BatchPlan, take_rows
from hyqjax.sim.compile_phase import notify
from hyqjax.sim.rollout import RolloutResult, rollout_result

Progress = Callable[[float, float], None]


def run_split(runners: list, parts: list, progress: Progress | None = None,
              chunk_seconds: float | None = None) -> RolloutResult:
    """One program per device: ``parts[i] = (mx_batched, d0, params, push)``, committed to device ``i``, runs on
    ``runners[i]`` (a single-device :class:`hyqjax.sim.runner.BatchRunner` of the same static setup, one per
    device, best :meth:`~hyqjax.sim.runner.BatchRunner.placed` from one runner: the program is then traced once for
    every device). Every device's program is compiled first (device 0's by XLA; on a GPU the persistent compilation
    cache then serves the others: its key leaves out the device), then the chunks of
    simulated time are dispatched to every device in turn (asynchronously, so the devices run at once) and the
    results concatenated along the batch axis on the host. ``progress`` as a runner's (device 0's
    chunks; the slices are of equal size). One ``done`` event reports the whole run (``devices``: how many)."""
    if progress is not None and chunk_seconds is None:
        chunk_seconds = 1.0
    r0 = runners[0]
    k = r0.chunk_ticks(chunk_seconds)
    t_start = time.perf_counter()
    states = []
    compile_s = trace_s = 0.0
    compiled = from_cache = 0
    for r, (mb, d0, params, push) in zip(runners, parts):
        b = int(d0.qpos.shape[0])
        r._new_timing(BatchPlan(b, b, 1))
        if r._init is None:
            r._build(mb, d0, params, push)
        init = r._executable("init", r._init, (mb, d0, params), batch=b)
        carry = init(mb, d0, params)
        advance = r._executable("advance", r._advance, (mb, carry, params, push), (k,), batch=b)
        r._end_compile_phase(b)
        t = r.last_timing
        compile_s, trace_s = compile_s + t["compile_s"], trace_s + t["trace_s"]
        compiled, from_cache = compiled + t["compiled"], from_cache + t["from_cache"]
        states.append([advance, carry, []])
    t0 = time.perf_counter()
    cfg = r0.cfg
    n, dt = cfg.n_ticks, cfg.control_dt
    for done in range(0, n, k):
        for st, (mb, _, params, push) in zip(states, parts):
            st[1], tr = st[0](mb, st[1], params, push)
            st[2].append(tr)
        if progress is not None:
            jax.block_until_ready(states[0][1].tick)
            progress((done + k) * dt, n * dt)
    jax.block_until_ready([st[1].tick for st in states])
    simulate_s = time.perf_counter() - t0
    outs = []
    for r, st in zip(runners, states):
        trace = None
        if r.record is not None:
            trace = st[2][0] if len(st[2]) == 1 else jax.tree_util.tree_map(
                lambda *xs: jnp.concatenate(xs, axis=1), *st[2])
        outs.append(jax.tree_util.tree_map(np.asarray, rollout_result(st[1], trace)))
    sizes = [int(p[1].qpos.shape[0]) for p in parts]
    total = sum(sizes)
    out = _join(outs, sizes)  # batched leaves joined; one without the batch axis (Warp's contact buffer) is device 0's
    timing = dict(compile_s=compile_s, trace_s=trace_s, simulate_s=simulate_s, compiled=compiled,
                  from_cache=from_cache, batch=total, passes=1, instances=total, devices=len(runners),
                  wall_s=time.perf_counter() - t_start)
    for r in runners:
        r.last_timing = dict(r.last_timing, simulate_s=simulate_s)
    notify("done", **timing)
    return out


def _join(outs: list, sizes: list):
    """Results of consecutive row groups joined along the batch axis (host NumPy); a leaf without the batch axis
    (Warp's contact buffer) is the first group's."""
    def cat(*xs):
        if all(np.ndim(x) >= 1 and x.shape[0] == b for x, b in zip(xs, sizes)):
            return np.concatenate(xs, 0)
        return xs[0]

    return outs[0] if len(outs) == 1 else jax.tree_util.tree_map(cat, *outs)


def run_on(devices: list, n: int, inputs_of: Callable, runner_of: Callable, impl: str,
           progress: Progress | None = None, chunk_seconds: float | None = None,
           how: str | None = None) -> RolloutResult:
    """Run a batch of ``n`` instances over ``devices`` in the layout of the resolved simulator ``impl``
    (:func:`hyqjax.sim.devices.layout`): ``one`` device, or ``split``, one single-device program per device
    (:func:`run_split`), the devices running at once:

    * MJX-JAX on host (CPU) devices: the passes of the one-device run (:meth:`hyqjax.sim.runner.BatchRunner.plan`:
      ``CPU_PASS`` rows, or one bucket up to it) dealt out to the devices, ``len(devices)`` passes at a time, from
      inputs made once for the whole batch: every pass runs the one-device program's shape on the same rows, so
      the results are bitwise those of one device (XLA's code for another batch shape may round differently). A
      batch of one pass runs on the first device.
    * otherwise (a GPU, MuJoCo Warp, a runner without buckets such as a sweep's, whose chunk is its compiled
      shape): N equal contiguous slices, the last padded by repeating instance ``n - 1``
      (MuJoCo Warp: each slice's data made for the slice, its contact buffer sized for it).

    ``inputs_of(idx)``: ``(mx_batched, d0, params, push)`` of the instances ``idx`` (a host integer array);
    ``runner_of(where)``: the :class:`hyqjax.sim.runner.BatchRunner` for ``where``, None (one device), a mesh, or a
    device (one runner per device, kept by the caller; :class:`RunnersByPlace` places the one-device runner on
    it). ``how`` overrides the layout (``"mesh"``: one program sharded over
    :func:`batch_mesh`). Returns the :class:`RolloutResult` of the ``n`` instances in order."""
    from hyqjax.sim import devices as hdevices

    devices = list(devices)
    how = how or hdevices.layout(impl, len(devices))
    if how != "split":
        runner = runner_of(None if how == "one" else batch_mesh(devices))
        return runner(*inputs_of(np.arange(n)), progress=progress, chunk_seconds=chunk_seconds)
    k = len(devices)
    rows_of = inputs_of
    if impl != "warp":  # the inputs made once for the whole batch, then cut: a part's rows are bitwise the batch's
        mb, d0, params, push = inputs_of(np.arange(n))
        m_axes, pax = hmodel.model_in_axes(mb), runner_of(devices[0]).params_axes

        def rows_of(idx):
            return (take_rows(mb, m_axes, idx), take_rows(d0, 0, idx), take_rows(params, pax, idx),
                    take_rows(push, 0, idx))

    if impl != "warp" and devices[0].platform == "cpu" and runner_of(None).buckets:
        plan = runner_of(None).plan(n, mb)  # the one-device run's passes (its batch buckets)
        groups = [[np.minimum(np.arange(p * plan.size, (p + 1) * plan.size), n - 1)
                   for p in range(r, min(r + k, plan.passes))] for r in range(0, plan.passes, k)]
    else:
        size = -(-n // k)
        groups = [[np.minimum(np.arange(i * size, (i + 1) * size), n - 1) for i in range(k)]]
    outs, sizes = [], []
    for g, group in enumerate(groups):
        parts = [jax.device_put(rows_of(idx), devices[i]) for i, idx in enumerate(group)]
        prog = None if progress is None else (
            lambda d, t, g=g: progress(g * t + d, len(groups) * t))
        outs.append(run_split([runner_of(devices[i]) for i in range(len(group))], parts, prog, chunk_seconds))
        sizes.append(sum(len(idx) for idx in group))
    total = sum(sizes)
    out = _join(outs, sizes)
    return jax.tree_util.tree_map(lambda x: x[:n] if np.ndim(x) >= 1 and x.shape[0] == total else x, out)


class RunnersByPlace:
    """The runners of ONE static setup, one per placement, built on first use by ``make(mesh)`` (a
    :class:`hyqjax.sim.runner.BatchRunner` factory) and kept: ``runners(None)`` the one-device runner,
    ``runners(device)`` the runner of that device's slice of a split batch (:func:`run_on`): the one-device runner
    placed on ``device`` (:meth:`hyqjax.sim.runner.BatchRunner.placed`, sharing its traced and compiled programs;
    ``make(None)`` for a runner that cannot be placed), ``runners(mesh)`` the runner sharded over ``mesh``."""

    def __init__(self, make: Callable[[Mesh | None], Any]):
        self.make, self._kept = make, {}

    def __call__(self, where=None):
        if where is None:
            key, mesh = None, None
        elif hasattr(where, "axis_names"):
            key, mesh = ("mesh", tuple(d.id for d in where.devices.flat), where.axis_names), where
        else:
            key, mesh = ("device", where.id), None
        if key not in self._kept:
            base = self(None) if key is not None and mesh is None else None
            self._kept[key] = base.placed(where) if hasattr(base, "placed") else self.make(mesh)
        return self._kept[key]


def run_tree_on(devices, runners: Callable, impl: str, tree: Any, inputs_of: Callable,
                progress: Progress | None = None, chunk_seconds: float | None = None) -> RolloutResult:
    """:func:`run_on` of a batch given as a PyTree ``tree`` whose every leaf has the leading batch axis (e.g.
    ``(scenario, params)``): ``inputs_of(rows)`` makes ``(mx_batched, d0, params, push)`` of a PyTree of rows;
    ``runners`` e.g. a :class:`RunnersByPlace`. Each row keeps its inputs whatever device computes it (a
    population's common random numbers stay common)."""
    n = int(jax.tree_util.tree_leaves(tree)[0].shape[0])
    full = np.arange(n)

    def rows(idx):
        if len(idx) == n and np.array_equal(idx, full):
            return inputs_of(tree)
        return inputs_of(jax.tree_util.tree_map(lambda x: x[idx], tree))

    return run_on(list(devices), n, rows, runners, impl, progress, chunk_seconds)


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named ``"batch"`` over ``devices`` (default: all local devices)."""
    devs = np.asarray(jax.local_devices() if devices is None else devices)
    return Mesh(devs, ("batch",))


__all__ = ["RunnersByPlace", "batch_mesh", "run_on", "run_split", "run_tree_on"]
