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
plane is small and far away.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr

from .rules import Rules
from .scene import FPlane, Plane, Scene, Sphere, TPlane, cross, dot, sub

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


def object_constants(scene: Scene) -> list[ObjectConstants]:
    v = scene.viewpoint
    out = []
    for i, o in enumerate(scene.objects):
        if isinstance(o, Sphere):
            q = sub(o.center, v)
            # |q|² − r² = (|q| − r)(|q| + r): no cancellation for origins near the surface
            qn = math.sqrt(dot(q, q))
            out.append(ObjectConstants(i, o.kind, q, radius=o.radius,
                                       c=(qn - o.radius) * (qn + o.radius)))
        else:
            q = sub(o.point, v)
            xd = getattr(o, "xdir", (0.0, 0.0, 0.0))
            yd = getattr(o, "ydir", (0.0, 0.0, 0.0))
            size = getattr(o, "size", (0.0, 0.0))
            out.append(ObjectConstants(i, o.kind, q, o.normal, dot(o.normal, q), xd, yd, size))
    return out


# --- helpers ---------------------------------------------------------------------------------

def opaque3(Array3, v):
    """A host vector as an opaque Dr.Jit value (data, not a literal baked into the kernel)."""
    F = dr.value_t(Array3)
    return Array3(*(dr.opaque(F, float(c)) for c in v))


def _check(d):
    Array3 = type(d)
    assert dr.size_v(Array3) == 3 and dr.is_float_v(Array3), "d must be a Dr.Jit Array3"
    F = dr.value_t(Array3)
    return F, dr.mask_t(F)


# --- level 1: t and mask ---------------------------------------------------------------------

def plane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """Ray–plane distance: t = n·q'/(n·d). Miss if n·d = 0, t <= t_min, or screen-clipped.

    Returns (t, hit, inv_den, q') — the last two let ``fplane_t`` reuse this work."""
    F, B = _check(d)
    n = opaque3(type(d), obj.n)
    q = opaque3(type(d), obj.q)
    if o is None:
        nq = dr.opaque(F, obj.nq)
    else:
        q = q - o
        nq = dr.dot(n, q)
    den = dr.dot(n, d)
    inv_den = dr.rcp(den)
    t = nq * inv_den
    hit = (den != 0) & (t > dr.opaque(F, rules.t_min)) & dr.isfinite(t)
    if rules.screen_clip != "off":
        # hit z = zn/den with zn = (vz + o.z)·den + n·q'·d.z: the sign test on zn is exact
        # for a plane in z = 0 (vz·d.z − vz·d.z = 0), where vz + t·d.z is noise around 0
        vzo = dr.opaque(F, vz) if o is None else dr.opaque(F, vz) + o.z
        zn = vzo * den + nq * d.z
        hit &= clip_ok(dr.select(den > 0, zn, -zn), rules)
    return t, hit, inv_den, q


def clip_ok(z, rules: Rules):
    """False where a hit at height z lies in front of the window (z > 0; z >= 0 with '>=')."""
    if rules.screen_clip == "off":
        return True
    return (z <= 0) if rules.screen_clip == ">" else (z < 0)


def fplane_uv(d, q, inv_den, obj: ObjectConstants):
    """The seed's newhit.xy, without forming the hit point (see the module docstring)."""
    Array3 = type(d)
    c = dr.cross(q, d)
    u = dr.dot(opaque3(Array3, obj.ydir), c) * inv_den
    v = -dr.dot(opaque3(Array3, obj.xdir), c) * inv_den
    return u, v


def fplane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """plane_t, then the bounds test 0 <= u <= w, 0 <= v <= h (strict with open edges)."""
    F, B = _check(d)
    t, hit, inv_den, q = plane_t(d, o, obj, rules, vz)
    u, v = fplane_uv(d, q, inv_den, obj)
    w, h = dr.opaque(F, obj.size[0]), dr.opaque(F, obj.size[1])
    if rules.edges == "closed":
        inside = (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
    else:
        inside = (u > 0) & (u < w) & (v > 0) & (v < h)
    return t, hit & inside


def sphere_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    """The near root of |o + t·d − centre|² = r²; miss if the discriminant <= 0 or t <= 0.

    The discriminant is taken as a·(r² − |q'⊥|²) (distance of the centre from the ray line),
    and the near root as c/(b' + √disc) when b' > 0, so neither cancels."""
    F, B = _check(d)
    q = opaque3(type(d), obj.q)
    r = dr.opaque(F, obj.radius)
    if o is None:
        c = dr.opaque(F, obj.c)
    else:
        q = q - o
        qn = dr.norm(q)
        c = (qn - r) * (qn + r)
    a = dr.squared_norm(d)
    bh = dr.dot(q, d)                       # −b/2 of the course's quadratic
    pn = dr.norm(q - d * (bh / a))           # distance of the centre from the ray line
    disc = a * (r - pn) * (r + pn)
    s = dr.sqrt(dr.maximum(disc, 0))
    t = dr.select(bh > 0, c / (bh + s), (bh - s) / a)
    hit = (disc > 0) & (t > 0) & dr.isfinite(t)
    if rules.clip_spheres:
        z = dr.fma(t, d.z, dr.opaque(F, vz))
        hit &= clip_ok(z if o is None else z + o.z, rules)
    return t, hit


def object_t(d, o, obj: ObjectConstants, rules: Rules, vz: float):
    if obj.kind == "sphere":
        return sphere_t(d, o, obj, rules, vz)
    if obj.kind == "fplane":
        return fplane_t(d, o, obj, rules, vz)
    t, hit, _, _ = plane_t(d, o, obj, rules, vz)     # plane, tplane
    return t, hit
