"""Tuning (hyqjax.studies.tune): parameter space, kinematic surrogate, Adam with resume, baselines' budgets,
and the closed-loop objective through MJX (gradient vs central differences; a few steps lower it)."""
from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from hyqjax.crawl import controller as crawl
from hyqjax.reflex import step as hreflex
from hyqjax.studies.tune import objective, optimize, windows
from hyqjax.studies.tune.study import baselines, kinematic, gradient as study
from hyqjax.studies.tune import space as spmod

SMALL_KIN = kinematic.Objective(duration=0.5, t_lift=0.05, lift=0.02)

#: Names of the functions jax traced (for the closed-loop tuner step's retrace guard).
TRACED: list[str] = []
jax.monitoring.register_event_duration_secs_listener(
    lambda name, secs, fun_name=None, **kw: TRACED.append(fun_name) if name == "/jax/core/compile/jaxpr_trace_duration"
    else None)


def test_space_roundtrip_and_always_valid():
    sp = spmod.ParamSpace.make(tuple(spmod.GROUPS))
    th0 = spmod.table1_theta(sp)
    vals = sp.describe(th0)
    t1 = hreflex.ReflexParams.table1()
    for k in ("k_base", "d_sw_min", "d_sw_max", "d_st_min", "d_st_max", "m_min", "m_max", "k_x", "delta", "k_kl"):
        assert vals[k] == pytest.approx(float(getattr(t1, k)), rel=1e-5), k
    assert vals["body_height"] == pytest.approx(0.56, rel=1e-5)
    rng = np.random.default_rng(1)
    for _ in range(20):
        p = sp.concrete(th0 + 3.0 * rng.standard_normal(sp.size))  # validates the reflex parameters
        crawl.CrawlParams.make(body_height=float(p.body_height), max_step_length=float(p.max_step_length),
                               step_height=float(p.step_height), search_speed=float(p.search_speed))
        assert float(p.reflex.m_max) < spmod.M_NOMINAL
    # Far out, where float32's sigmoid rounds to 0 or 1: the damping maxima stay above their minima and m_min
    # below m_max (a search that wandered there once stopped with "d_sw_min=93.963 must be < d_sw_max=93.963").
    for far in (-120.0, 120.0):
        th = th0.copy()
        th[[i for i, c in enumerate(sp.coords) if c.kind in ("gap", "ratio")]] = far
        v = sp.describe(th)
        assert v["d_sw_min"] < v["d_sw_max"] and v["d_st_min"] < v["d_st_max"] and v["m_min"] < v["m_max"], v
        sp.concrete(th)
    from hyqjax.core.params import param_ranges

    ranges = {"reflex": param_ranges(hreflex.ReflexParams), "crawl": param_ranges(crawl.CrawlParams)}
    for c in sp.coords:
        if c.kind in ("log", "box"):
            eps = 1e-9 * max(1.0, c.hi)  # sigmoid maps onto the open interval
            assert ranges[c.owner][c.name].in_range(np.asarray([c.lo + eps, c.hi - eps])).all(), c.name


@pytest.mark.slow
def test_kinematic_gradient_matches_central_differences(x64):
    sp = spmod.ParamSpace.make(("k_base", "damping", "mobility", "k_x", "delta", "k_kl"))
    sc = kinematic.make_scenarios(2, 5, depth=(0.02, 0.05), dtype=jnp.float64)
    base = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating)
                                  else x, crawl.CrawlParams.make())
    th = jnp.asarray(spmod.table1_theta(sp))
    th = th.at[sp.names.index("m_max")].add(-0.3)  # inside the schedule's transition band
    f = kinematic.make_value_and_grad(sp, sc, SMALL_KIN, base)
    g = np.asarray(f(th)["grad"])
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    rng = np.random.default_rng(0)
    for _ in range(2):
        v = rng.standard_normal(sp.size)
        eps = 1e-5
        fd = (float(f(th + eps * v)["loss"]) - float(f(th - eps * v)["loss"])) / (2 * eps)
        assert float(g @ v) == pytest.approx(fd, rel=1e-4, abs=1e-8)


@pytest.fixture(scope="module")
def kin_runs(tmp_path_factory):
    sp = spmod.ParamSpace.make(("k_base", "damping", "mobility"))
    sc = kinematic.make_scenarios(3, 0, depth=(0.02, 0.06))
    f = kinematic.make_value_and_grad(sp, sc, SMALL_KIN, crawl.CrawlParams.make())
    th0 = jnp.asarray(spmod.table1_theta(sp), jnp.float32)
    cfg = optimize.AdamConfig(steps=4, lr=0.1, checkpoint_every=2)
    conf = dict(kind="test")
    full, part = (str(tmp_path_factory.mktemp(n)) for n in ("full", "part"))
    r_full = optimize.run_adam(f, th0, cfg, full, conf, 7, sp.describe, progress=False)
    r_part = optimize.run_adam(f, th0, cfg, part, conf, 7, sp.describe, stop_after=2, progress=False)
    assert r_part["step"] == 2
    r_res = optimize.run_adam(f, th0, cfg, part, conf, 7, sp.describe, progress=False)
    return f, th0, cfg, conf, full, part, r_full, r_res, sp


@pytest.mark.slow
def test_adam_lowers_loss_logs_and_counts_budget(kin_runs):
    _, _, _, _, full, _, r_full, _, _ = kin_runs
    log = optimize.read_log(full)
    assert [r["step"] for r in log] == [0, 1, 2, 3]
    assert log[-1]["loss"] < log[0]["loss"]
    assert [r["spent"] for r in log] == [7, 14, 21, 28] and r_full["spent"] == 28
    assert all(np.isfinite(r["grad_norm"]) and r["grad_norm"] > 0 for r in log)
    assert log[0]["params"]["k_base"] == pytest.approx(1500.0, rel=1e-5)
    assert os.path.exists(os.path.join(full, "checkpoint.npz"))
    with open(os.path.join(full, "config.json")) as fh:
        assert json.load(fh)["config"] == dict(kind="test")


@pytest.mark.slow
def test_resume_matches_uninterrupted_and_refuses_other_config(kin_runs):
    f, th0, cfg, conf, _, part, r_full, r_res, sp = kin_runs
    assert r_res["step"] == 4
    np.testing.assert_allclose(r_res["theta"], r_full["theta"], rtol=1e-6)
    assert [r["step"] for r in optimize.read_log(part)] == [0, 1, 2, 3]
    with pytest.raises(RuntimeError, match="another configuration"):
        optimize.run_adam(f, th0, optimize.AdamConfig(steps=4, lr=0.2), part, dict(kind="other"), 7, progress=False)


@pytest.mark.slow
def test_baselines_respect_budget_and_improve():
    target = np.array([1.0, -2.0, 0.5])
    calls = []

    def f_pop(xs):
        calls.append(len(xs))
        return np.sum((np.asarray(xs) - target) ** 2, 1)

    x0 = np.zeros(3)
    cma = baselines.cma_es(f_pop, x0, budget=600, cost_per_eval=10, sigma=0.5, popsize=6, seed=0)
    assert cma["budget_spent"] <= 600 and sum(calls) * 10 == cma["budget_spent"]
    assert cma["value"] < 0.1 * float(np.sum(target ** 2))  # 10 generations of 6 (evosax CMA_ES)
    best = [h["best"] for h in cma["history"]]
    assert all(b <= a for a, b in zip(best, best[1:]))
    calls.clear()
    rs = baselines.random_search(f_pop, x0, budget=600, cost_per_eval=10, sigma=0.5, chunk=16, seed=0)
    assert rs["budget_spent"] == 600 and rs["evaluations"] == 60
    assert rs["value"] < float(np.sum(target ** 2))


@pytest.mark.parametrize("kw, match", [(dict(objective="fancy"), "objective must be"),
                                       (dict(groups=("k_base", "spring")), "groups must be"),
                                       (dict(baselines=("pso",)), "baselines must be"),
                                       (dict(train_heights=(0.6,)), "train_heights"),
                                       (dict(heldout=-1), "heldout must be")])
def test_study_config_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        study.StudyConfig(**kw)


def test_objective_and_window_validation():
    with pytest.raises(ValueError, match="ticks must be"):
        objective.ClosedLoopObjective(ticks=0)
    with pytest.raises(ValueError, match="prefixes must be"):
        objective.ClosedLoopObjective(ticks=10, prefixes=(20,))
    with pytest.raises(ValueError, match="offset must be"):
        windows.WindowSpec(offset=-1)


def test_cli_bad_input_is_one_line():
    from conftest import run_python

    p = run_python("from hyqjax.cli.app import main; raise SystemExit(main(['tune', '--groups', 'k_base,spring']))", timeout=120)
    assert p.returncode != 0 and "Traceback" not in p.stderr
    assert "groups must be" in p.stderr.strip().splitlines()[-1]


# ------------------------------------------------------------------ closed loop through MJX (CPU, slow)


@pytest.fixture(scope="module")
def su64():
    """The step-down's float64 window setup (model, ids, contact slots), shared by this module's window tests."""
    with jax.enable_x64(True):
        return windows.setup(dtype="float64")


@pytest.fixture(scope="module")
def cl64(su64):
    """Float64 windows of one 24 cm step-down with the shin-strike remedy (what ``hyqjax tune`` tunes), both front
    legs' snapshots, and the jitted per-robot jacfwd objective (``objective.make_per_robot_value_and_jac``) of two
    robots with one window each (``wins``: two copies of the window that runs from just before the first front
    leg's swing is planned into its haptic search over the edge, where the tuned search direction acts), through
    the crawl that the shared parameterisation of the five groups schedules (``schedule.Parameterisation("shared",
    sp)``: the tuner's forward-mode step; its ``theta`` is ``sp``'s). Built under x64 and returned outside it: the
    tests turn x64 on where they use them (yielded inside ``enable_x64``, the fixture left x64 on for every later
    test of this module)."""
    from hyqjax.studies.tune import schedule

    su = su64
    with jax.enable_x64(True):
        from hyqjax.studies.tune import evaluate

        start = crawl.CrawlParams.make(shin_remedy=True)
        sc, _ = evaluate.scenarios([0.24], 1, 3, params=start)
        both = windows.make_windows(sc, windows.WindowSpec(per_scenario=2, lead=6.0, offset=190), su)
        win = both.take([0])
        sp = spmod.ParamSpace.make(("k_base", "damping", "body_height", "search_forward", "terrain_adaptation"))
        base = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if jnp.issubdtype(
            jnp.asarray(x).dtype, jnp.floating) else x, start)
        obj = objective.ClosedLoopObjective(ticks=260)
        wins, axes = windows.grouped(win.take([0, 0]), 2)
        pr = objective.make_per_robot_value_and_jac(base, schedule.Parameterisation("shared", sp), obj, su, axes)
    return win, sp, pr, wins, base, obj, both


@pytest.fixture(scope="module")
def pr_start(cl64):
    """``theta`` at the start point and the per-robot program's first call there, both front legs' windows as its
    two robots (robot 0 the first window, robot 1 the second; numpy)."""
    _, sp, pr, _, base, _, both = cl64
    with jax.enable_x64(True):
        th = np.asarray(sp.theta_of(base), np.float64)
        r = pr(jnp.asarray(np.stack([th, th])), windows.grouped(both, 2)[0])
        return th, jax.tree_util.tree_map(np.asarray, r)


