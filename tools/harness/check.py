"""rtval check: a user's course tracer, pixel by pixel, every difference explained.

For one scene and the image a tracer wrote (PPM P6/P3 or PNG), rt_core renders the course
image in float64 (exact decisions) and every pixel gets one class:

* ``match``: the same 8-bit colour;
* ``rounding``: a channel off by one where the intensity lies within its float64 error bound
  of an 8-bit level (computed by the shading oracle), so a float64 tracer may floor it to
  either side; ``boundary`` where a decision is within its bound (but for a systematic
  offset, over 5% of the image nine in ten one way, only where the colour is another rule
  variant's); else ``wrong``;
* ``boundary``: a ray of the pixel (primary, shadow or reflection) passes within a float64
  error bound of a decision — an edge, a tie, the window plane, a sphere outline, a shadow's
  blocker, a tile border, the distance cut-off — so either answer is defensible, and the
  pixel has a colour those decisions give, taken either way in some combination.  The bound
  and the colours are computed by the float64 shading oracle (mitsuba_ref/shade_oracle.py),
  independently of rt_core;
* ``variant``: the pixel is right under the rule variant inferred for the image and wrong
  under the notes' rule (``variant_rule`` names it);
* ``wrong``: anything else.

**Rule inference.**  Each rule with variants seen in real course programs (finite-plane
edges, screen clip, tie order, plane t threshold, clipped spheres, the reflection distance
cut-off) is set, one at a time and repeatedly until nothing changes, to the value whose render
leaves the fewest differing pixels.  A rule is *determined* when another value would leave
more (the count that decides it is reported), *undetermined* when the scene cannot tell.

The verdict: ``pass`` when no pixel is ``wrong`` under the inferred (or given) rules.
"""
from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rt_core.kinds import PLANE_KINDS

from .pipes import Tail as _Tail

CLASSES = ("match", "rounding", "boundary", "variant", "wrong")
# named colours of the class image (legend in the report)
# (told apart by the colour-blind too: no green beside the red, a red that is not dark, a
# near-black match; tests/test_html_report.py test09 simulates the three dichromacies)
COLORS = {"match": ("near black", (24, 24, 24)), "rounding": ("blue", (40, 80, 200)),
          "boundary": ("yellow", (240, 228, 66)), "variant": ("lavender", (150, 150, 255)),
          "wrong": ("red", (255, 40, 0))}
DEFAULT_MAX_DIST = 1000.0
WRONG_LISTED = 1000      # wrong pixels --json lists (the first in image order; counts: all)
# A tracer computing in float32 instead of double leaves a few wrong pixels scattered one or
# two at a time, each where a decision lies within float32's rounding of its threshold (a
# shadow's blocker, a tile border, an edge) and with the colour its other side gives.  The
# hint (never the verdict) asks F32_SAMPLE of the wrong pixels of a scene whose wrong pixels
# are at most F32_SHARE of the image in groups of at most F32_GROUP, the shading oracle's
# bounds taken with F32_U for u: float32's unit roundoff, times 4 (the oracle bounds the
# notes' float64 formulas; measured on a float32 build of tests/ctracer/course.c, README
# "A tracer in float")
F32_U = 4 * 2.0 ** -24
F32_SAMPLE = 12
F32_SHARE = 0.02
F32_GROUP = 12
F32_MIN = 3              # a scene's hint needs this many pixels asked, all explained
F32_RUN = 0.8            # a run's: this share of 10 or more asked in its failing scenes
# (neither where the shadow-speck hint names a bug: ``_speckles``)
SPECKS = "shadow rays that hit the surface"
# boundary pixels at least this share of the image (and 20) are summed up in words: which
# decision most of them sit at (``boundary_note``)
BOUNDARY_NOTE = 0.01
MAX_DISTS = (1000.0, 20.0, 30.0, 50.0, 70.0, 200.0, 50000.0)
# (rule, values with the notes' first, which scenes it can matter in)
DIMENSIONS = (
    ("edges", ("closed", "open"), lambda k: bool(set(k) & {"fplane", "triangle", "disk"})),
    ("screen_clip", (">", ">="), lambda k: bool(set(k) & {"plane", "fplane", "tplane",
                                                          "triangle", "disk"})),
    ("ties", ("first", "last"), lambda k: len(k) > 0),
    ("t_min", (0.0, 1e-4, 1e-5), lambda k: bool(set(k) & {"plane", "fplane", "tplane",
                                                          "triangle", "disk"})),
    ("clip_spheres", (False, True), lambda k: "sphere" in k),
    ("max_dist", MAX_DISTS, None),
    ("reflect", ("total", "segment"), "specular"),
    ("rows", ("course", "shifted"), lambda k: len(k) > 0),
    ("tile_add_first", (False, True), lambda k: "tplane" in k),
    ("tile_project", (True, False), lambda k: "tplane" in k),
)
WORDS = {
    ("edges", "open"): "finite-plane edges are open (0 < u < w; a triangle's or disk's edge "
                       "too): the notes' bounds are closed, 0 <= u <= w, so rays exactly "
                       "through an edge are lost",
    ("screen_clip", ">="): "hits exactly in the window plane (z = 0) are clipped: the notes clip "
                           "only z > 0, so a plane lying in z = 0 should be visible",
    ("ties", "last"): "an exact tie goes to the later object (a list built by inserting at the "
                      "head?): the notes keep the earlier one",
    ("t_min", 1e-4): "plane hits need t > 1e-4: the notes accept any t > 0",
    ("t_min", 1e-5): "plane hits need t > 1e-5: the notes accept any t > 0",
    ("clip_spheres", True): "spheres are clipped at the window plane too: the notes clip planes "
                            "only",
    ("reflect", "segment"): "reflections are divided by the segment length, the notes divide by "
                            "the total path",
    ("rows", "shifted"): "every row is sampled one row too high ((H - r)/(H - 1) instead of "
                         "(H - 1 - r)/(H - 1)): the top row lies above the window",
    ("tile_add_first", True): "the tile parity adds the offset before dividing, "
                              "floor((OFF + u)/w): the notes take floor(OFF + u/w)",
    ("tile_project", False): "the tiled plane's direction is not projected onto the plane, so "
                             "the tiles are stretched where it is tilted",
}


@dataclass
class RuleFinding:
    rule: str
    value: object
    determined: bool
    pixels: int          # differing pixels the next-best value would add (0: undetermined)
    notes: object        # the notes' value
    # no value fits: the image does not follow the one the search found (``infer``'s veto),
    # and the notes' is reported
    unfollowed: bool = False

    def as_dict(self):
        return dataclasses.asdict(self)


@dataclass
class SceneCheck:
    """The result for one scene."""
    scene: str
    image: str | None
    status: str                      # pass, fail, error (bad input, crash, ...) or refused
    reason: str = ""
    columns: int = 0
    rows: int = 0
    counts: dict = field(default_factory=dict)
    variant_counts: dict = field(default_factory=dict)
    rules: str = ""
    max_dist: float = DEFAULT_MAX_DIST
    findings: list = field(default_factory=list)
    deviations: list = field(default_factory=list)
    hints: list = field(default_factory=list)       # what the wrong pixels look like
    worst: dict = field(default_factory=dict)
    seconds: float = 0.0
    hits: dict = field(default_factory=dict)
    # wrong pixels not asked about: the oracle's sample of their set had one nothing excuses
    unasked: int = 0
    unasked_pixels: np.ndarray | None = None      # their flat indices (row 0 the top)
    provenance: dict = field(default_factory=dict)   # what was checked, by what
    # wrong pixels asked whether float32's rounding explains them, and how many it does
    # (``float32_evidence``; empty where the scene's wrong pixels do not look like that)
    float32: dict = field(default_factory=dict)
    boundary_note: str = ""      # many boundary pixels: the decision most of them sit at
    classes: np.ndarray | None = None        # (rows, columns) class index
    ours: np.ndarray | None = None
    theirs: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.status == "pass"

    def summary(self) -> dict:
        out = {k: v for k, v in dataclasses.asdict(self).items()
               if k not in ("classes", "ours", "theirs", "findings", "unasked_pixels")}
        out["findings"] = [f.as_dict() for f in self.findings]
        out["wrong_pixels"] = self.wrong_pixels()
        return out

    def wrong_pixels(self, limit: int | None = None) -> list:
        """The first ``limit`` (WRONG_LISTED) wrong pixels in image order (row 0 the top):
        column, row, the image's colour and rt_core's, and whether the oracle was asked
        about it (false: wrong because a sample of its kind held a wrong pixel; ``classify``)."""
        if self.classes is None:
            return []
        ys, xs = np.nonzero(self.classes == CLASSES.index("wrong"))
        n = WRONG_LISTED if limit is None else limit
        unasked = set() if self.unasked_pixels is None else set(self.unasked_pixels.tolist())
        W = self.classes.shape[1]
        return [{"column": int(x), "row": int(y), "theirs": self.theirs[y, x].tolist(),
                 "rtval": self.ours[y, x].tolist(),
                 "asked": int(y) * W + int(x) not in unasked} for y, x in zip(ys[:n], xs[:n])]


# --- rendering ----------------------------------------------------------------------------------

class Renderer:
    """rt_core f64 course images of one scene, cached per (rules, max_dist)."""

    def __init__(self, scene, columns: int, rows: int):
        from rt_core import backend
        from rt_core.camera import make_camera
        self.scene, self.T = scene, backend.types("f64")
        self.cameras = {r: make_camera(scene, columns, rows, rules=_rows(r))
                        for r in ("course", "shifted")}
        self.cam = self.cameras["course"]
        self.cache = {}             # (rules, max_dist) -> 8-bit image
        self.geometry = {}          # rules -> (ids, depth)
        self.unclamped = {}         # (rules, max_dist) -> the intensities, not clamped

    def image(self, rules, max_dist: float) -> np.ndarray:
        key = (rules, max_dist)
        if key not in self.cache:
            rgb = self._intensity(self.cameras[rules.rows], rules, max_dist)
            self.cache[key] = np.floor(255.0 * np.clip(rgb, 0.0, 1.0)).astype(np.uint8)
            self.unclamped[key] = rgb
        return self.cache[key]

    def centres(self, rules, max_dist: float) -> np.ndarray:
        """The 8-bit image sampled at the pixels' centres instead of the window's corners
        (a common deviation: ``hints``), under ``rules``."""
        from rt_core.camera import make_camera
        cam = make_camera(self.scene, self.cam.columns, self.cam.rows, "centers",
                          _rows(rules.rows))
        rgb = self._intensity(cam, rules, max_dist)
        return np.floor(255.0 * np.clip(rgb, 0.0, 1.0)).astype(np.uint8)

    def _intensity(self, cam, rules, max_dist: float) -> np.ndarray:
        """rt_core's float64 intensities (rows, columns, 3) of the camera's rays."""
        from rt_core.render import render_image
        imgs, _ = render_image(self.scene, cam, self.T, rules, geometry=False, shade=True,
                               max_dist=max_dist)
        return np.stack([imgs[c] for c in ("R", "G", "B")], -1)

    def ids(self, rules):
        """(object ids, depth) of the primary hits under ``rules`` (cached)."""
        if rules not in self.geometry:
            from rt_core.render import trace_geometry, to_images
            cam = self.cameras[rules.rows]
            g = to_images(trace_geometry(self.scene, cam, self.T, rules), cam)
            self.geometry[rules] = g["object.id"].astype(np.int64), g["depth.Z"]
        return self.geometry[rules]


def _rows(value: str):
    from rt_core.rules import Rules
    return Rules(rows=value)


