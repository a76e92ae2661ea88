"""The references' own PPM reader (P6 and P3, maxval 1..65535), independent of rt_core's
(rt_core/textures.py): texel = value / maxval in float64, row 0 the file's first row.
Files must already be valid (rt_core reports errors); this raises ValueError otherwise."""
from __future__ import annotations

import functools
import os
import re

import numpy as np

# magic, then width, height, maxval, each after whitespace and any '#' comment lines
_HEADER = re.compile(rb"(P[36])((?:\s+|#[^\n\r]*[\n\r])+)(\d+)((?:\s+|#[^\n\r]*[\n\r])+)(\d+)"
                     rb"((?:\s+|#[^\n\r]*[\n\r])+)(\d+)(\s)")


def texels(path: str) -> np.ndarray:
    """(H, W, 3) float64 texels of the PPM file at ``path`` (read-only; read again when the
    file has changed since: a long-lived worker may see a texture rewritten)."""
    st = os.stat(path)
    return _texels(os.path.abspath(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=16)
def _texels(path: str, mtime_ns: int, size: int) -> np.ndarray:
    with open(path, "rb") as f:
        data = f.read()
    m = _HEADER.match(data)
    if m is None:
        raise ValueError(f"{path}: not a PPM header")
    w, h, maxval = int(m.group(3)), int(m.group(5)), int(m.group(7))
    n = 3 * w * h
    if m.group(1) == b"P6":
        dtype = np.dtype(np.uint8) if maxval < 256 else np.dtype(">u2")
        vals = np.frombuffer(data, dtype, n, m.end())
    else:
        vals = np.array(data[m.end():].split()[:n], dtype=np.int64)
    out = vals.astype(np.float64).reshape(h, w, 3) / float(maxval)
    out.flags.writeable = False
    return out
