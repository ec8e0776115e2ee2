"""The closed-loop objective: a smooth cost of a step-down window through MJX, differentiable by ``jax.jacfwd``
and, through a fixed-length constraint solver, by reverse mode.

A window (:mod:`.windows`) runs ``n`` control ticks of the full closed loop (crawl + height reflex + joint
impedance + ``mjx.step``, ``impl=jax``) from a snapshot, with the tuned parameters ``theta`` mapped by
:class:`.space.ParamSpace`. Per tick ``k`` (``d_c`` the signed distance of MJX contact slot ``c``, ``s`` a
softness, ``sp(x) = s softplus(x / s)`` a smooth ``max(x, 0)``):

* clearance (shin and trunk vs. the terrain, i.e. the platform edge):
  ``C_k = sum_{c in shin, trunk} sp_{s_c}(c_0 - d_c)`` (m), zero while every shin and the trunk keep ``c_0``;
* joint-range margin: ``J_k = sum_j sp_{s_q}(q_j - (q_max,j - q_0)) + sp_{s_q}((q_min,j + q_0) - q_j)`` (rad);
* workspace margin: ``E_k = sum_i sp_{s_e}(e_i - (e_max - e_0))`` with ``e_i`` the HFE-to-foot distance
  (``kinematics.leg_extension``) and ``e_max`` the crawl's ``max_leg_extension`` (m);
* lost foothold: ``F_k = 1[stance triggered at k] relu(min_c d_c^{foot(i)} - f_0)``, the swing foot's
  distance to the ground at the tick its stance is triggered (touchdown or limit), a smooth proxy of a
  foothold lost in the air (m);
* orientation: ``O_k = roll_k^2 + pitch_k^2`` (rad^2);
* mobility: ``m_bar = sum_k c_sd(k) sum_i m_i(k) / max(1, sum_k c_sd(k))`` (Eq. 12, footnote 8, per
  swing-down tick as ``stepdown``'s ``mean_mobility``);
* progress: ``v = (x_trunk(n) - x_trunk(0)) / (n dt)`` (m/s), so that shorter steps are not free;
* stability: ``S = relu(sigma - 0.9)^2`` with ``sigma = dt lambda_max / 2`` the reflex's explicit-integration
  stability number (``reflex.params.stability_number``, stable below 1), per window.

The window cost is

.. math:: L = w_C \\bar C + w_J \\bar J + w_E \\bar E + w_F \\sum_k F_k + w_O \\bar O - w_m \\bar m - w_v v + w_S S

(bars: means over the window's ticks), and the objective of ``theta`` is the mean of ``L`` over the valid
windows. A window whose state becomes non-finite gets no gradient and is counted (``non_finite``), never
silently averaged.

Gradients: the per-window Jacobian rows ``dL_w / dtheta`` (``W x P``; they give the gradient variance across
scenarios), two ways with the same result:

* :func:`make_value_and_jac`: ``jax.jacfwd`` over ``theta``, ``P`` tangents carried with one primal rollout (forward
  mode runs through ``mjx.step``'s solver ``while_loop``); cost about ``(1 + c P)`` forward windows, ``c`` the cost
  of one tangent relative to the primal.
* :func:`make_value_and_grad_reverse`: reverse mode. With the window's tick map ``x_{k+1} = f(x_k, theta)`` and
  per-tick cost terms ``l_k``, the adjoint ``a_k = dL/dx_k`` runs backwards,
  ``a_k = dl_k/dx_k + a_{k+1} df/dx (x_k)`` and ``dL/dtheta = sum_k dl_k/dtheta + a_{k+1} df/dtheta (x_k)``: one
  vector-Jacobian product per tick, whatever ``P``. Windows are independent and each reads its own copy of
  ``theta``, so one backward pass through the ``vmap``-ed windows gives every window's row of one prefix; the
  ``len(obj.lengths)`` passes (one per prefix) run one after another. MJX's constraint
  solver ``while_loop`` has no transpose; traced inside :func:`hyqjax.sim.reverse_mode.fixed_length_solver` it is a
  ``lax.scan`` of at most ``m.opt.iterations`` ``lax.cond`` steps with the same early stop (the same primal). The
  window's tick scan is checkpointed (``jax.checkpoint`` of the per-tick body): the forward pass stores only the
  carry ``x_k`` of each tick (memory ``O(ticks x state)``, not ``O(ticks x solver residuals)``), and the backward
  pass recomputes each tick from its carry before its vector-Jacobian product. Cost: one forward pass, then one
  recomputation and one backward pass per prefix length (:func:`reverse_physics_steps` counts
  ``1 + 2 len(obj.lengths)`` physics steps per window tick, 3 without prefixes), independent of ``P``.

The crawl's phase switches are ``jnp.where`` selects, so the gradient is that of the current contact /
phase sequence: it ignores how ``theta`` moves the switching times (the bias of any pathwise gradient of
a hybrid system); short windows keep the number of switches small.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import kinematics, robot, spatial
from hyqjax.core.batching import vmap_unless_one
from hyqjax.core.scan_carry import tie_carry
from hyqjax.crawl import controller as crawl
from hyqjax.reflex import params as rparams
from hyqjax.sim import contacts
from hyqjax.sim import contacts_from_distance as cfdm
from hyqjax.sim import rollout as sim
from hyqjax.studies.tune import windows as wmod
from hyqjax.studies.tune.surrogate_weights import check_weights
from hyqjax.studies.tune.space import ParamSpace


@dataclasses.dataclass(frozen=True)
class ClosedLoopObjective:
    """Window length and the objective's margins, softnesses and weights (see the module docstring)."""

    ticks: int = 750
    clearance: float = 0.03
    clearance_soft: float = 0.005
    joint_margin: float = 0.1
    joint_soft: float = 0.02
    ext_margin: float = 0.02
    ext_soft: float = 0.005
    foothold_tol: float = 0.01
    w_clearance: float = 100.0
    w_joint: float = 10.0
    w_workspace: float = 50.0
    w_foothold: float = 20.0
    w_tilt: float = 10.0
    w_mobility: float = 1.0
    w_progress: float = 2.0
    w_stability: float = 10.0
    prefixes: tuple = ()
    #: backward-only virtual springs under the feet (:mod:`hyqjax.sim.contacts_from_distance`; default off): the
    #: window's values are unchanged, its derivative sees the ground before touchdown
    contacts_from_distance: cfdm.ContactsFromDistance = cfdm.ContactsFromDistance()

    def __post_init__(self):
        if not (isinstance(self.ticks, int) and 1 <= self.ticks <= 20000):
            raise ValueError(f"ticks must be an int in [1, 20000], got {self.ticks!r}")
        for k in ("clearance_soft", "joint_soft", "ext_soft"):
            if not (0.0 < getattr(self, k) <= 0.2):
                raise ValueError(f"{k} must be in (0, 0.2], got {getattr(self, k)}")
        if any(not (isinstance(n, int) and 1 <= n <= self.ticks) for n in self.prefixes):
            raise ValueError(f"prefixes must be ints in [1, ticks={self.ticks}], got {self.prefixes}")

    @property
    def lengths(self) -> tuple:
        """Window lengths (ticks) of ``prefix_loss``: ``prefixes`` and ``ticks``."""
        return tuple(sorted(set(self.prefixes) | {self.ticks}))

    def weights(self) -> dict[str, float]:
        return dict(clearance=self.w_clearance, joint=self.w_joint, workspace=self.w_workspace,
                    foothold=self.w_foothold, tilt=self.w_tilt, mobility=-self.w_mobility,
                    progress=-self.w_progress, stability=self.w_stability)

    def reweighted(self, overrides) -> "ClosedLoopObjective":
        """The same objective with the weights ``overrides`` (``((term, w), ...)``, :func:`check_weights`) names
        (``w_<term>``; the sign each term enters ``L`` with stays), the others unchanged."""
        return dataclasses.replace(self, **{f"w_{k}": float(w) for k, w in check_weights(overrides)})


