"""Why two tracers disagree at a pixel: float64 re-evaluation of every object along the ray.

A disagreement (mask or object id) is *explained* when an object involved (ours or the
reference's) is within a float32 error bound of a decision boundary:

  edge        a finite plane's hit lies within the bound of its rectangle's border (a
              triangle's: of its edges; a disk's: of its rim)
  tie         the two objects lie at the same depth within the bound (two objects of the
              same numbers tie exactly, where the tie rule decides: rt_core must take the
              rule's object)
  clip        a plane hit within the bound of the window plane z = 0 (the screen clip)
  extent      our hit on an infinite/tiled plane lies beyond the reference's finite stand-in
  silhouette  the ray passes within the bound of a sphere's outline
  graze       the ray is within the bound of parallel to a plane

The bound on a position is ``K · 2⁻²⁴ · S / |cos θ|``: S the magnitude of the coordinates the
float32 arithmetic works with (viewpoint, the object's anchor, the distance t, the object's
size — for an infinite or tiled plane the half-size R of the reference's stand-in square,
whose float32 vertices tilt and shift it by about 2⁻²⁴·R, in the reference's bound only:
rt_core traces the plane's equation), θ the angle between ray and normal, and K = 16
rounding steps (vertex rounding, ray origin on the window, direction rounding, Embree's edge
tests, our own float32 evaluation).
"""
from __future__ import annotations

from typing import Any as Scene         # a parsed course scene (duck-typed)

import numpy as np

from rt_core.kinds import kind
from rt_core.rules import Rules

from . import quadric
from .convert import kept, stand_in_frame, written_value
from .geometry import frame, given_normal, normal, unit
from .oracle_planar import points, triangle_normal

K_ROUNDING = 16.0
EPS32 = 2.0 ** -24
CLASSES = ("agree", "edge", "tie", "clip", "extent", "silhouette", "graze", "unexplained")
CLASS_CODE = {c: i for i, c in enumerate(CLASSES)}


def _norm(a):
    return np.sqrt(np.sum(a * a, axis=-1))


def plane_terms(obj, extent: float):
    """(unit normal, anchor point, size) of a planar object: the size is what its float32
    numbers scale with in the bound (a finite plane's longer side, a disk's radius, a
    triangle's longer edge from its first vertex; for an infinite or tiled plane the
    reference's stand-in square, whose float32 vertices lie ~``extent`` away)."""
    if obj.kind == "triangle":                 # mitsuba_ref/oracle_planar.py
        P = [np.asarray(p, np.float64) for p in points(obj)]
        return (np.asarray(unit(triangle_normal(obj))), P[0],
                max(_norm(P[1] - P[0]), _norm(P[2] - P[0])))
    if obj.kind == "disk":
        return np.asarray(normal(obj)), np.asarray(obj.center, np.float64), obj.radius
    size = max(obj.size) if obj.kind == "fplane" else extent
    return np.asarray(normal(obj)), np.asarray(obj.point, np.float64), size


