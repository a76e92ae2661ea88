"""rt_core against the exact oracle, pixel by pixel: the scenes Mitsuba cannot check.

Mitsuba has no cone, ellipsoid or torus, so the Mitsuba comparisons leave those objects out
on both sides (mitsuba_ref.convert.mitsuba_subset) and a fault in rt_core's cone passed every
one of them.  This comparison traces the whole scene, every kind, through rt_core's camera
and against mitsuba_ref/exact.py, which decides each pixel's closest hit in rational
arithmetic on the course's ideal ray (the exact corner sample − viewpoint) from the file's
text read by the references' own reader: nothing of rt_core's parser, scene model, camera or
kernels is shared.

* float64: rt_core decides every primary hit exactly (certified, the rest by
  rt_core/decide.py), so every pixel must be the exact oracle's object: any other is
  ``unexplained``.  Nothing is excused.
* float32: a pixel whose object differs is excused only where rt_core's answer is one that
  decisions within K·u·S of their thresholds give (``ExactResult.reasons(reach=True)``: its
  object, if the oracle's misses it, can flip to a hit, and every object hit in front of it
  can flip to a miss or lies at its depth within their bounds, both hit); the class names
  the decision (CLASSES: an outline or the torus's crossing is a
  silhouette, a rectangle's, rim's, triangle's or axial bound's or t's test an edge, the
  screen clip a clip, a plane parallel to the ray a graze).  Else ``unexplained``.  A
  margin of exactly 0 is within reach too: the ideal ray hits the edge exactly, but
  rt_core's camera rounds it (``trace_exact`` on ideal rays).
* depth: where both hit the same object, |t − t*|/t* <= K·u·κ_t (κ_t: the relative
  condition number of the exact t), else ``over_bound``; in float32 but ``other_root``
  where an open cylinder or cone is hit at its other root within that root's bound and
  decisions within reach take it there (the same object, at the other depth).
"""
from __future__ import annotations

import hashlib
import time

import numpy as np

from mitsuba_ref.exact import K_ROUNDING, U, ideal_rays, parse_exact, trace_exact
from mitsuba_ref.explain import CLASS_CODE
from rt_core import backend
from rt_core.camera import make_camera
from rt_core.memory import compare_bytes, guard
from rt_core.render import to_images, trace_geometry
from rt_core.rules import Rules
from rt_core.scene import Scene, SceneError
from .agree import same_rows
from .compare import Comparison
from .timing import Stopwatch

MODE = "exact"
KEYS = ("hit.mask", "object.id", "depth.Z")
# which class a decision of mitsuba_ref/exact.py's DECISIONS excuses a pixel as
DECISION_CLASS = {"outline": "silhouette", "crossing": "silhouette", "clip": "clip",
                  "parallel": "graze", "tie": "tie"}
REFERENCE = "exact oracle (mitsuba_ref/exact.py, rational arithmetic, ideal rays)"


# The exact oracle's rational arithmetic takes 0.03-0.18 ms a pixel on the scenes with
# these kinds (measured at 48 and 160 columns, this project's 2-core machine): an image of
# more pixels than this (about 580 columns of a 4:3 window, up to ~45 s a scene) is
# refused rather than left to run for hours
MAX_PIXELS = 250_000

# the exact oracle of the last image compared: a scene's f32 and f64 comparisons share it
_ORACLE: list = [None, None]


def needs_exact(scene: Scene) -> bool:
    """Has the scene an object that the Mitsuba comparisons leave out (no Mitsuba shape)?"""
    from mitsuba_ref.convert import oracle_only
    return bool(oracle_only(scene))


def check_size(columns: int, rows: int, option: str = "--columns", limit: int = MAX_PIXELS,
               why: str = "exact oracle's {limit:,} (its rational arithmetic takes up to "
                          "0.18 ms a pixel)") -> None:
    """InputError where an oracle would take too long: more pixels than ``limit`` (the
    exact oracle's ``MAX_PIXELS``, or another's with its ``why``)."""
    if columns * rows > limit:
        from rt_core.errors import InputError
        raise InputError(f"{option} {columns}: {columns} x {rows} pixels is more than the "
                         f"{why.format(limit=limit)}; give fewer columns")


def scene_source(scene: Scene) -> bytes:
    """The bytes of the scene's file, as the references' reader reads them (validate reads
    them here, so that a job on another machine needs no file)."""
    from rt_core.inputfile import read_input
    return read_input(scene.path, "scene")


def reference_scene(scene: Scene, code27: str = "auto", source: bytes | None = None):
    """The scene's file (``source``: its bytes, else read now) read by the references'
    reader, numbers exact (the file must be the one rt_core read: its SHA-256)."""
    raw = scene_source(scene) if source is None else source
    if scene.sha256 and hashlib.sha256(raw).hexdigest() != scene.sha256:
        raise SceneError("the file changed while rtval read it; run again", str(scene.path))
    return parse_exact(raw.decode("utf-8", "replace"), code27)


