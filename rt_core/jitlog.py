"""Which Dr.Jit kernels a render launched, pass by pass, and whether each was compiled.

Built on Dr.Jit's kernel history (drjit 1.5): with ``JitFlag.KernelHistory`` set, every launch
is recorded, and ``dr.kernel_history()`` returns the records since the last call (and clears
them).  A record has ``type`` (``KernelType.JIT`` for generated kernels; ``Memset``,
``Compress``, ... for built-in operations), and for JIT kernels ``hash``, ``cache_hit``
(found in the in-memory cache) and ``cache_disk`` (loaded from the on-disk cache, default
``~/.drjit``).  A JIT kernel with neither was compiled by LLVM (or NVRTC) for this launch.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import drjit as dr


@dataclass
class PassRecord:
    """The launches of one pass of a render."""
    name: str               # 'hit' (geometry only), 'bounce' (hit, shadows, shading)
    group: str              # 'primary' or 'reflection'
    bounce: int             # 0 for the primary rays, k for the k-th reflection
    rays: int
    kernels: int = 0        # JIT kernels launched
    compiled: int = 0       # of those: neither in the memory nor in the disk cache
    disk: int = 0           # of those: loaded from the on-disk cache
    hashes: list = field(default_factory=list)
    other: Counter = field(default_factory=Counter)   # built-in launches by type

    @property
    def memory(self) -> int:
        return self.kernels - self.compiled - self.disk


class KernelLog:
    """Collects kernel-history records per pass while active (``with KernelLog() as log``).

    ``mark(...)`` closes a pass: every launch since the previous mark belongs to it."""

    def __init__(self):
        self.passes: list[PassRecord] = []
        self._saved = None

    def __enter__(self):
        self._saved = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                       # drop what earlier code launched
        return self

    def __exit__(self, *exc):
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, self._saved)
        return False

    def mark(self, name: str, group: str, bounce: int, rays: int) -> PassRecord:
        rec = PassRecord(name, group, bounce, rays)
        for e in dr.kernel_history():
            if e["type"] == dr.KernelType.JIT:
                rec.kernels += 1
                rec.hashes.append(e["hash"])
                if e.get("cache_disk"):
                    rec.disk += 1
                elif not e.get("cache_hit"):
                    rec.compiled += 1
            else:
                rec.other[e["type"].name] += 1
        self.passes.append(rec)
        return rec

    def groups(self) -> list[str]:
        return list(dict.fromkeys(p.group for p in self.passes))

    def total(self, group: str | None = None) -> PassRecord:
        """All passes (of one group) summed into one record."""
        out = PassRecord(group or "all", group or "all", -1, 0)
        for p in self.passes:
            if group is None or p.group == group:
                out.rays += p.rays
                out.kernels += p.kernels
                out.compiled += p.compiled
                out.disk += p.disk
                out.hashes += p.hashes
                out.other.update(p.other)
        return out


class NullLog:
    """A KernelLog that records nothing (the default when nobody asks)."""
    passes: list = []

    def mark(self, *args, **kw):
        return None