class ObjectEval:
    """t, validity and decision margins of one object along rays O + t·d (float64).

    ``O``: (N, 3) ray origins in world space; None for rays from the viewpoint."""

    def __init__(self, scene: Scene, obj, d: np.ndarray, rules: Rules, extent: float,
                 O: np.ndarray | None = None):
        V = np.asarray(scene.viewpoint, np.float64)
        n = len(d)
        # rays from the viewpoint: O is one row, broadcast (what depends on O alone, as
        # |O| and the anchor's offset, is computed once instead of once per ray)
        O = V[None, :] if O is None else np.asarray(O, np.float64)
        kind(obj.kind)                          # an unknown kind raises, never "a plane"
        self.kind = obj.kind
        self.margin = np.full(n, np.inf)       # world-unit distance to the decision boundary
        self.clip_margin = np.full(n, np.inf)
        self.beyond = np.zeros(n, bool)
        self.cos = np.ones(n)
        origin = _norm(O) + np.sqrt(V @ V)
        if obj.kind in quadric.KINDS:          # mitsuba_ref/quadric.py; its classes: silhouette
            self.t, self.valid, self.margin, size = quadric.classify_eval(
                obj, np.broadcast_to(O, (n, 3)), d, rules)
            self.size = size
            if rules.clip_spheres:
                self.clip_margin = np.abs(O[:, 2] + self.t * d[:, 2])
            self.scale = origin + size
            return
        if obj.kind == "sphere":
            q = np.asarray(obj.center) - O
            a = np.sum(d * d, 1)
            bh = np.sum(q * d, 1)
            pn = _norm(q - d * (bh / a)[:, None])
            disc = a * (obj.radius - pn) * (obj.radius + pn)
            s = np.sqrt(np.maximum(disc, 0))
            qn = _norm(q)
            c = (qn - obj.radius) * (qn + obj.radius)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(bh > 0, c / (bh + s), (bh - s) / a)
            self.valid = (disc > 0) & (t > 0)
            if rules.clip_spheres:
                self.clip_margin = np.abs(O[:, 2] + t * d[:, 2])
            self.t = t
            self.margin = np.abs(pn - obj.radius)          # distance from the outline
            self.scale = origin + qn + obj.radius
            return
        planar = obj.kind in ("triangle", "disk")      # mitsuba_ref/oracle_planar.py
        nrm, anchor, size = plane_terms(obj, extent)
        q = anchor - O
        den = d @ nrm
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (q @ nrm) / den
        valid = (den != 0) & (t > rules.t_min) & np.isfinite(t)
        z = O[:, 2] + t * d[:, 2]
        self.clip_margin = np.abs(z)
        if rules.screen_clip == ">":
            valid &= z <= 0
        elif rules.screen_clip == ">=":
            valid &= z < 0
        self.cos = np.abs(den)
        self.t = t
        if obj.kind == "fplane":
            w, h = obj.size
            rel = t[:, None] * d - q
            fx, fy, _ = frame(obj)
            u, v = rel @ np.asarray(fx), rel @ np.asarray(fy)
            inside = ((u >= 0) & (u <= w) & (v >= 0) & (v <= h)) if rules.edges == "closed" \
                else ((u > 0) & (u < w) & (v > 0) & (v < h))
            # distance to the border (inside: >0; outside: distance to the rectangle)
            du = np.maximum(np.maximum(-u, u - w), 0)
            dv = np.maximum(np.maximum(-v, v - h), 0)
            self.margin = np.where(inside, np.minimum.reduce([u, w - u, v, h - v]),
                                   np.hypot(du, dv))
            valid &= inside
        elif planar:
            # signed distance of the hit inside the edges (triangle) or the rim (disk)
            H = O + t[:, None] * d
            with np.errstate(invalid="ignore"):
                if obj.kind == "disk":
                    m = obj.radius - _norm(H - np.asarray(obj.center))
                else:
                    P = [np.asarray(p, np.float64) for p in points(obj)]
                    N = np.cross(P[1] - P[0], P[2] - P[0])
                    m = np.min([(np.cross(B - A, H - A) @ N) / (_norm(N) * _norm(B - A))
                                for A, B in ((P[0], P[1]), (P[1], P[2]), (P[2], P[0]))], 0)
            inside = (m >= 0) if rules.edges == "closed" else (m > 0)
            self.margin = np.where(np.isfinite(m), np.abs(m), np.inf)
            valid &= inside
        else:
            # beyond the reference's stand-in square (half-size extent, its own axes)
            ax, ay, foot = stand_in_frame(obj, scene.viewpoint)
            with np.errstate(invalid="ignore"):        # t = inf on rays parallel to it
                rel = O + t[:, None] * d - np.asarray(foot)
                far = np.maximum(np.abs(rel @ np.asarray(ax)), np.abs(rel @ np.asarray(ay)))
            self.beyond = valid & (far > extent * (1 - 1e-6))
        self.valid = valid
        self.scale = origin + _norm(q) + size
        if obj.kind in ("plane", "tplane"):
            # rt_core traces the plane's equation: the stand-in square's half-size is the
            # reference's term alone
            self.own_scale = origin + _norm(q)

    def bound(self, t=None, own: bool = False):
        """Position error bound (world units) at distance t along the ray (default: the
        object's own t).  ``own``: of rt_core's hit, which for an infinite or tiled plane
        leaves out the reference's stand-in square (its size term)."""
        scale = getattr(self, "own_scale", self.scale) if own else self.scale
        return position_bound(scale, self.t if t is None else t, self.cos)


