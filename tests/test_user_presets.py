"""A user's own presets (hyqjax.presets.registry.user_dir) and `hyqjax presets save NAME --from FILE`.

Every test points HYQJAX_PRESETS_DIR at its tmp_path (conftest.py gives the session an empty one, never the home's).
Fast lane: a saved per-leg, shared and conditioned run and a bounding parameter file load as the shipped presets of
the same source (leaf for leaf), with the run's provenance (command, seed, device, the file's path and SHA-256) and
its held-out figure; every refusal of `save` is one line, exit 2, nothing written; a corrupt, foreign or
shipped-named file beside a good one is named in one line and breaks nothing else; a user preset is reached by the
sweep spec (its scenario's params equal the preset), `hyqjax tune --preset`, `hyqjax bound --preset` and the reach
map; a sweep store refuses a resume after its user preset's values changed (naming both digests) and resumes one
written before the digest was recorded. Slow: `hyqjax stepdown --preset NAME` of a user preset runs (C MuJoCo).
"""
from __future__ import annotations

import hashlib
import json
import os

import jax
import numpy as np
import pytest

from hyqjax import presets
from hyqjax.cli import app as cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
R = os.path.join(ROOT, "docs", "results")
PER_LEG = os.path.join(R, "tune_default_repeats_leading_foot_h200", "run_1", "results.json")  # the preset `clean`
SHARED = os.path.join(R, "tune_reach_h200_10min", "snes", "results.json")  # `tuned_shared`
COND = os.path.join(R, "tune_wallclock_h200_10min_68", "results.json")  # `tuned_per_leg_cond`
BOUND = os.path.join(R, "bounding_refine_h200", "params_refined.json")  # `bound_robust`


@pytest.fixture
def pdir(tmp_path, monkeypatch):
    d = tmp_path / "presets"
    monkeypatch.setenv("HYQJAX_PRESETS_DIR", str(d))
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HYQJAX_CACHE_DIR", str(tmp_path / "cache-must-not-appear"))
    return d


def _leaves_equal(a, b) -> bool:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


def _files(d) -> dict:
    return {} if not os.path.isdir(d) else {f: open(os.path.join(d, f), "rb").read() for f in sorted(os.listdir(d))}


def _save(name, src, *more):
    return cli.main(["presets", "save", name, "--from", src, *more])


def test_saved_runs_load_as_the_shipped_presets_of_the_same_runs(pdir, capsys):
    """The per-leg run of `clean`, the shared run of `tuned_shared` (key snes), the conditioned run of
    `tuned_per_leg_cond` (hybrid/per_leg_cond) and the bounding file of `bound_robust`: saved, each loads leaf for
    leaf as the shipped preset, lists after the shipped ones, and carries its run's provenance and figure."""
    cases = (("mine", PER_LEG, "clean"), ("shared-set", SHARED + ":snes", "tuned_shared"),
             ("cond", COND + ":hybrid/per_leg_cond", "tuned_per_leg_cond"), ("bnd", BOUND, "bound_robust"))
    for name, src, shipped in cases:
        assert _save(name, src) == 0, capsys.readouterr().err
        out = capsys.readouterr().out
        assert f"saved {presets.get(shipped).kind} preset {name}: {pdir / (name + '.json')}" in out
        rec = presets.get(name)
        assert rec.user and rec.user_dir == str(pdir) and rec.kind == presets.get(shipped).kind
        assert _leaves_equal(presets.load(name), presets.load(shipped)), name
        assert rec.values == json.loads(json.dumps(presets.get(shipped).values)) or shipped == "bound_robust"
    assert presets.names() == presets.names(user=False) + ["bnd", "cond", "mine", "shared-set"]
    assert presets.names("bound")[-1] == "bnd" and "bnd" not in presets.names("crawl")
    # provenance: the run's command, seed, device, date, and the results file's absolute path and SHA-256
    res = json.load(open(PER_LEG))
    p = presets.get("mine").provenance
    assert p["command"] == res["provenance"]["command"] and p["seed"] == 1 and p["device"] == "NVIDIA H200"
    assert p["source"] == PER_LEG and p["run"] == "cma_es/per_leg" and p["start_preset"] == "reach"
    assert p["sha256"] == hashlib.sha256(open(PER_LEG, "rb").read()).hexdigest() and p["date"] == "2026-11-29"
    # the figure the run measured: its held-out clean rate at its last checkpoint, with its interval and set
    (fig,) = presets.get("mine").figures
    h = res["heldout"]["cma_es/per_leg@3min"]
    assert fig["value"] == round(h["clean"], 3) and fig["interval"] == [round(x, 3) for x in h["clean_ci95"]]
    assert "256 step-downs, seed 7777" in fig["heldout"] and fig["command"] == p["command"]
    shipped = presets.get("clean").figures[-1]  # the same figure of the same run in the shipped preset
    assert {k: fig[k] for k in ("what", "value", "interval", "heldout", "command", "device", "date")} == {
        k: shipped[k] for k in ("what", "value", "interval", "heldout", "command", "device", "date")}
    cond_fig = presets.get("cond").figures[0]
    assert cond_fig["value"] == presets.get("tuned_per_leg_cond").figures[0]["value"]
    # the listing: shipped first, then yours under your directory; one preset in full says it is yours
    assert cli.main(["presets"]) == 0
    out = capsys.readouterr().out
    assert out.index("bound_robust_grad") < out.index(f"your presets ({pdir}):") < out.index("\nmine ")
    assert cli.main(["presets", "mine"]) == 0
    assert f"mine (crawl preset, yours: {pdir / 'mine.json'})" in capsys.readouterr().out


