"""Stiff and extreme cases: generated scene families, each swept over one parameter, traced by
rt_core (f32, f64), Mitsuba (f32) and the notes' naive float32 formulation, and judged against
the exact oracle (``mitsuba_ref.exact``) on the very rays each tracer traced.

Families (``FAMILIES``; each case is a scene file text plus a camera or a list of rays):

  grazing      finite plane seen at incidence θ = 1e-6 .. 0.5 rad (ray bundle spread ∝ θ)
  distance     finite plane and sphere at distance D = 1 .. 1e7 from the viewpoint
  size         finite plane of size s·D (s = 1e-6 .. 1e6): small ones framed by a shrinking
               window, large ones with a corner in view and reaching s·D beyond
  window       world window 1e-6 .. 1e6 wide, objects framed in it
  offset       viewpoint X = 1 .. 1e7 off the window's centre, above one of its samples
  far_square   the issue's case: 2e-7·D square tilted 50°, D = 10 .. 1e4, window 1e-6
  orient       orient within α = 1e-8 .. 1e-2 rad of the normal
  normal       normals (and orients) of magnitude 1e-20 .. 1e20
  edges        rays exactly through edges, corners and a shared edge, and ±1 ulp around them
  viewpoint    a plane and a panel through the viewpoint (exactly, in the file's decimals)
  ties         coplanar and coincident panels, normals written differently, at distance D
  tangent      rays within δ = 1e-1 .. 1e-11 (relative) of a sphere's outline
  tiny_sphere  a sphere of radius r at distance D, D/r = 10 .. 1e9, 20° off axis
  straddle     panel and sphere straddling the window plane z = 0, panel at angle β to it
  parallel     rays exactly parallel to a plane through the viewpoint and to a panel, and rays
               tilted by 1e-30 .. 1e-5 toward them

Per tracer and case (``Metrics``): mask/id mismatches against the exact answer; those not
explained (no decision of the objects involved within K·u·S of its threshold, no tie within
the bounds: ``mitsuba_ref.exact``); relative depth error (max, median) where tracer and oracle
hit the same object, and its maximum over kappa_t·u (backward stability); non-finite
outputs; for rt_core the camera's ray angle error against the exact course ray of the
scene's float64 numbers (units of u); for f64, the depth check where the condition number
allows: rays with kappa_t·2^-52 <= 1e-12 must be within 1e-12.

The bar (``case_ok``): rt_core f32 no more unexplained mismatches than Mitsuba on the same
rays, rt_core f64 none and no depth error over 1e-12 where allowed, no NaN/Inf from rt_core.

Mitsuba traces rt_core's float32 rays with ``reference.trace_rays``: plane kinds from the
window plane z = 0 (the course's screen clip; with the viewpoint behind the window, from the
viewpoint up to it), spheres from the viewpoint.  Moving the origin along the ray costs one
float32 rounding of V + s·d, which the explanation bound covers (its |V_i| and t|d_i|
terms), so it does not distort any family.
"""
from __future__ import annotations

import dataclasses
import math
import random
import time
from dataclasses import asdict, dataclass, field
from decimal import Decimal
from fractions import Fraction

import numpy as np

from mitsuba_ref.exact import U, direction_error, parse_exact, trace_exact
from rt_core.accel import device_array
from rt_core.rules import Rules

TRACERS = ("rt_f32", "rt_f64", "mitsuba", "naive_f32")
F64_TARGET = 1e-12          # f64 depth: relative error bound where kappa_t·eps64 <= this
EPS64 = 2.0 ** -52
MAT = "1 1 1  2 2 2  0 0 0"
SIZES = {"quick": (24, 18), "test": (32, 24), "full": (64, 48)}


# --- scene text ----------------------------------------------------------------------------------

def num(x) -> str:
    """A number as written in the file: a float as its shortest round-trip decimal, a
    Fraction/Decimal exactly (it must have a finite decimal expansion)."""
    if isinstance(x, (Fraction, Decimal)):
        if isinstance(x, Fraction):
            d = Decimal(x.numerator) / Decimal(x.denominator)
            if Fraction(d) != x:
                raise ValueError(f"{x} has no short exact decimal")
            x = d
        s = format(x, "f") if abs(x.adjusted()) < 20 else format(x, "E")
        return s
    return repr(float(x))


def exact_num(x: float) -> str:
    """A float written with its exact (terminating) decimal expansion."""
    return num(Decimal(float(x)))


def vec(v, fmt=num) -> str:
    return " ".join(fmt(c) for c in v)


def fplane(normal, point, orient, size, fmt=num) -> str:
    return (f"fplane\n{MAT}\n{vec(normal, fmt)}\n{vec(point, fmt)}\n{vec(orient, fmt)}\n"
            f"{vec(size, fmt)}\n")


def plane(normal, point, fmt=num) -> str:
    return f"plane\n{MAT}\n{vec(normal, fmt)}\n{vec(point, fmt)}\n"


def sphere(center, radius, fmt=num) -> str:
    return f"sphere\n{MAT}\n{vec(center, fmt)}\n{fmt(radius)}\n"


def scene_text(window, viewpoint, objects, comment="", fmt=num) -> str:
    head = "".join(f"# {line}\n" for line in comment.splitlines())
    return head + f"{vec(window, fmt)}\n{vec(viewpoint, fmt)}\n" + "".join(objects)


# --- float64 geometry helpers for the generators -------------------------------------------------

def _unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def _perp(n, rng):
    """A random unit vector perpendicular to n."""
    while True:
        m = np.cross(n, _unit([rng.gauss(0, 1) for _ in range(3)]))
        if np.linalg.norm(m) > 0.1:
            return _unit(m)


def _rotate_toward(n, m, angle):
    return _unit(np.cos(angle) * np.asarray(n) + np.sin(angle) * np.asarray(m))


