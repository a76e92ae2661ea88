"""Kernels of the planar kinds triangle and disk (rt_core/planar.py), type-generic like
rt_core/shapes.py, and their host constants and certified bounds.

Both are the plane's hit (``shapes._plane``: t = n·q/(n·d), q = anchor − viewpoint) and an
extent test without division, in the finite plane's form: for a frame vector a, the hit's
coordinate along it times n·d is (n × a)·(q × d) (Binet–Cauchy; shapes.py's docstring).

* triangle, anchor P1, N = (P2 − P1) × (P3 − P1), frame x̂ = (P2 − P1)/|N|, ŷ = (P3 − P1)/|N|
  (not unit): u·(n·d) = ŷ·(q × d) and v·(n·d) = −x̂·(q × d) are the barycentric weights of
  P2 and P3 times n·d, so inside is u >= 0, v >= 0, 1 − u − v >= 0, tested as
  su >= 0, sv >= 0, den − su − sv >= 0 with su, sv, den sign-folded (den = |n·d|);
* disk, anchor the centre, frame (x̂, ŷ) unit in-plane: inside is |hit − c|² <= r², tested as
  r²·den² − su² − sv² >= 0.

``size`` holds |N| twice for a triangle (so that q, q + |N|x̂, q + |N|ŷ are its corners);
``c`` holds a disk's r² (rounded once from the exact square).  Certified bounds ``bm``:
the triangle's three values share one (each is at most the sum of su's, sv's and den's
bounds); the disk's value is quadratic in d, so its bound scales with |d|² and is tested on
its own (a ``_Least`` with a data bound), not merged with the linear ones.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .planar import AXES, disk_axis, triangle_normal_exact
from .rules import Rules
from .scene import exact
from .shapes import (KB, KD, U64, ObjectConstants, _canonical, _check, _fast, _fast_result,
                     _plane, _plane_bounds, _plane_fast, _scaled, _sg, _fold,
                     cross_x, dot_x, frame_coords, least, opaque, opaque3, rounded)


def planar_constants(i: int, o, V, groups: dict, vz: float) -> ObjectConstants:
    """The host constants of a triangle or disk (rounded once from exact values), grouped
    with every object on the same plane (the same t on every ray: the tie rule decides)."""
    if o.kind == "triangle":
        P = [tuple(exact(c) for c in p) for p in o.points]
        N = triangle_normal_exact(o.points)
        anchor = P[0]
    else:
        N = tuple(exact(c) for c in o.given_normal)
        anchor = tuple(exact(c) for c in o.center)
    NN0 = dot_x(N, N)
    Nc = _canonical(N)
    NN = dot_x(Nc, Nc)
    Q = tuple(c - v for c, v in zip(anchor, V))
    n = tuple(rounded(c, NN) for c in Nc)
    NQ = dot_x(Nc, Q)
    g = rounded(NQ + Nc[2] * V[2], NN)
    Nk = tuple(_sg(Nc) * c for c in Nc)
    grp = groups.setdefault(("p", Nk, dot_x(Nk, anchor)), len(groups))
    q = tuple(rounded(c) for c in Q)
    if o.kind == "triangle":
        e1 = tuple(a - b for a, b in zip(P[1], P[0]))
        e2 = tuple(a - b for a, b in zip(P[2], P[0]))
        xd = tuple(rounded(c, NN0) for c in e1)
        yd = tuple(rounded(c, NN0) for c in e2)
        nlen = math.sqrt(float(NN0))
        size, radius, c2 = (nlen, nlen), 0.0, 0.0
    else:
        O = tuple(exact(c) for c in AXES[disk_axis(o.given_normal)])
        p = tuple(c * NN - dot_x(O, Nc) * nc for c, nc in zip(O, Nc))
        PP = dot_x(p, p)
        xd = tuple(rounded(c, PP) for c in p)
        yd = tuple(rounded(c, PP * NN) for c in cross_x(Nc, p))
        r = exact(o.radius)
        size, radius, c2 = (0.0, 0.0), float(o.radius), rounded(r * r)
    b = _plane_bounds(vz, q, n, g, (0.0, 0.0, 0.0), yd, size)      # the clip's bound
    b["bm"] = _extent_bound(o.kind, q, n, xd, yd, c2)
    return ObjectConstants(i, o.kind, q, n, rounded(NQ, NN), xd, yd, size, radius, c2, g,
                           grp, **b)


def _extent_bound(kind: str, q, n, X, Y, c2) -> float:
    """The extent test's bound for rays with |d| <= KD (shapes.py "Certified decisions"):
    |(q×d)_i| <= |q_j| + |q_k|, so |su| <= Σ|Y_i|(|q_j| + |q_k|) = Su, and the same for sv."""
    k = KB * U64 * KD
    aq = [abs(c) for c in q]
    cab = (aq[1] + aq[2], aq[2] + aq[0], aq[0] + aq[1])
    an = KD * sum(abs(c) for c in n)
    Su = KD * sum(abs(y) * c for y, c in zip(Y, cab))
    Sv = KD * sum(abs(x) * c for x, c in zip(X, cab))
    if kind == "triangle":
        # su, sv, den each within k·(its absolute terms); den − su − sv adds two roundings
        return 2 * k * (Su + Sv + an)
    # r²den² − su² − sv²: each square within (2ε + ε² + u) of its absolute value squared
    # (ε <= k/2 the relative bound of su, sv, den), the sum two more roundings
    return 2 * k * (c2 * an * an + Su * Su + Sv * Sv)


def _values(kind, su, sv, den, obj, F):
    """The extent test's value (>= 0 inside with closed edges, > 0 with open ones)."""
    if kind == "triangle":
        return None, (su, sv, den - su - sv)
    c = opaque(F, obj.c)
    return c * den * den - su * su - sv * sv, ()


