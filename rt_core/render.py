"""Whole-image renders: primary-ray geometry AOVs and the shaded image as numpy arrays, their
provenance, and EXR."""
from __future__ import annotations

import functools
import hashlib
import os
import platform
import subprocess
from importlib import metadata

import drjit as dr
import numpy as np

from . import accel, backend as backends
from .camera import Camera, make_camera, primary_directions
from .exrio import DEFAULT_COMPRESSION, write_exr
from .rules import Rules
from .scene import Scene
from . import shading
from .shading import DEFAULT_MAX_DIST
from .tracer import closest_hit, position, prepare, surface

GEOMETRY_CHANNELS = ("hit.mask", "depth.Z", "object.id", "normal.X", "normal.Y", "normal.Z",
                     "position.X", "position.Y", "position.Z", "uv.U", "uv.V")
DIRECTION_CHANNELS = ("direction.X", "direction.Y", "direction.Z")
MISS_CONVENTION = ("miss: hit.mask=0, depth.Z=0, object.id=-1, normal/position/uv=0; "
                   "depth.Z = Euclidean distance from the viewpoint")


def geometry_channels(ks, d, t, oid, hit, normal, u, v) -> dict:
    """The GEOMETRY_CHANNELS of primary-ray hits, as lazy Dr.Jit arrays."""
    F = ks.T.Float
    pos = position(ks, d, t, hit)
    return {"hit.mask": dr.select(hit, F(1), F(0)), "depth.Z": t, "object.id": F(oid),
            "normal.X": normal.x, "normal.Y": normal.y, "normal.Z": normal.z,
            "position.X": pos.x, "position.Y": pos.y, "position.Z": pos.z,
            "uv.U": u, "uv.V": v}


def _empty_geometry(T, n: int) -> dict:
    z = dr.zeros(T.Float, n)
    out = {name: z for name in GEOMETRY_CHANNELS}
    out["object.id"] = z - 1
    return out


# float32 camera rays whose closest hits loop (accel.camera_loops) get their directions
# evaluated first, by a kernel of their own, and the trace reads them.  Fused into the
# trace kernel, each packet's bin lookup waited for the whole direction (a division, a
# square root) before its short loop could start, which costs more than writing and
# reading them (1920 columns, same process, median of 11, closest hits: 64 spheres 7.64
# -> 5.82 ms, 1024 spheres 10.86 -> 8.03, 4096 13.13 -> 9.48, 64 finite planes 11.05 ->
# 9.86).  float64 keeps them fused and finds the bins by the pixels' window offsets
# instead (tracer.BIN_BY_OFFSETS: 0.90-0.98 of the evaluated rays' time, whose arrays are
# twice float32's); unrolled scenes, where it gains little, keep them fused.
EVAL_LOOPED_DIRECTIONS = True


@backends.traced
def camera_rays(ks, cam: Camera):
    """The camera's unit ray directions for ``ks``'s kernels (``primary_directions``),
    evaluated where float32 camera rays loop (EVAL_LOOPED_DIRECTIONS)."""
    d = primary_directions(ks.scene, cam, ks.T)
    if EVAL_LOOPED_DIRECTIONS and ks.T.precision == "f32" and ks.scene.objects and \
            accel.camera_loops(ks):
        dr.eval(d)
    return d


@backends.traced
def trace_geometry(scene: Scene, cam: Camera, T: backends.Types, rules: Rules = Rules(),
                   log=None, directions: bool = False):
    """Dr.Jit arrays (flat, image order) of the primary-ray geometry AOVs, evaluated.
    ``directions``: also the rays' unit directions as traced (DIRECTION_CHANNELS)."""
    ks = prepare(scene, T)
    d = camera_rays(ks, cam)
    if not scene.objects:
        out = _empty_geometry(T, cam.size)
    else:
        t, oid, hit = closest_hit(ks, d, None, rules, cam=cam)
        normal, u, v = surface(ks, d, t, oid, hit)
        out = geometry_channels(ks, d, t, oid, hit, normal, u, v)
    if directions:
        out.update(zip(DIRECTION_CHANNELS, (d.x, d.y, d.z)))
    dr.eval(*out.values())
    if log is not None:
        log.mark("hit", "primary", 0, cam.size)
    return out


