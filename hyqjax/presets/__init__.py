"""Named parameter sets for the crawl and the bounding gait, shipped with the package, and the user's own: one
registry.

Every preset is one JSON file beside this module (``<name>.json``, format :data:`FORMAT`): its ``kind``
(``crawl`` or ``bound``), a one-line ``description``, its ``values``, its ``provenance`` (command, seed, device,
date, hyqjax version, source result file) and the ``figures`` measured for it (value, interval, the held-out set
it was measured on, the command that measured it, device, date, source).

* ``names(kind=None)``: the preset names (of one kind);
* ``get(name)``: the :class:`Preset` record (``.name .kind .description .provenance .figures .values``);
* ``load(name, **kw)``: the parameter object. A crawl preset gives a ``CrawlParams`` (``kw``: more
  ``CrawlParams.make`` settings, e.g. ``forward_velocity``), or a per-leg set
  (:class:`hyqjax.crawl.scheduled.PerLegCrawlParams`) when its values are per swing leg; both run wherever a
  crawl runs (``hyqjax stepdown``, ``hyqjax sweep``, the reach map, renders, the library), or a conditioned set
  (:class:`hyqjax.studies.tune.schedule.ConditionedCrawlParams`) for ``values.conditioned``. A bounding preset
  gives a ``BoundingParams`` (``kw``: the command and switches of
  :func:`hyqjax.bounding.params.paper_params`, e.g. ``speed=0.5, yaw_rate=0.3``).

Values of a crawl preset (``values``): ``crawl`` (``CrawlParams.make`` settings), ``reflex`` (``ReflexParams``
fields, over Table I) and optionally ``per_leg`` (``{field: {LF: v, RF: v, LH: v, RH: v}}``, ``reflex.<field>``
for a reflex field) or ``conditioned`` (a tuner's conditioned set: ``parameterisation``, ``groups``, ``theta``,
the ``fields`` it chooses per tick and their ``values`` for reading). Values of a bounding preset: ``amplitudes``
(``a_fz, a_hz, a_fx, a_hx``, N per leg) and
``gains`` (``BoundingGains`` fields) over the paper's stored limit cycle; empty for the paper's own gains.

The user's own presets are files of the same format in :func:`user_dir` (``$HYQJAX_PRESETS_DIR``, else
``$XDG_DATA_HOME/hyqjax/presets``, else ``~/.local/share/hyqjax/presets``), listed after the shipped ones and
loaded wherever a shipped one is (``Preset.user_dir`` names the directory). ``hyqjax presets save NAME --from
RESULTS.json[:METHOD/DIM]`` writes one from a tuning run's returned set (:mod:`hyqjax.presets.from_results`); a
user file that cannot be used is named by :func:`user_problems` (and by ``get`` of its name) and breaks nothing
else.

Refusals are one line (a :class:`PresetError`, a ``ValueError``): an unknown name (naming the known ones), a
preset of the other kind (:func:`check_kind`), a stored value outside its declared range (naming the field).
Reading a preset imports JAX's parameter classes only, never MJX.
"""
from __future__ import annotations

from hyqjax.presets.registry import (  # noqa: F401  (the registry's API, re-exported)
    FIGURE_CLEAN,
    FIGURE_TALL,
    FORMAT,
    KINDS,
    NAME_RULE,
    ORDER,
    Preset,
    PresetError,
    check_kind,
    crawl_settings,
    describe,
    format_figure,
    get,
    name_problem,
    names,
    user_dir,
    user_problems,
    values_digest,
)


def load(name: str, **kw):
    """The parameter object of preset ``name`` (module docstring); ``kw`` as documented there. A one-line
    :class:`PresetError` for an unknown name or a stored (or given) value outside its declared range."""
    p = get(name)
    return load_preset(p, **kw)


def load_preset(p: Preset, **kw):
    """:func:`load` of a :class:`Preset` record."""
    from hyqjax.core.params import ParameterError

    try:
        return (_crawl if p.kind == "crawl" else _bound)(p, **kw)
    except ParameterError as e:
        raise PresetError(f"preset {p.name}: {e}") from None
    except (TypeError, ValueError) as e:
        raise PresetError(f"preset {p.name}: {e}") from None


def _crawl(p: Preset, **kw):
    from hyqjax.crawl.params import CrawlParams
    from hyqjax.reflex.params import ReflexParams

    v = p.values
    settings = dict(v.get("crawl", {}))
    settings.update(kw)
    reflex = ReflexParams.make(**{k: float(x) for k, x in v.get("reflex", {}).items()})
    base = CrawlParams.make(**settings, reflex_params=reflex)
    cond = v.get("conditioned")
    if cond:
        from hyqjax.studies.tune import schedule

        clash = sorted(set(kw) & set(cond.get("fields", ())))
        if clash:
            raise PresetError(f"preset {p.name}: {clash[0]} is chosen per tick by the preset; leave it out")
        return schedule.ConditionedCrawlParams.of_theta(schedule.make(cond["parameterisation"], cond["groups"]),
                                                        cond["theta"], base)
    per_leg = v.get("per_leg") or {}
    if not per_leg:
        return base
    from hyqjax.crawl.scheduled import PerLegCrawlParams

    clash = sorted(set(kw) & set(per_leg))
    if clash:
        raise PresetError(f"preset {p.name}: {clash[0]} is set per leg by the preset; leave it out")
    return PerLegCrawlParams.make(base, per_leg)


def _bound(p: Preset, **kw):
    from hyqjax.bounding import params as bp

    v = p.values
    return bp.params_of_values(dict(v.get("amplitudes", {}), **v.get("gains", {})), **kw)
