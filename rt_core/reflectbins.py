"""Closest hits of reflection rays through bins of directions around each bounded object.

A reflection ray leaves the surface of the object it was reflected by (the ``skip`` of
``tracer.closest_hit``), so its origin lies in that object's box, and every ray leaving a box
B_s toward a box B_t goes in a direction of the box B_t − B_s (the Minkowski difference: all
differences of a point of B_t and a point of B_s).  So, as rt_core/lightbins.py does around a
light, each bounded object (the source) gets a cube of directions (6 faces, each a
``SIDE`` × ``SIDE`` grid), whose cells list, per target kind, the objects whose difference
box (and ball, below) covers the cell, nearest first; a ray reads the list of its source's
cell, with the kind's own hit function on the same constants and the same skip and tie rules
as the BVH walk, and stops at the first row whose distance bound is beyond its closest hit so
far.  In the benchmark scenes a ray visits a few rows where the BVH walk takes ~30 steps.  Built on the host once per
KernelScene and kind (numpy): a list holds row numbers of one table of the kind's rows (in
the packet layout of rt_core/bvh.py), one more gather a step than copies of the rows, which
measured 2-4% faster but take 4-8 times the memory.

Why no hit the BVH finds is missing from a ray's list (the BVH's own premise, rt_core/bvh.py:
a hit function accepts a ray only where the exact line o + t·d passes within
e = PAD·(|o|∞ + S) of the object):

* the kernel checks that the ray's origin lies in its source's box widened by ``SOURCE_PAD``·S
  (the float64 box rounded inward) and in its bounding ball (rt_core/cull.py's) widened as
  much, |o − c|² <= rs² (the hit point that made the ray is off the surface by its rounding;
  rs² rounded down in float32);
  rays outside either, rays from unbounded objects and rays whose direction is not finite take
  the BVH instead;
* the targets are widened by PAD·2.01·S >= e, so an accepted point X = o + t*·d, t* > 0,
  makes X − o a point of the difference box D (target box − source box) and of the
  difference ball (centre c_t − c_s, radius R = rs + rt, rs widened by 2⁻¹⁰ of itself and
  2⁻²⁰·S for the kernel's rounding of |o − c|² and of c), and d points along it;
* a face lists D by the bounds of v_j/(s·v_i), v_k/(s·v_i) over the part of D with
  s·v_i >= R0/2, widened by lightbins.MARGIN (2⁻⁸ face units, against a few ulps of rounding
  in the kernel's cell); every point of D in the face's pyramid with s·v_i < R0/2 is within
  √3·R0/2 < R0 of the origin, so it is in neither D nor the ball when the pair's distance
  bound (below) exceeds R0 = ``NEAR``·S; the other pairs are listed in every cell of the
  source;
* of those cells, a pair keeps the ones whose centre is within asin(R/|c_t − c_s|) + the
  cell's angular radius + 2·MARGIN of the ball's direction (a face unit moves the direction
  by at most a radian): for spheres this halves the lists;
* a row's bound is the larger of the distances from the origin to D and to the ball (rounded
  down), a lower bound of |X − o| = t*·|d|; a ray stops at a row whose bound exceeds
  t·|d|·(1 + 2·KAPPA) (t: its closest hit so far).  That needs a hit function's t within
  KAPPA of the exact crossing, which is a tighter demand than the BVH's (it prunes on a
  leaf box's entry, looser than one object's distance): a sphere's or a quadric's t is off
  by ~√u relative at most (at tangency), but a planar object's by ~u/|cos θ| (θ: the angle
  of the ray to the normal), and within ~10⁻⁴ rad of its plane (float32) t is noise.  So a
  planar target's rows in the cells holding directions within ``GRAZE`` (2⁻¹⁰ rad; 2⁻³⁰ in
  float64) of its plane get the bound 0 and are never stopped before, and a torus's rows
  (a quartic's roots) always get 0: a second reader found rays leaving one of two coplanar
  tilted tiles toward the other within 10⁻⁷ rad, where the other's noise t beat a sphere
  between them in the BVH and the plain loop, and the stop skipped it
  (tests/test_reflectbins.py test10; that grazing cells' rows cost nothing measurable).

The sources' object is left out of its own lists (the skip rule would mask it anyway).  Above
``MAX_PAIRS`` source–target pairs, or ``MAX_ROWS`` listed rows (counted before the cones'
cut, so before they are made) or source cells, or with more than ``MAX_UNSTOPPED`` of its
rows never stopped before (bound 0: coplanar tiles), a kind keeps the BVH.

Measured (``rtval bench --shaded``'s scenes at 256 objects, f32, the whole one-bounce image
against the BVH walk, same process, median of 5): spheres 0.57-0.59 of the time (0.95 M rows,
4.3 a cell, built in 0.4 s), finite planes 0.67, mixed 0.70; the reflection rays' closest hits
alone, spheres: 57 ms CPU against the walk's 215.  Without the balls' cone (boxes only):
spheres 0.65, 8.5 rows a cell.  SIDE = 8: spheres 0.63; 16: 0.59 with 1.5 times the rows.
At 1024 spheres (boxes only) 0.8, but the build took 5 s; at 16 objects the bins' loop was
3-10% slower than the unrolled tests (rt_core/tracer.py; 6-13% before the balls' cut), which
keep those.  A single
default render (the wavefront) saved only 0.03 s at 256 spheres, less than the build: so the
bins are built for a KernelScene's ``AFTER_IMAGES``-th shaded image, and its first walks the
BVH.  The two give the same answers except at the BVH's own exception (rt_core/bvh.py): a
planar object grazed within ~10⁻⁴ rad (float32) whose leaf the walk prunes by its box,
where the plain loop reports its noise t and so do the bins (test10).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .accel import BOUNDED, closest_fold, device_array, packet_type, tested
from .bvh import KAPPA, PAD, _upload, object_boxes, row_view, rows as packed_rows
from .shapes import directed
from . import lightbins
from .lightbins import cube_cells, face_cell

SIDE = 12                   # cells along a face side, per source object
NEAR = 2.0 ** -12           # R0 = NEAR · S: pairs this near are in every cell of the source
SOURCE_PAD = 2.0 ** -10     # the source boxes' widening, relative to S
MAX_PAIRS = 1 << 18         # sources × targets of a kind at most (the build's time)
MAX_ROWS = 1 << 22          # listed rows of a kind at most (memory)
# the bins are built for the AFTER_IMAGES-th image shaded through a KernelScene (shading.shade
# counts them): the build (0.4 s at 256 spheres) costs more than a single image saves
AFTER_IMAGES = 2
# a reflection ray's cell found from the reflection before its normalization, where the
# caller has it (closest_kind's ``along``): shaded bench f32, same process, median of 9,
# images identical: spheres 256 0.99 of the time, finite planes 256 0.99, mixed 256 1.00
ALONG = True
# more rows than this share with bound 0 (grazing or near: never stopped before), the BVH:
# a floor of coplanar mirror tiles had 92% (tests/test_bvh.py mirror_hall: 1.04 of the BVH's
# time at one bounce, 1.21 at all), the bench scenes 10-25%
MAX_UNSTOPPED = 0.5
# planar targets: directions within this angle of the plane make t noise (their bound is 0)
GRAZE = {"f32": 2.0 ** -10, "f64": 2.0 ** -30}
PLANAR = ("fplane", "triangle", "disk")


@dataclass
class ReflectBins:
    kind: str
    side: int
    source: object              # Sources.source and .boxes (shared by the kinds)
    boxes: object
    table: object               # Float[targets × row width]: the kind's rows (bvh.rows)
    index: object               # UInt32[entries]: each cell's rows in the table, nearest first
    near: object                # Float[entries]: a lower bound of each row's distance
    offsets: object             # UInt32[sources·6·side² + 1]: the rows of (source, cell)
    counts: np.ndarray          # host: rows per (source, cell) (tests, statistics)


@dataclass
class Sources:
    """Every bounded object as a source of reflection rays (host float64, and the kernel's
    tables), the same for every target kind: built once per KernelScene."""
    ids: np.ndarray             # object ids, in source order
    lo: np.ndarray              # boxes widened by es
    hi: np.ndarray
    centre: np.ndarray          # bounding balls' centres
    rs: np.ndarray              # their radii widened by es: what the kernel admits
    wide: np.ndarray            # rs widened by its rounding and a margin: what the lists hold
    S: float                    # the largest coordinate of any bounded object's box
    source: object              # Int32[objects]: each object's source index, −1 if unbounded
    boxes: object               # Float[sources × 16]: box (inward), centre, rs² (down)


def sources(ks) -> Sources:
    """The KernelScene's Sources (once)."""
    from .cull import bounding
    cache = ks.__dict__.setdefault("_accel", {})
    if "reflect_sources" in cache:
        return cache["reflect_sources"]
    T = ks.T
    kinds = [k for k in BOUNDED if ks.by_kind.get(k)]
    ids = np.array([c.id for k in kinds for c in ks.by_kind[k]])
    lo, hi = (np.concatenate(b) for b in zip(*(object_boxes(k, ks.by_kind[k]) for k in kinds)))
    S = float(max(np.abs(lo).max(), np.abs(hi).max()))
    es = SOURCE_PAD * S
    lo, hi = lo - es, hi + es
    # bounding balls (rt_core/cull.py): the kernel admits origins within rs of a source's
    # centre (as rounded); the lists hold the ball widened by that rounding and a margin
    balls = bounding(ks)
    centre = np.array([balls[i][0] for i in ids]).reshape(-1, 3)
    rs = np.array([balls[i][1] for i in ids]) + es
    index = np.full(len(ks.scene.objects), -1, np.int64)
    index[ids] = np.arange(len(ids))
    boxes = np.zeros((len(ids), 16))
    boxes[:, 0:3] = directed(lo, T.precision, down=False)       # inward: lo up, hi down
    boxes[:, 3:6] = directed(hi, T.precision, down=True)
    boxes[:, 6:9] = centre
    boxes[:, 9] = directed(rs * rs, T.precision, down=True)
    out = cache["reflect_sources"] = Sources(
        ids, lo, hi, centre, rs, rs * (1 + 2.0 ** -10) + 2.0 ** -20 * S, S,
        device_array(T.Int32, index), _upload(T, boxes))
    return out


