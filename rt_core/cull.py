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

``CONST_E``: the widening is a constant of each object instead of each ray's. A ray whose
origin has |o|∞ <= ``NEAR_ORIGIN``·S (every origin on a bounded object; the threshold
rounded down) has e <= PAD·(NEAR_ORIGIN + 1)·S, so the radius r·(1 + 2⁻¹⁰) +
PAD·(NEAR_ORIGIN + 1)·S is at least its own (up to PAD·NEAR_ORIGIN·S larger: objects small
against S are culled less), and its square is rounded up on the host. The test is then
fma(|p|², a·(1 − SLACK), −b²) > rr²·a; divided by a, its roundings come to about 17u·|p|²
(|p|² 3u, a·(1 − SLACK) u, the fma u, b² 7u and a's 3u in it, the product rr²·a u, rr²
itself u), and the centre's rounding to the kernel's precision (√3·u·S) is inside PAD·S:
all far inside the slack (256u in float32; measured by a reviewer, 1.6 M grazing float32
rays: at least 248u left). The fma also keeps |p|²·a from overflowing, which the per-ray
form did for |d| ~ 10¹⁹. The argument needs normal numbers: a ray is culled only where a
lies in ``A_RANGE`` (a float32 direction of |d| ~ 10⁻²³, a lane whose arithmetic kept
subnormals, was culled wrongly by the per-ray form: tests/test_shade_speed.py test03d),
and, like it, for a ray from farther than NEAR_ORIGIN·S (a far point of an unbounded plane)
|p|²·a's factor is 0: never culled. It also takes |p|²·a and rr²·a to be normal numbers,
true but for scenes within ~2⁵⁰ of the precision's range; grazing rays in scenes of 10⁻²⁰
to 10¹⁶ times a unit scene (float32; 10⁻¹⁶⁰ to 10¹⁴⁰ in float64), with directions of 10⁻²¹
to 10¹⁹, found the same answers with the culls and without. Per object that leaves one
product of a per-ray number by a constant where the ray's radius took a sum and two
products (shaded bench f32, same process, median of 9, images identical: spheres 16 0.98 of
the time, finite planes 16 1.00, mixed 16 1.01; the primary kernel of spheres 16 0.96).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .shapes import directed, opaque3
from .shapes_planar import planar_corners

GROW = 2.0 ** -10           # relative widening of each bounding radius
SLACK = 2.0 ** -16          # relative allowance for the rounding of |p|²·a − b²
NEAR_ORIGIN = 4.0           # the origins (|o|∞ <= NEAR_ORIGIN·S) of a constant widening
CONST_E = True


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


# (CONST_E) the rays culled: a = |d|² in this range, so that it is a normal number
A_RANGE = (2.0 ** -40, 2.0 ** 40)


def near_origins(T, S: float) -> float:
    """NEAR_ORIGIN·S rounded down to T's precision: the largest |o|∞ of a culled ray."""
    return float(directed(np.array(NEAR_ORIGIN * S), T.precision, down=True))


def _radius2(ks, oid: int) -> float:
    """(CONST_E) the square of object ``oid``'s widened radius r·(1 + GROW) + PAD·(NEAR_ORIGIN
    + 1)·S, rounded up: its float64 product's rounding, then the kernel's precision (host,
    once per KernelScene and object)."""
    from .bvh import PAD
    cache = ks.__dict__.setdefault("_accel", {}).setdefault("cull_rr2", {})
    if oid not in cache:
        T, S = ks.T, bounding(ks)[None]
        rr = bounding(ks)[oid][1] * (1 + GROW) + PAD[T.precision] * (NEAR_ORIGIN + 1) * S
        cache[oid] = float(directed(np.array(rr * rr * (1 + 2.0 ** -40)), T.precision,
                                    down=False))
    return cache[oid]


class Rays:
    """Per-ray numbers of the test, computed once for all objects: a = |d|² and the
    widening e = PAD·(|o|∞ + S); with ``CONST_E``, a·(1 − SLACK) where |o|∞ <= NEAR_ORIGIN·S
    and 0 elsewhere (never culled)."""

    def __init__(self, ks, d, o):
        from .bvh import PAD
        T = ks.T
        self.d, self.o = d, o
        self.a = dr.squared_norm(d)
        m = dr.maximum(dr.maximum(dr.abs(o.x), dr.abs(o.y)), dr.abs(o.z))
        S = bounding(ks)[None]
        self.keep = dr.opaque(T.Float, 1 - SLACK)
        self.const = CONST_E
        if self.const:
            # (a NaN |o|∞ or a compares false: 0, never culled)
            ok = (m <= dr.opaque(T.Float, near_origins(T, S))) & \
                (self.a >= dr.opaque(T.Float, A_RANGE[0])) & \
                (self.a <= dr.opaque(T.Float, A_RANGE[1]))
            self.ak = dr.select(ok, self.a * self.keep, 0)
        else:
            self.e = dr.opaque(T.Float, PAD[T.precision]) * (m + dr.opaque(T.Float, S))


def may_hit(ks, rays: Rays, oid: int):
    """False where the ray o + t·d (t > 0) certainly misses object ``oid``; None for an
    unbounded object, or with the test turned off (no test)."""
    entry = bounding(ks).get(oid) if enabled(ks) else None
    if entry is None:
        return None
    T = ks.T
    centre, radius = entry
    p = opaque3(T.Array3, centre) - rays.o
    if rays.const:
        rr2 = _radius2(ks, oid)
        b = dr.dot(p, rays.d)
        b = dr.select(b < 0, 0, b)          # max(b, 0), a NaN kept
        far = dr.fma(dr.squared_norm(p), rays.ak, -b * b) > dr.opaque(T.Float, rr2) * rays.a
        return ~far
    b = dr.maximum(dr.dot(p, rays.d), 0)
    rr = dr.opaque(T.Float, radius * (1 + GROW)) + rays.e
    far = dr.fma(dr.squared_norm(p) * rays.a, rays.keep, -b * b) > rr * rr * rays.a
    return ~far
