"""The experiments: the step-down (Section IV), parameter sweeps and reflex tuning."""