def build(ks, kind: str) -> ReflectBins | None:
    """The bins of the target ``kind`` around every bounded object, or None when too large."""
    from .cull import bounding
    T = ks.T
    targets = ks.by_kind[kind]
    ns, nt = sum(len(ks.by_kind.get(k, ())) for k in BOUNDED), len(targets)
    cells = 6 * SIDE * SIDE
    if ns * nt > MAX_PAIRS or ns * cells > MAX_ROWS:       # (the offsets: ns·cells + 1)
        return None
    src = sources(ks)
    tlo, thi = object_boxes(kind, targets)
    S = src.S                       # (the targets are sources too)
    et = PAD[T.precision] * 2.01 * S
    slo, shi, sids, sc, rs_wide = src.lo, src.hi, src.ids, src.centre, src.wide
    R0 = NEAR * S
    tids = np.array([c.id for c in targets])
    balls = bounding(ks)
    tc = np.array([balls[i][0] for i in tids]).reshape(-1, 3)
    rt = np.array([balls[i][1] for i in tids]) + et
    # every (source, target) pair but an object and itself; D = target − source
    a, b = np.divmod(np.arange(ns * nt), nt)
    keep = sids[a] != tids[b]
    a, b = a[keep], b[keep]
    lo = tlo[b] - et - shi[a]
    hi = thi[b] + et - slo[a]
    v = tc[b] - sc[a]
    L = np.sqrt((v ** 2).sum(1))
    R = rs_wide[a] + rt[b]
    # a lower bound of |X − o|: the boxes' distance, or the balls'
    dist = np.maximum(np.sqrt((np.clip(0.0, lo, hi) ** 2).sum(1)), L - R)
    near = dist <= R0
    listed = cube_cells(lo, hi, SIDE, R0 / 2, keep=~near,
                        limit=MAX_ROWS - int(near.sum()) * cells)
    if listed is None:
        return None
    pair, cell = listed
    # and of those the cells within the balls' cone
    inside = lightbins.in_cone(v, L, R, pair, cell, SIDE)
    pair, cell = pair[inside], cell[inside]
    # a planar target's t is off by ~ulps/|cos θ| (rt_core/bvh.py): in the cells that hold
    # directions within GRAZE of its plane its rows' bound is 0 (never stopped before)
    bound = dist[pair] if kind != "torus" else np.zeros(len(pair))
    if kind in PLANAR:
        centre, radius = lightbins.cell_centres(SIDE)
        n = np.array([c.n for c in targets], np.float64).reshape(-1, 3)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        off_plane = np.arcsin(np.clip(np.abs((n[b[pair]] * centre[cell]).sum(1)), 0, 1))
        graze = off_plane <= radius[cell] + GRAZE[T.precision] + 2 * lightbins.MARGIN
        bound = np.where(graze, 0.0, bound)
    close = np.flatnonzero(near)
    pair = np.concatenate([pair, np.repeat(close, cells)])
    cell = np.concatenate([cell, np.tile(np.arange(cells), len(close))])
    # (near pairs: bound 0, as a hit's t nearer than ~2⁻¹⁶·S need not be within KAPPA of
    # the exact crossing)
    bound = np.concatenate([bound, np.zeros(len(close) * cells)])
    if len(pair) > MAX_ROWS or np.count_nonzero(bound == 0) > MAX_UNSTOPPED * len(pair):
        return None
    bins = a[pair] * cells + cell
    # each (source, cell)'s rows nearest first (then by id)
    order = np.lexsort((tids[b[pair]], bound, bins))
    pair, bins, bound = pair[order], bins[order], bound[order]
    counts = np.bincount(bins, minlength=ns * cells)
    offsets = np.zeros(ns * cells + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    table = packed_rows(kind, targets, np.arange(nt))
    index = b[pair]
    off = device_array(T.UInt32, offsets)
    empty = not len(index)
    return ReflectBins(kind, SIDE, src.source, src.boxes, _upload(T, table),
                       device_array(T.UInt32, np.zeros(1) if empty else index),
                       _upload(T, np.zeros(1) if empty else
                               directed(bound, T.precision, down=True)),
                       off, counts)


def reflect_bins(ks, kind: str) -> ReflectBins | None:
    """The kind's ReflectBins (built once per KernelScene), or None: keep the BVH."""
    cache = ks.__dict__.setdefault("_accel", {}).setdefault("reflectbins", {})
    if kind not in cache:
        cache[kind] = build(ks, kind)
    return cache[kind]


def closest_kind(ks, kind: str, d, o, rules, skip, st, along=None):
    """accel.closest_kind for reflection rays (``skip``: the object each leaves): the rows of
    its source's cell; the other rays through the kind's BVH.  ``along``: d unnormalized
    (the same direction within a few roundings, far inside MARGIN), which the kernel has
    sooner: the cell is found from it."""
    from . import bvh
    on = ks.__dict__.get("_accel_opts", {}).get("reflectbins")
    if on is None:                      # by default from the second image shaded on
        on = ks.__dict__.get("_images", 0) >= AFTER_IMAGES
    rb = reflect_bins(ks, kind) if on and skip is not None else None
    if rb is None:
        return bvh.closest_kind(ks, kind, d, o, rules, skip, st)
    T = ks.T
    F, U, I = T.Float, T.UInt32, T.Int32
    n = dr.width(d)
    vz = ks.scene.viewpoint[2]
    # the ray's source, if bounded, whose box holds its origin, and a finite direction
    src = dr.gather(I, rb.source, dr.maximum(skip, 0), skip >= 0)
    dn = dr.norm(d)
    ok = (skip >= 0) & (src >= 0) & (dn > 0) & (dn < dr.inf)
    box = dr.gather(packet_type(T), rb.boxes, U(dr.maximum(src, 0)), ok, shape=(16, n))
    for i, c in enumerate((o.x, o.y, o.z)):
        ok &= (box[i] <= c) & (c <= box[3 + i])
    ok &= dr.squared_norm(o - T.Array3(box[6], box[7], box[8])) <= box[9]
    b = U(src) * dr.opaque(U, 6 * rb.side * rb.side) + \
        face_cell(T, rb.side, d if along is None or not ALONG else along)
    start = dr.gather(U, rb.offsets, b, ok)
    end = dr.select(ok, dr.gather(U, rb.offsets, b + 1, ok), start)
    reach = dn * dr.opaque(F, 1 + 2 * KAPPA)
    st.fresh = False

    def body(i, *state):
        obj = row_view(T, kind, rb.table, dr.gather(U, rb.index, i))
        return (i + 1, *tested(d, o, obj, rules, vz, skip, closest_fold(st, obj.id, rules),
                               state))

    def more(i, *state):
        # rows left, and the next row not beyond the closest hit so far
        go = i < end
        return go & (dr.gather(F, rb.near, i, go) <= state[0] * reach)

    names = st.names()
    out = dr.while_loop((start, *st.state()), more, body,
                        labels=("i",) + tuple("best_" + k for k in names),
                        label=f"reflectbins_{kind}")
    st.set(out[1:])
    # the other rays through the BVH, in a symbolic if: a packet without one skips the walk

    def walk(*state):
        return bvh.closest_kind(ks, kind, d, o, rules, skip, st.set(state), active=~ok).state()

    return st.set(dr.if_stmt(st.state(), ~ok, walk, lambda *s: s,
                             label=f"reflectbins_{kind}_far"))
