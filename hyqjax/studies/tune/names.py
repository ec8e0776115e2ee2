"""The names the tuner's command line checks before anything heavy is imported: methods of the equal-wall-clock
study, parameterisations, and the default tuner's choice (no JAX import here; :mod:`hyqjax.studies.tune.search`,
:mod:`hyqjax.studies.tune.schedule` and :mod:`hyqjax.studies.tune.wallclock` take them from this module)."""
from __future__ import annotations

#: CMA-ES with restarts (:mod:`hyqjax.studies.tune.restarts`): IPOP (population doubled at each restart; Auger &
#: Hansen 2005) and BIPOP (large and small population regimes under one budget; Hansen 2009).
RESTART_METHODS = ("ipop_cma_es", "bipop_cma_es")
#: Zero-order methods driven by closed-loop clean success (evosax CMA-ES, SNES, OpenES; random search; CMA-ES with
#: restarts).
SEARCH_METHODS = ("cma_es", "snes", "open_es", "random_search") + RESTART_METHODS
#: The pathwise gradient through closed-loop windows, and the hybrid (search, then gradient polish).
GRADIENT_METHODS = ("gradient", "hybrid")
#: Guided evolution strategies (Maheswaranathan et al. 2019; evosax GuidedES): antithetic search whose samples
#: lean into the subspace of recent surrogate gradients from MJX-JAX (:func:`hyqjax.studies.tune.guided.run_guided`).
GUIDED_METHODS = ("guided_es",)
#: Suh et al.'s (ICML 2022) alpha-order blend of the MJX-JAX window gradient and the population's antithetic
#: zeroth-order estimate, Adam on the blend (:func:`hyqjax.studies.tune.blend.run_blend`).
BLEND_METHODS = ("blend",)
METHODS = SEARCH_METHODS + GRADIENT_METHODS + GUIDED_METHODS + BLEND_METHODS
#: The methods of the equal-wall-clock study when none are named (``python -m experiments.tune_study``): those
#: every stored study ran; the restart rules and the blend run when named (``--methods``).
STUDY_METHODS = ("cma_es", "snes", "open_es", "random_search") + GRADIENT_METHODS + GUIDED_METHODS
#: Methods that build the gradient's programs (snapshot windows and the tuning step on MJX-JAX).
USES_GRADIENT = GRADIENT_METHODS + GUIDED_METHODS + BLEND_METHODS
#: Of those, the ones that take no line search along the gradient: the windows' value program is not built for them.
NO_LINE_SEARCH = GUIDED_METHODS + BLEND_METHODS
#: Methods that sample antithetic pairs (an even --popsize).
ANTITHETIC = ("open_es", "guided_es", "blend")
#: Parameterisations (:data:`hyqjax.studies.tune.schedule.NAMES` holds what each one means).
DIMS = ("shared", "per_leg", "per_leg_cond", "per_leg_cond_all")
#: The default tuner (``hyqjax tune`` with no method, parameterisation or budget given): CMA-ES on the 56 per-leg
#: coordinates for 30 minutes (checkpoints 3, 10, 30), the method and parameterisation of the best set measured from
#: Table I (0.741 held-out clean at 30 minutes on the study's set, 0.841 on the independent 2,400 step-downs of
#: 2026-11-29: the preset ``tuned_per_leg``; 14 shared coordinates: 0.621 at 30 minutes). Five runs of it at 3
#: minutes from ``reach`` on the training spread returned 0.707 [0.585, 0.829] over runs on held-out step-downs,
#: below their start's 0.814, from starts 10-15 cm before the edge that the training spread never drew; the
#: default therefore trains on the wide spread (``hyqjax.cli.tune.OBJECTIVES``; docs/tuning.md, "Five default
#: runs"). With the leading-foot start (``hyqjax.studies.stepdown.START_POSE``) five 3-minute runs from ``reach``
#: returned 0.863 [0.796, 0.930] over runs, range 0.130, against ``reach``'s 0.777 on the same map; the one with the
#: highest validation score of its own is the preset ``clean`` (0.925 on fresh held-out instances). From ``clean``,
#: five 30-minute runs return 0.941 [0.935, 0.947] over runs on held-out step-downs (C MuJoCo, 2026-11-30), +0.014
#: above ``clean`` in every run; the iterates they held at 3 and 10 minutes tie with ``clean``, so the budget stays
#: 30 minutes (docs/tuning.md, "What hyqjax tune returns by default").
DEFAULT_METHOD = "cma_es"
DEFAULT_DIM = "per_leg"
DEFAULT_WALL_MINUTES = (3.0, 10.0, 30.0)
#: The equal-wall-clock study's default checkpoints (``python -m experiments.tune_study``).
STUDY_WALL_MINUTES = (1.0, 3.0, 10.0)
#: The default start point of ``hyqjax tune`` per (objective, parameterisation): the best measured crawl preset of
#: :mod:`hyqjax.presets` for that objective that the parameterisation can start from.
#:
#: * objective ``clean`` on a per-leg parameterisation: ``clean`` (0.925 clean up to 26 cm on fresh held-out
#:   step-downs of the wide spread with the leading-foot start, against 0.837 for ``tuned_per_leg_reach`` and
#:   0.787 for ``reach`` on the same instances; docs/tuning.md). A conditioned parameterisation starts from its
#:   four rows with zero conditioning weights.
#: * objective ``clean`` on the 14 shared coordinates (a per-leg set cannot start them) and objective ``reach``:
#:   ``reach`` (SNES gains trained on the reach, the edge probe and the depth gate). At 29 cm ``clean`` completes
#:   0.57-0.59 of the step-downs against ``reach``'s 0.75-0.77, so the reach objective keeps ``reach``.
#:
#: ``clean_refined`` (``clean`` refined by one 3-minute run of this default, +0.011 above ``clean`` on fresh
#: step-downs) is not the default start: the five-run measurements of the default started from ``clean``.
#:
#: Coordinates no parameterisation tunes (the edge probe) stay as the preset has them
#: (``WallClockConfig.start_preset``). A pair not listed starts from Table I with the shin remedy; ``--preset none``
#: starts there too.
DEFAULT_PRESETS = {("clean", "shared"): "reach", ("clean", "per_leg"): "clean",
                   ("clean", "per_leg_cond"): "clean", ("clean", "per_leg_cond_all"): "clean",
                   ("reach", "shared"): "reach", ("reach", "per_leg"): "reach"}

