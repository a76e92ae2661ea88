"""Closest-hit search over a scene, one vectorized Dr.Jit kernel for all rays.

The kernel holds code only for the object kinds present; objects are grouped by kind and
every number enters as opaque data, so scenes with the same kinds and counts share one
compiled kernel.  Up to accel.UNROLL_MAX objects each gets its own unrolled block (float32
camera rays: up to 1.5 or 2 times that, accel.camera_factor); above, a
kind is one symbolic loop over a table of its objects (with screen-space bins for rays from
the viewpoint; rt_core/accel.py), whose kernel does not depend on the count either.
Surface data (normal, uv) is computed once, for the closest hit only, from
per-object constants gathered by object id.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np

import drjit as dr

from . import accel, backend, cull
from .backend import Types, traced
from .camera import Camera, primary_offsets
from .decide import decide, decide_rays, prepare as prepare_exact
from .rules import Rules
from .scene import Scene, SceneError, locate, written
from .kinds import KIND_CODE, PLANE_KINDS
from .shapes import (ObjectConstants, cone_rays, least, numbers, object_constants,
                     object_t, plane_cone, sphere_cone, sphere_cone_cert, sphere_live, sphere_t)
from .shapes_quadric import is_quadric, quadric_code, quadric_normal
from .shapes_torus import torus_surface

# Unrolled spheres of camera rays, when a scene has at least this many: each behind a
# packet-wide branch past its test when every ray of the packet certainly misses it.
# Measured single-thread in-process: 8 spheres 17% faster, 4 about even to 12%, 2 even,
# 1 sphere twice as slow (docs/speed.md)
SPHERE_BRANCH_MIN = 4
# float64's from one sphere on: its square roots and divisions cost 3-4 times float32's a
# lane (docs/speed.md), so the branch pays sooner.  Finite planes (on their bounding balls)
# from 4 bounded objects on, of any kind: what matters is how much of the view each covers
# (bench scenes, one process: finite planes 3 1.03 of the time, 4 0.84, 16 0.51; mixed 4,
# 2 of them finite planes, 0.91)
BRANCH_MIN = {("sphere", "f32"): SPHERE_BRANCH_MIN, ("sphere", "f64"): 1,
              ("fplane", "f32"): 4, ("fplane", "f64"): 4}

backend.require("llvm")     # fail early, with a message, on an LLVM that would abort kernels


@dataclass
class KernelScene:
    """A scene prepared for one backend/precision: host constants and gather tables."""
    scene: Scene
    T: Types
    consts: list
    by_kind: dict = field(default_factory=dict)

    @property
    def kinds(self) -> tuple:
        return tuple(k for k in KIND_CODE if self.by_kind.get(k))

    def table(self, name: str):
        """Per-object Dr.Jit array of one constant (for gathers by object id)."""
        cache = self.__dict__.setdefault("_tables", {})
        if name not in cache:
            if name in ("w", "h"):          # finite-plane width / height (tile size)
                vals = [c.size[name == "h"] for c in self.consts]
            else:
                vals = [getattr(c, name) for c in self.consts]
            if name == "kind":
                cache[name] = self.T.UInt32([KIND_CODE[v] for v in vals])
            elif isinstance(vals[0], tuple):
                cache[name] = self.T.Array3(*([v[i] for v in vals] for i in range(3)))
            else:
                cache[name] = self.T.Float(vals)
            dr.make_opaque(cache[name])     # a one-object table would be a literal otherwise
        return cache[name]


FLOAT_MAX = {"f32": float(np.finfo(np.float32).max), "f64": float(np.finfo(np.float64).max)}


def prepare(scene: Scene, T: Types) -> KernelScene:
    """Host constants of the scene for one backend/precision.

    Raises SceneError (naming the object's line) when a constant overflows float64 or does
    not fit the kernel's precision: a float32 kernel would turn it into inf and silently
    lose the object."""
    try:
        consts, bigs = _checked_constants(scene)
    except OverflowError:
        consts = bigs = None
    if bigs is None:
        bad = next((o for o in scene.objects if not _finite_obj(scene, o)), scene.objects[0])
        raise _overflow(scene, bad)
    limit = FLOAT_MAX[T.precision]
    for c, big in zip(consts, bigs):
        if big > limit:
            o = scene.objects[c.id]
            raise SceneError(f"{o.kind}: a constant of its intersection test ({big:.3g}) "
                             f"exceeds the {T.precision} range ({limit:.3g})"
                             + ("; render with --precision f64" if T.precision == "f32" else ""),
                             scene.path, o.line or None)  # a product of several fields
    by_kind = {k: [c for c in consts if c.kind == k] for k in KIND_CODE}
    return KernelScene(scene, T, consts, by_kind)


# object_constants of the scenes prepared last (each is frozen; its constants are computed
# in exact arithmetic, ~3 ms a scene, and every render, precision and comparison of a scene
# prepares it again).  They depend on the objects and the viewpoint only: keyed on the
# objects' tuple and the viewpoint, a copy of the scene with another window (compare's
# camera mode, on square pixels) or another path finds them too
_CONSTS: dict = {}


def scene_constants(scene: Scene) -> list:
    """``shapes.object_constants(scene)``, computed once for the scenes prepared last (an
    entry holds its objects' tuple, so its id stays that tuple's)."""
    return _checked_constants(scene)[0]


def _kept(table: dict, scene: Scene, make):
    """``make(scene)``, kept in ``table`` for the last 16 scenes' objects and viewpoint (as
    written): an entry holds its objects' tuple, so its id stays that tuple's; objects in a
    list (which could change under the key) are computed each time."""
    if not isinstance(scene.objects, tuple):
        return make(scene)
    key = (id(scene.objects), written(scene.viewpoint))
    hit = table.get(key)
    if hit is None:
        if len(table) >= 16:
            table.clear()
        hit = table[key] = (scene.objects, make(scene))
    return hit[1]


def _checked_constants(scene: Scene) -> tuple[list, tuple | None]:
    """scene_constants and, per object, the largest magnitude its kernel receives (None
    when any is not finite): prepare's checks, kept with the constants."""
    consts, bigs = _kept(_CONSTS, scene, _make_constants)
    return list(consts), bigs


