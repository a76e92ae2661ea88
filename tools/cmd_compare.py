"""rtval compare: one scene, rt_core against Mitsuba, every pixel classed."""
from __future__ import annotations

import json
import sys

from .options import add_code27, add_image_options, add_max_dist, add_texture_dir, given


EVIDENCE_DIR = "out/compare"


def add_parser(sub) -> None:
    p = sub.add_parser("compare", help="compare rt_core with Mitsuba on one scene",
                       description="Compare hit mask, object id and depth of rt_core with "
                                   "Mitsuba 3. Exit 0 if no pixel is unexplained and the depth "
                                   "error is within its bound, 1 otherwise (evidence EXRs are "
                                   "written and their paths printed), 2 on bad input.")
    p.add_argument("scene")
    add_image_options(p)
    p.add_argument("--mode", choices=("rays", "camera", "both", "exact"), default="both",
                   help="rays: Mitsuba traces rt_core's exact rays; camera: Mitsuba's own "
                        "perspective sensor (default: both); exact: every object (cones, "
                        "ellipsoids and the torus too, which Mitsuba lacks) against the exact "
                        "oracle, in rational arithmetic on the course's ideal rays (slow: "
                        "0.1-0.3 s per 2,000 pixels of the course scenes with them)")
    p.add_argument("--shaded", action="store_true",
                   help="compare the shaded 8-bit course image instead: rt_core (float64) "
                        "against Mitsuba's 'course' integrator, each pixel match, rounding "
                        "(±1 at an 8-bit level), boundary (a decision within float32's bound, "
                        "from the float64 shading oracle) or wrong; exit 1 on a wrong pixel")
    p.add_argument("--reference", choices=("mitsuba", "oracle"), default=None,
                   help="with --shaded: the reference image, Mitsuba's (default) or the "
                        "float64 shading oracle's, every object (cones, ellipsoids and the "
                        "torus too), each decision within float64's bound (slow: 0.3-1.6 ms "
                        "a pixel; at most 20,000 pixels)")
    add_max_dist(p, "--shaded: reflections stop at this path length (default 1000)")
    add_texture_dir(p)
    add_code27(p)
    p.add_argument("--evidence", metavar="DIR",
                   help=f"where evidence EXRs go on failure (default {EVIDENCE_DIR})")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--report", metavar="DIR",
                   help="also write an HTML report into DIR (new, empty or an earlier "
                        "report): Mitsuba's picture, rt_core's and the classes per mode")
    p.add_argument("--junit", metavar="FILE.xml",
                   help="also write JUnit XML, one test case per mode")
    p.set_defaults(func=run, usage_error=p.error)


def run(args) -> int:
    from tools.harness.agree import parse_agreed
    from rt_core.rules import Rules
    from tools.harness.compare import compare, write_evidence
    from tools.harness.html_report import comparison_pictures
    from tools.harness.validate import public, stem_of

    if args.reference is not None and not args.shaded:
        args.usage_error("--reference goes with --shaded (the geometry's reference is the "
                         "mode: --mode exact for the exact oracle)")
    if args.max_dist is not None and not args.shaded:
        args.usage_error("--max-dist goes with --shaded (the geometry comparison has no "
                         "reflections)")
    # the outputs refused before the comparison, not after it (the default evidence
    # directory is not probed: it is written only if a comparison fails)
    from rt_core.outputs import check_dir_target, check_file_target
    if args.evidence is None:
        args.evidence = EVIDENCE_DIR
    else:
        check_dir_target(args.evidence)
    if args.report:
        from tools.harness.html_report import check_target
        check_target(args.report, {"--evidence": args.evidence, "--junit": args.junit})
    if args.junit:
        check_file_target(args.junit, make_dirs=False)
    if args.shaded and given(args.precision):
        args.usage_error("--precision does not apply with --shaded: the course image is "
                         "rt_core's float64 one against Mitsuba's")
    scene = parse_agreed(args.scene, args.code27)     # (tools/harness/agree.py)
    if args.shaded:
        return _run_shaded(args, scene)
    modes = ("rays", "camera") if args.mode == "both" else (args.mode,)
    ok, rows = True, []
    for mode in modes:
        if mode == "exact":
            from tools.harness.exact_compare import compare_exact
            cmp = compare_exact(scene, args.columns, args.precision, args.rules or Rules(),
                                args.backend, args.code27, rows=args.rows,
                                sampling=args.sampling)
        else:
            cmp = compare(scene, args.columns, args.rows, args.precision, mode, args.sampling,
                          args.rules or Rules(), args.backend)
        row = cmp.summary()
        if cmp.note:
            print(f"rtval compare: note: {cmp.note}", file=sys.stderr)
        if not cmp.ok:
            ok = False
            row["evidence"] = write_evidence(cmp, args.evidence,
                                             f"{stem_of(scene.path)}.{mode}.{args.precision}")
        if args.report:
            row["pictures"] = comparison_pictures(cmp)
        rows.append(row)
        if not args.json:
            d = row["depth"]
            classes = " ".join(f"{k}={v}" for k, v in row["classes"].items() if v)
            print(f"{mode:6s} {args.precision} {row['columns']}x{row['rows']}: {classes}")
            print(f"       depth over {d['pixels']} same-object pixels: max rel {d['max_rel']:.3g}"
                  f", p99 {d['p99_rel']:.3g}, mean {d['mean_rel']:.3g}, over bound "
                  f"{d['over_bound']}" + (f", at an open quadric's other root within reach "
                                          f"{d['other_root']}" if d.get("other_root") else ""))
            for path in row.get("evidence", []):
                print(f"       evidence: {path}")
    if args.junit:
        from tools.harness.validate import comparison_cases
        from tools.harness.junit import write_junit
        write_junit(args.junit, "rtval compare", comparison_cases(rows, "rtval.compare"))
    _report(args, rows)
    if args.json:
        json.dump([public(r) for r in rows], sys.stdout, indent=1)
        print()
    else:
        print(f"{'PASS' if ok else 'FAIL'} {args.scene}: {len(rows)} comparison"
              f"{'s' if len(rows) != 1 else ''}, "
              + ("no unexplained pixel, depth within its bound" if ok else
                 f"{sum(not r.get('ok', True) for r in rows)} failed")
              + ("" if modes == ("exact",) else _left_out(scene)))   # (exact: every object)
    return 0 if ok else 1


