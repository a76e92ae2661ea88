"""The course scene format's numbers as written, read independently of rt_core's parser.

Both dialects (notes/course-format.md): the keyword dialect (``pointlight``, ``sphere``,
``plane``, ``fplane``, ``tplane`` and the forms of mitsuba_ref/layouts.py; ``#`` comments;
groups may wrap lines) and the numeric one (codes on their own line; every line ``numbers
[free text]``, one group a line; cd's 9000/9001 header flags add a number after every MAT;
nw's refraction index may follow the code).  The forms and code tables are the references'
own (layouts.py): only the kinds' names are shared with rt_core.  The references read a
scene only through this module, so a bug in rt_core's parser or
scene model cannot pass a comparison with them.  Files must already be valid (rt_core's
parser reports errors with file, line and column); this reader only extracts numbers and
raises ``ValueError`` on what it cannot read.

Every number is kept exactly (``Fraction`` of its decimal text) and as a float; nothing is
derived here (no unit normal, no frame): each reference computes those by its own few lines.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from decimal import Decimal
from fractions import Fraction

from rt_core.inputfile import read_input
from rt_core.kinds import KINDS, LIGHTS
from .layouts import (CODE_TABLES, FORMS, HEADER_FLAGS, KEYWORDS, SHARED_CODES, form_of_code,
                      form_of_keyword)

# number groups after the type token: (field, count); None = not geometry (materials)
LAYOUT = {
    "pointlight": (("emissivity", 3), ("center", 3)),
    "spotlight": (("emissivity", 3), ("center", 3), ("aim", 3), ("theta", 1)),
    "sphere": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3), ("radius", 1)),
    "plane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3)),
    "fplane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3),
               ("orient", 3), ("size", 2)),
    "tplane": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("normal", 3), ("point", 3),
               ("orient", 3), ("size", 2), ("bg_ambient", 3), ("bg_diffuse", 3),
               ("bg_specular", 3)),
    "cylinder": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3),
                 ("centerline", 3), ("radius_height", 2)),
    "cone": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3),
             ("centerline", 3), ("radius_height", 2)),
    "ellipsoid": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3), ("axes", 3)),
    "triangle": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("point1", 3), ("point2", 3),
                 ("point3", 3)),
    "disk": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3), ("radius", 1),
             ("normal", 3)),
    "torus": (("ambient", 3), ("diffuse", 3), ("specular", 3), ("center", 3), ("axis", 3),
              ("major", 1), ("minor", 1)),
}
# the notes' numbers (ASCII digits only) and separators (space, tab, \f, \v: the C library's
# isspace, which str.split() is not: it splits on NBSP and U+2028 too)
_NUM = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z", re.ASCII)
_TOKEN = re.compile(r"[^ \t\f\v]+")


@dataclass(frozen=True)
class Item:
    """One light or object: ``x[name]`` exact Fractions, ``f[name]`` floats, per field."""
    kind: str
    index: int                  # object id (index among non-light objects), -1 for lights
    line: int
    x: dict = field(default_factory=dict)
    f: dict = field(default_factory=dict)
    form: str = ""              # the FORMS name when not the plain kind
    extras: tuple = ()          # the form's and the flags' fields, as read (not geometry)

    def __getattr__(self, name):       # obj.center, obj.radius, ... as floats
        f = self.__dict__.get("f", {})
        if name in f:
            v = f[name]
            return v[0] if name in ("radius", "theta", "major", "minor") else v
        raise AttributeError(name)


@dataclass(frozen=True)
class File:
    window: tuple               # Fractions
    viewpoint: tuple
    lights: tuple
    objects: tuple
    dialect: str
    flags: tuple = ()           # cd's header flags
    table: str = ""             # numeric: the code table when not the notes' one

    def floats(self) -> "File":
        """The same scene with the header as floats (what a float reference reads)."""
        return File(tuple(float(c) for c in self.window),
                    tuple(float(c) for c in self.viewpoint), self.lights, self.objects,
                    self.dialect, self.flags, self.table)

    def default_rows(self, columns: int) -> int:
        """rows = int(world_h / world_w · columns), the keyword programs' rule."""
        return int(self.window[1] / self.window[0] * columns)


def _lines(text: str):
    """(line number, tokens) of every line, comments removed."""
    for no, raw in enumerate(re.split(r"\r\n|\r|\n", text.lstrip("\ufeff")), 1):
        yield no, _TOKEN.findall(raw.split("#", 1)[0])


def read_text(text: str, code27: str = "auto") -> File:
    lines = [(no, t) for no, t in _lines(text) if t]
    # the header's five numbers; then a keyword, or a number (a code) starting a line
    got, k, after, worded = 0, 0, None, False
    while k < len(lines) and got < 5:
        ts = lines[k][1]
        lead = next((i for i, t in enumerate(ts) if not _NUM.match(t)), len(ts))
        if lead == 0:
            break
        got += lead
        after = ts[lead] if lead < len(ts) else None
        worded |= after is not None
        k += 1
    if after is not None and after.lower() in KEYWORDS:
        return _keyword(lines)
    # numeric: a code starts the next line, or the header alone with its words after the
    # numbers ("8 6 window"), or more than five numbers before the first word (the keyword
    # dialect would need a word there), as rt_core's parser reads it
    if got > 5 or got >= 5 and (k < len(lines) and _NUM.match(lines[k][1][0]) or
                                k == len(lines) and worded):
        try:
            return _numeric(lines, code27)
        except ValueError as first:
            # another course year's code table (layouts.CODE_TABLES): the first that
            # reads the whole file
            for name, table in CODE_TABLES.items():
                try:
                    return _numeric(lines, code27, table, name)
                except ValueError:
                    continue
            raise first
    return _keyword(lines)


