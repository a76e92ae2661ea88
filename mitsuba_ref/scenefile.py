"""The course scene format's numbers as written, read independently of rt_core's parser.

Both dialects (notes/course-format.md): the keyword dialect (``pointlight``, ``sphere``,
``plane``, ``fplane``, ``tplane``; ``#`` comments; groups may wrap lines) and the numeric one
(codes 10, 13, 14, 15, 16 on their own line; every line ``numbers [free text]``, one group a
line).  The references read a scene only through this module, so a bug in rt_core's parser or
scene model cannot pass a comparison with them.  Files must already be valid (rt_core's
parser reports errors with file, line and column); this reader only extracts numbers and
raises ``ValueError`` on what it cannot read.

Every number is kept exactly (``Fraction`` of its decimal text) and as a float; nothing is
derived here (no unit normal, no frame): each reference computes those by its own few lines.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from decimal import Decimal
from fractions import Fraction

from rt_core.inputfile import read_input
from rt_core.kinds import KEYWORDS, KINDS, kind_of_code, kind_of_keyword

# number groups after the type token: (field, count); None = not geometry (materials)
LAYOUT = {
    "pointlight": (("emissivity", 3), ("center", 3)),
    "sphere": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3), ("radius", 1)),
    "plane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3)),
    "fplane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3),
               ("orient", 3), ("size", 2)),
    "tplane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3),
               ("orient", 3), ("size", 2), ("bg_ambient", 3), ("bg_diffuse", 3),
               ("bg_specular", 3)),
}
_NUM = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z")


@dataclass(frozen=True)
class Item:
    """One light or object: ``x[name]`` exact Fractions, ``f[name]`` floats, per field."""
    kind: str
    index: int                  # object id (index among non-light objects), -1 for lights
    line: int
    x: dict = field(default_factory=dict)
    f: dict = field(default_factory=dict)

    def __getattr__(self, name):       # obj.center, obj.radius, ... as floats
        f = self.__dict__.get("f", {})
        if name in f:
            v = f[name]
            return v[0] if name == "radius" else v
        raise AttributeError(name)


@dataclass(frozen=True)
class File:
    window: tuple               # Fractions
    viewpoint: tuple
    lights: tuple
    objects: tuple
    dialect: str

    def floats(self) -> "File":
        """The same scene with the header as floats (what a float reference reads)."""
        return File(tuple(float(c) for c in self.window),
                    tuple(float(c) for c in self.viewpoint), self.lights, self.objects,
                    self.dialect)

    def default_rows(self, columns: int) -> int:
        """rows = int(world_h / world_w · columns), the keyword programs' rule."""
        return int(self.window[1] / self.window[0] * columns)


def _lines(text: str):
    """(line number, tokens) of every line, comments removed."""
    for no, raw in enumerate(re.split(r"\r\n|\r|\n", text.lstrip("\ufeff")), 1):
        yield no, raw.split("#", 1)[0].split()


def read_text(text: str) -> File:
    lines = [(no, t) for no, t in _lines(text) if t]
    # the header's five numbers; then a keyword, or a number (a code) starting a line
    got, k, after = 0, 0, None
    while k < len(lines) and got < 5:
        ts = lines[k][1]
        lead = next((i for i, t in enumerate(ts) if not _NUM.match(t)), len(ts))
        if lead == 0:
            break
        got += lead
        after = ts[lead] if lead < len(ts) else None
        k += 1
    if after is not None and after.lower() in KEYWORDS:
        return _keyword(lines)
    if got >= 5 and k < len(lines) and _NUM.match(lines[k][1][0]):
        return _numeric(lines)
    return _keyword(lines)


def read(path) -> File:
    return read_text(read_input(path, "scene").decode("utf-8", "replace"))


def _exact(tok: str) -> Fraction:
    if not _NUM.match(tok):
        raise ValueError(f"expected a number, found {tok!r}")
    return Fraction(Decimal(tok))


def _make(kind, values, line, nobj):
    x = {name: vals for (name, _), vals in zip(LAYOUT[kind], values)}
    f = {name: tuple(float(c) for c in vals) for name, vals in x.items()}
    return Item(kind, -1 if kind == "pointlight" else nobj, line, x, f)


def _keyword(lines) -> File:
    toks = [(no, t) for no, ts in lines for t in ts]
    pos = 0

    def take(n):
        nonlocal pos
        if pos + n > len(toks):
            raise ValueError("truncated scene")
        vals = tuple(_exact(t) for _, t in toks[pos:pos + n])
        pos += n
        return vals

    window, viewpoint = take(2), take(3)
    lights, objects = [], []
    while pos < len(toks):
        line, word = toks[pos]
        pos += 1
        kind = kind_of_keyword(word)
        item = _make(kind, [take(n) for _, n in LAYOUT[kind]], line, len(objects))
        (lights if kind == "pointlight" else objects).append(item)
    return File(window, viewpoint, tuple(lights), tuple(objects), "keyword")


def _numeric(lines) -> File:
    idx = 0

    def group(n):
        nonlocal idx
        if idx >= len(lines):
            raise ValueError("truncated scene")
        no, toks = lines[idx]
        idx += 1
        lead = []
        for t in toks:
            if not _NUM.match(t):
                break
            lead.append(t)
        if len(lead) < n:
            raise ValueError(f"line {no}: expected {n} numbers")
        return tuple(_exact(t) for t in lead[:n])

    window, viewpoint = group(2), group(3)
    lights, objects = [], []
    while idx < len(lines):
        line, toks = lines[idx]
        idx += 1
        kind = kind_of_code(int(toks[0]))
        item = _make(kind, [group(n) for _, n in LAYOUT[kind]], line, len(objects))
        (lights if kind == "pointlight" else objects).append(item)
    return File(window, viewpoint, tuple(lights), tuple(objects), "numeric")


assert set(LAYOUT) == set(KINDS) | {"pointlight"}, "scenefile.LAYOUT must cover every kind"
