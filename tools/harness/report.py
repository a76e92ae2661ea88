"""Error against run time: rt_core f32, rt_core f64 and Mitsuba 3, each scene, several
resolutions, one report (``rtval report``).

Configurations, each at every resolution:

* ``rt_core-f32-prelim`` / ``rt_core-f64-prelim``: camera rays and the closest hit (t, id) in
  one kernel; ``-full`` adds the surface (normal, position, uv): ``render_geometry``'s kernel.
* ``mitsuba-prelim`` / ``mitsuba-full``: Mitsuba's ``ray_intersect_preliminary`` /
  ``ray_intersect`` on rt_core f32's exact rays (mitsuba_ref/reference.py's same-ray mode:
  plane kinds traced from the window plane, spheres whole, the nearer hit kept).

Reference: the float64 per-ray oracle (mitsuba_ref/oracle.py), a plain-Python trace of the notes'
formulas, at ``sample`` pixels drawn per (scene, resolution) with a fixed seed (every pixel when
the image has no more).  Errors at those pixels: mask mismatches (hit or object id differ),
the same excluding pixels the oracle flags as within reach of rounding of a decision (margin
below 64 u of the precision that decides: f32 for Mitsuba), and the depth's max and 99th
percentile relative error where both hit the same object.  Preliminary and full runs of one
tracer return the same t and id, so they share their errors.

Timing: the first call (compilation included: ``kernels``/``compiled`` count them; the CLI
starts from an empty kernel cache unless told to keep it) and the steady state, the median of
``reps`` further calls, each ``dr.eval`` + ``dr.sync_thread()``, round-robin over the
configurations of a (scene, resolution).  rt_core's time is its whole kernel (rays included);
Mitsuba's is its intersection kernels only, on rays prepared beforehand — the host-side numpy
work of reference.trace_rays (about 3x its kernel time) is not counted.  Memory: the first
call's peak growth of Dr.Jit's allocations (its allocator watermark, cache flushed first) and of
the process's resident set (VmHWM, reset through /proc/self/clear_refs).
"""
from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bench import first_call, machine, round_robin

CONFIGS = ("rt_core-f32-prelim", "rt_core-f32-full", "rt_core-f64-prelim", "rt_core-f64-full",
           "mitsuba-prelim", "mitsuba-full")
COLUMNS = (160, 320, 640, 1280, 1920)
QUICK_COLUMNS = (160, 640, 1920)
SAMPLE = 4000
QUICK_SAMPLE = 400
REPS = 7
QUICK_REPS = 2
FLAG = 64.0                     # margin (units of u) below which the oracle flags a pixel
U = {"f32": 2.0 ** -24, "f64": 2.0 ** -53}


@dataclass
class Settings:
    columns: tuple = COLUMNS
    sample: int = SAMPLE
    reps: int = REPS
    seed: int = 20240601


QUICK = Settings(QUICK_COLUMNS, QUICK_SAMPLE, QUICK_REPS)


# --- the configurations ------------------------------------------------------------------------

def _rt_calls(scene, cam, precision):
    """{prelim, full}: functions returning flat numpy (mask, id, depth) ... evaluated."""
    import drjit as dr
    from rt_core import backend
    from rt_core.camera import primary_directions
    from rt_core.render import trace_geometry
    from rt_core.tracer import closest_hit, prepare
    T = backend.types(precision)
    ks = prepare(scene, T)
    state = {}

    def prelim():
        d = primary_directions(scene, cam, T)
        t, oid, hit = closest_hit(ks, d)
        dr.eval(t, oid)
        return t, oid

    def full():
        state["out"] = trace_geometry(scene, cam, T)
        return state["out"]

    def result():
        o = state["out"]
        return (np.asarray(o["hit.mask"].numpy()) > 0, np.asarray(o["object.id"].numpy()),
                np.asarray(o["depth.Z"].numpy(), np.float64))
    return {"prelim": prelim, "full": full}, result


def _mitsuba_rays(ms, d32: np.ndarray):
    """Per group of the MitsubaScene: its rays (reference.group_rays), evaluated, so that
    timing sees the intersection kernels only."""
    import drjit as dr
    from mitsuba_ref.reference import group_rays
    V = np.asarray(ms.scene.viewpoint, np.float64)
    out = []
    for g in ms.groups:
        ray, _, _ = group_rays(g, V, d32)
        dr.eval(ray)
        out.append((g, ray))
    return out


