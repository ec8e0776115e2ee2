"""The MuJoCo Warp path (``impl="warp"``) on the CPU: the same step-down instances under MJX-JAX and MJX-Warp.

Warp 1.18.0 runs on the CPU (slowly: each tick is one FFI call), so the warp path is tested here rather than
only around it: the batch runner, the Warp data with per-instance terrain poses, the contact sensors, the
overflow flag and the derivative guard. The first warp call of a machine compiles Warp's kernels through
LLVM (about 2 minutes on 2 cores, cached in ``~/.cache/warp`` afterwards). Skipped when warp-lang is not
installed (it is part of the ``test`` extra).
"""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("warp")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from hyqjax.studies import stepdown  # noqa: E402

DURATION = 0.4  # 200 ticks: the first body phase and the start of the first swing


@pytest.fixture(scope="module")
def paired():
    """Two instances (16 and 24 cm, reflex on) under both implementations, with traces every 10 ticks."""
    scen, table = stepdown.make_scenarios([0.16, 0.24], [True], 1, seed=5)
    out = {}
    for impl in ("jax", "warp"):
        cfg = stepdown.StepdownConfig(duration=DURATION, record_every=10, impl=impl)
        cols, trace = stepdown.run_batch(scen, cfg)
        out[impl] = (cols, trace)
    return scen, table, out


@pytest.mark.slow
def test_warp_and_jax_trajectories_agree(paired):
    _, table, out = paired
    (_, tj), (_, tw) = out["jax"], out["warp"]
    base_j, base_w = np.asarray(tj["base_pos"]), np.asarray(tw["base_pos"])
    assert base_j.shape == base_w.shape and np.all(np.isfinite(base_w))
    # Per-instance platform heights took effect under warp (the trunk starts on its own platform).
    np.testing.assert_allclose(base_w[:, 0, 2] - table["height"], base_j[:, 0, 2] - table["height"], atol=1e-3)
    assert np.max(np.abs(base_w - base_j)) < 1e-3  # metres, over 0.4 s of crawling
    assert np.max(np.abs(np.asarray(tw["q"]) - np.asarray(tj["q"]))) < 1e-2  # rad


@pytest.mark.slow
def test_warp_outcomes_and_contact_sensors_agree(paired):
    _, _, out = paired
    cj, cw = out["jax"][0], out["warp"][0]
    for k in ("completed", "clean", "lost_foothold", "shin_strike", "trunk_strike", "diverged", "contact_overflow"):
        np.testing.assert_array_equal(cj[k], cw[k], err_msg=k)
    assert not np.any(cw["contact_overflow"])  # the contact buffer was sized for the batch
    # Foot forces are read from the contact sensors under both implementations.
    fj, fw = np.asarray(out["jax"][1]["foot_force"]), np.asarray(out["warp"][1]["foot_force"])
    assert np.max(np.abs(fw - fj)) < 5.0  # N, on forces of ~200 N per stance foot


@pytest.mark.slow
def test_a_derivative_through_a_warp_rollout_is_refused(paired):
    scen, _, _ = paired
    rollout = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.02, impl="warp"))
    one = scen.instance(1)

    def final_z(k_base):
        p = one.params.replace(reflex=one.params.reflex.replace(k_base=k_base))
        out, d = rollout(p, one)
        return d.qpos[2]

    with pytest.raises(ValueError, match="impl='warp' is not differentiable"):
        jax.jacfwd(final_z)(jnp.asarray(1500.0))
    # Forward, one instance is refused with its reason (warp runs batches: rollout.run).
    with pytest.raises(ValueError, match="one-instance rollout needs impl='jax'"):
        final_z(jnp.asarray(1500.0))
