"""The start-distance profile of a stored reach map (``experiments.start_distance_profile``): its bins agree with the
map's own ``by_factor.start_distance`` thirds, its intervals hold their rates, the stored profile is the one the npz
gives, bad input is refused in one line, and (slow, C MuJoCo) a far start strikes a shin where a near one is clean."""
import json
import os

import numpy as np
import pytest

from experiments import start_distance_profile as sdp

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MAP = os.path.join(ROOT, "docs", "results", "tune_default_repeats_leading_foot_h200", "confirm_31415")
NPZ = os.path.join(MAP, "reach_instances.npz")
STORED = os.path.join(ROOT, "docs", "results", "tune_default_repeats_leading_foot_h200", "start_distance_profile")


@pytest.fixture(scope="module")
def inst():
    return sdp.load_instances(NPZ)


def test_five_cm_bins_are_the_reach_maps_thirds(inst):
    """Binned at 5 cm, one height at a time, the profile's counts, clean and shin-strike shares are those of the
    stored reach_map.json's ``by_factor.start_distance`` (48 cells: 4 variants x 12 heights, 3 thirds each)."""
    with open(os.path.join(MAP, "reach_map.json"), encoding="utf-8") as f:
        cells = json.load(f)["cells"]
    lo, hi = sdp.spread_range(NPZ, inst)
    assert (lo, hi) == (0.0, 0.15)
    edges = sdp.bin_edges(lo, hi, 0.05)
    checked = 0
    for cell in cells:
        for ph in cell["per_height"]:
            rows = sdp.profile(inst, edges, ph["height"], ph["height"], [cell["variant"]])
            thirds = ph["by_factor"]["start_distance"]
            assert [r["n"] for r in rows] == [t["n"] for t in thirds]
            assert sum(r["n"] for r in rows) == ph["n"]
            for r, t in zip(rows, thirds):
                assert r["clean_rate"] == pytest.approx(t["clean"], abs=1e-12)
                assert r["shin_strike_rate"] == pytest.approx(t["shin_strike"], abs=1e-12)
                assert r["completed_rate"] == pytest.approx(t["completed"], abs=1e-12)
            assert sum(r["clean"] for r in rows) == ph["clean"]
            checked += 1
    assert checked == 48


def test_one_cm_bins_cover_every_run_and_their_intervals_hold_their_rates(inst):
    from hyqjax.studies import statistics

    edges = sdp.bin_edges(0.0, 0.15, 0.01)
    assert len(edges) == 16 and edges[-1] == 0.15
    rows = sdp.profile(inst, edges, 0.0, 0.26)
    h = inst["height"]
    for v in ("reach", "tuned_per_leg_reach", "run_1", "run_4"):
        mine = [r for r in rows if r["variant"] == v]
        assert sum(r["n"] for r in mine) == int(((inst["variant"] == v) & (h <= 0.26 + 1e-9)).sum()) == 5120
        for r in mine:
            lo, hi = r["clean_ci95"]
            assert lo <= r["clean_rate"] <= hi and 0.0 <= lo < hi <= 1.0
            assert (lo, hi) == statistics.wilson_interval(r["clean"], r["n"])
    # the collapse the profile shows: reach clean in the last bin far below the first (measured: 7% against 100%)
    reach = [r for r in rows if r["variant"] == "reach"]
    assert reach[-1]["clean_rate"] < 0.2 and reach[0]["clean_rate"] > 0.95


def test_heading_bins_split_every_start_bin_without_losing_a_run(inst):
    edges = sdp.bin_edges(0.0, 0.15, 0.02)
    whole = sdp.profile(inst, edges, 0.0, 0.26, ["reach", "run_1"])
    ylo, yhi = sdp.spread_range(NPZ, inst, "yaw")
    assert (ylo, yhi) == (-0.1, 0.1)
    split = sdp.profile(inst, edges, 0.0, 0.26, ["reach", "run_1"], np.linspace(ylo, yhi, 5))
    assert len(split) == 4 * len(whole)
    for i, w in enumerate(whole):
        part = split[4 * i: 4 * i + 4]
        assert {(p["variant"], p["lo"]) for p in part} == {(w["variant"], w["lo"])}
        assert [p["yaw_lo"] for p in part] == pytest.approx([-0.1, -0.05, 0.0, 0.05])
        assert sum(p["n"] for p in part) == w["n"] and sum(p["clean"] for p in part) == w["clean"]
        assert sum(p["shin_strike"] for p in part) == w["shin_strike"]