def _mitsuba_calls(ms, d32):
    import drjit as dr
    rays = _mitsuba_rays(ms, d32)

    def prelim():
        res = [g.mi_scene.ray_intersect_preliminary(ray) for g, ray in rays]
        dr.eval(*[(p.t, p.shape_index) for p in res])
        return res

    def full():
        res = [g.mi_scene.ray_intersect(ray) for g, ray in rays]
        dr.eval(*[(s.t, s.n, s.p, s.uv, s.shape) for s in res])
        return res
    return {"prelim": prelim, "full": full}, rays


# --- errors against the oracle -----------------------------------------------------------------

def sample_index(n_pixels: int, sample: int, seed: int) -> np.ndarray:
    """Sorted flat pixel indices: all pixels if n_pixels <= sample, else ``sample`` of them
    drawn without replacement (seeded)."""
    if n_pixels <= sample:
        return np.arange(n_pixels)
    return np.sort(np.random.default_rng(seed).choice(n_pixels, sample, replace=False))


def errors(hit, oid, depth, orc: dict, precision: str, modelled=None) -> dict:
    """Errors of one tracer at the sampled pixels (flat arrays aligned with ``orc``).

    ``modelled``: mask of pixels where a mismatch is explained by how the reference models
    the scene (mitsuba_ref.explain classes: a plane's finite stand-in, ...); those are
    counted apart and not as unflagged."""
    from mitsuba_ref.oracle import DIAG_KEYS
    o_hit = orc["hit.mask"] > 0
    o_id = orc["object.id"]
    bad = (hit != o_hit) | (np.where(hit, oid, -1) != np.where(o_hit, o_id, -1))
    flagged = np.any(np.stack([orc[k] < FLAG * U[precision] for k in DIAG_KEYS]), axis=0)
    same = hit & o_hit & (oid == o_id)
    t, t0 = depth[same], orc["depth.Z"][same]
    rel = np.abs(t - t0) / np.maximum(np.abs(t0), 1e-300)
    modelled = np.zeros(len(o_hit), bool) if modelled is None else modelled
    return {"pixels": int(len(o_hit)), "mask_mismatch": int(bad.sum()),
            "mask_mismatch_unflagged": int((bad & ~flagged & ~modelled).sum()),
            "mask_mismatch_modelled": int((bad & ~flagged & modelled).sum()),
            "flagged": int(flagged.sum()), "depth_pixels": int(same.sum()),
            "depth_max_rel": float(rel.max()) if len(rel) else 0.0,
            "depth_p99_rel": float(np.percentile(rel, 99)) if len(rel) else 0.0}


# --- one scene at one resolution ---------------------------------------------------------------

