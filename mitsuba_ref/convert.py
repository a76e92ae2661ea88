"""Course scene -> the equivalent Mitsuba 3 scene, as a dict for ``mi.load_dict`` and as XML.

* finite plane -> ``rectangle``; ``to_world`` columns (w/2)x̂, (h/2)ŷ, n̂, centre, so that
  Mitsuba's uv·(w, h) is the course's ``lasthit`` and its normal is the course normal;
* plane, tiled plane -> a square ``rectangle`` of half-size ``R`` centred on the viewpoint's
  projection onto the plane (size rule: ``plane_extent``);
* sphere -> ``sphere``;
* camera -> ``perspective`` sensor whose pixel centres are the course's samples; ``near_clip``
  = viewpoint.z starts every ray on the window plane z = 0 (the course's screen clip); with
  the viewpoint behind the window (z < 0) the sensor faces +z and ``far_clip`` = |z| clips.

Shape ids are ``obj<course id>_<kind>``.  Mitsuba's variant here is ``llvm_ad_rgb`` (float32;
the wheel has no double variants).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from decimal import Decimal
from fractions import Fraction
from typing import Any as Scene         # a parsed course scene (duck-typed)
from xml.sax.saxutils import quoteattr

from rt_core.usererror import InputError
from rt_core.kinds import KINDS, dispatch
from rt_core.rules import Rules

DEFAULT_MAX_DIST = 1000.0       # the notes' MAX_DIST, as ``rtval render``'s default

from . import quadric
from . import convert_planar
from .geometry import corners, cross, dot, frame, normal, sub, unit
from .oracle import OFF

VARIANT = "llvm_ad_rgb"
# the variant of each Dr.Jit backend (rtval bench --backend cuda; the rest of rtval uses LLVM)
VARIANTS = {"llvm": VARIANT, "cuda": "cuda_ad_rgb"}
AOVS = "dd:depth,pp:position,nn:geo_normal,uv:uv"
AOV_CHANNELS = ("dd.T", "pp.X", "pp.Y", "pp.Z", "nn.X", "nn.Y", "nn.Z", "uv.U", "uv.V")
PLANE_EXTENT_FACTOR = 64.0
EPS32 = 2.0 ** -24


def mitsuba(variant: str = VARIANT):
    """Mitsuba in ``variant`` (one of VARIANTS' values; rtval's own by default, whatever an
    earlier benchmark set), with the course plugins registered (mitsuba_ref/integrator.py)."""
    import mitsuba as mi
    if mi.variant() != variant:
        mi.set_variant(variant)
    from .integrator import register
    register(mi)
    return mi


def loaded():
    """Mitsuba for building a scene description (``scene_dict``, the XML): in the variant
    already set if it is one of VARIANTS' (a benchmark's CUDA one), else rtval's.  The
    description is the same in every variant, so building it switches none."""
    import mitsuba as mi
    return mitsuba(mi.variant() if mi.variant() in VARIANTS.values() else VARIANT)


def shape_id(oid: int, kind: str) -> str:
    return f"obj{oid}_{kind}"


def course_id(shape_id_str: str) -> int:
    """'obj3_fplane' -> 3."""
    head = shape_id_str.split("_", 1)[0]
    return int(head[3:])


def kept(table: dict, scene: Scene, key: tuple, make, size: int = 16):
    """``make(scene)``, kept in ``table`` for the last ``size`` keys (the scene's objects'
    tuple, and ``key``: what else ``make`` reads): an entry holds its objects' tuple, so its
    id stays that tuple's; objects in a list are computed each time.  (The references'
    own: rt_core's scene model is not theirs to import.)"""
    if not isinstance(scene.objects, tuple):
        return make(scene)
    k = (id(scene.objects), *key)
    hit = table.get(k)
    if hit is None:
        if len(table) >= size:
            table.clear()
        hit = table[k] = (scene.objects, make(scene))
    return hit[1]


# scene_scale of the scenes asked last: a comparison asks it a few times for each of its
# rays' tracers, the converter and the classifier (~0.1 ms each, thousands in a validate)
_SCALES: dict = {}


def scene_scale(scene: Scene) -> float:
    """The largest distance from the viewpoint to anything bounded in the scene (and the
    window): what a camera ray must reach."""
    return kept(_SCALES, scene, (tuple(scene.viewpoint), tuple(scene.window)), _scene_scale,
                64)


def _scene_scale(scene: Scene) -> float:
    v = scene.viewpoint
    r = math.hypot(*scene.window) / 2 + math.sqrt(dot(v, v))
    return max([r] + [dispatch(_REACH, o.kind)(o, v) for o in scene.objects])


def _far(v, points) -> float:
    """The largest distance from v to the points."""
    return max(math.sqrt(dot(sub(c, v), sub(c, v))) for c in points)


def _quadric_reach(o, v) -> float:
    """Its centre's distance and its largest extent (semi-axis; radius + height)."""
    f = quadric.fields(o)
    size = max(f[1]) if o.kind == "ellipsoid" else float(f[2]) + float(f[3])
    return _far(v, [f[0]]) + float(size)


