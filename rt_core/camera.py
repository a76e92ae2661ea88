"""The course camera: one ray per pixel from the viewpoint through the window in z = 0.

Corner sampling (the course): column x = 0..W-1, row y = 0..H-1 with y = 0 the bottom row,
``world = (x/(W-1)·ww - ww/2, y/(H-1)·wh - wh/2, 0)``.  Centre sampling puts the samples at
pixel centres, ``((x+½)/W·ww - ww/2, ...)``.  Image row 0 is the top (y = H-1).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from .backend import Types
from .errors import InputError
from .scene import Scene

SAMPLINGS = ("corners", "centers")


@dataclass(frozen=True)
class Camera:
    columns: int
    rows: int
    sampling: str
    # world = (x·sx + ox, y·sy + oy, 0), host float64
    sx: float
    ox: float
    sy: float
    oy: float

    @property
    def size(self) -> int:
        return self.columns * self.rows


def make_camera(scene: Scene, columns: int, rows: int | None = None,
                sampling: str = "corners") -> Camera:
    if sampling not in SAMPLINGS:
        raise InputError(f"sampling must be corners or centers, not {sampling!r}")
    if rows is None:
        rows = scene.default_rows(columns)
    least = 2 if sampling == "corners" else 1
    if columns < least or rows < least:
        raise InputError(f"image {columns}x{rows} is too small: {sampling} sampling needs at "
                         f"least {least} columns and rows"
                         + ("" if rows >= least or columns < least else
                            f" (rows = int(h/w·columns) = {rows}; give --rows)"))
    ww, wh = scene.window
    if sampling == "corners":
        sx, sy = ww / (columns - 1), wh / (rows - 1)
        ox, oy = -ww / 2, -wh / 2
    else:
        sx, sy = ww / columns, wh / rows
        ox, oy = -ww / 2 + sx / 2, -wh / 2 + sy / 2
    return Camera(columns, rows, sampling, sx, ox, sy, oy)


def pixel_grid(cam: Camera, T: Types):
    """Course column x and row y (0 = bottom) of every pixel, in image order (top row first)."""
    i = dr.arange(T.UInt32, cam.size)
    r = i // cam.columns                    # literal divisor: a multiply-shift, vectorized
    x = i - r * cam.columns
    y = (cam.rows - 1) - r
    return x, y


def primary_directions(scene: Scene, cam: Camera, T: Types):
    """Unit ray directions (Array3 of T) for every pixel; the origin is the viewpoint.

    Scene numbers enter as opaque values, so scenes that differ only in numbers share the
    compiled kernel."""
    x, y = pixel_grid(cam, T)
    vx, vy, vz = scene.viewpoint
    F = T.Float
    # world − viewpoint, with the offsets (ox − vx) summed on the host in float64
    wx = dr.fma(F(x), dr.opaque(F, cam.sx), dr.opaque(F, cam.ox - vx))
    wy = dr.fma(F(y), dr.opaque(F, cam.sy), dr.opaque(F, cam.oy - vy))
    wz = dr.opaque(F, -vz) + dr.zeros(F, cam.size)
    return dr.normalize(T.Array3(wx, wy, wz))
