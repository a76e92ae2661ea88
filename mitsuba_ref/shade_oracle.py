"""A slow, obviously correct per-pixel float64 oracle of the course's shading.

The notes' recursion written out literally (shared/notes/course-format.md, "Shading"), one
pixel at a time, on top of the per-ray geometry oracle (``mitsuba_ref/oracle.py``: its hit functions,
its closest-hit ``trace`` with the ``skip`` of the surface a ray leaves, its error-carrying
``EF`` numbers).  Nothing here is vectorized or shares code with ``rt_core.shading``
(``shade_batch`` runs many pixels' paths on arrays, with these same numbers:
``shade_pixels``, ``other_sides_of``).

Beside the intensity I (with a first-order bound on its rounding error, in units of u) every
pixel carries the *margins* of the discontinuous decisions that made it, each the distance of
the decided quantity from its threshold over that quantity's error bound (as in oracle.py):

  geo      the closest hits of the primary and reflection rays (edges, ties, clip, graze, ...)
  shadow   the shadow tests: the blocking hit's own decisions, and its t against the light's
           distance d
  tile     a tiled plane's parity: x = u/w, y = v/h against the integers
  maxdist  total_dist against MAX_DIST (whether the path goes on)
  texel    a textured object's texel: s·W and t·H against the integers where the nearest
           texel changes (README "Textures"; the texture read by mitsuba_ref/ppm.py)

and its ``reach``: how far from the viewpoint's foot point, along the axes of the square
that stands in for the plane in Mitsuba's scene (``convert.stand_in_frame``), the path's
farthest hit on an infinite or tiled plane lies (its closest hits, and the nearest blocker
of a shadow ray that is blocked); 0 if it has none.  Beyond the square's half-size
(``convert.plane_extent``) Mitsuba's scene has no plane there (tools/harness/shaded.py).

The light test c > 0 is not among them: the diffuse term is c·(...), continuous where c
changes sign; where c lies within float32's rounding of 0, the term a tracer may add (c's
bound times diffuse·E/d, huge at tiny scales) joins the intensity's bound (``FACING``).
``flags`` turns margins into per-pixel flags for one precision.
"""
from __future__ import annotations

import collections
import functools
import math

import numpy as np

from rt_core.kinds import kind
from rt_core.rules import Rules
from mitsuba_ref import oracle, ppm, quadric
from mitsuba_ref.convert import stand_in_frame
from mitsuba_ref.oracle import EF, diff3, dot3, length3, scale3, trace, unit3, vec

INF = math.inf
U = {"f32": 2.0 ** -24, "f64": 2.0 ** -53}
# The oracle's bounds are first-order bounds of the notes' formulas evaluated in the stated
# precision.  rt_core evaluates other, equivalent formulas (relative to the viewpoint, fma,
# Binet-Cauchy uv, a bounce-by-bounce sum), whose rounding errors are of the same order but
# not bounded by the same expression, hence two safety factors:
#   K_DECISION = 64: a decision is flagged when its margin is below 64·u, as in
#     test_tracer_vs_oracle (50x headroom over the worst error/bound ratio measured there);
#   K_VALUE = 8: the intensity may differ by 8·u·err; measured over scenes/*.txt and the 94
#     supported course scenes with at most 8 lights (24 columns, f32 and f64), with no 8-bit
#     difference outside the flags, |I_rt_core − I_oracle| never exceeded 0.77·u·err.
K_DECISION = 64.0
K_VALUE = 8.0
MARGINS = ("geo", "shadow", "tile", "maxdist", "texel")
# a light whose c = L·N lies at or below 0 within this many times its error bound still adds
# its term's size to the intensity's bound (float32's decision limit, the widest asked)
FACING = K_DECISION * U["f32"]
# from this many pixels on, shade_pixels runs shade_batch (where it covers the scene): below,
# numpy's per-call cost outweighs the per-pixel loop's.  Measured on the differing pixels of
# rtval validate's 149 shaded comparisons (48 columns, a test run beside it): the
# per-pixel oracle took 1.08 s; with the batch from 8, 16, 32 or 64 pixels on, 0.37, 0.34,
# 0.39 and 0.53 s
BATCH_MIN = 16
# paths ``reaches`` traces at most for one pixel
REACH_RUNS = 256