def _sp(x, s):
    return s * jax.nn.softplus(x / s)


def window_terms(theta, mx, d, cs, tau, base: crawl.CrawlParams, space: ParamSpace, obj: ClosedLoopObjective,
                 su: wmod.Setup, checkpoint: bool = False) -> dict[str, jax.Array]:
    """Terms of ONE window (``vmap`` over windows; ``mx`` that window's model). ``space`` is a
    :class:`.space.ParamSpace` (one parameter set) or a :class:`.schedule.Parameterisation` (parameters selected
    per tick by swing leg and features; the stability term is the largest over the legs' rows). ``checkpoint``:
    the per-tick body is ``jax.checkpoint``-ed (rematerialised), so reverse mode keeps only each tick's carry and
    recomputes the tick in the backward pass (the values are the same)."""
    from hyqjax.studies.tune import schedule

    sched = isinstance(space, schedule.Parameterisation)  # static
    if sched:
        sp = space.scheduled(theta, base)
        p = space.params_at(sp, 0, jnp.zeros(len(schedule.FEATURES), theta.dtype))
    else:
        p = space.crawl_params(theta, base)
    ids, slots = su.ids, su.slots
    dt = float(su.m.opt.timestep)
    dtype = d.qpos.dtype
    qadr = np.asarray(ids.qpos_joints)
    q_lo = jnp.asarray(robot.Q_MIN, dtype) + obj.joint_margin
    q_hi = jnp.asarray(robot.Q_MAX, dtype) - obj.joint_margin
    strike_slots = np.concatenate([slots.shin, slots.trunk]).astype(int)

    def body(carry, _):
        d, cs, tau = carry
        if sched:
            obs = sim.observe(ids, d, tau, mx)
            pk = space.params_at(sp, cs.sequence[cs.seq_index], schedule.features(cs, obs).astype(theta.dtype))
        else:
            pk = p
        d1, cs1, tau1, info = wmod.tick(mx, ids, pk, d, cs, tau, dt, cfd=obj.contacts_from_distance)
        dist = contacts.slot_distances(d1)
        clear = jnp.sum(_sp(obj.clearance - dist[strike_slots], obj.clearance_soft))
        q = d1.qpos[qadr]
        joint = jnp.sum(_sp(q - q_hi, obj.joint_soft) + _sp(q_lo - q, obj.joint_soft))
        ext = kinematics.leg_extension(q)
        work = jnp.sum(_sp(ext - (p.max_leg_extension - obj.ext_margin), obj.ext_soft))
        foot_d = jnp.stack([jnp.min(dist[s]) for s in slots.feet])
        trig = (info.touchdown | info.limit_stop).astype(dtype)
        foot = trig * jax.nn.relu(foot_d[info.swing_leg] - obj.foothold_tol)
        rpy = spatial.rot_to_rpy(spatial.quat_to_rot(d1.qpos[robot.QPOS_BASE_QUAT]))
        sd = info.swing_down.astype(dtype)
        y = dict(clearance=clear, joint=joint, workspace=work, foothold=foot, tilt=rpy[0] ** 2 + rpy[1] ** 2,
                 mobility=sd * jnp.sum(info.mobility), sd=sd, x=d1.qpos[robot.QPOS_BASE_POS][0])
        return (d1, cs1, tau1), y

    if checkpoint:
        body = jax.checkpoint(body, prevent_cse=False)  # in a scan, CSE across ticks cannot undo the remat
    _, ys = jax.lax.scan(body, tie_carry((d, cs, tau), theta), None, length=obj.ticks)
    if sched:
        rows = [space.params_at(sp, leg, jnp.zeros(len(schedule.FEATURES), theta.dtype)).reflex for leg in range(4)]
        sigma = jnp.max(jnp.stack([rparams.stability_number(r, dt) for r in rows]))
    else:
        sigma = rparams.stability_number(p.reflex, dt)
    stab = jax.nn.relu(sigma - 0.9) ** 2
    cum = {k: jnp.cumsum(v) for k, v in ys.items() if k != "x"}

    def at(n):
        i = n - 1
        out = {k: cum[k][i] / n for k in ("clearance", "joint", "workspace", "tilt")}
        out["foothold"] = cum["foothold"][i]
        out["mobility"] = cum["mobility"][i] / jnp.maximum(cum["sd"][i], 1.0)
        out["progress"] = (ys["x"][i] - d.qpos[robot.QPOS_BASE_POS][0]) / (n * dt)
        out["stability"] = stab
        return out

    terms = at(obj.ticks)
    terms["prefix_loss"] = jnp.stack([combine(at(n), obj) for n in obj.lengths])
    return terms