@pytest.fixture(scope="module")
def fwd64(cl64, su64):
    """Forward evaluation alone (no derivative program) of both windows of ``cl64`` under the per-leg crawl of the
    five groups with ``K_base`` conditioned on the three features (``par``, 35 coordinates), 260 ticks and the
    130-tick prefix: ``central(theta, dirs)`` evaluates ``theta`` and ``theta +- 1e-6 dirs`` (8 directions) in one
    call of one compiled program and returns the central differences of every window's prefix losses
    ``(8, W, 2)`` and the evaluation at ``theta`` (per-window ``loss``, ``terms``, ``finite``). ``per_leg(x)``: the
    shared parameterisation's ``x`` as ``par``'s (every leg's row ``x``, no conditioning: the same crawl)."""
    from hyqjax.studies.tune import schedule

    _, sp, _, _, base, _, both = cl64
    par = schedule.Parameterisation("per_leg", sp, per_leg=True, conditioned=("k_base",))
    obj = objective.ClosedLoopObjective(ticks=260, prefixes=(130,))
    eps = 1e-6

    @jax.jit
    def evaluate(ths, win):
        def one(th):
            loss, terms, finite = objective.window_losses(th, win, base, par, obj, su64)
            return dict(loss=loss, terms=terms, finite=finite)

        return jax.vmap(one)(ths)

    def central(theta, dirs):
        dirs = np.asarray(dirs, np.float64)
        assert dirs.shape == (8, par.size)  # one batch size, one program
        with jax.enable_x64(True):
            out = jax.tree_util.tree_map(np.asarray, evaluate(jnp.asarray(np.concatenate(
                [np.asarray(theta, np.float64)[None], theta + eps * dirs, theta - eps * dirs])), both))
        pre = out["terms"]["prefix_loss"]
        return (pre[1:9] - pre[9:]) / (2 * eps), jax.tree_util.tree_map(lambda x: x[0], out)

    def per_leg(x):
        return np.concatenate([np.tile(np.asarray(x, np.float64), 4), np.zeros(par.size - 4 * sp.size)])

    from types import SimpleNamespace

    return SimpleNamespace(par=par, obj=obj, central=central, per_leg=per_leg)


@pytest.mark.slow
def test_windows_follow_the_remedy_leg_order(cl64, su64):
    """With the remedy the other front leg swings right after the first one stepped down: both front legs get
    a window (RF first in this scenario's rh-rf-lh-lf cycle, then LF brought forward)."""
    both = cl64[-1]
    su = su64
    # The terrain contact slots (read from the collision pass alone): every slot pairs its own geom with the floor or
    # the platform, and every foot, shin and the trunk has its slots.
    terrain = {su.ids.floor_geom, su.ids.platform_geom}
    with jax.enable_x64(True):
        geom = np.asarray(jax.jit(mjx.collision)(su.mx, mjx.make_data(su.mx))._impl.contact.geom)
    for rows, own in [(su.slots.trunk, [su.ids.trunk_geom]), (su.slots.shin, su.ids.shin_geoms),
                      *((f, [g]) for f, g in zip(su.slots.feet, su.ids.foot_geoms))]:
        assert len(rows) > 0
        assert all(set(geom[r]) & terrain and set(geom[r]) & set(own) for r in rows)
    assert np.asarray(both.valid).all()
    assert np.asarray(both.leg).tolist() == [1, 0]
    assert int(both.tick[1]) > int(both.tick[0])


@pytest.mark.slow
def test_windows_retaken_under_a_parameterised_crawl(cl64, su64):
    """Windows re-taken at an iterate (``make_windows(..., param=, theta=)``, the hybrid's ``--retake-windows``)
    are the windows of the plain crawl run with that iterate's parameters, and differ from the start point's."""
    from hyqjax.studies.tune import evaluate, schedule

    _, sp, _, _, base, _, both = cl64
    su = su64
    with jax.enable_x64(True):
        th = np.asarray(sp.theta_of(base))
        th[sp.names.index("body_height")] -= 1.0  # a lower trunk: another gait, other snapshot states
        spec = windows.WindowSpec(per_scenario=2, lead=6.0, offset=190)
        sc0, _ = evaluate.scenarios([0.24], 1, 3, params=base)
        programs = windows._capture_batch._cache_size()
        retaken = windows.make_windows(sc0, spec, su, param=schedule.Parameterisation("shared", sp), theta=th)
        sc1, _ = evaluate.scenarios([0.24], 1, 3, params=sp.crawl_params(jnp.asarray(th), base))
        plain = windows.make_windows(sc1, spec, su)
        # one new program (the scheduled crawl's): the plain crawl with other values reuses the fixture's
        assert windows._capture_batch._cache_size() == programs + 1
    assert np.asarray(retaken.valid).all()
    for a, b in ((retaken.leg, plain.leg), (retaken.tick, plain.tick)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(retaken.data.qpos), np.asarray(plain.data.qpos), rtol=0, atol=1e-9)
    for a, b in zip(jax.tree_util.tree_leaves(retaken.ctrl), jax.tree_util.tree_leaves(plain.ctrl)):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(b, np.float64), rtol=0, atol=1e-9)
    moved = np.abs(np.asarray(retaken.data.qpos) - np.asarray(both.data.qpos)).max()
    assert moved > 1e-3 or not np.array_equal(np.asarray(retaken.tick), np.asarray(both.tick)), moved


@pytest.mark.slow
def test_closed_loop_gradient_matches_central_differences_per_robot(cl64, pr_start, fwd64):
    """The closed-loop window objective's jacfwd (the per-robot program; each robot on one front leg's window)
    against central differences of the objective's forward evaluation (``fwd64`` with every leg's row the robot's
    ``theta``: the same crawl, the same losses to 1e-12), for both robots along two random directions and along six
    coordinates alone, the remedy's forward search among them (its gradient is not zero); per robot: each robot's
    loss and gradient depend on its own parameters and window only (a robot keeps its row when the other robot
    takes other parameters and another window and the two swap slots), and the step with new parameter values and
    other windows reuses its program."""
    win, sp, pr, wins, base, _, _ = cl64
    th, r = pr_start
    with jax.enable_x64(True):
        assert bool(win.valid[0])
        traced = TRACED.count(pr.__name__)
        g = r["grad"][0]
        assert np.all(np.isfinite(r["grad"])) and np.any(g != 0)
        assert abs(g[sp.names.index("search_forward")]) > 1e-7  # it moves the searching foot
        rng = np.random.default_rng(0)
        axes = [sp.names.index(n) for n in ("search_forward", "k_base", "d_sw_max", "d_st_min", "d_st_max",
                                            "body_height")]
        dirs = np.concatenate([rng.standard_normal((2, sp.size)), np.eye(sp.size)[axes]])
        fd, at = fwd64.central(fwd64.per_leg(th), np.stack([fwd64.per_leg(v) for v in dirs]))
        np.testing.assert_allclose(at["loss"], r["loss"], rtol=1e-12)
        for robot in (0, 1):  # robot r on window r, its whole length
            for v, d in zip(dirs, fd[:, robot, -1]):
                assert float(r["grad"][robot] @ v) == pytest.approx(float(d), rel=2e-3, abs=1e-10), (robot, v)
        # Per robot: robot 1 at theta on the first window, next to theta - 0.3 on it, has robot 0's row of the first
        # call (next to theta on the second window).
        moved = jax.tree_util.tree_map(np.asarray, pr(jnp.asarray(np.stack([th - 0.3, th])), wins))
        np.testing.assert_allclose(moved["loss"][1], r["loss"][0], rtol=1e-9)
        np.testing.assert_allclose(moved["grad"][1], g, rtol=1e-6, atol=1e-12)
        assert not np.allclose(moved["grad"][0], g) and not np.allclose(r["grad"][0], r["grad"][1])
        # Retrace guard: the tuner step with new values of theta (and other windows) reuses its program.
        assert TRACED.count(pr.__name__) == traced, "the closed-loop tuner step was traced again"


@pytest.mark.slow
def test_closed_loop_gradient_steps_lower_objective(cl64, pr_start):
    """Two normalised gradient steps with backtracking (length 0.5, quartered until the objective falls) from the
    start point each lower the closed-loop objective; the program's two robots try a length and its quarter in
    one call."""
    _, _, pr, wins, _, _, _ = cl64
    th, r = pr_start
    losses, g = [float(r["loss"][0])], r["grad"][0]
    with jax.enable_x64(True):
        for _ in range(2):
            d, step = g / (np.linalg.norm(g) + 1e-12), 0.5
            while step > 1e-3:
                cands = np.stack([th - step * d, th - step / 4 * d])
                res = jax.tree_util.tree_map(np.asarray, pr(jnp.asarray(cands), wins))
                lower = np.nonzero(res["loss"] < losses[-1])[0]
                if lower.size:
                    i = int(lower[0])  # the longer step when both lower the objective
                    th, g = cands[i], res["grad"][i]
                    losses.append(float(res["loss"][i]))
                    break
                step /= 16
    assert len(losses) == 3 and losses[2] < losses[1] < losses[0], losses


#: The reverse-mode program is compiled at XLA's backend optimisation level 0: the same traced program (what is
#: compared), about 40 % less compile time on the CPU.
FAST_COMPILE = {"xla_backend_optimization_level": 0}


@pytest.mark.slow
def test_reverse_mode_and_scheduled_parameterisation_gradients(cl64, su64, fwd64, pr_start):
    """The reverse-mode tuning step (:func:`objective.make_value_and_grad_reverse`: MJX's solver as a fixed-length
    loop, the checkpointed tick scan, one backward pass per prefix) through the per-leg, feature-conditioned crawl
    (parameters selected per tick; the parameterisation's two coordinate kinds: a per-leg row of the five groups
    and ``K_base``'s conditioning columns) on both front legs' float64 windows, two prefix lengths:

    * forward mode: at the start point every leg runs the same row, so a window's rows summed over the legs are its
      gradient in the shared parameterisation, jacfwd's (the per-robot program of ``cl64`` with the two windows as
      its two robots, ``pr_start``): the same to 1e-6, and the same losses;
    * central differences of the forward evaluation (``fwd64``), for every window and both prefixes, along a
      random direction, each window's own leg's ``K_base`` row, the first window's leg's ``d_sw_max`` row (it acts
      within the first 130 ticks), the three conditioning columns and a random direction in the hind legs' rows;
    * a window's rows of the legs other than its own swinging front leg (the hind legs among them) do not act
      (parameters are selected per swing leg); every window's row is not zero, and its prefix rows differ;
    * the forward evaluation gives the reverse step's per-window losses and terms.

    One derivative program is compiled here (the forward-mode one is the per-robot test's)."""
    from hyqjax.studies.tune import schedule

    _, sp, _, _, base, _, both = cl64
    par, obj = fwd64.par, fwd64.obj
    legs = [schedule.LEGS[int(x)] for x in np.asarray(both.leg)]
    with jax.enable_x64(True):
        th = np.asarray(par.theta_of(base), np.float64)
        assert np.array_equal(th[:sp.size], pr_start[0])
        fwd_mode = pr_start[1]  # jacfwd's rows of both windows at the start point
        prog = objective.make_value_and_grad_reverse(base, par, obj, su64, checkpoint=True)
        res = prog.lower(jnp.asarray(th), both).compile(compiler_options=FAST_COMPILE)(jnp.asarray(th), both)
        res = jax.tree_util.tree_map(np.asarray, res)
        rng = np.random.default_rng(1)
        hind = np.asarray([n.endswith("[LH]") or n.endswith("[RH]") for n in par.names])
        unit = np.eye(par.size)
        dirs = np.stack([rng.standard_normal(par.size), unit[par.names.index(f"k_base[{legs[0]}]")],
                         unit[par.names.index(f"k_base[{legs[1]}]")], unit[par.names.index(f"d_sw_max[{legs[0]}]")],
                         *(unit[par.names.index(f"k_base~{f}")] for f in schedule.FEATURES),
                         np.where(hind, rng.standard_normal(par.size), 0.0)])
        fd, at = fwd64.central(th, dirs)
    assert res["ok"].all() and at["finite"].all()
    pg, pw = res["per_window_prefix_grad"], res["per_window_grad"]  # (W, 2, P), (W, P)
    # forward mode: the rows summed over the legs, the shared parameterisation's jacfwd rows
    n0 = sp.size
    np.testing.assert_allclose(pw[:, :4 * n0].reshape(2, 4, n0).sum(1), fwd_mode["grad"], rtol=1e-6,
                               atol=1e-9 * np.abs(fwd_mode["grad"]).max())
    np.testing.assert_allclose(res["per_window_loss"], fwd_mode["loss"], rtol=1e-12)
    # central differences, every window and prefix
    an = np.einsum("wlp,dp->dwl", pg, dirs)
    np.testing.assert_allclose(an, fd, rtol=2e-3, atol=1e-9)
    assert np.abs(fd[1:3, [0, 1], -1].diagonal()).min() > 1e-7  # each window's own K_base row acts
    assert np.abs(fd[:, 0, 0]).max() > 1e-7 and np.abs(fd[3:7, :, -1]).max() > 1e-7
    # the rows of the legs that do not swing in a window do not act (the parameters are selected per swing leg)
    for w, leg in enumerate(legs):
        rows = pg[w, :, :4 * n0].reshape(2, 4, n0)
        other = [i for i, x in enumerate(schedule.LEGS) if x != leg]
        assert np.abs(rows[:, other]).max() < 1e-3 * np.abs(pw[w]).max()
    assert np.abs(res["grad"][hind]).max() < 1e-3 * np.abs(res["grad"]).max()
    assert np.all(np.abs(pw).max(1) > 1e-6) and not np.allclose(pg[:, 0], pg[:, 1])
    # the forward evaluation's per-window losses and terms: the reverse step's primal
    np.testing.assert_allclose(res["per_window_loss"], at["loss"], rtol=1e-12)
    np.testing.assert_allclose(res["loss"], at["loss"].mean(), rtol=1e-12)
    for k, v in res["terms"].items():
        np.testing.assert_allclose(v, at["terms"][k].mean(), rtol=1e-10, atol=1e-14)


