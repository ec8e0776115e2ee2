"""The examples of docs/api.md, run as written (public names only), with checks of what they compute: a batch step-down
with per-instance reflex parameters, and the forward-mode gradient of a closed-loop metric with respect to K_base
and the reflex's damping bounds against central finite differences (float64); a bounding batch (the batch runner
against the single-instance rollout under vmap, and against the same batch on C MuJoCo), the forward-mode derivative
of the bound's final speed with respect to the commanded speed against central finite differences (float64), and the
retrace guard of the bounding rollout."""
from __future__ import annotations

import dataclasses
import os
import re
import sys

import jax
import numpy as np
import pytest

from conftest import REPO_ROOT

DOC = os.path.join(REPO_ROOT, "docs", "api.md")


def _doc_blocks() -> list[str]:
    with open(DOC) as f:
        return re.findall(r"```python\n(.*?)```", f.read(), flags=re.S)


def _run_block(i: int) -> dict:
    ns: dict = {}
    exec(compile(_doc_blocks()[i], f"docs/api.md block {i}", "exec"), ns)
    return ns


def test_examples_use_public_names_only():
    blocks = _doc_blocks()
    assert len(blocks) == 4
    for code in blocks:
        assert not re.search(r"\b_[a-z]\w*", code), "a private name in docs/api.md"
        assert "from hyqjax." not in code and "hyqjax._" not in code


@pytest.mark.slow
def test_public_api_is_reexported_lazily():
    from conftest import run_python

    r = run_python("""
    import sys, hyqjax
    assert "jax" not in sys.modules
    for name in hyqjax.__all__:
        getattr(hyqjax, name)
    print("OK", len(hyqjax.__all__))
    """, timeout=300)
    assert r.returncode == 0 and "OK" in r.stdout, r.stderr[-2000:]


@pytest.mark.slow
def test_batch_with_per_instance_reflex_params(capsys):
    ns = _run_block(0)
    out, res, params, n = ns["outcome"], ns["result"], ns["params"], ns["n"]
    assert n == 4 and out.completed.shape == (4,) and res.data.qpos.shape == (4, 19)
    np.testing.assert_allclose(np.asarray(params.reflex.k_base), np.linspace(1000.0, 2500.0, 4))
    np.testing.assert_allclose(np.asarray(res.ctrl_state.q_cmd).shape, (4, 12))
    # 2 s of crawling (two body phases and swings): no instance diverged or tilted, each moved forward.
    assert not np.any(np.asarray(out.diverged)) and not np.any(np.asarray(out.tilt))
    assert np.all(np.asarray(out.progress) > 0.0) and np.all(np.asarray(out.n_touchdowns) >= 1)
    # The same instance run alone through the single-instance function gives the batch's row.
    import hyqjax

    rollout = hyqjax.make_stepdown_rollout(ns["cfg"])
    i = 3
    one = ns["scenario"].replace(params=params).instance(i)
    single, final = jax.jit(rollout)(jax.tree_util.tree_map(lambda x: x[i], params), one)
    np.testing.assert_allclose(np.asarray(final.qpos), np.asarray(res.data.qpos[i]), atol=1e-3)
    assert float(single.peak_pitch) == pytest.approx(float(out.peak_pitch[i]), abs=1e-3)
    # Compile once: the same static config gives the same rollout, and a batch of new parameter values (same
    # shapes) reuses the compiled programs of the runner.
    assert rollout is hyqjax.make_stepdown_rollout(hyqjax.StepdownConfig(duration=2.0))
    compiled = rollout.runner().n_compiles
    assert compiled >= 1
    params2 = hyqjax.batch_params(hyqjax.CrawlParams.make(), n, use_reflex=1.0, reflex=dict(k_base=np.full(n, 1800.0)))
    out2, _ = rollout.run(ns["scenario"].replace(params=params2))
    assert rollout.runner().n_compiles == compiled, "a batch with new parameter values compiled again"
    assert out2.completed.shape == (4,) and not np.array_equal(np.asarray(out2.peak_pitch), np.asarray(out.peak_pitch))


