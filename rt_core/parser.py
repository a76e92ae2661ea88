"""Parser for the course scene files, both dialects (see notes/course-format.md).

``parse_scene(path)`` and ``parse_text(text)`` return a :class:`~rt_core.scene.Scene` or raise
:class:`~rt_core.scene.SceneError`, whose ``str`` is one line ``file:line:col: message``
(columns are 1-based and count characters).  No other exception escapes for any file content:
bytes that are not UTF-8 are decoded with replacement characters.

Rules common to both dialects
  * A file is a two-group header (world window ``w h``, viewpoint ``x y z``) and then objects
    until end of file.  A header-only file is a valid, empty scene.
  * ``#`` starts a comment that runs to the end of the line, in both dialects (the numeric
    programs never used it, but free text there may contain it).
  * Lines end at ``\\n``, ``\\r\\n`` or a lone ``\\r``; space, tab, ``\\f`` and ``\\v`` separate
    tokens.  A number is a C-style decimal literal (``3``, ``-.5``, ``1.``, ``2e-3``).
    ``nan``, ``inf``, ``infinity`` and literals that overflow (``1e999``) are rejected.
  * The dialect is told from the first token that starts a line after the five header
    numbers: a word means the keyword dialect, a number the numeric dialect.  (A keyword
    written on the viewpoint line itself also means the keyword dialect.)
  * End-of-file errors point just past the last token of the file.
  * Geometry the tracer cannot use is an error at the offending group: a zero normal, an
    orient parallel to the normal, a size/tile size or radius <= 0, a world window <= 0.
  * An object kind that the course used but this project does not implement is an error
    ``... is not supported`` naming the kind, at its type token; parsing stops there.

Keyword dialect (the finite-plane notes, ``course-scenes/keyword``)
  * A token stream: each object is a keyword (matched case-insensitively) followed by its
    number groups; groups may wrap over lines and several may share a line.  Anything else
    (free text without ``#``) is an error.

Numeric dialect (2011-2015, ``course-scenes/numeric``); rules chosen so that every real file
parses as its own course program read it
  * Each line is ``numbers [free text]``: its numbers are the leading tokens that are numbers;
    the first token that is not a number starts free text running to the end of the line
    (numbers inside free text, e.g. ``r g b ambient 5 5 15``, are text).  Blank lines are
    skipped.
  * One line carries exactly one group.  The line must start with at least as many numbers as
    the group needs; whatever follows them (text or further numbers) is ignored, as the course
    programs' ``fscanf`` + ``fgets`` ignore it (nw's ``15 15  8 6`` header is window 15 x 15).
    A line with too few numbers is an error: no real file wraps a group over lines, and
    the programs that would allow it silently misread the following line.
  * An object starts with a line whose first number is its integer code: 10 point light,
    13 sphere, 14 plane, 15 finite plane, 16 tiled plane, 22 cylinder, 23 cone (nw's
    layouts: rt_core/quadrics.py), 25 nw's torus or cd's lens (the lens with cd's header
    flags, or when the line after the centre has one number: ``_shared_code_form``),
    27 triangle, 29 disk.  Code 27 is
    a disk (centre, radius, normal) in nw's older layout: a 27 whose second geometry line
    starts with 1 number (not 3) is read as a disk, unless the ``code27`` option forces
    either (rt_core/kinds_planar.py).  A second number on the code line
    is nw's refraction index (``13 1.33``): not supported.  The other codes the course used
    (11-12, 17-29 and cd's 9000/9001 header flags, which add fields to every material) are
    named in the "not supported" error.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import re
from dataclasses import dataclass
from .inputfile import read_input
from .kinds import (CODE_TABLES, CODES, FORMS, HEADER_FLAGS, KEYWORDS, LIGHTS, SHAPED_CODES,
                    SHARED_CODES, Form)
from .kinds_planar import CODE27_CHOICES, shaped_form
from .planar import make_disk, make_triangle
from .quadrics import make_cone, make_cylinder, make_ellipsoid
from .scene import (GeometryError, Material, Num, PointLight, Scene, SceneError, SpotLight,
                    make_fplane, make_plane, make_sphere, make_tplane)
from .torus import make_torus

__all__ = ["parse_scene", "parse_text", "SUPPORTED_KEYWORDS", "SUPPORTED_CODES"]

# unambiguous (no two ways to split a digit run), so a long non-number fails in linear time
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?\Z", re.ASCII)
_INTEGER = re.compile(r"[+-]?\d{1,9}\Z", re.ASCII)
_NONFINITE = re.compile(r"[+-]?(?:nan|inf|infinity)\Z", re.IGNORECASE)
_TOKEN = re.compile(r"[^ \t\f\v]+")

# field groups per kind: (name, count, what the numbers are)
_MAT = (("ambient", 3, "r g b"), ("diffuse", 3, "r g b"), ("specular", 3, "r g b"))
_XYZ = "x y z"
_GROUPS = {
    "pointlight": (("emissivity", 3, "r g b"), ("center", 3, _XYZ)),
    "spotlight": (("emissivity", 3, "r g b"), ("center", 3, _XYZ), ("aim", 3, _XYZ),
                  ("theta", 1, "half-angle in degrees")),
    "sphere": _MAT + (("center", 3, _XYZ), ("radius", 1, "r")),
    "plane": _MAT + (("normal", 3, _XYZ), ("point", 3, _XYZ)),
    "fplane": _MAT + (("normal", 3, _XYZ), ("point", 3, _XYZ), ("orient", 3, _XYZ),
                      ("size", 2, "w h")),
    "tplane": _MAT + (("normal", 3, _XYZ), ("point", 3, _XYZ), ("xdir", 3, _XYZ),
                      ("tile size", 2, "w h"), ("background ambient", 3, "r g b"),
                      ("background diffuse", 3, "r g b"),
                      ("background specular", 3, "r g b")),
    "cylinder": _MAT + (("center", 3, _XYZ), ("centerline", 3, _XYZ),
                        ("radius height", 2, "r h")),
    "cone": _MAT + (("center", 3, _XYZ), ("centerline", 3, _XYZ), ("radius height", 2, "r h")),
    "ellipsoid": _MAT + (("center", 3, _XYZ), ("semi-axes", 3, "a b c")),
    "triangle": _MAT + (("point 1", 3, _XYZ), ("point 2", 3, _XYZ), ("point 3", 3, _XYZ)),
    "disk": _MAT + (("center", 3, _XYZ), ("radius", 1, "r"), ("normal", 3, _XYZ)),
    "torus": _MAT + (("center", 3, _XYZ), ("axis", 3, _XYZ), ("major radius", 1, "R"),
                     ("minor radius", 1, "r")),
}
QUADRIC_MAKERS = {"cylinder": make_cylinder, "cone": make_cone, "ellipsoid": make_ellipsoid}
_HEADER = (("world window", 2, "w h"), ("viewpoint", 3, _XYZ))

SUPPORTED_KEYWORDS = KEYWORDS
SUPPORTED_CODES = dict(CODES)
_CODE_WORDS = {10: "point light", 11: "spotlight", 13: "sphere", 14: "plane",
               15: "finite plane", 16: "tiled plane", 17: "textured plane",
               19: "procedural sphere", 20: "procedural plane", 26: "textured sphere",
               22: "cylinder", 23: "cone", 25: "torus (cd: lens)",
               27: "triangle (a disk in nw's older layout)", 28: "displacement sphere",
               29: "disk"}
_CODE_LIST = ", ".join(f"{c} {_CODE_WORDS[c]}" for c in sorted(CODES))

# kinds the course used that this project does not implement
_UNSUPPORTED_KEYWORDS = {
    # keyword spellings of forms read only by their numeric code (no keyword file uses them,
    # so their keyword layout is unknown)
    "psphere": "procedural sphere: only numeric code 19 is read",
    "pplane": "procedural plane: only numeric code 20 is read",
    "texplane": "textured plane: only numeric code 17 or fplanetex is read",
    "tex_plane": "textured plane: only numeric code 17 or fplanetex is read",
    "texsphere": "textured sphere: only numeric code 26 or sphere_pixmap is read",
    "projector": "projector",
    "paraboloid": "paraboloid",
    "cylinder": "cylinder",
    "cone": "cone",
    "hyperboloid": "hyperboloid",
    "torus": "torus: only numeric code 25 is read",
    "lens": "lens: only cd's numeric code 25 is read",
}
_UNSUPPORTED_CODES = {
    12: "projector",
    18: "reflective sphere",
    21: "paraboloid",
    24: "hyperboloid",
}


@dataclass(frozen=True)
class _Tok:
    text: str
    line: int
    col: int

    @property
    def end(self) -> int:
        return self.col + len(self.text)


def _show(text: str, limit: int = 40) -> str:
    """A token for a one-line message: quoted, control characters escaped, shortened."""
    s = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text[:limit])
    return f"'{s}...'" if len(text) > limit else f"'{s}'"


def _numbers(n: int) -> str:
    return f"{n} number" if n == 1 else f"{n} numbers"


class _Ctx:
    """Source text split into token lines, and error construction."""

    def __init__(self, text: str, path: str):
        self.path = path
        self.header_at: tuple = ()
        self.flags: tuple = ()
        self.code27 = "auto"          # parse option: how code 27 is read (kinds_planar.py)
        text = text.lstrip("\ufeff").replace("\r\n", "\n").replace("\r", "\n")
        self.lines: list[list[_Tok]] = []   # tokens per line, comments removed
        for lineno, raw in enumerate(text.split("\n"), 1):
            hash_at = raw.find("#")
            if hash_at >= 0:
                raw = raw[:hash_at]
            self.lines.append([_Tok(m.group(), lineno, m.start() + 1)
                               for m in _TOKEN.finditer(raw)])
        last = next((toks[-1] for toks in reversed(self.lines) if toks), None)
        self.eof = (last.line, last.end) if last else (1, 1)

    def error(self, message: str, at) -> SceneError:
        line, col = (at.line, at.col) if isinstance(at, _Tok) else at
        return SceneError(message, self.path, line, col)

    def number(self, tok: _Tok, what: str) -> float:
        """The value of a token known to be where a number must be."""
        if _NUMBER.match(tok.text):
            value = Num(tok.text)
            if value == 0.0 and any(c in "123456789" for c in re.split("[eE]", tok.text)[0]):
                # (kept exact, 1e-9999999 made every exact decision's numbers millions of
                # digits long: a run of minutes that ignored SIGTERM)
                raise self.error(f"{what}: number {_show(tok.text)} is below float64's "
                                 "range (it rounds to 0): write 0 or a larger number", tok)
            if math.isfinite(value):
                return value
            raise self.error(f"{what}: number {_show(tok.text)} is out of range (not finite)",
                             tok)
        if _NONFINITE.match(tok.text):
            raise self.error(f"{what}: {_show(tok.text)} is not a finite number", tok)
        raise AssertionError("not a number token")  # callers check _NUMBER first


def _is_number(tok: _Tok) -> bool:
    return bool(_NUMBER.match(tok.text) or _NONFINITE.match(tok.text))


def _detect(ctx: _Ctx) -> str:
    """'keyword' or 'numeric', from the first line-start token after the 5 header numbers."""
    count, free_text = 0, False
    for toks in ctx.lines:
        if not toks:
            continue
        if count >= 5:
            return "numeric" if _is_number(toks[0]) else "keyword"
        lead = 0
        while lead < len(toks) and _is_number(toks[lead]):
            lead += 1
        if lead == 0:
            # a word before the header is complete: a keyword file with a broken header,
            # unless earlier header lines carried free text
            return "numeric" if free_text else "keyword"
        count += lead
        if count > 5:
            return "numeric"       # keyword dialect: the next token would be a number
        if lead < len(toks):
            word = toks[lead].text.lower()
            if count == 5 and (word in SUPPORTED_KEYWORDS or word in _UNSUPPORTED_KEYWORDS):
                return "keyword"
            free_text = True
    return "numeric" if free_text else "keyword"


def _unsupported_keyword(ctx: _Ctx, tok: _Tok) -> SceneError:
    name = tok.text.lower()
    return ctx.error(f"{name} ({_UNSUPPORTED_KEYWORDS[name]}) is not supported "
                     f"(supported: {', '.join(SUPPORTED_KEYWORDS)})", tok)


def _unsupported_code(ctx: _Ctx, code: int, tok: _Tok) -> SceneError:
    return ctx.error(f"{code} ({_UNSUPPORTED_CODES[code]}) is not supported "
                     f"(supported codes: {_CODE_LIST})", tok)


# --- building objects -------------------------------------------------------------------

def _build(ctx: _Ctx, kind: str, start: _Tok, values: list, where: list):
    """Make the light or object of ``kind`` from its groups; geometry errors point at the
    offending group."""
    if kind == "pointlight":
        return PointLight(tuple(values[0]), tuple(values[1]), start.line)
    if kind == "spotlight":
        theta = values[3][0]
        if not 0 < theta <= 180:
            raise ctx.error(f"spotlight: half-angle {theta:g} must be in (0, 180] degrees",
                            where[3][0])
        if tuple(values[2]) == tuple(values[1]):
            raise ctx.error("spotlight: the point it aims at is its centre (no direction)",
                            where[2][0])
        return SpotLight(tuple(values[0]), tuple(values[1]), tuple(values[2]), theta,
                         start.line)
    mat = Material(tuple(values[0]), tuple(values[1]), tuple(values[2]))
    g = values[3:]
    if kind in ("triangle", "disk"):
        return _build_planar(ctx, kind, mat, start, g, where)
    try:
        if kind == "sphere":
            return make_sphere(mat, tuple(g[0]), g[1][0], start.line)
        if kind == "plane":
            return make_plane(mat, tuple(g[0]), tuple(g[1]), start.line)
        if kind in QUADRIC_MAKERS:
            return QUADRIC_MAKERS[kind](mat, *map(tuple, g), start.line)
        if kind == "torus":
            return make_torus(mat, tuple(g[0]), tuple(g[1]), g[2][0], g[3][0], start.line)
        if kind == "fplane":
            return make_fplane(mat, tuple(g[0]), tuple(g[1]), tuple(g[2]), tuple(g[3]),
                               start.line)
        bg = Material(tuple(g[4]), tuple(g[5]), tuple(g[6]))
        return make_tplane(mat, tuple(g[0]), tuple(g[1]), tuple(g[2]), tuple(g[3]), bg,
                           start.line)
    except GeometryError as exc:
        raise ctx.error(f"{kind}: {_geometry_message(kind, str(exc))}",
                        _geometry_location(kind, str(exc), start, g, where)) from None


def _build_planar(ctx: _Ctx, kind: str, mat, start: _Tok, g: list, where: list):
    """A triangle (three points) or disk (centre, radius, normal); a geometry error points
    at the group it is about (the triangle's third point, the disk's radius or normal)."""
    try:
        if kind == "triangle":
            return make_triangle(mat, tuple(g[0]), tuple(g[1]), tuple(g[2]), start.line)
        return make_disk(mat, tuple(g[0]), g[1][0], tuple(g[2]), start.line)
    except GeometryError as exc:
        msg = str(exc)
        at = where[5][0] if kind == "triangle" or msg.startswith("normal") else where[4][0]
        raise ctx.error(f"{kind}: {msg}", at) from None


def _geometry_message(kind: str, msg: str) -> str:
    # the tiled plane's orient is called xdir in the format table
    return msg.replace("orient", "xdir", 1) if kind == "tplane" else msg


def _geometry_location(kind: str, msg: str, start: _Tok, g: list, where: list):
    """The group a GeometryError from scene.py is about: groups after the material are
    normal, point/center, orient/xdir, size (where[3], [4], [5], [6])."""
    if msg.startswith("normal"):
        return where[3][0]
    if msg.startswith(("orient", "projected orient", "n x orient")):
        return where[5][0]
    if msg.startswith(("size", "tile size")):
        return where[6][0] if not g[3][0] > 0 else where[6][1]
    if msg.startswith(("radius and height", "semi-axes")):   # quadrics: their last group
        return where[-1][next(i for i, c in enumerate(g[-1]) if not c > 0)]
    if msg.startswith("radius"):
        return where[4][0]
    if kind == "torus":          # centre, axis, major radius, minor radius
        return {"axis": where[4], "major": where[5], "minor": where[6]}.get(
            msg.split()[0], [start])[0]
    return start


def _check_window(ctx: _Ctx, window: list, where: list) -> None:
    if not (window[0] > 0 and window[1] > 0):
        raise ctx.error(f"header: world window ({window[0]:g}, {window[1]:g}) must be "
                        "positive (w h)", where[0] if not window[0] > 0 else where[1])


def _read_header(ctx: _Ctx, group):
    """The two header groups (window w h, viewpoint x y z) with the dialect's reader."""
    window, wloc = group("header", *_HEADER[0])
    _check_window(ctx, window, wloc)
    viewpoint, vloc = group("header", *_HEADER[1])
    ctx.header_at = tuple((t.line, t.col) for t in wloc + vloc)
    return window, viewpoint


