"""A sweep's CI verdict and the reports CI systems read: JUnit XML, a Markdown summary, JSON.

:class:`Verdict` joins the expectation checks (:mod:`hyqjax.studies.sweep.expect`) and a baseline comparison
(:mod:`hyqjax.studies.sweep.compare`) of one run; :meth:`Verdict.exit_status` is the command's status:

* 0: every expectation met and no regression;
* 1: an expectation failed (or was inconclusive with ``inconclusive="fail"``), or the baseline comparison found a
  regression;
* 3: an expectation was inconclusive (its Wilson interval straddles the value) and nothing failed
  (``inconclusive="report"``, the default; ``"pass"`` exits 0).

Reports (each written atomically):

* :func:`junit_xml`: one ``<testsuite>`` for the expectations (one ``<testcase>`` per check, a ``<failure>`` for a
  failed one, ``<skipped>`` for an inconclusive one unless it counts as failed) and one for the comparison (one
  ``<testcase>`` per cell and level, a ``<failure>`` for a regression);
* :func:`markdown`: a heading with the verdict and a table per part (``| status | check | ... |``), also appended
  to ``$GITHUB_STEP_SUMMARY`` by the command line when that is set;
* :meth:`Verdict.to_dict`: the JSON verdict (strict JSON).
"""
from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET

from hyqjax.io.atomic import atomic_write, write_json


@dataclasses.dataclass
class Verdict:
    """The gate's result of one run (module docstring)."""

    checks: list = dataclasses.field(default_factory=list)  # expect.Check
    comparison: object = None  # compare.Comparison or None
    inconclusive: str = "report"
    title: str = "hyqjax sweep"
    notes: list = dataclasses.field(default_factory=list)

    def exit_status(self) -> int:
        from hyqjax.studies.sweep.expect import exit_status

        status = exit_status(self.checks, self.inconclusive)
        if self.comparison is not None and self.comparison.regressed:
            return 1
        return status

    @property
    def outcome(self) -> str:
        return {0: "passed", 1: "failed", 3: "inconclusive"}[self.exit_status()]

    def lines(self) -> list[str]:
        out = [c.text() for c in self.checks]
        if self.comparison is not None:
            out += self.comparison.lines()
        out += [f"note: {n}" for n in self.notes]
        out.append(f"gate: {self.outcome.upper()} (exit status {self.exit_status()})")
        return out

    def to_dict(self) -> dict:
        return dict(title=self.title, outcome=self.outcome, exit_status=self.exit_status(),
                    inconclusive=self.inconclusive, expectations=[c.to_dict() for c in self.checks],
                    comparison=None if self.comparison is None else self.comparison.to_dict(), notes=self.notes)


def _case_status(check, inconclusive: str) -> str:
    if check.status == "inconclusive":
        return {"fail": "fail", "pass": "pass", "report": "inconclusive"}[inconclusive]
    return check.status


def junit_xml(v: Verdict) -> bytes:
    """The verdict as JUnit XML (module docstring)."""
    root = ET.Element("testsuites", name=v.title)
    if v.checks:
        suite = ET.SubElement(root, "testsuite", name="expectations", tests=str(len(v.checks)))
        fails = skips = 0
        for c in v.checks:
            case = ET.SubElement(suite, "testcase", classname="expectations", name=c.name)
            st = _case_status(c, v.inconclusive)
            if st == "fail":
                fails += 1
                ET.SubElement(case, "failure", message=c.text(), type=c.status).text = c.text()
            elif st == "inconclusive":
                skips += 1
                ET.SubElement(case, "skipped", message=c.text())
            ET.SubElement(case, "system-out").text = c.text()
        suite.set("failures", str(fails))
        suite.set("skipped", str(skips))
        suite.set("errors", "0")
    cmp = v.comparison
    if cmp is not None:
        suite = ET.SubElement(root, "testsuite", name="baseline comparison", tests=str(len(cmp.tests)))
        fails = 0
        for t in cmp.tests:
            case = ET.SubElement(suite, "testcase", classname="baseline", name=t.name)
            if t.verdict == "regressed":
                fails += 1
                ET.SubElement(case, "failure", message=t.text(), type="regressed").text = t.text()
            ET.SubElement(case, "system-out").text = t.text()
        suite.set("failures", str(fails))
        suite.set("skipped", "0")
        suite.set("errors", "0")
        if cmp.notes:
            ET.SubElement(suite, "system-out").text = "\n".join(cmp.notes)
    ET.indent(root)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n"