@pytest.mark.slow
def test_gradient_wrt_k_base_and_damping_bounds_matches_finite_differences():
    with jax.enable_x64(True):
        ns = _run_block(1)
        f, x0, g = ns["trunk_height"], np.asarray(ns["x0"]), np.asarray(ns["dz_dx"])
        rel = 0.01  # central differences with steps of 1% of each parameter
        steps = rel * x0
        # Of the three parameters checked below (K_base and the stance-damping bounds): 6 rollouts, not 10.
        k = 3
        xs = np.concatenate([x0 + np.diag(steps)[:k], x0 - np.diag(steps)[:k]])
        one = jax.jit(f)  # one rollout a call: traced and compiled in less time than a batch of six
        vals = np.asarray([one(jax.numpy.asarray(x)) for x in xs])
        fd = (vals[:k] - vals[k:]) / (2 * steps[:k])
    sys.stdout.write(f"jacfwd {g}\nfinite differences {fd}\n")
    assert np.all(np.isfinite(g))
    scale = np.abs(g * x0).max()  # the largest effect of a relative change of a parameter
    assert scale > 1e-6, f"metric insensitive to the reflex parameters: {g}"
    # K_base and the stance-damping bounds: within 2% (measured: 0.4% or better). The swing-damping bounds do
    # not match at 1% steps (docs/api.md gives the numbers); only their finiteness is checked here.
    np.testing.assert_allclose(g[:3], fd[:3], rtol=0.02)
    assert abs(g[0] * x0[0]) > 1e-5  # K_base moves the trunk height by more than 10 um per unit log-change


COMPILES: list[str] = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, **kw: COMPILES.append(name) if name == "/jax/core/compile/backend_compile_duration" else None)


def test_bounding_rollout_config_names_the_bad_setting():
    import hyqjax
    from hyqjax.bounding.batch import SettingError

    for kwargs, name in ((dict(duration=0.0), "duration"), (dict(duration=float("nan")), "duration"),
                         (dict(duration=601.0), "duration"), (dict(control_dt=0.05), "control_dt"),
                         (dict(record_every=-1), "record_every"), (dict(record_every=2.0), "record_every"),
                         (dict(impl="cuda"), "impl"), (dict(duration=0.8, record_every=3), "record_every"),
                         (dict(duration=0.8011), "duration")):
        with pytest.raises(SettingError, match=name) as e:
            hyqjax.BoundingRolloutConfig(**kwargs)
        assert e.value.name == name
    cfg = hyqjax.BoundingRolloutConfig(duration=1.0)
    assert hash(cfg) == hash(hyqjax.BoundingRolloutConfig(duration=1.0))
    with pytest.raises(SettingError, match="multiple of the gait period 0.4"):
        cfg.check_period(0.4)  # 1.0 s is 2.5 periods
    with pytest.raises(SettingError, match="share the gait period"):
        cfg.check_period([0.5, 0.25])
    hyqjax.BoundingRolloutConfig(duration=1.2, record_every=10).check_period(np.full(3, 0.4))


@pytest.mark.slow
def test_bounding_batch_equals_single_instance_rollout_under_vmap():
    import hyqjax

    ns = _run_block(2)
    out, res, batch, rollout = ns["outcome"], ns["result"], ns["batch"], ns["rollout"]
    assert out.fell.shape == (2,) and res.data.qpos.shape == (2, 19) and res.trace is None
    # 0.8 s from a randomised apex state: both bound on, neither fell nor diverged.
    assert not np.any(np.asarray(out.fell)) and not np.any(np.asarray(out.diverged))
    assert np.all(np.asarray(out.min_z) > 0.45) and np.all(np.asarray(out.fall_tick) == -1)
    one, final = jax.jit(jax.vmap(rollout))(*hyqjax.bounding.instance_args(batch))
    np.testing.assert_array_equal(np.asarray(one.fell), np.asarray(out.fell))
    np.testing.assert_allclose(np.asarray(one.min_z), np.asarray(out.min_z), atol=1e-5)
    np.testing.assert_allclose(np.asarray(one.final_speed), np.asarray(out.final_speed), atol=1e-4)
    np.testing.assert_allclose(np.asarray(final.qpos), np.asarray(res.data.qpos), atol=1e-4)
    # The final position is the final data's; the heading stays near its start (yaw rates of 0.05 rad/s).
    assert np.all(np.abs(np.asarray(out.final_yaw)) < 0.2)
    np.testing.assert_allclose(np.asarray(out.final_position), np.asarray(res.data.qpos[:, :3]))


