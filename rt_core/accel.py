"""Many objects: one symbolic loop per object kind, and screen-space bins for primary rays.

``tracer.closest_hit`` unrolls one block of code per object while a scene has at most
``UNROLL_MAX`` bounded objects (spheres and finite planes together; infinite planes count per
kind; float32 camera rays, ``CAMERA_FACTOR`` times that): the fastest kernel
for a few objects, but its size, compile time and run time grow with
the count (7 s to compile and 7 Mrays/s at 256 finite planes).  Above that, a kind is traced
here, by one Dr.Jit symbolic loop (``dr.while_loop``) whose body is that kind's hit function,
with the object's constants gathered per iteration from a table: the kernel no longer depends
on the count, and scenes of the same kinds share it whatever their sizes.

Rays from the viewpoint (``o is None``, the camera's rays) share their origin, so an object can
only be hit by rays that cross the window plane z = 0 inside its projection from the viewpoint.
A grid of bins covers the window; each bin lists, per kind and in ascending object id, the
objects whose (conservatively enlarged) projected bounding box overlaps it, as copies of their
table rows, so a ray reads its bin's rows in sequence.  With up to 512 bins per object (one
per 64 rays at most) a camera ray visits 1.2-3.5 rows in the benchmark scenes
(tools/harness/bench.py) whatever N: time grows as
~N^0.1-0.3 from 16 to 1024 objects, against N^1 for the unrolled or unbinned search.  A ray computes its
bin from its own direction (camera rays whose directions the kernel computes: from the
unnormalized one, the pixel's window offset, tracer.BIN_BY_OFFSETS) and loops over that bin's
list only; rays that cross the plane
outside the grid (or not at all) take a last bin that lists every object.  The per-object test
is the same function on the same (float64-derived) constants as the unrolled code, and the tie
test compares object ids, so the results are bit-identical to the unrolled search (tested in
tests/test_kernels.py).  Other rays have structures of their own: reflection rays the bins of
directions around the object they leave (rt_core/reflectbins.py), shadow rays those around
their light (rt_core/lightbins.py), and the rest a BVH (rt_core/bvh.py); without them
(``configure(bvh=False)``) they loop over every object of the kind.

Why the culling is conservative: an object is left out of a bin only if its float64 projected
box, enlarged by ``MARGIN`` (2⁻¹² of the window, viewpoint and box scales), misses the bin.  A
float32 hit test can accept a ray that exactly misses only within a few ulps of an edge, i.e.
within ~1e-6 of those scales in window coordinates, and the float32 bin of a ray (from its
direction or its window offset: the same line, each within a few roundings) is off by as
little; the margin is 2.4e-4 of them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import drjit as dr
import numpy as np

from .backend import host_cpu
from .rules import Rules
from .kinds import PLANE_KINDS
from .shapes import BOUND_FIELDS, TAME, object_t, sphere_live, sphere_t
from .quadrics import KINDS as QUADRICS
from .shapes_quadric import ROW_SLOTS, quadric_boxes, row_view as quadric_row_view


def wide_vectors() -> bool:
    """Has this CPU AVX-512 (Dr.Jit's LLVM backend then computes 16 floats a vector, else
    8)?  Read from /proc/cpuinfo; False where it cannot be read."""
    return "avx512f" in host_cpu().get("flags", "").split()


# More (bounded) objects than this: the symbolic loop instead of unrolled code.  Measured
# crossover (bench, f32): unrolled wins up to ~8-12 objects, the binned loop above.
UNROLL_MAX = 8
# Closest hits of rays with an origin (reflections) loop only above SECONDARY_FACTOR times
# that: their loop walks a BVH (rt_core/bvh.py), ~10-20 steps a ray at 16-48 objects, each
# costing about three unrolled hit tests (measured: unrolled is faster up to ~24 finite
# planes, ~48 spheres).
SECONDARY_FACTOR = 3
# Camera rays in float32 (and certified float64's: camera_unrolls) loop over bounded objects
# only above CAMERA_FACTOR times UNROLL_MAX:
# their unrolled tests are the cheap ones (a sphere behind one dot product,
# shapes.sphere_cone; a finite plane without bounds, since behind its ball's, plane_cone).
# Measured before that (bench scenes, 1920 columns,
# median of 11 interleaved calls), unrolled time over binned: spheres 9 0.59, 12 0.66, 16
# 0.90, 20 0.98, 24 1.06; finite planes 10 0.76, 12 0.84, 14 0.83, 16 1.02; mixed 10 0.58,
# 14 0.71, 16 0.86, 20 0.99.  float64 with exact decisions too, since its spheres and finite
# planes branch on cone tests, but with at most 12 spheres (two alternated bench runs
# against the loop, float64 over Mitsuba: spheres 12 1.10/1.04 against 0.93/0.95, 16
# 0.99/0.99 against 1.09/1.09; mixed 16 3.76/3.42 against 3.12/2.90; finite planes 12
# 2.87/2.87 against 2.19/2.20, 16 2.44/2.39 against 2.05/2.06); not float64 without
# (before its finite planes branched: finite planes 12: 1.43, 16: 1.81; spheres 16: 1.04).
# That measurement was on an AVX-512 CPU (16 floats a vector).  On an AVX2 one (8 floats:
# an AMD EPYC, two sessions later) 16 spheres unrolled ran at 1.09-1.65x Mitsuba, and
# through the binned loop 1.42-2.15x (medians of six alternated bench runs: 1.49 against
# 1.99); 10 to 14 spheres about even (unrolled 1.95-2.06x at 10, the loop 1.29-1.87x): there
# the camera rays unroll up to 12.  CUDA's: the host CPU's vectors say nothing of a GPU's,
# where the crossover has not been measured (the factor long used there, 2).
CAMERA_FACTOR = {"avx512": 2, "avx2": 1.5, "cuda": 2}
CAMERA_SPHERES_F64 = 12
# ... where every bounded object is of these kinds (measured on them; 12 tori unrolled took
# 7 times the binned loop's time)
CAMERA_KINDS = ("sphere", "fplane")
# Shadow rays search spheres through the light bins (rt_core/lightbins.py) from more than
# SHADOW_SPHERES · UNROLL_MAX spheres on, where the other kinds still unroll: unrolled, every
# lit hit ran each sphere's whole test a light (three square roots and a division).  Shaded
# bench scenes, f32, 1920 columns, same process, median of 7, images identical, time with
# the light bins over unrolled: spheres 4 0.985, 6 0.77, 7 0.71, 8 0.68 (1.19x Mitsuba ->
# 1.76x); with every bounded kind through them from 2 objects on, finite planes 4 1.14,
# mixed 4 1.34, mixed 6 1.13, spheres 2 1.40: not done
SHADOW_SPHERES = 0.5
# Bins per looped object (bounded kinds), at most one per RAYS_PER_BIN rays of the first
# batch traced, and at most MAX_BINS.  Finer bins list fewer rows a ray misses (spheres, 16
# objects: 1.41 rows a ray at 32 bins per object, 1.20 at 512; 64: 2.54, 2.16) and were
# 10-15% faster in-process; one bin per 16 rays was slower again.
BINS_PER_OBJECT = 512
RAYS_PER_BIN = 64
MAX_BINS = 1 << 16
MARGIN = 2.0 ** -12
# Per-kind constants that the hit functions read (shapes.object_t), in the order of a row;
# the object id rides along as a float (exact below 2**24).  A table stores each row
# zero-padded to stride(kind) numbers, a power of two, and a loop reads a row with one packet
# gather (``KindTable.view``): Dr.Jit loads each 8-number block of it that the kernel uses
# with one vector load per lane.  Separate scalar gathers cost ~3x more: LLVM's znver3
# target scalarizes every masked gather into 8 branches and inserts (measured:
# docs/speed.md).
LAYOUT = {"sphere": ("qx", "qy", "qz", "radius", "c", "id", "grp", "bo", "bs"),
          "plane": ("qx", "qy", "qz", "nq", "nx", "ny", "nz", "g", "id", "grp", "bz"),
          "fplane": ("qx", "qy", "qz", "nq", "nx", "ny", "nz", "g", "w", "xx", "xy", "xz", "h",
                     "yx", "yy", "yz", "id", "grp", "bz", "bm")}
LAYOUT["tplane"] = LAYOUT["plane"]
LAYOUT.update({k: ROW_SLOTS for k in QUADRICS})     # rt_core/shapes_quadric.py
# the planar kinds (rt_core/shapes_planar.py): a triangle's size is |N| twice, a disk's c r²
LAYOUT["triangle"] = LAYOUT["fplane"]
LAYOUT["disk"] = ("qx", "qy", "qz", "nq", "nx", "ny", "nz", "g", "c", "xx", "xy", "xz", "radius",
                  "yx", "yy", "yz", "id", "grp", "bz", "bm")
LAYOUT["torus"] = ("qx", "qy", "qz", "radius", "c", "nx", "ny", "nz", "w", "h", "id", "grp",
                   "bo", "bs")
BOUNDED = ("sphere", "fplane", "triangle", "disk", "torus") + QUADRICS


def stride(kind: str) -> int:
    """Numbers per table row: LAYOUT[kind]'s, padded to a power of two (a packet)."""
    return 1 << (len(LAYOUT[kind]) - 1).bit_length()


