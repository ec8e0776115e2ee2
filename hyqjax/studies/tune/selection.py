"""Closed-loop validation selection of a tuning method's iterates (:class:`Selection`) and the final
re-evaluation of its best candidates (:func:`final_choice`).

With a selection, the iterate a method returns at a checkpoint is the best of the iterates it had validated by
then on a fixed validation batch (closed-loop clean success), the validations paid from its clock
(:class:`.clock.Clock`); :class:`.trace.Trace` asks it which iterate that is.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from hyqjax.studies.tune.clock import Clock


class Selection:
    """Closed-loop validation selection: the iterate a method returns is the best, by clean success on a FIXED
    validation batch, of the iterates it has validated so far (the start point first).

    ``evaluate(thetas (1, P)) -> dict(clean (1, V), completed (1, V), physics_steps)`` runs one iterate on the
    ``V`` validation scenarios (the forward program of :mod:`.forward`; the study draws them like the training
    scenarios from a seed of their own, never the held-out set). An iterate is validated when it is *due*:
    ``every`` iterations (0: not by iterations) or ``every_s`` seconds of the method's clock (0: not by time) have
    passed since the last validation, and it differs from the last validated iterate (an unchanged incumbent of
    random search is not run again; it stays due until it changes). Its wall time runs on the method's clock and
    its physics steps are added to the clock's, so the selection is paid from the method's budget.

    Score: (clean rate, completed rate) on the validation batch; an iterate replaces the selected one when its
    score is at least as high (ties go to the later iterate, the one with more optimisation behind it).

    The first validated iterate is the start point (:meth:`.trace.Trace.begin`); it is kept as ``start`` so that
    the final re-evaluation always weighs it against the best validated iterates (:meth:`candidates`): a run
    returns another set only when that set beats its start on the larger pooled batch, not on the luck of one
    validation batch among many iterates."""

    def __init__(self, evaluate: Callable, every: int = 5, every_s: float = 0.0, keep: int = 1):
        if every <= 0 and every_s <= 0:
            raise ValueError("a selection needs every > 0 iterations or every_s > 0 seconds")
        self.evaluate, self.every, self.every_s = evaluate, int(every), float(every_s)
        #: the ``keep`` best validated iterates, best first: ``[score, iteration, theta]`` (a final re-evaluation
        #: of the top candidates chooses among them, :func:`final_choice`)
        self.keep, self.top = int(keep), []
        self.log: list = []
        self.best: tuple | None = None  # (score, theta)
        #: the first validated iterate (the start point): ``[score, iteration, theta]``
        self.start: list | None = None
        self._since, self._t_last, self._theta_last = 0, -math.inf, None

    def due(self, clock: Clock, theta) -> bool:
        self._since += 1
        if self._theta_last is not None and np.array_equal(np.asarray(theta, np.float64), self._theta_last):
            return False
        return bool((self.every > 0 and self._since >= self.every)
                    or (self.every_s > 0 and clock.elapsed() - self._t_last >= self.every_s))

    def validate(self, clock: Clock, theta, iteration: int) -> bool:
        """Run ``theta`` on the validation batch (on ``clock``); True when it becomes the selected iterate."""
        theta = np.asarray(theta, np.float64).copy()
        t0, s0 = clock.elapsed(), clock.physics_steps
        r = self.evaluate(theta[None])
        clock.physics_steps += int(r["physics_steps"])
        score = (float(np.mean(r["clean"][0])), float(np.mean(r["completed"][0])))
        better = self.best is None or score >= self.best[0]
        if self.start is None:
            self.start = [list(score), int(iteration), theta]
        if better:
            self.best = (score, theta)
        self.top = sorted(self.top + [[list(score), int(iteration), theta]],
                          key=lambda t: (t[0][0], t[0][1], t[1]), reverse=True)[:self.keep]
        self._since, self._t_last, self._theta_last = 0, clock.elapsed(), theta
        self.log.append(dict(iteration=int(iteration), wall_s=round(clock.elapsed(), 3),
                             physics_steps=int(clock.physics_steps), clean=score[0], completed=score[1],
                             selected=bool(better), wall_s_run=round(clock.elapsed() - t0, 3),
                             physics_steps_run=int(clock.physics_steps - s0)))
        return better

    def candidates(self) -> list:
        """The candidates of the final re-evaluation: the ``keep`` best validated iterates (best first) and the start
        point after them when it is not one of them."""
        s = self.start
        if s is None or any(t[1] == s[1] and np.array_equal(t[2], s[2]) for t in self.top):
            return list(self.top)
        return list(self.top) + [s]

    def state(self) -> dict:
        return dict(log=self.log, best=None if self.best is None else [list(self.best[0]), self.best[1]],
                    since=self._since, t_last=self._t_last, theta_last=self._theta_last, top=self.top,
                    start=self.start)

    def restore(self, s: dict) -> None:
        self.top = [[list(t[0]), int(t[1]), np.asarray(t[2], np.float64)] for t in s.get("top", [])]
        st = s.get("start")  # absent in a state stored before the start was kept: no start candidate
        self.start = None if st is None else [list(st[0]), int(st[1]), np.asarray(st[2], np.float64)]
        self.log = list(s["log"])
        self.best = None if s["best"] is None else (tuple(s["best"][0]), np.asarray(s["best"][1], np.float64))
        self._since, self._t_last = int(s["since"]), float(s["t_last"])
        self._theta_last = None if s["theta_last"] is None else np.asarray(s["theta_last"], np.float64)


def final_choice(top: list, validation_n: int, evaluate: Callable) -> dict:
    """The final re-evaluation of the top candidates of a selection (``top``: ``[score, iteration, theta]``, best
    first, ``score[0]`` the clean rate on ``validation_n`` validation runs): ``evaluate(thetas (K, P)) ->
    dict(clean (K, F), completed (K, F), physics_steps)`` runs them all on ``F`` further scenarios, and the one with
    the best clean rate pooled over both batches (``(n_v c_v + F c_f) / (n_v + F)``, completed breaking ties, then
    the earlier rank) is chosen: a larger validation set than the selection's, so that the returned set is less
    the luck of one batch. Returns ``chosen`` (its index in ``top``), ``theta``, per candidate the rates, and the
    physics steps spent."""
    thetas = np.stack([np.asarray(t[2], np.float64) for t in top])
    r = evaluate(thetas)
    f_clean = np.asarray(r["clean"], np.float64).mean(axis=1)
    f_done = np.asarray(r["completed"], np.float64).mean(axis=1)
    n_f = np.asarray(r["clean"]).shape[1]
    rows = []
    for i, t in enumerate(top):
        pooled = (validation_n * t[0][0] + n_f * f_clean[i]) / (validation_n + n_f)
        pooled_c = (validation_n * t[0][1] + n_f * f_done[i]) / (validation_n + n_f)
        rows.append(dict(iteration=int(t[1]), validation_clean=float(t[0][0]), final_clean=float(f_clean[i]),
                         final_completed=float(f_done[i]), pooled_clean=float(pooled), pooled_completed=float(pooled_c)))
    chosen = max(range(len(rows)), key=lambda i: (rows[i]["pooled_clean"], rows[i]["pooled_completed"], -i))
    return dict(chosen=int(chosen), theta=thetas[chosen], candidates=rows, instances=int(n_f),
                physics_steps=int(r["physics_steps"]))
