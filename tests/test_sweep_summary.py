"""Sweep summary with both outcome levels (completed, clean) on synthetic rows: no model is built.

The summary's counts, Wilson intervals, height curves, maps and h95 of each level equal those computed
here independently from the rows; a diverged instance is a failure of both levels; rows of an older store
(no ``completed`` column) give None for completed, with a note, and never raise.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from hyqjax.io import report
from hyqjax.io.atomic import dumps
from hyqjax.studies import statistics, sweep

HEIGHTS = [0.08, 0.12, 0.16, 0.2]
N_SAMPLES = 80  # >= 73 per height level, so h95 (Wilson) can be reached


def strict_loads(text: str):
    def no_constant(name):
        raise ValueError(f"non-strict JSON constant {name}")

    return json.loads(text, parse_constant=no_constant)


def synthetic(diverge: int = 3):
    """Rows of a height x reflex grid with a random friction: completed and clean differ (clean also needs no shin
    strike, none up to 12 cm), a few reflex-off instances diverged, all through :func:`sweep.count_outcomes`."""
    spec = sweep.SweepSpec.from_dict(dict(grid=dict(height=HEIGHTS, reflex=[False, True]), samples=N_SAMPLES,
                                          random=dict(friction=[0.5, 1.0]), maps=[["height", "friction"]], bins=3))
    rows = spec.instance_inputs(0, spec.n_instances)
    n = spec.n_instances
    h, s, on = rows["height"], rows["sample"], rows["reflex"].astype(bool)
    completed = (h < np.where(on, 0.17, 0.13)) | (s % 10 == 0)
    shin = ((s * 7 + np.round(h * 100).astype(int)) % 20) < np.round((h - 0.12) * 200).astype(int)
    diverged = np.zeros(n, bool)
    diverged[np.nonzero(completed & ~shin & ~on)[0][:diverge]] = True
    out = dict(completed=completed, clean=completed & ~shin, success=completed & ~shin, shin_strike=shin,
               diverged=diverged, peak_roll=np.zeros(n), peak_pitch=np.where(diverged, np.nan, 0.1),
               progress=np.ones(n), mean_mobility=np.full(n, 0.5))
    return spec, {**rows, **sweep.count_outcomes(out)}, diverged


def h95_by_hand(h, y):
    """Largest height whose Wilson lower bound, and that of every lower height, is >= 0.95 (None if none)."""
    best = None
    for level in sorted(set(h.tolist())):
        m = h == level
        if not statistics.wilson_interval(int(y[m].sum()), int(m.sum()))[0] >= 0.95:
            break
        best = level
    return best


def test_both_levels_equal_independent_counts_intervals_and_h95():
    spec, rows, diverged = synthetic()
    assert not rows["completed"][diverged].any() and not rows["clean"][diverged].any()
    s = sweep.summarize_sweep(spec, rows)
    strict_loads(dumps(s))
    comp, clean = rows["completed"], rows["success"]
    assert (comp & ~clean).sum() > 50  # the levels differ
    for key, y in (("completed", comp), ("successes", clean)):
        assert s[key] == int(y.sum())
    assert s["completed_ci95"] == list(statistics.wilson_interval(int(comp.sum()), comp.size))
    assert s["ci95"] == list(statistics.wilson_interval(int(clean.sum()), clean.size))
    assert s["completed_rate"] == comp.mean() and s["rate"] == clean.mean()
    h95s = set()
    for name, on in (("off", False), ("on", True)):
        r, m = s["by_reflex"][name], rows["reflex"] == on
        h = rows["height"][m]
        for y, count, rate, ci, hw, hl in ((comp[m], "completed", "completed_rate", "completed_ci95",
                                           "h95_completed_wilson", "h95_completed_logistic"),
                                          (clean[m], "successes", "rate", "ci95", "h95_wilson", "h95_logistic")):
            k = int(y.sum())
            assert (r[count], r[rate], r[ci]) == (k, k / m.sum(), list(statistics.wilson_interval(k, int(m.sum()))))
            assert r[hw] == h95_by_hand(h, y)
            assert r[hl] == pytest.approx(statistics.h95_logistic(h, y.astype(float)), rel=1e-9)
            h95s.add((name, count, r[hw]))
            for c in r["height_curve"]:
                lm = np.isclose(h, c["height"])
                kk = int(y[lm].sum())
                assert c["n"] == lm.sum() and c[count] == kk
                assert c[ci] == list(statistics.wilson_interval(kk, int(lm.sum())))
    # The two levels' h95 (Wilson) differ somewhere, and both are reached for reflex on.
    assert {w for n_, c, w in h95s if n_ == "on"} == {0.12, 0.16}
    edges = np.linspace(0.5, 1.0, 4)
    fi = np.clip(np.searchsorted(edges, rows["friction"], side="right") - 1, 0, 2)
    hi = np.searchsorted(HEIGHTS, rows["height"])
    for mp in s["maps"]:
        m = rows["reflex"] == mp["reflex"]
        for i in range(len(HEIGHTS)):
            for j in range(3):
                cell = m & (hi == i) & (fi == j)
                nn = int(cell.sum())
                assert mp["n"][i][j] == nn
                for y, count, lo, hi_ in ((comp, "completed", "completed_ci95_lo", "completed_ci95_hi"),
                                          (clean, "successes", "ci95_lo", "ci95_hi")):
                    k = int(y[cell].sum())
                    assert mp[count][i][j] == k
                    np.testing.assert_equal([mp[lo][i][j], mp[hi_][i][j]], statistics.wilson_interval(k, nn))


def test_diverged_and_non_finite_rows_fail_both_levels():
    out = dict(completed=np.array([True, True, True, True]), clean=np.array([True, True, True, False]),
               success=np.array([True, True, True, False]), shin_strike=np.array([False, False, False, True]),
               diverged=np.array([False, True, False, False]), peak_pitch=np.array([0.1, 0.1, np.inf, 0.1]),
               mean_mobility=np.ones(4))
    c = sweep.count_outcomes(out)
    assert c["completed"].tolist() == [True, False, False, True]
    assert c["clean"].tolist() == c["success"].tolist() == [True, False, False, False]
    assert c["failure_reason"].tolist() == ["", "diverged", "non-finite metrics", "shin_strike"]
    only_clean = sweep.count_outcomes(dict(clean=np.array([True, True]), diverged=np.array([True, False])))
    assert only_clean["success"].tolist() == only_clean["clean"].tolist() == [False, True]
    spec = sweep.SweepSpec.from_dict(dict(grid=dict(height=[0.2], reflex=[True]), samples=4))
    s = sweep.summarize_sweep(spec, {**spec.instance_inputs(0, 4), **c})
    r = s["by_reflex"]["on"]
    assert (s["n_instances"], r["n"], s["completed"], s["successes"], s["diverged"]) == (4, 4, 2, 1, 1)
    assert r["height_curve"][0]["completed"] == 2 and r["height_curve"][0]["successes"] == 1


def test_old_rows_without_completed_give_none_with_a_note(tmp_path):
    spec, rows, _ = synthetic()
    old = {k: v for k, v in rows.items() if k not in ("completed", "clean")}
    s = sweep.summarize_sweep(spec, old)
    new = sweep.summarize_sweep(spec, rows)
    assert s["completed"] is None and s["completed_rate"] is None and s["completed_ci95"] is None
    assert s["notes"] and "completed" in s["notes"][0] and "notes" not in new
    for r in s["by_reflex"].values():
        assert r["completed"] is None and r["h95_completed_wilson"] is None and r["h95_completed_logistic"] is None
        assert all(c["completed"] is None and c["completed_ci95"] is None for c in r["height_curve"])
    assert all(m["completed"] is None and m["completed_ci95_lo"] is None for m in s["maps"])
    # The clean level is the same as with the completed column.
    for k in ("successes", "rate", "ci95"):
        assert s[k] == new[k]
    assert s["by_reflex"]["on"]["h95_wilson"] == new["by_reflex"]["on"]["h95_wilson"]
    strict_loads(dumps(s))
    text = sweep.format_summary(s)
    assert "completed n/a" in text and "note: completed: absent" in text
    assert sweep.plot_maps(s, str(tmp_path / "m.png")) and sweep.plot_height_curves(s, str(tmp_path / "h.png"))
    page = report.sweep_html(strict_loads(dumps(s)))
    assert "Note: completed: absent" in page and "<td class=\"\">-</td>" in page


def test_format_summary_and_report_show_both_levels():
    spec, rows, _ = synthetic()
    s = strict_loads(dumps(sweep.summarize_sweep(spec, rows)))
    lines = sweep.format_summary(s).splitlines()
    assert lines[0].startswith(f"{spec.n_instances}/{spec.n_instances} instances, completed {s['completed']}/")
    on = lines.index(next(x for x in lines if x.startswith("reflex  on")))
    assert lines[on + 1].strip().startswith(f"completed {s['by_reflex']['on']['completed']}/320")
    assert "h95 Wilson 0.160 m" in lines[on + 1]
    assert lines[on + 2].strip().startswith(f"clean {s['by_reflex']['on']['successes']}/320")
    assert "h95 Wilson 0.120 m" in lines[on + 2]
    assert sum("h = " in x and "completed" in x and "clean" in x for x in lines) == 2 * len(HEIGHTS)
    page = report.sweep_html({**s, "_sweep": True})
    assert "Completed and clean vs. height, reflex on" in page
    assert f"{s['completed']} completed, {s['successes']} clean" in page


def test_written_summary_json_has_both_levels_and_is_strict(tmp_path):
    """A store whose chunks hold both levels: summary.json (strict JSON) has the clean keys of older summaries
    and the completed keys next to them; the figures are written."""
    spec, rows, _ = synthetic()
    layout = dict(platform="cpu", device_kind="cpu", devices=1)
    with sweep.SweepStore(str(tmp_path), spec, 320, layout, writer=True) as st:
        for c in st.todo():
            a, b = st.chunk_range(c)
            st.write_chunk(c, {k: v[a:b] for k, v in rows.items()}, 0.1)
    s = sweep.write_outputs(sweep.open_store(str(tmp_path)))
    disk = strict_loads((tmp_path / "summary.json").read_text())
    assert disk["completed"] == int(rows["completed"].sum()) and disk["successes"] == int(rows["success"].sum())
    on = disk["by_reflex"]["on"]
    assert (on["h95_completed_wilson"], on["h95_wilson"]) == (0.16, 0.12)
    assert {"completed", "completed_rate", "completed_ci95_lo", "successes", "rate", "ci95_lo"} <= set(disk["maps"][0])
    assert len(s["figures"]) == 2 and all((tmp_path / f).exists() for f in ("success_maps.png", "success_height.png"))
