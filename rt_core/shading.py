"""The course's shading (notes, "Shading"), vectorized over the whole image with Dr.Jit.

For the closest hit H on object O, reached after ``total_dist`` along the ray's path::

    I  = ambient(O) + Σ_lights [c > 0, unshadowed] diffuse(O) ⊙ E · c / d     (1/d, not 1/d²)
    I /= total_dist
    I += specular(O) ⊙ trace(H, reflect(dir, N), total_dist, skip=O)   if total_dist < MAX_DIST

with D = L − H, d = |D|, c = unit(D)·N; a light is shadowed when any object other than O is hit
along unit(D) closer than d (``tracer.occluded``: same hit functions, same rules).  N is the
plane normal as given (never flipped: the back of a plane gets ambient only) or the outward
sphere normal.  A tiled plane takes its foreground MAT where floor(OFF + u/w) + floor(OFF + v/h)
is odd (u, v: its ``lasthit``), else its background MAT.

The recursion is unrolled into bounces: pixel = Σ_k (Π_{j<k} specular_j) ⊙ I_k.  Each bounce is
a wavefront of the rays still active; after it, ``dr.compress`` keeps only the rays that go on,
so deep mirror paths cost only their own pixels.  A bounce is one kernel (one evaluation):
closest hit, surface, material, one shadow ray per light from each hit that faces it (only
those lanes trace: ``tracer.occluded``'s ``active``), the division, the sum into the image and
the reflection rays; nothing in between goes through memory (as separate passes, one per light,
it was 2.5 times slower at a few objects).  What a scene does not need is not in the kernel:
no lights, no shadow rays; no specular anywhere, no reflection bounces.  Every scene number
enters kernels as opaque data, so scenes that differ only in numbers reuse the compiled kernels.
With ``max_bounces=1`` (``rtval bench --shaded``) the one reflection bounce's rays are traced
masked in the primary kernel instead, and only those that hit go through memory, to a second
kernel that shades them (``_one_bounce``): the same numbers.

Everything is relative to the viewpoint, as in the tracer: ray origins ``o``, hit points, light
positions.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace

import drjit as dr
import numpy as np

from .backend import traced
from .rules import Rules
from .scene import sub, unit
from .kinds import KIND_CODE
from .shapes import opaque3
from . import accel
from .accel import device_array, packet_type
from .jitlog import NullLog
from .textures import MODE_CODE, Texture
from .tracer import KernelScene, closest_hit, occluded, shadow_cells, surface, widened

# Path length at which reflection stops (the notes' MAX_DIST; the course programs used 20 to
# 50000).  1000 is the keyword-dialect course program's value (rocketman768/ClemsonRaytracer,
# ray.c) and, measured at 96 columns, leaves the 8-bit image of every supported course scene
# with specular surfaces exactly as at 50000 (at 100 two pixels of rm768__hisworld change, at
# 20 hundreds in several scenes), while two facing mirrors (scenes/shade_mirrors.txt) stop
# after 69 bounces instead of 3470 (6 pixels differ).
DEFAULT_MAX_DIST = 1000.0
TILE_OFF = 10000.0          # the notes' tile-parity offset (even: no effect unless added first)
# Safety cap on reflection bounces.  Each bounce adds its t > 0 to total_dist, so the loop
# normally ends at MAX_DIST; but t has no lower bound (a grazing corner of two mirrors, or a
# float32 total_dist that stops growing once t < ulp(total_dist)/2), so this cap guarantees
# termination.  Reaching it is reported (ShadeResult.capped), never silent.
MAX_BOUNCES = 10_000
# With max_bounces = 1, trace the one reflection bounce's rays in the primary rays' kernel
# (``_one_bounce``) rather than as a compacted wavefront (tests compare the two)
FUSE_ONE_BOUNCE = True
# Every light's light-bin cells looked up before the first light's shadow rays are
# searched (tracer.shadow_cells)
PREFETCH_CELLS = True
# The reflection rays run their bounces in one kernel (``_tail``) instead of one compacted
# wavefront a bounce (tests compare the two); the bounces ``record`` keeps stay wavefronts.
# Where their closest hits walk a BVH or bins (many objects), a bounce of more than
# TAIL_FRACTION of the pixels stays a wavefront: the lanes that stop early idle in the
# loop's packets, and a long walk makes that cost more than a bounce's launch and
# compaction.  Measured (the bench's shaded scenes, all bounces,
# and two mirror scenes; 1920 columns, f32; CPU time of the image over the wavefront's,
# median of 5): 16 spheres 0.50, scenes/shade_mirrors.txt 0.37, course sgw__spec3 0.40;
# with this rule 256 spheres 0.79, fplanes 0.74, mixed 0.72, 4096 spheres 0.99, mixed 0.92
# (the tail from the first reflection bounce at 4096 spheres: 1.06-1.10)
TAIL = True
TAIL_FRACTION = 1 / 16


@dataclass
class ShadeResult:
    """Unclamped intensity per pixel (flat Array3, image order) and how the render went."""
    rgb: object
    bounces: int = 0            # reflection bounces traced (0: primary rays only)
    capped: bool = False        # stopped by the bounce cap with rays still active
    left_active: int = 0        # rays that would have gone on when the cap stopped them
    extra: dict = field(default_factory=dict)      # evaluated primary-pass extras
    records: list = field(default_factory=list)    # per recorded bounce: numpy arrays


def _spot(T, light):
    """(unit axis, cos θ) of a spotlight as kernel constants (the axis from the numbers as
    written, in float64 on the host, rounded once); None for a point light."""
    if light.kind != "spotlight":
        return None
    a = [float(x) - float(c) for x, c in zip(light.aim, light.center)]
    n = math.sqrt(sum(x * x for x in a))
    return (opaque3(T.Array3, tuple(x / n for x in a)),
            dr.opaque(T.Float, math.cos(math.radians(float(light.theta)))))


def any_specular(scene) -> bool:
    """Does any MAT of the scene (tiled-plane backgrounds included) reflect?"""
    mats = [o.material for o in scene.objects] + \
           [o.background for o in scene.objects if o.kind == "tplane"]
    return any(c != 0 for m in mats for c in m.specular)


def _material_tables(ks: KernelScene, rules: Rules = Rules()):
    """Per-object MAT tables: rows 0..n-1 foreground, n..2n-1 background (a copy of the
    foreground for every kind but the tiled plane), plus tile sizes (1 for the others).
    Built once per KernelScene and tile rule (the only rule they depend on): a render, a
    benchmark's calls and a rule sweep's renders of one scene share them (6.5 ms a call at
    4096 objects)."""
    cache = ks.__dict__.setdefault("_materials", {})
    if rules.tile_project not in cache:
        cache[rules.tile_project] = _build_material_tables(ks, rules)
    return cache[rules.tile_project]


def _build_material_tables(ks: KernelScene, rules: Rules):
    T, objs = ks.T, ks.scene.objects
    bg = [o.background if o.kind == "tplane" else o.material for o in objs]
    mats = [o.material for o in objs] + bg
    col = lambda name: T.Array3(*([getattr(m, name)[i] for m in mats] for i in range(3)))
    size = [_tile_size(o, rules) if o.kind == "tplane" else (1.0, 1.0) for o in objs]
    # the offset added first (a variant) is OFF to |p|·u, so OFF/|p| to u: w'/w of it
    off = [TILE_OFF * s[0] / o.size[0] if o.kind == "tplane" else TILE_OFF
           for s, o in zip(size, objs)]
    tables = {"ambient": col("ambient"), "diffuse": col("diffuse"), "specular": col("specular"),
              "tile_w": T.Float([s[0] for s in size]), "tile_h": T.Float([s[1] for s in size]),
              "tile_off": T.Float(off)}
    tex = [getattr(o, "texture", None) for o in objs]
    if any(t is not None for t in tex):
        tables.update(_texture_tables(T, tex))
    dr.make_opaque(*tables.values())        # data, not literals, even for one object
    return tables


def _texture_tables(T, tex: list) -> dict:
    """Per-object texture parameters (mode 0: none) and every texture's texels, one flat
    Array3 (texture k from its offset, row by row)."""
    none = Texture("", "", "", 1, 1, "fit")
    ts = [t or none for t in tex]
    offs, n = [], 0
    for t in tex:
        offs.append(n)
        n += t.width * t.height if t is not None else 0
    flat = np.concatenate([t.texels.reshape(-1, 3) for t in tex if t is not None])
    vec = lambda name: T.Array3(*([getattr(t, name)[i] for t in ts] for i in range(3)))
    return {"tex_mode": T.UInt32([MODE_CODE[t.mode] if t is not None else 0 for t in tex]),
            "tex_off": T.UInt32(offs),
            "tex_w": T.UInt32([t.width for t in ts]), "tex_h": T.UInt32([t.height for t in ts]),
            "tex_sx": T.Float([t.scale[0] for t in ts]),
            "tex_sy": T.Float([t.scale[1] for t in ts]),
            "tex_b": T.Float([t.brightness for t in ts]),
            "tex_fwd": vec("forward"), "tex_side": vec("side"),
            "texels": T.Array3(*(device_array(T.Float, flat[:, i]) for i in range(3)))}


def _texel(T, x, size, wrap):
    """Nearest texel index along one axis: floor(x·size), x wrapped into [0, 1) first
    (``wrap``) or not; clamped to 0..size−1 either way."""
    x = dr.select(wrap, x - dr.floor(x), x)
    n = T.Float(size)
    i = dr.clip(dr.floor(x * n), 0, n - 1)
    return T.UInt32(i)


def _texture_ambient(ks: KernelScene, tables: dict, idx, hit, u, v, normal, amb):
    """The ambient reflectivity of textured objects: brightness × texel at (s, t)
    (rt_core/textures.py), the MAT's elsewhere."""
    T = ks.T
    F = T.Float
    g = lambda k, t=F: dr.gather(t, tables[k], idx, hit)
    mode = g("tex_mode", T.UInt32)
    on = hit & (mode != 0)
    sphere = mode == MODE_CODE["sphere"]
    # planes: frame coordinates over the scale; spheres: longitude from the forward vector
    # towards the side vector, latitude from +y (d = the outward unit normal = unit(H − c))
    a = dr.dot(normal, g("tex_side", T.Array3))
    b = dr.dot(normal, g("tex_fwd", T.Array3))
    lon = dr.atan2(a, b) * (0.5 / math.pi)
    lat = dr.acos(dr.clip(normal.y, -1, 1)) * (1 / math.pi)
    s = dr.select(sphere, lon, u / g("tex_sx"))
    t = dr.select(sphere, lat, v / g("tex_sy"))
    W, H = g("tex_w", T.UInt32), g("tex_h", T.UInt32)
    col = _texel(T, s, W, mode != MODE_CODE["fit"])
    row = _texel(T, t, H, mode == MODE_CODE["repeat"])
    k = g("tex_off", T.UInt32) + row * W + col
    texel = dr.gather(T.Array3, tables["texels"], k, on)
    return dr.select(on, g("tex_b") * texel, amb)