def _make_constants(scene: Scene):
    consts = tuple(object_constants(scene))
    return consts, _largest(consts)


def _largest(consts) -> tuple | None:
    """max(_magnitudes(c)) per constants c, or None when a magnitude is not finite."""
    if not all(_finite(c) for c in consts):
        return None
    return tuple(max(_magnitudes(c)) for c in consts)


# decide.prepare's exact objects of the scenes decided last, kept as _CONSTS keeps the
# constants: each precision, comparison and render of a scene prepares a KernelScene of its
# own (~0.5 ms a scene in GMP rationals)
_EXACT: dict = {}


def _exact_objects(scene: Scene):
    return _kept(_EXACT, scene, prepare_exact)


def _overflow(scene: Scene, obj) -> SceneError:
    """The error for an object too far from the viewpoint for float64, at whichever of the
    two has the larger coordinate (the one at fault), or at a radius larger than both."""
    name = "center" if hasattr(obj, "center") else "point"
    pos = obj.center if hasattr(obj, "center") else obj.point
    r = getattr(obj, "radius", None)
    if isinstance(r, (int, float)) and abs(r) > max(map(abs, (*pos, *scene.viewpoint))):
        # a radius larger than every coordinate: its square is what overflows
        line, col = locate(obj, "radius")
        return SceneError(f"{obj.kind}: its radius {r:g} squared overflows float64; numbers "
                          "this large are out of range", scene.path, line, col)
    i = max(range(3), key=lambda k: max(abs(pos[k]), abs(scene.viewpoint[k])))
    if abs(scene.viewpoint[i]) >= abs(pos[i]):
        line, col = scene.at_viewpoint(i)
        return SceneError(f"header: the viewpoint is so far from the {obj.kind} on line "
                          f"{obj.line} that their distance overflows float64; numbers this "
                          "large are out of range", scene.path, line, col)
    line, col = locate(obj, name, i)
    return SceneError(f"{obj.kind}: its distance from the viewpoint overflows float64; "
                      "numbers this large are out of range", scene.path, line, col)


def _magnitudes(c: ObjectConstants):
    """Absolute values of every number a kernel receives for object constants ``c`` (the
    certified decisions' bounds, where NaN marks a certain miss, are not among them)."""
    return (abs(x) for x in numbers(c))


def _finite(c: ObjectConstants) -> bool:
    return all(math.isfinite(x) for x in _magnitudes(c))


def _finite_obj(scene: Scene, obj) -> bool:
    try:
        return all(_finite(c) for c in object_constants(
            dataclasses.replace(scene, objects=(obj,))))
    except OverflowError:
        return False


