"""The MuJoCo Warp path (``impl="warp"``) on the CPU: the same step-down instances under MJX-JAX and MJX-Warp.

Warp 1.18.0 runs on the CPU (slowly: each tick is one FFI call), so the warp path is tested here rather than
only around it: the batch runner, the Warp data with per-instance terrain poses, the contact sensors, the
overflow flag and the derivative guard. The first warp call of a machine compiles Warp's kernels through
LLVM (about 2 minutes on 2 cores, cached in ``~/.cache/warp`` afterwards).

The runs happen in a fresh process, so that a crash in Warp's native code fails this test instead of ending the
session. (The whole session with warp-lang installed once died around here of SIGABRT; the cause was the pytest
process reaching the kernel's limit on memory mappings with the XLA programs of ~440 tests, not this file:
tests/conftest.py now releases JAX's compiled programs after each test module.)
The test extra installs warp-lang (``pip install -e ".[test]"``), so CI runs this file; it is skipped where
warp-lang is not installed.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("warp")

DURATION = 0.4  # 200 ticks: the first body phase and the start of the first swing

SCRIPT = r"""
import json, sys
import numpy as np
import hyqjax
import jax, jax.numpy as jnp
from hyqjax.studies import stepdown

scen, table = stepdown.make_scenarios([0.16, 0.24], [True], 1, seed=5)
out = {}
for impl in ("jax", "warp"):
    cfg = stepdown.StepdownConfig(duration=DURATION, record_every=10, impl=impl)
    cols, trace = stepdown.run_batch(scen, cfg)
    out[impl] = dict(cols={k: np.asarray(v).tolist() for k, v in cols.items()
                           if k in ("completed", "clean", "lost_foothold", "shin_strike", "trunk_strike", "diverged",
                                    "contact_overflow")},
                     base_pos=np.asarray(trace["base_pos"]).tolist(), q=np.asarray(trace["q"]).tolist(),
                     foot_force=np.asarray(trace["foot_force"]).tolist())
one = scen.instance(1)
rollout = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.02, impl="warp"))

def final_z(k_base):
    p = one.params.replace(reflex=one.params.reflex.replace(k_base=k_base))
    return rollout(p, one)[1].qpos[2]

errors = {}
for name, call in (("jacfwd", lambda: jax.jacfwd(final_z)(jnp.asarray(1500.0))),
                   ("one_instance", lambda: final_z(jnp.asarray(1500.0)))):
    try:
        call()
        errors[name] = None
    except ValueError as e:
        errors[name] = str(e)
print("RESULT " + json.dumps(dict(out=out, heights=table["height"].tolist(), errors=errors)))
""".replace("DURATION", repr(DURATION))


@pytest.fixture(scope="module")
def paired():
    """Two instances (16 and 24 cm, reflex on) under both implementations, with traces every 10 ticks."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=900, env=env)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    assert r.returncode == 0 and lines, f"exit {r.returncode}\n{r.stderr[-3000:]}"
    return json.loads(lines[-1][len("RESULT "):])


@pytest.mark.slow
def test_warp_and_jax_trajectories_agree(paired):
    import numpy as np

    j, w, h = paired["out"]["jax"], paired["out"]["warp"], np.asarray(paired["heights"])
    base_j, base_w = np.asarray(j["base_pos"]), np.asarray(w["base_pos"])
    assert base_j.shape == base_w.shape and np.all(np.isfinite(base_w))
    # Per-instance platform heights took effect under warp (each trunk starts on its own platform).
    np.testing.assert_allclose(base_w[:, 0, 2] - h, base_j[:, 0, 2] - h, atol=1e-3)
    assert np.max(np.abs(base_w - base_j)) < 1e-3  # metres, over 0.4 s of crawling
    assert np.max(np.abs(np.asarray(w["q"]) - np.asarray(j["q"]))) < 1e-2  # rad


@pytest.mark.slow
def test_warp_outcomes_and_contact_sensors_agree(paired):
    import numpy as np

    cj, cw = paired["out"]["jax"]["cols"], paired["out"]["warp"]["cols"]
    for k in cj:
        assert cj[k] == cw[k], k
    assert not any(cw["contact_overflow"])  # the contact buffer was sized for the batch
    # Foot forces are read from the contact sensors under both implementations.
    fj, fw = np.asarray(paired["out"]["jax"]["foot_force"]), np.asarray(paired["out"]["warp"]["foot_force"])
    assert np.max(np.abs(fw - fj)) < 5.0  # N, on forces of ~200 N per stance foot


@pytest.mark.slow
def test_a_derivative_through_a_warp_rollout_is_refused(paired):
    err = paired["errors"]
    assert err["jacfwd"] is not None and "impl='warp' is not differentiable" in err["jacfwd"]
    # Forward, one instance is refused with its reason (warp runs batches: rollout.run).
    assert err["one_instance"] is not None and "one-instance rollout needs impl='jax'" in err["one_instance"]
