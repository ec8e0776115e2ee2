"""Expectations on a sweep's outcome rates: ``"clean >= 0.85"``, ``"completed >= 0.95 where height <= 0.21"``.

An expectation names a *metric* (the rate of an outcome over the instances it covers), a comparison and a value
in ``[0, 1]``, optionally a *filter* (``where AXIS OP VALUE [and AXIS OP VALUE ...]`` over the sweep's axes) and
``per cell`` (the rate of each grid cell that the filter selects, each cell its own check, instead of the pooled
rate)::

    clean >= 0.85
    completed >= 0.95 where height <= 0.21
    clean > 0.5 where reflex == on and height == 0.16
    diverged <= 0.01
    clean >= 0.6 per cell where reflex == on

Metrics (:data:`METRICS`): ``completed`` and ``clean`` (the two outcome levels; ``success`` is ``clean`` under the
name older results use), ``diverged`` and ``terminated`` (the rates of simulator blow-ups and of runs that fell).
Comparisons: ``>=``, ``>``, ``<=``, ``<``. Filter comparisons: ``==`` (or ``=``), ``!=``, ``<=``, ``<``, ``>=``,
``>``; a bool axis (``reflex``) takes ``on``/``off``/``true``/``false`` with ``==``/``!=`` only, a choice axis
(``foot_sequence``) one of its options.

A check is decided on the Wilson interval of the rate (:func:`hyqjax.studies.statistics.wilson_interval`, 95% by
default): for ``>=`` it **passes** when the interval's lower bound is at least the value, **fails** when the whole
interval lies below it (upper bound below the value) and is **inconclusive** when the interval straddles the
value (more instances would decide it); ``>`` is the same with strict bounds, ``<=`` and ``<`` the mirror image.
A check over no instance (the filter selects none) fails: a gate never passes on nothing.

:func:`parse` refuses a bad expectation with a :class:`~hyqjax.studies.sweep.axes.SpecError` naming what is wrong
and what is allowed (an unknown metric or axis, a bad comparison, a value outside ``[0, 1]`` or outside the axis'
range); :func:`check_selects` refuses a filter that selects no instance of a given spec. Both run before anything
is simulated. :func:`evaluate` gives one :class:`Check` per expectation (per cell with ``per cell``).
"""
from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

from hyqjax.studies.sweep.axes import AXES, SpecError

#: Metric -> the row column whose mean is its rate (``success`` is ``clean`` under the name older results use).
METRICS = {"completed": "completed", "clean": "success", "success": "success", "diverged": "diverged",
           "terminated": "terminated"}
#: Comparisons of a metric with its value.
RATE_OPS = (">=", "<=", ">", "<")
#: Comparisons of an axis with a value in a filter (``=`` is ``==``).
FILTER_OPS = ("==", "!=", ">=", "<=", ">", "<", "=")
#: The outcomes of a check, best first.
STATUSES = ("pass", "inconclusive", "fail")

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_HEAD = re.compile(r"^\s*(?P<metric>[A-Za-z_][A-Za-z0-9_]*)\s*(?P<op>[<>=!]+)\s*(?P<value>\S+)\s*(?P<rest>.*)$")
_COND = re.compile(r"^\s*(?P<axis>[A-Za-z_][A-Za-z0-9_]*)\s*(?P<op>[<>=!]+)\s*(?P<value>\S+)\s*$")


@dataclasses.dataclass(frozen=True)
class Condition:
    """``axis op value`` of a filter (value normalised as the axis' values are)."""

    axis: str
    op: str
    value: object

    def mask(self, rows: dict) -> np.ndarray:
        col = np.asarray(rows[self.axis])
        v = self.value
        if AXES[self.axis].kind == "float":
            col = col.astype(np.float64)
            # Grid values are stored as given; a filter value written with fewer digits still matches.
            eq = np.isclose(col, float(v), rtol=0.0, atol=1e-9)
            return {"==": eq, "!=": ~eq, ">=": (col >= v) | eq, "<=": (col <= v) | eq, ">": (col > v) & ~eq,
                    "<": (col < v) & ~eq}[self.op]
        eq = col.astype(type(v)) == v if AXES[self.axis].kind == "bool" else col.astype(str) == str(v)
        return eq if self.op == "==" else ~eq

    def text(self) -> str:
        v = ("on" if self.value else "off") if isinstance(self.value, bool) else (
            f"{self.value:g}" if isinstance(self.value, float) else self.value)
        return f"{self.axis} {self.op} {v}"


