"""Validation runs: every scene × precision × mode compared, with a report on disk."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from rt_core.parser import parse_scene
from rt_core.scene import SceneError
from .compare import compare, write_evidence

REPO = Path(__file__).resolve().parents[2]
COURSE_SCENES = REPO.parent / "shared" / "course-scenes"


def default_scene_paths() -> list[Path]:
    """Bundled scenes, then every course scene when ../shared/course-scenes is present."""
    paths = sorted((REPO / "scenes").glob("*.txt"))
    if COURSE_SCENES.is_dir():
        paths += sorted(COURSE_SCENES.glob("*/*.txt"))
    return paths


def is_course_scene(path) -> bool:
    """Is ``path`` one of ../shared/course-scenes (symlinks resolved on both sides)?"""
    return COURSE_SCENES.resolve() in Path(path).resolve().parents


@dataclass
class Skipped:
    path: str
    reason: str
    category: str = "malformed"       # or "unsupported" (SceneError.category)


def skip_counts(skipped) -> str:
    """'12 course files unsupported (object kinds rtval does not implement), 5 malformed'."""
    if not skipped:
        return "none"
    n = {c: sum(s.category == c for s in skipped) for c in ("unsupported", "malformed")}
    return (f"{n['unsupported']} course files unsupported (object kinds rtval does not "
            f"implement), {n['malformed']} malformed (errors in the file itself)")


def load_supported(paths, explicit: bool):
    """(scenes, skipped): in the default list, course files rtval cannot read (an object kind
    it does not implement: "unsupported"; an error in the file itself: "malformed") are
    skipped and listed; a bundled scene or a scene named explicitly must parse (its error is
    raised)."""
    scenes, skipped = [], []
    for p in paths:
        try:
            scenes.append(parse_scene(p))
        except SceneError as e:
            if explicit or not is_course_scene(p):
                raise
            skipped.append(Skipped(str(p), str(e), e.category))
    return scenes, skipped


def stem_of(path: str) -> str:
    p = Path(path)
    return f"{p.parent.name}__{p.stem}" if p.parent.name in ("keyword", "numeric") else p.stem


def validate(scenes, columns: int, precisions, modes, outdir: str, progress=None,
             evidence: str = "failures", shaded_columns: int = 0, pictures: bool = False):
    """Run every comparison; write the evidence EXRs under ``outdir``: of every failing
    comparison (ours, Mitsuba, difference, classes, in ``failures/``) and, with
    ``evidence="all"``, ours and Mitsuba's of the passing ones too (in ``exr/``).

    ``shaded_columns`` > 0: each scene's course image is also compared with Mitsuba's
    (``rtval compare --shaded``, tools/harness/shaded.py) at that width; the evidence PNGs of
    a failing one go to ``failures/`` too.

    ``pictures``: each row also gets "pictures", its PNGs for the HTML report
    (tools/harness/html_report.py; ``public`` drops them from what is written as JSON).

    Evidence of an earlier run in ``outdir/failures`` and ``outdir/exr`` is removed first,
    so what is there belongs to this run."""
    if pictures:
        from .html_report import comparison_pictures
    for sub in ("failures", "exr"):
        for old in [*Path(outdir, sub).glob("*.exr"), *Path(outdir, sub).glob("*.png")]:
            old.unlink()
    results = []
    for scene in scenes:
        for mode in modes:
            for precision in precisions:
                cmp = compare(scene, columns, None, precision, mode)
                row = cmp.summary()
                stem = f"{stem_of(scene.path)}.{mode}.{precision}"
                # ours and the reference for every comparison; full evidence when it fails
                if not cmp.ok:
                    row["evidence"] = write_evidence(cmp, os.path.join(outdir, "failures"), stem)
                elif evidence == "all" and precision == precisions[0]:
                    row["evidence"] = write_evidence(cmp, os.path.join(outdir, "exr"), stem,
                                                     ("ours", "mitsuba"))
                if pictures:
                    row["pictures"] = comparison_pictures(cmp)
                results.append(row)
                if progress:
                    progress(row)
        if shaded_columns:
            from tools.harness.shaded import compare_shaded, write_shaded_evidence
            cmp = compare_shaded(scene, shaded_columns)
            row = cmp.summary()
            if not cmp.ok:
                row["evidence"] = write_shaded_evidence(cmp, os.path.join(outdir, "failures"),
                                                        stem_of(scene.path))
            if pictures:
                row["pictures"] = comparison_pictures(cmp)
            results.append(row)
            if progress:
                progress(row)
    return results


def public(row: dict) -> dict:
    """A result row as written to JSON: without the report's pictures."""
    return {k: v for k, v in row.items() if k != "pictures"}


