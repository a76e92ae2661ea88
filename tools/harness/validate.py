"""Validation runs: every scene × precision × mode compared, with a report on disk."""
from __future__ import annotations

import contextlib
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from tools.harness.agree import parse_agreed
from rt_core.scene import Scene, SceneError
from .compare import compare, write_evidence
from .shaded import ORACLE_MODE, SHADED_MODES

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
    n = {c: sum(s.category == c for s in skipped)
         for c in ("unsupported", "malformed", "texture", "disagree")}
    return (f"{n['unsupported']} course files unsupported (object kinds rtval does not "
            f"implement), {n['malformed']} malformed (errors in the file itself)"
            + (f", {n['texture']} shaded comparisons without their texture file"
               if n["texture"] else "")
            + (f", {n['disagree']} read differently by rt_core and the references (FAILED)"
               if n["disagree"] else ""))


def attach_textures(scenes, dirs=()):
    """(scenes, skipped): each scene with its textures loaded (rt_core/textures.py: the
    ``dirs``, then the scene's directory).  A scene whose texture cannot be found or read
    keeps none: its geometry comparisons run as always, its shaded comparison is skipped
    (category "texture", the reason naming the file; ``jobs`` leaves it out)."""
    from rt_core.imageio import ImageError
    from rt_core.textures import attach
    out, skipped = [], []
    for sc in scenes:
        try:
            out.append(attach(sc, dirs))
        except (SceneError, ImageError) as e:
            out.append(sc)
            skipped.append(Skipped(str(sc.path), f"shaded comparison skipped: {e}", "texture"))
    return out, skipped


def lacks_texture(scene) -> bool:
    """Has the scene a textured object whose texture is not loaded?"""
    from rt_core.textures import textured
    return any(o.texture is None for _, o in textured(scene))


def load_supported(paths, explicit: bool, code27: str = "auto"):
    """(scenes, skipped): in the default list, course files rtval cannot read (an object kind
    it does not implement: "unsupported"; an error in the file itself: "malformed") are
    skipped and listed, and so are files that rt_core's parser and the references' own
    reader read differently, or that rt_core refuses as malformed where the references'
    reader reads them ("disagree": a failure, ``failed_reading``; a review broke the
    parser's reading of '-.5' and validate skipped 22 course files and passed); a bundled
    scene or a scene named explicitly must parse (its error is raised)."""
    from .agree import references_read
    scenes, skipped = [], []
    for p in paths:
        try:
            scenes.append(parse_agreed(p, code27))
        except SceneError as e:
            if explicit or not is_course_scene(p):
                raise
            category, reason = e.category, str(e)
            if category == "malformed" and references_read(p, code27):
                category = "disagree"
                reason += " (the references' own reader reads this file)"
            skipped.append(Skipped(str(p), reason, category))
    return scenes, skipped


def failed_reading(skipped) -> list:
    """The skipped files the two readers read differently: failures of the run."""
    return [s for s in skipped if s.category == "disagree"]


def unique_stems(paths) -> dict:
    """{path: stem_of(path)}, a stem two different paths share prefixed with their folders'
    names (``a__plane``, ``b__plane``; numbered where those agree too): their evidence files
    would take each other's names."""
    paths = list(dict.fromkeys(str(p) for p in paths))
    out = {p: stem_of(p) for p in paths}
    count = Counter(out.values())
    for p in paths:
        if count[out[p]] > 1:
            out[p] = f"{Path(p).parent.name}__{out[p]}"
    used: set = set()
    for p in paths:                     # (numbered where the folders agree too)
        out[p] = free_name(out[p], used)
    return out


def free_name(stem: str, used: set, suffix: str = "") -> str:
    """``stem + suffix``, or ``stem-2 + suffix``, ``stem-3 + suffix``, ... : the first not in
    ``used``, which it is added to."""
    name, k = stem + suffix, 1
    while name in used:
        k += 1
        name = f"{stem}-{k}{suffix}"
    used.add(name)
    return name


def row_stem(row: dict) -> str:
    """A result row's scene as the reports name it: validate's unique stem, else the
    scene's own."""
    return row.get("stem") or stem_of(row["scene"])


def stem_of(path: str) -> str:
    p = Path(path)
    return f"{p.parent.name}__{p.stem}" if p.parent.name in ("keyword", "numeric") else p.stem


