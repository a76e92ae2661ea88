"""JUnit XML for CI systems: one test suite, one test case per scene or comparison."""
from __future__ import annotations

import re
from dataclasses import dataclass
from xml.sax.saxutils import escape as _escape, quoteattr as _quoteattr

# characters XML 1.0 does not allow (C0 controls but tab, newline, CR; a surrogate: a file
# name's byte that is not UTF-8): written as \xNN, or the file is not XML
_NOT_XML = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]")


def _text(s) -> str:
    def code(m) -> str:
        c = ord(m.group())              # (a surrogate escape \udcNN stands for the byte NN)
        return f"\\x{c - 0xdc00 if 0xdc00 <= c <= 0xdcff else c & 0xff:02x}"
    return _NOT_XML.sub(code, str(s))


def escape(s) -> str:
    return _escape(_text(s))


def quoteattr(s) -> str:
    return _quoteattr(_text(s))


@dataclass
class Case:
    name: str
    classname: str
    seconds: float = 0.0
    failure: str | None = None     # message of a failed case
    error: str | None = None       # message of a case that could not run (bad input, crash)
    error_type: str | None = None  # its kind (rtval check: 'refused' scene, or 'error')
    body: str = ""                 # failure details, or what a passing case printed
    skipped: str | None = None     # why a case was not run (the run passes without it)


def junit_xml(suite: str, cases: list[Case]) -> str:
    """The XML text, with rtval's provenance (package versions, commit) as properties."""
    from rt_core.render import versions
    fails = sum(c.failure is not None for c in cases)
    errors = sum(c.error is not None for c in cases)
    skips = sum(c.skipped is not None for c in cases)
    out = ['<?xml version="1.0" encoding="UTF-8"?>',
           f'<testsuite name={quoteattr(suite)} tests="{len(cases)}" failures="{fails}" '
           f'errors="{errors}" skipped="{skips}" time="{sum(c.seconds for c in cases):.3f}">',
           "  <properties>"] + [
           f'    <property name={quoteattr(k)} value={quoteattr(str(v))}/>'
           for k, v in versions().items()] + ["  </properties>"]
    seen: dict = {}
    for c in cases:
        # (a name given twice, a scene listed twice or two of one file name: CI tools merge
        # cases of one class and name, so the later ones are numbered)
        key = (c.classname, c.name)
        seen[key] = seen.get(key, 0) + 1
        name = c.name if seen[key] == 1 else f"{c.name} ({seen[key]})"
        out.append(f'  <testcase classname={quoteattr(c.classname)} name={quoteattr(name)} '
                   f'time="{c.seconds:.3f}">')
        if c.failure is not None:
            out.append(f'    <failure message={quoteattr(c.failure)}>{escape(c.body)}</failure>')
        elif c.error is not None:
            kind = f" type={quoteattr(c.error_type)}" if c.error_type else ""
            out.append(f'    <error message={quoteattr(c.error)}{kind}/>')
        elif c.skipped is not None:
            out.append(f'    <skipped message={quoteattr(c.skipped)}/>')
        elif c.body:
            out.append(f'    <system-out>{escape(c.body)}</system-out>')
        out.append("  </testcase>")
    out.append("</testsuite>")
    return "\n".join(out) + "\n"


def write_junit(path: str, suite: str, cases: list[Case]) -> None:
    from rt_core.outputs import atomic_write
    text = junit_xml(suite, cases)

    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
    atomic_write(path, write)


def stability_cases(results) -> list[Case]:
    """JUnit cases of ``rtval stability``: one per generated case (family[parameter]#seed),
    a failure when it misses the bar (tools/harness/stability.py ``case_ok``), saying which
    part of the bar and by how much."""
    from .stability import F64_TARGET, case_ok
    cases = []
    for r in results:
        m = r.metrics
        c = Case(r.label, f"rtval.stability.{r.family}", r.seconds)
        c.body = "\n".join(f"{k}: {v.rays} rays, mismatch {v.mismatch}, unexplained "
                           f"{v.unexplained}, non-finite {v.nonfinite}, depth max rel "
                           f"{v.depth_max:.3g}" for k, v in m.items())
        if not case_ok(r):
            why = [f"{k} {v.nonfinite} non-finite values" for k, v in m.items()
                   if k.startswith("rt_") and v.nonfinite]
            if "rt_f32" in m and "mitsuba" in m and \
                    m["rt_f32"].unexplained > m["mitsuba"].unexplained:
                why.append(f"rt_f32 {m['rt_f32'].unexplained} unexplained mismatches, more "
                           f"than Mitsuba's {m['mitsuba'].unexplained}")
            if "rt_f64" in m and m["rt_f64"].unexplained:
                why.append(f"rt_f64 {m['rt_f64'].unexplained} unexplained mismatches")
            if "rt_f64" in m and m["rt_f64"].over_target:
                why.append(f"rt_f64 {m['rt_f64'].over_target} depths over {F64_TARGET:g} "
                           "where the condition number allows it")
            c.failure = "; ".join(why)
        cases.append(c)
    return cases
