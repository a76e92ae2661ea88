"""The torus in the exact oracle (mitsuba_ref/exact.py), on its own: rational arithmetic and
Descartes' rule of signs, no rounding in a decision.

For the ray V + t·d with d = D/Dd exactly (integers) and the numbers as written, w = t·d − Q
(Q = centre − V) and A the axis as written (not normalised), the torus equation times |A|²,

    F(t) = |A|²·(|w|² + R² − r²)² − 4R²·(|A|²·|w|² − (w·A)²),

has rational coefficients; ``torus_poly`` computes a positive integer multiple of it in
integers, and its square-free part is itself wherever a gcd modulo a prime shows it (no
Fraction arithmetic on the common path).  Its real roots in (0, ∞) are isolated on its
square-free part by bisection with Descartes' rule of signs (the sign variations of (1 +
x)ⁿ·p((a + b·x)/(1 + x)) count the roots in (a, b) up to an even number: 0 and 1 are exact
answers).  The hit is the smallest t > 0 where F changes sign (a tangency, touching without
crossing, is a miss).  It is kept as ``TorusT``: a tuple (num, den) of a rational within
2⁻¹¹⁰ (relative) of the root, for exact.py's float t and margins, which carries the
polynomial and an isolating interval, so that ``less`` compares it exactly with a rational
(a plane's t) and with another torus's root.
"""
from __future__ import annotations

import math
from fractions import Fraction

APPROX_BITS = 110


def _trim(p):
    p = list(p)
    while len(p) > 1 and p[-1] == 0:
        p.pop()
    return p


def _pmul(a, b):
    out = [Fraction(0)] * (len(a) + len(b) - 1)
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            out[i + j] += x * y
    return out


def _padd(*ps):
    n = max(len(p) for p in ps)
    return [sum((p[i] for p in ps if i < len(p)), Fraction(0)) for i in range(n)]


def _divmod(a, b):
    a, b = _trim(a), _trim(b)
    q = [Fraction(0)] * max(1, len(a) - len(b) + 1)
    a = list(a)
    while len(a) >= len(b) and any(a):
        c = a[-1] / b[-1]
        k = len(a) - len(b)
        q[k] = c
        for i, y in enumerate(b):
            a[i + k] -= c * y
        a.pop()
        if not a:
            break
    return q, _trim(a) if a else [Fraction(0)]


def _gcd(a, b):
    """The monic gcd (Fractions) of two polynomials (integer or rational coefficients)."""
    a, b = _trim([Fraction(c) for c in a]), _trim([Fraction(c) for c in b])
    while any(b):
        a, b = b, _divmod(a, b)[1]
    return [c / a[-1] for c in a]


def _value(p, x):
    v = Fraction(0)
    for c in reversed(p):
        v = v * x + c
    return v


def _sg(x) -> int:
    return (x > 0) - (x < 0)


def _ints(p):
    """A rational polynomial times a positive integer: integer coefficients."""
    L = 1
    for c in p:
        L = math.lcm(L, Fraction(c).denominator)
    return [int(c * L) for c in p]


def _shift1(p):
    """The coefficients of p(x + 1) (integers, lowest degree first): Taylor shift."""
    a = list(p)
    n = len(a) - 1
    for i in range(n):
        for j in range(n - 1, i - 1, -1):
            a[j] += a[j + 1]
    return a


def _var01(q) -> int:
    """Descartes' bound on q's roots in (0, 1): the sign variations of (x + 1)ⁿ q(1/(x + 1))."""
    s = [c > 0 for c in _shift1(q[::-1]) if c != 0]
    return sum(1 for x, y in zip(s, s[1:]) if x != y)


def _sign_dyadic(p, c: int, e: int) -> int:
    """sign(p(c·2^e)) for integer coefficients p, exactly in integers."""
    n = len(p) - 1
    if e >= 0:
        v = sum(k * (c << e) ** i for i, k in enumerate(p))
    else:
        v = sum(k * c ** i << (-e * (n - i)) for i, k in enumerate(p))
    return (v > 0) - (v < 0)