@dataclass(frozen=True)
class Job:
    """The comparisons of a validation run that share their work: ``modes`` (rays, camera)
    at ``precision``, which trace rt_core once and load Mitsuba's scene once between them
    (``compare``'s cache), or ("shaded",): the course image at ``columns``.  ``keep_all``:
    their evidence is written even when they pass (``--evidence all``, first precision)."""
    scene: Scene
    modes: tuple
    precision: str
    columns: int
    keep_all: bool = False
    pictures: bool = False       # the rows get their PNGs for the HTML report
    code27: str = "auto"         # how the scene's file was read (the exact oracle reads it)
    source: bytes | None = field(default=None, repr=False)   # its bytes: the exact oracle

    @property
    def mode(self) -> str:
        return "shaded" if self.modes == ("shaded",) else "+".join(self.modes)


def jobs(scenes, columns: int, precisions, modes, evidence: str = "failures",
         shaded_columns: int = 0, pictures: bool = False, exact_columns: int = 0,
         code27: str = "auto", oracle_columns: int = 0) -> list:
    """The run's jobs: per scene, one per precision (its modes together), then, where the
    scene has objects Mitsuba has no shape for, one per precision against the exact oracle
    (tools/harness/exact_compare.py), then the shaded course image, and for those scenes
    their course image against the shading oracle (``oracle_columns``)."""
    from .exact_compare import needs_exact, scene_source
    out = []
    for scene in scenes:
        for precision in precisions:
            out.append(Job(scene, tuple(modes), precision, columns,
                           evidence == "all" and precision == precisions[0], pictures))
        if exact_columns and needs_exact(scene):
            source = scene_source(scene)
            out += [Job(scene, ("exact",), precision, exact_columns,
                        evidence == "all" and precision == precisions[0], pictures, code27,
                        source) for precision in precisions]
        if shaded_columns and not lacks_texture(scene):
            out.append(Job(scene, ("shaded",), "f64", shaded_columns, pictures=pictures))
        if oracle_columns and needs_exact(scene) and not lacks_texture(scene):
            out.append(Job(scene, (ORACLE_MODE,), "f64", oracle_columns, pictures=pictures))
    return out


def check_memory(scenes, columns: int, precisions, shaded_columns: int,
                 exact_columns: int = 0, oracle_columns: int = 0) -> None:
    """The run's largest comparison of each kind against the memory there is, and its
    largest exact one against the exact oracle's pixels (exact_compare.check_size), its
    largest shading oracle one against that oracle's (shaded.check_oracle_size): InputError
    naming the option to lower (``--columns``, ``--shaded-columns``, ``--exact-columns``,
    ``--oracle-columns``)."""
    from rt_core.camera import make_camera
    from rt_core.memory import compare_bytes, guard
    top = "f64" if "f64" in precisions else "f32"
    for cols, key, what, option in (
            (columns, top, "compare", "--columns"),
            (shaded_columns, "shaded", "compare --shaded", "--shaded-columns"),
            (exact_columns, top, "compare --mode exact", "--exact-columns")):
        if cols > 0 and scenes:
            rows = max(make_camera(s, cols).rows for s in scenes)
            guard(lambda px: compare_bytes(px, key), what, cols, rows, option=option)
    from .exact_compare import check_size, needs_exact
    from .shaded import check_oracle_size
    odd = [s for s in scenes if needs_exact(s)]         # (the oracles' scenes)
    for cols, check, option in ((exact_columns, check_size, "--exact-columns"),
                                (oracle_columns, check_oracle_size, "--oracle-columns")):
        if cols > 0 and odd:
            check(cols, max(make_camera(s, cols).rows for s in odd), option)


def seconds_per_comparison(columns: int) -> float:
    """Rough serial seconds of one comparison at ``columns`` (measured on 2 cores: the
    default run's 670 comparisons at 160 columns take about 90 s): whether a run is worth a
    local cluster (parallel.Plan)."""
    return 0.15 * max(1.0, (columns / 160) ** 2)


# cores a serial run keeps busy (its CPU seconds over its wall time: 77 s over 43.5 s for the
# default run on 2 cores, benchmarks/parallel_speedup.py): Dr.Jit's and Mitsuba's threads
# leave a 2-core machine no room for a second worker (parallel.Plan.resolve).  Measured on 2
# cores only: on more, the threads spread wider and the serial run keeps more busy
SERIAL_BUSY_CORES = 1.8


# compare's cache of the scene whose jobs ran last in this process: its precisions' jobs
# (which follow each other, ``jobs``) share Mitsuba's loaded scenes (Mitsuba traces in
# float32 whatever rt_core's precision); rt_core's entries are keyed by precision.  Emptied
# at each validate's start and end
_LAST: list = [None, {}]


def _scene_cache(scene) -> dict:
    if _LAST[0] is not scene:
        _LAST[:] = [scene, {}]
    return _LAST[1]


