"""The torus's kernel (nw's code 25; rt_core/torus.py): type-generic Dr.Jit, f32 and f64.

With e = d/|d|, q' = centre − origin, t0 = q'·e (the ray's closest approach to the centre)
and p0 = t0·e − q' (the centre's foot point on the ray, relative to the centre; p0 ⊥ e), the
ray point at distance t0 + s is w = p0 + s·e, and the torus equation
(|w|² + R² − r²)² − 4R²(|w|² − (w·â)²) = 0 is the depressed quartic

    g(s) = s⁴ + c2·s² + c1·s + c0,   P = |p0|², A = P + R² − r², ea = e·â, m = p0·â,
    c2 = 2A − 4R²|e × â|²,  c1 = 8R²·ea·m,  c0 = (A − 2Rρ0)(A + 2Rρ0), ρ0 = |p0 × â|,

(the cubic term vanishes because p0 ⊥ e).  Its values near the torus are of the torus's own
scale whatever the distance of the viewpoint (no cancellation of |q'|-sized terms: no
Ferrari closed form, which cancels badly in float32).  The search:

1. the bounding sphere (centre, R + r): s ∈ [−hb, hb], hb = √((R + r)² − P), cut to
   s > −t0 (t > 0); none: a miss;
2. g's critical points (the roots of the depressed cubic g'/4 = s³ + (c2/2)s + c1/4, by the
   trigonometric or Cardano form, each polished by Newton steps) split that interval into
   pieces on which g is monotone: g at the pieces' ends has the sign pattern of g, and the
   first root is in the first piece whose end's sign differs from the start's;
3. safeguarded Newton in that bracket (a Newton step that leaves the bracket is replaced by
   bisection): ``ITERATIONS`` steps.

The hit is the smallest root with t > 0 (also from inside the tube: the exit).

Certified decisions (f64, rays from the viewpoint; rt_core/shapes.py "Certified decisions"):
the verdict rests on the signs of g at the pieces' ends up to the bracket (all of them for a
miss) and on the bounding sphere; each value is within ``bo`` (g) or ``bs`` (the sphere's
B² − P) of its exact value on the scene's numbers and the ideal ray, for |d| <= 1.01 (host
constants, ``torus_constants``), and a ray any of whose signs lies within its bound is
flagged (decided exactly by rt_core/decide_torus.py).  The bound assumes the critical points
are located to first order (Newton-polished: g's value there then errs by second-order
terms); the exact-oracle tests (tests/test_torus.py) check the verdicts on every ray.
"""
from __future__ import annotations

import math

import drjit as dr

from .shapes import (KB, KD, U64, ObjectConstants, _Cert, _canonical, _check, _sg, cross_x,
                     dot_x, opaque, opaque3, rounded)
from .scene import exact

ITERATIONS = {"f32": 14, "f64": 20}       # safeguarded Newton steps in the bracket
POLISH = 2                                 # Newton steps on each critical point


def frame_axis(A) -> int:
    """The world axis that x̂ is projected from: the one with the smallest |â_k| (the first
    of equal ones).  x̂ = unit(e_k − (e_k·â)â), ŷ = â × x̂: the uv frame (both oracles use the
    same rule, computed on their own)."""
    m = min(abs(c) for c in A)
    return next(k for k, c in enumerate(A) if abs(c) == m)


def torus_constants(i: int, o, V, groups: dict) -> ObjectConstants:
    """Host constants of a torus relative to the viewpoint V (exact): q = centre − V, n = â,
    the frame x̂, ŷ (uv), size = (R, r), radius = R + r (the bounding sphere), c = R² − r²,
    and the bounds bo (g) and bs (B² − P) of the certified decisions."""
    Q = tuple(exact(c) - v for c, v in zip(o.center, V))
    A = tuple(exact(c) for c in o.given_axis)
    AA = dot_x(A, A)
    k = frame_axis(A)
    E = tuple(1 if j == k else 0 for j in range(3))
    p = tuple(e * AA - A[k] * a for e, a in zip(E, A))       # (e_k − (e_k·â)â)·|A|²
    PP = dot_x(p, p)
    y = cross_x(A, p)
    R, r = exact(o.major), exact(o.minor)
    q = tuple(rounded(c) for c in Q)
    An = tuple(_sg(A) * c for c in _canonical(A))
    grp = groups.setdefault(("t", Q, An, R, r), len(groups))
    return ObjectConstants(i, "torus", q, tuple(rounded(c, AA) for c in A),
                           xdir=tuple(rounded(c, PP) for c in p),
                           ydir=tuple(rounded(c, PP * AA) for c in y),
                           size=(float(R), float(r)), radius=float(R + r),
                           c=rounded(R * R - r * r), grp=grp,
                           **torus_bounds(q, float(R), float(r)))


