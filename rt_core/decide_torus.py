"""Exact decisions for a torus (rt_core/decide.py's flagged rays): rational arithmetic and
Sturm sequences, no rounding.

Along the exact ray V + s·E (E = world − viewpoint), with Q = centre − V and A the axis as
written (not normalised), w = s·E − Q and the torus is the zero set of

    F(s) = |A|²·(|w|² + R² − r²)² − 4R²·(|A|²·|w|² − (w·A)²),

a quartic in s with rational coefficients (the torus equation times |A|²).  The hit is the
smallest s > 0 at which F changes sign (a root of odd multiplicity: a tangency, F touching 0
without crossing, is a miss, as the sphere's discriminant 0 is).  The roots are isolated
exactly on F's square-free part by its Sturm sequence and bisection at rational points;
a hit is kept as a ``Root`` (the square-free polynomial and a rational interval (lo, hi]
holding exactly that root), which compares exactly with a rational, with α + β√D (a
sphere's hit, by the sign of the polynomial at it in Q(√D)) and with another ``Root``.
"""
from __future__ import annotations

import decimal
from fractions import Fraction

from .scene import exact

_CTX = decimal.Context(prec=40, Emax=10 ** 6, Emin=-10 ** 6)


# --- polynomials over Fractions: coefficient lists, lowest degree first -----------------------

def _trim(p):
    p = list(p)
    while p and p[-1] == 0:
        p.pop()
    return p


def _mul(a, b):
    out = [Fraction(0)] * (len(a) + len(b) - 1)
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            out[i + j] += x * y
    return out


def _add(a, b):
    n = max(len(a), len(b))
    return [(a[i] if i < len(a) else 0) + (b[i] if i < len(b) else 0) for i in range(n)]


def _scale(a, c):
    return [c * x for x in a]


def _deriv(p):
    return [i * p[i] for i in range(1, len(p))]


def _rem(a, b):
    a, b = _trim(a), _trim(b)
    while len(a) >= len(b) and a:
        c = a[-1] / b[-1]
        k = len(a) - len(b)
        for i, y in enumerate(b):
            a[i + k] -= c * y
        a = _trim(a)
    return a


def _quo(a, b):
    a, b = _trim(a), _trim(b)
    q = [Fraction(0)] * max(1, len(a) - len(b) + 1)
    while len(a) >= len(b) and a:
        c = a[-1] / b[-1]
        k = len(a) - len(b)
        q[k] = c
        for i, y in enumerate(b):
            a[i + k] -= c * y
        a = _trim(a)
    return _trim(q)


def _gcd(a, b):
    a, b = _trim(a), _trim(b)
    while b:
        a, b = b, _rem(a, b)
    return _scale(a, 1 / a[-1])


def _ev(p, x):
    v = Fraction(0)
    for c in reversed(p):
        v = v * x + c
    return v


def _sign(x) -> int:
    return (x > 0) - (x < 0)


def _sturm(p):
    seq = [p, _deriv(p)]
    while True:
        r = _rem(seq[-2], seq[-1])
        if not r:
            return seq
        seq.append(_scale(r, -1))


def _changes(seq, x) -> int:
    """Sign changes of the Sturm sequence at x (x = None: +∞)."""
    signs = [_sign(q[-1]) if x is None else _sign(_ev(q, x)) for q in seq]
    signs = [s for s in signs if s]
    return sum(1 for a, b in zip(signs, signs[1:]) if a != b)


def _ev_sqrt(p, a, b, D):
    """p(a + b√D) as (X, Y): X + Y√D."""
    X, Y = Fraction(0), Fraction(0)
    for c in reversed(p):
        X, Y = X * a + Y * b * D + c, X * b + Y * a
    return X, Y


def _sgn_sqrt(p, q, r) -> int:
    """sign(p + q√r), r >= 0."""
    sp, sq = _sign(p), (_sign(q) if r > 0 else 0)
    if sq == 0 or sp == sq:
        return sp if sp else sq
    if sp == 0:
        return sq
    c = p * p - q * q * r
    return sp if c > 0 else (sq if c < 0 else 0)