def _hit_margin(scene, h, base, d, skip, ties: bool = True, tmax: float = INF,
                near=None) -> float:
    """The smallest margin of the decisions behind a ray's verdict: oracle.trace's own (edge,
    clip, t_min, graze; tie for a closest hit), except the sphere discriminant.  For spheres the
    notes' b² − 4ac cancels badly far from the ray origin (its bound, and so its margin, grows
    with |base|²); the decision it stands for is the ray passing inside or outside the sphere,
    whose well-conditioned margin is |p − r|, p the distance of the centre from the ray line."""
    m = min(h.edge_margin, h.clip_margin, h.tmin_margin, h.graze)
    m = min(m, h.tie_gap) if ties else m
    if any(o.kind in quadric.KINDS for o in scene.objects):
        m = min(m, h.disc_margin)        # a quadric's outline (its rim: edge_margin)
    tw = h.t if h.hit else INF
    bv, dv = [x.v for x in base], [x.v for x in d]
    for i, o in enumerate(scene.objects):
        if o.kind != "sphere" or i == skip:
            continue
        c, r = _sphere_inputs(tuple(o.center), o.radius)
        # along.v of the EF numbers below, in plain floats (EF arithmetic computes v as
        # float64 does, in the same order): most spheres are behind the ray or beyond
        # what decides it, and their error bounds are never needed
        along_v = ((c[0].v - bv[0]) * dv[0] + (c[1].v - bv[1]) * dv[1]) + \
            (c[2].v - bv[2]) * dv[2]
        if along_v + r.v < 0 or along_v - r.v > min(tw, tmax):
            continue                     # behind the ray, or beyond what decides it
        q = diff3(c, base)
        along = dot3(q, d)
        p = length3(diff3(q, scale3(along, d)))
        m = min(m, _margin(p.v - r.v, p.e + r.e))
        if near is not None:
            near.append((i, _margin(p.v - r.v, p.e + r.e)))
    return m


@functools.lru_cache(maxsize=4096)
def _sphere_inputs(center: tuple, radius):
    """A sphere's centre and radius as inputs rounded once (EF; never modified), made once per
    sphere rather than once per ray."""
    return vec(center), EF(radius)


def _margin(slack: float, err: float) -> float:
    return INF if err == 0.0 else abs(slack) / err


def _int_margin(x: EF, extra: float = 0.0) -> float:
    """Distance of x from the nearest integer (minus an absolute ``extra``) over x's error."""
    dist = abs(x.v - round(x.v)) - extra
    return 0.0 if dist <= 0 else _margin(dist, x.e)


def _ef3(vals, errs):
    return tuple(EF(v, e) for v, e in zip(vals, errs))


class _Pixel:
    def __init__(self):
        self.geo = self.shadow = self.tile = self.maxdist = self.texel = INF
        self.bounces = 0
        self.reach = 0.0


def reach(scene, obj, p) -> float:
    """How far the hit ``p`` on ``obj`` lies from the viewpoint's foot point along the axes
    of the stand-in square of an infinite or tiled plane (module docstring); 0 on a bounded
    object."""
    if kind(obj.kind).bounded:
        return 0.0
    ax, ay, foot = _frame(obj, tuple(scene.viewpoint))
    rel = [p[i] - foot[i] for i in range(3)]
    return max(abs(sum(r * a for r, a in zip(rel, ax))),
               abs(sum(r * a for r, a in zip(rel, ay))))


@functools.lru_cache(maxsize=256)
def _frame(obj, viewpoint: tuple):
    """``convert.stand_in_frame``, once per plane and viewpoint rather than once per hit."""
    return stand_in_frame(obj, viewpoint)


class _Alt:
    """The choice points of one pixel's path (``other_sides``): each decision within its
    float64 bound (margin below K_DECISION·u) is named by a key (bounce, what, which) --
    ('geo', object) the closest hit, ('shadow', light), ('spot', light) the cone, ('tile',
    axis), ('texel', axis), ('maxdist', 0) -- recorded in ``seen``; those in ``flips`` are
    taken the other way."""
    LIMIT = K_DECISION * U["f64"]

    def __init__(self, flips=frozenset(), limit: float | None = None):
        self.flips, self.seen = flips, []
        self.limit = self.LIMIT if limit is None else limit

    def choose(self, key, m: float, outcome: bool) -> bool:
        """``outcome``, or its negation where this decision is near and flipped."""
        if m < self.limit:
            self.seen.append(key)
            return outcome != (key in self.flips)
        return outcome


