"""rtval check: validate a user's own course tracer, pixel by pixel, with every difference
explained (tools/harness/check.py)."""
from __future__ import annotations

import os
import sys

from .options import (add_code27, add_max_dist, add_parallel, add_rules, add_texture_dir,
                      positive_int, timeout_seconds)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "check", help="check a course tracer's image (or run the tracer) against rt_core",
        description="Check the image a course tracer wrote for SCENE (binary/ASCII PPM or PNG; "
                    "its size gives the columns and rows), or with --run run the tracer on each "
                    "SCENE and check what it writes, or with --images check the images it left "
                    "in DIR, named after the scenes.  Every pixel is classed match, rounding, "
                    "boundary (within a float64 error bound of a decision), variant (explained "
                    "by a rule variant of real course programs, inferred from the image) or "
                    "wrong.  Exit 0 if no pixel is wrong, 1 if some are (or, with --run or "
                    "--images, a scene's run or image failed), 2 on bad input (with --run or "
                    "--images: a scene refused, and none failed).")
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="SCENE IMAGE; with --run or --images: one or more SCENEs")
    p.add_argument("--run", metavar="CMD",
                   help="the tracer's command line, with {scene} {out} {columns} {rows} and "
                        "optionally {hits}, e.g. './ray {columns} {rows} < {scene} > {out}'")
    p.add_argument("--images", metavar="DIR",
                   help="check the images a tracer left in DIR, one per SCENE named after "
                        "it (STEM.ppm, .pnm or .png): a directory of submitted images, "
                        "checked as --run checks what the tracer writes")
    p.add_argument("--columns", type=positive_int, default=None,
                   help="image width (with --run: required; with --images or an image: the "
                        "width each image must have, default its own)")
    p.add_argument("--rows", type=positive_int, default=None,
                   help="image height (default: int(h/w*columns) where --columns is given, "
                        "else the image's)")
    add_rules(p, "fix the rules instead of inferring them (edges, screen_clip, ties, t_min, "
                 "clip_spheres, reflect, rows, tile_add_first, tile_project); 'notes': "
                 "every rule as the notes say, so that a course variant fails")
    add_max_dist(p, "fix the reflection cut-off instead of inferring it")
    add_texture_dir(p)
    add_code27(p)
    p.add_argument("--hits", metavar="FILE",
                   help="a hit dump of the image: 'column row object t' per pixel")
    p.add_argument("--timeout", type=timeout_seconds, default=60.0, metavar="S",
                   help="with --run: seconds before a run is killed (default 60)")
    p.add_argument("--report", metavar="DIR",
                   help="write an HTML report into DIR (new, empty or an earlier report): "
                        "failures first, rt_core's image, yours and the classes side by side")
    p.add_argument("--junit", metavar="FILE", help="write JUnit XML (one test case per scene)")
    p.add_argument("--json", action="store_true", help="print the results as JSON on stdout")
    p.add_argument("--name", metavar="NAME",
                   help="whose tracer this is (a student's name): in the JUnit suite's and "
                        "classes' names and the report's title")
    add_parallel(p, "checks of --run's images (the tracer itself runs here)")
    p.set_defaults(func=run, usage_error=p.error)


