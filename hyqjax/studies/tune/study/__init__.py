"""The tuning study harness, apart from the tuner itself (:mod:`hyqjax.studies.tune`: search methods, parameterisation,
objective, evaluation): the gradient study at equal physics budget (:mod:`.gradient`) with its baselines and the
kinematic surrogate, the gradient's bias against a zero-order reference (:mod:`.bias`), the study's grid of cells and
its repeated runs (:mod:`.cells`, :mod:`.repeats`), the window objective's ranking of iterates (:mod:`.ranking`) and
the hand-set configurations on a study's held-out set (:mod:`.handset`). Run through ``python -m experiments.tune_study``
and the other ``experiments/tune_*`` scripts (docs/tuning.md)."""
