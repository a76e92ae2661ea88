"""rt_core against Mitsuba, pixel by pixel: every disagreement classed and counted.

Modes: ``rays`` — Mitsuba intersects the exact rays rt_core traced; ``camera`` — Mitsuba
renders through its own perspective sensor (aov integrator).
"""
from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field

import numpy as np

from rt_core import backend
from rt_core.camera import make_camera
from rt_core.memory import compare_bytes, guard
from rt_core.render import (DIRECTION_CHANNELS, provenance, to_images, trace_geometry,
                            write_images)
from rt_core.rules import Rules
from rt_core.scene import Scene
from mitsuba_ref.convert import mitsuba_subset, plane_extent, sensor_setup
from mitsuba_ref.explain import CLASS_CODE, CLASSES, classify, over_bound
from mitsuba_ref.reference import MitsubaScene, render_camera, trace_rays
from .agree import same_rows
from .timing import Stopwatch

MODES = ("rays", "camera")


@dataclass
class Comparison:
    scene: Scene
    mode: str
    precision: str
    columns: int
    rows: int
    classes: np.ndarray                 # (rows, columns) class codes
    ours: dict
    ref: dict
    depth: dict                         # max, p99, mean relative error; pixels; over_bound
    ms_ours: float
    ms_ref: float
    note: str = ""
    counts: dict = field(default_factory=dict)
    sampling: str = "corners"
    rules: Rules = Rules()
    backend: str = "llvm"
    seconds: dict = field(default_factory=dict)     # per phase (tools/harness/timing.py)
    timed: str = "second call"          # which call ms_ours and ms_ref time (``compare``)

    @property
    def unexplained(self) -> int:
        return self.counts.get("unexplained", 0)

    @property
    def explained(self) -> int:
        return sum(v for k, v in self.counts.items() if k not in ("agree", "unexplained"))

    @property
    def ok(self) -> bool:
        return self.unexplained == 0 and self.depth["over_bound"] == 0

    def summary(self) -> dict:
        return {"scene": self.scene.path, "scene_sha256": self.scene.sha256,
                "mode": self.mode, "precision": self.precision, "backend": self.backend,
                "sampling": self.sampling, "rules": self.rules.describe(),
                "columns": self.columns, "rows": self.rows, "pixels": self.columns * self.rows,
                "classes": self.counts, "explained": self.explained,
                "unexplained": self.unexplained, "depth": self.depth,
                "rt_core_ms": round(self.ms_ours, 3), "mitsuba_ms": round(self.ms_ref, 3),
                "timed": self.timed, "seconds": self.seconds, "ok": self.ok, "note": self.note}