def combine(terms: dict, obj: ClosedLoopObjective):
    """``L`` of the module docstring from (per-window) terms."""
    return sum(w * terms[k] for k, w in obj.weights().items())


def window_losses(theta, win: wmod.Windows, base, space, obj, su, checkpoint: bool = False):
    """Per-window ``(L, terms, finite)``: ``(W,)`` losses with non-finite ones replaced by 0 (``checkpoint``:
    :func:`window_terms`'s)."""
    axes = wmod.hmodel.model_in_axes(win.model)
    terms = vmap_unless_one(lambda mm, dd, cc, tt: window_terms(theta, mm, dd, cc, tt, base, space, obj, su,
                                                                checkpoint),
                            in_axes=(axes, 0, 0, 0))(win.model, win.data, win.ctrl, win.tau)  # one window: no vmap
    loss = combine({k: v for k, v in terms.items() if k != "prefix_loss"}, obj)
    finite = jnp.isfinite(loss)
    return jnp.where(finite, loss, 0.0), terms, finite


def batch_objective(theta, win: wmod.Windows, base, space, obj, su):
    """``(mean L over valid finite windows, per-window L)``; differentiable in ``theta``."""
    loss, _, finite = window_losses(theta, win, base, space, obj, su)
    w = (win.valid & finite).astype(loss.dtype)
    return jnp.sum(w * loss) / jnp.maximum(jnp.sum(w), 1.0), loss


