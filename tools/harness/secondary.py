"""rt_core's secondary rays against Mitsuba 3, ray by ray: shadow visibility and reflections.

rt_core renders a scene and records the rays its shading cast (``shading.shade(record=2)``):
for the primary hits and the first reflection bounce, every shadow ray (origin on the
surface, unit direction to the light, the light's distance d, the surface to skip) with our
verdict (blocked or not), and every first-bounce reflection ray with the object it hit.
Mitsuba intersects the same rays (rounded to float32):

* skip: the surface a ray leaves is left out of the Mitsuba scene the ray is traced in (one
  scene per skipped object, loaded once), which is the course's ``skip`` exactly;
* shadows: ``ray_intersect`` with ``ray.maxt`` = d, not ``ray_test`` (unreliable for spheres,
  notes/mitsuba.md);
* screen clip: as in ``reference.py``, plane kinds and spheres are separate Mitsuba scenes;
  planes are traced only along the part of the ray with z <= 0 (z < 0 for ``>=``), spheres
  along all of it (unless ``clip_spheres``), and the nearer hit counts.

A disagreement is *explained* when an object along the ray is within a float32 bound of a
decision boundary (the bound of ``explain.py``: K·2⁻²⁴·S/|cos θ|, S now including the ray's
origin), in the first of these classes that applies:

  edge        the ray passes within the bound of a finite plane's border
  silhouette  the ray passes within the bound of a sphere's outline
  graze       the ray is within the bound of parallel to a plane
  clip        a plane hit within the bound of the window plane z = 0
  light       (shadows) the blocking hit lies within the bound of the light's distance
  origin      a hit within the bound of the ray's origin (t ≈ 0: surfaces that touch)
  tie         (reflections) the two objects lie at the same distance within the bound
  extent      a hit on an infinite/tiled plane beyond the reference's finite stand-in
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rt_core import backend
from rt_core.camera import make_camera
from rt_core.render import render_image
from rt_core.rules import Rules
from rt_core.scene import Scene
from rt_core.shading import DEFAULT_MAX_DIST
from mitsuba_ref.convert import (course_id, mitsuba, mitsuba_subset, plane_extent, scene_dict,
                                 shape_id)
from mitsuba_ref.explain import EPS32, K_ROUNDING, ObjectEval
from mitsuba_ref.jitdata import jit_array, jit_vectors

CLASSES = ("agree", "edge", "silhouette", "graze", "clip", "light", "origin", "tie", "extent",
           "unexplained")
CLASS_CODE = {c: i for i, c in enumerate(CLASSES)}
PLANE_KINDS = {"plane", "fplane", "tplane", "triangle", "disk"}


# --- Mitsuba: the scene without the surface a ray leaves -------------------------------------

class SkipScenes:
    """Loaded Mitsuba scenes of the course scene minus one object, per kind group."""

    def __init__(self, scene: Scene, columns: int, rows: int | None, sampling: str):
        self.scene, self.args = scene, (columns, rows, sampling)
        self._cache: dict = {}

    def get(self, skip: int, kinds: frozenset):
        """(Mitsuba scene or None, shapes() index -> course id) for objects of ``kinds``
        except ``skip``.  The dicts come from convert.scene_dict: same shapes, same
        stand-in squares as every other reference in this package."""
        key = (skip, kinds)
        if key not in self._cache:
            mi = mitsuba()
            d = scene_dict(self.scene, *self.args, only=kinds, integrator=False)
            if 0 <= skip < len(self.scene.objects):
                d.pop(shape_id(skip, self.scene.objects[skip].kind), None)
            shapes = [k for k, v in d.items() if isinstance(v, dict) and k.startswith("obj")]
            if not shapes:
                self._cache[key] = (None, np.zeros(0, np.int32))
            else:
                s = mi.load_dict(d, optimize=False)
                self._cache[key] = (s, np.array([course_id(x.id()) for x in s.shapes()],
                                                np.int32))
        return self._cache[key]


def _intersect(ms, ids, O, d, a, b):
    """Closest hit of the rays O + s·d for s in [a, b] (float64 host arrays; b may be inf) in
    one Mitsuba scene: (hit, course id, s).  Empty intervals miss."""
    n = len(O)
    hit, oid, s = np.zeros(n, bool), np.full(n, -1), np.full(n, np.inf)
    live = b > a
    if ms is None or not live.any():
        return hit, oid, s
    mi = mitsuba()
    import drjit as dr
    o = (O[live] + a[live, None] * d[live]).astype(np.float32)
    dd = d[live].astype(np.float32)
    ray = mi.Ray3f(jit_vectors(mi.Point3f, o), jit_vectors(mi.Vector3f, dd))
    span = b[live] - a[live]
    if np.isfinite(span).any():
        ray.maxt = jit_array(mi.Float, np.where(np.isfinite(span), span,
                                                np.finfo(np.float32).max))
    pi = ms.ray_intersect_preliminary(ray)
    dr.eval(pi)
    h = np.asarray(pi.is_valid().numpy())
    t = np.asarray(pi.t.numpy(), np.float64)
    idx = np.minimum(np.asarray(pi.shape_index.numpy()), len(ids) - 1)
    h &= np.isfinite(t)
    hit[live] = h
    oid[live] = np.where(h, ids[idx], -1)
    s[live] = np.where(h, a[live] + t, np.inf)
    return hit, oid, s


def reference_hits(refs: SkipScenes, rules: Rules, O, d, maxt, skip):
    """Mitsuba's closest hit (hit, course id, distance) of each ray O + s·d, 0 < s < maxt,
    ignoring object ``skip`` (per ray), with the course's screen clip for plane kinds."""
    n = len(O)
    hit, oid, s = np.zeros(n, bool), np.full(n, -1), np.full(n, np.inf)
    present = {o.kind for o in refs.scene.objects}
    zero = np.zeros(n)
    # the part of each ray on which plane hits count: z <= 0 (the screen clip), as [a, b]
    if rules.screen_clip == "off":
        pa, pb = zero, maxt.copy()
    else:
        with np.errstate(divide="ignore", invalid="ignore"):
            cross = -O[:, 2] / d[:, 2]                  # where the ray meets z = 0
        ahead = O[:, 2] <= 0
        pa = np.where(ahead, 0.0, np.where(d[:, 2] < 0, cross, np.inf))
        pb = np.where(ahead, np.where(d[:, 2] > 0, np.minimum(cross, maxt), maxt), maxt)
    groups = [(frozenset(PLANE_KINDS & present), pa, pb)]
    if present & {"sphere", "cylinder"}:             # unclipped unless clip_spheres
        sa, sb = (pa, pb) if rules.clip_spheres else (zero, maxt)
        groups.append((frozenset({"sphere", "cylinder"} & present), sa, sb))
    for kinds, a, b in groups:
        if not kinds:
            continue
        for k in np.unique(skip):
            sel = skip == k
            ms, ids = refs.get(int(k), kinds)
            h, i, t = _intersect(ms, ids, O[sel], d[sel], a[sel], b[sel])
            # nearer hit wins; an exact tie goes to the earlier object (the course's rule)
            better = h & ((t < s[sel]) | ((t == s[sel]) & (i < oid[sel])))
            hit[sel] |= h
            oid[sel] = np.where(better, i, oid[sel])
            s[sel] = np.where(better, t, s[sel])
    return hit, oid, s


