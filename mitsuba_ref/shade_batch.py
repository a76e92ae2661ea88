"""The shading oracle's paths (``shade_oracle.shade_pixels``, ``other_sides_of``) of many
pixels at once.

``shade_oracle.ray_trace`` follows one pixel's path in Python floats, which costs about a
millisecond a bounce: 4,000 differing pixels of a validation run take a second, and a mirror
corridor's 800 bounces a pixel take ``rtval check`` half a minute.  Here the same operations
run in the same order on numpy float64 arrays, one lane per pixel: every value, error bound
and margin is the same float64 number as the per-pixel oracle's (IEEE operations on arrays
round as on scalars), and tests/test_shade_batch.py asserts that equality, bit for bit, on
the bundled and the course scenes.  Where the per-pixel code branches, the lanes are
selected (``np.where``) or the lanes that go on are kept (a bounce's lanes shrink as paths
end).

Covers what most course scenes hold (``supported``): spheres, planes, finite and tiled
planes, point lights and spotlights, no texture.  The per-pixel oracle does the rest, and
every pixel where it raises (``shade``'s 'raised': a division by zero, a rounding of
infinity, a flipped verdict with no hit to take), as it always has, and, to be safe, every
pixel whose intensity comes out NaN.

Decisions can be taken the other way (``flips``, as ``shade_oracle._Alt`` takes them):
``shade_oracle.other_sides_of`` traces the paths of many pixels' near decisions, in every
combination, a round at a time here.  The per-pixel oracle stays the specification.  The
near decisions of a path (``paths``' second entry) are the same set, listed by bounce;
their order means nothing to ``other_sides``.
"""
from __future__ import annotations

import math

import numpy as np

from rt_core.kinds import kind
from mitsuba_ref import oracle
from mitsuba_ref.convert import stand_in_frame
from mitsuba_ref.oracle import EF, _f32_exact
from mitsuba_ref.shade_oracle import FACING, _Alt, quantize

INF = math.inf
KINDS = ("sphere", "plane", "fplane", "tplane")
# fewer lanes than this still going after a bounce go on in the per-pixel code, from where
# they are: a mirror corridor's few long paths cost the arrays a few milliseconds a bounce
# whatever the lanes, the per-pixel code a tenth of a millisecond a lane.  Measured on 100
# pixels of scenes/shade_mirrors.txt at 97 columns, cut-off 50000 (up to 2,900 bounces):
# per pixel 10.6 s; the arrays handing over below 1, 4, 8, 16, 32 or 64 lanes 9.6, 8.9,
# 8.3, 7.5, 7.9 and 10.4 s
TAIL_LANES = 16
LIMIT = _Alt.LIMIT                      # a decision is near below this margin


def supported(scene) -> bool:
    """Can this module shade the scene's pixels (its kinds, no texture)?"""
    return all(o.kind in KINDS and getattr(o, "texture", None) is None
               for o in scene.objects) and \
        all(l.kind in ("pointlight", "spotlight") for l in scene.lights)


# --- EF on arrays: shade_oracle's EF, each rule elementwise ----------------------------------

class V:
    """An EF whose value and bound are arrays (or floats, broadcast): ``v``, ``e``."""
    __slots__ = ("v", "e")

    def __init__(self, v, e):
        self.v, self.e = v, e

    def at(self, idx) -> "V":
        """The lanes ``idx`` (a constant stays itself)."""
        return V(_at(self.v, idx), _at(self.e, idx))


def _at(x, idx):
    return x[idx] if isinstance(x, np.ndarray) else x


def c(x: EF) -> V:
    """A constant: an EF made once (an input read from a file, a computed constant)."""
    return V(x.v, x.e)


def inp(x: float) -> V:
    """``EF(x)``: an input read from a file, rounded once unless it is a float32 number."""
    return V(float(x), 0.0 if _f32_exact(float(x)) else abs(float(x)))


def _zero(a: V):
    """An exact 0 (False when no lane is: most bounds are not 0, and numpy's calls cost)."""
    e = a.e
    if type(e) is float:
        return False if e != 0.0 else a.v == 0.0
    z = e == 0.0
    if not z.any():
        return False
    return z & (a.v == 0.0)


def _pow2(a: V):
    """An exact ±2^k or 0 (oracle._pow2; False when no lane is exact)."""
    e, v = a.e, a.v
    if type(e) is float:
        if e != 0.0:
            return False
        if type(v) is float:
            return v == 0.0 or math.frexp(abs(v))[0] == 0.5
        return (v == 0.0) | (np.frexp(np.abs(v))[0] == 0.5)
    z = e == 0.0
    if not z.any():
        return False
    return z & ((v == 0.0) | (np.frexp(np.abs(v))[0] == 0.5))


def _sum_bound(a: V, b: V, v):
    """The bound of a sum: EF.__add__'s exact zeros first, else both bounds and a rounding."""
    e = a.e + b.e + np.abs(v)
    zb = _zero(b)
    if zb is not False:
        e = np.where(zb, a.e, e)
    za = _zero(a)
    if za is not False:
        e = np.where(za, b.e, e)
    return e


def add(a: V, b: V) -> V:
    v = a.v + b.v
    return V(v, _sum_bound(a, b, v))


def sub(a: V, b: V) -> V:
    v = a.v + -b.v
    return V(v, _sum_bound(a, b, v))


def neg(a: V) -> V:
    return V(-a.v, a.e)


def mul(a: V, b: V) -> V:
    v = a.v * b.v
    e = np.abs(a.v) * b.e + np.abs(b.v) * a.e
    p = _pow2(a) | _pow2(b)
    return V(v, e + np.abs(v) if p is False else np.where(p, e, e + np.abs(v)))


