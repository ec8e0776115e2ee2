"""``python -m experiments.tune_judge``: finished tuning studies judged together on their shared held-out set."""
import json
import shutil

import pytest

from experiments import tune_judge

STORED = "docs/results/tune_guided_h200x2_3min"
MATCHED = "docs/results/tune_guided_matched_h200x2_3min_56"


def _clean(comp, member):
    return [r["clean"] for r in comp["summary"][member]["runs"]]


def test_merged_studies_keep_every_run_its_own_held_out_result(tmp_path):
    """The stored SNES and CMA-ES runs (five seeds, budgets 1 and 3 min) judged with the guided-ES and OpenES runs at
    the matched scale (five seeds, 3 min): every member's per-run held-out clean rates are exactly those its own
    study measured, the start is counted once per seed, and the result is the stored comparison."""
    out = tmp_path / "j"
    assert tune_judge.main(["--out", str(out), f"{STORED}:snes,cma_es", f"{MATCHED}/guided_es",
                            f"{MATCHED}/open_es"]) == 0
    comp = json.loads((out / "comparison.json").read_text())
    old = json.loads(open(f"{STORED}/comparison.json").read())
    for m in ("snes/per_leg", "cma_es/per_leg", "start", "table1"):
        assert _clean(comp, m) == _clean(old, m)
    for m in ("guided_es", "open_es"):
        own = [json.loads(open(f"{MATCHED}/{m}/seed{s}/results.json").read())["heldout"][f"{m}/per_leg@3min"]["clean"]
               for s in range(5)]
        assert _clean(comp, f"{m}/per_leg") == own
    assert _clean(comp, "guided_es/per_leg") != _clean(old, "guided_es/per_leg")  # the old scale's runs left out
    assert comp["minutes"] == 3.0 and comp["summary"]["start"]["clean"]["n"] == 5
    stored = json.loads(open(f"{MATCHED}/comparison.json").read())
    assert comp["summary"] == stored["summary"] and comp["differences"] == stored["differences"]