def _tie_key(obj):
    """The numbers an object's t is computed from, exactly as written: equal keys tie
    exactly in any precision (two numbers that round to the same float are not equal here:
    a float64 tracer deciding on the numbers as written tells them apart); None for the other
    kinds."""
    ex = lambda v: tuple(written_value(c) for c in v)
    if obj.kind == "sphere":
        return ("s", ex(obj.center), written_value(obj.radius))
    if obj.kind in ("plane", "fplane", "tplane"):
        return ("p", ex(given_normal(obj)), ex(obj.point))
    return None


def position_bound(scale, t, cos):
    """K·ε·(S + |t|)/|cos θ| (module docstring), inf where that is not finite."""
    with np.errstate(divide="ignore", invalid="ignore"):
        b = K_ROUNDING * EPS32 * (scale + np.abs(t)) / np.maximum(cos, 1e-300)
    return np.where(np.isfinite(b), b, np.inf)


def classify(scene: Scene, d: np.ndarray, ours: dict, ref: dict, rules: Rules,
             extent: float) -> np.ndarray:
    """Class code per ray (CLASS_CODE) from flat arrays 'hit.mask' and 'object.id' of both
    tracers ('agree' = the same object hit, or both miss)."""
    d = np.asarray(d, np.float64)
    a_id = np.where(ours["hit.mask"] > 0, ours["object.id"], -1).astype(np.int64)
    b_id = np.where(ref["hit.mask"] > 0, ref["object.id"], -1).astype(np.int64)
    out = np.zeros(len(d), np.int8)
    n = len(scene.objects)
    for side, ids in (("ours", a_id), ("the reference's", b_id)):
        if (ids >= n).any():
            raise ValueError(f"{side} object ids go up to {int(ids.max())}; the scene has "
                             f"{n} objects")
    bad = np.nonzero(a_id != b_id)[0]
    if not len(bad):
        return out
    dd = d[bad]
    # every test below reads only the objects that one side or the other hits on a
    # disagreeing ray: those alone are evaluated, row j for object used[j]
    used = np.unique(np.r_[a_id[bad], b_id[bad]])
    used = used[used >= 0]
    evals = [ObjectEval(scene, scene.objects[i], dd, rules, extent) for i in used.tolist()]
    row = np.full(max(n, 1), -1, np.int64)  # object id -> row (−1: the NaN row below)
    row[used] = np.arange(len(used))
    reason = np.full(len(bad), CLASS_CODE["unexplained"], np.int8)

    def mark(mask, name):
        sel = mask & (reason == CLASS_CODE["unexplained"])
        reason[sel] = CLASS_CODE[name]

    # per object along each disagreeing ray: distance t and its position error bound
    # (a last row of NaN for "no object": a miss on one side, never compared)
    # (rt_core's bounds, ``own``: an infinite plane's without the stand-in square's term,
    # which only the reference's hit carries: a review dropped the road, a finite plane
    # 1e-3 above the floor, and rt_core's floor 0.0035 behind it passed as a tie)
    nan = [np.full(len(bad), np.nan)]
    t_all = np.stack([ev.t for ev in evals] + nan)
    b_ref = np.stack([ev.bound(ev.t) for ev in evals] + nan)
    b_own = np.stack([ev.bound(ev.t, own=True) for ev in evals] + nan)
    cols = np.arange(len(bad))
    a, b = a_id[bad], b_id[bad]
    ia, ib = (np.where(x >= 0, row[np.maximum(x, 0)], -1) for x in (a, b))
    ta, tb, ba, bb = t_all[ia, cols], t_all[ib, cols], b_own[ia, cols], b_ref[ib, cols]
    for side_ids, t_self, t_other, b_self, b_other, b_all in ((a, ta, tb, ba, bb, b_own),
                                                              (b, tb, ta, bb, ba, b_ref)):
        # a side's object explains the ray by its own decision only where it may be the
        # closest hit: not beyond the other side's object by more than their bounds (an
        # edge 6 units behind the object the other side hits firmly decides nothing; a
        # miss on the other side, NaN, leaves it in front)
        with np.errstate(invalid="ignore"):
            front = ~(t_self > t_other + b_self + b_other)
        for j, ev in enumerate(evals):
            involved = (side_ids == used[j]) & front
            if not involved.any():
                continue
            if ev.kind in ("fplane", "triangle", "disk"):
                mark(involved & (np.abs(ev.margin) <= b_all[j]), "edge")
            if ev.kind == "sphere" or ev.kind in quadric.KINDS:
                mark(involved & (ev.margin <= b_all[j]), "silhouette")
            else:
                mark(involved & (ev.clip_margin <= b_all[j]), "clip")
                mark(involved & (ev.cos <= K_ROUNDING * EPS32), "graze")
                mark(involved & ev.beyond, "extent")
    # ties: both hit, different objects, at the same depth within the bounds; two objects of
    # the same numbers (plane equation, or sphere) tie exactly in any precision, where the
    # rule decides: rt_core's object must be the rule's (a review turned rt_core's ties to
    # the last object and every such pixel passed as a tie)
    both = (a >= 0) & (b >= 0)
    keys = np.empty(len(used) + 1, object)             # (filled: a tuple each, not an axis)
    keys[:-1] = [_tie_key(scene.objects[i]) for i in used.tolist()]
    same = both & (keys[ia] == keys[ib]) & (keys[ia] != None)      # noqa: E711
    ruled = (a < b) if rules.ties == "first" else (a > b)
    with np.errstate(invalid="ignore"):
        mark(both & (np.abs(ta - tb) <= ba + bb) & (~same | ruled), "tie")
    out[bad] = reason
    return out