def _read_object(ctx: _Ctx, form: Form, start: _Tok, group, word, lights: list,
                 objects: list, flags=(), extras=(), order=None):
    """Read the groups of one object or light written in ``form`` with the dialect's
    ``group`` (numbers) and ``word`` (a file name) readers, build it and append it to
    ``lights`` or ``objects``.  ``flags``: cd's header flags, one number after every MAT
    each; ``extras``: fields already read (nw's refraction index on the code line);
    ``order``: the groups' names in the file's order when not the kind's (another code
    table: kinds.CODE_TABLES); a name the kind lacks is one number, recorded."""
    kind = form.kind
    spec = {name: (n, desc) for name, n, desc in _GROUPS[kind]}
    got, extras = {}, list(extras)
    for name in order or spec:
        n, desc = spec.get(name, (1, "a number"))
        v, locs = group(form.name, name, n, desc)
        if name not in spec:
            extras.append((name, v[0]))
        got[name] = (v, locs)
        if name.endswith("specular"):                  # the end of a MAT: the flags' fields
            prefix = name[:-len("specular")]
            for f in flags:
                field = prefix + HEADER_FLAGS[f]
                fv, _ = group(form.name, f"{field} (header flag {f})", 1, "a number")
                extras.append((field, fv[0]))
    values = [got[name][0] for name in spec]
    where = [got[name][1] for name in spec]
    for name, n in form.extra:                         # the form's own fields, recorded
        if n == 0:
            extras.append((name, word(form.name, name)))
        else:
            fv, _ = group(form.name, name, n, "numbers" if n > 1 else "a number")
            extras.append((name, fv[0] if n == 1 else tuple(fv)))
    obj = _build(ctx, kind, start, values, where)
    if kind not in LIGHTS:            # where each number is, for errors found later
        obj = dataclasses.replace(obj, at=tuple(
            (name, tuple((t.line, t.col) for t in locs))
            for (name, _, _), locs in zip(_GROUPS[kind], where)),
            form="" if form.name == kind else form.name, extras=tuple(extras))
    (lights if kind in LIGHTS else objects).append(obj)


