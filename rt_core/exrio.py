"""OpenEXR I/O: float32 channels named ``layer.channel`` plus string header attributes.

Writes go to a temporary name in the target directory, are checked to be complete (the
binding does not report a failed flush when the file is closed: a small EXR on a full disk
would be lost silently) and are renamed into place, so a failed or interrupted write never
leaves a partial file.
"""
from __future__ import annotations

import os

import struct

import numpy as np
import OpenEXR

from .inputfile import check_input
from .native import native_output_captured
from .usererror import InputError
from .outputs import atomic_write  # noqa: F401  (re-exported: EXR writers use it)


# Compression, chosen by measurement (README "Speed"): PIZ is lossless, read by every OpenEXR
# since 1.x, and with the library's worker threads wrote a 7680-column shaded EXR in 10.5 s
# (ZIP: 15.6 s, 16% larger).  ZSTD and HTJ2K are faster and 2-4x smaller, but only OpenEXR
# 3.4 and later read them: they are options (``rtval render --compression``).
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
        header[k] = str(v)
    atomic_write(path, lambda tmp: OpenEXR.File(header, data).write(tmp), verify=incomplete)


def incomplete(path: str) -> str | None:
    """Why a single-part scanline EXR is not complete, or None: the header ends, the
    offset table points at chunks that follow one another and the last one ends the file.
    (What ``write_exr`` writes; the chunk count comes from the table itself, so no table of
    lines per chunk per compression is needed.)"""
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


def _native_reason(path: str, lines: list[str]) -> str | None:
    """The most telling line the library printed (its EXR_ERR_* message), without the path."""
    for ln in lines:
        if "EXR_ERR_" in ln:
            ln = ln[len(path) + 2:] if ln.startswith(f"{path}: ") else ln
            if ln.startswith("(EXR_ERR_") and ") " in ln:  # "(CODE) text" -> "CODE: text"
                code, text = ln[1:].split(") ", 1)
                ln = f"{code}: {text}"
            return ln
    return None


DEEP = ("deepscanline", "deeptile")


def _storage(header) -> str:
    t = header.get("type")
    return getattr(t, "name", str(t) if t is not None else "scanlineimage")


def read_exr(path: str, deep_ok: bool = False) -> tuple[dict, dict]:
    """Return (channels {name: 2-D array}, header {name: value}); ExrError if unreadable.

    Every part of a multi-part file is read: its channels are named ``part.channel`` (the
    part's name, or ``part<i>``) and must share one data window; the header is part 0's with
    ``parts`` added (their names).  A deep file is refused (``deep_ok``: its channels are
    per-pixel sample arrays, for ``info``)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ExrError(f"{path}: no such file")
    try:
        check_input(path, "EXR")
    except InputError as exc:
        raise ExrError(str(exc)) from None
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise ExrError(f"{path}: cannot read OpenEXR file ({e.strerror or e})") from None
    if magic != b"\x76\x2f\x31\x01":
        raise ExrError(f"{path}: not an OpenEXR file (bad magic number)")
    native: list[str] = []
    try:
        with native_output_captured() as native:
            f = OpenEXR.File(path, separate_channels=True)
            parts = [(p.name() if hasattr(p, "name") else "", dict(p.header),
                      {name: ch.pixels for name, ch in p.channels.items()}) for p in f.parts]
    except Exception as e:  # the OpenEXR binding raises plain RuntimeError/OSError
        reason = (_native_reason(path, native)
                  or (str(e).splitlines()[0] if str(e) else type(e).__name__))
        raise ExrError(f"{path}: cannot read OpenEXR file, truncated or corrupt "
                       f"({reason})") from None
    if not parts:
        raise ExrError(f"{path}: the file has no parts")
    deep = [i for i, (_, h, _) in enumerate(parts) if _storage(h) in DEEP]
    if deep and not deep_ok:
        raise ExrError(f"{path}: a deep EXR ({_storage(parts[deep[0]][1])}): rtval compares "
                       "flat images only; flatten it first (oiiotool IN --flatten -o OUT)")
    header = dict(parts[0][1])
    if len(parts) == 1:
        chans = {k: v if _storage(header) in DEEP else np.asarray(v)
                 for k, v in parts[0][2].items()}
        return chans, header
    names = [n or f"part{i}" for i, (n, _, _) in enumerate(parts)]
    chans, shape = {}, None
    for pname, (_, h, ch) in zip(names, parts):
        for k, v in ch.items():
            a = v if _storage(h) in DEEP else np.asarray(v)
            if shape is not None and a.shape != shape:
                raise ExrError(f"{path}: a multi-part EXR whose parts differ in size "
                               f"({pname} is {a.shape[1]} x {a.shape[0]}, part 0 is "
                               f"{shape[1]} x {shape[0]}); rtval reads parts of one size")
            shape = a.shape
            chans[f"{pname}.{k}"] = a
    header["parts"] = names
    return chans, header
