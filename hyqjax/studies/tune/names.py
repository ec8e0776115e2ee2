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
#: The default tuner: the best held-out clean success at the longest budget of the equal-wall-clock study
#: (docs/tuning.md): at 10 minutes on one GPU, every compile cold, over seven seeds, CMA-ES on the 14 shared
#: coordinates returns 0.542 [0.516, 0.568] (95% interval over runs), random search 0.449 [0.401, 0.496], the best
#: hand-set preset 0.406. No method on 56, 68 or 98 coordinates measured clear of it. Flip these names when a
#: study with repeated runs says otherwise.
DEFAULT_METHOD = "cma_es"
DEFAULT_DIM = "shared"