def test_line_search_never_raises_the_objective_even_with_a_biased_gradient(tmp_path):
    """Adam with backtracking (``AdamConfig.line_search``): with a gradient whose first component has the
    wrong sign (the kind of bias a pathwise gradient through contact events has), plain Adam raises the
    objective while the line search only ever lowers it, and the budget counts its evaluations."""
    target = jnp.asarray([1.0, -1.0, 0.5])
    loss = lambda th: float(jnp.sum((th - target) ** 2) + 3.0 * (th[0] - target[0]) ** 2)  # noqa: E731

    def step_fn(th):
        g = 2.0 * (th - target) * jnp.asarray([4.0, 1.0, -1.0])  # biased: points the wrong way along x2
        return dict(loss=loss(th), grad=g)

    evaluate = lambda ths: np.asarray([loss(t) for t in ths])  # noqa: E731
    th0 = jnp.zeros(3)
    ls = optimize.AdamConfig(steps=16, lr=0.1, line_search=(0.25, 0.5, 1.0))
    r = optimize.run_adam(step_fn, th0, ls, str(tmp_path / "ls"), dict(k="ls"), 10, progress=False, evaluate=evaluate)
    losses = [row["loss"] for row in r["log"]] + [loss(jnp.asarray(r["theta"]))]
    assert all(b <= a + 1e-12 for a, b in zip(losses, losses[1:])) and losses[-1] < losses[0]
    assert r["spent"] == 16 * 10
    plain = optimize.run_adam(step_fn, th0, optimize.AdamConfig(steps=16, lr=0.1), str(tmp_path / "plain"),
                              dict(k="plain"), 10, progress=False)
    assert any(b > a for a, b in zip([row["loss"] for row in plain["log"]], [row["loss"] for row in plain["log"]][1:]))
    with pytest.raises(ValueError, match="line_search"):
        optimize.AdamConfig(line_search=(0.0,))


@pytest.mark.parametrize("kw, match", [(dict(select_instances=-1), "select_instances must be"),
                                       (dict(select_every=0), "select_every must be"),
                                       (dict(remedy="yes"), "remedy must be")])
def test_study_selection_and_remedy_validation(kw, match):
    with pytest.raises(ValueError, match=match):
        study.StudyConfig(**kw)


def test_selection_steps_include_start_and_last():
    assert study.selection_steps(study.StudyConfig(select_instances=8, select_every=5,
                                                   adam=optimize.AdamConfig(steps=12))) == (0, 5, 10, 12)
    assert study.selection_steps(study.StudyConfig(select_instances=0)) == ()
    assert study.start_params(study.StudyConfig()).shin_remedy == 1.0
    assert study.start_params(study.StudyConfig(remedy=False)).shin_remedy == 0.0


# ------------------------------------------------------------------ run directory: lock, fingerprint, checkpoints


def test_fingerprint_holds_every_result_setting_of_both_objectives():
    base = study.StudyConfig(objective="kinematic", adam=optimize.AdamConfig(steps=4, lr=0.1, checkpoint_every=2))
    fp = study.fingerprint(base)
    assert fp["adam"]["lr"] == 0.1 and "checkpoint_every" not in fp["adam"]
    import dataclasses

    assert fp["kinematic"] == dict(scenarios=study.KINEMATIC_SCENARIOS,
                                   objective=dataclasses.asdict(kinematic.Objective()))

    for change in (dict(adam=dataclasses.replace(base.adam, lr=0.2)), dict(seed=1), dict(groups=("k_base",)),
                   dict(adam=dataclasses.replace(base.adam, steps=5)), dict(remedy=False)):
        assert study.fingerprint(dataclasses.replace(base, **change)) != fp, change
    assert study.fingerprint(dataclasses.replace(base, adam=dataclasses.replace(base.adam, checkpoint_every=7))) == fp
    cl = dataclasses.replace(base, objective="closed_loop")
    assert "kinematic" not in study.fingerprint(cl)
    assert study.fingerprint(dataclasses.replace(cl, loss=objective.ClosedLoopObjective(ticks=300))) != \
        study.fingerprint(cl)
    assert study.settings_of(study.stored_config(cl)) == study.fingerprint(cl)
    # a study stored before the start pose was recorded ran the hip-line start: not the same settings
    assert study.settings_of(cl.to_dict()) == dict(study.fingerprint(cl), start_pose="hip-line")


@pytest.mark.slow
def test_kinematic_objective_honours_checkpoint_every_and_refuses_another_learning_rate(kin_runs, tmp_path,
                                                                                      monkeypatch):
    f, th0, *_ = kin_runs
    cfg = study.StudyConfig(objective="kinematic", groups=("k_base", "damping", "mobility"),
                            adam=optimize.AdamConfig(steps=4, lr=0.1, checkpoint_every=3))
    kcfg, kconf = study.kinematic_adam(cfg)
    assert (kcfg.steps, kcfg.lr, kcfg.checkpoint_every) == (4, 0.1, 3) and kconf["adam"]["lr"] == 0.1
    saved = []
    real = optimize.save_checkpoint
    monkeypatch.setattr(optimize, "save_checkpoint", lambda path, step, *a: (saved.append(step), real(path, step, *a)))
    optimize.run_adam(f, th0, kcfg, str(tmp_path), kconf, 0, progress=False)
    assert saved == [3, 4]
    import dataclasses

    other = dataclasses.replace(cfg, adam=dataclasses.replace(cfg.adam, lr=0.2))
    with pytest.raises(RuntimeError, match="another configuration"):
        kc, kconf2 = study.kinematic_adam(other)
        optimize.run_adam(f, th0, kc, str(tmp_path), kconf2, 0, progress=False)


def test_second_tune_run_refused_in_one_line_before_mjx_is_imported(tmp_path):
    """A run holds DIR/.lock (here a process holding it as a running `hyqjax tune` does): a second run into DIR
    stops with one line naming the holder, before MJX is imported (let alone anything compiled; only the tuned
    groups' declarations, JAX's parameter classes, are loaded by the option checks)."""
    from conftest import run_python, start_python

    d = str(tmp_path / "t")
    holder = start_python(f"""
        import sys, time
        from hyqjax.io.lock import DirLock
        DirLock({d!r}, what="tune run").acquire()
        print("held", flush=True)
        time.sleep(60)
    """)
    try:
        assert holder.stdout.readline().strip() == "held"
        p = run_python(f"""
            import sys
            from experiments.tune_study import main
            code = main(["--gradient-study", "--out", {d!r}, "--steps", "1"])
            print("mjx imported:", "mujoco.mjx" in sys.modules, "code:", code)
        """, timeout=120)
    finally:
        holder.kill()
        holder.wait()
    err = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and "is being written by pid" in err[0] and "--wait" in err[0], p.stderr
    assert "mjx imported: False code: 2" in p.stdout, p.stdout


def test_waiting_tune_run_then_refused_for_other_settings_before_any_compile(tmp_path, capsys):
    """--wait queues behind the holder; once it has the directory, a resume whose settings differ from the
    recorded fingerprint is refused in one line naming the setting, nothing compiled."""
    import threading
    import time

    from experiments import tune_study
    from hyqjax.io.fingerprint import check_or_record
    from hyqjax.io.lock import DirLock

    d = str(tmp_path / "t")
    args = ["--gradient-study", "--out", d, "--no-progress", "--no-cache"]
    cfg = tune_study.build_parser().parse_args(args + ["--seed", "0"])
    cfg.validate_command(cfg)
    check_or_record(d, study.fingerprint(tune_study._gradient_study_config(cfg)), "tuning study")
    lock = DirLock(d).acquire()
    threading.Thread(target=lambda: (time.sleep(1.0), lock.release()), daemon=True).start()
    traced = len(TRACED)
    t0 = time.time()
    code = tune_study.main(args + ["--seed", "1", "--wait"])
    io = capsys.readouterr()
    assert time.time() - t0 >= 0.9 and "waiting for" in io.out
    assert code == 2 and len(io.err.strip().splitlines()) == 1, io.err
    assert "other settings" in io.err and "seed: 0 there, 1 here" in io.err
    assert len(TRACED) == traced, "traced before refusing"

# ------------------------------------------------------------------ parameterisations, search methods, wall-clock study


@pytest.mark.slow
def test_parameterisations_sizes_and_start_point_rows():
    from hyqjax.studies.tune import schedule

    base = crawl.CrawlParams.make(shin_remedy=True)
    sizes = {n: schedule.make(n).size for n in schedule.NAMES}
    assert sizes == dict(shared=14, per_leg=56, per_leg_cond=68, per_leg_cond_all=98)
    for n in schedule.NAMES:
        p = schedule.make(n)
        assert len(p.names) == p.size == len(set(p.names))
        th = p.theta_of(base)
        table, cond = p.split(jnp.asarray(th))
        np.testing.assert_allclose(np.asarray(table), np.tile(p.space.theta_of(base), (4, 1)), rtol=1e-6)
        assert not np.any(np.asarray(cond))
        # the start point runs the start parameters on every leg, whatever the features
        sp = p.scheduled(jnp.asarray(th, jnp.float32), base)
        for leg in range(4):
            q = p.params_at(sp, leg, jnp.asarray([0.7, 0.4, 0.5], jnp.float32))
            for c in p.space.coords:
                own = q.reflex if c.owner == "reflex" else q
                ref = base.reflex if c.owner == "reflex" else base
                assert float(getattr(own, c.name)) == pytest.approx(float(getattr(ref, c.name)), rel=1e-4), c.name