# --- keyword dialect ----------------------------------------------------------------------

def _parse_keyword(ctx: _Ctx):
    toks = [t for line in ctx.lines for t in line]
    pos = 0

    def group(what: str, name: str, n: int, desc: str):
        nonlocal pos
        vals, locs = [], []
        for _ in range(n):
            if pos >= len(toks):
                raise ctx.error(f"{what}: expected {_numbers(n)} for {name} ({desc}), "
                                "found end of file", ctx.eof)
            tok = toks[pos]
            if not _is_number(tok):
                raise ctx.error(f"{what}: expected {_numbers(n)} for {name} ({desc}), "
                                f"found {_show(tok.text)}", tok)
            vals.append(ctx.number(tok, what))
            locs.append(tok)
            pos += 1
        return vals, locs

    def word(what: str, name: str) -> str:
        nonlocal pos
        if pos >= len(toks):
            raise _no_word(ctx, what, name)
        pos += 1
        return Word.of(toks[pos - 1])

    window, viewpoint = _read_header(ctx, group)
    lights, objects = [], []
    while pos < len(toks):
        start = toks[pos]
        kind = start.text.lower()
        if kind not in SUPPORTED_KEYWORDS:
            if kind in _UNSUPPORTED_KEYWORDS:
                raise _unsupported_keyword(ctx, start)
            found = (f"number {_show(start.text)}" if _is_number(start)
                     else f"unknown keyword {_show(start.text)}")
            raise ctx.error(f"expected an object keyword ({', '.join(SUPPORTED_KEYWORDS)}), "
                            f"found {found}", start)
        pos += 1
        form = next(f for f in FORMS.values() if f.keyword == kind)
        _read_object(ctx, form, start, group, word, lights, objects)
    return window, viewpoint, lights, objects