@traced
def closest_hit(ks: KernelScene, d, o=None, rules: Rules = Rules(), skip=None, cam=None,
                dmax: float = 1.0, along=None):
    """(t, object id, hit mask) of the closest hit along o + t·d (o relative to the
    viewpoint; None for rays from the viewpoint).  Misses: t = 0, id = -1.
    ``skip``: per-ray object id to ignore (the surface a secondary ray leaves).
    ``cam``: the camera of the primary rays ``d``; with it, in float64 (``exact_decisions``),
    every decision is certified and the rays the kernel cannot certify are decided exactly
    on the scene's numbers and the ideal ray (rt_core/decide.py).  ``cam="rays"``: the same,
    with the directions ``d`` themselves as the exact rays, ``dmax`` (host) bounding their
    lengths (the bounds hold for |d| <= 1.01·dmax).  ``along``: rays with an origin, the
    directions unnormalized (the reflection before its normalization), which the kernel
    has sooner: the unrolled objects' culls take them (the same lines within a few
    roundings: cull.py's widening covers far more)."""
    T = ks.T
    given, d = d, widened(T, d)
    cert = cam is not None and o is None and exact_decisions(ks)
    if cert and isinstance(cam, str):
        assert cam == "rays", cam
    n = dr.width(d)
    vz = ks.scene.viewpoint[2]
    st = Best(dr.full(T.Float, dr.inf, n), dr.full(T.Int32, -1, n))
    shared = cert and shared_groups(ks)
    scale = (float(dmax) if isinstance(cam, str) else 1.0) if cert else 0.0
    if cert:
        st.certify(T, n, shared)
    # file order is id order within one kind: then no tie term is needed for 'first'
    single_kind = len(ks.kinds) == 1
    near = cone_a = offsets = None
    gos = {}

    def culled(obj, near):
        # (rays with an origin) the lanes that test ``obj``: not leaving it, and not
        # certainly missing its bounding sphere (rt_core/cull.py)
        go = dr.opaque(T.Int32, obj.id) != skip
        reach = cull.may_hit(ks, near, obj.id)
        return go if reach is None else go & reach
    if skip is not None and PRE_CULL:
        # rays with an origin: every unrolled object's cull before the first object's test
        near = cull.Rays(ks, d if along is None else along, o)
        gos = {obj.id: culled(obj, near) for kind in ks.kinds
               if not accel.looped(ks, kind, o is not None, camera=o is None)
               for obj in ks.by_kind[kind]}
    for kind in ks.kinds:
        # many objects: one loop, constants as data
        if accel.looped(ks, kind, o is not None, camera=o is None):
            if offsets is None and BIN_BY_OFFSETS and isinstance(cam, Camera) and \
                    o is None and d.x.state != dr.VarState.Evaluated:
                offsets = primary_offsets(ks.scene, cam, T)
            st = accel.closest_kind(ks, kind, d, o, rules, skip, st, scale,
                                    offsets if o is None else along)
            continue
        for obj in ks.by_kind[kind]:
            oid = dr.opaque(T.Int32, obj.id)
            if skip is not None:
                # (rays with an origin: no certification) a packet whose lanes all leave
                # this object, or certainly miss its bounding sphere (rt_core/cull.py),
                # skips its test
                def test(*state, obj=obj, oid=oid):
                    t, hit = object_t(d, o, obj, rules, vz)
                    s = st.set(state)
                    s.fold(t, hit, oid, rules, single_kind)
                    return s.state()
                if obj.id not in gos:
                    near = near or cull.Rays(ks, d, o)
                    gos[obj.id] = culled(obj, near)
                st.set(dr.if_stmt(st.state(), gos[obj.id], test, lambda *s: s,
                                  label="closest_object"))
                continue
            def test(*state, obj=obj, oid=oid, live=None):
                s = st.set(state)
                res = (object_t(d, o, obj, rules, vz, scale) if live is None else
                       sphere_t(d, o, obj, rules, vz, scale, live))
                # (one object: no ties, so no t bound to carry)
                s.fold(res[0], res[1], oid, rules, single_kind,
                       *((res[2], res[3] if len(ks.consts) > 1 else None,
                          dr.opaque(T.Int32, obj.grp) if shared else None) if cert else ()))
                return s.state()
            if o is not None or not branches(ks, kind):
                st.set(test(*st.state()))
                continue
            # a camera ray's sphere or finite plane: a packet whose rays all certainly
            # miss skips the test (a sphere's two square roots and division, a plane's
            # division) and the fold, by one dot product against the cone of the object's
            # ball: its own (shapes.sphere_cone; certified, sphere_cone_cert) or its
            # bounding ball's (shapes.plane_cone); else by sphere_live, whose |q×d|² and
            # r√a the test reuses
            if cone_a is None:              # (once: each if_stmt starts a new scope)
                cone_a = cone_rays(d, scale if cert else None)
            if kind != "sphere":
                cone = plane_cone(d, obj, *cull.bounding(ks)[obj.id], T.precision, cone_a)
            elif cert:
                cone = sphere_cone_cert(d, obj, T.precision, cone_a)
            else:
                cone = sphere_cone(d, obj, T.precision, cone_a)
            if cone is not None:
                st.set(dr.if_stmt(st.state(), cone, test, lambda *s: s,
                                  label=f"{kind}_object"))
                continue
            if kind != "sphere":
                st.set(test(*st.state()))
                continue
            live = sphere_live(d, obj, scale)
            st.set(dr.if_stmt(st.state(), live.mask, functools.partial(test, live=live),
                              lambda *s: s, label="sphere_object"))
    if cert:
        return _decide_flagged(ks, cam, rules, st, given)
    hit = st.id >= 0
    return dr.select(hit, st.t, 0), st.id, hit