def test_per_leg_and_conditioned_coordinates_act_where_declared():
    from hyqjax.studies.tune import schedule

    base = crawl.CrawlParams.make(shin_remedy=True)
    p = schedule.make("per_leg_cond")
    th = p.theta_of(base)
    i_rf = p.names.index("k_base[RF]")
    i_cond = p.names.index("k_base~search_depth")
    th2 = th.copy()
    th2[i_rf] += 1.0
    th2[i_cond] = 2.0
    sp = p.scheduled(jnp.asarray(th2, jnp.float32), base)
    k = lambda leg, phi: float(p.params_at(sp, leg, jnp.asarray(phi, jnp.float32)).reflex.k_base)  # noqa: E731
    assert k(0, [0, 0, 0]) == pytest.approx(1500.0, rel=1e-4)  # LF untouched
    assert k(1, [0, 0, 0]) > 1600.0  # RF's own row
    assert k(0, [0, 0.5, 0]) > k(0, [0, 0, 0])  # conditioned on the search depth
    assert k(0, [1.0, 0, 0]) == pytest.approx(k(0, [0, 0, 0]), rel=1e-6)  # not on the payload
    # every theta gives valid parameters on every leg (bounded maps)
    rng = np.random.default_rng(0)
    for _ in range(5):
        d = p.describe(th + 3.0 * rng.standard_normal(p.size))
        assert all(np.isfinite(v) for v in d.values())
        assert all(0.0 < d[f"m_min[{leg}]"] < d[f"m_max[{leg}]"] < spmod.M_NOMINAL for leg in schedule.LEGS)


@pytest.mark.slow
def test_features_are_the_controllers_own_measurements():
    from hyqjax.core import robot
    from hyqjax.core.types import Observation
    from hyqjax.studies.tune import schedule

    st = crawl.crawl_init(crawl.CrawlParams.make(), _standing_obs())
    obs = _standing_obs(extra_kg=7.5)
    import dataclasses

    st = dataclasses.replace(st, search_depth=jnp.asarray(0.06, jnp.float32), deep=jnp.asarray([True, False, False, False]))
    phi = np.asarray(schedule.features(st, obs))
    assert phi[0] == pytest.approx(7.5 / schedule.PAYLOAD_SCALE, rel=1e-4)
    assert phi[1] == pytest.approx(0.06 / schedule.DEPTH_SCALE, rel=1e-5)
    assert phi[2] == pytest.approx(0.25)
    del robot, Observation


def _standing_obs(extra_kg: float = 0.0):
    from hyqjax.core import robot
    from hyqjax.core.types import Observation

    w = (robot.TOTAL_MASS + extra_kg) * robot.GRAVITY / 4.0
    q = jnp.asarray(robot.Q_STANDING, jnp.float32)
    return Observation(q=q, qd=jnp.zeros(12, jnp.float32), quat=jnp.asarray([1.0, 0, 0, 0], jnp.float32),
                       gyro=jnp.zeros(3, jnp.float32), foot_force=jnp.tile(jnp.asarray([0, 0, w], jnp.float32), (4, 1)),
                       tau=jnp.zeros(12, jnp.float32), time=jnp.asarray(0.0, jnp.float32))


def _FakeClock():
    """A clock that advances by a fixed cost per evaluation (tests of the checkpoint semantics): the analytic
    studies' evaluation clock."""
    from hyqjax.studies.tune.study.analytic import EvalClock

    return EvalClock()


def test_checkpoints_get_the_iterate_finished_before_them():
    from hyqjax.studies.tune import search

    clk = _FakeClock()
    tr = search.Trace((1.0, 2.5), np.zeros(2))
    clk.now, clk.physics_steps = 0.8, 10
    tr.advance(clk, np.ones(2), {})
    clk.now, clk.physics_steps = 1.6, 20  # passes 1 s: the iterate finished at 0.8 s is what it had then
    tr.advance(clk, 2 * np.ones(2), {})
    assert tr.points == [dict(seconds=1.0, theta=[1.0, 1.0], physics_steps=10)]
    assert tr.finish(clk)[1] == dict(seconds=2.5, theta=[2.0, 2.0], physics_steps=20)
    clk2 = _FakeClock()
    clk2.charge(5.0)  # compile longer than the budget: the start point at every checkpoint
    tr2 = search.Trace((1.0, 2.0), np.full(2, 3.0))
    assert tr2.done(clk2)
    assert [p["theta"] for p in tr2.finish(clk2)] == [[3.0, 3.0], [3.0, 3.0]]


@pytest.mark.slow
def test_forward_gradient_is_unbiased_and_exact_along_its_directions():
    """The forward-gradient estimate (K random directions) of the Jacobian of a smooth vector function: its mean
    over many keys is the exact Jacobian (unbiased), its per-draw error matches (P + 1) |g|^2 / K, and with K = P
    orthogonal-ish directions it is a projection (J V^T V / K)."""
    from hyqjax.studies.tune import objective

    a = jnp.asarray(np.random.default_rng(0).normal(size=(3, 5)), jnp.float32)

    def fn(th):
        y = jnp.sin(a @ th) + 0.1 * (a @ th) ** 2
        return (y, jnp.sum(y)), y

    th = jnp.linspace(-0.5, 0.5, 5, dtype=jnp.float32)
    exact = jax.jacfwd(lambda t: fn(t)[0][0])(th)  # (3, 5)
    est = jax.vmap(lambda kk: objective.forward_gradient(fn, th, kk, 2)[0][0])(jax.random.split(jax.random.key(1),
                                                                                                20000))
    g = np.asarray(exact, np.float64)
    se = np.sqrt((np.sum(g**2, -1, keepdims=True) + g**2) / 2 / 20000)  # Var = (|g|^2 + g_j^2) / K per entry
    assert np.all(np.abs(np.mean(np.asarray(est), 0) - g) < 4.5 * se)
    err = np.mean(np.sum((np.asarray(est) - np.asarray(exact)) ** 2, -1), 0)  # per output row
    np.testing.assert_allclose(err, (5 + 1) * np.sum(np.asarray(exact) ** 2, -1) / 2, rtol=0.1)
    (j, s), aux = objective.forward_gradient(fn, th, jax.random.key(3), 4)
    assert j.shape == (3, 5) and s.shape == (5,) and aux.shape == (3,)
    np.testing.assert_allclose(np.asarray(s), np.asarray(j).sum(0), rtol=1e-5, atol=1e-6)


def test_selection_returns_the_best_validated_iterate_and_charges_its_cost():
    """Closed-loop selection with a fake validation: the returned iterate at every checkpoint is the best of the
    iterates validated before it (start point included; ties go to the later one), validated every 2 iterations;
    the validations' time runs on the method's clock and their physics steps are counted."""
    from hyqjax.studies.tune import search

    clk = _FakeClock()
    score = {0.0: 0.5, 1.0: 0.2, 2.0: 0.7, 3.0: 0.9, 4.0: 0.6, 5.0: 0.1, 6.0: 0.7, 7.0: 0.3, 8.0: 0.2}

    def validate(thetas):
        clk.now += 0.25  # a validation costs 0.25 s of the method's clock
        c = np.full((1, 4), False)
        c[0, :round(4 * score[float(thetas[0, 0])])] = True
        return dict(clean=c, completed=np.ones((1, 4), bool), physics_steps=40)

    sel = search.Selection(validate, every=2)
    tr = search.Trace((2.0, 3.5, 100.0), np.zeros(1), select=sel)
    tr.begin(clk)  # the start point (0.5 -> 2 of 4 clean) is validated first
    assert clk.now == 0.25 and clk.physics_steps == 40
    for i in range(1, 9):  # iterates 1..8, 0.25 s and 100 physics steps each; 2, 4, 6, 8 validated
        clk.now += 0.25
        clk.physics_steps += 100
        tr.advance(clk, np.full(1, float(i)), dict(step=i))
    # validated: start 0.5 (2/4), 2 -> 0.75 (3/4), 4 -> 0.5 (2/4), 6 -> 0.75 (3/4, a tie: the later), 8 -> 0.25
    assert [(r["iteration"], r["clean"], r["selected"]) for r in sel.log] == [
        (0, 0.5, True), (2, 0.75, True), (4, 0.5, False), (6, 0.75, True), (8, 0.25, False)]
    pts = tr.finish(clk)
    # at 2.0 s: iterate 2 finished validating at 1.0 s; iterate 6 finished validating at 3.0 s (< 3.5 s)
    assert [p["theta"] for p in pts] == [[2.0], [6.0], [6.0]]
    assert pts[1]["selected_iteration"] == 6 and pts[1]["validation_clean"] == 0.75
    assert clk.now == pytest.approx(0.25 * (8 + 5)) and clk.physics_steps == 8 * 100 + 5 * 40
    # an unchanged iterate (random search's incumbent) is not validated again; it stays due until it changes
    clk2 = _FakeClock()
    sel2 = search.Selection(validate, every=1)
    tr2 = search.Trace((10.0,), np.zeros(1), select=sel2)
    tr2.begin(clk2)
    for th in (0.0, 0.0, 2.0, 2.0, 3.0):
        tr2.advance(clk2, np.full(1, th), {})
    assert [r["iteration"] for r in sel2.log] == [0, 3, 5]
    with pytest.raises(ValueError, match="every"):
        search.Selection(validate, every=0, every_s=0.0)


@pytest.mark.slow
def test_search_with_selection_keeps_its_best_mean():
    """CMA-ES with a validation that scores the true success rate: the returned iterate at the end is the best
    validated mean (not the last one), and the run's clock carries the validations' physics steps."""
    from hyqjax.studies.tune import search

    target = np.array([1.0, -1.0])
    rate = lambda th: np.exp(-0.5 * np.sum((np.asarray(th) - target) ** 2, -1))  # noqa: E731
    clk = _FakeClock()

    def f_gen(thetas, g):
        clk.now += 0.05
        u = np.random.default_rng([3, g]).random(16)
        clean = u[None, :] < rate(thetas)[:, None]
        return dict(fitness=clean.mean(1), clean=clean, completed=clean, physics_steps=thetas.shape[0] * 16)

    vals = []

    def validate(thetas):
        clk.now += 0.05
        vals.append((thetas[0].copy(), rate(thetas[0])))
        c = np.random.default_rng(9).random((1, 400)) < rate(thetas[0])  # fixed scenarios: common draws
        return dict(clean=c, completed=c, physics_steps=400)

    sel = search.Selection(validate, every=3)
    tr = search.Trace((1.0,), np.zeros(2), select=sel)
    tr.begin(clk)
    search.run_search("cma_es", f_gen, np.zeros(2), 8, 0.3, clk, tr, seed=2)
    out = np.asarray(tr.finish(clk)[-1]["theta"])
    before = [r for r in sel.log if r["wall_s"] < 1.0]  # validations finished before the checkpoint
    best = max(before, key=lambda r: (r["clean"], r["completed"], r["iteration"]))
    assert out.tolist() == vals[sel.log.index(best)][0].tolist() and best["selected"]
    assert rate(out) > rate(np.zeros(2)) + 0.1
    gens = len(tr.log)
    assert clk.physics_steps == gens * 9 * 16 + len(sel.log) * 400


@pytest.mark.slow
@pytest.mark.parametrize("method", ["cma_es", "snes", "open_es", "random_search"])
def test_search_methods_maximise_a_noisy_success_rate_with_common_random_numbers(method):
    """A synthetic 'success' (Bernoulli with probability decreasing with the distance to a target, M draws per
    generation shared by all members): every method improves the returned iterate's true rate and counts its
    physics steps; members of one generation see the same draws."""
    from hyqjax.studies.tune import search

    target = np.array([1.0, -1.0, 0.5, 0.0])
    rate = lambda th: np.exp(-0.5 * np.sum((np.asarray(th) - target) ** 2, -1))  # noqa: E731
    seen = []

    clk = _FakeClock()  # 50 ms per generation: 24 generations, whatever the machine's load

    def f_gen(thetas, g):
        clk.now += 0.05
        u = np.random.default_rng([7, g]).random(64)  # common random numbers of generation g
        seen.append(u)
        clean = u[None, :] < rate(thetas)[:, None]
        return dict(fitness=clean.mean(1), clean=clean, completed=clean, physics_steps=thetas.shape[0] * 64 * 10)

    tr = search.Trace((0.6, 1.2), np.zeros(4))
    out = search.run_search(method, f_gen, np.zeros(4), 12, 0.3, clk, tr, seed=1)
    assert rate(out) > rate(np.zeros(4)) + 0.1
    assert len(tr.log) == 24 and clk.physics_steps == 24 * 13 * 64 * 10
    assert [r["generation"] for r in tr.log] == list(range(24))
    assert len(tr.finish(clk)) == 2