def _roots01(q, c: int, k: int, e: int, out: list):
    """Roots of p in (c·2^(e−k), (c + 1)·2^(e−k)), q(x) = p((c + x)·2^(e−k)) (up to a positive
    factor), ascending, as dyadic (lo, hi) pairs (num, exponent) — (x, x) for a root x."""
    v = _var01(q)
    if v == 0:
        return
    if v == 1:
        out.append(((c, e - k), (c + 1, e - k)))
        return
    n = len(q) - 1
    left = [q[i] << (n - i) for i in range(n + 1)]          # q(x/2)·2ⁿ
    right = _shift1(left)                                    # q((x + 1)/2)·2ⁿ
    _roots01(left, 2 * c, k + 1, e, out)
    if right[0] == 0:                                        # the midpoint is a root
        out.append(((2 * c + 1, e - k - 1), (2 * c + 1, e - k - 1)))
        right = right[1:]
    _roots01(right, 2 * c + 1, k + 1, e, out)


def _dy(x) -> Fraction:
    c, e = x
    return Fraction(c << e) if e >= 0 else Fraction(c, 1 << -e)


def _roots(p, a, b):
    """Compatibility for gcd checks: p's roots in (a, b) as Fraction intervals (bisection on
    Fractions with Sturm-free Descartes counts on the transformed polynomial)."""
    q = _ints(_compose(p, a, b - a))
    out = []
    _roots01(q, 0, 0, 0, out)
    return [(a + (b - a) * _dy(lo), a + (b - a) * _dy(hi)) for lo, hi in out]


def _compose(p, a, h):
    """p(a + h·x) (Fractions)."""
    out = [Fraction(0)]
    for c in reversed(p):
        out = _padd(_pmul(out, [Fraction(a), Fraction(h)]), [c])
    return out


def _variations(p, a, b) -> int:
    """Descartes' bound on p's roots in (a, b)."""
    return _var01(_ints(_compose(p, a, b - a)))


class TorusT(tuple):
    """(num, den): a rational within 2⁻¹¹⁰ of the root; ``poly``, ``lo``, ``hi``: the
    square-free polynomial and an interval holding only that root (lo == hi: exact)."""

    @classmethod
    def make(cls, poly, lo, hi):
        """From an isolating interval of poly (dyadic pairs (num, exponent)), refined by
        integer bisection to 2⁻¹¹⁰ of its size."""
        pi = _ints(poly)
        (c0, e0), (c1, e1) = lo, hi
        if (c0, e0) != (c1, e1):
            e = min(e0, e1)
            a, b = c0 << (e0 - e), c1 << (e1 - e)
            sa = _sign_dyadic(pi, a, e)
            while (b - a).bit_length() + e > max(a.bit_length(), b.bit_length()) + e - \
                    APPROX_BITS:
                a, b, e = 2 * a, 2 * b, e - 1
                m = (a + b) // 2
                sm = _sign_dyadic(pi, m, e)
                if sm == 0:
                    a = b = m
                    break
                if sm == sa:
                    a = m
                else:
                    b = m
            lo, hi = (a, e), (b, e)
        flo, fhi = _dy(lo), _dy(hi)
        x = (flo + fhi) / 2
        out = cls((x.numerator, x.denominator))
        out.poly, out.lo, out.hi = poly, flo, fhi
        return out

    def cmp(self, x: Fraction) -> int:
        """sign(root − x), exactly."""
        if self.lo == self.hi:
            return _sg(self.lo - x)
        if x <= self.lo:
            return 1
        if x >= self.hi:
            return -1
        px = _value(self.poly, x)
        if px == 0:
            return 0
        return 1 if _sg(px) == _sg(_value(self.poly, self.lo)) else -1


def less(a, b) -> bool:
    """a < b for exact.py's t values (num, den), one or both a TorusT, exactly."""
    if isinstance(a, TorusT) and isinstance(b, TorusT):
        if a.lo == a.hi:
            return b.cmp(a.lo) > 0
        if b.lo == b.hi:
            return a.cmp(b.lo) < 0
        g = _gcd(a.poly, b.poly)
        lo, hi = max(a.lo, b.lo), min(a.hi, b.hi)
        if len(g) > 1 and lo < hi and any(
                r for r in _roots(g, lo, hi)) and _shared(a, b, g, lo, hi):
            return False                                # the same root
        return _sep(a, b) < 0
    if isinstance(a, TorusT):
        return a.cmp(Fraction(b[0], b[1])) < 0
    return b.cmp(Fraction(a[0], a[1])) > 0


def _shared(a, b, g, lo, hi) -> bool:
    """Do a's and b's roots coincide (a root of their gcd g in both intervals)?"""
    for r0, r1 in _roots(g, lo, hi):
        if a.cmp(r0) >= 0 >= a.cmp(r1) and b.cmp(r0) >= 0 >= b.cmp(r1):
            return True
    return False