@backends.traced
def render_image(scene: Scene, cam: Camera, T: backends.Types, rules: Rules = Rules(), *,
                 geometry: bool = True, shade: bool = False,
                 max_dist: float = DEFAULT_MAX_DIST, log=None, record: int = 0):
    """One render: the geometry channels (``geometry``) and/or the shaded image (``shade``:
    channels 'R', 'G', 'B', the unclamped intensity) as (rows, columns) numpy arrays, row 0
    the top.  Geometry only skips shading entirely.  Returns (images, ShadeResult or None)."""
    if not shade:
        return to_images(trace_geometry(scene, cam, T, rules, log), cam), None
    ks = prepare(scene, T)
    d = camera_rays(ks, cam)
    extra = (lambda *a: geometry_channels(ks, d, *a)) if geometry else None
    res = shading.shade(ks, d, rules, max_dist, log=log, extra=extra, record=record, cam=cam)
    flat = dict(res.extra) if geometry else {}
    if geometry and not scene.objects:
        flat = _empty_geometry(T, cam.size)
    flat.update({"R": res.rgb.x, "G": res.rgb.y, "B": res.rgb.z})
    return to_images(flat, cam), res


def to_images(flat: dict, cam: Camera) -> dict:
    """Flat Dr.Jit arrays -> (rows, columns) numpy arrays, row 0 the top of the image."""
    return {k: np.asarray(v.numpy()).reshape(cam.tile_rows, cam.columns)
            for k, v in flat.items()}


def render_geometry(scene: Scene, columns: int, rows: int | None = None, precision: str = "f32",
                    backend: str = "llvm", sampling: str = "corners",
                    rules: Rules = Rules()) -> dict:
    """Geometry AOVs of the primary rays as numpy arrays (rows, columns), row 0 = top.

    Keys: GEOMETRY_CHANNELS. Arrays are float32 or float64 per ``precision``."""
    T = backends.types(precision, backend)
    cam = make_camera(scene, columns, rows, sampling, rules)
    return to_images(trace_geometry(scene, cam, T, rules), cam)


