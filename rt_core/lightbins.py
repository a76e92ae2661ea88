"""Shadow rays through bins of directions around each point light (a "light buffer").

A shadow ray runs from a hit point H to a light at C: every point of it lies, seen from C,
in the direction −L.  So, as the camera's rays share the viewpoint (rt_core/accel.py's
screen-space bins), a light's shadow rays share C: a cube of directions around C (6 faces,
each a SIDE × SIDE grid) lists in each cell the objects of a kind whose bounding box, seen from
C, covers the cell; a shadow ray tests the objects of its cell only, with the kind's own hit
function on the same constants and the same skip rule as the plain loop (a blocker anywhere
counts, so the order does not matter).  In the benchmark scenes a cell lists a few objects
whatever N, against ~30 steps of a BVH walk.  A cell's rows are nearest to the light first,
and the first is often the surface the ray leaves (which its test skips): each cell names
that row's object, and a ray leaving it starts past it (shaded bench, 16 objects, with
``SIDE``: loop iterations a ray 1.6–1.9 → 0.9–1.2 for finite planes, 1.3 → 0.3 for
spheres).  Built on
the host once per KernelScene, kind and light (numpy); the rows are copies, in the packet
layout of rt_core/bvh.py.

Why no blocker the plain loop finds is missing from a ray's cell:

* the kernel's ray is H + t·L with L = (C − H)/|C − H| rounded, C the light's centre in the
  kernel's precision (the bins are built around that same point): the line passes within
  ~2u·|C − H| of C (u: the unit roundoff), and a hit function accepts a point within a few
  u·(S + |C − H|) of its object (S: the largest distance from C to any box corner); the
  ray's cell is found from H − C as computed (``CELL_BY_OFFSET``), whose direction is
  within ~3u of L's;
* so a blocker's accepted point P, at distance r from C, lies within an angle of
  ~8u·(S + |C − H|)/r of a point of the object's box, seen from C; objects within
  R0 = ``NEAR``·S of C are listed in every cell, so r >= R0 for the others, and rays with
  |C − H| > ``dmax`` (so long that the angle could exceed the margin) take the kind's BVH
  instead;
* a face (axis i, sign s) lists an object by the bounds of v_j/(s·v_i), v_k/(s·v_i) over the
  part of its box with s·v_i >= R0/2 (which holds every point of the box at distance >= R0
  in or near the face's pyramid), widened by ``MARGIN`` (face units; an angle a moves a
  face coordinate by at most √6·a, at a face's corner; dmax keeps a below MARGIN/8) and
  clamped to the face: a ray near a face's edge, put on either face by rounding, finds the
  object on both;
* of those cells an object keeps the ones within the cone of its bounding ball seen from C
  (``in_cone``: the angle from the ball's centre to the cell's centre at most asin(R/L) +
  the cell's angular radius + 2·MARGIN): a blocker's accepted point lies as near the ball as
  the box, so the same angle covers it.  For spheres this halves the rows (spheres 256: 55 k
  → 30 k rows over 4 lights; the shaded bench image 0.92 of the time, mixed 256 0.86,
  spheres 16 0.93; finite planes, whose balls fit worse, 0.96–1.03).

The one exception, as for the BVH (rt_core/bvh.py): a planar object within ~10⁻⁴ rad
(float32) of parallel to the ray returns a noise t, so the plain loop's verdict there is
rounding noise, which these bins (stopping at rows beyond the light) need not repeat.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import drjit as dr
import numpy as np

from .bvh import _upload, object_boxes, row_view, rows as packed_rows
from .shapes import directed, opaque3
from .accel import blocks, device_array, tested

# cells along a face side, whatever the object count.  Finer cells more often start with the
# surface a ray leaves (which it then starts past); coarser ones keep the cells' table in
# cache.  Shaded bench, one process, images identical, time against 16·√N cells a side
# (which this replaced, at most 256): 16 objects (side 16) 0.94-0.96 with 64, one object
# even; 1024 (128) 0.98; 4096 (256) 0.91 (128: 0.94-0.96).  6·64² cells of 16 bytes: 0.4 MB
# a light and kind
SIDE = 64
# ... for images of SIDE²·RAYS_PER_CELL rays or more (2 M: 1920 columns).  The build's
# numpy work grows with the cells, and a small image's render was mostly that build: a
# 48-column course image (cbl__spec3, 5 lights) spent 32 of its 58 ms building 64 a side.
# Fewer rays get the least power of two from MIN_SIDE whose cells hold RAYS_PER_CELL rays
# or fewer (``side_for``); the cells only pick which objects a ray tests, so the answers
# are the same at every side
MIN_SIDE = 8
RAYS_PER_CELL = 512
MARGIN = 2.0 ** -8          # face units each cell range is widened by
NEAR = 2.0 ** -7            # R0 = NEAR · S: objects this near the light are in every cell
NEAR_SLACK = 2.0 ** -10     # relative slack on a row's distance from the light
UNIT = {"f32": 2.0 ** -24, "f64": 2.0 ** -53}
CONE = True                 # cells also cut by the cone of each object's bounding ball
# A shadow ray's cell is found from H − C, not from −L = −(C − H)/|C − H|: the same
# direction within a few roundings, so the same cell but far inside MARGIN (the argument
# above), and the cell's lookup, and the loop after it, need not wait for the square root
# and the division (shaded bench, f32, same process, median of 9, images identical:
# spheres 16 0.96 of the time, finite planes 16 0.95, spheres 256 0.96, mixed 16 1.02)
CELL_BY_OFFSET = True


@dataclass
class LightBins:
    kind: str
    side: int                   # nb: cells along a face side
    rows: object                # Float[entries × row width]: each cell's objects' rows,
                                # nearest to the light first
    near: object                # Float[entries]: a lower bound of each row's distance from
                                # the light (a ray ends its cell at a row beyond its length)
    cells: object               # UInt32[6·side² × 4]: cell b's first row, its end, the id of
                                # its first row's object (2³² − 1 for none) and 0 (a packet)
    dmax: float                 # rays longer than this take the BVH
    counts: np.ndarray          # host: rows per cell (tests, statistics)


def _project(lo, hi, side: int, h: float):
    """Per face (6) the cell rectangles (object index, x0, x1, y0, y1) of the boxes (lo, hi)
    (relative to the light), as arrays."""
    out = []
    for i in range(3):
        j, k = [a for a in range(3) if a != i]
        for s in (1.0, -1.0):
            a, b = s * lo[:, i], s * hi[:, i]
            vlo, vhi = np.minimum(a, b), np.maximum(a, b)
            on = vhi >= h
            v0 = np.maximum(vlo, h)                      # the part with s·v_i >= h
            with np.errstate(divide="ignore", invalid="ignore"):
                rng = []
                for ax in (j, k):
                    q = np.stack([lo[:, ax] / v0, lo[:, ax] / vhi,
                                  hi[:, ax] / v0, hi[:, ax] / vhi], 1)
                    rng.append((q.min(1) - MARGIN, q.max(1) + MARGIN))
            cells = []
            for c0, c1 in rng:
                f0 = np.floor((np.clip(c0, -1, 1) + 1) / 2 * side)
                f1 = np.floor((np.clip(c1, -1, 1) + 1) / 2 * side)
                cells += [np.clip(f0, 0, side - 1), np.clip(f1, 0, side - 1)]
            idx = np.flatnonzero(on)
            out.append((idx, *(c[idx].astype(np.int64) for c in cells)))
    return out


def cube_cells(lo, hi, side: int, h: float, keep=None, limit: int | None = None):
    """(box index, cell) pairs, int64 arrays: the cells of the 6 faces' side × side grids
    (cell = face·side² + y·side + x) that the boxes (lo, hi), relative to the cube's centre,
    cover seen from it (``_project``, the part of each box with s·v_i >= h); ``keep``: a mask
    of the boxes to list; None when there would be more than ``limit`` pairs (counted
    before any is made)."""
    cells_per_face = side * side
    faces = []
    for face, (idx, x0, x1, y0, y1) in enumerate(_project(lo, hi, side, h)):
        if keep is not None:
            k = keep[idx]
            idx, x0, x1, y0, y1 = idx[k], x0[k], x1[k], y0[k], y1[k]
        faces.append((face, idx, x0, y0, x1 - x0 + 1, y1 - y0 + 1))
    if limit is not None and sum(int((w * hgt).sum()) for *_, w, hgt in faces) > limit:
        return None
    items, bins = [], []
    for face, idx, x0, y0, w, hgt in faces:
        cnt = w * hgt
        rep = np.repeat(np.arange(len(idx)), cnt)
        local = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        cx = x0[rep] + local % w[rep]
        cy = y0[rep] + local // w[rep]
        items.append(idx[rep])
        bins.append(face * cells_per_face + cy * side + cx)
    return (np.concatenate(items).astype(np.int64) if items else np.zeros(0, np.int64),
            np.concatenate(bins).astype(np.int64) if bins else np.zeros(0, np.int64))


@functools.lru_cache(maxsize=8)
def cell_centres(side: int):
    """Unit directions of the cells' centres (6·side², 3) and each cell's angular radius
    (the largest angle from its centre to a corner), as lightbins.face_cell numbers them."""
    g = -1 + 2 * np.arange(side + 1) / side                 # cell borders on a face
    c = -1 + (2 * np.arange(side) + 1) / side               # cell centres
    dirs, rad = [], []
    for i in range(3):
        j, k = [a for a in range(3) if a != i]
        for s in (1.0, -1.0):
            cy, cx = np.meshgrid(c, c, indexing="ij")
            v = np.zeros((side, side, 3))
            v[..., i], v[..., j], v[..., k] = s, cx, cy
            v /= np.linalg.norm(v, axis=-1, keepdims=True)
            worst = np.zeros((side, side))
            for dy in (0, 1):
                for dx in (0, 1):
                    w = np.zeros((side, side, 3))
                    w[..., i] = s
                    w[..., j] = g[dx:dx + side][None, :]
                    w[..., k] = g[dy:dy + side][:, None]
                    w /= np.linalg.norm(w, axis=-1, keepdims=True)
                    worst = np.maximum(worst, np.arccos(np.clip((v * w).sum(-1), -1, 1)))
            dirs.append(v.reshape(-1, 3))
            rad.append(worst.ravel())
    return np.concatenate(dirs), np.concatenate(rad)


def in_cone(v, L, R, which, cell, side: int):
    """Which of the (ball ``which``, cell) entries may hold a direction toward ball k of
    centre v[k] (|v[k]| = L[k]) and radius R[k], seen from the cube's centre (cells numbered
    as face_cell's): the angle from v to the cell's centre at most asin(R/L) + the cell's
    angular radius + 2·MARGIN (a face unit moves a direction by at most a radian); all where
    R >= L.  Compared as cosines (cos(a + b) from each side's cosine and sine), without a
    transcendental function per entry."""
    centre, radius = cell_centres(side)
    Ls = np.where(L > 0, L, 1)
    u = v / Ls[:, None]
    sin_c = np.clip(R / Ls, 0, 1)
    cos_c = np.sqrt(1 - sin_c * sin_c)
    r = radius + 2 * MARGIN
    cos_r, sin_r = np.cos(r), np.sin(r)
    whole = (np.arcsin(sin_c)[which] + r[cell] >= np.pi) | (R >= L)[which]
    cosang = np.einsum("ij,ij->i", u[which], centre[cell])
    limit = cos_c[which] * cos_r[cell] - sin_c[which] * sin_r[cell]
    return whole | (cosang >= limit)


def side_for(rays: int | None) -> int:
    """Cells along a face side for bins that ``rays`` shadow rays will query first (None:
    unknown, SIDE)."""
    side = MIN_SIDE if rays is not None else SIDE
    while side < SIDE and side * side * RAYS_PER_CELL < rays:
        side *= 2
    return side


def build(ks, kind: str, center, side: int = SIDE) -> LightBins:
    """The bins of one kind around the light at ``center`` (relative to the viewpoint, host
    float64; rounded here to the kernel's precision, as the shading rounds it), ``side``
    cells along a face side."""
    T = ks.T
    consts = ks.by_kind[kind]
    n = len(consts)
    C = np.array(center, np.float64)
    if T.precision == "f32":
        C = C.astype(np.float32).astype(np.float64)
    lo, hi = object_boxes(kind, consts)
    lo, hi = lo - C, hi - C
    corners = np.maximum(np.abs(lo), np.abs(hi))
    S = float(np.sqrt((corners ** 2).sum(1)).max())
    R0 = NEAR * S
    nearest = np.clip(0.0, lo, hi)
    near = np.sqrt((nearest ** 2).sum(1)) <= R0
    cells_per_face = side * side
    nbins = 6 * cells_per_face
    items, bins = cube_cells(lo, hi, side, R0 / 2, keep=~near)
    if CONE:
        # and of those the cells within the cone of the object's bounding ball
        # (rt_core/cull.py's, widened by its rounding and 2⁻²⁰·S: a blocker's accepted point
        # lies as near the ball as the box, and MARGIN holds that angle)
        from .cull import bounding
        balls = bounding(ks)
        v = np.array([balls[c.id][0] for c in consts]).reshape(-1, 3) - C
        R = np.array([balls[c.id][1] for c in consts]) * (1 + 2.0 ** -20) + 2.0 ** -20 * S
        L = np.sqrt((v ** 2).sum(1))
        inside = in_cone(v, L, R, items, bins, side)
        items, bins = items[inside], bins[inside]
    items, bins = [items], [bins]
    for k in np.flatnonzero(near):                      # near the light: every cell
        items.append(np.full(nbins, k))
        bins.append(np.arange(nbins))
    items = np.concatenate(items).astype(np.int64) if items else np.zeros(0, np.int64)
    bins = np.concatenate(bins).astype(np.int64) if bins else np.zeros(0, np.int64)
    # each cell's rows nearest to the light first (then by id)
    dist = np.sqrt((nearest ** 2).sum(1))
    order = np.lexsort((items, dist[items], bins))
    counts = np.bincount(bins, minlength=nbins)
    offsets = np.zeros(nbins + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    table = packed_rows(kind, consts, np.arange(n))[items[order]]
    # a blocker's accepted point lies within |C − H|(1 + 2u) + ~16u(|C − H| + S) of C: a row
    # whose distance, less NEAR_SLACK of it and of S, exceeds |C − H| cannot block
    near = directed(dist[items[order]] * (1 - NEAR_SLACK) - NEAR_SLACK * S, T.precision,
                   down=True)
    u = UNIT[T.precision]
    dmax = (MARGIN - 5 * u) * R0 / (64 * u) - S
    # per cell one packet: start, end and the object of its first row (the nearest to the
    # light: often the surface a ray leaves, which it then starts past)
    cells = np.zeros((nbins, 4), np.uint32)
    cells[:, 0], cells[:, 1] = offsets[:-1], offsets[1:]
    first = np.full(nbins, 0xFFFFFFFF, np.uint32)
    full = counts > 0
    ids = np.array([c.id for c in consts], np.int64)
    first[full] = ids[items[order][offsets[:-1][full]]].astype(np.uint32)
    cells[:, 2] = first
    empty = not len(table)
    return LightBins(kind, side, _upload(T, np.zeros(8) if empty else table),
                     _upload(T, np.zeros(1) if empty else near), device_array(T.UInt32, cells),
                     max(dmax, 0.0), counts)


# Scenes whose every point is within the bins' reach of the light (bounded objects only)
# trace no BVH walk for the long shadow rays: a packet never took it, but its code cost
# every image's Python tracing and the kernel's size (shaded bench f32, same process,
# median of 7-11, images identical: spheres 16 0.94 of the time, finite planes 16 0.95;
# mixed 16, whose plane keeps the walk, and spheres 256 and 4096 even)
NO_FAR = True


def light_bins(ks, kind: str, center, rays: int | None = None) -> LightBins:
    """The kind's LightBins around ``center`` (built once per KernelScene, as fine as the
    ``rays`` of its first query ask: ``side_for``)."""
    cache = ks.__dict__.setdefault("_accel", {}).setdefault("lightbins", {})
    key = (kind, tuple(float(c) for c in center))
    if key not in cache:
        cache[key] = build(ks, kind, center, side_for(rays))
    return cache[key]


def cell(T, lb: LightBins, L):
    """The cell of each ray with direction L toward the light (``face_cell`` of −L)."""
    return face_cell(T, lb.side, -L)


def face_cell(T, side: int, v):
    """The cube-map cell of direction v: the face of v's largest component, then
    v_j/|v_i|, v_k/|v_i| (j < k the other axes) on the face's side × side grid."""
    F, U = T.Float, T.UInt32
    vx, vy, vz = v.x, v.y, v.z
    ax, ay, az = dr.abs(vx), dr.abs(vy), dr.abs(vz)
    fx = (ax >= ay) & (ax >= az)
    fy = ~fx & (ay >= az)
    fz = ~fx & ~fy
    vi = dr.select(fx, vx, dr.select(fy, vy, vz))
    vj = dr.select(fx, vy, vx)
    vk = dr.select(fz, vy, vz)
    axis = dr.select(fx, U(0), dr.select(fy, U(1), U(2)))
    face = 2 * axis + dr.select(vi < 0, U(1), U(0))
    inv = 1 / dr.abs(vi)
    half = dr.opaque(F, side / 2)
    top = dr.opaque(F, side - 1)
    cx = dr.clip(dr.floor((vj * inv + 1) * half), 0, top)
    cy = dr.clip(dr.floor((vk * inv + 1) * half), 0, top)
    side = dr.opaque(U, side)
    return face * side * side + U(cy) * side + U(cx)


def cells(ks, kind: str, o, maxt, skip, center, active=None):
    """(far, start, end) of shadow rays from ``o`` toward the light at ``center`` (maxt =
    |C − o| as the shading makes it): the rows start..end−1 of each ray's cell, and the rays
    too long for the bins (``far``: the BVH's).  Made by ``occluded_kind``, or beforehand
    (tracer.shadow_cells): the shading asks every light's before the first light's loop,
    so that their lookups need not wait for the loops before them; ``active``: the lanes
    whose cell is read (the others, whose o may be no hit point at all, get none: rows
    0..0), where made outside ``occluded``'s branch on its active lanes."""
    T = ks.T
    U = T.UInt32
    lb = light_bins(ks, kind, center, dr.width(o))
    far = ~(maxt <= dr.opaque(T.Float, lb.dmax))
    C = opaque3(T.Array3, center)
    if CELL_BY_OFFSET:
        b = dr.select(far, U(0), face_cell(T, lb.side, o - C))
    else:                                   # from L = (C − o)/|C − o|, as the shading's
        b = dr.select(far, U(0), cell(T, lb, (C - o) / maxt))
    se = dr.gather(T.module.ArrayXu, lb.cells, b, True if active is None else active,
                   shape=(4, dr.width(b)))
    # a ray leaving the cell's first object starts past it: skipping it is what its test
    # does for such a ray (``tested``'s skip), so the answer is the same
    start = se[0] + dr.select(T.Int32(se[2]) == skip, U(1), U(0)) if skip is not None \
        else se[0]
    end = dr.select(far, start, se[1])
    return far, start, end


def occluded_kind(ks, kind: str, d, o, maxt, rules, skip, blocked, center, rows=None):
    """accel.occluded_kind for shadow rays toward the light at ``center`` (d = L, o = H,
    maxt = |C − H| as the shading makes them): the objects of the ray's cell; rays longer
    than the bins' dmax (and any NaN) through the kind's BVH.  ``rows``: ``cells``' answer
    for these rays, where made before."""
    from . import bvh
    T = ks.T
    lb = light_bins(ks, kind, center, dr.width(d))
    vz = ks.scene.viewpoint[2]
    far, start, end = rows if rows is not None else cells(ks, kind, o, maxt, skip, center)

    def body(i, blk):
        obj = row_view(T, kind, lb.rows, i)
        # (the surface the ray leaves is in its cell: a packet whose lanes all leave this
        # row's object skips the test)
        return i + 1, tested(d, o, obj, rules, vz, skip, blocks(maxt), (blk,),
                             skip_branch=True)[0]

    def more(i, blk):
        # rows left, not blocked, and the next row not beyond the light
        go = (i < end) & ~blk
        return go & (dr.gather(T.Float, lb.near, i, go) <= maxt)

    _, near = dr.while_loop((start, blocked), more, body,
                            labels=("i", "blocked"), label=f"lightbins_{kind}")
    # the long rays (rare: from far points of unbounded planes) through the BVH, in a
    # symbolic if: a packet without one skips the walk's set-up too (three divisions a ray)
    if NO_FAR and within_reach(ks, center, lb.dmax):
        # no shading point is that far from the light: ``far`` only where maxt is NaN (no
        # hit point), which the walk finds unblocked too (t < NaN fails), as the loop left
        # them (their cells list no rows)
        return near

    def walk(blk):
        return (bvh.occluded_kind(ks, kind, d, o, maxt, rules, skip, blk | ~far),)

    walked = dr.if_stmt((blocked,), far, walk, lambda blk: (blk,),
                        label=f"lightbins_{kind}_far")[0]
    return dr.select(far, walked, near)


def within_reach(ks, center, dmax: float) -> bool:
    """Does every point of every object lie within dmax of the light at ``center`` (a scene
    of bounded objects only, whose boxes' farthest corners are that near, with room for
    the roundings of H, C and |C − H| in the shading: 2⁻¹⁰ of that distance and of the
    largest coordinate of C and the boxes, relative to the viewpoint, as H and C are)?"""
    from .accel import BOUNDED
    cache = ks.__dict__.setdefault("_accel", {}).setdefault("reach", {})
    key = tuple(float(c) for c in center)
    if key not in cache:
        far = np.inf
        if all(k in BOUNDED for k in ks.kinds):
            C = np.array(center, np.float64)
            far, scale = 0.0, float(np.abs(C).max())
            for k in ks.kinds:
                lo, hi = object_boxes(k, ks.by_kind[k])
                corner = np.maximum(np.abs(lo - C), np.abs(hi - C))
                # (np.max keeps a NaN, Python's max would drop it)
                far = np.max([far, np.sqrt((corner ** 2).sum(1)).max()])
                scale = np.max([scale, np.abs(lo).max(), np.abs(hi).max()])
            far = float(far + 2.0 ** -10 * (far + scale))
            if not np.isfinite(far):            # (a NaN box: never within reach)
                far = np.inf
        cache[key] = far
    return cache[key] <= dmax
