"""Where a run's time goes: each comparison times its phases, and a run sums them.

Phases: ``rt_core`` (tracing or shading, both calls, and its images as arrays), ``mitsuba``
(loading the converted scene, both calls), ``oracle`` (the exact oracle's or the shading
oracle's image: the reference of the comparisons of objects Mitsuba has no shape for,
mitsuba_ref/exact.py and shade_oracle.py), ``classify`` (pixel classification, the oracles it
runs, the depth bounds, FLIP), ``other`` (the rest of the comparison: parsing, rays for
Mitsuba, the row) and ``write`` (evidence and pictures, in the rtval process).  Sums are of
each comparison's own wall time, so with several workers they add up to more than the run's
wall time; the shares are what ``rtval validate`` prints.
"""
from __future__ import annotations

import time
from contextlib import contextmanager

PHASES = ("rt_core", "mitsuba", "oracle", "classify", "other", "write")


class Stopwatch:
    """Seconds per phase: ``with sw("rt_core"): ...`` adds the block's wall time."""

    def __init__(self):
        self.seconds = dict.fromkeys(PHASES, 0.0)

    @contextmanager
    def __call__(self, phase: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - t0

    def rounded(self) -> dict:
        return {k: round(v, 4) for k, v in self.seconds.items()}


def time_split(rows) -> dict:
    """Summed seconds and share of each phase over result rows' ``seconds``."""
    total = dict.fromkeys(PHASES, 0.0)
    for r in rows:
        for k, v in r.get("seconds", {}).items():
            total[k] += v
    whole = sum(total.values())
    return {"seconds": {k: round(v, 3) for k, v in total.items()},
            "share": {k: round(v / whole, 4) if whole else 0.0 for k, v in total.items()}}


def split_line(split: dict) -> str:
    """One line: each phase's share and seconds."""
    names = {"rt_core": "rt_core", "mitsuba": "Mitsuba", "oracle": "oracles",
             "classify": "classification",
             "other": "other Python", "write": "writing"}
    return "time (summed over comparisons): " + ", ".join(
        f"{names[k]} {100 * split['share'][k]:.0f}% ({split['seconds'][k]:.1f} s)"
        for k in PHASES)
