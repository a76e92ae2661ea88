"""rtval stability: generated stiff and extreme scenes, rt_core and Mitsuba against the exact
oracle (tools.harness.stability does the work)."""
from __future__ import annotations

import contextlib
import os
import sys

from .options import add_parallel, at_most

# --seeds at most this: a quick run of every case takes most of a minute a seed, so 1000 seeds
# are half a day (an unbounded count made range() of it raise MemoryError, or ran on forever)
MAX_SEEDS = 1000

FAMILY_HELP = ("grazing distance size window offset far_square orient normal edges viewpoint "
               "ties tangent tiny_sphere straddle parallel")


def add_parser(sub) -> None:
    p = sub.add_parser("stability", help="stiff and extreme cases against the exact oracle",
                       description="Generate seeded families of stiff scenes (grazing "
                                   "incidence, far and tiny objects, tiny and huge windows, "
                                   "edges, ties, tangents, planes through the viewpoint, ...), "
                                   "each swept over its parameter; trace them with rt_core "
                                   "(f32, f64), Mitsuba (f32) and the notes' naive float32 "
                                   "formulation; judge every ray against the exact rational "
                                   "oracle. Prints a table (stdout), writes a log-log plot per "
                                   "family. Exit 0 iff on every case rt_core f32 has no more "
                                   "unexplained mask/id mismatches than Mitsuba, rt_core f64 "
                                   "none and depth within 1e-12 where the condition number "
                                   "allows, and no rt_core output is NaN or Inf; 1 otherwise.")
    p.add_argument("--quick", action="store_true",
                   help="first, middle and last parameter of each family, 24x18 rays "
                        "(well under a minute); default: every parameter, 64x48 rays")
    p.add_argument("--families", nargs="+", metavar="NAME", default=None,
                   help=f"only these families (default all: {FAMILY_HELP})")
    p.add_argument("--seeds", type=at_most(MAX_SEEDS, "each seed runs every case again: "
                                           "--quick takes most of a minute a seed"),
                   default=1, metavar="N",
                   help=f"run N seeds (0..N-1) of every case (default 1; at most {MAX_SEEDS})")
    p.add_argument("--json", nargs="?", const="-", metavar="FILE",
                   help="print the results as JSON on stdout (the tables go to stderr), as "
                        "rtval's other commands do; with FILE write them there instead")
    p.add_argument("--junit", metavar="FILE.xml",
                   help="also write JUnit XML: one test case per generated case, a failure "
                        "for each case that misses the bar")
    p.add_argument("-o", "--output", metavar="DIR", default="out/stability",
                   help="where stability.png goes (default out/stability)")
    add_parallel(p, "cases")
    p.set_defaults(func=run, usage_error=p.error)


def run(args) -> int:
    from tqdm import tqdm
    from rt_core.render import versions
    from tools.harness import stability as S
    from tools.harness.parallel import plan_of

    # (a family named twice runs once: its cases twice made duplicate JUnit names)
    fams = list(dict.fromkeys(args.families or S.FAMILIES))
    unknown = [f for f in fams if f not in S.FAMILIES]
    if unknown:
        args.usage_error(f"unknown famil{'y' if len(unknown) == 1 else 'ies'} "
                         f"{', '.join(unknown)}; expected some of {', '.join(S.FAMILIES)}")
    # the outputs refused before the cases run, not after them
    from rt_core.outputs import check_dir_target, check_file_target
    for f in (args.json if args.json not in (None, "-") else None, args.junit):
        if f:
            check_file_target(f, make_dirs=False)
    check_dir_target(args.output)
    mode = "quick" if args.quick else "full"
    seeds = tuple(range(args.seeds))
    total = len(S.case_specs(mode, fams, seeds))
    plan = plan_of(args).resolve(total, S.SECONDS_PER_CASE[mode], S.SERIAL_BUSY_CORES)
    bar = tqdm(total=total, file=sys.stderr, unit="case", disable=None)
    results = S.run_suite(mode, fams, seeds, progress=lambda r: bar.update(1), plan=plan)
    bar.close()
    to_json = args.json == "-"      # stdout is the JSON's; the tables go to stderr
    tables = contextlib.redirect_stdout(sys.stderr) if to_json else contextlib.nullcontext()
    with tables:
        print(S.table(results))
        summ = S.summary(results)
        print()
        print(f"{'family':12s} {'cases':>5s}  {'rt_f32 unexpl':>13s} {'mitsuba unexpl':>14s} "
              f"{'naive unexpl':>12s} {'rt_f64 unexpl':>13s} {'f64 >1e-12':>10s} "
              f"{'rt nonfinite':>12s}  ok")
        for fam, f in summ.items():
            g = lambda t, k: f.get(t, {}).get(k, 0)
            print(f"{fam:12s} {f['cases']:5d}  {g('rt_f32', 'unexplained'):13d} "
                  f"{g('mitsuba', 'unexplained'):14d} {g('naive_f32', 'unexplained'):12d} "
                  f"{g('rt_f64', 'unexplained'):13d} {g('rt_f64', 'over_target'):10d} "
                  f"{g('rt_f32', 'nonfinite') + g('rt_f64', 'nonfinite'):12d}  "
                  f"{'yes' if f['ok'] else 'NO'}")
        head = S.headline(results)
        if head:
            print("\nthe issue's case (square of side 2e-7·D tilted 50°, D away, 1e-6 window): "
                  "fraction of the square's pixels missed")
            for row in head:
                print(f"  D = {row['distance']:<8g} exact hits {row['exact_hits']:4d}:  "
                      + "  ".join(f"{k} {row[k]:.1%}" for k in S.TRACERS if k in row))
    meta = dict(mode=mode, seeds=list(seeds), backend="llvm", precisions="f32 f64",
                reference="mitsuba llvm_ad_rgb", **versions(), ran=plan.describe())
    plot = os.path.join(args.output, "stability.png")
    from rt_core.outputs import together
    said = []
    with together():                    # the plot, the JSON and the JUnit: all or none
        S.write_plot(results, plot, {f"rtval.{k}": v for k, v in meta.items()})
        said.append(f"plot: {plot}")
        if args.json and not to_json:
            S.write_json(results, args.json, meta)
            said.append(f"json: {args.json}")
        if args.junit:
            from tools.harness.junit import stability_cases, write_junit
            write_junit(args.junit, "rtval stability", stability_cases(results))
            said.append(f"junit: {args.junit}")
    for line in said:                   # each file named once all are in place
        print(line, file=sys.stderr)
    if to_json:
        from rt_core.outputs import json_text
        print(json_text(S.report_data(results, meta)), end="")
    bad = [fam for fam, f in summ.items() if not f["ok"]]
    if bad:
        print(f"rtval stability: bar not met in: {', '.join(bad)}", file=sys.stderr)
    return 1 if bad else 0