# --- float64 re-evaluation along rays with their own origins ---------------------------------

def _near_boundary(ev: ObjectEval, b, t_hi):
    """Per ray, the first class of a decision of this object within the bound (or '')."""
    out = np.full(len(b), "", dtype=object)

    def mark(mask, name):
        out[mask & (out == "")] = name

    reach = np.isfinite(ev.t) & (ev.t >= -b) & (ev.t <= t_hi + b)
    if ev.kind in ("fplane", "triangle", "disk"):
        mark(reach & (np.abs(ev.margin) <= b), "edge")
    if ev.kind == "sphere":
        mark(reach & (ev.margin <= b), "silhouette")
    else:
        mark(reach & (ev.cos <= K_ROUNDING * EPS32), "graze")
    mark(reach & (ev.clip_margin <= b), "clip")
    mark(ev.valid & np.isfinite(t_hi) & (np.abs(ev.t - t_hi) <= b), "light")
    mark(reach & (np.abs(ev.t) <= b), "origin")
    mark(reach & ev.beyond, "extent")
    return out


def classify_shadows(scene, O, d, maxt, skip, ours, ref, rules, extent) -> np.ndarray:
    """Class code per shadow ray: 'agree' when both say blocked or both say lit."""
    out = np.zeros(len(O), np.int8)
    bad = np.nonzero(ours != ref)[0]
    if not len(bad):
        return out
    reason = np.full(len(bad), "", dtype=object)
    Ob, db, tb, sb = O[bad], d[bad], maxt[bad], skip[bad]
    for i, obj in enumerate(scene.objects):
        ev = ObjectEval(scene, obj, db, rules, extent, Ob)
        cls = _near_boundary(ev, ev.bound(), tb)
        cls[sb == i] = ""
        reason = np.where(reason == "", cls, reason)
    out[bad] = [CLASS_CODE[r or "unexplained"] for r in reason]
    return out


def classify_hits(scene, O, d, ours, ref, rules, extent) -> np.ndarray:
    """Class code per closest-hit ray: 'agree' when both hit the same object or both miss;
    otherwise a decision of one of the two objects, or their depths, within the bound."""
    out = np.zeros(len(O), np.int8)
    bad = np.nonzero(ours != ref)[0]
    if not len(bad):
        return out
    Ob, db = O[bad], d[bad]
    a, b = ours[bad], ref[bad]
    reason = np.full(len(bad), "", dtype=object)
    evals = {}
    for i in set(a.tolist()) | set(b.tolist()):
        if i >= 0:
            evals[i] = ObjectEval(scene, scene.objects[i], db, rules, extent, Ob)
    inf = np.full(len(bad), np.inf)
    for side in (a, b):
        for i, ev in evals.items():
            cls = _near_boundary(ev, ev.bound(), inf)
            reason = np.where((reason == "") & (side == i), cls, reason)
    # ties: both hit, at the same distance within the sum of the bounds
    ta = np.array([evals[i].t[r] if i >= 0 else np.nan for r, i in enumerate(a)])
    tb = np.array([evals[i].t[r] if i >= 0 else np.nan for r, i in enumerate(b)])
    ba = np.array([evals[i].bound()[r] if i >= 0 else 0.0 for r, i in enumerate(a)])
    bb = np.array([evals[i].bound()[r] if i >= 0 else 0.0 for r, i in enumerate(b)])
    with np.errstate(invalid="ignore"):
        tie = (a >= 0) & (b >= 0) & (np.abs(ta - tb) <= ba + bb)
    reason = np.where((reason == "") & tie, "tie", reason)
    out[bad] = [CLASS_CODE[r or "unexplained"] for r in reason]
    return out