def _tile_size(o, rules: Rules):
    """A tiled plane's tile size; with the variant that leaves xdir unprojected, u is
    unit(xdir)·(hit − point) = |p|·u (p: xdir projected, |p| = the cosine of its tilt), so the
    tiles are w/|p| wide along the projected axis."""
    w, h = o.size
    if rules.tile_project:
        return (w, h)
    n = unit(o.given_normal or o.normal)
    x = unit(o.orient)
    c = x[0] * n[0] + x[1] * n[1] + x[2] * n[2]
    return (w / math.sqrt(max(1.0 - c * c, 0.0)), h)


def _odd_floor(x):
    """floor(x) mod 2 as 0 or 1, exactly, for any float x (no integer overflow)."""
    f = dr.floor(x)
    return f - 2 * dr.floor(0.5 * f)


def material(ks: KernelScene, tables: dict, oid, hit, u, v, rules: Rules = Rules(),
             normal=None):
    """(ambient, diffuse, specular) at each hit; zeros on a miss.  A tiled plane's MAT by tile
    parity: floor(OFF + u/w) + floor(OFF + v/h) odd -> foreground.  OFF = 10000 is even, so
    the parity is that of floor(u/w) + floor(v/h); leaving OFF out keeps float32 from rounding
    u/w to the 2⁻¹⁰ steps of numbers near 10000."""
    T = ks.T
    idx = T.UInt32(dr.select(hit, oid, 0))
    if "tplane" in ks.kinds:
        tiled = True if len(ks.kinds) == 1 else \
            dr.gather(T.UInt32, ks.table("kind"), idx, hit) == KIND_CODE["tplane"]
        w = dr.gather(T.Float, tables["tile_w"], idx, hit)
        h = dr.gather(T.Float, tables["tile_h"], idx, hit)
        if rules.tile_add_first:            # a variant: floor((OFF + u)/w)
            # (u here is along the projected axis: with xdir left unprojected too, the
            # course adds OFF to |p|·u, which is OFF/|p| added to u, the table's tile_off)
            off_u = dr.gather(T.Float, tables["tile_off"], idx, hit)
            off = dr.opaque(T.Float, TILE_OFF)
            odd = (_odd_floor((u + off_u) / w) + _odd_floor((v + off) / h)) == 1
        else:
            odd = (_odd_floor(u / w) + _odd_floor(v / h)) == 1
        # (the count as data: scenes of other sizes share the kernel)
        idx = dr.select(tiled & ~odd, idx + dr.opaque(T.UInt32, len(ks.scene.objects)), idx)
    amb, dif, spec = (dr.gather(T.Array3, tables[k], idx, hit)
                      for k in ("ambient", "diffuse", "specular"))
    if "texels" in tables:
        # (by object id: a tiled plane is never textured)
        amb = _texture_ambient(ks, tables, T.UInt32(dr.select(hit, oid, 0)), hit, u, v,
                               normal, amb)
    return amb, dif, spec


