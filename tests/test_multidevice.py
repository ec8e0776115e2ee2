"""Every device of a host (hyqjax.sim.devices, hyqjax.sim.runner.run_on): the ``--devices`` option, and the same
instances with bitwise the same results on 1 and 2 XLA host devices (``--xla_force_host_platform_device_count=2``)
for the step-down rollout, a sweep's chunk, a tuner generation and the bounding envelope's batch.

The three multi-device runs share one fresh process (:func:`two_device_runs`): it imports JAX and MJX once, and
each device's programs are compiled once for all of them. Two devices exercise every path of the split
(:func:`hyqjax.sim.runner.run_on`) that four did: passes dealt out to the devices, a last group with fewer passes
than devices (the step-down's 3 passes on 2 devices), padding rows dropped, equal slices of a sweep chunk; each
further device only compiled the same programs once more (a program is compiled per device on the CPU)."""
from __future__ import annotations

import json
import os

import pytest

from conftest import run_python
from hyqjax.sim import devices

#: Host devices of the multi-device process.
N_DEVICES = 2


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
from hyqjax.crawl import controller as crawl
from hyqjax.studies import stepdown, stepdown_outcome, sweep

scen, table = stepdown.make_scenarios([0.10, 0.16], [True], 9, 0, params=crawl.CrawlParams.make())
ro = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.4, impl="jax"))
out1, r1 = ro.run(scen, devices=1)
out4, r4 = ro.run(scen, devices=N)
leaves = lambda r: jax.tree_util.tree_leaves(jax.tree_util.tree_map(np.asarray, r._replace(trace=None)))
a, b = leaves(r1), leaves(r4)
res = dict(n_leaves=len(a), rollout_differ=sum(not np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b)),
           qpos_shape=list(np.asarray(r4.data.qpos).shape),
           outcomes_differ=sum(not np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True)
                               for x, y in zip(jax.tree_util.tree_leaves(out1), jax.tree_util.tree_leaves(out4))),
           completed=np.asarray(stepdown_outcome.to_columns(out4)["completed"]).tolist())
spec = sweep.SweepSpec.from_dict(dict(seed=3, samples=4, duration=0.3, grid=dict(height=[0.16, 0.24]),
                                      random=dict(friction=[0.6, 1.0])))
rows = spec.instance_inputs(0, 8)  # a chunk of 8: one program of 8 rows, or 2 devices x 4 rows
s1 = sweep.run_rows(rows, spec, 8, devices=jax.local_devices()[:1])
s4 = sweep.run_rows(rows, spec, 8, devices=jax.local_devices())
res.update(sweep_cols=len(s1), sweep_differ=[k for k in s1 if not np.array_equal(s1[k], s4[k],
                                                                                equal_nan=s1[k].dtype.kind == "f")])
RESULT = res
"""


@pytest.mark.slow
def test_one_and_two_host_devices_give_bitwise_the_same_rollouts_and_sweep_rows(two_device_runs):
    res = two_device_runs("stepdown")
    assert res["qpos_shape"][0] == 18  # the 18 instances (3 passes of 8: 2 on 2 devices, then 1), the padding dropped
    assert res["n_leaves"] > 50 and res["rollout_differ"] == 0, res
    assert res["outcomes_differ"] == 0 and len(res["completed"]) == 18, res
    assert res["sweep_cols"] > 10 and res["sweep_differ"] == [], res
    # the rollout's program traced once for the one-device run and both devices of the split, compiled once per
    # device (device 0's program serves the one-device run and device 0's passes; JAX's trace and compile events)
    assert res["programs"]["traced advance"] == 1 and res["programs"]["compiled advance"] == N_DEVICES, res


TUNE_CODE = r"""
from hyqjax.studies.tune import forward, schedule
from hyqjax.crawl import controller as crawl

p = schedule.make("shared")
base = crawl.CrawlParams.make()
th0 = p.theta_of(base)
thetas = np.stack([th0, th0 + 0.3, th0 - 0.2])
sc = forward.train_scenarios(4, 3, 0)
res = {}
for d in (1, N):
    ev = forward.SuccessEvaluator(p, base, 0.4, "jax", devices=d)
    res[d] = ev(thetas, sc)
a, b = res[1], res[N]
RESULT = dict(
    fitness1=a["fitness"].tolist(), fitness4=b["fitness"].tolist(),
    columns_differ=[k for k in a["columns"] if not np.array_equal(a["columns"][k], b["columns"][k], equal_nan=True)],
    n_columns=len(a["columns"]),
    differs_between_members=not np.array_equal(b["columns"]["progress"][0], b["columns"]["progress"][1]),
    steps=[a["physics_steps"], b["physics_steps"]])