def div(a: V, b: V) -> V:
    q = a.v / b.v
    e = (a.e + np.abs(q) * b.e) / np.abs(b.v)
    return V(q, np.where(_pow2(b), e, e + np.abs(q)))


def sqrt(x: V) -> V:
    s = np.sqrt(x.v)
    e = np.where(s > 0, x.e / (2.0 * s), np.where(x.e == 0, 0.0, INF))
    return V(s, e + s)


def exact(x: float) -> V:
    return V(float(x), 0.0)


def dot3(a, b) -> V:
    return add(add(mul(a[0], b[0]), mul(a[1], b[1])), mul(a[2], b[2]))


def diff3(a, b) -> tuple:
    return (sub(a[0], b[0]), sub(a[1], b[1]), sub(a[2], b[2]))


def sum3(a, b) -> tuple:
    return (add(a[0], b[0]), add(a[1], b[1]), add(a[2], b[2]))


def scale3(s: V, a) -> tuple:
    return (mul(s, a[0]), mul(s, a[1]), mul(s, a[2]))


def length3(a) -> V:
    return sqrt(dot3(a, a))


def unit3(a) -> tuple:
    n = length3(a)
    return (div(a[0], n), div(a[1], n), div(a[2], n))


def unit3z(a) -> tuple:
    """(unit3(a), where a's length is 0: the per-pixel oracle's division by zero)."""
    n = length3(a)
    return (div(a[0], n), div(a[1], n), div(a[2], n)), n.v == 0.0


def cross3(a, b) -> tuple:
    return (sub(mul(a[1], b[2]), mul(a[2], b[1])), sub(mul(a[2], b[0]), mul(a[0], b[2])),
            sub(mul(a[0], b[1]), mul(a[1], b[0])))


def xform3(m, a) -> tuple:
    return (dot3(m[0], a), dot3(m[1], a), dot3(m[2], a))


def where(m, a: V, b: V) -> V:
    return V(np.where(m, a.v, b.v), np.where(m, a.e, b.e))


def pmin(a, *bs):
    """Python's min(a, b, ...) on every lane: the first of the smallest (a NaN is never
    smaller, so where one comes first it stays; numpy's minimum would spread it)."""
    for b in bs:
        a = np.where(b < a, b, a)
    return a


def pmax(a, *bs):
    """Python's max(a, b, ...) on every lane."""
    for b in bs:
        a = np.where(b > a, b, a)
    return a


def _margin(slack, err):
    """oracle._margin: |slack| / err, inf where err is 0."""
    return np.where(err == 0.0, INF, np.abs(slack) / np.where(err == 0.0, 1.0, err))


def _vec(p) -> tuple:
    return tuple(c(x) for x in p)


# --- oracle.trace on lanes, the objects of a kind stacked ----------------------------------------

class _Group:
    """The objects of one kind ('sphere', or 'plane' for plane, fplane and tplane), their
    numbers stacked (k, 1): an operation with the lanes (n,) gives (k, n), one row an
    object, so a trace costs numpy's calls once a kind, not once an object."""

    def __init__(self, kind, obs):
        self.kind, self.obs = kind, obs
        self.rows = [ob.idx for ob in obs]
        self.idx = np.array(self.rows)[:, None]

        def col(efs):
            return V(np.array([[x.v] for x in efs]), np.array([[x.e] for x in efs]))

        zero3 = (EF(0.0, 0.0),) * 3
        if kind == "sphere":
            self.center = tuple(col([ob.center[i] for ob in obs]) for i in range(3))
            self.radius = col([ob.radius for ob in obs])
            return
        self.normal = tuple(col([ob.normal[i] for ob in obs]) for i in range(3))
        self.point = tuple(col([ob.point[i] for ob in obs]) for i in range(3))
        self.rotmat = tuple(tuple(col([(ob.rotmat[r] if ob.rotmat else zero3)[i] for ob in obs])
                                  for i in range(3)) for r in range(3))
        self.size = tuple(col([ob.size[i] if ob.size else EF(0.0, 0.0) for ob in obs])
                          for i in range(2))
        self.finite = np.array([[ob.kind == "fplane"] for ob in obs])
        self.framed = np.array([ob.kind in ("fplane", "tplane") for ob in obs])


class Groups(list):
    """The scene's objects by kind (``_Group``), spheres first, with ``nobj``, ``order``
    ((group, row) of every object in the scene's order: trace's and _diagnose's loops) and
    ``other`` (nobj, nobj): whether two objects' surfaces differ (oracle._Obj.key: the same
    surface ties exactly, and the tie rule decides)."""

    def __init__(self, obs):
        super().__init__()
        for name, kinds in (("sphere", ("sphere",)), ("plane", KINDS[1:])):
            mine = [ob for ob in obs if ob.kind in kinds]
            if mine:
                self.append(_Group(name, mine))
        self.nobj = len(obs)
        self.order = sorted(((k, r) for k, g in enumerate(self) for r in range(len(g.rows))),
                            key=lambda kr: self[kr[0]].rows[kr[1]])
        self.other = np.array([[a.key != b.key for b in obs] for a in obs]).reshape(
            len(obs), len(obs))


class _Cand:
    """A kind's verdicts (oracle.Cand), (k, n): ``par`` where a plane's n·d is 0 (no t)."""

    def __init__(self, ok, t, hitloc, par=None, ndotd=None, disc=None, newhit=()):
        self.ok, self.t, self.hitloc, self.par = ok, t, hitloc, par
        self.ndotd, self.disc, self.newhit = ndotd, disc, newhit


