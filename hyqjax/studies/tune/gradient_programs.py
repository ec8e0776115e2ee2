"""The gradient's programs in the equal-wall-clock study (:mod:`.wallclock`), and what decides whether it can pay.

:class:`GradientPrograms` builds, once per study process, on MJX-JAX: the snapshot windows at the start point
(:mod:`.windows`: a forward run per training scenario keeps the state one tick before the body phase of each leg
about to step over the edge), and per parameterisation the tuning step (the exact gradient of the closed-loop window
objective, :mod:`.objective`: ``jax.jacfwd`` with ``P`` tangents, or with ``grad_mode`` ``"reverse"`` reverse mode
through a fixed-length constraint solver and a checkpointed scan; or the forward-gradient estimate with
``grad_directions`` random tangents)
and the forward evaluation of a batch of candidates on the same windows (the line search). Their one-off costs
(compile and, for the windows, the forward run) go into the study's compile charges (:class:`.clock.Charges`),
so a gradient method pays them as a stand-alone run would.

:func:`gradient_diagnostics`, outside every clock: the gradient's signal-to-noise ratio across windows at the
start point, and Spearman's rank correlation of the window objective with held-out clean success over the
evaluated iterates (:func:`diagnostic_iterates`). ``GradientPrograms.step_cost`` times the ``jacfwd`` and the
reverse-mode steps against one forward evaluation of the same windows.
"""
from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.sim.contacts_from_distance import ContactsFromDistance
from hyqjax.studies.tune import schedule, search
from hyqjax.studies.tune.gradient_stats import gradient_stats

#: Offset of the seed of the gradient's snapshot scenarios.
WINDOW_SEED_OFFSET = 11


def _resource_error(e: BaseException) -> bool:
    """Whether ``e`` says the device (or host) ran out of memory."""
    msg = str(e)
    return isinstance(e, MemoryError) or "RESOURCE_EXHAUSTED" in msg or "out of memory" in msg.lower()


