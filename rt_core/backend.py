"""Dr.Jit backend and precision: one place that maps ('llvm'|'cuda', 'f32'|'f64') to types,
and that refuses, with a clear message, an LLVM too old to run Dr.Jit's kernels."""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from types import ModuleType

MIN_LLVM = 16       # LLVM 14/15 abort on dr.maximum/dr.minimum ("Cannot select: fmaximum")
PRECISIONS = ("f32", "f64")
BACKENDS = ("llvm", "cuda")


@functools.lru_cache(maxsize=None)
def host_cpu() -> dict:
    """The first processor's fields in /proc/cpuinfo ("model name", "flags", ...); empty
    where it cannot be read."""
    out = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break                       # (the first processor's block ends)
                key, _, value = line.partition(":")
                out[key.strip()] = value.strip()
    except OSError:
        pass
    return out


class BackendError(Exception):
    """Dr.Jit cannot run here (missing or too old LLVM, no CUDA device)."""
    exit_code = 2


_checked: set[str] = set()


def require(backend: str = "llvm") -> None:
    """Raise BackendError unless ``backend`` can run kernels; never lets LLVM abort us."""
    if backend in _checked:
        return
    import drjit as dr
    if backend == "llvm":
        # Dr.Jit prints its own line about an old LLVM; ours below says what to do
        from .native import native_output_captured
        with native_output_captured():
            ok = dr.has_backend(dr.JitBackend.LLVM)
        ver = dr.detail.llvm_version() if ok else (-1, -1, -1)
        hint = ("install Debian's libllvm19 (apt-get install -y libllvm19), or point "
                "DRJIT_LIBLLVM_PATH at a libLLVM.so of version 16 or newer")
        if not ok:
            where = os.environ.get("DRJIT_LIBLLVM_PATH")
            raise BackendError("Dr.Jit found no usable LLVM"
                               + (f" at DRJIT_LIBLLVM_PATH={where}" if where else "")
                               + f"; {hint}")
        if ver[0] < MIN_LLVM:
            raise BackendError(f"Dr.Jit loaded LLVM {'.'.join(map(str, ver))}, which aborts "
                               f"Dr.Jit kernels (needs >= {MIN_LLVM}); {hint}")
    elif backend == "cuda":
        if not dr.has_backend(dr.JitBackend.CUDA):
            raise BackendError("no CUDA device or driver found; use --backend llvm")
    else:
        raise BackendError(f"unknown backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if backend == "llvm":
        import sys
        from . import DRJIT_IMPORT_MESSAGES
        for line in DRJIT_IMPORT_MESSAGES:
            print(line, file=sys.stderr)
        DRJIT_IMPORT_MESSAGES.clear()
    _checked.add(backend)


@dataclass(frozen=True)
class Types:
    """The Dr.Jit array types of one (backend, precision) pair."""
    backend: str
    precision: str
    module: ModuleType
    Float: type
    Array3: type
    Bool: type
    UInt32: type
    Int32: type

    @property
    def label(self) -> str:
        return f"{self.backend}-{self.precision}"


def types(precision: str = "f32", backend: str = "llvm") -> Types:
    if precision not in PRECISIONS:
        raise BackendError(f"unknown precision {precision!r}; expected f32 or f64")
    require(backend)
    import drjit
    m = getattr(drjit, backend)
    if precision == "f32":
        return Types(backend, precision, m, m.Float, m.Array3f, m.Bool, m.UInt32, m.Int32)
    return Types(backend, precision, m, m.Float64, m.Array3f64, m.Bool, m.UInt32, m.Int32)


# rt_core traces its kernels with Dr.Jit's local value numbering (its common-subexpression
# elimination while tracing) off.  LLVM merges the same expressions anyway, so the kernels
# run as fast; but the hash table Dr.Jit keeps for it never shrinks, and once a large scene
# of any library in the process has grown it (Mitsuba's of 4096 finite planes, which
# `rtval bench` loads before its spheres), every later operation traced pays for it
# (benchmarks/after_large_scene.py, 16 spheres f32, wall ms before / after that scene, two
# runs: primary rays on 3.56 / 3.86 and 3.49 / 3.68, off 3.42 / 3.64 and 3.41 / 3.43; shaded
# image on 28.7 / 29.9 and 28.4 / 29.5, off 27.9 / 28.6 and 27.7 / 28.5).  In a fresh
# process, same process interleaved, primary and shaded bench scenes, f32 and f64: off over
# on 0.97-1.004 of the time.  Mitsuba keeps Dr.Jit's default.
VALUE_NUMBERING = False


def traced(fn):
    """``fn`` traced in rt_core's Dr.Jit state (value numbering: ``VALUE_NUMBERING``)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        import drjit as dr                  # (this module imports without Dr.Jit)
        with dr.scoped_set_flag(dr.JitFlag.ValueNumbering, VALUE_NUMBERING):
            return fn(*args, **kwargs)
    return wrapper


def host_view(x):
    """A numpy view of ``x``'s memory where it has some on this host (an evaluated array of
    the LLVM backend: Dr.Jit hands numpy its buffer, no copy); None elsewhere (CUDA memory,
    or an expression not evaluated: reading it would copy, or compute, the whole array)."""
    import drjit as dr
    if dr.backend_v(x) != dr.JitBackend.LLVM or x.state != dr.VarState.Evaluated:
        return None
    return x.numpy()
