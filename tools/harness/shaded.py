"""The course image from rt_core against the course image Mitsuba renders with the ``course``
integrator (mitsuba_ref/integrator.py), 8-bit pixel by pixel.

Classes of a pixel (``SHADED_CLASSES``):

* ``match``: the same three 8-bit values;
* ``rounding``: no channel off by more than 1, and the float64 shading oracle
  (mitsuba_ref/shade_oracle.py) puts each channel that differs within float32's error bound
  of an 8-bit level (255·I within K·u·err of an integer): the two floors may differ there;
* ``boundary``: the oracle puts a decision of the pixel's rays (the primary or a reflection
  ray's closest hit, a shadow test, a tile's parity, the distance cut-off) within float32's
  bound of its threshold, and those decisions taken the other way give Mitsuba's colour
  (``other_sides``, any colour where they cannot all be enumerated), or a hit of its path
  on an infinite or tiled plane (a closest hit, or a shadow ray's blocker) beyond the
  square that stands in for the plane in Mitsuba's scene (the oracle's ``reach`` over
  ``plane_extent``, the geometry classifier's "extent" test: a reflection ray down a
  corridor of mirrors), or the geometry classifier
  (mitsuba_ref/explain.py, as in ``rtval compare --mode rays``) explains the primary ray's
  disagreement (an edge, a tie, the clip, the stand-in plane's extent, a grazing or
  parallel ray);
* ``wrong``: anything else.  A wrong pixel fails the comparison.

Beside the classes, NVIDIA FLIP (tools/harness/flip.py) says how visible the differences
are: its mean over the image (0 when the images are identical), and its error map among the
evidence.

rt_core renders in float64 with exact decisions; Mitsuba's variant is float32, so the
oracle's bounds are taken for float32 (``shade_oracle.flags(.., "f32")``).

Mode ``shaded-oracle`` (``compare_shaded(.., reference="oracle")``): the reference is the
float64 shading oracle's image of every object (Mitsuba has no cone, ellipsoid or torus, and
the comparison above leaves them out on both sides); the same classes, the bounds taken for
float64, no stand-in planes and no geometry classifier (both are Mitsuba's).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np

from rt_core import backend
from rt_core.camera import make_camera
from rt_core.memory import compare_bytes, guard
from rt_core.render import render_image
from rt_core.rules import Rules
from rt_core.scene import Scene
from rt_core.shading import DEFAULT_MAX_DIST, quantize
from .agree import same_rows
from .check import COLORS as CHECK_COLORS
from .timing import Stopwatch

SHADED_CLASSES = ("match", "rounding", "boundary", "wrong")
# the course image of a scene with objects Mitsuba has no shape for, every object, against
# the float64 shading oracle (``compare_shaded(.., reference="oracle")``)
ORACLE_MODE = "shaded-oracle"
SHADED_MODES = ("shaded", ORACLE_MODE)
# the object kinds the shaded comparison keeps (the others are left out on both sides, named
# in its note)
SHADED_KINDS = ("sphere", "plane", "fplane", "tplane", "cylinder", "triangle", "disk")
SHADED_CODE = {c: i for i, c in enumerate(SHADED_CLASSES)}
# other_sides_of stops a pixel's combinations once the colours asked about are found
# (False: every combination enumerated, as before; the same classes either way)
EARLY_OUT = True
# named colours of the classes image (evidence, HTML report): those of rtval check's classes
SHADED_COLOURS = {c: rgb for c, (_, rgb) in CHECK_COLORS.items() if c in SHADED_CLASSES}
SHADED_COLOUR_NAMES = {c: name for c, (name, _) in CHECK_COLORS.items() if c in SHADED_CLASSES}


@dataclass
class ShadedComparison:
    scene: Scene
    columns: int
    rows: int
    ours: np.ndarray                  # (rows, columns, 3) uint8, rt_core f64
    theirs: np.ndarray                # (rows, columns, 3) uint8, Mitsuba's course integrator
    classes: np.ndarray               # (rows, columns) SHADED_CODE
    counts: dict
    ms_ours: float
    ms_ref: float
    sampling: str = "corners"
    rules: Rules = Rules()
    max_dist: float = DEFAULT_MAX_DIST
    worst: list = field(default_factory=list)   # a few wrong pixels: (x, y, ours, theirs)
    flip_mean: float = 0.0            # NVIDIA FLIP, Mitsuba's image the reference
    flip: np.ndarray | None = None    # FLIP's per-pixel error; None when the images are equal
    note: str = ""                    # objects left out of the comparison
    seconds: dict = field(default_factory=dict)     # per phase (tools/harness/timing.py)
    reference: str = "mitsuba"        # or "oracle": the float64 shading oracle (ORACLE_MODE)
    boundary_reasons: dict = field(default_factory=dict)    # count by BOUNDARY_REASONS key

    @property
    def ok(self) -> bool:
        return self.counts.get("wrong", 0) == 0

    def summary(self) -> dict:
        oracle = self.reference == "oracle"
        return {"scene": self.scene.path, "scene_sha256": self.scene.sha256,
                "mode": ORACLE_MODE if oracle else "shaded",
                "precision": "f64 / oracle f64" if oracle else "f64 / mitsuba f32",
                "sampling": self.sampling,
                "rules": self.rules.describe(), "max_dist": self.max_dist,
                "columns": self.columns, "rows": self.rows,
                "pixels": self.columns * self.rows, "classes": self.counts,
                "wrong": self.counts.get("wrong", 0), "worst": self.worst,
                "flip_mean": self.flip_mean,
                "rt_core_ms": round(self.ms_ours, 3), "mitsuba_ms": round(self.ms_ref, 3),
                "timed": "first call", "seconds": self.seconds, "ok": self.ok, "note": self.note,
                "boundary_reasons": self.boundary_reasons}


def mitsuba_course_image(scene: Scene, columns: int, rows: int, sampling: str = "corners",
                         rules: Rules = Rules(), max_dist: float = DEFAULT_MAX_DIST,
                         integrator=None) -> np.ndarray:
    """Mitsuba's course image: (rows, columns, 3) float32 intensities, row 0 the top."""
    from mitsuba_ref.convert import mitsuba, scene_dict
    mi = mitsuba()
    d = scene_dict(scene, columns, rows, sampling, shading=True, rules=rules,
                   max_dist=max_dist)
    if integrator is not None:
        d["integrator"]["type"] = integrator
    ms = mi.load_dict(d, optimize=False)
    return np.asarray(ms.integrator().render(ms, 0), np.float32)