def _sep(a, b) -> int:
    """sign(a − b) of two distinct roots: their intervals refined until apart."""
    alo, ahi, blo, bhi = a.lo, a.hi, b.lo, b.hi
    while True:
        if ahi <= blo and not (ahi == blo == bhi == alo):
            return -1
        if bhi <= alo:
            return 1
        for p, (lo, hi), which in ((a.poly, (alo, ahi), 0), (b.poly, (blo, bhi), 1)):
            if lo == hi:
                continue
            m = (lo + hi) / 2
            pm = _value(p, m)
            if pm == 0:
                lo = hi = m
            elif _sg(pm) == _sg(_value(p, lo)):
                lo = m
            else:
                hi = m
            if which == 0:
                alo, ahi = lo, hi
            else:
                blo, bhi = lo, hi


def torus_poly(Q, A, R, r, D, Dd):
    """F(t) along V + t·D/Dd (Q = centre − V, A the axis as written), lowest degree first, as
    (G, K): integer coefficients G = K·F, K > 0 an integer (so G has F's roots and signs, and
    G[i]/K is F's coefficient rounded once)."""
    L = 1
    for c in (*Q, R, r):
        L = math.lcm(L, Fraction(c).denominator)
    La = 1
    for c in A:
        La = math.lcm(La, Fraction(c).denominator)
    return _poly(_Ints([int(c * L) for c in Q], [int(c * La) for c in A], R, r, L, La), D, Dd)


class _Ints:
    """A torus's numbers relative to the viewpoint as integers: q = L·Q, a = La·A, R·L and
    r·L (L clears the denominators of Q, R and r, La those of A)."""

    def __init__(self, q, a, R, r, L, La):
        self.q, self.a, self.L, self.La = tuple(q), tuple(a), L, La
        RL, rL = int(R * L), int(r * L)
        self.R2, self.r2, self.B2 = RL * RL, rL * rL, (RL + rL) ** 2
        self.qq, self.AA = sum(c * c for c in q), sum(c * c for c in a)
        self.qa = sum(x * y for x, y in zip(q, a))


def _poly(c: _Ints, D, Dd):
    """torus_poly in integers: w' = L·w = σ·D − q for σ = t·L/Dd, and F'(σ) = L⁴·La²·F(t)
    has integer coefficients; G(t) = Dd⁴·F'(t·L/Dd), K = Dd⁴·L⁴·La²."""
    R2, AA = c.R2, c.AA
    w2 = (c.qq, -2 * sum(x * y for x, y in zip(c.q, D)), sum(x * x for x in D))   # |w'|²
    wa = (-c.qa, sum(x * y for x, y in zip(D, c.a)))                               # w'·A'
    s0 = w2[0] + R2 - c.r2
    ss = (s0 * s0, 2 * s0 * w2[1], w2[1] * w2[1] + 2 * s0 * w2[2], 2 * w2[1] * w2[2],
          w2[2] * w2[2])
    wawa = (wa[0] * wa[0], 2 * wa[0] * wa[1], wa[1] * wa[1])
    Fs = [AA * ss[i] - 4 * R2 * AA * (w2[i] if i < 3 else 0) +
          4 * R2 * (wawa[i] if i < 3 else 0) for i in range(5)]
    L = c.L
    G = _trim([f * L ** i * Dd ** (4 - i) for i, f in enumerate(Fs)])
    return G, Dd ** 4 * L ** 4 * c.La ** 2


def _squarefree(G):
    """The square-free part of the integer polynomial G (lowest degree first): G itself where
    gcd(G, G') = 1, which its image modulo the prime P shows (P does not divide G's leading
    coefficient, so a common factor over the rationals would stay one of the same degree
    modulo P); else by Euclid in Fractions."""
    dG = [i * G[i] for i in range(1, len(G))]
    if G[-1] % _P and len(_gcd_mod(G, dG)) == 1:
        return G
    return _divmod([Fraction(c) for c in G], _gcd(G, dG))[0]


_P = (1 << 61) - 1          # a prime


def _gcd_mod(a, b):
    """gcd of two integer polynomials modulo _P (monic, lowest degree first)."""
    a, b = _trim([c % _P for c in a]), _trim([c % _P for c in b])
    while any(b):
        inv = pow(b[-1], -1, _P)
        a = list(a)
        while len(a) >= len(b) and any(a):
            c = a[-1] * inv % _P
            k = len(a) - len(b)
            for i, y in enumerate(b):
                a[i + k] = (a[i + k] - c * y) % _P
            a.pop()
            a = _trim(a) if a else [0]
        a, b = b, a
    return a


