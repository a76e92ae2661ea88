"""The one table of shape kinds, and the forms the course files write them in.  Every per-kind
dispatch (rt_core's kernels, the references' oracles, the Mitsuba converter, the readers) is
keyed by these names, and a kind missing from a dispatch raises instead of falling through to
another kind (tests/test_independence.py test04 checks that every table covers every kind).

A pure table: no geometry, nothing the references could share with the tracer's arithmetic.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kind:
    name: str                # keyword of the keyword dialect
    code: int                # numeric dialect's object code
    bounded: bool            # has a finite extent (a bounding box)
    planar: bool             # the plane equation n·(x − point) = 0 with a frame or not


KINDS = {
    "sphere": Kind("sphere", 13, True, False),
    "plane": Kind("plane", 14, False, True),
    "fplane": Kind("fplane", 15, True, True),
    "tplane": Kind("tplane", 16, False, True),
    # quadrics (rt_core/quadrics.py): open cylinder and cone, axis-aligned ellipsoid
    "cylinder": Kind("cylinder", 22, True, False),
    "cone": Kind("cone", 23, True, False),
    "ellipsoid": Kind("ellipsoid", -1, True, False),      # keyword only (rm768)
    # the plane of three points, inside its three edges (README "Triangle"; kinds_planar.py)
    "triangle": Kind("triangle", 27, True, True),
    # the plane through a centre, within a radius of it (README "Disk"; kinds_planar.py)
    "disk": Kind("disk", 29, True, True),
    # nw's torus (nw__t.txt): centre, axis (normal of its plane), major radius R, minor r;
    # the surface (|w|² + R² − r²)² = 4R²(|w|² − (w·â)²), w = x − centre (a ring torus,
    # 0 < r < R).  Code 25 is also cd's lens: see SHARED_CODES
    "torus": Kind("torus", 25, True, False),
}
LIGHTS = {"pointlight": 10, "spotlight": 11}


@dataclass(frozen=True)
class Form:
    """One way the course files write an object or light: its type token (keyword and/or
    numeric code), the geometric kind (a KINDS name) or light it is, and the field groups that
    follow the kind's own, recorded with the object.  ``count`` 0 is one word (a file name).
    ``stand_in`` says how rtval shades it where the course programs' own shading (procedural
    shaders, textures) is not implemented: the geometry is traced and checked regardless."""
    name: str
    kind: str
    code: int | None = None
    keyword: str | None = None
    extra: tuple = ()
    stand_in: str = ""


_MAT_ONLY = "shaded with the object's own MAT"
FORMS = {f.name: f for f in (
    Form("pointlight", "pointlight", 10, "pointlight"),
    Form("spotlight", "spotlight", 11, "spotlight"),
    Form("sphere", "sphere", 13, "sphere"),
    Form("plane", "plane", 14, "plane"),
    Form("fplane", "fplane", 15, "fplane"),
    Form("tplane", "tplane", 16, "tplane"),
    Form("cylinder", "cylinder", 22),      # nw: base centre, centerline, radius height
    Form("cone", "cone", 23),              # nw: apex, centerline, radius height
    Form("ellipsoid", "ellipsoid", None, "ellipsoid"),   # rm768: centre, semi-axes
    Form("triangle", "triangle", 27, "triangle"),
    Form("disk", "disk", 29, "disk"),
    # procedural shaders (cbl, cd, m4, nw, sgw): the shader index after the geometry
    Form("psphere", "sphere", 19, None, (("shader", 1),),
         f"procedural sphere: its shader is not implemented, {_MAT_ONLY}"),
    Form("pplane", "plane", 20, None, (("shader", 1),),
         f"procedural plane: its shader is not implemented, {_MAT_ONLY}"),
    # textures (nw's 17 and 26 as numeric codes, rm768's keywords)
    Form("texplane", "fplane", 17, None, (("texture", 0), ("tile mode", 1)),
         f"textured plane: its texture is not applied, {_MAT_ONLY}"),
    Form("texsphere", "sphere", 26, None, (("texture", 0),),
         f"textured sphere: its texture is not applied, {_MAT_ONLY}"),
    Form("fplanetex", "fplane", None, "fplanetex",
         (("brightness", 1), ("texture size", 2), ("texture", 0)),
         f"textured finite plane: its texture is not applied, {_MAT_ONLY}"),
    Form("sphere_pixmap", "sphere", None, "sphere_pixmap",
         (("brightness", 1), ("forward", 3), ("texture", 0)),
         f"texture-mapped sphere: its texture is not applied, {_MAT_ONLY}"),
    Form("torus", "torus", 25),
    # cd's lens (code 25 in cd files): centre, radius.  cd's lens.c is a sphere hit only
    # from inside (the negated near root) that refracts: traced here as the sphere
    Form("lens", "sphere", None, None, (),
         "cd's lens (code 25): traced as the sphere (centre, radius); cd's lens.c hits it "
         f"only from inside and refracts, which is not implemented: {_MAT_ONLY}"),
    # nw's displacement sphere (dispsphere.c): a sphere whose hit distance nw shortens by
    # 0.1·(r + g + b) of the map's pixel at the hit; the map is not in the course corpus
    Form("dispsphere", "sphere", 28, None, (("displacement map", 0),),
         "displacement sphere: traced as its undisplaced sphere (nw subtracts 0.1·(r+g+b) of "
         f"the map's pixel from t; the map is not applied), {_MAT_ONLY}"),
)}
# code 25 is nw's torus and cd's lens: a file's 25 is the lens when it has cd's header flags
# (9000/9001), or else when the line after the centre has one number (the lens's radius; the
# torus has its axis there, 3 numbers).  Both readers apply this rule (rt_core/parser.py,
# mitsuba_ref/scenefile.py)
SHARED_CODES = {25: "lens"}
# Other course years' code tables: code -> (form, the groups' names in the file's order, None
# for the kind's own; a name the kind lacks is one number, recorded).  A numeric file that
# CODES cannot read is read with the first of these that reads the whole file; the scene
# records which, and every output says so (TABLE_NOTES).
CODE_TABLES = {
    # nw__a3t7.txt's (an assignment file that nw's final program, whose table is CODES, no
    # longer reads): each kind's geometry before its MAT, lights with a radius after the centre
    "geometry-first": {
        10: ("pointlight", ("center", "radius", "emissivity")),
        11: ("sphere", ("center", "radius", "ambient", "diffuse", "specular")),
        12: ("plane", ("normal", "point", "ambient", "diffuse", "specular")),
        16: ("spotlight", ("center", "radius", "emissivity", "aim", "theta")),
    },
    # nw__cone-sphere.txt's (nw's repository, another early table): the MAT first as in CODES,
    # but 11 sphere, 13 cylinder, 17 cone, and a light with a radius after its centre
    "early-nw": {
        10: ("pointlight", ("emissivity", "center", "radius")),
        11: ("sphere", None),
        13: ("cylinder", None),
        17: ("cone", None),
    },
}
TABLE_NOTES = {
    "geometry-first": "read with the geometry-first code table (10 light, 11 sphere, 12 plane, "
                      "16 spotlight; geometry before the MAT; a light's radius is not used), "
                      "which the notes' table could not read",
    "early-nw": "read with nw's early code table (10 light with a radius, 11 sphere, "
                "13 cylinder, 17 cone; a light's radius is not used), which the notes' table "
                "could not read; its cone is nw's final 23 (the point is the apex), though "
                "the file's own sphere meets the rim exactly if the point is the base centre",
}
# cd's header flags (numeric dialect, after the viewpoint): each adds one number after every
# MAT (ambient, diffuse, specular), in the order the flags are given
HEADER_FLAGS = {9000: "transparency", 9001: "refraction index"}
FLAG_STAND_IN = "{}: recorded, not used in shading (the course's refraction is not implemented)"
# numeric codes whose field layout differs between course programs, told apart by the line
# shape (rt_core/kinds_planar.py SHAPED_CODES)
from .kinds_planar import SHAPED_CODES  # noqa: E402  (a table, like this module)
KEYWORDS = tuple(f.keyword for f in FORMS.values() if f.keyword)
CODES = {f.code: f.name for f in FORMS.values() if f.code is not None}
PLANE_KINDS = tuple(n for n, k in KINDS.items() if k.planar)
KIND_CODE = {n: i for i, n in enumerate(KINDS)}      # kernels' kind number


def kind(name: str) -> Kind:
    try:
        return KINDS[name]
    except KeyError:
        raise ValueError(f"unknown object kind {name!r} (known: {', '.join(KINDS)})") from None


def dispatch(table: dict, name: str):
    """``table[name]`` for a per-kind table; an unknown kind raises (no fall-through)."""
    try:
        return table[name]
    except KeyError:
        raise ValueError(f"object kind {name!r} has no entry here (known: "
                         f"{', '.join(sorted(table))})") from None
