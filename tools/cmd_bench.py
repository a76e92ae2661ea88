"""rtval bench: rt_core f32/f64 against Mitsuba's preliminary intersection, each case in a
process of its own (tools/harness/isolate.py)."""
from __future__ import annotations

import json
import os
import sys
import tempfile

from .options import at_most, positive_int

# tools.harness.bench's DEFAULT_OBJECTS and SCENES (not imported here: importing rt_core loads
# Dr.Jit, which must see DRJIT_CACHE_DIR first; tests/test_report.py checks they agree)
DEFAULT_OBJECTS = (1, 16, 64, 256, 1024)
SCENES = ("fplanes", "spheres", "mixed")
# tools.harness.bench_shaded's SHADED_OBJECTS, DEFAULT_LIGHTS and TRACERS (same reason)
SHADED_OBJECTS = (1, 16, 256, 4096)
DEFAULT_LIGHTS = 4
# the largest object count and light count a bench takes (16 and 16 times the largest it
# reports on; beyond, its tables grow without a memory guard)
MAX_OBJECTS = 1 << 16
MAX_LIGHTS = 64
SHADED_TRACERS = ("rt_core-f32", "rt_core-f64", "mitsuba")


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="throughput of rt_core against Mitsuba",
                       description="Trace identical 1920x1080 camera rays with rt_core (f32, "
                                   "f64) and Mitsuba 3 (ray_intersect_preliminary) against N "
                                   "finite planes, N spheres and a mixed scene, interleaved, "
                                   "each case in a process of its own: Mrays/s, first call "
                                   "(compilation), scene preparation, peak memory, and the "
                                   "ratio rt_core/Mitsuba. "
                                   "Compare ratios, not absolute times, on a shared machine.")
    p.add_argument("--objects", type=at_most(MAX_OBJECTS, "the scenes' tables grow with it"),
                   nargs="+", default=None,
                   metavar="N", help=f"object counts (default: {' '.join(map(str, DEFAULT_OBJECTS))}; "
                                     f"--shaded: {' '.join(map(str, SHADED_OBJECTS))})")
    p.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES),
                   help="scene kinds (default: all)")
    p.add_argument("--columns", type=positive_int, default=1920,
                   help="rays per row; rows follow the 16:9 window (default 1920 -> 1080)")
    p.add_argument("--reps", type=positive_int, default=None,
                   help="timed calls per tracer, round-robin (default 9; --shaded 5); the "
                        "median counts")
    p.add_argument("--threads", type=at_most(1024, "each is a thread of Dr.Jit's pool"),
                   default=None,
                   help="Dr.Jit worker threads (default: Dr.Jit's, one per core)")
    p.add_argument("--brute", action="store_true",
                   help="also time rt_core f32 without screen-space bins (a loop over every "
                        "object) and fully unrolled (up to 64 objects)")
    p.add_argument("--one-process", action="store_true",
                   help="run every case in this process (default: each in a process of its "
                        "own, after a warm-up case there: in one process a case's times "
                        "depended on the cases run before it)")
    p.add_argument("--keep-cache", action="store_true",
                   help="use Dr.Jit's on-disk kernel cache (default: an empty one, so that "
                        "rt_core's first calls show compilation; Mitsuba's primary-ray kernel, "
                        "the same for every scene, is made in the first case or warm-up)")
    p.add_argument("--shaded", action="store_true",
                   help="time the course's whole shading instead (primary hit, one shadow ray "
                        "per light per hit, one reflection bounce with its shadows) against "
                        "Mitsuba casting the same rays (ray_intersect_preliminary, ray_test) on "
                        "the scenes with reflective objects and --lights lights")
    p.add_argument("--lights", type=at_most(MAX_LIGHTS, "each is a shadow ray a pixel"),
                   default=DEFAULT_LIGHTS,
                   help=f"--shaded: point lights (default {DEFAULT_LIGHTS})")
    p.add_argument("--tracers", nargs="+", choices=SHADED_TRACERS,
                   default=list(SHADED_TRACERS),
                   help="--shaded: which sides to time (default: all; mitsuba is needed for "
                        "the ratios)")
    p.add_argument("--command", action="store_true", dest="whole_command",
                   help="time whole `rtval render` runs instead (a new process each), split "
                        "into import (the start-up too), parse, kernel, write and exit")
    p.add_argument("--command-columns", type=positive_int, nargs="+", default=[1920, 7680],
                   metavar="N", help="--command: image widths (default: 1920 7680)")
    p.add_argument("--scene", metavar="SCENE",
                   help="--command: the scene to render (default: scenes/mixed.txt)")
    p.add_argument("--runs", type=positive_int, default=3,
                   help="--command: runs per case, interleaved (default 3)")
    p.add_argument("--backend", choices=("llvm", "cuda"), default="llvm",
                   help="Dr.Jit backend of both sides (cuda: rt_core on the GPU against "
                        "Mitsuba's cuda_ad_rgb variant, OptiX); every mode (default llvm)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("-o", "--output", metavar="FILE.json", help="also write the JSON here")
    p.set_defaults(func=run, usage_error=p.error, before_import=lambda args: fresh_kernel_cache(args.keep_cache))


def fresh_kernel_cache(keep: bool) -> None:
    """Point Dr.Jit at an empty kernel cache (unless ``keep``), so that first calls compile;
    only possible before Dr.Jit is imported."""
    if not keep and "drjit" not in sys.modules:
        import atexit
        import shutil
        # (its PID in the name: a killed run's is found and removed by the next one,
        # rt_core.outputs.claim_kernel_cache, which marks it once rt_core can be imported)
        path = tempfile.mkdtemp(prefix=f"rtval-kernels-{os.getpid()}-")
        atexit.register(shutil.rmtree, path, True)      # runs after Dr.Jit's own exit hooks
        os.environ["DRJIT_CACHE_DIR"] = path


def _not_used(args) -> str | None:
    """The options given that the chosen mode does not use, in words (each option's help
    names its mode): they were accepted and ignored, exit 0 (a review)."""
    if args.whole_command:
        mode = "--command"
        unused = {"--objects": args.objects is not None, "--reps": args.reps is not None,
                  "--threads": args.threads is not None, "--brute": args.brute,
                  "--one-process": args.one_process,
                  "--scenes": list(args.scenes) != list(SCENES),
                  "--columns": args.columns != 1920}
    else:
        mode = "--shaded" if args.shaded else "the default mode (primary rays)"
        unused = {"--command-columns": args.command_columns != [1920, 7680],
                  "--scene": args.scene is not None, "--runs": args.runs != 3}
    if not args.shaded:
        unused.update({"--lights": args.lights != DEFAULT_LIGHTS,
                       "--tracers": list(args.tracers) != list(SHADED_TRACERS)})
    given = [o for o, v in unused.items() if v]
    return f"{', '.join(given)} not used by {mode}" if given else None


def run(args) -> int:
    if args.shaded and (args.whole_command or args.brute):
        args.usage_error(f"--shaded and {'--command' if args.whole_command else '--brute'} "
                         "do not go together (--shaded is a mode of its own)")
    said = _not_used(args)
    if said:
        args.usage_error(said + " (each option's help names the mode it belongs to)")
    from rt_core.backend import require
    from rt_core.outputs import claim_kernel_cache
    claim_kernel_cache()        # (this run's empty kernel cache marked, killed runs' gone)
    require(args.backend)       # no CUDA device: one line, exit 2, before any work
    if args.output:             # refused before the run, not after it
        from rt_core.outputs import check_file_target
        check_file_target(args.output)
    if args.whole_command:      # (not args.command: that is the subcommand's name)
        return run_command(args)
    # too large a request: one line (exit 2) before any ray is traced
    from functools import partial
    from rt_core.memory import bench_bytes, guard
    from tools.harness.bench import bench_scene
    rows = bench_scene("mixed", 1).default_rows(args.columns)
    guard(partial(bench_bytes, shaded=args.shaded), "bench" + (" --shaded" if args.shaded
                                                                 else ""), args.columns, rows)
    if args.threads:
        import drjit as dr
        dr.set_thread_count(args.threads)
    if args.shaded:
        return run_shaded(args)
    from tools.harness.bench import run_bench, table

    def progress(case):
        f32 = case["tracers"].get("rt_core-f32", {})
        print(f"bench: {case['scene']} N={case['objects']}: rt_core f32 "
              f"{f32.get('mrays_per_s', 0):.0f} Mrays/s, "
              f"{case.get('ratio_f32_vs_mitsuba', 0):.2f}x Mitsuba", file=sys.stderr)
    objects = list(dict.fromkeys(args.objects or DEFAULT_OBJECTS))      # each count once
    result = run_bench(objects, args.scenes, args.columns, args.reps or 9, args.brute,
                       progress=progress, backend_name=args.backend,
                       isolated=not args.one_process, threads=args.threads)
    return _emit(args, result, table)


def run_shaded(args) -> int:
    from tools.harness.bench_shaded import run_shaded as bench, shaded_table

    def progress(case):
        f32 = case["tracers"].get("rt_core-f32", {})
        print(f"bench --shaded: {case['scene']} N={case['objects']}: rt_core f32 "
              f"{f32.get('median_ms', 0):.0f} ms, "
              f"{case.get('ratio_f32_vs_mitsuba', 0):.2f}x Mitsuba", file=sys.stderr)
    objects = list(dict.fromkeys(args.objects or SHADED_OBJECTS))
    result = bench(objects, args.scenes, args.columns, args.reps or 5, args.lights,
                   list(dict.fromkeys(args.tracers)), progress=progress,
                   backend_name=args.backend, isolated=not args.one_process,
                   threads=args.threads)
    return _emit(args, result, shaded_table)


def run_command(args) -> int:
    from tools.harness.bench import command_bench, command_table

    def progress(c, out, rep, p):
        print(f"bench: render {c} columns {out} run {rep + 1}: {p['wall']:.2f} s (kernel "
              f"{p['kernel']:.2f}, write {p['write']:.2f})", file=sys.stderr)
    result = command_bench(list(dict.fromkeys(args.command_columns)), args.runs,
                           scene=args.scene, progress=progress, backend_name=args.backend)
    return _emit(args, result, command_table)


def _emit(args, result, table) -> int:
    text = json.dumps(result, indent=1)
    if args.output:
        from pathlib import Path
        from rt_core.exrio import atomic_write
        atomic_write(args.output, lambda tmp: Path(tmp).write_text(text + "\n"))
    print(text if args.json else table(result))
    return 0
