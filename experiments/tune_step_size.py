"""How much a search's first samples lose around a tuned set, per step size: the local landscape that decides the
step size a search started from a tuned preset should take.

    python -m experiments.tune_step_size --out DIR                                   # C MuJoCo on a CPU
    python -m experiments.tune_step_size --out DIR --impl warp --samples 64 --instances 256     # one GPU
    python -m experiments.tune_step_size --out DIR --preset none --antithetic --samples 64 --sigmas 0.028 0.1 0.3
    python -m experiments.tune_step_size --out DIR --instances 256 --sigmas --line -0.4 0.1 0.4     # down the surrogate

The start is a crawl preset (``--preset``, ``clean`` by default) in the tuner's coordinates (``--dim``, the 56
per-leg ones by default; :func:`hyqjax.studies.tune.wallclock_config.start_theta`). For every step size ``sigma``
of ``--sigmas`` it draws ``--samples`` points ``theta_0 + sigma z`` (``z`` standard normal: exactly a first
generation of CMA-ES, SNES or isotropic ES at that step) and runs the start and every sample on the same
``--instances`` training step-downs (the tuner's training heights, 16-28 cm, on the wide spread or ``--spread``'s;
seed ``--seed``).
Because every member runs the same instances, the differences are paired: per sample the difference of its clean
rate from the start's, ``d_i``, and of its fitness (clean + 0.1 x completed, the tuner's). Per step size: the mean
``d`` with its 95% interval over samples, the best and worst sample, the share of samples at least as clean as the
start, and the runs not completed, not clean, fallen and diverged. Writes ``DIR/step_size.json`` and
``DIR/step_size.md``.

A sample as clean as its start on the same instances is what a search needs to climb; a step size whose mean loss is
large and whose best sample does not beat the start spends its generations off the ridge (the measured cause of
five 3-minute runs from ``clean`` returning it, docs/tuning.md).

``--antithetic`` draws the samples as ``--samples / 2`` pairs ``theta_0 +- sigma z`` (an antithetic generation of
OpenES or guided ES) and measures whether their differences carry a direction the search can follow: per pair the
fitness difference ``d = f(theta_0 + sigma z) - f(theta_0 - sigma z)`` on each half of the instances (the halves
split every height's instances in two), and over pairs the correlation of the two halves' ``d`` (Pearson, 95%
interval by Fisher's z): near 0 when the differences are outcome noise of the instances, positive when the same
perturbation helps on other instances too, i.e. when the zero-order estimate ``sum_i d_i z_i`` measures a
gradient. Also the cosine of the two halves' estimates, the pairs whose members differ at all and the mean
``|d|``. ``--preset none`` starts from Table I with the shin remedy (the equal-wall-clock study's start).

``--surrogate`` (with ``--antithetic``) also computes at the start the surrogate gradient guided ES is given there
(the tuner's window objective differentiated on MJX-JAX, :class:`hyqjax.studies.tune.gradient_programs.
GradientPrograms`, ``jacfwd``) and measures, per step size, its agreement with the pairs
(:func:`hyqjax.studies.tune.guided.guided_cosines` with isotropic samples): the slope of the fitness along its descent
direction, its cosine with the pairs' zero-order estimate (and with each half's), and inside the sampled directions.
A step size whose estimate reproduces across the halves is a reference the surrogate can be judged against.

``--line T [T ...]`` also computes that surrogate gradient ``g`` and runs the points ``theta_0 - t g / |g|`` (``t``
the distance in the tuner's normalised coordinates; a negative ``t`` goes up the surrogate) on the same step-downs:
per distance the clean rate and fitness and their differences from the start's, paired over the step-downs, with
95% intervals, and the window objective the surrogate descends (on the start's windows) at that point. It measures
how far the surrogate's descent direction stays a descent of the full-run fitness, the distance a guided search's
mean may travel along it (its Adam step moves every coordinate about ``lr`` a generation, ``lr sqrt(P)`` in norm).
``--sigmas`` with no value runs the line alone.
"""
from __future__ import annotations

import sys