def primary_ray(scene, x: int, y: int, W: int, H: int, sampling: str = "corners"):
    """(base, dir) as EF triples for column x, row y (y = 0 the bottom row): the notes' camera."""
    ww, wh = EF(scene.window[0]), EF(scene.window[1])
    if sampling == "corners":
        wx = EF(x, 0.0) / EF(W - 1, 0.0) * ww - ww / 2.0
        wy = EF(y, 0.0) / EF(H - 1, 0.0) * wh - wh / 2.0
    else:
        wx = (EF(x, 0.0) + 0.5) / EF(W, 0.0) * ww - ww / 2.0
        wy = (EF(y, 0.0) + 0.5) / EF(H, 0.0) * wh - wh / 2.0
    base = vec(scene.viewpoint)
    return base, unit3(diff3((wx, wy, EF(0.0, 0.0)), base))


def pixel_ray(scene, columns: int, rows: int, pixel: int, sampling: str, rules: Rules):
    """``primary_ray`` of pixel index ``pixel`` in image order (row 0 the top; rows shifted
    one up under rules.rows = 'shifted')."""
    r, x = divmod(int(pixel), columns)
    shift = 1 if rules.rows == "shifted" else 0
    return primary_ray(scene, x, rows - 1 - r + shift, columns, rows, sampling)


def ray_trace(scene, base, d, total_dist, skip, rules: Rules, max_dist: float, px: _Pixel,
              alt: _Alt | None = None, bounce: int = 0):
    """The notes' trace(): intensity (3 EF) of the ray base + t·d, path length so far
    ``total_dist`` (EF), ignoring object ``skip``; margins go into ``px``.

    The notes recurse, I = local + specular · trace(reflection ray); here the bounces run in
    a loop that keeps each bounce's (local, specular), and the sums are made afterwards from
    the last bounce back: the same operations in the same order, without Python's recursion
    limit (a corridor of mirrors reaches thousands of bounces before a long MAX_DIST).
    ``alt``: the decisions within their bound are recorded there, and those it names taken
    the other way (``other_sides``).  ``bounce``: the ray's bounce in its path (alt's keys;
    shade_batch hands a path's last bounces over here)."""
    alt = _Alt() if alt is None else alt
    stack = []                          # (local intensity, specular) of the bounces so far
    b = bounce                          # the bounce (alt's keys)
    while True:
        h = trace(scene, base, d, rules, skip)
        near = []
        px.geo = min(px.geo, _hit_margin(scene, h, base, d, skip, near=near))
        # the objects whose verdict is within its bound; those flipped are taken the other
        # way (oracle.trace: ValueError where that side has no hit to take), and the
        # verdicts near on the hit that gives are choice points too
        risks, flip = near + h.risks, frozenset()
        for _ in range(4):
            now = frozenset(j for j, m in risks if alt.choose((b, "geo", j), m, False))
            if now == flip:
                break
            flip = now
            h = trace(scene, base, d, rules, skip, flip)
            risks = risks + h.risks
        if not h.hit:
            I = [EF(0.0, 0.0)] * 3
            break
        obj = scene.objects[h.id]
        px.reach = max(px.reach, reach(scene, obj, h.position))
        total_dist = total_dist + EF(h.t, h.err_t)
        H = _ef3(h.position, h.err_position)
        N = _ef3(h.normal, h.err_normal)
        mat = obj.material
        if obj.kind == "tplane":
            # floor(OFF + u/w): the oracle's float64 sum rounds by up to ulp(OFF)/2
            k = oracle.tile_scale(obj, rules)
            u = EF(h.uv[0], h.err_uv[0]) * EF(k)
            vv = EF(h.uv[1], h.err_uv[1])
            if rules.tile_add_first:
                u, vv = u + EF(oracle.OFF, 0.0), vv + EF(oracle.OFF, 0.0)
            x = u / EF(obj.size[0])
            y = vv / EF(obj.size[1])
            off = oracle.OFF * 2.0 ** -53
            mx, my = _int_margin(x, off), _int_margin(y, off)
            px.tile = min(px.tile, mx, my)
            fg = oracle.tile_foreground(obj, h.uv[0], h.uv[1], rules)
            # (either axis's floor flipped: the other colour)
            fg = alt.choose((b, "tile", 1), my, alt.choose((b, "tile", 0), mx, fg))
            if not fg:
                mat = obj.background
        I = [EF(a) for a in mat.ambient]
        if getattr(obj, "texture", None) is not None:
            I = _textured_ambient(scene, obj, h, N, px, alt, b)
        for l, light in enumerate(scene.lights):
            D = diff3(vec(light.center), H)
            dist = length3(D)
            L = unit3(D)
            c = dot3(L, N)
            if c.v <= 0:
                if c.v > -FACING * c.e:
                    # c within float32's rounding of 0 (a light in the surface's plane): a
                    # tracer's c may come out > 0 and add the light's term, whose size (c's
                    # bound times diffuse·E/d: huge at tiny scales) joins I's bound, not its
                    # value
                    for i in range(3):
                        I[i] = I[i] + EF(mat.diffuse[i]) * EF(light.emissivity[i]) * \
                            EF(0.0, c.e) / dist
                continue                                    # light behind the surface
            if light.kind == "spotlight":
                # inside the cone iff unit(H − centre)·unit(aim − centre) > cos θ: a decision
                # (its margin joins the shadow tests': whether the light reaches H)
                axis = unit3(diff3(vec(light.aim), vec(light.center)))
                cos_t = math.cos(math.radians(light.theta))       # within a few ulps
                s = dot3(scale3(EF(-1.0, 0.0), L), axis) - EF(cos_t, 4.0 * abs(cos_t))
                px.shadow = min(px.shadow, _margin(s.v, s.e))
                inside = alt.choose((b, "spot", l), _margin(s.v, s.e), s.v > 0)
                if not inside:
                    continue                                # outside the spotlight's cone
            s = trace(scene, H, L, rules, h.id)
            m = _hit_margin(scene, s, H, L, h.id, False, dist.v)
            if s.hit:
                m = min(m, _margin(s.t - dist.v, s.err_t + dist.e))
            px.shadow = min(px.shadow, m)
            # (whichever test is near: the light blocked or not)
            if s.hit and s.t < dist.v:
                px.reach = max(px.reach, reach(scene, scene.objects[s.id], s.position))
            blocked = alt.choose((b, "shadow", l), m, s.hit and s.t < dist.v)
            if blocked:
                continue                                    # shadow
            for i in range(3):
                I[i] = I[i] + EF(mat.diffuse[i]) * EF(light.emissivity[i]) * c / dist
        seg = EF(h.t, h.err_t) if rules.reflect == "segment" else total_dist
        I = [a / seg for a in I]
        if not any(mat.specular):
            break
        px.maxdist = min(px.maxdist, _margin(total_dist.v - max_dist, total_dist.e))
        going = alt.choose((b, "maxdist", 0), _margin(total_dist.v - max_dist, total_dist.e),
                           total_dist.v < max_dist)
        if not going:
            break
        # the reflection ray: trace it next, and add specular · its intensity afterwards
        px.bounces += 1
        stack.append((I, mat.specular))
        R = unit3(diff3(d, scale3(2.0 * dot3(d, N), N)))
        base, d, skip = H, R, h.id
        b += 1
    for local, spec in reversed(stack):
        I = [local[i] + EF(spec[i]) * I[i] for i in range(3)]
    return tuple(I)


