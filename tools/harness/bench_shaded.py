"""rtval bench --shaded: the course's whole shading (rt_core/shading.py ``shade``) against
Mitsuba 3 casting the same rays, interleaved in one process.

Scenes: tools/harness/bench.py's ``bench_scene`` (fplanes, spheres, mixed) with the N objects
made reflective (``REFLECTIVE``: specular 0.4) and ``lights`` point lights in front of them
(``shaded_scene``); the mixed scene's back wall and tiled floor stay matte.

Per pixel both sides do the course's work for one reflection bounce:

* the primary hit (rt_core ``closest_hit``; Mitsuba ``ray_intersect_preliminary`` and
  ``compute_surface_interaction`` with ``RayFlags.Minimal`` for the point and normal);
* one shadow ray per light from each hit that faces the light (c = L·N > 0): rt_core
  ``occluded``, Mitsuba ``ray_test`` on ``spawn_ray_to(light)``;
* the reflection ray of each hit on a reflective surface (total path < MAX_DIST), its hit and
  its shadow rays, and the course's sums (ambient + Σ diffuse·E·c/d, divided by the path
  length; the reflection weighted by the specular).

rt_core runs ``shade(..., max_bounces=1)``, which traces the reflection rays masked in the
primary rays' kernel and shades their hits in a second kernel, one a lane (rt_core/shading.py
``_one_bounce``); Mitsuba traces them masked (its integrators' way).  Both start
from rt_core's float32 camera directions.  Timed: the image evaluated (``dr.eval`` +
``dr.sync_thread``), median and best of ``reps`` round-robin calls after an untimed second one,
the first call (with compilation) reported apart.  Agreement (one untimed call each): shadow rays cast, how many were
blocked, reflection rays, and the pixels whose 8-bit value differs by more than 2 levels
(float32 edges, Mitsuba's ray offsets where rt_core skips the surface a ray leaves).
"""
from __future__ import annotations

import math
import statistics
import time

import numpy as np

from rt_core.scene import Material, PointLight, Scene

from .bench import (PROCESS, SCENES, bench_scene, first_call, in_own_process, machine,
                    round_robin)

SHADED_OBJECTS = (1, 16, 256, 4096)
DEFAULT_LIGHTS = 4
TRACERS = ("rt_core-f32", "rt_core-f64", "mitsuba")
REFLECTIVE = Material((2.0, 2.0, 2.0), (4.0, 4.0, 4.0), (0.4, 0.4, 0.4))
EMISSIVITY = (30.0, 30.0, 30.0)
MAX_DIST = 1000.0            # rt_core.shading.DEFAULT_MAX_DIST (not imported: no Dr.Jit yet)
LEVELS = 2                   # 8-bit levels within which two pixels count as the same


def shaded_scene(kind: str, n: int, lights: int = DEFAULT_LIGHTS, seed: int = 1) -> Scene:
    """``bench_scene(kind, n)`` with reflective objects and ``lights`` point lights on an
    ellipse in front of them (z = 4, between the window and the viewpoint)."""
    base = bench_scene(kind, n, seed, material=REFLECTIVE)
    ls = tuple(PointLight(EMISSIVITY, (round(7.0 * math.cos(a), 6), round(4.0 * math.sin(a), 6),
                                       4.0))
               for a in (2 * math.pi * (j + 0.5) / lights for j in range(lights)))
    return Scene(base.window, base.viewpoint, ls, base.objects,
                 path=f"<bench shaded {kind} {n} L={lights}>")


# --- the two sides -------------------------------------------------------------------------------

class Side:
    """One way of shading a case's pixels: ``run()`` returns the evaluated image (flat RGB);
    ``counts()`` an untimed call's ray counts and its image as numpy (pixels, 3)."""

    def __init__(self, name, run, counts, prepare_ms, keep):
        self.name, self.run, self.counts, self.prepare_ms, self.keep = \
            name, run, counts, prepare_ms, keep


