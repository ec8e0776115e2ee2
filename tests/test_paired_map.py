"""experiments/paired_map.py: paired differences of a reach map's variants on the same instances."""
from __future__ import annotations

import numpy as np
import pytest

from experiments import paired_map


def _pairs(n11, n10, n01, n00):
    a = np.array([1] * n11 + [1] * n10 + [0] * n01 + [0] * n00, bool)
    b = np.array([1] * n11 + [0] * n10 + [1] * n01 + [0] * n00, bool)
    return a, b


def test_newcombe_interval_matches_the_published_example():
    """Newcombe (1998), Stat. Med. 17, 2635-2650, Table II example (a, b, c, d) = (36, 12, 2, 0): method 10 gives
    0.0569 to 0.3404 for the difference 0.2; McNemar's exact p is 2 P(Bin(14, 1/2) <= 2)."""
    from scipy.stats import binom

    r = paired_map.paired_difference(*_pairs(36, 12, 2, 0))
    assert r["d"] == pytest.approx(0.2)
    assert r["ci95"] == pytest.approx([0.0569, 0.3404], abs=5e-5)
    assert (r["only_variant"], r["only_reference"], r["n"]) == (12, 2, 50)
    assert r["p_mcnemar"] == pytest.approx(2 * binom.cdf(2, 14, 0.5))


def test_the_paired_interval_covers_the_true_difference_95_percent_of_the_time():
    """Correlated pairs with known rates (0.90 and 0.86, 80% of instances shared): over 1,500 simulated maps of 300
    pairs, the interval holds the true difference 0.04 in 93-97.5% of them, and it is narrower than the two
    independent Wilson intervals' combination would be (the point of pairing)."""
    rng = np.random.default_rng(5)
    hits, n, width = 0, 300, []
    for _ in range(1500):
        shared = rng.random(n) < 0.8
        u = rng.random(n)
        a = np.where(shared, u < 0.88, rng.random(n) < 0.98)
        b = np.where(shared, u < 0.88, rng.random(n) < 0.78)
        r = paired_map.paired_difference(a, b)
        lo, hi = r["ci95"]
        hits += lo <= 0.88 * 0.8 + 0.98 * 0.2 - (0.88 * 0.8 + 0.78 * 0.2) <= hi
        width.append(hi - lo)
    assert 0.93 <= hits / 1500 <= 0.975, hits / 1500
    from hyqjax.studies.sweep.compare import newcombe_interval

    lo, hi = newcombe_interval(270, n, 258, n)  # unpaired, at the same rates
    assert np.median(width) < 0.75 * (hi - lo)


def _table(rng, variants=("ref", "v"), heights=(0.15, 0.25), k=40):
    rows = []
    for v in variants:
        for h in heights:
            for i in range(k):
                rows.append((v, "wide", h, i))
    t = dict(variant=np.array([r[0] for r in rows]), spread=np.array([r[1] for r in rows]),
             height=np.array([r[2] for r in rows]), instance=np.array([r[3] for r in rows]))
    key = t["instance"] * 7 + np.round(t["height"] * 100).astype(int)
    t["friction"] = 0.4 + (key % 60) / 100.0
    t["out_clean"] = rng.random(len(rows)) < 0.7
    t["out_completed"] = t["out_clean"] | (rng.random(len(rows)) < 0.5)
    t["out_diverged"] = np.zeros(len(rows), bool)
    return t


def test_pairs_are_matched_by_instance_whatever_the_row_order_and_other_instances_are_refused():
    rng = np.random.default_rng(0)
    t = _table(rng)
    want = paired_map.compare(t, "ref", max_height=0.26)
    perm = rng.permutation(len(t["variant"]))
    got = paired_map.compare({k: v[perm] for k, v in t.items()}, "ref", max_height=0.26)
    assert got == want
    iv = t["variant"] == "v"
    ir = t["variant"] == "ref"
    d = want["variants"]["v"]["clean"]["pooled"]
    assert d["d"] == pytest.approx(t["out_clean"][iv].mean() - t["out_clean"][ir].mean())
    assert d["n"] == 80 and set(want["variants"]["v"]["clean"]["per_height"]) == {"0.15", "0.25"}
    low = paired_map.compare(t, "ref", max_height=0.2)["variants"]["v"]["clean"]["pooled"]
    assert low == want["variants"]["v"]["clean"]["per_height"]["0.15"]
    bad = {k: v.copy() for k, v in t.items()}
    bad["instance"][np.flatnonzero(iv)[0]] = 999
    with pytest.raises(ValueError, match="different instances"):
        paired_map.compare(bad, "ref")
    bad = {k: v.copy() for k, v in t.items()}
    bad["friction"][np.flatnonzero(iv)[3]] += 0.01
    with pytest.raises(ValueError, match="friction"):
        paired_map.compare(bad, "ref")


def test_bad_input_is_one_line_before_anything_is_read(tmp_path, capsys):
    rng = np.random.default_rng(1)
    np.savez(tmp_path / "reach_instances.npz", **_table(rng))
    for argv, needle in (([str(tmp_path), "--reference", "nope"], "--reference nope"),
                         ([str(tmp_path), "--reference", "ref", "--max-height", "0"], "--max-height"),
                         ([str(tmp_path), "--reference", "ref", "--level", "fell"], "--level"),
                         ([str(tmp_path / "none"), "--reference", "ref"], "reach_instances.npz")):
        assert paired_map.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0], err
    assert paired_map.main([str(tmp_path), "--reference", "ref"]) == 0
    assert (tmp_path / "paired_ref.md").read_text().startswith("paired against `ref`")


def test_a_map_above_the_pooled_heights_reports_every_level_per_height_and_no_empty_pooled_row():
    """A map of heights above --max-height (one deep height, say) has no pooled rows: the report says so in one
    line instead of printing undefined ones, and its per-height lines give each level's rates and difference,
    the same numbers as the per-height records."""
    rng = np.random.default_rng(2)
    t = _table(rng, heights=(0.27,), k=60)
    res = paired_map.compare(t, "ref", max_height=0.26)
    text = paired_map.markdown(res)
    assert "nan" not in text and "no height up to 26 cm" in text
    for lv in ("clean", "completed"):
        x = res["variants"]["v"][lv]["per_height"]["0.27"]
        iv, ir = t["variant"] == "v", t["variant"] == "ref"
        assert x["variant"] == pytest.approx(t[f"out_{lv}"][iv].mean())
        assert x["reference"] == pytest.approx(t[f"out_{lv}"][ir].mean())
        assert f"per height ({lv})" in text
        assert f"27 cm {x['variant']:.3f} / {x['reference']:.3f}, {x['d']:+.3f}" in text
    both = paired_map.markdown(paired_map.compare(_table(rng), "ref", max_height=0.26))
    assert "heights up to 26 cm pooled" in both and "| v | completed | 80 |" in both