def _plane_reach(o, v) -> float:
    """An unbounded plane: its point, and the plane's distance from v."""
    q = sub(o.point, v)
    return max(abs(dot(normal(o), q)), math.sqrt(dot(q, q)))


_REACH = {   # the largest distance from a viewpoint v to (a bound of) the object, per kind
    "sphere": lambda o, v: _far(v, [o.center]) + o.radius,
    "disk": lambda o, v: _far(v, [o.center]) + o.radius,
    "torus": lambda o, v: _far(v, [o.center]) + o.major + o.minor,
    "fplane": lambda o, v: _far(v, corners(o)),
    "triangle": lambda o, v: _far(v, convert_planar.points(o)),
    "plane": _plane_reach,
    "tplane": _plane_reach,
    **{k: _quadric_reach for k in quadric.KINDS},
}


def plane_extent(scene: Scene) -> float:
    """Half-size R of the square standing in for an infinite (or tiled) plane.

    Rule: R = 64 × the scene scale.  A camera ray then finds the plane wherever it hits it
    within R of the viewpoint's foot point — i.e. everywhere but at grazing angles beyond
    atan(64) ≈ 89.1° — and the rectangle's float32 vertices put an error of about
    R·2⁻²⁴ ≈ 4e-6·scale on its position (depth error of that size over cos θ)."""
    return PLANE_EXTENT_FACTOR * scene_scale(scene)


def far_clip(scene: Scene) -> float:
    """Far beyond everything: 4 × the largest plane extent / scene scale."""
    has_infinite = any(not KINDS[o.kind].bounded for o in scene.objects)
    return 4.0 * (plane_extent(scene) if has_infinite else scene_scale(scene))


def rectangle_matrix(obj) -> list:
    """4×4 ``to_world`` of the rectangle equivalent to a finite plane (its frame computed
    here from the numbers as written)."""
    w, h = obj.size
    x, y, n = frame(obj)
    c = tuple(obj.point[i] + 0.5 * w * x[i] + 0.5 * h * y[i] for i in range(3))
    return _matrix(x, y, n, c, 0.5 * w, 0.5 * h)


def infinite_matrix(obj, viewpoint, R: float) -> list:
    """A square of half-size R standing in for an infinite or tiled plane, centred on the
    viewpoint's foot point on the plane (a tiled plane keeps its tile axes)."""
    x, y, c = stand_in_frame(obj, viewpoint)
    return _matrix(x, y, normal(obj), c, R, R)


_SHAPES = {   # Mitsuba shape dict per kind
    "sphere": lambda o, v, R, T: {"type": "sphere", "center": list(o.center), "radius": o.radius},
    "fplane": lambda o, v, R, T: {"type": "rectangle", "to_world": T(rectangle_matrix(o))},
    "plane": lambda o, v, R, T: {"type": "rectangle", "to_world": T(infinite_matrix(o, v, R))},
    "tplane": lambda o, v, R, T: {"type": "rectangle", "to_world": T(infinite_matrix(o, v, R))},
    "cylinder": lambda o, v, R, T: cylinder_shape(o),
    # no Mitsuba shape (its sphere forbids non-uniform scale): checked against the oracles only
    "cone": lambda o, v, R, T: None,
    "ellipsoid": lambda o, v, R, T: None,
    # mitsuba_ref/convert_planar.py
    "disk": lambda o, v, R, T: {"type": "disk", "to_world": convert_planar.disk_to_world(o)},
    "triangle": lambda o, v, R, T: convert_planar.triangle_spec(o),
    "torus": lambda o, v, R, T: None,       # Mitsuba has no torus: oracles only
}


def cylinder_shape(o) -> dict:
    """Mitsuba's ``cylinder`` (open, as the course's): p0 the base centre, p1 = p0 + h·â."""
    p0, axis, r, h = quadric.fields(o)
    a = unit(tuple(float(c) for c in axis))
    p0 = [float(c) for c in p0]
    return {"type": "cylinder", "p0": p0, "p1": [c + float(h) * x for c, x in zip(p0, a)],
            "radius": float(r)}


def mitsuba_subset(scene: Scene, keep=lambda kind: True, inside: bool = False):
    """(scene, note): the scene without the objects Mitsuba has no shape for (``oracle_only``)
    and the kinds ``keep`` refuses, for a comparison with Mitsuba; with ``inside``, without
    the spheres that hold the viewpoint too (shaded comparisons: rays from inside them, the
    viewpoint's and others, miss them in the course and not in Mitsuba); the note names what
    was left out ("" when nothing was)."""
    import dataclasses
    gone = [o for o in scene.objects if not keep(o.kind)
            or dispatch(_SHAPES, o.kind)(o, scene.viewpoint, 1.0, lambda m: m) is None]
    held = [o for o in scene.objects if inside and encloses_viewpoint(o, scene.viewpoint)
            and all(o is not g for g in gone)]
    if not gone and not held:
        return scene, ""
    kept = tuple(o for o in scene.objects if all(o is not g for g in gone + held))
    notes = []
    if gone:
        notes.append("left out of this Mitsuba comparison (checked against rtval's oracles "
                     "only): " + ", ".join(f"line {o.line} {o.kind}" for o in gone))
    notes += [f"line {o.line} sphere left out of this comparison: it {INSIDE_NOTE}"
              for o in held]
    return dataclasses.replace(scene, objects=kept), "; ".join(notes)