#: The search's first step (``--sigma``, in the tuner's normalised coordinates) of ``hyqjax tune`` from a tuned
#: start (a registry preset or ``--start-from``). Around ``clean`` a step of 0.3 leaves 0 of 16 first-generation
#: samples as clean as the start (mean paired loss 0.400), 0.1 leaves 5 of 16 (loss 0.057; C MuJoCo,
#: ``python -m experiments.tune_step_size``). Five 3-minute runs from ``clean`` (two H200s, MuJoCo Warp, held-out map
#: seed 27182, 6,144 step-downs a set): at 0.3 every run returned ``clean`` (0.924); at 0.1 four of five returned a
#: later iterate, 0.937 [0.925, 0.949] over runs, range 0.023 (docs/tuning.md, "The step size").
SIGMA_TUNED_START = 0.1
#: The first step from Table I with the shin remedy (``--preset none``) and in the equal-wall-clock study: the one
#: every stored study ran (``python -m experiments.tune_study``).
SIGMA_TABLE_I = 0.3


def default_sigma(tuned_start: bool, study: bool = False) -> float:
    """``--sigma`` when none is given: :data:`SIGMA_TUNED_START` for ``hyqjax tune`` from a tuned set, else
    :data:`SIGMA_TABLE_I` (a start far from any tuned set, and every study, whose stored runs used it)."""
    return SIGMA_TUNED_START if tuned_start and not study else SIGMA_TABLE_I
