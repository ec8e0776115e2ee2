"""Tracing several programs over one model, and compiling one: jitted physics and controller steps, or plain calls.

A process that builds several programs over one model (the tuner's window capture, its ``jacfwd`` objective, an
evaluation, a ``vjp``) traces each from Python. Calling ``mjx.step`` and the crawl's step as jitted functions inside
those programs would let JAX keep their traced programs and the derivative and batched programs derived from them.
``--mode jitted`` calls ``jax.jit(mjx.step)`` and ``jax.jit(crawl_step)`` (``--inline``: with ``inline=True``, the
traced program copied into the caller's), ``--mode plain`` calls them as hyqjax does (traced into every program).

For ``--programs`` programs in a row, each a new closure over the tuner's float64 window model (a ``lax.scan`` of
``--ticks`` control ticks: observe, the crawl at Table I, one physics step), the script records the seconds
``jax.make_jaxpr`` takes for its forward program, its ``jax.jacfwd`` over a scale of the crawl parameters, and that
``jacfwd`` under ``jax.vmap`` over three scales. With ``--compile`` it then compiles the first program's batched
``jacfwd`` (XLA seconds, lines of the optimised HLO) and prints the sum of its result, to compare the modes' values.
Prints one line per program and writes JSON. Run the modes in separate processes, alternated:

    PYTHONPATH=. python benchmarks/bench_trace_reuse.py --mode jitted --compile --out out/trace_jitted.json
    PYTHONPATH=. python benchmarks/bench_trace_reuse.py --mode plain --compile --out out/trace_plain.json
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
from mujoco import mjx  # noqa: E402

from hyqjax.crawl import controller as crawl  # noqa: E402
from hyqjax.sim import rollout as sim  # noqa: E402
from hyqjax.studies.tune import windows  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", choices=("jitted", "plain"), default="jitted")
    ap.add_argument("--programs", type=int, default=3, help="programs traced in a row (>= 1)")
    ap.add_argument("--ticks", type=int, default=5, help="control ticks of each program's scan (>= 1)")
    ap.add_argument("--inline", action="store_true", help="jitted with inline=True (--mode jitted)")
    ap.add_argument("--compile", action="store_true", help="compile the first program's batched jacfwd")
    ap.add_argument("--out", default=None, help="JSON file")
    a = ap.parse_args(argv)
    for name, v in (("--programs", a.programs), ("--ticks", a.ticks)):
        if v < 1:
            print(f"{name}={v}: must be >= 1", file=sys.stderr)
            return 2
    su = windows.setup(0.002, "float64")
    mx, ids = su.mx, su.ids
    d0 = mjx.make_data(mx)
    floating = lambda x: hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)  # noqa: E731
    p0 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if floating(x) else x, crawl.CrawlParams.make())
    cs0 = crawl.crawl_init(p0, sim.observe(ids, d0, jnp.zeros(12), mx))
    if a.mode == "plain":
        physics, controller = mjx.step, crawl.crawl_step
    else:
        physics = jax.jit(mjx.step, inline=a.inline)
        controller = jax.jit(crawl.crawl_step, static_argnames="dt", inline=a.inline)

    def program(k):
        def f(scale):
            p = jax.tree_util.tree_map(lambda x: x * scale if floating(x) else x, p0)

            def tick(c, _):
                d, cs, tau = c
                obs = sim.observe(ids, d, tau, mx)
                cs, tau, _ = controller(p, cs, obs, 0.002)
                return (physics(mx, d.replace(ctrl=tau)), cs, tau), None

            (d, _, _), _ = jax.lax.scan(tick, (d0, cs0, jnp.zeros(12) + k), None, length=a.ticks)
            return d.qpos
        return f

    rows = []
    for k in range(a.programs):
        row = dict(program=k)
        for kind, make in (("forward", lambda f: (f, 1.0)), ("jacfwd", lambda f: (jax.jacfwd(f), 1.0)),
                           ("vmap_jacfwd", lambda f: (jax.vmap(jax.jacfwd(f)), jnp.ones(3)))):
            fn, x = make(program(k))
            t = time.perf_counter()
            jax.make_jaxpr(fn)(x)
            row[kind + "_s"] = round(time.perf_counter() - t, 3)
        rows.append(row)
        print(a.mode, " ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    compiled = {}
    if a.compile:
        x = jnp.ones(3)
        lowered = jax.jit(jax.vmap(jax.jacfwd(program(0)))).lower(x)
        t = time.perf_counter()
        exe = lowered.compile()
        compiled = dict(xla_s=round(time.perf_counter() - t, 3), hlo_lines=exe.as_text().count("\n"),
                        result_sum=float(jnp.sum(exe(x))))
        print(a.mode, " ".join(f"{k}={v!r}" for k, v in compiled.items()), flush=True)
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        meta = dict(mode=a.mode, inline=a.inline, ticks=a.ticks, xla_flags=os.environ.get("XLA_FLAGS", ""),
                    date=datetime.date.today().isoformat(), jax=jax.__version__,
                    machine=platform.machine(), cpus=os.cpu_count())
        with open(a.out, "w") as fh:
            json.dump(dict(meta=meta, rows=rows, compiled=compiled), fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
