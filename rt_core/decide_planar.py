"""Exact decisions of the planar kinds triangle and disk (rt_core/decide.py's rational
arithmetic on the numbers as written; independent of mitsuba_ref/exact.py).

* triangle, anchor P1, N = (P2 − P1) × (P3 − P1), e1 = P2 − P1, e2 = P3 − P1: with the ray
  from the viewpoint along E and Q = P1 − V, the barycentric weights times N·E are
  β·(N·E) = e2·(Q × E), γ·(N·E) = −e1·(Q × E), α·(N·E) = N·E − both; inside iff all three
  times sign(N·E) are >= 0 (> 0 with open edges);
* disk: H = s·E − Q (the hit relative to the centre, s = N·Q/N·E): inside iff H·H <= r²
  (< with open edges).
"""
from __future__ import annotations

from .planar import triangle_normal_exact
from .scene import exact


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def init(x, obj, V) -> None:
    """The exact numbers of a triangle or disk on decide._Exact ``x``: N, Q, N·Q and the
    extent's own."""
    if obj.kind == "triangle":
        P = [tuple(exact(c) for c in p) for p in obj.points]
        x.N = triangle_normal_exact(obj.points)
        x.e1 = tuple(a - b for a, b in zip(P[1], P[0]))
        x.e2 = tuple(a - b for a, b in zip(P[2], P[0]))
        anchor = P[0]
    else:
        x.N = tuple(exact(c) for c in obj.given_normal)
        x.r2 = exact(obj.radius) ** 2
        anchor = tuple(exact(c) for c in obj.center)
    x.Q = tuple(a - v for a, v in zip(anchor, V))
    x.NQ = _dot(x.N, x.Q)


def inside(x, E, s, edges: str) -> bool:
    """The extent test of a plane hit at parameter s along E (module docstring)."""
    ok = (lambda v: v >= 0) if edges == "closed" else (lambda v: v > 0)
    if x.kind == "triangle":
        c = _cross(x.Q, E)
        ND = _dot(x.N, E)
        sg = 1 if ND > 0 else -1
        b, g = _dot(x.e2, c) * sg, -_dot(x.e1, c) * sg
        return ok(b) and ok(g) and ok(ND * sg - b - g)
    H = tuple(s * e - q for e, q in zip(E, x.Q))
    return ok(x.r2 - _dot(H, H))
