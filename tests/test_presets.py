"""The preset registry (hyqjax.presets), per-leg crawl parameters (hyqjax.crawl.scheduled) and --preset.

Fast lane: every preset loads into its parameter object; the files are what the stored results give
(experiments/build_presets.py --check); every figure names its held-out set and its command; the presets the
old spellings named are the same parameters (reach = the SNES run + the probe; robust_8s = bound_robust_8s; --remedy
= remedy; hyqjax bound's default = bound_robust); unknown, wrong-kind and out-of-range presets are refused in one
line with exit status 2 and nothing written. Slow: every bounding preset runs a C MuJoCo batch; a per-leg set with
four equal rows runs bit for bit as its CrawlParams on C MuJoCo; every crawl preset runs a CPU batch; `hyqjax
stepdown --preset tuned_per_leg` runs.
"""
from __future__ import annotations

import dataclasses
import json
import os
import types

import jax
import numpy as np
import pytest

from hyqjax import presets
from hyqjax.cli import app as cli
from hyqjax.crawl.params import CrawlParams
from hyqjax.crawl.scheduled import LEGS, PerLegCrawlParams, at_tick, common_structure

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NAMES = ("paper", "remedy", "reach", "clean", "clean_refined", "tuned_shared", "tuned_per_leg", "tuned_per_leg_reach",
         "tuned_per_leg_cond", "bound_paper", "bound_robust", "bound_robust_8s", "bound_robust_grad")
N_CRAWL = 9


def _leaves_equal(a, b) -> bool:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


def _tree(root) -> dict:
    out = {}
    for d, _, files in os.walk(root):
        for f in files:
            out[os.path.relpath(os.path.join(d, f), root)] = os.path.getsize(os.path.join(d, f))
    return out


def test_every_preset_loads_into_its_parameter_object():
    from hyqjax.bounding.params import BoundingParams
    from hyqjax.studies.tune.schedule import ConditionedCrawlParams

    assert tuple(presets.names()) == NAMES
    assert presets.names("crawl") == list(NAMES[:N_CRAWL]) and presets.names("bound") == list(NAMES[N_CRAWL:])
    for n in NAMES:
        rec = presets.get(n)
        assert rec.name == n and rec.kind in presets.KINDS and rec.description and rec.provenance
        p = presets.load(n)
        want = {"crawl": (CrawlParams, PerLegCrawlParams, ConditionedCrawlParams), "bound": (BoundingParams,)}[rec.kind]
        assert isinstance(p, want), n
    assert isinstance(presets.load("tuned_per_leg"), PerLegCrawlParams)
    # crawl keywords reach every row of a per-leg set; a per-leg field is refused as a keyword
    p = presets.load("tuned_per_leg", forward_velocity=0.15)
    assert all(float(p.row(i).forward_velocity) == pytest.approx(0.15) for i in range(4))
    with pytest.raises(presets.PresetError, match="body_height"):
        presets.load("tuned_per_leg", body_height=0.5)


def test_registry_files_are_what_the_stored_results_give():
    from experiments import build_presets

    assert build_presets.main(["--check"]) == 0


