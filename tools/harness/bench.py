"""Throughput of rt_core (f32, f64) against Mitsuba 3's ray_intersect_preliminary, on identical
rays, interleaved in one process.

Scenes (``bench_scene``): a 16 × 9 window seen from (0, 0, 10), so 1920 columns give 1920 × 1080
rays; N objects on a jittered grid over the view, each covering about 1.5 × 1.5 grid cells (so
a ray passes 2-3 objects on average), at depths 2..30 behind the window:

* ``fplanes``: N finite planes, tilted up to ~17° and turned in their planes;
* ``spheres``: N spheres of 1.2 cells' apparent diameter;
* ``mixed``: N objects alternating sphere / finite plane, in front of an infinite back wall and
  above a tiled floor (every kind the course has).

Everything lies behind the window (z < 0) so the course's screen clip decides nothing, and one
Mitsuba scene with rays from the viewpoint computes the course's answer (up to float32 edge
rounding: ``agree`` counts the rays where rt_core f32 and Mitsuba see different objects).

Rays: rt_core's float32 camera directions, evaluated once; rt_core f64 traces the same values
widened exactly in its kernel (every tracer reads the same float32 arrays; a float64 copy of
them, twice the bytes, cost float64 11-15% of its time at 4-16 objects), with its
exact decisions on them (``rt_core-f64-plain``: the same kernel
without the certification; ``f64_exact_vs_plain`` is their speed ratio), Mitsuba the same
float32 values from the (float32) viewpoint.  ``rt_core-f32-camera`` and ``rt_core-f64-camera``
trace rt_core's own camera rays instead, as ``rtval render`` does (``camera_tracer``: each
direction computed in the kernel, in the tracer's precision); ``f64_vs_f32_camera`` is their
speed ratio.  Timed: the
closest-hit kernel alone (rt_core ``closest_hit`` → t, id; Mitsuba ``ray_intersect_preliminary``
→ t, shape index), each call ``dr.eval`` + ``dr.sync_thread``.  The first call (compilation
included, unless a kernel of the same structure ran before in the process) is reported apart;
steady state is the median of ``reps`` calls, taken round-robin over the tracers so that the
machine's drift hits them alike (``*_best``: the fastest call, which a shared machine's
one-sided slowdowns disturb least).  Scene preparation is timed apart too: rt_core's host
constants and screen-space bins, Mitsuba's ``load_dict`` (its BVH build).
"""
from __future__ import annotations

import math
import os
import random
import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from rt_core.scene import Material, Scene, make_fplane, make_plane, make_sphere, make_tplane

DEFAULT_OBJECTS = (1, 16, 64, 256, 1024)
SCENES = ("fplanes", "spheres", "mixed")
WINDOW = (16.0, 9.0)
VIEWPOINT = (0.0, 0.0, 10.0)
GREY = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))
TRACERS = ("rt_core-f32", "rt_core-f64", "rt_core-f64-plain", "mitsuba",
           "rt_core-f32-camera", "rt_core-f64-camera")
# optional variants (--brute): what the many-object path replaced
BRUTE = ("rt_core-f32-nobins", "rt_core-f32-unrolled")
UNROLLED_LIMIT = 64          # the unrolled kernel beyond this takes seconds to compile and run


# --- scenes -----------------------------------------------------------------------------------