def other_sides(scene, columns: int, rows: int, pixel: int, sampling: str = "corners",
                rules: Rules = Rules(), max_dist: float = 1000.0, runs: int = 32,
                bounces: int = 64, first=None, limit: float | None = None, targets=None):
    """The 8-bit colours of one pixel (index in image order, row 0 the top) that its
    decisions within their float64 bound can give, taken either way in every combination
    (``_Alt``): a float64 tracer may take any of them.  None where they cannot all be
    enumerated: more than ``runs`` paths, ``bounces`` reflection bounces traced in all or 8
    near decisions (a mirror corridor's collapsed bounds make every bounce a choice), a
    verdict whose other side has no hit to take (a quadric's, a torus's, a sphere's missed
    by its discriminant), or one taken at t = 0 that the intensity divides by: then any
    colour is the caller's answer.  ``first``: the unflipped path from ``shade_pixels``
    (its 'paths' entry, recorded at this ``limit``), not traced again.  ``limit``: a
    decision is near below this margin (default float64's, ``_Alt.LIMIT``; a wider one asks
    what a tracer computing in lower precision may take either way).  ``targets``: colours
    the caller asks about; True as soon as every one of them is among the colours found
    (they are then among the whole set's: the answer the set would give), else as
    without."""
    want = _wanted(targets)
    # breadth first, the order of ``reaches``' levels and of other_sides_of's rounds: with
    # ``targets``, True only where reaches would find them within its budget too (a review:
    # depth first found a fourth-level combination after 5 paths where the levels above it
    # held more than REACH_RUNS, and the pixel went from wrong to boundary)
    colours, todo, done = set(), collections.deque([frozenset()]), set()
    while todo:
        flips = todo.popleft()
        if flips in done:
            continue
        if len(done) >= runs:
            return None
        done.add(flips)
        got = _flipped(scene, columns, rows, pixel, sampling, rules, max_dist, flips, first,
                       limit)
        if got is None:
            # no hit to take, or a hit taken at t = 0 that the intensity divides by (a
            # course program's inf or NaN: not a colour to name)
            return None
        colour, near, went = got
        bounces -= went + 1
        new = [k for k in near if k not in flips]
        if bounces < 0 or len(flips) + len(new) > 8:
            return None                 # (2^8 paths: more than ``runs`` anyway)
        colours.add(colour)
        if want is not None and want <= colours:
            return True
        todo.extend(flips | {k} for k in new)
    return colours


