"""rtval validate: the main job — every scene compared with Mitsuba, a table and a report."""
from __future__ import annotations

import sys

from .options import add_code27, add_parallel, add_texture_dir, positive_int


def add_parser(sub) -> None:
    p = sub.add_parser("validate", help="compare rt_core with Mitsuba on many scenes",
                       description="Compare rt_core with Mitsuba (same rays and Mitsuba's "
                                   "camera, f32 and f64) on the given scenes, by default every "
                                   "scene in scenes/ and every supported course scene in "
                                   "../shared/course-scenes. Writes report.md, report.json and "
                                   "the evidence EXRs of failing comparisons. Exit 0 iff every "
                                   "comparison passes.")
    p.add_argument("scenes", nargs="*")
    p.add_argument("--columns", type=positive_int, default=160)
    p.add_argument("--precision", choices=("f32", "f64", "both"), default="both")
    p.add_argument("--mode", choices=("rays", "camera", "both"), default="both")
    p.add_argument("-o", "--output", default="out/validate", metavar="DIR")
    p.add_argument("--junit", metavar="FILE.xml",
                   help="also write JUnit XML: one test case per comparison (CI systems show "
                        "them), a failure for each failing one, an error for each skipped file")
    p.add_argument("--report", metavar="DIR",
                   help="also write an HTML report into DIR (new, empty or an earlier "
                        "report): a row per comparison, failures first, Mitsuba's picture, "
                        "rt_core's and the classes side by side, the skipped files")
    p.add_argument("--json", action="store_true",
                   help="print the results as JSON on stdout (what report.json holds) "
                        "instead of the table")
    add_texture_dir(p)
    add_code27(p)
    p.add_argument("--shaded-columns", type=int, default=48, metavar="N",
                   help="also compare each scene's shaded course image with Mitsuba's 'course' "
                        "integrator at N columns (rtval compare --shaded; default 48; 0: off; "
                        "about 2 s a scene, mostly Mitsuba's kernel launches)")
    p.add_argument("--exact-columns", type=int, default=48, metavar="N",
                   help="also compare each scene that has objects Mitsuba has no shape for "
                        "(cone, ellipsoid, torus: left out of the Mitsuba comparisons), every "
                        "object, with the exact oracle at N columns, in each precision (rtval "
                        "compare --mode exact; default 48; 0: off; 0.1-0.3 s a scene)")
    p.add_argument("--oracle-columns", type=int, default=24, metavar="N",
                   help="also compare the shaded course image of each such scene, every "
                        "object, with the float64 shading oracle's at N columns (rtval "
                        "compare --shaded --reference oracle; default 24; 0: off; 0.05-0.7 s "
                        "a scene)")
    p.add_argument("--evidence", choices=("failures", "all"), default="failures",
                   help="EXRs of the failing comparisons only (default), or also ours and "
                        "Mitsuba's of every passing one (under DIR/exr)")
    add_parallel(p, "comparisons")
    p.set_defaults(func=run)


def _log_progress(total: int):
    import time
    t0, state = time.monotonic(), {"n": 0, "failed": 0, "shown": 0}

    def progress(row):
        state["n"] += 1
        state["failed"] += not row["ok"]
        tenth = state["n"] * 10 // max(total, 1)
        if tenth > state["shown"] or state["n"] == total:
            state["shown"] = tenth
            print(f"rtval validate: {state['n']}/{total} comparisons ({tenth * 10}%), "
                  f"{state['failed']} failed, {time.monotonic() - t0:.0f} s",
                  file=sys.stderr, flush=True)
    return progress