def measure(scene, columns: int, settings: Settings, progress=None) -> list[dict]:
    """Every configuration of ``scene`` at ``columns``: rows for the report."""
    from rt_core import backend
    from rt_core.camera import make_camera, primary_directions
    from mitsuba_ref.oracle import oracle_pixels
    from rt_core.rules import Rules
    from mitsuba_ref.convert import plane_extent
    from mitsuba_ref.explain import CLASS_CODE, classify
    from mitsuba_ref.reference import MitsubaScene, trace_rays
    from mitsuba_ref.convert import mitsuba_subset
    # objects Mitsuba has no shape for (cone, ellipsoid, torus) are left out on every side,
    # and said so
    scene, note = mitsuba_subset(scene)
    cam = make_camera(scene, columns)
    idx = sample_index(cam.size, settings.sample, settings.seed + columns)
    t0 = time.perf_counter()
    orc = oracle_pixels(scene, cam.columns, cam.rows, idx)
    oracle_s = time.perf_counter() - t0
    base = {"scene": scene.path, "scene_sha256": scene.sha256, "columns": cam.columns,
            "rows": cam.rows, "rays": cam.size,
            "sample": len(idx), "oracle_s": round(oracle_s, 3), **({"note": note} if note else {})}

    calls, results, prep = {}, {}, {}
    for p in ("f32", "f64"):
        t0 = time.perf_counter()
        fns, result = _rt_calls(scene, cam, p)
        prep[f"rt_core-{p}"] = time.perf_counter() - t0
        for mode, fn in fns.items():
            calls[f"rt_core-{p}-{mode}"] = fn
        results[f"rt_core-{p}"] = (result, p)
    T32 = backend.types("f32")
    d = primary_directions(scene, cam, T32)
    d32 = np.stack([np.asarray(c.numpy(), np.float32) for c in (d.x, d.y, d.z)], 1)
    t0 = time.perf_counter()
    ms = MitsubaScene(scene, cam.columns, cam.rows)
    fns, _ = _mitsuba_calls(ms, d32)
    prep["mitsuba"] = time.perf_counter() - t0
    for mode, fn in fns.items():
        calls[f"mitsuba-{mode}"] = fn

    rows = {}
    for name, fn in calls.items():
        sec, _, stats, mem = first_call(fn)
        tracer = name.rsplit("-", 1)[0]
        rows[name] = dict(base, config=name, tracer=tracer, mode=name.rsplit("-", 1)[1],
                          precision="f64" if "f64" in name else "f32",
                          prepare_ms=round(prep[tracer] * 1e3, 3),
                          first_ms=round(sec * 1e3, 3), **stats,
                          jit_peak_bytes=mem.jit_peak, rss_peak_bytes=mem.rss_peak)
    times = round_robin(calls, settings.reps)
    for name, ts in times.items():
        rows[name]["steady_ms"] = round(statistics.median(ts) * 1e3, 4)
        rows[name]["steady_min_ms"] = round(min(ts) * 1e3, 4)
        rows[name]["mrays_per_s"] = round(cam.size / statistics.median(ts) / 1e6, 2)

    # errors: rt_core from its full render, Mitsuba from the reference's own trace_rays
    for tracer, (result, p) in results.items():
        hit, oid, depth = result()
        e = errors(hit[idx], oid[idx], depth[idx], orc, p)
        for mode in ("prelim", "full"):
            rows[f"{tracer}-{mode}"].update(e)
    ref = trace_rays(ms, d32, full=False)
    ref = {k: np.asarray(v)[idx] for k, v in ref.items()}
    # Mitsuba's mismatches that its scene model explains (explain.classify, oracle as "ours")
    classes = classify(scene, d32[idx].astype(np.float64), orc, ref, Rules(),
                       plane_extent(scene))
    modelled = (classes != CLASS_CODE["agree"]) & (classes != CLASS_CODE["unexplained"])
    e = errors(ref["hit.mask"] > 0, ref["object.id"], np.asarray(ref["depth.Z"], np.float64),
               orc, "f32", modelled)
    for mode in ("prelim", "full"):
        rows[f"mitsuba-{mode}"].update(e)
    del ms
    out = [rows[c] for c in CONFIGS]
    if progress:
        progress(out)
    return out


def run_report(scenes, settings: Settings = Settings(), progress=None) -> dict:
    """Every scene at every resolution; {'meta', 'rows', 'summary', 'pareto'}."""
    from rt_core.render import versions
    t0 = time.perf_counter()
    rows = []
    for scene in scenes:
        for c in settings.columns:
            rows += measure(scene, c, settings, progress)
    summ = summary(rows)
    meta = {"columns": list(settings.columns), "sample": settings.sample,
            "reps": settings.reps, "seed": settings.seed, "scenes": [s.path for s in scenes],
            "reference": "float64 per-ray oracle (mitsuba_ref/oracle.py) at sampled pixels",
            "flag_margin_u": FLAG, "run_s": round(time.perf_counter() - t0, 2),
            **versions(), **machine()}
    return {"meta": meta, "rows": rows, "summary": summ, "pareto": pareto(summ)}


# --- aggregation, Pareto front ----------------------------------------------------------------

def summary(rows) -> list[dict]:
    """One point per (configuration, resolution): times summed over the scenes, the worst
    errors over them."""
    out = []
    keys = dict.fromkeys((r["config"], r["columns"]) for r in rows)
    for cfg, cols in keys:
        rs = [r for r in rows if r["config"] == cfg and r["columns"] == cols]
        rays = sum(r["rays"] for r in rs)
        steady = sum(r["steady_ms"] for r in rs)
        out.append({"config": cfg, "columns": cols, "scenes": len(rs),
                    "steady_ms": round(steady, 4),
                    "ns_per_ray": round(steady * 1e6 / rays, 4),
                    "first_ms": round(sum(r["first_ms"] for r in rs), 3),
                    "compile_ms": round(sum(r["compile_ms"] for r in rs), 3),
                    "rays": rays,
                    "sample": sum(r["sample"] for r in rs),
                    "mask_mismatch": sum(r["mask_mismatch"] for r in rs),
                    "mask_mismatch_unflagged": sum(r["mask_mismatch_unflagged"] for r in rs),
                    "mask_mismatch_modelled": sum(r.get("mask_mismatch_modelled", 0)
                                                  for r in rs),
                    "depth_p99_rel": max(r["depth_p99_rel"] for r in rs),
                    "depth_max_rel": max(r["depth_max_rel"] for r in rs),
                    "jit_peak_bytes": max(r["jit_peak_bytes"] for r in rs),
                    "rss_peak_bytes": max(r["rss_peak_bytes"] for r in rs)})
        p = out[-1]
        # one error per configuration: a wrong pixel counts, not only the depth of right ones
        p["error"] = max(p["depth_p99_rel"], p["mask_mismatch_unflagged"] / max(p["sample"], 1))
    return out