def run(args) -> int:
    from rt_core.outputs import check_file_target
    from tools.harness.check import check_image, check_run
    kw = {"rules": args.rules, "max_dist": args.max_dist, "texture_dirs": args.texture_dir,
          "code27": args.code27}
    if args.report:                     # refused before the runs, not after them
        from tools.harness.html_report import check_target
        image = args.inputs[1] if args.run is None and args.images is None and \
            len(args.inputs) == 2 else None
        check_target(args.report, {"--junit": args.junit, "--hits": args.hits,
                                   "image": image})
    if args.junit:
        check_file_target(args.junit, make_dirs=False)
    if args.run is not None and args.images is not None:
        args.usage_error("--run or --images, not both")
    if args.run is not None or args.images is not None:
        # a scene listed twice (overlapping globs, scenes/x.txt and ./scenes/x.txt) is
        # checked once: --images refused both as two scenes of one name, --run checked it
        # twice (an instructor's review)
        seen: dict = {}
        for s in args.inputs:
            seen.setdefault(os.path.realpath(s), s)
        args.inputs = list(seen.values())
    # each scene's verdict on stderr as it is known, where someone watches (a terminal) or
    # asks (--verbose): a run of many scenes is not silent for minutes
    watch = sys.stderr if len(args.inputs) > 1 and (args.verbose or sys.stderr.isatty()) \
        else None
    if args.run is not None:
        if not args.run.strip():
            args.usage_error("--run: give the tracer's command line, e.g. "
                             "'./ray {columns} {rows} < {scene} > {out}'")
        if args.columns is None:
            args.usage_error("--run needs --columns (the image width to ask the tracer for)")
        for need in ("{scene}", "{out}"):
            if need not in args.run:
                args.usage_error(f"--run: the command must contain {need} (e.g. "
                                 "'./ray {columns} {rows} < {scene} > {out}')")
        if args.hits:
            args.usage_error("--hits is for a given image; with --run put {hits} in the "
                             "command")
        from tools.harness.check import misspelt_placeholder, quoted_placeholder
        said = misspelt_placeholder(args.run)
        if said:
            args.usage_error(f"--run: {said} (the placeholders: {{scene}} {{out}} "
                             "{columns} {rows} {hits})")
        said = quoted_placeholder(args.run)
        if said:
            args.usage_error(f"--run: {said}")
        from tools.harness.parallel import plan_of
        results = check_run(args.run, args.inputs, args.columns, args.rows, args.timeout,
                            plan_of(args), progress=watch, **kw)
    elif args.images is not None:
        if args.hits:
            args.usage_error("--hits is for one given image, not --images")
        if args.rows is not None and args.columns is None:
            args.usage_error("--images: --rows goes with --columns (the size every image "
                             "must have)")
        # (a missing directory is a student who handed in nothing: each scene an error, the
        # JUnit and the report written, exit 1; a file is the instructor's slip)
        if os.path.exists(args.images) and not os.path.isdir(args.images):
            print(f"rtval check: --images {args.images}: not a directory", file=sys.stderr)
            return 2
        from tools.harness.check import check_images
        from tools.harness.parallel import plan_of
        results = check_images(args.images, args.inputs, plan_of(args), progress=watch,
                               columns=args.columns, rows=args.rows, **kw)
    else:
        if args.scheduler or (args.workers or 0) > 1:
            args.usage_error("--workers/--scheduler: only with --run or --images (one image "
                             "is checked in this process)")
        if len(args.inputs) != 2:
            args.usage_error(f"expected SCENE IMAGE, got {len(args.inputs)} argument(s); for "
                             "several scenes use --run (your tracer) or --images DIR (its "
                             "images, named after the scenes)")
        results = [check_image(args.inputs[0], args.inputs[1], columns=args.columns,
                               rows=args.rows, hits_path=args.hits, **kw)]
    many = args.run is not None or args.images is not None
    single = len(results) == 1 and not many
    code = _exit_code(results, single, many)
    try:
        page = _write_outputs(args, results, single, kw)
        if sys.stdout is not None:
            sys.stdout.flush()          # (a full disk shows here)
    except OSError as e:
        # an output it cannot write: 2, bad input, unless a scene fails besides (README)
        if code == 1:
            e.exit_code = 1
        raise
    if page:
        print(f"report: {page}", file=sys.stderr)
    if single and results[0].status in ("error", "refused"):
        print(f"rtval check: {results[0].reason}", file=sys.stderr)
    return code


def _exit_code(results, single: bool, many: bool) -> int:
    """The README's exit codes of a check's results: 1 some scene fails (or, of several, has
    no image or run), 2 bad input with no failure besides, 0 every scene passes."""
    if single and results[0].status in ("error", "refused"):
        return 2
    if any(r.status == "fail" for r in results):
        return 1
    if any(r.status == "error" for r in results):
        return 1 if many else 2
    # (--run) a scene that could not be checked at all: malformed, or of a kind rtval
    # does not implement; it is listed as REFUSED
    if any(r.status == "refused" for r in results):
        return 2
    return 0


def _write_outputs(args, results, single: bool, kw: dict):
    """The verdicts on standard output (text or --json), the JUnit file and the HTML report;
    the report's page, or None."""
    from tools.harness.check import junit_xml, text_report
    if args.json:                       # (strict JSON: a t of NaN in a hit dump as "nan")
        from rt_core.outputs import json_text
        sys.stdout.write(json_text([r.summary() for r in results]))
    elif not (single and results[0].status in ("error", "refused")):
        print(text_report(results))     # (one image it could not check: its one line below)
    from rt_core.outputs import atomic_write, together
    page = None
    with together():                    # the JUnit and the report: both or neither
        if args.junit:
            text = junit_xml(results, args.name)

            def write(tmp):
                with open(tmp, "w", encoding="utf-8") as f:
                    f.write(text)
            atomic_write(args.junit, write)
        if args.report:
            from tools.harness.html_report import check_report
            page = check_report(args.report, results, args.name, run=args.run, rows=args.rows,
                                hits=args.hits, timeout=args.timeout, columns=args.columns,
                                **kw)
    return page
