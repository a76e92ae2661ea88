"""Exact decisions for the primary rays whose float64 answer the kernel could not certify.

The float64 kernel computes every decision (parallel, t > t_min, screen clip, finite-plane
edges, sphere outline and front, closest hit) together with a certified bound on its error
(rt_core/shapes.py); a ray any of whose decisions lies within its bound of the threshold is
flagged and decided here instead, in rational arithmetic on the scene's numbers as written
(``scene.exact``: the decimal text of the file) and the course's ideal ray through the exact
corner-grid (or centre) sample, ``E = world − viewpoint``.  No rounding enters a decision:

* plane kinds: s = N·Q / N·E (the hit is V + s·E; N·E = 0 is a miss); t > t_min is
  s > 0 and s²|E|² > t_min²; the clip is the sign of V.z + s·E.z;
* finite plane, with the unnormalised frame p = O(N·N) − (O·N)N (the projected orient) and
  y = N × p: u = p·(sE − Q)/|p|, v = y·(sE − Q)/(|N||p|), so 0 <= u <= w is
  a >= 0 and a² <= w²|p|² (a = p·(sE − Q)), and the same for v;
* sphere: the near root s = (Q·E − √D)/|E|², D = (Q·E)² − |E|²(|Q|² − r²): a hit iff
  D > 0, Q·E > 0 and |Q|² > r²;
* triangle, disk: the plane's s, then the extent test (rt_core/decide_planar.py);
* closest hit: the parameters s (numbers of the form α + β√D) are compared exactly; an exact
  tie goes to the rule's object.

This code shares nothing with the references that check rt_core (mitsuba_ref/exact.py's oracle is
independent of it and of the kernels).
"""
from __future__ import annotations

import decimal
import functools
import math
from fractions import Fraction
from types import SimpleNamespace

import numpy as np
from gmpy2 import mpq as Q

from .quadrics import KINDS as QUADRICS, coefficients, equation
from . import decide_planar
from .decide_torus import Root, TorusExact, torus_hit
from .rules import Rules
from .scene import Scene, exact

_CTX = decimal.Context(prec=40, Emax=10 ** 6, Emin=-10 ** 6)


def _sign(x) -> int:
    return (x > 0) - (x < 0)


def sgn_sqrt(p, q, r) -> int:
    """sign(p + q·√r) exactly (r >= 0)."""
    sp, sq = _sign(p), (_sign(q) if r > 0 else 0)
    if sq == 0 or sp == sq:
        return sp if sp else sq
    if sp == 0:
        return sq
    c = p * p - q * q * r               # opposite signs: the larger square wins
    return sp if c > 0 else (sq if c < 0 else 0)


def sgn_two_sqrt(a, b, x, c, y) -> int:
    """sign(a + b·√x + c·√y) exactly (x, y >= 0)."""
    s1, s2 = sgn_sqrt(a, b, x), (_sign(c) if y > 0 else 0)
    if s2 == 0 or s1 == s2:
        return s1 if s1 else s2
    if s1 == 0:
        return s2
    # (a + b√x)² − c²y = (a² + b²x − c²y) + 2ab√x
    s = sgn_sqrt(a * a + b * b * x - c * c * y, 2 * a * b, x)
    return s1 if s > 0 else (s2 if s < 0 else 0)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _q(v):
    """A Fraction (or a tuple of them) as GMP rationals (gmpy2.mpq: the same exact numbers,
    arithmetic about 12 times faster than Python's Fraction); anything else as is."""
    if isinstance(v, Fraction):
        return Q(v.numerator, v.denominator)
    if isinstance(v, tuple) and any(isinstance(c, Fraction) for c in v):
        return tuple(_q(c) for c in v)
    return v


def _fraction(x) -> Fraction:
    """An exact number (mpq, Fraction, int) as a Fraction (the torus's Sturm code's type)."""
    return x if isinstance(x, Fraction) else Fraction(int(x.numerator), int(x.denominator))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