def _wanted(targets):
    """The set of colours (int tuples) of ``targets``, or None."""
    return None if targets is None else {tuple(int(c) for c in t) for t in targets}


def reaches(scene, columns: int, rows: int, pixel: int, targets, sampling: str = "corners",
            rules: Rules = Rules(), max_dist: float = 1000.0, first=None,
            limit: float | None = None, runs: int = REACH_RUNS, tol: int = 0,
            exclude=()) -> bool | None:
    """Do some of the pixel's near decisions, taken the other way, give each 8-bit colour of
    ``targets`` (within ``tol`` levels in every channel)?  Where ``other_sides`` cannot
    enumerate every combination (too many near decisions), a search for these colours only:
    flip sets in order of size (one decision, then two, ...), at most ``runs`` paths.  True
    as soon as every target is found, or a path has no colour to name (as other_sides' None:
    a flip with no hit to take, a division by zero); False when every combination was
    traced without; None when the budget ran out first (not decided).  ``first``, ``limit``: as
    other_sides'.  A path whose colour is one of ``exclude`` finds nothing (rtval check:
    rt_core's own colour, which is within a level of any one-level bug's)."""
    want = [tuple(int(c) for c in t) for t in targets]
    exclude = {tuple(int(c) for c in e) for e in exclude}
    found, done, level = set(), set(), [frozenset()]
    while level:
        nxt = []
        for flips in level:
            if flips in done:
                continue
            if len(done) >= runs:
                return None
            done.add(flips)
            got = _flipped(scene, columns, rows, pixel, sampling, rules, max_dist, flips,
                           first, limit)
            if got is None:
                # a flip with no hit to take, or a path dividing by zero: not a colour this
                # oracle can name, so any colour (as other_sides' None)
                return True
            colour, near, _ = got
            if tuple(colour) not in exclude:
                found.update(k for k, t in enumerate(want)
                             if max(abs(int(a) - b) for a, b in zip(colour, t)) <= tol)
            if len(found) == len(want):
                return True
            nxt += [flips | {k} for k in near if k not in flips]
        level = nxt
    return False


def _flipped(scene, columns, rows, pixel, sampling, rules, max_dist, flips, first, limit):
    """``_path`` with ``flips``, the unflipped one being ``first`` where the caller has it."""
    if not flips and first is not None:
        return first
    return _path(scene, columns, rows, pixel, sampling, rules, max_dist, flips, limit)


def _path(scene, columns: int, rows: int, pixel: int, sampling: str, rules: Rules,
          max_dist: float, flips, limit):
    """(colour, near decisions, bounces) of a pixel's path with ``flips`` taken the other way
    (``other_sides``), or None where it raises (no hit to take, a division by zero)."""
    base, d = pixel_ray(scene, columns, rows, pixel, sampling, rules)
    alt, px = _Alt(flips, limit), _Pixel()
    try:
        I = ray_trace(scene, base, d, EF(0.0, 0.0), None, rules, max_dist, px, alt)
    except (ValueError, ArithmeticError):
        return None
    return _colour(I), tuple(dict.fromkeys(alt.seen)), px.bounces