def test_every_figure_names_its_heldout_set_device_date_and_command():
    n_figs = 0
    for n in NAMES:
        rec = presets.get(n)
        assert rec.figures, n
        for f in rec.figures:
            n_figs += 1
            for key in ("what", "value", "heldout", "command", "device", "date", "source"):
                assert f.get(key) not in (None, ""), (n, key, f)
            src = f["source"]
            if src.startswith("docs/results/"):  # a stored result: the command that made it, and the value in it
                assert f["command"].startswith(("hyqjax ", "python -m ")), (n, f["command"])
                assert os.path.exists(os.path.join(ROOT, src)), src
            else:  # the 2026-11-29 evaluation: marked unrecorded, with the command that re-measures it if any
                assert f["command"].startswith("unrecorded"), (n, f)
                assert f["date"] == "2026-11-29"
    assert n_figs >= 16
    # Spot checks of values against the files they come from.
    rm = json.load(open(os.path.join(ROOT, "docs/results/reach_recommended_h200/warp_wide/reach_map.json")))
    h90 = {c["variant"]: c["h90"] for c in rm["cells"]}
    assert presets.get("reach").figures[0]["value"] == round(100 * h90["snes_reach_probe_deep"]) == 27
    assert presets.get("paper").figures[0]["value"] == round(100 * h90["default"])
    res = json.load(open(os.path.join(ROOT, "docs/results/bounding_robust_h100_8s/results.json")))
    assert presets.get("bound_robust_8s").figures[0]["value"] == res["heldout"]["methods"]["cma_es"]["failures"] == 0
    ref = json.load(open(os.path.join(ROOT, "docs/results/bounding_refine_h200/results.json")))
    assert ref["heldout"]["target"]["refined"]["met"]
    assert presets.get("bound_robust").figures[0]["value"] == ref["heldout"]["target"]["refined"]["falls"] == 0
    assert presets.get("bound_robust").figures[1]["value"] == round(ref["heldout"]["target"]["refined"]["worst_yaw_deg"], 2) < 4
    assert presets.get("bound_paper").figures[0]["value"] == res["heldout"]["methods"]["default"]["failures"]


def test_old_spellings_are_the_same_parameters():
    from hyqjax.bounding import params as bp
    from hyqjax.bounding import robust as rb
    from hyqjax.crawl import presets as hand
    from hyqjax.studies.tune import tuned

    # reach: the SNES run with the probe settings of the recommended configuration, as --params ... --crawl ...
    snes = tuned.crawl_params(os.path.join(ROOT, "docs/results/tune_reach_h200_10min/snes/results.json"), "snes",
                              **hand.PROBE_DEEP)
    assert _leaves_equal(presets.load("reach"), snes)
    tuned_shared = tuned.crawl_params(os.path.join(ROOT, "docs/results/tune_reach_h200_10min/snes/results.json"),
                                      "snes")
    assert _leaves_equal(presets.load("tuned_shared"), tuned_shared)
    assert _leaves_equal(presets.load("remedy"), CrawlParams.make(**hand.REMEDY)) and hand.REMEDY == dict(
        shin_remedy=True, terrain_adaptation=0.8)
    assert _leaves_equal(presets.load("paper"), CrawlParams.make())
    # the per-leg set: the tuner's rows of its returned theta, leg by leg
    res = json.load(open(os.path.join(ROOT, "docs/results/tune_cells_h200_30min/cma_es_per_leg_30min/results.json")))
    stored = res["runs"]["cma_es/per_leg"]["params"]
    p = presets.load("tuned_per_leg")
    for i, leg in enumerate(LEGS):
        row = p.row(i)
        for key, want in stored.items():
            name, _, rest = key.partition("[")
            if rest.rstrip("]") != leg:
                continue
            obj = row.reflex if hasattr(row.reflex, name) and not hasattr(row, name) else row
            assert float(np.asarray(getattr(obj, name))) == pytest.approx(want, rel=1e-5), key
    # bounding: robust_8s / robust are the presets; default_params is bound_robust; paper_params is bound_paper
    for old, new in (("robust_8s", "bound_robust_8s"), ("robust", "bound_robust_grad")):
        assert _leaves_equal(rb.preset_params(old, speed=0.5), presets.load(new, speed=0.5))
    assert _leaves_equal(bp.default_params(speed=0.5, yaw_rate=0.3), presets.load("bound_robust", speed=0.5,
                                                                                   yaw_rate=0.3))
    assert _leaves_equal(bp.paper_params(speed=0.5, yaw_rate=0.3), presets.load("bound_paper", speed=0.5,
                                                                                 yaw_rate=0.3))
    assert not np.allclose(np.asarray(bp.default_params().gains.k_roll), np.asarray(bp.paper_params().gains.k_roll))