def _free() -> dict:
    _LAST[:] = [None, {}]
    return {}


def _on_worker() -> bool:
    """Does this run on a Dask worker (a task of tools/harness/parallel.py's clusters)?"""
    dist = sys.modules.get("distributed")
    if dist is None:
        return False
    try:
        dist.get_worker()
    except ValueError:
        return False
    return True


def run_job(job: Job) -> list:
    """A job's comparisons (in this process or on a Dask worker): for each, its report row,
    and the comparison itself when its evidence is to be written (it failed, or
    ``keep_all``); evidence is written by the caller, never on a worker."""
    # (a shaded job frees them first: with them loaded Mitsuba's course images took 1.7
    # times the time, and compiled new kernels on the first run; likely its virtual calls,
    # which dispatch over every live instance, the other scene's BSDFs too.  On a Dask
    # worker nothing is shared: its jobs come pickled, each with a scene of its own, and
    # what it kept would outlive the run)
    worker = _on_worker()
    if worker:
        cache = {}
    else:
        cache = _scene_cache(job.scene) if job.modes != ("shaded",) else _free()
    # (validate checked the run's largest comparisons against this machine's memory before
    # it started; a worker's memory is its own)
    guarded = not worker
    out = []
    for mode in job.modes:
        t0 = time.perf_counter()
        if mode == "shaded":
            from tools.harness.shaded import compare_shaded
            cmp = compare_shaded(job.scene, job.columns, guarded=guarded)
        elif mode == ORACLE_MODE:
            from tools.harness.shaded import compare_shaded
            cmp = compare_shaded(job.scene, job.columns, guarded=guarded, reference="oracle")
        elif mode == "exact":
            from tools.harness.exact_compare import compare_exact
            cmp = compare_exact(job.scene, job.columns, job.precision, code27=job.code27,
                                guarded=guarded, source=job.source)
        else:
            # one call a side: validate checks, rtval bench times (a second call of each
            # was a fifth of the run)
            cmp = compare(job.scene, job.columns, None, job.precision, mode, cache=cache,
                          calls=1, guarded=guarded)
        row = cmp.summary()
        # the time outside the comparison's own phases (imports, the summary) is "other"
        row["seconds"] = dict(row["seconds"])
        row["seconds"]["other"] += round(time.perf_counter() - t0
                                         - sum(row["seconds"].values()), 4)
        if job.pictures:
            from .html_report import comparison_pictures
            t1 = time.perf_counter()
            row["pictures"] = comparison_pictures(cmp)
            row["seconds"]["write"] += round(time.perf_counter() - t1, 4)
        out.append((row, cmp if not cmp.ok or job.keep_all else None))
    return out


def validate(scenes, columns: int, precisions, modes, outdir: str, progress=None,
             evidence: str = "failures", shaded_columns: int = 0, plan=None,
             pictures: bool = False, exact_columns: int = 0, code27: str = "auto",
             oracle_columns: int = 0):
    """Run every comparison (``plan``: where, tools/harness/parallel.py; default in this
    process); write the evidence EXRs under ``outdir``: of every failing comparison (ours,
    Mitsuba, difference, classes, in ``failures/``) and, with ``evidence="all"``, ours and
    Mitsuba's of the passing ones too (in ``exr/``).  The rows come in the same order
    however the comparisons ran; ``progress(row)`` as each one completes.

    ``shaded_columns`` > 0: each scene's course image is also compared with Mitsuba's
    (``rtval compare --shaded``, tools/harness/shaded.py) at that width; the evidence PNGs of
    a failing one go to ``failures/`` too.

    ``exact_columns`` > 0: each scene with objects Mitsuba has no shape for (cone, ellipsoid,
    torus) is also compared, every object, with the exact oracle at that width and each
    precision (tools/harness/exact_compare.py; ``code27``: how its file was read).

    ``oracle_columns`` > 0: the course image of each such scene is also compared, every
    object, with the float64 shading oracle's at that width (mode ``shaded-oracle``,
    ``compare_shaded(.., reference="oracle")``).

    ``pictures``: each row also gets "pictures", its PNGs for the HTML report
    (tools/harness/html_report.py, made where the comparison ran; ``public`` drops them
    from what is written as JSON).

    Evidence of an earlier run in ``outdir/failures`` and ``outdir/exr`` is removed first,
    so what is there belongs to this run; a run stopped (a signal, Ctrl-C, an error)
    removes what it wrote there, and the directories it made.

    The run's largest comparison of each kind is checked against the memory there is before
    any runs (InputError naming the option to lower); each comparison then skips its own
    check, but on a Dask worker."""
    check_memory(scenes, columns, precisions, shaded_columns, exact_columns, oracle_columns)
    _free()                 # (what an earlier run in this process left is not this run's)
    try:
        with evidence_run(outdir):
            return _validate(scenes, columns, precisions, modes, outdir, progress, evidence,
                             shaded_columns, pictures, plan, exact_columns, code27,
                             oracle_columns)
    finally:
        _free()