@traced
def shade(ks: KernelScene, d, rules: Rules = Rules(), max_dist: float = DEFAULT_MAX_DIST, *,
          log=None, extra=None, record: int = 0, max_bounces: int | None = None,
          cam=None) -> ShadeResult:
    """Shade the rays from the viewpoint along ``d`` (one per pixel, image order).

    ``extra(t, oid, hit, normal, u, v)``: a dict of further primary-ray outputs to evaluate in
    the primary pass (the geometry channels), returned evaluated in ``ShadeResult.extra``.
    ``record``: keep the rays of the first ``record`` bounces as numpy arrays (validation).
    ``log``: a :class:`~rt_core.jitlog.KernelLog` that gets one mark per pass.
    ``max_bounces``: the safety cap (default ``MAX_BOUNCES``).
    ``cam``: the camera of ``d``; in float64 the primary hits are then decided exactly
    (``tracer.closest_hit``)."""
    T = ks.T
    F = T.Float
    # (float32 directions in a float64 kernel: widened there, tracer.widened; the primary
    # hits' closest_hit reads the given ones back where it decides exactly)
    given, d = d, widened(T, d)
    # images shaded through this KernelScene (rt_core/reflectbins.py builds its bins for
    # the second: their build costs more than one image saves)
    ks.__dict__["_images"] = ks.__dict__.get("_images", 0) + 1
    log = log or NullLog()
    max_bounces = MAX_BOUNCES if max_bounces is None else max_bounces
    n = dr.width(d)
    image = dr.zeros(T.Array3, n)
    scene = ks.scene
    if not scene.objects:
        return ShadeResult(image)
    tables = _material_tables(ks, rules)
    # light centres relative to the viewpoint (host float64, then one rounding) and emissivity
    centres = [sub(L.center, scene.viewpoint) for L in scene.lights]
    lights = [(opaque3(T.Array3, c), opaque3(T.Array3, L.emissivity), _spot(T, L))
              for c, L in zip(centres, scene.lights)]
    reflect = any_specular(scene) and max_dist > 0
    max_d = dr.opaque(F, max_dist)
    out = ShadeResult(image)
    # the wavefront: pixel index (None: lane i is pixel i), origin (None: the viewpoint),
    # direction, surface to skip, path length so far, product of the speculars on the way
    # (None: start values), and which lanes are real (None: all)
    pixel, o, skip, dist, weight, live = None, None, None, None, None, None
    bounce, count = 0, n          # count: real rays in the wavefront

    def segment(d, o, skip, dist, weight, live, bounce, rec, found=None):
        """One bounce of the rays o + t·d: its closest hits (or ``found``: (t, oid, hit)
        already traced), shadow rays and shading (``add``: what it adds to the pixels where
        ``hit``) and its reflection rays."""
        # closest hit, surface, material (in float64 the primary hits are decided exactly
        # first: closest_hit evaluates them)
        t, oid, hit = found or closest_hit(ks, given if bounce == 0 else d, o, rules, skip,
                                           cam=cam if bounce == 0 else None)
        if live is not None:
            hit &= live
        normal, u, v = surface(ks, d, t, oid, hit, o)
        total = t if dist is None else dist + t
        H = d * t if o is None else dr.fma(d, t, o)         # hit point, relative
        amb, dif, spec = material(ks, tables, oid, hit, u, v, rules, normal)
        ex = extra(t, oid, hit, normal, u, v) if extra is not None and bounce == 0 else {}
        # one shadow ray per light from each hit that faces it: diffuse where unblocked
        I = amb
        # every light's path and light-bin cells before the first light's search
        # (tracer.shadow_cells)
        Ds = [Lp - H for Lp, _, _ in lights]
        lds = [dr.norm(D) for D in Ds]
        # (read on the lanes that hit: the others have no hit point H)
        cells = [shadow_cells(ks, H, ld, oid, c, hit) if PREFETCH_CELLS else None
                 for ld, c in zip(lds, centres)]
        for j, (Lp, E, spot) in enumerate(lights):
            D, ld = Ds[j], lds[j]
            L = D / ld
            c = dr.dot(L, normal)
            cast = hit & (c > 0)
            if spot is not None:            # a spotlight lights H only inside its cone:
                axis, cos_theta = spot      # unit(H − centre)·axis = −L·axis > cos θ
                cast &= -dr.dot(L, axis) > cos_theta
            blocked = occluded(ks, L, H, ld, rules, oid, cast, centres[j], cells[j])
            I = I + dr.select(cast & ~blocked, dif * E * (c / ld), 0)
            if rec is not None:
                rec.update({f"L{j}.dir": L, f"L{j}.dist": ld, f"L{j}.cast": cast,
                            f"L{j}.blocked": blocked})
        # divide by the path length (a variant: by this segment's)
        local = I / (t if rules.reflect == "segment" else total)
        add = local if weight is None else weight * local
        seg = SimpleNamespace(t=t, oid=oid, hit=hit, normal=normal, H=H, total=total,
                              ex=ex, add=add)
        if reflect:
            # the reflection rays
            seg.go = hit & ((spec.x != 0) | (spec.y != 0) | (spec.z != 0)) & (total < max_d)
            seg.Rn = dr.fma(normal, -2 * dr.dot(d, normal), d)   # reflect(dir, N), and
            seg.R = dr.normalize(seg.Rn)                           # normalized
            seg.w_next = spec if weight is None else weight * spec
        return seg

    if reflect and max_bounces == 1 and not record and FUSE_ONE_BOUNCE:
        return _one_bounce(T, d, image, segment, out, log,
                           lambda d, o, skip, along: closest_hit(ks, d, o, rules, skip,
                                                                 along=along))
    # reflection rays' closest hits through a BVH (or bins): ``TAIL_FRACTION``
    deep = any(accel.looped(ks, k, True) for k in ks.kinds)
    while True:
        group = "primary" if bounce == 0 else "reflection"
        rays = count
        rec = {} if bounce < record else None       # this bounce's shadow rays, recorded
        seg = segment(d, o, skip, dist, weight, live, bounce, rec)
        t, oid, hit, normal, H, total, ex, add = (seg.t, seg.oid, seg.hit, seg.normal, seg.H,
                                                  seg.total, seg.ex, seg.add)
        # add to the pixel
        if pixel is None:
            # lane i is pixel i: a plain masked sum (0 + add as the read-modify-write gave)
            image = image + dr.select(hit, add, 0)
        else:
            # each pixel appears at most once per wavefront: a plain read-modify-write (not
            # dr.scatter_add, which drops NaN: a NaN must reach the image, to be counted),
            # the sums evaluated with the bounce and scattered after it (_scatter_sums)
            summed = dr.gather(T.Array3, image, pixel, hit) + add
        # (a bounce with pixels reflects: its pixels are among the outputs below)
        outputs = [image, ex] if pixel is None else [summed, hit, ex]
        if reflect:
            go, R, w_next = seg.go, seg.R, seg.w_next
            # the pixel of each lane, evaluated: the next wavefront gathers it (at bounce 0
            # lane i is pixel i; an array as in later bounces, so that they share a kernel)
            if pixel is None:
                lanes = dr.arange(T.UInt32, n)
            outputs += [go, R, w_next, H, oid, total, lanes if pixel is None else pixel]
        if rec is not None:
            outputs += [t, oid, hit, normal, H, total, rec]
        # one kernel for the bounce: nothing in between goes through memory
        dr.eval(*outputs)
        if pixel is not None:
            image = _scatter_sums(image, summed, pixel, hit)
        log.mark("bounce", group, bounce, rays)
        if rec is not None:
            shadows = _numpy(rec, rays)
            rec = _record(dr.arange(T.UInt32, n) if pixel is None else pixel, o, d, skip, t,
                          oid, hit, normal, H, total, count=rays)
            rec.update(shadows)
            out.records.append(rec)
        out.extra.update(ex)
        if not reflect:
            break
        # the next wavefront: the rays that go on, compacted (measured: no faster masked in
        # place, even with half the lanes going on)
        idx = dr.compress(go)
        count = dr.width(idx)
        if count == 0:
            break
        if bounce == max_bounces:
            out.capped, out.left_active = True, count
            break
        # a wavefront of one ray would be a width-1 array, which Dr.Jit compiles as a scalar
        # (kernels of its own): pad it with an idle copy
        if count == 1:
            idx = T.UInt32([idx[0], idx[0]])
        live = dr.arange(T.UInt32, dr.width(idx)) < dr.opaque(T.UInt32, count)
        # (these gathers fuse into the next bounce's kernel)
        pixel = dr.gather(T.UInt32, lanes if pixel is None else pixel, idx)
        o = dr.gather(T.Array3, H, idx)
        d = dr.gather(T.Array3, R, idx)
        skip = dr.gather(T.Int32, oid, idx)
        dist = dr.gather(F, total, idx)
        weight = dr.gather(T.Array3, w_next, idx)
        bounce += 1
        out.bounces = bounce
        if TAIL and bounce >= record and (count <= TAIL_FRACTION * n or not deep):
            # the few rays left: their remaining bounces in one kernel
            image = _tail(T, segment, image, pixel, o, d, skip, dist, weight, live, bounce,
                          max_bounces, out, log, count)
            break
    out.rgb = image
    return out