def _other_root(ex, ids, t_ours, rays, u: float) -> int:
    """How many of ``rays`` (the tracer's object the exact one, its depth over the bound)
    hit that open cylinder or cone at its other root instead, within the bound of that
    root's depth, where decisions within reach of rounding in precision u take it there."""
    n = 0
    for k in np.unique(ids[rays]):
        ob, sel = ex.objects[k], rays[ids[rays] == k]
        if "other t" not in ob.margin:
            continue
        t_o = ob.margin["other t"][sel]
        with np.errstate(invalid="ignore"):
            near = np.abs(t_ours[sel] - t_o) <= K_ROUNDING * u * ob.cond["other t"][sel]
        n += int(np.count_nonzero(near & ob.other_root_within_reach(u, sel)))
    return n


def compare_exact(scene: Scene, columns: int, precision: str = "f32", rules: Rules = Rules(),
                  backend_name: str = "llvm", code27: str = "auto", guarded: bool = False,
                  rows: int | None = None, sampling: str = "corners",
                  source: bytes | None = None) -> Comparison:
    """rt_core at ``precision`` against the exact oracle on every pixel of the scene's
    image at ``columns`` (module docstring).  ``code27``: how the file was read;
    ``source``: its bytes (``scene_source``), else it is read here."""
    sw = Stopwatch()
    with sw("other"):
        T = backend.types(precision, backend_name)
        cam = make_camera(scene, columns, rows, sampling)
        same_rows(scene, columns, rows, cam)
        check_size(cam.columns, cam.rows)
        if not guarded:
            guard(lambda px: compare_bytes(px, precision), "compare", cam.columns, cam.rows)
    with sw("rt_core"):
        t0 = time.perf_counter()
        ours = to_images(trace_geometry(scene, cam, T, rules), cam)
        ms_ours = (time.perf_counter() - t0) * 1e3
    n = cam.columns * cam.rows
    with sw("oracle"):              # the reference's image (Mitsuba's phase elsewhere)
        t0 = time.perf_counter()
        key = (str(scene.path), scene.sha256, cam.columns, cam.rows, sampling, rules, code27)
        shared = _ORACLE[0] == key
        if not shared:
            _ORACLE[:] = [None, None]           # (a failed read keeps nothing)
            xs = reference_scene(scene, code27, source)
            rays, d = ideal_rays(xs.window, xs.viewpoint, cam.columns, cam.rows, range(n),
                                 sampling)
            ex = trace_exact(xs, d, rules, rays=rays)
            # distances along the unit ray: the exact t is in units of the ray E/L
            _ORACLE[:] = [key, (ex, ex.t * ex.length)]
        ex, t_ref = _ORACLE[1]
        ms_ref = (time.perf_counter() - t0) * 1e3
    with sw("classify"):
        u = U[precision]
        ids = np.where(ours["hit.mask"].ravel() > 0, ours["object.id"].ravel(), -1)
        ids = ids.astype(np.int64)
        classes = np.full(n, CLASS_CODE["agree"], np.int8)
        bad = np.flatnonzero(ids != ex.id)
        if len(bad):
            classes[bad] = CLASS_CODE["unexplained"]
            if precision != "f64":      # float64 decides exactly: nothing to excuse
                # (on the ideal rays, not rt_core's rounded ones, a zero margin is within
                # reach: trace_exact)
                why = ex.reasons(ids, u, reach=True)
                for r in bad:
                    if why[r] is not None:
                        classes[r] = CLASS_CODE[DECISION_CLASS.get(why[r], "edge")]
        t_ours = ours["depth.Z"].ravel().astype(np.float64)
        same = np.flatnonzero(ex.hit & (ids == ex.id))
        rel = np.abs(t_ours[same] - t_ref[same]) / t_ref[same]
        with np.errstate(invalid="ignore"):
            out_of = same[~(rel <= K_ROUNDING * u * ex.kappa_t[same])]
        other = _other_root(ex, ids, t_ours, out_of, u) if precision != "f64" else 0
        over = len(out_of) - other
        shape = (cam.rows, cam.columns)
        ref = {"hit.mask": ex.hit.reshape(shape).astype(np.float32),
               "object.id": ex.id.reshape(shape).astype(np.float32),
               "depth.Z": t_ref.reshape(shape)}
    depth = {"pixels": len(same),
             "max_rel": float(rel.max()) if len(rel) else 0.0,
             "p99_rel": float(np.percentile(rel, 99)) if len(rel) else 0.0,
             "mean_rel": float(rel.mean()) if len(rel) else 0.0,
             "over_bound": over, "other_root": other}
    counts = {c: int(np.count_nonzero(classes == i)) for c, i in CLASS_CODE.items()}
    return Comparison(scene, MODE, precision, cam.columns, cam.rows,
                      classes.reshape(cam.rows, cam.columns),
                      {k: ours[k] for k in KEYS}, ref, depth, ms_ours, ms_ref,
                      "every object, against " + REFERENCE, counts, sampling, rules,
                      backend_name, sw.rounded(),
                      "first call" + ("; the exact oracle shared with another precision"
                                      if shared else ""))
