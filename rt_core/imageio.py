"""8-bit images: binary PPM as the course programs write it, and PNG; and reading what a
course tracer wrote (``read_image``: PPM P6 or P3, PNG).

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
from .inputfile import read_input
from .usererror import InputError


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


class ImageError(ValueError):
    """An image that cannot be read; ``str(err)`` is one line naming the file."""
    exit_code = 2


def _ppm_header(data: bytes, path: str):
    """(magic, width, height, maxval, offset of the pixels): the header's four tokens,
    separated by white space, with '#' comments (Netpbm)."""
    toks, i, n = [], 0, len(data)
    while len(toks) < 4:
        while i < n and data[i:i + 1].isspace():
            i += 1
        if i < n and data[i:i + 1] == b"#":
            while i < n and data[i:i + 1] not in (b"\n", b"\r"):
                i += 1
            continue
        j = i
        while j < n and not data[j:j + 1].isspace() and data[j:j + 1] != b"#":
            j += 1
        if j == i:
            raise ImageError(f"{path}: PPM header ends after {len(toks)} of its 4 fields "
                             "(magic, width, height, maxval)")
        toks.append(data[i:j])
        i = j
    magic = toks[0].decode("ascii", "replace")
    try:
        w, h, maxval = (int(t) for t in toks[1:])
    except ValueError:
        raise ImageError(f"{path}: PPM header: expected width, height and maxval as "
                         f"integers, found {b' '.join(toks[1:]).decode('ascii', 'replace')!r}")
    if not (w > 0 and h > 0 and 0 < maxval < 65536):
        raise ImageError(f"{path}: PPM header: {w}x{h} with maxval {maxval} is not an image")
    return magic, w, h, maxval, i + 1


def read_image(path: str) -> np.ndarray:
    """A (rows, columns, 3) uint8 image from a binary (P6) or ASCII (P3) PPM or a PNG, row 0
    the top.  16-bit PPMs (maxval > 255) are scaled to 8 bits; PNG through Pillow."""
    try:
        data = read_input(path, "image")
    except InputError as exc:
        raise ImageError(str(exc)) from None
    except OSError as exc:
        raise ImageError(f"{path}: cannot read the image: {exc.strerror or exc}") from None
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        import io
        from PIL import Image
        try:
            with Image.open(io.BytesIO(data)) as im:
                return np.asarray(im.convert("RGB"), np.uint8).copy()
        except Exception as exc:
            raise ImageError(f"{path}: not a readable PNG: {exc}") from None
    if not data:
        raise ImageError(f"{path}: the image file is empty")
    if data[:2] not in (b"P6", b"P3"):
        head = data[:2].decode("ascii", "replace")
        raise ImageError(f"{path}: not a PPM (P6/P3) or PNG image (it starts with {head!r})")
    magic, w, h, maxval, off = _ppm_header(data, path)
    if magic not in ("P6", "P3"):
        raise ImageError(f"{path}: unknown PPM magic {magic!r}; expected P6 or P3")
    count = w * h * 3
    if count > 1 << 31:
        raise ImageError(f"{path}: {w}x{h} is too large an image")
    if magic == "P6":
        size = 2 if maxval > 255 else 1
        body = data[off:off + count * size]
        if len(body) < count * size:
            raise ImageError(f"{path}: P6 {w}x{h} needs {count * size} bytes of pixels, the "
                             f"file has {len(body)} (truncated?)")
        a = np.frombuffer(body, ">u2" if size == 2 else np.uint8).astype(np.int64)
    else:
        vals = data[off:].split()
        if len(vals) < count:
            raise ImageError(f"{path}: P3 {w}x{h} needs {count} numbers, the file has "
                             f"{len(vals)} (truncated?)")
        try:
            a = np.array([int(v) for v in vals[:count]], np.int64)
        except ValueError:
            raise ImageError(f"{path}: P3 pixel values must be integers") from None
    if a.max(initial=0) > maxval:
        raise ImageError(f"{path}: a pixel value exceeds the header's maxval {maxval}")
    if maxval != 255:
        a = (a * 255 + maxval // 2) // maxval
    return a.astype(np.uint8).reshape(h, w, 3)