def rt_side(name: str, scene: Scene, precision: str, d32, max_dist: float = MAX_DIST,
            backend_name: str = "llvm") -> Side:
    import drjit as dr
    from rt_core import backend
    from rt_core.rules import Rules
    from rt_core.shading import shade
    from rt_core.tracer import prepare
    T = backend.types(precision, backend_name)
    d = d32                 # (float64 widens the float32 directions in its kernel: bench.py)
    t0 = time.perf_counter()
    ks = prepare(scene, T)
    prep = (time.perf_counter() - t0) * 1e3

    def run():
        # float64: the primary hits decided exactly on the given rays, as `rtval render` does
        res = shade(ks, d, Rules(), max_dist, max_bounces=1, cam="rays")
        dr.eval(res.rgb)
        return res.rgb

    def counts():
        res = shade(ks, d, Rules(), max_dist, max_bounces=1, cam="rays", record=2)
        out = {"shadow_rays": 0, "shadow_blocked": 0, "reflection_rays": 0}
        for b, rec in enumerate(res.records):
            for j in range(len(scene.lights)):
                cast = rec[f"L{j}.cast"]
                out["shadow_rays"] += int(cast.sum())
                out["shadow_blocked"] += int((cast & rec[f"L{j}.blocked"]).sum())
            if b == 1:
                out["reflection_rays"] = len(rec["pixel"])
        return out, _rgb(res.rgb)
    return Side(name, run, counts, prep, [ks, d])


def _rgb(a) -> np.ndarray:
    return np.stack([np.asarray(c.numpy(), np.float64) for c in (a.x, a.y, a.z)], 1)


def mitsuba_side(scene: Scene, d32, columns: int, max_dist: float = MAX_DIST,
                 backend_name: str = "llvm") -> Side:
    """The course's shading for one bounce written with Mitsuba's ray queries (materials by
    shape index; the bench's tiled floor has one MAT, so no tile parity)."""
    import drjit as dr
    from mitsuba_ref.convert import VARIANTS, course_id, mitsuba, scene_dict
    mi = mitsuba(VARIANTS[backend_name])
    t0 = time.perf_counter()
    ms = mi.load_dict(scene_dict(scene, columns, None, integrator=False, clip=False),
                      optimize=False)
    prep = (time.perf_counter() - t0) * 1e3
    # per shape index (plus a last row for misses): the course MAT
    mats = [scene.objects[course_id(s.id())].material for s in ms.shapes()]
    zero = Material((0, 0, 0), (0, 0, 0), (0, 0, 0))
    table = {k: mi.Color3f(*([getattr(m, k)[i] for m in mats + [zero]] for i in range(3)))
             for k in ("ambient", "diffuse", "specular")}
    miss = len(mats)
    # the course's screen clip: a plane kind's hit in front of the window (z > 0) does not
    # count (in these scenes nothing lies beyond such a hit, so it is a miss)
    planar = mi.Bool([scene.objects[course_id(s.id())].kind != "sphere" for s in ms.shapes()]
                     + [False])
    lights = [(mi.Point3f(*L.center), mi.Color3f(*L.emissivity)) for L in scene.lights]
    n = dr.width(d32)
    o = mi.Point3f(*(dr.full(mi.Float, float(c), n) for c in scene.viewpoint))
    ray = mi.Ray3f(o, mi.Vector3f(d32.x, d32.y, d32.z))
    dr.make_opaque(table, planar, ray)
    flags = mi.RayFlags.Minimal

    def segment(ray, active, dist, tally):
        """(local intensity, hit, surface interaction, specular, path length) of one ray."""
        pi = ms.ray_intersect_preliminary(ray, active=active)
        si = pi.compute_surface_interaction(ray, flags, active)
        hit = active & si.is_valid()
        hit &= ~(dr.gather(mi.Bool, planar, dr.select(hit, pi.shape_index, miss)) &
                 (si.p.z > 0))
        idx = dr.select(hit, pi.shape_index, miss)
        amb, dif, spec = (dr.gather(mi.Color3f, table[k], idx)
                          for k in ("ambient", "diffuse", "specular"))
        total = si.t if dist is None else dist + si.t
        I = mi.Color3f(amb)
        for Lp, E in lights:
            D = Lp - si.p
            ld = dr.norm(D)
            c = dr.dot(D / ld, si.n)
            cast = hit & (c > 0)
            blocked = ms.ray_test(si.spawn_ray_to(Lp), cast)
            I += dr.select(cast & ~blocked, dif * E * (c / ld), 0)
            if tally is not None:
                tally.append((cast, cast & blocked))
        return dr.select(hit, I / total, 0), hit, si, spec, total

    def shade(tally=None):
        local, hit, si, spec, total = segment(ray, True, None, tally)
        go = hit & dr.any(spec != 0) & (total < max_dist)
        R = dr.normalize(ray.d - 2 * dr.dot(ray.d, si.n) * si.n)
        local2, _, _, _, _ = segment(si.spawn_ray(R), go, total, tally)
        image = local + dr.select(go, spec * local2, 0)
        return image, go

    def run():
        image, _ = shade()
        dr.eval(image)
        return image

    def counts():
        tally = []
        image, go = shade(tally)
        dr.eval(image)
        out = {"shadow_rays": sum(int(dr.count(c)[0]) for c, _ in tally),
               "shadow_blocked": sum(int(dr.count(b)[0]) for _, b in tally),
               "reflection_rays": int(dr.count(go)[0])}
        return out, _rgb(image)
    return Side("mitsuba", run, counts, prep, [ms, ray, table])


