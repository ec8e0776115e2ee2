"""The task registry (hyqjax.studies.tasks) and the generic rollout (hyqjax.sim.task) that runs every task."""
from __future__ import annotations

import subprocess
import sys

import pytest

from hyqjax.studies import tasks


def test_reading_the_registry_imports_no_jax_or_mujoco():
    """The command line reads the registry while it builds its parser and checks options (before anything heavy
    is imported): names, simulators and commands come without importing a task's module."""
    code = ("import sys; from hyqjax.studies import tasks; e = tasks.get('stepdown'); "
            "print(tasks.names(), e.impls, e.command, tasks.get('bound').impls); "
            "print(sorted(m for m in ('jax', 'mujoco', 'hyqjax.studies.stepdown', 'hyqjax.bounding.rollout') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines()[-1] == "[]", out
    assert "('stepdown', 'bound')" in out


def test_unknown_task_is_one_line_naming_the_tasks():
    with pytest.raises(ValueError, match=r"task must be one of stepdown, bound, got 'walk'"):
        tasks.get("walk")


def test_each_task_module_declares_what_the_registry_says():
    """One home per declaration: a task module's supported simulators are the registry's, its configuration class
    and rollout factory are the registry's names, and the factory's rollout runs that module's task through the
    generic :class:`hyqjax.sim.task.Rollout`."""
    from hyqjax.sim import task as simtask

    for name in tasks.names():
        e = tasks.get(name)
        mod = e.load()
        assert mod.SUPPORTED_IMPLS == e.impls
        assert e.config is getattr(mod, e.config_class)
        assert isinstance(e.default_config(), e.config)
        rollout_class = getattr(mod, e.factory).__annotations__["return"]
        cls = getattr(mod, rollout_class) if isinstance(rollout_class, str) else rollout_class
        assert issubclass(cls, simtask.Rollout)


def test_registry_rollout_is_the_factorys_compiled_once_per_configuration():
    """``tasks.rollout(name, **overrides)`` is the task's cached rollout of that configuration (so the command line,
    the sweeps and user code share one compile per configuration); the task and its outcome come with it."""
    from hyqjax.studies import stepdown

    ro = tasks.rollout("stepdown", duration=0.5, impl="c")
    assert ro is stepdown.make_stepdown_rollout(stepdown.StepdownConfig(duration=0.5, impl="c"))
    assert ro is tasks.get("stepdown").rollout(stepdown.StepdownConfig(duration=0.5, impl="c"))
    assert isinstance(ro.task, stepdown.StepdownTask) and ro.cfg.duration == 0.5
    assert ro.setup.impl == "c" and ro.sim_config.n_ticks == 250
    with pytest.raises(ValueError, match="impl must be one of"):
        tasks.rollout("bound", impl="cuda")  # not a simulator: the configuration says so before any compile
    assert tasks.get("bound").impls == tasks.get("stepdown").impls  # both tasks run on every simulator
