"""Compare two sweep stores of the same spec: did the robot get worse (``hyqjax compare BASE NEW``)?

Per grid cell and outcome level (``completed``, ``clean``), and pooled over all cells, the difference of the
rates ``NEW - BASE`` with **Newcombe's hybrid score interval** (Newcombe 1998, method 10: from the two Wilson
intervals; for paired outcomes it is conservative, i.e. wider than a paired interval) and a test:

* **paired** (the usual case): the same spec and seed give the same instances in both stores (common random
  numbers). That is checked, not assumed: every input column stored in the rows (grid values, random draws,
  instance seeds, terrain blocks) must be equal, instance by instance. The test is **McNemar's exact test** on
  the discordant pairs: ``b`` instances that pass in BASE and fail in NEW, ``c`` the reverse, two-sided
  ``p = min(1, 2 P(X <= min(b, c)))`` with ``X ~ Binomial(b + c, 1/2)`` (``p = 1`` when ``b + c = 0``). An
  unchanged controller gives identical outcomes (``b = c = 0``), so it is never flagged.
* **unpaired** (``allow_change=("seed",)``: two different samples of the same grid): Fisher's exact test.

The p-values of every test (each cell x level, and the pooled test of each level) are corrected together with
**Holm's step-down method**, which bounds the probability of *any* false alarm (the family-wise error rate) by
``alpha`` (0.05). That is the property a CI gate needs: a false alarm fails a build. (Benjamini-Hochberg bounds
only the expected share of false discoveries among the flagged cells, so with several cells it would fail
unchanged builds more often than ``alpha``.) A test whose Holm-adjusted p-value is below ``alpha`` is
``regressed`` (NEW lower) or ``improved`` (NEW higher); otherwise ``no significant change``. A cell is regressed
when one of its levels is, improved when one is and none regressed; the overall verdict likewise over all tests.

Refused (:class:`~hyqjax.studies.sweep.manifest.StoreMismatch`, naming the difference): stores of different specs
(other grid, random ranges, samples, duration, seed, fixed values; ``allow_change`` names [fixed] axes, or
``seed``, whose change is the point of the comparison), of different schemas, or whose rows have different columns
(computed by hyqjax versions with different outcome definitions); a store with a damaged chunk or a missing
manifest (:func:`hyqjax.studies.sweep.verify.verify_store`'s lines name the chunks) and an incomplete store. Stores
computed on different simulators or device layouts are compared, with a note: their outcomes differ by float
rounding.
"""
from __future__ import annotations

import dataclasses
import math
import os

import numpy as np

from hyqjax.studies.sweep.axes import AXES
from hyqjax.studies.sweep.manifest import StoreCorrupt, StoreMismatch

LEVEL_COLUMNS = {"completed": "completed", "clean": "success"}
VERDICTS = ("regressed", "improved", "no significant change")
#: Spec keys other than the axis sections; ``seed`` may be allowed to change (an unpaired comparison).
_SCALARS = ("samples", "seed", "paired", "duration", "control_dt", "max_tilt", "min_progress", "blocks")


# ---------------------------------------------------------------- statistics
def newcombe_interval(k_new: int, n_new: int, k_base: int, n_base: int,
                      confidence: float = 0.95) -> tuple[float, float]:
    """Newcombe's hybrid score interval (method 10) of ``k_new / n_new - k_base / n_base``."""
    from hyqjax.studies.statistics import wilson_interval

    if n_new == 0 or n_base == 0:
        return (float("nan"), float("nan"))
    p1, p2 = k_new / n_new, k_base / n_base
    l1, u1 = wilson_interval(k_new, n_new, confidence)
    l2, u2 = wilson_interval(k_base, n_base, confidence)
    d = p1 - p2
    return (max(-1.0, d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)),
            min(1.0, d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)))


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value of ``b`` and ``c`` discordant pairs."""
    from scipy.stats import binom

    n = int(b) + int(c)
    if n == 0:
        return 1.0
    return float(min(1.0, 2.0 * binom.cdf(min(b, c), n, 0.5)))


def fisher_exact(k_new: int, n_new: int, k_base: int, n_base: int) -> float:
    """Two-sided p-value of Fisher's exact test of two independent proportions."""
    from scipy.stats import fisher_exact as fe

    if n_new == 0 or n_base == 0:
        return 1.0
    return float(fe([[k_new, n_new - k_new], [k_base, n_base - k_base]])[1])