def other_sides_of(scene, columns: int, rows: int, pixels, sampling: str = "corners",
                   rules: Rules = Rules(), max_dist: float = 1000.0, runs: int = 32,
                   bounces: int = 64, firsts=None, limit: float | None = None,
                   targets=None) -> list:
    """``other_sides`` of each of ``pixels`` (``firsts``: their unflipped paths or None), the
    same answers.  Where shade_batch covers the scene, the pixels' paths are traced
    together, a round at a time: each round, every pixel's paths not traced yet (its near
    decisions taken the other way, in every combination found so far), on arrays where
    they are BATCH_MIN or more (``_paths``), however few the pixels: a handful of pixels
    can have dozens of paths.  A pixel's answer depends only on the set of its paths, which
    every order reaches whole: the colours, or None where one path raises, there are more
    than ``runs``, their bounces exceed ``bounces`` or one has more than 8 near
    decisions.  ``targets``: each pixel's colours asked about (other_sides' ``targets``):
    a pixel whose colours found so far hold all of its own is True and traces no more.
    With targets the answers may differ in one way: a round is traced whole or not (not
    where it would take the pixel past ``runs``), where other_sides traces its paths one
    at a time, so other_sides may find the targets within ``runs`` where this answers
    None (``reaches``, breadth first with a larger budget, then finds them too)."""
    from mitsuba_ref import shade_batch
    pixels = [int(p) for p in pixels]
    firsts = list(firsts) if firsts is not None else [None] * len(pixels)
    targets = list(targets) if targets is not None else [None] * len(pixels)
    if not shade_batch.supported(scene):
        return [other_sides(scene, columns, rows, p, sampling, rules, max_dist, runs, bounces,
                            f, limit, t) for p, f, t in zip(pixels, firsts, targets)]
    want = [_wanted(t) for t in targets]
    todo = [[frozenset()] for _ in pixels]
    done = [set() for _ in pixels]
    left = [bounces] * len(pixels)
    colours = [set() for _ in pixels]
    answer = [False] * len(pixels)          # False: not known yet
    while True:
        lanes = []                          # (pixel's position, flips) to trace this round
        for k in range(len(pixels)):
            if answer[k] is not False:
                continue
            new = [f for f in dict.fromkeys(todo[k]) if f not in done[k]]
            todo[k] = []
            if not new:
                answer[k] = colours[k]
            elif len(done[k]) + len(new) > runs:
                answer[k] = None
            else:
                done[k].update(new)
                lanes += [(k, f) for f in new]
        if not lanes:
            return answer
        for (k, flips), got in zip(lanes, _paths(scene, columns, rows, pixels, sampling, rules,
                                                  max_dist, lanes, firsts, limit)):
            if answer[k] is not False:
                continue
            if got is None:
                answer[k] = None
                continue
            colour, near, went = got
            left[k] -= went + 1
            new = [key for key in near if key not in flips]
            if left[k] < 0 or len(flips) + len(new) > 8:
                answer[k] = None
                continue
            colours[k].add(colour)
            if want[k] is not None and want[k] <= colours[k]:
                answer[k] = True
                continue
            todo[k] += [flips | {key} for key in new]


def _paths(scene, columns, rows, pixels, sampling, rules, max_dist, lanes, firsts, limit):
    """``_path`` of each (pixel's position, flips) of ``lanes``: a pixel's unflipped path
    from ``firsts`` where known, the rest on arrays (shade_batch) where they are
    BATCH_MIN or more, each lane the per-pixel code raises on by that code."""
    from mitsuba_ref import shade_batch
    out = [firsts[k] if not flips and firsts[k] is not None else False
           for k, flips in lanes]
    todo = [i for i, got in enumerate(out) if got is False]
    if len(todo) >= BATCH_MIN:
        px = np.array([pixels[lanes[i][0]] for i in todo])
        base, d = shade_batch.rays(scene, columns, rows, px, sampling, rules)
        got = shade_batch.shade(scene, base, d, rules, max_dist,
                                [lanes[i][1] for i in todo], limit)
        for i, path in zip(todo, shade_batch.paths(got)):
            if path is not None:
                out[i] = path
    for i, got in enumerate(out):
        if got is False:
            k, flips = lanes[i]
            out[i] = _path(scene, columns, rows, pixels[k], sampling, rules, max_dist, flips,
                           limit)
    return out


def _colour(I) -> tuple:
    """The 8-bit colour of an intensity (3 EF)."""
    return tuple(int(c) for c in quantize(np.array([c.v for c in I])))


def _extra(obj, name):
    return next(v for k, v in obj.extras if k == name)


def _atan2(a: EF, b: EF) -> EF:
    """atan2 with a first-order bound: |∂/∂a|·e_a + |∂/∂b|·e_b plus one rounding."""
    r2 = a.v * a.v + b.v * b.v
    th = math.atan2(a.v, b.v)
    e = (abs(b.v) * a.e + abs(a.v) * b.e) / r2 if r2 > 0 else INF
    return EF(th, e + 2 * abs(th))