PROVENANCE = "rtval.provenance"


def planes_note(scene: Scene) -> str:
    """What the scene's infinite and tiled planes stand in as (the XML's comment and
    convert's note on stderr), or "" where it has none."""
    if not any(not KINDS[o.kind].bounded for o in scene.objects):
        return ""
    return (f"infinite and tiled planes: rectangles of half-size {plane_extent(scene):.6g} "
            "(64 x scene scale) around the viewpoint's foot point (Mitsuba has no infinite "
            "plane)")


def xml_provenance(source: dict, setup, sampling: str, mode: str, rules, max_dist) -> dict:
    """What a converted scene came from: ``source``, the scene's own provenance as rtval
    render records it (rt_core/render.py's ``scene_provenance``, handed in by the caller: the
    converter reads no part of the tracer), its ``rtval.scene`` named ``rtval.source_scene``,
    with the camera, the rules and the mode."""
    out = dict(source)
    out["rtval.source_scene"] = out.pop("rtval.scene")
    out.update({"rtval.sampling": sampling, "rtval.resolution": f"{setup.columns}x{setup.rows}",
                "rtval.converted": mode})
    if mode != "sensor":
        out["rtval.rules"] = (rules or Rules()).describe()
    if mode == "shading":
        out["rtval.max_dist"] = f"{max_dist:g}"
    return out


def _comment(text: str) -> str:
    """``text`` as an XML comment: '--' may not stand in one, nor a '-' at its end (XML 1.0;
    Mitsuba's parser lets them pass, ElementTree and xmllint do not), so each hyphen that
    follows a hyphen is spaced off."""
    text = str(text)
    while "--" in text:
        text = text.replace("--", "- -")
    return f"<!-- {text} -->"


def read_provenance(xml_text: str) -> dict:
    """The provenance comment ``scene_xml`` wrote ({} if there is none)."""
    start = xml_text.find("<!-- " + PROVENANCE + " ")
    if start < 0:
        return {}
    end = xml_text.find(" -->", start)
    try:
        return json.loads(xml_text[start + len(PROVENANCE) + 6:end])
    except ValueError:
        return {}


def encloses_viewpoint(obj, viewpoint) -> bool:
    """A sphere that holds the viewpoint (|V − C|² <= r², exactly, on the numbers as
    written): the course takes a sphere's near root only, t > 0, so a ray from the viewpoint
    never hits it (both roots of a ray from inside are not > 0 together with the near one),
    where Mitsuba's sphere returns its exit."""
    if obj.kind != "sphere":
        return False
    q = [written_value(v) - written_value(c) for v, c in zip(viewpoint, obj.center)]
    return sum(x * x for x in q) <= written_value(obj.radius) ** 2


def written_value(v) -> Fraction:
    """A scene number exactly as written (its decimal text where the reader kept it)."""
    text = getattr(v, "text", None)
    return Fraction(Decimal(text)) if text is not None else Fraction(v)


def oracle_only(scene: Scene) -> list:
    """One line per object left out of the Mitsuba scene: no Mitsuba equivalent (compared
    against the oracles only; the ``course`` integrator shades every shape the scene has)."""
    out = []
    for o in scene.objects:
        if dispatch(_SHAPES, o.kind)(o, scene.viewpoint, 1.0, lambda m: m) is None:
            out.append(f"line {o.line}: {o.kind} has no Mitsuba shape; left out of the "
                       "Mitsuba scene (checked against rtval's oracles only)")
    return out


INSIDE_NOTE = ("holds the viewpoint: the course never hits it from there (its near root "
               "only), Mitsuba's sphere would (its exit)")


def inside_notes(scene: Scene, shading: bool) -> list:
    """One line per sphere holding the viewpoint, as ``scene_dict`` treats it: left out of a
    sensor's scene, kept (and differing) in the course image's."""
    return [f"line {o.line}: the sphere {INSIDE_NOTE}: " + (
        "this course image differs from the course's wherever a ray from inside it meets it"
        if shading else "left out of this scene (rays from the viewpoint)")
        for o in scene.objects if encloses_viewpoint(o, scene.viewpoint)]


def stand_in_frame(obj, viewpoint):
    """Axes and centre of the square standing in for an infinite or tiled plane: the tile
    axes (or any in-plane pair) and the viewpoint's foot point on the plane."""
    n = normal(obj)
    x, y = frame(obj)[:2] if obj.kind == "tplane" else _any_frame(n)
    s = dot(n, sub(obj.point, viewpoint))
    return x, y, tuple(viewpoint[i] + s * n[i] for i in range(3))


def _any_frame(n):
    a = (1.0, 0.0, 0.0) if abs(n[0]) < 0.9 else (0.0, 1.0, 0.0)
    x = unit(cross(a, n))
    return x, cross(n, x)