def nonfinite_by_channel(images: dict, as_float32: bool = True) -> dict:
    """Each channel's count of values that are not finite as written: an EXR holds float32
    (a float64 value beyond float32's range becomes inf there); ``as_float32=False``: as
    computed, for the 8-bit images, which hold a finite intensity beyond 1 as 255 (a
    review: an f64 --ppm render of a 3e38 light said '125 NON-FINITE values', exit 1, of a
    correct image)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return {k: int(np.count_nonzero(~np.isfinite(np.asarray(a, np.float32) if as_float32
                                                      else np.asarray(a))))
                for k, a in images.items()}


def nonfinite_count(images: dict, as_float32: bool = True) -> int:
    """The total of ``nonfinite_by_channel``."""
    return sum(nonfinite_by_channel(images, as_float32).values())


@functools.lru_cache(maxsize=None)
def versions() -> dict:
    """Versions of Python and the packages that made an output, and rtval's git commit when
    it runs from a checkout ('+dirty' with uncommitted changes)."""
    out = {"python": platform.python_version()}
    for pkg in ("rtval", "drjit", "mitsuba", "numpy", "OpenEXR"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        git = lambda *a: subprocess.run(["git", "-C", repo, *a], capture_output=True,
                                        text=True, timeout=5).stdout.strip()
        commit = git("rev-parse", "--short=12", "HEAD")
        if commit:
            out["commit"] = commit + ("+dirty" if git("status", "--porcelain", "-uno") else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return dict(out)


def provenance(scene: Scene, cam: Camera, precision: str, backend_name: str, rules: Rules,
               **extra) -> dict:
    """Header attributes recording what produced an output."""
    attrs = scene_provenance(scene)
    attrs.update({
        "rtval.precision": precision,
        "rtval.backend": backend_name,
        "rtval.sampling": cam.sampling,
        "rtval.resolution": f"{cam.columns}x{cam.rows}",
        "rtval.rules": rules.describe(),
        "rtval.miss": MISS_CONVENTION,
    })
    attrs.update({f"rtval.{k}": str(v) for k, v in extra.items()})
    return attrs


def scene_provenance(scene: Scene) -> dict:
    """The part of an output's provenance that is the scene's: path, sha256, dialect, the
    stand-ins, extra fields and textures, and the versions that read it (also rtval
    convert's, mitsuba_ref/convert.py)."""
    attrs = {
        "rtval.scene": os.path.abspath(scene.path) if scene.path != "<memory>" else scene.path,
        "rtval.scene_sha256": scene.sha256 or hashlib.sha256(repr(scene).encode()).hexdigest(),
        "rtval.dialect": scene.dialect,
        "rtval.versions": " ".join(f"{k}={v}" for k, v in versions().items()),
    }
    stand_ins, extras = scene.stand_ins(), extras_text(scene)
    if stand_ins:
        attrs["rtval.stand_ins"] = "; ".join(stand_ins)
    if extras:
        attrs["rtval.extras"] = extras
    from .textures import provenance_text
    textures = provenance_text(scene)
    if textures:
        attrs["rtval.textures"] = textures
    return attrs


def extras_text(scene: Scene) -> str:
    """The fields the scene's forms and header flags add (shader indices, texture names,
    refraction indices, ...), recorded as read: ``line 4 pplane: shader=2; ...``."""
    def show(v):
        if isinstance(v, tuple):
            return " ".join(show(c) for c in v)
        return getattr(v, "text", None) or (v if isinstance(v, str) else f"{v:g}")
    parts = [f"line {o.line} {o.form or o.kind}: "
             + ", ".join(f"{k}={show(v)}" for k, v in o.extras)
             for o in scene.objects if o.extras]
    if scene.flags:
        parts.insert(0, "header flags " + " ".join(map(str, scene.flags)))
    return "; ".join(parts)


def write_images(path: str, images: dict, attrs: dict,
                 compression: str = DEFAULT_COMPRESSION) -> None:
    """Write AOVs as float32 EXR (atomically), recording the count of non-finite values."""
    attrs = dict(attrs, **{"rtval.nonfinite": str(nonfinite_count(images))})
    write_exr(path, images, attrs, compression)


# a tile's rays: bounded working memory (the kernels' arrays) whatever the image size
TILE_PIXELS = 1 << 21      # 1920×1080 is one band


@backends.traced
def render_tiled(scene: Scene, cam: Camera, T: backends.Types, rules: Rules = Rules(), *,
                 tile_pixels: int = TILE_PIXELS, geometry: bool = True, shade: bool = False,
                 max_dist: float = DEFAULT_MAX_DIST, log=None, progress=None):
    """``render_image`` band by band of whole rows (``Camera.tiles``), each band's arrays
    copied into the image's: memory grows with the outputs only, not with the kernels'
    working arrays.  Every ray is traced as in one whole-image render (the same offsets,
    the same exact decisions), so the images are identical.  Geometry channels are kept as
    float32 (what the EXR holds); R, G, B in the render's precision (the 8-bit image
    quantizes them).  Returns (images, ShadeResult without arrays, or None)."""
    images, summary = {}, None
    for tile in cam.tiles(tile_pixels):
        part, res = render_image(scene, tile, T, rules, geometry=geometry, shade=shade,
                                 max_dist=max_dist, log=log)
        for name, a in part.items():
            if name not in images:
                dtype = a.dtype if name in "RGB" else np.float32
                images[name] = np.empty((cam.rows, cam.columns), dtype)
            # (a float64 value beyond float32 becomes inf: counted and said by the caller,
            # not numpy's warning with its source line on stderr, a review)
            with np.errstate(over="ignore"):
                images[name][tile.row0:tile.row0 + tile.tile_rows] = a
        if res is not None:
            summary = summary or shading.ShadeResult(rgb=None)
            summary.bounces = max(summary.bounces, res.bounces)
            summary.capped = summary.capped or res.capped
            summary.left_active += res.left_active
        del part, res
        if progress is not None:
            progress(tile.row0 + tile.tile_rows, cam.rows)
    return images, summary
