"""OpenEXR I/O: float32 channels named ``layer.channel`` plus string header attributes.

Writes go to a temporary name in the target directory and are renamed into place, so a
failed or interrupted write never leaves a partial file.
"""
from __future__ import annotations

import contextlib
import ctypes
import io
import os
import sys
import tempfile
import threading

import numpy as np
import OpenEXR


class ExrError(Exception):
    """An EXR that cannot be read or written; ``str(err)`` is one line naming the file."""
    exit_code = 4


def atomic_write(path: str, write) -> None:
    """Call ``write(tmp_path)`` and rename the result to ``path`` only if it succeeded."""
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)
    suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=directory)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_exr(path: str, channels: dict, attrs: dict | None = None,
              compression=OpenEXR.ZIP_COMPRESSION) -> None:
    """Write ``{name: 2-D array}`` (rows top first) as FLOAT channels (UINT for uint32)."""
    data = {}
    shape = None
    for name, arr in channels.items():
        a = np.asarray(arr)
        if a.dtype != np.uint32:
            a = a.astype(np.float32)
        if a.ndim != 2 or (shape is not None and a.shape != shape):
            raise ExrError(f"{path}: channel {name} has shape {a.shape}, expected {shape}")
        shape = a.shape
        data[name] = np.ascontiguousarray(a)
    header = {"compression": compression, "type": OpenEXR.scanlineimage}
    for k, v in (attrs or {}).items():
        header[k] = str(v)
    atomic_write(path, lambda tmp: OpenEXR.File(header, data).write(tmp))


_native_lock = threading.Lock()


@contextlib.contextmanager
def _native_output_captured():
    """Capture what the OpenEXR binding prints while it runs.

    On a corrupt or truncated file it prints its own messages: "Warning: Exception raised
    reading pixel data ..." through Python's ``sys.stdout`` and "(EXR_ERR_BAD_CHUNK_LEADER)
    ..." from C++ straight to file descriptor 2.  Either would break one-line error messages
    and ``--json`` output, so both the Python streams and descriptors 1 and 2 are redirected.
    Yields a list that is filled with the captured lines when the block ends.
    """
    lines: list[str] = []
    with _native_lock, tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        saved = []
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(sink.fileno(), fd)
        except OSError:  # a closed descriptor: nothing to protect
            pass
        py_out = io.StringIO()
        try:
            with contextlib.redirect_stdout(py_out), contextlib.redirect_stderr(py_out):
                yield lines
        finally:
            with contextlib.suppress(Exception):  # C stdio may buffer the library's output
                ctypes.CDLL(None).fflush(None)
            for fd, dup in saved:
                os.dup2(dup, fd)
                os.close(dup)
            sink.seek(0)
            text = py_out.getvalue() + sink.read().decode("utf-8", "replace")
            lines.extend(ln.strip() for ln in text.splitlines() if ln.strip())


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


def read_exr(path: str) -> tuple[dict, dict]:
    """Return (channels {name: 2-D array}, header {name: value}); ExrError if unreadable."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ExrError(f"{path}: no such file")
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except OSError as e:
        raise ExrError(f"{path}: cannot read OpenEXR file ({e.strerror or e})") from None
    if magic != b"\x76\x2f\x31\x01":
        raise ExrError(f"{path}: not an OpenEXR file (bad magic number)")
    native: list[str] = []
    try:
        with _native_output_captured() as native:
            f = OpenEXR.File(path, separate_channels=True)
            chans = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
            header = dict(f.header())
    except Exception as e:  # the OpenEXR binding raises plain RuntimeError/OSError
        reason = (_native_reason(path, native)
                  or (str(e).splitlines()[0] if str(e) else type(e).__name__))
        raise ExrError(f"{path}: cannot read OpenEXR file, truncated or corrupt "
                       f"({reason})") from None
    return chans, header
