"""Names whose code lives in a module of its own stay importable from the module that gathers them (fast lane):
``hyqjax.studies.tune.search`` (the clock, trace and selection beside the methods), ``hyqjax.sim.cpu_backend``
(the C MuJoCo backend's runner, models and host programs), ``hyqjax.bounding.params`` (the parameter classes and
the apex state beside the parameter sets), ``hyqjax.bounding.robust`` (the coordinates and the stored sets beside the
optimisers) and ``hyqjax.sim.runner`` (the batch buckets and the multi-device run beside the runner). Each name is the very object of its home, so a class check, a patched
class attribute or a shared registry (the runner's active batches) is one and the same through either path."""
from __future__ import annotations

import importlib

import pytest

#: (gathering module, home module, names defined in the home and importable from the gathering module)
HOMES = [
    ("hyqjax.studies.tune.search", "hyqjax.studies.tune.clock", ("Clock", "Charges", "COMPILE_EVENTS")),
    ("hyqjax.studies.tune.search", "hyqjax.studies.tune.selection", ("Selection", "final_choice")),
    ("hyqjax.studies.tune.search", "hyqjax.studies.tune.trace", ("Trace",)),
    ("hyqjax.sim.cpu_backend", "hyqjax.sim.cpu_runner",
     ("CBatchRunner", "MIN_SHARD_ROWS", "PHYSICS_TARGET", "_ACTIVE")),
    ("hyqjax.sim.cpu_backend", "hyqjax.sim.cpu_models", ("CInitialData", "batch_models", "prepare_model")),
    ("hyqjax.sim.cpu_backend", "hyqjax.sim.host_jit",
     ("COMPILER_OPTIONS", "compiler_options", "host_jit", "host_sharding")),
    ("hyqjax.bounding.params", "hyqjax.bounding.apex", ("Apex", "APEX_NAMES", "N_APEX")),
    ("hyqjax.bounding.params", "hyqjax.bounding.param_types",
     ("FRONT", "HIND", "LEG_PAIR", "LEG_SIDE", "PROFILES", "NOMINAL_FOOT_XY", "LATERAL_SPEED_LIMIT", "check_range",
      "check_field", "GaitParams", "BoundingGains", "Switches", "BoundingCommand", "BoundingParams")),
    ("hyqjax.bounding.robust", "hyqjax.bounding.robust_params",
     ("AMPLITUDE_NAMES", "COORDS", "FORMAT", "PRESETS", "load_params", "params_from_values", "preset_params",
      "preset_path", "save_params")),
    ("hyqjax.sim.runner", "hyqjax.sim.buckets", ("BatchPlan", "batch_plan", "bucket", "host_physics_plan", "pad_batch")),
    ("hyqjax.sim.runner", "hyqjax.sim.multidevice", ("run_on", "run_split", "RunnersByPlace", "run_tree_on", "batch_mesh")),
]


@pytest.mark.parametrize("gathering, home, names", HOMES, ids=[f"{g}<-{h}" for g, h, _ in HOMES])
def test_gathered_names_are_their_homes_objects(gathering, home, names):
    g, h = importlib.import_module(gathering), importlib.import_module(home)
    for name in names:
        assert getattr(g, name) is getattr(h, name), f"{gathering}.{name} is not {home}.{name}"
    defined = [n for n in names if getattr(getattr(h, n), "__module__", home) not in (home, None)
               and callable(getattr(h, n))]
    assert not defined, f"{home} imports {defined} from elsewhere: not their home"


def test_c_backend_warnings_keep_the_backend_logger():
    """MuJoCo's warnings while a C batch runs go to the ``hyqjax.sim.cpu_backend`` logger, the one the backend's
    documentation names, though the runner that routes them has a module of its own."""
    from hyqjax.sim import cpu_runner

    assert cpu_runner.log.name == "hyqjax.sim.cpu_backend"
