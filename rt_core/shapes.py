"""Shape kernels, type-generic over Dr.Jit backend and precision, in two levels:

* ``*_t``:   distance t and a hit mask for a batch of rays (what the closest-hit search needs);
* ``*_surface``: normal and uv, computed once for the closest hit only.

Every quantity is taken relative to the ray origin.  Per-object constants are computed once on
the host in float64 (``ObjectConstants``): q = anchor − viewpoint (the plane's corner or the
sphere's centre), n·q, and for spheres |q|² − r².  Primary rays start at the viewpoint, so
they use these directly; other rays pass their origin ``o`` relative to the viewpoint.

Finite-plane bounds: the seed's ``newhit = rotmat · (hit − point)`` equals, for
hit = o + t·d with t = n·q'/(n·d) and q' = q − o (Binet–Cauchy identity),

    u = ŷ · (q' × d) / (n·d),      v = −x̂ · (q' × d) / (n·d),

which never forms the absolute hit point, so it does not cancel catastrophically when the
plane is small and far away.  The bounds are tested without dividing, ``0 <= u·|n·d| <=
w·|n·d|`` with ``u·|n·d| = ŷ·(q'×d)·sign(n·d)``: every comparison is then monotone in one
rounded quantity, so a ray exactly through an edge that the arithmetic represents exactly is
decided exactly (``u·(1/(n·d))`` rounds twice and can land past w).  For rays from the
viewpoint a hit has sign(n·d) = sign(n·q) (t > 0), a host constant: the sign is folded into
ŷ, x̂, w, h (and the screen clip's constants) and costs nothing per ray.

Numerical choices measured against the exact oracle (rt_core/exact.py, mitsuba_ref/stability.py):

* screen clip: the sign of the hit's z·(n·d) = V.z·(n·d) + (n·q)·d.z is taken as
  V.z·(n.x d.x + n.y d.y) + g·d.z with the host constant g = n·q + n.z V.z = n·P − n.x V.x −
  n.y V.y (rounded once): the n.z V.z d.z terms, which cancel, are gone; for a plane nearly
  parallel to the window the old form lost z to ~u·V.z, four orders above its condition.
  (Same operation count: n.x d.x + n.y d.y is the first part of n·d.)
* sphere: the distance of the centre from the ray is |q × d|/|d|, not |q − d(q·d)/|d|²|, whose
  error along the ray adds in quadrature (for a ray along an axis the cross product is exact);
* host constants: n·q, g and the sphere's |q|² − r² are rounded once from exact values
  (``Fraction``); |n·q| within its float64 uncertainty of 0 is 0 (a plane through the
  viewpoint: t = 0, a miss, instead of a hit at t ~ 1e-17); planes with the same unit normal
  (up to sign) and n·q within that uncertainty share n and n·q exactly, so coplanar objects
  tie exactly and the tie rule decides, as in exact arithmetic;
* a parallel ray (n·d = 0) gives t = ±inf or NaN, rejected by ``t < inf`` (no separate test).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import drjit as dr

from .rules import Rules
from .scene import Scene, Sphere, sub

KIND_CODE = {"sphere": 0, "plane": 1, "fplane": 2, "tplane": 3}
PLANE_KINDS = ("plane", "fplane", "tplane")


@dataclass(frozen=True)
class ObjectConstants:
    """Host float64 constants of one object (relative to the viewpoint)."""
    id: int
    kind: str
    q: tuple                 # anchor − viewpoint (plane point / sphere centre)
    n: tuple = (0.0, 0.0, 0.0)
    nq: float = 0.0          # n·q
    xdir: tuple = (0.0, 0.0, 0.0)
    ydir: tuple = (0.0, 0.0, 0.0)
    size: tuple = (0.0, 0.0)  # fplane w h, tplane tile w h
    radius: float = 0.0
    c: float = 0.0           # sphere |q|² − r²
    g: float = 0.0           # plane kinds: n·q + n.z·viewpoint.z, for the screen clip


# |n·q| below SNAP · Σ|n_i|(|P_i| + |V_i|) is within float64 rounding of the scene's numbers
# (the unit normal's rounding, ~3 units of 2^-53 per component): its sign is not known.
SNAP = 8 * 2.0 ** -53


def _exact_nq(n, point, v) -> tuple[float, float]:
    """(n·(point − v) rounded once, its uncertainty from the rounding of n)."""
    q = [Fraction(p) - Fraction(c) for p, c in zip(point, v)]
    nq = float(sum(Fraction(a) * b for a, b in zip(n, q)))
    scale = math.fsum(abs(a) * (abs(p) + abs(c)) for a, p, c in zip(n, point, v))
    return nq, SNAP * scale


def object_constants(scene: Scene) -> list[ObjectConstants]:
    v = scene.viewpoint
    out = []
    planes = {}                 # unit normal -> [(n·q, tolerance)] of the planes seen so far
    for i, o in enumerate(scene.objects):
        if isinstance(o, Sphere):
            q = sub(o.center, v)
            # |q|² − r², rounded once from the exact value (q = centre − viewpoint exactly)
            qx = [Fraction(a) - Fraction(b) for a, b in zip(o.center, v)]
            c = float(sum(x * x for x in qx) - Fraction(o.radius) ** 2)
            out.append(ObjectConstants(i, o.kind, q, radius=o.radius, c=c))
            continue
        q = sub(o.point, v)
        n = tuple(o.normal)
        nq, tol = _exact_nq(n, o.point, v)
        if abs(nq) <= tol:
            nq = 0.0                                 # through the viewpoint
        # the same plane as an earlier one (same unit normal, up to sign, and n·q within
        # rounding): share its numbers, so that the two tie exactly
        for sg in (1.0, -1.0):
            key = tuple(sg * c + 0.0 for c in n)
            match = next((mq for mq, mtol in planes.get(key, ())
                          if abs(sg * nq - mq) <= tol + mtol), None)
            if match is not None:
                n, nq = tuple(sg * c + 0.0 for c in key), sg * match
                break
        else:
            planes.setdefault(n, []).append((nq, tol))
        xd = getattr(o, "xdir", (0.0, 0.0, 0.0))
        yd = getattr(o, "ydir", (0.0, 0.0, 0.0))
        size = getattr(o, "size", (0.0, 0.0))
        g = float(Fraction(nq) + Fraction(n[2]) * Fraction(v[2]))
        out.append(ObjectConstants(i, o.kind, q, n, nq, xd, yd, size, g=g))
    return out


# --- helpers ---------------------------------------------------------------------------------

def opaque3(Array3, v):
    """A host vector as an opaque Dr.Jit value (data, not a literal baked into the kernel);
    a Dr.Jit vector (constants gathered per ray, rt_core/accel.py) passes through."""
    if isinstance(v, Array3):
        return v
    F = dr.value_t(Array3)
    return Array3(*(dr.opaque(F, float(c)) for c in v))


def opaque(F, v):
    """A host number as an opaque Dr.Jit value; a Dr.Jit array passes through."""
    return v if isinstance(v, F) else dr.opaque(F, v)


def _check(d):
    Array3 = type(d)
    assert dr.size_v(Array3) == 3 and dr.is_float_v(Array3), "d must be a Dr.Jit Array3"
    F = dr.value_t(Array3)
    return F, dr.mask_t(F)


# --- level 1: t and mask ---------------------------------------------------------------------

def plane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """Ray–plane distance: t = n·q'/(n·d). Miss if n·d = 0, t <= t_min, or screen-clipped."""
    t, hit, _, _ = _plane(d, o, obj, rules, vz)
    return t, hit