def _acos(y: EF) -> EF:
    c = min(1.0, max(-1.0, y.v))
    s = math.sqrt(max(1.0 - c * c, 0.0))
    e = y.e / s if s > 0 else INF
    return EF(math.acos(c), e + 2 * math.acos(c))


def _index(x: EF, n: int, wrap: bool, px: _Pixel, alt: _Alt, key) -> int:
    """Nearest texel floor(x·n) (x wrapped into [0, 1) first, or clamped to 0..n−1); the
    margin of x·n from the integers where the texel changes (all with ``wrap``, the inner
    ones 1..n−1 without) goes into ``px.texel``."""
    xn = x * EF(float(n), 0.0)
    k = round(xn.v)
    i = math.floor(xn.v)
    if wrap or 0 < k < n:
        px.texel = min(px.texel, _int_margin(xn))
        if alt.choose(key, _int_margin(xn), False):
            i = k - 1 if i == k else k            # the texel on the integer's other side
    return i % n if wrap else min(max(i, 0), n - 1)


def _textured_ambient(scene, obj, h, N, px: _Pixel, alt: _Alt, b: int) -> list:
    """brightness × texel of a textured object (README "Textures"), computed from the fields
    as written and the file the scene's texture names (read here by mitsuba_ref/ppm.py)."""
    tex = ppm.texels(obj.texture.path)
    H, W = tex.shape[:2]
    form = obj.form
    bright = 1.0 if form in ("texplane", "texsphere") else float(_extra(obj, "brightness"))
    if obj.kind == "sphere":
        # d = unit(hit − centre) (the oracle's outward normal), forward projected onto xz
        f = [float(c) for c in _extra(obj, "forward")] if form == "sphere_pixmap" \
            else [0.0, 0.0, 1.0]
        m = math.hypot(f[0], f[2])
        fx, fz = f[0] / m, f[2] / m
        along = N[0] * EF(fx) + N[2] * EF(fz)          # d·f̂
        across = N[0] * EF(-fz) + N[2] * EF(fx)        # d·ŝ, ŝ = (−f̂z, 0, f̂x)
        s = _atan2(across, along) / EF(2 * math.pi)
        t = _acos(N[1]) / EF(math.pi)
        col = _index(s, W, True, px, alt, (b, "texel", 0))
        row = _index(t, H, False, px, alt, (b, "texel", 1))
    else:
        u = EF(h.uv[0], h.err_uv[0])
        v = EF(h.uv[1], h.err_uv[1])
        if form == "fplanetex":
            sx, sy = _extra(obj, "texture size")
            wrap = True
        elif _extra(obj, "tile mode") == 2:
            sx, sy = scene.window
            wrap = True
        else:
            sx, sy = obj.size
            wrap = False
        col = _index(u / EF(float(sx)), W, wrap, px, alt, (b, "texel", 0))
        row = _index(v / EF(float(sy)), H, wrap, px, alt, (b, "texel", 1))
    return [EF(bright) * EF(float(c)) for c in tex[row, col]]


def render_shade_oracle(scene, columns: int, rows: int | None = None,
                        sampling: str = "corners", rules: Rules = Rules(),
                        max_dist: float = 1000.0) -> dict:
    """Per-pixel oracle images, row 0 = TOP: 'I' and 'err' (rows, columns, 3): intensity and
    its error bound in units of u; MARGINS (rows, columns); 'bounces', 'reach'."""
    W = int(columns)
    H = scene.default_rows(W) if rows is None else int(rows)
    out = {"I": np.zeros((H, W, 3)), "err": np.zeros((H, W, 3)),
           "bounces": np.zeros((H, W), np.int32), "reach": np.zeros((H, W))}
    out.update({m: np.full((H, W), INF) for m in MARGINS})
    for y in range(H):
        for x in range(W):
            _trace_into(out, (H - 1 - y, x), scene, lambda: primary_ray(scene, x, y, W, H,
                                                                         sampling),
                        rules, max_dist)
    return out


