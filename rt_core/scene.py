"""Immutable scene model of the course tracer.

Everything a tracer needs is computed once here, in float64 on the host: unit normals, the
finite/tiled-plane frame (rows x̂, ŷ, n̂ of the seed's ``rotmat``).  Object ids are the index
among non-light objects in file order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from decimal import Decimal
from fractions import Fraction
from typing import Tuple, Union

from .kinds import KINDS as _KINDS

Vec3 = Tuple[float, float, float]


class SceneError(Exception):
    """A scene that cannot be used. ``str(err)`` is one line: ``file:line:col: message``."""
    exit_code = 2

    def __init__(self, message: str, path: str | None = None, line: int | None = None,
                 col: int | None = None):
        self.message, self.path, self.line, self.col = message, path, line, col
        where = ":".join(str(p) for p in (path, line, col) if p is not None)
        super().__init__(f"{where}: {message}" if where else message)

    @property
    def category(self) -> str:
        """'unsupported' (an object kind the course used that rtval does not implement) or
        'malformed' (the file itself is wrong)."""
        return "unsupported" if " is not supported" in self.message else "malformed"


class GeometryError(ValueError):
    """Invalid geometry (zero normal, orient parallel to the normal, ...); the parser adds
    the location and re-raises it as a :class:`SceneError`."""


class Num(float):
    """A scene number: its float64 value, and the decimal text it was read from (``text``),
    so that the kernels' host constants and the exact decisions (rt_core/decide.py) use the
    number as written, not its rounding."""
    __slots__ = ("text",)

    def __new__(cls, text: str):
        x = float.__new__(cls, text)
        x.text = text
        return x


def exact(x) -> Fraction:
    """A scene number exactly as written (a plain float: its binary value)."""
    return Fraction(Decimal(x.text)) if isinstance(x, Num) else Fraction(x)


def written(v) -> tuple:
    """Scene numbers as a cache key: each value and, for a Num, the text it was read from
    (``exact`` reads that: two texts of one float64 are two numbers); other numbers as they
    are (a Fraction stays exact)."""
    return tuple((float(c), c.text) if isinstance(c, Num) else (c, None) for c in v)


# --- small float64 vector helpers (host side) ---------------------------------------------

def dot(a: Vec3, b: Vec3) -> float:
    return math.fsum((a[0] * b[0], a[1] * b[1], a[2] * b[2]))


def sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def unit(v: Vec3, what: str = "vector") -> Vec3:
    """v / |v| without overflow or underflow for any finite magnitude (1e-300 .. 1e300)."""
    m = max(abs(c) for c in v)
    if m == 0.0 or not math.isfinite(m):
        raise GeometryError(f"{what} {fmt(v)} has no direction")
    s = tuple(c / m for c in v)
    n = math.sqrt(math.fsum(c * c for c in s))
    return (s[0] / n, s[1] / n, s[2] / n)


def fmt(v) -> str:
    """Numbers as written in the file where known (``Num``), else ``%g``."""
    return "(" + ", ".join(c.text if isinstance(c, Num) else f"{c:g}" for c in v) + ")"


def plane_frame(normal: Vec3, orient: Vec3) -> tuple[Vec3, Vec3, Vec3]:
    """The seed's rotmat rows: x̂ = unit(orient projected onto the plane), ŷ = n̂ × x̂, n̂."""
    n = unit(normal, "normal")
    o = unit(orient, "orient")
    # project the (unit) orient onto the plane; relative size 1e-12 or less means parallel
    c = dot(o, n)
    p = (o[0] - c * n[0], o[1] - c * n[1], o[2] - c * n[2])
    if max(abs(x) for x in p) <= 1e-12:
        raise GeometryError(f"orient {fmt(orient)} is parallel to the normal {fmt(normal)}; "
                            "give an in-plane direction")
    x = unit(p, "projected orient")
    y = unit(cross(n, x), "n x orient")
    return x, y, n


# --- the model ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Material:
    ambient: Vec3
    diffuse: Vec3
    specular: Vec3


@dataclass(frozen=True)
class PointLight:
    emissivity: Vec3
    center: Vec3
    line: int = 0
    kind = "pointlight"


