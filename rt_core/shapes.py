"""Shape kernels, type-generic over Dr.Jit backend and precision, in two levels:

* ``*_t``: distance t and a hit mask for a batch of rays (what the closest-hit search needs),
  and with ``cert`` the certified decisions (below);
* surface data (normal, uv) for the closest hit only, in rt_core/tracer.py ``surface``.

Every quantity is taken relative to the ray origin.  Per-object constants are computed once on
the host (``ObjectConstants``), each rounded once from its exact value on the scene's numbers
as written: q = anchor − viewpoint (the plane's corner or the sphere's centre), the unit
normal and frame, n·q, and for spheres |q|² − r².  Primary rays start at the viewpoint, so
they use these directly; other rays pass their origin ``o`` relative to the viewpoint.

Finite-plane bounds: the seed's ``newhit = rotmat · (hit − point)`` equals, for
hit = o + t·d with t = n·q'/(n·d) and q' = q − o (Binet–Cauchy identity),

    u = ŷ · (q' × d) / (n·d),      v = −x̂ · (q' × d) / (n·d),

which never forms the absolute hit point, so it does not cancel catastrophically when the
plane is small and far away.  The bounds are tested without dividing, ``0 <= u·|n·d| <=
w·|n·d|`` with ``u·|n·d| = ŷ·(q'×d)·sign(n·d)``: every comparison is then monotone in one
rounded quantity, so a ray exactly through an edge that the arithmetic represents exactly is
decided exactly (``u·(1/(n·d))`` rounds twice and can land past w).  For rays from the
viewpoint a hit has sign(n·d) = sign(n·q) (t > 0), a host constant: the sign is folded into
ŷ, x̂, w, h (and the screen clip's constants) and costs nothing per ray.

Numerical choices measured against the exact oracle (mitsuba_ref/exact.py, tools/harness/stability.py):

* screen clip: the sign of the hit's z·(n·d) = V.z·(n·d) + (n·q)·d.z is taken as
  V.z·(n.x d.x + n.y d.y) + g·d.z with the host constant g = n·q + n.z V.z = n·P − n.x V.x −
  n.y V.y (rounded once): the n.z V.z d.z terms, which cancel, are gone; for a plane nearly
  parallel to the window the old form lost z to ~u·V.z, four orders above its condition.
  (Same operation count: n.x d.x + n.y d.y is the first part of n·d.)
* sphere: the distance of the centre from the ray is |q × d|/|d|, not |q − d(q·d)/|d|²|, whose
  error along the ray adds in quadrature (for a ray along an axis the cross product is exact);
* host constants are rounded once from exact values (``Fraction``, 40-digit ``Decimal`` for
  the square roots): n·q of a plane through the viewpoint is exactly 0 (t = 0, a miss), and
  objects on the same plane (the same exact plane equation, up to orientation) get the same
  n and n·q up to sign, so they tie exactly and the tie rule decides, as in exact arithmetic;
* n·d and the clip's sum are plain products and sums, no unpaired fma: exactly opposite
  products cancel to 0 (a ray parallel to the plane: t = ±inf or NaN, rejected by
  ``t < inf``).
"""
from __future__ import annotations

import dataclasses
import functools
import decimal
import math
from dataclasses import dataclass
from fractions import Fraction
from types import SimpleNamespace

import drjit as dr
import numpy as np

from .rules import Rules
from .scene import Scene, Sphere, exact

from .kinds import dispatch


@dataclass(frozen=True)
class ObjectConstants:
    """Host float64 constants of one object (relative to the viewpoint)."""
    id: int
    kind: str
    q: tuple                 # anchor − viewpoint (plane point / sphere centre)
    n: tuple = (0.0, 0.0, 0.0)
    nq: float = 0.0          # n·q
    xdir: tuple = (0.0, 0.0, 0.0)
    ydir: tuple = (0.0, 0.0, 0.0)
    size: tuple = (0.0, 0.0)  # fplane w h, tplane tile w h
    radius: float = 0.0
    c: float = 0.0           # sphere |q|² − r²
    g: float = 0.0           # plane kinds: n·q + n.z·viewpoint.z, for the screen clip
    grp: int = 0             # objects of one group are the same plane or sphere: equal t
    # bounds of the certified decisions (see "Certified decisions" below), for unit rays
    bz: float = 0.0          # plane kinds: the clip's z·|n·d|
    bm: float = 0.0          # fplane: u·|n·d| >= 0, v·|n·d| >= 0, u <= w, v <= h (one bound)
    bo: float = 0.0          # sphere: outline r√a − |q×d| and front q·d; for t's bound
    # bo + √(the discriminant's error): the error of b' + √disc (bs)
    bs: float = 0.0


_CTX = decimal.Context(prec=40, Emax=10 ** 6, Emin=-10 ** 6)


def rounded(num: Fraction, den2: Fraction = Fraction(1)) -> float:
    """num / √den2 from exact rationals, rounded once to float64 (40 digits first: the double
    rounding is below 10⁻²³ of an ulp).  Equal exact values give equal floats, and opposite
    ones opposite floats: objects that are the same plane get the same constants."""
    with decimal.localcontext(_CTX):
        dec = lambda f: decimal.Decimal(f.numerator) / decimal.Decimal(f.denominator)
        v = dec(Fraction(num))
        if den2 != 1:
            v /= dec(Fraction(den2)).sqrt()
        return float(v)


def _canonical(N):
    """N scaled so that its largest component is ±1 (sign kept): parallel normals with the
    same orientation give the same triple."""
    m = max(abs(c) for c in N)
    return tuple(c / m for c in N)