def first_crossing(F):
    """The smallest t > 0 at which F changes sign, as a TorusT, or None."""
    if len(F) < 2:
        return None
    Fi = _ints(F)                                        # (a positive multiple: same roots)
    # a root at t = 0 (the viewpoint on the surface) is no hit: F/tᵐ has F's signs for t > 0
    # and no root at 0 (with it, an isolating interval from 0 had a sign 0 at its end, and
    # TorusT.make's bisection never ended)
    while len(Fi) > 1 and Fi[0] == 0:
        Fi = Fi[1:]
    if len(Fi) < 2:
        return None
    sf = _squarefree(Fi)
    if len(sf) < 2:
        return None
    # every root below it (Cauchy): 1 + max |c_i / c_n|
    if isinstance(sf[-1], int):
        bound = 1 + Fraction(max(abs(c) for c in sf[:-1]), abs(sf[-1]))
    else:
        bound = 1 + max(abs(c / sf[-1]) for c in sf[:-1])
    e = max(1, math.ceil(math.log2(bound)) + 1)
    si = _ints(sf)
    q = [c << (e * i) for i, c in enumerate(si)]           # sf(2^e·x): roots in (0, 1)
    out = []
    _roots01(q, 0, 0, e, out)
    for lo, hi in out:
        if lo == hi:
            # a rational root: F's signs a little to each side (no other root there)
            x = _dy(lo)
            h = Fraction(1, 2)
            while _variations(sf, x - h, x) or _variations(sf, x, x + h) or \
                    _value(sf, x - h) == 0 or _value(sf, x + h) == 0:
                h /= 2
            left, right = _sg(_value(Fi, x - h)), _sg(_value(Fi, x + h))
        else:
            left, right = _sign_dyadic(Fi, *lo), _sign_dyadic(Fi, *hi)
            # an end of the interval can be another root of F (sign 0 there, which differs
            # from the other end's: a touching ray read as a crossing; a helper's fuzzing):
            # F's sign just inside that end instead, which no root separates from its root
            if left == 0:
                left = _sign_inside(Fi, sf, _dy(lo), 1)
            if right == 0:
                right = _sign_inside(Fi, sf, _dy(hi), -1)
        if left != right:
            return TorusT.make(sf, lo, hi)
    return None


def _sign_inside(Fi, sf, x: Fraction, toward: int) -> int:
    """F's sign a little from its root ``x`` toward ``toward`` (±1), where no root lies
    between."""
    h = Fraction(1, 2)
    while True:
        y = x + toward * h
        a, b = (x, y) if toward > 0 else (y, x)
        if not _variations(sf, a, b) and _value(sf, y) != 0:
            return _sg(_value(Fi, y))
        h /= 2


