"""Refine the default bounding gains at the fast corners of the command envelope: CMA-ES warm-started from a
bounding preset on a training batch that weights the hard region, then the start and the refined sets compared on
the same held-out instances. One command, one GPU, everything under ``--out``:

    python -m experiments.bounding_refine --impl warp --out out/bounding_refine                  # one H200, ~7 min
    python -m experiments.bounding_refine --impl c --popsize 4 --train-envelope 2 --train-corners 2 \\
        --train-duration 0.8 --duration 0.8 --instances 2 --broad 4 --max-wall 20 --out /tmp/br   # CPU check
    python -m experiments.bounding_refine --impl warp --methods cma_es guided_es --max-wall 150 --instances 256 \\
        --out out/bounding_guided                                          # guided ES vs CMA-ES, one H200, ~6.5 min

1. ``training``: evosax CMA-ES (:func:`hyqjax.bounding.robust.cma_es`) on the robust study's coordinates
   (:class:`hyqjax.bounding.robust.RobustSpace` around the paper's gains, the same scales and bounds), started at
   ``theta0 = space.theta_of(values of --start-preset)`` with step ``--sigma``. Every candidate is judged by the mean
   :func:`hyqjax.bounding.tracking.total_cost` (falls dominate) over ONE fixed training batch (seed ``--seed``), a
   mixture of ``--train-envelope`` instances of the whole envelope (the robust study's training draw: speed
   0-1.1 m/s, yaw rate +-0.9 rad/s, lateral +-0.2 m/s, friction 0.4-1.0, payload 0-12 kg) and ``--train-corners``
   instances of the fast corners at low friction and high payload (speed ``--corner-speed``, yaw rate of magnitude
   ``--corner-yaw-rate`` with both signs in equal numbers, friction ``--corner-friction``, payload
   ``--corner-payload``, no lateral command), ``--train-duration`` s each. Stopped at ``--max-wall`` s (a generation
   started before the limit finishes; the compile happens before, in the start's evaluation on the same batch).
   Recorded per generation: best so far, the generation's best, mean and median, falls of its best candidate and of
   the whole population, the mean cost on the envelope and on the corner part of the batch. The refined set is the best candidate on the training
   batch (the start itself if none beats it); CMA-ES's final mean is kept as a second candidate.
2. ``heldout``: the start preset, the refined set and CMA-ES's final mean on the same instances: (a) the six
   conditions of :mod:`experiments.bounding_presets` (the nominal command at friction 0.7-1.0 and 0-5 kg; the nominal
   command and the four corners (0 and 1.0 m/s x -0.8 and +0.8 rad/s) at friction ``--friction`` with ``--payload``
   kg) at ``--instances`` each, seed ``--heldout-seed`` (default 2911: the start's rows reproduce
   ``docs/results/bounding_presets_h200``); (b) the robust study's held-out envelope (``--broad`` instances of
   ``--duration`` s, speed 0-1 m/s, yaw rate +-0.8 rad/s, friction 0.5-1.0, payload 0-10 kg, seed ``--broad-seed``,
   default 7777). Falls with Wilson 95 % intervals and reasons, worst and 95th-percentile yaw error, runs above
   4 deg, mean absolute speed error, mean cost.

Sizing for one H200 under MuJoCo Warp (one call of at most 9 minutes): a generation is popsize 16 x 128 training
instances = 2,048 rollouts of 8 s. The robust study's CMA-ES ran 4,096 such rollouts per generation in about 3.9 s on
one H100 (``docs/results/bounding_robust_h100_8s``: 55 generations in 295 s, the first with its compile), so 2,048
take about 2-3 s and ``--max-wall 280`` gives about 90-140 generations (the start's evaluation before it carries the
compile). Held-out: 3 sets x (6 x 1,024 + 4,096) = 30,720 rollouts, 15 chunks of 2,048, about 40-75 s.

Guided ES against CMA-ES at equal wall-clock (``--methods cma_es guided_es``): each method in turn from the same
start on the same training batch and the same ``f_pop``, each until ``--max-wall`` s (the start's evaluation, with the
forward runs' compile, comes before both), then the start and every method's best candidate and final mean (sets
``<method>`` and ``<method>_mean``, files ``params_<method>.json`` and ``params_<method>_mean.json``) on the same
held-out instances. Guided ES (:func:`hyqjax.bounding.guided.guided_es`: evosax ``GuidedES``, antithetic, the mean moved
by Adam at ``--guided-lr``, perturbations of expected norm ``--guided-sigma``, isotropic share ``--alpha``, the last
``--subspace`` gradients spanning the guided part) takes a surrogate gradient every ``--grad-every`` generations:
:func:`hyqjax.bounding.robust.make_value_and_jac` (MJX-JAX ``jacfwd``, 22 tangents) at its mean on ``--grad-instances``
of the training instances (spread over the envelope and corner parts) for ``--grad-duration`` s; the gradient is built
and compiled inside the method's clock, so its compile is part of the budget. Reported per method
(``results.json``: ``training.methods``, ``comparison``; ``refine.md``): wall-clock, generations, physics steps
(forward candidates, gradient tangents: ``robust.physics_steps(instances, duration, tangents=22)`` a gradient, and
total), the broad held-out falls with Wilson 95 % intervals and worst yaw of both sets; for guided ES every
generation's surrogate loss, gradient time (and compile), and the cosines of the surrogate gradient with what that
generation's antithetic pairs measured (:func:`hyqjax.studies.tune.guided.guided_cosines`; ``cos_sampled``, inside the
span of the pairs, is 1 on a linear cost whose gradient the surrogate is, and has a chance spread of about
``1 / sqrt(popsize / 2)`` for an unrelated one), summarised by median and share > 0. With ``--methods cma_es`` alone
(the default) the run and its outputs are the refinement above.

Sizing of the comparison on one H200 (one call of at most 9 minutes), from the runs above and the robust study's
(``docs/results/bounding_robust_h100*``): the start's evaluation with the Warp compile about 120 s; a CMA-ES generation
about 3.2 s; the MJX-JAX ``jacfwd`` gradient (22 tangents) took 6.0 s per call over 128 instances x 3.2 s and 16 s over
128 x 8 s on one H100 (about 2 s per simulated second at 128 instances), its first call 45-65 s more (compile).
Assumed here: 64 instances x 3.2 s take no longer than 128 did, about 6 s on an H200 (two CMA-ES generations; sized
to stay under three), and compile in about 60 s, both on guided ES's clock. ``--max-wall 150 --instances 256``:
2 x 150 s of training, held-out 5 sets x (6 x 256 + 4,096) = 28,160 runs, about 35 s; about 480 s in all.

Every simulator call runs in chunks of ``--chunk`` instances (default: popsize x training instances), so one
compiled program serves the training and every held-out batch. The training seed must differ from both held-out
seeds. Writes ``OUT/results.json`` (config, provenance, training history, held-out rows), ``OUT/refine.md`` (the
tables), ``OUT/params_refined.json`` and ``OUT/params_refined_mean.json`` (:func:`hyqjax.bounding.robust.save_params`
files with provenance: command, seeds, device, date, versions; ``hyqjax bound --params FILE`` runs them and
``experiments/build_presets.py`` can read them as a preset's source). Bad options: one line, exit code 2, before
anything compiles.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

#: The robust study's training draw (experiments/bounding_robust.py defaults): the whole envelope.
ENVELOPE_TRAIN = dict(speed=(0.0, 1.1), yaw_rate=(-0.9, 0.9), lateral=(-0.2, 0.2), friction=(0.4, 1.0),
                      payload=(0.0, 12.0))
#: The robust study's held-out draw (experiments/bounding_robust.py defaults, seed 7777).
BROAD_HELDOUT = dict(speed=(0.0, 1.0), yaw_rate=(-0.8, 0.8), lateral=(0.0, 0.0), friction=(0.5, 1.0),
                     payload=(0.0, 10.0))
PROG = "python -m experiments.bounding_refine"
#: The search methods of ``--methods``.
METHODS = ("cma_es", "guided_es")


def log(msg):
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


def parse(argv):
    from experiments import bounding_presets as bpre

    ap = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="out/bounding_refine")
    ap.add_argument("--impl", default="auto", help="simulator: auto | jax | warp | c")
    ap.add_argument("--start-preset", default="bound_robust_8s", metavar="NAME", help="bounding preset to start from")
    ap.add_argument("--seed", type=int, default=4242, help="training instances and CMA-ES seed (not a held-out seed)")
    # training
    ap.add_argument("--methods", nargs="+", default=["cma_es"], metavar="METHOD",
                    help=f"search methods, run one after the other from the same start on the same training batch at "
                         f"the same --max-wall each: {' '.join(METHODS)} (default: cma_es alone, the sets named "
                         f"refined and refined_mean)")
    ap.add_argument("--popsize", type=int, default=16, help="population of each method (even for guided_es)")
    ap.add_argument("--sigma", type=float, default=0.15, help="CMA-ES initial step (theta units: a coordinate's scale)")
    ap.add_argument("--max-wall", type=float, default=280.0,
                    help="wall-clock limit of each method (s; the forward runs' compile comes before, in the start's "
                         "evaluation; guided ES's gradient compile is inside its limit)")
    # guided ES (hyqjax.bounding.guided)
    ap.add_argument("--guided-sigma", type=float, default=0.7,
                    help="guided ES: the perturbations' expected norm (theta units; 0.7 ~ CMA-ES's 0.15 x sqrt(22))")
    ap.add_argument("--guided-lr", type=float, default=0.1, help="guided ES: Adam's step on the mean (theta units)")
    ap.add_argument("--alpha", type=float, default=0.5, help="guided ES: isotropic share of the sampling variance")
    ap.add_argument("--subspace", type=int, default=1, help="guided ES: recent gradients spanning the guided part")
    ap.add_argument("--grad-instances", type=int, default=64,
                    help="guided ES: training instances of the surrogate gradient (spread over the batch's parts)")
    ap.add_argument("--grad-duration", type=float, default=3.2,
                    help="guided ES: rollout of the surrogate gradient (s), a multiple of 0.4, <= --train-duration")
    ap.add_argument("--grad-every", type=int, default=1, help="guided ES: a new surrogate gradient every N generations")
    ap.add_argument("--max-generations", type=int, default=100000)
    ap.add_argument("--train-envelope", type=int, default=64, help="training instances from the whole envelope")
    ap.add_argument("--train-corners", type=int, default=64,
                    help="training instances at the fast corners (an even number: half each yaw sign)")
    ap.add_argument("--train-duration", type=float, default=8.0, help="training rollout (s), a multiple of 0.4")
    ap.add_argument("--corner-speed", type=float, nargs=2, default=(0.85, 1.1), metavar=("LO", "HI"))
    ap.add_argument("--corner-yaw-rate", type=float, nargs=2, default=(0.65, 0.9), metavar=("LO", "HI"),
                    help="magnitude of the corners' yaw rate (both signs)")
    ap.add_argument("--corner-friction", type=float, nargs=2, default=(0.4, 0.6), metavar=("LO", "HI"))
    ap.add_argument("--corner-payload", type=float, nargs=2, default=(8.0, 12.0), metavar=("LO", "HI"))
    # held-out
    bpre.add_condition_arguments(ap)  # the six held-out conditions of experiments.bounding_presets
    ap.add_argument("--heldout-seed", type=int, default=2911, help="seed of the six conditions")
    ap.add_argument("--broad", type=int, default=4096, help="instances of the broad held-out envelope")
    ap.add_argument("--broad-seed", type=int, default=7777)
    ap.add_argument("--chunk", type=int, default=0,
                    help="instances per simulator call (default: popsize x training instances)")
    return ap.parse_args(argv)


class Refused(ValueError):
    pass


def _multiple(name, v):
    if not (np.isfinite(v) and v > 0 and abs(v / 0.4 - round(v / 0.4)) < 1e-6):
        raise Refused(f"--{name} must be a positive multiple of the gait period 0.4 s, got {v:g}")


def check(args):
    """Every option checked before anything compiles (:class:`Refused`, one line naming the option)."""
    from hyqjax import presets
    from hyqjax.bounding import batch as bbatch
    from hyqjax.sim import backend
    from hyqjax.studies import tasks

    try:
        backend.validate_impl(args.impl, tasks.get("bound").impls)
    except ValueError as e:
        raise Refused(f"--impl: {e}") from None
    try:
        presets.check_kind(args.start_preset, "bound", "--start-preset")
    except ValueError as e:
        raise Refused(str(e)) from None
    bad = [m for m in args.methods if m not in METHODS]
    if bad or len(set(args.methods)) != len(args.methods):
        raise Refused(f"--methods must be distinct names of {', '.join(METHODS)}, got {' '.join(args.methods)}")
    from hyqjax.bounding import robust

    for name, lo, hi in (("popsize", 4, 4096), ("max_generations", 1, 10**6), ("train_envelope", 0, 65536),
                         ("train_corners", 0, 65536), ("instances", 1, 1 << 20), ("broad", 1, 1 << 20),
                         ("chunk", 0, 1 << 20), ("subspace", 1, len(robust.COORDS) - 1), ("grad_every", 1, 10**4),
                         ("grad_instances", 1, args.train_envelope + args.train_corners if "guided_es" in args.methods
                          else 1 << 20)):
        v = getattr(args, name)
        if not lo <= v <= hi:
            raise Refused(f"--{name.replace('_', '-')} must be an int in [{lo}, {hi}], got {v}")
    if args.train_envelope + args.train_corners < 1:
        raise Refused("--train-envelope plus --train-corners must be at least 1")
    if args.train_corners % 2:
        raise Refused(f"--train-corners must be even (half each yaw sign), got {args.train_corners}")
    for name, lo, hi in (("sigma", 1e-3, 10.0), ("max_wall", 1.0, 86400.0)):
        v = getattr(args, name)
        if not (np.isfinite(v) and lo <= v <= hi):
            raise Refused(f"--{name.replace('_', '-')} must be in [{lo:g}, {hi:g}], got {v:g}")
    for name, lo, hi in (("guided_sigma", 1e-3, 10.0), ("guided_lr", 1e-4, 10.0)):
        v = getattr(args, name)
        if not (np.isfinite(v) and lo <= v <= hi):
            raise Refused(f"--{name.replace('_', '-')} must be in [{lo:g}, {hi:g}], got {v:g}")
    if not (np.isfinite(args.alpha) and 0.0 < args.alpha <= 1.0):
        raise Refused(f"--alpha must be in (0, 1], got {args.alpha:g}")
    if "guided_es" in args.methods and args.popsize % 2:
        raise Refused(f"--popsize must be even for guided_es (antithetic pairs), got {args.popsize}")
    _multiple("train-duration", args.train_duration)
    _multiple("duration", args.duration)
    _multiple("grad-duration", args.grad_duration)
    if "guided_es" in args.methods and args.grad_duration > args.train_duration + 1e-9:
        raise Refused(f"--grad-duration must be <= --train-duration ({args.train_duration:g}), got "
                      f"{args.grad_duration:g}")
    if args.seed in (args.heldout_seed, args.broad_seed):
        raise Refused(f"--seed must differ from --heldout-seed ({args.heldout_seed}) and --broad-seed "
                      f"({args.broad_seed}), got {args.seed}")
    if not 0.0 <= args.payload <= 100.0:
        raise Refused(f"--payload must be in [0, 100] kg, got {args.payload:g}")
    try:
        for d in train_draws(args).values():
            d.commands(1, 0)
        heldout_specs(args)
        draw_of(BROAD_HELDOUT)
    except (ValueError, bbatch.SettingError) as e:
        name = getattr(e, "name", "")
        raise Refused(f"{name + ': ' if name else ''}{e}") from None


def draw_of(d: dict):
    from hyqjax.bounding import robust

    return robust.Draw(**{k: tuple(v) for k, v in d.items()})


def train_draws(args) -> dict:
    """The training mixture's parts: ``envelope``, ``corners+`` and ``corners-`` (:class:`robust.Draw`)."""
    lo, hi = args.corner_yaw_rate
    if not 0.0 <= lo <= hi:
        raise Refused(f"--corner-yaw-rate must be 0 <= LO <= HI (a magnitude), got {lo:g} {hi:g}")
    c = dict(speed=tuple(args.corner_speed), lateral=(0.0, 0.0), friction=tuple(args.corner_friction),
             payload=tuple(args.corner_payload))
    return {"envelope": draw_of(ENVELOPE_TRAIN), "corners+": draw_of(dict(c, yaw_rate=(lo, hi))),
            "corners-": draw_of(dict(c, yaw_rate=(-hi, -lo)))}


