"""The references' own quadrics (cylinder 22, cone 23, ellipsoid), written from the course's
intended geometry independently of rt_core (tests/test_independence.py):

* cylinder: base centre P, centerline a (0 0 0 read as the y axis, as nw's code), radius r,
  height h: |w|²|a|² − (w·a)² = r²|a|², w = p − P, open, 0 <= w·a <= h|a|;
* cone: apex P, centerline a, k = (r/h)²: |w|²|a|² − (1+k)(w·a)² = 0, open,
  0 <= w·a <= h|a|;
* ellipsoid: centre P, semi-axes (a, b, c): Σ (w_i/s_i)² = 1, closed.

Along base + t·d (w = base − P + t·d): α t² + β t + γ = 0 with β = 2·(d·M·w0) (the course's
a, b, c quadratic).  Closed: the near root only (as the sphere); open: the nearer root with
t > 0 in the axial range.  The float64 oracle (``hits``) follows that literally with
rounding-error bounds (mitsuba_ref/oracle.py's EF); the exact oracle (``evaluate``) decides it
in rational arithmetic, signs of α + β√D exactly.
"""
from __future__ import annotations

import copy
import math
from fractions import Fraction

import numpy as np

from .geometry import pow2_scaled, ray_length

KINDS = ("cylinder", "cone", "ellipsoid")
INF = math.inf
OPEN = ("cylinder", "cone")


def fields(o):
    """(centre, axis, radius, height) or (centre, semi-axes) of a quadric read by rt_core
    (.given_axis, .radius, .height) or by mitsuba_ref.scenefile / exact (.centerline,
    .radius_height): numbers as given.  The centerline as written, never rt_core's reading of
    it (its .axis): a zero one is the y axis here, by this rule of its own."""
    if o.kind == "ellipsoid":
        return tuple(o.center), tuple(o.axes)
    axis = tuple(o.given_axis) if _has(o, "given_axis") else tuple(o.centerline)
    if all(c == 0 for c in axis):
        axis = tuple(type(axis[0])(c) for c in (0, 1, 0))
    if not 2.0 ** -200 < max(abs(float(c)) for c in axis) < 2.0 ** 200:
        axis = pow2_scaled(axis)        # (a direction: a centerline 1e308 0.3 1, 1e-320 0 0)
    if _has(o, "height"):
        r, h = o.radius, o.height
    else:
        r, h = o.radius_height
    return tuple(o.center), axis, r, h


def _has(o, name) -> bool:
    try:
        getattr(o, name)
        return True
    except AttributeError:
        return False


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _form(kind, f):
    """(mdiag, c, a, e, hh): f(w) = Σ m_i w_i² − c (w·a)² − e; axial range w·a in
    [0, √hh] (None: closed)."""
    if kind == "ellipsoid":
        a2, b2, c2 = (s * s for s in f[1])
        return (b2 * c2, a2 * c2, a2 * b2), 0, (0, 0, 0), a2 * b2 * c2, None
    _, a, r, h = f
    aa = _dot(a, a)
    k = r * r / (h * h) if kind == "cone" else None
    c = (1 + k) if kind == "cone" else 1
    e = r * r * aa if kind == "cylinder" else 0
    return (aa, aa, aa), c, a, e, h * h * aa


def _mul(m, c, a, x, y):
    return (m[0] * x[0] * y[0] + m[1] * x[1] * y[1] + m[2] * x[2] * y[2]
            - c * _dot(x, a) * _dot(y, a))


# --- the float64 oracle (EF numbers) ---------------------------------------------------------

def prepare(i, o, Obj, vec, EFof):
    """oracle._Obj of a quadric: its numbers as inputs rounded once."""
    f = fields(o)
    # point: the axis (or the semi-axes), size: radius and height
    return Obj(i, o.kind, o, ("q", o.kind, f), center=vec(f[0]), point=vec(f[1]),
               size=tuple(EFof(x) for x in f[2:]))