class Word(str):
    """A file-name field (a texture) as written, with where it is (``line``, ``col``) for
    errors found later (a texture that cannot be found or read)."""
    line: int | None = None
    col: int | None = None

    @classmethod
    def of(cls, tok) -> "Word":
        w = cls(tok.text)
        w.line, w.col = tok.line, tok.col
        return w


def _no_word(ctx: _Ctx, what: str, name: str) -> SceneError:
    """The error of a file-name field (a texture) missing at the end of the file."""
    return ctx.error(f"{what}: expected the {name} (a file name), found end of file", ctx.eof)


# --- numeric dialect ----------------------------------------------------------------------

def lead_count(toks: list[_Tok]) -> int:
    """How many tokens at the start of a line are numbers."""
    k = 0
    while k < len(toks) and _NUMBER.match(toks[k].text):
        k += 1
    return k


def _parse_numeric(ctx: _Ctx, table: dict | None = None):
    """The numeric dialect with the notes' code table, or with ``table`` (code -> (form,
    the groups' order), one of kinds.CODE_TABLES)."""
    content = [toks for toks in ctx.lines if toks]
    idx = 0


    def group(what: str, name: str, n: int, desc: str):
        nonlocal idx
        expected = f"{what}: expected {_numbers(n)} for {name} ({desc})"
        if idx >= len(content):
            raise ctx.error(f"{expected}, found end of file", ctx.eof)
        toks = content[idx]
        idx += 1
        k = lead_count(toks)
        if k < n:
            if k < len(toks):
                bad = toks[k]
                if _NONFINITE.match(bad.text):
                    ctx.number(bad, what)        # raises the non-finite error
                raise ctx.error(f"{expected}, found {_show(bad.text)}", bad)
            raise ctx.error(f"{expected} on one line, found end of line after "
                            f"{_numbers(k)}", (toks[-1].line, toks[-1].end))
        return [ctx.number(t, what) for t in toks[:n]], toks[:n]

    def word(what: str, name: str) -> str:
        nonlocal idx
        if idx >= len(content):
            raise _no_word(ctx, what, name)
        idx += 1
        return Word.of(content[idx - 1][0])

    window, viewpoint = _read_header(ctx, group)
    lights, objects, flags = [], [], []
    while idx < len(content):
        toks = content[idx]
        start = toks[0]
        if not _INTEGER.match(start.text):
            if _is_number(start):
                found = f"number {_show(start.text)}"
            elif start.text.lower() in SUPPORTED_KEYWORDS + tuple(_UNSUPPORTED_KEYWORDS):
                found = f"keyword {_show(start.text)} (keyword and numeric dialects mixed?)"
            else:
                found = _show(start.text)
            raise ctx.error(f"expected an integer object code ({_CODE_LIST}), found {found}",
                            start)
        code = int(start.text)
        if code in HEADER_FLAGS:
            if lights or objects:
                raise ctx.error(f"header flag {code} ({HEADER_FLAGS[code]}) after the first "
                                "object; cd's flags follow the viewpoint", start)
            if code in flags:
                raise ctx.error(f"header flag {code} given twice", start)
            flags.append(code)
            idx += 1
            continue
        if table is not None:
            if code not in table:
                raise ctx.error(f"code {code} is not in this code table", start)
            name, order = table[code]
            if lead_count(toks) > 1:
                raise ctx.error("expected the code alone on its line", toks[1])
            idx += 1
            _read_object(ctx, FORMS[name], start, group, word, lights, objects, order=order)
            continue
        lens = code in SHARED_CODES and _shared_code_form(content, idx, flags)
        if code not in SUPPORTED_CODES and not lens:
            if code in _UNSUPPORTED_CODES:
                raise _unsupported_code(ctx, code, start)
            raise ctx.error(f"unknown object code {code}; expected {_CODE_LIST}", start)
        form = FORMS[SHARED_CODES[code] if lens else SUPPORTED_CODES[code]]
        extras = []
        if code in SHAPED_CODES:          # 27: a triangle, or a disk in nw's older layout
            form = _shaped(ctx, code, content, idx, len(flags), lead_count, start)
            how = "the line shape" if ctx.code27 == "auto" else "the code27 option"
            extras.append((f"code {code} read as", f"{form.kind} (by {how})"))
        if lead_count(toks) > 1:          # nw: a refraction index after the code, recorded
            if form.kind in LIGHTS:
                raise ctx.error(f"{code} ({form.kind}): expected the code alone on its line, "
                                f"found {_show(toks[1].text)}", toks[1])
            extras.append(("refraction index", ctx.number(toks[1], form.name)))
        idx += 1
        _read_object(ctx, form, start, group, word, lights, objects, flags, extras)
    ctx.flags = tuple(flags)
    return window, viewpoint, lights, objects