def concat_batches(batches):
    """One :class:`hyqjax.bounding.batch.Batch` of the instances of ``batches`` in order."""
    import jax
    import jax.numpy as jnp

    return jax.tree_util.tree_map(
        lambda *xs: np.concatenate(xs) if all(isinstance(x, np.ndarray) for x in xs)
        else jnp.concatenate([jnp.asarray(x) for x in xs]), *batches)


def training_batch(args, base=None):
    """The fixed training batch (envelope part first, then the corners, + then - yaw) and each instance's part
    (``"envelope"`` or ``"corners"``). Each part has its own seed derived from ``--seed``."""
    draws = train_draws(args)
    half = args.train_corners // 2
    sizes = {"envelope": args.train_envelope, "corners+": half, "corners-": half}
    parts, labels = [], []
    for i, (k, d) in enumerate(draws.items()):
        if sizes[k]:
            parts.append(d.batch(sizes[k], seed=args.seed * 10 + i, base=base))
            labels += ["envelope" if k == "envelope" else "corners"] * sizes[k]
    return concat_batches(parts), np.array(labels)


def heldout_specs(args):
    """The six conditions of experiments.bounding_presets (name, EnvelopeSpec) at ``--heldout-seed``."""
    from experiments import bounding_presets as bp

    ns = argparse.Namespace(friction=args.friction, payload=args.payload, corner_speeds=args.corner_speeds,
                            corner_yaw_rates=args.corner_yaw_rates, instances=args.instances, duration=args.duration,
                            seed=args.heldout_seed)
    return bp.specs(ns)