def _plane(d, o, obj, rules: Rules, vz: float):
    """plane_t's work, shared with fplane_t: (t, hit, n·d, q')."""
    F, B = _check(d)
    n = opaque3(type(d), obj.n)
    q = opaque3(type(d), obj.q)
    if o is None:
        nq = opaque(F, obj.nq)
    else:
        q = q - o
        nq = dr.dot(n, q)
    nd_xy = dr.fma(n.x, d.x, n.y * d.y)
    den = dr.fma(n.z, d.z, nd_xy)
    inv_den = dr.rcp(den)
    t = nq * inv_den
    # n·d = 0 (parallel) gives t = ±inf or NaN: '< inf' rejects it with the non-finite t's
    hit = (t > dr.opaque(F, rules.t_min)) & (t < dr.inf)
    if rules.screen_clip != "off":
        # hit z = zn/den with zn = vz'·den + n·q'·d.z = vz'·(n.x d.x + n.y d.y) + g'·d.z,
        # g' = n·q' + n.z·vz' (host constant g; see the module docstring): nothing cancels
        # that is not the answer (exact 0 for a plane in z = 0)
        g = getattr(obj, "g", None)
        if o is None and g is not None and isinstance(obj.nq, (int, float)):
            # rays from the viewpoint: a hit has sign(den) = sign(nq) (t > 0), known here;
            # fold it into the constants: z·|den| with no work per ray
            sg = -1.0 if obj.nq < 0 else 1.0
            zs = dr.fma(dr.opaque(F, sg * vz), nd_xy, dr.opaque(F, sg * g) * d.z)
        else:
            vzo = dr.opaque(F, vz) if o is None else dr.opaque(F, vz) + o.z
            if g is None:           # constants without g (older tables): the plain form
                zn = vzo * den + nq * d.z
            else:
                g = opaque(F, g)
                if o is not None:
                    g = g - dr.fma(n.x, o.x, n.y * o.y)
                zn = dr.fma(vzo, nd_xy, g * d.z)
            zs = dr.mulsign(zn, den)
        hit &= clip_ok(zs, rules)
    return t, hit, den, q