def torus_bounds(q, R: float, r: float) -> dict:
    """bo: g's error at any s of the bounding interval (|w| <= B = R + r), for unit rays:
    p0's position error (~10u·(|q| + B): q rounded once, e normalised, t0·e) times g's
    gradient bound G = 4(B² + R² + r²)B + 8R²B, plus the roundings of g's terms (their
    absolute sum Ga = (B² + R² + r²)² + 4R²B²), KB units each; bs: B² − P's
    (2B·|δp0| + B²).  KD: room for |d| a few units above 1."""
    k = KB * U64 * KD
    B = R + r
    nq = math.sqrt(sum(x * x for x in q))
    dp = nq + B
    G = 4 * (B * B + R * R + r * r) * B + 8 * R * R * B
    Ga = (B * B + R * R + r * r) ** 2 + 4 * R * R * B * B
    return {"bo": k * (G * dp + Ga), "bs": k * (2 * B * dp + B * B)}


def _g(s, c2, c1, c0):
    s2 = s * s
    return dr.fma(dr.fma(s2, 1, c2), s2, dr.fma(c1, s, c0))


def _dg(s, c2, c1):
    return dr.fma(dr.fma(4 * s, s, 2 * c2), s, c1)


def _critical(F, c2, c1):
    """The real roots of s³ + p·s + h (p = c2/2, h = c1/4), ascending (one real root: three
    equal values), Newton-polished."""
    p, h = c2 * 0.5, c1 * 0.25
    p3 = p * (1.0 / 3.0)
    D = dr.fma(h * 0.5, h * 0.5, p3 * p3 * p3)
    # one real root: Cardano without cancellation (u³ of the larger magnitude)
    sq = dr.sqrt(dr.maximum(D, 0))
    u = -dr.mulsign(dr.cbrt(dr.abs(h) * 0.5 + sq), h)
    one = u - dr.select(u != 0, p3 / u, 0)
    # three real roots (D < 0, so p < 0): 2√(−p/3)·cos((φ − 2πj)/3)
    m = dr.sqrt(dr.maximum(-p3, 0))
    cosarg = dr.clip(dr.select(m > 0, (-0.5 * h) / (m * m * m), 0), -1, 1)
    phi = dr.acos(cosarg) * (1.0 / 3.0)
    two_pi3 = 2.0 * math.pi / 3.0
    r0 = 2 * m * dr.cos(phi)
    r1 = 2 * m * dr.cos(phi - two_pi3)
    r2 = 2 * m * dr.cos(phi - 2 * two_pi3)
    three = D < 0
    roots = [dr.select(three, r, one) for r in (r2, r1, r0)]
    out = []
    for x in roots:
        for _ in range(POLISH):
            f = dr.fma(dr.fma(x, x, p), x, h)
            fp = dr.fma(3 * x, x, p)
            x = dr.select(fp != 0, x - f / fp, x)
        out.append(x)
    a, b, c = out
    a, b = dr.minimum(a, b), dr.maximum(a, b)
    b, c = dr.minimum(b, c), dr.maximum(b, c)
    a, b = dr.minimum(a, b), dr.maximum(a, b)
    return a, b, c