def _apart(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per pixel, the most 8-bit levels any channel of a and b differ by."""
    return np.abs(a.astype(np.int16) - b.astype(np.int16)).max(-1)


def _differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pixels whose colours differ by more than one level in some channel."""
    return _apart(a, b) > 1


def _one_way(ours: np.ndarray, theirs: np.ndarray, one) -> tuple:
    """(up, down): how many of the one-level pixels ``one`` (a mask or flat indices) are a
    level brighter than rt_core's, and how many darker."""
    d = (theirs.astype(np.int16) - ours.astype(np.int16)).reshape(-1, 3)[np.ravel(one)]
    up = int((d.max(-1) == 1).sum())
    return up, len(d) - up


def _systematic(up: int, down: int, size: int) -> bool:
    """One-level differences over SYSTEMATIC of the image, nine in ten one way."""
    n = up + down
    return n > SYSTEMATIC * size and max(up, down) >= 0.9 * n


def _config(rules, max_dist, name, value):
    if name == "max_dist":
        return rules, float(value)
    return dataclasses.replace(rules, **{name: value}), max_dist


def _decisions(rules) -> tuple:
    """The rules a pixel's path, and so its decisions' margins, depend on: all but the
    edges, the screen clip and ties, whose variants differ from the notes only where a
    decision's value lies exactly at its threshold (a margin of 0: near under each of them),
    and the reflection's division, which moves no decision.  t_min and clipped spheres
    change paths far from any threshold (a review: a wall lit or shadowed, a hole through a
    sphere), and the tile rules move the tiles' borders."""
    return rules.rows, rules.t_min, rules.clip_spheres, rules.tile_add_first, \
        rules.tile_project


def _shading(rules) -> tuple:
    """The rules a pixel's intensity depends on away from the decisions: those of its path
    (``_decisions``) and the reflection's division."""
    return _decisions(rules) + (rules.reflect,)


def _near_where_differs(near, ours, theirs) -> bool:
    """Is every channel where ``ours`` and ``theirs`` differ near an 8-bit level (``near``,
    per channel)?  (A pixel with none differing: whether any is.)"""
    differs = [int(a) != int(b) for a, b in zip(ours, theirs)]
    if not any(differs):
        return any(near)
    return all(n for n, d in zip(near, differs) if d)


class Boundary:
    """Which pixels are ``boundary``: a decision of one of their rays within the float64
    shading oracle's bound (mitsuba_ref/shade_oracle.py), under the given rules.  The
    margins are properties of the rays' paths and the scene, which not every rule moves (the
    edges' or the clip's threshold is where it is for every variant), so they are computed
    once per pixel, cut-off and the rules a path depends on (``_decisions``), lazily; the
    intensity's closeness to an 8-bit level ('quant') once per pixel, cut-off and the rules
    it depends on (``_shading``)."""

    SAMPLE = 60              # above this many pixels, a sample decides the count
    THIN = 0.05              # boundary pixels lie on curves: a set of more than this
                             # fraction of the image is counted unexcused without asking

    def __init__(self, r: Renderer, max_dist: float, theirs: np.ndarray):
        self.r, self.max_dist = r, max_dist
        self.theirs = theirs.reshape(-1, 3).astype(np.int16)     # the image checked
        self.known = {}          # (_decisions(rules), max_dist, pixel) -> bool
        self.quant = {}          # (_shading(rules), max_dist, pixel) -> per channel, near
                                 # a level
        self.colours = {}        # (rules, max_dist, pixel) -> colours its decisions give
        self.paths = {}          # (rules, max_dist, pixel) -> the oracle's unflipped path
        # one fixed random order of the pixels: every sample takes the first ones in it, so
        # the samples of different variants share their pixels (and the oracle's work)
        n = r.cam.columns * r.cam.rows
        self.rank = np.random.default_rng(1).permutation(n)

    def _oracle(self, todo, rules, md: float) -> None:
        """The float64 shading oracle's flags of pixels ``todo`` under (rules, md) into the
        caches: a decision within its bound ('jump'), an intensity within its bound of an
        8-bit level ('quant')."""
        from mitsuba_ref.shade_oracle import flags, shade_pixels
        cam = self.r.cam
        orc = shade_pixels(self.r.scene, cam.columns, cam.rows, todo, cam.sampling, rules, md)
        f = flags(orc, "f64")
        for p, j, q, path in zip(todo, f["jump"], f["quant_rgb"], orc["paths"]):
            self.known.setdefault((_decisions(rules), md, p), bool(j))
            self.quant[(_shading(rules), md, p)] = tuple(bool(c) for c in q)
            self.paths[(rules, md, p)] = path       # (sides: its first path, not again)

    def of(self, pixels, rules, md: float | None = None) -> np.ndarray:
        """Which ``pixels`` have a decision within its float64 bound (under the cut-off
        ``md``, default the first one's)."""
        md = self.max_dist if md is None else md
        pixels = np.asarray(pixels, np.int64)
        key = _decisions(rules)
        todo = [int(p) for p in pixels if (key, md, int(p)) not in self.known]
        if todo:
            self._oracle(todo, rules, md)
        return np.array([self.known[(key, md, int(p))] for p in pixels], bool)

    def excuses(self, pixels, rules, md: float | None = None) -> np.ndarray:
        """Which ``pixels`` are boundary: a decision within its float64 bound (``of``) and
        the image's colour one those decisions give (``sides``)."""
        pixels = np.asarray(pixels, np.int64)
        ok = self.of(pixels, rules, md)
        if ok.any():
            ok[ok] = self.sides(pixels[ok], rules, self.max_dist if md is None else md)
        return ok

    def sides(self, pixels, rules, md: float) -> np.ndarray:
        """Which ``pixels`` have a colour (within a level) that their decisions within the
        float64 bound give taken either way, in some combination (the shading oracle's
        ``other_sides``); where those cannot all be enumerated, a search for the image's
        colour (``reaches``: found within its budget, or not excused).  rt_core's own colour
        is not one of them: a pixel a level off it is what any one-level bug gives (a pixel
        mapping one off, floor(256 I)), and a decision near its threshold does not excuse
        that unless taking it the other way gives the image's colour (a review: the off-by-one
        build passed a course scene of a plane in z = 0, every pixel at the clip's
        threshold, whose other side is black)."""
        from mitsuba_ref.shade_oracle import other_sides_of, reaches
        cam = self.r.cam
        ours = self.r.image(rules, md).reshape(-1, 3)
        pixels = np.asarray(pixels, np.int64).tolist()
        todo = [p for p in dict.fromkeys(pixels) if (rules, md, p) not in self.colours]
        if todo:
            got = other_sides_of(self.r.scene, cam.columns, cam.rows, todo, cam.sampling,
                                 rules, md, firsts=[self.paths.get((rules, md, p))
                                                    for p in todo])
            self.colours.update({(rules, md, p): g for p, g in zip(todo, got)})
        out = []
        for p in pixels:
            own = tuple(int(c) for c in ours[p])
            got = self.colours[(rules, md, p)]
            if got is None:
                key = (rules, md, p, "reach")
                if key not in self.colours:
                    self.colours[key] = reaches(
                        self.r.scene, cam.columns, cam.rows, p, (self.theirs[p],),
                        cam.sampling, rules, md, first=self.paths.get((rules, md, p)),
                        tol=1, exclude=(own,)) is True
                out.append(self.colours[key])
                continue
            out.append(any(np.abs(self.theirs[p] - np.array(c)).max() <= 1 for c in got
                           if tuple(c) != own))
        return np.array(out, bool)

    def float32_sides(self, pixels, rules, md: float) -> np.ndarray:
        """Which ``pixels`` a tracer computing in float may make: one level off where the
        intensity lies within float32's bound of an 8-bit level, or a colour (within a
        level) that the decisions within float32's rounding give taken either way,
        F32_U standing for float32's unit roundoff (a pixel whose sides cannot all be
        enumerated is not explained).  For a hint, never the verdict."""
        from mitsuba_ref.shade_oracle import K_DECISION, flags, other_sides_of, shade_pixels
        cam = self.r.cam
        pixels = np.asarray(pixels, np.int64)
        orc = shade_pixels(self.r.scene, cam.columns, cam.rows, pixels, cam.sampling, rules,
                           md)
        quant = flags(orc, "f32", u=F32_U)["quant_rgb"]
        ours = self.r.image(rules, md).reshape(-1, 3).astype(np.int16)
        pixels = pixels.tolist()
        level = [np.abs(self.theirs[p] - ours[p]).max() == 1 and
                 _near_where_differs(quant[k], ours[p], self.theirs[p])
                 for k, p in enumerate(pixels)]
        ask = [p for p, lv in zip(pixels, level) if not lv]
        sides = dict(zip(ask, other_sides_of(self.r.scene, cam.columns, cam.rows, ask,
                                             cam.sampling, rules, md,
                                             limit=K_DECISION * F32_U)))
        # (where the sides cannot all be enumerated, not explained: a hint that may send a
        # student after the wrong cause had better say nothing.  The unflipped path's own
        # colour, rt_core's, counts only as ``level`` does, where its intensity is near a
        # level: within a level of it is what any one-level bug gives, floor(256 I) say)
        return np.array([lv or (sides[p] is not None and any(
            np.abs(self.theirs[p] - np.array(c)).max() <= 1 for c in sides[p]
            if tuple(c) != tuple(ours[p].tolist())))
            for p, lv in zip(pixels, level)], bool)

    def levels(self, pixels, rules, md: float) -> tuple:
        """(jump, quant) of ``pixels`` under exactly (rules, md): a decision within its bound,
        and an intensity within its bound of an 8-bit level in every channel where the image
        differs from rt_core's render (where a tracer's rounding may put the pixel on either
        side of the level; a channel near its level excuses no other)."""
        pixels = [int(p) for p in np.asarray(pixels, np.int64)]
        key = _shading(rules)
        todo = [p for p in pixels if (key, md, p) not in self.quant]
        if todo:
            self._oracle(todo, rules, md)
        ours = self.r.image(rules, md).reshape(-1, 3)
        return (np.array([self.known[(_decisions(rules), md, p)] for p in pixels], bool),
                np.array([_near_where_differs(self.quant[(key, md, p)], ours[p],
                                              self.theirs[p]) for p in pixels], bool))

    def sample(self, pixels, size: int | None = None) -> np.ndarray:
        """The first ``size`` (SAMPLE) of ``pixels`` in the fixed random order (all if
        fewer)."""
        size = self.SAMPLE if size is None else size
        pixels = np.asarray(pixels, np.int64)
        return pixels if len(pixels) <= size else \
            pixels[np.argsort(self.rank[pixels])[:size]]

    def unexcused(self, mask: np.ndarray, rules, md: float | None = None) -> float:
        """How many differing pixels are not boundary (estimated from a fixed sample when
        there are more than SAMPLE)."""
        px = np.flatnonzero(mask.ravel())
        if len(px) > self.THIN * mask.size:
            return float(len(px))
        if len(px) > self.SAMPLE:
            return len(px) * (1.0 - self.excuses(self.sample(px), rules, md).mean())
        return float(len(px) - self.excuses(px, rules, md).sum())


# the share of the pixels a variant's render changes that the image must take its colour at
# for the variant to be named (``infer``)
CONSISTENT = 0.5
# one-level differences in more than this share of the image, nine in ten one way, are
# systematic (a tracer that rounds, say): a decision near its threshold excuses them only
# where the colour is another variant's (``classify``)
SYSTEMATIC = 0.05
# and on every object where its render differs, the share of pixels the image must have the
# variant's colour at (within a level)
OBJECT_SHARE = 0.9
# the level-offset hint needs one-level pixels to be this share of the wrong ones at least,
# and names a quantization (rounding, 256) that makes this share of them
LEVEL_SHARE = 0.75
LEVEL_FIT = 0.9
# one-level pixels the inference asks the oracle about per candidate (evidence, not the
# verdict: classify asks a sample of Boundary.SAMPLE, then all of them if need be)
LEVEL_SAMPLE = 12


def infer(r: Renderer, theirs: np.ndarray, start_rules, start_max_dist: float, fixed=()):
    """Coordinate descent over DIMENSIONS from the notes' rules: (rules, max_dist, findings,
    Boundary).  A value replaces the current one when it leaves fewer differing pixels that
    are not ``boundary``: a variant that only explains pixels either answer of which is
    defensible is not named (a correct float64 tracer rounds those either way), unless the
    image follows it systematically (it removes 95% of the differing pixels, and they are 5%
    of the image: rounding flips some pixels of a region, not all), and the image takes the
    value's colour at most pixels where the value's render differs (``CONSISTENT``).  Two
    values are compared on the pixels where they differ only (the oracle's work stays
    small)."""
    kinds = set(r.scene.kinds())
    specular = any(any(o.material.specular) for o in r.scene.objects)
    dims = [(n, v) for n, v, relevant in DIMENSIONS if n not in fixed and (
        specular if relevant in (None, "specular") else relevant(kinds)) and
        _can_matter(r, n)]
    rules, md = start_rules, start_max_dist
    bnd = Boundary(r, md, theirs)
    total = r.cam.columns * r.cam.rows
    masks = {}

    def diff(cfg):
        """The pixels that differ under config ``cfg`` by more than one level, or by one
        where the intensity is not within its float64 bound of an 8-bit level (kept).  (An
        image that differs by more than one level in over THIN of the pixels is judged on
        those: its one-level pixels would cost the oracle's work and decide nothing.)"""
        if cfg not in masks:
            lv = _apart(r.image(*cfg), theirs)
            m = lv > 1
            one = np.flatnonzero(lv.ravel() == 1)
            if len(one) and m.sum() > bnd.THIN * lv.size:
                if len(one) > SYSTEMATIC * lv.size:     # far off anyway: counted unasked
                    m |= lv == 1
            elif len(one):
                # the oracle on a fixed sample of LEVEL_SAMPLE of them (its work bounded:
                # deep mirror paths cost it 0.1-0.3 s a pixel, and every candidate value is
                # asked about); more than SYSTEMATIC with one in the sample that neither a
                # level nor a decision explains: all of them count
                pick = bnd.sample(one, LEVEL_SAMPLE)
                jump, quant = bnd.levels(pick, *cfg)
                if len(one) > SYSTEMATIC * lv.size and not (jump | quant).all():
                    m |= lv == 1
                else:
                    m.ravel()[pick[~quant]] = True
            masks[cfg] = m
        return masks[cfg]

    def delta(a, b) -> float:
        """Unexcused differing pixels of config a minus those of config b."""
        da, db = diff(a), diff(b)
        return bnd.unexcused(da & ~db, *a) - bnd.unexcused(db & ~da, *b)

    def notes_value(name):
        return DEFAULT_MAX_DIST if name == "max_dist" else \
            next(v for n, v, _ in DIMENSIONS if n == name)[0]

    def consistent(name, cfg) -> bool:
        """Does the image follow rule ``name``'s value in config ``cfg``?  Where cfg's render
        differs from the render with the notes' value of that rule (the rest as in cfg), the
        image must, at CONSISTENT of those pixels or more, have cfg's colour, or be within
        one level of it and more than one from the other's (a second bug that adds a level
        keeps a deviation named).  An image wrong for another reason (upside down, t not a
        distance) matches a variant's render by chance at a few of them, which a pixel
        count alone would take for the variant."""
        alt = _config(*cfg, name, notes_value(name))
        a, b = r.image(*cfg), r.image(*alt)
        changed = (a != b).any(-1)
        la, lb = _apart(a, theirs), _apart(b, theirs)
        agree = changed & ((la == 0) | ((la <= 1) & (lb > 1)))
        if agree.sum() < CONSISTENT * changed.sum():
            return False
        # and so where the two renders are 2 levels apart or more, which a one-level bug on
        # the other's colours cannot match (it gives la >= 1 and lb <= 1 there): a tracer
        # flooring 256 I took the shifted rows' colour at half the pixels the rows variant
        # changes, on gradients where a row's move adds a level too (a helper's review)
        far = changed & (_apart(a, b) >= 2)
        if (agree & far).sum() < CONSISTENT * far.sum():
            return False
        # and on the objects it changes, the image has cfg's colours nearly everywhere
        # (OBJECT_SHARE): a tracer that swaps a tiled plane's colours took the tile offset
        # variant's colour at every pixel that variant changes (shifted by 2/3 of a tile),
        # and one saturated white everywhere took a variant's where it saturates too, each
        # wrong on the rest of the same objects
        ids_a, ids_b = r.ids(cfg[0])[0], r.ids(alt[0])[0]
        objs = np.setdiff1d(np.union1d(ids_a[changed], ids_b[changed]), [-1])
        region = changed | np.isin(ids_a, objs)
        return (la[region] <= 1).sum() >= OBJECT_SHARE * region.sum()

    def better(v, cur) -> bool:
        d = delta(v, cur)
        if d > 0:
            return False
        if d < 0:
            return True
        n0, n1 = int(diff(cur).sum()), int(diff(v).sum())
        return n0 >= 0.05 * total and n1 <= 0.05 * n0

    if ("max_dist", MAX_DISTS) in dims:
        # the cut-off changes a pixel only where a path's length crosses it: if the
        # extremes agree, every value does
        lo, hi = (rules, min(MAX_DISTS)), (rules, max(MAX_DISTS))
        if np.array_equal(r.image(*lo), r.image(*hi)):
            dims.remove(("max_dist", MAX_DISTS))
    def descend(rules, md, dims):
        for _ in range(3):
            changed = False
            for name, values in dims:
                for v in values:       # the notes' value first: a tie keeps what is there
                    cur = (rules, md)
                    cand = _config(rules, md, name, v)
                    if v != _value(rules, md, name) and better(cand, cur):
                        rules, md = cand
                        changed = True
            if not changed:
                break
        return rules, md

    rules, md = descend(rules, md, dims)
    # the veto: a value the image does not follow goes back to the notes' and the others are
    # looked for again without it (it may have steered them), once; a second veto only
    # resets
    unfollowed = set()
    for again in (True, False):
        vetoed = [(n, v) for n, v in dims if _value(rules, md, n) != notes_value(n)
                  and not consistent(n, (rules, md))]
        if not vetoed:
            break
        for n, _ in vetoed:
            rules, md = _config(rules, md, n, notes_value(n))
            unfollowed.add(n)
        dims = [d for d in dims if d not in vetoed]
        if again:
            rules, md = descend(rules, md, dims)
    findings = []
    for name, values, _ in DIMENSIONS:
        notes = values[0] if name != "max_dist" else None
        here = _value(rules, md, name)
        if (name, values) not in dims:
            findings.append(RuleFinding(name, here, False, 0, notes, name in unfollowed))
            continue
        alts = [_config(rules, md, name, v) for v in values if v != here]
        extra = min(delta(c, (rules, md)) for c in alts) if alts else 0
        if extra <= 0 and here != values[0] and alts:
            # taken because the image follows it systematically
            extra = min(int(diff(c).sum()) for c in alts) - int(diff((rules, md)).sum())
        extra = int(round(extra))
        findings.append(RuleFinding(name, here, extra > 0, max(extra, 0), notes))
    return rules, md, findings, bnd


def _tile_quotients(o) -> list:
    """OFF/w and OFF/h of a tiled plane, exactly (Fractions)."""
    from fractions import Fraction
    from rt_core.scene import exact
    from rt_core.shading import TILE_OFF
    return [Fraction(TILE_OFF) / exact(c) for c in o.size]


def _alike(scene, rule: str, value) -> str:
    """What else gives a deviation's image on this scene, in words ('' for nothing known).
    Adding the tile offset first shifts each parity by OFF/w (and OFF/h): where every tiled
    plane's are integers it only exchanges the two colours, which a tracer swapping the
    foreground and background materials does too (a review: that bug was named this
    deviation)."""
    if (rule, value) == ("tile_add_first", True) and all(
            q.denominator == 1 for o in scene.objects if o.kind == "tplane"
            for q in _tile_quotients(o)):
        return ("; with these tile sizes that only exchanges the tiles' two colours, as "
                "swapping the foreground and background materials would")
    return ""


def _can_matter(r: Renderer, name: str) -> bool:
    """Whether a rule's variants can change this scene's image at all, decided on the host
    (so that no render is spent on a rule the scene cannot tell apart)."""
    sc = r.scene
    V = sc.viewpoint
    if name == "ties":
        # exact ties need two objects on one plane (or one sphere twice); others tie only
        # on measure-zero curves, which the other rules' renders show anyway
        from rt_core.tracer import scene_constants
        grp = [c.grp for c in scene_constants(sc)]
        return len(set(grp)) < len(grp)
    if name == "t_min":
        # a hit within 1e-4 of a ray's origin: a plane that close to the viewpoint, or any
        # secondary ray (shadow rays start on surfaces, which planes may pass near)
        if sc.lights or any(any(o.material.specular) for o in sc.objects):
            return True
        for o in sc.objects:
            if o.kind in PLANE_KINDS:
                n = o.normal
                q = tuple(p - v for p, v in zip(o.point, V))
                if abs(sum(a * b for a, b in zip(n, q))) < 1e-4 * (1 + 1e-9):
                    return True
        return False
    if name == "tile_add_first":
        # floor((OFF + u)/w) = OFF/w + floor(u/w) where OFF/w is an integer, and of the same
        # parity as floor(OFF + u/w) where it is even (and OFF/h): the two differ then only
        # by rounding at tile borders, which a whole row or column can share, and a correct
        # tracer's borders were named this deviation (tiles 1 x 1, 0.5 x 1; a review)
        even = lambda q: q.denominator == 1 and q.numerator % 2 == 0      # noqa: E731
        return any(not all(map(even, _tile_quotients(o)))
                   for o in sc.objects if o.kind == "tplane")
    if name == "clip_spheres":
        # a sphere reaching z >= 0, where the clip cuts (shapes.clip_ok: z > 0 literally,
        # as the C programs do, whichever side the viewpoint is on: a viewpoint at
        # z = -1.1 looking at spheres at z = 4 sees every one of them clipped)
        return any(o.kind == "sphere" and o.center[2] + o.radius >= 0
                   or o.kind in ("cylinder", "cone", "ellipsoid")   # (not bounded here)
                   for o in sc.objects)
    return True


def _value(rules, md, name):
    return md if name == "max_dist" else getattr(rules, name)


# --- one scene ------------------------------------------------------------------------------------

def check_image(scene_path: str, image_path: str, *, columns: int | None = None,
                rows: int | None = None, rules=None, max_dist: float | None = None,
                hits_path=None, theirs: np.ndarray | None = None,
                scene=None, texture_dirs=(), maxval: int | None = None,
                code27: str = "auto") -> SceneCheck:
    """Check one image of one scene.  ``rules``/``max_dist`` given: no inference of those.
    ``theirs``, ``scene``: the image and the parsed scene with its textures, already read
    (``check_run`` on a Dask worker, which need not see the files); ``texture_dirs``: where
    a textured scene's PPMs are looked for first (rt_core/textures.py); ``hits_path``: a hit dump's path, or what
    ``read_hits`` made of it (arrays, or the exception it raised)."""
    from rt_core.imageio import ImageError, pnm_maxval, read_image
    from rt_core.memory import check_bytes, guard
    from tools.harness.agree import parse_agreed
    from rt_core.usererror import InputError
    from rt_core.rules import Rules
    from rt_core.scene import SceneError
    t0 = time.perf_counter()
    res = SceneCheck(str(scene_path), str(image_path) if image_path else None, "error")
    try:
        scene = scene if scene is not None else parse_agreed(scene_path, code27)
    except SceneError as exc:
        res.status, res.reason = "refused", _not_a_scene(scene_path) or str(exc)
        return res
    except OSError as exc:
        res.reason = f"{scene_path}: {(exc.strerror or str(exc)).lower()}"
        return res
    why = _textures_missing(scene, texture_dirs)
    if isinstance(why, str):
        res.reason = why
        return res
    scene = why
    try:
        img = theirs if theirs is not None else read_image(image_path)
    except ImageError as exc:
        res.reason = str(exc)
        return res
    if theirs is None:
        maxval = pnm_maxval(image_path)
    H, W = img.shape[:2]
    if columns and rows is None:
        # the rows a tracer given only the columns writes (a student's review: --columns 10
        # on a 64x48 image said 'expected 10x48')
        try:
            rows = scene.default_rows(columns)
        except SceneError as exc:
            res.status, res.reason = "refused", str(exc)
            return res
    W, H = columns or W, rows or H
    if (H, W) != img.shape[:2]:
        h, w = img.shape[:2]
        why = ("; its width and height swapped?" if (w, h) == (H, W) else
               f"; the course's rows for {W} columns are int(h/w·columns) = {H}"
               if w == W and H == scene.default_rows(W) else "")
        res.reason = (f"{image_path}: the image is {w}x{h}, expected {W}x{H} "
                      f"(--columns/--rows){why}")
        return res
    if W < 2 or H < 2:
        res.reason = f"{image_path}: {W}x{H} is too small for the course's corner sampling"
        return res
    try:
        guard(check_bytes, "check of", W, H, "(render your image smaller)")
    except InputError as exc:
        res.reason = f"{image_path}: {exc}"
        return res
    res.columns, res.rows, res.theirs = W, H, img
    res.provenance = provenance(scene, img)
    r = Renderer(scene, W, H)
    notes = Rules()
    fixed = ()
    if rules is not None:
        fixed += tuple(n for n, _, _ in DIMENSIONS if n != "max_dist")
    if max_dist is not None:
        fixed += ("max_dist",)
    final_rules, md, res.findings, bnd = infer(
        r, img, rules or notes, DEFAULT_MAX_DIST if max_dist is None else max_dist, fixed)
    res.rules, res.max_dist = final_rules.describe(), md
    ours = r.image(final_rules, md)
    res.ours = ours
    res.classes, res.variant_counts, unasked = classify(r, img, final_rules, md, notes, bnd)
    res.unasked, res.unasked_pixels = len(unasked), unasked
    res.counts = {c: int((res.classes == i).sum()) for i, c in enumerate(CLASSES)}
    res.deviations = [WORDS[(f.rule, f.value)] + _alike(scene, f.rule, f.value)
                      for f in res.findings if (f.rule, f.value) in WORDS and f.determined]
    if hits_path:
        try:
            res.hits = check_hits(r, final_rules, hits_path)
        except (OSError, ValueError, InputError) as exc:
            res.status = "error"
            res.reason = str(exc) if isinstance(exc, (ValueError, InputError)) else \
                f"{exc.filename or hits_path}: {(exc.strerror or str(exc)).lower()}"
            return res
    wrong = res.classes == CLASSES.index("wrong")
    res.status = "pass" if not wrong.any() and not res.hits.get("wrong") else "fail"
    res.boundary_note = boundary_note(scene, bnd, res.classes == CLASSES.index("boundary"),
                                      final_rules, md)
    res.hints += hit_hints(scene, res.hits)
    if wrong.any():
        res.worst = worst_region(wrong)
        ids, _ = r.ids(final_rules)
        on = ids[wrong]
        objs = [(int(k), int(n)) for k, n in zip(*np.unique(on, return_counts=True))]
        objs.sort(key=lambda kn: -kn[1])
        res.worst["objects"] = [_describe(scene, k, n) for k, n in objs[:3]]
        res.worst.update(_example(ours, img, wrong, res.worst["middle"]))
        res.hints = hints(ids, wrong, ours, img, r.unclamped[(final_rules, md)],
                          bool(scene.lights)) + res.hints
        res.hints = _centres(ours, r.centres(final_rules, md), img) + res.hints
        if rules is not None:
            res.hints += _variant_given_away(r, img, ours, final_rules, md, max_dist)
        if columns is None and rows is None:
            res.hints += _swapped(scene, W, H)
        # an image upside down or with channels exchanged may still have a rule variant
        # inferred that explains some of its pixels (a near-symmetric scene): asked against
        # the notes' image too
        base = r.image(notes, DEFAULT_MAX_DIST)
        if (base != ours).any():
            res.hints = _orientation(base, img) + _channels(base, img) + res.hints
        res.float32 = float32_evidence(bnd, wrong, res.worst, final_rules, md)
        n, k = res.float32.get("asked", 0), res.float32.get("explained", 0)
        specks = any(SPECKS in h for h in res.hints)
        if n >= F32_MIN and k == n and not specks:
            res.hints.append(
                (f"all {n} wrong pixels" if n == res.worst["pixels"] else
                 f"the {n} wrong pixels asked (of {res.worst['pixels']}) all")
                + " lie within float32's rounding of a decision (a shadow's blocker, a tile "
                "border, an edge) and have the colour its other side gives: does your tracer "
                "compute in float? (the course's programs use double)")
        if maxval not in (None, 255):
            res.hints.insert(0, f"the image's maxval is {maxval}, the course writes 255: "
                             "its samples were scaled to 8 bits rounding to nearest, so a "
                             "level either way may come from that; write maxval 255")
    res.seconds = round(time.perf_counter() - t0, 3)
    return res


def boundary_note(scene, bnd: Boundary, boundary: np.ndarray, rules, md: float) -> str:
    """Where the boundary pixels are many (BOUNDARY_NOTE of the image, 20 at least), the
    decision most of them sit at, in words: a scene whose decision lies on its threshold
    over a region (a plane in the window plane z = 0, a light in a plane) checks nothing
    there, and the user should know."""
    n = int(boundary.sum())
    if n < max(20, BOUNDARY_NOTE * boundary.size):
        return ""
    count: dict = {}
    for p in np.flatnonzero(boundary.ravel()).tolist():
        path = bnd.paths.get((rules, md, p))
        for key in set(path[1]) if path else ():
            count[key] = count.get(key, 0) + 1
    head = f"{n} pixels ({100.0 * n / boundary.size:.0f}% of the image)"
    if not count:
        return head
    key, k = max(count.items(), key=lambda kv: (kv[1], kv[0]))
    return (f"{head}; {k} of them at {_decision_words(scene, key)}: within float64's rounding "
            "of its threshold there, so either side is right and the scene checks nothing at "
            "those pixels")


def _decision_words(scene, key) -> str:
    """A choice point of shade_oracle (``_Alt``'s key: bounce, what, which) in words."""
    b, what, which = key
    ray = "the primary ray" if b == 0 else f"the reflection ray of bounce {b}"
    if what == "geo":
        o = scene.objects[which]
        return f"whether {ray} hits object {which} ({o.kind}, line {o.line})"
    if what in ("shadow", "spot"):
        light = scene.lights[which]
        test = "shadow test" if what == "shadow" else "spotlight cone"
        hit = "the primary hit" if b == 0 else f"the hit of bounce {b}"
        return f"the {test} of {hit} toward light {which} (line {light.line})"
    if what == "maxdist":
        return "the reflection cut-off (the path length against MAX_DIST" + \
            (f" after bounce {b})" if b else ")")
    return f"a {what} border ({'u' if which == 0 else 'v'}" + \
        (f", bounce {b})" if b else ")")


def float32_evidence(bnd: Boundary, wrong: np.ndarray, worst: dict, rules, md: float) -> dict:
    """{asked, explained}: how many of a sample of the wrong pixels float32's rounding
    explains (``Boundary.float32_sides``); empty where the wrong pixels are not few and
    scattered (F32_SHARE, F32_GROUP), as a float tracer leaves them."""
    if worst["pixels"] > F32_SHARE * wrong.size or worst["largest_group"] > F32_GROUP:
        return {}
    pick = bnd.sample(np.flatnonzero(wrong.ravel()), F32_SAMPLE)
    return {"asked": int(len(pick)),
            "explained": int(bnd.float32_sides(pick, rules, md).sum())}


# the first bytes of the image files a scene's place may be given by mistake
_IMAGE_MAGIC = ((re.compile(rb"P[1-6]\s"), "a PPM/PGM/PBM image"),
                (re.compile(rb"\x89PNG"), "a PNG image"),
                (re.compile(rb"v/1\x01"), "an EXR image"))


def _not_a_scene(path) -> str | None:
    """Why a file that is no scene was given as one, where its first bytes are an image's:
    the arguments in the wrong order (IMAGE SCENE)."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return None
    for magic, what in _IMAGE_MAGIC:
        if magic.match(head):
            return (f"{path}: {what}, not a scene file: the scene comes first (SCENE IMAGE), "
                    "and --run and --images take scenes only")
    return None


def _textures_missing(scene, dirs):
    """The scene with its textures loaded, or why they cannot be (one line): without its
    textures rtval's image of a textured scene is not the course's, so there is nothing to
    check against (an error, not the user's fault: --texture-dir)."""
    from rt_core.imageio import ImageError
    from rt_core.scene import SceneError
    from rt_core.textures import attach
    try:
        return attach(scene, dirs)
    except (SceneError, ImageError) as exc:
        return f"{exc}; rtval needs the textures to know the course image"


def provenance(scene, img: np.ndarray) -> dict:
    """The scene's and the image's sha256, the reference (rt_core float64, exact decisions,
    corner sampling) and the versions that made the verdict."""
    import hashlib
    from rt_core.render import extras_text, versions
    from rt_core.textures import provenance_text
    return {"scene_sha256": scene.sha256, "dialect": scene.dialect,
            "textures": provenance_text(scene),
            "image_sha256": hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest(),
            "reference": "rt_core float64, exact decisions, corner sampling",
            "boundary": "mitsuba_ref.shade_oracle float64 margins < 64 u, in a colour "
                        "other_sides gives",
            "stand_ins": scene.stand_ins(), "extras": extras_text(scene),
            "versions": versions()}


def hints(ids: np.ndarray, wrong: np.ndarray, ours=None, theirs=None, intensity=None,
          lit: bool = True) -> list:
    """Plain-words guesses about what the wrong pixels look like (not part of the verdict):
    outlines only; the image as rt_core's upside down or mirrored; a one-level offset all
    one way; shadow specks (``lit``: the scene has a light); two colour channels swapped;
    intensities above 1 wrapped around (``intensity``: rt_core's, not clamped)."""
    out = []
    if ours is not None:
        out += _grey(ours, theirs) + _orientation(ours, theirs) + \
            _level_offset(ours, theirs, wrong, intensity) + \
            (_speckles(wrong, ours, theirs) if lit else []) + _channels(ours, theirs)
        if intensity is not None:
            out += _wrapped(intensity, theirs, wrong)
    edge = np.zeros_like(wrong)
    edge[:, 1:] |= ids[:, 1:] != ids[:, :-1]
    edge[:, :-1] |= ids[:, 1:] != ids[:, :-1]
    edge[1:] |= ids[1:] != ids[:-1]
    edge[:-1] |= ids[1:] != ids[:-1]
    on_edge = (wrong & edge).sum()
    if wrong.sum() >= 20 and on_edge >= 0.9 * wrong.sum() and on_edge >= 0.3 * edge.sum():
        out.append("the wrong pixels lie on object outlines, along most of them: antialiased "
                   "or jittered samples? (a pixel-exact comparison needs one sample per "
                   "pixel at the course's grid corners)")
    return out


def _example(ours: np.ndarray, theirs: np.ndarray, wrong: np.ndarray, middle) -> dict:
    """A wrong pixel to look at (the largest group's middle: row, column), its colour in
    the image and in rt_core's, and how many wrong pixels are darker or brighter (the sum
    of the three samples) than rt_core's."""
    y, x = middle
    a = theirs.astype(np.int32).sum(-1)[wrong]
    b = ours.astype(np.int32).sum(-1)[wrong]
    # (keys as wrong_pixels' rows: the image's colour "theirs", rt_core's "rtval")
    return {"example": {"column": int(x), "row": int(y), "theirs": theirs[y, x].tolist(),
                        "rtval": ours[y, x].tolist()},
            "darker": int((a < b).sum()), "brighter": int((a > b).sum())}


def _swapped(scene, W: int, H: int) -> list:
    """An image WxH whose rows are not the course's for W columns, where H columns would
    give W rows: the header's width and height written the other way round (a student's
    review: checked alone, such an image was only wrong; --run's size check names it)."""
    from rt_core.scene import SceneError
    try:
        if H == scene.default_rows(W) or scene.default_rows(H) != W:
            return []
    except SceneError:
        return []
    return [f"the image is {W}x{H}, but {W} columns of this window make "
            f"{scene.default_rows(W)} rows, and {H} columns make {W}: width and height "
            "written the other way round in the header?"]


def _far_better(other: np.ndarray, theirs: np.ndarray, straight: int):
    """(pixels ``theirs`` differs from ``other`` by, ``straight``) where it matches
    ``other`` far better than rt_core's own image, from which it differs at ``straight``
    pixels: at 5% of the image at most and a fifth of ``straight``; else None."""
    n = int(_differs(other, theirs).sum())
    if straight and n <= 0.05 * other[..., 0].size and n <= 0.2 * straight:
        return n, straight
    return None


def _centres(ours: np.ndarray, centred: np.ndarray, theirs: np.ndarray) -> list:
    """The image matches rt_core's sampled at the pixels' centres far better than at the
    window's corners (as _orientation: a student's review found it the most common
    deviation, with no hint)."""
    got = _far_better(centred, theirs, int(_differs(ours, theirs).sum()))
    if got:
        return [f"your image is rt_core's sampled at the pixels' centres ({got[0]} pixels "
                f"differ that way, {got[1]} as it is): x = (c + 0.5)/W across the window? "
                "the course samples its corners, x = c/(W - 1) of its width, and likewise "
                "the rows"]
    return []


def _variant_given_away(r, theirs, ours, rules, max_dist, given_max_dist) -> list:
    """With --rules given, the rules inferred as without them, where the image follows
    them far better: a course variant the given rules fail (a student's review: with
    rows=course the row bug failed with no word that rows=shifted explains it)."""
    from rt_core.rules import Rules
    md0 = DEFAULT_MAX_DIST if given_max_dist is None else given_max_dist
    alt, md, found, _ = infer(r, theirs, Rules(), md0,
                              ("max_dist",) if given_max_dist is not None else ())
    if (alt, md) == (rules, max_dist):
        return []
    straight = int(_differs(ours, theirs).sum())
    n = int(_differs(r.image(alt, md), theirs).sum())
    if n > 0.2 * straight:
        return []
    words = [WORDS[(f.rule, f.value)] for f in found if (f.rule, f.value) in WORDS and
             f.determined]
    said = "; ".join(words) if words else f"rules {alt.describe()}, max_dist={md:g}"
    return [f"the image follows a course variant the rules given do not ({n} pixels differ "
            f"under it, {straight} under --rules): {said}"]


def _orientation(ours: np.ndarray, theirs: np.ndarray) -> list:
    """The image matches rt_core's flipped (upside down, left to right, or both) far better
    than rt_core's as it is."""
    straight = int(_differs(ours, theirs).sum())
    rev, keep = slice(None, None, -1), slice(None)
    words = [((rev, keep), "upside down: rows written bottom first? (the image's first row "
              "is the top one, y = H - 1)"),
             ((keep, rev), "mirrored left to right: columns written right to left? "
              "(column 0 is x = -w/2)"),
             ((rev, rev), "turned by 180 degrees: rows and columns both written in "
              "reverse?")]
    for flip, what in words:
        got = _far_better(ours[flip], theirs, straight)
        if got:
            return [f"your image is rt_core's {what} ({got[0]} pixels differ that way, "
                    f"{got[1]} as it is)"]
    return []


def _grey(ours: np.ndarray, theirs: np.ndarray) -> list:
    """The image is grey (R = G = B at every pixel) where rt_core's has colour: a P5 or P2
    file (one sample a pixel, read as grey), or one sample written for three (a student's
    review: a P5 image failed with no word of it)."""
    coloured = int(((ours[..., 0] != ours[..., 1]) | (ours[..., 1] != ours[..., 2])).sum())
    if coloured < max(20, 0.01 * ours[..., 0].size) or \
            (theirs[..., 0] != theirs[..., 1]).any() or (theirs[..., 1] != theirs[..., 2]).any():
        return []
    return [f"your image is grey (R = G = B at every pixel) where rt_core's has colour at "
            f"{coloured} pixels: written as a P5 or P2 (grey) file, one sample a pixel? the "
            "course writes P6 (or P3), three samples a pixel"]


def _channels(ours: np.ndarray, theirs: np.ndarray) -> list:
    """The image matches rt_core's with two colour channels exchanged far better than as it
    is (the light's or the material's red and blue read in the other order, say)."""
    straight = int(_differs(ours, theirs).sum())
    names = "red", "green", "blue"
    for a, b in ((0, 2), (0, 1), (1, 2)):
        perm = [0, 1, 2]
        perm[a], perm[b] = b, a
        got = _far_better(ours[..., perm], theirs, straight)
        if got:
            return [f"your image is rt_core's with {names[a]} and {names[b]} exchanged "
                    f"({got[0]} pixels differ that way, {got[1]} as it is): a colour read or "
                    "written in the wrong order (the scene's triples are r g b)?"]
    return []


def _wrapped(intensity: np.ndarray, theirs: np.ndarray, wrong: np.ndarray) -> list:
    """Wrong pixels where the image holds floor(255 I) modulo 256: intensities above 1
    converted to a byte without the clamp, so they wrap around to dark."""
    n = int(wrong.sum())
    if n < 20:
        return []
    with np.errstate(invalid="ignore", over="ignore"):
        wrapped = np.mod(np.floor(255.0 * np.maximum(intensity, 0.0)), 256.0)
    over = (intensity > 1).any(-1) & wrong
    same = over & (wrapped == theirs).all(-1)
    if same.sum() < 0.8 * n:
        return []
    return [f"{int(same.sum())} wrong pixels hold floor(255 I) modulo 256 where I is above 1: "
            "the intensity converted to a byte without clamping it to [0, 1] first (the "
            "notes clamp, then floor)"]


def _speckles(wrong: np.ndarray, ours: np.ndarray, theirs: np.ndarray) -> list:
    """Wrong pixels nearly all darker than rt_core's and scattered one or two at a time
    (measured on the C builds: self-shadowing gives groups of median size 1, 45-69 of them;
    missing shadows, 1/d², the aliased transform: 1-12 groups, median 3.5 and up, or one
    region holding most of them)."""
    darker = (theirs <= ours).all(-1) & (theirs < ours).any(-1)
    n = int(wrong.sum())
    if n < 20 or (darker & wrong).sum() < 0.9 * n:
        return []
    sizes = [len(g) for g in _groups(wrong)]
    # (and no region holding most of them: 1/d² on a spotlight scene left 21 groups of
    # median size 2, one of them 517 of its 759 pixels; self-shadowing's largest: 37%)
    if len(sizes) < 10 or np.median(sizes) > 2 or max(sizes) > 0.5 * n:
        return []
    return [f"{n} wrong pixels darker than rt_core's, scattered in {len(sizes)} specks: "
            f"{SPECKS} they start on (rounding puts it at a tiny "
            "t > 0)? the notes test only the other objects"]


def _level_offset(ours: np.ndarray, theirs: np.ndarray, wrong: np.ndarray,
                  intensity=None) -> list:
    """Wrong one-level differences in more than SYSTEMATIC of the image, nearly all one
    way, and most of the wrong pixels (LEVEL_SHARE): a tracer wrong by more (its pixels
    mapped one off, say) has one-level pixels too, on gradients, which no rounding made.
    A quantization that makes nearly all the wrong pixels from rt_core's intensity
    (``intensity``, unclamped) is named; the others are only guessed at."""
    up, down = _one_way(ours, theirs, (_apart(ours, theirs) == 1) & wrong)
    if not _systematic(up, down, wrong.size) or up + down < LEVEL_SHARE * wrong.sum():
        return []
    if intensity is not None:
        I = np.clip(np.nan_to_num(intensity, nan=0.0), 0.0, 1.0)
        for words, img in (("rounded, floor(255 I + 0.5)", np.floor(255.0 * I + 0.5)),
                           ("floor(256 I) (a scale of 256, at most 255)",
                            np.minimum(np.floor(256.0 * I), 255.0))):
            fit = int(((img == theirs).all(-1) & wrong).sum())
            if fit >= LEVEL_FIT * wrong.sum():
                return [f"{fit} of the {int(wrong.sum())} wrong pixels are one level "
                        f"brighter than floor(255 I), as rt_core's intensity {words} makes "
                        "them: the notes floor 255 I"]
    if up > down:
        return [f"{up} pixels are one level brighter than floor(255 I) and {down} darker, "
                "and neither rounding (floor(255 I + 0.5)) nor floor(256 I) makes most of "
                "them: a level added to the colours?"]
    return [f"{down} pixels are one level darker than floor(255 I) and {up} brighter: "
            "a scale below 255, or an intensity made a little smaller (float instead of "
            "double)?"]


def _describe(scene, k: int, n: int) -> str:
    if k < 0:
        return f"{n} where rt_core sees no object"
    o = scene.objects[k]
    return f"{n} where rt_core sees object {k} ({o.kind}, line {o.line})"


def _variant_colour(r: Renderer, ours: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """Where the image is within one level of a render under another rule variant that
    differs from ``ours`` there (every render made so far: they flip the decisions exactly
    at their thresholds, ties, the clip, the edges)."""
    out = np.zeros(theirs.shape[:2], bool)
    for img in r.cache.values():
        out |= (_apart(img, theirs) <= 1) & (img != ours).any(-1)
    return out


def classify(r: Renderer, theirs: np.ndarray, rules, md: float, notes, bnd: Boundary):
    """(classes (rows, columns) of CLASSES indices, {rule: pixels it explains}, the pixels
    left wrong unasked (flat indices; below))."""
    ours = r.image(rules, md)
    diff = _apart(ours, theirs)
    cls = np.where(diff == 0, 0, np.where(diff == 1, 1, 4)).astype(np.int8)
    flat = cls.ravel()
    variant = _variant_colour(r, ours, theirs).ravel()
    unasked = []
    # Each set below is asked about in a fixed sample first when it holds more than
    # SAMPLE pixels (the oracle's work grows with the pixels and their bounces: 0.1-0.3 s a
    # pixel on deep mirror paths).  A sampled pixel that nothing excuses fails the image,
    # and the set's other pixels stay wrong unasked (counted: ``unasked``); a sample all
    # excused has every pixel asked (a decision a float64 tracer takes either way over a
    # whole region: a plane lying in z = 0).  So the verdict is the one asking every pixel
    # would give.
    one = np.flatnonzero(flat == 1)
    if len(one):
        # rounding where the intensity lies within its float64 bound of an 8-bit level
        # (the shading oracle's); boundary where a decision does; else wrong.  A systematic
        # offset (over SYSTEMATIC of the image, nine in ten one way: a tracer that rounds)
        # is boundary only where the colour is another variant's (an exact tie taken the
        # other way, say): on a plane lying in z = 0 every pixel has a decision at its
        # threshold, which excused the rounding tracer's every pixel
        systematic = _systematic(*_one_way(ours, theirs, one), flat.size)

        def judge(pick):
            jump, quant = bnd.levels(pick, rules, md)
            edge = jump & ~quant
            if edge.any():
                # and the decisions taken the other way give the image's colour (sides: not
                # rt_core's own, a level off any one-level bug's)
                edge[edge] = bnd.sides(pick[edge], rules, md)
            return quant, (edge & variant[pick]) if systematic else edge
        pick = bnd.sample(one)
        rnd, edge = judge(pick)
        if len(pick) < len(one) and (rnd | edge).all():
            pick = one
            rnd, edge = judge(pick)
        unasked.append(np.setdiff1d(one, pick))
        flat[one] = CLASSES.index("wrong")
        flat[pick[rnd]] = CLASSES.index("rounding")
        flat[pick[edge]] = CLASSES.index("boundary")
    bad = np.flatnonzero((flat == 4) & (diff.ravel() > 1))
    if len(bad):
        # the float64 shading oracle's margins: a decision within K·u of its threshold, and
        # a colour those decisions give taken either way (Boundary.excuses)
        def judge(pick):
            return bnd.excuses(pick, rules, md)
        pick = bnd.sample(bad)
        edge = judge(pick)
        if len(pick) < len(bad) and edge.all():
            pick = bad
            edge = judge(pick)
        unasked.append(np.setdiff1d(bad, pick))
        flat[pick[edge]] = CLASSES.index("boundary")
    # pixels the inferred variants explain: wrong under the notes' value of that rule
    variants = {}
    for name, values, _ in DIMENSIONS:
        v = md if name == "max_dist" else getattr(rules, name)
        base = DEFAULT_MAX_DIST if name == "max_dist" else getattr(notes, name)
        if v == base:
            continue
        alt = r.image(*_config(rules, md, name, base))
        flips = _differs(alt, theirs) & (cls <= 1)
        if name != "max_dist":
            cls[flips] = CLASSES.index("variant")
            variants[f"{name}={v}"] = int(flips.sum())
    return cls, variants, np.concatenate(unasked + [np.zeros(0, np.int64)]).astype(np.int64)


def _groups(mask: np.ndarray) -> list:
    """The 8-connected groups of ``mask`` pixels, each a list of (row, column)."""
    H, W = mask.shape
    seen = np.zeros_like(mask)
    out = []
    for start in zip(*np.nonzero(mask)):
        if seen[start]:
            continue
        stack, comp = [start], []
        seen[start] = True
        while stack:
            y, x = stack.pop()
            comp.append((y, x))
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = y + dy, x + dx
                    if 0 <= yy < H and 0 <= xx < W and mask[yy, xx] and not seen[yy, xx]:
                        seen[yy, xx] = True
                        stack.append((yy, xx))
        out.append(comp)
    return out


def worst_region(mask: np.ndarray) -> dict:
    """The bounding box of the largest 8-connected group of ``mask`` pixels, and its pixel
    nearest its centre of mass (``middle``: row, column; where a view of part of it looks)."""
    best = np.array(max(_groups(mask), key=len))
    middle = best[np.argmin(((best - best.mean(0)) ** 2).sum(1))]
    return {"pixels": int(mask.sum()), "largest_group": len(best),
            "rows": [int(best[:, 0].min()), int(best[:, 0].max())],
            "columns": [int(best[:, 1].min()), int(best[:, 1].max())],
            "middle": [int(middle[0]), int(middle[1])]}


# --- hit dumps ------------------------------------------------------------------------------------

def read_hits(path: str, W: int, H: int):
    """A hit dump: one line per pixel, ``column row object t`` (row 0 the top, object −1 and
    t anything on a miss).  (ids (H, W) int, t (H, W) float); pixels not listed are −2."""
    from rt_core.inputfile import check_input
    check_input(path, "hit dump")
    ids = np.full((H, W), -2, np.int64)
    ts = np.full((H, W), np.nan)
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for no, line in enumerate(f, 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            if len(parts) < 4:
                raise ValueError(f"{path}:{no}: expected 'column row object t', found "
                                 f"{line.strip()[:40]!r}")
            try:
                x, y, k, t = int(parts[0]), int(parts[1]), int(parts[2]), float(parts[3])
            except ValueError:
                raise ValueError(f"{path}:{no}: expected integers column row object and a "
                                 f"number t, found {line.strip()[:40]!r}") from None
            if not (0 <= x < W and 0 <= y < H):
                raise ValueError(f"{path}:{no}: pixel ({x}, {y}) is outside the {W}x{H} image")
            if not -1 <= k < 2 ** 31:
                raise ValueError(f"{path}:{no}: object {k} is no object number (expected -1 "
                                 "for a miss, or 0 and up)")
            ids[y, x], ts[y, x] = k, t
    return ids, ts


def check_hits(r: Renderer, rules, path) -> dict:
    """Object id by id and depth by depth against rt_core f64 (exact decisions): ids must be
    equal; depth within 1e-9 relative.  ``path``: the dump, or what ``read_hits`` made of it
    (its arrays, or the exception it raised)."""
    W, H = r.cam.columns, r.cam.rows
    if isinstance(path, BaseException):
        raise path
    # OSError, ValueError: the caller reports them
    theirs, tt = path if isinstance(path, tuple) else read_hits(path, W, H)
    ids, t = r.ids(rules)
    listed = theirs != -2
    id_wrong = listed & (theirs != ids)
    both = listed & (theirs == ids) & (ids >= 0)
    rel = np.where(both, np.abs(tt - t) / np.maximum(np.abs(t), 1e-300), 0.0)
    depth_wrong = both & ~(rel <= 1e-9)
    pairs = [(int(a), int(b), int(n)) for (a, b), n in zip(*np.unique(
        np.stack([theirs[id_wrong], ids[id_wrong]], 1), axis=0, return_counts=True))]
    pairs.sort(key=lambda p: -p[2])
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = tt[depth_wrong] / t[depth_wrong]
    ratio = ratio[np.isfinite(ratio)]
    return {"pixels": int(listed.sum()), "missing": int((~listed).sum()),
            "id_wrong": int(id_wrong.sum()), "depth_wrong": int(depth_wrong.sum()),
            "depth_max_rel": float(rel.max(initial=0.0)),
            "wrong": int(id_wrong.sum() + depth_wrong.sum() + (~listed).sum()),
            # (your id, rt_core's id, pixels), most pixels first
            "confusions": [list(p) for p in pairs[:3]],
            "depth_ratio_median": float(np.median(ratio)) if len(ratio) else None,
            "depth_compared": int(both.sum())}


def hit_hints(scene, h: dict) -> list:
    """What a hit dump's differences suggest: t not a distance; the objects mixed up."""
    out = []
    if not h:
        return out
    q = h.get("depth_ratio_median")
    if q is not None and h["depth_wrong"] >= 0.5 * max(h["depth_compared"], 1) and \
            abs(q - 1) > 1e-3:
        out.append(f"your t differs from rt_core's distance in {h['depth_wrong']} of "
                   f"{h['depth_compared']} hits on the same object (yours / rt_core's: "
                   f"{q:.4g} in the median): the notes' t is the distance along a unit "
                   "direction; is dir made unit?")
    for yours, ref, n in h.get("confusions", [])[:1]:
        def name(k):
            return "no object" if k < 0 else (
                f"object {k} ({scene.objects[k].kind}, line {scene.objects[k].line})"
                if k < len(scene.objects) else f"object {k} (no such object)")
        out.append(f"the hit dump has {name(yours)} where rt_core has {name(ref)} in "
                   f"{n} pixels")
    return out


# --- running the user's tracer --------------------------------------------------------------------

_RUNNING: set = set()           # the tracer processes running now (check_run's worker thread)


def _stop_running() -> None:
    """Kill every running tracer's process group (rtval interrupted or terminated: the
    signal reaches the main thread only, not the worker thread waiting on the tracer)."""
    for p in list(_RUNNING):
        with contextlib.suppress(OSError):
            os.killpg(p.pid, signal.SIGKILL)


class _Watchdog:
    """Kills a tracer's process group if rtval dies without doing it (SIGKILL, a crash: no
    handler runs).  A shell in a session of its own waits on a pipe whose only writer is
    rtval; the kernel closes that end when rtval dies, the read ends, and the shell kills
    the group (``kill -KILL -PGID``: dash takes no ``--``).  ``stop``, when the run ends
    normally, ends the shell first."""

    def __init__(self, pgid: int):
        self._p = self._w = None
        try:
            r, self._w = os.pipe()          # (not inherited: no other child holds it)
        except OSError:
            return                          # (no pipe, no shell: the run goes unguarded)
        try:
            self._p = subprocess.Popen(
                ["/bin/sh", "-c", f"read _ ; kill -KILL -{int(pgid)} 2>/dev/null"], stdin=r,
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        except OSError:
            pass
        finally:
            os.close(r)

    def stop(self) -> None:
        if self._p is not None:
            with contextlib.suppress(OSError):
                self._p.kill()
            self._p.wait()
        if self._w is not None:
            os.close(self._w)


PLACEHOLDERS = ("scene", "out", "columns", "rows", "hits")


def fill_command(template: str, **values) -> str:
    """``template`` with each {scene} {out} {columns} {rows} {hits} replaced by its value;
    every other brace stays as written (awk '{print $1}', a shell's ${VAR} or {a,b})."""
    return re.sub(r"\{(" + "|".join(PLACEHOLDERS) + r")\}",
                  lambda m: str(values[m.group(1)]), template)


def misspelt_placeholder(template: str) -> str | None:
    """'{colums}' meant as {columns}: the first brace word close to a placeholder but not
    one, as 'did you mean' words; None when there is none ('{print $1}' is not close)."""
    import difflib
    for word in re.findall(r"(?<!\$)\{([A-Za-z_]+)\}", template):     # (not ${VAR})
        if word in PLACEHOLDERS:
            continue
        close = PLACEHOLDER_ALIASES.get(word.lower()) or next(iter(difflib.get_close_matches(
            word.lower(), PLACEHOLDERS, n=1, cutoff=0.8)), None)
        if close:
            return f"{{{word}}} is not a placeholder: did you mean {{{close}}}?"
    return None


def quoted_placeholder(template: str) -> str | None:
    """A path placeholder ({scene}, {out}, {hits}) inside shell quotes: rtval puts each path
    there quoted for the shell already, so quotes around it break on a path with a space or
    a quote (a student's review: '< "{scene}"' passed until a folder had a space, then the
    shell said "cannot open"); None when there is none.  (A number, {columns} or {rows},
    needs no quotes and takes them; sh -c "./ray < {scene}" passes the path's own quotes on
    to the inner shell.)"""
    quote, i, n = None, 0, len(template)
    while i < n:
        ch = template[i]
        if ch == "\\" and quote != "'":             # (an escaped character: skipped)
            i += 2
            continue
        if quote is None and ch in "'\"":
            quote = ch
        elif ch == quote:
            quote = None
        elif quote is not None:
            m = re.match(r"\{(scene|out|hits)\}", template[i:])
            # (in single quotes the path's own quotes end them; double quotes hold them,
            # as in sh -c "./ray < {scene}", unless they hold the placeholder alone)
            if m and (quote == "'" or (template[i - 1] == '"' and
                                       template[i + m.end():i + m.end() + 1] == '"')):
                kind_ = "double" if quote == '"' else "single"
                alone = template[i - 1] == quote and \
                    template[i + m.end():i + m.end() + 1] == quote
                return (f"{m.group()} is inside {kind_} "
                        f"quotes; rtval quotes the path it puts there for the shell, so the "
                        f"quotes break on a path with a space: write {m.group()} without them"
                        + ("" if alone else " (in sh -c '...', use double quotes)"))
        i += 1
    return None


# names meant for a placeholder that no spelling distance finds ('{count}', '{print $1}'
# stay as written; a command that needs jq's '{width}' shorthand writes '{width: .width}')
PLACEHOLDER_ALIASES = {"output": "out", "outfile": "out", "out_file": "out", "ouput": "out",
                       "width": "columns", "cols": "columns", "height": "rows",
                       "scenefile": "scene", "scene_file": "scene"}


def run_tracer(template: str, scene: str, columns: int, rows: int, workdir: str,
               timeout: float) -> tuple[str | None, str | None, str]:
    """Run ``template`` for one scene: (image path or None, hit-dump path or None, failure
    reason or '').  Placeholders: {scene} {out} {columns} {rows} {hits}; the command runs in
    a shell (redirections as the course programs use them), in its own process group, killed
    whole on timeout."""
    stem = Path(scene).stem
    out = os.path.join(workdir, f"{stem}.ppm")
    hits = os.path.join(workdir, f"{stem}.hits")
    cmd = fill_command(template, scene=shlex.quote(str(scene)), out=shlex.quote(out),
                       columns=columns, rows=rows, hits=shlex.quote(hits))
    # the command as the reasons show it: {out} and {hits} named, not the scratch files
    # that are gone once the check ends
    shown = fill_command(template, scene=shlex.quote(str(scene)), out="{out}",
                         columns=columns, rows=rows, hits="{hits}")
    started = time.time()
    try:
        p = subprocess.Popen(cmd, shell=True, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, stdin=subprocess.DEVNULL,
                             start_new_session=True)
    except OSError as exc:
        return None, None, f"cannot run {cmd!r}: {exc.strerror or exc}"
    _RUNNING.add(p)
    guard = _Watchdog(p.pid)
    said = _Tail(p.stderr)              # what it says, read as it goes: the last lines only
    timed_out = False
    try:
        p.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        timed_out = True
    except BaseException:             # rtval itself interrupted or terminated: stop the run
        with contextlib.suppress(OSError):
            os.killpg(p.pid, signal.SIGKILL)
        raise
    finally:
        # the run ends with its command: what it left running in its process group goes
        # too (a background child holding stderr made a finished run time out)
        with contextlib.suppress(OSError):
            os.killpg(p.pid, signal.SIGKILL)
        guard.stop()                    # (before the group's id can be another's)
        p.wait()
        _RUNNING.discard(p)
        said.stop()
    if timed_out:
        return None, None, f"timed out after {timeout:g} s: {shown}"
    tail = said.last_line()
    said = f" ({tail})" if tail else ""
    rc = p.returncode
    name = _signal_name(-rc if rc < 0 else rc - 128) if rc < 0 or 128 < rc <= 128 + 64 \
        else None
    if name and rc < 0:
        return None, None, f"crashed with {name}: {shown}{said}"
    if name:                            # (the shell's status for a command a signal killed)
        return None, None, f"crashed with {name} (exit status {rc}): {shown}{said}"
    if rc != 0:
        return None, None, f"exited with status {rc}: {shown}{said}"
    here = _written_here(started) if not os.path.exists(out) or not os.path.getsize(out) \
        else []
    if here:
        # a name of its own in rtval's current directory, where the command runs
        what = "no image" if not os.path.exists(out) else "an empty image"
        return None, None, (f"wrote {what} to {{out}}: {shown} ({', '.join(here[:3])} in the "
                            f"current directory {os.getcwd()} changed meanwhile: does it "
                            "write its image there? write it to the path {out} stands for)")
    if not os.path.exists(out):
        # what it wrote instead, in the run's directory (a name of its own, {out} ignored)
        other = sorted(f for f in os.listdir(workdir) if f != os.path.basename(hits))
        return None, None, (f"wrote no image to {{out}}: {shown}" + (
            f" (it wrote {', '.join(other[:3])} beside it: write the path {{out}} stands for)"
            if other else " (write the image to the path {out} stands for, e.g. "
            "'> {out}' for a tracer that prints it)"))
    return out, (hits if "{hits}" in template and os.path.exists(hits) else None), ""


def _written_here(since: float) -> list:
    """The image files (by their names' endings) in the current directory modified since
    ``since``: where a tracer that ignores {out} writes its own file name."""
    try:
        with os.scandir(".") as it:
            return sorted(e.name for e in it
                          if e.name.lower().endswith((".ppm", ".pnm", ".png"))
                          and e.is_file() and e.stat().st_mtime >= since - 1.0)
    except OSError:
        return []


def _signal_name(sig: int) -> str | None:
    try:
        return signal.Signals(sig).name
    except ValueError:
        return None


def seconds_per_check(columns: int) -> float:
    """Rough serial seconds of one check at ``columns`` (the rule inference renders the
    scene several times): whether ``check_run`` is worth a local cluster (parallel.Plan)."""
    return 1.0 * max(1.0, (columns / 64) ** 2)


def check_run(template: str, scenes, columns: int, rows: int | None, timeout: float = 60.0,
              plan=None, progress=None, **kw) -> list:
    """Run the user's tracer on each scene, then check its image.  The runs go ahead of the
    checks in a background thread (one run at a time, in this process: the tracer is the
    user's program on this machine), so the tracer's time and rtval's overlap; the checks
    run where ``plan`` says (default in this process; tools/harness/parallel.py), each
    sent with its scene and image as data as soon as the tracer has written it.
    ``progress``: a text stream that gets each scene's one-line verdict as it is known,
    numbered ([k/n]), in the order they finish (a long run is not silent)."""
    from concurrent.futures import ThreadPoolExecutor
    from tools.harness.parallel import SERIAL, run_cases
    from rt_core.outputs import scratch_dir
    scenes = list(scenes)
    work = scratch_dir("check")         # (one a SIGKILL left is removed by the next run)
    with contextlib.ExitStack() as stack:
        stack.callback(shutil.rmtree, work, ignore_errors=True)
        pool = ThreadPoolExecutor(max_workers=1)
        try:
            results = run_cases(_check_job, _check_runs(pool, work, template, scenes, columns,
                                                        rows, timeout, kw),
                                plan or SERIAL, each=_progress(progress, len(scenes)),
                                count=len(scenes),
                                seconds_per_case=seconds_per_check(columns))
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)      # no queued run starts
            _stop_running()
            pool.shutdown(wait=True)
            raise
        pool.shutdown(wait=True)
    return results


def _read_scene(s, kw):
    """The scene of a --run or --images job with its textures, or the SceneCheck that
    refuses it (malformed, missing, an image given in its place, its textures missing:
    rtval's input, so the tracer is not run for it)."""
    from tools.harness.agree import parse_agreed
    from rt_core.scene import SceneError
    from rt_core.usererror import InputError
    try:
        sc = parse_agreed(s, kw.get("code27", "auto"))
    except (SceneError, InputError) as exc:
        return SceneCheck(str(s), None, "refused", _not_a_scene(s) or str(exc))
    except OSError as exc:
        return SceneCheck(str(s), None, "refused", f"{s}: {(exc.strerror or str(exc)).lower()}")
    sc = _textures_missing(sc, kw.get("texture_dirs", ()))
    return SceneCheck(str(s), None, "refused", sc) if isinstance(sc, str) else sc


def _check_runs(pool, work, template, scenes, columns, rows, timeout, kw):
    """check_run's jobs: the runs submitted to ``pool``, then, as each finishes, a job for
    ``_check_job`` (a finished SceneCheck when the scene or the run failed)."""
    from rt_core.imageio import ImageError, read_image
    from rt_core.memory import check_bytes, guard
    from rt_core.usererror import InputError
    jobs = []
    for k, s in enumerate(scenes):
        # a scene rtval cannot read is refused, as a malformed one is (exit 2 when no
        # scene fails): a missing one was a failed run (exit 1), a directory stopped them all
        sc = _read_scene(s, kw)
        if isinstance(sc, SceneCheck):
            jobs.append((s, None, sc))
            continue
        h = rows if rows is not None else sc.default_rows(columns)
        if h < 2:                               # (the tracer would refuse it, or divide by 0)
            jobs.append((s, None, SceneCheck(
                str(s), None, "error", f"{s}: {columns} columns give this window {h} "
                "rows; the course's corner sampling needs 2 at least: use more --columns "
                "or give --rows")))
            continue
        try:                                    # (before the tracer runs: the check's
            guard(check_bytes, "check of", columns, h, "")      # memory is known now)
        except InputError as exc:
            jobs.append((s, None, SceneCheck(str(s), None, "error", f"{s}: {exc}")))
            continue
        sub = os.path.join(work, str(k))
        os.mkdir(sub)
        jobs.append((s, (sc, h, sub), pool.submit(run_tracer, template, s, columns, h, sub,
                                                  timeout)))
    for s, parsed, job in jobs:
        if parsed is None:
            yield job
            continue
        sc, h, sub = parsed
        img, hits, why = job.result()
        try:
            if why:
                _scratch_has_room(sub, why)
                yield SceneCheck(str(s), None, "error", why, columns, h)
                continue
            # the image and the hit dump as data: a worker elsewhere cannot read them
            try:
                theirs = read_image(img)
            except ImageError as exc:
                _scratch_has_room(sub, str(exc))
                # (named as what it is: the file is a temporary, gone after the run)
                yield SceneCheck(str(s), "(--run)", "error",
                                 str(exc).replace(img, "the tracer's image {out}", 1))
                continue
            job = _check_job_of(s, img, sc, theirs, columns, h, hits, template, kw)
        finally:
            # each run's files go once read: they took the temporary folder's space from
            # the runs after them (a helper's review: a full TMPDIR failed correct tracers)
            shutil.rmtree(sub, ignore_errors=True)
        yield job


def _scratch_has_room(sub: str, why: str) -> None:
    """A run's failure that a full temporary folder explains is rtval's (exit 2, naming the
    folder), not the tracer's: its image came out empty or truncated there."""
    from rt_core.outputs import free_bytes
    from rt_core.usererror import InputError
    free = free_bytes(sub)
    if free is not None and free < (1 << 20):
        raise InputError(f"{os.path.dirname(os.path.dirname(sub))}: the temporary folder is "
                         f"full ({free} bytes free), where the tracer writes {{out}}: {why}; "
                         "free some space there or set TMPDIR to a folder that has some")


def _check_job_of(s, img, sc, theirs, columns, h, hits, template, kw):
    """check_run's job for one scene whose image was read: with its hit dump, read too."""
    from rt_core.imageio import pnm_maxval
    from rt_core.usererror import InputError
    if hits is None and "{hits}" in template:
        hits = ValueError("the tracer wrote no hit dump to {hits} (the command asks "
                          "for one)")
    elif hits is not None:
        try:
            hits = read_hits(hits, columns, h)
        except (ValueError, InputError) as exc:
            hits = ValueError(str(exc).replace(hits, "the tracer's hit dump {hits}", 1))
        except OSError as exc:
            hits = exc
    return (str(s), img, sc, theirs, columns, h, hits, {**kw, "maxval": pnm_maxval(img)})


# the image files ``check_images`` looks for, per scene, in this order
IMAGE_SUFFIXES = (".ppm", ".pnm", ".png")


def check_images(directory: str, scenes, plan=None, progress=None, columns=None,
                 rows=None, **kw) -> list:
    """Check the images a tracer left in ``directory``, one per scene named after it
    (STEM.ppm, .pnm or .png, the suffix in any case): what ``check_run`` does with the
    tracer run already (an instructor's directory of submitted images).  A scene without
    its image (or the directory missing: a student who handed in nothing), or whose image
    cannot be read, is an error; a scene rtval cannot read is refused.  ``columns`` (and
    ``rows``, default the course's for those columns): the size every image must have, else
    each image's own."""
    from tools.harness.parallel import SERIAL, run_cases
    scenes = list(scenes)
    return run_cases(_check_image_job, _image_jobs(directory, scenes, kw, columns, rows),
                     plan or SERIAL, each=_progress(progress, len(scenes)),
                     count=len(scenes), seconds_per_case=seconds_per_check(160))


def _progress(stream, n: int):
    """run_cases' ``each``: the one-line verdict on ``stream`` as each is known ([k/n])."""
    done = []

    def each(i, r):
        if stream is not None:
            done.append(i)
            print(f"rtval check: [{len(done)}/{n}] {_one_line(r)}", file=stream, flush=True)
        return r
    return each


def _image_jobs(directory, scenes, kw, columns=None, rows=None):
    """check_images' jobs: a finished SceneCheck where the scene or its image is missing or
    unreadable, else the scene and image as data (for ``_check_image_job``)."""
    from rt_core.imageio import ImageError, pnm_maxval, read_image
    from rt_core.scene import SceneError
    try:
        names = os.listdir(directory)
    except OSError:
        names = None                    # (no directory: every scene's image is missing)
    # each scene read first: an image given where a scene goes is refused as that, and
    # takes no stem from the real scene of its name (an instructor's review)
    read = [(s, _read_scene(s, kw)) for s in scenes]
    stems = [Path(s).stem for s, sc in read if not isinstance(sc, SceneCheck)]
    for s, sc in read:
        if isinstance(sc, SceneCheck):
            yield sc
            continue
        stem = Path(s).stem
        if stems.count(stem) > 1:       # (a/x.txt, b/x.txt: both would take DIR/x.ppm)
            yield SceneCheck(str(s), None, "refused",
                             f"{s}: {stems.count(stem)} scenes are named {stem}, and --images "
                             f"gives each the image named after it: check them in separate "
                             "runs")
            continue
        if names is None:
            yield SceneCheck(str(s), os.path.join(directory, stem + ".ppm"), "error",
                             f"{directory}: no such directory, so no image for this scene")
            continue
        # STEM.ppm, .pnm, .png in that order, the suffix in any case (.PPM from Windows:
        # reported missing, an instructor's review), the exact name first
        lower = {x: sorted((n for n in names if n.lower() == (stem + x).lower()),
                           key=lambda n: n != stem + x) for x in IMAGE_SUFFIXES}
        named = [os.path.join(directory, n) for x in IMAGE_SUFFIXES for n in lower[x]]
        found = [f for f in named if os.path.isfile(f)]
        if not found:
            odd = named[0] if named else None
            yield SceneCheck(str(s), odd or os.path.join(directory, stem + ".ppm"), "error",
                             f"{odd}: {_not_a_file(odd)}; give an image file" if odd else
                             f"{directory}: no image for this scene (looked for "
                             f"{', '.join(stem + x for x in IMAGE_SUFFIXES)}, any case)")
            continue
        try:
            theirs = read_image(found[0])
        except ImageError as exc:
            # (the others are not tried: which one is the tracer's is the directory's to say)
            others = ", ".join(os.path.basename(f) for f in found[1:])
            yield SceneCheck(str(s), found[0], "error", str(exc) + (
                f" (also there: {others}; --images checks the first of "
                f"{', '.join(IMAGE_SUFFIXES)}: remove the one that is not the tracer's)"
                if others else ""))
            continue
        if len(found) > 1:              # (checked the first; said, not silently chosen)
            print(f"rtval check: note: {s}: checked {os.path.basename(found[0])}; also there: "
                  f"{', '.join(os.path.basename(f) for f in found[1:])} (--images checks the "
                  f"first of {', '.join(IMAGE_SUFFIXES)}: remove the one that is not the "
                  "tracer's)", file=sys.stderr)
        try:
            h = rows if rows is not None or columns is None else sc.default_rows(columns)
        except SceneError as exc:       # (a window with no rows for those columns)
            yield SceneCheck(str(s), found[0], "refused", str(exc))
            continue
        yield (str(s), found[0], sc, theirs, columns, h, None,
               {**kw, "maxval": pnm_maxval(found[0])})


def _not_a_file(path: str) -> str:
    """What a path named like an image is, when it is not a regular file."""
    if os.path.islink(path) and not os.path.exists(path):
        return "a link to nothing"
    if os.path.isdir(path):
        return "a directory"
    return "not a regular file" if os.path.exists(path) else "no such file"


def _check_image_job(job) -> SceneCheck:
    """One of check_images' checks (in this process or on a Dask worker)."""
    if isinstance(job, SceneCheck):
        return job
    scene_path, image_path, scene, theirs, columns, rows, hits, kw = job
    return check_image(scene_path, image_path, columns=columns, rows=rows, hits_path=hits,
                       theirs=theirs, scene=scene, **kw)


def _check_job(job) -> SceneCheck:
    """One of check_run's checks (in this process or on a Dask worker)."""
    if isinstance(job, SceneCheck):
        return job
    res, image_path = _check_image_job(job), job[1]
    res.image = "(--run)"
    # (named as what it is: the file is a temporary, gone after the run)
    res.reason = res.reason.replace(image_path, "the tracer's image {out}")
    return res


# --- outputs --------------------------------------------------------------------------------------

def junit_xml(results, name: str | None = None) -> str:
    """One test case per scene; ``name`` (whose tracer: check --name) names the suite and
    the cases' class."""
    from .junit import Case, junit_xml as xml
    cases = []
    names = [Path(r.scene).name for r in results]
    for r in results:
        # the file's name, or its path where two scenes share one (a/x.txt, b/x.txt)
        c = Case(Path(r.scene).name if names.count(Path(r.scene).name) == 1 else r.scene,
                 # (a dot would make a package of the name's parts in CI tools)
                 "rtval.check" + (f".{name.replace('.', '_')}" if name else ""), r.seconds)
        if r.status == "fail":
            hits = r.hits.get("wrong", 0) if r.hits else 0
            c.failure = f"{r.counts.get('wrong', 0)} wrong pixels" + (
                f", {hits} wrong in the hit dump" if hits else "")
            c.body = "\n".join([f"rules: {r.rules}, max_dist={r.max_dist:g}"] +
                               details(r, ("deviation", "hint", "wrong", "hit dump")))
        elif r.status in ("error", "refused"):
            # (type: a scene rtval refused is the checker's input, an error the tracer's
            # image or run; a grading tool can tell them apart, an instructor's review)
            c.error, c.error_type = r.reason, r.status
        else:
            # (the deviations a pass names, in words: the terminal and the page show them,
            # the JUnit file had the verdict line only, an instructor's review)
            c.body = "\n".join([_one_line(r)] + details(r, ("deviation", "boundary")))
        cases.append(c)
    return xml("rtval check" + (f": {name}" if name else ""), cases)


def _one_line(r: SceneCheck) -> str:
    if r.status in ("error", "refused"):
        return f"{r.status.upper()} {r.scene}: {r.reason}"
    counts = ", ".join(f"{c} {r.counts.get(c, 0)}" for c in CLASSES if r.counts.get(c))
    return f"{'PASS' if r.ok else 'FAIL'} {r.scene} {r.columns}x{r.rows}: {counts}"


def details(r: SceneCheck, kinds=("rules", "deviation", "hint", "wrong", "boundary",
                                   "hit dump")) -> list:
    """The lines under a checked scene's verdict, in words (the text report, the HTML
    report, JUnit): the rules, each deviation and hint, the wrong pixels, the hit dump."""
    out = []
    if "rules" in kinds:
        det = [f"{f.rule}={f.value:g}" if isinstance(f.value, float) else f"{f.rule}={f.value}"
               for f in r.findings if f.determined]
        und = [f.rule for f in r.findings if not f.determined and not f.unfollowed]
        unf = [f.rule for f in r.findings if f.unfollowed]
        out.append("rules: " + (", ".join(det) if det else "none determined") +
                   (f"; undetermined: {', '.join(und)}" if und else "") +
                   (f"; matched only by chance, not named: {', '.join(unf)}" if unf else ""))
    if "deviation" in kinds:
        out += [f"deviation: {d}" for d in r.deviations]
    if "hint" in kinds:
        out += [f"hint: {h}" for h in r.hints]
    if r.worst and "wrong" in kinds:
        w = r.worst
        ex = w.get("example")
        seen = ""
        if ex:
            seen = (f"; at column {ex['column']}, row {ex['row']}: yours "
                    f"{tuple(ex['theirs'])}, rt_core's {tuple(ex['rtval'])}")
            for way in ("darker", "brighter"):
                if w.get(way, 0) >= 0.9 * w["pixels"]:
                    seen += f"; yours {way} at {100 * w[way] // w['pixels']}% of them"
        out.append(f"wrong: {w['pixels']} pixels"
                   + (f" ({r.unasked} of them counted wrong without a check of their own: "
                      "a sample of pixels like them held wrong ones)" if r.unasked else "")
                   + f", the largest group {w['largest_group']} in "
                   f"rows {w['rows'][0]}-{w['rows'][1]}, columns {w['columns'][0]}-"
                   f"{w['columns'][1]}; " + "; ".join(w.get("objects", [])) + seen)
    if r.boundary_note and "boundary" in kinds:
        out.append(f"boundary: {r.boundary_note}")
    if r.hits and "hit dump" in kinds:
        h = r.hits
        out.append(f"hit dump: {h['pixels']} pixels listed"
                   + (f", {h['missing']} missing" if h["missing"] else "")
                   + f"; {h['id_wrong']} with another object, {h['depth_wrong']} "
                   f"with another depth (max relative depth error "
                   f"{h['depth_max_rel']:.3g}; 1e-09 allowed)")
    return out


def text_report(results) -> str:
    lines = []
    for r in results:
        lines.append(_one_line(r))
        if r.status in ("pass", "fail"):
            lines += ["  " + d for d in details(r)]
    # (the refused scenes apart, as the HTML report counts them)
    refused = sum(r.status == "refused" for r in results)
    n = len(results) - refused
    ok = sum(r.ok for r in results)
    lines.append(f"{ok} of {n} scenes pass" + (f"; {refused} refused" if refused else ""))
    hint = float32_run_hint(results)
    if hint:
        lines.append(f"hint: {hint}")
    return "\n".join(lines)


def float32_run_hint(results) -> str:
    """Across a run: every failing scene's wrong pixels few and scattered, and F32_RUN of
    those asked explained by float32's rounding (a scene alone may have too few to say)."""
    failed = [r for r in results if r.status == "fail"]
    if not failed or any(not r.float32 or any(SPECKS in h for h in r.hints) for r in failed):
        return ""
    asked = sum(r.float32["asked"] for r in failed)
    explained = sum(r.float32["explained"] for r in failed)
    if asked < 10 or explained < F32_RUN * asked:
        return ""
    scenes = "the failing scene" if len(failed) == 1 else f"the {len(failed)} failing scenes"
    return (f"{explained} of the {asked} wrong pixels asked in {scenes} lie within float32's "
            "rounding of a decision and have the colour its other side gives: does your tracer "
            "compute in float rather than double?")
