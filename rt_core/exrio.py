"""OpenEXR output: float32 channels named ``layer.channel`` plus string header attributes;
reading goes through OpenImageIO (``read_exr``, ``imageio.read_channels``).

The OpenEXR binding writes, not OpenImageIO: it takes each channel's array as it is and
compresses with the library's worker threads, where OpenImageIO's writer needs the channels
interleaved first and wrote the same 14-channel 1920-column PIZ image 1.6x slower
(docs/speed.md, "Who writes the EXR").  Writes go to a temporary name in the target
directory, are checked to be complete (the binding does not report a failed flush when the
file is closed: a small EXR on a full disk would be lost silently) and are renamed into
place, so a failed or interrupted write never leaves a partial file.
"""
from __future__ import annotations

import os
import struct

import numpy as np
import OpenEXR

# (atomic_write re-exported: EXR writers use it)
from .outputs import atomic_write, attr_text  # noqa: F401


# Compression, chosen by measurement (README "The whole command"): PIZ is lossless, read by
# every OpenEXR since 1.x, and with the library's worker threads wrote a 7680-column shaded
# EXR in 10.5 s (ZIP: 15.6 s, 16% larger).  ZSTD and HTJ2K are faster and 2-4x smaller, but
# only OpenEXR 3.4 and later read them: they are options (``rtval render --compression``).
COMPRESSIONS = {"none": OpenEXR.NO_COMPRESSION, "zip": OpenEXR.ZIP_COMPRESSION,
                "piz": OpenEXR.PIZ_COMPRESSION, "zstd": OpenEXR.ZSTD_COMPRESSION,
                "htj2k": OpenEXR.HTJ2K256_COMPRESSION}
DEFAULT_COMPRESSION = "piz"
# the library's worker threads compress (and decompress) chunks in parallel
OpenEXR.set_global_thread_count(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                else (os.cpu_count() or 1))


class ExrError(Exception):
    """An EXR that cannot be read or written; ``str(err)`` is one line naming the file."""
    exit_code = 4


def write_exr(path: str, channels: dict, attrs: dict | None = None,
              compression: str = DEFAULT_COMPRESSION) -> None:
    """Write ``{name: 2-D array}`` (rows top first) as FLOAT channels (UINT for uint32);
    ``compression`` a COMPRESSIONS name."""
    data = {}
    shape = None
    for name, arr in channels.items():
        a = np.asarray(arr)
        if a.dtype != np.uint32:
            with np.errstate(over="ignore", invalid="ignore"):   # counted by the caller
                a = a.astype(np.float32, copy=False)
        if a.ndim != 2 or (shape is not None and a.shape != shape):
            raise ExrError(f"{path}: channel {name} has shape {a.shape}, expected {shape}")
        shape = a.shape
        data[name] = np.ascontiguousarray(a)
    header = {"compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    for k, v in (attrs or {}).items():
        header[k] = attr_text(v)
    atomic_write(path, lambda tmp: OpenEXR.File(header, data).write(tmp), verify=incomplete)


def incomplete(path: str) -> str | None:
    """Why a single-part scanline EXR is not complete, or None: the header ends, the
    offset table points at chunks that follow one another and the last one ends the file.
    (What ``write_exr`` writes; the chunk count comes from the table itself, so no table of
    lines per chunk per compression is needed.)  OpenImageIO finds a cut file too, but only
    by decoding every pixel: 3.5 s against this walk's 1 ms at 1920 columns (docs/speed.md)."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        head = f.read(8)
        if len(head) < 8 or head[:4] != b"\x76\x2f\x31\x01":
            return "the file is truncated (no EXR header)"
        pos, buf = 8, b""
        while True:                                   # attributes: name\0 type\0 size value
            f.seek(pos)
            buf = f.read(1 << 16)
            if not buf:
                return "the file is truncated (in its header)"
            if buf[0] == 0:                           # the header's terminating null byte
                pos += 1
                break
            name_end = buf.find(b"\0")
            type_end = buf.find(b"\0", name_end + 1)
            if name_end < 0 or type_end < 0 or type_end + 5 > len(buf):
                return "the file is truncated (in its header)"
            (n,) = struct.unpack_from("<i", buf, type_end + 1)
            pos += type_end + 5 + n
        f.seek(pos)
        first = f.read(8)
        if len(first) < 8:
            return "the file is truncated (no chunk table)"
        (start,) = struct.unpack("<Q", first)
        count = (start - pos) // 8
        if start <= pos or (start - pos) % 8 or start >= size:
            return "the file is incomplete (its chunk table was not written)"
        f.seek(pos)
        table = np.frombuffer(f.read(8 * count), "<u8")
        end = start
        for off in np.sort(table):
            if off != end:
                return "the file is incomplete (a chunk is missing)"
            f.seek(int(off))
            head = f.read(8)                         # y, then the chunk's byte count
            if len(head) < 8:
                return "the file is truncated (its last chunk is short)"
            (n,) = struct.unpack_from("<i", head, 4)
            end = int(off) + 8 + n
        if end != size:
            return "the file is truncated (its last chunk is short)"
    return None


def read_exr(path: str, deep_ok: bool = False) -> tuple[dict, dict]:
    """Return (channels {name: 2-D array}, header {name: value}); ExrError if unreadable.

    Read by OpenImageIO (``imageio.read_channels``; any format it reads): every part of a
    multi-part file, channels named ``part.channel``; a deep file is refused (``deep_ok``:
    checked, no channels).  Header names are OpenImageIO's (``compression`` is ``piz``);
    rtval's ``rtval.*`` attributes keep theirs."""
    from .imageio import read_channels
    img = read_channels(path, deep_ok, "EXR", ExrError)
    return img.channels, img.header
