"""Keep native libraries' own console output out of ours."""
from __future__ import annotations

import contextlib
import ctypes
import io
import os
import sys
import tempfile
import threading

_lock = threading.Lock()


@contextlib.contextmanager
def native_output_captured(fds=(1, 2)):
    """Capture what native libraries print while the block runs.

    Dr.Jit prints a message (from C++, straight to descriptor 2) when it meets an old LLVM;
    it would break one-line error messages and ``--json`` output, so both the Python streams
    and descriptors ``fds`` (1 and 2) are redirected.  OpenImageIO's errors are retrieved
    from the library, but its PNG reader also has libpng print them ("libpng error: ...",
    descriptor 2): image reads capture descriptor 2 alone.  Yields a list that is filled
    with the captured lines when the block ends.
    """
    lines: list[str] = []
    with _lock, tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        saved = []
        try:
            for fd in fds:
                saved.append((fd, os.dup(fd)))
                os.dup2(sink.fileno(), fd)
        except OSError:  # a closed descriptor: nothing to protect
            pass
        py_out = io.StringIO()
        try:
            with (contextlib.redirect_stdout(py_out) if 1 in fds else contextlib.nullcontext()), \
                    (contextlib.redirect_stderr(py_out) if 2 in fds else contextlib.nullcontext()):
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