import numpy as np

from hyqjax.cli.common import HelpFormatter, UsageError, check_range


def parse(argv=None):
    from hyqjax.cli.app import Parser

    ap = Parser(prog="python -m experiments.tune_step_size", description=__doc__,
                                 formatter_class=HelpFormatter)
    ap.add_argument("--out", default="out/tune_step_size")
    ap.add_argument("--preset", default="clean", help="the crawl preset the samples are drawn around")
    ap.add_argument("--dim", default="per_leg", help="the tuner's parameterisation (hyqjax tune --dim)")
    ap.add_argument("--sigmas", type=float, nargs="*", default=[0.03, 0.1, 0.3],
                    help="step sizes in the tuner's normalised coordinates (hyqjax tune --sigma: 0.3); none: only "
                         "--line")
    ap.add_argument("--samples", type=int, default=8, help="samples per step size")
    ap.add_argument("--instances", type=int, default=32,
                    help="training step-downs every member runs (a multiple of the 4 training heights)")
    ap.add_argument("--seed", type=int, default=0, help="draws the samples and the instances")
    ap.add_argument("--duration", type=float, default=24.0, help="simulated seconds per run (the tuner's 24)")
    ap.add_argument("--impl", default="c", help="simulator: auto | jax | warp | c (default c: a CPU)")
    ap.add_argument("--spread", default="wide",
                    help="the training step-downs' spread: wide (hyqjax tune's) or train (the equal-wall-clock "
                         "study's)")
    ap.add_argument("--antithetic", action="store_true",
                    help="samples in antithetic pairs; adds the split-half signal of the pairs' differences")
    ap.add_argument("--surrogate", action="store_true",
                    help="with --antithetic: the tuner's surrogate gradient at the start (MJX-JAX jacfwd of the "
                         "window objective) against every step size's pairs")
    ap.add_argument("--window-ticks", type=int, default=500, help="--surrogate: control ticks of each window")
    ap.add_argument("--windows-per-scenario", type=int, default=2,
                    help="--surrogate, --line: snapshot windows per scenario, legs in the order they step down (the "
                         "tuner's 2: the front legs; 4 adds the hind legs)")
    ap.add_argument("--lead", type=float, default=10.0,
                    help="--surrogate, --line: seconds of the forward run that takes the snapshots (the tuner's 10; a "
                         "window whose leg has not reached the edge by then stays empty)")
    ap.add_argument("--surrogate-weights", nargs="+", default=[], metavar="TERM=W",
                    help="--surrogate, --line: the window objective's term weights other than their defaults (e.g. "
                         "mobility=0 progress=0 stability=0; hyqjax.studies.tune.objective)")
    ap.add_argument("--line", type=float, nargs="+", default=[], metavar="T",
                    help="distances along the surrogate's descent direction at the start (normalised coordinates; "
                         "negative: up the surrogate), run on the same step-downs")
    a = ap.parse_args(argv)
    if a.impl not in ("auto", "jax", "warp", "c"):
        raise UsageError(f"--impl must be auto, jax, warp or c, got {a.impl!r}")
    if any(not 0 < s <= 5 for s in a.sigmas) or not (a.sigmas or a.line):
        raise UsageError(f"--sigmas must be in (0, 5] (none only with --line), got {a.sigmas}")
    if len(a.line) > 64 or any(not -10 <= t <= 10 for t in a.line):
        raise UsageError(f"--line must be at most 64 distances in [-10, 10], got {a.line}")
    if not 2 <= a.samples <= 4096:
        raise UsageError(f"--samples must be in [2, 4096], got {a.samples}")
    if a.surrogate and not a.antithetic:
        raise UsageError("--surrogate needs --antithetic (the pairs it is compared with)")
    if not 1 <= a.window_ticks <= 20000:
        raise UsageError(f"--window-ticks must be in [1, 20000], got {a.window_ticks}")
    check_range("--lead", a.lead, 0.1, 60.0, "s")
    check_range("--windows-per-scenario", a.windows_per_scenario, 1, 8, integer=True)
    from hyqjax.studies.tune.surrogate_weights import parse_weights

    try:
        a.surrogate_weights = parse_weights(a.surrogate_weights)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if a.surrogate_weights and not (a.surrogate or a.line):
        raise UsageError("--surrogate-weights weighs the surrogate: it needs --surrogate or --line")
    if a.spread not in ("wide", "train"):
        raise UsageError(f"--spread must be wide or train, got {a.spread!r}")
    if a.antithetic and (a.samples % 2 or a.samples < 8):
        raise UsageError(f"--samples must be even and at least 8 with --antithetic (4 pairs), got {a.samples}")
    if not (4 <= a.instances <= 65536 and a.instances % 4 == 0):
        raise UsageError(f"--instances must be a multiple of 4 in [4, 65536], got {a.instances}")
    if a.antithetic and a.instances % 8:
        raise UsageError(f"--instances must be a multiple of 8 with --antithetic (two halves of every height), "
                         f"got {a.instances}")
    if not 0 <= a.seed < 2**31:
        raise UsageError(f"--seed must be in [0, 2^31), got {a.seed}")
    if not 2 <= a.duration <= 60:
        raise UsageError(f"--duration must be in [2, 60] s, got {a.duration}")
    from hyqjax import presets
    from hyqjax.studies.tune import schedule

    if a.preset.lower() == "none":
        a.preset = ""
    try:
        if a.preset:
            presets.check_kind(a.preset, "crawl", "--preset")
    except ValueError as e:
        raise UsageError(str(e)) from None
    if a.dim not in schedule.NAMES:
        raise UsageError(f"--dim must be one of {', '.join(schedule.NAMES)}, got {a.dim!r}")
    return a