def object_constants(scene: Scene) -> list[ObjectConstants]:
    """Every constant is rounded once from the exact value on the scene's numbers as written
    (``exact``), so each has a relative error of at most one rounding (unit vectors: two),
    and a constant that is exactly 0 is 0: the error bounds of the kernels' certified
    decisions rest on this (module docstring)."""
    V = tuple(exact(c) for c in scene.viewpoint)
    out = []
    groups = {}                 # exact plane or sphere -> group number (same t on every ray)
    for i, o in enumerate(scene.objects):
        if o.kind in QUADRIC_KINDS:                 # rt_core/shapes_quadric.py
            out.append(quadric_constants(i, o, V, groups))
            continue
        if o.kind in ("triangle", "disk"):          # rt_core/shapes_planar.py
            out.append(_planar().planar_constants(i, o, V, groups, scene.viewpoint[2]))
            continue
        if o.kind == "torus":
            out.append(torus_constants(i, o, V, groups))
            continue
        if isinstance(o, Sphere):
            Q = tuple(exact(c) - v for c, v in zip(o.center, V))
            r = exact(o.radius)
            q = tuple(rounded(c) for c in Q)
            grp = groups.setdefault(("s", Q, r), len(groups))
            c = rounded(dot_x(Q, Q) - r * r)
            out.append(ObjectConstants(i, o.kind, q, radius=o.radius, c=c, grp=grp,
                                       **_sphere_bounds(q, o.radius, c)))
            continue
        N = _canonical(tuple(exact(c) for c in (getattr(o, "given_normal", ()) or o.normal)))
        NN = dot_x(N, N)
        P = tuple(exact(c) for c in o.point)
        Q = tuple(c - v for c, v in zip(P, V))
        n = tuple(rounded(c, NN) for c in N)
        NQ = dot_x(N, Q)
        # hit z·(n·d) = V.z (n·d) + (n·q) d.z = V.z (n.x d.x + n.y d.y) + g·d.z
        g = rounded(NQ + N[2] * V[2], NN)
        Nk = tuple(_sg(N) * c for c in N)          # orientation dropped: the plane itself
        grp = groups.setdefault(("p", Nk, dot_x(Nk, P)), len(groups))
        xd = yd = (0.0, 0.0, 0.0)
        if o.kind in ("fplane", "tplane"):
            O = tuple(exact(c) for c in o.orient)
            p = tuple(c * NN - dot_x(O, N) * nc for c, nc in zip(O, N))
            PP = dot_x(p, p)
            y = cross_x(N, p)
            xd = tuple(rounded(c, PP) for c in p)
            yd = tuple(rounded(c, PP * NN) for c in y)
        size = getattr(o, "size", (0.0, 0.0))
        q = tuple(rounded(c) for c in Q)
        out.append(ObjectConstants(i, o.kind, q, n, rounded(NQ, NN), xd, yd, size, g=g,
                                   grp=grp, **_plane_bounds(scene.viewpoint[2], q, n, g, xd,
                                                            yd, size)))
    return out


BOUND_FIELDS = ("bz", "bm", "bo", "bs")


# The certified decisions' bounds, for rays with |d| <= 1 (unit directions): each is the
# bound KB·u·f_abs of "Certified decisions" below with every |d_i| replaced by 1, so a
# constant per object; KD adds room for |n|, |d| a few units above 1.
KD = 1.01


def _plane_bounds(vz, q, n, g, X, Y, size) -> dict:
    k = KB * U64 * KD
    out = {"bz": k * (abs(vz) * (abs(n[0]) + abs(n[1])) + abs(g))}
    if any(X):
        aq = [abs(c) for c in q]
        # |(q×d)_i| <= |q_j| + |q_k|
        cab = (aq[1] + aq[2], aq[2] + aq[0], aq[0] + aq[1])
        an = sum(abs(c) for c in n)
        bu = k * sum(abs(y) * c for y, c in zip(Y, cab))
        bv = k * sum(abs(x) * c for x, c in zip(X, cab))
        # one bound for the four edges (bw >= bu, bh >= bv): they are tested as one
        out["bm"] = max(bu + 2 * k * abs(size[0]) * an, bv + 2 * k * abs(size[1]) * an)
    return out


def _sphere_bounds(q, r, c) -> dict:
    k = KB * U64 * KD
    nq = math.sqrt(sum(x * x for x in q))
    bo = k * (r + 3 * nq)
    # bo also bounds the front test's q·d (Σ|q_i d_i| <= √3|q| <= 3|q|): one constant for both
    ed = 4 * bo * (r + nq + bo)             # the discriminant (ra − cn)(ra + cn)
    bs = bo + math.sqrt(ed)
    if not c > 0:
        # the viewpoint inside or on the sphere (exact on the host): the near root is <= 0,
        # a certain miss; a NaN bound fails both comparisons of the outline test
        bo = math.nan
    # t's bound is t·(bs·t/c + K u): one constant bs/c
    return {"bo": bo, "bs": bs if c > 0 else 0.0}


def _first(N) -> int:
    return next(k for k, c in enumerate(N) if c != 0)


def _sg(N) -> int:
    return 1 if N[_first(N)] > 0 else -1