# no depth bound is below this: a planar object's is K·ε·(S + t)/(cos θ·t) >= K·ε/cos θ, and
# cos θ <= 1 up to d's rounding; a quadric's is at least its planar form with cos θ = 1; a
# sphere's K·ε·S/(t·√x) with x <= 1, and S >= |q| + r >= t where the hit lies on the sphere
# (over_bound checks that last one ray by ray)
DEPTH_FLOOR = K_ROUNDING * EPS32 / 2


def over_bound(scene: Scene, d: np.ndarray, rays: np.ndarray, ids: np.ndarray, t: np.ndarray,
               rel: np.ndarray, extent: float, rules: Rules) -> int:
    """How many of the rays ``rays`` (rows of ``d``), hitting object ``ids`` at distance
    ``t`` with relative depth error ``rel``, exceed their depth_bound.  The bound is computed
    only where rel > DEPTH_FLOOR, or on a sphere where t > S/2 (its floor's argument needs
    t <= S): no other ray can exceed it."""
    terms = _bound_terms(scene, extent)
    i = np.where((ids >= 0) & (ids < len(scene.objects)), ids, 0)
    with np.errstate(invalid="ignore"):
        may = (rel > DEPTH_FLOOR) | ((terms.code[i] == 1) & (t > terms.scale[i] / 2))
    k = np.flatnonzero(may)
    if not len(k):
        return 0
    b = depth_bound(scene, d[rays[k]], ids[k], t[k], extent, rules)
    return int(np.count_nonzero(rel[k] > b))


