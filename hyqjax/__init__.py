"""hyqjax: IIT HyQ's height reflex, crawl and bounding gaits as pure, batched, differentiable JAX on MJX.

Modules, one concept each:
  robot        HyQ constants (names, geometry, limits, standing pose)
  model        HyQ + step-down terrain as MjModel / batched mjx.Model
  kinematics   FK, foot Jacobians, analytic IK (trunk frame)
  sim          closed-loop batched rollout (lax.scan over ticks, vmap over instances, sharding)
  impedance    joint PD + feed-forward
  reflex       the height reflex (Focchi et al. 2017, Section III)
  crawl        the statically stable crawl (Section II) with the reflex hooked in
  stepdown     the step-down experiment (Section IV)
"""
from __future__ import annotations

import os as _os
import sys as _sys

__version__ = "0.1.0"

# jaxlib 0.10.x on CPU deadlocks jit(vmap(mjx.step)) at batch >= 256. hyqjax pins jax 0.9.2; if a
# newer jax is installed and not yet imported, switch off the two XLA:CPU features involved.
if "jax" not in _sys.modules:
    _flags = _os.environ.get("XLA_FLAGS", "")
    if "concurrency_optimized_scheduler" not in _flags:
        _os.environ["XLA_FLAGS"] = (
            _flags + " --xla_cpu_enable_concurrency_optimized_scheduler=false"
            " --xla_cpu_experimental_ynn_fusion_type="
        ).strip()