def _matrix(x, y, n, c, sx, sy) -> list:
    return [[sx * x[0], sy * y[0], n[0], c[0]],
            [sx * x[1], sy * y[1], n[1], c[1]],
            [sx * x[2], sy * y[2], n[2], c[2]],
            [0.0, 0.0, 0.0, 1.0]]


@dataclass(frozen=True)
class SensorSetup:
    """The perspective sensor equivalent to the course camera (pixel centres = samples)."""
    fov: float
    ppo_x: float
    ppo_y: float
    near_clip: float
    far_clip: float
    columns: int
    rows: int
    square: bool
    note: str
    facing: int            # -1: looks down -z (viewpoint z > 0); +1: looks up +z (mirrored)


@dataclass(frozen=True)
class _Grid:
    columns: int
    rows: int
    sx: float
    sy: float


def reference_rows(scene, columns: int) -> int:
    """The notes' default row count, int(h/w·columns), computed here rather than by
    rt_core."""
    ww, wh = scene.window
    return int(wh / ww * columns)


def _grid(scene, columns: int, rows: int | None, sampling: str) -> _Grid:
    """The course's sample grid (notes: rows = int(h/w·columns) by default; corner samples
    are ww/(W−1) apart, centre samples ww/W), computed here rather than by rt_core."""
    ww, wh = scene.window
    if rows is None:
        rows = reference_rows(scene, columns)
    least = 2 if sampling == "corners" else 1
    if columns < least or rows < least:
        raise InputError(f"image {columns}x{rows} is too small for {sampling} sampling")
    k = 1 if sampling == "corners" else 0
    return _Grid(columns, rows, ww / (columns - k), wh / (rows - k))


def sensor_setup(scene: Scene, columns: int, rows: int | None, sampling: str = "corners",
                 clip: bool = True) -> SensorSetup:
    """The sensor; ``clip`` False drops the screen clip (near clip ~0: for spheres, which the
    course does not clip)."""
    cam = _grid(scene, columns, rows, sampling)
    vx, vy, vz = scene.viewpoint
    if vz == 0 or not math.isfinite(vz):
        raise InputError(f"{scene.path}: viewpoint z = {vz:g} lies in the window plane; no "
                         "camera can look through the window from there")
    # window whose pixel centres are the samples: W·spacing wide
    ww_c = cam.sx * cam.columns
    fov = math.degrees(2 * math.atan(ww_c / (2 * abs(vz))))
    square = math.isclose(cam.sx, cam.sy, rel_tol=1e-12)
    note = ""
    if not square:
        note = (f"course sample grid is not square ({cam.sx:.9g} x {cam.sy:.9g} world units); "
                "Mitsuba's pixels are square, so its camera samples rows "
                f"{cam.sx:.9g} apart instead of {cam.sy:.9g}: its image is the course image "
                "rescaled vertically. Compare it only with rt_core rendering the same "
                "square-pixel camera (rtval compare does so); same-ray comparisons are exact")
    if not clip:
        return SensorSetup(fov, -vx / ww_c if vz > 0 else vx / ww_c, vy / (cam.rows * cam.sx),
                           1e-6 * abs(vz), far_clip(scene), cam.columns, cam.rows, square, note,
                           -1 if vz > 0 else +1)
    if vz > 0:
        # rays start on the window plane: the near clip is the course's screen clip
        return SensorSetup(fov, -vx / ww_c, vy / (cam.rows * cam.sx), vz, far_clip(scene),
                           cam.columns, cam.rows, square, note, -1)
    # viewpoint behind the window (z < 0), looking toward +z: the screen clip (z > 0 is a
    # miss) is the far clip; any proper camera facing +z sees the course image mirrored in x,
    # so the principal point flips and the reference flips its columns back
    return SensorSetup(fov, vx / ww_c, vy / (cam.rows * cam.sx), 1e-6 * abs(vz), abs(vz),
                       cam.columns, cam.rows, square, note, +1)


def _point_light(light, T) -> dict:
    return {"type": "point", "position": [float(c) for c in light.center],
            "intensity": {"type": "rgb", "value": [float(c) for c in light.emissivity]}}


def _spot_light(light, T) -> dict:
    """Mitsuba's ``spot``: cutoff_angle = the course's half-angle θ, and beam_width = θ
    too, so that the intensity is constant inside the cone and 0 outside, as in the course
    (Mitsuba's falls off as 1/d², the course's diffuse term as 1/d: the shading is an
    approximation, as for point lights)."""
    theta = float(light.theta)
    return {"type": "spot", "cutoff_angle": theta, "beam_width": theta,
            "to_world": T().look_at(origin=[float(c) for c in light.center],
                                    target=[float(c) for c in light.aim],
                                    up=_up(light.center, light.aim)),
            "intensity": {"type": "rgb", "value": [float(c) for c in light.emissivity]}}


def _up(center, aim) -> list:
    """An up vector not parallel to aim − centre."""
    a = [float(x) - float(c) for x, c in zip(aim, center)]
    return [1, 0, 0] if abs(a[1]) > 0.9 * math.sqrt(sum(x * x for x in a)) else [0, 1, 0]


_LIGHTS = {"pointlight": _point_light, "spotlight": _spot_light}