def quantize32(I: np.ndarray) -> np.ndarray:
    """floor(255 · clamp(I, 0, 1)) in float32 (Mitsuba's precision); NaN -> 0."""
    a = np.nan_to_num(np.asarray(I, np.float32), nan=0.0)
    return np.floor(np.float32(255) * np.clip(a, 0, 1)).astype(np.uint8)


# why a boundary pixel is one: the first of its near decisions in this order (the oracle's
# margins, shade_oracle.flags), in words (compare --shaded, a porting user's review: the
# boundary pixels' count said nothing of where Mitsuba differs)
BOUNDARY_REASONS = (
    ("beyond", "beyond the stand-in square of an infinite plane (Mitsuba's is finite)"),
    ("geo", "a ray's hit (an edge, the clip, a tie, a grazing ray)"),
    ("shadow", "a shadow ray (its blocker, or the light's side of the surface)"),
    ("tile", "a tile border"),
    ("maxdist", "the reflection cut-off (max_dist)"),
    ("texel", "a texel border"))


def classify_shaded(scene: Scene, ours: np.ndarray, theirs: np.ndarray, sampling: str,
                    rules: Rules, max_dist: float, precision: str = "f32",
                    stand_in: bool = True, reasons: dict | None = None) -> np.ndarray:
    """SHADED_CODE per pixel (module docstring); the oracle runs on the differing pixels.
    ``precision``: the reference's (Mitsuba's float32, or the shading oracle's float64);
    ``stand_in``: the reference's infinite planes are Mitsuba's finite squares;
    ``reasons``: a dict that gets the boundary pixels' count by BOUNDARY_REASONS key."""
    from mitsuba_ref.convert import plane_extent
    from mitsuba_ref.shade_oracle import (K_DECISION, U, flags, other_sides_of, reaches,
                                          shade_pixels)
    H, W = ours.shape[:2]
    diff = np.abs(ours.astype(np.int16) - theirs.astype(np.int16)).max(-1)
    classes = np.zeros((H, W), np.int8)
    pix = np.flatnonzero(diff.ravel())
    if not len(pix):
        return classes
    near = K_DECISION * U[precision]   # (the paths' near decisions, for other_sides)
    orc = shade_pixels(scene, W, H, pix, sampling, rules, max_dist, limit=near)
    f = flags(orc, precision)
    # (beyond the stand-in square as explain.ObjectEval's "extent" test takes it)
    beyond = orc["reach"] > plane_extent(scene) * (1 - 1e-6) if stand_in else \
        np.zeros(len(pix), bool)
    jump = f["jump"] | beyond
    # rounding: every channel that differs (by one level) lies near its level; another
    # channel near one is no excuse (a review: 69 of 223 such pixels a broken Mitsuba made)
    differs = (ours != theirs).reshape(-1, 3)[pix]
    quant = ~(differs & ~f["quant_rgb"]).any(-1)
    small = diff.ravel()[pix] <= 1
    # a decision within float32's bound excuses Mitsuba's colour only where those decisions,
    # taken the other way in some combination, give it exactly (other_sides): a review
    # scaled Mitsuba's green by 1.005 and 223 of 268 boundary pixels had no such
    # combination (134 were within a level of one).  Not asked where rounding excuses the
    # pixel anyway: class boundary, as before
    asked = np.flatnonzero((f["jump"] | beyond) & ~(small & quant))
    if len(asked):
        want = theirs.reshape(-1, 3)[pix[asked]].tolist()
        own = ours.reshape(-1, 3)[pix[asked]].tolist()
        # each pixel's two colours must both be ones its decisions give: Mitsuba's, and
        # rt_core's too (it is the unflipped path's only where rt_core is right: a review's
        # mutations of rt_core's shading, 1 to 250 levels off, passed as boundary); where the
        # combinations cannot all be enumerated, a search for them decides (REACH_RUNS
        # paths; not found, or not within them: not excused).  A path beyond the stand-in
        # square excuses Mitsuba's colour (its scene cannot see there), not rt_core's: the
        # oracle traces the plane itself
        aims = [(o,) if far else (w, o) for w, o, far in zip(want, own, beyond[asked])]
        # (a pixel stops once both are found: the rest of its combinations would not change
        # the answer)
        sides = other_sides_of(scene, W, H, pix[asked], sampling, rules, max_dist,
                               firsts=[orc["paths"][i] for i in asked], limit=near,
                               targets=aims if EARLY_OUT else None)
        gives = []
        for i, targets, s in zip(asked, aims, sides):
            if s is True:
                gives.append(True)
            elif s is None:
                gives.append(reaches(scene, W, H, int(pix[i]), targets, sampling, rules,
                                     max_dist, first=orc["paths"][i], limit=near) is True)
            else:
                gives.append(all(any(list(c) == list(t) for c in s) for t in targets))
        jump[asked] = np.array(gives, bool)
    code = np.where(jump, SHADED_CODE["boundary"],
                    np.where(small & quant, SHADED_CODE["rounding"], SHADED_CODE["wrong"]))
    classes.ravel()[pix] = code
    if reasons is not None:
        left = jump.copy()
        for key, _ in BOUNDARY_REASONS:
            took = left & (beyond if key == "beyond" else f[key])
            if took.any():
                reasons[key] = reasons.get(key, 0) + int(took.sum())
            left &= ~took
    return classes


