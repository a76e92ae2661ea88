"""The quadric kinds' scene model: cylinder (nw code 22), cone (nw 23), ellipsoid (rm768's
``ellipsoid`` keyword), and their exact equations.

Each is the zero set of a quadratic polynomial whose coefficients are rational in the numbers
as written when the axis is left unnormalised (a = the centerline as given, w = p − anchor):

* cylinder (anchor: the base centre): |w|²|a|² − (w·a)² = r²|a|², open (no caps), its finite
  part 0 <= w·a <= h|a|;
* cone (anchor: the apex, the point the file gives; k = (r/h)²): |w|²|a|² − (1+k)(w·a)² = 0,
  open, the nappe 0 <= w·a <= h|a| (radius r at distance h along the axis);
* ellipsoid (anchor: the centre; semi-axes a b c, axis-aligned): b²c²w_x² + a²c²w_y² +
  a²b²w_z² = a²b²c².

Along a ray p = V + s·E (V the viewpoint) w = s·E − Q with Q = anchor − V, so the surface
is A s² − 2B s + C = 0 with rational A, B, C (``coefficients``): the hit parameter is
(B ± √(B² − AC))/A, a number α + β√D like the sphere's.  A closed surface (ellipsoid) is hit
at its near root only, as the sphere; an open one (cylinder, cone) at the nearest root with
s > 0 inside its axial range (the inside wall shows through the open ends).

This module is the model only (no Dr.Jit): rt_core/shapes_quadric.py traces it,
rt_core/decide.py decides it exactly through ``coefficients``.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from fractions import Fraction

from .scene import GeometryError, Material, Vec3, exact, fmt

KINDS = ("cylinder", "cone", "ellipsoid")
OPEN = ("cylinder", "cone")          # axial range, both roots; the ellipsoid: near root only


@dataclass(frozen=True)
class _OpenQuadric:
    """The fields of the open quadrics: a point, the axis (the centerline as given), the
    radius at ``height`` along the axis."""
    material: Material
    center: Vec3
    axis: Vec3
    radius: float
    height: float
    line: int = 0
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)
    extras: tuple = field(default=(), compare=False)
    note: str = field(default="", compare=False)   # how a degenerate field was read
    # the centerline as written (``axis`` is what rt_core reads it as): the references read
    # this one and apply their own rule (tools/harness/agree.py checks it against their
    # reader's numbers)
    given_axis: Vec3 = field(default=(), compare=False)


class Cylinder(_OpenQuadric):
    """Open finite cylinder: base centre, axis, radius, height."""
    kind = "cylinder"


class Cone(_OpenQuadric):
    """Open finite cone: apex ``center`` (nw's "centerpoint of base" is the apex of its
    equation), axis, radius at ``height`` along the axis."""
    kind = "cone"


@dataclass(frozen=True)
class Ellipsoid:
    """Axis-aligned ellipsoid: centre and semi-axes (a, b, c) along x, y, z."""
    material: Material
    center: Vec3
    axes: Vec3
    line: int = 0
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)
    extras: tuple = field(default=(), compare=False)
    note: str = ""
    kind = "ellipsoid"


Y_AXIS = (0.0, 1.0, 0.0)


def _axis_of(kind: str, axis) -> tuple:
    """(axis, note): a zero centerline is read as the y axis, as nw's code does (it rotates
    nothing), with a note for the provenance."""
    if all(c == 0 for c in axis):
        return Y_AXIS, (f"{kind} centerline {fmt(axis)} has no direction: read as the y axis "
                        "(0 1 0), as nw's program does")
    return tuple(axis), ""


def make_cylinder(material: Material, center, axis, dims, line: int = 0) -> Cylinder:
    r, h = dims
    if not (r > 0 and h > 0):
        raise GeometryError(f"radius and height {fmt(dims)} must be positive")
    a, note = _axis_of("cylinder", axis)
    return Cylinder(material, tuple(center), a, r, h, line, note=note,
                    given_axis=tuple(axis))


def make_cone(material: Material, center, axis, dims, line: int = 0) -> Cone:
    r, h = dims
    if not (r > 0 and h > 0):
        raise GeometryError(f"radius and height {fmt(dims)} must be positive")
    a, note = _axis_of("cone", axis)
    return Cone(material, tuple(center), a, r, h, line, note=note, given_axis=tuple(axis))


def make_ellipsoid(material: Material, center, axes, line: int = 0) -> Ellipsoid:
    if not all(c > 0 for c in axes):
        raise GeometryError(f"semi-axes {fmt(axes)} must be positive")
    return Ellipsoid(material, tuple(center), tuple(axes), line)


# --- exact equations (rational, on the numbers as written) -----------------------------------

def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@dataclass(frozen=True)
class Equation:
    """f(w) = w·M·w − e with M = diag(m) − c·a aᵀ (all rational), and for an open kind the
    axial range 0 <= w·a <= h|a| (``hh`` = h²|a|², or None)."""
    m: tuple
    c: Fraction
    a: tuple
    e: Fraction
    hh: Fraction | None

    def quad(self, x, y):
        """x·M·y."""
        return (sum(mi * xi * yi for mi, xi, yi in zip(self.m, x, y))
                - self.c * _dot(x, self.a) * _dot(y, self.a))


def equation(obj) -> Equation:
    """The object's equation with exact coefficients (see the module docstring)."""
    if obj.kind == "ellipsoid":
        a, b, c = (exact(x) ** 2 for x in obj.axes)
        zero = (Fraction(0),) * 3
        return Equation((b * c, a * c, a * b), Fraction(0), zero, a * b * c, None)
    A = tuple(exact(x) for x in obj.axis)
    AA = _dot(A, A)
    r, h = exact(obj.radius), exact(obj.height)
    if obj.kind == "cylinder":
        return Equation((AA,) * 3, Fraction(1), A, r * r * AA, h * h * AA)
    return Equation((AA,) * 3, 1 + r * r / (h * h), A, Fraction(0), h * h * AA)


def coefficients(eq: Equation, Q, E):
    """(A, B, C) of A s² − 2B s + C = 0 along w = s·E − Q."""
    return eq.quad(E, E), eq.quad(E, Q), eq.quad(Q, Q) - eq.e