def _synthetic_run(method, stop_at_iteration=None, stored=None):
    """A method on a synthetic noisy success rate (or, for ``gradient``, a quadratic) under a fake clock, with
    selection; stopped (:class:`resume.Paused`) once ``stop_at_iteration`` iterations are stored, or resumed from
    ``stored``. Returns (trace, selection, clock, stored state or None)."""
    from hyqjax.studies.tune import resume, search

    target = np.array([1.0, -1.0, 0.5])
    rate = lambda th: np.exp(-0.5 * np.sum((np.asarray(th) - target) ** 2, -1))  # noqa: E731
    clk = _FakeClock()

    def f_gen(thetas, g):
        clk.now += 0.05
        clean = np.random.default_rng([7, g]).random(32)[None, :] < rate(thetas)[:, None]
        return dict(fitness=clean.mean(1), clean=clean, completed=clean, physics_steps=thetas.shape[0] * 32)

    def validate(thetas):
        clk.now += 0.02
        c = np.random.default_rng(9).random((1, 200)) < rate(thetas[0])
        return dict(clean=c, completed=c, physics_steps=200)

    def step_fn(theta):
        clk.now += 0.05
        return dict(loss=jnp.sum((theta - target) ** 2), grad=2.0 * (theta - target))

    def evaluate(cands):
        clk.now += 0.01
        return np.sum((np.asarray(cands, np.float64) - target) ** 2, -1)

    sel = search.Selection(validate, every=3)
    tr = search.Trace((0.5, 1.2), np.zeros(3), select=sel)
    saved = []

    def checkpoint(state_fn):
        if len(tr.log) == stop_at_iteration:  # through JSON, as the file stores it
            saved.append(resume.unpack(json.loads(json.dumps(resume.pack(
                dict(clock=clk.state(), trace=tr.state(), method=state_fn()))))))
            raise resume.Paused(method)

    if stored is not None:
        clk.restore(stored["clock"])
        tr.restore(stored["trace"])
    else:
        tr.begin(clk)
    state = None if stored is None else stored["method"]
    try:
        if method == "gradient":
            search.run_gradient(step_fn, evaluate, np.zeros(3), clk, tr, step_cost=10, resume=state,
                                checkpoint=checkpoint)
        else:
            search.run_search(method, f_gen, np.zeros(3), 6, 0.3, clk, tr, seed=4, resume=state,
                              checkpoint=checkpoint)
    except resume.Paused:
        return tr, sel, clk, saved[0]
    tr.finish(clk)
    return tr, sel, clk, None


@pytest.mark.parametrize("method", ["cma_es", "snes", "open_es", "random_search", "gradient"])
def test_a_run_stopped_mid_budget_resumes_exactly_where_it_was(method):
    """Every method stopped in the middle of its budget and resumed from its stored state (through JSON) takes
    the same iterates, validations, checkpoints and physics steps as the uninterrupted run."""
    full, full_sel, full_clk, _ = _synthetic_run(method)
    assert len(full.log) > 12
    tr0, _, _, stored = _synthetic_run(method, stop_at_iteration=7)
    assert stored is not None and len(tr0.log) == 7
    tr, sel, clk, _ = _synthetic_run(method, stored=stored)
    assert json.dumps(tr.log) == json.dumps(full.log)
    assert json.dumps(tr.points) == json.dumps(full.points)
    assert json.dumps(sel.log) == json.dumps(full_sel.log)
    assert clk.physics_steps == full_clk.physics_steps
    np.testing.assert_array_equal(tr.returned, full.returned)