def test_bound_command_defaults_to_bound_robust_and_aliases_the_old_names(tmp_path):
    from hyqjax.cli import bound

    parser = cli.build_parser()
    for argv, want_preset in ((["bound"], "bound_robust"), (["bound", "--preset", "bound_paper"], "bound_paper"),
                              (["bound", "--params", "robust_8s"], "bound_robust_8s"),
                              (["bound", "--params", "robust"], "bound_robust_grad")):
        args = parser.parse_args(argv + ["--out", str(tmp_path / "b")])
        bound.check_options(args)
        assert args.preset == want_preset and args.params is None, argv
    from hyqjax.bounding.params import DEFAULT_PRESET

    assert DEFAULT_PRESET == "bound_robust"


def test_per_leg_rows_and_tick_selection():
    base = CrawlParams.make(shin_remedy=True)
    pl = PerLegCrawlParams.make(base, {"reflex.k_base": dict(LF=100.0, RF=200.0, LH=300.0, RH=400.0),
                                       "body_height": [0.5, 0.52, 0.54, 0.56]})
    for i in range(4):
        assert float(pl.row(i).reflex.k_base) == 100.0 * (i + 1)
        assert float(pl.row(i).body_height) == pytest.approx(0.5 + 0.02 * i)
        assert float(pl.row(i).terrain_adaptation) == float(base.terrain_adaptation)
    seq = np.asarray(base.foot_sequence)
    st = types.SimpleNamespace(sequence=jax.numpy.asarray(seq), seq_index=2)
    assert float(at_tick(pl, st).reflex.k_base) == 100.0 * (seq[2] + 1)  # the row of the leg that swings
    assert float(at_tick(pl).reflex.k_base) == 100.0 * (seq[0] + 1)  # before the first tick: the first leg
    assert at_tick(base, st) is base
    with pytest.raises(ValueError, match=r"reflex.k_base\[RF\]"):
        PerLegCrawlParams.make(base, {"reflex.k_base": [1.0, -5.0, 1.0, 1.0]})
    with pytest.raises(ValueError, match="not a field"):
        PerLegCrawlParams.make(base, {"no_such": [1.0] * 4})
    both = common_structure(dict(a=base, b=pl))
    assert jax.tree_util.tree_structure(both["a"]) == jax.tree_util.tree_structure(both["b"])
    assert all(float(both["a"].row(i).reflex.k_base) == float(base.reflex.k_base) for i in range(4))


@pytest.mark.parametrize("argv, needle", [
    (["stepdown", "--preset", "nope"], "--preset must be one of paper, remedy, reach"),
    (["stepdown", "--preset", "bound_robust"], "bound preset"),
    (["stepdown", "--remedy", "--preset", "reach"], "--remedy"),
    (["bound", "--preset", "reach"], "crawl preset"),
    (["bound", "--preset", "fastest"], "bound_paper, bound_robust, bound_robust_8s, bound_robust_grad"),
    (["bound", "--params", "robust", "--preset", "bound_paper"], "bound_robust_grad"),
    (["sweep", "--preset", "bound_paper", "--dry-run"], "bound preset"),
    (["sweep", "--preset", "tuned_per_leg", "--grid", "reflex_k_base=1000,2000", "--dry-run"], "per leg"),
    (["presets", "nope"], "NAME must be one of"),
])
def test_bad_preset_is_one_line_exit_2_nothing_written(tmp_path, monkeypatch, capsys, argv, needle):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYQJAX_CACHE_DIR", str(tmp_path / "cache-must-not-appear"))
    before = _tree(tmp_path)
    rc = cli.main(argv + (["--out", "out"] if argv[0] != "presets" else []))
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and needle in err and "Traceback" not in err, err
    assert _tree(tmp_path) == before


