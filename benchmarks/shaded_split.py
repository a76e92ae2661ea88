"""Where a shaded image's time goes: `rtval bench --shaded`'s scene and work (one reflection
bounce) with parts left out, rt_core against Mitsuba doing the same rays, interleaved in
this process.  Four variants of each side:

    primary      no lights, no reflection: the primary hits and their shading
    +reflection  no lights: the primary hits and the reflection rays' closest hits
    +shadows     no reflection: the primary hits and one shadow ray per light
    full         the bench's work (+reflection +shadows and the reflection hits' shadows)

so that +reflection − primary is what the reflection rays' closest hits cost, +shadows −
primary what the primary hits' shadow rays cost, and the rest of full what the reflection
hits' shadow rays cost.  Prints per variant and side the median [min-max] of the wall time
and of the process CPU time (all threads; steadier than wall time on a busy machine).

    python benchmarks/shaded_split.py spheres 16 [--precision f32] [--reps 5]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402

from rt_core import backend  # noqa: E402
from rt_core.camera import make_camera, primary_directions  # noqa: E402
from tools.harness.bench import SCENES  # noqa: E402
from tools.harness.bench_shaded import (DEFAULT_LIGHTS, MAX_DIST, mitsuba_side,  # noqa: E402
                                        rt_side, shaded_scene)

VARIANTS = {"primary": (0, 0.0), "+reflection": (0, MAX_DIST),
            "+shadows": (DEFAULT_LIGHTS, 0.0), "full": (DEFAULT_LIGHTS, MAX_DIST)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", choices=SCENES)
    p.add_argument("objects", type=int)
    p.add_argument("--precision", choices=("f32", "f64"), default="f32")
    p.add_argument("--columns", type=int, default=1920)
    p.add_argument("--reps", type=int, default=5)
    a = p.parse_args()
    scene = shaded_scene(a.scene, a.objects)
    cam = make_camera(scene, a.columns)
    d32 = primary_directions(scene, cam, backend.types("f32"))
    dr.eval(d32)
    sides = {}
    for name, (lights, max_dist) in VARIANTS.items():
        sc = shaded_scene(a.scene, a.objects, lights)
        sides[name, "rt_core"] = rt_side(name, sc, a.precision, d32, max_dist).run
        sides[name, "mitsuba"] = mitsuba_side(sc, d32, cam.columns, max_dist).run
    for run in sides.values():          # compiled, and Mitsuba's second call
        run()
        run()
    wall = {k: [] for k in sides}
    cpu = {k: [] for k in sides}
    for _ in range(a.reps):
        for k, run in sides.items():
            dr.sync_thread()
            t0, c0 = time.perf_counter(), time.process_time()
            run()
            dr.sync_thread()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)

    def ms(v):
        return f"{statistics.median(v) * 1e3:7.1f} [{min(v) * 1e3:.0f}-{max(v) * 1e3:.0f}]"
    print(f"{a.scene} N={a.objects} {a.precision}, {a.reps} interleaved calls: ms, median "
          "[min-max]")
    for name in VARIANTS:
        for side in ("rt_core", "mitsuba"):
            k = (name, side)
            print(f"  {name:12s} {side:8s} wall {ms(wall[k])}   cpu {ms(cpu[k])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
