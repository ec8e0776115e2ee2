"""experiments/reach_map_merge.py: maps made in parts judged as one; parts that did not run the same step-downs, or
disagree on a variant they share, are refused in one line."""
import json
import os
import zlib

import numpy as np
import pytest

from experiments import reach_map
from experiments import reach_map_merge as merge


def _part(variants, seed=5, instances=2, params=None):
    """A part as the reach map stores it: its configuration and rows (scenario columns, then outcomes)."""
    rows = reach_map.build_rows(variants, ["narrow"], [0.16, 0.24], instances, seed)
    n = len(rows["variant"])
    # every variant's outcome depends on the variant and the row alone, as a simulator that repeats a batch
    key = np.array([zlib.crc32(f"{v} {h} {i}".encode()) % 1000 for v, h, i in
                    zip(rows["variant"], rows["height"], rows["instance"])])
    table = dict(rows, out_clean=key % 3 == 0, out_completed=key % 3 != 2, out_diverged=np.zeros(n, bool),
                 out_progress=(key / 1000.0).astype(np.float32))
    cfg = dict(start_pose="leading-foot", impl="c", instances=instances, heights=[0.16, 0.24],
               spreads={"narrow": reach_map.SPREADS["narrow"]}, variants=list(variants), seed=seed, duration=1.0,
               terminate=True, params={v: (params or {}).get(v, {"k": v}) for v in variants}, custom=[], tuned_runs=[])
    return dict(config=cfg, impl="c", device="cpu", wall_s=10.0, physics_steps=100), table


def test_parts_merge_into_every_variant_once_and_a_shared_one_is_checked_row_by_row():
    a, b = _part(["clean", "run_0"]), _part(["clean", "run_1"])
    config, rows, notes = merge.merge([("A", *a), ("B", *b)])
    assert config["variants"] == ["clean", "run_0", "run_1"]
    assert len(rows["variant"]) == 3 * 4 and sorted(set(rows["variant"])) == ["clean", "run_0", "run_1"]
    assert notes == ["clean: in A and B, the same outcome in all 4 runs (kept once)"]
    # the merged rows are those of one map of the three variants (in its order)
    full = _part(["clean", "run_0", "run_1"])[1]
    for k in full:
        assert np.array_equal(rows[k], full[k]), k


def test_parts_that_do_not_share_their_step_downs_or_a_variant_are_refused():
    a = _part(["clean", "run_0"])
    with pytest.raises(merge.MergeError, match="its seed"):
        merge.merge([("A", *a), ("B", *_part(["run_1"], seed=6))])
    with pytest.raises(merge.MergeError, match="its instances"):
        merge.merge([("A", *a), ("B", *_part(["run_1"], instances=3))])
    moved = _part(["run_1"])
    moved[1]["friction"] = moved[1]["friction"] + 0.01  # same settings, other draws: another code version
    with pytest.raises(merge.MergeError, match="differs from A's"):
        merge.merge([("A", *a), ("B", *moved)])
    other = _part(["clean", "run_1"])
    other[1]["out_clean"] = other[1]["out_clean"].copy()
    other[1]["out_clean"][np.flatnonzero(other[1]["variant"] == "clean")[1]] ^= True
    with pytest.raises(merge.MergeError, match=r"variant clean differs from A in 1 of 4 runs \(clean in 1\)"):
        merge.merge([("A", *a), ("B", *other)])
    renamed = _part(["clean", "run_1"], params={"clean": {"k": "other"}})
    with pytest.raises(merge.MergeError, match="variant clean has other parameters"):
        merge.merge([("A", *a), ("B", *renamed)])
    with pytest.raises(merge.MergeError, match="at least two"):
        merge.merge([("A", *a)])


def test_the_command_refuses_in_one_line(tmp_path, capsys):
    assert merge.main([str(tmp_path / "nothing"), str(tmp_path / "neither"), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("reach_map_merge: ") and "not a finished reach map" in err[0]
    assert merge.main([str(tmp_path / "a"), str(tmp_path / "m"), "--out", str(tmp_path / "m")]) == 2
    assert "one of the parts" in capsys.readouterr().err


def test_the_repeats_driver_judges_a_map_made_elsewhere_only_with_judge_only(tmp_path, capsys):
    from experiments import tune_default_repeats as tdr

    assert tdr.main(["--out", str(tmp_path), "--heldout-dir", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(
        "tune_default_repeats: --heldout-dir")
    assert tdr.main(["--out", str(tmp_path), "--judge-only", "--heldout-dir", str(tmp_path / "no")]) == 2
    assert "no reach_map.json there" in capsys.readouterr().err


@pytest.mark.slow
def test_two_c_mujoco_maps_merge_into_the_map_of_all_their_variants(tmp_path):
    """Two tiny C MuJoCo maps sharing one variant, merged, give bit for bit the cells and rows of one map of the three
    variants, and the paired comparison reads the merged map."""
    from experiments import paired_map

    base = ["--impl", "c", "--instances", "1", "--heights", "0.16", "0.24", "--duration", "0.6", "--spread", "narrow",
            "--chunk", "4"]
    assert reach_map.main(["--out", str(tmp_path / "a"), *base, "--variants", "default", "remedy_all"]) == 0
    assert reach_map.main(["--out", str(tmp_path / "b"), *base, "--variants", "remedy_all", "paper_off"]) == 0
    assert reach_map.main(["--out", str(tmp_path / "full"), *base, "--variants", "default", "remedy_all",
                           "paper_off"]) == 0
    assert merge.main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "m")]) == 0
    got = json.loads((tmp_path / "m" / "reach_map.json").read_text())
    want = json.loads((tmp_path / "full" / "reach_map.json").read_text())
    assert got["cells"] == want["cells"] and got["config"]["variants"] == want["config"]["variants"]
    assert got["wall_s"] > 0 and [p["variants"] for p in got["merged_from"]] == [["default", "remedy_all"],
                                                                                 ["remedy_all", "paper_off"]]
    with np.load(tmp_path / "m" / "reach_instances.npz") as z, np.load(tmp_path / "full" / "reach_instances.npz") as w:
        assert sorted(z.files) == sorted(w.files)
        for k in w.files:
            assert np.array_equal(z[k], w[k]), k
    assert paired_map.main([str(tmp_path / "m"), "--reference", "default"]) == 0
    # the merged map is not run over again by a reach map given it as --out
    assert reach_map.main(["--out", str(tmp_path / "m"), *base, "--variants", "default"]) == 2
    assert os.path.exists(tmp_path / "m" / "paired_default.json")