# --- the comparison ---------------------------------------------------------------------------

@dataclass
class RayCheck:
    """One family of rays (shadow rays of one light and bounce, or reflection rays)."""
    name: str
    pixel: np.ndarray
    classes: np.ndarray
    ours: np.ndarray
    ref: np.ndarray
    O: np.ndarray
    d: np.ndarray

    @property
    def counts(self) -> dict:
        return {c: int(np.count_nonzero(self.classes == i)) for i, c in enumerate(CLASSES)
                if c == "agree" or np.any(self.classes == i)}

    @property
    def unexplained(self) -> int:
        return int(np.count_nonzero(self.classes == CLASS_CODE["unexplained"]))

    def examples(self, k: int = 5) -> list[str]:
        """The first unexplained rays, one line each."""
        rows = np.nonzero(self.classes == CLASS_CODE["unexplained"])[0][:k]
        return [f"{self.name} pixel {self.pixel[r]}: origin {self.O[r].tolist()} dir "
                f"{self.d[r].tolist()}: ours {self.ours[r]}, mitsuba {self.ref[r]}" for r in rows]


@dataclass
class SecondaryComparison:
    scene: Scene
    precision: str
    columns: int
    rows: int
    max_dist: float
    checks: list = field(default_factory=list)
    note: str = ""               # objects left out (no Mitsuba shape: cone, ellipsoid)

    @property
    def unexplained(self) -> int:
        return sum(c.unexplained for c in self.checks)

    def summary(self) -> dict:
        return {"scene": self.scene.path, "precision": self.precision,
                "columns": self.columns, "rows": self.rows, "max_dist": self.max_dist,
                "rays": {c.name: {"rays": len(c.classes), **c.counts} for c in self.checks},
                "unexplained": self.unexplained, "note": self.note}


def compare_secondary(scene: Scene, columns: int, rows: int | None = None,
                      precision: str = "f32", sampling: str = "corners",
                      rules: Rules = Rules(), max_dist: float = DEFAULT_MAX_DIST,
                      backend_name: str = "llvm") -> SecondaryComparison:
    """Shadow rays (primary hits and first reflection bounce, every light) and first-bounce
    reflection rays of rt_core's shading, each against Mitsuba."""
    T = backend.types(precision, backend_name)
    # kinds without a Mitsuba shape (cone, ellipsoid, torus) are left out on both sides
    scene, note = mitsuba_subset(scene)
    cam = make_camera(scene, columns, rows, sampling)
    _, res = render_image(scene, cam, T, rules, geometry=False, shade=True,
                          max_dist=max_dist, record=2)
    V = np.asarray(scene.viewpoint, np.float64)
    refs = SkipScenes(scene, cam.columns, cam.rows, sampling)
    extent = plane_extent(scene)
    out = SecondaryComparison(scene, precision, cam.columns, cam.rows, max_dist, note=note)
    recs = res.records if scene.objects else []
    for b, rec in enumerate(recs):
        hit = rec["hit"].astype(bool)
        pos = V + rec["position"].astype(np.float64)
        for j in range(len(scene.lights)):
            cast = rec[f"L{j}.cast"].astype(bool)
            O, d = pos[cast], rec[f"L{j}.dir"][cast].astype(np.float64)
            maxt = rec[f"L{j}.dist"][cast].astype(np.float64)
            skip = rec["id"][cast].astype(np.int64)
            ours = rec[f"L{j}.blocked"][cast].astype(bool)
            r_hit, _, _ = reference_hits(refs, rules, O, d, maxt, skip)
            cls = classify_shadows(scene, O, d, maxt, skip, ours, r_hit, rules, extent)
            out.checks.append(RayCheck(f"shadow L{j} bounce {b}", rec["pixel"][cast], cls,
                                       ours, r_hit, O, d))
        if b == 1:
            # the first reflection bounce: closest hit ids
            O = V + rec["origin"].astype(np.float64)
            d = rec["dir"].astype(np.float64)
            skip = rec["skip"].astype(np.int64)
            ours = np.where(hit, rec["id"], -1).astype(np.int64)
            _, r_id, _ = reference_hits(refs, rules, O, d, np.full(len(O), np.inf), skip)
            cls = classify_hits(scene, O, d, ours, r_id, rules, extent)
            out.checks.append(RayCheck("reflection", rec["pixel"], cls, ours, r_id, O, d))
    return out
