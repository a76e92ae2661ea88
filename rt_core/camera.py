"""The course camera: one ray per pixel from the viewpoint through the window in z = 0.

Corner sampling (the course): column x = 0..W-1, row y = 0..H-1 with y = 0 the bottom row,
``world = (x/(W-1)·ww - ww/2, y/(H-1)·wh - wh/2, 0)``.  Centre sampling puts the samples at
pixel centres, ``((x+½)/W·ww - ww/2, ...)``.  Image row 0 is the top (y = H-1).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from fractions import Fraction
from types import SimpleNamespace

import drjit as dr
import numpy as np

from .backend import Types
from .errors import InputError
from .scene import Num, Scene, exact, written

SAMPLINGS = ("corners", "centers")


@dataclass(frozen=True)
class Camera:
    columns: int
    rows: int
    sampling: str
    sx: float               # sample spacing in world units (host float64)
    sy: float
    row_shift: int = 0      # 1: image row r samples course row H − r (a course variant)
    row0: int = 0           # a tile: image rows row0 .. row0 + band − 1 of the full grid
    band: int = 0           # (0: every row)

    @property
    def tile_rows(self) -> int:
        """Rows traced: the tile's, or the image's."""
        return self.band or self.rows

    @property
    def size(self) -> int:
        """Rays traced: columns × tile_rows."""
        return self.columns * self.tile_rows

    def tiles(self, max_pixels: int):
        """The image as bands of whole rows of at most ``max_pixels`` (at least one row)."""
        step = max(1, max_pixels // self.columns)
        for r in range(0, self.rows, step):
            yield dataclasses.replace(self, row0=r, band=min(step, self.rows - r))


def make_camera(scene: Scene, columns: int, rows: int | None = None,
                sampling: str = "corners", rules=None) -> Camera:
    """The camera; ``rules.rows == 'shifted'`` shifts every row up by one (a variant)."""
    if sampling not in SAMPLINGS:
        raise InputError(f"sampling must be corners or centers, not {sampling!r}")
    given_rows = rows is not None
    if rows is None:
        rows = scene.default_rows(columns)
    if columns * rows >= 2 ** 31:
        said = f"image {columns}x{rows} has {columns * rows} pixels; Dr.Jit indexes at most " \
            "2^31 rays in one kernel: "
        if given_rows:
            # (the rows given are the ones to cut: 'use --columns <= 0 (and --rows in
            # proportion)' for 3x10^12, a review)
            raise InputError(said + f"use --rows <= {(2 ** 31 - 1) // columns} at "
                                    f"{columns} columns, or fewer of both")
        # the most columns, rows in proportion, below 2^31 pixels
        fit = math.isqrt(int((2 ** 31 - 1) * columns / rows))
        while fit * max(1, fit * rows // columns) >= 2 ** 31:
            fit -= 1
        raise InputError(said + f"use --columns <= {fit}")
    least = 2 if sampling == "corners" else 1
    if columns < least or rows < least:
        raise InputError(f"image {columns}x{rows} is too small: {sampling} sampling needs at "
                         f"least {('one column and one row', '2 columns and 2 rows')[least - 1]}"
                         + ("" if given_rows or rows >= least or columns < least else
                            f" (rows = int(h/w·columns) = {rows}; give --rows)"))
    ww, wh = scene.window
    if sampling == "corners":
        sx, sy = ww / (columns - 1), wh / (rows - 1)
    else:
        sx, sy = ww / columns, wh / rows
    shift = 1 if rules is not None and getattr(rules, "rows", "course") == "shifted" else 0
    return Camera(columns, rows, sampling, sx, sy, shift)


def _axis_offsets(cam: Camera, scene: Scene, axis: int):
    """World − viewpoint along one axis is (i − c)·s for pixel index i, with s the sample
    spacing and c the (fractional) index of the viewpoint's foot, both exact from the
    scene's numbers.  Returns (s, c_hi, c_lo·s) as floats: c_hi = round(c) is an integer, so
    (i − c_hi) is exact in the kernel and (i − c_hi)·s − c_lo·s is one fma, accurate to its
    own size even for the pixel right below a far-off viewpoint (where x·sx + (ox − vx)
    cancels to the ulp of ox − vx)."""
    n = cam.columns if axis == 0 else cam.rows
    size = exact(scene.window[axis])
    if cam.sampling == "corners":
        step, origin = size / (n - 1), -size / 2
    else:
        step = size / n
        origin = -size / 2 + step / 2
    c = (exact(scene.viewpoint[axis]) - origin) / step
    hi = round(c)
    return step, hi, -(c - hi) * step


def _split(v: Fraction, precision: str) -> tuple[float, float]:
    """v as hi + lo in the kernel's precision (hi = v rounded, lo = the rest rounded)."""
    rnd = (lambda f: float(np.float32(float(f)))) if precision == "f32" else float
    hi = rnd(v)
    return hi, rnd(v - Fraction(hi))