def _left_out(scene, shaded: bool = False) -> str:
    """'; N of its M objects not compared ...' where objects were left out of the comparison
    (no Mitsuba shape, or a sphere holding the viewpoint in a shaded one), said in the verdict: on
    stderr only, a scene of an ellipsoid alone read 'PASS' (a review)."""
    from mitsuba_ref.convert import mitsuba_subset
    from tools.harness.shaded import SHADED_KINDS
    kept, note = mitsuba_subset(scene, (lambda k: k in SHADED_KINDS) if shaded else
                                (lambda k: True), inside=shaded)
    if not note:
        return ""
    n = len(scene.objects) - len(kept.objects)
    return (f"; {n} of its {len(scene.objects)} objects not compared (named above: "
            "`rtval validate` compares every object with rtval's oracles)")


def _run_shaded(args, scene) -> int:
    from rt_core.rules import Rules
    from rt_core.shading import DEFAULT_MAX_DIST
    from tools.harness.html_report import comparison_pictures
    from tools.harness.shaded import compare_shaded, write_shaded_evidence
    from tools.harness.validate import public, stem_of
    from rt_core.textures import attach
    max_dist = DEFAULT_MAX_DIST if args.max_dist is None else args.max_dist
    scene = attach(scene, args.texture_dir)       # the shaded image needs the textures
    cmp = compare_shaded(scene, args.columns, args.rows, args.sampling, args.rules or Rules(),
                         max_dist, reference=args.reference or "mitsuba")
    them = "the shading oracle" if cmp.reference == "oracle" else "Mitsuba"
    row = cmp.summary()
    if cmp.note and not args.json:          # (objects left out: said, as the geometry's is)
        print(f"rtval compare: note: {cmp.note}", file=sys.stderr)
    if not cmp.ok:
        row["evidence"] = write_shaded_evidence(cmp, args.evidence, stem_of(scene.path))
    if args.report:
        row["pictures"] = comparison_pictures(cmp)
    if args.junit:
        from tools.harness.validate import comparison_cases
        from tools.harness.junit import write_junit
        write_junit(args.junit, "rtval compare", comparison_cases([row], "rtval.compare"))
    _report(args, [row])
    if args.json:
        json.dump([public(row)], sys.stdout, indent=1)
        print()
        return 0 if cmp.ok else 1
    classes = " ".join(f"{k}={v}" for k, v in row["classes"].items() if v)
    ref = "float64 shading oracle" if cmp.reference == "oracle" else \
        "Mitsuba course integrator"
    print(f"{row['mode']} rt_core f64 / {ref} {row['columns']}x{row['rows']}: "
          f"{classes}; FLIP mean {row['flip_mean']:.4g}")
    if row["boundary_reasons"]:
        from tools.harness.shaded import BOUNDARY_REASONS
        words = dict(BOUNDARY_REASONS, primary="the primary ray's hit (the geometry "
                     "classifier's reasons: rtval compare without --shaded)")
        bits = "float64" if cmp.reference == "oracle" else "float32"
        print(f"       boundary pixels by the decision within {bits}'s rounding there: " +
              "; ".join(f"{words[k]}: {n}" for k, n in row["boundary_reasons"].items()))
    for x, y, ours, theirs in row["worst"]:
        print(f"       wrong pixel (column {x}, row {y}): rt_core {ours}, {them} {theirs}")
    for path in row.get("evidence", []):
        print(f"       evidence: {path}")
    print(f"{'PASS' if cmp.ok else 'FAIL'} {args.scene}: {row['mode']}, "
          + ("no wrong pixel" if cmp.ok else f"{row['wrong']} wrong pixels")
          + ("" if cmp.reference == "oracle" else _left_out(scene, shaded=True)))
    return 0 if cmp.ok else 1


def _report(args, rows) -> None:
    if args.report:
        from tools.harness.html_report import comparisons_report
        page = comparisons_report(args.report, "rtval compare", rows, rows_given=args.rows)
        print(f"report: {page}", file=sys.stderr)
