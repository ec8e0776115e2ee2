"""Retrace guard of the tuner's step: Adam steps on the kinematic surrogate trace the objective once and compile
nothing after the first step (new values of theta, the gradient and the Adam state reuse the programs).

The other guards: ``reflex_step`` (tests/test_reflex_stability.py), the batch runner of the rollout
(tests/test_sim.py), the step-down rollout of the public API (tests/test_api.py) and the closed-loop tuner
step (tests/test_tune.py).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.crawl import controller as crawl
from hyqjax.studies.tune import optimize
from hyqjax.studies.tune.study import kinematic
from hyqjax.studies.tune import space as spmod

COMPILES: list[str] = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: COMPILES.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)


@pytest.mark.slow
def test_tuner_step_traces_and_compiles_once(tmp_path, monkeypatch):
    traces = []
    batch_terms = kinematic.batch_terms

    def counting(*args, **kwargs):
        traces.append(1)
        return batch_terms(*args, **kwargs)

    monkeypatch.setattr(kinematic, "batch_terms", counting)
    # The configuration of tests/test_tune.py's Adam runs (same program: the compilation cache serves both).
    sp = spmod.ParamSpace.make(("k_base", "damping", "mobility"))
    sc = kinematic.make_scenarios(3, 0, depth=(0.02, 0.06))
    f = kinematic.make_value_and_grad(sp, sc, kinematic.Objective(duration=0.5, t_lift=0.05, lift=0.02),
                                      crawl.CrawlParams.make())
    th0 = jnp.asarray(spmod.table1_theta(sp), jnp.float32)
    compiles_after = []
    res = optimize.run_adam(f, th0, optimize.AdamConfig(steps=4, lr=0.1, checkpoint_every=2), str(tmp_path),
                            dict(kind="retrace"), 7, progress=False,
                            on_step=lambda step, theta, spent: compiles_after.append(len(COMPILES)))
    assert res["step"] == 4 and len(compiles_after) == 4
    assert len(traces) == 1, f"the tuner's objective was traced {len(traces)} times in 4 steps"
    assert compiles_after[1:] == [compiles_after[0]] * 3, f"steps 2-4 compiled: {compiles_after}"
    thetas = np.asarray([r["theta"] for r in optimize.read_log(str(tmp_path))])
    assert np.all(np.abs(np.diff(thetas, axis=0)).max(1) > 0)  # every step moved theta (new values, same program)
