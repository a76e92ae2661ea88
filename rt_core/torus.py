"""The torus object of the scene model (nw's code 25): host-side, float64, like rt_core/scene.py.

Fields as nw__t.txt writes them after the MAT: centre (x y z), axis (the normal of the
torus's plane, any length), major radius R (centre to the tube's core circle), minor
radius r (the tube's).  The surface is {x : (|w|² + R² − r²)² = 4R²(|w|² − (w·â)²)},
w = x − centre, â = unit(axis): the points at distance r from the core circle.  Only ring
tori (0 < r < R) are read: a horn or spindle torus (r >= R) is an error at the minor radius.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .scene import GeometryError, Material, Vec3, fmt, unit


@dataclass(frozen=True)
class Torus:
    material: Material
    center: Vec3
    axis: Vec3              # unit
    major: float            # R
    minor: float            # r
    line: int = 0
    given_axis: Vec3 = ()   # as written in the file
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)
    extras: tuple = field(default=(), compare=False)
    kind = "torus"


def make_torus(material: Material, center: Vec3, axis: Vec3, major: float, minor: float,
               line: int = 0) -> Torus:
    a = unit(axis, "axis")
    if not major > 0:
        raise GeometryError(f"major radius {fmt((major,))[1:-1]} must be positive")
    if not minor > 0:
        raise GeometryError(f"minor radius {fmt((minor,))[1:-1]} must be positive")
    if not minor < major:
        raise GeometryError(f"minor radius {fmt((minor,))[1:-1]} must be below the major "
                            f"radius {fmt((major,))[1:-1]} (a ring torus; horn and spindle "
                            "tori are not supported)")
    return Torus(material, tuple(center), a, major, minor, line, tuple(axis))