def device_array(Type, a: np.ndarray):
    """An opaque Dr.Jit array of Type holding host array ``a``, at a 64-byte aligned address.
    (Dr.Jit maps a numpy array of its own dtype without copying, and gathers packets only from
    aligned memory: from a numpy buffer that happens to be unaligned, it silently falls back to
    scalar gathers and compiles another kernel.)"""
    dtype = np.dtype(dr.type_v(Type).name.lower())        # float32, float64, uint32
    flat = np.ascontiguousarray(a, dtype).ravel()
    raw = np.empty(flat.nbytes + 64, np.uint8)
    start = -raw.ctypes.data % 64
    out = raw[start:start + flat.nbytes].view(dtype)
    out[:] = flat
    arr = Type(out)
    dr.make_opaque(arr)
    return arr


def packet_type(T):
    """The dynamic-size array type of a packet gather of T's floats."""
    return getattr(T.module, "ArrayXf" if T.precision == "f32" else "ArrayXf64")


def configure(ks, unroll_max: int | None = None, bins: bool | None = None,
              bvh: bool | None = None, reflectbins: bool | str | None = None):
    """Override UNROLL_MAX, the use of bins (rays from the viewpoint), of the BVH (other
    rays, rt_core/bvh.py) and of the reflection rays' bins (rt_core/reflectbins.py; else
    they walk the BVH; "auto", the default: from the second image shaded) for one
    KernelScene (benchmarks, tests).  None leaves a setting as it is."""
    opts = ks.__dict__.setdefault("_accel_opts", {})
    if reflectbins == "auto":
        opts.pop("reflectbins", None)
    elif reflectbins is not None:
        opts["reflectbins"] = bool(reflectbins)
    if unroll_max is not None:
        opts["unroll_max"] = unroll_max
    if bins is not None:
        opts["bins"] = bins
    if bvh is not None:
        opts["bvh"] = bvh
    return ks


