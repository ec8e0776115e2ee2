"""The names the tuner's command line checks before anything heavy is imported: methods of the equal-wall-clock
study, parameterisations, and the default tuner's choice (no JAX import here; :mod:`hyqjax.studies.tune.search`,
:mod:`hyqjax.studies.tune.schedule` and :mod:`hyqjax.studies.tune.wallclock` take them from this module)."""
from __future__ import annotations

#: Zero-order methods driven by closed-loop clean success (evosax CMA-ES, SNES, OpenES; random search).
SEARCH_METHODS = ("cma_es", "snes", "open_es", "random_search")
#: The pathwise gradient through closed-loop windows, and the hybrid (search, then gradient polish).
GRADIENT_METHODS = ("gradient", "hybrid")
#: Guided evolution strategies (Maheswaranathan et al. 2019; evosax GuidedES): antithetic search whose samples
#: lean into the subspace of recent surrogate gradients from MJX-JAX (:func:`hyqjax.studies.tune.search.run_guided`).
GUIDED_METHODS = ("guided_es",)
METHODS = SEARCH_METHODS + GRADIENT_METHODS + GUIDED_METHODS
#: Methods that build the gradient's programs (snapshot windows and the tuning step on MJX-JAX).
USES_GRADIENT = GRADIENT_METHODS + GUIDED_METHODS
#: Parameterisations (:data:`hyqjax.studies.tune.schedule.NAMES` holds what each one means).
DIMS = ("shared", "per_leg", "per_leg_cond", "per_leg_cond_all")
#: The default tuner (``hyqjax tune`` with no method, parameterisation or budget given): CMA-ES on the 56 per-leg
#: coordinates for 30 minutes (checkpoints 3, 10, 30). On the project's independent held-out set (2,400
#: step-downs at heights between the trained ones, another seed, the wide spread; one H200, 2026-11-29, issue 58's
#: table) CMA-ES on 56 per-leg coordinates returned 0.735 clean at 10 minutes and 0.841 [0.826, 0.855] at 30
#: (one run), against 0.677 (mean of 8 runs, 0.645-0.714) for CMA-ES on the 14 shared coordinates at 10 minutes
#: and 0.735 for the shared 30-minute run at 30: the per-leg run is ahead at both budgets and still gaining
#: from 10 to 30 minutes, the shared one is not (docs/tuning.md). One per-leg run each: the spread over runs of
#: this default is not measured yet.
DEFAULT_METHOD = "cma_es"
DEFAULT_DIM = "per_leg"
DEFAULT_WALL_MINUTES = (3.0, 10.0, 30.0)
#: The equal-wall-clock study's default checkpoints (``python -m experiments.tune_study``).
STUDY_WALL_MINUTES = (1.0, 3.0, 10.0)
#: The default start point of ``hyqjax tune`` per (objective, parameterisation): the best measured preset of
#: :mod:`hyqjax.presets` that the parameterisation can start from (a per-leg set starts per-leg ones only); a
#: pair not listed starts from Table I with the shin remedy. ``--preset none`` starts there too.
DEFAULT_PRESETS = {("clean", "shared"): "tuned_shared", ("clean", "per_leg"): "tuned_per_leg",
                   ("clean", "per_leg_cond"): "tuned_per_leg", ("clean", "per_leg_cond_all"): "tuned_per_leg",
                   ("reach", "shared"): "reach"}