@pytest.mark.slow
def test_bounding_final_speed_derivative_wrt_command_matches_finite_differences():
    """Block 3 in a fresh float64 process (``JAX_ENABLE_X64=1``): jax's scoped ``enable_x64`` after float32 traces
    of the same code in one process reuses their int32 index constants (jax-ml/jax#11092: enable x64 at start)."""
    from conftest import run_python

    r = run_python(f"""
    import json
    import hyqjax
    import jax
    import numpy as np
    assert jax.config.jax_enable_x64
    ns = {{}}
    exec(compile({_doc_blocks()[3]!r}, "docs/api.md block 3", "exec"), ns)
    f, dv = ns["speed_and_slope"], float(ns["dv"])
    h = 0.005  # 1% of the commanded 0.5 m/s
    # The speeds at 0.5 +- h from the block's own compiled program (the same signature: no second compile).
    (up, _), (down, _) = f(0.5 + h), f(0.5 - h)
    out = dict(dv=dv, fd=(float(up) - float(down)) / (2 * h), dtype=str(ns["rollout"].setup.mx.qpos0.dtype),
               speed_dtype=str(up.dtype), speed=float(ns["speed"]), up=float(up), down=float(down),
               compiled=f._cache_size())
    print("RESULT", json.dumps(out))
    """, timeout=900, env={"JAX_ENABLE_X64": "1"})
    lines = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
    assert r.returncode == 0 and lines, r.stderr[-3000:]
    import json

    res = json.loads(lines[-1][len("RESULT "):])
    mid = abs(res["speed"] - (res["up"] + res["down"]) / 2) / abs(res["up"] - res["down"])
    sys.stdout.write(f"jvp {res['dv']}\nfinite differences {res['fd']}\nvalue against its neighbours' mean {mid}\n")
    assert res["dtype"] == "float64" and res["speed_dtype"] == "float64", res
    assert res["compiled"] == 1, res  # one program for the value, the derivative and both differences
    # The value that comes with the derivative is the rollout's at 0.5: the mean of its neighbours at +-h, up to
    # the curvature term (measured: 3.8e-5 of the difference between them).
    assert mid <= 0.01, res
    assert np.isfinite(res["dv"]) and abs(res["dv"]) > 1e-3, res  # the command moves the final speed
    np.testing.assert_allclose(res["dv"], res["fd"], rtol=1e-3)  # measured: 1e-8 (the gait's phases follow the clock)


@pytest.mark.slow
def test_bounding_rollout_is_cached_and_a_new_batch_compiles_nothing():
    import hyqjax

    ns = _run_block(2)
    rollout, cfg = ns["rollout"], ns["cfg"]
    assert rollout is hyqjax.make_bounding_rollout(hyqjax.BoundingRolloutConfig(duration=0.8, impl="jax"))
    assert rollout is hyqjax.make_bounding_rollout(cfg)
    compiled = rollout.runner().n_compiles
    assert compiled >= 1
    # New parameter values (same shapes): commanded speeds and a gain, new randomisation.
    plist = [hyqjax.bounding.default_params(speed=s, k_roll=500.0) for s in (0.3, 0.7)]
    batch2 = hyqjax.bounding.make_batch(plist, seed=1)
    compiles = len(COMPILES)
    out2, _ = rollout.run(batch2)
    assert rollout.runner().n_compiles == compiled, "a batch with new parameter values traced the runner again"
    assert len(COMPILES) == compiles, f"a batch with new parameter values compiled {len(COMPILES) - compiles} programs"
    assert not np.array_equal(np.asarray(out2.final_speed), np.asarray(ns["outcome"].final_speed))


