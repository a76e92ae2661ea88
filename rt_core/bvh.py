"""A bounding-volume hierarchy per bounded object kind, for rays that do not start at the
viewpoint (shadow rays, reflections).

Rays from the viewpoint have screen-space bins (rt_core/accel.py); other rays used to test
every object of a kind.  Here each bounded kind (spheres: centre ± r; finite planes: their
four corners) gets a binary BVH, built on the host once per KernelScene (numpy, binned SAH,
leaves of at most ``LEAF_SIZE`` objects).  The kind's table rows are reordered so that a
leaf's objects are a contiguous row range, and the nodes are flattened in depth-first order
with a skip link per inner node (the node after its subtree), so the kernel walks the tree
without a stack, in one ``dr.while_loop``: a ray at an inner node whose box it misses (or
enters beyond the current closest t, or beyond a shadow ray's length) goes to the skip link,
otherwise to the next node; a leaf's rows are tested one per iteration, by the kind's own hit
function (``shapes.object_t``) on the same constants, with the same skip and tie rules as
the plain loop.  The closest hit folds hits with the id tie rule, which does not depend on
the order objects are visited in: so wherever the box test keeps every object that the
plain loop finds a hit on, the answers are identical, bit for bit.

Why the box test keeps them (``visit``):

* boxes are float64 bounds of the float64 constants the hit functions read, rounded outward
  to the kernel's precision;
* each ray widens every box by e = ``PAD``·(|o|∞ + S) on every side (S: the largest
  coordinate of any box; |q − o| <= S + |o| bounds the lengths the hit functions round, so a
  hit function's accepted point lies within a few ulps of those lengths of the object, far
  inside e = 2¹² ulps of them);
* the slab test is pbrt-v4's Bounds3::IntersectP: the far distance scaled by 1 + 2γ₃, and a
  ray parallel to a slab (d_i = 0, or |d_i| below 1/``BIG``) takes ±BIG for 1/d_i, so no
  0·∞ = NaN arises; flat boxes (axis-aligned finite planes) are widened like any other;
* a box is pruned only when it starts beyond ``limit``·(1 + ``KAPPA``): the closest t so far
  (closest hit) or the shadow ray's length.  A hit function's t is within a relative few
  ulps/|cos θ| of the exact t (θ: the angle between the ray and the plane's normal), and the
  ray enters the widened box at least e before the exact hit point, so only a finite plane
  within ~10⁻⁴ rad (float32; 10⁻¹³ in float64) of parallel to the ray could have a rounded
  t far enough off to matter; there the plain loop's own answer is rounding noise.

Inner and leaf steps are two branches of a symbolic ``dr.if_stmt``, so a packet of lanes
that are all at inner nodes does not run the hit function, and vice versa.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import numpy as np

from types import SimpleNamespace

from .accel import blocks, closest_fold, device_array, pack, packet_type, tested
from .shapes import directed
from .quadrics import KINDS as QUADRICS
from .shapes_quadric import ROW_SLOTS, quadric_boxes, row_view as quadric_row_view

LEAF_SIZE = 4
SAH_BINS = 16
# per-ray widening of the boxes, relative to |o|∞ + S, and the relative margin on t
# (both 2¹² units of the kernel's rounding, at least 2⁻¹²... see the module docstring)
PAD = {"f32": 2.0 ** -12, "f64": 2.0 ** -40}
KAPPA = 2.0 ** -8
BIG = {"f32": 1e30, "f64": 1e300}
# node rows: lo.xyz, hi.xyz, a, b; inner: a = skip link, b = 0; leaf: a = first row, b = count
NODE = 8
# object rows: the constants the hit functions read for rays with an origin, padded to a
# power of two so that a row is one packet load (Dr.Jit's packet gathers: several times
# faster than one gather per constant on the LLVM backend)
ROW = {"sphere": ("qx", "qy", "qz", "radius", "id"),
       "fplane": ("qx", "qy", "qz", "nx", "ny", "nz", "g", "w", "xx", "xy", "xz", "h",
                  "yx", "yy", "yz", "id"),
       "torus": ("qx", "qy", "qz", "radius", "c", "nx", "ny", "nz", "w", "h", "id")}
ROW.update({k: ROW_SLOTS for k in QUADRICS})      # rt_core/shapes_quadric.py
ROW["triangle"] = ROW["fplane"]                     # rt_core/shapes_planar.py
ROW["disk"] = ("qx", "qy", "qz", "nx", "ny", "nz", "g", "c", "xx", "xy", "xz", "radius",
               "yx", "yy", "yz", "id")


@dataclass
class Tree:
    """One kind's hierarchy on the host: node rows (float64) flattened once per ray octant
    (``nodes[octant]``, each ``count`` rows), the object order of the table rows (positions
    in ``ks.by_kind[kind]``), and the largest coordinate S of any box."""
    nodes: np.ndarray            # (8, count, NODE)
    order: np.ndarray
    scale: float
    depth: int

    @property
    def count(self) -> int:
        return self.nodes.shape[1]


def object_boxes(kind: str, consts) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi), float64 (count, 3): the bounds of each object from its constants (relative
    to the viewpoint, as the hit functions see them)."""
    if kind == "sphere":
        q = np.array([c.q for c in consts], np.float64).reshape(-1, 3)
        r = np.array([c.radius for c in consts], np.float64)[:, None]
        return q - r, q + r
    if kind in QUADRICS:
        return quadric_boxes(consts)
    if kind in ("fplane", "triangle", "disk"):
        from .shapes_planar import planar_corners
        corners = planar_corners(kind, consts)
        return corners.min(1), corners.max(1)
    if kind == "torus":
        # the ring's extent along axis i is R·√(1 − â_i²), plus the tube's r
        q = np.array([c.q for c in consts], np.float64).reshape(-1, 3)
        a = np.array([c.n for c in consts], np.float64).reshape(-1, 3)
        R, r = (np.array([c.size[j] for c in consts], np.float64)[:, None] for j in (0, 1))
        ext = R * np.sqrt(np.clip(1 - a * a, 0, 1)) + r
        return q - ext, q + ext
    raise ValueError(f"{kind} objects are unbounded: no BVH")


