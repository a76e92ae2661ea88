"""A slow, obviously correct per-ray float64 oracle of the course tracer's geometry.

(Lives in the library so that ``rtval report`` can measure errors against it; the tests import
it as ``tests.oracle``.)

Written straight from the notes (shared/notes/course-format.md and the finite-plane chapter),
independently of rt_core's Dr.Jit tracer: plain Python floats, one ray and one object at a time,
every formula in the order the notes give it.  numpy is used only to assemble the images.

Beside each value the oracle carries a first-order rounding-error bound (class ``EF``), so that a
disagreement with a float32/float64 vectorised tracer can be explained instead of hidden:

* ``err.*`` arrays: for every output value, a bound on its rounding error in units of the unit
  roundoff ``u`` of whatever precision computes it (``u = 2**-24`` for f32, ``2**-53`` for f64),
  assuming every input that is not a float32 number and every operation is rounded once
  (Wilkinson's running error bound; see ``EF``).  A tracer in precision p should agree within a
  small multiple of ``u_p * err``.
* margins (``edge_margin``, ``tie_gap``, ``clip_margin``, ``tmin_margin``, ``graze``,
  ``disc_margin``): the distance of a decided quantity from its threshold divided by that
  quantity's error bound (so a relative measure: |n·d|/err for ``graze``, disc/err for
  ``disc_margin``, (t2 − t1)/(err1 + err2) for ``tie_gap``, ...).  A decision with margin m can
  flip in precision p only if m < u_p (times the safety factor of the caller's tolerance
  table); ``inf`` means no decision at risk, or one computed exactly.  Only decisions that
  could change the pixel count: the winner's tests (any one flipping loses it), and for a miss
  not behind the winner the cheapest way to gain it (all of its failed tests flipping); each
  object adds that one margin to the diagnostic of the test it names.  Two objects with the
  same plane equation (normal, point) or the same sphere tie exactly in any precision: the tie
  rule decides, so that tie is not a risk.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from rt_core.kinds import PLANE_KINDS, dispatch
from rt_core.rules import Rules

from . import quadric
from . import oracle_planar
from .geometry import given_normal, normal, pow2_scaled, unit
from .torus_oracle import torus_hits, torus_obj, torus_surface, torus_tests

INF = math.inf
OFF = 10000.0           # the notes' tile-parity offset


# --- a float64 value with a first-order rounding-error bound --------------------------------

def _f32_exact(x: float) -> bool:
    """True if x is a float32 number (so no precision rounds it when it is read)."""
    try:
        return struct.unpack("f", struct.pack("f", x))[0] == x
    except OverflowError:
        return False


def _pow2(x: "EF") -> bool:
    """An exact ±2^k (or 0): multiplying or dividing by it rounds nothing."""
    return x.e == 0.0 and (x.v == 0.0 or math.frexp(abs(x.v))[0] == 0.5)


def _ef(v: float, e: float) -> "EF":
    """An EF from a float64 value and its bound, without __init__'s checks (the arithmetic's
    results: the oracle spends most of its time making these)."""
    r = _new(EF)
    r.v = v
    r.e = e
    return r


_new = object.__new__


class EF:
    """``v``: the float64 value; ``e``: bound on its rounding error, in units of u.

    ``EF(x)`` is an input read from a file: exact if x is a float32 number, else rounded once
    (e = |x|); ``EF(x, 0.0)`` is exact.  Arithmetic follows the float64 operations exactly for
    ``v`` and adds, for ``e``, the propagated errors plus one rounding of the result, except
    where every implementation is exact whatever its formula: adding an exact 0, multiplying
    or dividing by an exact power of two, x − x of exact operands.
    """
    __slots__ = ("v", "e")

    def __init__(self, v: float, e: float | None = None):
        self.v = float(v)
        self.e = (0.0 if _f32_exact(self.v) else abs(self.v)) if e is None else e

    def __repr__(self):
        return f"EF({self.v!r}, e={self.e:.3g})"

    @staticmethod
    def of(x) -> "EF":
        return x if type(x) is EF else EF(x, 0.0)

    def __add__(self, o):
        if type(o) is not EF:
            o = EF(o, 0.0)
        v = self.v + o.v
        if self.e == 0.0 and self.v == 0.0:
            return _ef(v, o.e)
        if o.e == 0.0 and o.v == 0.0:
            return _ef(v, self.e)
        return _ef(v, self.e + o.e + abs(v))

    __radd__ = __add__

    def __sub__(self, o):
        # self + (−o), written out
        if type(o) is not EF:
            o = EF(o, 0.0)
        v = self.v + -o.v
        if self.e == 0.0 and self.v == 0.0:
            return _ef(v, o.e)
        if o.e == 0.0 and o.v == 0.0:
            return _ef(v, self.e)
        return _ef(v, self.e + o.e + abs(v))

    def __rsub__(self, o):
        return EF.of(o) - self

    def __neg__(self):
        return _ef(-self.v, self.e)

    def __mul__(self, o):
        if type(o) is not EF:
            o = EF(o, 0.0)
        a, b = self.v, o.v
        v = a * b
        e = abs(a) * o.e + abs(b) * self.e
        # a rounding unless one factor is an exact power of two (_pow2, inlined)
        if (self.e == 0.0 and (a == 0.0 or math.frexp(abs(a))[0] == 0.5)) or \
                (o.e == 0.0 and (b == 0.0 or math.frexp(abs(b))[0] == 0.5)):
            return _ef(v, e)
        return _ef(v, e + abs(v))

    __rmul__ = __mul__

    def __truediv__(self, o):
        o = EF.of(o)
        q = self.v / o.v
        e = (self.e + abs(q) * o.e) / abs(o.v)
        return _ef(q, e if _pow2(o) else e + abs(q))

    def __rtruediv__(self, o):
        return EF.of(o) / self


def esqrt(x: EF) -> EF:
    s = math.sqrt(x.v)
    if x.e == 0.0 and s * s == x.v and Fraction(s) ** 2 == x.v:
        return _ef(s, 0.0)          # an exact square's root (|n̂| = 1 of an axis): exact
    return EF(s, (x.e / (2.0 * s) if s > 0 else (0.0 if x.e == 0 else INF)) + s)


def vec(p, exact: bool = False):
    """A 3-vector of EF: inputs from a file (rounded once) unless ``exact``."""
    return tuple(c if isinstance(c, EF) else EF(c, 0.0 if exact else None) for c in p)


def vals(p) -> tuple:
    return tuple(c.v for c in p)


def errs(p) -> tuple:
    return tuple(c.e for c in p)


# --- vector helpers written as the course's vl_* functions ----------------------------------

def dot3(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def diff3(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def sum3(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def scale3(s, a):
    return (s * a[0], s * a[1], s * a[2])


def length3(a):
    return esqrt(dot3(a, a))


def unit3(a):
    n = length3(a)
    return (a[0] / n, a[1] / n, a[2] / n)


def cross3(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def xform3(m, a):
    """m · a with rows m[0], m[1], m[2]; a new tuple (the notes' aliasing bug cannot happen)."""
    return (dot3(m[0], a), dot3(m[1], a), dot3(m[2], a))


# --- camera ---------------------------------------------------------------------------------

def _primary_ray_ef(scene, x, y, W, H, sampling="corners"):
    ww, wh = EF(scene.window[0]), EF(scene.window[1])
    if sampling == "corners":
        if W < 2 or H < 2:
            raise ValueError(f"corner sampling needs at least 2x2 pixels, got {W}x{H}")
        wx = EF(x, 0.0) / EF(W - 1, 0.0) * ww - ww / 2.0
        wy = EF(y, 0.0) / EF(H - 1, 0.0) * wh - wh / 2.0
    elif sampling == "centers":
        wx = (EF(x, 0.0) + 0.5) / EF(W, 0.0) * ww - ww / 2.0
        wy = (EF(y, 0.0) + 0.5) / EF(H, 0.0) * wh - wh / 2.0
    else:
        raise ValueError(f"sampling must be 'corners' or 'centers', not {sampling!r}")
    world = (wx, wy, EF(0.0, 0.0))
    base = vec(scene.viewpoint)
    return base, unit3(diff3(world, base))


def primary_ray(scene, x, y, W, H, sampling="corners"):
    """(base, dir) as float tuples for column x, row y (y = 0 is the BOTTOM row)."""
    base, d = _primary_ray_ef(scene, x, y, W, H, sampling)
    return vals(base), vals(d)


# --- objects prepared once: EF inputs ---------------------------------------------------------

@dataclass
class _Obj:
    idx: int
    kind: str
    src: object
    key: tuple                       # identical key => identical t computation (exact ties)
    normal: tuple = ()
    point: tuple = ()
    rotmat: tuple = ()
    size: tuple = ()
    center: tuple = ()
    radius: EF | None = None


def _sphere_obj(i, o):
    return _Obj(i, o.kind, o, ("s", tuple(o.center), o.radius),
                center=vec(o.center), radius=EF(o.radius))


def _scaled(v):
    """A direction as inputs rounded once, scaled by a power of two (exactly) so that its
    squared length neither overflows nor underflows (a normal 1e200 0 1)."""
    return tuple(EF(s, 0.0 if _f32_exact(float(c)) else None)
                 for c, s in zip(v, pow2_scaled(v, rounded=True)))


def _plane_obj(i, o):
    """The normal computed here from the numbers as written (mitsuba_ref/geometry.py), then
    taken as an input rounded once (as a tracer's host would round it); a finite or tiled
    plane's rotmat (x̂ = unit(ô − (ô·n̂)n̂), ŷ = n̂ × x̂, n̂) in EF arithmetic from the
    numbers as written, so that its bound holds the cancellation of ô − (ô·n̂)n̂ where the
    orient is nearly the normal (rounded once, its error was taken as u: a helper's fuzzing
    found 7 pixels decided against the exact oracle 100× outside that bound)."""
    n = normal(o)
    p = _Obj(i, o.kind, o, ("p", n, tuple(o.point)), normal=vec(n), point=vec(o.point))
    if o.kind in ("fplane", "tplane"):
        ne, oe = unit3(_scaled(given_normal(o))), unit3(_scaled(o.orient))
        x = unit3(diff3(oe, scale3(dot3(oe, ne), ne)))
        p.rotmat = (x, unit3(cross3(ne, x)), ne)
        p.size = (EF(o.size[0]), EF(o.size[1]))
    return p


def _quadric_obj(i, o):
    return quadric.prepare(i, o, _Obj, vec, EF)


def _planar_obj(i, o):
    return oracle_planar.prepare(i, o, _Obj, vec, EF)


_PREPARE = {"sphere": _sphere_obj, "plane": _plane_obj, "fplane": _plane_obj,
            "tplane": _plane_obj, "cylinder": _quadric_obj, "cone": _quadric_obj,
            "ellipsoid": _quadric_obj, "triangle": _planar_obj, "disk": _planar_obj,
            "torus": torus_obj}


def _prepare(scene):
    """The objects' numbers as written, and the normal and frame computed here."""
    return [dispatch(_PREPARE, o.kind)(i, o) for i, o in enumerate(scene.objects)]


_prep_cache: dict = {}


def prepared(scene):
    k = id(scene)
    hit = _prep_cache.get(k)
    if hit is None or hit[0] is not scene:
        hit = (scene, _prepare(scene))
        _prep_cache.clear()
        _prep_cache[k] = hit
    return hit[1]


# --- per-kind hit functions (the notes, literally) ----------------------------------------------

@dataclass
class Cand:
    """One object's verdict for one ray, with the numbers a decision depended on."""
    ok: bool                 # a valid hit under the rules
    t: EF | None = None      # the (near) root, also for invalid hits when defined
    hitloc: tuple = ()
    newhit: tuple = ()       # rotmat · (hitloc − point) for fplane/tplane
    ndotd: EF | None = None
    disc: EF | None = None
    why: str = ""            # for a miss: 'parallel', 'tmin', 'clip', 'edge', 'disc'
    outline: EF | None = None    # a cylinder's outline, well conditioned (quadric.outline)


def _clipped(z: EF, rules: Rules) -> bool:
    if rules.screen_clip == ">":
        return z.v > 0.0
    if rules.screen_clip == ">=":
        return z.v >= 0.0
    return False


def plane_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """Infinite plane: n·d == 0 misses; t = (n·P − n·base)/(n·d) must exceed t_min; then the
    screen clip on hitloc.z."""
    n = ob.normal
    ndotd = dot3(n, d)
    if ndotd.v == 0.0:
        return Cand(False, ndotd=ndotd, why="parallel")
    t = (dot3(n, ob.point) - dot3(n, base)) / ndotd
    hitloc = sum3(base, scale3(t, d))
    if not t.v > rules.t_min:
        return Cand(False, t, hitloc, ndotd=ndotd, why="tmin")
    if _clipped(hitloc[2], rules):
        return Cand(False, t, hitloc, ndotd=ndotd, why="clip")
    return Cand(True, t, hitloc, ndotd=ndotd)


def _inside(newhit, size, rules: Rules) -> bool:
    u, v = newhit[0].v, newhit[1].v
    w, h = size[0].v, size[1].v
    if rules.edges == "closed":
        return 0.0 <= u <= w and 0.0 <= v <= h
    return 0.0 < u < w and 0.0 < v < h


def fplane_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """plane_hits, then newhit = rotmat · (hitloc − point) must lie in [0,w] × [0,h]."""
    c = plane_hits(ob, base, d, rules)
    if c.t is None:
        return c
    c.newhit = xform3(ob.rotmat, diff3(c.hitloc, ob.point))
    if c.ok and not _inside(c.newhit, ob.size, rules):
        c.ok, c.why = False, "edge"
    return c


def tplane_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """The infinite plane; newhit.xy are the tile coordinates."""
    c = plane_hits(ob, base, d, rules)
    if c.t is not None:
        c.newhit = xform3(ob.rotmat, diff3(c.hitloc, ob.point))
    return c


def sphere_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """a = d·d, b = 2 d·(base − c), c = |base − c|² − r²; disc ≤ 0 misses; only the near root
    t = (−b − √disc)/2a, t ≤ 0 misses; the screen clip only if rules.clip_spheres."""
    oc = diff3(base, ob.center)
    a = dot3(d, d)
    b = 2.0 * dot3(d, oc)
    c = dot3(oc, oc) - ob.radius * ob.radius
    disc = b * b - 4.0 * a * c
    if not disc.v > 0.0:
        # the root where the discriminant would vanish: where a flip would put the hit
        t = -b / (2.0 * a)
        return Cand(False, t, sum3(base, scale3(t, d)), disc=disc, why="disc")
    t = (-b - esqrt(disc)) / (2.0 * a)
    hitloc = sum3(base, scale3(t, d))
    if not t.v > 0.0:
        return Cand(False, t, hitloc, disc=disc, why="tmin")
    if rules.clip_spheres and _clipped(hitloc[2], rules):
        return Cand(False, t, hitloc, disc=disc, why="clip")
    return Cand(True, t, hitloc, disc=disc)


def quadric_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """Cylinder, cone, ellipsoid (mitsuba_ref/quadric.py)."""
    return quadric.hits(ob, base, d, rules, Cand, EF, esqrt,
                        (dot3, diff3, sum3, scale3, cross3, length3))


def planar_hits(ob: _Obj, base, d, rules: Rules) -> Cand:
    """plane_hits, then the triangle's or disk's extent test (mitsuba_ref/oracle_planar.py);
    newhit holds the uv."""
    c = plane_hits(ob, base, d, rules)
    if c.t is None:
        return c
    inside, c.slacks, c.newhit = oracle_planar.extent(ob, c.hitloc, rules,
                                                      (dot3, diff3, cross3))
    if c.ok and not inside:
        c.ok, c.why = False, "edge"
    return c


# kinds whose invalid hit has a place to be taken at (trace's ``flip``)
FLIPPABLE = ("plane", "fplane", "tplane", "sphere", "triangle", "disk")
HITS = {"plane": plane_hits, "fplane": fplane_hits, "tplane": tplane_hits,
        "sphere": sphere_hits, "cylinder": quadric_hits, "cone": quadric_hits,
        "ellipsoid": quadric_hits, "triangle": planar_hits, "disk": planar_hits,
        "torus": torus_hits}


def tile_scale(tplane, rules: Rules = Rules()) -> float:
    """u's factor under the variant that leaves xdir unprojected: u' = unit(xdir)·(hit −
    point) = |p|·u, p the projected unit xdir (1 with the notes' projection)."""
    if rules.tile_project:
        return 1.0
    n, x = normal(tplane), unit(tplane.orient)
    c = sum(a * b for a, b in zip(n, x))
    return math.sqrt(max(1.0 - c * c, 0.0))


def tile_foreground(tplane, u: float, v: float, rules: Rules = Rules()) -> bool:
    """The tiled plane's MAT choice: foreground iff floor(OFF + u/w) + floor(OFF + v/h) is odd
    (variants: floor((OFF + u)/w); u scaled by ``tile_scale``)."""
    w, h = tplane.size
    u = u * tile_scale(tplane, rules)
    if rules.tile_add_first:
        relx, rely = math.floor((OFF + u) / w), math.floor((OFF + v) / h)
    else:
        relx, rely = math.floor(OFF + u / w), math.floor(OFF + v / h)
    return (relx + rely) % 2 == 1


# --- decision margins ---------------------------------------------------------------------------

def _margin(slack: float, err: float) -> float:
    """|slack| / err; an exactly computed quantity (err == 0) can never flip: inf."""
    if err == 0.0:
        return INF
    return abs(slack) / err


def _edge_margin(c: Cand, ob: _Obj, base, d, rules: Rules) -> float:
    """How far the inside/outside verdict is from flipping, in units of its error bound.
    Inside: the nearest of the four edges.  Outside: every violated edge must flip, so the
    farthest violated one.

    Each slack (u, w − u, v, h − v) is judged twice: as the notes compute it (from the hit
    point), and times n·d in the division-free form u·(n·d) = ŷ·(q × d), v·(n·d) = −x̂·(q × d)
    with q = point − base (the same predicate: only the sign of n·d, which t > t_min already
    tests, relates the two).  The larger margin counts: near n·d = 0 the first-order bound of
    the hit-point form is useless (u is huge either way), while the division-free form stays
    well-conditioned.  Unless the two forms' values fall on different sides: then float64
    evaluations of the same predicate disagree, and the smaller margin counts (a ray through
    a closed edge exactly, x·(n·d) = 0 computed exactly and u = −3e−16 from the hit point:
    a tracer computing u as the notes do takes the other side, and was called wrong)."""
    u, v = c.newhit[0], c.newhit[1]
    w, h = ob.size
    nd = c.ndotd
    qxd = cross3(diff3(ob.point, base), d)
    su, sv = dot3(ob.rotmat[1], qxd), -dot3(ob.rotmat[0], qxd)
    swu, shv = w * nd - su, h * nd - sv
    slacks = ((u.v, u.e, su), (w.v - u.v, u.e + w.e, swu),
              (v.v, v.e, sv), (h.v - v.v, v.e + h.e, shv))
    sign = 1.0 if nd.v > 0.0 else -1.0              # x = slack · (n·d)
    if rules.edges == "closed":
        ok = [s >= 0.0 for s, _, _ in slacks]
        free = [sign * x.v >= 0.0 for _, _, x in slacks]
    else:
        ok = [s > 0.0 for s, _, _ in slacks]
        free = [sign * x.v > 0.0 for _, _, x in slacks]
    ms = [(max if good == other else min)(_margin(s, e), _margin(x.v, x.e))
          for (s, e, x), good, other in zip(slacks, ok, free)]
    if all(ok):
        return min(ms)
    return max(m for m, good in zip(ms, ok) if not good)


def _tests(ob: _Obj, c: Cand, base, d, rules: Rules) -> list:
    """Every test of the object's verdict as (diagnostic, passed, margin), evaluated on the same
    numbers as the verdict (also the tests the literal code skipped after an earlier miss)."""
    if ob.kind == "torus":
        return torus_tests(ob, c, rules)
    out = []
    clip = rules.screen_clip != "off" and (ob.kind in PLANE_KINDS or rules.clip_spheres)
    if ob.kind in quadric.KINDS:
        out.append(("disc_margin", c.disc.v > 0.0, quadric.outline_margin(c, _margin)))
        if c.disc.v > 0.0:
            out.append(("tmin_margin", c.t.v > 0.0, _margin(c.t.v, c.t.e)))
            if c.newhit and c.t.v > 0.0:
                sl = quadric.axis_slacks(c)
                ok = [v >= 0.0 for v, _ in sl]
                ms = [_margin(v, e) for v, e in sl]
                out.append(("edge_margin", all(ok), min(ms) if all(ok) else
                            max(m for m, g in zip(ms, ok) if not g)))
        if not (c.disc.v > 0.0 and c.t.v > 0.0 and c.why != "edge"):
            clip = False
    elif ob.kind == "sphere":
        out.append(("disc_margin", c.disc.v > 0.0, _margin(c.disc.v, c.disc.e)))
        out.append(("tmin_margin", c.t.v > 0.0, _margin(c.t.v, c.t.e)))
    else:
        out.append(("graze", c.ndotd.v != 0.0, _margin(c.ndotd.v, c.ndotd.e)))
        if c.t is None:
            return out
        tmin = EF(rules.t_min)
        out.append(("tmin_margin", c.t.v > tmin.v, _margin(c.t.v - tmin.v, c.t.e + tmin.e)))
    if clip:
        z = c.hitloc[2]
        out.append(("clip_margin", not _clipped(z, rules), _margin(z.v, z.e)))
    if ob.kind == "fplane":
        out.append(("edge_margin", _inside(c.newhit, ob.size, rules),
                    _edge_margin(c, ob, base, d, rules)))
    if ob.kind in ("triangle", "disk"):
        # each slack against its own bound: the nearest inside, the farthest failed outside
        ok = [(s.v >= 0.0) if rules.edges == "closed" else (s.v > 0.0) for s in c.slacks]
        ms = [_margin(s.v, s.e) for s in c.slacks]
        out.append(("edge_margin", all(ok), min(ms) if all(ok) else
                    max(m for m, good in zip(ms, ok) if not good)))
    assert all(p for _, p, _ in out) == c.ok, (ob, c, out)
    return out


def _clip_test(rules: Rules):
    """The screen clip of a quadric's root as a test (name, passed, margin), None where the
    rules clip no quadric."""
    if not (rules.clip_spheres and rules.screen_clip != "off"):
        return lambda c: None
    return lambda c: ("clip_margin", not _clipped(c.hitloc[2], rules),
                      _margin(c.hitloc[2].v, c.hitloc[2].e))


def _at_risk(tests: list, valid: bool) -> tuple:
    """(diagnostic, margin) of the cheapest flip of the verdict: a valid hit is lost if any test
    flips; an invalid one is gained only if every failed test flips."""
    if valid:
        return min(((m, k) for k, _, m in tests))[::-1]
    return max(((m, k) for k, p, m in tests if not p))[::-1]


# --- trace -------------------------------------------------------------------------------------

@dataclass
class Hit:
    hit: bool = False
    t: float = 0.0
    id: int = -1
    normal: tuple = (0.0, 0.0, 0.0)
    position: tuple = (0.0, 0.0, 0.0)
    uv: tuple = (0.0, 0.0)
    # rounding-error bounds (units of u) of t, position, normal, uv
    err_t: float = 0.0
    err_position: tuple = (0.0, 0.0, 0.0)
    err_normal: tuple = (0.0, 0.0, 0.0)
    err_uv: tuple = (0.0, 0.0)
    # decision margins (see the module docstring); inf = no decision at risk
    edge_margin: float = INF
    tie_gap: float = INF
    clip_margin: float = INF
    tmin_margin: float = INF
    graze: float = INF
    disc_margin: float = INF
    cands: list = field(default_factory=list, repr=False)
    # (object index, margin) of each object whose verdict could change the answer: its
    # cheapest flip (the winner's for a near tie) -- what ``trace(flip=...)`` may toggle
    risks: list = field(default_factory=list, repr=False)


def trace(scene, base, dir, rules: Rules = Rules(), skip=None, flip=frozenset()) -> Hit:
    """Closest valid hit of the ray base + t·dir over ``scene.objects`` (except index ``skip``).

    ``base``/``dir`` are float triples (taken as inputs rounded once) or EF triples.  Ties in t
    go to the earlier object (rules.ties == 'first') or the later one ('last').
    ``flip``: objects whose verdict is taken the other way (a decision within its bound taken
    as another precision may take it: shade_oracle.other_sides); an invalid hit is taken at
    the t its failed test computed (FLIPPABLE kinds, a t at all, not a sphere's tangent
    point), else ValueError.
    """
    base, d = vec(base), vec(dir)
    obs = prepared(scene)
    cands = []
    win = wc = None                 # the winner and its Cand
    for ob in obs:
        if ob.idx == skip:
            cands.append(None)
            continue
        c = HITS[ob.kind](ob, base, d, rules)
        cands.append(c)
        ok = c.ok
        if ob.idx in flip and getattr(c, "roots", None):
            # an open quadric: its cheapest other answer (the other root, or a miss); the
            # diagnostics stay the computed answer's, as for the other kinds
            c = quadric.risk(c, _margin, _clip_test(rules))[2]
            ok = c.ok
        elif ob.idx in flip:
            # (a sphere missed by its discriminant has no first-order place to be hit: a
            # float64 tracer whose disc comes out positive hits it √disc/2a, about √u of
            # the distance, from the tangent point, and what it reflects or shadows there
            # lies beyond every first-order bound -- a review built two such images)
            if not ok and (c.t is None or ob.kind not in FLIPPABLE or c.why == "disc"):
                raise ValueError(f"object {ob.idx}: no hit to take")
            ok = not ok
        if not ok:
            continue
        if win is None or c.t.v < wc.t.v or (c.t.v == wc.t.v and rules.ties == "last"):
            win, wc = ob.idx, c

    hit = Hit(cands=cands)
    if win is not None:
        ob, c = obs[win], wc
        hit.hit, hit.id, hit.t, hit.err_t = True, win, c.t.v, c.t.e
        hit.position, hit.err_position = vals(c.hitloc), errs(c.hitloc)
        n = dispatch(_SURFACE, ob.kind)(ob, c, hit)
        hit.normal, hit.err_normal = vals(n), errs(n)
    _diagnose(hit, obs, cands, win, base, d, rules, wc)
    return hit


def _flat(ob, c, hit):
    return ob.normal


def _flat_uv(ob, c, hit):
    """The plane's normal; the hit's (u, v) in its frame."""
    hit.uv, hit.err_uv = (c.newhit[0].v, c.newhit[1].v), (c.newhit[0].e, c.newhit[1].e)
    return ob.normal


def _torus_normal(ob, c, hit):
    n, hit.uv, hit.err_uv = torus_surface(ob, c)
    return n


_SURFACE = {   # the winner's normal (EF), per kind; where the kind has them, hit.uv set too
    "sphere": lambda ob, c, hit: unit3(diff3(c.hitloc, ob.center)),
    "plane": _flat,
    **{k: _flat_uv for k in ("tplane", "fplane", "triangle", "disk")},
    "torus": _torus_normal,
    **{k: (lambda ob, c, hit: quadric.normal(ob, c, unit3, diff3)) for k in quadric.KINDS},
}


def _diagnose(hit: Hit, obs, cands, win, base, d, rules: Rules, wc=None) -> None:
    """Margins of the decisions that could change this ray's answer: the winner's tests, the
    tests of each miss whose (near) t is not behind the winner, and near-ties with the winner.
    Each object contributes its cheapest flip (see _at_risk) to that flip's diagnostic."""
    tw = (wc or cands[win]).t if win is not None else None
    for ob, c in zip(obs, cands):
        if c is None or (c.ok and ob.idx != win):
            # a valid hit behind the winner: only a near-tie can matter (an identical surface
            # ties exactly in any precision, and the rule decides)
            if c is not None and win is not None and ob.key != obs[win].key:
                m = _margin(c.t.v - tw.v, c.t.e + tw.e)
                hit.tie_gap = min(hit.tie_gap, m)
                hit.risks.append((win, m))          # (the winner lost: the other wins)
            continue
        if ob.idx != win:
            if c.t is None:
                # exactly parallel: a flip puts the hit at a huge t, which only matters if
                # nothing else is hit and the object is unbounded
                if win is not None or ob.kind in ("fplane", "triangle", "disk"):
                    continue
            elif tw is not None and min(abs(r.t.v) for r in getattr(c, "roots", [c])) > \
                    tw.v + 1e-4 * (tw.v + tw.e + c.t.e):
                continue                             # behind the winner: cannot matter
        if getattr(c, "roots", None):       # an open quadric's two roots
            key, m, _ = quadric.risk(c, _margin, _clip_test(rules))
        else:
            key, m = _at_risk(_tests(ob, c, base, d, rules), c.ok)
        setattr(hit, key, min(getattr(hit, key), m))
        hit.risks.append((ob.idx, m))


# --- images ------------------------------------------------------------------------------------

GEOMETRY_KEYS = ("hit.mask", "depth.Z", "object.id", "normal.X", "normal.Y", "normal.Z",
                 "position.X", "position.Y", "position.Z", "uv.U", "uv.V")
DIAG_KEYS = ("edge_margin", "tie_gap", "clip_margin", "tmin_margin", "graze", "disc_margin")


def _pixel(scene, x: int, y: int, W: int, H: int, sampling: str, rules: Rules) -> dict:
    """Oracle values (GEOMETRY_KEYS, 'err.<key>', DIAG_KEYS) of column x, row y (0 = bottom);
    None for the values of a miss."""
    base, d = _primary_ray_ef(scene, x, y, W, H, sampling)
    h = trace(scene, base, d, rules)
    out = {k: getattr(h, k) for k in DIAG_KEYS}
    if not h.hit:
        return out
    px = {"hit.mask": (1.0, 0.0), "depth.Z": (h.t, h.err_t), "object.id": (float(h.id), 0.0)}
    for i, a in enumerate("XYZ"):
        px["normal." + a] = (h.normal[i], h.err_normal[i])
        px["position." + a] = (h.position[i], h.err_position[i])
    px["uv.U"], px["uv.V"] = (h.uv[0], h.err_uv[0]), (h.uv[1], h.err_uv[1])
    for k, (val, err) in px.items():
        out[k] = val
        out["err." + k] = err
    return out


def _empty(keys, shape) -> dict:
    out = {k: np.zeros(shape, np.float64) for k in keys}
    out["object.id"][...] = -1
    return out


ALL_KEYS = GEOMETRY_KEYS + tuple("err." + k for k in GEOMETRY_KEYS) + DIAG_KEYS


def render_oracle(scene, columns: int, rows: int | None = None, sampling: str = "corners",
                  rules: Rules = Rules()) -> dict:
    """Per-pixel oracle images (H, W), row 0 = TOP: GEOMETRY_KEYS as render_geometry gives them,
    'err.<key>' (error bounds in units of u, 0 where exact or missed) and DIAG_KEYS."""
    W = int(columns)
    H = scene.default_rows(W) if rows is None else int(rows)
    out = _empty(ALL_KEYS, (H, W))
    for y in range(H):
        r = H - 1 - y                                # image row 0 is world row y = H-1
        for x in range(W):
            for k, v in _pixel(scene, x, y, W, H, sampling, rules).items():
                out[k][r, x] = v
    return out


def oracle_pixels(scene, columns: int, rows: int | None, index, sampling: str = "corners",
                  rules: Rules = Rules()) -> dict:
    """The oracle at some pixels only: ``index`` holds flat image-order pixel indices (row 0
    the top, as ``render_geometry``'s arrays ravel); returns flat arrays of ALL_KEYS, one value
    per index.  For large images, where ``render_oracle`` would take hours."""
    W = int(columns)
    H = scene.default_rows(W) if rows is None else int(rows)
    index = np.asarray(index, np.int64)
    out = _empty(ALL_KEYS, (len(index),))
    for j, i in enumerate(index):
        r, x = divmod(int(i), W)
        for k, v in _pixel(scene, x, H - 1 - r, W, H, sampling, rules).items():
            out[k][j] = v
    return out