class GradientPrograms:
    """The gradient's programs (MJX-JAX), built once: windows at the start point, exact step, forward window
    value of a batch of candidates; their one-off costs go into ``charges``. ``cfg`` is the study's
    :class:`.wallclock.WallClockConfig` (its seed and gradient settings), ``base`` the start point's parameters."""

    def __init__(self, cfg, base, charges: search.Charges, log):
        from hyqjax.studies.tune import evaluate, objective, windows

        self.cfg, self.base = cfg, base
        self.su = windows.setup()
        sc, _ = evaluate.scenarios(tuple(cfg.train_heights), cfg.grad_train_per_height, cfg.seed + WINDOW_SEED_OFFSET,
                                   params=base)
        spec = windows.WindowSpec(per_scenario=cfg.windows_per_scenario, lead=cfg.window_lead)
        self.sc, self.spec = sc, spec
        self.win = charges.one_off("gradient_windows", lambda: jax.block_until_ready(
            windows.make_windows(sc, spec, self.su)))
        self.win_start = self.win  # the start point's windows (the diagnostics' SNR reads these)
        self.obj = objective.ClosedLoopObjective(ticks=cfg.window_ticks, contacts_from_distance=ContactsFromDistance(
            stiffness=float(cfg.contacts_from_distance))).reweighted(cfg.surrogate_weights)
        #: how the exact step differentiates: ``"jacfwd"`` or ``"reverse"`` (``WallClockConfig.grad_mode``)
        self.grad_mode = cfg.grad_mode
        self.fns: dict = {}
        self.exact_fns: dict = {}
        self.value_fns: dict = {}
        self._value_warm: set = set()  # the parameterisations whose window value program is compiled
        self.step_costs: dict = {}
        self.charges = charges
        log(f"gradient windows: {int(np.asarray(self.win.valid).sum())} of {self.win.size} triggered "
            f"({charges.seconds['gradient_windows']:.1f} s incl. compile)")

    def retake(self, param: schedule.Parameterisation, theta) -> int:
        """Re-take the windows on the same scenarios under the crawl ``theta`` schedules (:func:`.windows.make_windows`
        with ``param``), so that a gradient started from ``theta`` (the hybrid's, after its search) descends from
        states its own gait visits, not the start point's. Same shapes: the step and value programs do not
        recompile (the capture does, once per parameterisation). Returns the physics steps of the forward run;
        :meth:`restore` goes back to the start point's windows."""
        from hyqjax.studies.tune import windows

        self.win = jax.block_until_ready(windows.make_windows(self.sc, self.spec, self.su, param=param, theta=theta))
        return int(self.sc.batch_size * round(self.spec.lead / float(self.su.m.opt.timestep)))

    def restore(self) -> None:
        """Back to the start point's windows (after a run that re-took them)."""
        self.win = self.win_start

    def step_name(self, param) -> str:
        """Charge name of the tuning step's program: ``jacfwd`` (``P`` tangents), ``reverse`` (reverse mode,
        :func:`.objective.make_value_and_grad_reverse`) or the forward gradient with ``K = grad_directions`` tangents
        (:func:`.objective.make_value_and_forward_gradient`)."""
        k = self.cfg.grad_directions
        if k:
            return f"forward_gradient_{k}/{param.name}"
        return f"{self.grad_mode}/{param.name}"

    def exact(self, param, mode: str | None = None, checkpoint: bool = True):
        """The jitted exact step of ``param`` (built on first use): ``mode`` ``"jacfwd"`` or ``"reverse"`` (default:
        the study's ``grad_mode``); ``checkpoint``: the reverse-mode step's rematerialised scan."""
        from hyqjax.studies.tune import objective

        mode = mode or self.grad_mode
        key = (mode, bool(checkpoint) if mode == "reverse" else None, param.name)
        if key not in self.exact_fns:
            if mode == "reverse":
                fn = objective.make_value_and_grad_reverse(self.base, param, self.obj, self.su, checkpoint=checkpoint)
            elif mode == "jacfwd":
                fn = objective.make_value_and_jac(self.win, self.base, param, self.obj, self.su)
            else:
                raise ValueError(f"mode must be 'jacfwd' or 'reverse', got {mode!r}")
            self.exact_fns[key] = fn
        return self.exact_fns[key]

    def exact_physics_steps(self, param) -> int:
        """Physics steps of one exact step on the windows: ``P`` tangents (``jacfwd``) or forward, recompute and
        backward pass (``reverse``, :func:`.objective.reverse_physics_steps`)."""
        from hyqjax.studies.tune import objective

        if self.grad_mode == "reverse":
            return objective.reverse_physics_steps(self.win.size, self.obj)
        return objective.physics_steps(self.win.size, self.obj, param.size)

    def programs(self, param: schedule.Parameterisation, line_search: bool = True):
        """``(step_fn, evaluate, step_cost)`` for ``param``; compiles (charged once) on first use. ``line_search``
        False (guided ES, which takes no line search): the window value program ``evaluate`` runs is not compiled
        here (a later call with ``line_search`` compiles it)."""
        from hyqjax.studies.tune import objective

        if param.name not in self.fns:
            k_dir = self.cfg.grad_directions
            if k_dir:
                fg = objective.make_value_and_forward_gradient(self.base, param, self.obj, self.su, k_dir)
                keys = iter(range(1 << 30))
                key0 = jax.random.key(self.cfg.seed + 17)

                def vj(t, win):  # a new set of directions every step
                    return fg(t, win, jax.random.fold_in(key0, next(keys)))
            else:
                vj = self.exact(param)
            fval = objective.make_value(self.base, param, self.obj, self.su)
            self.value_fns[param.name] = fval
            th = jnp.asarray(param.theta_of(self.base), jnp.float32)
            k = 6  # c = 0 and the five line-search scales of search.run_gradient
            with self.charges.track(self.step_name(param)):
                jax.block_until_ready(vj(th, self.win))
            n_win = self.win.size
            step = objective.physics_steps(n_win, self.obj, k_dir) if k_dir else self.exact_physics_steps(param)
            cost = step + k * objective.physics_steps(n_win, self.obj)
            self.step_costs[param.name] = step  # the tuning step alone (guided ES takes no line search)
            self.fns[param.name] = (lambda t: vj(jnp.asarray(t, jnp.float32), self.win),
                                    lambda ts: np.asarray(fval(jnp.asarray(ts, jnp.float32), self.win)), cost)
        if line_search and param.name not in self._value_warm:
            th = jnp.asarray(param.theta_of(self.base), jnp.float32)
            cands = jnp.tile(th[None], (6, 1))  # c = 0 and the five line-search scales of search.run_gradient
            with self.charges.track(f"window_value/{param.name}"):
                jax.block_until_ready(self.value_fns[param.name](cands, self.win))
            self._value_warm.add(param.name)
        return self.fns[param.name]

    def charge_names(self, param) -> list:
        return ["gradient_windows", self.step_name(param), f"window_value/{param.name}"]

    def exact_step(self, param):
        """``theta -> dict`` of the exact step on the windows (the diagnostics' SNR)."""
        return lambda t: self.exact(param)(jnp.asarray(t, jnp.float32), self.win)

    def step_cost(self, param, reps: int = 3) -> dict:
        """Wall seconds (median of ``reps``, after compiles) of one tuning step on the windows (value and
        Jacobian: exact ``jacfwd``, exact reverse mode with and without the checkpointed scan and, with
        ``grad_directions``, the forward gradient) and of one forward evaluation of the same windows for one
        candidate (:func:`.objective.make_value`), all on MJX-JAX; the ratios are the step's cost in forward
        windows (the target: <= 5). The reverse-mode step without checkpoint keeps every tick's solver residuals:
        where that does not fit in memory, ``reverse_nocheckpoint_s`` is None and ``reverse_nocheckpoint_error`` says
        why. ``first_call_s``: each program's first call (its compile, if new, and one run);
        ``reverse_vs_jacfwd_rel_diff``: the largest difference of the two exact steps' per-window rows over the
        largest ``jacfwd`` entry (windows both call valid). The programs built only for this measurement are
        released afterwards."""
        th = jnp.asarray(param.theta_of(self.base), jnp.float32)
        self.programs(param)
        first: dict = {}
        last: dict = {}
        kept = set(self.exact_fns)  # the programs built here for the measurement only are released at the end

        def timed(name, fn):
            t = time.perf_counter()
            jax.block_until_ready(fn())  # compiles (if new) and warms
            first[name] = time.perf_counter() - t
            ts = []
            for _ in range(reps):
                t = time.perf_counter()
                last[name] = jax.block_until_ready(fn())
                ts.append(time.perf_counter() - t)
            return float(np.median(ts))

        value = timed("window_value", lambda: self.value_fns[param.name](th[None], self.win))
        jac = timed("jacfwd", lambda: self.exact(param, "jacfwd")(th, self.win))
        rev = timed("reverse", lambda: self.exact(param, "reverse")(th, self.win))
        out = dict(windows=int(self.win.size), ticks=int(self.obj.ticks), tangents=int(param.size),
                   window_value_s=value, jacfwd_s=jac, jacfwd_over_value=jac / value,
                   reverse_s=rev, reverse_over_value=rev / value, reps=int(reps))
        # the two exact steps' rows on the windows both call valid (rounding, amplified through contact events)
        ok = np.asarray(last["jacfwd"]["ok"]) & np.asarray(last["reverse"]["ok"])
        g_f, g_r = (np.asarray(last[k]["per_window_grad"], np.float64)[ok] for k in ("jacfwd", "reverse"))
        scale = float(np.abs(g_f).max()) if g_f.size else 0.0
        out["reverse_vs_jacfwd_rel_diff"] = float(np.abs(g_r - g_f).max() / scale) if scale > 0 else None
        try:
            nock = timed("reverse_nocheckpoint", lambda: self.exact(param, "reverse", checkpoint=False)(th, self.win))
            out.update(reverse_nocheckpoint_s=nock, reverse_nocheckpoint_over_value=nock / value)
        except Exception as e:  # noqa: BLE001 (only running out of memory is a result; anything else is raised)
            if not _resource_error(e):
                raise
            out.update(reverse_nocheckpoint_s=None, reverse_nocheckpoint_over_value=None,
                       reverse_nocheckpoint_error=f"{type(e).__name__}: {str(e).strip().splitlines()[0][:300]}")
        if self.cfg.grad_directions:
            fg = self.fns[param.name][0]
            fgs = timed("forward_gradient", lambda: fg(th))
            out.update(forward_gradient_directions=int(self.cfg.grad_directions), forward_gradient_s=fgs,
                       forward_gradient_over_value=fgs / value)
        out["first_call_s"] = first
        for key in set(self.exact_fns) - kept:
            del self.exact_fns[key]
        return out


