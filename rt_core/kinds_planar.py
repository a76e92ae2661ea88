"""The planar kinds triangle and disk in the course files: their numeric codes' two layouts.

rt_core's parser's rule (the references' reader, mitsuba_ref/scenefile.py, has its own,
and tools/harness/agree.py checks that the two read the same kind).

Code 27 is a triangle in NickWilsonDev's final program (``triangle_init``: MAT, then three
points, one a line) and a disk in an older file of the same course program (nw__disk1.txt:
MAT, then centre, radius, normal); code 29 is the disk in the final program.  A 27 is read as
the layout whose *second geometry line* has the count of numbers it starts with: 3 numbers
(point 2; or more, the rest ignored as on any line) a triangle, 1 number (the radius) a disk;
2 numbers fit neither and are an error.  The parse option ``code27`` forces either
(``rtval render --code27 triangle|disk``).
"""
from __future__ import annotations

# code -> (index of the geometry line that tells the layouts apart, {its number count: form})
SHAPED_CODES = {27: (1, {3: "triangle", 1: "disk"})}
CODE27_CHOICES = ("auto", "triangle", "disk")


def shaped_form(code: int, count: int, force: str | None = None) -> str | None:
    """The form a shaped code is read as: ``force`` (a form name, not 'auto') if given, else
    the one whose distinguishing geometry line starts with ``count`` numbers; None if no
    layout has that count."""
    if force and force != "auto":
        return force
    layouts = SHAPED_CODES[code][1]
    if count is not None and count > max(layouts):   # numbers after a group are ignored
        count = max(layouts)
    return layouts.get(count)
