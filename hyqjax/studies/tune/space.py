"""The tuned parameters as one flat unconstrained vector ``theta`` (for ``jax.jacfwd``, Adam and CMA-ES).

A :class:`ParamSpace` is a static tuple of *coordinates*. Every coordinate maps one real number to one
parameter inside its allowed range, so every ``theta`` gives valid parameters (``ReflexParams.validate``,
``CrawlParams.make``):

* ``log``: ``log p = log lo + (log hi - log lo) sigmoid(theta)`` (stiffness ``K_base``, ``K_kl``, damping
  minima: a log scale inside ``(lo, hi)``);
* ``gap``: ``p = p_ref + (hi - p_ref) (g + (1 - g) sigmoid(theta))`` for an upper bound above its lower bound
  (``D_max`` above ``D_min``), so ``D_min < D_max <= hi`` always holds, in float32 too: the floor
  ``g`` = :data:`SEPARATION` keeps the two apart where ``sigmoid`` underflows (a search that drives ``theta``
  far negative otherwise rounds ``D_max`` onto ``D_min``, which ``ReflexParams`` refuses);
* ``box``: ``p = lo + (hi - lo) sigmoid(theta)`` for a parameter in ``(lo, hi)`` (``K_x`` in
  ``(0, K_x,max)``, ``Delta`` in ``(0, 0.5)``, the crawl's trunk height, step length, apex, search speed, the remedy's
  forward search per metre of depth and terrain adaptation, and the edge probe's and depth gate's settings);
* ``ratio``: ``m_min = m_max (g + (1 - 2 g) sigmoid(theta))`` (``0 < m_min < m_max``, in float32 too:
  ``sigmoid`` rounds to 1 above ``theta`` of about 17 and to 0 far below).

Every ``(lo, hi)`` lies inside the range ``ReflexParams`` / ``CrawlParams`` declare for the field (checked
by the tests against ``core.params.param_ranges``). ``m_max`` is a ``box`` in ``(0, M_NOMINAL)``: the damping schedule reacts to a *loss* of mobility, and
thresholds above the standing pose's mobility (``M_NOMINAL``) make every swing on flat ground squat the trunk.

Groups (``GROUPS``) name sets of coordinates; ``ParamSpace.make(groups)`` picks them in a fixed order.
Per-robot batched tuning stacks ``theta`` as ``(R, P)`` (``objective.make_per_robot_value_and_jac`` on
``windows.grouped`` windows); :meth:`ParamSpace.crawl_params` is traceable and ``vmap``-able.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core.params import ParameterError

from hyqjax.crawl import controller as crawl
from hyqjax.reflex import step as hreflex

#: Mobility m(e_z) (Eq. 12) of every leg in the standing pose (m/rad): upper bound of m_max.
M_NOMINAL = 0.2149


@dataclasses.dataclass(frozen=True)
class Coord:
    """One coordinate: ``name`` of the parameter, ``kind`` (log / gap / box / ratio), its owner
    (``reflex`` or ``crawl``), the range of a ``box`` and the lower-bound field of a ``gap`` / ``ratio``."""

    name: str
    kind: str
    owner: str
    lo: float = 0.0
    hi: float = 0.0
    ref: str = ""


#: Tunable groups: name -> coordinates (in this order).
GROUPS: dict[str, tuple[Coord, ...]] = {
    "k_base": (Coord("k_base", "log", "reflex", 10.0, 2.0e4),),
    "damping": (Coord("d_sw_min", "log", "reflex", 0.1, 1.0e3),
                Coord("d_sw_max", "gap", "reflex", hi=1.0e4, ref="d_sw_min"),
                Coord("d_st_min", "log", "reflex", 1.0, 5.0e3),
                Coord("d_st_max", "gap", "reflex", hi=1.0e4, ref="d_st_min")),
    "mobility": (Coord("m_max", "box", "reflex", 0.0, M_NOMINAL), Coord("m_min", "ratio", "reflex", ref="m_max")),
    "k_x": (Coord("k_x", "box", "reflex", 0.0, 2.0e4),),
    "delta": (Coord("delta", "box", "reflex", 0.0, 0.5),),
    "k_kl": (Coord("k_kl", "log", "reflex", 10.0, 1.0e4),),
    "body_height": (Coord("body_height", "box", "crawl", 0.45, 0.62),),
    "step_length": (Coord("max_step_length", "box", "crawl", 0.12, 0.34),),
    "step_height": (Coord("step_height", "box", "crawl", 0.04, 0.18),),
    "search_speed": (Coord("search_speed", "box", "crawl", 0.05, 0.35),),
    "search_forward": (Coord("search_forward", "box", "crawl", 0.0, 1.5),),
    "terrain_adaptation": (Coord("terrain_adaptation", "box", "crawl", 0.0, 1.0),),
    "edge_probe": (Coord("edge_probe", "box", "crawl", 0.0, 0.2), Coord("edge_probe_depth", "box", "crawl", 0.0, 0.15)),
    "edge_gate": (Coord("edge_tilt", "box", "crawl", 0.0, 1.0), Coord("edge_margin", "box", "crawl", -0.3, 0.3),
                  Coord("edge_lowering", "box", "crawl", 0.0, 0.1), Coord("edge_deep", "box", "crawl", 0.0, 1.0),
                  Coord("edge_tilt_deep", "box", "crawl", 0.0, 1.0)),
}
REFLEX_GROUPS = ("k_base", "damping", "mobility", "k_x", "delta")
CRAWL_GROUPS = ("body_height", "step_length", "step_height")
#: The shin-strike remedy's continuous parameters (:mod:`hyqjax.crawl.remedy`; they act with ``shin_remedy`` on).
REMEDY_GROUPS = ("search_forward", "terrain_adaptation")
DEFAULT_GROUPS = REFLEX_GROUPS + CRAWL_GROUPS + REMEDY_GROUPS
#: The edge probe's step and depth and the depth gate's tilts, margin and lowering (:mod:`hyqjax.crawl.edge`; they act
#: with the probe on, ``edge_probe > 0``): tuned from a start whose probe is on (the presets ``reach`` and
#: ``clean``), since a ``box`` coordinate cannot hold the probe's ``0`` (off) exactly.
EDGE_GROUPS = ("edge_probe", "edge_gate")


#: The smallest share of its range that separates a ``gap`` coordinate from its lower bound, and a ``ratio``
#: coordinate from 0 and from its upper bound (module docstring).
SEPARATION = 1e-3


def _logit(p: float) -> float:
    p = min(max(p, 1e-6), 1 - 1e-6)
    return math.log(p / (1 - p))


def shared_value(params, name: str) -> float:
    """The one value of field ``name`` of ``params``; a per-instance field with different values is refused
    (one parameter set per robot is tuned with ``objective.make_per_robot_value_and_jac``), never averaged."""
    v = np.asarray(getattr(params, name), np.float64)
    if v.size > 1 and not np.all(v == v.reshape(-1)[0]):
        raise ParameterError(type(params).__name__, name, f"per-instance values {v.min():g}..{v.max():g}",
                             "one value shared by every instance (tune per robot for per-instance parameters)")
    return float(v.reshape(-1)[0])


@dataclasses.dataclass(frozen=True)
class ParamSpace:
    """A static set of coordinates (hashable: part of jit cache keys)."""

    coords: tuple[Coord, ...]
    groups: tuple[str, ...]

    @staticmethod
    def make(groups=DEFAULT_GROUPS) -> ParamSpace:
        groups = tuple(groups)
        bad = [g for g in groups if g not in GROUPS]
        if bad or not groups:
            raise ValueError(f"groups must be a non-empty subset of {list(GROUPS)}, got {list(groups)}")
        return ParamSpace(tuple(c for g in GROUPS if g in groups for c in GROUPS[g]), groups)

    @property
    def size(self) -> int:
        return len(self.coords)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.coords)

    def values(self, theta) -> dict[str, jax.Array]:
        """Parameter values of ``theta`` (``(P,)``; traceable), in coordinate order."""
        out: dict[str, jax.Array] = {}
        for i, c in enumerate(self.coords):
            t = theta[..., i]
            if c.kind == "log":
                out[c.name] = jnp.exp(math.log(c.lo) + (math.log(c.hi) - math.log(c.lo)) * jax.nn.sigmoid(t))
            elif c.kind == "gap":
                share = SEPARATION + (1.0 - SEPARATION) * jax.nn.sigmoid(t)
                out[c.name] = out[c.ref] + (c.hi - out[c.ref]) * share
            elif c.kind == "box":
                out[c.name] = c.lo + (c.hi - c.lo) * jax.nn.sigmoid(t)
            else:  # ratio
                out[c.name] = out[c.ref] * (SEPARATION + (1.0 - 2.0 * SEPARATION) * jax.nn.sigmoid(t))
        return out

    def theta_of(self, params: crawl.CrawlParams) -> np.ndarray:
        """The ``theta`` (float64 numpy) that reproduces ``params`` on the tuned coordinates."""
        val = lambda c: shared_value(params.reflex if c.owner == "reflex" else params, c.name)  # noqa: E731
        out = []
        for c in self.coords:
            v = val(c)
            if c.kind == "log":
                out.append(_logit((math.log(v) - math.log(c.lo)) / (math.log(c.hi) - math.log(c.lo))))
            elif c.kind == "gap":
                ref = val(next(cc for cc in self.coords if cc.name == c.ref))
                out.append(_logit(((v - ref) / (c.hi - ref) - SEPARATION) / (1.0 - SEPARATION)))
            elif c.kind == "box":
                out.append(_logit((v - c.lo) / (c.hi - c.lo)))
            else:
                ref = next(cc for cc in self.coords if cc.name == c.ref)
                out.append(_logit((v / val(ref) - SEPARATION) / (1.0 - 2.0 * SEPARATION)))
        return np.asarray(out, np.float64)

    def crawl_params(self, theta, base: crawl.CrawlParams) -> crawl.CrawlParams:
        """``base`` with the tuned fields from ``theta`` (traceable; leaves keep ``base``'s dtypes)."""
        v = self.values(theta)
        rk = {c.name: v[c.name].astype(jnp.asarray(getattr(base.reflex, c.name)).dtype)
              for c in self.coords if c.owner == "reflex"}
        ck = {c.name: v[c.name].astype(jnp.asarray(getattr(base, c.name)).dtype)
              for c in self.coords if c.owner == "crawl"}
        return dataclasses.replace(base, reflex=dataclasses.replace(base.reflex, **rk), **ck)

    def concrete(self, theta, base: crawl.CrawlParams | None = None) -> crawl.CrawlParams:
        """Validated ``CrawlParams`` of a concrete ``theta`` (outside jit): for evaluation and reports."""
        base = base or crawl.CrawlParams.make()
        v = {k: float(x) for k, x in self.values(jnp.asarray(np.asarray(theta, np.float64))).items()}
        rp = {f.name: shared_value(base.reflex, f.name) for f in dataclasses.fields(base.reflex)}
        rp.update({c.name: v[c.name] for c in self.coords if c.owner == "reflex"})
        ck = {c.name: v[c.name] for c in self.coords if c.owner == "crawl"}
        out = dataclasses.replace(base, reflex=hreflex.ReflexParams(**rp).validate(),
                                  **{k: jnp.asarray(x, jnp.float32) for k, x in ck.items()})
        return out

    def describe(self, theta, dt: float = 0.002) -> dict[str, float]:
        """Parameter values of ``theta`` and the reflex's stability number at ``dt`` (stable below 1)."""
        from hyqjax.reflex import params as rparams

        out = {k: float(x) for k, x in self.values(jnp.asarray(np.asarray(theta, np.float64))).items()}
        rp = {f.name: float(np.asarray(getattr(hreflex.ReflexParams(), f.name)).mean())
              for f in dataclasses.fields(hreflex.ReflexParams)}
        rp.update({c.name: out[c.name] for c in self.coords if c.owner == "reflex"})
        out["stability_number"] = float(rparams.stability_number(hreflex.ReflexParams(**rp), dt, np))
        return out


def table1_theta(space: ParamSpace) -> np.ndarray:
    """``theta`` of Table I and the default crawl."""
    return space.theta_of(crawl.CrawlParams.make())
