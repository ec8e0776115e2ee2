"""The registry of simulated tasks: a name, what it is, its configuration class and default configuration, the
simulators it runs on, and its rollout (:class:`hyqjax.sim.task.Rollout` of its :class:`hyqjax.sim.task.Task`).

======== ============================================ ================================ =====================
name     what                                         configuration                    command
======== ============================================ ================================ =====================
stepdown Focchi et al. (2017), Sec. IV: the crawl off  ``StepdownConfig``               ``hyqjax stepdown``,
         a platform, with and without the reflex      (:mod:`hyqjax.studies.stepdown`) ``sweep``, ``tune``
bound    Orsolino et al.: bounding from feed-forward  ``BoundingRolloutConfig``        ``hyqjax bound``
         impulses with speed and turning control      (:mod:`hyqjax.bounding.rollout`)
======== ============================================ ================================ =====================

``rollout("stepdown", duration=2.0)`` is ``make_stepdown_rollout(StepdownConfig(duration=2.0))`` (compiled once per
configuration), and the command line asks an entry for its configuration class (option checks), its simulators
(``--impl``'s choices and help) and its rollout. The task modules are imported on first use, so reading the
registry (``names()``, ``get(name).impls``) loads no JAX or MuJoCo.
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from hyqjax.sim.impls import ALL_IMPLS


@dataclasses.dataclass(frozen=True)
class TaskEntry:
    """One registered task.

    Attributes:
      name: the registry's key.  what: one line on what it simulates.
      module: the module that is the task's one home (its ``Task``, ``Rollout`` and configuration).
      config_class: the name of its configuration class there (frozen, hashable; validates itself).
      factory: the name of its cached rollout factory there (``factory(config) -> Rollout``).
      impls: the simulators it runs on (:mod:`hyqjax.sim.backend`; ``auto`` is always accepted too).
      command: the ``hyqjax`` subcommand that runs it.
    """

    name: str
    what: str
    module: str
    config_class: str
    factory: str
    impls: tuple[str, ...]
    command: str

    def load(self):
        return importlib.import_module(self.module)

    @property
    def config(self) -> type:
        """The configuration class (imports the task's module)."""
        return getattr(self.load(), self.config_class)

    def default_config(self) -> Any:
        return self.config()

    def rollout(self, config: Any = None, **overrides):
        """The task's rollout for ``config`` (default: the default configuration) with ``overrides`` replaced."""
        cfg = self.default_config() if config is None else config
        if overrides:
            cfg = dataclasses.replace(cfg, **overrides)
        return getattr(self.load(), self.factory)(cfg)


REGISTRY: dict[str, TaskEntry] = {
    e.name: e for e in (
        TaskEntry("stepdown", "Focchi et al. (2017), Section IV: HyQ crawls off a platform, with and without the "
                              "height reflex", "hyqjax.studies.stepdown", "StepdownConfig", "make_stepdown_rollout",
                  ALL_IMPLS, "stepdown"),
        TaskEntry("bound", "Orsolino et al.: bounding from optimised feed-forward impulses with speed and turning "
                           "control", "hyqjax.bounding.rollout", "BoundingRolloutConfig", "make_bounding_rollout",
                  ALL_IMPLS, "bound"),
    )
}


def names() -> tuple[str, ...]:
    return tuple(REGISTRY)


def get(name: str) -> TaskEntry:
    """The entry of task ``name``; a ``ValueError`` naming the registered tasks otherwise."""
    if name not in REGISTRY:
        raise ValueError(f"task must be one of {', '.join(REGISTRY)}, got {name!r}")
    return REGISTRY[name]


def rollout(name: str, config: Any = None, **overrides):
    """``get(name).rollout(config, **overrides)``."""
    return get(name).rollout(config, **overrides)
