"""A whole tuning study: gradient through the closed loop, baselines at equal budget, held-out evaluation.

:func:`run_study` (what ``hyqjax tune`` runs):

1. training scenarios (``evaluate.TRAIN_HEIGHTS`` x ``train_per_height``, seed ``seed``) and their
   snapshot windows (:mod:`.windows`, Table I parameters);
2. the gradient method: optionally ``warm_start`` steps of the kinematic surrogate (:mod:`.kinematic`),
   then Adam on the closed-loop objective (:mod:`.objective`, ``jax.jacfwd``), checkpointed
   (:mod:`.optimize`); with ``objective="kinematic"`` Adam on the surrogate alone (the former tuner); with
   ``select_instances`` the iterate kept is the one with the best clean success on selection scenarios
   (every ``select_every`` steps, the start included), its full runs counted in the budget;
3. the cost of one tuning step against one forward evaluation of the same windows (wall time, jitted,
   after compilation) and the simulation budget ``B = steps x W x n x (1 + P)`` physics steps, plus the
   selection's ``candidates x instances x duration / dt``;
4. baselines with budget ``B``: CMA-ES and random search on the same window objective, and CMA-ES and
   random search on closed-loop clean success of full runs on the training scenarios (:mod:`.baselines`),
   population ``1 + P``; with ``baseline_wall_s`` a baseline also stops at that wall time (recorded as
   ``stopped_by_wall_limit`` with the budget it spent);
5. held-out evaluation (:mod:`.evaluate`) of Table I and every method on ``heldout`` instances, and of each
   method's best point at fractions of the budget on ``curve_instances`` instances (the figure);
6. ``results.json`` and ``tuning.png``.

The tuned crawl runs with the shin-strike remedy (``remedy=True``, :mod:`hyqjax.crawl.remedy`): every method
starts from Table I and the default crawl with ``shin_remedy`` on (``start``) and tunes the remedy's continuous
parameters (forward search, terrain adaptation) with the rest. The reference ``table1`` is always the paper's
crawl with Table I; with ``remedy=True`` the held-out evaluation also reports ``start``, so what the tuning adds
to its starting point is measured, not only what it adds to the paper.

Resuming: ``results.json`` is written after every stage; the same command on the same directory (same
configuration) keeps every finished stage (the gradient resumes from its checkpoint) and runs the rest.
A study holds the directory's lock (:class:`hyqjax.io.lock.DirLock`) from start to end, so a second study
into it is refused (or waits, ``wait=True``); its first start records :func:`fingerprint` (every setting
that changes the results, for the closed-loop and the kinematic objective) in ``fingerprint.json``, and a
resume with other settings is refused naming them (:class:`hyqjax.io.fingerprint.SettingsMismatch`) before
anything is computed. Every objective checkpoints every ``adam.checkpoint_every`` steps.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.crawl import controller as crawl
from hyqjax.io.atomic import provenance, write_json
from hyqjax.sim import backend
from hyqjax.studies.tune import evaluate, optimize, windows
from hyqjax.studies.tune.study import baselines, kinematic
from hyqjax.studies.tune import objective as clobj
from hyqjax.studies.tune import space as spmod
from hyqjax.studies.tune.gradient_stats import gradient_stats

METHODS = ("gradient", "cma_es", "random_search", "cma_es_success", "random_search_success")


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    objective: str = "closed_loop"
    groups: tuple = spmod.DEFAULT_GROUPS
    seed: int = 0
    train_per_height: int = 4
    train_heights: tuple = evaluate.TRAIN_HEIGHTS
    window: windows.WindowSpec = windows.WindowSpec()
    loss: clobj.ClosedLoopObjective = clobj.ClosedLoopObjective()
    adam: optimize.AdamConfig = optimize.AdamConfig()
    warm_start: int = 0
    baselines: tuple = METHODS[1:]
    sigma: float = 0.5
    success_instances: int = 8
    success_duration: float = 24.0
    heldout: int = 2000
    heldout_seed: int = 7777
    heldout_duration: float = 24.0
    curve_instances: int = 0
    curve_fractions: tuple = (0.25, 0.5)
    #: wall-time limit (s) of each success baseline (0: budget only); the window-objective baselines always get
    #: the whole budget
    baseline_wall_s: float = 0.0
    #: selection among the gradient's iterates (every ``select_every`` steps, the start and the last included)
    #: by clean success over ``select_instances`` full runs of selection scenarios (a seed of the training
    #: distribution used for nothing else); its physics steps count in the gradient's budget. 0: no selection
    #: (the last iterate)
    select_instances: int = 0
    select_every: int = 5
    #: the tuned crawl runs with the shin-strike remedy (``CrawlParams.shin_remedy``); the ``table1`` reference
    #: is the paper's crawl either way
    remedy: bool = True
    #: MJX implementation of the forward-only runs (held-out evaluation, success baselines); the gradient's
    #: windows always run under impl jax (MuJoCo Warp is not differentiable).
    impl: str = "auto"

    def __post_init__(self):
        backend.validate_impl(self.impl)
        if not isinstance(self.remedy, bool):
            raise ValueError(f"remedy must be True or False, got {self.remedy!r}")
        if self.objective not in ("closed_loop", "kinematic"):
            raise ValueError(f"objective must be 'closed_loop' or 'kinematic', got {self.objective!r}")
        spmod.ParamSpace.make(self.groups)
        bad = [b for b in self.baselines if b not in METHODS[1:]]
        if bad:
            raise ValueError(f"baselines must be a subset of {list(METHODS[1:])}, got {list(self.baselines)}")
        for k, lo, hi in (("train_per_height", 1, 100000), ("heldout", 0, 10**6), ("warm_start", 0, 10000),
                          ("success_instances", 1, 100000), ("curve_instances", 0, 10**6),
                          ("select_instances", 0, 100000), ("select_every", 1, 100000)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if any(not 0.0 <= h <= 0.45 for h in self.train_heights) or not self.train_heights:
            raise ValueError(f"train_heights must be in [0, 0.45] m, got {self.train_heights}")
        if not (0.0 < self.sigma <= 5.0):
            raise ValueError(f"sigma must be in (0, 5], got {self.sigma}")
        for k in ("success_duration", "heldout_duration"):
            if not (1.0 <= getattr(self, k) <= 120.0):
                raise ValueError(f"{k} must be in [1, 120] s, got {getattr(self, k)}")

    def to_dict(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), default=list))


def _timed(fn, *args, repeats=2):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


#: kinematic-surrogate scenarios of the kinematic objective and of the warm start
KINEMATIC_SCENARIOS = 64


def fingerprint(cfg: StudyConfig) -> dict:
    """Every setting that changes a study's results: the configuration without ``adam.checkpoint_every`` (when
    checkpoints are written changes nothing), plus the kinematic surrogate's fixed settings (scenario count,
    objective weights) when it runs (``objective="kinematic"`` or a warm start), and the step-down's start pose
    (:data:`hyqjax.studies.stepdown.START_POSE`)."""
    return settings_of(stored_config(cfg))


def stored_config(cfg: StudyConfig) -> dict:
    """What results.json stores as ``config``: the settings and the step-down's start pose."""
    from hyqjax.studies.stepdown import START_POSE

    return dict(cfg.to_dict(), start_pose=START_POSE)