class _Exact:
    """One object's numbers as written, and the products every ray needs (GMP rationals)."""

    def __init__(self, obj, V):
        self._build(obj, V)
        for k, v in vars(self).items():
            setattr(self, k, _q(v))

    def _build(self, obj, V):
        self.kind = obj.kind
        if obj.kind in QUADRICS:                    # rt_core/quadrics.py: no float screen
            self.eq = equation(obj)
            self.Q = tuple(exact(c) - v for c, v in zip(obj.center, V))
            self.fQ, self.nQ = (0.0, 0.0, 0.0), 0.0
            return
        if obj.kind == "sphere":
            self.Q = tuple(exact(c) - v for c, v in zip(obj.center, V))
            self.cc = _dot(self.Q, self.Q) - exact(obj.radius) ** 2
            self.fQ, self.fcc = tuple(map(_float, self.Q)), _float(self.cc)
            self.nQ = math.sqrt(sum(c * c for c in self.fQ))
            self.screened = all(map(math.isfinite, (*self.fQ, self.fcc, self.nQ)))
            return
        if obj.kind in ("triangle", "disk"):
            decide_planar.init(self, obj, V)            # rt_core/decide_planar.py
        else:
            N = tuple(exact(c) for c in obj.given_normal)
            self.N = N
            self.Q = tuple(exact(c) - v for c, v in zip(obj.point, V))
            self.NQ = _dot(N, self.Q)
        if obj.kind == "fplane":
            O = tuple(exact(c) for c in obj.orient)
            NN = _dot(N, N)
            on = _dot(O, N)
            self.p = tuple(o * NN - on * n for o, n in zip(O, N))
            self.y = _cross(N, self.p)
            PP = _dot(self.p, self.p)
            w, h = (exact(c) for c in obj.size)
            self.w2 = w * w * PP
            self.h2 = h * h * NN * PP
        # float copies for a quick screen (``surely_missed``).  Its tests are homogeneous in
        # N, in p and in y, so each is scaled by a power of two to about 1 (exactly): p is
        # of degree 3 in N, and w²|p|² overflowed a float from |N| ~ 1e51 on.  An object
        # with a copy still not finite is not screened.
        norm = lambda v: math.sqrt(sum(c * c for c in v))
        self.fQ = tuple(map(_float, self.Q))
        self.nQ = norm(self.fQ)
        self.fN, k = _scaled(self.N)
        self.fNQ = _float(self.NQ / Fraction(2) ** k)
        self.nN = norm(self.fN)
        copies = [*self.fQ, self.nQ, *self.fN, self.fNQ, self.nN]
        if obj.kind == "fplane":
            self.fp, kp = _scaled(self.p)
            self.fy, ky = _scaled(self.y)
            self.np, self.ny = norm(self.fp), norm(self.fy)
            self.fw2 = _float(self.w2 / Fraction(4) ** kp)
            self.fh2 = _float(self.h2 / Fraction(4) ** ky)
            copies += [*self.fp, *self.fy, self.np, self.ny, self.fw2, self.fh2]
        self.screened = all(map(math.isfinite, copies))


def _plane(o: _Exact, E, EE, Vz, rules: Rules, tmin2):
    """s as (α, 0, 0), or None for a miss."""
    ND = _dot(o.N, E)
    if ND == 0:
        return None
    s = o.NQ / ND
    if s <= 0 or (tmin2 and s * s * EE <= tmin2):
        return None
    if rules.screen_clip != "off":
        z = _sign(Vz + s * E[2])
        if z > 0 or (z == 0 and rules.screen_clip == ">="):
            return None
    if o.kind == "fplane":
        H = tuple(s * e - q for e, q in zip(E, o.Q))
        a, b = _dot(o.p, H), _dot(o.y, H)
        if rules.edges == "closed":
            if not (a >= 0 and a * a <= o.w2 and b >= 0 and b * b <= o.h2):
                return None
        elif not (a > 0 and a * a < o.w2 and b > 0 and b * b < o.h2):
            return None
    if o.kind in ("triangle", "disk") and not decide_planar.inside(o, E, s, rules.edges):
        return None
    return (s, 0, 0)


