"""Per-leg crawl parameters: a :class:`CrawlParams` whose tuned fields take one value per swing leg.

The reflex acts on one swing leg at a time (Section III), so a parameter set may give every leg its own values:
``K_base``, the damping schedule and ``K_x`` in force while that leg swings, the trunk height, step length and
apex of that leg's body phase and swing (the tuner's ``per_leg`` parameterisation,
:mod:`hyqjax.studies.tune.schedule`). :class:`PerLegCrawlParams` is that set as a crawl parameter object in its
own right: ``base`` (a :class:`CrawlParams`: every field, batched or not, as usual) and ``legs``, per-leg values
of some of its fields (a trailing axis of 4, legs in :data:`LEGS` order, the leg indices of
``CrawlParams.foot_sequence``). At every control tick the crawl runs ``base`` with those fields set to the row
of the leg that swings now or swings next (``CrawlState.sequence[seq_index]``; at the start, the sequence's first
leg): :func:`at_tick`, called by :func:`hyqjax.crawl.controller.crawl_controller` for every parameter object, so
the step-down task, sweeps, the reach map, renders and the library API run a per-leg set exactly as they run a
``CrawlParams``. A per-leg set whose four rows equal ``base``'s values runs bit for bit as ``base``
(``tests/test_presets.py``).

``legs`` keys are ``CrawlParams`` field names or ``reflex.<ReflexParams field>``; values are validated against the
fields' declared ranges (and the reflex's orderings, row by row) when the object is made with :meth:`make`.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hyqjax.core.params import ParameterError, param_ranges
from hyqjax.crawl.params import CrawlParams

#: The legs in the order of ``CrawlParams.foot_sequence``'s indices (and of ``legs``' trailing axis).
LEGS = ("LF", "RF", "LH", "RH")
REFLEX_PREFIX = "reflex."


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class PerLegCrawlParams:
    """``base`` with per-swing-leg values ``legs`` (``{field: array (..., 4)}``; module docstring)."""

    base: CrawlParams
    legs: dict

    @staticmethod
    def make(base: CrawlParams, legs: dict) -> "PerLegCrawlParams":
        """Validated constructor: ``legs`` maps a field name (``body_height``, ``reflex.k_base``, ...) to 4 values
        (or a dict ``{LEG: value}`` over :data:`LEGS`); each row must make a valid ``CrawlParams`` with ``base``
        (a :class:`ParameterError` naming the field and the leg otherwise)."""
        if not isinstance(base, CrawlParams):
            raise ParameterError("PerLegCrawlParams", "base", type(base).__name__, "a CrawlParams")
        crawl_fields = set(param_ranges(CrawlParams))
        reflex_fields = set(param_ranges(type(base.reflex)))
        out = {}
        for key, v in legs.items():
            name = key[len(REFLEX_PREFIX):] if key.startswith(REFLEX_PREFIX) else key
            owner = reflex_fields if key.startswith(REFLEX_PREFIX) else crawl_fields
            if name not in owner or name in ("foot_sequence",):
                raise ParameterError("PerLegCrawlParams", key, "unknown", "a CrawlParams field or reflex.<ReflexParams "
                                     "field>", problem="is not a field")
            if isinstance(v, dict):
                missing = [leg for leg in LEGS if leg not in v]
                if missing or set(v) - set(LEGS):
                    raise ParameterError("PerLegCrawlParams", key, sorted(v), f"one value per leg {list(LEGS)}",
                                         problem="has the wrong legs")
                v = [v[leg] for leg in LEGS]
            ref = getattr(base.reflex if key.startswith(REFLEX_PREFIX) else base, name)
            arr = np.asarray(v, np.float64)
            if arr.shape != (4,) or np.shape(ref) != ():
                raise ParameterError("PerLegCrawlParams", key, f"shape {arr.shape}", "4 values (one per leg) of a "
                                     "scalar field", problem="has a wrong shape")
            out[key] = jnp.asarray(arr.astype(np.asarray(ref).dtype))
        p = PerLegCrawlParams(base, out)
        for i in range(4):  # every row validated as the CrawlParams it runs
            try:
                p.row(i)
            except ParameterError as e:
                key = next((k for k in out if k.removeprefix(REFLEX_PREFIX) == e.param), e.param)
                raise ParameterError("PerLegCrawlParams", f"{key}[{LEGS[i]}]", e.value, e.allowed) from None
        return p

    @staticmethod
    def uniform(base: CrawlParams, fields=("reflex.k_base", "body_height")) -> "PerLegCrawlParams":
        """``base`` as a per-leg set whose ``fields`` take ``base``'s own value on every leg (runs as ``base``)."""
        legs = {}
        for key in fields:
            obj = base.reflex if key.startswith(REFLEX_PREFIX) else base
            legs[key] = [float(np.asarray(getattr(obj, key.removeprefix(REFLEX_PREFIX))))] * 4
        return PerLegCrawlParams.make(base, legs)

    def at_tick(self, st=None, obs=None) -> CrawlParams:  # noqa: ARG002  (the per-leg choice needs no observation)
        """The row of the leg that swings now (:func:`swing_leg`; traceable)."""
        return self.at_leg(swing_leg(self, st))

    def at_leg(self, leg) -> CrawlParams:
        """``base`` with every per-leg field at leg ``leg``'s value (traceable; ``leg`` an index into :data:`LEGS`).
        Leaves keep ``base``'s dtypes; no validation (a traced leg)."""
        crawl_kw, reflex_kw = {}, {}
        for key, v in self.legs.items():
            val = jnp.take(v, leg, axis=-1)
            if key.startswith(REFLEX_PREFIX):
                reflex_kw[key[len(REFLEX_PREFIX):]] = val
            else:
                crawl_kw[key] = val
        reflex = _replace_unchecked(self.base.reflex, reflex_kw) if reflex_kw else self.base.reflex
        return _replace_unchecked(self.base, dict(crawl_kw, reflex=reflex))

    def row(self, i: int) -> CrawlParams:
        """The validated ``CrawlParams`` that runs while leg ``i`` swings (concrete values)."""
        p = self.at_leg(int(i))
        return dataclasses.replace(p, reflex=dataclasses.replace(p.reflex))

    def replace_base(self, **kwargs) -> "PerLegCrawlParams":
        """A copy with fields of ``base`` replaced (``dataclasses.replace``; a per-leg field is refused)."""
        clash = sorted(set(kwargs) & set(self.legs))
        if clash:
            raise ParameterError("PerLegCrawlParams", clash[0], kwargs[clash[0]], "left to its per-leg values",
                                 problem="is set per leg")
        return PerLegCrawlParams(dataclasses.replace(self.base, **kwargs), self.legs)

    def describe(self) -> dict:
        """``{field[LEG]: value}`` of the per-leg fields (concrete, unbatched)."""
        return {f"{k}[{leg}]": float(np.asarray(v)[..., i].reshape(-1)[0]) for k, v in self.legs.items()
                for i, leg in enumerate(LEGS)}


