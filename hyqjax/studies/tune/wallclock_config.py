"""Settings of the equal-wall-clock tuning study (:mod:`.wallclock`): :class:`WallClockConfig`, every field checked
once at construction (one line naming it), and the seeds its training draws use.

:meth:`WallClockConfig.from_dict` reads back the settings a ``results.json`` stores (``config``); a setting the
study predates takes its default, which is the behaviour that run had.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np

from hyqjax.sim import backend
from hyqjax.studies.tune import forward, schedule, search
from hyqjax.studies.tune import space as spmod
from hyqjax.studies.tune.gradient_programs import WINDOW_SEED_OFFSET
from hyqjax.studies.tune.surrogate_weights import check_weights


#: Differentiation modes of the exact tuning step (``WallClockConfig.grad_mode``).
GRAD_MODES = ("jacfwd", "reverse")

#: The settings only some methods read, and those methods (every other setting is read by every method): the
#: surrogate's windows and gradient by the methods that build it, the gradient step's rate by the gradient and the
#: hybrid, and each method's own rates. Runs of a comparison may differ in such a setting where one of them runs no
#: method that reads it (:func:`hyqjax.studies.tune.study.repeats.check_comparable`): the windows of guided ES's
#: surrogate do not change what CMA-ES did.
SETTING_READERS = {
    **dict.fromkeys(("grad_train_per_height", "windows_per_scenario", "window_lead", "window_ticks",
                     "surrogate_weights", "grad_directions", "grad_mode", "contacts_from_distance"),
                    search.USES_GRADIENT),
    "lr": search.GRADIENT_METHODS,
    "hybrid_split": ("hybrid",),
    "retake_windows": ("hybrid",),
    **dict.fromkeys(("guided_alpha", "guided_subspace", "guided_lr", "guided_grad_every"), search.GUIDED_METHODS),
    **dict.fromkeys(("blend_gamma", "blend_lr"), search.BLEND_METHODS),
    "restart_stall": search.RESTART_METHODS,
}


def generation_seed(seed: int, dim: str) -> int:
    """The seed of the training scenarios of the search methods on parameterisation ``dim``."""
    return seed + 1 + 1000 * list(schedule.NAMES).index(dim)


def training_seeds(seed: int) -> tuple:
    """Every seed the training draws of a study with ``seed`` use (the validation seed must be none of them)."""
    return (seed, seed + WINDOW_SEED_OFFSET) + tuple(generation_seed(seed, d) for d in schedule.NAMES)


@dataclasses.dataclass(frozen=True)
class WallClockConfig:
    """Settings of the study (module docstring); every field is checked at construction (one line naming it)."""

    methods: tuple = search.STUDY_METHODS
    dims: tuple = ("shared", "per_leg_cond")
    wall_minutes: tuple = (1.0, 3.0, 10.0)
    groups: tuple = spmod.DEFAULT_GROUPS
    remedy: bool = True
    seed: int = 0
    # success-driven search
    popsize: int = 16
    train_instances: int = 32
    train_duration: float = 24.0
    #: step heights (m) of the training scenarios (and the validation and gradient-window scenarios), each
    #: ``train_instances / len(train_heights)`` times per generation
    train_heights: tuple = forward.TRAIN_HEIGHTS
    #: scenario ranges of every training draw: ``"train"`` (:data:`.forward.TRAIN_RANGES`) or ``"wide"``
    #: (:data:`.forward.HELDOUT_RANGES`, the reach map's wide spread: start 0-15 cm, friction 0.4-1.0, payload 0-15 kg)
    train_spread: str = "train"
    sigma: float = 0.3
    completed_weight: float = 0.1
    # gradient (MJX-JAX)
    grad_train_per_height: int = 2
    windows_per_scenario: int = 2
    window_lead: float = 10.0
    window_ticks: int = 500
    #: weights of the window objective's terms other than its defaults, ``(("progress", 0.0), ...)``
    #: (:meth:`.objective.ClosedLoopObjective.reweighted`; every other weight at its default)
    surrogate_weights: tuple = ()
    lr: float = 0.1
    #: tangents of the tuning step: 0 = exact ``jacfwd`` (``P``); ``K > 0`` = the forward-gradient estimate from
    #: ``K`` random directions (:func:`.objective.make_value_and_forward_gradient`, unbiased, ``(P + 1) / K``
    #: times the variance of one window's gradient)
    grad_directions: int = 0
    #: how the exact tuning step differentiates the windows: ``"jacfwd"`` (forward mode, ``P`` tangents) or
    #: ``"reverse"`` (reverse mode through a fixed-length constraint solver and a checkpointed scan,
    #: :func:`.objective.make_value_and_grad_reverse`; cost independent of ``P``)
    grad_mode: str = "jacfwd"
    #: stiffness (N/m) of the backward-only virtual springs under the feet in the gradient's windows
    #: (:mod:`hyqjax.sim.contacts_from_distance`, reach 2 cm); 0: off
    contacts_from_distance: float = 0.0
    hybrid_split: float = 0.5
    #: the hybrid re-takes the gradient's snapshot windows under the iterate its gradient starts from (in its
    #: clock: the capture's compile and forward run), instead of descending from the start point's gait
    retake_windows: bool = False
    # held-out
    heldout: int = 2000
    heldout_seed: int = 7777
    heldout_duration: float = 24.0
    heldout_chunk: int = 8
    #: MJX implementation of the forward runs (search, held-out); the gradient always runs under impl jax
    impl: str = "auto"
    #: warm starts: ``(("method/dim", theta), ...)``, the start of that method on that parameterisation
    start_from: tuple = ()
    #: the start point of every run not in ``start_from``: a crawl preset of :mod:`hyqjax.presets` (its values
    #: outside the tuned coordinates stay fixed; a per-leg set starts the per-leg parameterisations from its four
    #: rows); "": Table I and the default crawl (with the shin remedy if ``remedy``)
    start_preset: str = ""
    #: charge each method the compile of its programs (False: only what it runs; e.g. with a warm compile cache)
    charge_compile: bool = True
    #: compile every program cold: JAX's persistent compilation cache and Warp's kernel cache in fresh empty
    #: directories of this process (:func:`hyqjax.io.cache.use_cold_caches`), so no process profits from another's
    cold_compile: bool = False
    #: closed-loop validation selection (:class:`.selection.Selection`): every method returns its best iterate by
    #: clean success on ``select_instances`` fixed validation scenarios (drawn like training from ``select_seed``),
    #: validated every ``select_every`` iterations and / or ``select_every_s`` seconds, paid from its clock.
    #: The default, (16 + 1) x 32 = 544, is the rows of a default generation: the selection runs on the forward
    #: program the search already compiled. 0: no selection (the last iterate is returned)
    select_instances: int = 544
    select_every: int = 5
    select_every_s: float = 0.0
    select_seed: int = 5555
    #: the final re-evaluation (:func:`.selection.final_choice`): after the budget, the ``final_candidates`` best
    #: validated iterates run on ``final_instances`` further scenarios (drawn like the validation batch, from its
    #: seed's next draw) and the best pooled over both batches is returned; 0: off (the selected iterate)
    final_instances: int = 0
    final_candidates: int = 3
    # guided ES (:func:`.guided.run_guided`)
    #: share of the sampling variance in the full space (1: isotropic antithetic ES; 0: the gradient subspace only)
    guided_alpha: float = 0.5
    #: number of recent surrogate gradients that span the guiding subspace
    guided_subspace: int = 1
    #: Adam learning rate of the search mean
    guided_lr: float = 0.05
    #: a new surrogate gradient (the tuning step's, on MJX-JAX) every this many generations
    guided_grad_every: int = 1
    # restarts of CMA-ES (:mod:`.restarts`; methods ipop_cma_es and bipop_cma_es)
    #: generations without a better validated score of the run that end it (0: the papers' lengths, longer than
    #: the tuner's budgets; :mod:`.restarts`)
    restart_stall: int = 25
    # the alpha-order blend (:func:`.blend.run_blend`)
    #: the bias the blend may take, relative to the norm of the population's zero-order estimate (Suh et al.'s
    #: gamma; the first-order samples are scaled to that norm)
    blend_gamma: float = 2.0
    #: Adam learning rate of the blend's iterate
    blend_lr: float = 0.05

    def __post_init__(self):
        backend.validate_impl(self.impl)
        bad = [m for m in self.methods if m not in search.METHODS]
        if bad or not self.methods or len(set(self.methods)) != len(self.methods):
            raise ValueError(f"methods must be distinct names among {list(search.METHODS)}, got {list(self.methods)}")
        bad = [d for d in self.dims if d not in schedule.NAMES]
        if bad or not self.dims or len(set(self.dims)) != len(self.dims):
            raise ValueError(f"dims must be distinct names among {list(schedule.NAMES)}, got {list(self.dims)}")
        spmod.ParamSpace.make(self.groups)
        wm = tuple(self.wall_minutes)
        if not wm or any(not (0.0 < float(x) <= 600.0) for x in wm) or list(wm) != sorted(set(wm)):
            raise ValueError(f"wall_minutes must be increasing values in (0, 600] minutes, got {list(wm)}")
        for k, lo, hi in (("popsize", 2, 4096), ("train_instances", 4, 100000), ("grad_train_per_height", 1, 1000),
                          ("windows_per_scenario", 1, 8), ("window_ticks", 1, 20000), ("heldout", 1, 10**6),
                          ("grad_directions", 0, 4096),
                          ("heldout_chunk", 1, 4096), ("seed", 0, 2**31 - 1), ("heldout_seed", 0, 2**31 - 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        for m in search.ANTITHETIC:
            if m in self.methods and self.popsize % 2:
                raise ValueError(f"popsize must be even with {m} (it samples antithetic pairs), got {self.popsize}")
        if not 0.0 <= float(self.guided_alpha) <= 1.0:
            raise ValueError(f"guided_alpha must be in [0, 1], got {self.guided_alpha}")
        if not 0.0 < float(self.guided_lr) <= 1.0:
            raise ValueError(f"guided_lr must be in (0, 1], got {self.guided_lr}")
        if not 0.0 < float(self.blend_gamma) <= 100.0:
            raise ValueError(f"blend_gamma must be in (0, 100], got {self.blend_gamma}")
        if not 0.0 < float(self.blend_lr) <= 1.0:
            raise ValueError(f"blend_lr must be in (0, 1], got {self.blend_lr}")

        for k, lo, hi in (("final_instances", 0, 10**6), ("final_candidates", 2, 16)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if self.final_instances and not self.select_instances:
            raise ValueError(f"final_instances ({self.final_instances}) re-evaluates the selection's best iterates: "
                             f"it needs select_instances > 0")
        restarting = [m for m in self.methods if m in search.RESTART_METHODS]
        if restarting and not self.select_instances:
            raise ValueError(f"select_instances must be > 0 with {restarting[0]}: its runs are compared on the "
                             f"validation batch (the selection spans the restarts), got 0")
        if self.final_instances % len(tuple(self.train_heights)):
            raise ValueError(f"final_instances must be a multiple of {len(tuple(self.train_heights))} (one share per "
                             f"training height), got {self.final_instances}")
        for k, lo, hi in (("guided_subspace", 1, 64), ("guided_grad_every", 1, 10**4), ("restart_stall", 0, 10**5)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        for k in ("charge_compile", "cold_compile", "retake_windows"):
            if not isinstance(getattr(self, k), bool):
                raise ValueError(f"{k} must be True or False, got {getattr(self, k)!r}")
        for k, lo, hi in (("select_instances", 0, 10**6), ("select_every", 0, 10**5), ("select_seed", 0, 2**31 - 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ValueError(f"{k} must be an int in [{lo}, {hi}], got {v!r}")
        if not 0.0 <= float(self.select_every_s) <= 3600.0:
            raise ValueError(f"select_every_s must be in [0, 3600] s, got {self.select_every_s}")
        th = tuple(self.train_heights)
        if (not th or len(th) > 16 or len(set(th)) != len(th)
                or any(isinstance(h, bool) or not isinstance(h, (int, float)) or not 0.0 <= float(h) <= 0.4 for h in th)):
            raise ValueError(f"train_heights must be 1 to 16 distinct heights in [0, 0.4] m, got {list(th)}")
        if self.train_spread not in forward.SPREADS:
            raise ValueError(f"train_spread must be one of {list(forward.SPREADS)}, got {self.train_spread!r}")
        if self.grad_mode not in GRAD_MODES:
            raise ValueError(f"grad_mode must be one of {list(GRAD_MODES)}, got {self.grad_mode!r}")
        if self.grad_mode == "reverse" and self.grad_directions:
            raise ValueError(f"grad_directions must be 0 with grad_mode reverse (the exact reverse-mode step), "
                             f"got {self.grad_directions}")
        if self.select_instances % len(th):
            raise ValueError(f"select_instances must be a multiple of {len(th)} (one share per "
                             f"training height; 0: no selection), got {self.select_instances}")
        if self.select_instances and not (self.select_every > 0 or self.select_every_s > 0):
            raise ValueError("select_every (iterations) or select_every_s (seconds) must be > 0 with "
                             f"select_instances {self.select_instances}")
        if self.select_seed in training_seeds(self.seed) or self.select_seed == self.heldout_seed:
            raise ValueError(f"select_seed must differ from heldout_seed ({self.heldout_seed}) and the training "
                             f"draws' seeds ({', '.join(map(str, training_seeds(self.seed)))}), got {self.select_seed}")
        if self.train_instances % len(th):
            raise ValueError(f"train_instances must be a multiple of {len(th)} (one share per "
                             f"training height), got {self.train_instances}")
        if self.heldout_seed == self.seed:
            raise ValueError(f"heldout_seed must differ from seed (held-out scenarios), got {self.heldout_seed}")
        for k, lo, hi in (("train_duration", 0.1, 120.0), ("heldout_duration", 0.1, 120.0), ("window_lead", 0.1, 60.0)):
            if not (lo <= float(getattr(self, k)) <= hi):
                raise ValueError(f"{k} must be in [{lo}, {hi}] s, got {getattr(self, k)}")
        for k, lo, hi in (("sigma", 0.0, 5.0), ("lr", 0.0, 1.0), ("hybrid_split", 0.0, 1.0)):
            if not (lo < float(getattr(self, k)) < hi or (k != "hybrid_split" and float(getattr(self, k)) == hi)):
                end = ")" if k == "hybrid_split" else "]"
                raise ValueError(f"{k} must be in ({lo}, {hi}{end}, got {getattr(self, k)}")
        if isinstance(self.contacts_from_distance, bool) or not 0.0 <= float(self.contacts_from_distance) <= 1e6:
            raise ValueError(f"contacts_from_distance must be in [0, 1e6] N/m, got {self.contacts_from_distance}")
        if not (0.0 <= self.completed_weight <= 10.0):
            raise ValueError(f"completed_weight must be in [0, 10], got {self.completed_weight}")
        if not isinstance(self.remedy, bool):
            raise ValueError(f"remedy must be True or False, got {self.remedy!r}")
        for key, theta in self.start_from:
            m, _, d = str(key).partition("/")
            if m not in self.methods or d not in self.dims:
                raise ValueError(f"start_from names {key!r}, not a run of this study ({list(self.methods)} on "
                                 f"{list(self.dims)})")
            size = schedule.make(d, self.groups).size
            if len(theta) != size or not np.all(np.isfinite(np.asarray(theta, float))):
                raise ValueError(f"start_from {key!r} must be {size} finite numbers, got {len(theta)}")

        check_weights(self.surrogate_weights)
        if not isinstance(self.start_preset, str):
            raise ValueError(f"start_preset must be a preset name or '', got {self.start_preset!r}")

    @property
    def checkpoints_s(self) -> tuple:
        return tuple(60.0 * float(m) for m in self.wall_minutes)

    def to_dict(self) -> dict:
        return json.loads(json.dumps(dataclasses.asdict(self), default=list))

    @staticmethod
    def defaults() -> dict:
        """Every setting's default, as :meth:`to_dict` writes it (no checks run)."""
        fields = {f.name: f.default for f in dataclasses.fields(WallClockConfig)}
        return json.loads(json.dumps(fields, default=list))

    @classmethod
    def from_dict(cls, config: dict) -> "WallClockConfig":
        """The configuration a ``results.json``'s ``config`` stores (lists back to tuples; a setting the study
        predates at its default; checked like any other)."""
        names = {f.name for f in dataclasses.fields(cls)}
        tup = lambda v: tuple(tup(x) for x in v) if isinstance(v, list) else v  # noqa: E731
        return cls(**{k: tup(v) for k, v in config.items() if k in names})



