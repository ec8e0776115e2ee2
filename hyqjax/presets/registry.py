"""The preset registry's files and records (no parameter classes imported: any module may read it).

:mod:`hyqjax.presets` builds the parameter objects; this module reads ``<name>.json`` beside it (format
:data:`FORMAT`, the shipped presets) and the user's own preset files of the same format in :func:`user_dir`
(``$HYQJAX_PRESETS_DIR``, else ``$XDG_DATA_HOME/hyqjax/presets``, else ``~/.local/share/hyqjax/presets``) into
:class:`Preset` records, and refuses unknown names and kinds in one line. A user file that cannot be used (not
JSON, not a preset of this format named after its file, a name that is not allowed or is a shipped preset's) is
left out of :func:`names` and named in one line by :func:`user_problems` and by :func:`get` of its name; the
shipped presets and the user's other files still work.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import re

FORMAT = "hyqjax.presets/1"
KINDS = ("crawl", "bound")
_DIR = os.path.dirname(os.path.abspath(__file__))


#: A user preset's name: a lowercase letter, then lowercase letters, digits, ``_`` or ``-`` (64 at most).
NAME_RE = re.compile(r"[a-z][a-z0-9_-]{0,63}")
NAME_RULE = "a lowercase letter, then lowercase letters, digits, '_' or '-' (64 characters at most)"
#: Names a user preset may not take besides the shipped presets': the old names of shipped bounding sets
#: (:data:`BOUND_ALIASES`) and the word of ``hyqjax presets save``.
RESERVED = ("save", "none", "robust", "robust_8s")
#: The environment variable naming the user's preset directory.
ENV_DIR = "HYQJAX_PRESETS_DIR"


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
    #: the user's preset directory the preset was read from; empty for a preset shipped with hyqjax
    user_dir: str = ""

    @property
    def user(self) -> bool:
        return bool(self.user_dir)

    @property
    def path(self) -> str:
        """The preset's file."""
        return os.path.join(self.user_dir or _DIR, f"{self.name}.json")

    @property
    def digest(self) -> str:
        """:func:`values_digest` of the preset's values."""
        return values_digest(self.values)

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


