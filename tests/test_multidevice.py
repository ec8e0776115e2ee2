"""Every device of a host (hyqjax.sim.devices, hyqjax.sim.runner.run_on): the ``--devices`` option, and the same
instances with bitwise the same results on 1 and 4 XLA host devices (``--xla_force_host_platform_device_count=4``,
in a fresh process) for the step-down rollout and a sweep's chunk."""
from __future__ import annotations

import json
import os

import pytest

from conftest import run_python
from hyqjax.sim import devices


def test_devices_option_forms():
    assert devices.parse("all") is None and devices.parse(None) is None
    assert devices.parse("3") == 3 and devices.parse(2) == 2
    assert devices.parse("0,2") == (0, 2) and devices.parse("1,") == (1,)
    for bad in ("0", "-1", "x", "0,0", "1.5", "0;1"):
        with pytest.raises(ValueError, match="--devices"):
            devices.parse(bad)
    assert devices.layout("jax", 1) == "one" and devices.layout("c", 4) == "one"
    assert devices.layout("jax", 4) == "split" and devices.layout("warp", 2) == "split"


def test_devices_refused_before_any_compile(capsys):
    """A count above the host's devices, an id that is not there, or a malformed value: exit 2, one line naming
    --devices, before anything compiles."""
    from hyqjax.cli.app import main
    import jax

    have = len(jax.local_devices())
    for value, expect in ((str(have + 1), f"--devices {have + 1}: this host has {have}"),
                          (f"0,{have + 5}", f"no device {have + 5}"), ("two", "--devices must be 'all'")):
        rc = main(["stepdown", "--instances", "1", "--no-figures", "--out", "/tmp/x-never",
                   "--devices", value])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and expect in err[0], err
        assert not os.path.exists("/tmp/x-never"), "a refused command leaves no output directory"


CODE = r"""
import json, numpy as np, jax
assert len(jax.local_devices()) == 4, jax.local_devices()
from hyqjax.crawl import controller as crawl
from hyqjax.studies import stepdown, stepdown_outcome, sweep

scen, table = stepdown.make_scenarios([0.10, 0.16], [True], 9, 0, params=crawl.CrawlParams.make())
ro = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.4, impl="jax"))
out1, r1 = ro.run(scen, devices=1)
out4, r4 = ro.run(scen, devices=4)
leaves = lambda r: jax.tree_util.tree_leaves(jax.tree_util.tree_map(np.asarray, r._replace(trace=None)))
a, b = leaves(r1), leaves(r4)
res = dict(n_leaves=len(a), rollout_differ=sum(not np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b)),
           qpos_shape=list(np.asarray(r4.data.qpos).shape),
           outcomes_differ=sum(not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                               for x, y in zip(jax.tree_util.tree_leaves(out1), jax.tree_util.tree_leaves(out4))),
           completed=np.asarray(stepdown_outcome.to_columns(out4)["completed"]).tolist())
spec = sweep.SweepSpec.from_dict(dict(seed=3, samples=4, duration=0.3, grid=dict(height=[0.16, 0.24]),
                                      random=dict(friction=[0.6, 1.0])))
rows = spec.instance_inputs(0, 8)  # a chunk of 8: one program of 8 rows, or 4 devices x 2 rows
s1 = sweep.run_rows(rows, spec, 8, devices=jax.local_devices()[:1])
s4 = sweep.run_rows(rows, spec, 8, devices=jax.local_devices())
res.update(sweep_cols=len(s1), sweep_differ=[k for k in s1 if not np.array_equal(s1[k], s4[k],
                                                                                equal_nan=s1[k].dtype.kind == "f")])
print("RESULT " + json.dumps(res))
"""


@pytest.mark.slow
def test_one_and_four_host_devices_give_bitwise_the_same_rollouts_and_sweep_rows():
    p = run_python(CODE, timeout=1200,
                   env={"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()})
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(next(line for line in p.stdout.splitlines() if line.startswith("RESULT "))[7:])
    assert res["qpos_shape"][0] == 18  # the 18 instances (3 passes of 8, on 3 devices), the padding rows dropped
    assert res["n_leaves"] > 50 and res["rollout_differ"] == 0, res
    assert res["outcomes_differ"] == 0 and len(res["completed"]) == 18, res
    assert res["sweep_cols"] > 10 and res["sweep_differ"] == [], res


TUNE_CODE = r"""
import json, numpy as np, jax
assert len(jax.local_devices()) == 4
from hyqjax.studies.tune import forward, schedule
from hyqjax.crawl import controller as crawl

p = schedule.make("shared")
base = crawl.CrawlParams.make()
th0 = p.theta_of(base)
thetas = np.stack([th0, th0 + 0.3, th0 - 0.2])
sc = forward.train_scenarios(4, 3, 0)
res = {}
for d in (1, 4):
    ev = forward.SuccessEvaluator(p, base, 0.4, "jax", devices=d)
    res[d] = ev(thetas, sc)
a, b = res[1], res[4]
print("RESULT " + json.dumps(dict(
    fitness1=a["fitness"].tolist(), fitness4=b["fitness"].tolist(),
    columns_differ=[k for k in a["columns"] if not np.array_equal(a["columns"][k], b["columns"][k], equal_nan=True)],
    n_columns=len(a["columns"]),
    differs_between_members=not np.array_equal(b["columns"]["progress"][0], b["columns"]["progress"][1]),
    steps=[a["physics_steps"], b["physics_steps"]])))
"""


@pytest.mark.slow
def test_tuner_generation_over_four_host_devices_gives_the_same_objective():
    """One generation (3 members x 4 common scenarios) evaluated on 1 and on 4 host devices (the 12 rows as 2 passes of
    8, one on each of 2 devices): the same fitness and the same per-row outcome columns."""
    p = run_python(TUNE_CODE, timeout=1200,
                   env={"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()})
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(next(line for line in p.stdout.splitlines() if line.startswith("RESULT "))[7:])
    assert res["fitness1"] == res["fitness4"] and len(res["fitness1"]) == 3, res
    assert res["n_columns"] > 10 and res["columns_differ"] == [], res
    assert res["differs_between_members"] and res["steps"] == [3 * 4 * 200] * 2, res


BOUND_CODE = r"""
import json, numpy as np, jax
assert len(jax.local_devices()) == 4
from hyqjax.bounding import envelope as be

spec = be.EnvelopeSpec(speeds=(0.0, 0.5), yaw_rates=(0.3,), instances=5, friction=(0.7, 1.0), payload=(0.0, 5.0),
                       duration=0.8)
batch = spec.batch(None)
from hyqjax.bounding import tracking
c1 = tracking.run_batch(batch, spec.duration, "jax", devices=1)
c4 = tracking.run_batch(batch, spec.duration, "jax", devices=4)
print("RESULT " + json.dumps(dict(n=int(len(c1["success"])), cols=len(c1),
    differ=[k for k in c1 if not np.array_equal(c1[k], c4[k], equal_nan=np.asarray(c1[k]).dtype.kind == "f")])))
"""


@pytest.mark.slow
def test_bounding_envelope_batch_on_one_and_four_host_devices_is_the_same():
    """The bounding envelope's batch (tracking.run_batch, MJX-JAX; 2 commands x 5 instances, 0.8 s: 2 passes of 8
    rows, on 2 devices) on 1 and on 4 host devices: every column equal."""
    p = run_python(BOUND_CODE, timeout=1200,
                   env={"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()})
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(next(line for line in p.stdout.splitlines() if line.startswith("RESULT "))[7:])
    assert res["n"] == 10 and res["cols"] > 10 and res["differ"] == [], res