def depth_bound(scene: Scene, d: np.ndarray, ids: np.ndarray, t: np.ndarray, extent: float,
                rules: Rules) -> np.ndarray:
    """Relative depth error bound per ray hitting object ``ids`` at distance ``t``: the
    position bound along the ray, over t.  For a sphere the bound grows as the ray nears
    the outline (t is ill-conditioned there): ε·S/√(relative discriminant)."""
    out = np.full(len(d), np.inf)
    if not len(d):
        return out
    terms = _bound_terms(scene, extent)
    known = (ids >= 0) & (ids < len(scene.objects))
    i = np.where(known, ids, 0)
    code = np.where(known, terms.code[i], -1)
    ts = np.maximum(t, 1e-300)
    # planar objects: ObjectEval's bound at the given t, from the terms it needs only (the
    # plane's normal, and its scale from the anchor and size): its hit, extent and edge
    # tests are not needed here
    sel = np.flatnonzero(code == 0)
    if len(sel):
        j = i[sel]
        cos = np.abs(np.einsum("ij,ij->i", d[sel], terms.nrm[j]))
        out[sel] = position_bound(terms.scale[j], t[sel], cos) / ts[sel]
    # spheres: ε·S/√(relative discriminant), the discriminant relative to r² taken as
    # 2r·(distance of the ray from the outline) / r² (ObjectEval's margin and scale, of
    # which only these are needed)
    sel = np.flatnonzero(code == 1)
    if len(sel):
        j, ds = i[sel], d[sel]
        q, r = terms.q[j], terms.radius[j]
        a = np.einsum("ij,ij->i", ds, ds)
        pn = _norm(q - ds * (np.einsum("ij,ij->i", ds, q) / a)[:, None])
        rel_disc = np.clip(np.abs(pn - r) * (2 * r) / (r ** 2), 1e-300, None)
        out[sel] = (K_ROUNDING * EPS32 * terms.scale[j] / np.sqrt(np.minimum(rel_disc, 1.0))
                    / ts[sel])
    # a quadric: as the sphere's, the root's condition near the outline or the rim, the
    # margin relative to the object's size
    for k in np.unique(i[code == 2]).tolist():
        sel = np.flatnonzero(known & (ids == k))
        ev = ObjectEval(scene, scene.objects[k], d[sel], rules, extent)
        with np.errstate(over="ignore"):       # (a root far out: a margin near 1e308)
            rel_disc = np.clip(2 * ev.margin / max(ev.size, 1e-300), 1e-300, None)
        b = np.maximum(ev.bound(t[sel]),
                       K_ROUNDING * EPS32 * ev.scale / np.sqrt(np.minimum(rel_disc, 1.0)))
        out[sel] = b / ts[sel]
    return out


class _BoundTerms:
    """Per object of a scene, what depth_bound needs: ``code`` (0 planar, 1 sphere, 2
    quadric), a planar object's unit normal, a sphere's centre − V and radius, and the
    scale S of either (ObjectEval's, with O = V)."""

    def __init__(self, scene: Scene, extent: float):
        V = np.asarray(scene.viewpoint, np.float64)
        origin = 2 * np.sqrt(V @ V)              # |O| + |V| of ObjectEval, O = V
        n = len(scene.objects)
        self.code = np.zeros(n, np.int8)
        self.nrm, self.q = np.zeros((n, 3)), np.zeros((n, 3))
        self.radius, self.scale = np.ones(n), np.zeros(n)
        for k, o in enumerate(scene.objects):
            if o.kind == "sphere":
                q = np.asarray(o.center, np.float64) - V
                self.code[k], self.q[k], self.radius[k] = 1, q, o.radius
                self.scale[k] = origin + np.sqrt(q @ q) + o.radius
            elif o.kind in quadric.KINDS:
                self.code[k] = 2
            else:
                nrm, anchor, size = plane_terms(o, extent)
                self.nrm[k] = nrm
                self.scale[k] = origin + np.sqrt((anchor - V) @ (anchor - V)) + size


# the terms of the last few scenes' objects: validate compares one scene four times (two
# modes, two precisions; the camera mode's copy has another window, the same objects)
_TERMS: dict = {}


def _bound_terms(scene: Scene, extent: float) -> _BoundTerms:
    return kept(_TERMS, scene, (tuple(scene.viewpoint), extent),
                lambda sc: _BoundTerms(sc, extent), 9)
