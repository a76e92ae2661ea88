"""Host (numpy) arrays into Mitsuba's Dr.Jit types, at a 64-byte aligned address.

Dr.Jit's LLVM backend maps a numpy array of the type's own dtype without copying (and a
converted one from a fresh host buffer), and a kernel that reads a mapped array at an address
not aligned to its vector width is generated with unaligned loads: another kernel, compiled
again (4–30 s for the course integrator's).  numpy's buffers are aligned to 16 bytes only, so
which kernel a render got depended on where the allocator put its rays.  Copying into an
aligned buffer here keeps one kernel per scene shape.  (rt_core has its own copy of this,
accel.device_array: the references share no code with what they check.)
"""
from __future__ import annotations

import numpy as np

ALIGN = 64


def aligned(a, dtype) -> np.ndarray:
    """A contiguous copy of ``a`` as ``dtype`` whose data starts at a multiple of ALIGN."""
    flat = np.ascontiguousarray(a, dtype).ravel()
    raw = np.empty(flat.nbytes + ALIGN, np.uint8)
    start = -raw.ctypes.data % ALIGN
    out = raw[start:start + flat.nbytes].view(dtype)
    out[:] = flat
    return out


def jit_array(Type, a):
    """Dr.Jit array ``Type`` (a 1-D type: Float, UInt32, ...) holding ``a``."""
    import drjit as dr
    dtype = np.dtype(dr.type_v(Type).name.lower())       # float32, uint32, ...
    return Type(aligned(a, dtype))


def jit_vectors(Type, a):
    """Dr.Jit 3-vector ``Type`` (Point3f, Vector3f) from the rows of an (n, 3) array."""
    import drjit as dr
    a = np.asarray(a)
    return Type(*(jit_array(dr.value_t(Type), a[:, i]) for i in range(3)))
