"""The references' own vector helpers, and the normal and finite-plane frame computed from the
numbers as written (never from rt_core's scene model: tests/test_independence.py)."""
from __future__ import annotations

import math
from fractions import Fraction


def dot(a, b) -> float:
    return math.fsum((a[0] * b[0], a[1] * b[1], a[2] * b[2]))


def sub(a, b) -> tuple:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def cross(a, b) -> tuple:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def unit(v) -> tuple:
    m = max(abs(c) for c in v)
    s = tuple(c / m for c in v)
    n = math.sqrt(math.fsum(c * c for c in s))
    return tuple(c / n for c in s)


def pow2_scaled(v, rounded: bool = False) -> tuple:
    """v times the power of two that brings its largest component into [0.5, 1): exact,
    and |v|² then neither overflows nor underflows float64 (a normal 1e200 0 1, a
    centerline 1e-320 0 0).  Fractions stay exact; ``rounded``: every component rounded
    to float64 first.  A zero vector as it is."""
    if rounded:
        v = tuple(float(c) for c in v)
    big = max(abs(float(c)) for c in v)
    if big == 0:
        return tuple(v)
    k = -math.frexp(big)[1]
    return tuple(c * Fraction(2) ** k if isinstance(c, Fraction) else math.ldexp(c, k)
                 for c in v)


def int_norm(D) -> tuple:
    """(m, r) with |D| = m·r for an integer vector: m its largest |component|, r in
    [1, √3] (0, 0 for a zero one); neither overflows nor underflows float64."""
    m = max(map(abs, D))
    return (m, math.sqrt(sum((c / m) ** 2 for c in D))) if m else (0, 0.0)   # (c/m rounded once)


def ray_length(D, Dd) -> float:
    """|D|/Dd in float64 for integers of any size (a ray D/Dd given exactly)."""
    m, r = int_norm(D)
    return m / abs(Dd) * r if m else 0.0


def given_normal(obj) -> tuple:
    """The plane's normal as written in the file (rt_core objects keep it as
    ``given_normal``; mitsuba_ref.scenefile items as ``normal``)."""
    g = getattr(obj, "given_normal", None)
    return tuple(g) if g else tuple(obj.normal)


def normal(obj) -> tuple:
    return unit(given_normal(obj))


def frame(obj) -> tuple:
    """(x̂, ŷ, n̂) of a finite or tiled plane, as the seed: x̂ = unit(orient projected onto the
    plane), ŷ = n̂ × x̂."""
    n = normal(obj)
    o = unit(obj.orient)
    c = dot(o, n)
    x = unit(tuple(a - c * b for a, b in zip(o, n)))
    return x, unit(cross(n, x)), n


def corners(obj) -> tuple:
    x, y, _ = frame(obj)
    w, h = obj.size
    p = obj.point
    at = lambda a, b: tuple(p[i] + a * x[i] + b * y[i] for i in range(3))
    return (at(0, 0), at(w, 0), at(w, h), at(0, h))
