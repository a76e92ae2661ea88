"""The torus in the float64 oracle (mitsuba_ref/oracle.py), written on its own.

With oc = base − centre, â = unit(axis) (computed here from the numbers as written) and the
ray base + t·d, the torus (|w|² + R² − r²)² = 4R²(|w|² − (w·â)²), w = oc + t·d, is the quartic

    f(t) = (a t² + b t + c + R² − r²)² − 4R²((a − e²) t² + (b − 2eh) t + c − h²),
    a = d·d, b = 2 d·oc, c = oc·oc, e = d·â, h = oc·â,

whose real roots are found by numpy (the companion matrix's eigenvalues), each polished by
Newton steps on f evaluated from w (f = (|w|² + R² − r²)² − 4R²ρ², ρ the distance from the
axis); the hit is the smallest t > 0 where f changes sign (a tangency is a miss).

Error bounds (units of u): t's is first order, (KF·f_abs + |∇f|·δw)/|f'(t)| + |t|: the
root's change when the ray point moves by δw (the running error bound of (base − centre) + t·d at
that t, from the viewpoint's, the ray's and the centre's own bounds) and f's terms (f_abs, their absolute sum) are rounded KF = 4 times.  The
decision's margin (``disc_margin``) is the least |f| at f's critical points that decide
the verdict (before the hit; all of them for a miss) over that same bound of f.
"""
from __future__ import annotations

import math

import numpy as np

KF = 4.0         # roundings of f's terms
POLISH = 6


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _unit(v):
    n = math.sqrt(_dot(v, v))
    return tuple(c / n for c in v)


def torus_obj(i, o):
    """The oracle's prepared torus: centre, unit axis, R, r (from the numbers as written)."""
    from .oracle import EF, _Obj, vec
    axis = getattr(o, "given_axis", None) or o.axis
    a = _unit(tuple(float(c) for c in axis))
    ob = _Obj(i, "torus", o, ("t", tuple(o.center), a, o.major, o.minor),
              normal=vec(a), center=vec(o.center), radius=EF(o.major))
    ob.minor = EF(o.minor)
    ob.frame = _frame(tuple(float(c) for c in axis))
    return ob


def _frame(A):
    """x̂ = unit(e_k − (e_k·â)â) with k the axis of the smallest |A_k| (the first of equal
    ones), ŷ = â × x̂: the uv frame."""
    a = _unit(A)
    m = min(abs(c) for c in A)
    k = next(j for j, c in enumerate(A) if abs(c) == m)
    p = tuple((1.0 if j == k else 0.0) - a[k] * a[j] for j in range(3))
    x = _unit(p)
    y = (a[1] * x[2] - a[2] * x[1], a[2] * x[0] - a[0] * x[2], a[0] * x[1] - a[1] * x[0])
    return x, y


def _f(ob, base, d, t):
    """(f, f_abs, |∇f|) at the ray point of parameter t (floats), w = (base − centre) + t·d."""
    C, a = ob.center, ob.normal
    w = tuple((base[i].v - C[i].v) + t * d[i].v for i in range(3))
    av = tuple(c.v for c in a)
    R, r = ob.radius.v, ob.minor.v
    ww = _dot(w, w)
    h = _dot(w, av)
    rho2 = max(ww - h * h, 0.0)
    s = ww + R * R - r * r
    f = s * s - 4 * R * R * rho2
    fabs = (ww + R * R + r * r) ** 2 + 4 * R * R * (ww + h * h)
    # ∇f = 4 s w − 8R²(w − h â)
    g = tuple(4 * s * w[i] - 8 * R * R * (w[i] - h * av[i]) for i in range(3))
    return f, fabs, math.sqrt(_dot(g, g))


def _poly(ob, base, d):
    """f's coefficients in t, highest first (floats)."""
    C, A = ob.center, ob.normal
    oc = tuple(base[i].v - C[i].v for i in range(3))
    dv = tuple(c.v for c in d)
    av = tuple(c.v for c in A)
    a, b, c = _dot(dv, dv), 2 * _dot(dv, oc), _dot(oc, oc)
    e, h = _dot(dv, av), _dot(oc, av)
    R, r = ob.radius.v, ob.minor.v
    k = c + R * R - r * r
    R4 = 4 * R * R
    return [a * a, 2 * a * b, b * b + 2 * a * k - R4 * (a - e * e),
            2 * b * k - R4 * (b - 2 * e * h), k * k - R4 * (c - h * h)]


def _span(ob, d) -> float:
    """The torus's size in units of t, (R + r)/|d|: the scale of the steps and tolerances
    below (they were absolute, 1e-6·(|t| + 1): at a scene 1e-4 across a step spanned the
    tube, and two pixels of a correct image were called wrong; a helper's fuzzing)."""
    dd = math.sqrt(sum(c.v * c.v for c in d))
    return (abs(ob.radius.v) + abs(ob.minor.v)) / dd if dd > 0 else 1.0


def _polish(ob, base, d, t, span):
    for _ in range(POLISH):
        f, _, _ = _f(ob, base, d, t)
        h = 1e-7 * (abs(t) + span)
        fp = (_f(ob, base, d, t + h)[0] - _f(ob, base, d, t - h)[0]) / (2 * h)
        if fp == 0 or not math.isfinite(fp):
            break
        step = f / fp
        t -= step
        if abs(step) <= 1e-17 * abs(t):
            break
    return t