def _shaped(ctx: _Ctx, code: int, content: list, idx: int, nflags: int, lead_count,
            start: _Tok) -> Form:
    """The form of a code whose layout the course programs disagree on (kinds_planar.py):
    forced by the parse option, else told by how many numbers its distinguishing geometry
    line (after the code line, the MAT's three lines and one line per header flag) starts
    with."""
    geo, by_count = SHAPED_CODES[code]
    at = idx + 1 + 3 + nflags + geo
    count = lead_count(content[at]) if at < len(content) else None
    name = shaped_form(code, count, ctx.code27)
    if name is None:
        layouts = " or ".join(f"{n} ({FORMS[f].kind})" for n, f in sorted(by_count.items(),
                                                                           reverse=True))
        found = "end of file" if count is None else f"{_numbers(count)}"
        where = ctx.eof if count is None else content[at][0]
        raise ctx.error(f"{code}: its geometry line {geo + 1} must start with {layouts} "
                        f"numbers, found {found}; force a layout with --code27", where)
    return FORMS[name]
def _shared_code_form(content: list, idx: int, flags) -> bool:
    """Is the object whose code is on content[idx] written in the other course program's
    layout (kinds.SHARED_CODES: 25 is cd's lens, not nw's torus)?  Yes with cd's header
    flags; else by the line shape: the lens has one number (its radius) on the line after
    the centre, the torus three (its axis)."""
    if flags:
        return True
    after = idx + 1 + 3 + 1                 # code line, MAT (3 lines), centre
    if after >= len(content):
        return False                        # truncated: read as the torus, which reports it
    return lead_count(content[after]) == 1