def sample_points(theta0, sigmas, samples: int, seed: int) -> dict:
    """``samples`` points ``theta0 + sigma z`` per step size (the same ``z`` for every ``sigma``, so the step sizes
    differ only in scale)."""
    theta0 = np.asarray(theta0, np.float64)
    z = np.random.default_rng(seed).standard_normal((samples, theta0.size))
    return {float(s): theta0[None] + float(s) * z for s in sigmas}


def antithetic_points(theta0, sigmas, pairs: int, seed: int) -> tuple[dict, np.ndarray]:
    """``2 pairs`` points per step size, ``theta0 + sigma z`` then ``theta0 - sigma z`` (the same ``z`` for every
    ``sigma``), and ``z`` (pairs, P)."""
    theta0 = np.asarray(theta0, np.float64)
    z = np.random.default_rng(seed).standard_normal((pairs, theta0.size))
    return {float(s): np.concatenate([theta0[None] + float(s) * z, theta0[None] - float(s) * z]) for s in sigmas}, z


def halves(instances: int, heights: int) -> np.ndarray:
    """True for the first half of every height's instances (the training scenarios run height by height, the same
    instance draws at every height)."""
    per = instances // heights
    return (np.arange(instances) % per) < per // 2


def scenario_fitness(members: dict, completed_weight: float) -> np.ndarray:
    """Each run's fitness (N, M): the tuner's clean + ``completed_weight`` x completed, per step-down."""
    return np.asarray(members["clean"], np.float64) + completed_weight * np.asarray(members["completed"], np.float64)


def half_differences(f, pairs: int, half) -> tuple:
    """The antithetic pairs' fitness differences ``f(theta_0 + sigma z_i) - f(theta_0 - sigma z_i)`` over all
    step-downs, the first half (``half``) and the second: three (pairs,) arrays."""
    d = f[:pairs] - f[pairs:]
    return d.mean(1), d[:, half].mean(1), d[:, ~half].mean(1)


def _cos(a, b) -> float:
    den = np.linalg.norm(a) * np.linalg.norm(b)
    return float(a @ b / den) if den > 0 else float("nan")