def clip_ok(z, rules: Rules):
    """False where a hit at height z lies in front of the window (z > 0; z >= 0 with '>=')."""
    if rules.screen_clip == "off":
        return True
    return (z <= 0) if rules.screen_clip == ">" else (z < 0)


def fplane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """plane_t, then the bounds test 0 <= u <= w, 0 <= v <= h (strict with open edges)."""
    F, B = _check(d)
    t, hit, den, q = _plane(d, o, obj, rules, vz)
    Array3 = type(d)
    c = dr.cross(q, d)
    # u·|den| in [0, w·|den|], v·|den| in [0, h·|den|] (see the module docstring): no
    # division, every comparison monotone in one rounded quantity
    X, Y = obj.xdir, obj.ydir
    w, h = obj.size
    if o is None and isinstance(obj.nq, (int, float)):
        # rays from the viewpoint: a hit has t = nq/den > 0, so sign(den) = sign(nq), known
        # here: fold it into the constants (no extra work per ray)
        sg = -1.0 if obj.nq < 0 else 1.0
        X, Y = tuple(sg * c for c in X), tuple(sg * c for c in Y)
        su = dr.dot(opaque3(Array3, Y), c)
        sv = -dr.dot(opaque3(Array3, X), c)
        wd, hd = opaque(F, sg * w) * den, opaque(F, sg * h) * den
    else:
        su = dr.mulsign(dr.dot(opaque3(Array3, Y), c), den)
        sv = dr.mulsign(-dr.dot(opaque3(Array3, X), c), den)
        aden = dr.abs(den)
        wd, hd = opaque(F, w) * aden, opaque(F, h) * aden
    if rules.edges == "closed":
        inside = (su >= 0) & (su <= wd) & (sv >= 0) & (sv <= hd)
    else:
        inside = (su > 0) & (su < wd) & (sv > 0) & (sv < hd)
    return t, hit & inside


def sphere_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """The near root of |o + t·d − centre|² = r²; miss if the discriminant <= 0 or t <= 0.

    The discriminant is taken as a·r² − |q' × d|² = (r√a − |q'×d|)(r√a + |q'×d|) (|q'×d|/√a
    is the distance of the centre from the ray line), and the near root as c/(b' + √disc)
    when b' > 0, so neither cancels."""
    F, B = _check(d)
    q = opaque3(type(d), obj.q)
    r = opaque(F, obj.radius)
    if o is None:
        c = opaque(F, obj.c)
    else:
        q = q - o
        qn = dr.norm(q)
        c = (qn - r) * (qn + r)
    a = dr.squared_norm(d)
    bh = dr.dot(q, d)                       # −b/2 of the course's quadratic
    cn = dr.norm(dr.cross(q, d))            # |d| × distance of the centre from the ray line
    ra = r * dr.sqrt(a)
    disc = (ra - cn) * (ra + cn)
    s = dr.sqrt(dr.maximum(disc, 0))
    # near root c/(b' + √disc): with b' <= 0 both roots are <= 0 (origin outside, c > 0) or
    # the near one is (origin inside, c <= 0), a miss either way, so no second branch
    t = c / (bh + s)
    hit = (disc > 0) & (bh > 0) & (t > 0) & dr.isfinite(t)
    if rules.clip_spheres:
        z = dr.fma(t, d.z, dr.opaque(F, vz))
        hit &= clip_ok(z if o is None else z + o.z, rules)
    return t, hit


def object_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    if obj.kind == "sphere":
        return sphere_t(d, o, obj, rules, vz)
    if obj.kind == "fplane":
        return fplane_t(d, o, obj, rules, vz)
    return plane_t(d, o, obj, rules, vz)              # plane, tplane
