"""The reach map study (experiments/reach_map.py): options refused before compiling, the reach definitions, the tuned
parameters loaded from a tuning study, and a tiny CPU run that writes, resumes and summarises its chunks."""
from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # the repository's experiments/
from experiments import reach_map  # noqa: E402


@pytest.mark.parametrize("argv, needle", [
    (["--spread", "medium"], "--spread 'medium'"),
    (["--variants", "nope"], "--variants 'nope'"),
    (["--custom", "x:terrain_adaptation=2", "--variants", "x"], "variant x"),
    (["--custom", "x:no_such_field=1"], "no_such_field"),
    (["--heights", "0.6"], "--heights 0.6"),
    (["--instances", "0"], "--instances 0"),
    (["--impl", "cuda"], "--impl 'cuda'"),
    (["--variants", "tuned", "--tuned-method", "nope"], "--tuned-method 'nope'"),
    (["--tuned-run", "only_a_name"], "--tuned-run 'only_a_name'"),
    (["--tuned-run", "remedy:x.json:cma_es"], "--tuned-run 'remedy:x.json:cma_es'"),
    (["--tuned-run", "v:x.json:cma_es", "--custom", "v:terrain_adaptation=0.5"], "--tuned-run 'v'"),
    (["--tuned-run", "t1:/no/such/results.json:cma_es", "--variants", "t1"], "/no/such/results.json"),
    (["--tuned-run", "t1:x.json:snes:bogus=1", "--variants", "t1"], "--tuned-run t1"),
])
def test_bad_options_are_one_line_and_exit_2_before_compiling(argv, needle, tmp_path, capsys):
    assert reach_map.main(["--out", str(tmp_path / "m"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert needle in err and "\n" not in err, err
    assert not os.path.exists(tmp_path / "m")


def test_reach_is_the_tallest_height_passing_at_every_height_below():
    from hyqjax.studies import statistics

    h = np.repeat([0.14, 0.16, 0.18, 0.20], 100)
    ok = np.concatenate([np.ones(100), np.r_[np.ones(95), np.zeros(5)], np.r_[np.ones(80), np.zeros(20)],
                         np.ones(100)]).astype(bool)
    curve = statistics.success_curve(h, ok)
    point, wilson = reach_map.reach(curve, 0.90)
    assert point == 0.16  # 18 cm fails (80%), so 20 cm (100%) does not count
    assert wilson == 0.14  # 95/100 has a Wilson lower bound of 0.888 < 0.90


def test_tuned_variant_is_the_study_selected_parameters():
    p = reach_map.tuned_params(reach_map.DEFAULT_TUNED, "gradient")
    with open(reach_map.DEFAULT_TUNED) as f:
        want = json.load(f)["gradient"]["params"]
    assert float(p.reflex.k_base) == pytest.approx(want["k_base"], rel=1e-5)
    assert float(p.terrain_adaptation) == pytest.approx(want["terrain_adaptation"], rel=1e-5)
    assert float(p.search_forward) == pytest.approx(want["search_forward"], rel=1e-5)
    assert float(p.shin_remedy) == 1.0


def test_tuned_run_settings_go_under_the_tuned_values_and_never_replace_one():
    """``--tuned-run NAME:PATH:METHOD:field=value,...``: the settings of fields the run did not tune are set (the
    tuned ones are the run's), and a tuned field or an out-of-range value is refused in one line naming it."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "results",
                        "tune_repeats_h100_10min", "snes_s1", "results.json")
    name, (p, m, settings) = reach_map.parse_tuned_run(f"v:{path}:snes:edge_probe=0.1,edge_lowering=0.01")
    assert name == "v" and settings == {"edge_probe": 0.1, "edge_lowering": 0.01}
    plain = reach_map.variant_params(["a"], {}, "", "", {"a": (p, m, {})})["a"]
    probe = reach_map.variant_params(["b"], {}, "", "", {"b": (p, m, settings)})["b"]
    assert float(probe.edge_probe) == pytest.approx(0.1) and float(plain.edge_probe) == 0.0
    assert float(probe.edge_lowering) == pytest.approx(0.01)
    for field in ("k_base", "terrain_adaptation", "search_forward"):
        a = getattr(plain.reflex, field) if field == "k_base" else getattr(plain, field)
        b = getattr(probe.reflex, field) if field == "k_base" else getattr(probe, field)
        assert float(a) == float(b)
    with pytest.raises(reach_map.UsageError, match="terrain_adaptation: tuned by run"):
        reach_map.variant_params(["c"], {}, "", "", {"c": (p, m, {"terrain_adaptation": 0.5})})
    with pytest.raises(reach_map.UsageError, match=r"edge_probe=0.5 out of range"):
        reach_map.variant_params(["d"], {}, "", "", {"d": (p, m, {"edge_probe": 0.5})})


def _study_copy(tmp_path, run: str):
    """A stored 10-minute run's ``results.json`` (``docs/results/tune_repeats_h100_10min/RUN``) reduced to its
    configuration and runs, written to ``tmp_path``; returns ``(results, path)``."""
    src = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "tune_repeats_h100_10min", run,
                       "results.json")
    with open(src) as f:
        res = json.load(f)
    path = tmp_path / "results.json"
    path.write_text(json.dumps(dict(config=res["config"], runs=res["runs"])))
    return res, path


def test_tuned_variant_reads_what_the_default_tuner_hands_back(tmp_path):
    """The equal-wall-clock study's layout (``runs["cma_es/shared"]``): its ``theta`` gives exactly the parameters
    the study stored next to it; a method the file lacks is one line naming what it has."""
    res, path = _study_copy(tmp_path, "cma_es_s1")
    want = res["runs"]["cma_es/shared"]["params"]
    for method in ("cma_es", "cma_es/shared"):
        p = reach_map.tuned_params(str(path), method)
        assert float(p.reflex.k_base) == pytest.approx(want["k_base"], rel=1e-5)
        assert float(p.reflex.d_st_max) == pytest.approx(want["d_st_max"], rel=1e-5)
        assert float(p.max_step_length) == pytest.approx(want["max_step_length"], rel=1e-5)
        assert float(p.terrain_adaptation) == pytest.approx(want["terrain_adaptation"], rel=1e-5)
    with pytest.raises(reach_map.UsageError, match="cma_es/shared"):
        reach_map.tuned_params(str(path), "snes")


def test_stepdown_params_are_the_run_s_theta_over_the_user_s_other_settings(tmp_path):
    """``hyqjax stepdown --params``' reader: the run's tuned values exactly as the study stored them, the user's
    speed and untuned fields on top, the run's remedy setting kept."""
    from hyqjax.studies.tune import tuned

    res, path = _study_copy(tmp_path, "snes_s1")
    want = res["runs"]["snes/shared"]["params"]
    p = tuned.crawl_params(str(path), None, forward_velocity=0.07, stance_min_force=1.0)
    assert float(p.forward_velocity) == pytest.approx(0.07)
    assert float(p.stance_min_force) == pytest.approx(1.0)
    assert float(p.shin_remedy) == float(res["config"]["remedy"])
    for k in ("body_height", "max_step_length", "search_forward", "terrain_adaptation", "step_height"):
        assert float(getattr(p, k)) == pytest.approx(want[k], rel=1e-5), k
    for k in ("k_base", "d_st_max", "d_sw_min"):
        assert float(getattr(p.reflex, k)) == pytest.approx(want[k], rel=1e-5), k


@pytest.mark.slow
def test_tiny_cpu_map_writes_resumes_and_counts_every_instance(tmp_path):
    out = tmp_path / "map"
    argv = ["--out", str(out), "--impl", "c", "--instances", "1", "--heights", "0.16", "0.24", "--duration", "0.6",
            "--variants", "default", "remedy_all", "--spread", "narrow", "--chunk", "4"]
    assert reach_map.main(argv) == 0
    res = json.loads((out / "reach_map.json").read_text())
    assert res["n_instances"] == 4 and (out / "reach_map.png").exists()
    cells = {c["variant"]: c for c in res["cells"]}
    assert set(cells) == {"default", "remedy_all"}
    for c in cells.values():
        assert [p["n"] for p in c["per_height"]] == [1, 1]
        # 0.6 s: nobody has stepped down yet, nothing completed, nothing fell or diverged
        assert c["h90"] is None and c["diverged"] == 0 and c["terminated"] == 0
        assert all(p["reasons"]["feet_not_down"] == 1.0 for p in c["per_height"])
    chunk = out / "chunks" / "00000.npz"
    mtime = chunk.stat().st_mtime_ns
    assert reach_map.main(argv) == 0  # resumed: the chunk is read, not recomputed
    assert chunk.stat().st_mtime_ns == mtime
    assert json.loads((out / "reach_map.json").read_text())["cells"] == res["cells"]
    # another configuration in the same directory is refused
    assert reach_map.main([*argv[:-2], "--chunk", "2", "--seed", "1"]) == 2


def test_factor_shares_split_every_run_into_thirds_of_the_spread_range():
    from hyqjax.studies import stepdown_outcome as so

    rng = np.random.default_rng(0)
    n = 600
    lo, hi = reach_map.SPREADS["wide"]["start_distance"]
    rows = dict(start_distance=np.r_[rng.uniform(lo, hi, n - 2), lo, hi].astype(np.float32),
                friction=rng.uniform(0.4, 1.0, n).astype(np.float32),
                payload_mass=rng.uniform(0.0, 15.0, n).astype(np.float32),
                height=np.full(n, 0.24), spread=np.full(n, "wide"), variant=np.full(n, "remedy"))
    # a crawl that completes exactly when it starts in the first 5 cm, and falls when friction is below 0.6
    out = {k: np.zeros(n, bool) for k in (*so.FAILURE_REASONS, "terminated")}
    out["completed"] = rows["start_distance"] < 0.05
    out["clean"] = out["completed"] & (rows["payload_mass"] > 5.0)
    out["terminated"] = out["tilt"] = rows["friction"] < 0.6
    mask = np.ones(n, bool)
    res = reach_map.factor_shares(rows, out, mask, "wide")
    assert set(res) == {"start_distance", "friction", "payload_mass"}
    for parts in res.values():
        assert sum(p["n"] for p in parts) == n  # both ends of the range included, nothing dropped
    sd = res["start_distance"]
    assert np.allclose([p["range"] for p in sd], [[0.0, 0.05], [0.05, 0.10], [0.10, 0.15]])
    assert [p["completed"] for p in sd] == [1.0, 0.0, 0.0]
    assert [p["terminated"] for p in res["friction"]] == [1.0, 0.0, 0.0]
    assert res["friction"][0]["tilt"] == 1.0
    x = rows["payload_mass"]
    want = [out["clean"][(x >= a) & (x < b)].mean() for a, b in ((0, 5), (5, 10))]
    assert [p["clean"] for p in res["payload_mass"][:2]] == pytest.approx(want)
    assert res["payload_mass"][0]["clean"] == 0.0
    # an empty part is None, not a made-up share
    empty = reach_map.factor_shares(rows, out, rows["start_distance"] < 0.05, "wide")["start_distance"]
    assert empty[0]["n"] > 0 and empty[2]["n"] == 0 and empty[2]["completed"] is None
    cells = reach_map.summarise(rows, out, ["remedy"], ["wide"])
    assert cells[0]["per_height"][0]["by_factor"] == res