def report_data(results, skipped, meta: dict) -> dict:
    """What report.json holds and ``rtval validate --json`` prints."""
    return {"meta": meta, "results": [public(r) for r in results],
            "skipped": [{"path": s.path, "category": s.category, "reason": s.reason}
                        for s in skipped]}


def write_report(results, skipped, outdir: str, meta: dict) -> tuple[str, str]:
    from rt_core.outputs import atomic_write, json_text
    text = json_text(report_data(results, skipped, meta))
    jpath = os.path.join(outdir, "report.json")
    mpath = os.path.join(outdir, "report.md")
    atomic_write(jpath, lambda tmp: Path(tmp).write_text(text))
    lines = ["# rtval validate", "",
             "rt_core against Mitsuba 3 (llvm_ad_rgb, float32), pixel by pixel. Modes: `rays` = "
             "Mitsuba intersects rt_core's exact rays; `camera` = Mitsuba's own perspective "
             "sensor. A disagreement is explained only within a float32 error bound of an edge,"
             " tie, the screen clip, a sphere outline or the reference plane's extent "
             "(mitsuba_ref/explain.py).", "",
             " ".join(f"{k}={v}" for k, v in meta.items()), "",
             "| scene | mode | prec | pixels | explained | unexplained | depth max rel | "
             "over bound | rt_core ms | Mitsuba ms |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    shaded = [r for r in results if r["mode"] == "shaded"]
    for r in results:
        if r["mode"] == "shaded":
            continue
        lines.append(f"| {stem_of(r['scene'])} | {r['mode']} | {r['precision']} | {r['pixels']} |"
                     f" {r['explained']} | {r['unexplained']} | {r['depth']['max_rel']:.2e} | "
                     f"{r['depth']['over_bound']} | {r['rt_core_ms']:.2f} | {r['mitsuba_ms']:.2f} |")
    if shaded:
        lines += ["", "## The course image (rt_core f64 against Mitsuba's `course` integrator)",
                  "", "8-bit pixels: match, rounding (±1 at an 8-bit level), boundary (a decision "
                  "within float32's bound: the float64 shading oracle or the geometry "
                  "classifier), wrong (tools/harness/shaded.py).", "",
                  "| scene | pixels | match | rounding | boundary | wrong | rt_core ms | "
                  "Mitsuba ms |", "|---|---|---|---|---|---|---|---|"]
        for r in shaded:
            c = r["classes"]
            lines.append(f"| {stem_of(r['scene'])} | {r['pixels']} | {c['match']} | "
                         f"{c['rounding']} | {c['boundary']} | {c['wrong']} | "
                         f"{r['rt_core_ms']:.2f} | {r['mitsuba_ms']:.2f} |")
    bad = [r for r in results if not r["ok"]]
    lines += ["", f"{len(results)} comparisons, {len(bad)} failed."]
    if skipped:
        lines += ["", f"## Skipped: {skip_counts(skipped)}", ""]
        lines += [f"- {s.category}: {s.reason}" for s in sorted(skipped,
                                                                key=lambda s: s.category)]
    atomic_write(mpath, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"))
    return mpath, jpath


def comparison_cases(rows, classname: str) -> list:
    """JUnit cases of compare/validate result rows."""
    from tools.harness.junit import Case
    cases = []
    for r in rows:
        prec = r["precision"].split()[0]
        c = Case(f"{stem_of(r['scene'])}.{r['mode']}.{prec}", classname,
                 (r["rt_core_ms"] + r["mitsuba_ms"]) / 1e3)
        counts = ", ".join(f"{k} {v}" for k, v in r["classes"].items() if v)
        if r["mode"] == "shaded":
            c.body = (f"{r['columns']}x{r['rows']} 8-bit: {counts}"
                      + "".join(f"\nevidence: {p}" for p in r.get("evidence", [])))
            if not r["ok"]:
                c.failure = f"{r['wrong']} wrong pixels"
            cases.append(c)
            continue
        depth = r["depth"]
        c.body = (f"{r['columns']}x{r['rows']}: {counts}; depth max rel {depth['max_rel']:.3g}, "
                  f"over bound {depth['over_bound']}"
                  + "".join(f"\nevidence: {p}" for p in r.get("evidence", [])))
        if not r["ok"]:
            c.failure = (f"{r['unexplained']} unexplained pixels, {depth['over_bound']} depths "
                         "over their bound")
        cases.append(c)
    return cases


def skip_case(s):
    from tools.harness.junit import Case
    return Case(s.path, "rtval.validate.skipped", error=f"{s.category}: {s.reason}")