def _real_roots(coef, span):
    r = np.roots(coef)
    return sorted(float(z.real) for z in r if abs(z.imag) <= 1e-7 * (span + abs(z)))


def _dfdt(ob, base, d, t, span):
    h = 1e-6 * (abs(t) + span)
    return (_f(ob, base, d, t + h)[0] - _f(ob, base, d, t - h)[0]) / (2 * h)


def _ferr(ob, base, d, t):
    """f's error bound at t (units of u): the ray point's error δw (the inputs' own error
    bounds, base + t·d − centre first order, plus the roundings of that sum) times |∇f|, and
    KF roundings of f's terms."""
    from .oracle import EF, diff3, scale3, sum3
    f, fabs, grad = _f(ob, base, d, t)
    w = sum3(diff3(base, ob.center), scale3(EF(t, 0.0), d))     # running error bounds
    dw = math.sqrt(sum(c.e * c.e for c in w))
    return f, KF * fabs + grad * dw


def torus_hits(ob, base, d, rules):
    """The oracle's verdict: the smallest t > 0 where f changes sign."""
    from .oracle import EF, scale3, sum3
    coef = _poly(ob, base, d)
    span = _span(ob, d)
    cands = [_polish(ob, base, d, t, span) for t in _real_roots(coef, span)]
    # critical points of f: the roots of f' (polished on f' numerically)
    crit = [t for t in _real_roots(np.polyder(coef), span)]
    hit_t = None
    cands.sort()
    for i, t in enumerate(cands):
        if not t > 0:
            continue
        # a sign change: f on both sides, a step small against the torus and under half
        # the distance to the neighbouring roots
        gaps = [abs(t - u) for u in cands[max(i - 1, 0):i + 2] if u != t]
        eps = min([1e-6 * (abs(t) + span)] + [g / 2 for g in gaps])
        lo, hi = _f(ob, base, d, t - eps)[0], _f(ob, base, d, t + eps)[0]
        if (lo > 0) != (hi > 0):
            hit_t = t
            break
    # the decision's margin: |f| at the critical points before the hit (all for a miss)
    margin = math.inf
    for tc in crit:
        if hit_t is not None and tc > hit_t:
            continue
        f, e = _ferr(ob, base, d, tc)
        margin = min(margin, abs(f) / e)
    if hit_t is None:
        tc = min(crit, key=lambda x: _f(ob, base, d, x)[0]) if crit else 0.0
        t = EF(tc, 0.0)
        return _torus_cand(False, t, sum3(base, scale3(t, d)), margin, "disc")
    f, e = _ferr(ob, base, d, hit_t)
    fp = abs(_dfdt(ob, base, d, hit_t, span))
    t = EF(hit_t, e / fp + abs(hit_t) if fp > 0 else math.inf)
    return _torus_cand(True, t, sum3(base, scale3(t, d)), margin, "")


def _torus_cand(ok, t, hitloc, margin, why):
    from .oracle import Cand
    c = Cand(ok, t, hitloc, why=why)
    c.margin = margin
    return c


def torus_tests(ob, c, rules) -> list:
    """The oracle's tests of a torus verdict: the crossing (disc_margin) and t > 0."""
    out = [("disc_margin", c.ok or c.why != "disc", c.margin)]
    if c.ok:
        out.append(("tmin_margin", c.t.v > 0.0, abs(c.t.v) / c.t.e if c.t.e else math.inf))
    return out


def torus_surface(ob, c):
    """(normal, (u, v), (err_u, err_v)) at a hit: the normal unit(w − R·unit(w⊥)) with
    w = hit − centre and w⊥ its part across the axis; u = atan2(w·ŷ, w·x̂), v = atan2(w·â,
    |w⊥| − R), radians."""
    from .oracle import EF, diff3, dot3, length3, scale3, unit3
    a = ob.normal
    w = diff3(c.hitloc, ob.center)
    h = dot3(w, a)
    wp = diff3(w, scale3(h, a))
    lp = length3(wp)
    core = scale3(ob.radius / lp, wp)
    n = unit3(diff3(w, core))
    # N = (w − R·unit(w⊥))/r moves by at most |δw|·(1 + R/|w⊥|)/r when w moves by δw
    # (unit(w⊥) by at most |δw|/|w⊥|): that first-order bound, plus a few roundings,
    # replaces the running bound (which counts correlated errors again at each step)
    dw = math.sqrt(sum(e * e for e in (c.e for c in w)))
    en = dw * (1 + ob.radius.v / lp.v) / ob.minor.v
    n = tuple(EF(c.v, min(c.e, en + 4 * abs(c.v) + 4)) for c in n)
    x, y = ob.frame
    wx, wy = dot3(w, vecx(x)), dot3(w, vecx(y))
    u, eu = _atan2(wy, wx)
    v, ev = _atan2(h, lp - ob.radius)
    return n, (u, v), (eu, ev)


def vecx(v):
    from .oracle import vec
    return vec(v)


def _atan2(y, x):
    """atan2 of two EF values, with a first-order bound (units of u)."""
    val = math.atan2(y.v, x.v)
    r2 = x.v * x.v + y.v * y.v
    e = (abs(x.v) * y.e + abs(y.v) * x.e) / r2 if r2 > 0 else math.inf
    return val, e + abs(val)