def start_point(cfg: WallClockConfig):
    """Where every run starts: the crawl preset ``cfg.start_preset`` (a ``CrawlParams`` or a per-leg set), else
    Table I and the default crawl, with the shin-strike remedy if ``cfg.remedy``."""
    if cfg.start_preset:
        from hyqjax import presets

        return presets.load(cfg.start_preset)
    from hyqjax.crawl import controller as crawl

    return crawl.CrawlParams.make(shin_remedy=cfg.remedy)


def start_settings(preset: str) -> dict:
    """The ``CrawlParams.make`` settings (``crawl``) and Table I values (``reflex``) of the crawl a run started
    from preset ``preset`` maps its ``theta`` on (``{}`` for none): stored in ``results.json`` as ``start_base``
    so that the returned set reads back (:func:`hyqjax.studies.tune.tuned.crawl_params`) with the preset's values
    of the coordinates the run did not tune (an edge probe, say)."""
    if not preset:
        return {}
    from hyqjax import presets

    values = presets.get(preset).values or {}
    return {"crawl": dict(values.get("crawl", {})), "reflex": dict(values.get("reflex", {}))}


def is_per_leg(start) -> bool:
    """Whether a start point is a scheduled set around a ``base`` (a per-leg set or a tuner's conditioned set)."""
    return hasattr(start, "base") and (hasattr(start, "row") or hasattr(start, "parameterisation"))


