"""The float64 oracle's triangle and disk (mitsuba_ref/oracle.py), from the definitions
(README "Triangle", "Disk"), with first-order error bounds (``EF``):

* triangle P1 P2 P3: the plane of N = (P2 − P1) × (P3 − P1) through P1; the hit is inside iff
  N·((B − A) × (hit − A)) >= 0 for the edges A→B = P1→P2, P2→P3, P3→P1 (the course's edge
  tests, each with its own edge: nw's second test used the first edge); uv = the barycentric
  weights of P2 and P3, (N·((P1 − P3) × (hit − P3)), N·((P2 − P1) × (hit − P1)))/|N|²;
* disk: the plane through the centre C with the normal as written; inside iff |hit − C|² <=
  r²; uv = (hit − C)·x̂, (hit − C)·ŷ with x̂ the world axis least aligned with the normal
  (smallest |n_k| as written, the first on a tie) projected onto the plane, ŷ = n̂ × x̂.
"""
from __future__ import annotations

from .geometry import cross, dot, given_normal, sub, unit

AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def points(o) -> tuple:
    """A triangle's three points (rt_core objects: ``points``; scenefile items: point1..3)."""
    pts = getattr(o, "points", None)
    return tuple(pts) if pts else (o.point1, o.point2, o.point3)


def triangle_normal(o) -> tuple:
    P1, P2, P3 = points(o)
    return cross(sub(P2, P1), sub(P3, P1))


def disk_frame(o) -> tuple:
    """(x̂, ŷ, n̂) of a disk (module docstring)."""
    g = given_normal(o)
    n = unit(g)
    a = [abs(c) for c in g]
    e = AXES[a.index(min(a))]
    c = dot(e, n)
    x = unit(tuple(p - c * q for p, q in zip(e, n)))
    return x, unit(cross(n, x)), n


def prepare(i, o, _Obj, vec, EF):
    """The oracle's _Obj of a triangle or disk, its numbers taken as inputs rounded once."""
    if o.kind == "triangle":
        from .oracle import cross3, diff3, unit3, vals     # (oracle imports this module)
        pts = points(o)
        P = tuple(vec(p) for p in pts)
        # N and its unit from the points with their error bounds (a rounded cross product
        # of differences: more than one rounding)
        N = cross3(diff3(P[1], P[0]), diff3(P[2], P[0]))
        n = unit3(N)
        ob = _Obj(i, o.kind, o, ("p", vals(n), tuple(pts[0])), normal=n, point=P[0])
        ob.pts, ob.N = P, N
        return ob
    x, y, n = disk_frame(o)
    ob = _Obj(i, o.kind, o, ("p", n, tuple(o.center)), normal=vec(n), point=vec(o.center),
              center=vec(o.center), radius=EF(o.radius))
    ob.rotmat = (vec(x), vec(y), vec(n))
    return ob


def extent(ob, hit, rules, ops) -> tuple:
    """(inside, slacks as EF (each >= 0 inside), uv as EF) of a plane hit."""
    dot3, diff3, cross3 = ops
    if ob.kind == "triangle":
        P, N = ob.pts, ob.N
        s = [dot3(N, cross3(diff3(B, A), diff3(hit, A)))
             for A, B in ((P[0], P[1]), (P[1], P[2]), (P[2], P[0]))]
        NN = dot3(N, N)
        uv = (s[2] / NN, s[0] / NN)
    else:
        rel = diff3(hit, ob.center)
        s = [ob.radius * ob.radius - dot3(rel, rel)]
        uv = (dot3(ob.rotmat[0], rel), dot3(ob.rotmat[1], rel))
    ok = (lambda v: v >= 0.0) if rules.edges == "closed" else (lambda v: v > 0.0)
    return all(ok(x.v) for x in s), s, uv