@contextlib.contextmanager
def evidence_run(outdir: str):
    """The evidence of one run under ``outdir``: what an earlier run left in ``failures/``
    and ``exr/`` is removed first; if the block is stopped (a signal, Ctrl-C, an error) the
    evidence it finished goes too, and the directories it made.  ``rtval validate`` holds
    it over the run and the reports after it (a signal while they were written left the
    run's evidence behind)."""
    made = [d for d in (outdir, os.path.join(outdir, "failures"), os.path.join(outdir, "exr"))
            if not os.path.exists(d)]
    for sub in ("failures", "exr"):
        for old in [*Path(outdir, sub).glob("*.exr"), *Path(outdir, sub).glob("*.png")]:
            old.unlink()
    try:
        yield
    except BaseException:
        # (the workers are stopped by now: run_cases closes its cluster on the way out)
        for sub in ("failures", "exr"):
            for ev in [*Path(outdir, sub).glob("*.exr"), *Path(outdir, sub).glob("*.png")]:
                with contextlib.suppress(OSError):
                    ev.unlink()
        for d in reversed(made):
            with contextlib.suppress(OSError):
                os.rmdir(d)                     # (only if empty)
        raise


def _validate(scenes, columns, precisions, modes, outdir, progress, evidence, shaded_columns,
              pictures, plan, exact_columns=0, code27="auto", oracle_columns=0):
    """``validate``'s comparisons, once the output directory is ready."""
    from tools.harness.parallel import SERIAL, run_cases
    todo = jobs(scenes, columns, precisions, modes, evidence, shaded_columns, pictures,
                exact_columns, code27, oracle_columns)
    stems = unique_stems([s.path for s in scenes])

    def each(i, outs):
        job = todo[i]
        rows = []
        for row, cmp in outs:
            t0 = time.perf_counter()
            row["stem"] = stems[job.scene.path]         # (its name in the reports)
            if row["mode"] in SHADED_MODES:
                if cmp is not None:
                    from tools.harness.shaded import write_shaded_evidence
                    row["evidence"] = write_shaded_evidence(
                        cmp, os.path.join(outdir, "failures"), row["stem"])
            elif cmp is not None:
                stem = f"{row['stem']}.{row['mode']}.{job.precision}"
                row["evidence"] = (write_evidence(cmp, os.path.join(outdir, "failures"), stem)
                                   if not cmp.ok else
                                   write_evidence(cmp, os.path.join(outdir, "exr"), stem,
                                                  ("ours", "reference")))
            row["seconds"]["write"] += round(time.perf_counter() - t0, 4)
            if progress:
                progress(row)
            rows.append(row)
        return rows
    per_job = sum(len(j.modes) for j in todo) / max(len(todo), 1)
    done = run_cases(run_job, todo, plan or SERIAL, each,
                     seconds_per_case=per_job * seconds_per_comparison(columns),
                     busy_cores=SERIAL_BUSY_CORES)
    # report order: per scene, every mode and precision (as given), then the exact oracle's,
    # then the shaded image
    order = {m: k for k, m in enumerate((*modes, "exact", *SHADED_MODES))}
    prec = {p: k for k, p in enumerate(precisions)}
    keyed = [(n, order[r["mode"]], prec.get(todo[n].precision, 0), r)
             for n, rows in enumerate(done) for r in rows]
    first = {}                              # a scene's first job: where its rows go
    for n, j in enumerate(todo):
        first.setdefault(id(j.scene), n)
    keyed.sort(key=lambda k: (first[id(todo[k[0]].scene)], k[1], k[2]))
    return [k[3] for k in keyed]


def public(row: dict) -> dict:
    """A result row as written to JSON: without the report's pictures."""
    return {k: v for k, v in row.items() if k != "pictures"}


def report_data(results, skipped, meta: dict) -> dict:
    """What report.json holds and ``rtval validate --json`` prints."""
    from .timing import time_split
    return {"meta": meta, "time_split": time_split(results),
            "results": [public(r) for r in results],
            "skipped": [{"path": s.path, "category": s.category, "reason": s.reason}
                        for s in skipped]}


