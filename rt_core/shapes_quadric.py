"""The quadric kinds' kernel (cylinder, cone, ellipsoid; rt_core/quadrics.py), type-generic over
Dr.Jit backend and precision, in the form of rt_core/shapes.py's level-1 functions.

Every quadric is written in a local frame G (rows g0, g1, g2; host constants): with l = G·w,
w = p − anchor, the surface is

    l0² + l1² + w2·l2² = e

cylinder: G an orthonormal frame with g2 = the unit axis, w2 = 0, e = r²; cone: the same
frame, w2 = −k = −(r/h)², e = 0; ellipsoid: G = diag(1/a, 1/b, 1/c), w2 = 1, e = 1.  Along a
ray w = t·d − q (q = anchor − origin), with ld = G·d, lq = G·q (a host constant for rays from
the viewpoint):

    A t² − 2B t + C = 0,  A = Σ wᵢ ldᵢ²,  B = Σ wᵢ ldᵢ lqᵢ,  C = Σ wᵢ lqᵢ² − e (host, rounded
    once from its exact rational value: its sign is exact),

and the discriminant by the weighted Lagrange identity, with no cancellation of B² against
A·C:  B² − A·C = e·A − Σ_{i<j} wᵢwⱼ (ldᵢ lqⱼ − ldⱼ lqᵢ)².  The roots are C/q' and q'/A with
q' = B + sign(B)·√disc (neither cancels).  Ellipsoid (closed): the near root only, as the
sphere; cylinder and cone (open): the nearest root with t > 0 whose axial coordinate
y = t·ld2 − lq2 lies in [0, h].  The screen clip applies as to spheres (``rules.clip_spheres``).

Certified decisions (``cert``, rays from the viewpoint, float64): each decided value (disc,
each root's t, each root's y and h − y, A's sign, the roots' order, the clip's z) gets a
first-order bound computed per ray from the absolute values of the same terms (KQ units of
roundoff per term: the inputs carry a few units each, the frame's rounding included, and the
polynomials are of degree at most 4).  A ray is ``sure`` when every value is beyond its bound;
otherwise it is unsure and rt_core/decide.py decides it exactly.  Relative bounds hold only
away from underflow: the discriminant's bound has ``UNDERFLOW`` (2⁻⁹⁰⁰) added, so that a scene
so small that its squares are subnormal (1e-155 and below) is decided exactly ray by ray, as
the other kinds' are there.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

import drjit as dr

from .quadrics import KINDS as QUADRICS, OPEN, equation
from .rules import Rules
from .scene import exact, unit
from .shapes import KB, U64, ObjectConstants, clip_ok, opaque, opaque3, rounded

KQ = 4 * KB * U64          # the bound per unit of |term| (128 units of float64 roundoff)
UNDERFLOW = 2.0 ** -900    # a discriminant this near 0 is never certain (module docstring)


@dataclass(frozen=True)
class QuadricConstants(ObjectConstants):
    """ObjectConstants (q = anchor − viewpoint, c = C) and the local frame."""
    g0: tuple = (0.0, 0.0, 0.0)
    g1: tuple = (0.0, 0.0, 0.0)
    g2: tuple = (0.0, 0.0, 0.0)
    lq: tuple = (0.0, 0.0, 0.0)     # G·q
    aq: tuple = (0.0, 0.0, 0.0)     # |G|·|q| + |lq|: lq's error is KQ·aq at most
    w2: float = 0.0
    e: float = 0.0
    hgt: float = 0.0                # axial range [0, hgt] (open kinds)

    def row(self) -> dict:
        """The slots of accel.LAYOUT's quadric rows (ROW_SLOTS) by name."""
        r = {"w2": self.w2, "e": self.e, "hgt": self.hgt}
        for name in ("g0", "g1", "g2", "lq", "aq"):
            r.update({name + a: v for a, v in zip("xyz", getattr(self, name))})
        return r


ROW_SLOTS = ("qx", "qy", "qz", "c", "id", "grp") + tuple(
    n + a for n in ("g0", "g1", "g2", "lq", "aq") for a in "xyz") + ("w2", "e", "hgt")


