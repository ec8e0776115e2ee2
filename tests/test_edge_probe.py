"""Edge localisation by a probing step (hyqjax.crawl.edge): off by default, its bounds bracket the platform's edge.

The step-down runs are short C MuJoCo batches (6 s at 24 cm: the first front leg finds the step down at about 3.7 s
and the other front leg's probe ends by 5 s), far starts (11-14 cm before the edge) and near ones (1-4 cm).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hyqjax.core.params import ParameterError
from hyqjax.crawl import edge
from hyqjax.crawl.params import CrawlParams, parse_settings
from hyqjax.studies import stepdown

REMEDY = dict(shin_remedy=True, terrain_adaptation=0.8)


def _run(params, starts, duration=6.0, instances=2):
    sc, table = stepdown.make_scenarios([0.24], [True], instances=instances, seed=3, start_distance=starts,
                                        friction=(0.9, 1.0), payload=(0.0, 2.0), lateral=(0.0, 0.0), yaw=(0.0, 0.0),
                                        params=params)
    return stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=duration, impl="c", record_every=5)).run(sc)


def _edge_in_world(res, i):
    """The final state's edge bounds in world x (the platform's edge is at x = 0): the current ``H0``'s origin
    from its stance feet, which have not moved in the world since the phase started (no yaw in these runs)."""
    cs = res.ctrl_state
    stance, feet_h0 = np.asarray(cs.stance[i]), np.asarray(cs.feet_h0[i])
    feet_world = np.asarray(res.trace["feet_world"][i, -1])
    origin = np.sum(stance * (feet_world[:, 0] - feet_h0[:, 0])) / stance.sum()
    return float(cs.edge_lo[i]) + origin, float(cs.edge_hi[i]) + origin


def test_a_bad_probe_setting_is_refused_in_one_line_naming_it_and_its_range():
    for name, bad in (("edge_probe", 0.5), ("edge_probe_depth", -0.01), ("edge_tilt", 1.5), ("edge_margin", 0.4),
                      ("edge_lowering", 0.15), ("edge_deep", 1.5), ("edge_tilt_deep", -0.1)):
        with pytest.raises(ParameterError) as e:
            CrawlParams.make(**{name: bad})
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"CrawlParams.{name}={bad:g} out of range: must be in ["), msg
        with pytest.raises(ParameterError, match=f"CrawlParams.{name}="):
            CrawlParams.make().replace(**{name: np.float32(bad)})
    assert parse_settings("edge_probe=0.1,edge_tilt=0.3") == dict(edge_probe=0.1, edge_tilt=0.3)
    assert parse_settings("edge_lowering=0.03") == dict(edge_lowering=0.03)


def test_the_trunk_is_lowered_only_while_a_front_hip_is_behind_the_edge():
    """``edge_lowering`` lowers the body phase's trunk target only where a front hip ends behind the edge's far
    bound plus ``edge_margin``; at 0, with the hips past and without a known edge the target is bitwise unchanged."""

    class St:  # the bounds the gate reads, in H0
        edge_lo, edge_hi = np.float32(0.0), np.float32(0.2)

    class Unknown:  # no step down yet
        edge_lo, edge_hi = np.float32(-edge.EDGE_UNKNOWN), np.float32(edge.EDGE_UNKNOWN)

    level = jnp.eye(3, dtype=jnp.float32)  # hR_b of a level trunk
    delta = jnp.array([-0.3, 0.0, 0.5], jnp.float32)  # front hips end at about +0.07 m

    def same(p, st):
        return np.asarray(edge.lowered(p, st, level, delta)).tobytes() == np.asarray(delta).tobytes()

    base = CrawlParams.make(**REMEDY, edge_probe=0.1, edge_tilt=0.3)
    assert bool(edge.behind(base, St, level, delta)) and same(base, St)
    low = base.replace(edge_lowering=np.float32(0.03))
    np.testing.assert_allclose(np.asarray(edge.lowered(low, St, level, delta)), [-0.3, 0.0, 0.47], atol=1e-6)
    past = low.replace(edge_margin=np.float32(-0.2))  # the hips are past 0.2 - 0.2 = 0
    assert not bool(edge.behind(past, St, level, delta)) and same(past, St) and same(low, Unknown)
    assert same(low.replace(edge_probe=np.float32(0.0)), St)


@pytest.mark.slow
def test_probe_off_leaves_every_output_bitwise_unchanged():
    """At ``edge_probe = 0`` the other probe settings change nothing: outcomes, traces, final state and the
    crawl's own memory are bitwise those of the defaults (the option's code paths are all ``where``-gated)."""
    base = CrawlParams.make(**REMEDY)
    other = CrawlParams.make(**REMEDY, edge_probe_depth=0.1, edge_tilt=1.0, edge_margin=-0.2, edge_lowering=0.1,
                             edge_deep=0.0, edge_tilt_deep=1.0)
    runs = [_run(p, (0.0, 0.15)) for p in (base, other)]  # 6 s: the program of the tests below
    (out_a, res_a), (out_b, res_b) = runs
    for a, b in zip(jax.tree.leaves((out_a, res_a.data.qpos, res_a.trace, res_a.ctrl_state)),
                    jax.tree.leaves((out_b, res_b.data.qpos, res_b.trace, res_b.ctrl_state))):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    assert not np.any(np.asarray(res_a.ctrl_state.probing)) and np.all(np.asarray(res_a.ctrl_state.probe_leg) == -1)


@pytest.mark.slow
@pytest.mark.parametrize("starts, hit", [((0.11, 0.14), True), ((0.01, 0.04), False)])
def test_the_probe_brackets_the_true_edge(starts, hit):
    """After the first front leg's step down and the other front leg's probe (10 cm), the bounds hold the
    platform's edge (world x = 0); a far start's probe lands on the platform (the near bound moves up to the probe
    point), a near start's misses it (the far bound falls to the probe point: a window of the probe's length)."""
    p = CrawlParams.make(**REMEDY, edge_probe=0.1)
    out, res = _run(p, starts)
    cs = res.ctrl_state
    for i in range(2):
        assert bool(edge.known(cs.edge_hi[i])) and int(cs.probe_leg[i]) == -1 and not bool(cs.probing[i])
        lo, hi = _edge_in_world(res, i)
        assert lo < 0.0 < hi, (starts, lo, hi)
        if hit:  # the near bound is the probe point: about the start distance less the probe ahead of the edge
            assert lo > -0.06 and hi - lo > 0.15, (lo, hi)
        else:
            assert hi - lo < 0.1 + 0.02, (lo, hi)
    assert not np.any(np.asarray(out.lost_foothold))  # the probe's miss is no stance trigger in the air


def test_the_gate_tilts_by_the_measured_depth():
    """Behind the edge the gate follows ``edge_tilt_deep`` where the measured step is deeper than ``edge_deep``,
    ``edge_tilt`` where it is not, and the crawl's own share where the hips are past (or the probe is off)."""
    p = CrawlParams.make(**REMEDY, edge_probe=0.1, edge_tilt=0.3, edge_deep=0.255, edge_tilt_deep=0.5)
    level, behind_delta = jnp.eye(3), jnp.zeros(3)

    class St:
        edge_lo, edge_hi = np.float32(0.2), np.float32(0.6)  # the hips (x about 0.37) are behind it

    for depth, want in ((0.24, 0.3), (0.27, 0.5)):
        St.edge_depth = np.float32(depth)
        assert float(edge.tilt_share(p, St, 0.8, level, behind_delta)) == pytest.approx(want)
    St.edge_lo, St.edge_hi = np.float32(-0.6), np.float32(-0.2)  # hips past the edge
    assert float(edge.tilt_share(p, St, 0.8, level, behind_delta)) == pytest.approx(0.8)
    off = p.replace(edge_probe=np.float32(0.0))
    assert float(edge.tilt_share(off, St, 0.8, level, behind_delta)) == pytest.approx(0.8)