def settings_of(config: dict) -> dict:
    """:func:`fingerprint` of a configuration as stored (:func:`stored_config`, e.g. in results.json; a study
    stored before the start pose was recorded ran the ``hip-line`` start)."""
    from hyqjax.studies.stepdown import recorded_start_pose

    s = json.loads(json.dumps(config))
    s["start_pose"] = recorded_start_pose(s)
    s.get("adam", {}).pop("checkpoint_every", None)
    if not (s.get("loss", {}).get("contacts_from_distance") or {}).get("stiffness"):  # off: as runs before it
        s.get("loss", {}).pop("contacts_from_distance", None)
    if s.get("objective") == "kinematic" or s.get("warm_start"):
        s["kinematic"] = dict(scenarios=KINEMATIC_SCENARIOS, objective=dataclasses.asdict(kinematic.Objective()))
    return s


def kinematic_adam(cfg: StudyConfig) -> tuple[optimize.AdamConfig, dict]:
    """The kinematic surrogate's Adam settings (the study's learning rate, clip and checkpoint period; its steps
    the warm start's or the study's) and the configuration its checkpoints are tied to."""
    kcfg = optimize.AdamConfig(steps=cfg.warm_start or cfg.adam.steps, lr=cfg.adam.lr, clip=cfg.adam.clip,
                               checkpoint_every=cfg.adam.checkpoint_every)
    return kcfg, dict(kind="kinematic", **{k: v for k, v in fingerprint(cfg).items()
                                           if k in ("groups", "seed", "remedy", "adam", "warm_start", "kinematic")})


def _legacy_settings(out_dir: str) -> dict | None:
    """The settings of a study recorded before ``fingerprint.json`` existed (from its results.json or its gradient
    run's config.json), None if there is none."""
    for path in (os.path.join(out_dir, "results.json"), os.path.join(out_dir, "gradient", "config.json")):
        try:
            with open(path) as f:
                config = json.load(f).get("config")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(config, dict) and "adam" in config:
            return settings_of(config)
    return None


