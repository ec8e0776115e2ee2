"""Rendering, viewing and reporting of recorded instances (headless, CPU, tiny frames).

The trajectory is synthesised (the standing keyframe walking forward off a platform) instead of
simulated, so these tests need no MJX compile; the trace file goes through the same
``hyqjax.io.recording.save`` the step-down command uses.
"""
from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest

from hyqjax.cli import app as cli
from hyqjax.sim import model as hmodel
from hyqjax.io import recording
from hyqjax.core import robot

W, H = 64, 48
N_SAMPLES = 12
DT = 0.02


def synthetic_trace(heights=(0.2, 0.3)) -> tuple[dict, dict]:
    """Two instances: HyQ's standing pose moving 0.8 m forward across the platform edge at x = 0,
    swinging its front-left leg, with the reflex active in the middle third and 200 N on every foot."""
    m = hmodel.load_model()
    t = DT * np.arange(1, N_SAMPLES + 1)
    qpos, act = [], []
    for h in heights:
        q = np.tile(hmodel.standing_qpos(m), (N_SAMPLES, 1))
        q[:, 0] = np.linspace(-0.5, 0.3, N_SAMPLES)
        q[:, 2] = robot.STANDING_BASE_Z + np.where(q[:, 0] < 0.0, h, 0.0)
        q[:, 7 + 1] += 0.4 * np.sin(np.linspace(0, np.pi, N_SAMPLES))  # LF HFE swings
        qpos.append(q)
        act.append((t > t[3]) & (t <= t[7]))
    b = len(heights)
    force = np.zeros((b, N_SAMPLES, 4, 3))
    force[..., 2] = 200.0
    trace = dict(time=np.tile(t, (b, 1)), qpos=np.stack(qpos), reflex_active=np.stack(act), foot_force=force)
    inputs = dict(height=np.asarray(heights), reflex=np.ones(b, bool), instance=np.arange(b))
    return trace, inputs


def results_json(n: int) -> dict:
    """A step-down results.json of ``n`` instances, in the schema ``hyqjax stepdown`` writes; the last one failed."""
    inst = [dict(height=0.2 + 0.1 * i, reflex=True, instance=i, success=i < n - 1,
                 failure_reason="" if i < n - 1 else "lost foothold", peak_pitch=0.1, progress=1.2) for i in range(n)]
    summary = [dict(height=r["height"], reflex=True, n=1, successes=int(r["success"]), success_rate=float(r["success"]),
                    success_ci95=[0.0, 1.0], all_feet_down=1.0, lost_footholds=float(not r["success"]),
                    joint_range_crossed=0.0, min_swing_mobility=0.2, mean_mobility=0.8, peak_pitch=0.1,
                    time_all_down=float("nan"), diverged=0) for r in inst]
    prov = dict(command="hyqjax stepdown --heights 0.2 0.3 --reflex on --out X", seed=7,
                date="2026-01-01T00:00:00+00:00", hyqjax="0.1.0", jax="0.9.2", mujoco="4.0.0",
                mujoco_mjx="3.17.0", python="3.11", devices=["cpu"])
    return dict(provenance=prov, config=dict(heights=[0.2, 0.3], seed=7), summary=summary, instances=inst,
                figures={}, wall_time_s=1.5)


@pytest.fixture(scope="module")
def recorded_dir(tmp_path_factory):
    """An experiment directory with results.json and a traces.npz of both instances."""
    d = tmp_path_factory.mktemp("stepdown")
    trace, inputs = synthetic_trace()
    recording.save(str(d / recording.TRACES_FILE), trace, inputs, np.arange(2), record_every=10, control_dt=0.002)
    with open(d / "results.json", "w") as f:
        json.dump(results_json(2), f)
    return str(d)


def test_recording_roundtrip_and_selection(recorded_dir):
    rec = recording.load(recorded_dir)
    assert rec.n_recorded == 2 and rec.record_every == 10 and rec.control_dt == pytest.approx(0.002)
    assert rec.sample_dt == pytest.approx(DT)
    assert rec.arrays["qpos"].shape == (2, N_SAMPLES, 19)
    assert recording.choose_row(rec, instance=1) == 1
    assert recording.choose_row(rec, worst=True) == 1  # the failed one
    assert recording.choose_row(rec, where=recording.parse_where(["height=0.2", "reflex=on"])) == 0
    assert "failed (lost foothold)" in recording.label(rec, 1)
    with pytest.raises(ValueError, match=r"--instance 5 was not recorded.*0-1"):
        recording.choose_row(rec, instance=5)


def test_parse_record_instances():
    assert recording.parse_instances("0,2-3", 5).tolist() == [0, 2, 3]
    assert recording.parse_instances("all", 3).tolist() == [0, 1, 2]
    assert recording.parse_instances("none", 3).size == 0
    with pytest.raises(ValueError, match=r"--record-instances.*\[0, 4\]"):
        recording.parse_instances("3-7", 5)
    with pytest.raises(ValueError, match="--record-instances"):
        recording.parse_instances("x", 5)