def values_digest(values: dict) -> str:
    """SHA-256 of the canonical JSON of a preset's ``values`` (sorted keys, no spaces): what a sweep store records
    of its spec's preset, so that a resume after the values changed is refused."""
    text = json.dumps(values, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def _record(d, fn: str, user_dir: str = "") -> Preset:
    """The :class:`Preset` of the parsed file ``fn``; a one-line :class:`PresetError` when it is not one."""
    if not isinstance(d, dict) or d.get("format") != FORMAT or d.get("kind") not in KINDS or d.get("name") != fn[:-5]:
        raise PresetError(f"{fn}: not a preset file of format {FORMAT} named after its file")
    if not isinstance(d.get("values", {}), dict) or not isinstance(d.get("provenance", {}), dict) \
            or not isinstance(d.get("figures", []), list) or not isinstance(d.get("description", ""), str):
        raise PresetError(f"{fn}: its values, provenance, figures or description are not of format {FORMAT}")
    bad = [k for k in ("crawl", "reflex", "per_leg", "conditioned", "amplitudes", "gains")
           if not isinstance(d.get("values", {}).get(k) or {}, dict)]
    if bad:
        raise PresetError(f"{fn}: values.{bad[0]} is not a table of format {FORMAT}")
    for fig in d.get("figures", ()):
        if not isinstance(fig, dict) or not fig.get("command"):
            raise PresetError(f"{fn}: figure {fig.get('what') if isinstance(fig, dict) else fig!r} has no command")
    return Preset(d["name"], d["kind"], d.get("description", ""), d.get("values", {}), d.get("provenance", {}),
                  tuple(d.get("figures", ())), tuple(d.get("aliases", ())) if not user_dir else (), user_dir)


@functools.lru_cache(maxsize=1)
def _shipped() -> dict:
    out = {}
    for fn in sorted(os.listdir(_DIR)):
        if not fn.endswith(".json"):
            continue
        with open(os.path.join(_DIR, fn)) as f:
            d = json.load(f)
        out[fn[:-5]] = _record(d, fn)
    return out


def user_dir() -> str:
    """The directory of the user's own presets: ``$HYQJAX_PRESETS_DIR``, else ``$XDG_DATA_HOME/hyqjax/presets``,
    else ``~/.local/share/hyqjax/presets`` (absolute; it need not exist)."""
    d = os.environ.get(ENV_DIR)
    if not d:
        base = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
        d = os.path.join(base, "hyqjax", "presets")
    return os.path.abspath(os.path.expanduser(d))


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot name a user preset (one line), or None: the allowed spelling (:data:`NAME_RULE`), not a
    shipped preset's name nor a reserved word (:data:`RESERVED`)."""
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        return f"a preset name is {NAME_RULE}, got {name!r}"
    if name in _shipped():
        return (f"{name} is the name of the shipped preset {name} ({os.path.join(_DIR, name + '.json')}); give "
                f"your preset another name")
    if name in RESERVED:
        return f"{name} is reserved ({', '.join(RESERVED)}); give your preset another name"
    return None


def _signature(d: str) -> tuple:
    try:
        entries = sorted(os.scandir(d), key=lambda e: e.name)
    except (FileNotFoundError, NotADirectoryError):
        return ()
    except OSError as e:
        return (("", str(e), 0),)
    out = []
    for e in entries:
        if e.name.endswith(".json") and not e.name.startswith("."):
            try:
                st = e.stat()
                out.append((e.name, st.st_mtime_ns, st.st_size))
            except OSError:
                continue
    return tuple(out)


@functools.lru_cache(maxsize=8)
def _read_user(d: str, signature: tuple) -> tuple[dict, dict]:
    presets, problems = {}, {}
    if signature and signature[0][0] == "":
        problems[""] = f"user presets directory {d} cannot be read ({signature[0][1]})"
        return presets, problems
    for fn, _, _ in signature:
        stem, path = fn[:-5], os.path.join(d, fn)
        why = name_problem(stem)
        if why and stem in _shipped():
            problems[stem] = (f"user preset file {path} is not used: its name is the shipped preset {stem}'s "
                              f"({os.path.join(_DIR, fn)}); rename it")
            continue
        if why:
            problems[stem] = f"user preset file {path} is not used: {why}"
            continue
        try:
            with open(path, "rb") as f:
                d_ = json.loads(f.read().decode("utf-8"))
            presets[stem] = _record(d_, fn, d)
        except (OSError, ValueError, UnicodeDecodeError) as e:
            what = str(e).splitlines()[0][:160] if str(e) else type(e).__name__
            problems[stem] = f"user preset file {path} is not used: {what}; fix or remove it"
    return presets, problems


def _user() -> tuple[dict, dict]:
    """``({name: Preset}, {name: problem line})`` of the user's preset directory, read again when its files
    change."""
    d = user_dir()
    return _read_user(d, _signature(d))


def user_problems() -> list[str]:
    """One line per file of the user's preset directory that is not used (module docstring)."""
    return [line for _, line in sorted(_user()[1].items())]


def user_problem(name: str) -> str | None:
    """The one-line problem of the user's preset file ``NAME.json`` when it is not used, else None."""
    return _user()[1].get(name)


def _registry() -> dict:
    """``{name: Preset}``: the shipped presets, then the user's usable ones."""
    reg = dict(_shipped())
    for n, p in _user()[0].items():
        reg.setdefault(n, p)
    return reg


def names(kind: str | None = None, user: bool = True) -> list[str]:
    """The preset names (of ``kind``: ``crawl`` or ``bound``), in the registry's order (paper's sets first), then
    the user's own (sorted; none with ``user=False``)."""
    if kind is not None and kind not in KINDS:
        raise PresetError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    reg = _registry()
    shipped = [n for n in reg if not reg[n].user_dir]
    order = ([n for n in ORDER if n in shipped] + sorted(n for n in shipped if n not in ORDER)
             + (sorted(n for n in reg if reg[n].user_dir) if user else []))
    return [n for n in order if kind is None or reg[n].kind == kind]


#: The old names of the shipped bounding sets (``--params robust_8s``, ``hyqjax.bounding.robust.load_params("robust")``):
#: aliases of bounding presets.
BOUND_ALIASES = {"robust": "bound_robust_grad", "robust_8s": "bound_robust_8s"}

#: The names (``what``) of the confirmation map's figures that ``hyqjax stepdown``'s summary quotes: clean success
#: pooled up to 26 cm and completed step-downs at 29 cm (written by experiments/build_presets.py).
FIGURE_CLEAN = "clean success up to 26 cm, held-out step-downs (confirmation map)"
FIGURE_TALL = "completed step-downs at 29 cm (confirmation map)"

#: Listing order: the paper's sets, then what beats them.
ORDER = ("paper", "remedy", "reach", "clean", "clean_refined", "tuned_shared", "tuned_per_leg", "tuned_per_leg_reach",
         "tuned_per_leg_cond", "bound_paper", "bound_robust", "bound_robust_8s", "bound_robust_grad")


def get(name: str, option: str = "preset") -> Preset:
    """The :class:`Preset` named ``name``; a one-line :class:`PresetError` naming the known ones otherwise."""
    reg = _registry()
    if name not in reg:
        _refuse_unusable(name)
        raise PresetError(f"{option} must be one of {', '.join(names())}, got {name!r}")
    return reg[name]


def _refuse_unusable(name) -> None:
    """A user preset file of ``name`` that is not used: its one-line problem as a :class:`PresetError`."""
    why = user_problem(name) if isinstance(name, str) else None
    if why:
        raise PresetError(why)


def check_kind(name: str, kind: str, option: str = "--preset") -> Preset:
    """:func:`get`, refusing a preset of another kind (one line naming the presets of ``kind``)."""
    known = names(kind)
    reg = _registry()
    if name in reg and reg[name].kind != kind:
        raise PresetError(f"{option} {name} is a {reg[name].kind} preset; this command takes a {kind} preset: "
                          f"{', '.join(known)}")
    if name not in reg:
        _refuse_unusable(name)
        raise PresetError(f"{option} must be one of {', '.join(known)}, got {name!r}")
    return reg[name]


def crawl_settings(name: str) -> dict:
    """The ``CrawlParams.make`` settings of crawl preset ``name`` (``values.crawl``)."""
    return dict(check_kind(name, "crawl", "preset").values.get("crawl", {}))


def describe(p: Preset) -> str:
    """A multi-line description: kind, description, values, provenance, figures (``hyqjax presets NAME``)."""
    lines = [f"{p.name} ({p.kind} preset{', yours: ' + p.path if p.user_dir else ''}): {p.description}"]
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