def compare(scene: Scene, columns: int, rows: int | None = None, precision: str = "f32",
            mode: str = "rays", sampling: str = "corners", rules: Rules = Rules(),
            backend_name: str = "llvm", cache: dict | None = None,
            calls: int = 2, guarded: bool = False) -> Comparison:
    """rt_core against Mitsuba on one scene in one mode.  ``cache``: a dict shared by the
    comparisons of one scene (validate's rays and camera modes): rt_core's trace of the same
    camera and Mitsuba's loaded scene are made once between them (the time charged to the
    first).  ``calls``: each side runs twice and its second call is timed (the steady state:
    ``rtval compare``), or once (``rtval validate``: its time then includes finding, or
    compiling, the kernels; ``rtval bench`` times the steady state).  ``guarded``: the
    caller has checked this size against the memory there is (validate, before its run)."""
    cache = {} if cache is None else cache
    if calls < 1:
        raise ValueError(f"calls must be 1 or more, not {calls}")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}")
    sw = Stopwatch()
    given = scene                   # (the cache's key: what follows makes copies of it)
    with sw("other"):
        T = backend.types(precision, backend_name)
        # kinds without a Mitsuba shape (cone, ellipsoid, torus) are left out on both sides
        scene, subset_note = mitsuba_subset(scene)
        cam = make_camera(scene, columns, rows, sampling)
        same_rows(scene, columns, rows, cam)
        if not guarded:
            guard(lambda px: compare_bytes(px, precision), "compare", cam.columns, cam.rows)
        note = ""
        if mode == "camera":
            setup = sensor_setup(scene, cam.columns, cam.rows, sampling)
            if not setup.square:
                # Mitsuba's pixels are square: compare with rt_core on that same camera
                note = setup.note
                ww = scene.window[0]
                h = cam.sx * ((cam.rows - 1) if sampling == "corners" else cam.rows)
                scene = dataclasses.replace(scene, window=(ww, h))
                cam = make_camera(scene, columns, cam.rows, sampling)
    # ours (timed: the last of ``calls`` calls); the same scene, camera and precision in
    # another mode reuses it (its row then repeats that time: "rt_core shared")
    key = (id(given), scene.window, cam.columns, cam.rows, sampling, rules, precision,
           backend_name)
    shared = ("ours", *key) in cache
    if not shared:
        with sw("rt_core"):
            for _ in range(calls):
                t0 = time.perf_counter()
                # (the directions as traced, by the same kernel: Mitsuba's rays and the
                # classifier's)
                flat = trace_geometry(scene, cam, T, rules, directions=True)
                ms_ours = (time.perf_counter() - t0) * 1e3
            dirs = [flat.pop(c) for c in DIRECTION_CHANNELS]
            ours = to_images(flat, cam)
        with sw("other"):
            d = np.stack([np.asarray(c.numpy(), np.float64) for c in dirs], 1)
        cache[("ours", *key)] = (ours, ms_ours, d, given)   # (the scene keeps its id alive)
    ours, ms_ours, d, _ = cache[("ours", *key)]
    with sw("mitsuba"):
        mkey = ("mitsuba", *key[:5], rules.clip_spheres)
        if mkey not in cache:
            cache[mkey] = (MitsubaScene(scene, cam.columns, cam.rows, sampling,
                                        clip_spheres=rules.clip_spheres), given)
        ms = cache[mkey][0]
        for _ in range(calls):
            t0 = time.perf_counter()
            if mode == "rays":
                ref = {k: v.reshape(cam.rows, cam.columns) for k, v in trace_rays(ms, d).items()}
            else:
                ref = render_camera(ms, d)
            ms_ref = (time.perf_counter() - t0) * 1e3
    with sw("classify"):
        flat_o = {k: v.ravel() for k, v in ours.items()}
        flat_r = {k: v.ravel() for k, v in ref.items()}
        extent = plane_extent(scene)
        classes = classify(scene, d, flat_o, flat_r, rules, extent).reshape(cam.rows, cam.columns)
        # depth error where both hit the same object
        same = np.flatnonzero((flat_o["hit.mask"] > 0) & (flat_r["hit.mask"] > 0) &
                              (flat_o["object.id"] == flat_r["object.id"]) &
                              (classes.ravel() == 0))
        t_o = flat_o["depth.Z"][same].astype(np.float64)
        t_r = flat_r["depth.Z"][same].astype(np.float64)
        rel = np.abs(t_o - t_r) / np.maximum(np.abs(t_r), 1e-300)
        over = over_bound(scene, d, same, flat_o["object.id"][same].astype(np.int64), t_r,
                          rel, extent, rules)
    depth = {"pixels": len(same),
             "max_rel": float(rel.max()) if len(rel) else 0.0,
             "p99_rel": float(np.percentile(rel, 99)) if len(rel) else 0.0,
             "mean_rel": float(rel.mean()) if len(rel) else 0.0,
             "over_bound": over}
    counts = {c: int(np.count_nonzero(classes == i)) for i, c in enumerate(CLASSES)}
    note = "; ".join(n for n in (note, subset_note) if n)
    return Comparison(scene, mode, precision, cam.columns, cam.rows, classes, ours, ref, depth,
                      ms_ours, ms_ref, note, counts, sampling, rules, backend_name,
                      sw.rounded(), ("second call" if calls > 1 else "first call")
                      + ("; rt_core shared with another mode" if shared else ""))


EVIDENCE = ("ours", "reference", "diff", "classes")


def write_evidence(cmp: Comparison, outdir: str, stem: str, which=EVIDENCE) -> list[str]:
    """EXRs of ours, the reference, their difference and the classes (or the ones named in
    ``which``); returns the paths written.  The reference's file is named for it:
    ``STEM.mitsuba.exr``, or ``STEM.exact.exr`` for a comparison with the exact oracle
    (tools/harness/exact_compare.py)."""
    cam = make_camera(cmp.scene, cmp.columns, cmp.rows, cmp.sampling)
    if cmp.mode == "exact":
        from .exact_compare import REFERENCE
        ref_name, reference = "exact", REFERENCE
    else:
        ref_name, reference = "mitsuba", "mitsuba " + _mitsuba_version() + " llvm_ad_rgb"
    attrs = provenance(cmp.scene, cam, cmp.precision, cmp.backend, cmp.rules, mode=cmp.mode,
                       reference=reference)
    legend = ", ".join(f"{i}={c}" for i, c in enumerate(CLASSES))
    images = {
        "ours": (cmp.ours, {}),
        "reference": (cmp.ref, {}),
        "diff": ({k: np.abs(cmp.ours[k].astype(np.float64) - cmp.ref[k]) for k in cmp.ours},
                 {"rtval.image": f"|ours - {ref_name}|"}),
        "classes": ({"class.id": cmp.classes,
                     "class.unexplained": cmp.classes == CLASS_CODE["unexplained"]},
                    {"rtval.classes": legend}),
    }
    paths = []
    for name in which:
        imgs, extra = images[name]
        name = ref_name if name == "reference" else name
        path = os.path.join(outdir, f"{stem}.{name}.exr")
        write_images(path, imgs, {**attrs, "rtval.image": name, **extra})
        paths.append(path)
    return paths


def _mitsuba_version() -> str:
    from importlib import metadata
    return metadata.version("mitsuba")