@pytest.mark.slow
def test_bounding_batch_on_c_mujoco_follows_mjx():
    """Block 2's batch (in place and 0.5 m/s, 0.8 s from the air) on C MuJoCo (float64; the controller compiled in
    JAX) against MJX-JAX (float32): the same outcome flags, and the final states, lowest trunk heights, largest
    angles and final speeds close (measured: trunk position 2.2 mm, joints 0.010 rad, lowest height 2.8 mm, final
    speed 5.5 mm/s, angles 1.2 mrad; impacts amplify float32 rounding). C MuJoCo refuses the one-instance rollout
    (batches only)."""
    import hyqjax

    ns = _run_block(2)
    out_j, res_j, cfg = ns["outcome"], ns["result"], ns["cfg"]
    out_c, res_c = hyqjax.make_bounding_rollout(dataclasses.replace(cfg, impl="c")).run(ns["batch"])
    for k in ("fell", "low_trunk", "roll", "pitch", "diverged"):
        np.testing.assert_array_equal(np.asarray(getattr(out_c, k)), np.asarray(getattr(out_j, k)), err_msg=k)
    q_c, q_j = np.asarray(res_c.data.qpos), np.asarray(res_j.data.qpos)
    np.testing.assert_allclose(q_c[:, :3], q_j[:, :3], atol=0.01)
    np.testing.assert_allclose(q_c[:, 3:7], q_j[:, 3:7], atol=0.005)
    np.testing.assert_allclose(q_c[:, 7:], q_j[:, 7:], atol=0.03)
    np.testing.assert_allclose(np.asarray(out_c.min_z), np.asarray(out_j.min_z), atol=0.01)
    np.testing.assert_allclose(np.asarray(out_c.final_speed), np.asarray(out_j.final_speed), atol=0.02)
    for k in ("max_roll", "max_pitch"):
        np.testing.assert_allclose(np.asarray(getattr(out_c, k)), np.asarray(getattr(out_j, k)), atol=0.005,
                                   err_msg=k)
    assert res_c.data.qpos.dtype == res_j.data.qpos.dtype  # the view is in JAX's float width on both
    one = jax.tree_util.tree_map(lambda x: x[0], hyqjax.bounding.instance_args(ns["batch"]))
    with pytest.raises(ValueError, match="one-instance rollout needs impl='jax'"):  # C MuJoCo runs batches only
        hyqjax.make_bounding_rollout(dataclasses.replace(cfg, impl="c"))(*one)


def _resolve(dotted: str):
    import importlib

    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for name in parts[i:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(dotted)


@pytest.mark.slow
def test_docs_name_objects_that_exist_and_k_base_enters_eq6_where_they_say():
    """Every ``module.name`` that docs/architecture.md and docs/api.md mention exists (the docs follow the code),
    and the one hop from the public API to Eq. 6 holds: ``hyqjax.ReflexParams.k_base`` is read by
    ``hyqjax.reflex.forces.distribute_virtual_forces`` as the base moment ``m = -K_base e_b``."""
    import dataclasses
    import inspect

    import hyqjax

    text = "".join(open(os.path.join(REPO_ROOT, "docs", n)).read() for n in ("architecture.md", "api.md"))
    pkgs = "core|sim|control|reflex|crawl|bounding|studies|io"
    dotted = set(re.findall(rf"(?<![\w/.])((?:hyqjax\.)?(?:{pkgs})\.[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)", text))
    dotted |= set(re.findall(r"(?<![\w/.])(hyqjax\.[A-Z]\w*(?:\.[A-Za-z_]\w*)*)", text))
    assert len(dotted) >= 15
    missing = []
    for d in sorted(dotted):
        d = d.rstrip(".")
        try:
            _resolve(d if d.startswith("hyqjax") else "hyqjax." + d)
        except (ImportError, AttributeError):
            missing.append(d)
    assert not missing, f"the docs name objects that do not exist: {missing}"
    assert "where k_base enters eq. 6" in text.replace("`", "").lower()
    assert "k_base" in {f.name for f in dataclasses.fields(hyqjax.ReflexParams)}
    source = inspect.getsource(_resolve("hyqjax.reflex.forces.distribute_virtual_forces"))
    assert re.search(r"moment = -_vec3\(params\.k_base, dtype\) \* jnp\.asarray\(e_b, dtype\)", source)