def _of(ob):
    """The oracle object's numbers in the order ``_form`` takes them."""
    return (ob.center, ob.point, *ob.size)


def outline(ob, w0, d, EF, ops):
    """A cylinder's outline decision in a well-conditioned form (None for the other kinds):
    r|d×a| − |det(d, a, w0)|, whose sign is the discriminant's (β² − 4αγ = 4|a|²(r|d×a| −
    |det|)(r|d×a| + |det|): |det|/|d×a| is the distance of the ray's line from the axis).
    The notes' β² − 4αγ cancels far from the ray's origin, so its bound says little there."""
    if ob.kind != "cylinder":
        return None
    dot3, _, _, _, cross3, length3 = ops
    _, a, r, _ = _of(ob)
    x = cross3(d, a)
    det = dot3(x, w0)
    return r * length3(x) - EF(abs(det.v), det.e)


def outline_margin(c, margin) -> float:
    """The margin of a quadric's outline decision: the discriminant's, or for a cylinder the
    larger of it and ``outline``'s where their signs agree (each bounds the same sign), the
    smaller where they do not."""
    m = margin(c.disc.v, c.disc.e)
    o = getattr(c, "outline", None)
    if o is None:
        return m
    mo = margin(o.v, o.e)
    return max(m, mo) if (o.v > 0.0) == (c.disc.v > 0.0) else min(m, mo)


def hits(ob, base, d, rules, Cand, EF, esqrt, ops):
    """The oracle's Cand for a quadric: the course's quadratic, literally (and a cylinder's
    ``outline`` for the margin of its discriminant's sign)."""
    dot3, diff3, sum3, scale3 = ops[:4]
    m, c, a, e, hh = _form(ob.kind, _of(ob))
    w0 = diff3(base, ob.center)
    A = _mul(m, c, a, d, d)
    B = 2.0 * _mul(m, c, a, d, w0)
    C = _mul(m, c, a, w0, w0) - e
    disc = B * B - 4.0 * A * C
    line = outline(ob, w0, d, EF, ops)
    if not disc.v > 0.0:
        if A.v == 0.0:      # a ray along a cylinder's axis (B = 0 then too): no t, a miss
            return Cand(False, EF(math.inf, 0.0), base, disc=disc, why="disc", outline=line)
        t = -B / (2.0 * A)
        return Cand(False, t, sum3(base, scale3(t, d)), disc=disc, why="disc", outline=line)
    if A.v == 0.0:
        # a ray along a cone's side: one root, −C/B, as the exact references take it (it
        # divided by A = 0: a ZeroDivisionError that check read as no colour to name, and
        # excused any; a helper's review)
        roots = [-C / B]
    else:
        s = esqrt(disc)
        r1, r2 = (-B - s) / (2.0 * A), (-B + s) / (2.0 * A)
        roots = sorted((r1, r2), key=lambda x: x.v)
    cands = []
    for t in (roots if hh is not None else roots[:1]):
        hit = sum3(base, scale3(t, d))
        y = dot3(diff3(hit, ob.center), a)
        cand = Cand(t.v > 0.0, t, hit, disc=disc, why="" if t.v > 0.0 else "tmin",
                    outline=line)
        cand.newhit = (y, hh) if hh is not None else ()
        if cand.ok and hh is not None and not (y.v >= 0.0 and y.v <= math.sqrt(hh.v)):
            cand.ok, cand.why = False, "edge"
        cands.append(cand)
    # the near root if valid, else the far one if valid, else the near one (a miss)
    first = next((c for c in cands if c.ok), cands[0])
    if len(cands) == 2:
        # both roots go with each (two_root_risk judges the answer from either)
        for c in cands:
            c.roots = cands
        first.answer = ("near" if first is cands[0] else "far") if first.ok else "miss"
    if first.ok and rules.clip_spheres and _clipped(first.hitloc[2], rules):
        first.ok, first.why, first.answer = False, "clip", "miss"
    return first