def run(args) -> int:
    from tqdm import tqdm
    from rt_core.render import versions
    from tools.harness.parallel import plan_of
    from tools.harness.validate import (SERIAL_BUSY_CORES, SHADED_MODES, check_memory,
                                        default_scene_paths, failed_reading, load_supported,
                                        seconds_per_comparison, skip_counts, row_stem,
                                        validate, write_report)

    from rt_core.outputs import check_dir_target, check_file_target
    if args.report:                     # refused before the run, not after it
        from tools.harness.html_report import check_target
        check_target(args.report, {"-o": args.output, "--junit": args.junit})
    check_dir_target(args.output)
    if args.junit:
        check_file_target(args.junit, make_dirs=False)
    paths = args.scenes or default_scene_paths()
    scenes, skipped = load_supported(paths, explicit=bool(args.scenes), code27=args.code27)
    if args.shaded_columns > 0 or args.oracle_columns > 0:   # shaded ones need the textures
        from tools.harness.validate import attach_textures
        scenes, no_texture = attach_textures(scenes, args.texture_dir)
        skipped += no_texture
    precisions = ("f32", "f64") if args.precision == "both" else (args.precision,)
    modes = ("rays", "camera") if args.mode == "both" else (args.mode,)
    for s in skipped:
        print(f"{'FAILED' if s.category == 'disagree' else 'skipped'} ({s.category}): "
              f"{s.reason}", file=sys.stderr)
    from tools.harness.validate import jobs
    total = sum(len(j.modes) for j in jobs(
        scenes, args.columns, precisions, modes, shaded_columns=args.shaded_columns,
        exact_columns=args.exact_columns, oracle_columns=args.oracle_columns))
    plan = plan_of(args).resolve(total, seconds_per_comparison(args.columns), SERIAL_BUSY_CORES)
    if sys.stderr.isatty():
        bar = tqdm(total=total, file=sys.stderr, unit="cmp")
        progress, done = (lambda row: bar.update(1)), bar.close
    else:                       # a log (CI): a plain line every tenth of the way
        progress, done = _log_progress(total), (lambda: None)
    for option, cols in (("--shaded-columns", args.shaded_columns),
                         ("--exact-columns", args.exact_columns),
                         ("--oracle-columns", args.oracle_columns)):
        if cols < 0 or cols == 1:
            from rt_core.errors import InputError
            raise InputError(f"{option} {cols}: give 0 (off) or a width of at least 2")
    # (validate() checks too, for its other callers; here it comes before evidence_run
    # removes an earlier run's evidence)
    check_memory(scenes, args.columns, precisions, args.shaded_columns, args.exact_columns,
                 args.oracle_columns)
    from tools.harness.validate import evidence_run
    with evidence_run(args.output):     # a run stopped while it reports leaves no evidence
        results = validate(scenes, args.columns, precisions, modes, args.output,
                           progress=progress, evidence=args.evidence,
                           shaded_columns=args.shaded_columns, pictures=bool(args.report),
                           plan=plan, exact_columns=args.exact_columns, code27=args.code27,
                           oracle_columns=args.oracle_columns)
        done()
        meta = dict(columns=args.columns, backend="llvm", reference="mitsuba llvm_ad_rgb",
                    exact_columns=args.exact_columns, oracle_columns=args.oracle_columns,
                    **versions(), ran=plan.describe())
        from rt_core.outputs import together
        page = None
        with together():                # the reports and the JUnit: all or none
            md, js = write_report(results, skipped, args.output, meta)
            if args.junit:
                from tools.harness.junit import write_junit
                from tools.harness.validate import comparison_cases, skip_case
                write_junit(args.junit, "rtval validate",
                            comparison_cases(results, "rtval.validate")
                            + [skip_case(s) for s in skipped])
            if args.report:
                from tools.harness.html_report import comparisons_report
                page = comparisons_report(args.report, "rtval validate", results, skipped,
                                          meta=meta)
    if page:
        print(f"report: {page}", file=sys.stderr)
    # (a file the two readers read differently fails the run as a failed comparison does)
    bad = [r for r in results if not r["ok"]] + failed_reading(skipped)
    from tools.harness.timing import split_line, time_split
    summary = (f"{len(results)} comparisons on {len(scenes)} scenes (skipped: "
               f"{skip_counts(skipped)}): {len(bad)} failed. Report: {md}, {js}\n"
               + split_line(time_split(results)))
    if args.json:
        from rt_core.outputs import json_text
        from tools.harness.validate import report_data
        print(json_text(report_data(results, skipped, meta)), end="")
        print(summary, file=sys.stderr)
        return 1 if bad else 0
    head = (f"{'scene':34s} {'mode':6s} {'prec':4s} {'pixels':>7s} {'explained':>9s} "
            f"{'unexpl':>6s} {'depth max rel':>13s} {'rt_core ms':>10s} {'Mitsuba ms':>10s}")
    print(head)
    for r in results:
        if r["mode"] in SHADED_MODES:       # explained: rounding and boundary; unexpl: wrong
            c = r["classes"]
            print(f"{row_stem(r)[:34]:34s} {r['mode']:6s} {'f64':4s} {r['pixels']:7d} "
                  f"{c['rounding'] + c['boundary']:9d} {c['wrong']:6d} {'(8-bit)':>13s} "
                  f"{r['rt_core_ms']:10.2f} {r['mitsuba_ms']:10.2f}"
                  + ("" if r["ok"] else "  FAIL"))
            continue
        print(f"{row_stem(r)[:34]:34s} {r['mode']:6s} {r['precision']:4s} "
              f"{r['pixels']:7d} {r['explained']:9d} {r['unexplained']:6d} "
              f"{r['depth']['max_rel']:13.2e} {r['rt_core_ms']:10.2f} {r['mitsuba_ms']:10.2f}"
              + ("" if r["ok"] else "  FAIL"))
    print(summary, file=sys.stderr)
    return 1 if bad else 0