def _clipped(z, rules):
    if rules.screen_clip == ">":
        return z > 0.0
    if rules.screen_clip == ">=":
        return z >= 0.0
    return np.zeros(np.shape(z), bool)


def _inside(g, newhit, rules):
    """oracle._inside on every row and lane."""
    u, v = newhit[0].v, newhit[1].v
    w, h = g.size[0].v, g.size[1].v
    if rules.edges == "closed":
        return (0.0 <= u) & (u <= w) & (0.0 <= v) & (v <= h)
    return (0.0 < u) & (u < w) & (0.0 < v) & (v < h)


def _plane(g, base, d, rules) -> _Cand:
    """oracle.plane_hits, fplane_hits, tplane_hits."""
    ndotd = dot3(g.normal, d)
    par = ndotd.v == 0.0
    t = div(sub(dot3(g.normal, g.point), dot3(g.normal, base)), ndotd)
    hitloc = sum3(base, scale3(t, d))
    ok = ~par & (t.v > rules.t_min) & ~_clipped(hitloc[2].v, rules)
    cand = _Cand(ok, t, hitloc, par=par, ndotd=ndotd)
    if g.framed.any():
        cand.newhit = xform3(g.rotmat, diff3(hitloc, g.point))
        cand.inside = _inside(g, cand.newhit, rules)
        cand.ok = ok & (cand.inside | ~g.finite)
    return cand


def _sphere(g, base, d, rules) -> _Cand:
    """oracle.sphere_hits: the near root where the discriminant is positive, else the root
    where it would vanish."""
    oc = diff3(base, g.center)
    a = dot3(d, d)
    b = mul(dot3(d, oc), exact(2.0))
    cc = sub(dot3(oc, oc), mul(g.radius, g.radius))
    disc = sub(mul(b, b), mul(mul(a, exact(4.0)), cc))
    pos = disc.v > 0.0
    two_a = mul(a, exact(2.0))
    t = where(pos, div(sub(neg(b), sqrt(disc)), two_a), div(neg(b), two_a))
    hitloc = sum3(base, scale3(t, d))
    ok = pos & (t.v > 0.0)
    if rules.clip_spheres:
        ok = ok & ~_clipped(hitloc[2].v, rules)
    cand = _Cand(ok, t, hitloc, disc=disc)
    cand.zero = two_a.v == 0.0                  # (the per-pixel oracle raises there)
    return cand


class _Hit:
    """oracle.Hit on lanes: hit, id (−1 on a miss), t, position, normal, uv, the margins,
    and ``risk`` (lanes, objects): each object's smallest margin among ``risks``."""


def _edge_margin(g, cand, base, d, rules):
    """oracle._edge_margin on every row and lane."""
    u, v = cand.newhit[0], cand.newhit[1]
    w, h = g.size
    nd = cand.ndotd
    qxd = cross3(diff3(g.point, base), d)
    su = dot3(g.rotmat[1], qxd)
    sv = neg(dot3(g.rotmat[0], qxd))
    swu, shv = sub(mul(w, nd), su), sub(mul(h, nd), sv)
    slacks = ((u.v, u.e, su), (w.v - u.v, u.e + w.e, swu),
              (v.v, v.e, sv), (h.v - v.v, v.e + h.e, shv))
    sign = np.where(nd.v > 0.0, 1.0, -1.0)             # x = slack · (n·d)
    ok = [(s >= 0.0) if rules.edges == "closed" else (s > 0.0) for s, _, _ in slacks]
    free = [(sign * x.v >= 0.0) if rules.edges == "closed" else (sign * x.v > 0.0)
            for _, _, x in slacks]
    # the larger margin, or the smaller where the two forms fall on different sides
    ms = [np.where(good == other, pmax(_margin(s, e), _margin(x.v, x.e)),
                   pmin(_margin(s, e), _margin(x.v, x.e)))
          for (s, e, x), good, other in zip(slacks, ok, free)]
    inside = ok[0] & ok[1] & ok[2] & ok[3]
    low = pmin(*ms)
    # max over the failed slacks, in their order: the first failed one, then larger ones
    high, seen = np.full(np.shape(low), np.nan), np.zeros(np.shape(low), bool)
    for m, good in zip(ms, ok):
        high = np.where(good, high, np.where(seen, pmax(high, m), m))
        seen = seen | ~good
    return np.where(inside, low, high)


def _tests(g, cand, base, d, rules) -> list:
    """oracle._tests on every row and lane: (diagnostic, passed, margin, present)."""
    out = []
    clip = rules.screen_clip != "off" and (g.kind == "plane" or rules.clip_spheres)
    if g.kind == "sphere":
        t = cand.t
        out.append(("disc_margin", cand.disc.v > 0.0, _margin(cand.disc.v, cand.disc.e), True))
        out.append(("tmin_margin", t.v > 0.0, _margin(t.v, t.e), True))
        has_t = True
    else:
        nd = cand.ndotd
        out.append(("graze", nd.v != 0.0, _margin(nd.v, nd.e), True))
        has_t = ~cand.par
        tmin = EF(rules.t_min)
        t = cand.t
        out.append(("tmin_margin", t.v > tmin.v, _margin(t.v - tmin.v, t.e + tmin.e), has_t))
    if clip:
        z = cand.hitloc[2]
        out.append(("clip_margin", ~_clipped(z.v, rules), _margin(z.v, z.e), has_t))
    if g.kind == "plane" and g.finite.any():
        out.append(("edge_margin", cand.inside, _edge_margin(g, cand, base, d, rules),
                    has_t & g.finite))
    return out