@dataclass(frozen=True)
class SpotLight:
    """A point light that lights H only inside its cone: unit(H − centre)·unit(aim − centre)
    > cos(theta), theta the half-angle in degrees (cd's and nw's code 11)."""
    emissivity: Vec3
    center: Vec3
    aim: Vec3
    theta: float
    line: int = 0
    kind = "spotlight"


@dataclass(frozen=True)
class Sphere:
    material: Material
    center: Vec3
    radius: float
    line: int = 0
    at: tuple = field(default=(), compare=False, repr=False)
    form: str = field(default="", compare=False)      # kinds.FORMS name when not the plain kind
    extras: tuple = field(default=(), compare=False)  # (field, value) the form adds, recorded
    texture: object = field(default=None, compare=False, repr=False)  # textures.Texture, loaded
    kind = "sphere"


@dataclass(frozen=True)
class Plane:
    material: Material
    normal: Vec3            # unit
    point: Vec3
    line: int = 0
    given_normal: Vec3 = ()  # as written in the file
    at: tuple = field(default=(), compare=False, repr=False)   # see locate()
    form: str = field(default="", compare=False)      # kinds.FORMS name when not the plain kind
    extras: tuple = field(default=(), compare=False)  # (field, value) the form adds, recorded
    kind = "plane"


@dataclass(frozen=True)
class FPlane:
    """Finite rectangle: corner ``point``, frame rows ``xdir``, ``ydir``, ``normal``, size w×h."""
    material: Material
    normal: Vec3            # unit (rotmat row 2)
    point: Vec3             # lower-left corner
    orient: Vec3            # as given in the file
    size: Tuple[float, float]
    xdir: Vec3              # rotmat row 0
    ydir: Vec3              # rotmat row 1
    line: int = 0
    given_normal: Vec3 = ()  # as written in the file
    at: tuple = field(default=(), compare=False, repr=False)   # see locate()
    form: str = field(default="", compare=False)      # kinds.FORMS name when not the plain kind
    extras: tuple = field(default=(), compare=False)  # (field, value) the form adds, recorded
    texture: object = field(default=None, compare=False, repr=False)  # textures.Texture, loaded
    kind = "fplane"

    @property
    def rotmat(self) -> tuple[Vec3, Vec3, Vec3]:
        return (self.xdir, self.ydir, self.normal)

    def corners(self) -> tuple[Vec3, Vec3, Vec3, Vec3]:
        """(0,0), (w,0), (w,h), (0,h) in world coordinates."""
        w, h = self.size
        p, x, y = self.point, self.xdir, self.ydir
        at = lambda a, b: tuple(p[i] + a * x[i] + b * y[i] for i in range(3))
        return (at(0, 0), at(w, 0), at(w, h), at(0, h))


@dataclass(frozen=True)
class TPlane:
    """Infinite plane tiled in w×h tiles: ``material`` when relx + rely is odd, else
    ``background``."""
    material: Material
    normal: Vec3
    point: Vec3
    orient: Vec3
    size: Tuple[float, float]
    xdir: Vec3
    ydir: Vec3
    background: Material
    line: int = 0
    given_normal: Vec3 = ()  # as written in the file
    at: tuple = field(default=(), compare=False, repr=False)   # see locate()
    form: str = field(default="", compare=False)      # kinds.FORMS name when not the plain kind
    extras: tuple = field(default=(), compare=False)  # (field, value) the form adds, recorded
    kind = "tplane"

    @property
    def rotmat(self) -> tuple[Vec3, Vec3, Vec3]:
        return (self.xdir, self.ydir, self.normal)


SceneObject = Union[Sphere, Plane, FPlane, TPlane]


def locate(obj, name: str, index: int = 0):
    """(line, col) of number ``index`` of the object's group ``name`` ("center", "point",
    ...) as the parser recorded it in ``obj.at``; (obj.line, None) when not recorded."""
    for group, places in obj.at:
        if group == name and index < len(places):
            return places[index]
    return (obj.line or None, None)
KINDS = tuple(_KINDS)