@dataclasses.dataclass(frozen=True)
class Expectation:
    """A parsed expectation (module docstring)."""

    metric: str
    op: str
    value: float
    where: tuple[Condition, ...] = ()
    per_cell: bool = False
    source: str = ""

    def text(self) -> str:
        """The canonical form (``parse(e.text()) == e`` up to ``source``)."""
        s = f"{self.metric} {self.op} {self.value:g}"
        if self.per_cell:
            s += " per cell"
        if self.where:
            s += " where " + " and ".join(c.text() for c in self.where)
        return s

    def mask(self, rows: dict) -> np.ndarray:
        m = np.ones(len(rows["index"]), bool)
        for c in self.where:
            m &= c.mask(rows)
        return m

    def decide(self, lo: float, hi: float) -> str:
        """``pass`` / ``fail`` / ``inconclusive`` of a rate with Wilson interval ``[lo, hi]``."""
        v = self.value
        if self.op == ">=":
            return "pass" if lo >= v else ("fail" if hi < v else "inconclusive")
        if self.op == ">":
            return "pass" if lo > v else ("fail" if hi <= v else "inconclusive")
        if self.op == "<=":
            return "pass" if hi <= v else ("fail" if lo > v else "inconclusive")
        return "pass" if hi < v else ("fail" if lo >= v else "inconclusive")


@dataclasses.dataclass(frozen=True)
class Check:
    """One decided check: an expectation over the instances it covers (one cell of a ``per cell`` one)."""

    expectation: str
    cell: str  # "" for a pooled check, else the grid cell ("height=0.16, reflex=on")
    metric: str
    op: str
    value: float
    n: int
    k: int
    rate: float | None
    ci: tuple[float, float] | None
    status: str
    note: str = ""

    @property
    def name(self) -> str:
        return self.expectation + (f" [{self.cell}]" if self.cell else "")

    def text(self) -> str:
        if self.n == 0:
            return f"{self.status.upper()}: {self.name}: no instance ({self.note})"
        return (f"{self.status.upper()}: {self.name}: {self.metric} {self.k}/{self.n} = {self.rate:.3f}, "
                f"Wilson 95% [{self.ci[0]:.3f}, {self.ci[1]:.3f}]" + (f" ({self.note})" if self.note else ""))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["ci"] = None if self.ci is None else list(self.ci)
        d["name"] = self.name
        return d


def _filter_value(axis: str, op: str, raw: str, where: str):
    a = AXES[axis]
    if a.kind == "bool":
        if op not in ("==", "!="):
            raise SpecError(f"{where}: {axis} is on/off: compare it with == or != (e.g. '{axis} == on'), not {op!r}")
        low = raw.lower()
        if low not in ("on", "off", "true", "false"):
            raise SpecError(f"{where}: {axis} must be on/off/true/false, got {raw!r}")
        return low in ("on", "true")
    if a.kind == "choice":
        if op not in ("==", "!="):
            raise SpecError(f"{where}: {axis} is one of {list(a.options)}: compare it with == or !=, not {op!r}")
        if raw not in a.options:
            raise SpecError(f"{where}: {axis} must be one of {list(a.options)}, got {raw!r}")
        return raw
    if not re.fullmatch(_NUM, raw):
        raise SpecError(f"{where}: {axis} must be compared with a number in {a.range_text}, got {raw!r}")
    v = float(raw)
    if not (math.isfinite(v) and a.lo <= v <= a.hi):
        raise SpecError(f"{where}: {axis}={raw} out of range: must be in {a.range_text}")
    return v


def parse(text: str, where: str = "--expect") -> Expectation:
    """Parse one expectation (module docstring); a :class:`SpecError` naming ``where``, the expectation and what is
    allowed otherwise."""
    if not isinstance(text, str) or not text.strip():
        raise SpecError(f"{where}: an expectation is a string like 'clean >= 0.85 [where height <= 0.21]', "
                        f"got {text!r}")
    w = f"{where} {text.strip()!r}"
    m = _HEAD.match(text)
    if not m:
        raise SpecError(f"{w}: expected 'METRIC OP VALUE [per cell] [where AXIS OP VALUE [and ...]]' with METRIC one "
                        f"of {sorted(METRICS)} and OP one of {list(RATE_OPS)}")
    metric, op, raw, rest = m["metric"], m["op"], m["value"], m["rest"].strip()
    if metric not in METRICS:
        raise SpecError(f"{w}: unknown metric {metric!r}; allowed: {sorted(METRICS)}")
    if op not in RATE_OPS:
        raise SpecError(f"{w}: bad comparison {op!r}; allowed: {list(RATE_OPS)}")
    if not re.fullmatch(_NUM, raw):
        raise SpecError(f"{w}: {metric} is a rate: compare it with a number in [0, 1], got {raw!r}")
    value = float(raw)
    if not 0.0 <= value <= 1.0:
        raise SpecError(f"{w}: value {raw} outside [0, 1] ({metric} is a rate; 85% is 0.85)")
    per_cell = False
    low = rest.lower()
    if low.startswith("per cell"):
        per_cell, rest = True, rest[len("per cell"):].strip()
        low = rest.lower()
    conds = []
    if rest:
        if not low.startswith("where "):
            raise SpecError(f"{w}: unexpected {rest!r} after the value; a filter is 'where AXIS OP VALUE [and ...]'")
        for part in re.split(r"\s+and\s+", rest[len("where "):].strip(), flags=re.IGNORECASE):
            c = _COND.match(part)
            if not c:
                raise SpecError(f"{w}: bad filter condition {part!r}; expected 'AXIS OP VALUE' with OP one of "
                                f"{list(FILTER_OPS[:-1])}")
            axis, cop = c["axis"], c["op"]
            if axis not in AXES:
                raise SpecError(f"{w}: unknown axis {axis!r}; allowed axes: {sorted(AXES)}")
            if cop not in FILTER_OPS:
                raise SpecError(f"{w}: bad comparison {cop!r} in the filter; allowed: {list(FILTER_OPS[:-1])}")
            cop = "==" if cop == "=" else cop
            conds.append(Condition(axis, cop, _filter_value(axis, cop, c["value"], w)))
    return Expectation(metric, op, value, tuple(conds), per_cell, text.strip())