# Camera rays (a Camera given) whose directions are not evaluated find their bins
# (accel._range) by the pixels' window offsets, of which the directions are the normalized
# values: the same line, so the same bin but within a few roundings, far inside the bins'
# MARGIN (accel.py); the lookup then need not wait for the normalization.  float64, 1920
# columns, same process, median of 11, closest hits: 64 spheres 12.31 -> 11.38 ms, 64 finite
# planes 16.6 -> 14.12, mixed 64 17.74 -> 15.25, 4096 spheres 21.14 -> 19.91.
BIN_BY_OFFSETS = True
# Rays with an origin (reflections): every unrolled object's cull (cull.may_hit) is made
# before the first object's test, so that none waits for the branches before it (shaded
# bench f32, same process, median of 9, images identical: finite planes 16 0.97 of the
# time, spheres 16 0.98-0.99, mixed 16 0.99), and from the unnormalized reflection where
# given (``along``: finite planes 16 0.96-0.97, spheres 16 0.98-0.99, mixed 16 0.98-0.99)
PRE_CULL = True


def widened(T: Types, d):
    """Directions for T's kernels: ``d`` itself, or float32 directions (an ``Array3f`` of
    the same backend) for a float64 kernel, widened there (exactly: every float32 is a
    float64), so that a float64 kernel traces float32 rays reading what a float32 one reads
    (``rtval bench``'s identical rays) instead of a float64 copy twice the size."""
    if isinstance(d, T.Array3):
        return d
    narrow = getattr(T.module, "Array3f")
    assert T.precision == "f64" and isinstance(d, narrow), \
        f"expected {T.Array3.__name__} (or, for float64, {narrow.__name__}) directions"
    return T.Array3(d)


def branches(ks: KernelScene, kind: str) -> bool:
    """Do the unrolled objects of ``kind`` sit behind camera rays' branches (``BRANCH_MIN``)?
    Spheres by their count, finite planes by the count of every bounded object."""
    need = BRANCH_MIN.get((kind, ks.T.precision))
    if need is None:
        return False
    n = len(ks.by_kind[kind]) if kind == "sphere" else \
        sum(len(ks.by_kind.get(k, ())) for k in accel.BOUNDED)
    return n >= need


def shared_groups(ks: KernelScene) -> bool:
    """Do two objects lie on the same plane (or are the same sphere)?  (Once per
    KernelScene: a set over every object, ~1 ms at 4096.)"""
    got = ks.__dict__.get("_shared_groups")
    if got is None:
        got = ks.__dict__["_shared_groups"] = len({c.grp for c in ks.consts}) < len(ks.consts)
    return got


def exact_decisions(ks: KernelScene) -> bool:
    """Whether primary rays get certified, exact decisions: float64 unless turned off."""
    return ks.T.precision == "f64" and ks.__dict__.get("exact_decisions", True)