def _step_result(jac, jac_prefix, loss, terms, finite, win):
    """The step's dict from the per-window Jacobian rows ``(W, P)`` (exact or estimated)."""
    terms = {k: v for k, v in terms.items() if k != "prefix_loss"}
    ok = win.valid & finite & jnp.all(jnp.isfinite(jac), -1)
    w = ok.astype(loss.dtype)
    nw = jnp.maximum(jnp.sum(w), 1.0)
    jac = jnp.where(ok[:, None], jac, 0.0)
    return dict(loss=jnp.sum(w * loss) / nw, grad=jnp.sum(w[:, None] * jac, 0) / nw, per_window_loss=loss,
                per_window_grad=jac, per_window_prefix_grad=jac_prefix, ok=ok,
                terms={k: jnp.sum(w * v) / nw for k, v in terms.items()})


def make_value_and_jac(win_example: wmod.Windows, base, space: ParamSpace, obj: ClosedLoopObjective,
                       su: wmod.Setup):
    """A jitted ``f(theta, windows) -> dict(loss, grad, per_window_loss, per_window_grad, terms, finite)``.

    One ``jax.jacfwd`` of the per-window loss vector: ``P`` tangents carried with one primal rollout; the
    mean gradient and the per-window Jacobian rows (for the variance across scenarios) come together.
    """
    del win_example

    def f(theta, win):
        def per_window(th):
            loss, terms, finite = window_losses(th, win, base, space, obj, su)
            return (loss, terms["prefix_loss"]), (loss, terms, finite)

        (jac, jac_prefix), (loss, terms, finite) = jax.jacfwd(per_window, has_aux=True)(theta)
        return _step_result(jac, jac_prefix, loss, terms, finite, win)

    return jax.jit(f)