def use_bvh(ks, kind: str, o) -> bool:
    """Are rays with origins ``o`` traced through the kind's BVH (rt_core/bvh.py)?  Rays
    that do not start at the viewpoint, against a looped bounded kind, unless turned off."""
    return (o is not None and kind in BOUNDED
            and ks.__dict__.get("_accel_opts", {}).get("bvh", True))


def camera_factor(backend: str) -> float:
    """CAMERA_FACTOR of ``backend`` on this machine."""
    if backend == "cuda":
        return CAMERA_FACTOR["cuda"]
    return CAMERA_FACTOR["avx512" if wide_vectors() else "avx2"]


def camera_unrolls(ks) -> bool:
    """Do camera rays unroll up to CAMERA_FACTOR × UNROLL_MAX objects?  float32's, and
    float64's with exact decisions (tracer.exact_decisions), whose unrolled spheres and
    finite planes branch on cone tests (tracer.BRANCH_MIN), with at most
    CAMERA_SPHERES_F64 spheres; not float64's without.  (Read from the KernelScene: an
    uncertified call on a scene with exact decisions, which only tests make, unrolls too.)"""
    if ks.T.precision == "f32":
        return True
    return ks.__dict__.get("exact_decisions", True) and \
        len(ks.by_kind.get("sphere", ())) <= CAMERA_SPHERES_F64


def looped(ks, kind: str, reflections: bool = False, camera: bool = False,
           shadows: bool = False) -> bool:
    """Is ``kind`` traced by a loop rather than unrolled?  Bounded kinds (spheres, finite
    planes) loop when there are more than UNROLL_MAX of them together; the unbounded ones
    (planes, tiled planes: every bin lists them) when there are more than UNROLL_MAX of the
    kind.  ``reflections``: for the closest hits of rays with an origin, above
    SECONDARY_FACTOR times that.  ``camera``: for the closest hits of camera rays, where
    in float32 bounded kinds loop above CAMERA_FACTOR times that if all are CAMERA_KINDS
    (every kind looped here is looped without ``camera`` too, not the other way round).
    ``shadows``: for shadow rays, where spheres also loop (through the light bins) when
    there are more than SHADOW_SPHERES times that of them (so every kind looped without
    ``shadows`` is looped with it)."""
    limit = ks.__dict__.get("_accel_opts", {}).get("unroll_max", UNROLL_MAX)
    if reflections:
        limit *= SECONDARY_FACTOR
    if shadows and kind == "sphere" and len(ks.by_kind.get(kind, ())) > limit * SHADOW_SPHERES:
        return True
    if kind in BOUNDED:
        if camera and camera_unrolls(ks) and all(
                k in CAMERA_KINDS for k in BOUNDED if ks.by_kind.get(k)):
            limit = int(limit * camera_factor(ks.T.backend))
        return sum(len(ks.by_kind.get(k, ())) for k in BOUNDED) > limit
    return len(ks.by_kind.get(kind, ())) > limit


