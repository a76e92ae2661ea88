"""A small scene's speed before and after a large scene in the same process, rt_core traced
with Dr.Jit's value numbering on and off (rt_core/backend.py ``VALUE_NUMBERING``): the
table Dr.Jit keeps for it never shrinks, so a large scene (Mitsuba's of 4096 finite
planes, as ``rtval bench`` loads before its spheres) slows every operation traced after it.

Prints, for the bench's primary rays (``rtval bench``) and shaded image (``--shaded``) of
16 spheres, rt_core f32 and Mitsuba in wall ms (median of the timed calls, interleaved),
first in a fresh process, then after loading and tracing the large scene.

    python benchmarks/after_large_scene.py [--objects 4096] [--reps 15]
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
from tools.harness.bench import bench_scene, mitsuba_tracer, rt_tracer  # noqa: E402
from tools.harness.bench_shaded import (MAX_DIST, mitsuba_side, rt_side,  # noqa: E402
                                        shaded_scene)


def sides(mode: str):
    """{name: run} of rt_core f32 with value numbering on and off, and Mitsuba."""
    scene = (shaded_scene if mode == "shaded" else bench_scene)("spheres", 16)
    cam = make_camera(scene, 1920)
    d = primary_directions(scene, cam, backend.types("f32"))
    dr.eval(d)
    out = {}
    for vn in (True, False):
        backend.VALUE_NUMBERING = vn
        rt = (rt_side("rt", scene, "f32", d, MAX_DIST) if mode == "shaded" else
              rt_tracer("rt", scene, "f32", d))
        out[f"rt_core VN {'on' if vn else 'off'}"] = (rt.run, vn)
    mi = (mitsuba_side(scene, d, cam.columns, MAX_DIST) if mode == "shaded" else
          mitsuba_tracer(scene, d, cam.columns))
    out["mitsuba"] = (mi.run, None)
    return out


def timed(runs: dict, reps: int) -> dict:
    for run, vn in runs.values():              # compiled, and Mitsuba's second call
        if vn is not None:
            backend.VALUE_NUMBERING = vn
        run()
        run()
    t = {k: [] for k in runs}
    for _ in range(reps):
        for k, (run, vn) in runs.items():
            if vn is not None:
                backend.VALUE_NUMBERING = vn
            dr.sync_thread()
            t0 = time.perf_counter()
            run()
            dr.sync_thread()
            t[k].append(time.perf_counter() - t0)
    return {k: statistics.median(v) * 1e3 for k, v in t.items()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", type=int, default=4096)
    p.add_argument("--reps", type=int, default=15)
    a = p.parse_args()
    modes = {m: sides(m) for m in ("primary", "shaded")}
    before = {m: timed(r, a.reps) for m, r in modes.items()}
    # the large scene: Mitsuba's finite planes, loaded and traced (as rtval bench does)
    scene = bench_scene("fplanes", a.objects)
    cam = make_camera(scene, 1920)
    d = primary_directions(scene, cam, backend.types("f32"))
    big = mitsuba_tracer(scene, d, cam.columns)
    big.run()
    del big
    after = {m: timed(r, a.reps) for m, r in modes.items()}
    print(f"spheres 16, wall ms, median of {a.reps}; before / after Mitsuba's "
          f"{a.objects} finite planes in this process")
    for m in modes:
        for k in before[m]:
            print(f"  {m:8s} {k:16s} {before[m][k]:7.2f} / {after[m][k]:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