def make_value_and_grad_reverse(base, space: ParamSpace, obj: ClosedLoopObjective, su: wmod.Setup,
                                checkpoint: bool = True):
    """A jitted ``f(theta, windows)`` with the output of :func:`make_value_and_jac`, differentiated in reverse mode.

    Windows are independent: window ``w`` reads its own copy ``theta_w`` of ``theta``, so one reverse pass through
    all windows (``jax.vjp`` of the ``vmap``-ed windows' ``prefix_loss``, ``(W, len(obj.lengths))``) with a cotangent
    of ones on one prefix gives every window's row ``dL_w / dtheta_w`` of that prefix at once (the last prefix is the
    window's ``L``); one pass per prefix length, in sequence (``lax.map``). MJX's constraint solver is traced as a
    fixed-length loop (:func:`hyqjax.sim.reverse_mode.fixed_length_solver`: every trace of ``f`` happens inside
    it), and with ``checkpoint`` the window's per-tick body is rematerialised (:func:`window_terms`). The values are
    those of the forward pass: the same loss, and the same gradient up to rounding.
    """
    from hyqjax.sim import reverse_mode

    def f(theta, win):
        axes = wmod.hmodel.model_in_axes(win.model)
        thetas = jnp.broadcast_to(theta, (win.size,) + theta.shape)

        def per_window(ths):
            terms = jax.vmap(lambda th, mm, dd, cc, tt: window_terms(th, mm, dd, cc, tt, base, space, obj, su,
                                                                     checkpoint),
                             in_axes=(0, axes, 0, 0, 0))(ths, win.model, win.data, win.ctrl, win.tau)
            return terms["prefix_loss"], terms

        with reverse_mode.fixed_length_solver():  # f runs only while jit traces it
            prefix, pullback, terms = jax.vjp(per_window, thetas, has_aux=True)
            n = prefix.shape[-1]
            cts = jnp.broadcast_to(jnp.eye(n, dtype=prefix.dtype)[:, None, :], (n,) + prefix.shape)
            # One backward pass per prefix, one after another: the backward program is traced once and not
            # batched (a vmap over the passes batches every transposed jaxpr: ~8 s more tracing on a CPU).
            jac_prefix = jnp.moveaxis(jax.lax.map(lambda ct: pullback(ct)[0], cts), 0, 1)
        raw = combine({k: v for k, v in terms.items() if k != "prefix_loss"}, obj)
        finite = jnp.isfinite(raw)
        loss = jnp.where(finite, raw, 0.0)
        return _step_result(jac_prefix[:, -1], jac_prefix, loss, terms, finite, win)

    return jax.jit(f)


def make_value_and_forward_gradient(base, space: ParamSpace, obj: ClosedLoopObjective, su: wmod.Setup,
                                    directions: int):
    """A jitted ``f(theta, windows, key)`` with the output of :func:`make_value_and_jac`, the Jacobian rows
    estimated from ``K = directions`` random directional derivatives (the forward gradient, Baydin et al. 2022;
    Nesterov & Spokoiny 2017 without the finite differences):

    .. math:: \\hat g = \\frac{1}{K} \\sum_{k=1}^{K} (\\nabla L \\cdot v_k)\\, v_k,
              \\qquad v_k \\sim \\mathcal N(0, I_P),

    unbiased (``E[v v^T] = I``) with ``K`` tangents carried instead of ``P`` (one ``jacfwd`` over the ``K``
    coordinates ``alpha`` of ``theta + V^T alpha`` at ``alpha = 0``), at the price of variance: per window
    ``E|g_hat - g|^2 = (P + 1) |g|^2 / K`` (the covariance of ``(g . v) v`` is ``|g|^2 I + g g^T``).
    ``key`` draws ``V`` (a new key per step)."""
    k = int(directions)
    if k < 1:
        raise ValueError(f"directions must be >= 1, got {directions}")

    def f(theta, win, key):
        def per_window(th):
            loss, terms, finite = window_losses(th, win, base, space, obj, su)
            return (loss, terms["prefix_loss"]), (loss, terms, finite)

        (jac, jac_prefix), (loss, terms, finite) = forward_gradient(per_window, theta, key, k)
        return _step_result(jac, jac_prefix, loss, terms, finite, win)

    return jax.jit(f)