def _tail(T, segment, image, pixel, o, d, skip, dist, weight, live, bounce: int,
          max_bounces: int, out: ShadeResult, log, count: int):
    """The rest of ``shade``'s wavefront loop for the rays of bounce ``bounce`` on (``live``:
    the ``count`` real lanes), in one kernel: a symbolic loop in which each lane goes on to
    its own end (no reflection, the cut-off, or the cap after bounce ``max_bounces``).

    A wavefront bounce costs a kernel launch, its tracing in Python and a compaction (about
    3 ms whatever its width), so a deep tail of few rays (mirrors facing each other: tens to
    hundreds of bounces) took most of a render.  Each lane's arithmetic is the wavefront's,
    and its sum into the pixel runs in the same order (the pixel's value so far, plus each
    bounce's term), so the image is the same, bit for bit.  Returns the image; sets
    ``out``'s bounces, capped and left_active as the wavefront loop would."""
    U = T.UInt32
    n = dr.width(d)
    # each lane's pixel value so far, to which its bounces add their terms in turn
    acc = dr.gather(T.Array3, image, pixel, live)
    cap = dr.opaque(U, max_bounces)

    def body(o, d, skip, dist, weight, live, acc, b, last, capped):
        seg = segment(d, o, skip, dist, weight, live, 1, None)
        acc = dr.select(seg.hit, acc + seg.add, acc)
        last = dr.select(live, b, last)
        go = seg.go                               # (only lanes that hit, so only live ones)
        capped |= go & (b >= cap)
        return (seg.H, seg.R, seg.oid, seg.total, seg.w_next, go & (b < cap), acc, b + 1,
                last, capped)

    state = (o, d, skip, dist, weight, live, acc, dr.opaque(U, bounce, n), dr.zeros(U, n),
             dr.zeros(T.Bool, n))
    state = dr.while_loop(state, lambda *s: s[5], body, label="shade_tail",
                          labels=("o", "d", "skip", "dist", "weight", "live", "acc", "b",
                                  "last", "capped"))
    acc, last, capped = state[6], state[8], state[9]
    del state           # (the loop's other outputs hold its entry state, which reads the image)
    dr.eval(acc, last, capped, pixel, live)
    # (the entry mask: the loop's is its own)
    image = _scatter_sums(image, acc, pixel, live)
    out.bounces = int(np.max(last.numpy()))
    log.mark("tail", "reflection", bounce, count)
    left = int(np.count_nonzero(capped.numpy()))
    if left:
        out.capped, out.left_active = True, left
    return image


