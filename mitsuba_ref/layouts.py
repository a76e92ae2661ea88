"""The references' own table of how the course files write each object and light: its type
token (keyword and/or numeric code), the kind it is, and the number groups that follow the
kind's own (mitsuba_ref/scenefile.py reads them), written from the notes
(../shared/notes/course-format.md) for the references alone.

rt_core's parser has its table (rt_core/kinds.py); the references used to read that one, so
a wrong group order there (a review: the geometry-first table's light read with its
emissivity where its centre is) gave both readers the same wrong scene, and validate passed.
Two tables written apart disagree on such a file, and tools/harness/agree.py says so.  Only
the kinds' names (rt_core.kinds.KINDS, LIGHTS) are shared: names, not layouts.
"""
from __future__ import annotations

from typing import NamedTuple


class Form(NamedTuple):
    name: str
    kind: str
    code: int | None = None
    keyword: str | None = None
    extra: tuple = ()           # (group name, count) after the kind's own; count 0: a word


FORMS = {f.name: f for f in (
    Form("pointlight", "pointlight", 10, "pointlight"),
    Form("spotlight", "spotlight", 11, "spotlight"),
    Form("sphere", "sphere", 13, "sphere"),
    Form("plane", "plane", 14, "plane"),
    Form("fplane", "fplane", 15, "fplane"),
    Form("tplane", "tplane", 16, "tplane"),
    Form("cylinder", "cylinder", 22),
    Form("cone", "cone", 23),
    Form("ellipsoid", "ellipsoid", None, "ellipsoid"),
    Form("triangle", "triangle", 27, "triangle"),
    Form("disk", "disk", 29, "disk"),
    Form("psphere", "sphere", 19, None, (("shader", 1),)),
    Form("pplane", "plane", 20, None, (("shader", 1),)),
    Form("texplane", "fplane", 17, None, (("texture", 0), ("tile mode", 1))),
    Form("texsphere", "sphere", 26, None, (("texture", 0),)),
    Form("fplanetex", "fplane", None, "fplanetex",
         (("brightness", 1), ("texture size", 2), ("texture", 0))),
    Form("sphere_pixmap", "sphere", None, "sphere_pixmap",
         (("brightness", 1), ("forward", 3), ("texture", 0))),
    Form("torus", "torus", 25),
    Form("lens", "sphere"),                 # cd's code 25 (SHARED_CODES)
    Form("dispsphere", "sphere", 28, None, (("displacement map", 0),)),
)}
KEYWORDS = tuple(f.keyword for f in FORMS.values() if f.keyword)
CODES = {f.code: f.name for f in FORMS.values() if f.code is not None}
# code 25: cd's lens where the file has cd's header flags or the line after the centre
# holds one number (the radius), else nw's torus
SHARED_CODES = {25: "lens"}
# other course years' code tables: code -> (form, the groups in the file's order, None for
# the kind's own; a name the kind lacks is one number, recorded)
CODE_TABLES = {
    "geometry-first": {         # nw__a3t7.txt: geometry before the MAT, lights with a radius
        10: ("pointlight", ("center", "radius", "emissivity")),
        11: ("sphere", ("center", "radius", "ambient", "diffuse", "specular")),
        12: ("plane", ("normal", "point", "ambient", "diffuse", "specular")),
        16: ("spotlight", ("center", "radius", "emissivity", "aim", "theta")),
    },
    "early-nw": {               # nw__cone-sphere.txt: 11 sphere, 13 cylinder, 17 cone
        10: ("pointlight", ("emissivity", "center", "radius")),
        11: ("sphere", None),
        13: ("cylinder", None),
        17: ("cone", None),
    },
}
# cd's header flags: each adds one number after every MAT, in the order given
HEADER_FLAGS = {9000: "transparency", 9001: "refraction index"}


def form_of_keyword(word: str) -> Form:
    w = word.lower()
    if w not in KEYWORDS:
        raise ValueError(f"unknown object keyword {word!r}")
    return next(f for f in FORMS.values() if f.keyword == w)


def form_of_code(code: int) -> Form:
    if code not in CODES:
        raise ValueError(f"unknown object code {code}")
    return FORMS[CODES[code]]