def eval_torus(p, D, Dd, rules):
    """exact.py's per-object evaluation: (t as TorusT or None, {'crossing': (passed,
    margin)}).  The margin: the least |F|/|∇F| (a first-order distance from the surface,
    world units) at F's critical points before the hit (all of them for a miss), signed.
    What ``conditions`` needs is kept per ray on ``p.torus_info``."""
    o = p.obj
    if Dd == 0 or not any(D):
        raise ZeroDivisionError("a ray of no direction")
    if Dd < 0:                                               # (the same ray, Dd > 0)
        D, Dd = tuple(-c for c in D), -Dd
    if not hasattr(p, "torus_info"):
        p.torus_info = []
        Q = tuple(c - v for c, v in zip(o.center, p.V))
        R, r = o.size
        L = math.lcm(p.L, R.denominator, r.denominator)        # (p.Q = (centre − V)·p.L)
        p.torus = Q, _Ints([c * (L // p.L) for c in p.Q], p.N, R, r, L, p.Ln)
    Q, c = p.torus
    A, (R, r) = o.normal, o.size
    # the bounding sphere (centre, R + r) holds the torus: a ray that misses it, or that
    # meets it only behind the viewpoint, misses (exact); its margin is the distance
    # from the sphere, a lower bound of the distance from the torus.  In integers, times
    # L²·|D|²: |Q × d̂|² > (R + r)², Q·d < 0 and |Q|² > (R + r)²
    DD = sum(x * x for x in D)
    qD = sum(x * y for x, y in zip(c.q, D))
    perp2 = c.qq * DD - qD * qD                              # |Q × d̂|²·L²·|D|²
    if perp2 > c.B2 * DD or (qD < 0 and c.qq > c.B2):
        B = float(R + r)
        gap = max(math.sqrt(perp2 / (c.L * c.L * DD)) - B,
                  math.sqrt(c.qq / (c.L * c.L)) - B if qD < 0 else 0.0)
        p.torus_info.append((0.0, gap, 1.0, 0.0))
        return None, {"crossing": (False, -gap)}
    G, K = _poly(c, D, Dd)
    hit = first_crossing(G)
    # (F's coefficients over the largest, not over K: the same critical points, where a
    # torus 1e-100 across had them underflow to 0)
    margin, tc, cos = _margin([g / (max(map(abs, G)) or 1) for g in G], Q, A, R, r, D, Dd,
                              hit)
    p.torus_info.append((tc, margin, cos, float(hit[0]) / hit[1] if hit is not None else 0.0))
    return hit, {"crossing": (hit is not None, margin if hit is not None else -margin)}


def _geom(w, a, R, r):
    ww = sum(c * c for c in w)
    h = sum(x * y for x, y in zip(w, a))
    s = ww + R * R - r * r
    f = s * s - 4 * R * R * (ww - h * h)
    g = [4 * s * w[i] - 8 * R * R * (w[i] - h * a[i]) for i in range(3)]
    return f, g


def _margin(F, Q, A, R, r, D, Dd, hit):
    """(min |F(t_c)|/|∇F(t_c)| over F's critical points t_c in (0, hit), that t_c, the
    cosine of the hit's incidence), floats; F's coefficients in any common scale."""
    d = [c / Dd for c in D]
    fF = [float(c) for c in F]      # (F: floats already, F's coefficients rounded once)
    crit = [float(z.real) for z in _np_roots(list(reversed(
        [i * fF[i] for i in range(1, len(fF))]))) if abs(z.imag) <= 1e-9 * (1 + abs(z))]
    th = float(hit[0]) / float(hit[1]) if hit is not None else math.inf
    an = math.sqrt(sum(float(c) ** 2 for c in A))
    a = [float(c) / an for c in A]
    Rf, rf = float(R), float(r)
    # F and ∇F in units of the torus's size k (F/k⁴, ∇F/k³: a torus 1e-100 across had F
    # and ∇F underflow to 0, its incidence cosine 0 and its t's condition 1e300)
    k = (Rf + rf) or 1.0
    d = [c / k for c in d]
    Qk, Rk, rk = [float(c) / k for c in Q], Rf / k, rf / k
    best, tbest = math.inf, 0.0
    for t in crit:
        if not 0 < t < th:
            continue
        f, g = _geom([t * d[i] - Qk[i] for i in range(3)], a, Rk, rk)
        ng = math.sqrt(sum(c * c for c in g))
        m = k * abs(f) / ng if ng > 0 else 0.0
        if m < best:
            best, tbest = m, t
    cos = 1.0
    if hit is not None:
        _, g = _geom([th * d[i] - Qk[i] for i in range(3)], a, Rk, rk)
        ng = math.sqrt(sum(c * c for c in g)) * math.sqrt(sum(c * c for c in d))
        cos = abs(sum(x * y for x, y in zip(g, d))) / ng if ng > 0 else 0.0
    return best, tbest, cos


def _np_roots(coef):
    import numpy as np
    return np.roots(coef) if len(coef) > 1 else []


def conditions(p, d, rays, length):
    """{'crossing': S, 't': S} per ray (exact.py's risk): the first-order change of the
    decided quantity (world units) when every input moves by one unit of itself, bounded
    by |value| + Σ|viewpoint| + Σ|centre| + R + r + |t|·Σ|d| (over the incidence cosine
    for t), t the world distance along the unit ray d: the rays ``rays`` (D, Dd) were
    evaluated with t along D/Dd, t·``length`` the world distance.  A ray of no direction
    was not evaluated (trace_exact decides it a miss): S = 0 there."""
    import numpy as np
    o = p.obj
    scale = (sum(abs(float(c)) for c in p.V) + sum(abs(float(c)) for c in o.center)
             + sum(abs(float(c)) for c in o.size))
    info = iter(getattr(p, "torus_info", []))
    n = len(d)
    sc, st = np.zeros(n), np.zeros(n)
    for i, (D, _) in enumerate(rays):
        if not any(D):
            continue
        tc, m, cos, t = next(info)
        tc, t = tc * length[i], t * length[i]
        d1 = float(np.abs(d[i]).sum())
        sc[i] = (abs(m) if math.isfinite(m) else 0.0) + scale + abs(tc) * d1
        st[i] = abs(t) + (scale + abs(t) * d1) / max(cos, 1e-300)
    return {"crossing": sc, "t": st}
