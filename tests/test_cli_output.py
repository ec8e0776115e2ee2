"""What the commands tell a user (no simulation here): help text, the compile phase, progress bars, the
failure reasons in every summary table, the step-down duration check against the crawl's gait timing, and the
batch buckets that keep one compiled shape across instance counts."""
from __future__ import annotations

import os
import re
import warnings

import numpy as np
import pytest

from hyqjax.cli import app
from hyqjax.cli import progress as cli_progress
from hyqjax.sim import compile_phase
from hyqjax.sim import runner as rn
from hyqjax.studies import stepdown_duration as sdd
from hyqjax.studies import stepdown_table
from hyqjax.studies.stepdown_outcome import FAILURE_REASONS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COMMANDS = ("stepdown", "sweep", "bound", "render", "report", "view")


def help_text(cmd: str, capsys) -> str:
    with pytest.raises(SystemExit):
        app.main([cmd, "--help"])
    return capsys.readouterr().out


# ---------------------------------------------------------------- help


@pytest.mark.parametrize("cmd", COMMANDS)
def test_help_names_each_default_once_and_has_an_example(cmd, capsys):
    text = help_text(cmd, capsys)
    flat = re.sub(r"\s+", " ", text)
    assert "(default: None)" not in flat and "(default: False)" not in flat
    for m in re.finditer(r"(--[a-z-]+)[^-]*?\(default:", flat):
        assert flat[m.end():].split("--", 1)[0].count("(default:") == 0, f"{cmd} {m.group(1)}: default twice"
    assert "hyqjax " + cmd in text.split("options:")[0] or cmd == "view" and "hyqjax view" in text