def camera_loops(ks) -> bool:
    """Do camera rays loop over some kind's objects (bins), not only unrolled code?"""
    return any(looped(ks, k, camera=True) for k in ks.kinds)


def _row(c) -> dict:
    """The numbers of one ObjectConstants by slot name (float64, host)."""
    r = {"id": float(c.id), "grp": float(c.grp), "radius": c.radius, "c": c.c, "nq": c.nq,
         "g": c.g}
    r.update({k: getattr(c, k) for k in BOUND_FIELDS})
    for name, v in (("q", c.q), ("n", c.n), ("x", c.xdir), ("y", c.ydir)):
        r[name + "x"], r[name + "y"], r[name + "z"] = v
    r["w"], r["h"] = c.size
    r.update(c.row() if hasattr(c, "row") else {})  # a quadric's own slots
    return r


@dataclass
class KindTable:
    """One kind's objects as a flat array of packed rows (LAYOUT): rows 0..count-1 are the
    objects in ascending id; with bins, each bin's rows follow (copies, so that a loop reads
    its rows in sequence, without an index list)."""
    kind: str
    count: int
    rows: object                 # Float[rows * stride(kind)]
    # UInt32[4 * (nbins + 1)]: bin b is rows offsets[4b]..offsets[4b + 1] (each bin's start
    # and end side by side, padded to a packet of 4: one vector load)
    offsets: object = None
    # bins (rays from the viewpoint): the largest of each certified bound over the rows, a
    # bound of every row's (a larger bound is still a bound): host numbers, not gathered
    wide: dict | None = None
    folded: bool = False         # plane kinds: rows with sign(n·q) folded in (fold_signs)
    tame: bool = False           # every row's numbers within shapes.TAME (shapes.least)

    def view(self, T, k):
        """The constants of row k (per ray), in the form shapes.object_t reads: one packet
        gather (Dr.Jit leaves out the blocks of it that no computation uses)."""
        names = LAYOUT[self.kind]
        wide = self.wide or {}
        g = dr.gather(packet_type(T), self.rows, T.UInt32(k),
                      shape=(stride(self.kind), dr.width(k)))
        v = {name: g[j] for j, name in enumerate(names) if name not in wide}
        A3 = T.Array3
        out = SimpleNamespace(kind=self.kind, id=T.Int32(v["id"]), grp=T.Int32(v["grp"]),
                              q=A3(v["qx"], v["qy"], v["qz"]))
        if self.kind in QUADRICS:
            return quadric_row_view(out, v, A3)
        for k in names[names.index("grp") + 1:]:      # the certified decisions' bounds
            setattr(out, k, wide[k] if k in wide else v[k])
        if self.kind == "torus":
            out.radius, out.c, out.size = v["radius"], v["c"], (v["w"], v["h"])
            out.n = A3(v["nx"], v["ny"], v["nz"])
        elif self.kind == "sphere":
            out.radius, out.c = v["radius"], v["c"]
        else:
            out.n, out.nq = A3(v["nx"], v["ny"], v["nz"]), v["nq"]
            out.g = v["g"]
        out.folded, out.tame = self.folded, self.tame
        if self.kind == "fplane":
            out.xdir = A3(v["xx"], v["xy"], v["xz"])
            out.ydir = A3(v["yx"], v["yy"], v["yz"])
            out.size = (v["w"], v["h"])
        if self.kind in ("triangle", "disk"):              # rt_core/shapes_planar.py
            out.xdir = A3(v["xx"], v["xy"], v["xz"])
            out.ydir = A3(v["yx"], v["yy"], v["yz"])
            out.c = v.get("c")
        return out


def pack(kind: str, consts) -> np.ndarray:
    """(len(consts), len(LAYOUT[kind])) float64 rows."""
    return np.array([[r[n] for n in LAYOUT[kind]] for r in map(_row, consts)], np.float64)


