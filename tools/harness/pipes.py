"""What a child process says on a pipe, kept within bounds."""
from __future__ import annotations

import contextlib
import os
import re


class Tail:
    """The last KEEP bytes a pipe carries, read in a thread until it closes (a tracer may
    print gigabytes of debug lines), or until ``stop`` (a child that left the process group
    may hold the pipe open: its reading is abandoned then)."""
    KEEP = 1 << 14

    def __init__(self, pipe):
        import threading
        self.buf = b""
        self.thread = threading.Thread(target=self._read, args=(pipe,), daemon=True)
        self.thread.start()

    def _read(self, pipe):
        with contextlib.suppress(OSError, ValueError):
            with pipe:
                while chunk := os.read(pipe.fileno(), 1 << 16):
                    self.buf = (self.buf + chunk)[-self.KEEP:]

    def stop(self):
        self.thread.join(timeout=2)

    def last_line(self) -> str:
        """The last line said, without terminal escapes and control characters (they made
        the JUnit XML ill-formed), at most 200 characters."""
        # (CSI sequences, colours and the like, and OSC ones, a window title: ESC ] ...
        # ended by BEL or ESC \)
        text = re.sub(r"\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?", "",
                      self.buf.decode("utf-8", "replace"))
        text = "".join(c if c.isprintable() or c == "\n" else " " for c in text)
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        return lines[-1][:200] if lines else ""