# --- the benchmark --------------------------------------------------------------------------------

def shaded_case(kind: str, n: int, columns: int = 1920, reps: int = 5,
                lights: int = DEFAULT_LIGHTS, tracers=TRACERS, backend_name: str = "llvm") -> dict:
    """One scene: every side's first call, steady state (interleaved) and ray counts."""
    import drjit as dr
    from rt_core import backend
    from rt_core.camera import make_camera, primary_directions
    from rt_core.shading import quantize
    scene = shaded_scene(kind, n, lights)
    cam = make_camera(scene, columns)
    d32 = primary_directions(scene, cam, backend.types("f32", backend_name))
    dr.eval(d32)
    makers = {"rt_core-f32": lambda: rt_side("rt_core-f32", scene, "f32", d32,
                                             backend_name=backend_name),
              "rt_core-f64": lambda: rt_side("rt_core-f64", scene, "f64", d32,
                                             backend_name=backend_name),
              "mitsuba": lambda: mitsuba_side(scene, d32, columns, backend_name=backend_name)}
    out = {"scene": kind, "objects": n, "total_objects": len(scene.objects), "lights": lights,
           "columns": cam.columns, "rows": cam.rows, "pixels": cam.size, "reps": reps,
           "backend": backend_name, "tracers": {}}
    sides = {}
    for name in tracers:
        side = makers[name]()
        sec, _, stats, mem = first_call(side.run, backend_name)
        sides[name] = side
        out["tracers"][name] = {"prepare_ms": round(side.prepare_ms, 3),
                                "first_ms": round(sec * 1e3, 3), **stats,
                                "jit_peak_bytes": mem.jit_peak, "rss_peak_bytes": mem.rss_peak}
    # an untimed second call each (its time recorded): Mitsuba's kernel compiles again on its
    # second call, and rt_core builds its reflection bins for its second image
    for name, ts in round_robin({k: s.run for k, s in sides.items()}, 1).items():
        out["tracers"][name]["second_ms"] = round(ts[0] * 1e3, 3)
    times = round_robin({k: s.run for k, s in sides.items()}, reps)
    images = {}
    for name, ts in times.items():
        r = out["tracers"][name]
        med = statistics.median(ts)
        r["median_ms"] = round(med * 1e3, 3)
        r["min_ms"] = round(min(ts) * 1e3, 3)
        r["mpixels_per_s"] = round(cam.size / med / 1e6, 3)
        c, rgb = sides[name].counts()
        r.update(c)
        if name.startswith("rt_core"):
            # the counts come from the recorded wavefront; the timed image (one bounce fused,
            # rt_core/shading.py _one_bounce) must be the same, bit for bit
            r["timed_image_is_counted"] = bool(np.array_equal(_rgb(sides[name].run()), rgb))
        images[name] = quantize(rgb.astype(np.float32)).astype(np.int16)
    mi = out["tracers"].get("mitsuba")
    ref = images.get("mitsuba")
    for name, r in out["tracers"].items():
        if name == "mitsuba" or not mi:
            continue
        r["ratio_vs_mitsuba"] = round(mi["median_ms"] / r["median_ms"], 3)
        r["ratio_vs_mitsuba_best"] = round(mi["min_ms"] / r["min_ms"], 3)
        r["pixels_differ_from_mitsuba"] = int(np.count_nonzero(
            np.abs(images[name] - ref).max(1) > LEVELS))
        for k in ("shadow_rays", "shadow_blocked", "reflection_rays"):
            r[f"{k}_vs_mitsuba"] = r[k] - mi[k]
    for p in ("f32", "f64"):
        r = out["tracers"].get(f"rt_core-{p}")
        if r and mi:
            out[f"ratio_{p}_vs_mitsuba"] = r["ratio_vs_mitsuba"]
            out[f"ratio_{p}_vs_mitsuba_best"] = r["ratio_vs_mitsuba_best"]
    return out