def run_sets(batches: dict, duration: float, impl: str, chunk: int, progress=None) -> dict:
    """Run every batch of ``batches`` (key -> Batch) in one call, in chunks of exactly ``chunk`` instances (the
    concatenation is padded with copies of its first instance to a multiple of ``chunk``, so the training's compiled
    program serves it), and split the columns by key (with the command, friction and payload of each instance)."""
    from hyqjax.bounding import tracking

    keys = list(batches)
    sizes = [int(np.shape(batches[k].apex0)[0]) for k in keys]
    n = sum(sizes)
    allb = concat_batches([batches[k] for k in keys])
    pad = -n % chunk
    if pad:
        allb = tracking.take(allb, np.concatenate([np.arange(n), np.zeros(pad, int)]))
    cols = tracking.run_batch(allb, duration, impl, max_batch=chunk, progress=progress)
    out, start = {}, 0
    for key, k in zip(keys, sizes):
        b = batches[key]
        c = {name: v[start:start + k] for name, v in cols.items()}
        cmd = np.asarray(b.params.command.velocity, np.float64)
        c.update(speed_cmd=cmd[:, 0], lateral_cmd=cmd[:, 1],
                 yaw_rate_cmd=np.asarray(b.params.command.yaw_rate, np.float64),
                 friction=np.asarray(b.terrain.friction, np.float64),
                 payload=np.asarray(b.terrain.payload_mass, np.float64))
        out[key] = c
        start += k
    return out