def test_stored_value_out_of_range_is_refused_naming_the_field(tmp_path, monkeypatch, capsys):
    from hyqjax.presets import registry

    reg = dict(registry._registry())
    bad = {
        "paper": dict(crawl=dict(body_height=9.0), reflex={}),
        "tuned_per_leg": dict(crawl={}, reflex={}, per_leg={"reflex.d_st_min": dict(LF=1.0, RF=-3.0, LH=1.0,
                                                                                      RH=1.0)}),
        "bound_robust": dict(amplitudes={}, gains=dict(k_speed=-5.0)),
    }
    for name, values in bad.items():
        reg[name] = dataclasses.replace(reg[name], values=values)
    monkeypatch.setattr(registry, "_registry", lambda: reg)
    for name, field in (("paper", "body_height"), ("tuned_per_leg", "d_st_min[RF]"), ("bound_robust", "k_speed")):
        with pytest.raises(presets.PresetError, match=field.replace("[", r"\[").replace("]", r"\]")):
            presets.load(name)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYQJAX_CACHE_DIR", str(tmp_path / "cache-must-not-appear"))
    for argv, field in ((["stepdown", "--preset", "paper"], "body_height"), (["stepdown"], "body_height"),
                        (["bound"], "k_speed")):
        before = _tree(tmp_path)
        rc = cli.main(argv + ["--out", "out"])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("\n") == 1 and field in err, err
        assert _tree(tmp_path) == before


def test_presets_command_lists_every_preset_with_figures(capsys):
    assert cli.main(["presets"]) == 0
    out = capsys.readouterr().out
    for n in NAMES:
        assert f"\n{n} " in "\n" + out
    assert "h90, wide spread: 27 cm" in out and "0 of 4,096" in out
    assert cli.main(["presets", "tuned_per_leg"]) == 0
    one = capsys.readouterr().out
    assert "per leg reflex.k_base: LF" in one and "command: hyqjax tune" in one
    assert cli.main(["presets", "--kind", "bound", "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert [g["name"] for g in got] == list(NAMES[N_CRAWL:])


@pytest.mark.slow
def test_per_leg_set_with_equal_rows_runs_bit_for_bit_as_its_crawl_params():
    """Four equal rows of the per-leg fields: the same outcome columns and traces, bit for bit, as the
    CrawlParams itself (C MuJoCo, 2 instances x 3 s)."""
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    base = CrawlParams.make(shin_remedy=True)
    pl = PerLegCrawlParams.uniform(base, ("reflex.k_base", "reflex.d_st_max", "body_height", "step_height"))
    cfg = stepdown.StepdownConfig(duration=3.0, impl="c", record_every=10)
    r = stepdown.make_stepdown_rollout(cfg)
    got = []
    for p in (base, pl):
        sc, _ = stepdown.make_scenarios([0.16], [True], 2, 3, params=p)
        o, res = r.run(sc)
        got.append((so.to_columns(o), jax.tree_util.tree_map(np.asarray, res.trace)))
    (c0, t0), (c1, t1) = got
    for k in c0:
        np.testing.assert_array_equal(c0[k], c1[k], err_msg=k)
    for k in t0:
        np.testing.assert_array_equal(t0[k], t1[k], err_msg=k)
    assert np.ptp(t0["base_pos"][..., 0]) > 0.0  # the runs moved


@pytest.mark.slow
def test_every_crawl_preset_runs_a_cpu_batch():
    """The five crawl presets in one C MuJoCo batch (one instance each, 16 cm, 6 s): no divergence, every crawl
    walks forward and steps."""
    from experiments import reach_map
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    names = [n for n in presets.names("crawl") if not presets.get(n).values.get("conditioned")]
    params = common_structure({n: presets.load(n) for n in names})
    rows = reach_map.build_rows(names, ["narrow"], [0.16], 1, 5)
    sc = reach_map.scenario_of(rows, np.arange(len(rows["height"])), params)
    out, _ = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=6.0, impl="c")).run(sc)
    cols = so.to_columns(out)
    assert list(rows["variant"]) == names
    assert not cols["diverged"].any(), cols["diverged"]
    assert np.all(cols["progress"] > 0.05), dict(zip(names, cols["progress"]))
    assert np.all(cols["n_steps"] >= 2), dict(zip(names, cols["n_steps"]))