def _panel(center, normal, orient, w, h):
    """(normal, corner point, orient, size) of a w×h panel centred on ``center``."""
    n = _unit(normal)
    x = _unit(np.asarray(orient) - np.dot(orient, n) * n)
    y = np.cross(n, x)
    p = np.asarray(center) - 0.5 * w * x - 0.5 * h * y
    return n, p, x, (w, h)


def _window_ray(rng, vp, window, spread=0.6):
    """Unit direction from vp through a random point of the central ``spread`` of the window."""
    ww, wh = window
    w = np.array([rng.uniform(-spread, spread) * ww / 2, rng.uniform(-spread, spread) * wh / 2,
                  0.0])
    return _unit(w - np.asarray(vp))


def _facing(rng, d, max_tilt):
    """A normal facing back along d, tilted by up to max_tilt."""
    return _rotate_toward(-np.asarray(d), _perp(d, rng), rng.uniform(0, max_tilt))


# --- cases ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One scene of a family at one parameter value, and the rays to trace: a camera
    (``columns`` × ``rows``, corner sampling) or ``rays`` (float64 directions; the float32
    tracers trace them rounded to float32)."""
    family: str
    param: float
    text: str
    columns: int = 0
    rows: int = 0
    rays: tuple | None = None
    seed: int = 0

    @property
    def label(self) -> str:
        return f"{self.family}[{self.param:g}]" + (f"#{self.seed}" if self.seed else "")


def grazing(theta, rng, size):
    W, H = size
    vp = (0.0, 0.0, 1.0)
    ww = theta                                   # bundle spread ≈ θ: incidence θ/2 .. 3θ/2
    d0 = np.array([0.0, 0.0, -1.0])
    phi = rng.uniform(0, 2 * math.pi)
    side = np.array([math.cos(phi), math.sin(phi), 0.0])
    n = _rotate_toward(side, -d0, theta)         # n·(−d0) = sin θ
    c = np.asarray(vp) + 11.0 * d0
    along = _unit(d0 - np.dot(d0, n) * n)        # in-plane, along the rays
    across = np.cross(n, along)
    w = 0.6 * 11.0 * ww
    h = 0.6 * 11.0 * ww / max(math.sin(theta), 1e-300) * 0.5
    c = c + rng.uniform(-0.1, 0.1) * w * across + rng.uniform(-0.1, 0.1) * h * along
    obj = _panel(c, n, across, w, min(h, 1e3))
    text = scene_text((ww, 0.75 * ww), vp, [fplane(*obj)], f"grazing incidence {theta:g} rad")
    return Case("grazing", theta, text, W, H)


def distance(D, rng, size):
    W, H = size
    vp = (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1.0)
    win = (1.0, 0.75)
    d1 = _window_ray(rng, vp, win, 0.4)
    d2 = _window_ray(rng, vp, win, 0.4)
    obj = _panel(np.asarray(vp) + D * d1, _facing(rng, d1, 1.0), _perp(d1, rng),
                 0.3 * D, 0.25 * D)
    sph = sphere(np.asarray(vp) + 1.3 * D * d2, 0.12 * D)
    text = scene_text(win, vp, [fplane(*obj), sph], f"panel and sphere at distance {D:g}")
    return Case("distance", D, text, W, H)


def size_family(s, rng, size):
    """A panel of size s·D at distance D = 10.  Small panels (s < 1): the window shrinks to
    frame it; large ones: a fixed window, the panel's corner near the view's centre and the
    panel reaching s·D beyond it."""
    W, H = size
    D = 10.0
    vp = (0.0, 0.0, 1.0)
    ww = 2.0 * s if s < 1 else 2.0
    d0 = _unit([rng.uniform(-0.2, 0.2) * ww, rng.uniform(-0.2, 0.2) * ww, -1.0])
    c = np.asarray(vp) + D * d0
    n = _facing(rng, d0, 0.8)
    w, h = s * D, 0.7 * s * D
    if s >= 1:
        x = _unit(_perp(d0, rng))
        x = _unit(x - np.dot(x, n) * n)
        y = np.cross(n, x)
        c = c - 0.3 * D * (x + y) + 0.5 * w * x + 0.5 * h * y
        obj = _panel(c, n, x, w, h)
    else:
        obj = _panel(c, n, _perp(d0, rng), w, h)
    text = scene_text((ww, 0.75 * ww), vp, [fplane(*obj)], f"panel of size {s:g} x distance")
    return Case("size", s, text, W, H)


def window_family(ww, rng, size):
    W, H = size
    vp = (rng.uniform(-0.2, 0.2) * ww, rng.uniform(-0.2, 0.2) * ww, 1.0)
    win = (ww, 0.75 * ww)
    d1 = _window_ray(rng, vp, win, 0.5)
    d2 = _window_ray(rng, vp, win, 0.5)
    ang = min(ww, 2.0)                       # angular size of the view, roughly
    obj = _panel(np.asarray(vp) + 5 * d1, _facing(rng, d1, 0.7), _perp(d1, rng),
                 2.0 * ang, 1.5 * ang)
    sph = sphere(np.asarray(vp) + 7 * d2, 0.6 * ang)
    text = scene_text(win, vp, [fplane(*obj), sph], f"window {ww:g} wide")
    return Case("window", ww, text, W, H)


def offset(X, rng, size):
    """The viewpoint's foot on z = 0 lies on a sample of a window X wide: that pixel looks
    straight down; its direction must survive the camera's x·sx + ox − vx in float32."""
    W, H = size
    ww, wh = float(X), 0.75 * X
    i, j = W // 3, H // 3
    fx = i / (W - 1) * ww - ww / 2
    fy = j / (H - 1) * wh - wh / 2
    vp = (fx, fy, 2.0)
    c = np.array([fx, fy, -1.0])
    obj = _panel(c, _facing(rng, [0, 0, -1], 0.5), _perp([0, 0, -1], rng), 1.5, 1.2)
    text = scene_text((ww, wh), vp, [fplane(*obj)], f"viewpoint offset {X:g} over the window")
    return Case("offset", X, text, W, H)