def test_subset_of_instances_keeps_results_rows(tmp_path):
    trace, inputs = synthetic_trace()
    recording.save(str(tmp_path / recording.TRACES_FILE), trace, inputs, np.array([1]), 10, 0.002)
    rec = recording.load(str(tmp_path))
    assert rec.instance_index.tolist() == [1]
    assert rec.row_of(1) == 0 and rec.row_of(0) is None
    assert float(rec.arrays["input_height"][0]) == pytest.approx(0.3)


@pytest.mark.slow
def test_frames_are_drawn_and_change_over_time(recorded_dir):
    from hyqjax.io import render

    rec = recording.load(recorded_dir)
    inst = rec.instance(0)
    opts = render.RenderOptions(width=W, height=H, strip_height=16)
    imgs = list(render.frames(inst, np.arange(N_SAMPLES), opts))
    assert len(imgs) == N_SAMPLES
    assert all(img.shape == (H + 16, W, 3) and img.dtype == np.uint8 for img in imgs)
    views = [img[:H].astype(float) for img in imgs]
    assert all(v.std() > 5.0 for v in views), "frames must not be blank"
    assert np.abs(views[0] - views[-1]).mean() > 2.0, "HyQ walks 0.8 m: the first and last frames must differ"
    # The reflex is active in samples 4..7: an orange border there, none at the start.
    border = np.asarray(render.REFLEX_RGB)
    assert np.all(imgs[5][0, :] == border) and not np.all(imgs[0][0, :] == border)
    # The strip's time cursor moves right.
    cursor = [int(np.argmax((img[H:] < 40).all(-1).sum(0))) for img in (imgs[0], imgs[-1])]
    assert cursor[1] > cursor[0]


@pytest.mark.slow
def test_force_bars_and_platform_height_show(recorded_dir):
    from hyqjax.io import render

    inst = recording.load(recorded_dir).instance(0)
    q = np.asarray(inst["qpos"][0], np.float64)
    with render.FrameRenderer(0.2, render.RenderOptions(width=W, height=H)) as fr:
        with_f = fr.render(q, inst["foot_force"][0])
        without = fr.render(q, None)
    assert np.abs(with_f.astype(float) - without).sum() > 0, "foot force bars must be drawn"
    m = render.scene_model(0.3)
    ids = hmodel.model_ids(m)
    top = m.geom_pos[ids.platform_geom, 2] + m.geom_size[ids.platform_geom, 2]
    assert top == pytest.approx(0.3)


