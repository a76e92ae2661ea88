"""Where `rtval validate`'s time goes, by function: the run's own split (rt_core, Mitsuba,
oracles, classification, other) is by phase; this runs validate in this process with a wall
clock around each of the functions below, and prints each one's seconds and calls (a
function called inside itself counted once), under the phase it is charged to.

    python benchmarks/validate_split.py [validate's options, e.g. -o DIR or scenes]

Validate runs in this process (``--serial``, unless the options name ``--workers``,
``--serial`` or ``--scheduler``: the clocks see only this process).  The clocks cost about a
microsecond a call: the run's own split moves by well under 1%.
"""
from __future__ import annotations

import collections
import functools
import importlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

# (phase, module, function, modules that imported it by name)
TIMED = [
    ("rt_core", "rt_core.render", "trace_geometry", ("tools.harness.compare",
                                                     "tools.harness.exact_compare")),
    ("rt_core", "rt_core.render", "render_image", ("tools.harness.shaded",)),
    ("rt_core", "rt_core.tracer", "_decide_flagged", ()),
    ("rt_core", "rt_core.decide", "decide_rays", ("rt_core.tracer",)),
    ("mitsuba", "mitsuba_ref.reference", "trace_rays", ("tools.harness.compare",)),
    ("mitsuba", "mitsuba_ref.reference", "render_camera", ("tools.harness.compare",)),
    ("mitsuba", "tools.harness.shaded", "mitsuba_course_image", ()),
    ("oracles", "mitsuba_ref.exact", "trace_exact", ("tools.harness.exact_compare",)),
    ("oracles", "mitsuba_ref.shade_oracle", "render_shade_oracle", ()),
    ("classify", "mitsuba_ref.explain", "classify", ("tools.harness.compare",)),
    ("classify", "mitsuba_ref.explain", "over_bound", ("tools.harness.compare",)),
    ("classify", "tools.harness.shaded", "classify_shaded", ()),
    ("classify", "mitsuba_ref.shade_oracle", "shade_pixels", ()),
    ("classify", "mitsuba_ref.shade_oracle", "other_sides_of", ()),
    ("classify", "mitsuba_ref.shade_oracle", "reaches", ()),
    ("classify", "tools.harness.flip", "flip_map", ()),
]


def clocked(seconds: collections.Counter, calls: collections.Counter):
    """Wrap every TIMED function (in its module and where it was imported by name)."""
    for _, mod, _, holders in TIMED:     # (all imported first: a holder imports the original)
        for target in (mod, *holders):
            importlib.import_module(target)
    for phase, mod, name, holders in TIMED:
        m = importlib.import_module(mod)
        f = getattr(m, name)
        key = (phase, f"{mod}.{name}")
        depth = [0]

        @functools.wraps(f)
        def g(*a, _f=f, _key=key, _depth=depth, **k):
            _depth[0] += 1
            t0 = time.perf_counter()
            try:
                return _f(*a, **k)
            finally:
                _depth[0] -= 1
                if not _depth[0]:
                    seconds[_key] += time.perf_counter() - t0
                    calls[_key] += 1
        for target in (mod, *holders):
            tm = importlib.import_module(target)
            assert getattr(tm, name) is f, f"{target}.{name} is not {mod}.{name}"
            setattr(tm, name, g)


def main() -> int:
    args = sys.argv[1:]
    made = None
    named = lambda *opts: any(a == o or a.startswith(o + "=") or (len(o) == 2 and
                                                                   a.startswith(o))
                              for a in args for o in opts)
    if not named("-o", "--output"):
        made = tempfile.mkdtemp(prefix="validate_split-")
        args += ["-o", made]
    if not named("--workers", "--serial", "--scheduler"):
        args += ["--serial"]            # (the clocks are in this process)
    seconds, calls = collections.Counter(), collections.Counter()
    clocked(seconds, calls)
    from tools.cli import main as rtval
    t0 = time.perf_counter()
    try:
        code = rtval(["validate", *args])
    except SystemExit as e:
        code = e.code
    wall = time.perf_counter() - t0
    if code not in (0, 1, None):
        # (validate refused its input and said why: no table, and no folder left behind)
        if made is not None:
            shutil.rmtree(made, ignore_errors=True)
        return code
    # (after --json's JSON on standard output, the table goes to standard error)
    out = sys.stderr if named("--json") else sys.stdout
    print(f"\nrtval validate: {wall:.2f} s wall (exit {code}); by function, wall seconds "
          "(nested calls of one function counted once; functions of one phase may nest):",
          file=out)
    print(f"{'phase':9s} {'function':48s} {'seconds':>8s} {'calls':>6s} {'ms/call':>8s}",
          file=out)
    for (phase, name), s in sorted(seconds.items(), key=lambda kv: (kv[0][0], -kv[1])):
        n = calls[(phase, name)]
        print(f"{phase:9s} {name:48s} {s:8.3f} {n:6d} {s / n * 1e3:8.2f}", file=out)
    return 0 if code in (0, None) else 1      # (1: some comparison failed; the table stands)


if __name__ == "__main__":
    sys.exit(main())