def far_square(D, rng, size):
    """A square of side 2e-7·D, tilted 50°, D away straight ahead, through a 1e-6 window at
    distance 3: at D = 1e4 the issue's 2 mm square 10 km away through a micrometre window."""
    W, H = size
    vp = (0.0, 0.0, 3.0)
    side = 2e-7 * D
    d0 = np.array([0.0, 0.0, -1.0])
    n = _rotate_toward(-d0, _perp(d0, rng), math.radians(50))
    c = np.asarray(vp) + (D + 3) * d0 + side * np.array([rng.uniform(-.1, .1),
                                                         rng.uniform(-.1, .1), 0])
    obj = _panel(c, n, _perp(n, rng), side, side)
    text = scene_text((1e-6, 0.75e-6), vp, [fplane(*obj)],
                      f"square of side {side:g} tilted 50 deg, {D:g} away, 1e-6 window")
    return Case("far_square", D, text, W, H)


def orient_family(alpha, rng, size):
    W, H = size
    vp = (0.0, 0.0, 2.0)
    win = (2.0, 1.5)
    objs = []
    for k in range(2):
        d1 = _window_ray(rng, vp, win, 0.5)
        n = _facing(rng, d1, 0.8)
        o = _rotate_toward(n, _perp(n, rng), alpha) * rng.uniform(0.5, 3)
        nn, p, _, sz = _panel(np.asarray(vp) + (5 + 3 * k) * d1, n, o, 2.5, 2.0)
        objs.append(fplane(nn, p, o, sz))
    text = scene_text(win, vp, objs, f"orient within {alpha:g} rad of the normal")
    return Case("orient", alpha, text, W, H)


def normal_family(m, rng, size):
    W, H = size
    vp = (0.0, 0.0, 2.0)
    win = (2.0, 1.5)
    objs = []
    for k in range(2):
        d1 = _window_ray(rng, vp, win, 0.5)
        n = _facing(rng, d1, 1.0)
        nn, p, x, sz = _panel(np.asarray(vp) + (5 + 3 * k) * d1, n, _perp(n, rng), 2.5, 2.0)
        objs.append(fplane(nn * m, p, x * m * rng.uniform(0.3, 3), sz))
    d3 = _window_ray(rng, vp, win, 0.2)
    objs.append(plane(_facing(rng, d3, 0.8) * m, np.asarray(vp) + 20 * d3))
    text = scene_text(win, vp, objs, f"normals of magnitude {m:g}")
    return Case("normal", m, text, W, H)


def edges(k, rng, size):
    """Dyadic panels (scale 2^k): an axis-aligned one, a tilted one (normal 0 3 4) and two
    sharing an edge; rays exactly through corners and edge points, and ±1 float32 ulp."""
    s = 2.0 ** k
    vp = np.array([0.25, 0.125, 2.0]) * s
    panels = [((0, 0, 1), np.array([-3.0, -2.0, -6.0]) * s, (1, 0, 0), (2.0 * s, 1.5 * s)),
              ((0, 3, 4), np.array([0.5, -2.5, -7.0]) * s, (1, 0, 0), (2.0 * s, 2.5 * s)),
              ((0, 0, 1), np.array([-3.0, 1.0, -5.0]) * s, (1, 0, 0), (1.5 * s, 1.0 * s)),
              ((0, 0, 1), np.array([-1.5, 1.0, -5.0]) * s, (1, 0, 0), (1.0 * s, 1.0 * s))]
    objs = [fplane(*p, fmt=exact_num) for p in panels]
    targets = []
    fracs = (0.0, 0.25, 0.5, 0.75, 1.0)
    for n, p, o, (w, h) in panels:
        x = np.asarray(o, float)
        y = np.array([0.0, 1.0, 0.0]) if n == (0, 0, 1) else np.array([0.0, 0.8, -0.6])
        for a in fracs:
            for b in fracs:
                if a in (0.0, 1.0) or b in (0.0, 1.0):
                    targets.append(p + a * w * x + b * h * y)
    rays = []
    for tgt in targets:
        d = (np.asarray(tgt) - vp).astype(np.float32)
        assert np.array_equal(d.astype(np.float64), np.asarray(tgt) - vp), "not exact"
        rays.append(tuple(map(float, d)))
        for i in range(3):
            for direction in (np.inf, -np.inf):
                e = d.copy()
                e[i] = np.nextafter(e[i], np.float32(direction))
                rays.append(tuple(map(float, e)))
    rng.shuffle(rays)
    text = scene_text((8 * s, 6 * s), vp, objs, f"dyadic panels at scale 2^{k}", fmt=exact_num)
    return Case("edges", s, text, rays=tuple(rays))


def _decimal(x: float, digits: int = 4) -> Fraction:
    """x rounded to ``digits`` significant decimal digits, exactly."""
    if x == 0:
        return Fraction(0)
    return Fraction(Decimal(f"{x:.{digits - 1}e}"))


def _decimal_vec(rng, scale, digits=4):
    return tuple(_decimal(rng.uniform(-1, 1) * scale, digits) for _ in range(3))