def test_a_run_given_twice_and_runs_of_other_settings_are_refused_in_one_line(tmp_path, capsys):
    assert tune_judge.main(["--out", str(tmp_path / "a"), f"{MATCHED}/guided_es", f"{MATCHED}/guided_es"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "given by two sources" in err[0]
    other = tmp_path / "other" / "seed0"
    other.mkdir(parents=True)
    shutil.copy(f"{MATCHED}/open_es/seed0/tuning.png", other)
    res = json.loads(open(f"{MATCHED}/open_es/seed0/results.json").read())
    res["config"]["popsize"] = 32
    (other / "results.json").write_text(json.dumps(res))
    assert tune_judge.main(["--out", str(tmp_path / "b"), f"{MATCHED}/guided_es", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "popsize" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


@pytest.mark.parametrize("source, needle", [("/nonexistent", "not a directory"), (f"{STORED}:", "at least one"),
                                            ("docs", "no finished"), (f"{STORED}:snes,cmaes", "no run of cmaes")])
def test_bad_sources_are_refused_in_one_line(source, needle, tmp_path, capsys):
    assert tune_judge.main(["--out", str(tmp_path / "x"), source]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err


def test_settings_only_the_surrogate_reads_must_agree_only_between_runs_that_build_it(tmp_path, capsys):
    """Guided ES with the hind legs' windows (``windows_per_scenario`` 4, ``window_lead`` 16) is judged with stored
    SNES, CMA-ES and OpenES runs, which read neither setting, and the judgement names the two settings; the same
    guided ES next to guided-ES runs with the default windows is refused in one line naming the first setting that
    differs, and so is an OpenES run whose sampling step differs."""
    out = tmp_path / "j"
    assert tune_judge.main(["--out", str(out), f"{STORED}:snes,cma_es", f"{MATCHED}/open_es",
                            f"{MATCHED}/guided_es_hind"]) == 0
    comp = json.loads((out / "comparison.json").read_text())
    own = [json.loads(open(f"{MATCHED}/guided_es_hind/seed{s}/results.json").read())["heldout"][
        "guided_es/per_leg@3min"]["clean"] for s in range(5)]
    assert _clean(comp, "guided_es/per_leg") == own
    assert comp["summary"] == json.loads(open(f"{MATCHED}/judged_hind/comparison.json").read())["summary"]
    assert comp["member_settings"] == {"guided_es/per_leg": {"windows_per_scenario": 4, "window_lead": 16.0}}
    assert "- guided_es/per_leg: window_lead 16.0, windows_per_scenario 4" in (out / "comparison.md").read_text()
    capsys.readouterr()
    assert tune_judge.main(["--out", str(tmp_path / "a"), f"{MATCHED}/guided_es", f"{MATCHED}/guided_es_hind"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "window_lead: 16.0 against 10.0" in err[0], err
    other = tmp_path / "other" / "seed0"
    other.mkdir(parents=True)
    res = json.loads(open(f"{MATCHED}/open_es/seed0/results.json").read())
    res["config"]["sigma"] = 0.2
    (other / "results.json").write_text(json.dumps(res))
    assert tune_judge.main(["--out", str(tmp_path / "b"), f"{MATCHED}/guided_es_hind", str(tmp_path / "other")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sigma" in err[0], err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_every_setting_some_methods_read_is_a_study_setting_read_by_named_methods():
    """:data:`SETTING_READERS` names fields of :class:`WallClockConfig` and methods of the study, and a comparison
    of a guided-ES run with a CMA-ES run ignores exactly those settings guided ES alone reads."""
    import dataclasses

    from hyqjax.studies.tune import names
    from hyqjax.studies.tune.study import repeats
    from hyqjax.studies.tune.wallclock_config import SETTING_READERS, WallClockConfig

    fields = {f.name for f in dataclasses.fields(WallClockConfig)}
    assert set(SETTING_READERS) <= fields
    assert all(readers and set(readers) <= set(names.METHODS) for readers in SETTING_READERS.values())
    base = json.loads(open(f"{MATCHED}/open_es/seed0/results.json").read())
    for k in SETTING_READERS:
        other = json.loads(json.dumps(base))
        other["config"]["methods"] = ["guided_es"]
        other["config"][k] = "changed"
        readers = set(SETTING_READERS[k])
        if "guided_es" in readers:  # read by guided ES: ignored against OpenES, refused against another guided run
            repeats.check_comparable([base, other], ["a", "b"])
            both = json.loads(json.dumps(base))
            both["config"]["methods"] = ["guided_es"]
            with pytest.raises(ValueError, match=k):
                repeats.check_comparable([both, other], ["a", "b"])
        else:  # guided ES does not read it either: the two runs differ in nothing they both read
            repeats.check_comparable([base, other], ["a", "b"])
    other = json.loads(json.dumps(base))
    other["config"]["train_instances"] = 64  # read by every method
    with pytest.raises(ValueError, match="train_instances"):
        repeats.check_comparable([base, other], ["a", "b"])


def test_runs_of_other_seeds_with_other_surrogate_settings_are_judged_with_truthful_configs(tmp_path):
    """Stored CMA-ES and SNES seeds 0-4 (their study also ran guided ES with the default windows, which is not
    judged) and guided ES with the hind legs' windows as seeds 5-9: each merged seed's config names the methods it
    holds and the windows its guided runs had, so the judgement over all ten seeds goes through."""
    hind = tmp_path / "hind"
    for s in range(5):
        res = json.loads(open(f"{MATCHED}/guided_es_hind/seed{s}/results.json").read())
        res["config"]["seed"] = s + 5
        (hind / f"seed{s + 5}").mkdir(parents=True)
        (hind / f"seed{s + 5}" / "results.json").write_text(json.dumps(res))
    out = tmp_path / "j"
    assert tune_judge.main(["--out", str(out), f"{STORED}:snes,cma_es", str(hind)]) == 0
    comp = json.loads((out / "comparison.json").read_text())
    assert comp["seeds"] == list(range(10))
    assert comp["summary"]["guided_es/per_leg"]["clean"]["n"] == 5
    assert comp["summary"]["snes/per_leg"]["clean"]["n"] == 5
    assert comp["summary"]["start"]["clean"]["n"] == 10