def _replace_unchecked(obj, kw: dict):
    """``obj`` with fields ``kw`` (traced or concrete) without running the parameter class's validation (the
    values were validated when the per-leg set was made)."""
    if not kw:
        return obj
    new = object.__new__(type(obj))
    for f in dataclasses.fields(obj):
        object.__setattr__(new, f.name, kw.get(f.name, getattr(obj, f.name)))
    return new


def swing_leg(p, st=None):
    """The leg whose row runs now: the swing leg of state ``st`` (``CrawlState.sequence[seq_index]``), the first
    leg of ``p``'s sequence before the first tick (``st=None``). Traceable."""
    if st is None:
        return jnp.asarray(base_of(p).foot_sequence)[..., 0]
    return st.sequence[st.seq_index]


def at_tick(p, st=None, obs=None) -> CrawlParams:
    """The ``CrawlParams`` the crawl runs now: ``p`` itself for a ``CrawlParams``; for a scheduled set (a
    :class:`PerLegCrawlParams`, or any parameter object with ``base``, ``replace_base`` and ``at_tick(st, obs)``,
    e.g. the tuner's conditioned sets, :class:`hyqjax.studies.tune.schedule.ConditionedCrawlParams`) its own
    choice for state ``st`` and observation ``obs`` (``st=None``: before the first tick). Traceable; a Python
    ``isinstance`` on the parameter object's type only."""
    if isinstance(p, CrawlParams):
        return p
    return p.at_tick(st, obs)


def base_of(p) -> CrawlParams:
    """The ``CrawlParams`` of every field that is not scheduled (``p`` itself for a ``CrawlParams``)."""
    return p if isinstance(p, CrawlParams) else p.base


def replace_base(p, **kwargs):
    """``dataclasses.replace`` on a ``CrawlParams``, the set's own ``replace_base`` on a scheduled set."""
    if isinstance(p, CrawlParams):
        return dataclasses.replace(p, **kwargs)
    return p.replace_base(**kwargs)


def common_structure(params: dict) -> dict:
    """``{name: parameters}`` with one PyTree structure, to be stacked into one batch: unchanged when none is a
    per-leg set; otherwise every one a :class:`PerLegCrawlParams` over the union of the per-leg fields (a field a
    set does not vary per leg gets its own value on every leg, which runs bit for bit as before)."""
    if all(isinstance(p, CrawlParams) for p in params.values()) or len(params) == 1:
        return dict(params)
    other = [n for n, p in params.items() if not isinstance(p, (CrawlParams, PerLegCrawlParams))]
    if other:
        raise ValueError(f"{other[0]}: a {type(params[other[0]]).__name__} runs in a batch of its own kind only; run "
                         f"it without the other variants")
    keys = []
    for p in params.values():
        if isinstance(p, PerLegCrawlParams):
            keys += [k for k in p.legs if k not in keys]
    out = {}
    for name, p in params.items():
        base = base_of(p)
        legs = dict(p.legs) if isinstance(p, PerLegCrawlParams) else {}
        for k in keys:
            if k not in legs:
                obj = base.reflex if k.startswith(REFLEX_PREFIX) else base
                v = jnp.asarray(getattr(obj, k.removeprefix(REFLEX_PREFIX)))
                legs[k] = jnp.broadcast_to(v[..., None], v.shape + (4,)).astype(np.asarray(v).dtype)
        out[name] = PerLegCrawlParams(base, {k: legs[k] for k in keys})
    return out
