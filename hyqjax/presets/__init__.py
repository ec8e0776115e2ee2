"""Named parameter sets for the crawl and the bounding gait, shipped with the package: one registry.

Every preset is one JSON file beside this module (``<name>.json``, format :data:`FORMAT`): its ``kind``
(``crawl`` or ``bound``), a one-line ``description``, its ``values``, its ``provenance`` (command, seed, device,
date, hyqjax version, source result file) and the ``figures`` measured for it (value, interval, the held-out set
it was measured on, the command that measured it, device, date, source).

* ``names(kind=None)``: the preset names (of one kind);
* ``get(name)``: the :class:`Preset` record (``.name .kind .description .provenance .figures .values``);
* ``load(name, **kw)``: the parameter object. A crawl preset gives a ``CrawlParams`` (``kw``: more
  ``CrawlParams.make`` settings, e.g. ``forward_velocity``), or a per-leg set
  (:class:`hyqjax.crawl.scheduled.PerLegCrawlParams`) when its values are per swing leg; both run wherever a
  crawl runs (``hyqjax stepdown``, ``hyqjax sweep``, the reach map, renders, the library). A bounding preset
  gives a ``BoundingParams`` (``kw``: the command and switches of
  :func:`hyqjax.bounding.params.paper_params`, e.g. ``speed=0.5, yaw_rate=0.3``).

Values of a crawl preset (``values``): ``crawl`` (``CrawlParams.make`` settings), ``reflex`` (``ReflexParams``
fields, over Table I) and optionally ``per_leg`` (``{field: {LF: v, RF: v, LH: v, RH: v}}``, ``reflex.<field>``
for a reflex field). Values of a bounding preset: ``amplitudes`` (``a_fz, a_hz, a_fx, a_hx``, N per leg) and
``gains`` (``BoundingGains`` fields) over the paper's stored limit cycle; empty for the paper's own gains.

Refusals are one line (a :class:`PresetError`, a ``ValueError``): an unknown name (naming the known ones), a
preset of the other kind (:func:`check_kind`), a stored value outside its declared range (naming the field).
Reading a preset imports JAX's parameter classes only, never MJX.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import os

FORMAT = "hyqjax.presets/1"
KINDS = ("crawl", "bound")
_DIR = os.path.dirname(os.path.abspath(__file__))


class PresetError(ValueError):
    """A preset name, kind or stored value that cannot be used; the message is one line."""


@dataclasses.dataclass(frozen=True)
class Preset:
    """One registry entry (module docstring). ``figures``: a tuple of dicts with ``what``, ``value``, ``unit``,
    ``interval`` (or None), ``heldout`` (the set it was measured on), ``command``, ``device``, ``date``,
    ``source``."""

    name: str
    kind: str
    description: str
    values: dict
    provenance: dict
    figures: tuple
    aliases: tuple = ()

    @property
    def per_leg(self) -> bool:
        return bool(self.values.get("per_leg"))

    def headline(self) -> str:
        """The first figure as ``what: value unit [interval]`` (empty without figures)."""
        return format_figure(self.figures[0]) if self.figures else ""


def format_figure(f: dict) -> str:
    v = f["value"]
    unit = f.get("unit") or ""
    val = f"{v:g}" if isinstance(v, (int, float)) else str(v)
    val = f"{val} {unit}".strip() if unit not in ("", "share") else val
    iv = f.get("interval")
    ivs = f" [{iv[0]:g}, {iv[1]:g}]" if iv else ""
    return f"{f['what']}: {val}{ivs}"


@functools.lru_cache(maxsize=1)
def _registry() -> dict:
    out = {}
    for fn in sorted(os.listdir(_DIR)):
        if not fn.endswith(".json"):
            continue
        with open(os.path.join(_DIR, fn)) as f:
            d = json.load(f)
        if d.get("format") != FORMAT or d.get("kind") not in KINDS or d.get("name") != fn[:-5]:
            raise PresetError(f"{fn}: not a preset file of format {FORMAT} named after its file")
        for fig in d.get("figures", ()):
            if not fig.get("command"):
                raise PresetError(f"{fn}: figure {fig.get('what')!r} has no command")
        out[d["name"]] = Preset(d["name"], d["kind"], d["description"], d.get("values", {}), d.get("provenance", {}),
                                tuple(d.get("figures", ())), tuple(d.get("aliases", ())))
    return out


def names(kind: str | None = None) -> list[str]:
    """The preset names (of ``kind``: ``crawl`` or ``bound``), in the registry's order (paper's sets first)."""
    if kind is not None and kind not in KINDS:
        raise PresetError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    reg = _registry()
    order = [n for n in ORDER if n in reg] + sorted(n for n in reg if n not in ORDER)
    return [n for n in order if kind is None or reg[n].kind == kind]


#: Listing order: the paper's sets, then what beats them.
ORDER = ("paper", "remedy", "reach", "tuned_shared", "tuned_per_leg", "bound_paper", "bound_robust",
         "bound_robust_grad")


def get(name: str, option: str = "preset") -> Preset:
    """The :class:`Preset` named ``name``; a one-line :class:`PresetError` naming the known ones otherwise."""
    reg = _registry()
    if name not in reg:
        raise PresetError(f"{option} must be one of {', '.join(names())}, got {name!r}")
    return reg[name]


def check_kind(name: str, kind: str, option: str = "--preset") -> Preset:
    """:func:`get`, refusing a preset of another kind (one line naming the presets of ``kind``)."""
    known = names(kind)
    reg = _registry()
    if name in reg and reg[name].kind != kind:
        raise PresetError(f"{option} {name} is a {reg[name].kind} preset; this command takes a {kind} preset: "
                          f"{', '.join(known)}")
    if name not in reg:
        raise PresetError(f"{option} must be one of {', '.join(known)}, got {name!r}")
    return reg[name]


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


def crawl_settings(name: str) -> dict:
    """The ``CrawlParams.make`` settings of crawl preset ``name`` (``values.crawl``)."""
    return dict(check_kind(name, "crawl", "preset").values.get("crawl", {}))


def describe(p: Preset) -> str:
    """A multi-line description: kind, description, values, provenance, figures (``hyqjax presets NAME``)."""
    lines = [f"{p.name} ({p.kind} preset): {p.description}"]
    if p.aliases:
        lines.append(f"  also: {', '.join(p.aliases)}")
    v = p.values
    if p.kind == "crawl":
        lines.append("  values: " + (_kv(v.get("crawl", {})) or "CrawlParams.make() defaults"))
        if v.get("reflex"):
            lines.append("  reflex: " + _kv(v["reflex"]))
        for field, legs in (v.get("per_leg") or {}).items():
            lines.append(f"  per leg {field}: " + ", ".join(f"{leg} {x:.6g}" for leg, x in legs.items()))
    else:
        lines.append("  amplitudes: " + (_kv(v.get("amplitudes", {})) or "the stored limit cycle's"))
        lines.append("  gains: " + (_kv(v.get("gains", {})) or "the paper's (bounding.params.DEFAULT_GAINS)"))
    lines.append("  provenance:")
    for k, x in p.provenance.items():
        lines.append(f"    {k}: {x}")
    lines.append("  figures:")
    for f in p.figures:
        lines.append(f"    {format_figure(f)}")
        lines.append(f"      held-out set: {f.get('heldout', '')}")
        lines.append(f"      measured on: {f.get('device', '')}, {f.get('date', '')}; source: {f.get('source', '')}")
        lines.append(f"      command: {f['command']}")
    return "\n".join(lines)


def _kv(d: dict) -> str:
    return ", ".join(f"{k}={x:.6g}" if isinstance(x, float) else f"{k}={x}" for k, x in d.items())