@pytest.mark.slow
def test_every_bound_preset_runs_a_cpu_batch(tmp_path):
    """Every bounding preset in one C MuJoCo batch (experiments.bounding_presets: the nominal command and the four
    corners at friction 0.5-0.6 with 10 kg, one 2.4 s run each): none diverges or falls at the nominal command; the
    robust presets stand at every command with a yaw error under the paper's 4 deg, and the default's worst yaw at low
    friction is below the paper's gains'."""
    from experiments import bounding_presets as bpre

    names = presets.names("bound")
    assert bpre.main(["--impl", "c", "--instances", "1", "--duration", "2.4", "--presets", *names,
                      "--out", str(tmp_path / "bp")]) == 0
    rows = json.load(open(tmp_path / "bp" / "bounding_presets.json"))["rows"]
    assert {r["preset"] for r in rows} == set(names) and len(rows) == 6 * len(names)
    assert all(r["failures"] == 0 for r in rows if r["condition"] == "nominal"), rows
    robust = [r for r in rows if r["preset"].startswith("bound_robust")]
    assert all(r["failures"] == 0 and r["yaw_error_worst_deg"] < 4.0 for r in robust), robust

    def worst(p):
        return max(r["yaw_error_worst_deg"] for r in rows if r["preset"] == p and r["condition"] != "nominal")

    assert worst("bound_robust") < worst("bound_paper")


@pytest.mark.slow
def test_stepdown_runs_the_per_leg_preset(tmp_path, capsys):
    rc = cli.main(["stepdown", "--preset", "tuned_per_leg", "--instances", "1", "--impl", "c", "--heights", "0.16",
                   "--reflex", "on", "--duration", "10", "--out", str(tmp_path / "sd")])
    out = capsys.readouterr().out
    assert rc == 0
    res = json.load(open(tmp_path / "sd" / "results.json"))
    assert res["config"]["preset"] == "tuned_per_leg" and len(res["instances"]) == 1
    assert res["preset"]["values"] == presets.get("tuned_per_leg").values  # what ran, in the results
    assert not res["instances"][0]["diverged"] and res["instances"][0]["progress"] > 0.1
    lines = out.rstrip().splitlines()
    assert lines[-1].startswith("wall ") and lines[-2].startswith(
        "best measured crawls: --preset clean_refined (93.5% clean up to 26 cm")
    # ... and its recording renders as any other: one frame per 100 recorded samples of the 10 s run
    from PIL import Image

    gif = str(tmp_path / "sd.gif")
    rc = cli.main(["render", str(tmp_path / "sd"), "--width", "48", "--height", "32", "--stride", "100", "--out", gif])
    assert rc == 0, capsys.readouterr().err
    with Image.open(gif) as im:
        assert im.n_frames == 5 and im.size[0] == 48


def test_per_leg_and_conditioned_tuning_runs_are_read_as_scheduled_sets(tmp_path):
    """``--params RESULTS`` of a per-leg run gives the per-leg set (the preset tuned_per_leg is that of the 30-min
    CMA-ES run), of a conditioned run the conditioned set (tuned_per_leg_cond: the hybrid run's), whose choice at a
    tick is the tuner's own (Parameterisation.params_at of the same rows and conditioning)."""
    import jax.numpy as jnp

    from hyqjax.studies.tune import schedule
    from hyqjax.cli import stepdown as sd
    from hyqjax.studies.tune import tuned

    src = os.path.join(ROOT, "docs/results/tune_cells_h200_30min/cma_es_per_leg_30min/results.json")
    p = tuned.crawl_params(src, None, forward_velocity=0.1)
    assert isinstance(p, PerLegCrawlParams) and _leaves_equal(p, presets.load("tuned_per_leg"))
    args = cli.build_parser().parse_args(["stepdown", "--params", src, "--out", str(tmp_path / "sd")])
    sd.validate(args)
    assert isinstance(args.tuned_params, PerLegCrawlParams) and args.preset is None
    cond = os.path.join(ROOT, "docs/results/tune_wallclock_h200_10min_68/results.json")
    with pytest.raises(ValueError, match="name one as PATH:RUN") as e:
        tuned.crawl_params(cond, None)
    assert "\n" not in str(e.value)
    c = tuned.crawl_params(cond, "hybrid")
    assert isinstance(c, schedule.ConditionedCrawlParams) and _leaves_equal(c, presets.load("tuned_per_leg_cond"))
    res = json.load(open(cond))
    pz = schedule.make("per_leg_cond", res["config"]["groups"])
    sp = pz.scheduled(jnp.asarray(res["runs"]["hybrid/per_leg_cond"]["theta"], jnp.float32), c.base)
    seq = np.asarray(c.base.foot_sequence)
    st = types.SimpleNamespace(sequence=jnp.asarray(seq), seq_index=1, search_depth=jnp.float32(0.1),
                               deep=jnp.asarray([True, False, False, False]))
    obs = types.SimpleNamespace(foot_force=jnp.full((4, 3), 250.0, jnp.float32))
    got = c.at_tick(st, obs)
    want = pz.params_at(sp, seq[1], schedule.features(st, obs))
    assert _leaves_equal(got, want)
    other_leg = types.SimpleNamespace(**{**vars(st), "seq_index": 3})
    assert not np.isclose(float(got.reflex.k_base), float(c.at_tick(other_leg, obs).reflex.k_base))
    with pytest.raises(ValueError, match="body_height"):
        presets.load("tuned_per_leg_cond", body_height=0.5)


