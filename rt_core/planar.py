"""The planar kinds triangle and disk in rtval's scene model (README "Triangle", "Disk").

* triangle: the plane of its three points P1, P2, P3 with the normal N = (P2 − P1) × (P3 − P1)
  (the course's (P1 − P2) × (P1 − P3)), a hit inside iff it lies on the inner side of all
  three edges (closed or open edges: ``Rules.edges``).  uv = the barycentric weights (u of
  P2, v of P3): hit = (1 − u − v)·P1 + u·P2 + v·P3.
* disk: the plane through ``center`` with ``normal``; a hit inside iff |hit − center| <=
  radius (< with open edges).  uv = the hit's coordinates relative to the centre in the frame
  of the normal, x̂ = the world axis least aligned with the normal (x, then y, then z on a
  tie) projected onto the plane, ŷ = n̂ × x̂ (world units, in [−r, r]).

Both keep ``normal`` (unit), ``point`` (the anchor: P1, the centre) and ``given_normal``
(the plane's normal as exact numbers allow: the disk's as written; the triangle's is not
written in the file, so () and the users compute it exactly from the points).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Tuple

from .scene import GeometryError, Material, Vec3, exact, fmt, plane_frame, unit

AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def _sub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def triangle_normal_exact(points) -> tuple:
    """N = (P2 − P1) × (P3 − P1) on the numbers as written (Fractions)."""
    P = [tuple(exact(c) for c in p) for p in points]
    return _cross(_sub(P[1], P[0]), _sub(P[2], P[0]))


def disk_axis(normal) -> int:
    """The world axis the disk's frame starts from: the one least aligned with the normal
    (smallest |n_k|; the first on a tie), exact on the numbers as written."""
    a = [abs(exact(c)) for c in normal]
    return a.index(min(a))


@dataclass(frozen=True)
class Triangle:
    material: Material
    points: Tuple[Vec3, Vec3, Vec3]
    normal: Vec3            # unit (P2 − P1) × (P3 − P1)
    point: Vec3             # P1, the plane's anchor
    line: int = 0
    given_normal: Vec3 = ()
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)
    extras: tuple = field(default=(), compare=False)
    kind = "triangle"


@dataclass(frozen=True)
class Disk:
    material: Material
    center: Vec3
    radius: float
    normal: Vec3            # unit
    xdir: Vec3              # the uv frame (module docstring)
    ydir: Vec3
    line: int = 0
    given_normal: Vec3 = ()  # as written in the file
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)
    extras: tuple = field(default=(), compare=False)
    kind = "disk"

    @property
    def point(self) -> Vec3:
        return self.center


def make_triangle(material: Material, p1: Vec3, p2: Vec3, p3: Vec3, line: int = 0) -> Triangle:
    pts = (tuple(p1), tuple(p2), tuple(p3))
    N = triangle_normal_exact(pts)
    if not any(N):
        raise GeometryError(f"points {fmt(p1)}, {fmt(p2)}, {fmt(p3)} are collinear: no plane")
    n = unit(tuple(float(c) for c in N), "normal")
    return Triangle(material, pts, n, pts[0], line)


def make_disk(material: Material, center: Vec3, radius: float, normal: Vec3,
              line: int = 0) -> Disk:
    if not radius > 0:
        raise GeometryError(f"radius {radius:g} must be positive")
    x, y, n = plane_frame(normal, AXES[disk_axis(normal)] if any(normal) else AXES[0])
    return Disk(material, tuple(center), radius, n, x, y, line, tuple(normal))