def _at_risk(tests, valid, shape):
    """oracle._at_risk on every lane: (index into ``tests``, margin).  Python's min and max
    of (margin, diagnostic) tuples, in the tests' order: a valid hit's smallest margin (on a
    tie, the first diagnostic by name), an invalid one's largest failed margin (on a tie,
    the last by name)."""
    rank = {name: r for r, name in enumerate(sorted(t[0] for t in tests))}
    # each test's name's rank, by index + 1 (0: none yet)
    by = np.array([-1] + [rank[t[0]] for t in tests])
    lo, lo_k = np.full(shape, np.nan), np.full(shape, -1)
    hi, hi_k = np.full(shape, np.nan), np.full(shape, -1)
    for k, (name, passed, m, present) in enumerate(tests):
        m, r = np.broadcast_to(m, shape), rank[name]
        less = (m < lo) | ((m == lo) & (r < by[lo_k + 1]))
        take = present & ((lo_k < 0) | less)
        lo, lo_k = np.where(take, m, lo), np.where(take, k, lo_k)
        more = (m > hi) | ((m == hi) & (r > by[hi_k + 1]))
        take = present & ~passed & ((hi_k < 0) | more)
        hi, hi_k = np.where(take, m, hi), np.where(take, k, hi_k)
    return np.where(valid, lo_k, hi_k), np.where(valid, lo, hi)


_KEYS = ("edge_margin", "tie_gap", "clip_margin", "tmin_margin", "graze", "disc_margin")


def _pick(g, cand_rows, pos):
    """Per lane, row ``pos`` (0 where −1) of a (k, n) V."""
    lanes = np.arange(pos.shape[0])
    at = np.maximum(pos, 0)
    return V(np.broadcast_to(cand_rows.v, (len(g.rows), len(lanes)))[at, lanes],
             np.broadcast_to(cand_rows.e, (len(g.rows), len(lanes)))[at, lanes])


def trace(gs: Groups, base, d, rules, skip, flip=None) -> _Hit:
    """oracle.trace on lanes: ``skip`` the object each lane ignores (−1: none); ``flip``
    (lanes, objects): the verdicts taken the other way (oracle.trace's ``flip``: where one
    has no hit to take, it raises ValueError, and 'raised' says so)."""
    n = len(skip)
    cands, raised, valid = [], np.zeros(n, bool), []
    for g in gs:
        cand = (_sphere if g.kind == "sphere" else _plane)(g, base, d, rules)
        live = skip != g.idx
        if g.kind == "sphere":
            raised |= (cand.zero & live).any(0)
        cand.ok = cand.ok & live
        cands.append(cand)
        ok = cand.ok
        if flip is not None:
            fl = flip[:, g.rows].T & live
            none = ~(cand.disc.v > 0.0) if g.kind == "sphere" else cand.par
            raised |= (fl & ~ok & none).any(0)
            ok = ok ^ fl
        valid.append(ok)
    # the closest valid hit, object by object in the scene's order (ties: rules.ties)
    win, wt = np.full(n, -1), np.zeros(n)
    last = rules.ties == "last"
    for k, r in gs.order:
        g, cand = gs[k], cands[k]
        t = cand.t.v[r]
        take = valid[k][r] & ((win < 0) | (t < wt) | ((t == wt) & last))
        win = np.where(take, g.rows[r], win)
        wt = np.where(take, t, wt)
    h = _Hit()
    h.hit, h.id = win >= 0, win
    z = np.zeros(n)
    h.t = V(z, z)
    h.position = [V(z, z)] * 3
    h.normal = [V(z, z)] * 3
    h.uv = [V(z, z)] * 2
    lut = np.full(gs.nobj + 1, -1)
    for g, cand in zip(gs, cands):
        lut[:] = -1
        lut[g.rows] = np.arange(len(g.rows))
        pos = lut[win]                          # (win −1: lut's last entry, −1)
        w = pos >= 0
        if not w.any():
            continue
        h.t = where(w, _pick(g, cand.t, pos), h.t)
        hit = [_pick(g, x, pos) for x in cand.hitloc]
        h.position = [where(w, a, b) for a, b in zip(hit, h.position)]
        if g.kind == "sphere":
            nrm, zero = unit3z(diff3(hit, [_pick(g, x, pos) for x in g.center]))
            raised |= w & zero
        else:
            nrm = [_pick(g, x, pos) for x in g.normal]
        h.normal = [where(w, a, b) for a, b in zip(nrm, h.normal)]
        if g.kind == "plane" and len(cand.newhit):
            framed = w & g.framed[np.maximum(pos, 0)]
            h.uv = [where(framed, _pick(g, a, pos), b) for a, b in zip(cand.newhit[:2], h.uv)]
    h.raised = raised
    _diagnose(h, gs, cands, base, d, rules, skip)
    return h