def _mat(m, prefix: str = "") -> dict:
    return {prefix + k: _color(getattr(m, k)) for k in ("ambient", "diffuse", "specular")}


def _color(v) -> list:
    return [float(c) for c in v]


def tile_size(o, rules: Rules) -> tuple:
    """A tiled plane's tile size; with the variant that leaves xdir unprojected
    (``tile_project`` off), u is unit(xdir)·(hit − point) = |p|·u, so the tiles are w/|p|
    wide along the projected axis (|p|: the sine of xdir's angle with the normal)."""
    w, h = o.size
    if rules.tile_project:
        return (float(w), float(h))
    c = dot(unit(o.orient), normal(o))
    return (w / math.sqrt(max(1.0 - c * c, 0.0)), float(h))


def course_material(o, oid: int, rules: Rules, window=(1.0, 1.0)) -> dict:
    """The ``course_material`` BSDF of one object (mitsuba_ref/integrator.py): its MAT, kind,
    a sphere's centre and radius, a cylinder's base centre, unit axis and radius, a plane's
    normal as given (unit) and point, a tiled plane's frame, computed here."""
    b = {"type": "course_material", "kind": o.kind, "course_id": oid, **_mat(o.material)}
    if o.kind == "sphere":
        b["center"], b["radius"] = [float(c) for c in o.center], float(o.radius)
    elif o.kind == "cylinder":              # the axial range is Mitsuba's cylinder's
        p0, axis, r, _ = quadric.fields(o)
        b["center"] = [float(c) for c in p0]
        b["axis"] = list(unit(tuple(float(c) for c in axis)))
        b["radius"] = float(r)
    elif o.kind == "triangle":              # its normal and anchor from the points
        b["normal"] = list(unit(convert_planar.triangle_normal(o)))
        b["point"] = [float(c) for c in convert_planar.points(o)[0]]
    else:
        b["normal"] = list(normal(o))
        b["point"] = [float(c) for c in (o.center if o.kind == "disk" else o.point)]
    if o.kind == "fplane":
        x, y, _ = frame(o)
        b.update({"xdir": list(x), "ydir": list(y),
                  "size": [float(o.size[0]), float(o.size[1]), 0.0]})
    if o.kind == "triangle":
        # uv = the barycentric weights of P2, P3 (H = P1 + u·e1 + v·e2): u = (H − P1)·xdir,
        # v = (H − P1)·ydir with the dual pair xdir = (e2 × N)/|N|², ydir = (N × e1)/|N|²
        P = convert_planar.points(o)
        e1, e2 = sub(P[1], P[0]), sub(P[2], P[0])
        N = cross(e1, e2)
        nn = dot(N, N)
        b.update({"xdir": [c / nn for c in cross(e2, N)], "ydir": [c / nn for c in cross(N, e1)]})
    if o.kind == "disk":                    # uv = the hit's coordinates in the disk's frame
        x, y, _ = convert_planar.disk_frame(o)
        b.update({"xdir": list(x), "ydir": list(y)})
    if o.kind == "tplane":
        x, y, _ = frame(o)
        tw, th = tile_size(o, rules)
        b.update({"xdir": list(x), "ydir": list(y),
                  # (z: the offset the variant adding it first adds to u, along the
                  # projected axis: OFF to |p|·u is OFF/|p| to u)
                  "tile_size": [tw, th, OFF * tw / float(o.size[0])],
                  **_mat(o.background, "background_")})
    if getattr(o, "texture", None) is not None:
        b.update(texture_spec(o, window))
    return b


def _extra(o, name):
    return next(v for k, v in o.extras if k == name)


def sphere_forward(o) -> tuple:
    """A textured sphere's forward direction projected onto the xz plane, unit (s = 0 there):
    sphere_pixmap's field, +z for nw's texsphere."""
    f = [float(c) for c in _extra(o, "forward")] if o.form == "sphere_pixmap" else [0, 0, 1]
    m = math.hypot(f[0], f[2])
    return (f[0] / m, 0.0, f[2] / m)


def textured_sphere(o, T) -> dict:
    """A textured sphere whose Mitsuba uv is the course's (1 − s, t): local z = +y (v =
    acos(d·ŷ)/π = t), local x = f̂, local y = ŷ × f̂ = −ŝ (u = atan2(−d·ŝ, d·f̂)/2π = 1 − s;
    the texture's to_uv flips it back)."""
    fx, _, fz = sphere_forward(o)
    r, c = float(o.radius), [float(v) for v in o.center]
    return {"type": "sphere", "to_world": T([[r * fx, r * fz, 0.0, c[0]],
                                             [0.0, 0.0, r, c[1]],
                                             [r * fz, -r * fx, 0.0, c[2]],
                                             [0.0, 0.0, 0.0, 1.0]])}