def run_shaded(objects=SHADED_OBJECTS, scenes=SCENES, columns: int = 1920, reps: int = 5,
               lights: int = DEFAULT_LIGHTS, tracers=TRACERS, progress=None,
               backend_name: str = "llvm", isolated: bool = True,
               threads: int | None = None) -> dict:
    """Every scene kind × object count; returns {'mode', 'meta', 'cases'}.  ``isolated``,
    ``threads``: as bench.run_bench's."""
    from rt_core.render import versions
    cases = []
    for kind in scenes:
        for n in objects:
            kw = {"kind": kind, "n": n, "columns": columns, "reps": reps, "lights": lights,
                  "tracers": list(tracers), "backend_name": backend_name}
            cases.append(in_own_process(f"bench --shaded {kind} N={n}", "shaded_case", kw,
                                        threads, module=__name__)
                         if isolated else shaded_case(**kw))
            if progress:
                progress(cases[-1])
    return {"mode": "shaded", "meta": {"columns": columns, "reps": reps, "lights": lights,
                                       "max_dist": MAX_DIST, "cases_in": PROCESS[isolated],
                                       **versions(), **machine(backend_name)},
            "cases": cases}


def shaded_table(result: dict) -> str:
    """A plain-text table of run_shaded's result."""
    lines = [f"{'scene':8s} {'N':>5s} {'tracer':12s} {'Mpix/s':>7s} {'median ms':>9s} "
             f"{'first ms':>9s} {'compiled':>8s} {'vs Mitsuba':>10s} {'(best)':>7s} "
             f"{'shadow rays':>11s} {'blocked':>9s} {'reflect':>8s} {'differ':>7s}"]
    for c in result["cases"]:
        for name, r in c["tracers"].items():
            ratio, best = r.get("ratio_vs_mitsuba"), r.get("ratio_vs_mitsuba_best")
            lines.append(f"{c['scene']:8s} {c['objects']:5d} {name:12s} "
                         f"{r['mpixels_per_s']:7.2f} {r['median_ms']:9.1f} {r['first_ms']:9.1f} "
                         f"{r['compiled']:8d} {(f'{ratio:.2f}x' if ratio else '-'):>10s} "
                         f"{(f'{best:.2f}x' if best else '-'):>7s} {r['shadow_rays']:11d} "
                         f"{r['shadow_blocked']:9d} {r['reflection_rays']:8d} "
                         f"{r.get('pixels_differ_from_mitsuba', '-')!s:>7s}")
    m = result["meta"]
    lines.append(f"{m['lights']} lights, 1 reflection bounce; 'differ': pixels more than "
                 f"{LEVELS} 8-bit levels from Mitsuba's")
    return "\n".join(lines)