def start_theta(param: schedule.Parameterisation, start) -> np.ndarray:
    """The ``theta`` of ``param`` that runs ``start``: a ``CrawlParams`` on every leg, a per-leg set's four rows
    (per-leg parameterisations only; no conditioning), or a conditioned set's own ``theta`` (its
    parameterisation only)."""
    if hasattr(start, "parameterisation") and hasattr(start, "table"):
        pz = start.parameterisation
        if pz.name != param.name or pz.space != param.space:
            raise ValueError(f"a start point conditioned as {pz.name} starts that parameterisation with its groups "
                             f"only, not {param.name}")
        table, cond = np.asarray(start.table, np.float64), np.asarray(start.cond, np.float64)
        rows = table.reshape(-1) if param.per_leg else table[0]
        idx = [param.space.names.index(c) for c in param.conditioned]
        return np.concatenate([rows, cond[:, idx].reshape(-1) if idx else np.zeros(0)])
    if not is_per_leg(start):
        return param.theta_of(start)
    if not param.per_leg:
        raise ValueError(f"a per-leg start point needs a per-leg parameterisation, not {param.name}")
    rows = [param.space.theta_of(start.row(i)) for i in range(4)]
    return np.concatenate(rows + [np.zeros(param.size - 4 * param.space.size)])