def holm(pvalues) -> np.ndarray:
    """Holm-adjusted p-values (step-down; monotone, capped at 1)."""
    p = np.asarray(pvalues, np.float64)
    m = p.size
    order = np.argsort(p, kind="stable")
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj


# ---------------------------------------------------------------- results
@dataclasses.dataclass
class Test:
    """One rate compared: a cell's (or all cells') level."""

    cell: str
    level: str
    n_base: int
    n_new: int
    k_base: int
    k_new: int
    diff: float
    ci: tuple[float, float]
    test: str  # "mcnemar" or "fisher"
    p: float
    b: int | None = None  # paired: pass in BASE, fail in NEW
    c: int | None = None  # paired: fail in BASE, pass in NEW
    p_holm: float = 1.0
    verdict: str = "no significant change"

    @property
    def name(self) -> str:
        return f"{self.level} [{self.cell}]"

    def text(self) -> str:
        pair = f", discordant {self.b} worse / {self.c} better" if self.b is not None else ""
        return (f"{self.verdict.upper() if self.verdict != VERDICTS[2] else self.verdict}: {self.name}: "
                f"{self.k_base}/{self.n_base} -> {self.k_new}/{self.n_new}, difference {self.diff:+.3f} "
                f"[{self.ci[0]:+.3f}, {self.ci[1]:+.3f}]{pair}, {self.test} p = {self.p:.3g}, Holm {self.p_holm:.3g}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["ci"] = list(self.ci)
        d["name"] = self.name
        return d


@dataclasses.dataclass
class Comparison:
    """What :func:`compare_stores` found (module docstring)."""

    base: str
    new: str
    spec_hash: str
    paired: bool
    alpha: float
    tests: list[Test]
    cells: dict  # cell -> verdict
    verdict: str
    identical: bool  # every paired outcome column equal
    n_pairs: int
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def regressed(self) -> bool:
        return self.verdict == "regressed"

    def lines(self) -> list[str]:
        n_cells = len([c for c in self.cells if c != "all cells"])
        head = (f"compare {self.base} -> {self.new}: {self.verdict.upper()} ({n_cells} cells, "
                f"{'paired' if self.paired else 'unpaired'}, {self.n_pairs} instances"
                + (", identical outcomes" if self.identical else "") + f"; Holm over {len(self.tests)} tests, "
                f"alpha {self.alpha:g})")
        return [head] + [f"  {t.text()}" for t in self.tests] + [f"  note: {n}" for n in self.notes]

    def to_dict(self) -> dict:
        return dict(base=self.base, new=self.new, spec_hash=self.spec_hash, paired=self.paired, alpha=self.alpha,
                    verdict=self.verdict, identical=self.identical, n_pairs=self.n_pairs, cells=self.cells,
                    tests=[t.to_dict() for t in self.tests], notes=self.notes)


# ---------------------------------------------------------------- store checks
def _load(path: str, role: str):
    """The verified, complete store in ``path`` (its rows), or :class:`StoreMismatch` naming what is wrong."""
    from hyqjax.studies.sweep.store import open_store
    from hyqjax.studies.sweep.verify import is_sweep_dir, verify_store

    if not is_sweep_dir(path):
        raise StoreMismatch(f"{role} {path} holds no sweep (no manifest.json, no chunks/)")
    chk = verify_store(path)
    if not chk.ok:
        raise StoreMismatch(f"{role} {path} is damaged: " + "; ".join(line.strip() for line in chk.lines()))
    try:
        st = open_store(path)
    except StoreCorrupt as e:
        raise StoreMismatch(f"{role} {path}: {e}") from None
    if len(st.done()) != st.n_chunks:
        raise StoreMismatch(f"{role} {path} is incomplete ({len(st.done())} of {st.n_chunks} chunks): run its "
                            f"`hyqjax sweep` command again to finish it")
    return st, st.load()


def spec_differences(a: dict, b: dict) -> list[str]:
    """``key: BASE value vs NEW value`` of every difference of two canonical specs (``SweepSpec.to_dict``)."""
    out = []
    for k in _SCALARS:
        if a.get(k) != b.get(k):
            out.append(f"{k}: {a.get(k)!r} vs {b.get(k)!r}")
    for sec in ("grid", "random", "fixed"):
        sa, sb = a.get(sec, {}), b.get(sec, {})
        for ax in sorted(set(sa) | set(sb)):
            if sa.get(ax) != sb.get(ax):
                fa = "absent" if ax not in sa else repr(sa[ax])
                fb = "absent" if ax not in sb else repr(sb[ax])
                out.append(f"[{sec}] {ax}: {fa} vs {fb}")
    return out


def check_allow_change(names) -> tuple[str, ...]:
    """Validate ``allow_change`` names (each may be comma-separated): ``seed`` or an axis (changed in [fixed]);
    ValueError naming the bad one. Returns the names, one per entry."""
    names = [x.strip() for n in names for x in str(n).split(",") if x.strip()]
    for n in names:
        if n != "seed" and n not in AXES:
            raise ValueError(f"--allow-change {n!r}: must be 'seed' or an axis set in [fixed] (e.g. reflex_d_st_max; "
                             f"`hyqjax sweep --list-axes`)")
    return tuple(names)


def _check_compatible(sb, sn, allow_change) -> list[str]:
    """Refuse stores of different specs (beyond ``allow_change``), schemas or columns; notes on layouts."""
    mb, mn = sb.manifest, sn.manifest
    if mb.get("schema") != mn.get("schema"):
        raise StoreMismatch(f"BASE {sb.dir} has schema {mb.get('schema')!r}, NEW {sn.dir} {mn.get('schema')!r}: "
                            f"convert the older store (python -m hyqjax.studies.sweep.convert DIR) and run it again")
    da, dn = sb.spec.to_dict(), sn.spec.to_dict()
    diffs = spec_differences(da, dn)
    allowed = []
    for d in diffs:
        key = d.split(":", 1)[0]
        name = key.split("] ", 1)[1] if key.startswith("[") else key
        if name in allow_change and (key.startswith("[fixed]") or name == "seed"):
            allowed.append(d)
    bad = [d for d in diffs if d not in allowed]
    if bad:
        raise StoreMismatch(f"BASE {sb.dir} and NEW {sn.dir} are different sweeps (BASE vs NEW: " + "; ".join(bad)
                            + "); compare stores of the same spec (--allow-change AXIS for a [fixed] axis or seed "
                              "changed on purpose)")
    cb, cn = mb.get("columns"), mn.get("columns")
    if cb is not None and cn is not None and list(cb) != list(cn):
        only_b, only_n = sorted(set(cb) - set(cn)), sorted(set(cn) - set(cb))
        raise StoreMismatch(f"BASE {sb.dir} and NEW {sn.dir} were computed by hyqjax versions with different outcome "
                            f"columns (only in BASE: {only_b}, only in NEW: {only_n}): rerun the baseline with this "
                            f"version")
    notes = [f"changed on purpose (BASE vs NEW): {d}" for d in allowed]
    lb, ln = mb.get("layout") or {}, mn.get("layout") or {}
    keys = ("platform", "device_kind", "devices", "chunk_size", "impl")
    if any(lb.get(k) != ln.get(k) for k in keys):
        fmt = lambda lo: ", ".join(f"{k} {lo.get(k)}" for k in keys)  # noqa: E731
        notes.append(f"computed on different layouts (BASE: {fmt(lb)}; NEW: {fmt(ln)}): outcomes may differ by "
                     f"float rounding, which the test counts as change")
    return notes


def _input_columns(spec) -> list[str]:
    return sorted(spec.instance_inputs(0, min(1, spec.n_instances)).keys())


def _paired(spec, rb: dict, rn: dict, skip) -> tuple[bool, str]:
    """Whether every input column of the rows is equal instance by instance (``skip``: changed on purpose)."""
    if not np.array_equal(rb["index"], rn["index"]):
        return False, "the stores hold different instance indices"
    for k in _input_columns(spec):
        if k in skip or k not in rb or k not in rn:
            continue
        a, b = np.asarray(rb[k]), np.asarray(rn[k])
        if a.shape != b.shape or not np.array_equal(a, b):
            return False, f"input column {k!r} differs (other instances: tested unpaired)"
    return True, ""


def compare_stores(base: str, new: str, alpha: float = 0.05, allow_change=(), confidence: float = 0.95,
                   levels=("completed", "clean")) -> Comparison:
    """Compare the sweep stores ``base`` and ``new`` (module docstring)."""
    from hyqjax.studies.sweep.expect import cell_label

    sb, rb = _load(base, "BASE")
    sn, rn = _load(new, "NEW")
    notes = _check_compatible(sb, sn, tuple(allow_change))
    ob, on = np.argsort(rb["index"]), np.argsort(rn["index"])
    rb = {k: np.asarray(v)[ob] for k, v in rb.items()}
    rn = {k: np.asarray(v)[on] for k, v in rn.items()}
    skip = set(allow_change) - {"seed"}
    paired, why = _paired(sb.spec, rb, rn, skip)
    if not paired:
        notes.append(why)
    levels = [lv for lv in levels if LEVEL_COLUMNS[lv] in rb and LEVEL_COLUMNS[lv] in rn]
    gb, gn = np.asarray(rb["grid_index"]), np.asarray(rn["grid_index"])
    cells = sorted(set(gb.tolist()) | set(gn.tolist()))
    labels = {}
    for c in cells:
        rows, g = (rb, gb) if (gb == c).any() else (rn, gn)
        labels[c] = cell_label(sb.spec, rows, int(np.argmax(g == c)))
    tests = []
    identical = paired
    for lv in levels:
        yb, yn = np.asarray(rb[LEVEL_COLUMNS[lv]], bool), np.asarray(rn[LEVEL_COLUMNS[lv]], bool)
        if paired:
            identical &= bool(np.array_equal(yb, yn))
        groups = [(labels[c], gb == c, gn == c) for c in cells]
        if len(cells) > 1:
            groups.append(("all cells", np.ones(len(yb), bool), np.ones(len(yn), bool)))
        for label, mb_, mn_ in groups:
            kb, nb, kn, nn = int(yb[mb_].sum()), int(mb_.sum()), int(yn[mn_].sum()), int(mn_.sum())
            ci = newcombe_interval(kn, nn, kb, nb, confidence)
            diff = kn / nn - kb / nb if nb and nn else float("nan")
            if paired:
                b = int((yb[mb_] & ~yn[mn_]).sum())
                c = int((~yb[mb_] & yn[mn_]).sum())
                tests.append(Test(label, lv, nb, nn, kb, kn, diff, ci, "mcnemar", mcnemar_exact(b, c), b, c))
            else:
                tests.append(Test(label, lv, nb, nn, kb, kn, diff, ci, "fisher", fisher_exact(kn, nn, kb, nb)))
    for t, p in zip(tests, holm([t.p for t in tests])):
        t.p_holm = float(p)
        if p < alpha and t.diff != 0:
            t.verdict = "regressed" if t.diff < 0 else "improved"
    cell_verdict = {}
    for label in [labels[c] for c in cells] + (["all cells"] if len(cells) > 1 else []):
        vs = {t.verdict for t in tests if t.cell == label}
        cell_verdict[label] = "regressed" if "regressed" in vs else ("improved" if "improved" in vs else VERDICTS[2])
    vs = set(cell_verdict.values())
    verdict = "regressed" if "regressed" in vs else ("improved" if "improved" in vs else VERDICTS[2])
    return Comparison(os.fspath(base), os.fspath(new), sb.spec.spec_hash, paired, alpha, tests, cell_verdict,
                      verdict, bool(identical), int(len(rb["index"])), notes)


__all__ = ["Comparison", "Test", "check_allow_change", "compare_stores", "fisher_exact", "holm", "mcnemar_exact",
           "newcombe_interval", "spec_differences"]