ERROR_FLOOR = 1e-17          # zero errors are drawn here on the log axis


def pareto(points, x: str = "ns_per_ray", y: str = "error") -> list[int]:
    """Indices of the points no other point beats in both x and y (both minimized)."""
    front = []
    for i, p in enumerate(points):
        if not any((q[x] <= p[x] and q[y] <= p[y]) and (q[x] < p[x] or q[y] < p[y])
                   for j, q in enumerate(points) if j != i):
            front.append(i)
    return front


def plot(result: dict, path: str) -> None:
    """Log-log PNG: error (worst depth p99 relative error, or the fraction of unflagged
    mismatching pixels if larger) against steady time per ray (summed over the scenes), one
    point per configuration and resolution, the Pareto front joined and ringed."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pts = result["summary"]
    front = set(result["pareto"])
    colors = {"rt_core-f32": "tab:blue", "rt_core-f64": "tab:green", "mitsuba": "tab:red"}
    fig, ax = plt.subplots(figsize=(8, 5.5), dpi=110)
    seen = set()
    for i, p in enumerate(pts):
        tracer, mode = p["config"].rsplit("-", 1)
        label = p["config"] if p["config"] not in seen else None
        seen.add(p["config"])
        y = max(p["error"], ERROR_FLOOR)
        ax.scatter(p["ns_per_ray"], y, c=colors[tracer], marker="o" if mode == "prelim" else "s",
                   s=28, label=label, zorder=3)
        ax.annotate(str(p["columns"]), (p["ns_per_ray"], y), fontsize=6,
                    xytext=(3, 3), textcoords="offset points")
        if i in front:
            ax.scatter(p["ns_per_ray"], y, s=140, facecolors="none", edgecolors="k", zorder=4)
    fr = sorted((pts[i]["ns_per_ray"], max(pts[i]["error"], ERROR_FLOOR)) for i in front)
    if fr:
        ax.step(*zip(*fr), where="post", color="k", lw=0.8, label="Pareto front")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("steady-state time per ray (ns): medians summed over the scenes / their rays")
    ax.set_ylabel("error: max(worst depth p99 rel., unflagged mismatch fraction)")
    ax.set_title("Error against time (labels: columns; o preliminary, s full)", fontsize=9)
    ax.grid(True, which="both", lw=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    from rt_core.outputs import save_figure
    save_figure(fig, path, {f"rtval.{k}": v for k, v in result["meta"].items()
                            if isinstance(v, (str, int, float))})
    plt.close(fig)


# --- files -------------------------------------------------------------------------------------

def _mib(b: int) -> str:
    return "n/a" if b < 0 else f"{b / 2 ** 20:.1f}"


def markdown(result: dict, png: str) -> str:
    m = result["meta"]
    L = ["# rtval report: error against run time", "",
         f"Scenes: {len(m['scenes'])}; resolutions (columns): {', '.join(map(str, m['columns']))};"
         f" rows per the scene's window (rows = int(h/w · columns)); {m['reps']} timed calls "
         f"per configuration after the first; whole run {m['run_s']} s.", "",
         "**Reference**: the float64 per-ray oracle (mitsuba_ref/oracle.py: the notes' formulas in "
         "plain Python, one ray at a time), evaluated at "
         f"**{m['sample']} pixels per scene and resolution** drawn with a fixed seed (all "
         "pixels when the image has fewer). Errors are counted at those pixels only: the "
         "sample is the reference, not rt_core f64.", "",
         "* mask mismatch: hit or object id differs from the oracle; *unflagged*: at pixels "
         f"whose decisions the oracle does not flag as within {m['flag_margin_u']:g} u of "
         "flipping (u of the deciding precision; Mitsuba is float32) and, for Mitsuba, not "
         "explained by its scene model (mitsuba_ref/explain.py classes, e.g. the horizon "
         "beyond an infinite plane's finite stand-in: counted as *modelled*);",
         "* depth: relative error where both hit the same object (max and 99th percentile);",
         "* time: first call (compilation included; `compiled` = kernels compiled then) and "
         "steady state (median, `dr.sync_thread()` after each). rt_core times its whole kernel "
         "(camera rays included); Mitsuba its intersection kernels only, on rays prepared "
         "beforehand (same rays as rt_core f32);",
         "* memory: first call's peak growth of Dr.Jit's allocations (allocator watermark, "
         "cache flushed first) and of the process's resident set (VmHWM reset via "
         "/proc/self/clear_refs; includes LLVM compiling and Embree's BVH).", "",
         f"Kernel cache: {m['kernel_cache']}. Machine: {m.get('cpu', '?')}, {m['cpus']} CPUs, "
         f"Dr.Jit {m.get('drjit')}, Mitsuba {m.get('mitsuba')}, LLVM {m['llvm']}. Shared machine:"
         " compare ratios within this run, not absolute times.", "",
         f"![error against time]({os.path.basename(png)})", "",
         "## Summary (per configuration and resolution, over all scenes)", "",
         "Pareto front (time per ray, error) marked ★; error = the worst depth p99, or the "
         "fraction of sampled pixels with an unflagged mismatch if that is larger.", "",
         "| config | columns | ns/ray | steady ms (sum) | first ms (sum) | compile ms | mismatches / "
         "sampled | unflagged | modelled | depth p99 (worst) | depth max (worst) | Dr.Jit peak "
         "MiB | RSS peak MiB |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    front = set(result["pareto"])
    for i, p in enumerate(result["summary"]):
        L.append(f"| {p['config']}{' ★' if i in front else ''} | {p['columns']} | "
                 f"{p['ns_per_ray']:.2f} | {p['steady_ms']:.2f} | {p['first_ms']:.1f} | {p['compile_ms']:.1f} | "
                 f"{p['mask_mismatch']} / {p['sample']} | {p['mask_mismatch_unflagged']} | "
                 f"{p.get('mask_mismatch_modelled', 0)} | {p['depth_p99_rel']:.2e} | {p['depth_max_rel']:.2e} | "
                 f"{_mib(p['jit_peak_bytes'])} | {_mib(p['rss_peak_bytes'])} |")
    L += ["", "## Per scene", ""]
    for scene in m["scenes"]:
        # (objects left out of the measured scene, said where it is: the JSON rows only,
        # a torus scene's report read as the torus's, a review)
        notes = dict.fromkeys(r["note"] for r in result["rows"]
                              if r["scene"] == scene and r.get("note"))
        L += [f"### {os.path.basename(scene)}", ""] + \
            [f"Measured without the objects Mitsuba has no shape for, in every "
             f"configuration (rt_core's and the oracle's too): {n.split(': ', 1)[-1]}.\n"
             for n in notes] + ["",
              "| config | columns | rays | sample | oracle s | mismatches | unflagged | depth "
              "pixels | depth p99 | depth max | first ms | compiled | steady ms (fastest) | "
              "Mrays/s | Dr.Jit MiB | RSS MiB |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in result["rows"]:
            if r["scene"] != scene:
                continue
            # (the depth's pixels: its p99 of 2 pixels read as a measure, and the fastest
            # call beside the median, a review)
            L.append(f"| {r['config']} | {r['columns']} | {r['rays']} | {r['sample']} | "
                     f"{r['oracle_s']:.2f} | {r['mask_mismatch']} | "
                     f"{r['mask_mismatch_unflagged']} | {r['depth_pixels']} | "
                     f"{r['depth_p99_rel']:.2e} | "
                     f"{r['depth_max_rel']:.2e} | {r['first_ms']:.1f} | {r['compiled']} | "
                     f"{r['steady_ms']:.3f} ({r['steady_min_ms']:.3f}) | "
                     f"{r['mrays_per_s']:.1f} | "
                     f"{_mib(r['jit_peak_bytes'])} | {_mib(r['rss_peak_bytes'])} |")
        L.append("")
    return "\n".join(L) + "\n"


def write_report(result: dict, outdir: str) -> tuple[str, str, str]:
    """report.json, report.md and error_vs_time.png under ``outdir``; returns their paths."""
    from rt_core.outputs import atomic_write, together, write_json
    js = os.path.join(outdir, "report.json")
    md = os.path.join(outdir, "report.md")
    png = os.path.join(outdir, "error_vs_time.png")
    # the three files or none of them, and no directory made for them (together: a full
    # disk left the PNG and a new directory, a review; over an earlier report, a new PNG
    # beside the old JSON)
    with together():
        plot(result, png)
        write_json(js, result)
        atomic_write(md, lambda tmp: Path(tmp).write_text(markdown(result, png)))
    return md, js, png