def test_force_replaces_atomically_and_the_file_is_complete(pdir, capsys):
    assert _save("mine", SHARED) == 0
    first = (pdir / "mine.json").read_bytes()
    assert _save("mine", PER_LEG) == 2 and "give --force" in capsys.readouterr().err
    assert (pdir / "mine.json").read_bytes() == first
    assert _save("mine", PER_LEG, "--force", "--description", "my leading-foot set") == 0
    assert presets.get("mine").description == "my leading-foot set"
    assert _leaves_equal(presets.load("mine"), presets.load("clean"))
    assert sorted(os.listdir(pdir)) == ["mine.json"]  # no temporary left
    json.loads((pdir / "mine.json").read_text())


@pytest.mark.parametrize("argv, needle", [
    (["Bad Name", "--from", PER_LEG], "a preset name is a lowercase letter"),
    (["reach", "--from", PER_LEG], "shipped preset reach"),
    (["save", "--from", PER_LEG], "reserved"),
    (["mine", "--from", "nope/results.json"], "--from nope/results.json: no such file"),
    (["mine", "--from", os.path.join(R, "reach_recommended_h200", "warp_wide", "reach_map.json")],
     "is not the results.json of `hyqjax tune`"),
    (["mine", "--from", PER_LEG + ":snes/shared"], "run 'snes/shared' is not a run of"),
    (["mine", "--from", COND], "has 2 runs"),
    (["mine"], "needs --from"),
    (["mine", "--from", BOUND + ":cma_es"], "has no runs"),
])
def test_save_refusals_are_one_line_exit_2_nothing_written(pdir, capsys, argv, needle):
    before = _files(pdir)
    rc = cli.main(["presets", "save", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and needle in err and "Traceback" not in err, err
    assert _files(pdir) == before


def test_run_without_a_returned_set_and_existing_name_refused(pdir, tmp_path, capsys):
    res = json.load(open(PER_LEG))
    del res["runs"]["cma_es/per_leg"]["theta"]
    bad = tmp_path / "unfinished.json"
    bad.write_text(json.dumps(res))
    for argv, needle in ((["mine", "--from", f"{bad}:cma_es/per_leg"], "has no returned set"),
                         (["mine", "--from", str(bad)], "has no run of a known parameterisation")):
        assert cli.main(["presets", "save", *argv]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err, err
    assert not pdir.exists()
    assert _save("mine", SHARED) == 0
    capsys.readouterr()
    assert _save("mine", PER_LEG) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"mine exists ({pdir / 'mine.json'})" in err


def test_corrupt_foreign_and_shipped_named_files_break_nothing_else(pdir, capsys):
    assert _save("mine", SHARED) == 0
    capsys.readouterr()
    (pdir / "broken.json").write_text('{"format": "hyqjax.presets/1", ')
    (pdir / "foreign.json").write_text(json.dumps({"amplitudes": {}, "gains": {}}))
    (pdir / "reach.json").write_text((pdir / "mine.json").read_text().replace('"name": "mine"', '"name": "reach"'))
    (pdir / "Upper.json").write_text("{}")
    shape = json.loads((pdir / "mine.json").read_text())
    shape.update(name="shape", values=dict(shape["values"], reflex=[1.0]))
    (pdir / "shape.json").write_text(json.dumps(shape))
    (pdir / "notes.txt").write_text("not a preset")
    assert presets.names(user=False) + ["mine"] == presets.names()
    assert _leaves_equal(presets.load("mine"), presets.load("tuned_shared"))
    assert not presets.get("reach").user and presets.get("reach").values["crawl"]["edge_probe"] == 0.1
    for name, needle in (("broken", "broken.json is not used: Expecting"), ("foreign", "not a preset file"),
                         ("Upper", "a preset name is"), ("shape", "values.reflex is not a table")):
        with pytest.raises(presets.PresetError, match=needle) as e:
            presets.load(name)
        assert "\n" not in str(e.value) and str(pdir) in str(e.value)
    assert len(presets.user_problems()) == 5
    assert cli.main(["presets"]) == 0
    out, err = capsys.readouterr()
    assert "\nmine " in out and "broken" not in out
    assert err.count("\n") == 5 and all(line.startswith("note: user preset file ") for line in err.splitlines())
    assert "its name is the shipped preset reach's" in err
    assert cli.main(["presets", "reach"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("reach (crawl preset): ") and err.count("\n") == 1 and "rename it" in err
    for argv in (["stepdown", "--preset", "broken", "--out", "o"], ["sweep", "--preset", "broken", "--dry-run"],
                 ["presets", "foreign"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "is not used" in err, (argv, err)
    # a preset of the other kind is refused by kind, naming the user's presets of the kind taken
    assert _save("bnd", BOUND) == 0
    capsys.readouterr()
    assert cli.main(["stepdown", "--preset", "bnd", "--out", "o"]) == 2
    err = capsys.readouterr().err
    assert "bnd is a bound preset" in err and err.rstrip().endswith("tuned_per_leg_cond, mine")


def test_user_preset_reaches_sweep_tune_bound_and_the_reach_map(pdir, tmp_path, capsys):
    from experiments import reach_map
    from hyqjax.cli import bound
    from hyqjax.studies.sweep.scenario import build_scenario
    from hyqjax.studies.sweep.spec import SweepSpec

    assert _save("mine", PER_LEG) == 0 and _save("sh", SHARED + ":snes") == 0 and _save("bnd", BOUND) == 0
    capsys.readouterr()
    # a sweep spec: the scenario's params are the preset's, instance for instance
    for name in ("mine", "sh"):
        spec = SweepSpec.from_dict(dict(grid=dict(height=[0.16, 0.2]), preset=name))
        sc, _ = build_scenario(spec.instance_inputs(0, 2), spec)
        want = presets.load(name)
        got, tg = jax.tree_util.tree_flatten(sc.params)
        exp, te = jax.tree_util.tree_flatten(want)
        assert tg == te, name
        for g, w in zip(got, exp):
            g = np.asarray(g)
            np.testing.assert_array_equal(g, np.broadcast_to(np.asarray(w), g.shape))
    assert cli.main(["sweep", "--preset", "mine", "--grid", "height=0.16", "--dry-run", "--out", "s"]) == 0
    capsys.readouterr()
    # hyqjax tune --preset: the start point (the values it maps theta on) is the user preset's
    from hyqjax.studies.tune.wallclock_config import start_settings

    args = cli.build_parser().parse_args(["tune", "--preset", "sh", "--out", str(tmp_path / "t")])
    args.validate_command(args)
    assert args.wallclock_config.start_preset == "sh"
    v = presets.get("sh").values
    assert start_settings("sh") == dict(crawl=v["crawl"], reflex=v["reflex"])
    # hyqjax bound --preset and --params NAME of a user bounding preset
    for argv in (["bound", "--preset", "bnd"], ["bound", "--params", "bnd"]):
        a = cli.build_parser().parse_args(argv + ["--out", str(tmp_path / "b")])
        bound.check_options(a)
        assert a.preset == "bnd" or a.params == "bnd"
    from hyqjax.bounding import robust as rb

    assert _leaves_equal(rb.params_from_values(rb.load_params("bnd")), presets.load("bound_robust"))
    # the reach map's --preset
    assert reach_map.check_presets(["mine", "reach"]) == ["mine", "reach"]
    params = reach_map.variant_params(["mine"], {}, "", "", preset_names=("mine",))
    assert _leaves_equal(params["mine"], presets.load("clean"))


def test_sweep_store_refuses_a_resume_after_the_presets_values_changed(pdir, tmp_path, capsys):
    """The manifest records the digest of the spec's preset's values; a writer is refused once the user preset's
    values change (one message naming the preset and both digests), a reader still reads, a manifest without
    the digest (an earlier hyqjax's) resumes."""
    from hyqjax.studies import sweep
    from hyqjax.studies.sweep.manifest import PRESET_DIGEST

    assert _save("mine", SHARED + ":snes") == 0
    capsys.readouterr()
    spec = sweep.SweepSpec.from_dict(dict(seed=5, grid=dict(height=[0.1, 0.2, 0.3], reflex=[False, True]),
                                          preset="mine"))
    layout = dict(platform="cpu", device_kind="cpu", devices=1)
    out = tmp_path / "s"

    def write(chunks):
        with sweep.SweepStore(str(out), spec, 2, layout, writer=True) as st:
            for c in chunks:
                a, b = st.chunk_range(c)
                rows = spec.instance_inputs(a, b)
                ok = rows["height"] < 0.25
                st.write_chunk(c, {**rows, **sweep.count_outcomes(dict(
                    success=ok, failure_reason=np.where(ok, "", "tilt"), diverged=ok & False,
                    peak_pitch=rows["height"], mean_mobility=rows["height"]))}, 0.1)

    write([0])
    man = json.loads((out / "manifest.json").read_text())
    old = presets.get("mine").digest
    assert man[PRESET_DIGEST] == old == presets.values_digest(json.loads((pdir / "mine.json").read_text())["values"])
    write([1])  # same values: resumes
    with sweep.SweepStore(str(out), spec, 2, layout, writer=True) as st:  # values changed while a writer runs
        assert _save("mine", PER_LEG, "--force") == 0  # the same name, other values
        capsys.readouterr()
        with pytest.raises(sweep.StoreMismatch, match="other values of preset mine"):
            st.write_chunk(2, spec.instance_inputs(*st.chunk_range(2)), 0.1)
    assert sorted(json.loads((out / "manifest.json").read_text())["chunks"]) == ["0", "1"]
    new = presets.get("mine").digest
    assert new != old and sweep.SweepSpec.from_dict(spec.to_dict()).spec_hash == spec.spec_hash
    with pytest.raises(sweep.StoreMismatch) as e:
        write([2])
    msg = str(e.value)
    assert "\n" not in msg and "preset mine" in msg and old[:16] in msg and new[:16] in msg
    with sweep.SweepStore(str(out), spec) as st:  # a reader reads the rows as they are
        assert len(st.load()["index"]) == 4
    # a Ray worker whose preset has other values than the driver's refuses the chunk (before any compile)
    from hyqjax.studies.sweep import cluster

    with pytest.raises(RuntimeError, match=f"other values of preset mine .*{new[:16]}.*{old[:16]}"):
        cluster.run_chunk(spec.to_dict(), spec.spec_hash, 0, 2, 2, "c", preset_digest=old)
    # the command line refuses it in one line, exit 2, before anything compiles
    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(spec.to_dict()))
    assert cli.main(["sweep", str(spec_file), "--out", str(out), "--impl", "c"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "other values of preset mine" in err and new[:16] in err, err
    man = json.loads((out / "manifest.json").read_text())
    del man[PRESET_DIGEST]  # a store written before the digest was recorded
    (out / "manifest.json").write_text(json.dumps(man))
    write([2])
    with sweep.SweepStore(str(out), spec) as st:
        assert len(st.load()["index"]) == 6


@pytest.mark.slow
def test_stepdown_runs_a_user_preset(pdir, tmp_path, capsys):
    assert _save("mine", PER_LEG) == 0
    capsys.readouterr()
    rc = cli.main(["stepdown", "--preset", "mine", "--instances", "1", "--impl", "c", "--heights", "0.16",
                   "--reflex", "on", "--duration", "9", "--no-figures", "--out", str(tmp_path / "sd")])
    assert rc == 0, capsys.readouterr().err
    res = json.load(open(tmp_path / "sd" / "results.json"))
    assert res["config"]["preset"] == "mine" and res["preset"]["values"] == presets.get("mine").values
    assert not res["instances"][0]["diverged"] and res["instances"][0]["progress"] > 0.0


def test_concurrent_writers_leave_one_whole_file(pdir):
    """Eight threads save the same name at once: without --force exactly one wins and the others are refused in one
    line; with --force every write lands whole (the file is one of them, byte for byte); no temporary is left."""
    import threading

    from hyqjax.presets import from_results

    base = from_results.crawl_preset("mine", SHARED, "snes")
    docs = [dict(base, description=f"writer {i}") for i in range(8)]
    for force in (False, True):
        if pdir.exists():
            for f in os.listdir(pdir):
                os.remove(pdir / f)
        won, refused = [], []

        def go(d, force=force, won=won, refused=refused):
            try:
                from_results.write(d, force)
                won.append(d["description"])
            except presets.PresetError as e:
                refused.append(str(e))

        threads = [threading.Thread(target=go, args=(d,)) for d in docs]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(os.listdir(pdir)) == ["mine.json"]
        got = json.loads((pdir / "mine.json").read_text())
        assert got["description"] in won and got["values"] == base["values"]
        if force:
            assert len(won) == 8 and not refused
        else:
            assert len(won) == 1 and len(refused) == 7 and all("give --force" in r and "\n" not in r for r in refused)


def test_user_dir_is_the_env_then_xdg_then_home(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HYQJAX_PRESETS_DIR", str(tmp_path / "env"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert presets.user_dir() == str(tmp_path / "env")
    monkeypatch.delenv("HYQJAX_PRESETS_DIR")
    assert presets.user_dir() == str(tmp_path / "xdg" / "hyqjax" / "presets")
    monkeypatch.delenv("XDG_DATA_HOME")
    assert presets.user_dir() == str(tmp_path / "home" / ".local" / "share" / "hyqjax" / "presets")
    # a presets directory that is a file: save refused in one line, exit 2
    monkeypatch.setenv("HYQJAX_PRESETS_DIR", str(tmp_path / "afile"))
    (tmp_path / "afile").write_text("")
    assert _save("mine", SHARED) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a file, not a directory" in err
    assert presets.names() == presets.names(user=False)


def test_tune_closing_line_names_a_save_command_that_works(pdir, tmp_path, capsys):
    """`hyqjax tune`'s closing lines name `hyqjax presets save NAME --from DIR/results.json`: with a name, that very
    command saves the run's returned set (here the run of `clean`, copied into DIR)."""
    import shlex
    import shutil

    from hyqjax.cli.tune_wallclock import returned_lines

    run_dir = tmp_path / "tune"
    run_dir.mkdir()
    shutil.copy(PER_LEG, run_dir / "results.json")
    lines = returned_lines(str(run_dir), json.load(open(PER_LEG)))
    cmd = lines[-1].split(": ", 1)[1]
    assert cmd == f"hyqjax presets save NAME --from {run_dir}/results.json"
    argv = [("mine" if a == "NAME" else a) for a in shlex.split(cmd)[1:]]
    assert cli.main(argv) == 0, capsys.readouterr().err
    assert _leaves_equal(presets.load("mine"), presets.load("clean"))
    several = returned_lines("D", json.load(open(COND)))[-1]
    assert several.endswith("--from D/results.json:cma_es/per_leg_cond")
