"""benchmarks/warp_determinism.py: its comparison finds every step-down whose outcome or outcome bits differ."""
import importlib.util
import os

import numpy as np


def _bench():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    spec = importlib.util.spec_from_file_location("warp_determinism",
                                                  os.path.join(root, "benchmarks", "warp_determinism.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(clean, completed, tilt, wall):
    cols = dict(clean=np.asarray(clean, np.float32), completed=np.asarray(completed, np.float32),
                tilt=np.asarray(tilt, np.float32))
    return dict(wall_s=wall, clean=np.asarray(clean, bool).tolist(), completed=np.asarray(completed, bool).tolist(),
                bits={k: v.tobytes().hex() for k, v in cols.items()})


def test_comparison_counts_flips_and_single_bit_differences():
    wd = _bench()
    first = _run([1, 1, 0, 1], [1, 1, 1, 1], [0.1, 0.2, 0.3, 0.4], 9.0)
    same = _run([1, 1, 0, 1], [1, 1, 1, 1], [0.1, 0.2, 0.3, 0.4], 2.0)
    one_ulp = _run([1, 1, 0, 1], [1, 1, 1, 1], [0.1, np.nextafter(np.float32(0.2), np.float32(1)), 0.3, 0.4], 2.2)
    flipped = _run([0, 1, 1, 1], [1, 0, 1, 1], [0.1, 0.2, 0.3, 0.4], 2.4)
    assert wd.compare(first, same) == dict(clean=0, completed=0, columns_differing=[], identical=True)
    assert wd.compare(first, one_ulp) == dict(clean=0, completed=0, columns_differing=["tilt"], identical=False)
    assert wd.compare(first, flipped)["clean"] == 2 and wd.compare(first, flipped)["completed"] == 1
    procs = [dict(device="H200", impl="warp", warp="1.18.0", xla_flags="", runs=[first, same]),
             dict(device="H200", impl="warp", warp="1.18.0", xla_flags="", runs=[one_ulp, flipped]),
             dict(error="exit 1: out of memory")]
    r = wd.summarise_mode(procs, 30.0)
    assert r["processes"] == 2 and r["error"] == "exit 1: out of memory"
    assert [c["identical"] for c in r["comparisons"]] == [True, False, False]
    assert (r["first_clean"], r["first_completed"]) == (3, 4)
    assert r["wall_s_after_first"] == [2.0, 2.4]  # each process's first run holds its compiles
    # the row: 1 of 3 runs identical to the first, the largest flips 2 / 1, the median later wall
    assert wd.table_row("run_to_run", r, 2) == "| run_to_run | failed: exit 1: out of memory | | | | |"
    ok = wd.summarise_mode(procs[:2], 30.0)
    assert wd.table_row("run_to_run", ok, 2) == "| run_to_run | 2 x 2 | 3 / 4 | 1 of 3 | 2 / 1 | 2.40 |"