def _sphere(o: _Exact, E, EE, Vz, rules: Rules):
    """s = α + β√D as (α, β, D), or None for a miss."""
    if o.cc <= 0:
        return None                      # viewpoint inside or on the sphere: near root <= 0
    b = _dot(o.Q, E)
    D = b * b - EE * o.cc
    if D <= 0 or b <= 0:
        return None
    s = (b / EE, Q(-1) / EE, D)
    if rules.clip_spheres and rules.screen_clip != "off":
        z = sgn_sqrt(Vz + s[0] * E[2], s[1] * E[2], D)
        if z > 0 or (z == 0 and rules.screen_clip == ">="):
            return None
    return s


def _quadric(o: _Exact, E, Vz, rules: Rules):
    """s = α + β√D as (α, β, D) of the first root that hits (rt_core/quadrics.py), or None.
    A s² − 2B s + C = 0: roots (B ± √D)/A with D = B² − AC, in increasing order; a closed
    quadric only at its near root, an open one at the first root with s > 0 and
    0 <= w·a <= h|a| (w·a = s·E·a − Q·a, sign-exact with sgn_two_sqrt)."""
    eq = o.eq
    A, B, C = coefficients(eq, o.Q, E)
    D = B * B - A * C
    if D <= 0:
        return None
    if A == 0:                                  # one root, B ≠ 0 (D = B² > 0)
        roots = [(C / (2 * B), Q(0), Q(0))]
    else:
        lo, hi = (B / A, Q(-1) / A, D), (B / A, Q(1) / A, D)
        roots = [lo, hi] if A > 0 else [hi, lo]
    if eq.hh is None:
        roots = roots[:1]
    Ea, Qa = _dot(E, eq.a), _dot(o.Q, eq.a)
    for s in roots:
        if sgn_sqrt(s[0], s[1], s[2]) <= 0:
            continue
        if eq.hh is not None:
            ya, yb = s[0] * Ea - Qa, s[1] * Ea          # w·a = ya + yb√D
            if sgn_sqrt(ya, yb, s[2]) < 0 or sgn_two_sqrt(ya, yb, s[2], -1, eq.hh) > 0:
                continue
        if rules.clip_spheres and rules.screen_clip != "off":
            z = sgn_sqrt(Vz + s[0] * E[2], s[1] * E[2], s[2])
            if z > 0 or (z == 0 and rules.screen_clip == ">="):
                return None
        return s
    return None


def _float(x: Fraction) -> float:
    """x rounded to a float, ±inf beyond the range (float() raises there)."""
    try:
        return float(x)
    except OverflowError:
        return math.copysign(math.inf, x)


def _scaled(v) -> tuple:
    """(floats of v·2⁻ᵏ, k): the exact vector ``v`` scaled by a power of two so that its
    largest component is about 1, then rounded."""
    m = max(abs(Fraction(c)) for c in v)
    if m == 0:
        return tuple(0.0 for _ in v), 0
    k = m.numerator.bit_length() - m.denominator.bit_length()
    return tuple(_float(Fraction(c) / Fraction(2) ** k) for c in v), k


SCREEN = 1e-6      # relative: float64 arithmetic errs by ~1e-15 here, so this never misjudges
SCREEN_PAIRS = 1 << 18      # (ray, object) pairs screened at once (the screen's memory)