def risk(c, margin, clip_test):
    """(decision, margin, Cand of that answer: a root's, valid, or a miss) of the cheapest
    change of an open quadric's answer (two_root_risk) from its Cand ``c`` (quadric.hits, or
    a Cand this returned); ``margin(slack, err)``, ``clip_test(cand)``: (name, passed,
    margin) or None where no clip applies."""
    near, far = c.roots

    def tests(r):
        out = [("tmin_margin", r.t.v > 0.0, margin(r.t.v, r.t.e))]
        out += [("edge_margin", v >= 0.0, margin(v, e)) for v, e in axis_slacks(r)]
        return out

    outline = ("disc_margin", c.disc.v > 0.0, outline_margin(c, margin))
    m, k, answer = two_root_risk(outline, tests(near), tests(far), clip_test(near),
                                 clip_test(far), c.answer)
    if answer == "miss":
        alt = copy.copy(c)
        alt.ok, alt.why, alt.answer = False, "flip", "miss"
        return k, m, alt
    alt = copy.copy(near if answer == "near" else far)
    alt.ok, alt.why, alt.answer = True, "", answer
    return k, m, alt


# --- an open quadric's two roots: which answer is nearest to changing -------------------------

ZERO, NEVER = (0.0, ""), (math.inf, "")


def _all_pass(tests):
    """Cost (margin, name) of making every test pass: the farthest failed one must flip."""
    return max(((m, k) for k, p, m in tests if not p), default=ZERO)


def _one_fails(tests):
    """Cost of making one test fail (none if one already does): the nearest passed one."""
    return ZERO if not all(p for _, p, _ in tests) else min(((m, k) for k, _, m in tests),
                                                             default=NEVER)


def two_root_risk(outline, near, far, clip_near, clip_far, now):
    """(cost, decision, answer) of the cheapest change of an open quadric's answer along one
    ray: the object is hit at the near root if the outline passes and the near root's tests
    (t, axial range) pass, else at the far root if its tests pass; then the screen clip of
    that root.  ``outline``: (name, passed, cost); ``near``/``far``: lists of (name, passed,
    cost); ``clip_*``: (name, passed, cost) or None where no clip applies; ``now``: "near",
    "far" or "miss", the answer.  Costs are margins over bounds (any monotone measure): every
    decision of a change must flip, so a change costs its largest one, and the cheapest
    answer other than ``now`` is returned ("near", "far" or "miss").

    Judging the chosen root alone (as the course code reads it, the near root of a miss)
    left out a far root lying on the rim within rounding, and a near root within rounding
    of valid behind a far hit: a correct float64 tracer was called wrong, and the float64
    oracle took a far hit unflagged (a helper's fuzzing; docs/open-defects.md)."""
    if not outline[1]:
        return outline[2], outline[0], "near"
    cost = two_root_costs(outline, near, far, clip_near, clip_far)
    (c, k), answer = min((v, a) for a, v in cost.items() if a != now)
    return c, k, answer


def two_root_costs(outline, near, far, clip_near, clip_far) -> dict:
    """{answer: (cost, decision)} of each answer of an open quadric along one ray whose
    outline passes ("near", "far", "miss"; the answer it has costs 0): two_root_risk's
    arguments, each answer's largest flip."""
    lose = (outline[2], outline[0])
    ok = lambda c: ZERO if c is None or c[1] else (c[2], c[0])
    fail = lambda c: NEVER if c is None else ((c[2], c[0]) if c[1] else ZERO)
    return {
        "near": max(_all_pass(near), ok(clip_near)),
        "far": max(_one_fails(near), _all_pass(far), ok(clip_far)),
        "miss": min(lose, max(_all_pass(near), fail(clip_near)),
                    max(_one_fails(near), _one_fails(far)),
                    max(_one_fails(near), _all_pass(far), fail(clip_far))),
    }


def _clipped(z, rules) -> bool:
    if rules.screen_clip == ">":
        return z.v > 0.0
    if rules.screen_clip == ">=":
        return z.v >= 0.0
    return False