def planar_t(d, o, obj: ObjectConstants, rules: Rules, vz: float, cert=False):
    """Ray–triangle or ray–disk: the plane's t and hit, then the extent test (module
    docstring); with ``cert`` the certified (t, certain, possible, lf) of shapes.object_t."""
    F, B = _check(d)
    Array3 = type(d)
    kind = obj.kind
    strict = rules.edges == "open"
    if _fast(obj, rules, o, cert):
        # rays from the viewpoint, certified: den > 0 on hits, sign folded into X, Y
        t, den, dec, lf = _plane_fast(d, obj, rules, vz, cert)
        if dec is None:
            return _fast_result(t, dec, lf)
        su, sv = frame_coords(d, obj)
        f, three = _values(kind, su, sv, den, obj, F)
        if kind == "triangle":
            tm = dec.tamed
            dec.add(least(least(three[0], three[1], tm), three[2], tm),
                    _scaled(obj.bm, cert), strict)
        else:
            dec.add(f, _disk_bound(F, obj.bm, cert), strict)
        return _fast_result(t, dec, lf)
    t, hit, den, q, ci = _plane(d, o, obj, rules, vz, cert)
    c = dr.cross(q, d)
    X, Y = obj.xdir, obj.ydir
    if o is None and isinstance(obj.nq, (int, float)):
        # rays from the viewpoint: sign(den) = sign(n·q) on a hit, folded into the constants
        sg = -1.0 if obj.nq < 0 else 1.0
        su = dr.dot(opaque3(Array3, _fold(sg, Y)), c)
        sv = -dr.dot(opaque3(Array3, _fold(sg, X)), c)
        aden = den * dr.opaque(F, sg)
    else:
        su = dr.mulsign(dr.dot(opaque3(Array3, Y), c), den)
        sv = dr.mulsign(-dr.dot(opaque3(Array3, X), c), den)
        aden = dr.abs(den)
    f, three = _values(kind, su, sv, aden, obj, F)
    vals = three if kind == "triangle" else (f,)
    inside = True
    for v in vals:
        inside = inside & ((v > 0) if strict else (v >= 0))
    if not cert:
        return t, hit & inside
    cc, lf = ci
    if kind == "triangle":
        m = dr.minimum(dr.minimum(vals[0], vals[1]), vals[2])
        cc.test(F, m, _scaled(obj.bm, cert), strict)
    else:
        cc.test(F, f, _disk_bound(F, obj.bm, cert), strict)
    return (t, *cc.split(), lf)


def _disk_bound(F, bm, cert):
    """The disk's bound for rays with |d| <= KD·cert (quadratic in d), as Dr.Jit data so that
    ``_Least`` tests it on its own."""
    b = bm if cert == 1 else bm * cert * cert
    return b if not isinstance(b, (int, float)) else dr.opaque(F, b)


def planar_corners(kind: str, consts) -> np.ndarray:
    """(count, m, 3) points (relative to the viewpoint) whose convex hull holds each object:
    a finite plane's four corners, a triangle's three points, a disk's circumscribed square.
    The one place these are computed (the bins, the BVH boxes and the reflection cull use
    it)."""
    q = np.array([c.q for c in consts], np.float64).reshape(-1, 3)
    x = np.array([c.xdir for c in consts], np.float64).reshape(-1, 3)
    y = np.array([c.ydir for c in consts], np.float64).reshape(-1, 3)
    if kind == "fplane":
        wh = np.array([c.size for c in consts], np.float64).reshape(-1, 2)
        ex, ey = x * wh[:, :1], y * wh[:, 1:]
        return np.stack([q, q + ex, q + ey, q + ex + ey], 1)
    if kind == "triangle":
        s = np.array([c.size[0] for c in consts], np.float64)[:, None]
        return np.stack([q, q + s * x, q + s * y], 1)
    r = np.array([c.radius for c in consts], np.float64)[:, None]
    return np.stack([q + r * (a * x + b * y) for a in (-1, 1) for b in (-1, 1)], 1)