def row_view(out, v, A3):
    """A looped table row's constants (accel.KindTable.view) as quadric_t reads them."""
    for name in ("g0", "g1", "g2", "lq", "aq"):
        setattr(out, name, A3(*(v[name + a] for a in "xyz")))
    out.c, out.w2, out.e, out.hgt = v["c"], v["w2"], v["e"], v["hgt"]
    return out


def _frame(axis):
    """Orthonormal rows (g0, g1, g2) with g2 = unit(axis), float64."""
    # (beyond 2^±200, where |axis|² overflows or loses bits to underflow (1e-160 0 0 gave
    # a g2 of length 1.0000056), scene.unit's scaled form: a centerline is a direction
    # whatever its length; the reference scales the same range, mitsuba_ref/quadric.fields)
    big = max(abs(c) for c in axis)
    if 2.0 ** -200 < big < 2.0 ** 200:
        n = math.sqrt(sum(c * c for c in axis))
        g2 = tuple(c / n for c in axis)
    else:
        g2 = unit(axis, "centerline")
    helper = (1.0, 0.0, 0.0) if abs(g2[0]) < 0.6 else (0.0, 1.0, 0.0)
    c = (helper[1] * g2[2] - helper[2] * g2[1], helper[2] * g2[0] - helper[0] * g2[2],
         helper[0] * g2[1] - helper[1] * g2[0])
    cn = math.sqrt(sum(x * x for x in c))
    g0 = tuple(x / cn for x in c)
    g1 = (g2[1] * g0[2] - g2[2] * g0[1], g2[2] * g0[0] - g2[0] * g0[2],
          g2[0] * g0[1] - g2[1] * g0[0])
    return g0, g1, g2