class _Screen:
    """The float copies of every object as arrays (``surely_missed``)."""

    def __init__(self, objs):
        self.n = n = len(objs)
        z3 = (0.0, 0.0, 0.0)
        col = lambda name, dflt=0.0: np.array([getattr(o, name, dflt) for o in objs],
                                              np.float64)
        vec = lambda name: np.array([getattr(o, name, z3) for o in objs],
                                    np.float64).reshape(n, 3)
        cols = {"fQ": vec("fQ"), "nQ": col("nQ"), "fcc": col("fcc"), "fN": vec("fN"),
                "fNQ": col("fNQ"), "nN": col("nN"), "fp": vec("fp"), "fy": vec("fy"),
                "np": col("np"), "ny": col("ny"), "fw2": col("fw2"), "fh2": col("fh2")}
        sphere = np.array([o.kind == "sphere" for o in objs], bool)
        fplane = np.array([o.kind == "fplane" for o in objs], bool)
        # quadrics have no float screen; an object whose copies are not finite neither
        quadric = np.array([o.kind in QUADRICS or not getattr(o, "screened", True)
                            for o in objs], bool)

        def rows(idx):
            return SimpleNamespace(idx=idx, **{k: v[idx] for k, v in cols.items()})
        # each test on its own kind's columns only (a sphere's on spheres, a plane's on the
        # plane kinds, the edges on finite planes): a flagged ray of 4,096 spheres took
        # 0.46 ms, mostly the planes' arrays
        self.spheres = rows(np.flatnonzero(sphere & ~quadric))
        self.planes = rows(np.flatnonzero(~sphere & ~quadric))
        at = np.flatnonzero(fplane[self.planes.idx])
        self.fplanes = rows(self.planes.idx[at])
        self.fplanes.at = at                    # (their columns among the planes')


def surely_missed(objs, fE: np.ndarray) -> np.ndarray:
    """A float screen before the exact test, for rays fE (m, 3) against every object: (m, n)
    True only where a decision fails by far more than float64 could err (then the exact test
    would fail too)."""
    S = getattr(objs, "screen", None)
    if S is None:
        S = _Screen(objs)
        if isinstance(objs, Prepared):
            objs.screen = S
    fE = np.asarray(fE, np.float64).reshape(-1, 3)
    nE = np.sqrt((fE * fE).sum(1))[:, None]
    fEE = nE * nE
    out = np.zeros((len(fE), S.n), bool)      # (quadrics: never screened)
    with np.errstate(all="ignore"):
        g = S.spheres
        if len(g.idx):
            # spheres: centre behind the viewpoint, or the discriminant far below 0
            b = fE @ g.fQ.T
            D = b * b - fEE * g.fcc
            out[:, g.idx] = (b < -SCREEN * g.nQ * nE) | \
                (D < -SCREEN * (b * b + fEE * np.abs(g.fcc) + 1e-300))
        g = S.planes
        if len(g.idx):
            # plane kinds: behind the viewpoint (nearly parallel: left to the exact test)
            nd = fE @ g.fN.T
            scale = np.abs(fE) @ np.abs(g.fN).T
            open_ = np.abs(nd) > SCREEN * scale
            s = g.fNQ / nd
            res = open_ & (s < 0) & (np.abs(g.fNQ) > SCREEN * g.nN * g.nQ)
            f = S.fplanes
            if len(f.idx):
                # finite planes: the hit far outside an edge
                sf = s[:, f.at]
                H = sf[..., None] * fE[:, None, :] - f.fQ[None]
                a = (H * f.fp[None]).sum(-1)
                bb = (H * f.fy[None]).sum(-1)
                nH = np.sqrt((H * H).sum(-1)) + f.nQ
                pa, ya = f.np * nH, f.ny * nH
                far = ((a < -SCREEN * pa) | (bb < -SCREEN * ya) |
                       (a * a > f.fw2 * (1 + SCREEN) + SCREEN * pa * pa) |
                       (bb * bb > f.fh2 * (1 + SCREEN) + SCREEN * ya * ya))
                res[:, f.at] |= open_[:, f.at] & (sf > 0) & far
            out[:, g.idx] = res
    return out


def _less(a, b) -> int:
    """sign(s_a − s_b) for s = α + β√D (or a torus's Root)."""
    if isinstance(a, Root):
        return a.cmp_root(b) if isinstance(b, Root) else a.cmp_number(*map(_fraction, b))
    if isinstance(b, Root):
        return -b.cmp_number(*map(_fraction, a))
    return sgn_two_sqrt(a[0] - b[0], a[1], a[2], -b[1], b[2])