def _diagnose(h, gs: Groups, cands, base, d, rules, skip) -> None:
    """oracle._diagnose on lanes."""
    n = len(skip)
    for key in _KEYS:
        setattr(h, key, np.full(n, INF))
    h.risk = np.full((n, gs.nobj), INF)
    win, has = h.id, h.hit
    lanes = np.arange(n)
    tw = h.t
    # each kind's tests, cheapest flips and tie margins on every row at once
    risk = []
    for g, cand in zip(gs, cands):
        tests = _tests(g, cand, base, d, rules)
        k, m = _at_risk(tests, cand.ok, cand.ok.shape)
        risk.append((tests, k, m, _margin(cand.t.v - tw.v, cand.t.e + tw.e)))
    other = gs.other
    for gk, r in gs.order:
        g, cand = gs[gk], cands[gk]
        tests, k, m, mt = risk[gk]
        idx = g.rows[r]
        live = skip != idx
        behind = live & cand.ok[r] & (win != idx)
        if behind.any():
            # a valid hit behind the winner: a near tie (not of an identical surface)
            j = np.maximum(win, 0)
            tie = behind & has & other[idx][j]
            h.tie_gap = np.where(tie, pmin(h.tie_gap, mt[r]), h.tie_gap)
            h.risk[lanes, j] = np.fmin(h.risk[lanes, j], np.where(tie, mt[r], INF))
        go = live & ~behind
        mine = win == idx
        t = cand.t.v[r]
        far = np.abs(t) > tw.v + 1e-4 * (tw.v + tw.e + cand.t.e[r])
        if g.kind == "sphere":
            go = go & (mine | ~(has & far))
        else:
            par = cand.par[r]
            gone = par & (has | (g.obs[r].kind == "fplane"))
            go = go & (mine | ~(gone | (~par & has & far)))
        if not go.any():
            continue
        for i, (name, *_rest) in enumerate(tests):
            sel = go & (k[r] == i)
            setattr(h, name, np.where(sel, pmin(getattr(h, name), m[r]), getattr(h, name)))
        # (risks: a key is near where any of its margins is: NaN margins are never near)
        h.risk[:, idx] = np.fmin(h.risk[:, idx], np.where(go, m[r], INF))


def _hit_margin(gs: Groups, h, base, d, skip, ties, tmax, near=None):
    """shade_oracle._hit_margin on lanes; ``near`` (lanes, objects) gets each sphere's margin
    of the ray passing inside or outside it."""
    m = pmin(h.edge_margin, h.clip_margin, h.tmin_margin, h.graze)
    if ties:
        m = pmin(m, h.tie_gap)
    tw = np.where(h.hit, h.t.v, INF)
    top = pmin(tw, tmax)
    bv, dv = [x.v for x in base], [x.v for x in d]
    for g in gs:
        if g.kind != "sphere":
            continue
        cen, r = g.center, g.radius
        along_v = ((cen[0].v - bv[0]) * dv[0] + (cen[1].v - bv[1]) * dv[1]) + \
            (cen[2].v - bv[2]) * dv[2]
        go = (skip != g.idx) & ~((along_v + r.v < 0) | (along_v - r.v > top))
        if not go.any():
            continue
        q = diff3(cen, base)
        along = dot3(q, d)
        p = length3(diff3(q, scale3(along, d)))
        mm = _margin(p.v - r.v, p.e + r.e)
        for row, idx in enumerate(g.rows):
            m = np.where(go[row], pmin(m, mm[row]), m)
            if near is not None:
                near[:, idx] = np.fmin(near[:, idx], np.where(go[row], mm[row], INF))
    return m


# --- shade_oracle.ray_trace on lanes ------------------------------------------------------------

def _reach(frames, ids, P) -> np.ndarray:
    """shade_oracle.reach on lanes: their hits P (V triple) on objects ``ids``."""
    out = np.zeros(len(ids))
    for j, (ax, ay, foot) in frames.items():
        on = np.flatnonzero(ids == j)
        if len(on):
            rel = [P[i].v[on] - foot[i] for i in range(3)]
            out[on] = np.maximum(np.abs(rel[0] * ax[0] + rel[1] * ax[1] + rel[2] * ax[2]),
                                 np.abs(rel[0] * ay[0] + rel[1] * ay[1] + rel[2] * ay[2]))
    return out


def _materials(scene):
    """Per object, as arrays indexed by object: ambient, diffuse, specular (3 V each, EF of
    the numbers as written), of the material and of a tiled plane's background."""
    def column(mats, f, i):
        efs = [inp(getattr(m, f)[i]) for m in mats]
        return V(np.array([x.v for x in efs]), np.array([x.e for x in efs]))

    def table(mats):
        return {f: [column(mats, f, i) for i in range(3)]
                for f in ("ambient", "diffuse", "specular")} | \
            {"shiny": np.array([any(m.specular) for m in mats], bool)}
    objs = scene.objects
    return table([o.material for o in objs]), \
        table([getattr(o, "background", None) or o.material for o in objs])


def _gather(tab, fg, ids):
    """Per lane, the field values of object ``ids``' material (background where not fg)."""
    fgm, bgm = tab
    out = {}
    for f in ("ambient", "diffuse", "specular"):
        out[f] = [V(np.where(fg, a.v[ids], b.v[ids]), np.where(fg, a.e[ids], b.e[ids]))
                  for a, b in zip(fgm[f], bgm[f])]
    out["shiny"] = np.where(fg, fgm["shiny"][ids], bgm["shiny"][ids])
    return out


def _int_margin(x: V, extra: float):
    dist = np.abs(x.v - np.round(x.v)) - extra
    return np.where(dist <= 0, 0.0, _margin(dist, x.e))


def shade(scene, base, d, rules, max_dist: float, flips=None, limit=None) -> dict:
    """shade_oracle.ray_trace of every lane's ray (base, d: EF triples of arrays): 'I',
    'err' (n, 3), 'bounces', the MARGINS (n,), 'seen' (each lane's near decisions, _Alt's
    keys), 'raised' (where the per-pixel code raises).  ``flips``: per lane, the near
    decisions taken the other way (_Alt's keys; default none), ``limit``: below what margin
    a decision is near (_Alt's).  (numpy's warnings are off: the lanes a branch does not
    take compute whatever they compute, and are not used.)"""
    with np.errstate(all="ignore"):
        return _shade(scene, base, d, rules, max_dist, flips, limit)