def _trace_into(out: dict, k, scene, ray, rules: Rules, max_dist: float,
                limit: float | None = None) -> None:
    """One pixel's path (its primary ray from ``ray()``) into the arrays of ``out`` at index
    ``k``: 'I', 'err', 'bounces', 'reach', MARGINS and, where ``out`` has them, 'paths'.  A
    path the notes' arithmetic cannot compute (a division by zero: a light at the point it
    lights, whose direction is 0/0; a primary ray of a degenerate camera) is a course
    program's inf or NaN, no colour to name: every margin 0, so every decision is flagged,
    and no path (other_sides: any colour).  ``limit``: the near decisions' (_Alt's)."""
    px, alt = _Pixel(), _Alt(limit=limit)
    try:
        base, d = ray()
        I = ray_trace(scene, base, d, EF(0.0, 0.0), None, rules, max_dist, px, alt)
    except ArithmeticError:
        out["I"][k] = out["err"][k] = 0.0
        out["bounces"][k], out["reach"][k] = px.bounces, px.reach
        for m in MARGINS:
            out[m][k] = 0.0
        if "paths" in out:
            out["paths"][k] = None
        return
    if "paths" in out:
        out["paths"][k] = (_colour(I), tuple(dict.fromkeys(alt.seen)), px.bounces)
    out["I"][k] = [c.v for c in I]
    out["err"][k] = [c.e for c in I]
    out["bounces"][k], out["reach"][k] = px.bounces, px.reach
    for m in MARGINS:
        out[m][k] = getattr(px, m)


def shade_pixels(scene, columns: int, rows: int, pixels, sampling: str = "corners",
                 rules: Rules = Rules(), max_dist: float = 1000.0,
                 limit: float | None = None) -> dict:
    """``render_shade_oracle`` for some pixels only (indices in image order, row 0 the top):
    'I', 'err' (n, 3), MARGINS, 'bounces' and 'reach' (n,), and 'paths', each unflipped
    path's (colour, near decisions, bounces) with decisions near below ``limit`` (_Alt's;
    other_sides' ``first`` at that limit)."""
    pixels = np.asarray(pixels, np.int64)
    n = len(pixels)
    out = {"I": np.zeros((n, 3)), "err": np.zeros((n, 3)), "bounces": np.zeros(n, np.int32),
           "reach": np.zeros(n)}
    out.update({m: np.full(n, INF) for m in MARGINS})
    out["paths"] = [None] * n           # (colour, near decisions, bounces): other_sides' first
    todo = range(n)
    if n >= BATCH_MIN:
        # many pixels: shade_batch, the same numbers on arrays; the per-pixel code below
        # only where its numbers are not all numbers (a division by zero: _trace_into)
        from mitsuba_ref import shade_batch
        if shade_batch.supported(scene):
            base, d = shade_batch.rays(scene, columns, rows, pixels, sampling, rules)
            got = shade_batch.shade(scene, base, d, rules, max_dist, limit=limit)
            for key in ("I", "err", "bounces", "reach", *MARGINS):
                out[key][:] = got[key]
            out["paths"] = shade_batch.paths(got)
            todo = [k for k, path in enumerate(out["paths"]) if path is None]
    for k in todo:
        _trace_into(out, k, scene, lambda: pixel_ray(scene, columns, rows, int(pixels[k]),
                                                      sampling, rules), rules, max_dist, limit)
    return out


def quantize(I: np.ndarray) -> np.ndarray:
    """floor(255 · clamp(I, 0, 1)), in float64."""
    return np.floor(255.0 * np.clip(I, 0.0, 1.0)).astype(np.uint8)


def flags(orc: dict, precision: str, u: float | None = None) -> dict:
    """Per-pixel flags (rows, columns) for a tracer in ``precision``: each discontinuous
    decision that may flip ('geo', 'shadow', 'tile', 'maxdist', 'texel', together 'jump');
    'quant': a channel within the intensity bound of an 8-bit level boundary (255·I near
    an integer), 'quant_rgb' which channels (rows, columns, 3): a one-level difference is
    rounding only in a channel near its level; 'any'.  ``u``: the unit roundoff to take
    instead of the precision's."""
    u = U[precision] if u is None else u
    out = {m: orc[m] < K_DECISION * u for m in MARGINS}
    q = 255.0 * orc["I"]
    bound = K_VALUE * u * orc["err"]
    near = np.abs(q - np.round(q)) < 255.0 * bound
    out["quant_rgb"] = near & (orc["I"] <= 1 + bound)      # per channel
    out["quant"] = np.any(out["quant_rgb"], -1)
    out["jump"] = out["geo"] | out["shadow"] | out["tile"] | out["maxdist"] | out["texel"]
    out["any"] = out["jump"] | out["quant"]
    return out
