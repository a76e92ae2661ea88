"""8-bit image output: binary PPM as the course programs write it, and PNG.

Both take a (rows, columns, 3) uint8 array, row 0 the top of the image, and write atomically
(``exrio.atomic_write``): an error never leaves a partial file.

PPM header: ``P6 <W> <H> 255`` and one newline, on one line, as five of the six course
programs write it (``"P6 %d %d 255\\n"`` in cblades, scottgigawatt, m4rk4l, coilingdragon and
NickWilsonDev; rocketman768 alone writes ``P6\\n<W>\\n<H>\\n255\\n``).  Pixels follow as RGB
bytes, top row first: byte for byte what those programs output for the same pixels.
"""
from __future__ import annotations

import numpy as np

from .exrio import atomic_write


def _check(pixels) -> np.ndarray:
    a = np.asarray(pixels)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected a (rows, columns, 3) uint8 image, got {a.dtype} {a.shape}")
    return np.ascontiguousarray(a)


def ppm_bytes(pixels) -> bytes:
    """The binary PPM (P6) file of an image, as the course programs write it."""
    a = _check(pixels)
    return b"P6 %d %d 255\n" % (a.shape[1], a.shape[0]) + a.tobytes()


def write_ppm(path: str, pixels) -> None:
    data = ppm_bytes(pixels)

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(data)
    atomic_write(path, write)


def write_png(path: str, pixels, text: dict | None = None) -> None:
    """PNG with ``text`` as tEXt chunks (provenance)."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo
    img = Image.fromarray(_check(pixels), "RGB")
    info = PngInfo()
    for k, v in (text or {}).items():
        info.add_text(k, str(v))
    atomic_write(path, lambda tmp: img.save(tmp, format="PNG", pnginfo=info))