def _to_float(s, EE) -> float:
    """t = s·|E| (the Euclidean distance), rounded to float64."""
    if isinstance(s, Root):
        return s.value(_fraction(EE))
    with decimal.localcontext(_CTX):
        dec = lambda f: decimal.Decimal(int(f.numerator)) / decimal.Decimal(int(f.denominator))
        v = dec(s[0])
        if s[1]:
            v += dec(s[1]) * dec(s[2]).sqrt()
        return float(v * dec(EE).sqrt())


def ideal_rays(scene: Scene, columns: int, rows: int, sampling: str, pixels, row_shift=0):
    """E = world − viewpoint (exact rationals) of each pixel index (image order, row 0 the
    top)."""
    ww, wh = (_q(exact(c)) for c in scene.window)
    V = tuple(_q(exact(c)) for c in scene.viewpoint)
    out = []
    for i in pixels:
        r, x = divmod(int(i), columns)
        y = rows - 1 - r + row_shift
        if sampling == "corners":
            wx = Q(x, columns - 1) * ww - ww / 2
            wy = Q(y, rows - 1) * wh - wh / 2
        else:
            wx = Q(2 * x + 1, 2 * columns) * ww - ww / 2
            wy = Q(2 * y + 1, 2 * rows) * wh - wh / 2
        out.append((wx - V[0], wy - V[1], -V[2]))
    return out


def decide(scene: Scene, columns: int, rows: int, sampling: str, rules: Rules, pixels,
           objs=None, row_shift: int = 0):
    """(object id, t) of the exact closest hit of each pixel's ideal ray: int32 and float64
    arrays, id −1 and t 0 on a miss.  ``objs``: ``prepare(scene)``, if kept from before."""
    return decide_rays(scene, rules, ideal_rays(scene, columns, rows, sampling, pixels,
                                                row_shift), distance=True, objs=objs)


class Prepared(list):
    """The scene's objects as exact numbers (and, once asked for, their float screen)."""
    screen = None

    @functools.cached_property
    def torus(self) -> bool:
        return any(o.kind == "torus" for o in self)


def prepare(scene: Scene) -> Prepared:
    """The scene's objects as exact numbers, for any number of ``decide`` calls."""
    V = tuple(exact(c) for c in scene.viewpoint)
    return Prepared((TorusExact(o, V) if o.kind == "torus" else _Exact(o, V))
                    for o in scene.objects)


def decide_rays(scene: Scene, rules: Rules, rays, distance: bool = False, objs=None):
    """``decide`` for rays from the viewpoint along the exact directions ``rays`` (triples of
    Fractions or floats, taken exactly); t is the ray parameter (hit = viewpoint + t·ray),
    or with ``distance`` the Euclidean distance."""
    V = tuple(_q(exact(c)) for c in scene.viewpoint)
    objs = prepare(scene) if objs is None else objs
    torus = objs.torus
    tmin = Q(rules.t_min)
    tmin2 = tmin * tmin
    ids = np.full(len(rays), -1, np.int32)
    ts = np.zeros(len(rays))
    if not len(rays):
        return ids, ts
    chunk = max(1, SCREEN_PAIRS // max(1, len(objs)))
    for k, E in enumerate(rays):
        if k % chunk == 0:                  # the screen, a chunk of rays at a time
            missed = surely_missed(objs, [[float(c) for c in R] for R in rays[k:k + chunk]])
        E = tuple(Q(c) for c in E)
        EE = _dot(E, E)
        EF = tuple(map(_fraction, E)) if torus else None
        best, best_s = -1, None
        for j in np.flatnonzero(~missed[k % chunk]).tolist():
            o = objs[j]
            s = (_sphere(o, E, EE, V[2], rules) if o.kind == "sphere"
                 else _quadric(o, E, V[2], rules) if o.kind in QUADRICS
                 else torus_hit(o, EF) if o.kind == "torus"
                 else _plane(o, E, EE, V[2], rules, tmin2))
            if s is None:
                continue
            c = -1 if best_s is None else _less(s, best_s)
            if c < 0 or (c == 0 and rules.ties == "last"):
                best, best_s = j, s
        if best >= 0:
            ids[k], ts[k] = best, _to_float(best_s, EE if distance else Q(1))
    return ids, ts
