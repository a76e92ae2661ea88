"""Cost of float64 exact decisions: rt_core f64 primary rays with certified decisions (and the
exact re-decision of the flagged rays) against the same kernel without them, interleaved in one
process on the `rtval bench` scenes.  Prints the median time ratio (exact / plain) and its
spread over the repetitions; run: tools/in-env.sh python tools/bench_exact.py"""
from __future__ import annotations

import statistics
import sys
import time

import drjit as dr

from rt_core import backend
from rt_core.camera import make_camera, primary_directions
from rt_core.rules import Rules
from rt_core.tracer import closest_hit, prepare
from tools.harness.bench import SCENES, bench_scene


def main(objects=(1, 16, 256), columns=1920, reps=7):
    T = backend.types("f64")
    print("scene      N   plain ms  exact ms  exact/plain (min-max)  flagged rays")
    for kind in SCENES:
        for n in objects:
            sc = bench_scene(kind, n)
            cam = make_camera(sc, columns, columns * 9 // 16)
            d = primary_directions(sc, cam, T)
            dr.eval(d)
            runs = {"plain": [], "exact": []}
            for name, ks in (("plain", prepare(sc, T)), ("exact", prepare(sc, T))):
                runs[name + "_ks"] = ks
            for rep in range(reps + 1):
                for name in ("plain", "exact"):
                    ks = runs[name + "_ks"]
                    t0 = time.perf_counter()
                    t, i, h = closest_hit(ks, d, None, Rules(), cam=cam if name == "exact" else None)
                    dr.eval(t, i)
                    dr.sync_thread()
                    if rep:
                        runs[name].append(time.perf_counter() - t0)
            ratios = [e / p for e, p in zip(runs["exact"], runs["plain"])]
            print(f"{kind:9s} {n:4d} {1e3 * statistics.median(runs['plain']):9.1f} "
                  f"{1e3 * statistics.median(runs['exact']):9.1f}  {statistics.median(ratios):5.2f} "
                  f"({min(ratios):.2f}-{max(ratios):.2f})   {runs['exact_ks'].decided}")
            sys.stdout.flush()


if __name__ == "__main__":
    main()