def viewpoint_family(scale, rng, size):
    """A plane and a panel that contain the viewpoint exactly (in the file's decimals): every
    ray meets them at t = 0, a miss.  The viewpoint is behind the window (z < 0, rays toward
    +z), so the hit at the viewpoint is not screen-clipped; a wall between it and the window.
    Normals are random decimals, so the unit normal rounds."""
    W, H = size
    vp = (_decimal(rng.uniform(-1, 1) * scale), _decimal(rng.uniform(-1, 1) * scale),
          -_decimal(rng.uniform(2, 3) * max(scale, 1) ** 0.5))
    objs = []
    for kind in ("plane", "fplane"):
        n = _decimal_vec(rng, 1.0, 3)
        m = _decimal_vec(rng, 1.0, 2)
        e1 = _xcross(n, m)                       # ⊥ n, exact decimals
        if kind == "plane":
            objs.append(plane(n, tuple(v + Fraction(3, 2) * e for v, e in zip(vp, e1))))
        else:
            # corner a quarter of e1 and of n × e1 away: the viewpoint lies inside the panel
            e2 = _xcross(n, e1)
            p = tuple(v - (a + b) / 4 for v, a, b in zip(vp, e1, e2))
            side = 2 * max(_norm(e1), _norm(e2), Fraction(1))
            objs.append(fplane(n, p, e1, (side, side)))
    vz = float(vp[2])
    wall = _panel((float(vp[0]) * 0.5, float(vp[1]) * 0.5, 0.4 * vz), (0.1, -0.2, -1), (1, 0, 0),
                  8 * abs(vz) + 4 * scale, 6 * abs(vz) + 4 * scale)
    objs.append(fplane(*wall))
    text = scene_text((2.0, 1.5), vp, objs,
                      f"plane and panel through the viewpoint, |V| ~ {scale:g}, V behind window")
    return Case("viewpoint", scale, text, W, H)


def _xcross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _norm(v) -> Fraction:
    """A decimal upper bound of |v| (2 significant digits)."""
    return _decimal(1.01 * math.sqrt(sum(float(c) ** 2 for c in v)), 2)


def ties(D, rng, size):
    """Coplanar panels (same plane, different corners and orients) and coincident ones
    (identical numbers; the normal also written scaled and negated): exact ties in the file's
    decimals, broken by file order."""
    W, H = size
    vp = (Fraction(0), Fraction(0), Fraction(1))
    n = (Fraction(1), Fraction(2), Fraction(11))
    p0 = (Fraction(0), Fraction(0), -_decimal(D, 3))
    a = (Fraction(2), Fraction(-1), Fraction(0))             # ⊥ n
    b = (Fraction(11), Fraction(0), Fraction(-1))            # ⊥ n
    L = _decimal(0.3 * D, 2)
    pts = [tuple(p - L * x / 2 - L * y / 10 for p, x, y in zip(p0, a, b)),
           tuple(p - L * x / 4 - L * y / 20 for p, x, y in zip(p0, a, b)),
           tuple(p - L * x / 2 - L * y / 10 for p, x, y in zip(p0, a, b))]
    sizes = [(L * 2, L), (L, L * Fraction(3, 2)), (L * 2, L)]
    normals = [n, tuple(3 * c for c in n), tuple(-c for c in n)]
    orients = [a, (Fraction(1), Fraction(1), Fraction(0)), a]
    objs = [fplane(nn, p, o, s) for nn, p, o, s in zip(normals, pts, orients, sizes)]
    win = (Fraction(1), Fraction(3, 4))
    text = scene_text(win, vp, objs, f"coplanar and coincident panels at distance {D:g}")
    return Case("ties", D, text, W, H)


def tangent(delta, rng, size):
    """Rays whose distance from a sphere's centre is r·(1 ± δ·[0, 1]): tangent within δ."""
    vp = np.array([0.1, -0.2, 1.0])
    C = np.array([0.4, 0.3, -10.0])
    r = 1.5
    q = C - vp
    rays = []
    for _ in range(size[0] * size[1]):
        e = _perp(_unit(q), rng)
        bimp = r * (1 + delta * rng.uniform(-1, 1))
        # direction from vp passing at distance bimp from C, on the side e
        L = np.linalg.norm(q)
        ang = math.asin(min(bimp / L, 1.0))
        d = _unit(math.cos(ang) * _unit(q) - math.sin(ang) * e)
        rays.append(tuple(d))
    text = scene_text((2.0, 1.5), vp, [sphere(C, r)], f"rays within {delta:g} of tangent")
    return Case("tangent", delta, text, rays=tuple(rays))


def tiny_sphere(ratio, rng, size):
    """A sphere of radius 1e-3 at distance D = ratio·r, about 20° off the z axis (so no ray
    direction component is exactly ±1), framed by a window 6r/D wide."""
    W, H = size
    r = 1e-3
    D = ratio * r
    off = (rng.uniform(0.3, 0.4), rng.uniform(-0.2, 0.2))
    vp = (-off[0], -off[1], 1.0)                 # the ray through the window centre
    axis = _unit([off[0], off[1], -1.0])
    ww = 6 * r / D
    c = np.asarray(vp) + D * axis + D * ww * np.array([rng.uniform(-.1, .1),
                                                       rng.uniform(-.1, .1), 0])
    text = scene_text((ww, 0.75 * ww), vp, [sphere(c, r)],
                      f"sphere of radius {r:g} at distance {D:g}, 20 deg off axis")
    return Case("tiny_sphere", ratio, text, W, H)