def _cells(n: int, rng: random.Random):
    """n jittered points of a grid over the window, with the cell size: (x, y, cw, ch)."""
    gx = max(1, round(math.sqrt(n * WINDOW[0] / WINDOW[1])))
    gy = max(1, math.ceil(n / gx))
    cw, ch = WINDOW[0] / gx, WINDOW[1] / gy
    return [(-WINDOW[0] / 2 + (i % gx + rng.uniform(0.3, 0.7)) * cw,
             -WINDOW[1] / 2 + (i // gx + rng.uniform(0.3, 0.7)) * ch, cw, ch)
            for i in range(n)]


def _fplane(rng, wx, wy, cw, ch, mat=GREY):
    z = -rng.uniform(2.0, 30.0)
    s = (VIEWPOINT[2] - z) / VIEWPOINT[2]           # window -> depth z magnification
    w, h = 1.5 * cw * s, 1.5 * ch * s
    normal = (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1.0)
    orient = (1.0, rng.uniform(-0.3, 0.3), 0.0)
    f = make_fplane(mat, normal, (0, 0, 0), orient, (w, h))
    # the corner that puts the panel's centre on the view ray through (wx, wy)
    c = (wx * s, wy * s, z)
    p = tuple(c[i] - 0.5 * w * f.xdir[i] - 0.5 * h * f.ydir[i] for i in range(3))
    return make_fplane(mat, normal, p, orient, (w, h))


def _sphere(rng, wx, wy, cw, ch, mat=GREY):
    z = -rng.uniform(2.0, 30.0)
    s = (VIEWPOINT[2] - z) / VIEWPOINT[2]
    return make_sphere(mat, (wx * s, wy * s, z), 0.6 * min(cw, ch) * s)


def bench_scene(kind: str, n: int, seed: int = 1, material: Material = GREY) -> Scene:
    """The benchmark scene ``kind`` (one of SCENES) with n objects of ``material`` (plus, for
    'mixed', a back wall and a tiled floor, GREY)."""
    if kind not in SCENES:
        raise ValueError(f"bench scene must be one of {', '.join(SCENES)}, not {kind!r}")
    rng = random.Random(seed * 7919 + n)
    objs = []
    for i, cell in enumerate(_cells(n, rng)):
        make = {"fplanes": _fplane, "spheres": _sphere}.get(kind)
        if make is None:
            make = _sphere if i % 2 == 0 else _fplane
        objs.append(make(rng, *cell, material))
    if kind == "mixed":
        objs.append(make_plane(GREY, (0, 0, 1), (0, 0, -40)))
        objs.append(make_tplane(GREY, (0, 1, 0), (0, -WINDOW[1] / 2 - 0.1, 0), (1, 0, 0),
                                (1.0, 1.0), GREY))
    return Scene(WINDOW, VIEWPOINT, (), tuple(objs), path=f"<bench {kind} {n}>")


# --- measuring ----------------------------------------------------------------------------------

def vm_kib(field_name: str) -> int:
    """A field of /proc/self/status in KiB (VmRSS, VmHWM); -1 where unavailable."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field_name + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return -1


def jit_backend(name: str):
    """Dr.Jit's JitBackend of a backend name ('llvm', 'cuda')."""
    import drjit as dr
    return dr.JitBackend.CUDA if name == "cuda" else dr.JitBackend.LLVM


class MemoryProbe:
    """Peak memory of a block: Dr.Jit's allocation watermark (its arrays: rt_core's and
    Mitsuba's; the allocator's cache is flushed first so the peak is this block's), and the
    process's peak RSS (VmHWM, reset through /proc/self/clear_refs; it also sees Embree's BVH
    and LLVM's compiler, which Dr.Jit does not allocate).  Both as growth over the start.
    On the CUDA backend the watermark is the device's memory."""

    def __init__(self, backend: str = "llvm"):
        self.backend = backend

    def __enter__(self):
        import drjit as dr
        dr.sync_thread()
        dr.flush_malloc_cache()
        dr.detail.malloc_clear_statistics()
        self.jit0 = dr.detail.malloc_watermark(jit_backend(self.backend))
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")
            self.hwm_ok = True
        except OSError:
            self.hwm_ok = False
        self.rss0 = vm_kib("VmRSS")
        return self

    def __exit__(self, *exc):
        import drjit as dr
        dr.sync_thread()
        self.jit_peak = dr.detail.malloc_watermark(jit_backend(self.backend)) - self.jit0
        hwm = vm_kib("VmHWM")
        # VmHWM is updated lazily and can read a few pages below the VmRSS taken just after
        # the reset: growth within that noise is 0, not negative
        self.rss_peak = max(hwm - self.rss0, 0) * 1024 if self.hwm_ok and hwm >= 0 else -1
        return False


def kernel_stats(history) -> dict:
    """Compilation of the JIT kernels in a kernel history: how many, how many compiled now
    (neither memory nor disk cache), and the LLVM time spent (ms)."""
    jit = [e for e in history if str(e["type"]).endswith("JIT")]
    return {"kernels": len(jit),
            "compiled": sum(1 for e in jit if not e.get("cache_hit") and not e.get("cache_disk")),
            "disk": sum(1 for e in jit if e.get("cache_disk")),
            "compile_ms": round(sum(e.get("codegen_time", 0.0) + e.get("backend_time", 0.0)
                                    for e in jit if not e.get("cache_hit")), 3)}


def timed_call(fn):
    """(seconds, result) of fn() followed by dr.sync_thread()."""
    import drjit as dr
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    return time.perf_counter() - t0, out


def first_call(fn, backend: str = "llvm") -> tuple:
    """(seconds, result, kernel_stats, MemoryProbe) of a first call."""
    import drjit as dr
    saved = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()
    try:
        with MemoryProbe(backend) as mem:
            sec, out = timed_call(fn)
        stats = kernel_stats(dr.kernel_history())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, saved)
    return sec, out, stats, mem


def round_robin(calls: dict, reps: int) -> dict:
    """{name: [seconds...]}: ``reps`` rounds, each calling every fn once, in turn."""
    out = {k: [] for k in calls}
    for _ in range(reps):
        for k, fn in calls.items():
            out[k].append(timed_call(fn)[0])
    return out


# --- the tracers -------------------------------------------------------------------------------

@dataclass
class Tracer:
    """One way of tracing a case's rays: ``run()`` returns evaluated (t, id) arrays."""
    name: str
    run: object
    prepare_ms: float
    ids: object = None            # -> numpy course ids of the last result
    keep: list = field(default_factory=list)   # objects that must outlive the calls


def rt_tracer(name, scene, precision, d32, unroll_max=None, bins=None,
              exact: bool = True, backend_name: str = "llvm") -> Tracer:
    import drjit as dr
    from rt_core import accel, backend
    from rt_core.tracer import closest_hit, prepare
    T = backend.types(precision, backend_name)
    # (float64 too traces the float32 directions: its kernel widens them, exactly)
    d = d32
    t0 = time.perf_counter()
    ks = accel.configure(prepare(scene, T), unroll_max, bins)
    ks.exact_decisions = exact
    # (the bins of the kinds camera rays loop over: what the timed calls read)
    if bins is not False and accel.camera_loops(ks):
        accel.binned(ks, dr.width(d))
    prep = (time.perf_counter() - t0) * 1e3
    state = {}

    def run():
        # float64 decides exactly on the given rays (rt_core/decide.py), as it does on the
        # camera's; rt_core-f64-plain is the same kernel without the certification
        t, oid, _ = closest_hit(ks, d, cam="rays")
        dr.eval(t, oid)
        state["id"] = oid
        return t, oid
    return Tracer(name, run, prep, lambda: np.asarray(state["id"].numpy()), [ks, d])


def camera_tracer(name, scene, precision, cam, backend_name: str = "llvm") -> Tracer:
    """rt_core on its own camera rays, as ``rtval render`` traces them: each ray's direction
    computed in the kernel from its pixel (in the tracer's precision; nothing read from
    memory), float64 deciding its flagged rays exactly, anew each call (the decisions kept
    across renders of a scene are forgotten first: ``tracer.forget_decisions``)."""
    import drjit as dr
    from rt_core import accel, backend, tracer
    from rt_core.render import camera_rays
    from rt_core.tracer import closest_hit, prepare
    T = backend.types(precision, backend_name)
    t0 = time.perf_counter()
    ks = prepare(scene, T)
    if accel.camera_loops(ks):
        accel.binned(ks, cam.size)
    prep = (time.perf_counter() - t0) * 1e3
    state = {}

    def run():
        tracer.forget_decisions()
        t, oid, _ = closest_hit(ks, camera_rays(ks, cam), cam=cam)
        dr.eval(t, oid)
        state["id"] = oid
        return t, oid
    return Tracer(name, run, prep, lambda: np.asarray(state["id"].numpy()), [ks])


def mitsuba_tracer(scene, d32, columns: int, backend_name: str = "llvm") -> Tracer:
    import drjit as dr
    from mitsuba_ref.convert import VARIANTS, course_id, mitsuba, scene_dict
    mi = mitsuba(VARIANTS[backend_name])
    t0 = time.perf_counter()
    ms = mi.load_dict(scene_dict(scene, columns, None, integrator=False, clip=False),
                      optimize=False)
    prep = (time.perf_counter() - t0) * 1e3
    ids = np.array([course_id(s.id()) for s in ms.shapes()] + [-1], np.int64)
    n = dr.width(d32)
    o = mi.Point3f(*(dr.full(mi.Float, float(c), n) for c in scene.viewpoint))
    ray = mi.Ray3f(o, mi.Vector3f(d32.x, d32.y, d32.z))
    dr.eval(ray)
    state = {}

    def run():
        pi = ms.ray_intersect_preliminary(ray)
        dr.eval(pi.t, pi.shape_index)
        state["pi"] = pi
        return pi.t, pi.shape_index
    def course_ids():
        idx = np.asarray(state["pi"].shape_index.numpy()).astype(np.int64)
        return ids[np.minimum(idx, len(ids) - 1)]
    return Tracer("mitsuba", run, prep, course_ids, [ms, ray])


# --- the benchmark -----------------------------------------------------------------------------

def bench_case(kind: str, n: int, columns: int = 1920, reps: int = 9, brute: bool = False,
               tracers=TRACERS, backend_name: str = "llvm") -> dict:
    """One scene: every tracer's first call and steady state, interleaved."""
    import drjit as dr
    from rt_core import backend
    from rt_core.camera import make_camera, primary_directions
    scene = bench_scene(kind, n)
    cam = make_camera(scene, columns)
    T32 = backend.types("f32", backend_name)
    d32 = primary_directions(scene, cam, T32)
    dr.eval(d32)
    rt = lambda name, precision, **kw: (lambda: rt_tracer(name, scene, precision, d32,
                                                          backend_name=backend_name, **kw))
    makers = {"rt_core-f32": rt("rt_core-f32", "f32"),
              "rt_core-f64": rt("rt_core-f64", "f64"),
              "rt_core-f64-plain": rt("rt_core-f64-plain", "f64", exact=False),
              "mitsuba": lambda: mitsuba_tracer(scene, d32, columns, backend_name),
              "rt_core-f32-camera": lambda: camera_tracer("rt_core-f32-camera", scene, "f32",
                                                          cam, backend_name),
              "rt_core-f64-camera": lambda: camera_tracer("rt_core-f64-camera", scene, "f64",
                                                          cam, backend_name),
              "rt_core-f32-nobins": rt("rt_core-f32-nobins", "f32", bins=False),
              "rt_core-f32-unrolled": rt("rt_core-f32-unrolled", "f32", unroll_max=1 << 30)}
    names = list(tracers) + (list(BRUTE) if brute else [])
    if n > UNROLLED_LIMIT and "rt_core-f32-unrolled" in names:
        names.remove("rt_core-f32-unrolled")
    out = {"scene": kind, "objects": n, "total_objects": len(scene.objects),
           "columns": cam.columns, "rows": cam.rows, "rays": cam.size, "reps": reps,
           "backend": backend_name, "tracers": {}}
    trs = {}
    for name in names:
        tr = makers[name]()
        sec, _, stats, mem = first_call(tr.run, backend_name)
        trs[name] = tr
        out["tracers"][name] = {"prepare_ms": round(tr.prepare_ms, 3),
                                "first_ms": round(sec * 1e3, 3), **stats,
                                "jit_peak_bytes": mem.jit_peak, "rss_peak_bytes": mem.rss_peak}
    times = round_robin({k: tr.run for k, tr in trs.items()}, reps)
    for name, ts in times.items():
        med = statistics.median(ts)
        r = out["tracers"][name]
        r["median_ms"] = round(med * 1e3, 3)
        r["min_ms"] = round(min(ts) * 1e3, 3)
        r["mrays_per_s"] = round(cam.size / med / 1e6, 2)
        r["mrays_per_s_best"] = round(cam.size / min(ts) / 1e6, 2)
    # agreement: rays whose object differs from rt_core f32
    if "rt_core-f32" in trs:
        ref = trs["rt_core-f32"].ids()
        for name, tr in trs.items():
            if name != "rt_core-f32":
                out["tracers"][name]["differ_from_f32"] = int(np.count_nonzero(tr.ids() != ref))
    mi = out["tracers"].get("mitsuba")
    for name, r in out["tracers"].items():
        if mi and name != "mitsuba":
            r["ratio_vs_mitsuba"] = round(mi["median_ms"] / r["median_ms"], 3)
            r["ratio_vs_mitsuba_best"] = round(mi["min_ms"] / r["min_ms"], 3)
    ex, pl = out["tracers"].get("rt_core-f64"), out["tracers"].get("rt_core-f64-plain")
    if ex and pl:
        out["f64_exact_vs_plain"] = round(pl["median_ms"] / ex["median_ms"], 3)
        out["f64_exact_vs_plain_best"] = round(pl["min_ms"] / ex["min_ms"], 3)
    # float64 against float32 on the camera's own rays (``camera_tracer``)
    c32, c64 = out["tracers"].get("rt_core-f32-camera"), out["tracers"].get("rt_core-f64-camera")
    if c32 and c64:
        out["f64_vs_f32_camera"] = round(c32["median_ms"] / c64["median_ms"], 3)
    for p in ("f32", "f64"):
        r = out["tracers"].get(f"rt_core-{p}")
        if r and mi:
            out[f"ratio_{p}_vs_mitsuba"] = r["ratio_vs_mitsuba"]
            out[f"ratio_{p}_vs_mitsuba_best"] = r["ratio_vs_mitsuba_best"]
    return out


def run_bench(objects=DEFAULT_OBJECTS, scenes=SCENES, columns: int = 1920, reps: int = 9,
              brute: bool = False, progress=None, backend_name: str = "llvm",
              isolated: bool = True, threads: int | None = None) -> dict:
    """Every scene kind × object count; returns {'meta', 'cases', 'growth'}.  ``isolated``:
    each case in a process of its own (tools/harness/isolate.py), else all in this one;
    ``threads``: Dr.Jit's worker threads of an isolated case's process."""
    from rt_core.render import versions
    cases = []
    for kind in scenes:
        for n in objects:
            kw = {"kind": kind, "n": n, "columns": columns, "reps": reps, "brute": brute,
                  "backend_name": backend_name}
            cases.append(in_own_process(f"bench {kind} N={n}", "bench_case", kw, threads)
                         if isolated else bench_case(**kw))
            if progress:
                progress(cases[-1])
    return {"meta": {"columns": columns, "reps": reps, "cases_in": PROCESS[isolated],
                     **versions(), **machine(backend_name)},
            "cases": cases, "growth": growth(cases)}


# where run_bench's and run_shaded's cases ran (the JSON's meta.cases_in)
PROCESS = {True: "a process each (after a warm-up case there)", False: "one process"}


def in_own_process(label: str, function: str, kw: dict, threads=None,
                   module: str = "tools.harness.bench") -> dict:
    """``function(**kw)`` of ``module`` in a process of its own, after a warm-up case there:
    one object of another scene kind than the case's (none of the case's own kernels made
    there) at 64 columns, a first call and one timed call a side."""
    from tools.harness.isolate import run_case
    warm = dict(kw, kind="fplanes" if kw["kind"] == "spheres" else "spheres", n=1,
                columns=64, reps=1)
    return run_case(label, module, function, kw, warm, threads)


def machine(backend_name: str = "llvm") -> dict:
    import os
    import drjit as dr
    info = {"backend": backend_name, "cpus": os.cpu_count(), "drjit_threads": dr.thread_count(),
            "llvm": ".".join(map(str, dr.detail.llvm_version())),
            "kernel_cache": os.environ.get("DRJIT_CACHE_DIR", "~/.drjit (shared)")}
    if backend_name == "cuda":
        info["gpu"] = gpu_name()
    from rt_core.accel import camera_factor, wide_vectors
    from rt_core.backend import host_cpu
    if "model name" in host_cpu():
        info["cpu"] = host_cpu()["model name"]
    # (the camera rays' unroll limit depends on it: rt_core/accel.py)
    info["avx512"], info["camera_factor"] = wide_vectors(), camera_factor(backend_name)
    return info


def gpu_name() -> str:
    """The GPU's name as nvidia-smi reports it ('?' where it cannot)."""
    import subprocess
    try:
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=20)
        return r.stdout.strip().splitlines()[0] if r.returncode == 0 and r.stdout.strip() \
            else "?"
    except (OSError, subprocess.SubprocessError):
        return "?"