def pair_signal(members: dict, z, half, completed_weight: float) -> dict:
    """Whether an antithetic generation's differences measure a direction (module docstring): ``members`` the
    evaluation of :func:`antithetic_points`' rows, ``half`` (M,) bool the instances of the first half."""
    from scipy import stats

    n = len(z)
    d_all, d_a, d_b = half_differences(scenario_fitness(members, completed_weight), n, half)
    if np.std(d_a) > 0 and np.std(d_b) > 0:
        r = float(stats.pearsonr(d_a, d_b)[0])
        zr, se = np.arctanh(np.clip(r, -0.999999, 0.999999)), 1.0 / np.sqrt(max(n - 3, 1))
        ci = [float(np.tanh(zr - 1.96 * se)), float(np.tanh(zr + 1.96 * se))]
    else:
        r, ci = float("nan"), [float("nan"), float("nan")]
    return dict(pairs=int(n), pairs_differing=int(np.sum(d_all != 0)), mean_abs_diff=float(np.abs(d_all).mean()),
                split_half_r=r, split_half_r_ci95=ci, split_half_cos=_cos(d_a @ z, d_b @ z))


def surrogate_agreement(g, thetas, theta0, members: dict, sigma: float, half, completed_weight: float) -> dict:
    """The surrogate gradient ``g`` (of a minimised objective) against one step size's antithetic pairs ``thetas``
    (rows ``theta0 + sigma z`` then ``theta0 - sigma z``): :func:`guided.guided_cosines` on the maximised fitness's
    negative (isotropic samples: ``alpha`` 1, GuidedES's ``std`` ``sigma sqrt(P)``), and the cosine of ``-g`` with each
    half's zero-order estimate."""
    from hyqjax.studies.tune import guided

    f, g = scenario_fitness(members, completed_weight), np.asarray(g, np.float64)
    out = guided.guided_cosines(g, thetas, theta0, -f.mean(1), guided.sampling_std(sigma, g.size), 1.0, g[:, None])
    n = len(thetas) // 2
    z = (np.asarray(thetas[:n], np.float64) - np.asarray(theta0, np.float64)) / sigma
    _, d_a, d_b = half_differences(f, n, half)
    out.update(cos_half_a=_cos(-g, d_a @ z), cos_half_b=_cos(-g, d_b @ z))  # the estimates ascend the fitness
    return {k: out[k] for k in ("descent_slope", "cos_zero_order", "cos_sampled", "cos_half_a", "cos_half_b")}


def surrogate_windows(grad) -> list:
    """When the surrogate's windows run: ``[first start, last end]`` (s) over its valid windows
    (:class:`hyqjax.studies.tune.gradient_programs.GradientPrograms`)."""
    t = np.asarray(grad.win.data.time, np.float64)[np.asarray(grad.win.valid, bool)]
    span = grad.obj.ticks * float(grad.su.m.opt.timestep)
    return [round(float(t.min()), 3), round(float(t.max() + span), 3)] if t.size else []


def descent_direction(g, names, top: int = 8) -> list:
    """The ``top`` largest components of the surrogate's descent direction ``-g / |g|``: ``[(coordinate, value)]``."""
    g = np.asarray(g, np.float64)
    n = np.linalg.norm(g)
    if not n > 0:
        return []
    u = -g / n
    return [(str(names[i]), round(float(u[i]), 4)) for i in np.argsort(-np.abs(u))[:top]]


def line_points(theta0, g, distances) -> np.ndarray:
    """The points ``theta0 - t g / |g|`` (len(distances), P): distance ``t`` down the surrogate ``g`` (of a minimised
    objective) in the tuner's normalised coordinates."""
    g = np.asarray(g, np.float64)
    u = -g / np.linalg.norm(g)
    return np.asarray(theta0, np.float64)[None] + np.asarray(distances, np.float64)[:, None] * u[None]