class Root:
    """The only root of the square-free ``poly`` in (lo, hi] (lo == hi: the rational root
    lo), with poly(lo) != 0 unless lo == hi."""

    def __init__(self, poly, seq, lo, hi):
        self.poly, self.seq, self.lo, self.hi = poly, seq, lo, hi

    def exact(self) -> bool:
        return self.lo == self.hi

    def refine(self):
        """Halve the interval (or land on the root)."""
        if self.exact():
            return
        m = (self.lo + self.hi) / 2
        pm = _ev(self.poly, m)
        if pm == 0:
            self.lo = self.hi = m
        elif _sign(pm) == _sign(_ev(self.poly, self.lo)):
            self.lo = m
        else:
            self.hi = m

    def cmp_number(self, a, b=Fraction(0), D=Fraction(0)) -> int:
        """sign(root − (a + b√D))."""
        y_lo = _sgn_sqrt(a - self.lo, b, D)            # sign(y − lo)
        if self.exact():
            return -y_lo
        if y_lo <= 0:
            return 1                                    # y <= lo < root
        y_hi = _sgn_sqrt(a - self.hi, b, D)
        if y_hi > 0:
            return -1                                   # root <= hi < y
        # lo < y <= hi: the sign of poly at y against its sign at lo (one root between)
        X, Y = _ev_sqrt(self.poly, a, b, D)
        sy = _sgn_sqrt(X, Y, D)
        if sy == 0:
            return 0
        return 1 if sy == _sign(_ev(self.poly, self.lo)) else -1

    def cmp_root(self, other: "Root") -> int:
        """sign(self − other), exactly."""
        if other.exact():
            return self.cmp_number(other.lo)
        if self.exact():
            return -other.cmp_number(self.lo)
        g = _gcd(self.poly, other.poly)
        if len(g) > 1:
            lo, hi = max(self.lo, other.lo), min(self.hi, other.hi)
            if lo < hi:
                gs = _sturm(g)
                if _changes(gs, lo) - _changes(gs, hi) == 1 and \
                        self._holds(g, gs) and other._holds(g, gs):
                    return 0                            # the common root of both
        while True:
            if self.hi <= other.lo or (self.exact() and self.lo <= other.lo):
                return -1
            if other.hi <= self.lo or (other.exact() and other.lo <= self.lo):
                return 1
            (self if self.hi - self.lo >= other.hi - other.lo else other).refine()
            if self.exact() or other.exact():
                return self.cmp_root(other) if not (self.exact() and other.exact()) \
                    else _sign(self.lo - other.lo)

    def _holds(self, g, gs) -> bool:
        """Is this root a root of g (a factor of poly)?"""
        return _changes(gs, self.lo) - _changes(gs, self.hi) == 1

    def value(self, scale2=Fraction(1)) -> float:
        """root·√scale2, rounded to float64 (the interval refined to 2⁻⁷⁰ relative)."""
        while not self.exact() and (self.hi - self.lo) > abs(self.hi) * Fraction(1, 2 ** 70):
            self.refine()
        with decimal.localcontext(_CTX):
            m = (self.lo + self.hi) / 2
            v = decimal.Decimal(m.numerator) / decimal.Decimal(m.denominator)
            return float(v * (decimal.Decimal(scale2.numerator) /
                              decimal.Decimal(scale2.denominator)).sqrt())


class TorusExact:
    """A torus's numbers as written (decide.prepare's entry for it)."""
    kind = "torus"

    def __init__(self, obj, V):
        self.Q = tuple(exact(c) - v for c, v in zip(obj.center, V))
        self.A = tuple(exact(c) for c in obj.given_axis)
        self.AA = sum(c * c for c in self.A)
        self.R2 = exact(obj.major) ** 2
        self.K = self.R2 - exact(obj.minor) ** 2
        self.QQ = sum(c * c for c in self.Q)
        self.QA = sum(q * a for q, a in zip(self.Q, self.A))
        # float copies for decide's screen (never screened out: no plane, no sphere)
        self.fQ = tuple(float(c) for c in self.Q)