def compare_shaded(scene: Scene, columns: int, rows: int | None = None,
                   sampling: str = "corners", rules: Rules = Rules(),
                   max_dist: float = DEFAULT_MAX_DIST, integrator=None,
                   guarded: bool = False, reference: str = "mitsuba") -> ShadedComparison:
    """rt_core's 8-bit course image (float64, exact decisions) against Mitsuba's.
    ``integrator``: the registered plugin name of the integrator to use (tests: a
    deliberately wrong one); default ``course``.  ``guarded``: the caller has checked this
    size against the memory there is.  ``reference="oracle"``: against the float64 shading
    oracle's image instead (mitsuba_ref/shade_oracle.py: every object, cones, ellipsoids
    and tori too; its decisions' bounds taken for float64; ``check_oracle_size``)."""
    oracle = reference == "oracle"
    sw = Stopwatch()
    with sw("other"):
        note = ""
        if not oracle:
            # the kinds compared: those below (cones, ellipsoids, the torus have no Mitsuba
            # shape)
            from mitsuba_ref.convert import mitsuba_subset
            scene, note = mitsuba_subset(scene, lambda k: k in SHADED_KINDS, inside=True)
        cam = make_camera(scene, columns, rows, sampling, rules)
        same_rows(scene, columns, rows, cam)
        if oracle:
            check_oracle_size(cam.columns, cam.rows)
        if not guarded:
            guard(lambda px: compare_bytes(px, "shaded"), "compare --shaded", cam.columns,
                  cam.rows)
    with sw("rt_core"):
        t0 = time.perf_counter()
        ims, _ = render_image(scene, cam, backend.types("f64"), rules, geometry=False,
                              shade=True, max_dist=max_dist)
        ms_ours = (time.perf_counter() - t0) * 1e3
        ours = quantize(np.stack([ims[c] for c in "RGB"], -1))
    with sw("oracle" if oracle else "mitsuba"):
        t0 = time.perf_counter()
        if oracle:
            from mitsuba_ref.shade_oracle import render_shade_oracle
            I = render_shade_oracle(scene, cam.columns, cam.rows, sampling, rules, max_dist)["I"]
        else:
            I = mitsuba_course_image(scene, cam.columns, cam.rows, sampling, rules, max_dist,
                                     integrator)
        ms_ref = (time.perf_counter() - t0) * 1e3
    with sw("classify"):
        if oracle:
            from mitsuba_ref.shade_oracle import quantize as quantize64
            theirs = quantize64(I)
        else:
            theirs = quantize32(I)
        reasons = {}
        classes = classify_shaded(scene, ours, theirs, sampling, rules, max_dist,
                                  "f64" if oracle else "f32", stand_in=not oracle,
                                  reasons=reasons)
        wrong = classes == SHADED_CODE["wrong"]
        if wrong.any() and not oracle:
            # the geometry classifier on the primary rays (Mitsuba tracing rt_core's rays, as
            # rtval compare --mode rays): a pixel whose first hit it explains (an edge, a tie,
            # the clip, the stand-in plane's extent, a grazing or parallel ray) is a boundary
            # pixel
            from tools.harness.compare import compare
            from mitsuba_ref.explain import CLASS_CODE
            geo = compare(scene, cam.columns, cam.rows, "f64", "rays", sampling, rules).classes
            explained = (geo != CLASS_CODE["agree"]) & (geo != CLASS_CODE["unexplained"])
            classes[wrong & explained] = SHADED_CODE["boundary"]
            if (wrong & explained).any():
                reasons["primary"] = int((wrong & explained).sum())
        counts = {c: int(np.count_nonzero(classes == i)) for i, c in enumerate(SHADED_CLASSES)}
        ys, xs = np.nonzero(classes == SHADED_CODE["wrong"])
        worst = [(int(x), int(y), ours[y, x].tolist(), theirs[y, x].tolist())
                 for y, x in list(zip(ys, xs))[:5]]
        flip, flip_mean = None, 0.0
        if (ours != theirs).any():          # FLIP of identical images is 0: not computed
            from tools.harness.flip import flip_map
            flip, flip_mean, _ = flip_map(theirs / np.float32(255), ours / np.float32(255))
    return ShadedComparison(scene, cam.columns, cam.rows, ours, theirs, classes, counts,
                            ms_ours, ms_ref, sampling, rules, max_dist, worst, flip_mean, flip,
                            note, sw.rounded(), reference, reasons)


