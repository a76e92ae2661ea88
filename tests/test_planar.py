"""The planar kinds triangle (code 27) and disk (29; 27 in nw's older layout), end to end:
both readers, rt_core's kernels in f32 and f64 against the float64 oracle and the exact
oracle, the exact decisions of f64, and the Mitsuba equivalents (README "Triangle", "Disk")."""
from __future__ import annotations

from pathlib import Path

import pytest

from mitsuba_ref import scenefile
from rt_core.parser import parse_text
from rt_core.scene import SceneError

REPO = Path(__file__).resolve().parents[1]
COURSE = REPO.parent / "shared" / "course-scenes" / "numeric"
NUM = "8 6 window\n0 0 5 eye\n"
MAT = "1 1 1\n2 2 2\n0 0 0\n"
TRI = NUM + "27 triangle\n" + MAT + "1 1 -1  p1\n0 1 -1\n-2 5 -1\n"
DISK27 = NUM + "27 disk\n" + MAT + "0 .6 -2.8 center\n1.8 radius\n1 1 1 normal\n"


def fails(text, **kw) -> SceneError:
    with pytest.raises(SceneError) as info:
        parse_text(text, "s.txt", **kw)
    assert "\n" not in str(info.value)
    return info.value


def test01_code27_by_line_shape():
    """A 27 whose second geometry line has 3 numbers is a triangle, 1 number a disk; both
    readers agree, and 29 is the disk."""
    t = parse_text(TRI).objects[0]
    assert t.kind == "triangle" and t.points == ((1, 1, -1), (0, 1, -1), (-2, 5, -1))
    assert t.normal == (0.0, 0.0, -1.0)          # (P2 − P1) × (P3 − P1) = (0, 0, −4)
    d = parse_text(DISK27).objects[0]
    assert d.kind == "disk" and d.center == (0, 0.6, -2.8) and d.radius == 1.8
    assert d.given_normal == (1, 1, 1)
    d29 = parse_text(DISK27.replace("27 disk", "29 disk")).objects[0]
    assert d29 == d
    assert [o.kind for o in scenefile.read_text(TRI).objects] == ["triangle"]
    assert [o.kind for o in scenefile.read_text(DISK27).objects] == ["disk"]


def test02_code27_forced():
    """The parse option reads a 27 as the layout it names; the other layout then fails on
    its own field (a triangle's point 2 needs 3 numbers, found 1)."""
    err = fails(DISK27, code27="triangle")
    assert (err.line, "point 2") == (8, err.message.split(" for ")[1][:7]), str(err)
    assert parse_text(TRI, code27="triangle").objects[0].kind == "triangle"
    three_then_one = TRI.replace("0 1 -1\n", "0 1 -1 0\n")   # extra numbers are ignored
    assert parse_text(three_then_one).objects[0].kind == "triangle"
    with pytest.raises(ValueError, match="code27"):
        parse_text(TRI, code27="hexagon")


def test03_code27_malformed():
    """A second geometry line with 2 numbers fits neither layout: one line naming both."""
    err = fails(TRI.replace("0 1 -1\n", "0 1\n"))
    assert (err.line, err.col) == (8, 1)
    assert "3 (triangle) or 1 (disk)" in err.message and "--code27" in err.message
    err = fails(NUM + "27\n" + MAT + "1 1 1\n")
    assert "end of file" in err.message


def test04_geometry_errors():
    err = fails(TRI.replace("-2 5 -1", "2 1 -1"))              # collinear
    assert (err.line, err.col) == (9, 1) and "collinear" in err.message
    err = fails(DISK27.replace("1.8 radius", "0 radius"))
    assert (err.line, err.col) == (8, 1) and "radius" in err.message
    err = fails(DISK27.replace("1 1 1 normal", "0 0 0 normal"))
    assert (err.line, err.col) == (9, 1) and "normal" in err.message


def test05_keywords():
    kw = "8 6\n0 0 5\ntriangle 1 1 1 2 2 2 0 0 0  1 1 -1  0 1 -1  -2 5 -1\n" \
         "disk 1 1 1 2 2 2 0 0 0  0 .6 -2.8  1.8  1 1 1\n"
    s = parse_text(kw)
    assert [o.kind for o in s.objects] == ["triangle", "disk"]
    assert [o.kind for o in scenefile.read_text(kw).objects] == ["triangle", "disk"]