def parallel(tilt, rng, size):
    """Rays parallel to planes: the viewpoint is behind the window (z = −1) and half the rays
    are exactly horizontal (d.z = 0): parallel to a plane through the viewpoint (n·d = 0 and
    n·q = 0: t = 0/0) and to a panel just below it (t = x/0); the other half are tilted by
    ±tilt toward them.  A wall to the side catches every ray."""
    vp = (Fraction(1, 4), Fraction(-1, 8), Fraction(-1))
    objs = [plane((0, 0, 1), (Fraction(3), Fraction(-2), Fraction(-1))),
            fplane((0, 0, -1), (Fraction(-4), Fraction(-4), Fraction(-1001, 1000)), (1, 0, 0),
                   (Fraction(8), Fraction(8))),
            plane((-1, 0, 0), (Fraction(6), Fraction(0), Fraction(0)))]
    rays = []
    for i in range(size[0] * size[1]):
        phi = rng.uniform(-1.2, 1.2)
        dz = 0.0 if i % 2 == 0 else rng.choice((-1.0, 1.0)) * tilt
        d = np.array([math.cos(phi), math.sin(phi), dz], np.float32)
        rays.append(tuple(map(float, d)))
    text = scene_text((2, 1.5), vp, objs, f"rays parallel to planes, tilt {tilt:g}")
    return Case("parallel", tilt, text, rays=tuple(rays))


def straddle(beta, rng, size):
    W, H = size
    vp = (0.1, 0.2, 3.0)
    phi = rng.uniform(0, 2 * math.pi)
    axis = np.array([math.cos(phi), math.sin(phi), 0.0])
    n = _rotate_toward([0, 0, 1], np.cross(axis, [0, 0, 1]), beta)
    obj = _panel((rng.uniform(-.3, .3), rng.uniform(-.3, .3), 0.0), n, axis, 3.0, 2.5)
    sph = sphere((-0.8, -0.5, 0.02), 0.5)
    text = scene_text((4.0, 3.0), vp, [fplane(*obj), sph],
                      f"panel at {beta:g} rad to the window plane, through it; sphere through it")
    return Case("straddle", beta, text, W, H)


FAMILIES = {
    "grazing": (grazing, [1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 0.5]),
    "distance": (distance, [1, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7]),
    "size": (size_family, [1e-6, 1e-4, 1e-2, 1, 1e2, 1e4, 1e6]),
    "window": (window_family, [1e-6, 1e-4, 1e-2, 1, 1e2, 1e4, 1e6]),
    "offset": (offset, [1, 1e2, 1e4, 1e6, 1e7]),
    "far_square": (far_square, [1e1, 1e2, 1e3, 1e4]),
    "orient": (orient_family, [1e-8, 1e-6, 1e-4, 1e-2]),
    "normal": (normal_family, [1e-20, 1e-10, 1, 1e10, 1e20]),
    "edges": (edges, [2.0 ** -40, 2.0 ** -20, 1, 2.0 ** 20, 2.0 ** 40]),
    "viewpoint": (viewpoint_family, [1, 1e2, 1e4, 1e6]),
    "ties": (ties, [1, 1e2, 1e4, 1e6]),
    "tangent": (tangent, [1e-1, 1e-3, 1e-5, 1e-7, 1e-9, 1e-11]),
    "tiny_sphere": (tiny_sphere, [1e1, 1e3, 1e5, 1e7, 1e9]),
    "straddle": (straddle, [1e-6, 1e-4, 1e-2, 0.3, 1.2]),
    "parallel": (parallel, [1e-30, 1e-20, 1e-10, 1e-5]),
}


# what each family sweeps: the x axis of its plot and the parameter column of the table
AXIS = {
    "grazing": "incidence angle θ (rad)",
    "distance": "distance of the panels D",
    "size": "panel size s (× distance)",
    "window": "window width",
    "offset": "window width X (viewpoint on a sample)",
    "far_square": "distance D (square side 2e-7·D)",
    "orient": "orient's angle to the normal (rad)",
    "normal": "normal's magnitude",
    "edges": "scale 2^k of the dyadic panels",
    "viewpoint": "scale of the scene through the viewpoint",
    "ties": "distance D of the coplanar panels",
    "tangent": "tangency δ (ray distance r·(1 ± δ))",
    "tiny_sphere": "distance / radius",
    "straddle": "panel's angle to the window plane (rad)",
    "parallel": "tilt of the near-parallel rays",
}


