"""Reading an input file a user named: a regular file of bounded size, or one clear line.

Devices (``/dev/zero``), FIFOs and sockets are refused before they are opened, so that no
read can block or run forever; a file over the size limit is refused before it is read.
Shared by rt_core and the references (it knows nothing of scenes or images).
"""
from __future__ import annotations

import contextlib
import os
import stat

from .usererror import InputError

MiB = 1 << 20
LIMITS = {"scene": 64 * MiB, "image": 1024 * MiB, "texture": 1024 * MiB, "hit dump": 4096 * MiB,
          "EXR": 64 * 1024 * MiB}
LIMITS["EXR or other image"] = LIMITS["EXR"]       # (rtval exr: any format, EXR-sized)


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def _a(what: str) -> str:
    return ("an " if what[0] in "aeiouAEIOU" else "a ") + what


# the files a command has read (device, inode), while ``tracking_inputs`` holds: an output
# may not replace one (a scene's texture overwritten by --ppm textures/x.ppm; outputs.py)
_READ: list = []


@contextlib.contextmanager
def tracking_inputs():
    """Within the block (one command of rtval's), every input file ``check_input`` passes is
    noted, and ``atomic_write`` refuses to replace one.  (Library calls outside it write
    where they are told: a test may rewrite the image it checked.)"""
    _READ.append(set())
    try:
        yield
    finally:
        _READ.pop()


def was_read(path) -> bool:
    """Has the command running (``tracking_inputs``) read the file at ``path``?"""
    if not _READ:
        return False
    try:
        st = os.stat(path)
    except OSError:
        return False
    return (st.st_dev, st.st_ino) in _READ[-1]


def check_input(path, what: str) -> int:
    """Refuse ``path`` unless it is a regular file within the size limit for ``what``;
    returns its size.  A missing file raises FileNotFoundError (an OSError naming it)."""
    path = os.fspath(path)
    st = os.stat(path)
    if _READ:
        _READ[-1].add((st.st_dev, st.st_ino))
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{path}: is a directory; give {_a(what)} file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{path}: is {_kind(st.st_mode)}, not {_a(what)} file; rtval reads "
                         "regular files only (save the stream to a file first)")
    limit = LIMITS[what]
    if st.st_size > limit:
        raise InputError(f"{path}: {st.st_size / MiB:.0f} MiB is too large for {_a(what)} file "
                         f"(the limit is {limit // MiB} MiB); is it the right file?")
    return st.st_size


def read_input(path, what: str) -> bytes:
    """The bytes of a regular input file within the size limit for ``what``."""
    check_input(path, what)
    limit = LIMITS[what]
    with open(path, "rb") as f:
        data = f.read(limit + 1)
    if len(data) > limit:                 # it grew while being read
        raise InputError(f"{os.fspath(path)}: more than {limit // MiB} MiB, too large for "
                         f"{_a(what)} file; is it the right file?")
    return data


def file_sha256(path) -> str:
    """The sha256 of a file's bytes, read a MiB at a time (provenance of an input)."""
    import hashlib
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