def _scatter_sums(image, summed, pixel, mask):
    """``image`` with ``summed`` (evaluated: each pixel's value so far plus its terms) written
    to its pixels, by a kernel of its own.  The kernel that computed the sums read the image;
    a scatter into an array that its own kernel also gathers from makes Dr.Jit copy the whole
    array first (three channels of every pixel, for a few thousand hits)."""
    dr.scatter(image, summed, pixel, mask)
    dr.eval(image)
    return image


def _one_bounce(T, d, image, segment, out: ShadeResult, log, trace) -> ShadeResult:
    """``shade`` with max_bounces = 1 in two kernels, nothing through memory but the image
    and the reflection rays that hit something.

    The first kernel is the primary rays' bounce with the reflection rays' closest hits
    traced in place, in a symbolic ``dr.if_stmt`` on the lanes that reflect (a packet none
    of whose lanes reflects skips it), instead of as a compacted wavefront.  Each reflection
    ray that hits takes a slot (an atomic counter) and writes there its pixel, what its
    hit's shading needs and its pixel's value so far; the second kernel shades those hits
    only (shadow rays, material, the sum written into the pixel), densely: shaded in place,
    they ran at the lanes' hit rate (a third of the lanes at 256 spheres), at the cost of
    whole packets.  Each pixel's arithmetic is the wavefront's, so the image is the same,
    bit for bit, whatever the slots' order."""
    n = dr.width(d)
    U, F, I, A3 = T.UInt32, T.Float, T.Int32, T.Array3
    s0 = segment(d, None, None, None, None, None, 0, None)
    # lane i is pixel i: a plain masked sum (0 + add as the read-modify-write gave)
    image = image + dr.select(s0.hit, s0.add, 0)

    def reflected(t, oid):
        # (the culls take the reflection before its normalization: tracer.closest_hit)
        t, oid, hit = trace(s0.R, s0.H, s0.oid, s0.Rn)
        return t, oid

    t1, oid1 = dr.if_stmt((dr.zeros(F, n), dr.full(I, -1, n)), s0.go, reflected,
                          lambda t, oid: (t, oid), label="one_bounce")
    hit1 = oid1 >= 0
    # the reflection hits, each in a slot of its own: pixel, hit, and the ray's state
    counts = dr.zeros(U, 3 * COUNTER)       # reflection rays, slots taken, rays going on
    dr.scatter_reduce(dr.ReduceOp.Add, counts, U(1), U(0), s0.go)
    # (one packet of SLOT numbers a slot: one packet scatter, one packet gather; the ids as
    # the bits of a float of their width.  The hit's shadow rays skip its own id, so the
    # surface the reflection ray left is not needed.)
    row = [_bits(T, dr.arange(U, n)), t1, _bits(T, oid1), *s0.H, *s0.R, s0.total,
           *s0.w_next]
    if SUMS_IN_SLOTS:
        # and the pixel's value so far (lane i is pixel i): the second kernel adds to it
        # and writes the sum, reading nothing from the image
        row += [image.x, image.y, image.z]
    row += [row[1]] * (SLOT - len(row))
    slots = dr.empty(F, n * SLOT)

    def take_slots():
        slot = dr.scatter_inc(counts, U(COUNTER), hit1)
        dr.scatter(slots, packet_type(T)(row), slot, hit1)
    if SLOTS_IN_IF:
        # in a symbolic if: a packet without a hit skips the packet scatter's transposition
        dr.if_stmt((), hit1, take_slots, lambda: None, label="take_slots")
    else:
        take_slots()
    dr.eval(image, s0.ex, counts, slots)
    log.mark("bounce", "primary", 0, n)
    out.extra.update(s0.ex)
    reflections, m = (int(c) for c in counts.numpy()[[0, COUNTER]])
    if m:
        # the second kernel over the m hits (at least two lanes: a width-1 array would be
        # compiled as a scalar, kernels of its own)
        k = dr.arange(U, max(m, 2))
        live = k < dr.opaque(U, m)
        g = dr.gather(packet_type(T), slots, k, live, shape=(SLOT, dr.width(k)))
        pixel, oid = (_bits(T, g[j], back=True) for j in (0, 2))
        s1 = segment(A3(g[6], g[7], g[8]), A3(g[3], g[4], g[5]), None, g[9],
                     A3(g[10], g[11], g[12]), None, 1, None, found=(g[1], I(oid), live))
        dr.scatter_reduce(dr.ReduceOp.Add, counts, U(1), U(2 * COUNTER), s1.go)
        if SUMS_IN_SLOTS:
            # the wavefront's read-modify-write (each pixel at most once), the value read
            # from the slot: the image is written in place by this kernel
            dr.scatter(image, A3(g[13], g[14], g[15]) + s1.add, pixel, live)
            dr.eval(image, counts)
        else:
            summed = dr.gather(A3, image, pixel, live) + s1.add
            dr.eval(summed, pixel, counts)
            image = _scatter_sums(image, summed, pixel, live)
        left = int(counts.numpy()[2 * COUNTER])
        if left:
            out.capped, out.left_active = True, left
    if reflections:
        out.bounces = 1
        # (the reflection rays were traced by the primary kernel; their hits shaded by this)
        log.mark("bounce", "reflection", 1, reflections)
    out.rgb = image
    return out