def _shade(scene, base, d, rules, max_dist: float, flips, limit) -> dict:
    obs = oracle.prepared(scene)
    gs = Groups(obs)
    n = len(base[0].v)
    nobj = len(obs)
    tabs = _materials(scene)
    tile = {ob.idx: (oracle.tile_scale(ob.src, rules), ob.src.size) for ob in obs
            if ob.kind == "tplane"}
    out = {"I": np.zeros((n, 3)), "err": np.zeros((n, 3)), "bounces": np.zeros(n, np.int32),
           "reach": np.zeros(n)}
    for k in ("geo", "shadow", "tile", "maxdist", "texel"):
        out[k] = np.full(n, INF)
    # the stand-in squares' frames of the infinite and tiled planes (shade_oracle.reach)
    frames = {j: stand_in_frame(o, scene.viewpoint) for j, o in enumerate(scene.objects)
              if not kind(o.kind).bounded}
    seen = [[] for _ in range(n)]
    # the lanes where the per-pixel oracle raises (a division by zero, a rounding of
    # infinity): a primary direction of no length first
    raised = np.isnan(d[0].v) & np.isnan(d[1].v) & np.isnan(d[2].v)
    lights = []
    for light in scene.lights:
        spot = None
        if light.kind == "spotlight":
            try:
                cos_t = math.cos(math.radians(light.theta))
                axis = oracle.unit3(oracle.diff3(oracle.vec(light.aim),
                                                 oracle.vec(light.center)))
            except (ValueError, ZeroDivisionError):
                # aimed at itself, or an infinite angle: raised where the light is asked
                cos_t, axis = 0.0, None
            spot = (axis and tuple(c(a) for a in axis), V(cos_t, 4.0 * abs(cos_t)))
        lights.append((_vec(oracle.vec(light.center)),
                       [inp(x) for x in light.emissivity], spot))

    lane = np.arange(n)                           # the lanes still going, into ``out``
    skip = np.full(n, -1)
    total = V(np.zeros(n), np.zeros(n))
    stack = []                                    # per bounce: (lanes, local I, specular)
    b = 0

    near_at = LIMIT if limit is None else limit
    # each key taken the other way somewhere: on which lanes
    flipped = {}
    for i, keys in enumerate(flips or ()):
        for key in keys:
            flipped.setdefault(key, np.zeros(n, bool))[i] = True

    def note(key, m, at):
        for i in np.flatnonzero(m < near_at):
            seen[at[i]].append(key)

    def choose(key, m, at, outcome):
        """_Alt.choose: ``outcome``, negated where the decision is near and flipped (the
        key noted where it is near)."""
        note(key, m, at)
        if key not in flipped:
            return outcome
        return outcome ^ ((m < near_at) & flipped[key][at])

    while len(lane):
        if b and len(lane) < TAIL_LANES:
            _hand_over(scene, lane, base, d, skip, total, b, rules, max_dist, flips, limit,
                       out, seen, raised)
            break
        h = trace(gs, base, d, rules, skip)
        raised[lane] |= h.raised
        near = np.full((len(lane), nobj), INF)
        out["geo"][lane] = pmin(out["geo"][lane],
                                _hit_margin(gs, h, base, d, skip, True, INF, near))
        risk = np.fmin(near, h.risk)
        for j in range(nobj):
            note((b, "geo", j), risk[:, j], lane)
        if any((b, "geo", j) in flipped for j in range(nobj)):
            h = _flip_geo(gs, h, risk, base, d, rules, skip, lane, b, flipped, near_at, note,
                          raised)
        # a miss ends the path, black
        gone = ~h.hit
        out["I"][lane[gone]] = 0.0
        out["err"][lane[gone]] = 0.0
        keep = np.flatnonzero(h.hit)
        lane, base, d, h = lane[keep], [x.at(keep) for x in base], [x.at(keep) for x in d], \
            _take(h, keep)
        total = add(total.at(keep), h.t)
        ids = h.id
        H, N = h.position, h.normal
        out["reach"][lane] = np.maximum(out["reach"][lane], _reach(frames, ids, H))
        fg = np.ones(len(lane), bool)
        for j, (k, size) in tile.items():
            on = np.flatnonzero(ids == j)
            if not len(on):
                continue
            u = mul(h.uv[0].at(on), inp(k))
            vv = h.uv[1].at(on)
            if rules.tile_add_first:
                u, vv = add(u, exact(oracle.OFF)), add(vv, exact(oracle.OFF))
            x, y = div(u, inp(size[0])), div(vv, inp(size[1]))
            raised[lane[on]] |= (inp(size[0]).v == 0.0) | (inp(size[1]).v == 0.0) | \
                ~np.isfinite(x.v) | ~np.isfinite(y.v)
            off = oracle.OFF * 2.0 ** -53
            mx, my = _int_margin(x, off), _int_margin(y, off)
            out["tile"][lane[on]] = pmin(out["tile"][lane[on]], mx, my)
            uu = h.uv[0].v[on] * k
            w, hh = size
            if rules.tile_add_first:
                relx, rely = np.floor((oracle.OFF + uu) / w), np.floor((oracle.OFF + h.uv[1].v[on]) / hh)
            else:
                relx, rely = np.floor(oracle.OFF + uu / w), np.floor(oracle.OFF + h.uv[1].v[on] / hh)
            raised[lane[on]] |= ~np.isfinite(relx) | ~np.isfinite(rely)
            # (floor + floor odd: the parities differ.  Not their float sum, which past 2^52
            # rounds to an even number where Python's integers keep the odd one)
            odd = (np.fmod(relx, 2.0) != 0.0) != (np.fmod(rely, 2.0) != 0.0)
            fg[on] = choose((b, "tile", 1), my, lane[on],
                            choose((b, "tile", 0), mx, lane[on], odd))
        mat = _gather(tabs, fg, ids)
        I = list(mat["ambient"])
        for l, (centre, emis, spot) in enumerate(lights):
            D = diff3(centre, H)
            dist = length3(D)
            L, zero = unit3z(D)
            raised[lane] |= zero
            cl = dot3(L, N)
            lit = ~(cl.v <= 0)
            near = np.flatnonzero((cl.v <= 0) & (cl.v > -FACING * cl.e))
            if len(near):           # (shade_oracle: the term's size joins the bound)
                zero, distn = V(np.zeros(len(near)), cl.e[near]), dist.at(near)
                for i in range(3):
                    term = div(mul(mul(mat["diffuse"][i].at(near), emis[i]), zero), distn)
                    I[i] = _put(I[i], near, add(I[i].at(near), term))
            if spot is not None:
                axis, cos_t = spot
                if axis is None:
                    raised[lane[lit]] = True
                    axis = (exact(0.0),) * 3
                s = sub(dot3(scale3(exact(-1.0), L), axis), cos_t)
                ms = _margin(s.v, s.e)
                at = np.flatnonzero(lit)
                out["shadow"][lane[at]] = pmin(out["shadow"][lane[at]], ms[at])
                inside = choose((b, "spot", l), ms[at], lane[at], s.v[at] > 0)
                lit[at] = inside
            at = np.flatnonzero(lit)
            if not len(at):
                continue
            Ha, La = [x.at(at) for x in H], [x.at(at) for x in L]
            sh = trace(gs, Ha, La, rules, ids[at])
            raised[lane[at]] |= sh.raised
            m = _hit_margin(gs, sh, Ha, La, ids[at], False, dist.v[at])
            m = np.where(sh.hit, pmin(m, _margin(sh.t.v - dist.v[at], sh.t.e + dist.e[at])), m)
            out["shadow"][lane[at]] = pmin(out["shadow"][lane[at]], m)
            real = sh.hit & (sh.t.v < dist.v[at])
            out["reach"][lane[at]] = np.maximum(
                out["reach"][lane[at]], np.where(real, _reach(frames, sh.id, sh.position), 0.0))
            blocked = choose((b, "shadow", l), m, lane[at], real)
            on = at[~blocked]
            cla, dista = cl.at(on), dist.at(on)
            for i in range(3):
                term = div(mul(mul(mat["diffuse"][i].at(on), emis[i]), cla), dista)
                I[i] = _put(I[i], on, add(I[i].at(on), term))
        seg = h.t if rules.reflect == "segment" else total
        raised[lane] |= seg.v == 0.0
        I = [div(a, seg) for a in I]
        # a path ends at a surface that does not reflect, or past the cut-off
        mm = _margin(total.v - max_dist, total.e)
        shiny = mat["shiny"]
        on = np.flatnonzero(shiny)
        out["maxdist"][lane[on]] = pmin(out["maxdist"][lane[on]], mm[on])
        going = np.zeros(len(lane), bool)
        going[on] = choose((b, "maxdist", 0), mm[on], lane[on], total.v[on] < max_dist)
        stop = np.flatnonzero(~going)
        out["I"][lane[stop]] = np.stack([a.v[stop] for a in I], -1)
        out["err"][lane[stop]] = np.stack([a.e[stop] for a in I], -1)
        on = np.flatnonzero(going)
        out["bounces"][lane[on]] += 1
        stack.append((lane[on], [a.at(on) for a in I], [a.at(on) for a in mat["specular"]]))
        Nn, dn, Hn = [x.at(on) for x in N], [x.at(on) for x in d], [x.at(on) for x in H]
        R, zero = unit3z(diff3(dn, scale3(mul(dot3(dn, Nn), exact(2.0)), Nn)))
        raised[lane[on]] |= zero
        lane, base, d, skip, total = lane[on], Hn, R, ids[on], total.at(on)
        b += 1
    # the sums from the last bounce back: I = local + specular · I
    for at, local, spec in reversed(stack):
        for i in range(3):
            got = add(local[i], mul(spec[i], V(out["I"][at, i], out["err"][at, i])))
            out["I"][at, i], out["err"][at, i] = got.v, got.e
    out["seen"] = [tuple(dict.fromkeys(s)) for s in seen]
    out["raised"] = raised
    return out