def test_the_shaded_starts_are_the_tuners_train_spread():
    from hyqjax.studies.tune import forward

    assert sdp.TRAIN_SPREAD_STARTS == forward.TRAIN_RANGES["start_distance"]


def test_a_bin_width_that_does_not_divide_the_range_keeps_a_narrower_last_bin():
    e = sdp.bin_edges(0.0, 0.15, 0.04)
    assert np.allclose(e, [0.0, 0.04, 0.08, 0.12, 0.15])


def test_the_stored_profile_is_the_one_the_npz_gives(inst):
    """docs/results/.../start_distance_profile/profile.json, read back, equals a recompute from the npz."""
    with open(os.path.join(STORED, "profile.json"), encoding="utf-8") as f:
        stored = json.load(f)
    rows = sdp.profile(inst, np.asarray(stored["edges"]), min(stored["heights"]), max(stored["heights"]))
    assert len(rows) == len(stored["rows"]) == 4 * 15
    for a, b in zip(rows, stored["rows"]):
        assert (a["variant"], a["n"], a["clean"], a["shin_strike"]) == (b["variant"], b["n"], b["clean"],
                                                                        b["shin_strike"])
    assert os.path.isfile(os.path.join(STORED, stored["figure"]))


def test_profile_writes_its_table_and_figure(tmp_path):
    out = tmp_path / "p"
    assert sdp.main([NPZ, "--out", str(out), "--bin-width", "0.05", "--variants", "reach", "run_1"]) == 0
    stored = json.loads((out / "profile.json").read_text())
    assert [r["variant"] for r in stored["rows"]] == ["reach"] * 3 + ["run_1"] * 3
    md = (out / "profile.md").read_text().splitlines()
    assert md[2].startswith("| start (cm) | n | `reach` clean % [95%]") and len(md) == 4 + 3
    assert (out / "profile.png").stat().st_size > 1000