def growth(cases) -> dict:
    """Per scene kind and tracer: the exponent b of time ∝ N^b fitted over the object counts
    from 16 up (least squares in log-log; all counts if fewer than two are >= 16), and the
    largest N where rt_core f32 is still ahead of Mitsuba."""
    out = {}
    for kind in dict.fromkeys(c["scene"] for c in cases):
        cs = sorted((c for c in cases if c["scene"] == kind), key=lambda c: c["objects"])
        row = {}
        for name in dict.fromkeys(k for c in cs for k in c["tracers"]):
            pts = [(c["objects"], c["tracers"][name]["median_ms"]) for c in cs
                   if name in c["tracers"]]
            if sum(1 for p in pts if p[0] >= 16) >= 2:
                pts = [p for p in pts if p[0] >= 16]
            if len(pts) >= 2:
                x = np.log([p[0] for p in pts])
                y = np.log([p[1] for p in pts])
                row[f"{name}_exponent"] = round(float(np.polyfit(x, y, 1)[0]), 3)
        ahead = [c["objects"] for c in cs if c.get("ratio_f32_vs_mitsuba", 0) >= 1]
        row["f32_ahead_of_mitsuba_up_to"] = max(ahead) if ahead else 0
        behind = [c["objects"] for c in cs
                  if c["tracers"].get("rt_core-f32-nobins", {}).get("ratio_vs_mitsuba", 9) < 1]
        if behind:
            row["brute_force_behind_mitsuba_from"] = min(behind)
        out[kind] = row
    return out