def broad_table(rows: list[dict]) -> str:
    out = [("| set | runs | falls [95 %] | fall reasons | worst yaw (deg) | yaw p95 (deg) | runs >= 4 deg | "
            "mean abs speed error (m/s) | mean cost |"), "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        ci = r["fall_rate_ci95"]
        f = lambda x, d=2: "-" if x is None else f"{x:.{d}f}"  # noqa: E731
        reasons = ", ".join(f"{k.replace('fell_', '')} {v}" for k, v in r["reasons"].items()) or "-"
        out.append(f"| `{r['set']}` | {r['n']} | {r['failures']} [{100 * ci[0]:.2f}-{100 * ci[1]:.2f} %] | {reasons} | "
                   f"{f(r['yaw_error_worst_deg'])} | {f(r['yaw_error_p95_deg'])} | {r['yaw_over_4deg']} | "
                   f"{f(r.get('speed_error_mean_abs'), 3)} | {r['cost_mean']:.4f} |")
    return "\n".join(out)


def _deg(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def target_of(rows: list[dict], name: str) -> dict:
    """Issue 57's target for set ``name``: no fall and worst yaw < 4 deg at every low-friction, payload row."""
    from hyqjax.bounding import envelope

    low = [r for r in rows if r["set"] == name and r["condition"] != "nominal"]
    falls = int(sum(r["failures"] for r in low))
    worst = max((r["yaw_error_worst_deg"] for r in low if r["yaw_error_worst_deg"] is not None), default=None)
    return dict(falls=falls, runs=int(sum(r["n"] for r in low)), per_command=[r["failures"] for r in low],
                worst_yaw_deg=worst, met=bool(falls == 0 and worst is not None and worst < envelope.YAW_LIMIT_DEG))


#: The cosines of guided ES's surrogate gradient with its population's measurement that the summary reports
#: (:func:`hyqjax.studies.tune.guided.guided_cosines`; ``cos_sampled`` first: inside the span the pairs explored).
COSINES = ("cos_sampled", "cos_zero_order", "cos_search")


def set_names(method: str, default: bool) -> tuple[str, str]:
    """The held-out set names (and ``params_<name>.json`` files) of a method's best candidate and final mean:
    ``refined`` and ``refined_mean`` for the refinement's own run (``--methods cma_es``), else ``<method>`` and
    ``<method>_mean``."""
    return ("refined", "refined_mean") if default else (method, f"{method}_mean")


def train_method(method: str, args, space, train, theta0, f_pop):
    """Run one search method from ``theta0`` for ``--max-wall`` s on ``f_pop`` (the training batch's forward
    runs): ``(its result dict, the method's record for results.json, dict(label, short, settings) for the
    provenance)``. ``cma_es``: :func:`hyqjax.bounding.robust.cma_es`; ``guided_es``:
    :func:`hyqjax.bounding.guided.guided_es` with the surrogate gradient of
    :func:`hyqjax.bounding.guided.make_surrogate` on ``--grad-instances`` of the training batch, ``--grad-duration`` s,
    built and compiled inside the method's clock."""
    from hyqjax.bounding import guided, robust, tracking

    n_train = int(np.shape(train.apex0)[0])
    step = robust.physics_steps(n_train, args.train_duration)
    if method == "cma_es":
        out = robust.cma_es(f_pop, theta0, args.max_wall, args.popsize, args.sigma, args.seed,
                            max_generations=args.max_generations, cost_per_candidate=step, log=log)
        return out, {}, dict(label="CMA-ES (evosax)", short="CMA-ES", settings=f"sigma {args.sigma:g}")
    idx = guided.spread_subset(n_train, args.grad_instances)
    grad_fn = guided.make_surrogate(space, tracking.take(train, idx), args.grad_duration)
    grad_cost = robust.physics_steps(len(idx), args.grad_duration, tangents=space.size)
    out = guided.guided_es(f_pop, grad_fn, theta0, args.max_wall, args.popsize, args.guided_sigma, args.seed,
                           alpha=args.alpha, subspace=args.subspace, lr=args.guided_lr, grad_every=args.grad_every,
                           max_generations=args.max_generations, cost_per_candidate=step, grad_cost=grad_cost, log=log)
    settings = (f"sigma {args.guided_sigma:g}, lr {args.guided_lr:g}, alpha {args.alpha:g}, subspace {args.subspace}, "
                f"surrogate gradient (MJX-JAX jacfwd, {space.size} tangents) on {len(idx)} training instances x "
                f"{args.grad_duration:g} s every {args.grad_every} generation(s)")
    rec = dict(physics_steps_forward=out["budget_forward"], physics_steps_gradient=out["budget_gradient"],
               gradients=out["gradients"], grad_wall_s=out["grad_wall_s"], grad_compile_s=out["grad_compile_s"],
               grad_instances=len(idx), grad_instance_index=idx.tolist(), grad_duration=args.grad_duration,
               grad_tangents=space.size, grad_physics_steps_each=grad_cost, sigma=args.guided_sigma,
               lr=args.guided_lr, alpha=args.alpha, subspace=args.subspace, grad_every=args.grad_every)
    return out, rec, dict(label="guided ES (evosax GuidedES)", short="guided ES", settings=settings)


def trained_settings(rec: dict) -> str:
    return (f"sigma {rec['sigma']:g}, lr {rec['lr']:g}, alpha {rec['alpha']:g}, subspace {rec['subspace']}; surrogate "
            f"gradient on {rec['grad_instances']} instances x {rec['grad_duration']:g} s, {rec['grad_tangents']} "
            f"tangents, every {rec['grad_every']} generation(s)")


def comparison(trained: dict, broad: list[dict], start_value: float) -> dict:
    """Per method: its wall-clock, generations, physics steps (forward, gradient tangents, total), training cost, and
    the broad held-out falls (Wilson 95 %) and worst yaw of its best candidate and final mean; guided ES's gradient
    count and time and its cosine summary."""
    by_set = {r["set"]: r for r in broad}
    out = {}
    for m, t in trained.items():
        o, rec = t["out"], t["rec"]
        best_name, mean_name = set_names(m, False)
        c = dict(wall_s=o["wall_s"], generations=o["generations"],
                 physics_steps_forward=rec.get("physics_steps_forward", o["budget_spent"]),
                 physics_steps_gradient=rec.get("physics_steps_gradient", 0), physics_steps=o["budget_spent"],
                 training_start=start_value, training_best=o["value"], improved=bool(o["value"] < start_value))
        for key, name in (("best", best_name), ("mean", mean_name)):
            r = by_set[name]
            c[key] = dict(set=name, runs=r["n"], falls=r["failures"], falls_ci95=r["fall_rate_ci95"],
                          worst_yaw_deg=r["yaw_error_worst_deg"], yaw_p95_deg=r["yaw_error_p95_deg"],
                          cost_mean=r["cost_mean"])
        if m == "guided_es":
            c.update(gradients=rec["gradients"], grad_wall_s=rec["grad_wall_s"], grad_compile_s=rec["grad_compile_s"],
                     cosines=rec["cosines"])
        out[m] = c
    return out


def comparison_table(comp: dict) -> str:
    """The methods side by side (equal wall-clock; their physics steps), then guided ES's cosine summary."""
    lines = ["| method | wall-clock (s) | generations | physics steps: forward + gradient = total | training cost "
             "(start -> best) | broad falls, best [95 %] | worst yaw, best (deg) | broad falls, mean [95 %] | worst "
             "yaw, mean (deg) |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for m, c in comp.items():
        b, mn = c["best"], c["mean"]
        ci = lambda r: f"{r['falls']} of {r['runs']} [{100 * r['falls_ci95'][0]:.2f}-{100 * r['falls_ci95'][1]:.2f} %]"  # noqa: E731
        lines.append(f"| `{m}` | {c['wall_s']:.0f} | {c['generations']} | {c['physics_steps_forward']:.3g} + "
                     f"{c['physics_steps_gradient']:.3g} = {c['physics_steps']:.3g} | {c['training_start']:.4f} -> "
                     f"{min(c['training_best'], c['training_start']):.4f} | {ci(b)} | {_deg(b['worst_yaw_deg'])} | "
                     f"{ci(mn)} | {_deg(mn['worst_yaw_deg'])} |")
    for m, c in comp.items():
        if "cosines" not in c:
            continue
        lines += ["", f"`{m}`: {c['gradients']} surrogate gradients in {c['grad_wall_s']:.0f} s of its "
                      f"{c['wall_s']:.0f} s (the first with its compile, {c['grad_compile_s']:.0f} s). Cosine of the "
                      f"surrogate gradient with its generation's antithetic measurement over "
                      f"{c['cosines']['generations']} generations:"]
        for k in COSINES:
            v = c["cosines"].get(k)
            lines.append(f"* `{k}`: " + ("no finite value" if not v else
                                         f"median {v['median']:+.3f}, share > 0 {v['share_positive']:.2f} "
                                         f"(n {v['n']}; first third {v['first_third']:+.3f}, last third "
                                         f"{v['last_third']:+.3f})"))
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse(argv)
    try:
        check(args)
    except Refused as e:
        print(f"bounding_refine: {e}", file=sys.stderr)
        return 2
    from hyqjax.sim import backend
    from hyqjax.studies import tasks

    args.impl = backend.resolve_impl(args.impl, tasks.get("bound").impls)
    args.chunk = args.chunk or args.popsize * (args.train_envelope + args.train_corners)
    os.makedirs(args.out, exist_ok=True)
    command = " ".join([PROG, *(sys.argv[1:] if argv is None else argv)])
    run(args, command)
    return 0


def run(args, command: str) -> dict:
    import jax

    from hyqjax import presets
    from hyqjax.bounding import envelope, robust
    from hyqjax.bounding.params import params_of_values
    from hyqjax.io import atomic

    t_start = time.time()
    out = args.out
    path = os.path.join(out, "results.json")
    cfg = {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(args).items() if k != "out"}
    prov = dict(atomic.provenance(seed=args.seed), command=command)
    device = str(jax.devices()[0].device_kind)
    res = dict(config=cfg, provenance=prov, device=device, impl=args.impl)

    def save():
        atomic.write_json(path, res)

    # ---- 1. training
    space = robust.RobustSpace.make()
    start_values = robust.load_params(args.start_preset)  # the names it sets; the others stay the paper's
    start_params = presets.load(args.start_preset)
    theta0 = space.theta_of(start_values)
    back = space.describe(theta0)
    res["space"] = dict(names=list(space.names), start=list(space.start),
                        scale=[c[1] for c in robust.COORDS if c[0] in space.names],
                        start_preset=args.start_preset, theta0=theta0.tolist(),
                        theta0_roundtrip_max_abs=max(abs(back[k] - robust.value_of(start_params, k)) for k in back))
    train, labels = training_batch(args)
    n_train = len(labels)
    corner = labels == "corners"
    res["training"] = dict(instances=n_train, envelope=int((~corner).sum()), corners=int(corner.sum()),
                           duration=args.train_duration, seed=args.seed, envelope_draw=ENVELOPE_TRAIN,
                           corner_draw=dataclasses.asdict(train_draws(args)["corners+"]),
                           corner_yaw_rate_magnitude=list(args.corner_yaw_rate), popsize=args.popsize,
                           sigma=args.sigma, max_wall_s=args.max_wall, chunk=args.chunk)
    save()
    gens: list[dict] = []
    t_cma = [None]

    def f_pop(xs):
        vals, cols = robust.population_cost(space, xs, train, args.train_duration, args.impl, max_batch=args.chunk)
        c = xs.shape[0]
        fell = ~np.asarray(cols["success"], bool).reshape(c, n_train)
        cost = np.asarray(cols["cost"], np.float64).reshape(c, n_train)
        i = int(np.argmin(np.where(np.isfinite(vals), vals, np.inf)))
        fin = vals[np.isfinite(vals)]
        gens.append(dict(wall_s=round(time.time() - t_cma[0], 3) if t_cma[0] else None,
                         generation_best=float(vals[i]), generation_mean=float(np.mean(fin)) if fin.size else None,
                         generation_median=float(np.median(fin)) if fin.size else None,
                         best_falls=int(fell[i].sum()), best_falls_corners=int(fell[i][corner].sum()),
                         population_falls=int(fell.sum()),
                         best_cost_envelope=float(cost[i][~corner].mean()) if (~corner).any() else None,
                         best_cost_corners=float(cost[i][corner].mean()) if corner.any() else None,
                         diverged=int(np.sum(cols["diverged"]))))
        return vals

    # the start on the training batch (the population's shape: one compiled program; its compile is here)
    t0 = time.time()
    log(f"start {args.start_preset} on the training batch ({n_train} instances: {int((~corner).sum())} envelope, "
        f"{int(corner.sum())} corners; x {args.popsize} copies, chunk {args.chunk}, impl {args.impl})")
    f_pop(np.tile(theta0, (args.popsize, 1)))
    start_rec = gens.pop()
    start_rec.update(value=start_rec.pop("generation_best"), wall_s=round(time.time() - t0, 3))
    for k in ("generation_mean", "generation_median", "population_falls"):
        start_rec.pop(k)
    res["training"]["start"] = start_rec
    log(f"start: training cost {start_rec['value']:.4f}, falls {start_rec['best_falls']} of {n_train} "
        f"({start_rec['best_falls_corners']} at the corners), {start_rec['wall_s']:.0f} s (compile included)")
    save()

    default = args.methods == ["cma_es"]  # the refinement's own outputs: sets refined / refined_mean
    trained = {}
    for m in args.methods:
        gens.clear()
        t_cma[0] = time.time()
        out_m, rec, meta = train_method(m, args, space, train, theta0, f_pop)
        hist = []
        for h, g in zip(out_m["history"], gens):
            extra = {k: v for k, v in h.items() if k not in ("generation", "wall_s", "best", "theta", "budget",
                                                              "generation_best")}
            hist.append(dict(generation=h["generation"], wall_s=h["wall_s"], best=h["best"], **{
                k: v for k, v in g.items() if k != "wall_s"}, **extra))
        improved = out_m["value"] < start_rec["value"]
        theta_ref = np.asarray(out_m["theta"]) if improved else theta0
        theta_mean = np.asarray(out_m["mean"])
        rec.update(generations=out_m["generations"], wall_s=out_m["wall_s"], physics_steps=out_m["budget_spent"],
                   best_value=out_m["value"], improved=bool(improved), theta=theta_ref.tolist(),
                   params=space.describe(theta_ref), mean_theta=theta_mean.tolist(),
                   mean_params=space.describe(theta_mean), history=hist)
        if m == "guided_es":
            from hyqjax.studies.tune.study.guided import cosine_summary

            rec["cosines"] = cosine_summary(hist, COSINES)
        if default:
            res["training"].update(rec)
        else:
            res["training"].setdefault("methods", {})[m] = rec
        log(f"{m}: {out_m['generations']} generations in {out_m['wall_s']:.0f} s, best {out_m['value']:.4f} "
            f"(start {start_rec['value']:.4f}{'' if improved else ': no candidate beat the start, kept'})")
        save()
        names = set_names(m, default)
        for fname, th, what in ((f"params_{names[0]}.json", theta_ref, "best candidate on the training batch"),
                                (f"params_{names[1]}.json", theta_mean, f"{meta['short']}'s final mean")):
            robust.save_params(os.path.join(out, fname), space.describe(th), dict(
                method=f"{meta['label']} warm-started from preset {args.start_preset}, {meta['settings']}, popsize "
                       f"{args.popsize}, impl {args.impl}: {what}",
                command=command, seed=args.seed, heldout_seeds=[args.heldout_seed, args.broad_seed], device=device,
                date=prov["date"], hyqjax=prov["hyqjax"], jax=prov["jax"], mujoco=prov["mujoco"],
                mujoco_mjx=prov["mujoco_mjx"], generations=out_m["generations"], wall_s=round(out_m["wall_s"], 1),
                training=dict(instances=n_train, envelope=int((~corner).sum()), corners=int(corner.sum()),
                              duration=args.train_duration, corner_draw=res["training"]["corner_draw"],
                              corner_yaw_rate_magnitude=list(args.corner_yaw_rate), envelope_draw=ENVELOPE_TRAIN),
                results="results.json"))
        trained[m] = dict(rec=rec, out=out_m, theta=theta_ref, mean=theta_mean)

    # ---- 2. held-out, the same instances for every set
    sets = {args.start_preset: start_params}
    for m, t in trained.items():
        best_name, mean_name = set_names(m, default)
        sets.update({best_name: params_of_values(space.describe(t["theta"])),
                     mean_name: params_of_values(space.describe(t["mean"]))})
    t0 = time.time()
    specs = heldout_specs(args)
    bd = draw_of(BROAD_HELDOUT)
    batches = {}
    for i, (cond, spec) in enumerate(specs):
        batches.update({(i, n): spec.batch(b) for n, b in sets.items()})
    batches.update({("broad", n): bd.batch(args.broad, seed=args.broad_seed, base=b) for n, b in sets.items()})
    total = sum(int(np.shape(b.apex0)[0]) for b in batches.values())
    log(f"held-out: {len(sets)} sets x ({', '.join(str(s.size) for _, s in specs)} + {args.broad}) = {total} runs of "
        f"{args.duration:g} s, chunks of {args.chunk}")
    cols = run_sets(batches, args.duration, args.impl, args.chunk,
                    progress=lambda d, t: log(f"held-out: {min(d, total)} of {total} runs done"))
    rows = []
    for i, (cond, spec) in enumerate(specs):
        for n in sets:
            for c in envelope.summarise(spec, cols[(i, n)]):
                rows.append(dict(set=n, preset=n, condition=cond, friction=list(spec.friction),
                                 payload=list(spec.payload), **c))
    broad = []
    for n in sets:
        s = envelope.group_summary(cols[("broad", n)])
        s.update(set=n, cost_mean=float(np.mean(cols[("broad", n)]["cost"])))
        broad.append(s)
    log(f"held-out: {total} runs in {time.time() - t0:.0f} s")
    res["heldout"] = dict(
        conditions=dict(seed=args.heldout_seed, instances=args.instances, duration=args.duration, rows=rows,
                        specs=[dict(name=n, **s.to_dict()) for n, s in specs]),
        broad=dict(seed=args.broad_seed, instances=args.broad, duration=args.duration, draw=BROAD_HELDOUT,
                   sets=broad),
        target={n: target_of(rows, n) for n in sets}, wall_s=time.time() - t0)
    if not default:
        res["comparison"] = comparison(trained, broad, start_rec["value"])
    res["wall_s"] = time.time() - t_start
    save()

    from experiments import bounding_presets as bp

    tg = res["heldout"]["target"]
    lines = [f"# Bounding refinement at the fast corners ({device}, impl {args.impl}, {prov['date']})", "",
             f"`{command}`", "",
             *[(f"{'CMA-ES' if m == 'cma_es' else 'Guided ES'} from `{args.start_preset}` "
                f"({'sigma %g' % args.sigma if m == 'cma_es' else trained_settings(t['rec'])}, popsize "
                f"{args.popsize}): {t['out']['generations']} generations in {t['out']['wall_s']:.0f} s on {n_train} "
                f"training instances ({int((~corner).sum())} envelope, {int(corner.sum())} fast corners) x "
                f"{args.train_duration:g} s, seed {args.seed}; training cost {start_rec['value']:.4f} -> "
                f"{min(t['out']['value'], start_rec['value']):.4f}.") for m, t in trained.items()],
             *([] if default else ["", f"## Methods at equal wall-clock ({args.max_wall:g} s each) on the broad "
                                       f"held-out envelope", "", comparison_table(res["comparison"])]),
             "", f"## Six conditions, seed {args.heldout_seed}, {args.instances} runs x {args.duration:g} s each", "",
             bp.table(rows), "",
             "Target (no fall and worst yaw < 4 deg at every low-friction, payload command): " + "; ".join(
                 f"`{n}` {'met' if t['met'] else 'not met'} ({t['falls']} falls in {t['runs']}, worst yaw "
                 f"{_deg(t['worst_yaw_deg'])} deg)"
                 for n, t in tg.items()), "",
             f"## Broad held-out envelope, seed {args.broad_seed}, {args.broad} runs x {args.duration:g} s", "",
             broad_table(broad), "", f"Total wall-clock {res['wall_s']:.0f} s.", ""]
    with open(os.path.join(out, "refine.md"), "w") as f:
        f.write("\n".join(lines))
    print("\n".join(lines))
    log(f"done: {path}")
    return res


if __name__ == "__main__":
    raise SystemExit(main())