def fold_signs(kind: str, rows: np.ndarray) -> bool:
    """Rows of a plane kind for rays from the viewpoint only: s = sign(n·q) folded into n,
    n·q, g and the frame (exact negations), so that a hit has s·(n·d) > 0 and the kernel
    needs no sign (shapes._plane_fast).  Every answer is unchanged: t = n·q/(n·d) and each
    test's sign depend on the plane, not its orientation.  In place; False if not done
    (a plane kind with a row whose n·q is 0, or too large for t's bound)."""
    if kind not in PLANE_KINDS:
        return False
    names = LAYOUT[kind]
    nq = rows[:, names.index("nq")]
    if not len(rows) or (nq == 0).any() or np.abs(nq).max() > 1e280:
        return False
    sg = np.where(nq < 0, -1.0, 1.0)
    for k in ("nq", "nx", "ny", "nz", "g", "xx", "xy", "xz", "yx", "yy", "yz"):
        if k in names:
            rows[:, names.index(k)] *= sg
    return True


def _upload(ks, kind: str, rows: np.ndarray, offsets=None, wide=None,
            folded: bool = False) -> KindTable:
    T = ks.T
    padded = np.zeros((len(rows), stride(kind)))
    padded[:, :rows.shape[1]] = rows
    flat = device_array(T.Float, padded)
    off = None
    if offsets is not None:
        se = np.zeros((len(offsets) - 1, 4), np.uint32)
        se[:, 0], se[:, 1] = offsets[:-1], offsets[1:]
        off = device_array(T.UInt32, se)
    bounds = [j for j, name in enumerate(LAYOUT[kind]) if name in BOUND_FIELDS]
    tame = bool((np.abs(np.delete(rows, bounds, axis=1)) <= TAME).all())
    return KindTable(kind, len(ks.by_kind[kind]), flat, off, wide, folded, tame)


# the bounds taken table-wide on bins (a sphere's bs too: its t bound is bs/(b' + √disc)
# relative, so a far sphere's larger bs loosens a near one's t bound, which only flags more
# near ties)
WIDE = ("bz", "bm", "bo", "bs")


def _wide(kind: str, rows: np.ndarray) -> dict | None:
    names = LAYOUT[kind]
    cols = [names.index(k) for k in WIDE if k in names]
    if not len(rows) or not cols or not np.isfinite(rows[:, cols]).all():
        return None
    # a clip bound of exactly 0 (a plane in z = 0) makes its clip certain: kept per row
    return {names[c]: float(rows[:, c].max()) for c in cols
            if names[c] != "bz" or (rows[:, c] > 0).all()}


def never_hit(kind: str, consts) -> np.ndarray:
    """Objects no ray from the viewpoint hits, in exact arithmetic and in rt_core's: a
    sphere around the viewpoint (c <= 0: the near root is <= 0) and a plane through it
    (n·q = 0: t = 0).  Both signs are exact (host constants rounded once)."""
    if kind == "sphere":
        return np.array([not c.c > 0 for c in consts], bool)
    if kind in QUADRICS or kind == "torus":   # an open quadric is seen from inside too
        return np.zeros(len(consts), bool)
    return np.array([c.nq == 0 for c in consts], bool)


def tables(ks) -> dict:
    """KindTables of the looped kinds, without bins (built once per KernelScene)."""
    cache = ks.__dict__.setdefault("_accel", {})
    if "tables" not in cache:
        cache["tables"] = {}
        for k in ks.kinds:
            if looped(ks, k, shadows=True):     # (every kind a ray loops over)
                assert len(ks.by_kind[k]) < 2 ** 24, "object ids must be exact in float32"
                cache["tables"][k] = _upload(ks, k, pack(k, ks.by_kind[k]))
    return cache["tables"]


# --- screen-space bins ------------------------------------------------------------------------

@dataclass
class Grid:
    """Bins over the window plane z = 0: nbx × nby cells of the rectangle [x0, x0 + nbx·bw] ×
    [y0, y0 + nby·bh] (world units), plus bin nbx·nby, which lists every object."""
    nbx: int
    nby: int
    x0: float
    y0: float
    bw: float
    bh: float

    @property
    def nbins(self) -> int:
        return self.nbx * self.nby


