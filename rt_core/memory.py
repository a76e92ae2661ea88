"""Memory a command will need, checked against what the machine has, before allocating.

A render too large for the machine used to grow until the kernel killed it (or Dr.Jit
aborted); now each command estimates its peak from the image size and refuses in one line
("needs ~31 GB, 19 GB available; use --columns <= N") before it traces.  The per-pixel
figures were measured with /usr/bin/time (peak RSS) on this project's scenes and rounded up;
``tests/test_faults.py`` checks them against real peaks.
"""
from __future__ import annotations

import math
import os
import resource

from .usererror import InputError

GB = 1e9
# bytes per traced pixel while a band's kernels run (rays, hits, shading state), by
# precision and shading: measured peaks less the outputs on 1600x1200 renders of the bundled
# scenes, the largest 50/100 (geometry) and 430/780 (shaded: scenes/shade_mirrors.txt, four
# bounces), rounded up (float32 camera rays that loop now evaluate their directions first,
# render.camera_rays: 12 bytes a pixel more, inside the rounding up)
KERNEL = {("f32", False): 80, ("f64", False): 130, ("f32", True): 500, ("f64", True): 900}
# rtval compare: rt_core, Mitsuba's own buffers and the per-pixel classification (measured
# 880 B/px f32, 1115 B/px f64); "shaded": --shaded, the course images of both (peak RSS at
# 1200 less at 400 columns: 416, 530 B/px on scenes/mixed.txt, planar_many.txt), and where a
# pixel is wrong the float64 geometry comparison after them (1088 B/px on shade_mirrors.txt)
COMPARE = {"f32": 1000, "f64": 1250, "shaded": 1300}
BASE = 300e6                   # Python, Dr.Jit, LLVM and the compiled kernels (~150 MB)
# rtval bench: every tracer's rays, outputs and Dr.Jit's cached blocks held at once
# (measured: peak RSS at 1920 less at 64 columns, spheres 1 and 4096 objects: 141 B/px for
# the primary mode, 1160 B/px --shaded, whose one-bounce kernel also holds 16 numbers a ray
# for the reflection hits), over a base with Mitsuba loaded (270 and 490 MB at 64 columns)
BENCH = {False: 160, True: 1300}
BENCH_BASE = 600e6


def available() -> tuple[float, str]:
    """(bytes this process may still allocate, what limits it): the least of MemAvailable,
    the memory cgroup's limit less its usage, and the address-space rlimit less the
    process's size."""
    found = []
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    found.append((int(line.split()[1]) * 1024, "available memory"))
    except OSError:
        pass
    for limit, usage, stat, cache in (
            ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current",
             "/sys/fs/cgroup/memory.stat", "inactive_file"),
            ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
             "/sys/fs/cgroup/memory/memory.usage_in_bytes",
             "/sys/fs/cgroup/memory/memory.stat", "total_inactive_file")):
        try:
            with open(limit) as f:
                text = f.read().strip()
            if text != "max" and int(text) < 1 << 60:
                with open(usage) as f:
                    used = int(f.read())
                # the usage counts the page cache; its inactive part is reclaimed on demand
                with open(stat) as f:
                    reclaim = next((int(ln.split()[1]) for ln in f
                                    if ln.split()[:1] == [cache]), 0)
                found.append((int(text) - used + reclaim, "the memory cgroup's limit"))
        except (OSError, ValueError, IndexError):
            pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        try:
            with open("/proc/self/statm") as f:
                vm = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError):
            vm = 0
        found.append((soft - vm, "the address-space limit (ulimit -v)"))
    if not found:
        return math.inf, "unknown"
    return min(found)


def render_bytes(pixels: int, precision: str, shade: bool, geometry: bool,
                 tile_pixels: int) -> float:
    """Peak of ``rtval render`` traced in bands of ``tile_pixels``: the kernels' arrays for
    one band, plus the whole image's outputs (float32 geometry channels, R G B in the
    precision and their 8-bit image, each with one temporary while it is written)."""
    item = 8 if precision == "f64" else 4
    out = (11 * 4 if geometry else 0) + ((3 * item + 3) * 2 if shade else 0)
    return BASE + min(pixels, tile_pixels) * KERNEL[(precision, shade)] + pixels * out


def compare_bytes(pixels: int, precision: str) -> float:
    """One comparison (``rtval compare``'s modes run one after the other; ``precision``
    "shaded": the course images, ``rtval compare --shaded``)."""
    return BASE + pixels * COMPARE[precision]


def report_bytes(pixels: int) -> float:
    """``rtval report``: every configuration of a scene at one size, rt_core's and
    Mitsuba's (measured on scenes/sphere.txt: 368 MB at 800 columns, 1018 MB at 1600, 451
    B/px; 600 taken)."""
    return BASE + pixels * 600


def check_bytes(pixels: int) -> float:
    """``rtval check``: rt_core's float64 shaded renders (one per rule variant tried, their
    images kept), the oracle's bounds and the classes (measured 340 B/px on
    scenes/mixed.txt; the shaded kernel alone can take 900)."""
    return BASE + pixels * 1500


def bench_bytes(pixels: int, shaded: bool) -> float:
    """``rtval bench`` (its primary or --shaded mode) on an image of ``pixels``."""
    return BENCH_BASE + pixels * BENCH[shaded]


def band_that_fits(need, band: int, least: int = 1 << 16) -> int:
    """The band size (pixels per kernel launch) to trace with: ``band``, halved while
    ``need(band)`` does not fit in memory (down to ``least``)."""
    budget = available()[0] * 0.9
    while band > least and need(band) > budget:
        band //= 2
    return band


def _gb(x: float) -> str:
    return f"{x / GB:.1f} GB" if x < 10 * GB else f"{x / GB:.0f} GB"


def guard(need, what: str, columns: int, rows: int, hint: str = "",
          option: str = "--columns") -> None:
    """InputError (exit 2) when ``need(pixels)`` bytes for the columns × rows image exceed
    what is available, naming the largest column count (rows in proportion) that fits, as
    a value of ``option``."""
    have, why = available()
    budget = have * 0.9
    total = need(columns * rows)
    if total <= budget:
        return
    lo, hi = 0, columns                       # largest c whose image (same aspect) fits
    while lo < hi:
        c = (lo + hi + 1) // 2
        if need(c * (c * rows // columns + 1)) <= budget:
            lo = c
        else:
            hi = c - 1
    fix = f"use {option} <= {lo}" if lo >= 2 else "free some memory"
    raise InputError(f"{what} {columns}x{rows} needs ~{_gb(total)}, {_gb(have)} available "
                     f"({why}); {fix}" + (f" {hint}" if hint else ""))