def axis_slacks(c):
    """(y, h|a| − y) of an open quadric's hit (values, error bounds in units of u)."""
    y, hh = c.newhit
    hv = math.sqrt(hh.v)
    return ((y.v, y.e), (hv - y.v, y.e + hh.e / (2 * hv) + hv))


def normal(ob, c, unit3, diff3):
    """Outward normal: the gradient M·w at the hit."""
    m, cc, a, e, hh = _form(ob.kind, _of(ob))
    w = diff3(c.hitloc, ob.center)
    wa = _dot(w, a)
    return unit3(tuple(m[i] * w[i] - cc * wa * a[i] for i in range(3)))


# --- the exact oracle -------------------------------------------------------------------------

def _sign(x) -> int:
    return (x > 0) - (x < 0)


def _sgn(p, q, r) -> int:
    """sign(p + q√r), r >= 0, exactly."""
    sp, sq = _sign(p), (_sign(q) if r > 0 else 0)
    if sq == 0:
        return sp
    if sp == 0 or sp == sq:
        return sq
    return sp * _sign(p * p - q * q * r)


def _sgn2(p, q, r, u, v) -> int:
    """sign(p + q√r + u√v) exactly."""
    s1, s2 = _sgn(p, q, r), (_sign(u) if v > 0 else 0)
    if s2 == 0 or s1 == s2:
        return s1 if s1 else s2
    if s1 == 0:
        return s2
    return s1 * _sgn(p * p + q * q * r - u * u * v, 2 * p * q, r)


def _float(p, q, r) -> float:
    """p + q√r as a float; where a term leaves a float's range (a scene at 1e-155: 1/A near
    1e310; rays 2⁻⁶⁰⁰ long: r near 2⁻¹²⁰⁰, q near 2⁶⁰⁰, r underflowed to 0) in 60-digit
    decimal arithmetic."""
    try:
        fq, fr = float(q), float(r)
        if (r and not 2.0 ** -1000 < fr < 2.0 ** 1000) or (
                q and not 2.0 ** -1000 < abs(fq) < 2.0 ** 1000):
            raise OverflowError
        return float(p) + fq * math.sqrt(fr)
    except OverflowError:
        import decimal
        with decimal.localcontext() as ctx:
            ctx.prec = 60
            dec = lambda x: (decimal.Decimal(Fraction(x).numerator) /
                             decimal.Decimal(Fraction(x).denominator))
            return float(dec(p) + dec(q) * dec(r).sqrt())