def line_summary(start: dict, members: dict, distances, completed_weight: float, window_loss=None,
                 dt: float | None = None) -> list:
    """Per distance of :func:`line_points`: the clean rate and fitness (clean + ``completed_weight`` x completed,
    the tuner's) and their differences from the start's, paired over the same step-downs (mean and 95% interval),
    with the runs not completed, not clean, fallen and diverged; and, given ``window_loss`` (one per distance), the
    surrogate's own window objective there (the value the gradient descends); and, given the control period ``dt``
    (s), the runs it ends early that the start does not, with when (:func:`ended_early`)."""
    from hyqjax.studies import statistics

    c0 = np.asarray(start["clean"], np.float64).reshape(-1)
    f0 = scenario_fitness(start, completed_weight).reshape(-1)
    f = scenario_fitness(members, completed_weight)
    clean = np.asarray(members["clean"], np.float64)
    out = []
    for i, t in enumerate(distances):
        dc, df = clean[i] - c0, f[i] - f0
        out.append(dict(distance=float(t), clean=float(clean[i].mean()), clean_diff=float(dc.mean()),
                        clean_diff_ci95=list(statistics.mean_interval(dc)), fitness_diff=float(df.mean()),
                        fitness_diff_ci95=list(statistics.mean_interval(df)), counts=counts(members, i)))
        if window_loss is not None:
            out[-1]["window_loss"] = float(window_loss[i])
        if dt is not None:
            out[-1].update(ended_early(start, members, i, dt))
    return out


def ended_early(start: dict, members: dict, member: int, dt: float) -> dict:
    """The runs member ``member`` ends early (a fall, a strike: the rollout's failure tick) that the start does not,
    on the same step-downs: their number and the 10th, 50th and 90th percentiles of when they end (s; ``dt`` the
    control period), to set beside the surrogate's windows (``surrogate["windows_s"]``); empty without the
    outcome columns."""
    if "columns" not in members or "columns" not in start:
        return {}
    t0 = np.asarray(start["columns"]["terminated_tick"]).reshape(-1)
    t = np.asarray(members["columns"]["terminated_tick"])[member].reshape(-1)
    new = (t >= 0) & (t0 < 0)
    q = np.percentile(t[new] * dt, [10, 50, 90]).round(2).tolist() if new.any() else None
    return dict(ended_early_not_at_start=int(new.sum()), ended_early_time_s=q)


def summarize(start: dict, members: dict, sigma: float) -> dict:
    """Paired differences of the members' clean rate and fitness from the start's on the same instances."""
    from hyqjax.studies import statistics

    c0, f0 = float(np.mean(start["clean"])), float(start["fitness"][0])
    clean = members["clean"].mean(1)
    d, df = clean - c0, members["fitness"] - f0
    lo, hi = statistics.mean_interval(d)
    return dict(sigma=sigma, samples=int(d.size), start_clean=c0, mean_clean=float(clean.mean()),
                mean_diff=float(d.mean()), mean_diff_ci95=[lo, hi], best_diff=float(d.max()), worst_diff=float(d.min()),
                share_at_least_start=float(np.mean(d >= 0)), mean_fitness_diff=float(df.mean()),
                best_fitness_diff=float(df.max()), per_sample_clean=[float(x) for x in clean],
                counts=counts(members))


def counts(r: dict, member: int | None = None) -> dict:
    """Runs of an evaluation (``SuccessEvaluator`` output; ``member``: its row alone) by outcome: all, not completed,
    not clean, fell (ended at a fall: tilt or trunk strike) and diverged (a simulator blow-up or a non-finite state: a
    counted failure)."""
    cols = dict(r.get("columns", {}), completed=r.get("completed"), clean=r["clean"])

    def rows(v):
        v = np.asarray(v, bool)
        return v if member is None else v[member]

    def n(key, false=False):
        if cols.get(key) is None:
            return None
        x = rows(cols[key])
        return int(np.sum(~x if false else x))

    return dict(runs=int(rows(r["clean"]).size), not_completed=n("completed", True), not_clean=n("clean", True),
                fell=n("terminated"), diverged=n("diverged"))


def _counts_cell(c: dict) -> str:
    """A table cell of :func:`counts`: not completed / not clean / fell / diverged of all."""
    return f"{c['not_completed']} / {c['not_clean']} / {c['fell']} / {c['diverged']} of {c['runs']}"


