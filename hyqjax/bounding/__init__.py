"""Impulse-based bounding and turning (Orsolino et al., "Turning maneuvers strategy for quadrupedal bounding gait").

Modules, one concept each:
  params      the bound's parameters in one import, and the parameter sets on the stored cycle (``paper_params``,
              ``default_params``, ``params_of_values``)
  param_types the parameter classes (gait, gains, switches, command, the cycle) with declared ranges
  apex        the apex state ``Apex``
  gait        clock, stance phases, impulse profiles, Park & Kim's impulse balance (Eqs. B1-B2)
  estimator   IMU attitude and rates, leg-odometry height and velocity
  kinematic   touchdown targets (B8), kinematic adjustment (Eqs. 1-2), joint references
  controller  apex / stance feedback (B4, B5, B7), yaw control (B6), centrifugal compensation (Eqs. 3-4),
              the controller ``bounding_controller``
  state       the controller's state and per-tick ``BoundingInfo``
  cycle       apex return map through MJX, Levenberg-Marquardt cycle optimisation (optimistix), gradient check
  stability   linearised return map, apex feedback matrix and design, the stance reference table
  defaults    the stored limit cycle (``default_cycle.json``)
  batch       a batch of instances: per-instance parameters, randomisation (``make_batch``), setting validation
  rollout     ``make_bounding_rollout``: the closed loop of one instance as a pure JAX function (jit / vmap /
              jacfwd) with a typed ``BoundingOutcome``, and the batch through the one compiled runner; the device
              fall metrics, the trace sample, ``run`` (NumPy traces)
  summary     per-instance ``InstanceResult`` and per-group tracking metrics, ablation contributions
  tracking    device tracking metrics (worst yaw error, filtered speed errors, fall margins), the robust cost,
              batched forward runs with them
  envelope    the command envelope: fall rate and yaw error per command (Wilson intervals), the safe area
  robust      robust baseline optimisation over commands / friction / payload: jacfwd + Adam, CMA-ES (evosax)
  robust_params  the robust study's coordinates and its stored parameter sets (kept importable from robust)
  plots       figures
"""
from hyqjax.bounding.controller import bounding_controller, bounding_init, bounding_step
from hyqjax.bounding.params import (
    APEX_NAMES,
    Apex,
    BoundingCommand,
    BoundingGains,
    BoundingParams,
    GaitParams,
    Switches,
    default_params,
    paper_params,
    params_of_values,
)
from hyqjax.bounding.batch import Batch, Randomisation, make_batch
from hyqjax.bounding.rollout import (
    BoundingOutcome,
    BoundingRollout,
    BoundingRolloutConfig,
    instance_args,
    make_bounding_rollout,
)
from hyqjax.bounding.state import BoundingInfo, BoundingState

__all__ = ["APEX_NAMES", "Apex", "Batch", "BoundingCommand", "BoundingGains", "BoundingInfo", "BoundingOutcome",
           "BoundingParams", "BoundingRollout", "BoundingRolloutConfig", "BoundingState", "GaitParams", "Randomisation",
           "Switches", "bounding_controller", "bounding_init", "bounding_step", "default_params", "instance_args",
           "paper_params", "params_of_values",
           "make_batch", "make_bounding_rollout"]