#: :func:`parse` under the name the package exports (``sweep.parse_expectation``).
parse_expectation = parse


def parse_all(texts, where: str = "--expect") -> list[Expectation]:
    return [parse(t, where) for t in texts]


def split_spec_dict(d: dict, where: str = "SPEC") -> tuple[dict, list[Expectation]]:
    """A spec table without its ``expect`` list, and that list parsed. The list is not part of the sweep (its hash
    does not cover it): changing an expectation never invalidates a store."""
    d = dict(d)
    raw = d.pop("expect", [])
    if isinstance(raw, str):
        raw = [raw]
    if not isinstance(raw, list) or not all(isinstance(t, str) for t in raw):
        raise SpecError(f"{where}: expect must be a list of strings like 'clean >= 0.85', got {raw!r}")
    return d, parse_all(raw, f"{where} expect")


def check_selects(exps, spec, limit: int = 1_000_000) -> None:
    """Refuse (:class:`SpecError`) an expectation whose filter selects no instance of ``spec`` (instance inputs
    are computed without simulating; skipped above ``limit`` instances) or whose metric the sweep cannot give."""
    if not exps or spec.n_instances > limit:
        return
    rows = spec.instance_inputs(0, spec.n_instances)
    for e in exps:
        if e.where and not e.mask(rows).any():
            vals = {c.axis: sorted({float(x) if AXES[c.axis].kind == "float" else str(x)
                                     for x in np.unique(rows[c.axis])})[:8] for c in e.where}
            raise SpecError(f"--expect {e.source!r}: the filter selects no instance of this sweep (its values: "
                            + "; ".join(f"{k} in {v}" for k, v in vals.items()) + ")")


def cell_label(spec, rows, i: int) -> str:
    parts = []
    for k, _ in spec.grid:
        v = rows[k][i]
        parts.append(f"{k}=" + (("on" if v else "off") if AXES[k].kind == "bool" else
                                (f"{float(v):g}" if AXES[k].kind == "float" else str(v))))
    return ", ".join(parts) or "all"


def _one(e: Expectation, rows: dict, m: np.ndarray, cell: str, confidence: float) -> Check:
    from hyqjax.studies.statistics import wilson_interval

    col = METRICS[e.metric]
    n = int(m.sum())
    if col not in rows:
        return Check(e.text(), cell, e.metric, e.op, e.value, 0, 0, None, None, "fail",
                     f"these rows have no {col!r} column (written by an earlier hyqjax)")
    if n == 0:
        return Check(e.text(), cell, e.metric, e.op, e.value, 0, 0, None, None, "fail",
                     "the filter selects no stored instance")
    k = int(np.asarray(rows[col], bool)[m].sum())
    lo, hi = wilson_interval(k, n, confidence)
    return Check(e.text(), cell, e.metric, e.op, e.value, n, k, k / n, (lo, hi), e.decide(lo, hi))


def evaluate(exps, spec, rows: dict, confidence: float = 0.95) -> list[Check]:
    """One :class:`Check` per expectation (per selected grid cell with ``per cell``) on the stored ``rows``."""
    out = []
    for e in exps:
        m = e.mask(rows) if len(rows.get("index", ())) else np.zeros(0, bool)
        if not e.per_cell:
            out.append(_one(e, rows, m, "", confidence))
            continue
        g = np.asarray(rows["grid_index"])
        cells = sorted(set(g[m].tolist()))
        if not cells:
            out.append(_one(e, rows, m, "", confidence))
        for c in cells:
            mc = m & (g == c)
            out.append(_one(e, rows, mc, cell_label(spec, rows, int(np.argmax(mc))), confidence))
    return out


def exit_status(checks, inconclusive: str = "report") -> int:
    """0 every check passed, 1 one failed (or one is inconclusive and ``inconclusive == "fail"``), 3 one is
    inconclusive and none failed (``inconclusive == "report"``; ``"pass"`` counts it as passed)."""
    st = {c.status for c in checks}
    if "fail" in st or ("inconclusive" in st and inconclusive == "fail"):
        return 1
    if "inconclusive" in st and inconclusive == "report":
        return 3
    return 0


__all__ = ["Check", "Condition", "Expectation", "METRICS", "cell_label", "check_selects", "evaluate", "exit_status",
           "parse", "parse_all", "parse_expectation", "split_spec_dict"]
