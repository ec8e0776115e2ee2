"""The names the tuner's command line checks before anything heavy is imported: methods of the equal-wall-clock
study, parameterisations, and the default tuner's choice (no JAX import here; :mod:`hyqjax.studies.tune.search`,
:mod:`hyqjax.studies.tune.schedule` and :mod:`hyqjax.studies.tune.wallclock` take them from this module)."""
from __future__ import annotations

#: Zero-order methods driven by closed-loop clean success (evosax CMA-ES, SNES, OpenES; random search).
SEARCH_METHODS = ("cma_es", "snes", "open_es", "random_search")
#: The pathwise gradient through closed-loop windows, and the hybrid (search, then gradient polish).
GRADIENT_METHODS = ("gradient", "hybrid")
METHODS = SEARCH_METHODS + GRADIENT_METHODS
#: Parameterisations (:data:`hyqjax.studies.tune.schedule.NAMES` holds what each one means).
DIMS = ("shared", "per_leg", "per_leg_cond", "per_leg_cond_all")
#: The default tuner: the best held-out clean success in the equal-wall-clock study on one H100 (docs/tuning.md),
#: measured up to 3 minutes (random search 0.502 [0.480, 0.524] on the 14 shared coordinates; CMA-ES 0.483 overlaps
#: it; start 0.406). 10 and 30 minutes were not run: flip these names when a longer study says otherwise.
DEFAULT_METHOD = "random_search"
DEFAULT_DIM = "shared"