def _area(lo, hi):
    e = np.maximum(hi - lo, 0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _split(lo, hi, idx):
    """Positions of ``idx`` in two non-empty parts, the first the lower along the split
    axis, and the axis: the binned-SAH split of the centroids (halves in id order when all
    centroids coincide)."""
    c = 0.5 * (lo[idx] + hi[idx])
    cmin, cmax = c.min(0), c.max(0)
    ext = cmax - cmin
    best = (math.inf, None, 0)
    for ax in np.flatnonzero(ext > 0):
        b = np.minimum(((c[:, ax] - cmin[ax]) / ext[ax] * SAH_BINS).astype(np.int64),
                       SAH_BINS - 1)
        blo = np.full((SAH_BINS, 3), np.inf)
        bhi = np.full((SAH_BINS, 3), -np.inf)
        np.minimum.at(blo, b, lo[idx])
        np.maximum.at(bhi, b, hi[idx])
        cnt = np.bincount(b, minlength=SAH_BINS)
        # prefix (left) and suffix (right) boxes and counts for the SAH_BINS - 1 planes
        llo, lhi = np.minimum.accumulate(blo), np.maximum.accumulate(bhi)
        rlo = np.minimum.accumulate(blo[::-1])[::-1]
        rhi = np.maximum.accumulate(bhi[::-1])[::-1]
        lc, rc = np.cumsum(cnt), np.cumsum(cnt[::-1])[::-1]
        cost = _area(llo[:-1], lhi[:-1]) * lc[:-1] + _area(rlo[1:], rhi[1:]) * rc[1:]
        cost = np.where((lc[:-1] > 0) & (rc[1:] > 0), cost, np.inf)
        k = int(np.argmin(cost))
        if cost[k] < best[0]:
            best = (cost[k], b <= k, int(ax))
    left = best[1]
    if left is None:                    # coincident centroids: halves in id order
        return idx[: len(idx) // 2], idx[len(idx) // 2:], 0
    return idx[left], idx[~left], best[2]


def build(lo: np.ndarray, hi: np.ndarray, leaf_size: int | None = None) -> Tree:
    """The hierarchy over boxes (lo, hi), depth-first, leaves of at most ``leaf_size``
    (default LEAF_SIZE)."""
    leaf_size = LEAF_SIZE if leaf_size is None else leaf_size
    n = len(lo)
    order = []
    depth = 0

    def rec(idx, level):
        """(box, axis, children) of an inner node, (box, first row, count) of a leaf."""
        nonlocal depth
        depth = max(depth, level)
        box = [*lo[idx].min(0), *hi[idx].max(0)]
        if len(idx) <= leaf_size:
            first = len(order)
            order.extend(sorted(idx.tolist()))      # ascending id within a leaf
            return (box, first, len(idx))
        a, b, axis = _split(lo, hi, idx)
        return (box, axis, (rec(a, level + 1), rec(b, level + 1)))

    def flatten(node, octant, out):
        box, a, b = node
        k = len(out)
        out.append(None)
        if isinstance(b, int):
            out[k] = [*box, a, b]
            return
        # the child nearer the ray's origin first: the lower one along the split axis for a
        # ray going up that axis (octant bit clear), the upper one otherwise
        near, far = b if not octant >> a & 1 else b[::-1]
        flatten(near, octant, out)
        flatten(far, octant, out)
        out[k] = [*box, len(out), 0]            # skip link: the node after the subtree

    nodes = np.zeros((8, 0, NODE))
    if n:
        root = rec(np.arange(n), 1)
        flat = []
        for octant in range(8):
            flatten(root, octant, out := [])
            flat.append(out)
        nodes = np.array(flat, np.float64)
    scale = float(np.abs(np.concatenate([lo, hi])).max()) if n else 0.0
    return Tree(nodes, np.array(order, np.int64), scale, depth)


def outward(nodes: np.ndarray, precision: str) -> np.ndarray:
    """Node rows in the kernel's precision with the boxes rounded outward (lo down, hi up)."""
    if precision == "f64":
        return nodes
    f = nodes.astype(np.float32)
    f[..., 0:3] = directed(nodes[..., 0:3], precision, down=True)
    f[..., 3:6] = directed(nodes[..., 3:6], precision, down=False)
    return f


def _width(kind: str) -> int:
    return 1 << (len(ROW[kind]) - 1).bit_length()


def rows(kind: str, consts, order) -> np.ndarray:
    """The kind's ROW constants in leaf order, zero-padded to a power of two per row."""
    from .accel import LAYOUT
    full = pack(kind, consts)[order]
    out = np.zeros((len(order), _width(kind)))
    for j, name in enumerate(ROW[kind]):
        out[:, j] = full[:, LAYOUT[kind].index(name)]
    return out


@dataclass
class KindBVH:
    kind: str
    rows: object                # Float[count * _width(kind)]: the objects in leaf order
    nodes: object               # Float[n_nodes * NODE]
    count: int                  # nodes
    scale: float                # S
    tree: Tree

    def view(self, T, k, active=True):
        return row_view(T, self.kind, self.rows, k, active)


def row_view(T, kind: str, rows, k, active=True):
    """Row k of a table of ``rows(kind, ...)`` (per ray), as shapes.object_t reads an
    object's constants for rays with an origin: one packet gather."""
    g = dr.gather(packet_type(T), rows, k, active, shape=(_width(kind), dr.width(k)))
    v = dict(zip(ROW[kind], g))
    A3 = T.Array3
    out = SimpleNamespace(kind=kind, id=T.Int32(v["id"]), q=A3(v["qx"], v["qy"], v["qz"]))
    if kind in QUADRICS:
        return quadric_row_view(out, v, A3)
    if kind == "torus":
        out.radius, out.c, out.size = v["radius"], v["c"], (v["w"], v["h"])
        out.n = A3(v["nx"], v["ny"], v["nz"])
    elif kind == "sphere":
        out.radius = v["radius"]
    else:
        out.n, out.g = A3(v["nx"], v["ny"], v["nz"]), v["g"]
        out.xdir = A3(v["xx"], v["xy"], v["xz"])
        out.ydir = A3(v["yx"], v["yy"], v["yz"])
        out.size = (v["w"], v["h"]) if "w" in v else None
        out.c = v.get("c")
    return out


def trees(ks) -> dict:
    """{kind: KindBVH} of the bounded kinds that are looped, by any rays (built once per
    KernelScene)."""
    from . import accel
    cache = ks.__dict__.setdefault("_accel", {})
    if "bvh" not in cache:
        cache["bvh"] = {}
        for kind in accel.BOUNDED:
            # (looped for shadow rays: every kind that any rays loop over)
            if not (ks.by_kind.get(kind) and accel.looped(ks, kind, shadows=True)):
                continue
            consts = ks.by_kind[kind]
            tree = build(*object_boxes(kind, consts))
            T = ks.T
            flat = _upload(T, rows(kind, consts, tree.order))
            nodes = _upload(T, outward(tree.nodes, T.precision))
            cache["bvh"][kind] = KindBVH(kind, flat, nodes, tree.count, tree.scale, tree)
    return cache["bvh"]


def _upload(T, a: np.ndarray):
    """A flat opaque Dr.Jit array of a host table, aligned for packet gathers."""
    return device_array(T.Float, a)


# --- the kernel -------------------------------------------------------------------------------

class _Rays:
    """Per-ray constants of the walk: the first row of the ray's octant's node order, and of
    the slab test: 1/d (±BIG for components below 1/BIG) and the origin moved by ±e,
    e = PAD·(|o|∞ + S)."""

    def __init__(self, T, d, o, scale: float, count: int):
        F, U = T.Float, T.UInt32
        octant = (dr.select(d.x < 0, U(1), U(0)) | dr.select(d.y < 0, U(2), U(0))
                  | dr.select(d.z < 0, U(4), U(0)))
        self.base = octant * dr.opaque(U, count)
        big = BIG[T.precision]
        self.inv = [dr.select(dr.abs(c) > 1 / big, 1 / c, dr.mulsign(dr.opaque(F, big), c))
                    for c in (d.x, d.y, d.z)]
        a = dr.maximum(dr.maximum(dr.abs(o.x), dr.abs(o.y)), dr.abs(o.z))
        e = dr.opaque(F, PAD[T.precision]) * (a + dr.opaque(F, scale))
        self.oa = [c + e for c in (o.x, o.y, o.z)]
        self.ob = [c - e for c in (o.x, o.y, o.z)]
        # 1 + 2γ₃ (pbrt's gamma(3) = 3u/(1 − 3u)) on the far distance
        u = 2.0 ** (-24 if T.precision == "f32" else -53)
        self.far = dr.opaque(F, 1 + 2 * (3 * u / (1 - 3 * u)))


def visit(T, rays: _Rays, nodes, node, limit, active):
    """(enter, a, b) for each ray at ``node``: whether the widened box holds a point of the
    ray with 0 <= t <= limit, and the node's link fields."""
    U = T.UInt32
    g = dr.gather(packet_type(T), nodes, rays.base + node, active,
                  shape=(NODE, dr.width(node)))
    tn, tf = dr.zeros(T.Float, 1), limit
    for i in range(3):
        t1 = (g[i] - rays.oa[i]) * rays.inv[i]
        t2 = (g[3 + i] - rays.ob[i]) * rays.inv[i]
        lo_i = dr.minimum(t1, t2)
        hi_i = dr.maximum(t1, t2) * rays.far
        tn = dr.maximum(tn, lo_i)
        tf = dr.minimum(tf, hi_i)
    return tn <= tf, U(g[6]), U(g[7])


def _step(T, bvh: KindBVH, rays, node, row, end, limit, active):
    """The inner-node step: (node, row, end) after testing ``node``'s box."""
    enter, a, b = visit(T, rays, bvh.nodes, node, limit, active)
    leaf = b > 0
    take = enter & leaf
    row = dr.select(take, a, row)
    end = dr.select(take, a + b, end)
    node = dr.select(leaf | enter, node + 1, a)
    return node, row, end


def closest_kind(ks, kind: str, d, o, rules, skip, st, active=None):
    """accel.closest_kind for rays with an origin, through the kind's BVH (``active``: the
    rays that walk it; the others keep ``st``)."""
    T = ks.T
    U = T.UInt32
    bvh = trees(ks)[kind]
    vz = ks.scene.viewpoint[2]
    rays = _Rays(T, d, o, bvh.scale, bvh.count)
    n = dr.width(d)
    nn = dr.opaque(U, bvh.count)
    grow = dr.opaque(T.Float, 1 + KAPPA)
    st.fresh = False
    def leaf(node, row, end, *state):
        obj = bvh.view(T, row)
        return (node, row + 1, end,
                *tested(d, o, obj, rules, vz, skip, closest_fold(st, obj.id, rules), state))

    def inner(node, row, end, *state):
        limit = state[0] * grow                 # the closest t so far (inf: none)
        node, row, end = _step(T, bvh, rays, node, row, end, limit, True)
        return (node, row, end, *state)

    def body(node, row, end, *state):
        return dr.if_stmt((node, row, end, *state), row < end, leaf, inner,
                          label=f"bvh_{kind}_step")

    zero = dr.zeros(U, n)
    node = zero if active is None else dr.select(active, zero, nn)
    out = dr.while_loop((node, zero, zero, *st.state()),
                        lambda node, row, end, *s: (node < nn) | (row < end), body,
                        labels=("node", "row", "end") + tuple("best_" + k for k in st.names()),
                        label=f"bvh_closest_{kind}")
    return st.set(out[3:])


def occluded_kind(ks, kind: str, d, o, maxt, rules, skip, blocked):
    """accel.occluded_kind through the kind's BVH: rays already ``blocked`` do nothing."""
    T = ks.T
    U = T.UInt32
    bvh = trees(ks)[kind]
    vz = ks.scene.viewpoint[2]
    rays = _Rays(T, d, o, bvh.scale, bvh.count)
    n = dr.width(d)
    nn = dr.opaque(U, bvh.count)
    limit = maxt * dr.opaque(T.Float, 1 + KAPPA)
    def leaf(node, row, end, blk):
        obj = bvh.view(T, row)
        blk, = tested(d, o, obj, rules, vz, skip, blocks(maxt), (blk,))
        return node, row + 1, end, blk

    def inner(node, row, end, blk):
        node, row, end = _step(T, bvh, rays, node, row, end, limit, True)
        return node, row, end, blk

    def body(node, row, end, blk):
        return dr.if_stmt((node, row, end, blk), row < end, leaf, inner,
                          label=f"bvh_{kind}_shadow_step")

    zero = dr.zeros(U, n)
    _, _, _, blocked = dr.while_loop(
        (zero, zero, zero, blocked),
        lambda node, row, end, blk: ((node < nn) | (row < end)) & ~blk, body,
        labels=("node", "row", "end", "blocked"), label=f"bvh_occluded_{kind}")
    return blocked