def _table(header: str, rows: list, cells, note: str) -> str:
    """A further table of the report: ``header`` (its two lines), a row per ``(sigma, record)`` with ``cells(record)``
    after the step size, and ``note`` below it."""
    return ("\n\n" + header + "\n" + "".join(f"| {sigma:g} | {cells(x)} |\n" for sigma, x in rows)
            + f"\n({note})")


def line_markdown(line: list, instances: int, surrogate: dict) -> str:
    """The ``--line`` table: one row per distance down the surrogate (with the window objective's column where
    every row has it)."""
    loss = all("window_loss" in x for x in line)
    early = all("ended_early_not_at_start" in x for x in line)

    def early_cell(x):
        q = x["ended_early_time_s"]
        return f" {x['ended_early_not_at_start']}" + (f" ({q[0]:g} / {q[1]:g} / {q[2]:g} s)" if q else "") + " |"

    rows = [f"| {x['distance']:+g} | {x['clean']:.3f} | {x['clean_diff']:+.3f} [{x['clean_diff_ci95'][0]:+.3f}, "
            f"{x['clean_diff_ci95'][1]:+.3f}] | {x['fitness_diff']:+.3f} [{x['fitness_diff_ci95'][0]:+.3f}, "
            f"{x['fitness_diff_ci95'][1]:+.3f}] | {_counts_cell(x['counts'])} |"
            + (f" {x['window_loss']:.4g} |" if loss else "") + (early_cell(x) if early else "") for x in line]
    win = surrogate.get("windows_s")
    direction = surrogate.get("direction")
    return ("| distance down the surrogate | clean | clean difference from the start [95%] | fitness difference "
            "[95%] | runs: not completed / not clean / fell / diverged |"
            + (f" window objective (start {surrogate['loss']:.4g}) |" if loss else "")
            + (" ended early where the start did not: runs (when: 10 / 50 / 90 %) |" if early else "")
            + "\n|---:|---:|---|---|---|" + ("---:|" if loss else "") + ("---|" if early else "") + "\n"
            + "\n".join(rows) + f"\n\n(points theta_0 - t g/|g|, g the tuner's window gradient at the start "
            f"(|g| {surrogate['grad_norm']:.4g}); every point on the same {instances} training step-downs as the "
            f"start, differences paired over them"
            + ("; the window objective, which g descends, on the start's windows" if loss else "")
            + (f"; the windows run from {win[0]:g} s to {win[1]:g} s into their step-downs" if win else "")
            + _weights_note(surrogate) + ")"
            + ("\n\nThe descent direction's largest components: "
               + ", ".join(f"`{k}` {v:+.2f}" for k, v in direction) + "." if direction else ""))


def _weights_note(surrogate: dict) -> str:
    """``; its weights ...`` where the surrogate's term weights are not the window objective's defaults."""
    from hyqjax.studies.tune.objective import ClosedLoopObjective

    w, w0 = surrogate.get("weights"), ClosedLoopObjective().weights()
    other = {k: v for k, v in (w or {}).items() if v != w0[k]}
    return ("; the objective's weights other than their defaults: "
            + ", ".join(f"{k} {abs(v):g}" for k, v in other.items())) if other else ""