@dataclass(frozen=True)
class Scene:
    window: Tuple[float, float]          # world width, height at z = 0, centred on the origin
    viewpoint: Vec3
    lights: Tuple[PointLight, ...] = ()
    objects: Tuple[SceneObject, ...] = ()  # object id = index here
    path: str = "<memory>"
    dialect: str = "keyword"
    sha256: str = ""
    header_at: tuple = field(default=(), compare=False, repr=False)  # (line, col) of w h x y z
    flags: tuple = ()                    # cd's header flags (9000, 9001) as given
    table: str = ""                      # numeric: the code table when not the notes' one

    def stand_ins(self) -> list[str]:
        """What this scene has that rtval traces but shades with a stand-in (kinds.FORMS),
        one line each: recorded in every output's provenance."""
        from .kinds import FLAG_STAND_IN, FORMS, HEADER_FLAGS, TABLE_NOTES
        out = [TABLE_NOTES[self.table]] if self.table else []
        out += [f"line {o.line}: {FORMS[o.form].stand_in}" for o in self.objects
               if o.form and FORMS[o.form].stand_in and getattr(o, "texture", None) is None]
        out += [f"line {o.line}: {o.note}" for o in self.objects if getattr(o, "note", "")]
        out += [FLAG_STAND_IN.format(f"header flag {f} ({HEADER_FLAGS[f]} after every MAT)")
                for f in self.flags]
        out += [f"line {o.line}: " + FLAG_STAND_IN.format(f"{o.kind}'s refraction index")
                for o in self.objects if any(k == "refraction index" for k, _ in o.extras)
                and not self.flags]
        return out

    def kinds(self) -> tuple[str, ...]:
        """Object kinds present, in the fixed order of KINDS."""
        present = {o.kind for o in self.objects}
        return tuple(k for k in KINDS if k in present)

    def default_rows(self, columns: int) -> int:
        """The keyword programs' rule: rows = int(world_h / world_w * columns).  A window so
        tall that no image can have that many rows is a SceneError at its height."""
        rows = self.window[1] / self.window[0] * columns
        if not rows < 2 ** 31:
            line, col = self.header_at[1] if self.header_at else (None, None)
            raise SceneError(f"header: world window {fmt(self.window)} gives int(h/w·columns) = "
                             f"{rows:.3g} rows at {columns} columns, more than an image can "
                             "have; use fewer --columns, fix the window or give --rows",
                             self.path, line, col)
        return int(rows)

    def at_viewpoint(self, axis: int):
        """(line, col) of the viewpoint's coordinate ``axis``, or (None, None)."""
        return self.header_at[2 + axis] if self.header_at else (None, None)


def make_fplane(material: Material, normal: Vec3, point: Vec3, orient: Vec3,
                size: Tuple[float, float], line: int = 0) -> FPlane:
    if not (size[0] > 0 and size[1] > 0):
        raise GeometryError(f"size {fmt(size)} must be positive")
    x, y, n = plane_frame(normal, orient)
    return FPlane(material, n, tuple(point), tuple(orient), tuple(size), x, y, line,
                  tuple(normal))


def make_tplane(material: Material, normal: Vec3, point: Vec3, orient: Vec3,
                size: Tuple[float, float], background: Material, line: int = 0) -> TPlane:
    if not (size[0] > 0 and size[1] > 0):
        raise GeometryError(f"tile size {fmt(size)} must be positive")
    x, y, n = plane_frame(normal, orient)
    return TPlane(material, n, tuple(point), tuple(orient), tuple(size), x, y, background, line,
                  tuple(normal))


def make_plane(material: Material, normal: Vec3, point: Vec3, line: int = 0) -> Plane:
    return Plane(material, unit(normal, "normal"), tuple(point), line, tuple(normal))


def make_sphere(material: Material, center: Vec3, radius: float, line: int = 0) -> Sphere:
    if not radius > 0:
        raise GeometryError(f"radius {radius:g} must be positive")
    # (a scene Num stays one: the exact decisions take the radius as written)
    return Sphere(material, tuple(center), radius if isinstance(radius, Num) else float(radius),
                  line)