class Best:
    """The running closest hit of a batch of rays, and with ``certify`` what proves it: the
    winner's t bound and group, the least lower bound ``lo2`` of the other hits, and the
    rays flagged for an exact decision."""

    def __init__(self, t, id):
        self.t, self.id = t, id
        self.cert = False
        self.fresh = True           # no object folded in yet

    def certify(self, T, n, shared: bool = True):
        self.cert = True
        self.shared = shared
        # the winner's lower bound t·lf (lf: its lower factor, shapes.py), carried as a
        # product so that the loop multiplies once per object
        self.tl = dr.full(T.Float, dr.inf, n)
        self.grp = dr.full(T.Int32, -1, n) if shared else None
        # the least lower bound of the other hits; −inf marks a ray to decide exactly
        self.lo2 = dr.full(T.Float, dr.inf, n)

    def names(self):
        if not self.cert:
            return ("t", "id")
        return ("t", "id", "tl", "lo2") + (("grp",) if self.shared else ())

    def state(self):
        return tuple(getattr(self, k) for k in self.names())

    def set(self, values):
        for k, v in zip(self.names(), values):
            setattr(self, k, v)
        return self

    def fold(self, t, hit, oid, rules: Rules, single_kind=False, possible=None, lf=None,
             grp=None):
        """Take object ``oid``'s hit at t into the running closest hit: smaller t wins; an
        exact tie goes to the smaller id ('first') or the larger ('last').  Certified:
        ``hit`` is the certain hit, ``possible`` the possible one (shapes.py)."""
        if rules.ties == "first":
            better = t < self.t
            if not single_kind:
                better |= (t == self.t) & (oid < self.id)
        else:
            better = t <= self.t if single_kind else (
                (t < self.t) | ((t == self.t) & (oid > self.id)))
        upd = hit & better
        old = None
        if self.cert:
            # a winner is certain when its upper bound is below every other hit's lower
            # bound, except hits on the same plane or sphere (equal t: the tie rule decides;
            # ``grp`` is None when no two objects share a plane or sphere)
            # an unsure object (possible, not certain) sets lo2 = −inf: the ray is flagged
            unsure = dr.select(possible, type(t)(-dr.inf), type(t)(dr.inf))
            tl = t * lf if lf is not None else t
            if self.fresh:
                # the first object: no other hit yet
                self.fresh = False
                self.tl = dr.select(upd, tl, self.tl)
                self.lo2 = dr.select(hit, self.lo2, unsure)
                if grp is not None:
                    self.grp = dr.select(upd, grp, self.grp)
            elif grp is None:
                # the displaced winner, or this hit, joins the others (inf before a hit)
                lo = dr.select(upd, self.tl, dr.select(hit, tl, unsure))
                # (lo is never NaN: a winner's or a certain hit's t·lf, inf or −inf; a
                # select, not dr.minimum: see shapes.least)
                self.lo2 = _least(self.lo2, lo)
                self.tl = dr.select(upd, tl, self.tl)
            else:
                uns = possible & ~hit
                # (NaN only on lanes the selects drop: see above)
                old = dr.select((self.id >= 0) & (self.grp != grp),
                                _least(self.lo2, self.tl), self.lo2)
                new = dr.select(hit & (grp != self.grp), _least(self.lo2, tl), self.lo2)
                self.grp = dr.select(upd, grp, self.grp)
            if old is not None:
                self.lo2 = dr.select(uns, -dr.inf, dr.select(upd, old, new))
                self.tl = dr.select(upd, tl, self.tl)
        self.t = dr.select(upd, t, self.t)
        self.id = dr.select(upd, oid, self.id)


def _least(a, b):
    return least(a, b, True)


FLAG_SLOTS = 4096
# flagged rays are counted per block of 2**FLAG_SHIFT rays in the trace kernel, and listed
# from the blocks that hold one (FLAG_BLOCKS of them at most; more: the whole image)
FLAG_SHIFT = 12
FLAG_BLOCKS = 64