def _subcommand_parsers():
    """Every ``hyqjax`` subcommand's parser (found in the parser, not listed by hand) and the tuning study's, which
    shares ``hyqjax tune``'s options."""
    import argparse

    from experiments import tune_study

    sub = next(a for a in app.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {**sub.choices, "experiments.tune_study": tune_study.build_parser()}


def option_entries(help_text: str) -> dict[str, str]:
    """The options section(s) of an argparse help text as {first option string: its entry, whitespace collapsed};
    an entry is the line that starts with the option and its indented continuation lines."""
    entries, key = {}, None
    for line in help_text.splitlines():
        m = re.match(r"^  (-[-\w]+)", line)
        if m:
            key = m.group(1)
            entries[key] = line
        elif key and line.startswith("   "):
            entries[key] += " " + line
        else:
            key = None
    return {k: re.sub(r"\s+", " ", v) for k, v in entries.items()}


@pytest.mark.parametrize("name", sorted(_subcommand_parsers()))
def test_every_help_states_each_option_default_at_most_once(name, monkeypatch):
    """``--help`` of every subcommand (and of the tuning study): no option entry carries "(default:" twice (the
    formatter adds a default only where the help text does not state one), and none says "(default: None)"."""
    monkeypatch.setenv("COLUMNS", "100")
    entries = option_entries(_subcommand_parsers()[name].format_help())
    assert "--debug" in entries and "--no-cache" in entries and len(entries) > 3, sorted(entries)
    for opt, entry in entries.items():
        assert entry.count("(default") <= 1, f"{name} {opt}: {entry}"
        assert "(default: None)" not in entry, f"{name} {opt}: {entry}"


def test_sweep_help_keeps_the_toml_example_lines(capsys):
    text = help_text("sweep", capsys)
    assert "\n    [grid]\n    height = [0.16, 0.21, 0.24]\n    reflex = [false, true]\n" in text


def test_stepdown_help_names_the_outcome_hierarchy_and_the_reasons(capsys):
    text = help_text("stepdown", capsys)
    assert re.search(r"\n  completed\s+the paper's criterion", text)
    assert re.search(r"\n  clean\s+completed and no shin contact", text)
    assert all(r in re.sub(r"\s+", " ", text) for r in FAILURE_REASONS)


def test_every_command_writes_under_out_by_default():
    parser = app.build_parser()
    for cmd in ("stepdown", "sweep", "bound"):
        assert parser.parse_args([cmd]).out == f"out/{cmd}"


# ---------------------------------------------------------------- failure reasons in every summary


def outcome_columns(n, **set_reasons):
    out = {k: np.zeros(n, bool) for k in FAILURE_REASONS}
    for k, idx in set_reasons.items():
        out[k][idx] = True
    failed = np.zeros(n, bool)
    for k in FAILURE_REASONS:
        failed |= out[k]
    out["clean"] = ~failed
    out["completed"] = ~(failed & ~out["shin_strike"])
    for k in ("lost_footholds", "min_swing_mobility", "mean_mobility", "peak_pitch", "diverged"):
        out[k] = np.zeros(n)
    out["time_all_down"] = np.full(n, np.nan)
    return out


def test_stepdown_table_prints_the_failure_reasons():
    """The case a user met: 0/2 completed at 27 cm because of feet_not_down, which the table must show."""
    table = dict(height=np.array([0.27, 0.27, 0.16, 0.16]), reflex=np.array([True, True, True, True]))
    out = outcome_columns(4, feet_not_down=[0, 1], shin_strike=[1, 2])
    rows = stepdown_table.summarize(table, out)
    assert rows[1]["failure_reasons"] == {"feet_not_down": 2, "shin_strike": 1}
    assert rows[0]["failure_reasons"] == {"shin_strike": 1}
    text = stepdown_table.format_table(rows)
    line27 = next(ln for ln in text.splitlines() if ln.lstrip().startswith("0.27"))
    assert line27.rstrip().endswith("feet_not_down 2, shin_strike 1")
    assert "failure reasons (runs)" in text.splitlines()[0]
    assert "completed:" in text and "clean: completed" in text


def test_sweep_prints_the_same_reason_names_as_stepdown():
    from hyqjax.studies.sweep.outcomes import count_outcomes
    from hyqjax.studies.sweep.summary import format_summary

    out = count_outcomes(outcome_columns(3, feet_not_down=[0, 1], lost_foothold=[1]))
    reasons: dict = {}
    for r in out["failure_reason"][~out["success"]]:
        for part in r.split("; "):
            reasons[part] = reasons.get(part, 0) + 1
    assert reasons == stepdown_table.failure_reasons(out) == {"feet_not_down": 2, "lost_foothold": 1}
    text = format_summary(dict(n_instances=3, n_planned=3, failure_reasons=reasons))
    assert "feet_not_down x2" in text and "lost_foothold x1" in text


def test_bound_table_counts_failure_reasons_and_explains_dashes():
    from hyqjax.bounding import summary as bs

    per = [bs.InstanceResult(success=False, fell_low_trunk=False, fell_roll=True, fell_pitch=False, diverged=False,
                             fail_time=1.0, yaw_error_max_deg=3.0, yaw_error_rms_deg=1.0, speed_cmd=0.5,
                             yaw_rate_cmd=0.3, speed_mean=None, speed_error_mean_abs=None, speed_error_rms=None,
                             lateral_speed_mean=None, yaw_rate_mean=None, yaw_rate_error_rms=None,
                             periodicity_residual=None)] * 2
    groups = dict(run=dict(aggregate=bs.aggregate(per)))
    assert groups["run"]["aggregate"]["failure_reasons"] == {"fell_roll": 2}
    text = bs.format_table(groups, settle=2.0, duration=2.4)
    assert "failure reasons (runs)" in text and "fell_roll 2" in text
    assert "- = not measured" in text and "ramp + 1 s = 2 s" in text and "--duration 2.8 s" in text


# ---------------------------------------------------------------- the step-down duration


def test_shortest_duration_is_a_lower_bound_of_measured_runs():
    """The gait-timing bound against 4,096 H100 step-downs (docs/results): no completed run got its feet down
    before it, and the typical time is below the median measured one."""
    z = np.load(os.path.join(ROOT, "docs/results/stepdown_default_h100/remedy_instances.npz"), allow_pickle=True)
    timing = sdd.CrawlTiming.from_params()
    done = z["completed"].astype(bool)
    t_down = z["time_all_down"][done]
    lower = np.array([sdd.shortest_duration(timing, s) for s in z["start_distance"][done]])
    assert np.all(t_down >= lower), np.min(t_down - lower)
    assert sdd.shortest_duration(timing) == pytest.approx(2 * 3.4 + 2 * 0.85 + 0.4)  # 3rd step of LH, 3rd in line
    for h in (0.16, 0.24):
        sel = done & (z["height"] == h) & z["reflex"].astype(bool)
        assert sdd.expected_duration(timing, h) < np.median(z["time_all_down"][sel])


def test_stepdown_refuses_a_duration_no_run_can_complete(capsys, tmp_path):
    code = app.main(["stepdown", "--duration", "5", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith("hyqjax stepdown: --duration must be at least 8.9 s") and "got 5" in err[0]
    assert not (tmp_path / "o").exists()


def test_stepdown_warns_about_a_short_duration():
    timing = sdd.CrawlTiming.from_params()
    note = sdd.check_duration(12.0, [0.16, 0.24], timing)
    assert note.startswith("warning: --duration 12 s") and "feet_not_down" in note and "15.8 s" in note
    assert sdd.check_duration(24.0, [0.16, 0.24], timing) is None
    slow = sdd.CrawlTiming.from_params(forward_velocity=0.05)  # half the step length: more steps
    assert sdd.shortest_duration(slow) > sdd.shortest_duration(timing)
    assert "no forward steps" in sdd.check_duration(24.0, [0.2], sdd.CrawlTiming.from_params(forward_velocity=0.0))


def test_sweep_duration_is_checked_against_its_slowest_instances(capsys, tmp_path):
    code = app.main(["sweep", "--duration", "4", "--out", str(tmp_path / "s"), "--dry-run"])
    assert code == 0  # a sweep too short for any step-down is warned about, not refused (short sweeps test stores)
    from hyqjax.cli import sweep as cli_sweep
    from hyqjax.studies import sweep

    short = sweep.SweepSpec.from_dict(dict(cli_sweep.DEFAULT_SPEC, duration=4.0))
    assert "every instance will fail with feet_not_down" in cli_sweep.check_spec_duration(short)

    spec = sweep.SweepSpec.from_dict(dict(cli_sweep.DEFAULT_SPEC, duration=12.0))
    assert "feet_not_down" in cli_sweep.check_spec_duration(spec)
    assert cli_sweep.check_spec_duration(sweep.SweepSpec.from_dict(cli_sweep.DEFAULT_SPEC)) is None


# ---------------------------------------------------------------- compile phase and progress


def test_progress_bar_ends_at_its_total_for_any_duration(capsys):
    """bound --duration 2.4 reported 0.8 s chunks whose float sum passes 2.4: no clamping warning, no overshoot."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with cli_progress.sim_progress("bound: 2 instances", 2.4) as progress:
            done = 0.0
            for _ in range(3):
                done += 0.8
                progress(done, 3 * 0.8)
            assert progress.bar.n == pytest.approx(2.4) and progress.bar.n <= progress.bar.total
    err = capsys.readouterr().err
    assert "2.4/2.4 sim s" in err and "-" not in err.split("<")[-1].split("]")[0]


def test_compile_phase_is_announced_with_its_time_and_kept_out_of_the_rate(capsys):
    with cli_progress.compile_status("stepdown") as status:
        for listener in list(compile_phase._LISTENERS):
            listener("start", dict(batch=8))
            listener("compile", dict(program="init"))
            listener("compiled", dict(program="init", from_cache=False))
            listener("end", dict(batch=8, seconds=12.5, from_cache=False))
            listener("done", dict(compile_s=12.5, simulate_s=2.0, batch=8, passes=1, instances=6))
    err = capsys.readouterr().err
    assert compile_phase.COMPILE_LABEL == "compiling (first run of this shape; cached afterwards)"
    assert "stepdown: " + compile_phase.COMPILE_LABEL in err and "compiled in 12.5 s" in err
    text = status.throughput_text(6, 1000)
    assert text.startswith("simulating 2.0 s: 3,000 env-steps/s of 6 instances; compile 12.5 s besides")
    assert "2 padded rows not counted" in text
    status.timings[-1] = dict(compile_s=0.0, simulate_s=2.0, batch=32, passes=1, instances=18, shards=2)
    assert status.throughput_text(18, 1000).endswith("; 2 shards of 16 rows, 14 padded rows not counted")


def test_a_program_from_the_persistent_cache_is_not_called_a_compile(capsys):
    """A compile phase whose programs all came from the persistent compilation cache (the runner's "compiled" events
    say ``from_cache``) never shows the compiling label; its one line says the program was loaded."""
    with cli_progress.compile_status("stepdown") as status:
        for listener in list(compile_phase._LISTENERS):
            listener("start", dict(batch=32))
            for program in ("init", "advance"):
                listener("compile", dict(program=program))
                listener("compiled", dict(program=program, from_cache=True))
            listener("end", dict(batch=32, seconds=1.5, from_cache=True))
    err = capsys.readouterr().err
    assert compile_phase.COMPILE_LABEL not in err and "compiled in" not in err
    assert "stepdown: " + cli_progress.PREPARE_LABEL in err
    assert "stepdown: compiled program loaded from the cache in 1.5 s" in err
    assert status.compile_s == 1.5 and not status.compiling


def test_a_slow_compile_request_is_shown_as_compiling(capsys):
    """A compile request still unanswered after COMPILE_AFTER_S (no cache hit: XLA is compiling) switches the line
    to the compiling label while it runs."""
    import time

    with cli_progress.compile_status("sweep") as status:
        listener = status
        listener("start", dict(batch=8))
        listener("compile", dict(program="advance"))
        deadline = time.time() + 10 * cli_progress.COMPILE_AFTER_S
        while not status.compiling and time.time() < deadline:
            time.sleep(0.05)
        assert status.compiling
        listener("compiled", dict(program="advance", from_cache=False))
        listener("end", dict(batch=8, seconds=3.0, from_cache=False))
    err = capsys.readouterr().err
    assert "sweep: " + compile_phase.COMPILE_LABEL in err and "compiled in 3.0 s" in err


# ---------------------------------------------------------------- batch buckets


def test_batch_buckets_keep_one_shape_across_instance_counts():
    plan = rn.batch_plan
    assert [plan(n).size for n in (1, 2, 3, 4, 5, 8)] == [1, 2, 4, 4, 8, 8]
    for n in (6, 12, 18, 24, 100):  # the default step-down (3 heights x 2) at any --instances: one shape
        p = plan(n)
        assert p.size == rn.CPU_PASS and p.passes == -(-n // rn.CPU_PASS) and 0 <= p.padded < rn.CPU_PASS
    assert plan(20, n_devices=2) == rn.BatchPlan(20, 16, 2)
    assert plan(3, n_devices=2) == rn.BatchPlan(3, 4, 1)
    assert plan(10200, "gpu") == rn.BatchPlan(10200, 10200, 1)  # accelerators: one pass at the batch's size
    assert plan(10201, "gpu", 2) == rn.BatchPlan(10201, 10202, 1)
    with pytest.raises(ValueError, match="at least one instance"):
        plan(0)


def test_c_mujoco_buckets_one_shape_for_the_step_down_at_3_4_and_5_instances():
    """The C MuJoCo backend's bucket rule (hyqjax.sim.runner.host_physics_plan): one pass of the next power of two,
    at least HOST_PHYSICS_MIN_BUCKET; the default step-down (3 heights x 2 reflex settings) at --instances 3, 4 and 5
    (18, 24, 30 instances) is one compiled shape, and no batch is padded to more than twice its size."""
    plan = rn.host_physics_plan
    low = rn.HOST_PHYSICS_MIN_BUCKET
    assert {plan(6 * k).size for k in (3, 4, 5)} == {32}
    assert [plan(n).size for n in (1, 2, low, low + 1, 32, 33, 1000)] == [low, low, low, 2 * low, 32, 64, 1024]
    for n in range(1, 300):
        p = plan(n)
        assert p.passes == 1 and p.size >= max(n, low) and (p.size & (p.size - 1)) == 0
        assert p.size < 2 * max(n, low)
    with pytest.raises(ValueError, match="at least one instance"):
        plan(0)


def test_padded_rows_repeat_the_last_instance():
    tree = dict(a=np.arange(5), b=np.arange(10).reshape(5, 2))
    idx = np.minimum(np.arange(8, 16), 4)
    rows = rn._rows(tree, 0, idx)
    assert rows["a"].tolist() == [4] * 8 and rows["b"].shape == (8, 2)
    assert rn._rows(tree, None, idx) is tree
    mixed = rn._rows(tree, dict(a=0, b=None), np.array([1, 2]))
    assert mixed["a"].tolist() == [1, 2] and mixed["b"] is tree["b"]


def test_success_figure_says_it_plots_clean_success():
    """success.png plots the clean level (``success`` = clean), and says so."""
    import matplotlib.pyplot as plt

    from hyqjax.studies import stepdown_figures

    table = dict(height=np.array([0.16, 0.16]), reflex=np.array([False, True]))
    rows = stepdown_table.summarize(table, outcome_columns(2, shin_strike=[1]))
    fig, ax = plt.subplots()
    stepdown_figures._draw_success(ax, rows)
    assert ax.get_ylabel() == "clean success rate" and "clean" in ax.get_title()
    heights = sorted(b.get_height() for b in ax.patches)
    assert heights == [pytest.approx(0.0), pytest.approx(1.0)]  # reflex on: completed but not clean
    plt.close(fig)


def test_a_program_compiled_in_the_background_is_kept_and_the_next_one_traces_for_its_outputs():
    """``AheadOfTime._executable_in_background``: the program's outputs (``out_info``) are known before XLA has
    compiled it, a second program traced for them runs on the first one's real outputs, each program is compiled
    once (the second request returns the kept program without compiling), and the phase counts both compiles."""
    import jax
    import jax.numpy as jnp

    class Runner(compile_phase.AheadOfTime):
        def __init__(self):
            self._executables, self.last_timing = {}, dict(compiled=0, from_cache=0)
            self._reset_compile_phase()

    r = Runner()
    first = jax.jit(lambda x: dict(y=2.0 * x, n=jnp.sum(x > 0).astype(jnp.int32)))
    second = jax.jit(lambda c, k: c["y"] * c["n"] + k, static_argnums=1)
    x = jnp.arange(5.0)
    get, out = r._executable_in_background("first", first, (x,), batch=5)
    assert jax.tree_util.tree_map(lambda s: (s.shape, s.dtype), out) == dict(y=((5,), jnp.float32), n=((), jnp.int32))
    nxt = r._executable("second", second, (out,), (3,), batch=5)
    c = get()(x)
    np.testing.assert_array_equal(np.asarray(nxt(c)), 2.0 * np.arange(5.0) * 4 + 3)
    again, _ = r._executable_in_background("first", first, (x,), batch=5)
    assert again() is get() and r.last_timing["compiled"] + r.last_timing["from_cache"] == 2
