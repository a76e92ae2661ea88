"""Code 25: cd's lens (a sphere with a stand-in note) and nw's torus.

The lens: both readers decide the 25 layout the same way (cd's header flags, or one number
after the centre) and read it as the sphere (centre, radius), with the lens's stand-in note
in the scene's provenance lines."""
from __future__ import annotations

from pathlib import Path

import pytest

from mitsuba_ref import scenefile
from rt_core.parser import parse_scene, parse_text

HERE = Path(__file__).resolve()
REPO = HERE.parents[1]
COURSE = HERE.parents[2] / "shared" / "course-scenes" / "numeric"
_M = "1 1 1\n1 1 1\n0 0 0\n"
NUM = "8 6\n0 0 5\n"


def _course(name):
    path = COURSE / name
    if not path.is_file():
        pytest.skip(f"real course scenes not found at {COURSE}")
    return path


def test01_cd_lens_is_read_as_a_sphere_with_a_stand_in():
    path = _course("cd__lens.txt")
    s = parse_scene(path)
    lens = s.objects[-1]
    assert (lens.kind, lens.form, lens.center, lens.radius, lens.line) == \
        ("sphere", "lens", (0.0, 0.0, -1.0), 1.0, 33)
    assert dict(lens.extras) == {"transparency": 0.9, "refraction index": 1.33}
    assert any(line.startswith("line 33: cd's lens (code 25): traced as the sphere")
               for line in s.stand_ins())
    r = scenefile.read(path).objects[-1]
    assert (r.kind, r.form, r.center, r.radius) == ("sphere", "lens", (0.0, 0.0, -1.0), 1.0)


def test02_lens_without_flags_by_its_line_shape():
    text = NUM + "25\n" + _M + "0 0 -4 centre\n1.5 radius\n"
    s = parse_text(text)
    assert (s.objects[0].kind, s.objects[0].form, s.objects[0].radius) == ("sphere", "lens", 1.5)
    r = scenefile.read_text(text).objects[0]
    assert (r.kind, r.form, r.radius) == ("sphere", "lens", 1.5)