def forward_gradient(fn, theta, key, directions: int):
    """``(J_hat, aux)``: the forward-gradient estimate ``J_hat = (1/K) (J V^T) V`` of the Jacobian ``J`` of
    ``fn(theta) -> (outputs, aux)`` (every output leaf gets a trailing ``P`` axis, as ``jax.jacfwd``'s), with
    ``V (K, P)`` standard normal directions drawn from ``key``; ``K`` tangents in one ``jacfwd`` over the
    coordinates ``alpha`` of ``theta + V^T alpha`` at 0 (:func:`make_value_and_forward_gradient`)."""
    k = int(directions)
    v = jax.random.normal(key, (k, theta.shape[-1]), theta.dtype)
    ja, aux = jax.jacfwd(lambda a: fn(theta + a @ v), has_aux=True)(jnp.zeros(k, theta.dtype))
    return jax.tree_util.tree_map(lambda x: x @ v / k, ja), aux


def make_value(base, space: ParamSpace, obj: ClosedLoopObjective, su: wmod.Setup):
    """A jitted ``f(thetas (N, P), windows) -> (N,) objective`` (a population on the same windows: CMA-ES,
    random search)."""

    def f(thetas, win):
        return jax.vmap(lambda th: batch_objective(th, win, base, space, obj, su)[0])(thetas)

    return jax.jit(f)


def make_per_robot_value_and_jac(base, space: ParamSpace, obj: ClosedLoopObjective, su: wmod.Setup,
                                 win_axes: wmod.Windows):
    """Per-robot batched tuning: a jitted ``f(thetas (R, P), windows (R, W_r, ...)) -> dict(loss (R,),
    grad (R, P))``, robot ``r``'s own parameters on its own windows (``windows.grouped``), ``P`` tangents per
    robot. ``win_axes`` are the ``vmap`` axes ``windows.grouped`` returns."""

    def one(theta, win):
        def mean_loss(th):
            loss = batch_objective(th, win, base, space, obj, su)[0]
            return loss, loss

        grad, loss = jax.jacfwd(mean_loss, has_aux=True)(theta)  # the value rides on the tangents' rollout
        return loss, grad

    def f(thetas, wins):
        loss, grad = jax.vmap(one, in_axes=(0, win_axes))(thetas, wins)
        return dict(loss=loss, grad=grad)

    return jax.jit(f)


def physics_steps(n_windows: int, obj: ClosedLoopObjective, tangents: int = 0) -> int:
    """Simulation budget of one evaluation: ``windows x ticks x (1 + tangents)`` physics steps (a forward pass
    and ``tangents`` forward-mode tangents; a reverse-mode step: :func:`reverse_physics_steps`)."""
    return int(n_windows) * obj.ticks * (1 + int(tangents))


def reverse_physics_steps(n_windows: int, obj: ClosedLoopObjective) -> int:
    """Simulation budget of one reverse-mode step (:func:`make_value_and_grad_reverse`), whatever the number of
    parameters: ``windows x ticks x (1 + 2 n)``, ``n = len(obj.lengths)`` backward passes (one per prefix length):
    the forward pass, and per backward pass the window's recomputation tick by tick (the checkpointed scan) and
    the backward pass itself (``windows x ticks x 3`` without prefixes)."""
    return int(n_windows) * obj.ticks * (1 + 2 * len(obj.lengths))