def _flagged(T, oid, per_block: np.ndarray) -> np.ndarray:
    """The indices of the rays with id −2, given their count in each block of 2**FLAG_SHIFT
    rays.  From up to FLAG_BLOCKS blocks: their ids read back and searched on the host (a
    kernel over those blocks only, 0.02 ms for one against 0.6 ms for a pass over 2 M
    rays); else up to FLAG_SLOTS listed by one pass (an atomic slot per flagged lane; a third
    of what dr.compress's passes cost, and kept out of the trace kernel, where its scatter
    would cost every ray); else compress."""
    nflag = int(per_block.sum())
    if nflag == 0:
        return np.zeros(0, np.int64)
    n = dr.width(oid)
    blocks = np.flatnonzero(per_block)
    if len(blocks) <= FLAG_BLOCKS:
        size = 1 << FLAG_SHIFT
        ids = backend.host_view(oid)
        if ids is not None:
            # (the LLVM backend's ids are host memory: their blocks searched in place, no
            # kernel and no wait for one: 0.17 against 0.27 ms in a 2 M-ray image, where
            # the caches are cold after the trace kernel)
            return np.concatenate([np.flatnonzero(ids[b:b + size] == -2) + b
                                   for b in (blocks << FLAG_SHIFT).tolist()])
        # the lanes of the listed blocks, made in the kernel (its code is the same for any
        # blocks: their list has at least two entries, never a literal)
        U = T.UInt32
        starts = blocks << FLAG_SHIFT
        lane = dr.arange(U, (len(blocks) + 1) * size)
        first = dr.gather(U, U(np.r_[starts, starts[-1]].tolist()), lane >> FLAG_SHIFT)
        idx = first + (lane & (size - 1))
        got = dr.gather(T.Int32, oid, idx, idx < n).numpy()[:len(blocks) * size]
        lanes = (starts[:, None] + np.arange(size)[None]).ravel()
        return lanes[got == -2].astype(np.int64)
    if nflag > FLAG_SLOTS:
        return dr.compress(oid == -2).numpy()
    flag = oid == -2
    count = dr.zeros(T.UInt32, 1)
    slot = dr.scatter_inc(count, T.UInt32(0), flag)
    listed = dr.zeros(T.UInt32, FLAG_SLOTS)
    dr.scatter(listed, dr.arange(T.UInt32, dr.width(oid)), slot, flag)
    dr.eval(listed)
    return np.sort(listed.numpy()[:nflag].astype(np.int64))


def _decide_flagged(ks: KernelScene, cam, rules: Rules, st: Best, d):
    """Replace the flagged rays' answers by the exact ones (rt_core/decide.py).  ``d``: the
    directions as closest_hit was given them (``cam="rays"``: the exact rays, read back at
    the flagged rays, float32 ones widened exactly)."""
    T = ks.T
    # [t·lf, t + (t − t·lf)] holds the exact t with room to spare (KB is twice the rounding
    # count), so intervals that merely touch are apart; a miss's upper end is inf, flagged
    # only at −inf
    flag = dr.select(st.id >= 0, st.t + (st.t - st.tl), dr.inf) > st.lo2
    t = dr.select(st.id >= 0, st.t, 0)
    # flagged rays carry id −2: one int output instead of two masks (Dr.Jit's LLVM kernels
    # write several mask outputs slowly)
    oid = dr.select(flag, -2, st.id)
    # count the flagged rays per block in the same kernel (an atomic add on flagged lanes
    # only)
    n = dr.width(oid)
    count = dr.zeros(T.UInt32, max(2, -(-n >> FLAG_SHIFT)))
    # (ReduceMode.Local: a packet's lanes add up before one atomic each; Dr.Jit's default
    # on LLVM gives each thread a copy of the counts and adds the copies in a kernel of its
    # own, 4% of a 4-sphere image: docs/speed.md)
    dr.scatter_reduce(dr.ReduceOp.Add, count, T.UInt32(1),
                      dr.arange(T.UInt32, n) >> FLAG_SHIFT, flag, mode=dr.ReduceMode.Local)
    dr.eval(t, oid, count)
    pix = _flagged(T, oid, count.numpy())
    ks.__dict__["decided"] = len(pix)
    if not len(pix):
        # (nothing to scatter: no kernel, 4% of a 4-sphere image's time; docs/speed.md)
        return t, oid, oid >= 0
    objs = ks.__dict__.get("_exact_objects")
    if objs is None:
        objs = ks.__dict__["_exact_objects"] = _exact_objects(ks.scene)
    if isinstance(cam, str):                 # the traced directions are the exact rays
        view = [backend.host_view(c) for c in (d.x, d.y, d.z)]
        if all(v is not None for v in view):
            # (read in place, as the ids above: no gather kernel)
            E = np.stack([np.asarray(v[pix], np.float64) for v in view], 1)
        else:
            g = dr.gather(type(d), d, T.UInt32(pix.astype(np.uint32).tolist()))
            E = np.stack([np.asarray(c.numpy(), np.float64) for c in (g.x, g.y, g.z)], 1)
        ids, ts = decide_rays(ks.scene, rules, E.tolist(), objs=objs)
    else:
        ids, ts = _decided(ks.scene, cam, rules, pix + cam.row0 * cam.columns, objs)
    # scattered into the arrays by one kernel, with two masked-off lanes added (so that it
    # never has one lane, a literal: its code is the same for any count)
    live = np.r_[np.ones(len(pix), bool), False, False]
    pix, ids, ts = np.r_[pix, 0, 0], np.r_[ids, -1, -1], np.r_[ts, 0.0, 0.0]
    # (from lists: Dr.Jit's own, aligned memory; numpy's alignment would change the
    # kernel)
    idx, mask = T.UInt32(pix.astype(np.uint32).tolist()), T.Bool(live.tolist())
    tv = T.Float(np.where(ids >= 0, ts, 0.0).tolist())
    iv = T.Int32(ids.astype(np.int32).tolist())
    dr.eval(idx, mask, tv, iv)
    dr.scatter(t, tv, idx, mask)
    dr.scatter(oid, iv, idx, mask)
    dr.eval(t, oid)                                 # one small kernel
    return t, oid, oid >= 0