def primary_offsets(scene: Scene, cam: Camera, T):
    """world − viewpoint of every pixel (Array3 of T, image order), scaled by one exact power
    of two so that squaring cannot overflow or underflow.

    world − viewpoint = ((x − cx)·sx, (y − cy)·sy, −vz), with cx, cy the viewpoint's foot in
    pixel units split into an integer and a fraction on the host (``_axis_offsets``).  The
    step is a double-float (hi + lo), so each offset is within two roundings of the exact
    value, and the window's edge samples (−ww/2 and ww/2 − vx with corner sampling), where
    the course's formula is exact, are the exact values rounded once.  Scene numbers enter as
    opaque values, so scenes that differ only in numbers share the compiled kernel."""
    F = T.Float
    k = _offset_constants(written(scene.window), written(scene.viewpoint), cam,
                          T.precision)
    i = dr.arange(T.UInt32, cam.size)
    r = i // cam.columns                    # image row − row0; course row y = rows − 1 − row
    x = i - r * cam.columns

    def axis(ix, c):
        # (ix)·s + c with s = hi + lo: the lo product first, then one fma
        hi, lo, c0, edges = c
        w = dr.fma(ix, dr.opaque(F, hi), dr.fma(ix, dr.opaque(F, lo), dr.opaque(F, c0)))
        for at, value in edges:             # corner sampling: the window's edge samples
            w = dr.select(ix == dr.opaque(F, at), dr.opaque(F, value), w)
        return w

    # x − c = (x − c_hi) − c_lo and y − c = ((rows − 1 − c_hi) − r) − c_lo: integers first
    ix = F(x) - dr.opaque(F, k.hx)
    iy = dr.opaque(F, k.y0) - F(r)
    wx, wy = axis(ix, k.x), axis(iy, k.y)
    # (with row_shift the row above the window, y = rows, is no edge: its fma value stays)
    wz = dr.opaque(F, k.z) + dr.zeros(F, cam.size)
    return T.Array3(wx, wy, wz)


def _numbers(key) -> tuple:
    """A ``written`` key back to numbers that ``exact`` reads as the scene's."""
    return tuple(v if t is None else Num(t) for v, t in key)


@functools.lru_cache(maxsize=256)
def _offset_constants(window, viewpoint, cam: Camera, precision: str) -> SimpleNamespace:
    """primary_offsets' host numbers (exact arithmetic on the scene's numbers as written,
    ~0.1 ms), kept for the cameras and scenes traced last: each comparison and render of a
    scene asks again."""
    scene = SimpleNamespace(window=_numbers(window), viewpoint=_numbers(viewpoint))
    sx, hx, cx = _axis_offsets(cam, scene, 0)
    sy, hy, cy = _axis_offsets(cam, scene, 1)
    vz = exact(scene.viewpoint[2])
    # one exact power of two brings the largest offset near 1
    big = max(abs(vz), abs(hx * sx) + abs(cx) + sx * cam.columns,
              abs(hy * sy) + abs(cy) + sy * cam.rows)
    k = -math.frexp(float(big))[1] if big else 0
    sc = Fraction(2) ** k

    def axis(s, c, edge0, edge1):
        hi, lo = _split(s * sc, precision)
        edges = ()
        if cam.sampling == "corners":
            edges = tuple((float(at), float(v * sc)) for at, v in (edge0, edge1))
        return hi, lo, float(c * sc), edges

    ww, wh = (exact(c) for c in scene.window)
    vx, vy = exact(scene.viewpoint[0]), exact(scene.viewpoint[1])
    return SimpleNamespace(
        hx=float(hx), y0=float(cam.rows - 1 + cam.row_shift - hy - cam.row0),
        x=axis(sx, cx, (-hx, -ww / 2 - vx), (cam.columns - 1 - hx, ww / 2 - vx)),
        y=axis(sy, cy, (-hy, -wh / 2 - vy), (cam.rows - 1 - hy, wh / 2 - vy)),
        z=float(-vz * sc))


def primary_directions(scene: Scene, cam: Camera, T: Types):
    """Unit ray directions (Array3 of T) for every pixel; the origin is the viewpoint."""
    return dr.normalize(primary_offsets(scene, cam, T))
