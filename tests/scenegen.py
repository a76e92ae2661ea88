"""Seeded random scenes for comparing the tracer with the oracle.

Every object is placed in front of the window (z < 0) along a random view ray, so a render sees
it; scales are log-uniform (pbrt style).  Some plane-kind objects copy the normal and point of an
earlier one (the same plane equation, so the two tie exactly and the tie rule decides).
"""
from __future__ import annotations

import math
import random

from rt_core.scene import (Material, PointLight, Scene, make_fplane, make_plane,
                           make_sphere, make_tplane, plane_frame)


# infinite planes cover most of the image: draw them less often, so misses stay common
WEIGHTS = {"sphere": 3, "plane": 1, "fplane": 4, "tplane": 1}


def _loguniform(rng: random.Random, lo: float, hi: float) -> float:
    return math.exp(rng.uniform(math.log(lo), math.log(hi)))


def _unit(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def _random_dir(rng: random.Random):
    while True:
        v = tuple(rng.gauss(0.0, 1.0) for _ in range(3))
        if sum(c * c for c in v) > 1e-6:
            return _unit(v)


def _material(rng: random.Random) -> Material:
    col = lambda hi: tuple(round(rng.uniform(0, hi), 3) for _ in range(3))
    return Material(col(1.0), col(8.0), col(0.5) if rng.random() < 0.3 else (0.0, 0.0, 0.0))


def _view_point(rng, vp, window, dist):
    """A point at distance ``dist`` from vp along the ray through a random window point."""
    ww, wh = window
    world = (rng.uniform(-ww / 2, ww / 2), rng.uniform(-wh / 2, wh / 2), 0.0)
    d = _unit(tuple(w - v for w, v in zip(world, vp)))
    return tuple(v + dist * c for v, c in zip(vp, d))


def _facing_normal(rng, toward):
    """A random unit normal, not within ~10 degrees of edge-on to the direction ``toward``."""
    while True:
        n = _random_dir(rng)
        c = sum(a * b for a, b in zip(n, _unit(toward)))
        if abs(c) > 0.17:
            return tuple(round(x, 6) for x in n)


def _orient(rng, n):
    """A random orient that is far from parallel to n (its projection does not vanish)."""
    while True:
        o = tuple(round(x * rng.uniform(0.5, 3.0), 6) for x in _random_dir(rng))
        if abs(sum(a * b for a, b in zip(_unit(o), n))) < 0.9:
            return o


def _corners(p, n, o, w, h):
    x, y, _ = plane_frame(n, o)
    return [tuple(p[i] + a * x[i] + b * y[i] for i in range(3))
            for a, b in ((0, 0), (w, 0), (w, h), (0, h))]


BASE_KINDS = ("sphere", "plane", "fplane", "tplane")     # the kinds generated here


def random_scene(seed: int, n_objects: int = 8, kinds=BASE_KINDS, tie_prob: float = 0.2) -> Scene:
    """A random scene: window 8 x 6, viewpoint near (0, 0, 3..6), ``n_objects`` objects drawn
    from ``kinds`` in front of the window, one or two point lights."""
    rng = random.Random(seed)
    kinds = tuple(kinds)
    window = (8.0, 6.0)
    vp = (round(rng.uniform(-0.5, 0.5), 4), round(rng.uniform(-0.5, 0.5), 4),
          round(rng.uniform(3.0, 6.0), 4))
    lights = tuple(PointLight(tuple(round(rng.uniform(1, 10), 2) for _ in range(3)),
                              (round(rng.uniform(-6, 6), 3), round(rng.uniform(0, 6), 3),
                               round(rng.uniform(-4, 4), 3)))
                   for _ in range(rng.randint(1, 2)))
    objects = []
    planes = []                                  # (normal, point) of plane-kind objects so far
    line = 3
    while len(objects) < n_objects:
        kind = rng.choices(kinds, [WEIGHTS.get(k, 1) for k in kinds])[0]
        mat = _material(rng)
        dist = _loguniform(rng, vp[2] + 1.0, vp[2] + 25.0)
        at = _view_point(rng, vp, window, dist)
        if at[2] > -0.5:
            continue
        toward = tuple(v - a for v, a in zip(vp, at))
        if kind == "sphere":
            r = min(_loguniform(rng, 0.1, 4.0), 0.8 * (-at[2]))
            objects.append(make_sphere(mat, tuple(round(c, 6) for c in at), round(r, 6), line))
            line += 1
            continue
        if planes and rng.random() < tie_prob:
            n, p = rng.choice(planes)            # an exact copy of an earlier plane equation
        else:
            n, p = _facing_normal(rng, toward), tuple(round(c, 6) for c in at)
        if kind == "plane":
            obj = make_plane(mat, n, p, line)
        elif kind == "tplane":
            o = _orient(rng, n)
            tile = (round(_loguniform(rng, 0.2, 3.0), 4), round(_loguniform(rng, 0.2, 3.0), 4))
            obj = make_tplane(mat, n, p, o, tile, _material(rng), line)
        else:
            o = _orient(rng, n)
            w, h = round(_loguniform(rng, 0.3, 8.0), 4), round(_loguniform(rng, 0.3, 8.0), 4)
            if (n, p) not in planes:
                # put the rectangle's centre (not its corner) on the view ray
                x, y, _ = plane_frame(n, o)
                p = tuple(round(p[i] - 0.5 * w * x[i] - 0.5 * h * y[i], 6) for i in range(3))
            if max(c[2] for c in _corners(p, n, o, w, h)) > -0.05:
                continue                         # keep the whole rectangle behind the window
            obj = make_fplane(mat, n, p, o, (w, h), line)
        if (n, p) not in planes:
            planes.append((n, p))
        objects.append(obj)
        line += 1
    return Scene(window, vp, lights, tuple(objects), path=f"<random seed={seed}>")
