"""The exact oracle's triangle and disk (mitsuba_ref/exact.py): integer constants and
decisions on the numbers as written, written here from the definitions (README "Triangle",
"Disk"), independently of rt_core's kernels and of rt_core/decide_planar.py.

* triangle P1 P2 P3: the plane of N = (P2 − P1) × (P3 − P1); the hit H is inside iff it lies
  on the inner side of each edge: N·((B − A) × (H − A)) >= 0 for the edges P1→P2, P2→P3,
  P3→P1 (> 0 with open edges).  Each is evaluated as an integer: with H = t·d − q (relative to
  the ray origin; q = P1 − V), N·((B − A) × (H − A))·(N·d) is an integer polynomial in the
  file's numbers and the ray's.  Margin: the hit's distance from the edge's line.
* disk centre C, radius r, normal N: inside iff |H − C|² <= r² (< with open edges), the
  integer (r²(N·d)² − |(N·q)d − (N·d)q|²); margin r − |H − C|.
"""
from __future__ import annotations

import math
from fractions import Fraction

DECISIONS = {"triangle": ("parallel", "t", "clip", "edge12", "edge23", "edge31"),
             "disk": ("parallel", "t", "clip", "radius")}


def _lcm(*vals) -> int:
    out = 1
    for v in vals:
        out = math.lcm(out, Fraction(v).denominator)
    return out


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def anchor(obj) -> tuple:
    """The point the plane's t is measured from: P1, or the centre."""
    return obj.points[0] if obj.kind == "triangle" else obj.center


def normal(obj):
    """(N as integers, its scale Ln: N_exact = N/Ln)."""
    if obj.kind == "triangle":
        P1, P2, P3 = obj.points
        Nx = _cross(tuple(b - a for a, b in zip(P1, P2)), tuple(c - a for a, c in zip(P1, P3)))
    else:
        Nx = tuple(obj.normal)
    L = _lcm(*Nx)
    return tuple(int(c * L) for c in Nx), L


def prepare(p, obj, V) -> None:
    """The kind's own integer constants on exact._Prep ``p`` (positions are integers / p.L)."""
    if obj.kind == "triangle":
        # the points relative to the viewpoint, as integers / L (a common scale)
        Lp = _lcm(*V, *(c for P in obj.points for c in P))
        p.Pt = [tuple(int((c - v) * Lp) for c, v in zip(P, V)) for P in obj.points]
        p.Lp = Lp
    else:
        r = Fraction(obj.radius)
        p.R2n, p.R2d = (r * r).numerator, (r * r).denominator
        p.r = float(r)


def _hit(p, D, Dd, tn, td):
    """The hit relative to the viewpoint, H = t·d (d = D/Dd), as exact Fractions."""
    return tuple(Fraction(tn * c, td * Dd) for c in D)


def eval_extent(p, D, Dd, tn, td, rules) -> dict:
    """{decision: (passed, margin)} of the extent tests for a hit at t = tn/td (td > 0)."""
    ge = (lambda x: x >= 0) if rules.edges == "closed" else (lambda x: x > 0)
    H = _hit(p, D, Dd, tn, td)
    out = {}
    if p.kind == "triangle":
        P = [tuple(Fraction(c, p.Lp) for c in Pt) for Pt in p.Pt]
        N = _cross(tuple(b - a for a, b in zip(P[0], P[1])),
                   tuple(c - a for a, c in zip(P[0], P[2])))
        nlen = math.sqrt(float(_dot(N, N)))
        for name, (A, B) in zip(("edge12", "edge23", "edge31"),
                                ((P[0], P[1]), (P[1], P[2]), (P[2], P[0]))):
            e = tuple(b - a for a, b in zip(A, B))
            s = _dot(N, _cross(e, tuple(h - a for h, a in zip(H, A))))
            # distance of H from the edge's line: s / (|N|·|e|)
            out[name] = (ge(s), float(s) / (nlen * math.sqrt(float(_dot(e, e)))))
        return out
    C = tuple(Fraction(c, p.L) for c in p.Q)
    rel = tuple(h - c for h, c in zip(H, C))
    slack = Fraction(p.R2n, p.R2d) - _dot(rel, rel)
    out["radius"] = (ge(slack), float(slack) / (p.r + math.sqrt(float(_dot(rel, rel)))))
    return out


def conditions(x, Vv, dv, _ddot, _dcross) -> dict:
    """The condition S of every decided quantity and of t, from dual inputs ``x`` (the
    object's numbers as written after the viewpoint and the ray: exact._conditions)."""
    if len(x) == 9 + 6:         # triangle: the three points
        P = [x[6:9], x[9:12], x[12:15]]
        e1 = tuple(b - a for a, b in zip(P[0], P[1]))
        e2 = tuple(c - a for a, c in zip(P[0], P[2]))
        N = _dcross(e1, e2)
        anchor_, out = P[0], {}
    else:                       # disk: centre, radius, normal
        C, r, N = x[6:9], x[9], x[10:13]
        anchor_, out = C, {}
    q = tuple(a - v for a, v in zip(anchor_, Vv))
    nd = _ddot(N, dv)
    t = _ddot(N, q) / nd
    z = Vv[2] + t * dv[2]
    out.update({"parallel": nd.cond(), "t": t.cond(), "clip": z.cond()})
    H = tuple(v + t * c for v, c in zip(Vv, dv))                    # the hit, absolute
    if len(x) == 15:
        nl = _ddot(N, N).sqrt()
        for name, (A, B) in zip(("edge12", "edge23", "edge31"),
                                ((P[0], P[1]), (P[1], P[2]), (P[2], P[0]))):
            e = tuple(b - a for a, b in zip(A, B))
            s = _ddot(N, _dcross(e, tuple(h - a for h, a in zip(H, A))))
            out[name] = (s / (nl * _ddot(e, e).sqrt())).cond()
    else:
        rel = tuple(h - c for h, c in zip(H, C))
        out["radius"] = (r - _ddot(rel, rel).sqrt()).cond()
    return out