def _hand_over(scene, lane, base, d, skip, total, b, rules, max_dist, flips, limit, out,
               seen, raised):
    """The rest of the paths of ``lane`` from bounce ``b`` on, by the per-pixel code
    (shade_oracle.ray_trace from the lanes' state, as EF numbers of the same values): their
    intensity from there into ``out`` (the bounces before add theirs as ever), margins and
    bounces on from the arrays', near decisions noted."""
    from mitsuba_ref import shade_oracle
    for i, p in enumerate(lane.tolist()):
        px = shade_oracle._Pixel()
        for k in shade_oracle.MARGINS:
            setattr(px, k, float(out[k][p]))
        px.reach = float(out["reach"][p])
        alt = shade_oracle._Alt(flips[p] if flips else frozenset(), limit)
        ef = lambda x: EF(float(x.v[i]), float(x.e[i]))
        try:
            I = shade_oracle.ray_trace(scene, tuple(ef(x) for x in base),
                                       tuple(ef(x) for x in d), ef(total), int(skip[i]), rules,
                                       max_dist, px, alt, bounce=b)
        except (ValueError, ArithmeticError):
            raised[p] = True
            continue
        out["I"][p] = [x.v for x in I]
        out["err"][p] = [x.e for x in I]
        out["bounces"][p] += px.bounces
        out["reach"][p] = px.reach
        for k in shade_oracle.MARGINS:
            out[k][p] = getattr(px, k)
        seen[p] += alt.seen


