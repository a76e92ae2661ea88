"""The references' own vector helpers, and the normal and finite-plane frame computed from the
numbers as written (never from rt_core's scene model: tests/test_independence.py)."""
from __future__ import annotations

import math


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