SLOT = 16
# _one_bounce's three counters, each in a 64-byte line of its own (every packet of both
# threads adds to the first two; in one line, the line goes back and forth between the
# cores), and its slots taken in a symbolic if, so that a packet without a reflection hit
# skips the packet scatter's transposition, which costs a packet ~100 cycles even with
# every lane masked off.  Shaded bench f32, same process, median of 7-9, images identical,
# both over neither: spheres 1 0.75 of the time, 16 0.93 (the lines alone 0.96), 256 0.985;
# finite planes 16 0.91; mixed 16 0.975
COUNTER = 16
SLOTS_IN_IF = True
# Each slot also holds its pixel's value after the primary kernel, so that the second
# kernel writes the sums in place (a kernel that gathers from the image cannot scatter into
# it without a copy: ``_scatter_sums``), and no third kernel does (same process, median of
# 9-15, images identical: spheres 16 0.985-0.987 of the time, finite planes 16 0.99, mixed
# 16 0.98, spheres 256 0.99)
SUMS_IN_SLOTS = True


def _bits(T, v, back=False):
    """Non-negative ids (below 2³²) as the bits of a float of T's width, or ``back``.  Small
    ids are denormal floats, and Dr.Jit's threads flush denormals (FTZ/DAZ): such a float
    may only be moved (reinterpreted, scattered, gathered), never computed with, compared
    or selected on, or the id silently becomes 0 (test01 would see it)."""
    wide = T.module.UInt64 if T.precision == "f64" else T.UInt32
    if back:
        return T.UInt32(dr.reinterpret_array(wide, v))
    return dr.reinterpret_array(T.Float, wide(T.UInt32(v)))