def quadric_constants(i: int, o, V, groups: dict) -> QuadricConstants:
    """Host constants of quadric ``o`` (id i) for viewpoint V (exact numbers)."""
    anchor = tuple(exact(c) for c in o.center)
    Q = tuple(a - v for a, v in zip(anchor, V))
    eq = equation(o)
    # C = f(−Q)/|a|² (cylinder, cone) or /(a²b²c²) (ellipsoid): the sign of f(q), exactly
    norm = eq.e if o.kind == "ellipsoid" else sum(c * c for c in eq.a)
    C = (eq.quad(Q, Q) - eq.e) / norm
    grp = groups.setdefault(("q", o.kind, anchor, eq), len(groups))
    if o.kind == "ellipsoid":
        a, b, c = (float(x) for x in o.axes)
        G = ((1.0 / a, 0.0, 0.0), (0.0, 1.0 / b, 0.0), (0.0, 0.0, 1.0 / c))
        w2, e, h = 1.0, 1.0, 0.0
    else:
        G = _frame(tuple(float(x) for x in o.axis))
        r, h = float(o.radius), float(o.height)
        w2, e = (0.0, r * r) if o.kind == "cylinder" else (-(r / h) ** 2, 0.0)
    lq = tuple(rounded(sum(Fraction(g) * c for g, c in zip(row, Q))) for row in G)
    q = tuple(rounded(c) for c in Q)
    aq = tuple(sum(abs(g) * abs(c) for g, c in zip(row, q)) + abs(l) for row, l in zip(G, lq))
    return QuadricConstants(i, o.kind, q, c=rounded(C), grp=grp, g0=G[0], g1=G[1], g2=G[2],
                            lq=lq, aq=aq, w2=w2, e=e, hgt=h)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def quadric_t(d, o, obj, rules: Rules, vz: float, cert=False):
    """(t, hit) or with ``cert`` (t, certain hit, possible hit, t's lower factor): see the
    module docstring."""
    Array3 = type(d)
    F = dr.value_t(Array3)
    G = [opaque3(Array3, g) for g in (obj.g0, obj.g1, obj.g2)]
    w2, e = opaque(F, obj.w2), opaque(F, obj.e)
    ld = [dr.dot(g, d) for g in G]
    if o is None:
        lq = list(opaque3(Array3, obj.lq))
        C = opaque(F, obj.c)
    else:
        qo = opaque3(Array3, obj.q) - o
        lq = [dr.dot(g, qo) for g in G]
        C = lq[0] * lq[0] + lq[1] * lq[1] + w2 * lq[2] * lq[2] - e
    A = ld[0] * ld[0] + ld[1] * ld[1] + w2 * (ld[2] * ld[2])
    B = ld[0] * lq[0] + ld[1] * lq[1] + w2 * (ld[2] * lq[2])
    c01 = ld[0] * lq[1] - ld[1] * lq[0]
    c02 = ld[0] * lq[2] - ld[2] * lq[0]
    c12 = ld[1] * lq[2] - ld[2] * lq[1]
    disc = e * A - (c01 * c01 + w2 * (c02 * c02 + c12 * c12))
    s = dr.sqrt(dr.select(disc > 0, disc, 0))
    qq = B + dr.mulsign(s, B)
    r1, r2 = C / qq, qq / A
    lo_first = r1 <= r2
    tlo, thi = dr.select(lo_first, r1, r2), dr.select(lo_first, r2, r1)
    outline = disc > 0
    closed = obj.kind not in OPEN
    zo = dr.opaque(F, vz) if o is None else dr.opaque(F, vz) + o.z
    if closed:
        t = tlo
        ok1 = tlo > 0
        hit = outline & ok1 & dr.isfinite(t)
    else:
        h = opaque(F, obj.hgt)
        y1, y2 = tlo * ld[2] - lq[2], thi * ld[2] - lq[2]
        in1 = (tlo > 0) & (y1 >= 0) & (y1 <= h)
        in2 = (thi > 0) & (y2 >= 0) & (y2 <= h)
        t = dr.select(in1, tlo, thi)
        hit = outline & (in1 | in2) & dr.isfinite(t)
    clip = rules.clip_spheres and rules.screen_clip != "off"
    if clip:
        z = dr.fma(t, d.z, zo)
        hit &= clip_ok(z, rules)
    if not cert:
        return t, hit
    assert o is None, "certified decisions are for rays from the viewpoint"
    # absolute terms: |ld_i| <= ad_i (with its error), |lq_i| <= aq_i (host)
    ad = [dr.dot(dr.abs(g), dr.abs(d)) for g in G]
    aq = [opaque(F, c) for c in obj.aq]
    aw = abs(obj.w2)
    k = dr.opaque(F, KQ)
    bA = k * (ad[0] * ad[0] + ad[1] * ad[1] + aw * ad[2] * ad[2])
    bB = k * (ad[0] * aq[0] + ad[1] * aq[1] + aw * ad[2] * aq[2])
    x01, x02, x12 = (ad[0] * aq[1] + ad[1] * aq[0], ad[0] * aq[2] + ad[2] * aq[0],
                     ad[1] * aq[2] + ad[2] * aq[1])
    bd = k * (abs(obj.e) * (bA / k) + x01 * x01 + aw * (x02 * x02 + x12 * x12))
    bq = bB + dr.sqrt(bd) + k * dr.abs(qq)
    aqq = dr.abs(qq)
    rel1 = k + bq / aqq                     # C is rounded once from its exact value
    rel2 = k + bq / aqq + bA / dr.abs(A)
    rlo, rhi = dr.select(lo_first, rel1, rel2), dr.select(lo_first, rel2, rel1)
    blo, bhi = dr.abs(tlo) * rlo, dr.abs(thi) * rhi
    sure = dr.abs(tlo) > blo
    if closed:
        rel = rlo
    else:
        for tt, bt, yy in ((tlo, blo, y1), (thi, bhi, y2)):
            by = bt * dr.abs(ld[2]) + k * (dr.abs(tt) * ad[2] + aq[2] + dr.abs(yy))
            sure &= (dr.abs(tt) > bt) & (dr.abs(yy) > by) & (dr.abs(h - yy) > by + k * h)
        # both roots valid: their order must be certain too; A's sign orders them
        sure &= (dr.abs(A) > bA) & (~(in1 & in2) | (thi - tlo > blo + bhi))
        rel = dr.select(in1, rlo, rhi)
    if clip:
        bz = dr.abs(t) * rel * dr.abs(d.z) + k * (dr.abs(zo) + dr.abs(t * d.z))
        sure &= dr.abs(z) > bz
    # (and never within UNDERFLOW of 0: the bounds are relative, and below ~2⁻¹⁰²² the
    # products they bound lose their digits; a cylinder at 1e-155 had e·A and the squares
    # subnormal, bd 0, and every ray certified a miss)
    bd = bd + dr.opaque(F, UNDERFLOW)
    sure = (disc <= -bd) | ((disc > bd) & sure)
    lf = 1 - rel - k
    return t, hit & sure, hit | ~sure, lf