def dot_x(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross_x(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


# --- helpers ---------------------------------------------------------------------------------

def opaque3(Array3, v):
    """A host vector as an opaque Dr.Jit value (data, not a literal baked into the kernel);
    a Dr.Jit vector (constants gathered per ray, rt_core/accel.py) passes through."""
    if isinstance(v, Array3):
        return v
    F = dr.value_t(Array3)
    return Array3(*(dr.opaque(F, float(c)) for c in v))


def opaque(F, v):
    """A host number as an opaque Dr.Jit value; a Dr.Jit array passes through."""
    return v if isinstance(v, F) else dr.opaque(F, v)


# The least of two decision values as a select (compare and blend): dr.minimum is IEEE
# 754-2019 minimum, NaN-propagating, which LLVM lowers to ~8 instructions on AVX2 and which
# cost exact f64 10-15% of its speed.  The select drops a NaN, so it serves only where no
# value can be NaN: every host number of the object (and the viewpoint's z) is at most
# TAME in magnitude, so that the sums of a few products of two of them with |d| <= 1.01
# that the decisions compute stay finite (no inf − inf).  Checked on the host (``tame``);
# an untamed object keeps dr.minimum.
TAME = 2.0 ** 500


def tame(obj, vz: float) -> bool:
    """Are ``obj``'s host numbers and ``vz`` within TAME (table rows: checked when packed)?"""
    if abs(vz) > TAME:
        return False
    if hasattr(obj, "tame"):                 # a KindTable row (rt_core/accel.py)
        return obj.tame
    return all(abs(x) <= TAME for x in numbers(obj))


def numbers(c):
    """Every number of object constants ``c`` that the kernels compute with (not its
    certified bounds)."""
    for f in dataclasses.fields(c):
        if f.name in BOUND_FIELDS:
            continue
        v = getattr(c, f.name)
        if isinstance(v, tuple):
            yield from v
        elif isinstance(v, float):
            yield v


def least(a, b, tamed: bool):
    """min(a, b): a select where neither can be NaN (``tamed``), else dr.minimum."""
    return dr.select(b < a, b, a) if tamed else dr.minimum(a, b)


def _check(d):
    Array3 = type(d)
    assert dr.size_v(Array3) == 3 and dr.is_float_v(Array3), "d must be a Dr.Jit Array3"
    F = dr.value_t(Array3)
    return F, dr.mask_t(F)


# --- level 1: t and mask -----------------------------------------------------------------------
#
# Certified decisions (``cert``: the largest |d| of the rays, 1 for the camera's; rays from
# the viewpoint): each function returns t, the masks ``certain`` (a hit in exact arithmetic
# for sure: the hit mask) and ``possible`` (a hit in exact arithmetic is possible: the verdict
# is unsure where possible & ~certain), and ``lf``, t's certified lower factor: on a hit
# (t > 0) the exact t lies in [t·lf, t·(2 − lf)] (lf = 1 − t's relative bound, rounded
# down within the slack of KB: one product per hit gives the lower bound).
#
# A value f computed from inputs with componentwise relative errors (host constants: one
# rounding from the exact value, ``object_constants``; ray components: a few units, the
# camera's double-float sample and the normalisation's product, the common scale factor
# being irrelevant to every decision) and k rounded operations is within
# (Σ input errors + k)·u·f_abs of the exact value on the scene's numbers and the ideal ray,
# f_abs being f with every term replaced by its absolute value.  Every decision here needs at
# most 16 units; KB = 32 covers it twice.  With |d_i| <= |d| <= 1 each f_abs is bounded by a
# constant of the object (``_plane_bounds``, ``_sphere_bounds``), so a bound costs no work per
# ray; a constant that is 0 (a plane in z = 0: n.x = n.y = g = 0) makes its decision certain.
# rt_core/decide.py decides the flagged rays exactly.

U64 = 2.0 ** -53
KB = 32.0


def _scaled(b, cert):
    """A bound for rays with |d| <= KD·cert (``cert``: 1 for the camera's unit rays, else the
    largest length of the given rays); every bound is proportional to |d|."""
    return b if cert == 1 else b * cert


class _Cert:
    """Running 'certainly passes' and 'possibly passes' masks of one object's decisions.  A
    decision on value v (exactly within b of the computed one) certainly passes iff
    v >= b (v > b if the rule is strict) and possibly passes iff v >= −b.  The object is a
    certain hit iff every decision certainly passes, and unsure iff every decision possibly
    passes but not all certainly: the verdict of a certain ray is the computed one."""

    def __init__(self, certain, possible):
        self.certain, self.possible = certain, possible

    def test(self, F, v, b, strict: bool):
        if isinstance(b, (int, float)):     # opaque: the kernel does not depend on it
            b, nb = dr.opaque(F, b), dr.opaque(F, -b)
        else:
            nb = -b
        self.add((v > b) if strict else (v >= b), (v > nb) if strict else (v >= nb))

    def add(self, certain, possible):
        """One more decision, as its own 'certainly passes' and 'possibly passes' masks."""
        self.certain = certain if self.certain is True else self.certain & certain
        self.possible = possible if self.possible is True else self.possible & possible

    def split(self):
        """(certain hit, possible hit): unsure is possible & ~certain"""
        return self.certain, self.possible


class _Least:
    """The decisions of the certified fast path (rays from the viewpoint, t_min = 0, signs
    folded so that every decision is 'value > 0' or 'value >= 0'), as one test: their least
    value against the largest of their host bounds (a larger bound is still a bound).
    Certain iff least > bound, possible iff least >= −bound: a strict decision's 'possible'
    and a non-strict one's 'certain' are taken one rounding wider, which flags (never
    misdecides) rays whose value is exactly ± the bound.  A bound that is per-ray data
    (a table row's, possibly exactly 0) is tested on its own (``sep``), with its strictness."""

    def __init__(self, v, b: float, tamed: bool):
        self.v, self.b, self.tamed = v, b, tamed
        self.sep = _Cert(True, True)

    def add(self, v, b, strict: bool = False):
        if isinstance(b, (int, float)):
            self.v, self.b = least(self.v, v, self.tamed), max(self.b, b)
        else:
            self.sep.test(type(v), v, b, strict)

    def split(self):
        F = type(self.v)
        c, p = self.sep.split()
        certain, possible = self.v > dr.opaque(F, self.b), self.v >= dr.opaque(F, -self.b)
        return (certain if c is True else certain & c, possible if p is True else possible & p)


def _fast(obj, rules: Rules, o, cert) -> bool:
    """Is the certified fast path open to this object?  Rays from the viewpoint, t > 0, and
    sign(n·q) known: on the host (unrolled objects; not 0, a plane through the viewpoint:
    t = 0), or folded into a table's rows (rt_core/accel.py ``fold_signs``)."""
    if not (cert and o is None and rules.t_min == 0):
        return False
    if isinstance(obj.nq, (int, float)):
        return obj.nq != 0
    return getattr(obj, "folded", False)


def _signed(obj):
    """(s, n·q·s) with s = sign(n·q) still to fold (1 for rows folded already)."""
    if isinstance(obj.nq, (int, float)):
        sg = -1.0 if obj.nq < 0 else 1.0
        return sg, abs(obj.nq)
    return 1.0, obj.nq


def _fold(sg, v):
    return tuple(sg * c for c in v) if isinstance(v, tuple) else v


def _plane_fast(d, obj, rules: Rules, vz: float, cert):
    """_plane's certified work on the fast path: with s = sign(n·q) folded into n, a hit has
    den = s·(n·d) > 0 and t = |n·q|/den; the clip's value is −z·den.  Returns (t, den, the
    decisions as a ``_Least`` or None for a certain miss, t's bound)."""
    F, B = _check(d)
    sg, anq = _signed(obj)
    n = opaque3(type(d), _fold(sg, obj.n))
    # n·d as plain products and sums (no unpaired fma, see _plane), sign-folded (exactly)
    nd_xy = n.x * d.x + n.y * d.y
    den = nd_xy + n.z * d.z
    inv_den = dr.rcp(den)
    t = opaque(F, anq) * inv_den
    bden = KB * U64 * KD * cert
    lf = dr.fma(-inv_den, bden, 1 - KB * U64)           # used on hits only (t, den > 0)
    dec = _Least(den, bden, tame(obj, vz))
    if rules.screen_clip != "off":
        bz = _scaled(obj.bz, cert)
        if isinstance(bz, (int, float)) and bz == 0:
            # n.x = n.y = g = 0 (or V.z = g = 0): z·den is exactly 0 on every ray
            if rules.screen_clip == ">=":
                return t, den, None, lf
        else:
            # −g·s: a host constant, or a folded row's −g
            ng = dr.opaque(F, -sg * obj.g) if isinstance(obj.g, (int, float)) else -obj.g
            nzs = dr.opaque(F, -vz) * nd_xy + ng * d.z
            dec.add(nzs, bz, rules.screen_clip == ">=")
    if isinstance(anq, (int, float)) and anq / dec.b > 1e300:
        # t = |n·q|/den may overflow even where den > bound: keep t < inf in the hit
        dec.add(dr.select(t < dr.inf, dr.inf, -dr.inf), 0.0)
    return t, den, dec, lf


def _fast_result(t, dec, lf):
    if dec is None:                         # a certain miss on every ray
        no = dr.mask_t(t)(False)
        return t, no, no, lf
    return (t, *dec.split(), lf)


def _clip_test(cert: _Cert, F, zs, bz, rules: Rules):
    """The screen clip on z·|n·d| (z <= 0 passes with '>', z < 0 with '>='): certain where
    z <= −bound, possible where z <= bound."""
    if rules.screen_clip == "off":
        return
    if isinstance(bz, (int, float)):
        b, nb = dr.opaque(F, bz), dr.opaque(F, -bz)
    else:
        b, nb = bz, -bz
    if rules.screen_clip == ">=":
        cert.add(zs < nb, zs < b)
    else:
        cert.add(zs <= nb, zs <= b)


def plane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float, cert: bool = False):
    """Ray–plane distance: t = n·q'/(n·d). Miss if n·d = 0, t <= t_min, or screen-clipped."""
    if _fast(obj, rules, o, cert):
        t, _, dec, lf = _plane_fast(d, obj, rules, vz, cert)
        return _fast_result(t, dec, lf)
    t, hit, _, _, c = _plane(d, o, obj, rules, vz, cert)
    if not cert:
        return t, hit
    return (t, *c[0].split(), c[1])


def _plane(d, o, obj, rules: Rules, vz: float, cert: bool = False):
    """plane_t's work, shared with fplane_t: (t, hit, n·d, q', certification) with
    certification = (_Cert of t > t_min and the clip, bound of t) when ``cert``."""
    F, B = _check(d)
    n = opaque3(type(d), obj.n)
    q = opaque3(type(d), obj.q)
    if o is None:
        nq = opaque(F, obj.nq)
    else:
        q = q - o
        nq = dr.dot(n, q)
    # n·d as plain products and sums (no unpaired fma): a sum of exactly opposite products
    # is exactly 0, as it is in exact arithmetic
    nx, ny, nz = n.x * d.x, n.y * d.y, n.z * d.z
    nd_xy = nx + ny
    den = nd_xy + nz
    inv_den = dr.rcp(den)
    t = nq * inv_den
    # n·d = 0 (parallel) gives t = ±inf or NaN: '< inf' rejects it with the non-finite t's
    hit = (t > dr.opaque(F, rules.t_min)) & (t < dr.inf)
    cinfo = None
    if cert:
        assert o is None, "certified decisions are for rays from the viewpoint"
        bden = KB * U64 * KD * cert          # Σ|n_i d_i| <= |n||d| <= KD·cert
        ainv = dr.abs(inv_den)
        tb = dr.abs(t) * dr.fma(ainv, bden, KB * U64)
        lf = dr.fma(-ainv, bden, 1 - KB * U64)
        if rules.t_min == 0:
            # t > 0 is sign(n·q)·sign(n·d) > 0: certain where n·d is beyond its bound (n·q
            # is exact), possible where t > 0 or n·d is within it (unless n·q = 0 exactly,
            # a plane through the viewpoint, t = 0; t is NaN there when n·d = 0 too)
            t_pos, den_ok = t > 0, dr.abs(den) > bden
            if isinstance(obj.nq, (int, float)):     # n·q on the host (its sign is folded
                maybe = ~den_ok if obj.nq != 0 else False     # into the kernel already)
            else:
                maybe = ~den_ok & (nq != 0)
            cinfo = [_Cert(t_pos & den_ok, t_pos | maybe if maybe is not False else t_pos),
                     lf]
        else:
            # t = n·q/(n·d): with n·d within its bound of 0, t may be anything
            tmin = dr.opaque(F, rules.t_min)
            possible = ~(t + tb <= tmin) | ((dr.abs(den) <= bden) & (nq != 0))
            cinfo = [_Cert(t - tb > tmin, possible), lf]
    if rules.screen_clip != "off":
        # hit z = zn/den with zn = vz'·den + n·q'·d.z = vz'·(n.x d.x + n.y d.y) + g'·d.z,
        # g' = n·q' + n.z·vz' (host constant g; see the module docstring): nothing cancels
        # that is not the answer (exact 0 for a plane in z = 0)
        g = obj.g
        if o is None and isinstance(obj.nq, (int, float)):
            # rays from the viewpoint: a hit has sign(den) = sign(nq) (t > 0), known here;
            # fold it into the constants: z·|den| with no work per ray
            sg = -1.0 if obj.nq < 0 else 1.0
            zs = dr.opaque(F, sg * vz) * nd_xy + dr.opaque(F, sg * g) * d.z
        else:
            vzo = dr.opaque(F, vz) if o is None else dr.opaque(F, vz) + o.z
            g = opaque(F, g)
            if o is not None:
                g = g - (n.x * o.x + n.y * o.y)
            zn = vzo * nd_xy + g * d.z
            zs = dr.mulsign(zn, den)
        hit = hit & clip_ok(zs, rules)
        if cert:
            _clip_test(cinfo[0], F, zs, _scaled(obj.bz, cert), rules)
    return t, hit, den, q, cinfo


def clip_ok(z, rules: Rules):
    """False where a hit at height z lies in front of the window (z > 0; z >= 0 with '>=')."""
    if rules.screen_clip == "off":
        return True
    return (z <= 0) if rules.screen_clip == ">" else (z < 0)


def frame_coords(d, obj):
    """The fast path's frame coordinates of the hit times n·d (sign-folded):
    su = s·ŷ·(q × d), sv = −s·x̂·(q × d) (the finite plane's, the triangle's, the disk's)."""
    Array3 = type(d)
    sg = _signed(obj)[0]
    c = dr.cross(opaque3(Array3, obj.q), d)
    return (dr.dot(opaque3(Array3, _fold(sg, obj.ydir)), c),
            -dr.dot(opaque3(Array3, _fold(sg, obj.xdir)), c))


def fplane_t(d, o, obj: ObjectConstants, rules: Rules, vz: float, cert: bool = False):
    """plane_t, then the bounds test 0 <= u <= w, 0 <= v <= h (strict with open edges)."""
    F, B = _check(d)
    Array3 = type(d)
    if _fast(obj, rules, o, cert):
        # rays from the viewpoint, certified: den > 0 on hits, sign folded into X, Y
        t, den, dec, lf = _plane_fast(d, obj, rules, vz, cert)
        if dec is None:
            return _fast_result(t, dec, lf)
        su, sv = frame_coords(d, obj)
        w, h = obj.size
        wd, hd = opaque(F, w) * den, opaque(F, h) * den
        tm = dec.tamed
        dec.add(least(least(su, wd - su, tm), least(sv, hd - sv, tm), tm),
                _scaled(obj.bm, cert), rules.edges == "open")
        return _fast_result(t, dec, lf)
    t, hit, den, q, ci = _plane(d, o, obj, rules, vz, cert)
    c = dr.cross(q, d)
    # u·|den| in [0, w·|den|], v·|den| in [0, h·|den|] (see the module docstring): no
    # division, every comparison monotone in one rounded quantity
    X, Y = obj.xdir, obj.ydir
    w, h = obj.size
    if o is None and isinstance(obj.nq, (int, float)):
        # rays from the viewpoint: a hit has t = nq/den > 0, so sign(den) = sign(nq), known
        # here: fold it into the constants (no extra work per ray)
        sg = -1.0 if obj.nq < 0 else 1.0
        X, Y = tuple(sg * c for c in X), tuple(sg * c for c in Y)
        Xo, Yo = opaque3(Array3, X), opaque3(Array3, Y)
        su = dr.dot(Yo, c)
        sv = -dr.dot(Xo, c)
        wo, ho = opaque(F, sg * w), opaque(F, sg * h)
        wd, hd = wo * den, ho * den
    else:
        Xo, Yo = opaque3(Array3, X), opaque3(Array3, Y)
        su = dr.mulsign(dr.dot(Yo, c), den)
        sv = dr.mulsign(-dr.dot(Xo, c), den)
        aden = dr.abs(den)
        wo, ho = opaque(F, w), opaque(F, h)
        wd, hd = wo * aden, ho * aden
    if rules.edges == "closed":
        tests = [(su >= 0), (su <= wd), (sv >= 0), (sv <= hd)]
    else:
        tests = [(su > 0), (su < wd), (sv > 0), (sv < hd)]
    inside = tests[0] & tests[1] & tests[2] & tests[3]
    if not cert:
        return t, hit & inside
    c, lf = ci
    # the four edges as one test: their least value against the largest of their bounds
    # (a larger bound is still a bound)
    m = dr.minimum(dr.minimum(su, wd - su), dr.minimum(sv, hd - sv))
    bm = _scaled(obj.bm, cert)
    c.test(F, m, bm, rules.edges == "open")
    return (t, *c.split(), lf)


def sphere_t(d, o, obj: ObjectConstants, rules: Rules, vz: float, cert: bool = False,
             live=None):
    """The near root of |o + t·d − centre|² = r²; miss if the discriminant <= 0 or t <= 0.

    The discriminant is taken as a·r² − |q' × d|² = (r√a − |q'×d|)(r√a + |q'×d|) (|q'×d|/√a
    is the distance of the centre from the ray line), and the near root as c/(b' + √disc)
    when b' > 0, so neither cancels.  ``live``: ``sphere_live``'s result for these rays
    from the viewpoint, whose |q×d|² and r√a (the same operations) are reused."""
    F, B = _check(d)
    q = opaque3(type(d), obj.q)
    r = opaque(F, obj.radius)
    if o is None:
        c = opaque(F, obj.c)
    else:
        q = q - o if live is None else live.q
        qn = dr.norm(q)
        c = (qn - r) * (qn + r)
    a = dr.squared_norm(d)
    bh = dr.dot(q, d) if live is None or o is None else live.bh  # −b/2 of the quadratic
    if live is None:
        cn = dr.norm(dr.cross(q, d))        # |d| × distance of the centre from the ray line
        ra = r * dr.sqrt(a)
    else:
        cn, ra = dr.sqrt(live.sn), live.ra
    disc = (ra - cn) * (ra + cn)
    # √max(disc, 0) as a select (dr.maximum costs ~8 instructions, see ``least``); a NaN
    # disc gives 0 here, and a miss either way (disc > 0 fails)
    s = dr.sqrt(dr.select(disc > 0, disc, 0))
    # near root c/(b' + √disc): with b' <= 0 both roots are <= 0 (origin outside, c > 0) or
    # the near one is (origin inside, c <= 0), a miss either way, so no second branch
    if cert:
        inv = dr.rcp(bh + s)                # 1/(b' + s) serves t's bound too
        t = c * inv
    else:
        t = c / (bh + s)
    outline, front = disc > 0, bh > 0
    hit = outline & front & (t > 0) & dr.isfinite(t)
    if rules.clip_spheres:
        z = dr.fma(t, d.z, dr.opaque(F, vz))
        z = z if o is None else z + o.z
        clip = clip_ok(z, rules)
        hit &= clip
    if not cert:
        return t, hit
    assert o is None, "certified decisions are for rays from the viewpoint"
    # t = c/(b' + s): its relative error is that of b' + s (at most bs, from b' and from
    # s = √disc, |√x − √y| <= √|x−y|: loose far from tangency, but t's bound only decides
    # which near ties are re-decided) over b' + s, plus roundings
    # (t > 0 on every hit, and the bound matters on hits only)
    bs = opaque(F, _scaled(obj.bs, cert))
    lf = dr.fma(-bs, inv, 1 - KB * U64)
    c = _Cert(True, True)
    bo = _scaled(obj.bo, cert)              # NaN when c <= 0: never passes
    # outline r√a − |q×d| > 0 and front q·d > 0 share their bound: one test on the least
    c.test(F, least(ra - cn, bh, tame(obj, vz)), bo, True)
    if rules.clip_spheres and rules.screen_clip != "off":
        zb = dr.fma(dr.abs(t), dr.abs(d.z), dr.opaque(F, abs(vz))) * (KB * U64) + t * dr.fma(bs, inv, KB * U64)
        _clip_test(c, F, z, zb, rules)
    return (t, *c.split(), lf)


# The unrolled sphere tests of camera rays (tracer.closest_hit) sit behind a packet-wide
# branch on ``sphere_live``: most packets miss most spheres there (measured: docs/speed.md).
# CULL_MARGIN: the relative margin on |q×d|², far above the few roundings (2⁻²⁴ each in
# float32) that separate its comparison's values from the sphere test's own
CULL_MARGIN = 2.0 ** -18


def sphere_live(d, obj: ObjectConstants, cert=False, o=None) -> SimpleNamespace:
    """The rays that may hit sphere ``obj``: ``mask``, all but those that ``sphere_t``
    certainly finds missing, decided without a square root or a division; with ``sn`` =
    |q×d|² and ``ra`` = r√a (and, for rays with an origin ``o``, q = centre − o and
    bh = q·d), computed as sphere_t computes them: it takes them as ``live`` instead of
    computing them again (measured with ``rtval bench``: ~7% of 4 spheres' camera rays; in
    a BVH leaf, reflection rays, ~25%).  Rays with an origin also fail on bh <= 0, which
    sphere_t's front test rejects."""
    F, B = _check(d)
    q = opaque3(type(d), obj.q)
    if o is not None:
        q = q - o
    sn = dr.squared_norm(dr.cross(q, d))            # |q×d|²
    ra = opaque(F, obj.radius) * dr.sqrt(dr.squared_norm(d))
    miss = _sphere_miss(F, sn, ra, _scaled(obj.bo, cert) if cert else None)
    if o is None:
        return SimpleNamespace(mask=~miss, sn=sn, ra=ra)
    bh = dr.dot(q, d)
    return SimpleNamespace(mask=~miss & (bh > 0), sn=sn, ra=ra, q=q, bh=bh)


# Camera rays without certification take a cheaper test still (``sphere_cone``).  From the
# viewpoint |q×d|² = |q|²|d|² − (q·d)², so a ray misses when (q·d)² <= (|q|² − r²)|d|²: the
# ray lies outside the cone of directions that hold the sphere.  One dot product against a
# host constant k = |q|² − r²(1 + m) replaces the cross product.  Its margin:
#   m = CONE_MARGIN + CONE_ROUNDING · u · |q|²/r²   (u: the kernel's unit roundoff)
# ``sphere_cone``'s docstring has the bound it rests on (m >= 15u + 22u·|q|²/r²).
CONE_MARGIN = 2.0 ** -10
CONE_ROUNDING = 64.0
# the argument assumes no overflow or underflow: it is used for spheres with r >= CONE_MIN
# and |q|∞ <= 1/CONE_MIN, and rays with CONE_MIN² <= |d|² <= 1/CONE_MIN²
CONE_MIN = 2.0 ** -20


def cone_k(q, radius, precision: str):
    """k = |q|² − r²(1 + m) of ``sphere_cone``, from q and r as the kernel rounds them, exact
    and then rounded down to the kernel's precision; None where the cone test is not used
    (a sphere too small or too far for its argument, or non-finite numbers)."""
    return _cone_k(tuple(float(c) for c in q), float(radius), precision)


@functools.lru_cache(maxsize=4096)
def _cone_k(q, radius, precision: str):
    f = np.float32 if precision == "f32" else np.float64
    u = 2.0 ** -24 if precision == "f32" else U64
    qk = [float(f(c)) for c in q]
    rk = float(f(radius))
    if not all(math.isfinite(c) for c in qk + [rk]) or rk < CONE_MIN or \
            max(abs(c) for c in qk) > 1 / CONE_MIN:
        return None
    q2 = sum(Fraction(c) ** 2 for c in qk)
    m = Fraction(CONE_MARGIN) + Fraction(CONE_ROUNDING * u) * q2 / Fraction(rk) ** 2
    k = q2 - Fraction(rk) ** 2 * (1 + m)
    kd = float(k)                                   # nearest, then down
    if Fraction(kd) > k:
        kd = math.nextafter(kd, -math.inf)
    return float(directed(np.array(kd), precision, down=True))


def directed(a: np.ndarray, precision: str, down: bool) -> np.ndarray:
    """float64 values rounded to the kernel's precision, down (or up), as float64 (host
    bounds that must stay below, or above, their float64 value in a float32 kernel)."""
    if precision == "f64":
        return a
    f = a.astype(np.float32)
    if down:
        f = np.where(f > a, np.nextafter(f, np.float32(-np.inf)), f)
    else:
        f = np.where(f < a, np.nextafter(f, np.float32(np.inf)), f)
    return f.astype(np.float64)


def cone_rays(d, dmax: float | None = None):
    """The per-ray part of ``sphere_cone`` and ``ball_cone``, computed once for all objects:
    a = |d|² as sphere_t computes it where CONE_MIN² <= a <= CONE_MIN⁻², else NaN (k·NaN
    drops nothing).  ``dmax``: certified rays (|d| <= KD·dmax), for which the lower limit is
    also (dmax/4)² (``cert_radius``, ``plane_ball``), raised past a's rounding."""
    F, B = _check(d)
    a = dr.squared_norm(d)
    lo = CONE_MIN * CONE_MIN
    if dmax is not None:
        lo = max(lo, dmax * dmax / 16 * (1 + 2.0 ** -20))
    sane = (a >= lo) & (a <= 1 / (CONE_MIN * CONE_MIN))
    return dr.select(sane, a, dr.nan)


def sphere_cone(d, obj: ObjectConstants, precision: str, a):
    """The camera rays that may hit sphere ``obj`` (uncertified kernels): all but those that
    ``sphere_t`` certainly finds missing, by one dot product; None where not used
    (``cone_k``).  ``a``: ``cone_rays(d)``.  (Not in the bins' loop: there most rays hit,
    and reusing sphere_live's products is worth more; measured: 1.03× the time.)

    A ray is dropped when b = q·d <= 0 (sphere_t's front test, on the same computed value,
    fails) or when fl(b·b) <= fl(k·a), a = |d|² as sphere_t computes it, with a within
    [CONE_MIN², CONE_MIN⁻²].  Then sphere_t's outline test fails: with Q, D the kernel's
    values, A = |D|², B = Q·D and S = |Q×D|² = |Q|²A − B² exact (u the unit roundoff, k >= 0,
    no underflow or overflow):
      * the test's roundings (a: γ₃, b: γ₃|Q||D|, the two products: u each) give
        B² <= kA(1 + 6u) + 3γ₃|Q|²A, so with k <= |Q|² − r²(1 + m):
        S >= r²A(1 + m) − 16u|Q|²A;
      * sphere_t computes cn = fl(√fl(|fl(Q×D)|²)) >= (√S − 2√2·u|Q||D|)(1 − 3u) (each
        component of the cross product within γ₂ of the sum of its two products' sizes)
        and ra = fl(r·fl(√a)) <= r√A(1 + 4u);
      * so cn >= ra, and disc = (ra − cn)(ra + cn) <= 0 (a miss), whenever
        S >= r²A(1 + 15u) + 6u|Q|²A, which m >= 15u + 22u|Q|²/r² guarantees; m is
        CONE_MARGIN (2⁻¹⁰, far above 15u) plus 64u|Q|²/r² (about three times 22u|Q|²/r²).
    k < 0 (the viewpoint within about a radius of the sphere) drops nothing but b <= 0,
    except where Dr.Jit's flush of denormals makes both k·a and b·b zero (|k| below
    2⁻¹²⁶/a): the rays there miss anyway, r²·m dwarfing such a k.  A NaN b fails b > 0 here
    and sphere_t's front test there; a NaN k·a or b·b drops nothing.  On CUDA, float32
    square roots are approximate (2u): the bound then needs about 17u + 22u|Q|²/r², still
    well inside m.  (Checked by a second reader, and by an exact emulation of the float32
    kernel on 80 M rays near the outlines of 1,600 spheres, |q|/r from 1.01 to 10⁶: no ray
    dropped that sphere_t hits; the largest margin such a ray needed was 0.13 of m.)"""
    k = cone_k(obj.q, obj.radius, precision)
    if k is None:
        return None
    F, B = _check(d)
    b = dr.dot(opaque3(type(d), obj.q), d)         # sphere_t's bh, the same operations
    return (b > 0) & ~(b * b <= dr.opaque(F, k) * a)


def ball_cone(d, centre, radius: float, precision: str, a):
    """The rays from the viewpoint that may pass within ``radius`` of ``centre`` (host
    float64, relative to the viewpoint): all but those that ``sphere_cone``'s argument finds
    outside the cone of that ball, on either side of the viewpoint (no front test: an
    object inside the ball may lie behind its centre); None where that argument does not
    hold (``cone_k``).  Rays from inside the ball (k < 0) all pass.  ``a``: ``cone_rays``."""
    k = cone_k(centre, radius, precision)
    if k is None:
        return None
    F, B = _check(d)
    b = dr.dot(opaque3(type(d), centre), d)
    return ~(b * b <= dr.opaque(F, k) * a)


# Certified camera rays (float64 with exact decisions) branch on ``ball_cone`` too, with the
# ball widened so that a ray it drops is one the certified test would find not even possibly
# hitting: then neither the answers nor the rays decided exactly change.  A sphere's
# certified outline test (``sphere_t``) finds a ray "not even possibly" hitting when its
# computed r√a − |q×d| <= −bo (bo: ``_sphere_bounds``, scaled by the rays' dmax).
# ``sphere_cone``'s argument, run with the radius r' = r + 4·bo₁ (bo₁ the bound for
# |d| <= KD), gives |q×d| as sphere_t computes it >= r'√A(1 + 4u) >= r√a as computed +
# 4·bo₁·√A, which is >= r√a + bo₁·dmax for rays with A >= (dmax/4)² (``cone_rays(d,
# dmax)``).

def cert_radius(radius: float, bo: float) -> float | None:
    """r + 4·bo₁, rounded up (``bo``: the sphere's bo₁, ``_sphere_bounds``); None where the
    bound is not finite (NaN: the viewpoint inside the sphere)."""
    if not math.isfinite(bo):
        return None
    return math.nextafter(float(Fraction(float(radius)) + 4 * Fraction(bo)), math.inf)


def sphere_cone_cert(d, obj: ObjectConstants, precision: str, a):
    """``ball_cone`` of sphere ``obj`` for certified rays: drops only rays that sphere_t's
    certified test finds not even possibly hitting it; None where not used."""
    r = cert_radius(obj.radius, obj.bo)
    return None if r is None else ball_cone(d, obj.q, r, precision, a)


# A finite plane's ball (``cull.bounding``: about c, out to its farthest corner R) is widened
# to R₂ so that a ray it drops fails one of the plane's edge decisions by more than their
# bound bm (``_plane_bounds``; for float32, in float32's unit): certified, not even possibly a
# hit; uncertified, no computed hit either, not even a grazing ray's noise hit.  With h = |n·q|
# the viewpoint's distance from the plane, a ray the cone drops meets the plane (if at all
# ahead, den = n·d̂ > 0) at P with |P − c| >= R₂, so outside the rectangle by e >= (R₂ − R)/√2
# along u or v; t = h/den <= |c| + |P − c| and (x − R)/(|c| + x) grows with x, so the edge
# value −e·den <= −(R₂ − R)·h/((|c| + R₂)·√2)·|d|, which is <= −2·bm₁·4|d| (the computed value
# then <= −bm, for rays |d| >= dmax/4 in certified kernels, whose bound is bm₁·dmax) when
# R₂ − R >= K·(|c| + R₂), K = 8√2·bm₁/h.  Rays with den <= 0: below −bden a certain miss;
# nearer 0, |(q×d)·x̂| or |(q×d)·ŷ| >= h|d|/√2 (d in the plane's directions), far beyond bm
# when h >= PLANE_H·(bm₁ + (w + h)·bden₁).  bm₁ is taken as the largest of the decisions'
# bounds (edges, clip, den), which the certified test compares their least with (``_Least``).
# Found by reviewers' fuzzing: the ball widened by 2⁻¹⁰ alone let nearly edge-on planes'
# unsure rays (certified) and noise hits (uncertified) be dropped, and bm alone, without the
# larger den bound of small scenes, unsure rays.
BALL_GROW = 2.0 ** -10      # relative widening, and BALL_ROOM of |c| + R for the host's
BALL_ROOM = 2.0 ** -40      # roundings of the corners and of the ball
PLANE_K_MAX = 0.5           # no branch where the widening would grow R₂ by half or more
PLANE_H = 64.0


def plane_ball(obj: ObjectConstants, centre, radius: float, precision: str) -> float | None:
    """R₂ of finite plane ``obj``'s ball (``centre``, ``radius``: cull.bounding's), for
    ``precision``'s kernels, certified or not; None where no branch is sound (the viewpoint
    too near the plane's)."""
    if not isinstance(obj.nq, (int, float)) or not isinstance(obj.bm, (int, float)):
        return None
    scale = 1.0 if precision == "f64" else 2.0 ** -24 / U64
    # (the certified test takes its decisions' least against their largest bound: _Least)
    bden1 = KB * U64 * KD * scale
    bm1 = max(obj.bm, obj.bz if isinstance(obj.bz, (int, float)) else math.inf,
              KB * U64 * KD) * scale
    h = abs(obj.nq)
    nc = math.sqrt(dot_x(centre, centre))
    if not (math.isfinite(bm1) and math.isfinite(nc)) or \
            h <= PLANE_H * (bm1 + (obj.size[0] + obj.size[1]) * bden1):
        return None
    K = 8 * math.sqrt(2) * bm1 / h * (1 + 2.0 ** -20)
    if K >= PLANE_K_MAX:
        return None
    r = (radius * (1 + BALL_GROW) + BALL_ROOM * (nc + radius) + K * nc) / (1 - K)
    return r * (1 + 2.0 ** -20)


def plane_cone(d, obj: ObjectConstants, centre, radius: float, precision: str, a):
    """``ball_cone`` of finite plane ``obj``'s ball widened to ``plane_ball``: the camera
    rays that may hit it (certified: possibly); None where not used."""
    r = plane_ball(obj, tuple(float(c) for c in centre), radius, precision)
    return None if r is None else ball_cone(d, centre, r, precision, a)


def _sphere_miss(F, sn, ra, bo):
    """|q×d|² >= x²(1 + m), with x = r√a as sphere_t computes it (uncertified: then
    |q×d| >= r√a, so its discriminant (r√a − |q×d|)(r√a + |q×d|) is <= 0, a miss) or
    x = r√a + bo (certified: then r√a − |q×d| <= −bo, and the outline test fails even
    'possibly').  With x, x², the margin's product and |q×d|² each rounded a few times
    (relative 2⁻²⁴ each in float32), x²(1 + m) as computed is still >= x²(1 + m/2) and
    sphere_t's rounded |q×d| >= x; a NaN anywhere compares false: the ray is tested."""
    x = ra if bo is None else ra + (dr.opaque(F, bo) if isinstance(bo, (int, float)) else bo)
    return sn >= (x * x) * dr.opaque(F, 1 + CULL_MARGIN)


from .quadrics import KINDS as QUADRIC_KINDS  # noqa: E402  (the quadrics' kernel uses the above)
from .shapes_quadric import quadric_constants, quadric_t  # noqa: E402
from .shapes_torus import torus_constants, torus_t  # noqa: E402  (uses the helpers above)


def _planar():
    from . import shapes_planar          # (it imports this module's helpers)
    return shapes_planar


def planar_t(*args, **kw):
    return _planar().planar_t(*args, **kw)


OBJECT_T = {"sphere": sphere_t, "plane": plane_t, "fplane": fplane_t, "tplane": plane_t,
            "cylinder": quadric_t, "cone": quadric_t, "ellipsoid": quadric_t,
            "triangle": planar_t, "disk": planar_t, "torus": torus_t}


def object_t(d, o, obj: ObjectConstants, rules: Rules, vz: float, cert: bool = False):
    """The kind's level-1 function: (t, hit), or with ``cert`` (t, certain hit, possible hit,
    t's lower factor)."""
    return dispatch(OBJECT_T, obj.kind)(d, o, obj, rules, vz, cert)
