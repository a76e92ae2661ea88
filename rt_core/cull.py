"""Bounding spheres of bounded objects, to skip the exact hit test of rays with an origin
(reflections) that certainly miss an object, in the unrolled closest-hit search.

Unrolled, a secondary ray runs every object's full hit function (a sphere's: five square
roots and a division) inside a symbolic ``dr.if_stmt`` on the object's "skip" test, so a
packet of lanes that all leave the object does not run it.  ``may_hit`` adds a cheap test of
the ray against the object's bounding sphere (float64, from its constants; a sphere's is
itself, a planar object's is centred on the mean of the corners that hold it) to that
condition: a packet none of whose rays come near the object skips it too.  Most reflection
rays miss most objects, and neighbouring pixels' reflection rays stay neighbours in a packet,
so whole packets skip.

The test only skips work, never changes an answer: a ray is culled only when its line's
distance from the centre, computed with generous slack, exceeds the sphere's radius widened
by e = ``bvh.PAD``·(|o|∞ + S) (as the BVH widens its boxes: a hit function's accepted point
lies within a few ulps of those lengths of the object) and 2⁻¹⁰ of itself.  With
p = C − o, b = p·d, a = |d|²: the least distance² of the points o + t·d, t > 0, from C is
|p|² − max(b, 0)²/a; it is computed as |p|²·a − max(b, 0)², whose rounding error is below
8u·|p|²·a, and the test allows 2⁻¹⁶·|p|²·a.  A NaN anywhere fails the comparison: not
culled, the exact test decides as before.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .shapes_planar import planar_corners

GROW = 2.0 ** -10           # relative widening of each bounding radius
SLACK = 2.0 ** -16          # relative allowance for the rounding of |p|²·a − b²


def configure(ks, on: bool):
    """Turn the test on or off for one KernelScene (tests, benchmarks); on by default."""
    ks.__dict__["_cull"] = on
    return ks


def enabled(ks) -> bool:
    return ks.__dict__.get("_cull", True)


def bounding(ks) -> dict:
    """{object id: (centre, radius)} (host float64, relative to the viewpoint) of every
    bounded object, and under None the largest box coordinate S (built once per
    KernelScene)."""
    from .accel import BOUNDED
    from .bvh import object_boxes
    cache = ks.__dict__.setdefault("_accel", {})
    if "cull" not in cache:
        out, S = {}, 0.0
        for kind in BOUNDED:
            consts = ks.by_kind.get(kind)
            if not consts:
                continue
            lo, hi = object_boxes(kind, consts)
            if kind == "sphere":                # its own centre and radius
                c = np.array([k.q for k in consts], np.float64).reshape(-1, 3)
                r = np.array([k.radius for k in consts], np.float64)
            elif kind in ("fplane", "triangle", "disk"):
                # about the mean of the corners that hold it, out to the farthest
                P = planar_corners(kind, consts)
                c = P.mean(1)
                r = np.sqrt(((P - c[:, None]) ** 2).sum(-1)).max(1)
            else:                               # around its box
                c = 0.5 * (lo + hi)
                r = 0.5 * np.sqrt(((hi - lo) ** 2).sum(1))
            for obj, ci, ri in zip(consts, c, r):
                out[obj.id] = (tuple(float(x) for x in ci), float(ri))
            S = max(S, float(np.abs(np.concatenate([lo, hi])).max()))
        out[None] = S
        cache["cull"] = out
    return cache["cull"]


class Rays:
    """Per-ray numbers of the test, computed once for all objects: a = |d|² and the
    widening e = PAD·(|o|∞ + S)."""

    def __init__(self, ks, d, o):
        from .bvh import PAD
        T = ks.T
        self.d, self.o = d, o
        self.a = dr.squared_norm(d)
        m = dr.maximum(dr.maximum(dr.abs(o.x), dr.abs(o.y)), dr.abs(o.z))
        self.e = dr.opaque(T.Float, PAD[T.precision]) * (m + dr.opaque(T.Float,
                                                                       bounding(ks)[None]))
        self.keep = dr.opaque(T.Float, 1 - SLACK)


def may_hit(ks, rays: Rays, oid: int):
    """False where the ray o + t·d (t > 0) certainly misses object ``oid``; None for an
    unbounded object, or with the test turned off (no test)."""
    entry = bounding(ks).get(oid) if enabled(ks) else None
    if entry is None:
        return None
    T = ks.T
    from .shapes import opaque3
    centre, radius = entry
    p = opaque3(T.Array3, centre) - rays.o
    b = dr.maximum(dr.dot(p, rays.d), 0)
    rr = dr.opaque(T.Float, radius * (1 + GROW)) + rays.e
    far = dr.fma(dr.squared_norm(p) * rays.a, rays.keep, -b * b) > rr * rr * rays.a
    return ~far