def test_stored_run_state_survives_only_intact(tmp_path):
    """The stored state comes back exactly (non-finite floats, arrays of any dtype, a generator's state); a file
    that is altered, truncated or of another configuration is reported and ignored, never half-read."""
    from hyqjax.studies.tune import resume

    logs = []
    st = resume.RunCheckpoint(str(tmp_path), "cma_es/shared", {"seed": 0}, log=logs.append)
    assert st.load() is None and not logs
    rng = np.random.default_rng(3)
    state = dict(a=np.arange(6, dtype=np.int32).reshape(2, 3), f=-np.inf, n=[np.float32(np.nan), 1.5],
                 key=jax.random.key_data(jax.random.key(2)), rng=rng.bit_generator.state)
    st.save(state)
    back = st.load()
    assert back["a"].dtype == np.int32 and back["a"].tolist() == state["a"].tolist()
    assert back["f"] == -np.inf and np.isnan(back["n"][0]) and back["rng"] == state["rng"]
    np.testing.assert_array_equal(back["key"], np.asarray(state["key"]))
    raw = open(st.path, "rb").read()
    i = raw.index(b"payload") + 40
    for bad in (raw[:i] + bytes([raw[i] ^ 1]) + raw[i + 1:], raw[: len(raw) // 2]):
        open(st.path, "wb").write(bad)
        assert st.load() is None
    assert len(logs) == 2 and all("starts over" in m for m in logs)
    st.save(state)
    other = resume.RunCheckpoint(str(tmp_path), "cma_es/shared", {"seed": 1}, log=logs.append)
    assert other.load() is None and "another configuration" in logs[-1]
    st.remove()
    assert not os.path.exists(st.path)


def test_charges_count_compile_not_run_time():
    import time as _t

    from hyqjax.studies.tune import search

    ch = search.Charges()
    f = jax.jit(lambda x: jnp.cumsum(jnp.sin(x) @ x.T, 0))
    x = jnp.ones((64, 64))
    with ch.track("p"):
        jax.block_until_ready(f(x))
    assert ch.seconds["p"] > 0.0
    with ch.track("again"):  # compiled already: nothing to charge
        jax.block_until_ready(f(x))
        _t.sleep(0.05)
    assert ch.seconds["again"] < 0.01
    first = ch.seconds["p"]
    with ch.track("p"):
        jax.block_until_ready(jax.jit(lambda y: y * 3)(x))
    assert ch.seconds["p"] == first  # measured once per program
    assert ch.one_off("w", lambda: _t.sleep(0.05) or 7) == 7 and ch.seconds["w"] >= 0.05


@pytest.mark.parametrize("kw, match", [(dict(methods=("pso",)), "methods must be"),
                                       (dict(dims=("huge",)), "dims must be"),
                                       (dict(wall_minutes=(3.0, 1.0)), "wall_minutes must be"),
                                       (dict(wall_minutes=()), "wall_minutes must be"),
                                       (dict(train_instances=6), "multiple of 4"),
                                       (dict(heldout_seed=0), "heldout_seed must differ"),
                                       (dict(hybrid_split=1.0), "hybrid_split"),
                                       (dict(start_from=(("cma_es/shared", (0.0,)),)), "start_from"),
                                       (dict(start_from=(("pso/shared", (0.0,) * 14),)), "start_from"),
                                       (dict(select_instances=6), "select_instances must be a multiple of 4"),
                                       (dict(select_instances=-4), "select_instances must be"),
                                       (dict(select_every=0), "select_every"),
                                       (dict(select_every_s=-1.0), "select_every_s"),
                                       (dict(select_seed=7777), "select_seed must differ"),
                                       (dict(select_seed=1), "select_seed must differ"),
                                       (dict(grad_directions=-1), "grad_directions"),
                                       (dict(cold_compile=1), "cold_compile"),
                                       (dict(final_instances=8, select_instances=0), "needs select_instances"),
                                       (dict(final_instances=6), "final_instances must be a multiple of 4"),
                                       (dict(final_instances=8, final_candidates=1), "final_candidates"),
                                       (dict(guided_alpha=1.5), "guided_alpha"),
                                       (dict(surrogate_weights=(("speed", 1.0),)), "surrogate_weights: the term"),
                                       (dict(surrogate_weights=(("tilt", -1.0),)), "the weight of tilt"),
                                       (dict(surrogate_weights=(("tilt", 1.0), ("tilt", 2.0))), "tilt given twice"),
                                       (dict(surrogate_weights=("tilt",)), "weight. pairs, got"),
                                       (dict(methods=("guided_es",), popsize=5), "popsize must be even")])
def test_wallclock_config_validation(kw, match):
    from hyqjax.studies.tune import wallclock

    with pytest.raises(ValueError, match=match):
        wallclock.WallClockConfig(**kw)


def test_surrogate_weights_reach_the_gradient_programs_and_survive_results_json(monkeypatch):
    """``WallClockConfig.surrogate_weights`` reweighs the objective the gradient programs descend (the terms named,
    the others at their defaults, each term's sign kept) and reads back from a ``results.json``'s ``config``."""
    from hyqjax.studies.tune import evaluate, gradient_programs, search, surrogate_weights
    from hyqjax.studies.tune.wallclock_config import WallClockConfig

    cfg = WallClockConfig(surrogate_weights=(("progress", 0.0), ("tilt", 25.0)))
    assert WallClockConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    # the programs' windows are not what is tested here: no model, no forward run
    monkeypatch.setattr(windows, "setup", lambda: None)
    monkeypatch.setattr(evaluate, "scenarios", lambda *a, **k: (None, None))
    monkeypatch.setattr(windows, "make_windows", lambda *a, **k: type("W", (), dict(valid=np.ones(4, bool), size=4)))
    grad = gradient_programs.GradientPrograms(cfg, None, search.Charges(), lambda *_: None)
    w, w0 = grad.obj.weights(), objective.ClosedLoopObjective().weights()
    assert w["progress"] == 0.0 and w["tilt"] == 25.0 and w0["tilt"] == 10.0
    assert {k: v for k, v in w.items() if k not in ("progress", "tilt")} == \
        {k: v for k, v in w0.items() if k not in ("progress", "tilt")}
    assert objective.ClosedLoopObjective().reweighted((("mobility", 3.0),)).weights()["mobility"] == -3.0
    assert surrogate_weights.parse_weights(["mobility=0", "stability=0.5"]) == (("mobility", 0.0), ("stability", 0.5))


@pytest.mark.parametrize("argv, match", [(["--methods", "cma_es,pso"], "--methods must be"),
                                         (["--wall-minutes", "0"], "--wall-minutes must be"),
                                         (["--gradient-study", "--guided-comparison"], "two different studies"),
                                         (["--warm-start", "5"], "--warm-start belongs to --gradient-study"),
                                         (["--methods", "open_es", "--popsize", "5"], "popsize must be even"),
                                         (["--methods", "guided_es", "--popsize", "5"], "popsize must be even"),
                                         (["--quick"], "--quick"),
                                         (["--select-seed", "7777"], "select_seed must differ"),
                                         (["--select-instances", "10"], "multiple of 4"),
                                         (["--select-every", "0"], "--select-every"),
                                         (["--gradient-study", "--select-seed", "3"], "--select-seed belongs"),
                                         (["--gradient-study", "--cold-compile"], "--cold-compile belongs"),
                                         (["--gradient-study", "--guided-alpha", "0.2"], "--guided-alpha belongs"),
                                         (["--gradient-study", "--objective", "reach"], "--objective belongs"),
                                         (["--gradient-study", "--preset", "paper"], "--preset belongs"),
                                         (["--state-every-s", "-1"], "--state-every-s must be"),
                                         (["--gradient-study", "--segment-minutes", "5"], "--segment-minutes belongs"),
                                         (["--surrogate-weights", "tilt"], "--surrogate-weights takes TERM=W"),
                                         (["--surrogate-weights", "tilt=x"], "--surrogate-weights takes TERM=W"),
                                         (["--surrogate-weights", "tilt=2000"], "the weight of tilt must be"),
                                         (["--gradient-study", "--surrogate-weights", "tilt=1"],
                                          "--surrogate-weights belongs")])
def test_tune_study_refuses_bad_settings_in_one_line(argv, match, tmp_path, capsys):
    from experiments import tune_study

    out = tmp_path / "o"
    assert tune_study.main(["--out", str(out), *argv]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and match in lines[0] and "Traceback" not in lines[0], lines
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("argv, match", [(["--dims", "per_leg,shared"], "take one name each"),
                                         (["--method", "guided_es", "--popsize", "7"], "popsize must be even"),
                                         (["--start-from", "/nonexistent.json"], "--start-from"),
                                         (["--segment-minutes", "0"], "--segment-minutes must be"),
                                         (["--study"], "unrecognized arguments: --study"),
                                         (["--preset", "nosuch"], "--preset"),
                                         (["--preset", "paper", "--start-from", "r.json"], "two start points"),
                                         (["--gradient-study"], "unrecognized arguments: --gradient-study")])
def test_tune_cli_refuses_bad_settings_in_one_line(argv, match, tmp_path, capsys):
    from hyqjax.cli.app import main

    out = tmp_path / "o"
    try:
        code = main(["tune", "--out", str(out), *argv])
    except SystemExit as e:
        code = e.code
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and match in lines[0] and "Traceback" not in lines[0], lines
    assert not out.exists() or not any(out.iterdir())


def test_tune_help_has_at_most_twenty_options():
    """``hyqjax tune`` is a user's command: its --help lists at most 21 options (the study's are in
    ``python -m experiments.tune_study``, which takes every one of them too); the 21st is ``--sigma``, the search's
    first step, which a run started from a tuned set needs (docs/tuning.md)."""
    from hyqjax.cli.app import build_parser
    from experiments import tune_study

    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["tune"]
    opts = [a for a in sub._actions if a.option_strings]
    assert len(opts) <= 21, [a.option_strings for a in opts]
    study = {o for a in tune_study.build_parser()._actions for o in a.option_strings}
    assert {o for a in opts for o in a.option_strings} <= study


@pytest.fixture(scope="module")
def c_success():
    """The forward success program of the tiny CPU studies below (C MuJoCo, 0.5 s, 12 rows), compiled once."""
    from hyqjax.studies.tune import forward, schedule, wallclock

    cfg = wallclock.WallClockConfig(impl="c")
    return forward.SuccessEvaluator(schedule.make("shared"), wallclock.start_params(cfg), 0.5, "c")


@pytest.mark.slow
def test_wallclock_study_end_to_end_resumes_and_uses_common_random_numbers(tmp_path, monkeypatch, c_success):
    """A tiny study on the CPU (random search and CMA-ES on the shared 14 coordinates, 0.5 s runs, one compiled
    forward program for training, selection and held-out), each method in its own call into the same directory
    (as one process per method would): members with equal parameters get equal outcomes on the common
    scenarios; every method validates its iterates on the fixed validation batch and pays for it (physics steps
    of generations plus validations); every checkpoint's iterate is the best validated one finished before it and
    is evaluated on the same held-out instances; the two calls compose into one results file; a further call keeps
    every finished stage and runs nothing; another configuration there is refused. CMA-ES's call first ends its
    segment in the middle of the run (``segment_minutes``): the run's state is stored and the next call goes on from
    it, generations continuing without a gap or a repeat, its clock from the stored seconds."""
    from hyqjax.studies.tune import forward, resume, schedule, wallclock, wallclock_results, wallclock_run

    cfg = wallclock.WallClockConfig(methods=("random_search", "cma_es"), dims=("shared",), wall_minutes=(0.04, 0.1),
                                    popsize=2, train_instances=4, train_duration=0.5, heldout=6, heldout_chunk=2,
                                    heldout_duration=0.5, impl="c", charge_compile=False, select_instances=12,
                                    select_every=1)
    assert wallclock_run.selection_program(cfg) == "forward"  # 12 rows: the generation's program
    base = wallclock.start_params(cfg)
    p = schedule.make("shared")
    ev = c_success
    th0 = p.theta_of(base)
    r = ev(np.stack([th0, th0 + 0.5, th0]), forward.train_scenarios(4, 3, 0))
    for k in ("clean", "completed", "progress", "mean_mobility"):
        np.testing.assert_array_equal(r["columns"][k][0], r["columns"][k][2])  # same member, same scenarios
    assert not np.array_equal(r["columns"]["progress"][0], r["columns"]["progress"][1])
    assert r["physics_steps"] == 3 * 4 * 250
    monkeypatch.setattr(forward, "SuccessEvaluator", lambda *a, **k: ev)  # one compiled program for the study
    logs = []
    for m in cfg.methods:  # one call per method, as one process per method
        if m == "cma_es":  # its first call ends its segment in the middle of the run; the next goes on from there
            first = wallclock.run_wallclock_study(dataclasses_replace(cfg, methods=(m,)), str(tmp_path), log=logs.append,
                                                  checkpoint_every_s=0.0, segment_minutes=3.0 / 60)
            assert first["paused"] == "cma_es/shared" and "cma_es/shared" not in first["runs"] and not first["complete"]
            store = resume.RunCheckpoint(str(tmp_path), "cma_es/shared", wallclock._fingerprint(wallclock._config(cfg)))
            stored = store.load()
            gens_before, t_stop = len(stored["trace"]["log"]), stored["clock"]["elapsed"]
            assert gens_before >= 1 and 0.0 < t_stop < cfg.checkpoints_s[-1]
        res = wallclock.run_wallclock_study(dataclasses_replace(cfg, methods=(m,)), str(tmp_path), log=logs.append)
        assert res["complete"] and set(res["runs"]) == {f"{x}/shared" for x in cfg.methods[:cfg.methods.index(m) + 1]}
    assert res["config"]["methods"] == ["cma_es", "random_search"]
    # the resumed run: generations go on without a gap or a repeat, its clock from the stored seconds, its stored
    # state removed once it is in results.json (physics steps counted once: below)
    run = res["runs"]["cma_es/shared"]
    assert run["segments"] == 2 and res["runs"]["random_search/shared"]["segments"] == 1
    assert any("resuming at" in m for m in logs) and not os.path.exists(store.path)
    assert [r["generation"] for r in run["log"]] == list(range(len(run["log"]))) and len(run["log"]) > gens_before
    assert run["log"][:gens_before] == stored["trace"]["log"] and run["log"][gens_before]["wall_s"] >= t_stop
    assert run["elapsed_s"] >= cfg.checkpoints_s[-1]
    members = {"table1", "start"} | {wallclock_results.member_key(m, "shared", s) for m in cfg.methods
                                     for s in cfg.checkpoints_s}
    assert set(res["heldout"]) == members
    assert all(h["n"] == 6 for h in res["heldout"].values())
    for m in cfg.methods:
        run = res["runs"][f"{m}/shared"]
        sel = run["selection"]
        assert sel["instances"] == 12 and sel["log"][0]["iteration"] == 0  # the start point first
        assert [pt["seconds"] for pt in run["points"]] == list(cfg.checkpoints_s)
        assert run["physics_steps"] == len(run["log"]) * 3 * 4 * 250 + len(sel["log"]) * 12 * 250
        assert sel["physics_steps"] == len(sel["log"]) * 12 * 250
        assert [pt["physics_steps"] for pt in run["points"]] == sorted(pt["physics_steps"] for pt in run["points"])
        for pt in run["points"]:
            done = [v for v in sel["log"] if v["wall_s"] < pt["seconds"]]
            if not done:  # still validating the start point: the start point
                assert pt["theta"] == th0.tolist()
                continue
            best = max(done, key=lambda v: (v["clean"], v["completed"], v["iteration"]))
            assert pt.get("selected_iteration", 0) == best["iteration"]
    assert sum(len(res["runs"][f"{m}/shared"]["selection"]["log"]) for m in cfg.methods) >= 3
    assert {(c["method"], len(c["points"])) for c in res["budget_curves"]} == {(m, 2) for m in cfg.methods}
    stale = resume.RunCheckpoint(str(tmp_path), "random_search/shared", {})
    stale.save(dict(left="by a kill after the run was stored"))
    again = wallclock.run_wallclock_study(cfg, str(tmp_path), log=lambda s: None)
    assert again["runs"] == json.loads(json.dumps(res["runs"])) and again["heldout"] == res["heldout"]
    assert not os.path.exists(stale.path)  # a finished run's stored state is removed, never resumed
    from hyqjax.studies.tune import figure

    assert os.path.getsize(figure.plot_wallclock(again, str(tmp_path / "t.png"))) > 0
    assert "random_search / shared (14)" in figure.wallclock_markdown(again)
    with pytest.raises(RuntimeError, match="another configuration"):
        wallclock.run_wallclock_study(dataclasses_replace(cfg, seed=5), str(tmp_path), log=lambda s: None)
    # Hand-set presets on the study's held-out set (experiments/tune_handset.py): the start point and the default
    # crawl (Table I) reproduce the study's own held-out results for those two members, instance for instance.
    from hyqjax.studies.tune.study import handset

    hs = handset.evaluate_presets(again, ["start", "default"], log=lambda s: None)
    for preset, member in (("start", "start"), ("default", "table1")):
        for k in ("n", "clean", "completed", "failure_counts", "per_height"):
            assert hs[preset][k] == again["heldout"][member][k], (preset, k)
    assert handset.best(hs)[0] in ("start", "default")
    with pytest.raises(ValueError, match="presets must be among"):
        handset.check_names(["start", "trunk_at_90"])


def test_study_runs_of_other_methods_compose_into_one_results_file(tmp_path):
    """A study directory written by one method's process is resumed by another method's process (the
    configuration's fingerprint leaves ``methods`` out; the stored configuration names every method run);
    another setting there is still refused."""
    from hyqjax.io.atomic import write_json
    from hyqjax.studies.tune import wallclock

    a = wallclock.WallClockConfig(methods=("random_search",), dims=("shared",))
    write_json(str(tmp_path / "results.json"),
               dict(kind="wallclock", config=wallclock._config(a), runs={"random_search/shared": {}}))
    b = wallclock.WallClockConfig(methods=("cma_es", "gradient"), dims=("shared",))
    prev = wallclock.previous(str(tmp_path), b)
    assert set(prev["runs"]) == {"random_search/shared"}
    assert wallclock._methods_union(prev["config"]["methods"], b.methods) == ["cma_es", "random_search", "gradient"]
    for other in (dataclasses_replace(b, select_instances=0), dataclasses_replace(b, cold_compile=True),
                  dataclasses_replace(b, wall_minutes=(1.0, 10.0))):
        with pytest.raises(RuntimeError, match="another configuration"):
            wallclock.previous(str(tmp_path), other)
    # a study run with the hip-line start (its stored config predates the start pose) is not resumed either
    write_json(str(tmp_path / "results.json"),
               dict(kind="wallclock", config=a.to_dict(), runs={"random_search/shared": {}}))
    with pytest.raises(RuntimeError, match="'hip-line' step-down start .*'leading-foot'"):
        wallclock.previous(str(tmp_path), b)


def dataclasses_replace(obj, **kw):
    import dataclasses

    return dataclasses.replace(obj, **kw)


@pytest.mark.slow
def test_gradient_diagnostics_measure_snr_and_rank_correlation():
    """With a window objective that ranks held-out success perfectly (lower loss, higher success) the rank
    correlation is -1; the signal-to-noise ratio is |mean| / (std / sqrt(W)) of the per-window gradients."""
    from types import SimpleNamespace

    from hyqjax.studies.tune import gradient_programs, schedule, wallclock
    from hyqjax.studies.tune import objective as obj_mod

    cfg = wallclock.WallClockConfig(methods=("gradient",), dims=("shared",))
    p = schedule.make("shared")
    base = wallclock.start_params(cfg)
    pw = np.stack([np.full(p.size, 1.0), np.full(p.size, 3.0)])[:, None, :]  # (W=2, L=1, P): mean 2, std sqrt(2)

    def step_fn(th):
        return dict(per_window_prefix_grad=pw, ok=np.array([True, True]))

    def evaluate(ths):
        return -np.asarray(ths)[:, 0]  # loss falls as theta_0 grows

    grad = SimpleNamespace(fns={"shared": (step_fn, evaluate, 0)}, obj=obj_mod.ClosedLoopObjective(ticks=10),
                           exact_step=lambda param: step_fn)
    th0 = p.theta_of(base)
    members = {"start": (p, th0, base)}
    heldout = {"start": dict(clean=0.1)}
    for i in range(7):
        members[f"m{i}"] = (p, th0 + 0.1 * (i + 1), base)
        heldout[f"m{i}"] = dict(clean=0.2 + 0.05 * i)
    d = gradient_programs.gradient_diagnostics(cfg, dict(heldout=heldout), {"shared": p}, base, grad, members)["shared"]
    assert d["objective_vs_heldout_spearman"] == pytest.approx(-1.0)
    assert d["snr_mean"] == pytest.approx(2.0 / (np.sqrt(2.0) / np.sqrt(2.0)))
    assert len(d["iterates"]) == 8 and d["windows"] == 2


def test_winner_is_clear_only_of_runs_that_exist():
    """The study's winner: the best held-out clean rate at a budget; its interval is "clear" only when it lies
    above every other run's, and a lone run is clear of nothing (it was compared with nothing)."""
    from hyqjax.studies.tune import wallclock_results

    def curve(method, clean, ci):
        return dict(method=method, dim="shared", points=[dict(minutes=10.0, clean=clean, completed=0.8,
                                                              clean_ci95=list(ci))])

    lone = dict(budget_curves=[curve("cma_es", 0.5, (0.45, 0.55))])
    w = wallclock_results.winner(lone, 10.0)
    assert w["method"] == "cma_es" and w["others"] == 0 and not w["clear_of_all_others"]
    tie = dict(budget_curves=[curve("cma_es", 0.53, (0.51, 0.55)), curve("random_search", 0.50, (0.48, 0.52))])
    w = wallclock_results.winner(tie, 10.0)
    assert w["method"] == "cma_es" and w["others"] == 1 and not w["clear_of_all_others"]
    clear = dict(budget_curves=[curve("random_search", 0.50, (0.48, 0.52)), curve("cma_es", 0.58, (0.56, 0.60))])
    w = wallclock_results.winner(clear, 10.0)
    assert w["method"] == "cma_es" and w["clear_of_all_others"]
    assert wallclock_results.winner(clear, 3.0) is None


def test_repeated_runs_are_compared_over_runs_and_only_like_with_like(tmp_path):
    """Repeated study runs (another seed each): per member, every run's held-out clean rate, the mean and the
    95% Student-t interval over runs (m +- t_{0.975,n-1} s / sqrt(n)); a member is apart from another only when
    its interval over runs lies above the other's; runs of another configuration or held-out set are refused
    naming what differs (the stored 14- and 68-coordinate H200 studies differ in their parameterisations)."""
    import json as _json
    from scipy import stats

    from hyqjax.studies.tune.study import repeats

    def study(seed, cma, rs):
        cfg = dict(seed=seed, methods=["cma_es", "random_search"], dims=["shared"], popsize=16)
        runs = {f"{m}/shared": dict(method=m, dim="shared") for m in ("cma_es", "random_search")}
        held = {"cma_es/shared@10min": dict(clean=cma, completed=0.9, clean_ci95=[cma - 0.02, cma + 0.02], n=2000),
                "random_search/shared@10min": dict(clean=rs, completed=0.8, clean_ci95=[rs - 0.02, rs + 0.02], n=2000),
                "start": dict(clean=0.41, completed=0.6, clean_ci95=[0.39, 0.43], n=2000)}
        return dict(kind="wallclock", config=cfg, runs=runs, heldout=held, heldout_set=dict(seed=7777, instances=2000))

    res = [study(0, 0.60, 0.50), study(1, 0.62, 0.52), study(2, 0.58, 0.49)]
    out = repeats.collect(res, ["a", "b", "c"], 10.0)
    c = out["cma_es/shared"]["clean"]
    m, s = np.mean([0.60, 0.62, 0.58]), np.std([0.60, 0.62, 0.58], ddof=1)
    half = stats.t.ppf(0.975, 2) * s / np.sqrt(3)
    assert c["n"] == 3 and c["mean"] == pytest.approx(m) and c["ci95"] == pytest.approx([m - half, m + half])
    assert [r["seed"] for r in out["cma_es/shared"]["runs"]] == [0, 1, 2]
    assert out["cma_es/shared"]["apart_from"] == ["random_search/shared", "start"]
    assert "random_search/shared" not in out["start"]["apart_from"]
    assert "cma_es/shared" in repeats.table(out, 10.0)
    d = repeats.differences(out)["cma_es/shared - random_search/shared"]
    welch = stats.ttest_ind([0.60, 0.62, 0.58], [0.50, 0.52, 0.49], equal_var=False)
    assert d["mean"] == pytest.approx(0.0966667) and d["p_two_sided"] == pytest.approx(welch.pvalue)
    ci = welch.confidence_interval(0.95)
    assert d["ci95"] == pytest.approx([ci.low, ci.high])
    one = repeats.collect(res[:1], ["a"], 10.0)
    assert one["cma_es/shared"]["clean"]["ci95"] is None and one["cma_es/shared"]["apart_from"] == []
    other = study(3, 0.6, 0.5)
    other["config"]["popsize"] = 32
    with pytest.raises(ValueError, match="popsize"):
        repeats.collect(res + [other], ["a", "b", "c", "d"], 10.0)
    moved = study(3, 0.6, 0.5)
    moved["heldout_set"] = dict(seed=1, instances=2000)
    with pytest.raises(ValueError, match="another held-out set"):
        repeats.collect(res + [moved], ["a", "b", "c", "d"], 10.0)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    stored = [os.path.join(repo, "docs", "results", d) for d in ("tune_wallclock_h200_10min", "tune_wallclock_h200_10min_68")]
    loaded = [repeats.load(d) for d in stored]
    with pytest.raises(ValueError, match="dims"):
        repeats.collect(loaded, stored, 10.0)
    (tmp_path / "results.json").write_text(_json.dumps(dict(kind="gradient")))
    with pytest.raises(ValueError, match="not an equal-wall-clock study"):
        repeats.load(str(tmp_path))


def test_grid_of_cells_takes_one_value_per_cell_with_the_right_interval_and_refuses_mixtures():
    """The study as a grid (:mod:`hyqjax.studies.tune.study.cells`): a cell of one run is its rate with its Wilson interval,
    a cell of several seeds their mean with the 95% t-interval over runs; a gradient method in reverse mode is a
    cell of its own; each cell carries its not-completed and diverged counts; runs of another device, another
    setting, or the same run twice are refused naming it. The stored H200 studies make one grid."""
    from scipy import stats

    from hyqjax.studies.tune.study import cells, repeats

    def study(seed, method, dim, clean, grad_mode="jacfwd", device="NVIDIA H200", diverged=0):
        cfg = dict(seed=seed, methods=[method], dims=[dim], grad_mode=grad_mode)
        runs = {f"{method}/{dim}": dict(method=method, dim=dim, points=[dict(seconds=600.0, physics_steps=7)])}
        held = {f"{method}/{dim}@10min": dict(clean=clean, completed=0.75, clean_ci95=[clean - 0.02, clean + 0.02],
                                               n=2000, failure_counts=dict(diverged=diverged)),
                "start": dict(clean=0.406, completed=0.6, clean_ci95=[0.39, 0.43], n=2000)}
        return dict(kind="wallclock", config=cfg, runs=runs, heldout=held, device=device,
                    heldout_set=dict(seed=7777, instances=2000))

    res = [study(0, "cma_es", "shared", 0.55), study(1, "cma_es", "shared", 0.52), study(0, "snes", "per_leg", 0.58),
           study(0, "gradient", "per_leg", 0.41, "reverse", diverged=3), study(0, "gradient", "shared", 0.40)]
    g = cells.gather(res, list("abcde"), 10.0)
    c = g["cells"]["shared"]["cma_es"]
    half = stats.t.ppf(0.975, 1) * np.std([0.55, 0.52], ddof=1) / np.sqrt(2)
    assert c["interval"] == "over_runs" and c["clean_ci95"] == pytest.approx([0.535 - half, 0.535 + half])
    s = g["cells"]["per_leg"]["snes"]
    assert s["interval"] == "wilson" and s["clean_ci95"] == pytest.approx([0.56, 0.60]) and s["runs"][0]["not_completed"] == 500
    assert g["cells"]["per_leg"]["gradient (reverse mode)"]["runs"][0]["diverged"] == 3
    assert "gradient" in g["cells"]["shared"] and g["start"] == dict(min=0.406, max=0.406)
    table = cells.markdown(g)
    assert "**0.580 [0.560, 0.600]** clear; 500 / 0" in table and "(2 runs)" in table and "not run" in table
    for bad, match in ((study(2, "snes", "shared", 0.5, device="NVIDIA H100 80GB HBM3"), "several kinds of device"),
                       (study(0, "cma_es", "shared", 0.5), "both hold cma_es on shared with seed 0")):
        with pytest.raises(ValueError, match=match):
            cells.gather(res + [bad], list("abcdef"), 10.0)
    other = study(2, "snes", "shared", 0.5)
    other["config"]["popsize"] = 32
    with pytest.raises(ValueError, match="popsize"):
        cells.gather(res + [other], list("abcdef"), 10.0)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    stored = os.path.join(repo, "docs", "results", "tune_cells_h200_10min")
    names = [os.path.join(stored, d) for d in ("cma_es_per_leg", "snes_per_leg", "gradient_per_leg", "hybrid_per_leg")]
    grid = cells.gather([repeats.load(d) for d in names], names, 10.0)
    assert set(grid["cells"]["per_leg"]) == {"cma_es", "snes", "gradient", "hybrid"}


def test_budget_curves_of_several_runs_merge_the_stored_30_minute_runs(tmp_path):
    """experiments/tune_budget_curves.py: the four stored 30-minute runs become one figure's four curves, each with
    its checkpoints at 3, 10 and 30 minutes and the held-out numbers its own run stored; a run given twice and a
    run of another configuration are refused in one line (exit 2), nothing written."""
    from experiments import tune_budget_curves as tbc
    from hyqjax.studies.tune.study import repeats

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    stored = os.path.join(repo, "docs", "results", "tune_cells_h200_30min")
    names = [os.path.join(stored, d) for d in ("cma_es_shared_30min", "random_search_shared_30min",
                                                "cma_es_per_leg_30min", "snes_per_leg_30min")]
    runs = [repeats.load(d) for d in names]
    res = tbc.merge(runs, names)
    got = {(c["method"], c["dim"]): c for c in res["budget_curves"]}
    assert set(got) == {("cma_es", "shared"), ("random_search", "shared"), ("cma_es", "per_leg"), ("snes", "per_leg")}
    for run in runs:
        for c in run["budget_curves"]:
            assert [p["minutes"] for p in got[(c["method"], c["dim"])]["points"]] == [3.0, 10.0, 30.0]
            assert got[(c["method"], c["dim"])]["points"] == c["points"]
    assert res["heldout"]["start"] == runs[0]["heldout"]["start"] and res["device"] == "NVIDIA H200"
    fig = tmp_path / "curves.png"
    assert tbc.main([*names, "--figure", str(fig)]) == 0 and fig.stat().st_size > 10_000
    other = os.path.join(repo, "docs", "results", "tune_cells_h200_10min", "cma_es_per_leg")
    for argv in ([names[0], names[0]], [names[0], other]):
        assert tbc.main([*argv, "--figure", str(tmp_path / "no.png")]) == 2
    assert not (tmp_path / "no.png").exists()


def test_objective_ranking_collects_every_evaluated_iterate_once(tmp_path):
    """The window-objective ranking (experiments/tune_objective_ranking.py) reads back the configuration a study
    ran with (``WallClockConfig.from_dict``) and collects the start point once and every held-out-evaluated checkpoint of every run, with its
    held-out clean rate; the stored 10-minute runs give 1 + 2 x 2 iterates."""
    import json as _json

    from hyqjax.studies.tune.study import ranking

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    d = os.path.join(repo, "docs", "results", "tune_repeats_h100_10min")
    res = [_json.load(open(os.path.join(d, r, "results.json"))) for r in ("cma_es_s1", "random_search_s1")]
    from hyqjax.studies.tune.wallclock import WallClockConfig

    # a setting the run predates (retake_windows) comes back at its default
    assert WallClockConfig.from_dict(res[0]["config"]).to_dict() == {**WallClockConfig.defaults(), **res[0]["config"]}
    rows = ranking.iterates(res, ["a", "b"])
    assert [r["name"] for r in rows].count("start") == 1 and len(rows) == 5
    for r in rows:
        if r["name"] != "start":
            run, key = r["name"].split(":")
            assert r["clean"] == res["ab".index(run)]["heldout"][key]["clean"] and len(r["theta"]) == 14


def test_training_draws_take_the_configured_heights_and_spread():
    """``train_heights`` and ``train_spread`` (the reach as the tuning objective): every height gets its share, and
    the wide spread reaches the start distances, frictions and payloads the training ranges exclude."""
    from hyqjax.studies.tune import forward, wallclock, wallclock_run

    hs = (0.24, 0.26, 0.28, 0.30)
    wide = forward.train_scenarios(256, 3, 0, hs, "wide")
    narrow = forward.train_scenarios(256, 3, 0, hs, "train")
    for sc in (wide, narrow):
        h, n = np.unique(np.asarray(sc.terrain.platform_height), return_counts=True)
        np.testing.assert_allclose(h, hs, atol=1e-6)
        assert set(n) == {64}
    lo, hi = forward.TRAIN_RANGES["start_distance"]
    assert np.all((np.asarray(narrow.start_distance) >= lo) & (np.asarray(narrow.start_distance) <= hi))
    assert np.mean(np.asarray(wide.start_distance) > hi) > 0.2
    assert np.asarray(wide.terrain.payload_mass).max() > forward.TRAIN_RANGES["payload"][1]
    assert np.asarray(wide.terrain.friction).min() < forward.TRAIN_RANGES["friction"][0]
    cfg = wallclock.WallClockConfig(train_heights=hs, train_spread="wide", dims=("shared",), methods=("cma_es",))
    sel = wallclock_run.validation_scenarios(cfg)
    assert sel.batch_size == cfg.select_instances
    np.testing.assert_allclose(np.unique(np.asarray(sel.terrain.platform_height)), hs, atol=1e-6)
    with pytest.raises(ValueError, match="train_spread"):
        wallclock.WallClockConfig(train_spread="narrow")


@pytest.mark.parametrize("change", [["--guided-alpha", "0.3"], ["--objective", "reach"], ["--guided-subspace", "2"]])
def test_tune_study_resume_with_other_new_settings_refused_before_any_compile(change, tmp_path, capsys):
    """A directory holding a study of one configuration: the same command with another guided-ES setting or
    objective is refused in one line before anything is compiled, and the directory is left as it was."""
    import json

    from experiments import tune_study

    out = tmp_path / "o"
    base = ["--out", str(out), "--methods", "guided_es,cma_es", "--dims", "shared", "--impl", "c", "--no-cache"]
    args = tune_study.build_parser().parse_args(base)
    args.validate_command(args)
    from hyqjax.studies.tune import wallclock

    (out / "results.json").write_text(json.dumps(dict(kind="wallclock", config=wallclock._config(args.wallclock_config),
                                                      runs={}, heldout={})))
    before = sorted(p.name for p in out.iterdir())
    traced = len(TRACED)
    assert tune_study.main(base + change) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "another configuration" in lines[0] and "Traceback" not in lines[0], lines
    assert len(TRACED) == traced and sorted(p.name for p in out.iterdir()) == before


def test_tune_starts_from_a_preset_at_the_theta_that_runs_it():
    """The default start of ``hyqjax tune`` (per_leg) is the preset ``clean`` (``reach`` for the shared coordinates); the 30-minute per-leg CMA-ES set
    ``tuned_per_leg`` starts at the stored run's returned ``theta`` (float32 storage); a conditioned preset starts its
    own parameterisation at its own ``theta``."""
    import json

    from hyqjax import presets
    from hyqjax.cli.app import build_parser
    from hyqjax.studies.tune import schedule, wallclock
    from hyqjax.studies.tune.wallclock_config import start_point, start_theta

    root = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "tune_cells_h200_30min",
                        "cma_es_per_leg_30min", "results.json")
    with open(root) as f:
        r = json.load(f)
    p = schedule.make("per_leg", tuple(r["config"]["groups"]))
    np.testing.assert_allclose(start_theta(p, presets.load("tuned_per_leg")), r["runs"]["cma_es/per_leg"]["theta"],
                               atol=1e-4)
    args = build_parser().parse_args(["tune", "--out", "o"])
    from hyqjax.cli import tune as tune_cli
    from hyqjax.cli import tune_start

    tune_cli._fill_hidden(args)
    assert tune_start.start_preset(args, ("cma_es",), ("per_leg",)) == "clean"
    assert tune_start.start_preset(args, ("cma_es",), ("shared",)) == "reach"
    args.objective = "reach"
    assert tune_start.start_preset(args, ("cma_es",), ("per_leg",)) == "reach"
    args.objective = "clean"
    args.preset = "none"
    assert tune_start.start_preset(args, ("cma_es",), ("per_leg",)) == ""
    c = presets.get("tuned_per_leg_cond").values["conditioned"]
    pc = schedule.make(c["parameterisation"], tuple(c["groups"]))
    cfg = wallclock.WallClockConfig(dims=(pc.name,), methods=("cma_es",), start_preset="tuned_per_leg_cond")
    np.testing.assert_allclose(start_theta(pc, start_point(cfg)), c["theta"], atol=1e-4)


def test_a_run_from_a_preset_keeps_and_returns_its_untuned_values(tmp_path):
    """A run started from ``reach`` (whose edge probe no parameterisation tunes) maps every ``theta`` on the
    preset's crawl, not on Table I's: the forward runs' base and the set read back from ``results.json`` carry the
    probe, per leg too; the start ``theta`` reads back as the preset itself; an older ``results.json`` without
    ``start_base`` reads the registry's values."""
    import json

    import jax

    from hyqjax import presets
    from hyqjax.studies.tune import schedule, tuned, wallclock
    from hyqjax.studies.tune.wallclock_config import start_point, start_settings, start_theta

    reach = presets.load("reach")
    assert float(reach.edge_probe) > 0
    for dim in ("shared", "per_leg"):
        cfg = wallclock.WallClockConfig(dims=(dim,), methods=("cma_es",), start_preset="reach")
        base = wallclock.start_params(cfg)
        assert float(base.edge_probe) == float(reach.edge_probe) and float(base.edge_deep) == float(reach.edge_deep)
        p = schedule.make(dim, cfg.groups)
        theta = start_theta(p, start_point(cfg))
        res = dict(kind="wallclock", config=cfg.to_dict(), start_base=start_settings("reach"),
                   runs={f"cma_es/{dim}": dict(theta=theta.tolist())})
        path = tmp_path / f"{dim}.json"
        for r in (res, {k: v for k, v in res.items() if k != "start_base"}):
            path.write_text(json.dumps(r))
            back = tuned.crawl_params(str(path), "cma_es")
            row = back.row(2) if dim == "per_leg" else back
            for (k, a), (_, b) in zip(jax.tree_util.tree_flatten_with_path(row)[0],
                                      jax.tree_util.tree_flatten_with_path(reach)[0]):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=1e-6,
                                           err_msg=jax.tree_util.keystr(k))
    table1 = wallclock.start_params(wallclock.WallClockConfig())
    assert float(table1.edge_probe) == 0.0 and float(table1.shin_remedy) == 1.0


def test_edge_groups_tune_the_probe_and_the_gate_from_a_start_with_the_probe_on(tmp_path, capsys):
    """``--groups ...,edge_probe,edge_gate`` adds the edge probe's step and depth and the depth gate's five settings
    as coordinates (per leg: 14 + 7 = 21 a leg, 84 in all): from ``clean`` the start ``theta`` reads back as
    ``clean`` itself, edge values included; moving one edge coordinate moves that field alone, inside its
    declared range; from a start with the probe off (Table I, ``--preset none``) the groups are refused in one
    line before anything runs."""
    import json

    import jax

    from hyqjax import presets
    from hyqjax.cli import tune as tune_cli
    from hyqjax.cli.app import build_parser, main
    from hyqjax.core.params import param_ranges
    from hyqjax.studies.tune import schedule, tuned, wallclock
    from hyqjax.studies.tune.wallclock_config import start_point, start_settings, start_theta

    groups = spmod.DEFAULT_GROUPS + spmod.EDGE_GROUPS
    a = build_parser().parse_args(["tune", "--out", str(tmp_path / "ok"), "--groups", ",".join(groups)])
    tune_cli.validate(a)
    cfg = a.wallclock_config
    assert cfg.start_preset == "clean" and cfg.groups == groups
    p = schedule.make("per_leg", cfg.groups)
    assert p.size == 4 * 21
    clean = presets.load("clean")
    theta = start_theta(p, start_point(cfg))
    res = dict(kind="wallclock", config=cfg.to_dict(), start_base=start_settings("clean"),
               runs={"cma_es/per_leg": dict(theta=theta.tolist())})
    path = tmp_path / "r.json"
    path.write_text(json.dumps(res))
    back = tuned.crawl_params(str(path), "cma_es")
    for leg in range(4):
        for (k, x), (_, y) in zip(jax.tree_util.tree_flatten_with_path(back.row(leg))[0],
                                  jax.tree_util.tree_flatten_with_path(clean.row(leg))[0]):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2e-5, atol=1e-6,
                                       err_msg=jax.tree_util.keystr(k))
    ranges = param_ranges(crawl.CrawlParams)
    names = p.space.names
    for field in ("edge_probe", "edge_probe_depth", "edge_tilt", "edge_margin", "edge_lowering", "edge_deep",
                  "edge_tilt_deep"):
        moved = theta.copy()
        moved[names.index(field)] += 1.5  # the first leg's row (LF) of that coordinate
        path.write_text(json.dumps(dict(res, runs={"cma_es/per_leg": dict(theta=moved.tolist())})))
        row = tuned.crawl_params(str(path), "cma_es").row(0)
        changed = [f for f in ranges if f != "foot_sequence"
                   and not np.allclose(np.asarray(getattr(row, f)), np.asarray(getattr(clean.row(0), f)), rtol=2e-5)]
        assert changed == [field], (field, changed)
        assert ranges[field].in_range(np.asarray(getattr(row, field))).all()
    for argv in (["--preset", "none"], ["--dim", "shared", "--preset", "none"]):
        out = tmp_path / f"no{len(argv)}"
        assert main(["tune", "--out", str(out), "--groups", "k_base,edge_gate", *argv]) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("hyqjax tune: --groups edge_gate:") and "probe off" in lines[0]
        assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("argv, match", [(["--preset", "bound_robust"], "bound preset"),
                                         (["--preset", "nosuch"], "tuned_per_leg"),
                                         (["--preset", "tuned_per_leg", "--dim", "shared"], "per-leg set"),
                                         (["--preset", "tuned_per_leg_cond", "--dim", "per_leg"], "conditioned set")])
def test_tune_refuses_a_preset_it_cannot_start_from_in_one_line(argv, match, tmp_path, capsys):
    from hyqjax.cli.app import main

    out = tmp_path / "o"
    assert main(["tune", "--out", str(out), *argv]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and match in lines[0] and lines[0].startswith("hyqjax tune: --preset"), lines
    assert not out.exists() or not any(out.iterdir())
