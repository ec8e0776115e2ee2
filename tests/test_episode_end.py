"""A formerly divergent step-down, replayed on the CPU from its saved state: the actuators' velocity limit and the
episode end each keep it from diverging.

``tests/data/divergent_stepdown.npz`` is the closed-loop state (MJX data and the crawl's state) of a wide-spread step
-down (25 cm, payload 5.5 kg, shin remedy; docs/notes/stepdown.md, "Divergences") 34 ticks before it diverged, as the
crawl ran before ``CrawlParams.joint_speed_limit`` and the episode end existed: HyQ lies on its back after a fall,
and the trunk controller still distributes its weight over legs whose feet are in the air. One compiled program
replays 60 ticks for four instances of that state:

* without the speed limit and without the episode end (the old behaviour): a knee is driven by torques at the
  150 N m limit to 100 rad/s, the divergence bound;
* with the speed limit (the default), no episode end: every joint stays near its 12 rad/s limit;
* with the episode end (the robot has fallen: tilt past 0.4 rad), with and without the speed limit: the episode ends
  at the first tick, the instance is frozen there, nothing diverges.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np
import pytest

DATA = os.path.join(os.path.dirname(__file__), "data", "divergent_stepdown.npz")
TICKS = 60


@pytest.mark.slow
def test_formerly_divergent_step_down_no_longer_diverges():
    import jax
    import jax.numpy as jnp
    from mujoco import mjx

    from hyqjax.core import robot
    from hyqjax.crawl import controller as crawl
    from hyqjax.crawl.params import JOINT_SPEED_BAND
    from hyqjax.sim import model as hmodel
    from hyqjax.sim import rollout as sim
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    s = np.load(DATA)
    cfg = stepdown.StepdownConfig(impl="jax", duration=TICKS * 0.002)
    st = stepdown.setup(cfg)
    terrain = hmodel.InstanceTerrain.make(s["platform_height"], s["friction"], s["payload_mass"], s["payload_com"])
    mx = hmodel.instance_model(st.mx, st.ids, jax.tree_util.tree_map(lambda x: x[0], terrain))
    d = sim.initial_data(mx, jnp.asarray(s["qpos"]), m=st.m)
    d = d.replace(qvel=jnp.asarray(s["qvel"]), ctrl=jnp.asarray(s["ctrl"]), act=jnp.asarray(s["act"]),
                  qacc_warmstart=jnp.asarray(s["qacc_warmstart"]), time=jnp.asarray(s["time"]))
    controller = crawl.crawl_controller(cfg.control_dt)
    base = crawl.CrawlParams.make(shin_remedy=True)
    # The structure and dtypes of the crawl's state (abstract: nothing is compiled for it).
    template = jax.eval_shape(lambda dd: controller.init(base, sim.observe(st.ids, dd, dd.ctrl, mx)), d)
    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    # A field the crawl state gained after the file was saved (``loaded``) starts at zero (False), its initial value.
    cs = treedef.unflatten([jnp.asarray(s[f"cs/{jax.tree_util.keystr(k)}"], leaf.dtype) if f"cs/{jax.tree_util.keystr(k)}"
                            in s.files else jnp.zeros(leaf.shape, leaf.dtype) for k, leaf in paths])

    # One metrics state per instance: the step-down's, plus whether its episode may end (so one program runs both).
    base_metrics = so.make_metrics(st.ids, cfg.strike_force)
    metrics = sim.Metrics(lambda dd: (base_metrics.init(dd), jnp.array(False)),
                          lambda m, dd, o, i: (base_metrics.update(m[0], dd, o, i), m[1]),
                          lambda m: m[1] & so.fallen(m[0], cfg.max_tilt))
    limits = jnp.asarray([1000.0, robot.VELOCITY_LIMIT, robot.VELOCITY_LIMIT, 1000.0], jnp.float32)
    ends = jnp.asarray([False, False, True, True])
    params = jax.vmap(lambda v: dataclasses.replace(base, joint_speed_limit=v))(limits)

    def replay(p, end, d):
        d = mjx.forward(mx, d)  # the derived fields the first observation reads (in the replay's one program)
        carry = sim.RolloutCarry(d, cs, (base_metrics.init(d), end), d.ctrl, jnp.array(False), jnp.array(-1, jnp.int32),
                                 jnp.array(0, jnp.int32), jnp.array(False), jnp.array(-1, jnp.int32))
        carry = jax.tree_util.tree_map(lambda x: jax.lax.convert_element_type(x, jnp.result_type(x)), carry)
        c, trace = sim.rollout_advance(mx, st.ids, carry, controller, p, dataclasses.replace(cfg.sim_config(),
                                       record_every=1), TICKS, metrics, lambda dd, o, i: jnp.max(jnp.abs(dd.qvel[6:])))
        return c.diverged, c.diverged_tick, c.terminated, c.terminated_tick, trace

    # Compiled at XLA's backend optimisation level 0: the program runs 60 ticks, its compile is the test's cost.
    program = jax.jit(jax.vmap(replay, in_axes=(0, 0, None))).lower(params, ends, d).compile(
        compiler_options={"xla_backend_optimization_level": 0})
    div, div_tick, term, term_tick, speed = program(params, ends, d)
    div, term, speed = np.asarray(div), np.asarray(term), np.asarray(speed)
    # The old behaviour: a joint spun to the divergence bound (|qvel| >= 100) within the replay.
    assert div[0] and 0 < int(div_tick[0]) < TICKS and not term[0]
    # The actuators' velocity limit alone: no divergence, joint speeds near the limit (impacts may add a little).
    assert not div[1] and not term[1]
    assert speed[1].max() < robot.VELOCITY_LIMIT + JOINT_SPEED_BAND + 15.0, speed[1].max()
    # The episode end: the robot had fallen (upside down), its episode ends at the first tick and it stays frozen.
    for i in (2, 3):
        assert term[i] and int(term_tick[i]) == 0 and not div[i]
        assert np.all(speed[i] == speed[i][0])  # frozen at its failure tick