@pytest.mark.slow
def test_render_command_writes_gif_and_stills(recorded_dir, tmp_path, capsys):
    from PIL import Image

    out = str(tmp_path / "worst.gif")
    rc = cli.main(["render", recorded_dir, "--worst", "--width", str(W), "--height", str(H), "--out", out,
                   "--stride", "2", "--stills", "2"])
    assert rc == 0
    with Image.open(out) as im:
        assert im.n_frames == N_SAMPLES // 2
        assert im.size == (W, H + max(24, H // 4))
    stills = sorted(p for p in os.listdir(tmp_path) if p.endswith(".png"))
    assert len(stills) == 2
    text = capsys.readouterr().out
    assert "instance 1" in text
    # The message says what its numbers are: the video's length, the simulated time it shows, the render time.
    video_s = (N_SAMPLES // 2) / (1.0 / (2 * DT))
    assert re.search(rf"a {video_s:.1f} s video of {video_s:.1f} s of simulated time; rendering took [0-9.]+ s "
                     r"\(wall time\)", text), text


@pytest.mark.slow
def test_render_command_writes_mp4(recorded_dir, tmp_path):
    from hyqjax.io import render

    assert render.has_ffmpeg(), "MP4 needs imageio + imageio-ffmpeg: install hyqjax[video] (the CI does)"
    import imageio.v2 as imageio

    out = str(tmp_path / "a.mp4")
    assert cli.main(["render", recorded_dir, "--instance", "0", "--width", str(W), "--height", str(H),
                     "--out", out, "--no-strip"]) == 0
    with imageio.get_reader(out) as r:
        assert r.count_frames() == N_SAMPLES
        assert r.get_meta_data()["fps"] == pytest.approx(1.0 / DT, rel=0.01)


def refused(capsys, argv) -> str:
    """Runs the command line, checks it was refused as a usage error (exit 2, one line, no traceback) and
    returns that line."""
    capsys.readouterr()
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("argv, message", [
    (["--instance", "7"], r"--instance 7 was not recorded.*recorded instances: 0-1"),
    (["--where", "height=0.5"], r"--where .*no recorded instance matches"),
    (["--width", "5"], r"--width must be in \[16, 4096\]"),
])
def test_render_command_rejects_bad_input(recorded_dir, argv, message, capsys):
    assert re.search(message, refused(capsys, ["render", recorded_dir, *argv]))


def test_render_command_rejects_missing_dir(tmp_path, capsys):
    assert re.search("SOURCE .* does not exist", refused(capsys, ["render", str(tmp_path / "missing")]))
    assert "no trace archive" in refused(capsys, ["render", str(tmp_path)])


def test_view_without_display_exits_with_message(recorded_dir, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    rc = cli.main(["view", recorded_dir, "--instance", "1"])
    assert rc != 0
    err = capsys.readouterr().err
    assert "no display" in err and "hyqjax render" in err


def test_report_from_stepdown_dir(recorded_dir, tmp_path, capsys):
    from hyqjax.io import render

    d = tmp_path / "exp"
    d.mkdir()
    with open(d / "results.json", "w") as f:
        json.dump(results_json(2), f)
    render.write_png(str(d / "success.png"), np.full((8, 8, 3), 200, np.uint8))
    render.write_png(str(d / "render" / "instance_001_t000.10s.png"), np.zeros((8, 8, 3), np.uint8))
    assert cli.main(["report", str(d)]) == 0
    # The message names the result files it read (not "from 1 results.json: .").
    assert f"from 1 result file(s): {os.path.join(str(d), 'results.json')}" in capsys.readouterr().out
    page = (d / "report.html").read_text()
    assert "hyqjax stepdown --heights 0.2 0.3 --reflex on --out X" in page  # the exact command
    assert "3.17.0" in page and "<td class=\"l\">7</td>" in page  # versions and seed
    assert "Step-down results" in page and "1/1 (100%)" in page and "0/1 (0%)" in page
    assert "lost foothold" in page and "Failed instances" in page
    assert page.count("data:image/png;base64,") == 2  # the figure and the still, embedded
    assert "instance_001_t000.10s.png" in page


def test_report_of_a_sweep_and_bad_dir(tmp_path, capsys):
    for name in ("a", "b", "c"):
        (tmp_path / name).mkdir()
    with open(tmp_path / "a" / "results.json", "w") as f:
        json.dump(results_json(1), f)
    bound = dict(provenance=dict(command="hyqjax bound --out b", seed=0),
                 groups=dict(run=dict(kinematic_adjustment=True, centrifugal=True,
                                      aggregate=dict(n=2, falls=0, yaw_error_max_deg_mean=1.5), instances=[])))
    with open(tmp_path / "b" / "results.json", "w") as f:
        json.dump(bound, f)
    curve = [dict(height=0.2, n=10, successes=9, rate=0.9, ci95=[0.6, 0.98])]
    sweep = dict(n_instances=10, n_planned=20, successes=9, diverged=0, failure_reasons={"tilt": 1}, complete=False,
                 by_reflex=dict(on=dict(n=10, successes=9, rate=0.9, ci95=[0.6, 0.98], mean_mobility=0.8,
                                        height_curve=curve, h95_wilson=None, h95_logistic=0.181)),
                 provenance=dict(command="hyqjax sweep --out c", seed=3))
    with open(tmp_path / "c" / "summary.json", "w") as f:
        json.dump(sweep, f)
    out = tmp_path / "r.html"
    assert cli.main(["report", str(tmp_path), "--out", str(out)]) == 0
    page = out.read_text()
    assert "Step-down results" in page and "Bounding results" in page and "hyqjax bound --out b" in page
    assert "Sweep results" in page and "10 of 20 planned instances (incomplete)" in page and "0.181" in page
    capsys.readouterr()
    assert cli.main(["report", str(tmp_path / "missing")]) == 2
    assert "is not a directory" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli.main(["report", str(empty)]) == 2
    assert "no results.json" in capsys.readouterr().err


def test_help_explains_the_commands(capsys):
    for cmd in ("render", "view", "report"):
        with pytest.raises(SystemExit):
            cli.main([cmd, "--help"])
        text = capsys.readouterr().out
        assert "usage: hyqjax " + cmd in text and len(text) > 400


@pytest.mark.parametrize("argv, message", [
    (["--record-instances", "2-5"], r"--record-instances: '2-5' is outside the instances \[0, 1\]"),
    (["--record-every", "7"], r"--record-every must divide the number of ticks \(500"),
])
def test_stepdown_recording_options_are_checked_before_compiling(tmp_path, argv, message, capsys):
    out = tmp_path / "out"
    err = refused(capsys, ["stepdown", "--heights", "0.2", "--reflex", "on", "--instances", "2", "--duration", "1",
                           "--out", str(out), *argv])
    assert re.search(message, err)
    assert not out.exists()  # refused before anything was written
