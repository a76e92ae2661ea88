"""rtval report: error against run time for rt_core f32/f64 and Mitsuba, every scene, several
resolutions."""
from __future__ import annotations

import sys

from .cmd_bench import fresh_kernel_cache
from .options import add_code27, positive_int


def add_parser(sub) -> None:
    p = sub.add_parser("report", help="error against run time, rt_core and Mitsuba",
                       description="Trace each scene (default scenes/*.txt) with rt_core f32, "
                                   "rt_core f64 and Mitsuba (preliminary and full "
                                   "intersection) at several resolutions; measure the error "
                                   "against the float64 oracle at sampled pixels, the first "
                                   "and steady-state run time and the peak memory. Writes "
                                   "report.md, report.json and error_vs_time.png.")
    p.add_argument("scenes", nargs="*", help="course scene files (default: scenes/*.txt)")
    p.add_argument("--quick", action="store_true",
                   help="3 resolutions (160, 640, 1920), 400 oracle pixels, 2 timed calls "
                        "(about 2 minutes and 2 GB of memory on the bundled scenes, 2 cores)")
    p.add_argument("--columns", type=positive_int, nargs="+", metavar="W",
                   help="resolutions (default 160 320 640 1280 1920)")
    p.add_argument("--sample", type=positive_int,
                   help="oracle pixels per scene and resolution (default 4000)")
    p.add_argument("--reps", type=positive_int, help="timed calls after the first (default 7)")
    p.add_argument("--keep-cache", action="store_true",
                   help="use Dr.Jit's on-disk kernel cache (default: an empty one, so that "
                        "first calls show compilation)")
    p.add_argument("-o", "--output", default="out/report", metavar="DIR")
    add_code27(p)
    p.set_defaults(func=run, before_import=lambda args: fresh_kernel_cache(args.keep_cache))


def run(args) -> int:
    from dataclasses import replace
    from pathlib import Path
    from tools.harness.agree import parse_agreed
    from tools.harness.report import QUICK, Settings, run_report, write_report
    from tools.harness.validate import REPO
    from rt_core.outputs import check_dir_target, claim_kernel_cache
    claim_kernel_cache()        # (this run's empty kernel cache marked, killed runs' gone)
    check_dir_target(args.output)            # refused before the run, not after it
    paths = args.scenes or sorted((REPO / "scenes").glob("*.txt"))
    scenes = [parse_agreed(p, args.code27) for p in paths]
    s = QUICK if args.quick else Settings()
    s = replace(s, **{k: v for k, v in (("columns", tuple(args.columns or ()) or None),
                                        ("sample", args.sample), ("reps", args.reps))
                      if v is not None})
    # too large a request: one line (exit 2) before any ray is traced, as render's (a
    # review: 20000 columns took 23.7 GB and the out-of-memory killer, no word)
    from rt_core.memory import guard, report_bytes
    for sc in scenes:
        for c in s.columns:
            guard(report_bytes, "report", c, sc.default_rows(c))

    def progress(rows):
        r = rows[0]
        print(f"report: {Path(r['scene']).name} {r['columns']}x{r['rows']}: "
              + ", ".join(f"{x['config']} {x['steady_ms']:.2f} ms" for x in rows)
              + (f" (note: {r['note']})" if r.get("note") else ""), file=sys.stderr)
    result = run_report(scenes, s, progress)
    md, js, png = write_report(result, args.output)
    print(f"{md}\n{js}\n{png}")
    print(f"report: {len(scenes)} scenes x {len(s.columns)} resolutions in "
          f"{result['meta']['run_s']} s", file=sys.stderr)
    return 0