# exact answers of camera rays, kept across renders of one scene: renders that differ only in
# shading (the distance cut-off, a tile or reflection variant) flag the same rays
_DECIDED: dict = {}
GEOMETRY_RULES = ("t_min", "screen_clip", "clip_spheres", "edges", "ties")


def forget_decisions() -> None:
    """Drop the exact answers kept across renders (``rtval bench`` times a render's own)."""
    _DECIDED.clear()


def _decided(scene, cam, rules: Rules, pix, objs):
    key = (id(scene), cam.columns, cam.rows, cam.sampling, cam.row_shift,
           tuple(getattr(rules, k) for k in GEOMETRY_RULES))
    entry = _DECIDED.get(key)
    if entry is None:                   # (an entry holds its scene: its id is not reused)
        if len(_DECIDED) > 16:
            _DECIDED.clear()
        entry = _DECIDED[key] = (scene, {})
    known = entry[1]
    todo = np.array([p for p in pix.tolist() if p not in known], np.int64)
    if len(todo):
        ids, ts = decide(scene, cam.columns, cam.rows, cam.sampling, rules, todo, objs,
                         cam.row_shift)
        known.update(zip(todo.tolist(), zip(ids.tolist(), ts.tolist())))
    out = [known[p] for p in pix.tolist()]
    return np.array([o[0] for o in out], np.int32), np.array([o[1] for o in out])


def surface(ks: KernelScene, d, t, oid, hit, o=None):
    """Normal (plane normal as given, or outward sphere normal) and uv (finite/tiled plane
    lasthit, else 0) at the closest hit; zeros on a miss."""
    T = ks.T
    kinds = ks.kinds
    idx = T.UInt32(dr.select(hit, oid, 0))
    q = dr.gather(T.Array3, ks.table("q"), idx, hit)
    if o is not None:
        q = q - o
    zero = dr.zeros(T.Array3, dr.width(d))
    normal = zero
    u = v = dr.zeros(T.Float, dr.width(d))
    kind = dr.gather(T.UInt32, ks.table("kind"), idx, hit) if len(kinds) > 1 else None
    if any(k in PLANE_KINDS for k in kinds):
        n = dr.gather(T.Array3, ks.table("n"), idx, hit)
        normal = n
    if "sphere" in kinds:
        ns = dr.normalize(dr.fma(d, t, -q))
        normal = ns if kind is None else dr.select(kind == KIND_CODE["sphere"], ns, normal)
    if any(is_quadric(k) for k in kinds):          # rt_core/shapes_quadric.py
        nq = quadric_normal(ks, d, t, idx, hit, o)
        isq = True if kind is None else quadric_code(kind)
        normal = nq if kind is None and len(kinds) == 1 else dr.select(isq, nq, normal)
    framed = [k for k in ("fplane", "tplane", "triangle", "disk") if k in kinds]
    if framed:
        # the kinds whose uv is the frame's (a triangle's: barycentric; rt_core/planar.py)
        planar = True
        if kind is not None:
            planar = kind == KIND_CODE[framed[0]]
            for k in framed[1:]:
                planar |= kind == KIND_CODE[k]
        # the seed's newhit.xy as u·(n·d) = ŷ·(q×d), v·(n·d) = −x̂·(q×d) (see shapes.py),
        # one correctly rounded division each
        c = dr.cross(q, d)
        den = dr.dot(n, d)
        xd = dr.gather(T.Array3, ks.table("xdir"), idx, hit)
        yd = dr.gather(T.Array3, ks.table("ydir"), idx, hit)
        u = dr.select(planar, dr.dot(yd, c) / den, 0)
        v = dr.select(planar, -dr.dot(xd, c) / den, 0)
        if "fplane" in kinds:
            # the inside test decided without dividing: keep the quotient in the rectangle
            fp = True if kind is None else (kind == KIND_CODE["fplane"])
            w = dr.gather(T.Float, ks.table("w"), idx, hit)
            h = dr.gather(T.Float, ks.table("h"), idx, hit)
            u = dr.select(fp, dr.clip(u, 0, w), u)
            v = dr.select(fp, dr.clip(v, 0, h), v)
    if "torus" in kinds:
        normal, u, v = torus_surface(ks, d, t, q, idx, hit, kind, normal, u, v)
    normal = dr.select(hit, normal, zero)
    return normal, dr.select(hit, u, 0), dr.select(hit, v, 0)