def _cell(s) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def markdown(v: Verdict) -> str:
    """The verdict as Markdown: a heading, a table of the expectation checks, a table of the comparison."""
    icon = {"passed": "PASSED", "failed": "FAILED", "inconclusive": "INCONCLUSIVE"}[v.outcome]
    out = [f"### {_cell(v.title)}: {icon}", ""]
    if v.checks:
        out += ["| status | expectation | instances | rate | Wilson 95% |", "| --- | --- | ---: | ---: | --- |"]
        for c in v.checks:
            rate = "-" if c.rate is None else f"{c.rate:.3f}"
            ci = "-" if c.ci is None else f"[{c.ci[0]:.3f}, {c.ci[1]:.3f}]"
            out.append(f"| {c.status} | {_cell(c.name)} | {c.k}/{c.n} | {rate} | {ci} |")
        out.append("")
    cmp = v.comparison
    if cmp is not None:
        out += [f"Baseline `{_cell(cmp.base)}` -> `{_cell(cmp.new)}`: **{cmp.verdict}** "
                f"({'paired, McNemar exact' if cmp.paired else 'unpaired, Fisher exact'}; Holm over {len(cmp.tests)} "
                f"tests at alpha {cmp.alpha:g}" + ("; identical outcomes" if cmp.identical else "") + ")", "",
                "| verdict | cell | level | base | new | difference [Newcombe 95%] | p | Holm p |",
                "| --- | --- | --- | ---: | ---: | --- | ---: | ---: |"]
        for t in cmp.tests:
            out.append(f"| {t.verdict} | {_cell(t.cell)} | {t.level} | {t.k_base}/{t.n_base} | {t.k_new}/{t.n_new} | "
                       f"{t.diff:+.3f} [{t.ci[0]:+.3f}, {t.ci[1]:+.3f}] | {t.p:.3g} | {t.p_holm:.3g} |")
        out.append("")
        out += [f"- {_cell(n)}" for n in cmp.notes]
    out += [f"- {_cell(n)}" for n in v.notes]
    return "\n".join(out).rstrip() + "\n"


def parse_markdown_tables(text: str) -> list[list[dict]]:
    """The tables of a Markdown text as lists of ``{header: cell}`` rows (the reader of :func:`markdown`'s output)."""
    tables, cur, header = [], None, None
    for line in text.splitlines():
        s = line.strip()
        if not s.startswith("|"):
            if cur is not None:
                tables.append(cur)
            cur, header = None, None
            continue
        cells = [c.strip().replace("\\|", "|") for c in s.strip("|").split(" | ")]
        if header is None:
            header, cur = cells, []
        elif set("".join(cells)) <= set("-: "):
            continue
        else:
            cur.append(dict(zip(header, cells)))
    if cur is not None:
        tables.append(cur)
    return tables


def write_reports(v: Verdict, junit: str | None = None, md: str | None = None, json_path: str | None = None,
                  step_summary: bool = True) -> list[str]:
    """Write the requested reports; append the Markdown to ``$GITHUB_STEP_SUMMARY`` when set (and
    ``step_summary``). Returns the paths written."""
    written = []
    for path, data in ((junit, lambda: junit_xml(v)), (md, lambda: markdown(v).encode())):
        if path:
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
            blob = data()
            atomic_write(path, lambda f, blob=blob: f.write(blob))
            written.append(path)
    if json_path:
        os.makedirs(os.path.dirname(os.path.abspath(json_path)), exist_ok=True)
        write_json(json_path, v.to_dict())
        written.append(json_path)
    gh = os.environ.get("GITHUB_STEP_SUMMARY")
    if step_summary and gh:
        with open(gh, "a", encoding="utf-8") as f:
            f.write(markdown(v) + "\n")
        written.append(gh)
    return written


__all__ = ["Verdict", "junit_xml", "markdown", "parse_markdown_tables", "write_reports"]