# The shading oracle's image takes 0.3-1.6 ms a pixel on the course scenes with cones,
# ellipsoids and tori (1 to 19 objects, 0 to 2 lights; measured at 24 columns, this
# project's 2-core machine): a larger image than this (about 160 columns of a 4:3 window,
# up to ~30 s a scene) is refused rather than left to run for minutes
MAX_ORACLE_PIXELS = 20_000


def check_oracle_size(columns: int, rows: int, option: str = "--columns") -> None:
    """InputError where the shading oracle's image would take too long."""
    from .exact_compare import check_size
    check_size(columns, rows, option, MAX_ORACLE_PIXELS,
               "shading oracle's {limit:,} (it takes up to 1.6 ms a pixel)")


def classes_rgb(classes: np.ndarray) -> np.ndarray:
    """The classes as an 8-bit RGB image in their named colours (SHADED_COLOURS)."""
    lut = np.array([SHADED_COLOURS[c] for c in SHADED_CLASSES], np.uint8)
    return lut[classes]


def write_shaded_evidence(cmp: ShadedComparison, outdir: str, stem: str) -> list[str]:
    """PNGs of ours, the reference's (Mitsuba's or the shading oracle's), the classes (named
    colours, legend in the PNG's text) and, where they differ, FLIP's error map (magma),
    with provenance; returns the paths written."""
    from rt_core.imageio import write_png
    from tools.harness.flip import flip_colours
    os.makedirs(outdir, exist_ok=True)
    legend = ", ".join(f"{c}={SHADED_COLOUR_NAMES[c]} {'rgb(%d,%d,%d)' % SHADED_COLOURS[c]}"
                       for c in SHADED_CLASSES)
    text = {"rtval.scene": str(cmp.scene.path), "rtval.scene_sha256": cmp.scene.sha256,
            "rtval.rules": cmp.rules.describe(), "rtval.max_dist": repr(cmp.max_dist)}
    paths = []
    oracle = cmp.reference == "oracle"
    ref, ref_text = (("oracle", "float64 shading oracle (mitsuba_ref/shade_oracle.py)")
                     if oracle else ("mitsuba", "mitsuba course integrator, llvm_ad_rgb"))
    mode = ORACLE_MODE if oracle else "shaded"
    for name, img, extra in (("ours", cmp.ours, {"rtval.image": "rt_core f64"}),
                             (ref, cmp.theirs, {"rtval.image": ref_text}),
                             ("classes", classes_rgb(cmp.classes),
                              {"rtval.image": "shaded classes", "rtval.classes": legend}),
                             *([("flip", flip_colours(cmp.flip),
                                 {"rtval.image": "NVIDIA FLIP error map (magma, 0 black, 1 "
                                                 f"light yellow), {ref} the reference",
                                  "rtval.flip.mean": repr(cmp.flip_mean)})]
                               if cmp.flip is not None else [])):
        path = os.path.join(outdir, f"{stem}.{mode}.{name}.png")
        write_png(path, img, {**text, **extra})
        paths.append(path)
    return paths