# --- public API ---------------------------------------------------------------------------

def _parse(text: str, path: str, sha: str, code27: str = "auto") -> Scene:
    if "\0" in text:
        # (a NUL is no separator: a file whose line ends are NULs read as one comment line)
        k = text.index("\0")
        line = text.count("\n", 0, k) + 1
        raise SceneError("a NUL byte: a scene file is text, numbers and words separated by "
                         "spaces and line ends", path, line, k - text.rfind("\n", 0, k))
    ctx = _Ctx(text, path)
    if code27 not in CODE27_CHOICES:
        raise ValueError(f"code27 must be one of {', '.join(CODE27_CHOICES)}, not {code27!r}")
    ctx.code27 = code27
    if not any(ctx.lines):
        raise ctx.error("empty scene file: expected the world window (w h), the viewpoint "
                        "(x y z), then objects", (1, 1))
    dialect, table = _detect(ctx), ""
    if dialect == "keyword":
        window, viewpoint, lights, objects = _parse_keyword(ctx)
    else:
        try:
            window, viewpoint, lights, objects = _parse_numeric(ctx)
        except SceneError as first:
            # another course year's code table, the first that reads the whole file; else
            # the notes' table's error stands
            for table, codes in CODE_TABLES.items():
                try:
                    ctx = _Ctx(text, path)
                    ctx.code27 = code27
                    window, viewpoint, lights, objects = _parse_numeric(ctx, codes)
                    break
                except SceneError:
                    continue
            else:
                raise first from None
    scene = Scene(window=tuple(window), viewpoint=tuple(viewpoint), lights=tuple(lights),
                  objects=tuple(objects), path=path, dialect=dialect, sha256=sha,
                  header_at=ctx.header_at, flags=ctx.flags, table=table)
    from .textures import check_mappings        # (numpy: imported when a scene is read)
    check_mappings(scene)
    return scene


def parse_text(text: str | bytes, path: str = "<string>", code27: str = "auto") -> Scene:
    """Parse scene text (either dialect); ``path`` is used in messages and ``Scene.path``.
    ``Scene.sha256`` is the hash of the bytes given, or of the UTF-8 encoded text.
    ``code27``: 'auto' (by the line shape), 'triangle' or 'disk' (rt_core/kinds_planar.py)."""
    if isinstance(text, (bytes, bytearray)):
        data = bytes(text)
        return _parse(data.decode("utf-8", "replace"), path, hashlib.sha256(data).hexdigest(),
                      code27)
    return _parse(text, path, hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest(),
                  code27)


def parse_scene(path, code27: str = "auto") -> Scene:
    """Parse a scene file (either dialect). ``Scene.sha256`` is the hash of the file's bytes.

    Raises SceneError for any problem in the content; OSError (missing file, ...) as is."""
    data = read_input(path, "scene")
    return _parse(data.decode("utf-8", "replace"), str(path), hashlib.sha256(data).hexdigest(),
                  code27)
