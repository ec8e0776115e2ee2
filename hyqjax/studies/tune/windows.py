"""Snapshot windows: short closed-loop rollouts started where a leg is about to step over the edge.

Gradients through 24 s of crawling with contact switching are useless (they grow with every touchdown
and the objective is a step function of contact events), so the closed-loop objective is evaluated on
*windows*: ``n`` control ticks started from a *snapshot* ``(mjx.Data, CrawlState, last torque)`` taken
in a forward run of the step-down (crawl + height reflex + joint impedance + MJX, Table I parameters)
at the control tick in which a swing ends and the next body phase is planned for a leg whose foot is
at most ``reach`` before the edge, i.e. the leg that will step down next (its swing over the edge, the
haptic search with the reflex active, and the landing all fall inside the window). The window starts
one tick *before* that body phase is planned, so the tuned crawl parameters (trunk height, step length,
swing apex) act on the whole step down, not only the reflex parameters.

Per scenario the first ``per_scenario`` such ticks are kept (front legs first, then hind legs), in
one ``lax.scan`` whose carry holds the snapshot slots (``jnp.where`` into slot ``i`` when the ``i``-th
trigger fires). A scenario that ends its forward run with fewer triggers leaves the rest of its slots
invalid (``valid = False``); they are masked out of every objective and counted.

The model comes from ``stepdown.setup`` (``impl="jax"``) and the contact slots from :func:`setup` (one per
control period and dtype).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hyqjax.core import robot
from hyqjax.core.batching import row_index, take_rows, vmap_unless_one
from hyqjax.crawl import controller as crawl
from hyqjax.sim import contacts
from hyqjax.sim import contacts_from_distance as cfdm
from hyqjax.sim import model as hmodel
from hyqjax.sim import rollout as sim
from hyqjax.studies import stepdown


class Slots(NamedTuple):
    """Static indices of the MJX contact slots that pair a shin, the trunk or each foot with the terrain."""

    shin: np.ndarray
    trunk: np.ndarray
    feet: list


class Setup(NamedTuple):
    """The compiled model (``stepdown.setup``, ``impl="jax"``: forward-mode derivatives need it), its MJX
    copy, ids and the terrain contact slots whose signed distances the objective reads."""

    m: mujoco.MjModel
    mx: mjx.Model
    ids: hmodel.ModelIds
    slots: Slots


@functools.lru_cache(maxsize=4)
def setup(control_dt: float = 0.002, dtype: str = "float32") -> Setup:
    """Model, ids and contact slots of the step-down terrain (no blocks); ``dtype`` float64 for tests."""
    st = stepdown.setup(stepdown.StepdownConfig(control_dt=control_dt, impl="jax"))
    m, ids, mx = st.m, st.ids, st.mx
    if dtype == "float64":
        mx = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64) if hasattr(x, "dtype") and
                                    jnp.issubdtype(x.dtype, jnp.floating) else x, mx)
    # The slots' geom pairs are the collision driver's static candidate pairs: its collision pass alone (a tenth
    # of a forward's compile) fills them in the same order as mjx.forward does.
    d = jax.jit(mjx.collision)(mx, mjx.make_data(mx))
    geom = contacts.slot_geoms(d)
    shin = np.nonzero(np.isin(geom, ids.shin_geoms).any(1))[0]
    trunk = np.nonzero(np.isin(geom, [ids.trunk_geom]).any(1))[0]
    feet = [np.nonzero(np.isin(geom, [g]).any(1))[0] for g in ids.foot_geoms]
    return Setup(m, mx, ids, Slots(shin, trunk, feet))


def tick(mx: mjx.Model, ids: hmodel.ModelIds, p, d: mjx.Data, cs, tau_prev, dt: float, step=None, cfd=None):
    """One control tick of the step-down closed loop (what ``sim.rollout`` does, without the divergence
    freeze): observe, crawl + reflex + joint impedance, torque limits, one ``mjx.step``. ``step(p, cs, obs)``
    is the controller's step (default: the crawl, ``p`` its ``CrawlParams``; a parameterisation's scheduled
    crawl, ``p`` its ``Scheduled``). ``cfd`` (a :class:`hyqjax.sim.contacts_from_distance.ContactsFromDistance`,
    default none) adds the backward-only virtual springs under the feet to the step's derivative (its value is
    unchanged). Returns ``(d, cs, tau, info)``."""
    obs = sim.observe(ids, d, tau_prev, mx)
    if step is None:
        cs, tau, info = crawl.crawl_step(p, cs, obs, dt)
    else:
        cs, tau, info = step(p, cs, obs)
    tau = jnp.clip(tau, -robot.TORQUE_LIMIT, robot.TORQUE_LIMIT)
    d = mjx.step(mx, d.replace(ctrl=tau))
    if cfd is not None and cfd.active:
        ci = ids.contacts
        d = cfdm.apply(cfd, mx, ci, cfdm.foot_bodies(mx, ci), d, dt)
    return d, cs, tau, info


@dataclasses.dataclass(frozen=True)
class WindowSpec:
    """Where windows start: ``per_scenario`` snapshots from a forward run of ``lead`` seconds, each taken
    ``offset`` ticks after the tick in which the next swing leg's foot is less than ``reach`` (m) before the
    edge (``offset`` > 0 starts windows later in the step, e.g. in the swing-down with the reflex active)."""

    per_scenario: int = 4
    lead: float = 14.0
    reach: float = 0.34
    offset: int = 0

    def __post_init__(self):
        if not (isinstance(self.per_scenario, int) and 1 <= self.per_scenario <= 8):
            raise ValueError(f"per_scenario must be an int in [1, 8], got {self.per_scenario!r}")
        if not (0.0 < self.lead <= 60.0):
            raise ValueError(f"lead must be in (0, 60] s, got {self.lead}")
        if not (0.0 < self.reach <= 0.6):
            raise ValueError(f"reach must be in (0, 0.6] m, got {self.reach}")
        if not (isinstance(self.offset, int) and 0 <= self.offset <= 5000):
            raise ValueError(f"offset must be an int in [0, 5000] ticks, got {self.offset!r}")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Windows:
    """Window start states, flattened to a leading axis ``W = scenarios x per_scenario``.

    Attributes:
      model: per-window batched ``mjx.Model`` fields (see ``hmodel.batch_model``).
      data, ctrl, tau: the snapshot (``mjx.Data``, ``CrawlState``, last torque).
      valid: (W,) the trigger fired (invalid windows are masked out).
      leg: (W,) the leg about to step down; ``tick``: (W,) control tick of the snapshot in the forward run.
      scenario: (W,) index of the scenario the window came from.
      height: (W,) step height (m).
    """

    model: mjx.Model
    data: mjx.Data
    ctrl: crawl.CrawlState
    tau: jax.Array
    valid: jax.Array
    leg: jax.Array
    tick: jax.Array
    scenario: jax.Array
    height: jax.Array

    @property
    def size(self) -> int:
        return int(self.valid.shape[0])

    def take(self, idx) -> Windows:
        """The windows at ``idx`` (integer indices in ``[-W, W)``) as a new batch (jitted gathers of the batched
        leaves: a program per shape, not one per leaf)."""
        idx = jnp.asarray(row_index(idx, self.size))
        rest = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "model"}
        return Windows(model=hmodel.map_batched_fields(self.model, lambda f: take_rows(f, idx)),
                       **take_rows(rest, idx))


def grouped(win: Windows, robots: int) -> tuple[Windows, Windows]:
    """``win`` with its leading ``W`` axis split into ``(robots, W / robots)`` (per-robot batched tuning: robot
    ``r`` owns windows ``r * W / robots ...``), and the matching ``vmap`` axes (0 on every batched leaf)."""
    if robots < 1 or win.size % robots:
        raise ValueError(f"robots must divide the {win.size} windows, got {robots}")
    rest = {f.name: getattr(win, f.name) for f in dataclasses.fields(win) if f.name != "model"}
    zeros = jax.tree_util.tree_map(lambda _: 0, rest)
    return (Windows(model=hmodel.map_batched_fields(win.model, lambda f: _split_rows(f, robots)),
                    **_split_rows(rest, robots)),
            Windows(model=hmodel.model_in_axes(win.model), **zeros))


@functools.partial(jax.jit, static_argnums=1)
def _split_rows(tree, robots: int):
    """Every leaf's leading axis ``W`` as ``(robots, W / robots)``."""
    return jax.tree_util.tree_map(lambda x: x.reshape((robots, x.shape[0] // robots) + x.shape[1:]), tree)


@functools.partial(jax.jit, static_argnums=1)
def _repeat_rows(tree, k: int):
    """Every row of every leaf ``k`` times (``jnp.repeat`` along the leading axis)."""
    return jax.tree_util.tree_map(lambda x: jnp.repeat(x, k, axis=0), tree)


@jax.jit
def _merge_rows(tree):
    """Every leaf's two leading axes ``(B, K)`` as one, ``B K``."""
    return jax.tree_util.tree_map(lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), tree)


def _capture(mx, ids, controller, p, d0, spec: WindowSpec, n_ticks: int, dt: float):
    """Forward run of ONE scenario under ``controller`` (a :class:`hyqjax.core.types.Controller`, ``p`` its
    parameters); returns the snapshot slots, their validity, leg and tick."""
    sites = np.asarray(ids.foot_sites)
    tau0 = jnp.zeros(robot.N_JOINTS, d0.qpos.dtype)
    cs0 = controller.init(p, sim.observe(ids, d0, tau0, mx))
    k_slots = spec.per_scenario
    stack = lambda x: jnp.broadcast_to(x, (k_slots,) + jnp.shape(x))
    snaps0 = jax.tree_util.tree_map(stack, (d0, cs0, tau0))
    meta0 = (jnp.zeros(k_slots, bool), jnp.zeros(k_slots, jnp.int32), jnp.zeros(k_slots, jnp.int32))

    off = spec.offset

    def body(carry, k):
        d, cs, tau, snaps, (valid, legs, ticks), count, pending, pend_leg = carry
        d1, cs1, tau1, info = tick(mx, ids, p, d, cs, tau, dt, controller.step)
        new_body = (cs.phase == crawl.PHASE_SWING) & (cs1.phase == crawl.PHASE_BODY)
        leg = cs1.sequence[cs1.seq_index]  # the remedy may have brought the other front leg forward
        foot_x = d.site_xpos[sites][leg, 0]
        trig = new_body & (foot_x < 0.0) & (foot_x > -spec.reach) & (count < k_slots) & (pending < 0)
        # offset 0: the trigger tick's inputs; offset > 0: the inputs ``offset`` ticks later.
        take = (pending == 0) if off else trig
        take_leg = pend_leg if off else leg
        slot = jnp.minimum(count, k_slots - 1)
        put = lambda s, x: s.at[slot].set(jnp.where(take, x, s[slot]))
        snaps = jax.tree_util.tree_map(put, snaps, (d, cs, tau))
        valid = valid.at[slot].set(valid[slot] | take)
        legs = legs.at[slot].set(jnp.where(take, take_leg, legs[slot]).astype(jnp.int32))
        ticks = ticks.at[slot].set(jnp.where(take, k, ticks[slot]).astype(jnp.int32))
        pending = jnp.where(pending >= 0, pending - 1, pending)
        if off:
            pending = jnp.where(trig, off - 1, pending)
            pend_leg = jnp.where(trig, leg, pend_leg)
        return (d1, cs1, tau1, snaps, (valid, legs, ticks), count + take.astype(jnp.int32), pending, pend_leg), None

    carry = (d0, cs0, tau0, snaps0, meta0, jnp.int32(0), jnp.int32(-1), jnp.int32(0))
    carry, _ = jax.lax.scan(body, carry, jnp.arange(n_ticks))
    return carry[3], carry[4]


@functools.partial(jax.jit, static_argnames=("ids", "param", "spec", "n_ticks", "dt"))
def _capture_batch(mb, params, d0, *, ids, param, spec: WindowSpec, n_ticks: int, dt: float):
    """:func:`_capture` over a batch of scenarios, under the plain crawl (``param`` None) or the crawl that
    ``param`` schedules; one program per static configuration, whatever the parameters' values (a tuner that
    re-takes its windows at every iterate traces it once)."""
    controller = crawl.crawl_controller(dt) if param is None else param.controller(dt)
    return vmap_unless_one(lambda mm, pp, dd: _capture(mm, ids, controller, pp, dd, spec, n_ticks, dt),
                           in_axes=(hmodel.model_in_axes(mb), 0, 0))(mb, params, d0)  # one scenario: no vmap


def make_windows(scenario: stepdown.Scenario, spec: WindowSpec = WindowSpec(), su: Setup | None = None,
                 param=None, theta=None) -> Windows:
    """Snapshots of a step-down batch (``stepdown.make_scenarios``, reflex on) under its own parameters, or, with
    ``param`` (a :class:`.schedule.Parameterisation`) and ``theta``, under the crawl that ``theta`` schedules on
    top of them (the gait an iterate of a tuner walks: windows re-taken where a tuning run has moved to)."""
    su = su or setup()
    dt = float(su.m.opt.timestep)
    b = scenario.batch_size
    mb = hmodel.batch_model(su.mx, su.ids, scenario.terrain)
    dtype = su.mx.body_mass.dtype
    d0 = sim.initial_data(su.mx, jnp.asarray(stepdown.initial_qpos(su.m, scenario), dtype), b)
    params = jax.tree_util.tree_map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x,
                                    scenario.params)
    n_ticks = int(round(spec.lead / dt))
    if param is not None:
        th = jnp.asarray(np.asarray(theta, np.float64), dtype)
        sched = param.scheduled(th, params)
        params = dataclasses.replace(sched, table=jnp.broadcast_to(sched.table, (b,) + sched.table.shape),
                                     cond=jnp.broadcast_to(sched.cond, (b,) + sched.cond.shape))
    (dd, cc, tt), (valid, legs, ticks) = _capture_batch(mb, params, d0, ids=su.ids, param=param, spec=spec,
                                                        n_ticks=n_ticks, dt=dt)
    k = spec.per_scenario
    rows = _merge_rows(dict(data=dd, ctrl=cc, tau=tt, valid=valid, leg=legs, tick=ticks))
    rows.update(_repeat_rows(dict(scenario=jnp.arange(b), height=scenario.terrain.platform_height), k))
    return Windows(model=hmodel.map_batched_fields(mb, lambda f: _repeat_rows(f, k)), **rows)