def poly(o: TorusExact, E):
    """F(s) along the ray V + s·E (E exact), lowest degree first."""
    EE = sum(c * c for c in E)
    QE = sum(q * e for q, e in zip(o.Q, E))
    EA = sum(e * a for e, a in zip(E, o.A))
    w2 = [o.QQ, -2 * QE, EE]                            # |w|²
    wa = [-o.QA, EA]                                    # w·A
    s = _add(w2, [o.K])
    F = _scale(_mul(s, s), o.AA)
    F = _add(F, _scale(w2, -4 * o.R2 * o.AA))
    F = _add(F, _scale(_mul(wa, wa), 4 * o.R2))
    return _trim(F)


def first_crossing(F, lo=Fraction(0)):
    """The smallest s > lo at which F changes sign, as a Root, or None."""
    if len(F) < 2:
        return None
    sf = _quo(F, _gcd(F, _deriv(F)))                   # square-free part
    seq = _sturm(sf)
    bound = 1 + max(abs(c / sf[-1]) for c in sf[:-1])   # Cauchy: every root below it
    if lo >= bound:
        return None
    # a root at lo itself (the viewpoint on the torus) is not a hit: start just past it
    a = _nudge(sf, seq, lo, bound) if _ev(sf, lo) == 0 else lo
    for r in _isolate(sf, seq, a, bound):
        # the root changes F's sign iff its multiplicity in F is odd: F's signs just
        # around it (the interval holds no other root of F)
        left, right = _around(F, sf, seq, r)
        if left != right:
            return r
    return None


def _nudge(sf, seq, a, b):
    """A point just above a (a root of sf) below the next root."""
    h = (b - a) / 2
    while _changes(seq, a) - _changes(seq, a + h) > 0 or _ev(sf, a + h) == 0:
        h /= 2
    return a + h


def _isolate(sf, seq, a, b):
    """The roots of sf in (a, b], ascending, each as a Root (sf(a) != 0)."""
    n = _changes(seq, a) - _changes(seq, b)
    if n == 0:
        return
    if n == 1:
        yield Root(sf, seq, a, b)
        return
    m = (a + b) / 2
    if _ev(sf, m) == 0:
        left = _nudge_down(sf, seq, m, a)
        yield from _isolate(sf, seq, a, left)
        yield Root(sf, seq, m, m)
        yield from _isolate(sf, seq, _nudge(sf, seq, m, b), b)
        return
    yield from _isolate(sf, seq, a, m)
    yield from _isolate(sf, seq, m, b)


def _nudge_down(sf, seq, m, a):
    """A point just below m (a root of sf) above the previous root, sf != 0 there."""
    h = (m - a) / 2
    while _changes(seq, m - h) - _changes(seq, m) > 1 or _ev(sf, m - h) == 0:
        h /= 2
    return m - h


def _around(F, sf, seq, r: Root):
    """(sign of F just left of r, just right of r)."""
    if r.exact():
        x = r.lo
        return (_sign(_ev(F, _nudge_down(sf, seq, x, x - 1))),
                _sign(_ev(F, _nudge(sf, seq, x, x + 1))))
    # (lo, hi] holds the only root; make hi a non-root
    while _ev(F, r.hi) == 0 and not r.exact():
        r.refine()
    if r.exact():
        return _around(F, sf, seq, r)
    return _sign(_ev(F, r.lo)), _sign(_ev(F, r.hi))


def torus_hit(o: TorusExact, E):
    """The exact hit parameter s (hit = V + s·E) as a Root, or None for a miss."""
    return first_crossing(poly(o, E))