def markdown(rows: list, instances: int, surrogate: dict | None = None) -> str:
    if not rows:
        return ""
    lines = ["| sigma | clean: start / samples' mean | mean difference [95% over samples] | best / worst sample | "
             "samples at least as clean as the start | fitness difference: mean / best | runs: not completed / "
             "not clean / fell / diverged |",
             "|---:|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["mean_diff_ci95"]
        lines.append(f"| {r['sigma']:g} | {r['start_clean']:.3f} / {r['mean_clean']:.3f} | {r['mean_diff']:+.3f} "
                     f"[{lo:+.3f}, {hi:+.3f}] | {r['best_diff']:+.3f} / {r['worst_diff']:+.3f} | "
                     f"{r['share_at_least_start']:.2f} of {r['samples']} | {r['mean_fitness_diff']:+.3f} / "
                     f"{r['best_fitness_diff']:+.3f} | {_counts_cell(r['counts'])} |")
    text = "\n".join(lines) + f"\n\n(every member on the same {instances} training step-downs; differences paired)"
    anti = [r for r in rows if "antithetic" in r]
    if anti:
        text += _table("| sigma | pairs whose members differ | mean abs(d) | split-half correlation of d [95%] | "
                       "cosine of the halves' estimates |\n|---:|---|---:|---|---:|",
                       [(r["sigma"], r["antithetic"]) for r in anti], lambda x: (
                           f"{x['pairs_differing']} of {x['pairs']} | {x['mean_abs_diff']:.4f} | "
                           f"{x['split_half_r']:+.2f} [{x['split_half_r_ci95'][0]:+.2f}, "
                           f"{x['split_half_r_ci95'][1]:+.2f}] | {x['split_half_cos']:+.2f}"),
                       f"d: a pair's fitness difference, clean + 0.1 x completed; halves: {instances // 2} step-downs "
                       f"each, every height in both")
    sur = [r for r in rows if "surrogate" in r]
    if sur:
        text += _table("| sigma | slope along the surrogate's descent | cosine with the pairs' estimate | with each "
                       "half's | inside the sampled directions |\n|---:|---:|---:|---|---:|",
                       [(r["sigma"], r["surrogate"]) for r in sur], lambda x: (
                           f"{x['descent_slope']:+.4f} | {x['cos_zero_order']:+.3f} | {x['cos_half_a']:+.3f} / "
                           f"{x['cos_half_b']:+.3f} | {x['cos_sampled']:+.3f}"),
                       f"the surrogate: the tuner's window objective at the start, MJX-JAX jacfwd, "
                       f"{surrogate['window_ticks']} ticks a window; |g| {surrogate['grad_norm']:.4g}")
    return text


def main(argv=None) -> int:
    from hyqjax.io import phases

    clock = phases.Clock.from_process_start()
    try:
        a = parse(argv)
    except (UsageError, ValueError) as e:
        print(f"tune_step_size: {e}", file=sys.stderr)
        return 2
    import os

    from hyqjax.io import atomic
    from hyqjax.studies.tune import forward
    from hyqjax.studies.tune.wallclock import start_evaluator
    from hyqjax.studies.tune.wallclock_config import WallClockConfig

    cfg = WallClockConfig(methods=("cma_es",), dims=(a.dim,), start_preset=a.preset, train_spread=a.spread,
                          window_ticks=a.window_ticks, surrogate_weights=a.surrogate_weights,
                          windows_per_scenario=a.windows_per_scenario, window_lead=a.lead,
                          impl=a.impl, train_duration=a.duration)
    try:
        param, theta0, evaluator = start_evaluator(cfg)
    except ValueError as e:
        print(f"tune_step_size: --preset {a.preset} on --dim {a.dim}: {e}", file=sys.stderr)
        return 2
    sc = forward.train_scenarios(a.instances, a.seed, 0, cfg.train_heights, a.spread)
    if a.antithetic:
        points, z = antithetic_points(theta0, a.sigmas, a.samples // 2, a.seed)
        half = halves(a.instances, len(cfg.train_heights))
    else:
        points = sample_points(theta0, a.sigmas, a.samples, a.seed)
    clock.lap("startup")
    start = evaluator(theta0[None], sc)
    print(f"start ({a.preset or 'Table I with the shin remedy'}, {param.size} coordinates of {a.dim}): clean "
          f"{np.mean(start['clean']):.3f} on "
          f"{a.instances} step-downs ({start['wall_s']:.0f} s with its compile)", flush=True)
    surrogate = None
    if a.surrogate or a.line:
        import time

        from hyqjax.studies.tune import search
        from hyqjax.studies.tune.gradient_programs import GradientPrograms
        from hyqjax.studies.tune.wallclock import start_params

        t = time.perf_counter()
        grad = GradientPrograms(cfg, start_params(cfg), search.Charges(), print)
        step_fn, window_value, _ = grad.programs(param, line_search=False)
        r = step_fn(theta0)
        g = np.asarray(r["grad"], np.float64)
        surrogate = dict(loss=float(r["loss"]), grad_norm=float(np.linalg.norm(g)), finite=bool(np.all(np.isfinite(g))),
                         window_ticks=a.window_ticks, windows_per_scenario=a.windows_per_scenario, lead_s=a.lead,
                         windows_valid=int(np.asarray(grad.win.valid).sum()), weights=grad.obj.weights(),
                         windows_s=surrogate_windows(grad), direction=descent_direction(g, param.names),
                         seconds=time.perf_counter() - t)
        print(f"surrogate at the start: |g| {surrogate['grad_norm']:.4g}, window loss {surrogate['loss']:.4g} "
              f"({surrogate['seconds']:.0f} s: windows, compile and one jacfwd step on MJX-JAX)", flush=True)
    rows = []
    for s, th in points.items():
        r = evaluator(th, sc)
        rows.append(summarize(start, r, s))
        if a.antithetic:
            rows[-1]["antithetic"] = pair_signal(r, z, half, cfg.completed_weight)
            if surrogate is not None and surrogate["finite"]:
                rows[-1]["surrogate"] = surrogate_agreement(g, th, theta0, r, s, half, cfg.completed_weight)
                print(f"sigma {s:g}: surrogate {rows[-1]['surrogate']}", flush=True)
            y = rows[-1]["antithetic"]
            print(f"sigma {s:g}: {y['pairs_differing']} of {y['pairs']} pairs differ, split-half correlation "
                  f"{y['split_half_r']:+.2f} {y['split_half_r_ci95']}", flush=True)
        x = rows[-1]
        print(f"sigma {s:g}: mean clean difference {x['mean_diff']:+.3f}, best {x['best_diff']:+.3f}, "
              f"{x['share_at_least_start']:.2f} of samples at least as clean ({r['wall_s']:.0f} s)", flush=True)
    line = None
    if a.line and surrogate["finite"] and surrogate["grad_norm"] > 0:
        pts = line_points(theta0, g, a.line)
        r = evaluator(pts, sc)
        line = line_summary(start, r, a.line, cfg.completed_weight, np.asarray(window_value(pts)).reshape(-1),
                            dt=a.duration / evaluator.ticks)
        for x in line:
            print(f"line {x['distance']:+g}: clean {x['clean']:.3f}, difference {x['clean_diff']:+.3f} "
                  f"{[round(v, 3) for v in x['clean_diff_ci95']]}, window objective {x['window_loss']:.4g}", flush=True)
    elif a.line:
        print("tune_step_size: the surrogate gradient at the start is zero or not finite: no line to run",
              file=sys.stderr)
    os.makedirs(a.out, exist_ok=True)
    res = dict(provenance=atomic.provenance(seed=a.seed), preset=a.preset or "none", dim=a.dim, size=param.size,
               antithetic=bool(a.antithetic), surrogate=surrogate,
               impl=evaluator.setup.impl, instances=a.instances, duration=a.duration, spread=a.spread,
               heights=[float(h) for h in cfg.train_heights], completed_weight=cfg.completed_weight,
               start=dict(clean=float(np.mean(start["clean"])), completed=float(np.mean(start["completed"])),
                          fitness=float(start["fitness"][0]), counts=counts(start)),
               rows=rows, line=line, physics_steps=int(evaluator.physics_steps))
    # the surrogate gradient (the tuner's windows, compile and jacfwd step) is the tuning phase, apart from the runs
    clock.lap("simulation", **({"tuning": surrogate["seconds"]} if surrogate else {}))
    res.update(wall_s=clock.wall(), phases=clock.to_dict())
    atomic.write_json(os.path.join(a.out, "step_size.json"), res)
    text = markdown(rows, a.instances, surrogate)
    if line is not None:
        text = (text + "\n\n" if text else "") + line_markdown(line, a.instances, surrogate)
    atomic.atomic_write(os.path.join(a.out, "step_size.md"), lambda f: f.write((text + "\n").encode()))
    print(text)
    print(f"wrote {a.out}/step_size.json and step_size.md")
    clock.lap("summary")
    print(clock.line())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