def _numpy(arrays: dict, count: int) -> dict:
    """The first ``count`` lanes of Dr.Jit arrays as numpy ((count,) or (count, 3))."""
    out = {}
    for k, a in arrays.items():
        if dr.size_v(a) == 3:
            a = np.stack([np.asarray(c.numpy()) for c in (a.x, a.y, a.z)], 1)
        out[k] = np.asarray(a.numpy() if hasattr(a, "numpy") else a)[:count]
    return out


def _record(pixel, o, d, skip, t, oid, hit, normal, H, total, count: int) -> dict:
    """The rays of one bounce, for validation: origins and hit points relative to the
    viewpoint (zeros = the viewpoint), skip = -1 for none."""
    rec = _numpy({"pixel": pixel, "dir": d, "t": t, "id": oid, "hit": hit, "normal": normal,
                  "position": H, "total": total}, count)
    rec["origin"] = np.zeros((count, 3)) if o is None else _numpy({"o": o}, count)["o"]
    rec["skip"] = np.full(count, -1) if skip is None else _numpy({"s": skip}, count)["s"]
    return rec


def quantize(rgb: np.ndarray) -> np.ndarray:
    """The course's pixel value: floor(255 · clamp(I, 0, 1)) per channel, in I's precision
    (float32 arithmetic for f32 renders, as a float32 tracer would do it)."""
    a = np.asarray(rgb)
    flat = a.reshape(-1)
    out = np.empty(flat.shape, np.uint8)
    # in blocks, so that the temporaries stay small for a large image
    for k in range(0, flat.size, 1 << 22):
        b = flat[k:k + (1 << 22)]
        # NaN (counted and reported by the caller) becomes 0; ±inf clamps like any value
        b = np.where(np.isnan(b), a.dtype.type(0), b)
        out[k:k + (1 << 22)] = np.floor(a.dtype.type(255) * np.clip(b, 0, 1))
    return out.reshape(a.shape)