def quadric_normal(ks, d, t, idx, hit, o=None):
    """Outward unit normal (the gradient Gᵀ·(l0, l1, w2·l2), l = G·(t·d − q)) at the hit of
    each ray on a quadric (undefined on other kinds: select by kind)."""
    T = ks.T
    cache = ks.__dict__.setdefault("_quadric_tables", {})
    if not cache:
        for name in ("g0", "g1", "g2", "q"):
            vals = [getattr(c, name, (0.0, 0.0, 0.0)) for c in ks.consts]
            cache[name] = T.Array3(*([v[i] for v in vals] for i in range(3)))
        cache["w2"] = T.Float([getattr(c, "w2", 0.0) for c in ks.consts])
        for v in cache.values():
            dr.make_opaque(v)
    G = [dr.gather(T.Array3, cache[n], idx, hit) for n in ("g0", "g1", "g2")]
    q = dr.gather(T.Array3, cache["q"], idx, hit)
    w2 = dr.gather(T.Float, cache["w2"], idx, hit)
    w = dr.fma(d, t, -q) if o is None else dr.fma(d, t, o - q)
    lw = [dr.dot(g, w) for g in G]
    n = G[0] * lw[0] + G[1] * lw[1] + G[2] * (w2 * lw[2])
    # scaled by its largest component first: at a scene scale of 1e-155 its squared norm
    # underflows to 0 (a NaN normal); the scaling is exact but for the division's rounding
    m = dr.maximum(dr.maximum(dr.abs(n.x), dr.abs(n.y)), dr.abs(n.z))
    return dr.normalize(n / dr.select(m > 0, m, 1))


def is_quadric(kind) -> bool:
    return kind in QUADRICS


def quadric_code(kind_code):
    """Mask of the lanes whose kernel kind number (kinds.KIND_CODE) is a quadric's."""
    from .kinds import KIND_CODE
    codes = sorted(KIND_CODE[k] for k in QUADRICS)
    m = kind_code == codes[0]
    for c in codes[1:]:
        m |= kind_code == c
    return m


def quadric_boxes(consts, pad: float = 2.0 ** -20) -> tuple:
    """(lo, hi) float64 (count, 3): axis-aligned boxes of quadrics relative to the viewpoint,
    from their host constants, enlarged by ``pad`` of their size (the constants' rounding is
    ~1e-16 of it): the ellipsoid's centre ± semi-axes; an open cylinder's or cone's two end
    discs (a disc of radius ρ and unit normal â reaches ρ·√(1 − â_i²) along axis i; the
    cone's apex is a disc of radius 0)."""
    import numpy as np
    lo, hi = [], []
    for c in consts:
        q = np.array(c.q, np.float64)
        if c.kind == "ellipsoid":
            ext = np.array([1.0 / c.g0[0], 1.0 / c.g1[1], 1.0 / c.g2[2]])
            a, b = q - ext, q + ext
        else:
            ax = np.array(c.g2, np.float64)
            top = q + c.hgt * ax
            rho = math.sqrt(c.e) if c.kind == "cylinder" else math.sqrt(-c.w2) * c.hgt
            reach = rho * np.sqrt(np.maximum(1.0 - ax * ax, 0.0))
            r0 = reach if c.kind == "cylinder" else 0.0 * reach
            a = np.minimum(q - r0, top - reach)
            b = np.maximum(q + r0, top + reach)
        m = pad * (np.abs(b - a).max() + np.abs(q).max())
        lo.append(a - m)
        hi.append(b + m)
    return np.array(lo).reshape(-1, 3), np.array(hi).reshape(-1, 3)
