"""The preset registry's files and records (no parameter classes imported: any module may read it).

:mod:`hyqjax.presets` builds the parameter objects; this module reads ``<name>.json`` beside it (format
:data:`FORMAT`) into :class:`Preset` records and refuses unknown names and kinds in one line.
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
        return bool(self.values.get("per_leg") or self.values.get("conditioned"))

    @property
    def scheduled_fields(self) -> tuple[str, ...]:
        """The fields the preset chooses per swing leg (or per tick), ``reflex.<name>`` for a reflex field."""
        return tuple(self.values.get("per_leg") or ()) + tuple((self.values.get("conditioned") or {}).get("fields", ()))

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


#: The old names of the shipped bounding sets (``--params robust_8s``, ``hyqjax.bounding.robust.load_params("robust")``):
#: aliases of bounding presets.
BOUND_ALIASES = {"robust": "bound_robust_grad", "robust_8s": "bound_robust_8s"}

#: Listing order: the paper's sets, then what beats them.
ORDER = ("paper", "remedy", "reach", "clean", "tuned_shared", "tuned_per_leg", "tuned_per_leg_reach", "tuned_per_leg_cond",
         "bound_paper", "bound_robust", "bound_robust_8s", "bound_robust_grad")


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
        if v.get("conditioned"):
            c = v["conditioned"]
            lines.append(f"  conditioned ({c['parameterisation']}, {len(c['theta'])} coordinates): "
                         + _kv(c.get("values", {})))
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