def make_grid(scene, n_objects: int, rays: int) -> Grid:
    """About BINS_PER_OBJECT bins per object, one per RAYS_PER_BIN rays at most, over the
    window (enlarged by 1% so rays through its edges fall inside), square in world units."""
    ww, wh = scene.window
    ww, wh = 1.02 * ww, 1.02 * wh
    nb = max(1, min(MAX_BINS, BINS_PER_OBJECT * n_objects, rays // RAYS_PER_BIN))
    nbx = max(1, min(nb, round(math.sqrt(nb * ww / wh))))
    nby = max(1, min(nb // nbx if nbx else 1, round(nb / nbx)))
    return Grid(nbx, nby, -ww / 2, -wh / 2, ww / nbx, wh / nby)


def _corners(kind: str, consts) -> np.ndarray:
    """(count, m, 3) points relative to the viewpoint whose convex hull holds each object."""
    if kind in ("fplane", "triangle", "disk"):
        from .shapes_planar import planar_corners
        return planar_corners(kind, consts)
    if kind in ("sphere", "torus"):              # a torus: its bounding sphere
        s = np.array([(i, j, k) for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], np.float64)
        q = np.array([c.q for c in consts], np.float64)
        r = np.array([c.radius for c in consts], np.float64) * (1 + MARGIN)
        return q[:, None, :] + r[:, None, None] * s[None]
    if kind in QUADRICS:                              # the corners of their boxes
        lo, hi = quadric_boxes(consts)
        s = np.array([(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)], bool)
        return np.where(s[None], hi[:, None, :], lo[:, None, :])
    return None                                       # unbounded: every bin


def project_boxes(scene, kind: str, consts):
    """Per object: (status, box) with status 0 = no ray from the viewpoint through the grid
    can hit it, 1 = box (x0, x1, y0, y1) in window coordinates, 2 = anywhere."""
    n = len(consts)
    status = np.full(n, 2, np.int8)
    box = np.zeros((n, 4))
    vx, vy, vz = scene.viewpoint
    P = _corners(kind, consts)
    if P is None or vz == 0:
        return status, box
    # rays through the window go along sign(-vz) in z: a point is ahead iff its z (relative
    # to the viewpoint) has that sign
    ahead = P[..., 2] * (-math.copysign(1.0, vz))
    tiny = MARGIN * np.linalg.norm(P, axis=-1)
    status[np.all(ahead < -tiny, axis=1)] = 0
    front = np.all(ahead > tiny, axis=1)
    status[front] = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -vz / P[..., 2]
        wx = vx + P[..., 0] * s
        wy = vy + P[..., 1] * s
    box[:, 0], box[:, 1] = wx.min(1), wx.max(1)
    box[:, 2], box[:, 3] = wy.min(1), wy.max(1)
    scale = math.hypot(*scene.window) + abs(vx) + abs(vy) + abs(vz)
    m = MARGIN * (scale + np.abs(box).max(1))
    box += np.stack([-m, m, -m, m], 1)
    return status, box


def bin_lists(grid: Grid, status, box, count: int, never=None):
    """(offsets, items) of one kind: bins 0..nbins-1 list the objects whose box overlaps them,
    in ascending position; bin nbins lists all (but those ``never`` hit)."""
    nbx, nby = grid.nbx, grid.nby
    bins, items = [], []
    keep = np.ones(count, bool) if never is None else ~never
    for k in range(count):
        if status[k] == 0 or not keep[k]:
            continue
        if status[k] == 2:
            bx0, bx1, by0, by1 = 0, nbx - 1, 0, nby - 1
        else:
            x0, x1, y0, y1 = box[k]
            fx0, fx1 = (x0 - grid.x0) / grid.bw, (x1 - grid.x0) / grid.bw
            fy0, fy1 = (y0 - grid.y0) / grid.bh, (y1 - grid.y0) / grid.bh
            if not (fx1 >= 0 and fx0 < nbx and fy1 >= 0 and fy0 < nby):
                continue
            bx0, bx1 = max(0, math.floor(fx0)), min(nbx - 1, math.floor(fx1))
            by0, by1 = max(0, math.floor(fy0)), min(nby - 1, math.floor(fy1))
        b = (np.arange(by0, by1 + 1)[:, None] * nbx + np.arange(bx0, bx1 + 1)[None]).ravel()
        bins.append(b)
        items.append(np.full(len(b), k))
    nb = grid.nbins
    bins = np.concatenate(bins + [np.full(int(keep.sum()), nb)]).astype(np.int64)
    items = np.concatenate(items + [np.flatnonzero(keep)]).astype(np.int64)
    order = np.lexsort((items, bins))
    offsets = np.zeros(nb + 2, np.int64)
    np.cumsum(np.bincount(bins, minlength=nb + 1), out=offsets[1:])
    return offsets.astype(np.uint32), items[order].astype(np.uint32)


def binned(ks, rays: int = 1 << 21):
    """(grid, {kind: KindTable whose rows are its bins' rows}) for rays from the viewpoint;
    None without bins (no looped kind, or the viewpoint in the window plane).  Built once per
    KernelScene, for the size ``rays`` of the first batch."""
    cache = ks.__dict__.setdefault("_accel", {})
    if "binned" not in cache:
        cache["binned"] = None
        kinds = [k for k in tables(ks) if looped(ks, k, camera=True)]
        if kinds and ks.scene.viewpoint[2] != 0:
            n = sum(len(ks.by_kind[k]) for k in kinds if k in BOUNDED)
            grid = make_grid(ks.scene, max(n, 1), rays)
            tabs = {}
            for kind in kinds:
                consts = ks.by_kind[kind]
                status, box = project_boxes(ks.scene, kind, consts)
                off, items = bin_lists(grid, status, box, len(consts),
                                       never_hit(kind, consts))
                rows = pack(kind, consts)[items]
                folded = fold_signs(kind, rows)
                tabs[kind] = _upload(ks, kind, rows, off, _wide(kind, rows), folded)
            cache["binned"] = (grid, tabs)
    return cache["binned"]


def ray_bins(ks, grid: Grid, d):
    """Bin of each ray from the viewpoint along d: where it crosses z = 0, or the all-objects
    bin.  Every grid number is opaque data: the kernel does not depend on the grid."""
    T = ks.T
    F, U = T.Float, T.UInt32
    vx, vy, vz = ks.scene.viewpoint
    s = dr.opaque(F, -vz) / d.z
    bx = dr.floor(dr.fma(d.x, s, dr.opaque(F, vx - grid.x0)) * dr.opaque(F, 1.0 / grid.bw))
    by = dr.floor(dr.fma(d.y, s, dr.opaque(F, vy - grid.y0)) * dr.opaque(F, 1.0 / grid.bh))
    inside = (s > 0) & (bx >= 0) & (bx < dr.opaque(F, grid.nbx)) & (by >= 0) & \
        (by < dr.opaque(F, grid.nby))
    # (signed conversions and arithmetic: AVX2 has no unsigned ones; every number is < 2³¹)
    I = T.Int32
    b = I(dr.select(inside, by, 0)) * dr.opaque(I, grid.nbx) + I(dr.select(inside, bx, 0))
    return U(dr.select(inside, b, dr.opaque(I, grid.nbins)))


# --- the loops ----------------------------------------------------------------------------------

def _range(ks, kind: str, d, o, along=None):
    """(table, start, end): the rows start..end-1 of the table that each ray visits, as
    Int32 (a signed comparison ends the loop: AVX2 has no unsigned one; rows < 2³¹); None
    when no ray can hit an object of the kind (its bins list none: every one is never_hit,
    and an empty table has nothing to gather from).  ``along``: for camera rays, vectors
    along d that the kernel has sooner (``closest_kind``), to find the bins by."""
    I = ks.T.Int32
    use = o is None and ks.__dict__.get("_accel_opts", {}).get("bins", True)
    b = binned(ks, dr.width(d)) if use else None
    # (no bins either for a kind that shadow rays from the viewpoint loop over and camera
    # rays do not: looped's ``camera``)
    tab = b[1].get(kind) if b is not None else None
    if tab is None:
        tab = tables(ks)[kind]
        return tab, dr.zeros(I, dr.width(d)), dr.opaque(I, tab.count, dr.width(d))
    if dr.width(tab.rows) == 0:
        return None
    se = dr.gather(ks.T.module.ArrayXu, tab.offsets,
                   ray_bins(ks, b[0], d if along is None else along), shape=(4, dr.width(d)))
    return tab, I(se[0]), I(se[1])


def closest_kind(ks, kind: str, d, o, rules: Rules, skip, st, scale: float = 0.0,
                 along=None):
    """Fold every object of ``kind`` into the running closest hit ``st`` (tracer.Best), with
    the same test, tie rule and certification as the unrolled code.  ``along``: the rays'
    directions unnormalized, which the kernel has before d, to look up their bins by:
    camera rays' window offsets (``_range``), reflection rays' reflection
    (rt_core/reflectbins.py)."""
    if use_bvh(ks, kind, o):
        from . import reflectbins
        return reflectbins.closest_kind(ks, kind, d, o, rules, skip, st, along)
    T = ks.T
    vz = ks.scene.viewpoint[2]
    got = _range(ks, kind, d, o, along)
    if got is None:
        return st
    tab, start, end = got
    cert = st.cert
    st.fresh = False                    # the body is traced once for every iteration

    def body(i, *state):
        obj = tab.view(T, i)

        def fold(res, *state):
            s = st.set(state)
            s.fold(res[0], res[1], obj.id, rules, False,
                   *((*res[2:], obj.grp if st.shared else None) if cert else ()))
            return s.state()
        return (i + 1, *tested(d, o, obj, rules, vz, skip, fold, state, scale if cert else False))

    names = st.names()
    out = dr.while_loop((start, *st.state()), lambda i, *state: i < end, body,
                        labels=("i",) + tuple("best_" + k for k in names),
                        label=f"closest_{kind}")
    return st.set(out[1:])


def closest_fold(st, oid, rules: Rules):
    """The fold of a closest-hit test for ``tested`` (uncertified rays): object ``oid``'s
    hit into the running closest hit ``st`` (tracer.Best)."""
    def fold(res, *state):
        s = st.set(state)
        s.fold(*res, oid, rules, False)
        return s.state()
    return fold


def blocks(maxt):
    """The fold of a shadow ray's test for ``tested``: blocked by a hit at t < maxt."""
    return lambda res, b: (b | (res[1] & (res[0] < maxt)),)


def tested(d, o, obj, rules: Rules, vz: float, skip, fold, state, cert=False,
           skip_branch: bool = False):
    """``fold(res, *state)`` of one object of a table (``obj``: its row, gathered per ray)
    for the rays o + t·d: ``res`` is ``shapes.object_t``'s answer (with ``cert``, its
    certified one), the rays that leave the object (``skip``) not hitting it.  A sphere's
    test sits behind a packet-wide branch on ``shapes.sphere_live``: a packet none of whose
    rays can hit it (not even possibly) skips the square roots and the division and keeps
    ``state`` (a certain miss folds to no change); the others reuse its products.
    ``skip_branch``: other kinds' tests too sit behind a packet-wide branch, on the lanes
    not leaving the object (where a table lists the surface its rays leave, as a light-bin
    cell does); else those lanes are masked."""
    # (certified decisions are for camera rays, which skip nothing: a skipped lane's
    # 'possible' would otherwise need keeping)
    assert not (cert and skip is not None), "certified rays skip no object"
    if obj.kind != "sphere":
        if skip is not None and skip_branch:
            return dr.if_stmt(tuple(state), obj.id != skip,
                              lambda *s: fold(object_t(d, o, obj, rules, vz, cert), *s),
                              lambda *s: s, label="tested_object")
        res = object_t(d, o, obj, rules, vz, cert)
        if skip is not None:
            res = (res[0], res[1] & (obj.id != skip), *res[2:])
        return fold(res, *state)
    live = sphere_live(d, obj, cert, o=o)
    go = live.mask if skip is None else live.mask & (obj.id != skip)
    return dr.if_stmt(tuple(state), go,
                      lambda *s: fold(sphere_t(d, o, obj, rules, vz, cert, live), *s),
                      lambda *s: s, label="tested_sphere")


def light_binned(ks, kind: str, o) -> bool:
    """Do shadow rays from ``o`` toward a light search ``kind`` through its light bins
    (``occluded_kind`` with ``toward``)?  A looped bounded kind, rays with an origin."""
    return looped(ks, kind, shadows=True) and use_bvh(ks, kind, o)


def occluded_kind(ks, kind: str, d, o, maxt, rules: Rules, skip, blocked, toward=None,
                  rows=None):
    """``blocked`` or any object of ``kind`` (other than ``skip``) hit at 0 < t < maxt; each
    ray stops at its first blocker (rays already ``blocked`` do nothing).  ``toward``: the
    light the rays go to (host, relative to the viewpoint; the rays as the shading makes
    them): its direction bins (rt_core/lightbins.py; ``rows``: their cells' rows, made
    before)."""
    if toward is not None and use_bvh(ks, kind, o):
        from . import lightbins
        return lightbins.occluded_kind(ks, kind, d, o, maxt, rules, skip, blocked, toward,
                                       rows)
    if use_bvh(ks, kind, o):
        from . import bvh
        return bvh.occluded_kind(ks, kind, d, o, maxt, rules, skip, blocked)
    T = ks.T
    vz = ks.scene.viewpoint[2]
    got = _range(ks, kind, d, o)
    if got is None:
        return blocked
    tab, start, end = got

    def body(i, blk):
        obj = tab.view(T, i)
        t, hit = object_t(d, o, obj, rules, vz)
        if skip is not None:
            hit &= obj.id != skip
        return i + 1, blk | (hit & (t < maxt))

    _, blocked = dr.while_loop((start, blocked), lambda i, blk: (i < end) & ~blk, body,
                               labels=("i", "blocked"), label=f"occluded_{kind}")
    return blocked