class Prep:
    """A quadric's exact numbers relative to the viewpoint (exact.trace_exact), and what a
    ray's terms need of them as integers: with a = aI/La, the form
    f(x, y) = Σ m_i x_i y_i − c (x·a)(y·a) is F(x, y)/Lm, F's coefficients mI and
    cI = c·Lm/La² integers, and w0 = W0I/Lw, so that along V + t·D/Dd (D integers)
    α = F(D, D)/(Lm·Dd²) and β/2 = F(D, W0I)/(Lm·Lw·Dd) take one fraction each (the
    Fractions' arithmetic term by term took most of trace_exact's time)."""

    def __init__(self, obj, V, rules):
        self.obj, self.kind = obj, obj.kind
        f = fields(obj)
        self.form = m, c, a, e, hh = _form(obj.kind, f)
        self.W0 = tuple(Fraction(v) - Fraction(c) for v, c in zip(V, f[0]))   # base − P
        self.Vz = Fraction(V[2])
        a = tuple(Fraction(x) for x in a)
        self.La = math.lcm(*(x.denominator for x in a))
        self.aI = tuple(int(x * self.La) for x in a)
        ca = Fraction(c) / (self.La * self.La)
        self.Lm = math.lcm(*(Fraction(x).denominator for x in m), ca.denominator)
        self.mI = tuple(int(Fraction(x) * self.Lm) for x in m)
        self.cI = int(ca * self.Lm)
        self.Lw = math.lcm(*(x.denominator for x in self.W0))
        self.W0I = tuple(int(x * self.Lw) for x in self.W0)
        self.WaI = _dot(self.W0I, self.aI)
        self.C = _mul(m, c, a, self.W0, self.W0) - e          # the ray's γ: its origin's
        self.Wa = _dot(self.W0, a)

    def ints(self, D):
        """The numerators (Ai, Bi, Da) of ``terms``: α = Ai/(Lm·Dd²), β/2 = Bi/(Lm·Lw·Dd),
        d·a = Da/(La·Dd)."""
        mI, cI, W = self.mI, self.cI, self.W0I
        Da = _dot(D, self.aI)
        A = mI[0] * D[0] * D[0] + mI[1] * D[1] * D[1] + mI[2] * D[2] * D[2] - cI * Da * Da
        B = (mI[0] * D[0] * W[0] + mI[1] * D[1] * W[1] + mI[2] * D[2] * W[2]
             - cI * Da * self.WaI)
        return A, B, Da

    def terms(self, D, Dd):
        """(α, β/2, d·a) of the ray V + t·D/Dd, exactly."""
        A, B, Da = self.ints(D)
        return (Fraction(A, self.Lm * Dd * Dd), Fraction(B, self.Lm * self.Lw * Dd),
                Fraction(Da, self.La * Dd))


DECISIONS = ("outline", "t", "axis>=0", "axis<=h", "clip")
# an open quadric's other root (the far one of a near hit or of a miss, the near one of a far
# hit): its answer turns on both (two_root_risk); the object's verdict is the others' alone
OTHER = ("other t", "other axis>=0", "other axis<=h", "other clip")
OPEN_DECISIONS = DECISIONS + OTHER


def evaluate(p: Prep, D, Dd, rules):
    """((tn, td) or None, {decision: (passed, margin)}) for the ray V + t·D/Dd; t's ratio is
    the float64 value of the exact root as a fraction (for ordering and depth)."""
    m, c, a, e, hh = p.form
    # the discriminant X = (β/2)² − α·γ in integers: Xn/(Lm²·Lw²·Dd²·Cd), γ = Cn/Cd; a ray
    # that misses (most of them) takes no Fraction but its t
    if Dd == 0:
        raise ZeroDivisionError("a ray of no direction")
    Ai, Bi, Di = p.ints(D)
    Cn, Cd, Lm, Lw = p.C.numerator, p.C.denominator, p.Lm, p.Lw
    Xn = Bi * Bi * Cd - Ai * Cn * Lm * Lw * Lw
    DD = _dot(D, D)
    tests = {"outline": (Xn > 0, Xn / (Lm * Lm * Lw * Lw * Cd * DD) if Xn else 0.0)}  # X/|d|²
    closed = hh is None
    if Xn <= 0 or Ai == 0 and Bi == 0:
        t0 = Fraction(-Bi * Dd, Lw * Ai) if Ai else Fraction(0)         # −(β/2)/α
        names = DECISIONS[1:] + (OTHER if hh is not None else ())
        tests.update({k: (False, 0.0) for k in names})
        return (t0.numerator, t0.denominator), tests
    A, Bh, da = (Fraction(Ai, Lm * Dd * Dd), Fraction(Bi, Lm * Lw * Dd),
                 Fraction(Di, p.La * Dd))                    # α, β/2, d·a
    C = p.C
    X = Fraction(Xn, Lm * Lm * Lw * Lw * Dd * Dd * Cd)
    norm = ray_length(D, Dd)            # (|D|²/Dd² left float64's range on rays 2^±600 long)
    if A == 0:
        roots = [(-C / (2 * Bh), Fraction(0))]
    else:
        lo, hi = (-Bh / A, Fraction(-1) / A), (-Bh / A, Fraction(1) / A)
        roots = [lo, hi] if A > 0 else [hi, lo]
    if closed:
        roots = roots[:1]
    found = []
    for al, be in roots:
        tp = _sgn(al, be, X)
        tv = _float(al, be, X)
        res = {"t": (tp > 0, tv * norm)}
        if closed:
            res["axis>=0"] = res["axis<=h"] = (True, math.inf)
        else:
            ya, yb = p.Wa + al * da, be * da        # w·a = ya + yb√X
            s_lo = _sgn(ya, yb, X)
            s_hi = _sgn2(ya, yb, X, -1, hh)
            na = math.sqrt(float(_dot(a, a)))
            y = _float(ya, yb, X) / na
            res["axis>=0"] = (s_lo >= 0, y)
            res["axis<=h"] = (s_hi <= 0, math.sqrt(float(hh)) / na - y)
        if rules.clip_spheres and rules.screen_clip != "off":
            d2 = Fraction(D[2], Dd)
            z = _sgn(p.Vz + al * d2, be * d2, X)
            ok = z < 0 or (z == 0 and rules.screen_clip == ">")
            res["clip"] = (ok, -(float(p.Vz) + tv * float(d2)))
        else:
            res["clip"] = (True, math.inf)
        found.append((res, tv))
    # the near root if valid, else the far one if valid, else the near one (a miss)
    pick = next((i for i, (res, _) in enumerate(found)
                 if all(res[n][0] for n in ("t", "axis>=0", "axis<=h"))), 0)
    res, tv = found[pick]
    tests.update(res)
    if not closed:
        # the other root's tests (a single root's other: never valid, never near)
        other = found[1 - pick][0] if len(found) == 2 else {n: (False, math.inf) for n in res}
        tests.update({"other " + n: v for n, v in other.items()})
    tq = Fraction(tv) if math.isfinite(tv) else Fraction(0)
    return (tq.numerator, tq.denominator), tests