def run_study(cfg: StudyConfig, out_dir: str, progress: bool = True, log=print, wait: bool = False,
              locked: bool = False) -> dict:
    """Run (or resume) a study into ``out_dir``; returns the results dict. Holds ``out_dir``'s lock throughout
    (``wait``: queue behind another study instead of :class:`hyqjax.io.lock.Busy`; ``locked``: the caller holds
    it) and refuses a resume with other settings (module docstring) before anything is computed."""
    if not locked:
        from hyqjax.io.lock import DirLock

        with DirLock(out_dir, wait=wait, what="tune study"):
            return run_study(cfg, out_dir, progress, log, locked=True)
    from hyqjax.io.fingerprint import check_or_record

    check_or_record(out_dir, fingerprint(cfg), "tuning study", legacy=_legacy_settings(out_dir))
    t_start = time.time()
    os.makedirs(out_dir, exist_ok=True)

    def save(r):  # after every stage, so an interrupted study keeps what it measured
        r["wall_s"] = time.time() - t_start
        write_json(os.path.join(out_dir, "results.json"), r)  # strict JSON: a non-finite value is null

    space = spmod.ParamSpace.make(cfg.groups)
    base = start_params(cfg)
    theta0 = space.theta_of(base)
    prev = _previous(out_dir, cfg)
    su = windows.setup()
    sc, _ = evaluate.scenarios(cfg.train_heights, cfg.train_per_height, cfg.seed, params=base)
    t = time.time()
    win = windows.make_windows(sc, cfg.window, su)
    valid = np.asarray(win.valid)
    log(f"windows: {int(valid.sum())} of {valid.size} triggered ({time.time() - t:.1f} s incl. compile)")
    n_win, n_tan = win.size, space.size
    eval_cost = clobj.physics_steps(n_win, cfg.loss)
    step_cost = clobj.physics_steps(n_win, cfg.loss, n_tan) + len(cfg.adam.line_search) * eval_cost
    sel_steps = selection_steps(cfg)
    per_sel = max(1, cfg.select_instances // len(cfg.train_heights)) if sel_steps else 0
    sel_cost = len(sel_steps) * _full_runs_cost(per_sel * len(cfg.train_heights), cfg.success_duration)
    budget = cfg.adam.steps * step_cost + sel_cost
    res: dict = dict(complete=False, provenance=provenance(seed=cfg.seed), device=str(jax.devices()[0].device_kind),
                     config=stored_config(cfg), params=list(space.names), theta_start=theta0.tolist(),
                     start_point="Table I, default crawl" + (", shin remedy" if cfg.remedy else ""),
                     windows=dict(n=n_win, valid=int(valid.sum()), legs=np.asarray(win.leg)[valid].tolist(),
                                  heights=np.asarray(win.height)[valid].tolist()),
                     budget_physics_steps=budget, step_physics_steps=step_cost, eval_physics_steps=eval_cost)
    # ---- gradient method
    vj = clobj.make_value_and_jac(win, base, space, cfg.loss, su)
    fval = clobj.make_value(base, space, cfg.loss, su)
    if cfg.warm_start or cfg.objective == "kinematic":
        ksc = kinematic.make_scenarios(KINEMATIC_SCENARIOS, cfg.seed)
        kf = kinematic.make_value_and_grad(space, ksc, kinematic.Objective(), base)
        kcfg, kconfig = kinematic_adam(cfg)
        kres = optimize.run_adam(kf, jnp.asarray(theta0, jnp.float32), kcfg, os.path.join(out_dir, "kinematic"),
                                 kconfig, 0, space.describe, progress=progress)
        res["kinematic"] = dict(theta=kres["theta"].tolist(), params=space.describe(kres["theta"]))
        theta_start = kres["theta"]
    else:
        theta_start = theta0
    snaps: dict[str, list] = {m: [] for m in METHODS}
    fracs = sorted(cfg.curve_fractions)

    t = time.time()
    if cfg.objective == "closed_loop":
        gres = optimize.run_adam(lambda th: vj(th, win), jnp.asarray(theta_start, jnp.float32), cfg.adam,
                                 os.path.join(out_dir, "gradient"), fingerprint(cfg), step_cost, space.describe, progress=progress,
                                 evaluate=lambda ths: fval(ths, win))
        theta_grad = gres["theta"]
        # theta after ``s`` steps is log row ``s``'s (the last one is the result), so a resumed run has them all
        iterate = {r["step"]: r["theta"] for r in gres["log"]}
        iterate[cfg.adam.steps] = np.asarray(theta_grad).tolist()
        for s_f in sorted({max(1, round(f * cfg.adam.steps)) for f in fracs}):
            if s_f in iterate:
                snaps["gradient"].append((s_f * step_cost, iterate[s_f]))
    else:
        theta_grad = theta_start
    if sel_steps:
        if prev and "selection" in prev.get("gradient", {}):
            sel = prev["gradient"]["selection"]
        else:
            cands = np.asarray([iterate[k] for k in sel_steps], np.float64)
            ssc, _ = evaluate.scenarios(cfg.train_heights, per_sel, cfg.seed + 2)
            rates = evaluate.success_objective(cands, space, base, ssc, cfg.success_duration, cfg.impl)
            best = int(max(range(len(sel_steps)), key=lambda i: (rates[i], sel_steps[i])))  # ties: the later
            sel = dict(steps=list(sel_steps), clean=[float(x) for x in rates], chosen_step=sel_steps[best],
                       instances=int(ssc.batch_size), physics_steps=sel_cost, theta=cands[best].tolist())
        theta_grad = np.asarray(sel["theta"])
        log(f"selection: clean success {['%.3f' % x for x in sel['clean']]} at steps {sel['steps']}; "
            f"step {sel['chosen_step']} chosen")
    res["gradient"] = dict(theta=np.asarray(theta_grad).tolist(), params=space.describe(theta_grad),
                           wall_s=(prev.get("gradient", {}).get("wall_s", 0.0) if prev else 0.0) + time.time() - t,
                           log_dir="gradient", budget_spent=budget)
    if sel_steps:
        res["gradient"]["selection"] = sel
    save(res)
    # ---- cost of a tuning step vs forward evaluations of the same windows: a population of 1 + P candidates
    # (the same physics budget; one CMA-ES generation) and, per candidate, one forward evaluation.
    th32 = jnp.asarray(theta0, jnp.float32)
    pop_n = 1 + n_tan
    if prev and "cost" in prev and "gradient_stats" in prev:
        res["cost"], res["gradient_stats"] = prev["cost"], prev["gradient_stats"]
    else:
        t_step = _timed(vj, th32, win)
        t_pop = _timed(fval, jnp.tile(th32[None], (pop_n, 1)), win)
        res["cost"] = dict(t_step_s=t_step, t_population_s=t_pop, population=pop_n,
                           t_forward_per_candidate_s=t_pop / pop_n, step_over_population=t_step / t_pop,
                           step_over_forward=t_step / (t_pop / pop_n), tangents=n_tan)
        # ---- gradient statistics across windows and window lengths, at the start point
        r0 = vj(th32, win)
        res["gradient_stats"] = gradient_stats(r0, cfg.loss.lengths, list(space.names))
        save(res)
    c = res["cost"]
    log(f"one tuning step {c['t_step_s']:.3f} s; {pop_n} forward evaluations of the same windows "
        f"{c['t_population_s']:.3f} s ({c['step_over_population']:.2f}x); budget {budget:,} physics steps")
    # ---- baselines
    found = {"start": theta0, "gradient": np.asarray(theta_grad)}
    pop = lambda xs: np.asarray(fval(jnp.asarray(xs, jnp.float32), win))
    for name in cfg.baselines:
        if prev and name in prev:  # finished before a resume
            res[name] = prev[name]
            found[name] = np.asarray(prev[name]["theta"])
            snaps[name] = [tuple(x) for x in prev[name].get("curve_points", [])]
            continue
        t = time.time()
        if name.endswith("_success"):
            per = max(1, cfg.success_instances // len(cfg.train_heights))
            ssc, _ = evaluate.scenarios(cfg.train_heights, per, cfg.seed + 1)
            cost = _full_runs_cost(ssc.batch_size, cfg.success_duration)
            f = lambda xs, ssc=ssc: -evaluate.success_objective(xs, space, base, ssc,  # noqa: E731
                                                                 cfg.success_duration, cfg.impl)
        else:
            f, cost = pop, eval_cost
        if cost > budget:
            log(f"{name}: one candidate costs {cost:,} > budget {budget:,}; skipped")
            continue
        # One population size for every baseline (1 + P: a generation costs what a gradient step costs on the
        # windows), so each objective compiles once.
        lam = int(min(pop_n, max(2, budget // cost)))
        wall = cfg.baseline_wall_s if name.endswith("_success") else 0.0
        if name.startswith("cma_es"):
            out = baselines.cma_es(f, theta0, budget, cost, cfg.sigma, popsize=lam, seed=cfg.seed,
                                   max_wall_s=wall)
        else:
            out = baselines.random_search(f, theta0, budget, cost, cfg.sigma, chunk=lam, seed=cfg.seed,
                                          max_wall_s=wall)
        found[name] = out["theta"]
        for fr in fracs:
            h = [r for r in out["history"] if r["budget"] <= fr * budget]
            if h:
                snaps[name].append((h[-1]["budget"], h[-1]["theta"]))
        res[name] = dict(theta=np.asarray(out["theta"]).tolist(), params=space.describe(out["theta"]),
                         value=out["value"], budget_spent=out["budget_spent"], wall_s=time.time() - t,
                         objective="clean success (negated)" if name.endswith("_success") else "window objective",
                         stopped_by_wall_limit=out["budget_spent"] + lam * cost <= budget, popsize=lam,
                         cost_per_candidate=cost,
                         history=[{k: v for k, v in r.items() if k != "theta"} for r in out["history"]],
                         curve_points=[[b, list(map(float, th))] for b, th in snaps[name]])
        save(res)
        log(f"{name}: best {out['value']:.4f} after {out['budget_spent']:,} physics steps ({time.time() - t:.1f} s)")
    # ---- held-out evaluation (the budget-curve points on a subset, in the same batch)
    if cfg.heldout and prev and "heldout" in prev and prev.get("complete"):
        res["heldout"], res["budget_curve"] = prev["heldout"], prev.get("budget_curve", [])
    elif cfg.heldout:
        params = {"table1": crawl.CrawlParams.make()}
        params.update({k: space.concrete(v, base) for k, v in found.items() if cfg.remedy or k != "start"})
        pts = [(m, b, th) for m, v in snaps.items() for b, th in v] if cfg.curve_instances else []
        extra = {f"{m}@{b}": space.concrete(np.asarray(th), base) for m, b, th in pts}
        ho = evaluate.evaluate(params, cfg.heldout, cfg.heldout_seed, duration=cfg.heldout_duration, extra=extra,
                               n_extra=cfg.curve_instances, impl=cfg.impl)
        res["heldout"] = {k: v for k, v in ho.items() if k != "extra"}
        res["budget_curve"] = [dict(method=m, budget=b, n=ho["extra"][f"{m}@{b}"]["n"],
                                    clean=ho["extra"][f"{m}@{b}"]["clean"],
                                    clean_ci95=ho["extra"][f"{m}@{b}"]["clean_ci95"]) for m, b, _ in pts]
        for k, r in res["heldout"]["methods"].items():
            log(f"held-out {k:>22}: clean {r['clean']:.3f} [{r['clean_ci95'][0]:.3f}, {r['clean_ci95'][1]:.3f}], "
                f"completed {r['completed']:.3f}, shin strike {r['shin_strike']:.3f} (n={r['n']})")
    res["wall_s"] = time.time() - t_start
    res["complete"] = True
    save(res)
    return res


def _full_runs_cost(runs: int, duration: float, dt: float = 0.002) -> int:
    """Physics steps of ``runs`` full closed-loop runs of ``duration`` seconds."""
    return int(runs) * int(round(duration / dt))


def selection_steps(cfg: StudyConfig) -> tuple:
    """Adam steps whose iterates the selection compares (empty without selection)."""
    if not (cfg.select_instances and cfg.objective == "closed_loop"):
        return ()
    return tuple(sorted({0, *range(cfg.select_every, cfg.adam.steps + 1, cfg.select_every), cfg.adam.steps}))


def start_params(cfg: StudyConfig) -> crawl.CrawlParams:
    """Where every method starts: Table I and the default crawl, with the shin-strike remedy if ``cfg.remedy``."""
    return crawl.CrawlParams.make(shin_remedy=cfg.remedy)


def _previous(out_dir: str, cfg: StudyConfig) -> dict | None:
    """The ``results.json`` of an earlier run of the same configuration in ``out_dir`` (its finished stages are
    kept), None if there is none; a study of another configuration there is refused."""
    path = os.path.join(out_dir, "results.json")
    if not os.path.exists(path):
        return None
    try:
        with open(path) as f:
            prev = json.load(f)
    except (OSError, ValueError):
        return None  # unreadable (e.g. cut off by a kill before the atomic writes): start over
    if not isinstance(prev.get("config"), dict) or settings_of(prev["config"]) != fingerprint(cfg):
        raise RuntimeError(f"{out_dir} holds a tuning study of another configuration; use another --out or remove it")
    return prev