"""


@pytest.mark.slow
def test_tuner_generation_over_two_host_devices_gives_the_same_objective(two_device_runs):
    """One generation (3 members x 4 common scenarios) evaluated on 1 and on 2 host devices (the 12 rows as 2 passes of
    8, one on each device): the same fitness and the same per-row outcome columns."""
    res = two_device_runs("tuner")
    assert res["fitness1"] == res["fitness4"] and len(res["fitness1"]) == 3, res
    assert res["n_columns"] > 10 and res["columns_differ"] == [], res
    assert res["differs_between_members"] and res["steps"] == [3 * 4 * 200] * 2, res
    # the second evaluator (same parameterisation and configuration) reuses the first one's programs: one trace,
    # one compile per device
    assert res["programs"]["traced advance"] == 1 and res["programs"]["compiled advance"] == N_DEVICES, res


BOUND_CODE = r"""
from hyqjax.bounding import envelope as be

spec = be.EnvelopeSpec(speeds=(0.0, 0.5), yaw_rates=(0.3,), instances=5, friction=(0.7, 1.0), payload=(0.0, 5.0),
                       duration=0.8)
batch = spec.batch(None)
from hyqjax.bounding import tracking
c1 = tracking.run_batch(batch, spec.duration, "jax", devices=1)
c4 = tracking.run_batch(batch, spec.duration, "jax", devices=N)
RESULT = dict(n=int(len(c1["success"])), cols=len(c1),
    differ=[k for k in c1 if not np.array_equal(c1[k], c4[k], equal_nan=np.asarray(c1[k]).dtype.kind == "f")])
"""


@pytest.mark.slow
def test_bounding_envelope_batch_on_one_and_two_host_devices_is_the_same(two_device_runs):
    """The bounding envelope's batch (tracking.run_batch, MJX-JAX; 2 commands x 5 instances, 0.8 s: 2 passes of 8
    rows, one on each device) on 1 and on 2 host devices: every column equal."""
    res = two_device_runs("bound")
    assert res["n"] == 10 and res["cols"] > 10 and res["differ"] == [], res
    assert res["programs"]["traced advance"] == 1 and res["programs"]["compiled advance"] == N_DEVICES, res


#: The driver of the multi-device process: each part's code runs in its own namespace and leaves its ``RESULT``
#: (or its traceback), printed as one JSON line per part.
DRIVER = r"""
import collections, json, traceback
import numpy as np, jax
N = %d
assert len(jax.local_devices()) == N, jax.local_devices()
COUNTS = collections.Counter()  # (what, function name) -> times, from JAX's own events

def count(event, duration, **kw):
    what = {"/jax/core/compile/jaxpr_trace_duration": "traced",
            "/jax/core/compile/backend_compile_duration": "compiled"}.get(event)
    if what is not None:  # the function's name ("advance"; "jit(advance)" in the compile event)
        COUNTS[f"{what} {str(kw.get('fun_name')).removeprefix('jit(').removesuffix(')')}"] += 1

jax.monitoring.register_event_duration_secs_listener(count)
for name, code in %r:
    ns = dict(N=N, np=np, jax=jax, json=json)
    before = COUNTS.copy()
    try:
        exec(code, ns)
        ns["RESULT"]["programs"] = {k: v for k, v in (COUNTS - before).items() if k.split()[1] in ("init", "advance")}
        print("RESULT " + json.dumps(dict(part=name, result=ns["RESULT"])), flush=True)
    except Exception:
        print("RESULT " + json.dumps(dict(part=name, error=traceback.format_exc()[-3000:])), flush=True)
"""


@pytest.fixture(scope="module")
def two_device_runs():
    """The step-down, sweep, tuner and bounding parts run in one process with ``N_DEVICES`` XLA host devices;
    returns ``part -> its RESULT`` (a part that raised fails the test that reads it, with its traceback)."""
    parts = (("stepdown", CODE), ("tuner", TUNE_CODE), ("bound", BOUND_CODE))
    p = run_python(DRIVER % (N_DEVICES, parts), timeout=1800,
                   env={"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "")
                                      + f" --xla_force_host_platform_device_count={N_DEVICES}").strip()})
    got = {}
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            r = json.loads(line[7:])
            got[r["part"]] = r
    tail = p.stderr[-3000:]

    def result(part):
        assert part in got, f"rc {p.returncode}, no result of {part}: {tail}"
        assert "error" not in got[part], got[part]["error"]
        return got[part]["result"]

    return result