def torus_t(d, o, obj, rules, vz: float, cert=False):
    """The smallest root t > 0 of the torus along o + t·d: (t, hit), or with ``cert``
    (t, certain hit, possible hit, t's lower factor).  The screen clip and t_min do not
    apply (as for spheres without clip_spheres: no course program clips a torus)."""
    F, B_ = _check(d)
    A3 = type(d)
    q = opaque3(A3, obj.q)
    if o is not None:
        q = q - o
    ax = opaque3(A3, obj.n)
    R = opaque(F, obj.size[0])
    Bv, k = opaque(F, obj.radius), opaque(F, obj.c)
    inv = dr.rsqrt(dr.squared_norm(d))
    e = d * inv
    t0 = dr.dot(q, e)
    p0 = dr.fma(e, t0, -q)
    P = dr.squared_norm(p0)
    ea = dr.dot(e, ax)
    m = dr.dot(p0, ax)
    exa = dr.squared_norm(dr.cross(e, ax))
    rho0 = dr.norm(dr.cross(p0, ax))
    A = P + k
    R4 = 4 * R * R
    c2 = dr.fma(-R4, exa, 2 * A)
    c1 = 2 * R4 * ea * m
    c0 = (A - 2 * R * rho0) * (A + 2 * R * rho0)
    inside = (Bv - dr.sqrt(P)) * (Bv + dr.sqrt(P))      # B² − P
    hb = dr.sqrt(dr.maximum(inside, 0))
    hi = hb
    lo = dr.minimum(dr.maximum(-hb, -t0), hi)
    cl, cm, ch = _critical(F, c2, c1)
    xs = [lo] + [dr.clip(c, lo, hi) for c in (cl, cm, ch)] + [hi]
    gs = [_g(x, c2, c1, c0) for x in xs]
    gs[4] = dr.abs(gs[4])           # the exit from the bounding sphere: g >= 0 there too
    # entering the bounding sphere (not starting inside it), the ray starts outside the
    # torus (g >= 0 there, 0 only on its outer equator): take that sign, not g's rounding
    s0 = (gs[0] > 0) | (hb <= t0)
    found = dr.zeros(B_, dr.width(d))
    a, b, last = lo, lo, dr.zeros(dr.int32_array_t(F), dr.width(d))
    for i in range(1, 5):
        ch_ = ~found & (((gs[i] > 0) != s0) | (gs[i] == 0))
        a = dr.select(ch_, xs[i - 1], a)
        b = dr.select(ch_, xs[i], b)
        last = dr.select(ch_, i, last)
        found |= ch_
    # safeguarded Newton in [a, b]: g(a) has the sign s0, g(b) the other (or is 0); only
    # on rays with a bracket (a packet of rays without one skips it)
    n_it = ITERATIONS[_precision(F)]

    def refine(x, a, b, c2, c1, c0, s0):
        for _ in range(n_it):
            gx = _g(x, c2, c1, c0)
            gp = _dg(x, c2, c1)
            zero = gx == 0
            same = ((gx > 0) == s0) & ~zero
            a = dr.select(same | zero, x, a)
            b = dr.select(same, b, x)
            xn = x - gx / gp
            lo_ab, hi_ab = dr.minimum(a, b), dr.maximum(a, b)
            ok = (xn >= lo_ab) & (xn <= hi_ab) & dr.isfinite(xn)
            x = dr.select(ok, xn, 0.5 * (a + b))
        return x, a, b

    x, a, b = dr.if_stmt((0.5 * (a + b), a, b, c2, c1, c0, s0), found & (inside > 0), refine,
                         lambda x, a, b, *rest: (x, a, b), label="torus_refine")
    t = (t0 + x) * inv
    hit = found & (inside > 0) & (t > 0) & dr.isfinite(t)
    if not cert:
        return t, hit
    assert o is None, "certified decisions are for rays from the viewpoint"
    bo, bs = opaque(F, obj.bo), opaque(F, obj.bs)
    unsure = dr.abs(inside) <= bs
    for i in range(5):
        relevant = (~found) | (last >= i)
        unsure |= relevant & (inside > 0) & (dr.abs(gs[i]) <= bo)
    # t's bound (relative): g's error over |g'| at the root, the bracket left, roundings
    gp = dr.abs(_dg(x, c2, c1))
    tb = (bo / gp + dr.abs(b - a) + KB * U64 * (dr.abs(t0) + dr.abs(x))) * inv
    lf = 1 - KB * U64 - tb / t
    lf = dr.select(dr.isfinite(lf), lf, -dr.inf)
    c = _Cert(hit & ~unsure, hit | unsure)
    return (t, *c.split(), lf)


def _precision(F) -> str:
    return "f64" if dr.type_v(F) == dr.VarType.Float64 else "f32"


def torus_surface(ks, d, t, q, idx, hit, kind, normal, u, v):
    """Normal and uv at a torus hit (the others' pass through): with w = t·d − q (the hit
    relative to the centre), w⊥ = w − (w·â)â its part in the torus's plane, the normal is
    unit(w − R·unit(w⊥)) (from the nearest point of the core circle: the gradient's
    direction), u = atan2(w·ŷ, w·x̂) the angle around the axis and v = atan2(w·â, |w⊥| − R)
    the angle around the tube, both in radians in (−π, π]."""
    from .kinds import KIND_CODE
    T = ks.T
    on = True if kind is None else (kind == KIND_CODE["torus"])
    w = dr.fma(d, t, -q)
    a = dr.gather(T.Array3, ks.table("n"), idx, hit)
    R = dr.gather(T.Float, ks.table("w"), idx, hit)
    xd = dr.gather(T.Array3, ks.table("xdir"), idx, hit)
    yd = dr.gather(T.Array3, ks.table("ydir"), idx, hit)
    h = dr.dot(w, a)
    wp = w - a * h
    lp = dr.norm(wp)
    nt = dr.normalize(w - wp * (R / lp))
    tu = dr.atan2(dr.dot(w, yd), dr.dot(w, xd))
    tv = dr.atan2(h, lp - R)
    return dr.select(on, nt, normal), dr.select(on, tu, u), dr.select(on, tv, v)
