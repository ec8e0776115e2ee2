"""Parameterisations of the tuned crawl and reflex from 14 coordinates to 98: per leg and conditioned.

A :class:`Parameterisation` maps one unconstrained vector ``theta`` to the parameters the crawl uses at every
control tick. It builds on :class:`.space.ParamSpace` (``P0`` bounded coordinates: ``K_base``, the damping
bounds, the mobility thresholds, ``K_x``, ``Delta``, trunk height, step length, apex, forward search, terrain
adaptation) in two ways:

* **per leg** (``per_leg``): every coordinate has one value per *swing leg* ``l`` (LF, RF, LH, RH), the leg
  that swings now or swings next (``CrawlState.sequence[seq_index]``). The reflex acts on one swing leg at a
  time (Section III), so ``K_base``, the damping schedule and ``K_x`` of a row are those in force while that
  leg swings; the crawl's trunk height, step length and apex of a row are those of that leg's body phase and
  swing; the forward search acts on front legs only (:mod:`hyqjax.crawl.remedy`), so its hind rows are inert;
* **conditioned** (``conditioned``): a coordinate ``i`` gets an offset linear in ``F = 3`` features the
  controller measures itself (:func:`features`): the payload estimated from the foot forces, the depth the
  current swing has searched past its nominal foothold (the live estimate of the step height), and the share
  of legs whose last swing found a step down.

The value of coordinate ``i`` at a tick with swing leg ``l`` and features ``phi`` is the bounded map of
:class:`.space.ParamSpace` applied to

.. math:: \\vartheta_i(l, \\phi) = T_{l i} + \\sum_f \\phi_f A_{f i}

with ``T`` the ``(4, P0)`` table (one row repeated without ``per_leg``) and ``A`` the ``(F, P0)`` conditioning
matrix (zero outside ``conditioned``), so every ``theta`` gives valid parameters at every tick. ``theta`` is
``T`` (``4 P0`` or ``P0`` entries) followed by the conditioned entries of ``A`` (feature-major). The start point
(:meth:`Parameterisation.theta_of`) repeats the start row and sets ``A = 0``: it runs exactly the start point's
crawl, whatever the dimension.

The controller (:meth:`Parameterisation.controller`) is the crawl of :mod:`hyqjax.crawl.controller` with its
parameters selected per tick; its state is the crawl's own :class:`CrawlState`, so every metric and outcome of
:mod:`hyqjax.studies.stepdown_outcome` applies unchanged. Its parameters (:class:`Scheduled`) have the same
shapes for every parameterisation of one ``ParamSpace``, so one compiled rollout serves all dimensions.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core import robot
from hyqjax.core.types import Controller
from hyqjax.crawl import controller as crawl
from hyqjax.studies.tune import space as spmod

LEGS = ("LF", "RF", "LH", "RH")
#: Features of :func:`features`, in order.
FEATURES = ("payload", "search_depth", "stepped_down")
#: Scale of the payload feature (kg) and of the search-depth feature (m).
PAYLOAD_SCALE = 15.0
DEPTH_SCALE = 0.3


def features(st: crawl.CrawlState, obs) -> jax.Array:
    """``(3,)`` features the controller measures (traceable):

    * payload: ``(|sum_l f_l| / g - m_HyQ) / 15 kg`` from the feet's estimated ground reaction forces
      (``Observation.foot_force``; the stance feet carry the weight, so this is the extra mass, noisy while
      the trunk accelerates);
    * search depth: ``search_depth / 0.3 m``, how far the current swing has searched past its nominal foothold
      (0 until the nominal swing ends; the live estimate of the step height);
    * stepped down: the share of legs whose last swing searched deeper than ``deep_search``.
    """
    dtype = obs.foot_force.dtype
    load = jnp.linalg.norm(jnp.sum(obs.foot_force, 0)) / robot.GRAVITY
    payload = jnp.clip((load - robot.TOTAL_MASS) / PAYLOAD_SCALE, -1.0, 2.0)
    depth = jnp.clip(st.search_depth / DEPTH_SCALE, 0.0, 2.0)
    down = jnp.mean(st.deep.astype(dtype))
    return jnp.stack([payload, depth, down]).astype(dtype)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Scheduled:
    """Controller parameters of a parameterised crawl: ``base`` (every untuned field), the ``(4, P0)`` table
    ``T`` and the ``(F, P0)`` conditioning ``A`` (module docstring). Batched: a leading axis on every leaf."""

    base: crawl.CrawlParams
    table: jax.Array
    cond: jax.Array


@dataclasses.dataclass(frozen=True)
class Parameterisation:
    """A static parameterisation (hashable; module docstring): ``space``, ``per_leg``, ``conditioned``."""

    name: str
    space: spmod.ParamSpace
    per_leg: bool = False
    conditioned: tuple = ()

    def __post_init__(self):
        bad = [c for c in self.conditioned if c not in self.space.names]
        if bad:
            raise ValueError(f"conditioned coordinates must be among {list(self.space.names)}, got {bad}")

    @property
    def base_size(self) -> int:
        return self.space.size

    @property
    def size(self) -> int:
        return (4 if self.per_leg else 1) * self.space.size + len(FEATURES) * len(self.conditioned)

    @property
    def names(self) -> tuple[str, ...]:
        rows = ([f"{n}[{leg}]" for leg in LEGS for n in self.space.names] if self.per_leg
                else list(self.space.names))
        return tuple(rows + [f"{n}~{f}" for f in FEATURES for n in self.conditioned])

    def split(self, theta):
        """``(T (4, P0), A (F, P0))`` of ``theta`` (traceable, any leading batch axes)."""
        p0, lead = self.space.size, theta.shape[:-1]
        n_rows = 4 * p0 if self.per_leg else p0
        rows = theta[..., :n_rows].reshape(lead + ((4, p0) if self.per_leg else (1, p0)))
        table = jnp.broadcast_to(rows, lead + (4, p0))
        cond = jnp.zeros(lead + (len(FEATURES), p0), theta.dtype)
        if self.conditioned:
            idx = np.asarray([self.space.names.index(c) for c in self.conditioned])
            a = theta[..., n_rows:].reshape(lead + (len(FEATURES), len(self.conditioned)))
            cond = cond.at[..., idx].set(a)
        return table, cond

    def theta_of(self, params: crawl.CrawlParams) -> np.ndarray:
        """The ``theta`` that runs ``params`` (start row on every leg, no conditioning)."""
        row = self.space.theta_of(params)
        rows = np.tile(row, 4) if self.per_leg else row
        return np.concatenate([rows, np.zeros(len(FEATURES) * len(self.conditioned))])

    def scheduled(self, theta, base: crawl.CrawlParams) -> Scheduled:
        """The controller parameters of ``theta`` (traceable)."""
        table, cond = self.split(jnp.asarray(theta))
        return Scheduled(base=base, table=table, cond=cond)

    def params_at(self, sp: Scheduled, leg, phi) -> crawl.CrawlParams:
        """The crawl parameters for swing leg ``leg`` and features ``phi`` (traceable)."""
        vartheta = sp.table[leg] + phi @ sp.cond
        return self.space.crawl_params(vartheta, sp.base)

    def controller(self, dt: float) -> Controller:
        """The crawl with its parameters selected per tick (:meth:`params_at`); state: ``CrawlState``."""
        space = self

        def init(sp: Scheduled, obs):
            leg = jnp.asarray(sp.base.foot_sequence)[0]
            return crawl.crawl_init(space.params_at(sp, leg, jnp.zeros(len(FEATURES), sp.table.dtype)), obs)

        def step(sp: Scheduled, st: crawl.CrawlState, obs):
            p = space.params_at(sp, st.sequence[st.seq_index], features(st, obs).astype(sp.table.dtype))
            return crawl.crawl_step(p, st, obs, dt)

        return Controller(init, step, tie_rollout_carry=True)

    def rows(self, theta) -> np.ndarray:
        """``(4, P0)`` table rows of a concrete ``theta`` (float64)."""
        return np.asarray(self.split(jnp.asarray(np.asarray(theta, np.float64)))[0], np.float64)

    def describe(self, theta) -> dict:
        """Values per leg (``name[LEG]``) and conditioning coefficients (``name~feature``, theta units), and
        the largest reflex stability number over the legs (stable below 1)."""
        out: dict = {}
        rows = self.rows(theta)
        stab = []
        for leg, r in zip(LEGS if self.per_leg else ("",), rows if self.per_leg else rows[:1]):
            d = self.space.describe(r)
            stab.append(d.pop("stability_number"))
            out.update({(f"{k}[{leg}]" if leg else k): v for k, v in d.items()})
        th = np.asarray(theta, np.float64)
        for n, v in zip(self.names[len(self.names) - len(FEATURES) * len(self.conditioned):],
                        th[th.size - len(FEATURES) * len(self.conditioned):]):
            out[n] = float(v)
        out["stability_number"] = float(max(stab))
        return out


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ConditionedCrawlParams:
    """A tuned per-leg, conditioned set as a crawl parameter object: the crawl runs it wherever it runs a
    ``CrawlParams`` (:func:`hyqjax.crawl.scheduled.at_tick` calls :meth:`at_tick`), with the tuner's own choice of
    parameters per tick (:meth:`Parameterisation.params_at`: the swing leg's row of ``table`` plus the
    conditioning ``cond`` times the features the controller measures, :func:`features`). ``base`` holds every
    field the set does not tune (batched or not, as a ``CrawlParams``); ``parameterisation`` is static."""

    base: crawl.CrawlParams
    table: jax.Array
    cond: jax.Array
    parameterisation: Parameterisation = dataclasses.field(metadata=dict(static=True))

    @staticmethod
    def of_theta(parameterisation: Parameterisation, theta, base: crawl.CrawlParams) -> "ConditionedCrawlParams":
        """The set of a concrete ``theta`` of ``parameterisation`` over ``base`` (every tick's parameters lie in
        their declared ranges by construction: :class:`.space.ParamSpace`)."""
        th = np.asarray(theta, np.float64)
        if th.shape != (parameterisation.size,) or not np.all(np.isfinite(th)):
            raise ValueError(f"theta of {parameterisation.name} must be {parameterisation.size} finite values, got "
                             f"shape {th.shape}")
        table, cond = parameterisation.split(jnp.asarray(th, jnp.float32))
        return ConditionedCrawlParams(base, table, cond, parameterisation)

    @property
    def fields(self) -> tuple[str, ...]:
        """The tuned fields (``reflex.<name>`` for a reflex field): chosen per tick, never ``base``'s."""
        return tuple(f"reflex.{c.name}" if c.owner == "reflex" else c.name for c in self.parameterisation.space.coords)

    def at_tick(self, st=None, obs=None) -> crawl.CrawlParams:
        """The parameters of this tick (traceable): the swing leg's row and, once the crawl runs (``st`` given),
        the conditioning on :func:`features`; before the first tick the features are zero, as in the tuner."""
        from hyqjax.crawl import scheduled

        leg = scheduled.swing_leg(self, st)
        if st is None:
            phi = jnp.zeros(self.cond.shape[:-2] + (len(FEATURES),), self.table.dtype)
        else:
            phi = features(st, obs).astype(self.table.dtype)
        return self.parameterisation.params_at(Scheduled(self.base, self.table, self.cond), leg, phi)

    def replace_base(self, **kwargs) -> "ConditionedCrawlParams":
        """A copy with fields of ``base`` replaced; a tuned crawl field is refused (a reflex field given through
        ``reflex`` keeps its tuned values, which the set chooses per tick)."""
        tuned = sorted(set(kwargs) & set(self.fields))
        if tuned:
            raise ValueError(f"{tuned[0]} is chosen per tick by the conditioned set {self.parameterisation.name}; "
                             f"leave it out")
        return dataclasses.replace(self, base=dataclasses.replace(self.base, **kwargs))

    def describe(self) -> dict:
        """Per-leg values and conditioning coefficients (concrete, unbatched; :meth:`Parameterisation.describe`)."""
        pz = self.parameterisation
        rows = np.asarray(self.table, np.float64).reshape(-1, 4, pz.space.size)[0]
        th = rows.reshape(-1) if pz.per_leg else rows[0]
        if pz.conditioned:
            idx = [pz.space.names.index(c) for c in pz.conditioned]
            a = np.asarray(self.cond, np.float64).reshape(-1, len(FEATURES), pz.space.size)[0][:, idx]
            th = np.concatenate([th, a.reshape(-1)])
        return pz.describe(th)


def make(name: str, groups=spmod.DEFAULT_GROUPS) -> Parameterisation:
    """A named parameterisation (:data:`NAMES`) of the ``groups`` of :class:`.space.ParamSpace`."""
    space = spmod.ParamSpace.make(groups)
    if name not in NAMES:
        raise ValueError(f"dims must be among {list(NAMES)}, got {name!r}")
    per_leg, cond = NAMES[name]
    cond = tuple(c for c in (space.names if cond == "all" else cond) if c in space.names)
    return Parameterisation(name, space, per_leg, cond)


#: Named parameterisations: name -> (per leg, conditioned coordinates). With the 14 default coordinates:
#: shared = 14, per_leg = 56, per_leg_cond = 56 + 3 x 4 = 68, per_leg_cond_all = 56 + 3 x 14 = 98.
NAMES = {
    "shared": (False, ()),
    "per_leg": (True, ()),
    "per_leg_cond": (True, ("k_base", "d_st_max", "body_height", "search_forward")),
    "per_leg_cond_all": (True, "all"),
}