def quick_params(values):
    """First, middle and last parameter value."""
    return sorted({values[0], values[len(values) // 2], values[-1]}, key=values.index)


def make_case(family: str, param: float, size=SIZES["test"], seed: int = 0) -> Case:
    gen, values = FAMILIES[family]
    rng = random.Random(f"{family}/{param!r}/{seed}")
    case = gen(round(math.log2(param)) if family == "edges" else param, rng, size)
    return dataclasses.replace(case, seed=seed)


def case_specs(mode: str = "test", families=None, seeds=(0,)) -> list:
    """(family, param, size, seed) of every case of a run, in report order: ``mode`` 'quick'
    (first, middle and last parameter, 24×18 rays), 'test' (every parameter, 32×24) or
    'full' (every parameter, 64×48).  Small: a sweep of 100,000 cases is sent to Dask
    workers as these, and each worker generates its cases (``run_spec``)."""
    size = SIZES[mode]
    out = []
    for seed in ([seeds] if isinstance(seeds, int) else seeds):
        for fam in families or FAMILIES:
            values = FAMILIES[fam][1]
            for p in (quick_params(values) if mode == "quick" else values):
                out.append((fam, p, size, seed))
    return out


def cases(mode: str = "test", families=None, seeds=(0,)):
    """Every case of a run (``case_specs``), generated."""
    for spec in case_specs(mode, families, seeds):
        yield make_case(*spec)


# --- tracers -------------------------------------------------------------------------------------

def _np3(v, dtype):
    return np.stack([np.asarray(c.numpy(), dtype) for c in (v.x, v.y, v.z)], 1)


def trace_rt(scene, case: Case, precision: str, rules: Rules = Rules()):
    """rt_core on the case's rays: (d as traced (N,3), t, id, nonfinite count)."""
    import drjit as dr
    from rt_core import backend
    from rt_core.camera import make_camera, primary_directions
    from rt_core.tracer import closest_hit, position, prepare, surface
    T = backend.types(precision)
    dt = np.float32 if precision == "f32" else np.float64
    ks = prepare(scene, T)
    if case.rays is None:
        d = primary_directions(scene, make_camera(scene, case.columns, case.rows), T)
        dmax = 1.0
    else:
        a = np.asarray(case.rays, dt)
        d = T.Array3(*(device_array(T.Float, a[:, i]) for i in range(3)))
        dmax = float(np.linalg.norm(a.astype(np.float64), axis=1).max())
    # float64 decides exactly on the rays as traced, which is what the exact oracle judges
    t, oid, hit = closest_hit(ks, d, None, rules, cam="rays", dmax=dmax)
    normal, u, v = surface(ks, d, t, oid, hit)
    pos = position(ks, d, t, hit)
    dr.eval(d, t, oid, hit, normal, u, v, pos)
    outs = [t.numpy(), u.numpy(), v.numpy()] + [_np3(x, dt) for x in (normal, pos, d)]
    nonfinite = sum(int(np.count_nonzero(~np.isfinite(np.asarray(a)))) for a in outs)
    return _np3(d, dt), np.asarray(t.numpy(), np.float64), \
        np.asarray(oid.numpy(), np.int64), nonfinite


def trace_mitsuba(scene, d32: np.ndarray, columns: int, rows: int):
    """Mitsuba 3 (llvm_ad_rgb, float32) on the same float32 rays: (t, id, nonfinite)."""
    from mitsuba_ref.reference import MitsubaScene, trace_rays
    ms = MitsubaScene(scene, max(columns, 2), max(rows, 2))
    ref = trace_rays(ms, d32, full=False)
    hit = ref["hit.mask"] > 0
    t = np.asarray(ref["depth.Z"], np.float64)
    ids = np.where(hit, ref["object.id"], -1).astype(np.int64)
    nonfinite = int(sum(np.count_nonzero(~np.isfinite(np.asarray(v, np.float64)))
                        for v in ref.values()))
    return np.where(hit, t, 0.0), ids, nonfinite


def naive_f32(scene, d32: np.ndarray, rules: Rules = Rules()):
    """REFERENCE ONLY — the notes' formulation, literally, in float32 (what a student's float
    port computes): t = (n·point − n·base)/(n·d), hit = base + t·d, and for a finite plane
    newhit = rotmat·(hit − point) tested against [0, w] × [0, h]; spheres by the textbook
    quadratic (−b − √(b² − 4ac))/2a.  Returns (t, id, nonfinite)."""
    f = np.float32
    d = np.asarray(d32, f)
    V = np.asarray(scene.viewpoint, f)
    n_rays = len(d)
    best_t = np.full(n_rays, np.inf, f)
    best_id = np.full(n_rays, -1, np.int64)
    nonfinite = 0
    with np.errstate(all="ignore"):
        for i, o in enumerate(scene.objects):
            if o.kind == "sphere":
                C = np.asarray(o.center, f)
                oc = V - C
                a = np.sum(d * d, 1, dtype=f)
                b = f(2) * (d @ oc)
                c = np.dot(oc, oc) - f(o.radius) * f(o.radius)
                disc = b * b - f(4) * a * c
                t = (-b - np.sqrt(np.maximum(disc, f(0)))) / (f(2) * a)
                ok = (disc > 0) & (t > 0)
            else:
                n = np.asarray(o.normal, f)
                P = np.asarray(o.point, f)
                den = d @ n
                t = (np.dot(n, P) - np.dot(n, V)) / den
                hitp = V[None, :] + t[:, None] * d
                ok = (den != 0) & (t > f(rules.t_min)) & np.isfinite(t)
                if rules.screen_clip == ">":
                    ok &= ~(hitp[:, 2] > 0)
                elif rules.screen_clip == ">=":
                    ok &= ~(hitp[:, 2] >= 0)
                if o.kind == "fplane":
                    R = np.asarray(o.rotmat, f)
                    newhit = (hitp - P[None, :]) @ R.T
                    w, h = f(o.size[0]), f(o.size[1])
                    ok &= (newhit[:, 0] >= 0) & (newhit[:, 0] <= w) & \
                          (newhit[:, 1] >= 0) & (newhit[:, 1] <= h)
            better = ok & (t < best_t)
            best_t = np.where(better, t, best_t)
            best_id = np.where(better, i, best_id)
    hit = best_id >= 0
    nonfinite += int(np.count_nonzero(~np.isfinite(best_t[hit])))
    return np.where(hit, best_t, 0).astype(np.float64), best_id, nonfinite


# --- one case ------------------------------------------------------------------------------------

@dataclass
class Metrics:
    rays: int
    exact_hits: int
    mismatch: int                # hit mask or object id differs from the exact answer
    unexplained: int             # ... and no decision involved is within K·u·S of flipping
    nonfinite: int
    depth_max: float             # relative, where tracer and oracle hit the same object
    depth_median: float
    depth_n: int                 # rays where tracer and oracle hit the same object
    missed_hits: int             # exact hits the tracer misses (any reason)
    cam_err_u: float = float("nan")     # camera ray angle error / u (rt_core, camera cases)
    cond_ratio: float = 0.0      # max depth error / (kappa_t·u): <= ~1 is backward stable
    cond_ok: int = 0             # f64: rays with kappa_t·eps64 <= 1e-12
    over_target: int = 0         # f64: of those, rays whose depth error exceeds 1e-12
    unexplained_rays: list = field(default_factory=list)   # a few, for evidence


@dataclass
class CaseResult:
    family: str
    param: float
    label: str
    metrics: dict                # tracer -> Metrics
    seconds: float
    seed: int = 0

    def to_json(self) -> dict:
        return {"family": self.family, "param": self.param, "seed": self.seed,
                "label": self.label, "seconds": round(self.seconds, 3),
                "tracers": {k: asdict(m) for k, m in self.metrics.items()}}


def _metrics(ex, t, ids, nonfinite, u, f64: bool = False) -> Metrics:
    ids = np.asarray(ids, np.int64)
    mism = ids != ex.id
    expl = ex.explained(ids, u)
    same = (ids == ex.id) & ex.hit
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(t[same] - ex.t[same]) / np.abs(ex.t[same])
    rel = np.nan_to_num(rel, nan=np.inf)
    m = Metrics(len(ids), int(ex.hit.sum()), int(mism.sum()), int((~expl).sum()), nonfinite,
                float(rel.max()) if len(rel) else 0.0,
                float(np.median(rel)) if len(rel) else 0.0, len(rel),
                int(np.count_nonzero(ex.hit & (ids < 0))))
    if len(rel):
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.nan_to_num(rel / (ex.kappa_t[same] * u), nan=0.0)
        m.cond_ratio = float(ratio.max())
    if f64:
        good = ex.kappa_t[same] * EPS64 <= F64_TARGET
        m.cond_ok = int(good.sum())
        m.over_target = int(np.count_nonzero(rel[good] > F64_TARGET))
    bad = np.nonzero(~expl)[0][:5]
    m.unexplained_rays = [{"ray": [float(c) for c in ex.d[i]], "exact_id": int(ex.id[i]),
                           "tracer_id": int(ids[i])} for i in bad]
    return m


def run_case(case: Case, tracers=TRACERS, rules: Rules = Rules()) -> CaseResult:
    from rt_core.parser import parse_text
    t0 = time.perf_counter()
    scene = parse_text(case.text, f"<{case.label}>")
    xs = parse_exact(case.text)
    out = {}
    d32, t32, id32, nf32 = trace_rt(scene, case, "f32", rules)
    ex32 = trace_exact(xs, d32, rules)
    if "rt_f32" in tracers:
        out["rt_f32"] = _metrics(ex32, t32, id32, nf32, U["f32"])
    if "rt_f64" in tracers:
        d64, t64, id64, nf64 = trace_rt(scene, case, "f64", rules)
        ex64 = trace_exact(xs, d64, rules)
        out["rt_f64"] = _metrics(ex64, t64, id64, nf64, U["f64"], f64=True)
        if case.rays is None:
            out["rt_f64"].cam_err_u = float(direction_error(
                scene.window, scene.viewpoint, case.columns, case.rows, d64).max() / U["f64"])
    if case.rays is None and "rt_f32" in out:
        out["rt_f32"].cam_err_u = float(direction_error(
            scene.window, scene.viewpoint, case.columns, case.rows, d32).max() / U["f32"])
    if "mitsuba" in tracers:
        tm, im, nfm = trace_mitsuba(scene, d32.astype(np.float32), case.columns, case.rows)
        out["mitsuba"] = _metrics(ex32, tm, im, nfm, U["f32"])
    if "naive_f32" in tracers:
        tn, idn, nfn = naive_f32(scene, d32.astype(np.float32), rules)
        out["naive_f32"] = _metrics(ex32, tn, idn, nfn, U["f32"])
    return CaseResult(case.family, case.param, case.label, out, time.perf_counter() - t0,
                      case.seed)


def run_spec(spec) -> CaseResult:
    """run_case on the case of a (family, param, size, seed) spec."""
    return run_case(make_case(*spec))


# rough serial seconds of one case, per mode (measured on 2 cores: the full sweep's 80
# cases take 44 s of case time): whether a run is worth a local cluster (parallel.Plan)
SECONDS_PER_CASE = {"quick": 0.2, "test": 0.3, "full": 0.6}
# cores a serial run keeps busy (the full sweep on 2 cores: 67 CPU s over 63 s): its small
# cases leave a core idle, which a second worker uses (parallel.Plan.resolve; measured on 2
# cores only)
SERIAL_BUSY_CORES = 1.06


def run_suite(mode: str = "test", families=None, seeds=(0,), progress=None, plan=None):
    """run_case over ``cases(mode, families, seeds)``, where ``plan`` says (default in this
    process; tools/harness/parallel.py); the results in the cases' order, ``progress(result)``
    as each completes."""
    from tools.harness.parallel import SERIAL, run_cases

    def each(i, res):
        if progress:
            progress(res)
        return res
    return run_cases(run_spec, case_specs(mode, families, seeds), plan or SERIAL, each,
                     seconds_per_case=SECONDS_PER_CASE[mode], busy_cores=SERIAL_BUSY_CORES)


# --- report --------------------------------------------------------------------------------------

TABLE_COLUMNS = (
    ("rays", "rays traced"),
    ("exact hits", "rays the exact oracle sees hit"),
    ("mismatch", "hit/miss or object differs from the exact oracle"),
    ("unexplained", "... and no error bound straddles the decision"),
    ("non-finite", "NaN or inf in the tracer's output"),
    ("depth err max", "max relative depth error where both hit the same object"),
    ("depth err median", "its median"),
    ("err / bound", "max depth error over its condition-number bound (k·u)"),
    ("camera err / u", "rt_core's ray directions against the exact rays, in units of u"),
    ("f64 within 1e-12", "rt_core f64 cases within 1e-12 where the condition allows / over"),
)


def table(results) -> str:
    """A plain-text table, one block per family: a row per parameter value and tracer, with
    the parameter named (AXIS) and a legend of the columns at the end."""
    head = (f"  {'value':>10s} {'tracer':10s} {'rays':>5s} {'exact hits':>10s} "
            f"{'mismatch':>8s} {'unexplained':>11s} {'non-finite':>10s} {'depth err max':>13s} "
            f"{'median':>9s} {'err / bound':>11s} {'camera err / u':>14s} "
            f"{'f64 within 1e-12':>16s}")
    lines, family = [], None
    for r in results:
        if r.family != family:
            family = r.family
            lines += ([""] if lines else []) + [f"{family}: {AXIS.get(family, 'parameter')}",
                                                head]
        for name, m in r.metrics.items():
            f64 = f"{m.cond_ok} / {m.over_target}" if name == "rt_f64" else ""
            cam = f"{m.cam_err_u:14.3g}" if math.isfinite(m.cam_err_u) else f"{'':14s}"
            lines.append(f"  {r.param:10.3g} {name:10s} {m.rays:5d} {m.exact_hits:10d} "
                         f"{m.mismatch:8d} {m.unexplained:11d} {m.nonfinite:10d} "
                         f"{m.depth_max:13.3g} {m.depth_median:9.3g} {m.cond_ratio:11.3g} "
                         f"{cam} {f64:>16s}")
    lines += ["", "columns: " + "; ".join(f"{k}: {v}" for k, v in TABLE_COLUMNS)]
    return "\n".join(lines)


def headline(results) -> list:
    """The issue's case (family far_square): per distance, the fraction of the square's
    pixels (exact hits) each tracer misses."""
    rows = []
    for r in results:
        if r.family != "far_square":
            continue
        row = {"distance": r.param, "exact_hits": next(iter(r.metrics.values())).exact_hits}
        for name, m in r.metrics.items():
            row[name] = m.missed_hits / m.exact_hits if m.exact_hits else 0.0
        rows.append(row)
    return rows


def case_ok(r: CaseResult) -> bool:
    """The issue's bar on one case: rt_core f32 no more unexplained mismatches than Mitsuba,
    rt_core f64 none and within 1e-12 wherever kappa_t allows, no non-finite rt_core output."""
    m = r.metrics
    ok = all(v.nonfinite == 0 for k, v in m.items() if k.startswith("rt_"))
    if "rt_f32" in m and "mitsuba" in m:
        ok &= m["rt_f32"].unexplained <= m["mitsuba"].unexplained
    if "rt_f64" in m:
        ok &= m["rt_f64"].unexplained == 0 and m["rt_f64"].over_target == 0
    return bool(ok)


def summary(results) -> dict:
    """Per family: totals per tracer, and whether every case meets the bar (``case_ok``)."""
    fams = {}
    for r in results:
        f = fams.setdefault(r.family, {"cases": 0, "ok": True})
        f["cases"] += 1
        f["ok"] = f["ok"] and case_ok(r)
        for name, m in r.metrics.items():
            s = f.setdefault(name, {"rays": 0, "mismatch": 0, "unexplained": 0, "nonfinite": 0,
                                    "over_target": 0, "depth_max": 0.0, "cond_ratio": 0.0})
            s["rays"] += m.rays
            for k in ("mismatch", "unexplained", "nonfinite", "over_target"):
                s[k] += getattr(m, k)
            s["depth_max"] = max(s["depth_max"], m.depth_max)
            s["cond_ratio"] = max(s["cond_ratio"], m.cond_ratio)
    return fams


def report_data(results, meta: dict | None = None) -> dict:
    """What ``--json`` prints or writes: provenance, per-family summary, the issue's case,
    every case."""
    return {"meta": meta or {}, "summary": summary(results), "headline": headline(results),
            "cases": [r.to_json() for r in results]}


def write_json(results, path: str, meta: dict | None = None) -> None:
    from rt_core.outputs import write_json as write
    write(path, report_data(results, meta))


def write_plot(results, path: str, provenance: dict | None = None) -> None:
    """One log-log subplot per family: max relative depth error against the parameter, per
    tracer (over seeds); the title counts each tracer's unexplained mismatches."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fams = list(dict.fromkeys(r.family for r in results))
    cols = 4
    rows = math.ceil(len(fams) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.4 * cols, 3.6 * rows), squeeze=False)
    style = {"rt_f32": ("C0", "o"), "rt_f64": ("C2", "s"), "mitsuba": ("C3", "^"),
             "naive_f32": ("C7", "x")}
    short = {"rt_f32": "rt32", "rt_f64": "rt64", "mitsuba": "mi", "naive_f32": "naive"}
    floor = 1e-18
    for ax, fam in zip(axes.flat, fams):
        rs = [r for r in results if r.family == fam]
        params = sorted({r.param for r in rs})
        unexpl = {}
        for name, (color, marker) in style.items():
            ms = {p: [r.metrics[name] for r in rs if r.param == p and name in r.metrics]
                  for p in params}
            # cases where tracer and oracle never hit the same object have no depth error
            pts = [(p, max(m.depth_max for m in v)) for p, v in ms.items()
                   if v and sum(m.depth_n for m in v)]
            if pts:
                ax.loglog([p for p, _ in pts], [max(e, floor) for _, e in pts], color=color,
                          marker=marker, label=name, lw=1)
            unexpl[name] = sum(m.unexplained for v in ms.values() for m in v)
        ax.set_title(f"{fam}\nunexplained: " + ", ".join(
            f"{short[k]} {v}" for k, v in unexpl.items()), fontsize=9)
        ax.set_xlabel(AXIS.get(fam, "parameter"), fontsize=8)
        ax.set_ylabel("max rel. depth error", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, which="major", alpha=0.3)
    for ax in list(axes.flat)[len(fams):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("rtval stability: max relative depth error against the exact oracle, per "
                 "family against what it sweeps; unexplained mask/id mismatches per tracer",
                 fontsize=10)
    fig.tight_layout()
    from rt_core.outputs import save_figure
    save_figure(fig, path, provenance, dpi=110)
    plt.close(fig)