def diagnostic_iterates(res: dict, members: dict, dim: str) -> list:
    """The held-out-evaluated iterates of parameterisation ``dim`` the diagnostics rank (start point included)."""
    return [k for k, (p, _, _) in members.items() if p.name == dim and k in res["heldout"] and k != "table1"]


def gradient_diagnostics(cfg, res: dict, params: dict, base, grad: GradientPrograms, members: dict) -> dict:
    """What decides whether the gradient can pay, per parameterisation with a gradient run:

    * the gradient's signal-to-noise ratio across windows at the start point, ``|mean| / (std / sqrt(W))`` per
      coordinate (:func:`.gradient_stats.gradient_stats`), and the median per-window gradient norm;
    * how well the window objective ranks held-out success: Spearman's rank correlation between the window
      objective ``L`` (lower is better) and held-out clean success over every iterate of that parameterisation
      that was evaluated (a useful objective gives a clearly negative correlation).
    """
    from scipy import stats

    out = {}
    for d, param in params.items():
        if param.name not in grad.fns:
            continue
        _, evaluate, _ = grad.fns[param.name]
        r0 = grad.exact_step(param)(param.theta_of(base))
        gs = gradient_stats(r0, grad.obj.lengths, list(param.names))["per_length"][-1]
        snr = np.asarray([np.nan if x is None else x for x in gs["snr"]], float)
        keys = diagnostic_iterates(res, members, d)
        thetas = np.stack([np.asarray(members[k][1], np.float64) for k in keys])
        k6 = 6  # the window program's batch (search.run_gradient's line search)
        vals = []
        for a in range(0, len(thetas), k6):
            chunk = thetas[a:a + k6]
            pad = np.concatenate([chunk, np.repeat(chunk[-1:], k6 - len(chunk), 0)])
            vals.extend(np.asarray(evaluate(pad), np.float64)[: len(chunk)].tolist())
        clean = [res["heldout"][k]["clean"] for k in keys]
        rho = stats.spearmanr(vals, clean).statistic if len(set(clean)) > 1 and len(set(vals)) > 1 else float("nan")
        out[d] = dict(snr_mean=float(np.nanmean(snr)), snr_median=float(np.nanmedian(snr)),
                      snr_above_2=float(np.mean(snr > 2.0)), median_window_grad_norm=gs["median_norm"],
                      windows=int(np.sum(np.asarray(r0["ok"]))), objective_vs_heldout_spearman=float(rho),
                      iterates=keys, window_objective=vals, heldout_clean=clean)
    return out
