"""What a tuning method did under its wall-clock budget (:class:`Trace`): a log row per generation or step, and
per checkpoint ``c`` (seconds of its :class:`.clock.Clock`) the iterate it would hand back had it been stopped at
``c``: the last iterate it had finished by then (the start point if it had finished none, e.g. while compiling),
or with a :class:`.selection.Selection` the best of the iterates it had validated by then.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from hyqjax.studies.tune.clock import Clock
from hyqjax.studies.tune.selection import Selection


@dataclasses.dataclass
class Trace:
    """What a method did: per generation / step a log row; per checkpoint the iterate it would return (with the
    physics steps spent by the last work finished before the checkpoint). With a :class:`Selection`, the iterate
    it would return is the selected one (:meth:`begin` validates the start point)."""

    checkpoints: tuple
    theta0: np.ndarray
    select: Selection | None = None
    log: list = dataclasses.field(default_factory=list)
    points: list = dataclasses.field(default_factory=list)
    _last: tuple = None

    def __post_init__(self):
        self._last = (np.asarray(self.theta0, np.float64).copy(), None)
        self._spent, self._iterations = 0, 0

    def done(self, clock: Clock) -> bool:
        return clock.elapsed() >= self.checkpoints[-1]

    def _pass(self, clock: Clock) -> None:
        """Checkpoints that passed during the work just finished get the iterate from before it."""
        now = clock.elapsed()
        for c in self.checkpoints[len(self.points):]:
            if now < c:
                break
            pt = dict(seconds=float(c), theta=self._last[0].tolist(), physics_steps=int(self._spent))
            pt.update(self._last[1] or {})
            self.points.append(pt)
        self._spent = int(clock.physics_steps)

    def _validate(self, clock: Clock, theta, iteration: int) -> None:
        better = self.select.validate(clock, theta, iteration)
        self._pass(clock)  # checkpoints passed while validating get the iterate selected before
        if better:
            row = self.select.log[-1]
            self._last = (np.asarray(theta, np.float64).copy(),
                          dict(selected_iteration=iteration, validation_clean=row["clean"],
                               validation_completed=row["completed"]))

    @property
    def returned(self) -> np.ndarray:
        """The iterate the method would return now."""
        return self._last[0].copy()

    def begin(self, clock: Clock) -> None:
        """With a selection: validate the start point (on ``clock``), so that an iterate is returned only when it
        validates at least as well as the start. Without one: nothing."""
        if self.select is not None and self.select.best is None:
            self._validate(clock, self.theta0, 0)

    def advance(self, clock: Clock, theta, row: dict | None = None) -> None:
        """Record that ``theta`` is the iterate after the work just finished (``clock`` now); checkpoints that
        passed during that work get the iterate from before it. With a selection, ``theta`` becomes the returned
        iterate only once validated (when due) at least as well as the selected one."""
        self._pass(clock)
        self._iterations += 1
        if row is not None:
            row.update(wall_s=round(clock.elapsed(), 3), physics_steps=int(clock.physics_steps))
            self.log.append(row)
        if self.select is None:
            self._last = (np.asarray(theta, np.float64).copy(), None)
        elif self.select.due(clock, theta):
            self._validate(clock, theta, self._iterations)

    def state(self) -> dict:
        """Everything :meth:`restore` needs to go on as if never stopped (:mod:`.resume`)."""
        return dict(checkpoints=list(self.checkpoints), log=self.log, points=self.points, last=list(self._last),
                    spent=self._spent, iterations=self._iterations,
                    select=None if self.select is None else self.select.state())

    def restore(self, s: dict) -> None:
        if [float(c) for c in s["checkpoints"]] != [float(c) for c in self.checkpoints]:
            raise ValueError(f"stored checkpoints {s['checkpoints']} differ from {list(self.checkpoints)}")
        if (s["select"] is None) != (self.select is None):
            raise ValueError("stored run and this one differ in their selection")
        self.log, self.points = list(s["log"]), list(s["points"])
        self._last = (np.asarray(s["last"][0], np.float64), s["last"][1])
        self._spent, self._iterations = int(s["spent"]), int(s["iterations"])
        if self.select is not None:
            self.select.restore(s["select"])

    def finish(self, clock: Clock) -> list:
        """Checkpoints not reached (the budget ran out at the last one): the iterate returned at the end."""
        for c in self.checkpoints[len(self.points):]:
            pt = dict(seconds=float(c), theta=self._last[0].tolist(), physics_steps=int(self._spent))
            pt.update(self._last[1] or {})
            self.points.append(pt)
        return self.points