def _flip_geo(gs, h, risk, base, d, rules, skip, lane, b, flipped, near_at, note, raised):
    """shade_oracle.ray_trace's closest hit with decisions taken the other way: the objects
    whose verdict is near and flipped are taken the other way, and the near verdicts of the
    hit that gives join them, up to four traces a lane; returns the hits."""
    nobj = gs.nobj
    want = np.zeros((len(lane), nobj), bool)
    for j in range(nobj):
        if (b, "geo", j) in flipped:
            want[:, j] = flipped[(b, "geo", j)][lane]
    cur = np.zeros_like(want)
    going = np.ones(len(lane), bool)
    for it in range(4):
        if it:          # (the choices made again over the risks so far: the keys noted)
            for j in range(nobj):
                note((b, "geo", j), np.where(going, risk[:, j], INF), lane)
        now = (risk < near_at) & want
        going &= (now != cur).any(1)
        at = np.flatnonzero(going)
        if not len(at):
            break
        cur[at] = now[at]
        h2 = trace(gs, [x.at(at) for x in base], [x.at(at) for x in d], rules, skip[at],
                   cur[at])
        raised[lane[at]] |= h2.raised
        risk[at] = np.fmin(risk[at], h2.risk)
        h = _put_hit(h, at, h2)
    return h


def _put_hit(h: _Hit, at, g: _Hit) -> _Hit:
    """``h`` with lanes ``at`` from ``g`` (the fields ray_trace reads)."""
    out = _Hit()
    out.hit, out.id = h.hit.copy(), h.id.copy()
    out.hit[at], out.id[at] = g.hit, g.id
    out.t = _put(h.t, at, g.t)
    out.position = [_put(a, at, x) for a, x in zip(h.position, g.position)]
    out.normal = [_put(a, at, x) for a, x in zip(h.normal, g.normal)]
    out.uv = [_put(a, at, x) for a, x in zip(h.uv, g.uv)]
    return out


def _put(a: V, idx, b: V) -> V:
    """``a`` with lanes ``idx`` replaced by ``b``'s values (a constant becomes an array)."""
    v, e = np.array(a.v, float, copy=True), np.array(a.e, float, copy=True)
    v[idx], e[idx] = b.v, b.e
    return V(v, e)


def _take(h: _Hit, keep) -> _Hit:
    g = _Hit()
    g.hit, g.id, g.t = h.hit[keep], h.id[keep], h.t.at(keep)
    g.position = [x.at(keep) for x in h.position]
    g.normal = [x.at(keep) for x in h.normal]
    g.uv = [x.at(keep) for x in h.uv]
    return g


def rays(scene, columns: int, rows: int, pixels, sampling: str, rules) -> tuple:
    """shade_oracle.pixel_ray of every pixel (image order, row 0 the top) on lanes."""
    with np.errstate(all="ignore"):
        return _rays(scene, columns, rows, pixels, sampling, rules)


def _rays(scene, columns: int, rows: int, pixels, sampling: str, rules) -> tuple:
    r, x = np.divmod(np.asarray(pixels, np.int64), max(columns, 1))
    y = rows - 1 - r + (1 if rules.rows == "shifted" else 0)
    ww, wh = inp(scene.window[0]), inp(scene.window[1])
    xs, ys = V(x.astype(float), 0.0), V(y.astype(float), 0.0)
    if sampling == "corners":
        wx = sub(mul(div(xs, exact(columns - 1)), ww), div(ww, exact(2.0)))
        wy = sub(mul(div(ys, exact(rows - 1)), wh), div(wh, exact(2.0)))
    else:
        wx = sub(mul(div(add(xs, exact(0.5)), exact(columns)), ww), div(ww, exact(2.0)))
        wy = sub(mul(div(add(ys, exact(0.5)), exact(rows)), wh), div(wh, exact(2.0)))
    base = tuple(inp(a) for a in scene.viewpoint)
    d, zero = unit3z(diff3((wx, wy, exact(0.0)), base))
    n = len(x)
    base = tuple(V(np.full(n, a.v), np.full(n, a.e)) for a in base)
    # where pixel_ray divides by zero (a direction of no length; one column or row with
    # corner sampling, or none), every component NaN: ``shade`` says 'raised' there
    bad = zero | (min(columns, rows) <= (1 if sampling == "corners" else 0))
    return base, tuple(V(np.where(bad, np.nan, a.v), np.where(bad, np.nan, a.e)) for a in d)


def colours(I: np.ndarray) -> list:
    """shade_oracle._colour of each row."""
    return [tuple(int(c) for c in q) for q in quantize(I)]


def paths(out: dict) -> list:
    """Each lane's (colour, near decisions, bounces), as shade_oracle's paths are, or None
    where the per-pixel code is to trace it (not ``usable``)."""
    ok = usable(out)
    cols = colours(np.where(ok[:, None], out["I"], 0.0))
    return [(col, seen, int(b)) if good else None
            for col, seen, b, good in zip(cols, out["seen"], out["bounces"], ok)]


def usable(out: dict) -> np.ndarray:
    """Lanes whose numbers the per-pixel oracle gives too: those where it does not raise
    (``shade``'s 'raised': a division by zero, a rounding of infinity) and, to be safe, whose
    intensity is not NaN (where the per-pixel oracle may give NaN too, only slower).  Bounds
    that overflow (a long mirror corridor's) and the margins they make are its own numbers:
    Python's min and max are followed where they meet a NaN."""
    return ~out["raised"] & ~np.isnan(out["I"]).any(-1)