def table(result: dict) -> str:
    """A plain-text table of run_bench's result."""
    lines = [f"{'scene':8s} {'N':>5s} {'tracer':21s} {'Mrays/s':>8s} {'median ms':>9s} "
             f"{'first ms':>9s} {'compiled':>8s} {'prep ms':>8s} {'vs Mitsuba':>10s} "
             f"{'(best)':>7s} {'differ':>7s}"]
    for c in result["cases"]:
        for name, r in c["tracers"].items():
            ratio = r.get("ratio_vs_mitsuba")
            best = r.get("ratio_vs_mitsuba_best")
            lines.append(f"{c['scene']:8s} {c['objects']:5d} {name:21s} {r['mrays_per_s']:8.1f} "
                         f"{r['median_ms']:9.2f} {r['first_ms']:9.1f} {r['compiled']:8d} "
                         f"{r['prepare_ms']:8.1f} "
                         f"{(f'{ratio:.2f}x' if ratio else '-'):>10s} "
                         f"{(f'{best:.2f}x' if best else '-'):>7s} "
                         f"{r.get('differ_from_f32', '-')!s:>7s}")
    ratios = [(c["scene"], c["objects"], c["f64_exact_vs_plain"]) for c in result["cases"]
              if "f64_exact_vs_plain" in c]
    if ratios:
        lines.append("f64 exact decisions, speed vs without: " + ", ".join(
            f"{k} {n}: {r:.2f}" for k, n, r in ratios))
    for kind, g in result["growth"].items():
        lines.append(f"{kind}: " + ", ".join(f"{k}={v}" for k, v in g.items()))
    return "\n".join(lines)