@pytest.mark.slow
def test_conditioned_preset_runs_a_cpu_batch():
    """tuned_per_leg_cond in a C MuJoCo batch of two (16 cm, 6 s): no divergence, both walk forward and step."""
    from hyqjax.studies import stepdown
    from hyqjax.studies import stepdown_outcome as so

    sc, _ = stepdown.make_scenarios([0.16], [True], 2, 5, params=presets.load("tuned_per_leg_cond"))
    out, _ = stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=6.0, impl="c")).run(sc)
    cols = so.to_columns(out)
    assert not cols["diverged"].any() and np.all(cols["progress"] > 0.05) and np.all(cols["n_steps"] >= 2), cols


def test_docs_presets_table_lists_every_preset_with_its_kind():
    """docs/presets.md's table: one row per registry preset, in the registry's order, with its kind."""
    rows = [line.split("|")[1:3] for line in open(os.path.join(ROOT, "docs", "presets.md")).read().splitlines()
            if line.startswith("| `")]
    got = [(name.strip().strip("`"), kind.strip()) for name, kind in rows]
    assert got == [(n, presets.get(n).kind) for n in presets.names()]


def test_sweep_spec_preset_sets_the_fields_no_axis_names():
    """A sweep spec's ``preset``: its values wherever no axis sets the field, an axis wins where it does; the hash
    of a spec without a preset is unchanged by the new field."""
    from hyqjax.studies.sweep.scenario import build_scenario
    from hyqjax.studies.sweep.spec import SweepSpec

    plain = SweepSpec.from_dict(dict(grid=dict(height=[0.16])))
    assert "preset" not in plain.to_dict()
    spec = SweepSpec.from_dict(dict(grid=dict(height=[0.16]), fixed=dict(reflex_d_st_max=900.0), preset="reach"))
    assert spec.spec_hash != plain.spec_hash and SweepSpec.from_dict(spec.to_dict()) == spec
    reach = presets.load("reach")
    rows = spec.instance_inputs(0, 1)
    assert rows["reflex_k_base"][0] == pytest.approx(float(reach.reflex.k_base), rel=1e-6)
    sc, _ = build_scenario(rows, spec)
    assert float(sc.params.edge_probe[0]) == pytest.approx(0.1) and float(sc.params.reflex.d_st_max[0]) == 900.0
    assert float(sc.params.reflex.k_base[0]) == pytest.approx(float(reach.reflex.k_base), rel=1e-6)
    per_leg = SweepSpec.from_dict(dict(grid=dict(height=[0.16]), preset="tuned_per_leg"))
    pl = build_scenario(per_leg.instance_inputs(0, 1), per_leg)[0].params
    assert isinstance(pl, PerLegCrawlParams) and pl.legs["reflex.k_base"].shape == (1, 4)
