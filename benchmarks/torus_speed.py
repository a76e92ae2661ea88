"""Primary-ray throughput of the torus kernel against the sphere's, in this process: the
closest hit of every camera ray of scenes/torus.txt (a torus, a sphere in its hole, a plane)
and of the same scene with its torus replaced by the sphere (centre, R + r), f32 and f64
(f64 with its certified decisions and the exact re-decision of flagged rays), interleaved;
prints Mrays/s as median [min-max] over the timed calls, and the rays f64 flagged.

    python benchmarks/torus_speed.py [--columns 1920] [--reps 7]
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drjit as dr  # noqa: E402

from rt_core import backend  # noqa: E402
from rt_core.camera import make_camera, primary_directions  # noqa: E402
from rt_core.parser import parse_scene  # noqa: E402
from rt_core.scene import make_sphere  # noqa: E402
from rt_core.tracer import closest_hit, prepare  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--columns", type=int, default=1920)
    ap.add_argument("--reps", type=int, default=7)
    a = ap.parse_args()
    torus = parse_scene(REPO / "scenes" / "torus.txt")
    t = torus.objects[1]
    sphere = dataclasses.replace(torus, objects=(torus.objects[0], make_sphere(
        t.material, t.center, t.major + t.minor, t.line), torus.objects[2]))
    cases = []
    for name, sc in (("torus", torus), ("sphere", sphere)):
        for p in ("f32", "f64"):
            T = backend.types(p)
            cam = make_camera(sc, a.columns)
            ks = prepare(sc, T)
            d = primary_directions(sc, cam, T)
            dr.eval(d)
            cases.append((name, p, ks, d, cam, []))
    for rep in range(a.reps + 1):                   # the first call compiles: not timed
        for name, p, ks, d, cam, times in cases:
            t0 = time.perf_counter()
            out = closest_hit(ks, d, cam=cam)
            dr.eval(*out)
            dr.sync_thread()
            if rep:
                times.append(time.perf_counter() - t0)
    for name, p, ks, d, cam, times in cases:
        n = cam.columns * cam.rows / 1e6
        m = [n / x for x in times]
        print(f"{name:6s} {p}: {statistics.median(m):6.1f} Mrays/s [{min(m):.1f}-{max(m):.1f}]"
              f"  ({cam.columns}x{cam.rows}; f64 flagged: {ks.__dict__.get('decided', '-')})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