def write_report(results, skipped, outdir: str, meta: dict) -> tuple[str, str]:
    from rt_core.outputs import atomic_write, attr_text, json_text
    text = json_text(report_data(results, skipped, meta))
    jpath = os.path.join(outdir, "report.json")
    mpath = os.path.join(outdir, "report.md")
    atomic_write(jpath, lambda tmp: Path(tmp).write_text(text))
    lines = ["# rtval validate", "",
             "rt_core against Mitsuba 3 (llvm_ad_rgb, float32), pixel by pixel. Modes: `rays` = "
             "Mitsuba intersects rt_core's exact rays; `camera` = Mitsuba's own perspective "
             "sensor. A disagreement is explained only within a float32 error bound of an edge,"
             " tie, the screen clip, a sphere outline or the reference plane's extent "
             "(mitsuba_ref/explain.py). Mode `exact`: scenes with objects Mitsuba has no "
             "shape for (cone, ellipsoid, torus), every object against the exact oracle "
             "(tools/harness/exact_compare.py; float64 must match it everywhere, float32 "
             "within K·u·S of a decision); its reference ms are the oracle's. The times (ms) "
             "are of one call of each side, finding (or compiling) its kernels included; "
             "`rtval bench` measures speed.", "",
             " ".join(f"{k}={v}" for k, v in meta.items()), "",
             "| scene | mode | prec | pixels | explained | unexplained | depth max rel | "
             "over bound | rt_core ms | Mitsuba ms |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    shaded = [r for r in results if r["mode"] in SHADED_MODES]
    for r in results:
        if r["mode"] in SHADED_MODES:
            continue
        lines.append(f"| {row_stem(r)} | {r['mode']} | {r['precision']} | {r['pixels']} |"
                     f" {r['explained']} | {r['unexplained']} | {r['depth']['max_rel']:.2e} | "
                     f"{r['depth']['over_bound']} | {r['rt_core_ms']:.2f} | {r['mitsuba_ms']:.2f} |")
    if shaded:
        lines += ["", "## The course image (rt_core f64 against Mitsuba's `course` integrator)",
                  "", "8-bit pixels: match, rounding (±1 at an 8-bit level), boundary (a decision "
                  "within float32's bound: the float64 shading oracle or the geometry "
                  "classifier), wrong (tools/harness/shaded.py). Mode `shaded-oracle`: "
                  "scenes with objects Mitsuba has no shape for, every object, against the "
                  "float64 shading oracle's image (decisions within float64's bound); its "
                  "reference ms are the oracle's.", "",
                  "| scene | mode | pixels | match | rounding | boundary | wrong | rt_core ms | "
                  "reference ms |", "|---|---|---|---|---|---|---|---|---|"]
        for r in shaded:
            c = r["classes"]
            lines.append(f"| {row_stem(r)} | {r['mode']} | {r['pixels']} | {c['match']} | "
                         f"{c['rounding']} | {c['boundary']} | {c['wrong']} | "
                         f"{r['rt_core_ms']:.2f} | {r['mitsuba_ms']:.2f} |")
    bad = [r for r in results if not r["ok"]]
    from .timing import split_line, time_split
    lines += ["", f"{len(results)} comparisons, {len(bad)} failed.", "",
              split_line(time_split(results)) + "."]
    if skipped:
        lines += ["", f"## Skipped: {skip_counts(skipped)}", ""]
        lines += [f"- {s.category}: {s.reason}" for s in sorted(skipped,
                                                                key=lambda s: s.category)]
    # (a scene path's bytes that are not UTF-8: \xNN, as the HTML report writes them)
    atomic_write(mpath, lambda tmp: Path(tmp).write_text(attr_text("\n".join(lines) + "\n")))
    return mpath, jpath


def comparison_cases(rows, classname: str) -> list:
    """JUnit cases of compare/validate result rows."""
    from tools.harness.junit import Case
    cases = []
    for r in rows:
        prec = r["precision"].split()[0]
        # the comparison's own wall time, every phase (a camera row whose rt_core trace was
        # the rays row's repeats that trace's ms, but not its seconds)
        c = Case(f"{row_stem(r)}.{r['mode']}.{prec}", classname,
                 sum(r["seconds"].values()))
        counts = ", ".join(f"{k} {v}" for k, v in r["classes"].items() if v)
        if r["mode"] in SHADED_MODES:
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
    """A skipped file's JUnit case: skipped, as the run passes without it (an error made CI
    red on a run that exited 0 and said PASS)."""
    from tools.harness.junit import Case
    if s.category == "disagree":        # (a defect of a reader: a failure)
        return Case(s.path, "rtval.validate.skipped", failure=s.reason)
    return Case(s.path, "rtval.validate.skipped", skipped=f"{s.category}: {s.reason}")
