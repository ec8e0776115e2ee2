"""Simulation: the HyQ + terrain model (:mod:`.model`) and the batched closed-loop rollout (:mod:`.rollout`)."""