@pytest.mark.parametrize("argv, names", [
    (["nope.npz"], "instances"),
    (["--bin-width", "0"], "--bin-width"),
    (["--bin-width", "0.2"], "--bin-width"),
    (["--min-height", "0.3", "--max-height", "0.2"], "--min-height"),
    (["--min-height", "0.35", "--max-height", "0.38"], "--min-height"),
    (["--variants", "reach", "nosuch"], "--variants"),
    (["--split-yaw", "1"], "--split-yaw"),
    (["--mode", "nosuch"], "--mode"),
    (["--mode", "mechanism", "--preset", "bound_paper"], "--preset"),
    (["--mode", "mechanism", "--starts", "0.15", "0.08", "0.005"], "--starts"),
    (["--mode", "mechanism", "--heights", "0.5"], "--heights"),
    (["--mode", "mechanism", "--yaw", "0.5"], "--yaw"),
    (["--mode", "mechanism", "--tuned-run", "nocolons"], "--tuned-run"),
    (["--mode", "mechanism", "--tuned-run", "x:no/such/results.json:cma_es"], "--tuned-run"),
])
def test_bad_input_is_refused_in_one_line(tmp_path, capsys, argv, names):
    out = tmp_path / "out"
    assert sdp.main(["--out", str(out), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and names in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("mode", ["profile", "mechanism"])
def test_an_out_that_is_a_file_is_refused_in_one_line(tmp_path, capsys, mode):
    f = tmp_path / "afile"
    f.write_text("x")
    assert sdp.main(["--mode", mode, "--out", str(f / "sub")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0], err


def test_a_file_without_the_columns_is_refused(tmp_path, capsys):
    bad = tmp_path / "x.npz"
    np.savez(bad, height=np.zeros(3))
    assert sdp.main(["--out", str(tmp_path / "o"), str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lacks the columns" in err[0]


def test_swings_split_a_probe_from_the_swing_that_follows_it():
    """A synthetic trace: LF swings (probe, ended by touchdown), then at once its full swing, then a body phase."""
    t = 10
    tr = dict(time=np.arange(t) * 0.002, phase=np.array([0, 1, 1, 1, 1, 1, 1, 0, 0, 0]),
              swing_leg=np.zeros(t, int), probing=np.array([0, 1, 1, 0, 0, 0, 0, 0, 0, 0], bool),
              touchdown=np.array([0, 0, 1, 0, 0, 0, 1, 0, 0, 0], bool), limit_stop=np.zeros(t, bool),
              limit_kind=np.zeros(t, int), search_depth=np.zeros(t), feet=np.zeros((t, 4, 3)))
    tr["feet"][:, 0, 0] = np.linspace(-0.1, 0.3, t)
    s = sdp.swings(tr, 0.2)
    assert [(x["leg"], x["first_tick"], x["last_tick"], x["end"]) for x in s] == [
        ("LF", 1, 2, "probe: touchdown"), ("LF", 3, 6, "touchdown")]
    assert s[1]["x_end"] == pytest.approx(tr["feet"][6, 0, 0], abs=1e-4)
    assert s[0]["z_end"] == pytest.approx(-0.2)


@pytest.mark.slow
def test_a_far_start_strikes_a_shin_where_a_near_one_is_clean(tmp_path):
    """``reach`` at 18 cm on C MuJoCo, zero heading, friction 0.7: a start 6 cm before the edge steps down clean, one
    13 cm before it strikes a front shin (the profile's 5-6 cm bin: 99% clean; 13-14 cm: 18%)."""
    out = tmp_path / "m"
    assert sdp.main(["--mode", "mechanism", "--out", str(out), "--heights", "0.18", "--starts", "0.06", "0.13",
                     "0.07"]) == 0
    runs = json.loads((out / "mechanism.json").read_text())["runs"]
    near, far = runs
    assert (near["start_distance"], far["start_distance"]) == (0.06, 0.13)
    assert near["clean"] and not near["shin_strike"] and not near["strikes"]
    assert far["shin_strike"] and not far["clean"]
    assert set(far["strikes"]) & {"LF", "RF"}
    assert far["peak_shin_force"] > 100.0


def test_the_stored_mechanism_runs_say_what_the_docs_say():
    """docs/stepdown.md "Far starts", read back from the stored ``reach`` runs: at 18 cm the
    shin strikes are RF's, in every run from 13 cm and in none before; from 9.5 cm on LF's probe finds ground and
    RF's smallest shin clearance shrinks as the start grows."""
    with open(os.path.join(STORED, "mechanism", "mechanism.json"), encoding="utf-8") as f:
        stored = json.load(f)
    assert stored["preset"] == "reach" and stored["impl"] == "c" and stored["yaw"] == 0.0
    runs = [r for r in stored["runs"] if r["height"] == 0.18]
    assert len(runs) == 15
    for r in runs:
        far = r["start_distance"] >= 0.13 - 1e-9
        assert r["shin_strike"] == far and (list(r["strikes"]) == ["RF"]) == far
        rf = [s for s in r["front_swings"] if s["leg"] == "RF"][0]
        assert rf["end"] == "touchdown" and rf["x_end"] > 0.27 and rf["z_end"] < -0.15  # on the lower ground
    probe = [r for r in runs if r["start_distance"] >= 0.095 - 1e-9]
    assert all(r["front_swings"][1]["end"] == "probe: touchdown" for r in probe)
    clearance = [r["shin_clearance"]["RF"]["min"] for r in probe]
    assert all(a > b for a, b in zip(clearance[:7], clearance[1:8])) and clearance[7] <= 0.0 < clearance[6]
