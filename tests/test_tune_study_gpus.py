"""``python -m experiments.tune_study --guided-comparison --gpus K``: one process per GPU, each with its share of the
seeds, then the comparison over every finished seed."""
import json
import os
import shutil

import pytest

STORED = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "tune_guided_h200x2_3min")


def test_child_command_drops_gpus_and_seeds_in_both_forms():
    from experiments.tune_study import child_argv

    argv = ["--guided-comparison", "--gpus", "2", "--out", "D", "--seeds=0,1,2", "--impl", "warp", "--gpus=2"]
    assert child_argv(argv, [0, 2]) == ["--guided-comparison", "--out", "D", "--impl", "warp", "--seeds", "0,2"]


@pytest.fixture
def fake_children(monkeypatch):
    """``subprocess.Popen`` replaced: a child 'runs' by copying the stored two-GPU study of each of its seeds into
    its seed directory (``status`` per GPU: 0 finishes, 75 stops after a segment, other values fail)."""
    import subprocess
    import types

    from experiments import tune_study

    started, status = [], {}

    class Child:
        def __init__(self, cmd, env=None, stdout=None, **kw):
            self.gpu = env["CUDA_VISIBLE_DEVICES"]
            seeds = [int(s) for s in cmd[cmd.index("--seeds") + 1].split(",")]
            out = cmd[cmd.index("--out") + 1]
            started.append((self.gpu, seeds, cmd))
            if status.get(self.gpu, 0) == 0:
                for s in seeds:
                    os.makedirs(os.path.join(out, f"seed{s}"), exist_ok=True)
                    shutil.copy(os.path.join(STORED, f"seed{s}", "results.json"), os.path.join(out, f"seed{s}"))

        def wait(self):
            return status.get(self.gpu, 0)

    monkeypatch.setattr(tune_study, "subprocess", types.SimpleNamespace(Popen=Child, STDOUT=subprocess.STDOUT))
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES", raising=False)
    return started, status


def test_seeds_spread_over_gpus_then_one_comparison(tmp_path, fake_children, capsys):
    """Seeds 0-4 on two GPUs, one process each with ``--seeds`` of its own (dealt round-robin: 0,2,4 and 1,3) and
    ``CUDA_VISIBLE_DEVICES`` 0 and 1; the parent's comparison over all five equals the stored one of the two-GPU
    study."""
    from experiments import tune_study

    started, status = fake_children
    out = tmp_path / "cmp"
    argv = ["--guided-comparison", "--out", str(out), "--impl", "c", "--methods", "guided_es,cma_es,snes",
            "--dims", "per_leg", "--seeds", "0,1,2,3,4", "--wall-minutes", "1", "3", "--heldout", "512", "--gpus", "2"]
    assert tune_study.main(argv) == 0, capsys.readouterr().err
    assert sorted((g, s) for g, s, _ in started) == [("0", [0, 2, 4]), ("1", [1, 3])]
    assert all("--gpus" not in cmd for _, _, cmd in started)
    with open(os.path.join(STORED, "comparison.json")) as f:
        want = json.load(f)
    with open(out / "comparison.json") as f:
        got = json.load(f)
    assert got == want
    assert (out / "comparison.md").read_text() == open(os.path.join(STORED, "comparison.md")).read()
    # a GPU whose process stopped after its segment: exit 75, the same command goes on; a failure wins over it
    started.clear()
    status.update({"0": 75})
    assert tune_study.main([*argv[:2], str(tmp_path / "b"), *argv[3:]]) == 75
    status.update({"1": 3})
    assert tune_study.main([*argv[:2], str(tmp_path / "c"), *argv[3:]]) == 3


@pytest.mark.parametrize("extra, needle", [(["--gpus", "0"], "--gpus must be in [1, 64]"),
                                           (["--gpus", "2", "--methods", "cma_es"], "--gpus belongs to")])
def test_gpus_refused_in_one_line(tmp_path, capsys, extra, needle):
    from experiments import tune_study

    base = [] if "--methods" in extra else ["--guided-comparison"]
    assert tune_study.main([*base, "--out", str(tmp_path / "x"), "--impl", "c", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