def position(ks: KernelScene, d, t, hit, o=None):
    """World position viewpoint + o + t·d of the hit; zeros on a miss."""
    T = ks.T
    V = T.Array3(*(dr.opaque(T.Float, c) for c in ks.scene.viewpoint))
    rel = d * t if o is None else dr.fma(d, t, o)
    return dr.select(hit, V + rel, dr.zeros(T.Array3, dr.width(d)))


def shadow_cells(ks: KernelScene, o, maxt, skip, toward, active=None) -> dict:
    """{kind: its light-bin rows} of the shadow rays from ``o`` toward the light ``toward``
    (as ``occluded`` would look them up: its ``cells``), read on the ``active`` lanes.  The
    shading makes every light's before the first light's search: each lookup waits for its
    division and gather, and made between the loops each would wait for the loop before it
    too (shaded bench, f32, same process, median of 9, images identical, three
    measurements: finite planes 16 0.92 of the time, mixed 16 0.88-0.89, spheres 16
    0.96-0.99, spheres 256 0.94-0.97)."""
    from . import lightbins
    return {kind: lightbins.cells(ks, kind, o, maxt, skip, toward, active)
            for kind in ks.kinds if accel.light_binned(ks, kind, o)}


@traced
def occluded(ks: KernelScene, d, o, maxt, rules: Rules = Rules(), skip=None, active=None,
             toward=None, cells=None):
    """Shadow-ray test: mask of the rays o + t·d that hit any object (other than ``skip``)
    at 0 < t < ``maxt``, with the same hit functions and rules as ``closest_hit``.  No t, no
    id, no tie order: the first level of the intersection only.

    ``active``: the lanes that cast a shadow ray (the others answer False): a looped kind's
    loop ends them at once, and a packet of lanes none of which is active skips the tests
    (a symbolic ``dr.if_stmt``).
    ``toward``: the point light the rays go to (host, relative to the viewpoint), for rays
    made as the shading makes them (d = unit(C − o) and maxt = |C − o| in the kernel's
    precision, C ``toward`` rounded to it): many objects are then searched through bins of
    directions around the light (rt_core/lightbins.py); ``cells``: ``shadow_cells`` of these
    rays, made before."""
    T = ks.T
    assert isinstance(d, T.Array3), f"expected {T.Array3.__name__} directions"
    vz = ks.scene.viewpoint[2]

    def search(blocked):
        for kind in ks.kinds:
            if accel.looped(ks, kind, shadows=True):
                blocked = accel.occluded_kind(ks, kind, d, o, maxt, rules, skip, blocked,
                                              toward, (cells or {}).get(kind))
                continue
            for obj in ks.by_kind[kind]:
                def test(b, obj=obj):
                    t, hit = object_t(d, o, obj, rules, vz)
                    return (b | (hit & (t < maxt)),)
                if skip is None:
                    blocked = test(blocked)[0]
                    continue
                # a packet whose lanes all leave this object skips its test
                blocked = dr.if_stmt((blocked,), dr.opaque(T.Int32, obj.id) != skip, test,
                                     lambda b: (b,), label="occluded_object")[0]
        return blocked

    if active is None:
        return search(dr.zeros(T.Bool, dr.width(d)))
    # inactive lanes start 'blocked' (a loop's condition ends them), and answer False
    return dr.if_stmt((~active,), active, lambda b: (search(b),), lambda b: (b,),
                      label="occluded_active")[0] & active