# --- the whole command: rtval bench --command ----------------------------------------------

COMMAND_COLUMNS = (1920, 7680)
COMMAND_PHASES = ("import", "parse", "kernel", "write", "exit")
# what a run writes: the geometry EXR; the course image (the PPM a course program writes) with
# the shaded EXR beside it; the course image alone
COMMAND_OUTPUTS = ("geometry", "shaded", "course")


def command_env(folder: str) -> dict:
    """The environment of a timed ``rtval render``: this one, with Python's bytecode written
    to (and read from) ``folder``/pycache.  An installed rtval's modules are compiled once;
    where PYTHONDONTWRITEBYTECODE is set (this project's machines set it) every run compiled
    every module again, 0.2-0.4 s of its import phase that no installed rtval spends."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = os.path.join(folder, "pycache")
    return env


def command_bench(columns=COMMAND_COLUMNS, repeats: int = 3, scene: str | None = None,
                  outputs=COMMAND_OUTPUTS, progress=None, backend_name: str = "llvm") -> dict:
    """Wall time of whole ``rtval render`` runs (a new process each), split into phases:
    import (the interpreter's start, the CLI, rt_core, Dr.Jit, numpy, OpenEXR: the wall time
    before the scene is read), parse, kernel (camera, tracing, shading; Dr.Jit's kernel cache
    warm), write (quantizing, provenance, the outputs), exit (the run's messages, then the
    interpreter and Dr.Jit shutting down: the wall time after the outputs, by the clock of
    the day on both sides).  ``outputs``: COMMAND_OUTPUTS' names.
    Medians and ranges of ``repeats`` runs, interleaved."""
    import json
    import subprocess
    import sys
    import tempfile
    repo = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    scene = scene or os.path.join(repo, "scenes", "mixed.txt")
    # (the scene file's own checks: missing, a FIFO or a device, too large, each named)
    from rt_core.inputfile import check_input
    check_input(scene, "scene")
    runs: dict = {}
    with tempfile.TemporaryDirectory(prefix="rtval-bench-") as d:
        for rep in range(-1, repeats):          # run -1: warm-up (kernels, bytecode cached)
            for c in columns:
                for out in outputs:
                    phases = os.path.join(d, "phases.json")
                    exr, ppm = os.path.join(d, f"{c}.{out}.exr"), os.path.join(d, f"{c}.ppm")
                    args = ["--columns", str(c), "--backend", backend_name] + (["-o", exr] if out != "course" else []) \
                        + (["--ppm", ppm] if out != "geometry" else [])
                    t0 = time.perf_counter()
                    r = subprocess.run([sys.executable, "-m", "tools.cli", "render", scene, *args],
                                       cwd=repo, capture_output=True, text=True,
                                       env={**command_env(d), "RTVAL_PHASES": phases})
                    wall, ended = time.perf_counter() - t0, time.time()
                    if r.returncode != 0:
                        from rt_core.usererror import InputError
                        last = (r.stderr.strip().splitlines() or ["(no message)"])[-1]
                        raise InputError(f"bench --command: rtval render failed: {last}")
                    with open(phases) as f:
                        p = json.load(f)
                    p["exit"] = ended - p.pop("ended_at")
                    p["import"] = wall - p["parse"] - p["kernel"] - p["write"] - p["exit"]
                    p["wall"] = wall
                    p["size_mb"] = os.path.getsize(exr if out != "course" else ppm) / 1e6
                    for f in (exr, ppm):        # (not replaced by the next run: an unlink of
                        if os.path.exists(f):   # a large file is no part of a render)
                            os.unlink(f)
                    if rep < 0:
                        continue
                    runs.setdefault((c, out), []).append(p)
                    if progress:
                        progress(c, out, rep, p)
    cases = []
    for (c, out), ps in runs.items():
        stat = {k: {"median": float(np.median([p[k] for p in ps])),
                    "min": float(min(p[k] for p in ps)), "max": float(max(p[k] for p in ps))}
                for k in (*COMMAND_PHASES, "wall", "size_mb")}
        largest = max(COMMAND_PHASES, key=lambda k: stat[k]["median"])
        cases.append({"columns": c, "outputs": out, "runs": len(ps), "phases": stat,
                      "largest": largest})
    from rt_core.inputfile import file_sha256
    from rt_core.render import versions
    return {"mode": "command", "scene": os.path.relpath(os.path.abspath(scene), repo),
            "scene_sha256": file_sha256(scene), **versions(),
            "machine": machine(backend_name),
            "bytecode": "compiled by the warm-up run, read by the timed ones (command_env)",
            "cases": cases}


def command_table(result: dict) -> str:
    head = f"{'columns':>7} {'outputs':8} " + " ".join(f"{k:>16}" for k in
                                                       (*COMMAND_PHASES, "wall")) + "  largest"
    lines = [f"rtval render {result['scene']}: seconds, median [min-max] of "
             f"{result['cases'][0]['runs'] if result['cases'] else 0} runs", head]
    for c in result["cases"]:
        cell = lambda k: (f"{c['phases'][k]['median']:.2f} [{c['phases'][k]['min']:.2f}-"
                          f"{c['phases'][k]['max']:.2f}]")
        lines.append(f"{c['columns']:>7} {c['outputs']:8} " + " ".join(
            f"{cell(k):>16}" for k in (*COMMAND_PHASES, "wall")) + f"  {c['largest']}")
    return "\n".join(lines)