def conditions(obj, V, d, Dual, inputs, ddot, near=None):
    """{decision or 't': S} (exact.py's componentwise condition) along unit rays d (N, 3),
    of the root ``evaluate`` picks (the near one if neither is valid) and, for an open
    quadric, of the other ("other t", ...).  ``near`` (an open quadric's): per ray, is
    evaluate's pick the near root (the float64 arithmetic picked here once, and at a rim
    chose the other root: its conditions went with the exact root's margins)."""
    n = len(d)
    f = fields(obj)
    fl = lambda vals: [float(x) for x in vals]
    params = fl(f[0]) + (fl(f[1]) if obj.kind == "ellipsoid" else fl(f[1]) + fl(f[2:]))
    x = inputs(fl(V) + [d[:, 0], d[:, 1], d[:, 2]] + params, n)
    Vv, dv, P = x[0:3], x[3:6], x[6:9]
    if obj.kind == "ellipsoid":
        form = _form("ellipsoid", (P, tuple(x[9:12])))
    else:
        form = _form(obj.kind, (P, tuple(x[9:12]), x[12], x[13]))
    m, c, a, e, hh = form
    w0 = tuple(v - pp for v, pp in zip(Vv, P))
    A = _mul(m, c, a, dv, dv)
    Bh = _mul(m, c, a, dv, w0)
    C = _mul(m, c, a, w0, w0) - e
    X = Bh * Bh - A * C
    with np.errstate(all="ignore"):
        s = Dual(np.sqrt(np.maximum(X.v, 0)), X.g / (2 * np.sqrt(np.maximum(X.v, 1e-300)))[:, None])
        r1, r2 = (-Bh - s) / A, (-Bh + s) / A
        lo_first = (r1.v <= r2.v)
        out = {"outline": X.cond()}
        conds = []
        for t in (r1, r2):
            y = (ddot(w0, a) + t * ddot(dv, a)) / ddot(a, a).sqrt() if hh is not None else t
            hl = (hh.sqrt() / ddot(a, a).sqrt()) if hh is not None else t
            z = Vv[2] + t * dv[2]
            conds.append({"t": t.cond(), "axis>=0": y.cond(), "axis<=h": (hl - y).cond(),
                          "clip": z.cond()})
        # evaluate's choice (``near``; a closed quadric's: the near root)
        if hh is not None and near is None:
            raise ValueError("an open quadric's conditions need evaluate's choice of root")
        near_i = np.where(lo_first, 0, 1)
        pick = near_i if hh is None else np.where(near, near_i, 1 - near_i)
        for k in conds[0]:
            out[k] = np.where(pick == 0, conds[0][k], conds[1][k])
            if hh is not None:
                out["other " + k] = np.where(pick == 0, conds[1][k], conds[0][k])
    return {k: np.nan_to_num(v, nan=np.inf) for k, v in out.items()}