def read(path, code27: str = "auto") -> File:
    """``code27``: how code 27 is read ('auto': by the line shape, this reader's own rule;
    'triangle' or 'disk')."""
    return read_text(read_input(path, "scene").decode("utf-8", "replace"), code27)


def _exact(tok: str) -> Fraction:
    if not _NUM.match(tok):
        raise ValueError(f"expected a number, found {tok!r}")
    # (as rt_core's parser: beyond float64 either way is refused, before its exact value,
    # millions of digits for 1e-9999999, is made)
    v = float(tok)
    if not math.isfinite(v) or (v == 0.0 and any(c in "123456789"
                                                 for c in re.split("[eE]", tok)[0])):
        raise ValueError(f"number {tok!r} is beyond float64's range")
    return Fraction(Decimal(tok))


def _make(form, values, line, nobj, extras=()):
    kind = form.kind
    x = {name: vals for (name, _), vals in zip(LAYOUT[kind], values)}
    f = {name: tuple(float(c) for c in vals) for name, vals in x.items()}
    return Item(kind, -1 if kind in LIGHTS else nobj, line, x, f,
                "" if form.name == kind else form.name, tuple(extras))


def _read_item(form, take, word, flags=(), extras=(), order=None):
    """The groups of one object: the kind's (with the flags' numbers after each MAT), then
    the form's extra fields.  ``order``: the groups' names in the file's order when not the
    kind's (a name the kind lacks is one number, kept as an extra)."""
    spec = dict(LAYOUT[form.kind])
    got, extras = {}, list(extras)
    for name in order or spec:
        got[name] = take(spec.get(name, 1))
        if name not in spec:
            extras.append((name, got[name][0]))
        if name.endswith("specular"):
            side = "background " if name.startswith("bg_") else ""
            extras += [(side + HEADER_FLAGS[fl], take(1)[0]) for fl in flags]
    for name, n in form.extra:
        extras.append((name, word() if n == 0 else take(1)[0] if n == 1 else take(n)))
    return [got[name] for name in spec], extras


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

    def word():
        nonlocal pos
        if pos >= len(toks):
            raise ValueError("truncated scene")
        pos += 1
        return toks[pos - 1][1]

    window, viewpoint = take(2), take(3)
    lights, objects = [], []
    while pos < len(toks):
        line, token = toks[pos]
        pos += 1
        form = form_of_keyword(token)
        values, extras = _read_item(form, take, word)
        item = _make(form, values, line, len(objects), extras)
        (lights if form.kind in LIGHTS else objects).append(item)
    return File(window, viewpoint, tuple(lights), tuple(objects), "keyword")


def _lead(toks):
    """The leading number tokens of a line."""
    for t in toks:
        if not _NUM.match(t):
            return
        yield t


def _numeric(lines, code27: str = "auto", table: dict | None = None, name: str = "") -> File:
    """The numeric dialect with the notes' code table, or ``table`` (code -> (form, the
    groups' order)) named ``name``."""
    idx = 0

    def group(n):
        nonlocal idx
        if idx >= len(lines):
            raise ValueError("truncated scene")
        no, toks = lines[idx]
        idx += 1
        lead = list(_lead(toks))
        if len(lead) < n:
            raise ValueError(f"line {no}: expected {n} numbers")
        return tuple(_exact(t) for t in lead[:n])

    def word():
        nonlocal idx
        if idx >= len(lines):
            raise ValueError("truncated scene")
        idx += 1
        return lines[idx - 1][1][0]

    window, viewpoint = group(2), group(3)
    lights, objects, flags = [], [], []
    while idx < len(lines):
        line, toks = lines[idx]
        idx += 1
        code = int(toks[0])
        if code in HEADER_FLAGS:
            flags.append(code)
            continue
        if table is not None:
            if code not in table:
                raise ValueError(f"line {line}: code {code} is not in the table")
            form, order = FORMS[table[code][0]], table[code][1]
        else:
            form, order = form_of_code(code), None
        if table is None and code == 27:    # nw's final triangle, or nw's older disk
            # (this reader's own rule, not rt_core's: the line after the MAT's (and the
            # flags') and the first point or centre has 3 numbers or more (point 2) in a
            # triangle, 1 (the radius) in a disk; ``code27`` forces one)
            at = idx + 3 + len(flags) + 1
            if at >= len(lines):
                raise ValueError("truncated scene")
            count = len(list(_lead(lines[at][1])))
            shaped = code27 if code27 in ("triangle", "disk") else \
                "triangle" if count >= 3 else "disk" if count == 1 else None
            if shaped is None:
                raise ValueError(f"line {lines[at][0]}: {count} numbers fit no layout of {code}")
            form = FORMS[shaped]
        # code 25: cd's lens with cd's header flags, or a single number after the centre
        # (nw's torus has its 3-number axis there): MAT 3 lines, the flags', the centre
        after = idx + 3 + len(flags) + 1
        if table is None and code in SHARED_CODES and (flags or (
                after < len(lines) and len(list(_lead(lines[after][1]))) == 1)):
            form = FORMS[SHARED_CODES[code]]
        extras = []
        if len(toks) > 1 and _NUM.match(toks[1]):        # nw's refraction index
            extras.append(("refraction index", _exact(toks[1])))
        values, extras = _read_item(form, group, word, flags, extras, order)
        item = _make(form, values, line, len(objects), extras)
        (lights if form.kind in LIGHTS else objects).append(item)
    return File(window, viewpoint, tuple(lights), tuple(objects), "numeric", tuple(flags),
                name)


assert set(LAYOUT) == set(KINDS) | set(LIGHTS), "scenefile.LAYOUT must cover every kind"