def texture_spec(o, window) -> dict:
    """The course_material's texture: a Mitsuba ``bitmap`` of the file's texels (read by
    mitsuba_ref/ppm.py), nearest texel, and the ``to_uv`` that makes the shape's uv the
    course's s, t (README "Textures"): a rectangle's uv is (x/w, y/h) of its frame, so fit
    mode is the identity (clamped), a repeat every (sx, sy) the scale (w/sx, h/sy)
    (repeated); a sphere's (1 − s, t) (``textured_sphere``) flips u."""
    import numpy as np
    from mitsuba_ref.ppm import texels
    mi = loaded()
    bright = 1.0 if o.form in ("texplane", "texsphere") else float(_extra(o, "brightness"))
    if o.kind == "sphere":
        m, wrap = [[-1.0, 0, 0, 1.0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]], "repeat"
    else:
        w, h = (float(c) for c in o.size)
        wrap = "repeat"
        if o.form == "fplanetex":
            sx, sy = (float(c) for c in _extra(o, "texture size"))
        elif _extra(o, "tile mode") == 2:
            sx, sy = (float(c) for c in window)
        else:
            sx, sy, wrap = w, h, "clamp"
        m = [[w / sx, 0, 0, 0], [0, h / sy, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    bitmap = mi.Bitmap(np.ascontiguousarray(texels(o.texture.path), np.float32))
    return {"brightness": bright,
            "texture": {"type": "bitmap", "bitmap": bitmap, "raw": True,
                        "filter_type": "nearest", "wrap_mode": wrap,
                        "to_uv": mi.ScalarTransform4f(m)}}


def course_integrator(scene: Scene, columns: int, rows: int, sampling: str, rules: Rules,
                      max_dist: float) -> dict:
    """The ``course`` integrator: the camera and the rules it shades with."""
    return {"type": "course", "viewpoint": [float(c) for c in scene.viewpoint],
            "window_width": float(scene.window[0]), "window_height": float(scene.window[1]),
            "columns": int(columns), "rows": int(rows),
            "sampling": "centres" if sampling.startswith("cent") else "corners",
            "row_shift": 1 if rules.rows == "shifted" else 0,
            "screen_clip": rules.screen_clip, "t_min": float(rules.t_min),
            "clip_spheres": bool(rules.clip_spheres), "reflect": rules.reflect,
            "tile_add_first": bool(rules.tile_add_first), "max_dist": float(max_dist)}


def scene_dict(scene: Scene, columns: int, rows: int | None = None, sampling: str = "corners",
               shading: bool = False, integrator: bool = True, only=None,
               clip: bool = True, rules: Rules | None = None,
               max_dist: float = DEFAULT_MAX_DIST, aovs: bool = False,
               meshes: bool = True, from_viewpoint: bool = False) -> dict:
    """The Mitsuba 3 scene as a dict for ``mi.load_dict(d, optimize=False)``.

    ``only``: a set of object kinds to include (default all); ``clip``: whether the sensor
    applies the course's screen clip (see ``sensor_setup``).  ``shading``: each shape gets
    its ``course_material``, the lights become emitters, and the integrator is ``course``
    (the course image, ``rules`` and ``max_dist`` as in ``rtval render``).  ``aovs``: the same,
    with the integrator in its AOV mode (rtval's geometry channels of the primary rays).
    ``from_viewpoint``: the scene is for rays from the viewpoint only (a primary-ray
    comparison, a sensor's scene): spheres that hold the viewpoint are left out
    (``encloses_viewpoint``); rays from surfaces (shadow, reflection) keep them."""
    mi = loaded()
    shading = shading or aovs
    rules = Rules() if rules is None else rules
    T = mi.ScalarTransform4f
    R = plane_extent(scene)
    d = {"type": "scene"}
    for oid, o in enumerate(scene.objects):
        if only is not None and o.kind not in only:
            continue
        sid = shape_id(oid, o.kind)
        if from_viewpoint and not shading and encloses_viewpoint(o, scene.viewpoint):
            continue                # rays from the viewpoint: invisible (INSIDE_NOTE)
        shape = dispatch(_SHAPES, o.kind)(o, scene.viewpoint, R, T)
        if shape is None:                   # oracle_only() says so
            continue
        shape["id"] = sid
        if shading:
            if o.kind == "sphere" and getattr(o, "texture", None) is not None:
                shape = dict(textured_sphere(o, T), id=sid)
            shape["bsdf"] = course_material(o, oid, rules, scene.window)
        d[sid] = shape
    if shading:
        for i, light in enumerate(scene.lights):
            d[f"light{i}"] = dispatch(_LIGHTS, light.kind)(light, T)
    s = sensor_setup(scene, columns, rows, sampling, clip)
    vx, vy, vz = scene.viewpoint
    d["sensor"] = {
        "type": "perspective", "fov_axis": "x", "fov": s.fov,
        "principal_point_offset_x": s.ppo_x, "principal_point_offset_y": s.ppo_y,
        "near_clip": s.near_clip, "far_clip": s.far_clip,
        "to_world": T().look_at(origin=[vx, vy, vz], target=[vx, vy, vz + s.facing],
                                up=[0, 1, 0]),
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        "film": {"type": "hdrfilm", "width": s.columns, "height": s.rows,
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }
    if integrator:
        d["integrator"] = (course_integrator(scene, columns, s.rows, sampling, rules, max_dist)
                           if shading else {"type": "aov", "aovs": AOVS})
        if aovs:
            d["integrator"]["aovs"] = True
    _check_float32(scene, d)
    # triangles: mi.Mesh objects (``meshes`` False: specs whose PLY files scene_xml writes)
    return convert_planar.realize(d, mi) if meshes else d


F32_MAX = 3.4028234663852886e38


def _numbers(v):
    """Every number in a scene-dict value (matrices, vectors, nested dicts)."""
    if isinstance(v, bool) or isinstance(v, str):
        return
    if isinstance(v, (int, float)):
        yield float(v)
    elif isinstance(v, dict):
        for x in v.values():
            yield from _numbers(x)
    elif isinstance(v, (list, tuple)):
        for x in v:
            yield from _numbers(x)
    elif hasattr(v, "matrix"):
        m = v.matrix
        yield from (float(m[i][j]) for i in range(4) for j in range(4))


def _check_float32(scene: Scene, d: dict) -> None:
    """Mitsuba works in float32: a number beyond its range would become inf or nan in the
    scene (and in the XML), so refuse it, naming the object."""
    for key, value in d.items():
        big = max((abs(x) for x in _numbers(value)), default=0.0)
        if not big <= F32_MAX:          # also catches nan
            where = ""
            if key.startswith("obj"):
                o = scene.objects[course_id(key)]
                where = f"{o.kind} (line {o.line}): "
            elif key.startswith("light") and key[5:].isdigit():
                li = scene.lights[int(key[5:])]
                where = f"{li.kind} (line {li.line}): "
            raise InputError(f"{scene.path}: {where}{key} needs the number {big:.3g}, beyond "
                             "the float32 range of Mitsuba's llvm_ad_rgb variant; this scene "
                             "can be rendered by rt_core in f64 but not converted")
    # an infinite plane's stand-in spans 64 × the scene's extent: one far object makes it so
    # large that its float32 hit points are coarser than the window (a sphere 1e20 away put
    # them ~1e15 off, every plane pixel then 'explained' by the clip's bound)
    if any(not KINDS[o.kind].bounded for o in scene.objects):
        # (over 1024 windows: rtval stability's far viewpoints, whose stand-ins reach a grain
        # of a few windows, are compared, their bounds taking it into account)
        grain = plane_extent(scene) * 2.0 ** -24
        if not grain <= 1024 * min(scene.window):
            raise InputError(f"{scene.path}: the rectangles standing in for its infinite "
                             f"planes would span {plane_extent(scene):.3g} (64 x the scene's "
                             f"extent), too large for Mitsuba's float32 to place a hit within "
                             f"1024 windows; this scene can be rendered by rt_core in f64 but "
                             "not converted")
    # Mitsuba's sphere test forms |o − c|² − r² in float32 (llvm_ad_rgb), o the ray's
    # origin: from the viewpoint, beyond the range it is inf, and every ray misses (a sphere
    # 3e20 away: no hit, where rt_core f64 sees the plane in front of it)
    vp = scene.viewpoint
    for o in scene.objects:
        if o.kind != "sphere":
            continue
        reach = math.dist(o.center, vp) + o.radius
        if not reach * reach <= F32_MAX / 16:
            raise InputError(f"{scene.path}: sphere (line {o.line}): its test from the "
                             f"viewpoint squares {reach:.3g}, beyond the float32 range of "
                             "Mitsuba's llvm_ad_rgb variant (every ray would miss it); this "
                             "scene can be rendered by rt_core in f64 but not converted")


# --- XML ---------------------------------------------------------------------------------------

def _num(v: float) -> str:
    return repr(float(v))


def _xml_value(name: str, v, indent: str) -> list:
    mi = loaded()
    if isinstance(v, bool):
        return [f'{indent}<boolean name="{name}" value="{str(v).lower()}"/>']
    if isinstance(v, int):
        return [f'{indent}<integer name="{name}" value="{v}"/>']
    if isinstance(v, float):
        return [f'{indent}<float name="{name}" value="{_num(v)}"/>']
    if isinstance(v, str):
        return [f'{indent}<string name="{name}" value={quoteattr(v)}/>']
    if isinstance(v, list) and len(v) == 3:
        tag = "point" if name in POINTS else "rgb" if name == "value" else "vector"
        return [f'{indent}<{tag} name="{name}" value="{", ".join(_num(c) for c in v)}"/>']
    if isinstance(v, (mi.ScalarTransform4f, mi.ScalarTransform4d)):
        m = v.matrix
        vals = " ".join(_num(m[i][j]) for i in range(4) for j in range(4))
        return [f'{indent}<transform name="{name}">', f'{indent}    <matrix value="{vals}"/>',
                f'{indent}</transform>']
    if isinstance(v, dict):
        return _xml_object(v, indent, name)
    raise TypeError(f"cannot write {name}={v!r} as Mitsuba XML")


TAGS = {"rectangle": "shape", "sphere": "shape", "cylinder": "shape", "disk": "shape", "ply": "shape", "perspective": "sensor", "stratified":
        "sampler", "hdrfilm": "film", "box": "rfilter", "aov": "integrator", "path": "integrator",
        "course": "integrator", "course_material": "bsdf", "diffuse": "bsdf", "point": "emitter",
        "spot": "emitter", "rgb": "rgb", "bitmap": "texture"}
POINTS = ("center", "position", "viewpoint", "point", "p0", "p1")


def _xml_object(d: dict, indent: str, name: str | None = None) -> list:
    tag = TAGS[d["type"]]
    if tag == "rgb":
        return [f'{indent}<rgb name="{name}" value="{", ".join(_num(c) for c in d["value"])}"/>']
    attrs = f' type="{d["type"]}"' + (f' id={quoteattr(d["id"])}' if "id" in d else "")
    if name and tag not in ("shape", "sensor", "sampler", "film", "rfilter", "integrator",
                            "bsdf", "emitter"):
        attrs += f' name="{name}"'
    lines = [f"{indent}<{tag}{attrs}>"]
    for k, v in d.items():
        if k not in ("type", "id"):
            lines += _xml_value(k, v, indent + "    ")
    return lines + [f"{indent}</{tag}>"]


def _texture_files(d: dict, stem: str) -> dict:
    """Each course_material's in-memory bitmap replaced by a file name beside the XML: name ->
    the mi.Bitmap to write there."""
    out = {}
    for key, shape in d.items():
        tex = shape.get("bsdf", {}).get("texture") if isinstance(shape, dict) else None
        if tex is not None and "bitmap" in tex:
            name = f"{stem}.{key}_texture.exr"
            out[name] = tex.pop("bitmap")
            tex["filename"] = name
    return out


def scene_xml(scene: Scene, columns: int, rows: int | None = None, sampling: str = "corners",
              shading: bool = False, rules: Rules | None = None,
              max_dist: float = DEFAULT_MAX_DIST, aovs: bool = False,
              files: dict | None = None, stem: str = "scene",
              source: dict | None = None) -> str:
    """The same scene as ``scene_dict``, as Mitsuba 3 XML (``mi.load_file`` accepts it once
    mitsuba_ref has registered its plugins: ``rtval render --mitsuba``).  Triangles refer
    to PLY files ``<stem>.obj<id>_triangle.ply`` beside the XML, and textures to EXR files
    ``<stem>.obj<id>_texture.exr`` (their texels, float32: a PPM's maxval need not be 255),
    added to ``files`` (name -> text, or the texture's mi.Bitmap) for the caller to write.
    ``source`` is the scene's provenance (``xml_provenance``); without it the XML records the
    scene's path only."""
    d = scene_dict(scene, columns, rows, sampling, shading, rules=rules, max_dist=max_dist,
                   aovs=aovs, meshes=False, from_viewpoint=True)
    plys = {**convert_planar.ply_files(d, stem), **_texture_files(d, stem)}
    if plys and files is None:
        raise ValueError("this scene has triangles or textures: pass files= to receive the "
                         "files they refer to")
    if files is not None:
        files.update(plys)
    s = sensor_setup(scene, columns, rows, sampling)
    mode = "aovs" if aovs else "shading" if shading else "sensor"
    prov = xml_provenance(source or {"rtval.scene": scene.path}, s, sampling, mode, rules,
                          max_dist)
    lines = ['<?xml version="1.0" encoding="utf-8"?>',
             _comment(f"rtval convert: {scene.path} ({columns}x{s.rows}, {sampling} "
                      "sampling)"),
             # (machine-readable, for rtval render --mitsuba's outputs; '--' may not stand
             # in a comment, so its second '-' is a JSON escape)
             "<!-- " + PROVENANCE + " " +
             json.dumps(prov, sort_keys=True).replace("--", "-\\u002d") + " -->"]
    if (planes := planes_note(scene)):
        lines.append(_comment(planes))
    # (how to load it: a review's own script rendered another image with Mitsuba's
    # optimize on, and expected the film it edited to be used)
    load = ("load it in Python with mi.set_variant('llvm_ad_rgb'), import mitsuba_ref, then "
            "mi.load_file(path, optimize=False): Mitsuba's optimize, on by default, merges "
            "and reorders the shapes, so an exact tie between two objects goes to another; "
            f"it renders the course's camera, {columns}x{s.rows} {sampling}, whatever "
            "sensor, film or spp is given")
    if aovs:
        lines.append(_comment("AOVs (rtval convert's aovs option): the 'course' integrator in "
                              "its AOV mode: rtval's geometry channels (hit.mask, depth.Z, "
                              "object.id, normal, position, uv); write them to an EXR with "
                              "rtval render and its mitsuba option, or " + load))
    elif shading:
        lines.append(_comment("the course image (rtval convert's shading option): the 'course' "
                              "integrator and each shape's 'course_material' (plugins of "
                              "rtval's mitsuba_ref): render with rtval render and its mitsuba "
                              "option, or " + load))
    if s.note and mode == "sensor":     # (the course integrator samples the course's grid)
        lines.append(_comment(f"WARNING: {s.note}"))
    lines += [_comment(note) for note in oracle_only(scene) + scene.stand_ins()
              + inside_notes(scene, shading or aovs)]
    lines.append('<scene version="3.0.0">')
    for k, v in d.items():
        if k != "type":
            lines += _xml_object(v, "    ")
    lines.append("</scene>")
    return "\n".join(lines) + "\n"