# --- the classifier's float64 view (mitsuba_ref/explain.py) -----------------------------------

def classify_eval(obj, O, d, rules):
    """(t, valid, margin, scale) of a quadric along rays O + t·d (float64 arrays (N, 3)):
    the hit rule as above; ``margin`` the world distance of the decision nearest to flipping:
    the outline (the distance of the ray's closest approach from the surface, |min f|/|∇f|)
    or an open quadric's rim (the hit's axial distance from 0 or h)."""
    f = fields(obj)
    P = np.array([float(c) for c in f[0]])
    fl = (P, tuple(float(c) for c in f[1])) + tuple(float(c) for c in f[2:])
    m, c, a, e, hh = _form(obj.kind, fl)
    m, a = np.array(m, float), np.array(a, float)
    w0 = O - P
    M = lambda x, y: (x * y * m).sum(-1) - c * (x @ a) * (y @ a)
    with np.errstate(all="ignore"):
        A, Bh, C = M(d, d), M(d, w0), M(w0, w0) - e
        X = Bh * Bh - A * C
        s = np.sqrt(np.maximum(X, 0))
        r1, r2 = (-Bh - s) / A, (-Bh + s) / A
        lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
        ts = w0 + (-Bh / A)[:, None] * d                     # the closest approach
        g = 2 * (ts * m - c * (ts @ a)[:, None] * a)
        margin = np.abs(X / A) / np.linalg.norm(g, axis=1)
        if hh is None:
            t = lo
            valid = (X > 0) & (t > 0)
        else:
            na, h = math.sqrt(a @ a), math.sqrt(hh) / math.sqrt(a @ a)
            y = lambda t: ((w0 + t[:, None] * d) @ a) / na
            ok = lambda t: (t > 0) & (y(t) >= 0) & (y(t) <= h)
            t = np.where(ok(lo), lo, hi)
            valid = (X > 0) & (ok(lo) | ok(hi))
            # two_root_risk in world distances, on the axial tests (t's sign is not
            # weighed, as before): the cheapest change of answer among hit at the near
            # root, at the far one, a miss; a miss does not weigh the outline
            yl, yh = y(lo), y(hi)
            gain = lambda r, yr: np.where(r > 0, np.maximum(np.maximum(-yr, yr - h), 0), INF)
            lose = lambda r, yr: np.where(ok(r), np.minimum(yr, h - yr), 0.0)
            near = gain(lo, yl)
            far = np.maximum(lose(lo, yl), gain(hi, yh))
            miss = np.minimum(margin, np.maximum(lose(lo, yl), lose(hi, yh)))
            roots = np.where(ok(lo), np.minimum(far, miss),
                             np.where(ok(hi), np.minimum(near, miss), np.minimum(near, far)))
            margin = np.where(X > 0, roots, margin)
        if rules.clip_spheres and rules.screen_clip != "off":
            z = O[:, 2] + t * d[:, 2]
            valid &= (z <= 0) if rules.screen_clip == ">" else (z < 0)
    size = max(fl[1]) if obj.kind == "ellipsoid" else fl[2] + fl[3]
    return t, valid, np.nan_to_num(margin, nan=0.0), float(np.linalg.norm(P) + size)
