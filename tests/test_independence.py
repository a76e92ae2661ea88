"""The references share no code with what they check.

* Import test: the oracles (float64, exact, pixel classification), the references' scene reader
  and geometry import nothing of rt_core's scene model, parser, camera or kernels: only the
  table of kind names (rt_core.kinds) and the rules' parameter object (rt_core.rules).
* Mutation test: a frame bug in the tracer (x̂ rotated by 90° in the plane: still orthonormal and
  right-handed) is caught by the exact oracle, which computes its frame from the numbers as
  written, and so is a normal taken from the wrong field.
* One table of kinds: every per-kind dispatch covers every kind, and an unknown kind raises.
"""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_core.kinds import KIND_CODE, KINDS

REPO = Path(__file__).resolve().parents[1]
REFERENCES = ("mitsuba_ref.oracle", "mitsuba_ref.exact", "mitsuba_ref.scenefile",
              "mitsuba_ref.geometry", "mitsuba_ref.explain", "mitsuba_ref.convert",
              "mitsuba_ref.reference", "mitsuba_ref.integrator", "mitsuba_ref.oracle_planar",
              "mitsuba_ref.exact_planar", "mitsuba_ref.convert_planar",
              "mitsuba_ref.shade_oracle", "mitsuba_ref.shade_batch")
FORBIDDEN = ("rt_core.scene", "rt_core.parser", "rt_core.camera", "rt_core.shapes",
             "rt_core.tracer", "rt_core.accel", "rt_core.decide", "rt_core.shading",
             "rt_core.render", "rt_core.quadrics", "rt_core.shapes_quadric")


@pytest.mark.parametrize("module", REFERENCES)
def test01_references_do_not_import_the_tracer(module):
    code = (f"import sys, {module}\n"
            f"print(','.join(m for m in {FORBIDDEN!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "", f"{module} imports {out}"


def test01b_converting_reads_no_more_of_the_tracer():
    """scene_xml and scene_dict, called on a parsed scene (rt_core's parser and scene model
    loaded by then), load no further module of the tracer: the converter took the scene's
    provenance from rt_core.render, which loads the tracer and its kernels."""
    code = ("import sys\n"
            "from rt_core.parser import parse_scene\n"
            "from mitsuba_ref.convert import scene_dict, scene_xml\n"
            f"sc = parse_scene({str(REPO / 'scenes' / 'mixed.txt')!r})\n"
            f"before = {{m for m in {FORBIDDEN!r} if m in sys.modules}}\n"
            "xml = scene_xml(sc, 16, shading=True, aovs=False)\n"
            "scene_dict(sc, 16, shading=True)\n"
            "assert 'rtval.converted' in xml\n"
            f"print(','.join(m for m in {FORBIDDEN!r} if m in sys.modules and m not in before))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert out == "", f"converting imports {out}"


TILTED = """8 6
0 0 5
fplane 1 1 1 0 0 0 0 0 0
  0.3 0.2 1      # normal
  -2 -1.5 -1     # corner
  1 0.4 0        # orient
  3.5 1.2        # size (not square: a rotated frame covers other pixels)
sphere 1 1 1 0 0 0 0 0 0  2 1.5 -3  0.7
"""


def _rt_ids(text, mutate=None, monkeypatch=None):
    from rt_core import backend, shapes
    from rt_core.parser import parse_text
    from rt_core.render import trace_geometry
    from rt_core.camera import make_camera
    if mutate:
        orig = shapes.object_constants
        monkeypatch.setattr(shapes, "object_constants", lambda sc: [mutate(c) for c in orig(sc)])
        import rt_core.tracer as tr
        monkeypatch.setattr(tr, "object_constants", shapes.object_constants)
    sc = parse_text(text)
    cam = make_camera(sc, 48, 36)
    g = trace_geometry(sc, cam, backend.types("f64"))
    return np.array(g["object.id"]).astype(int)


def _exact_ids(text):
    from mitsuba_ref.exact import ideal_rays, parse_exact, trace_exact
    xs = parse_exact(text)
    rays, d = ideal_rays(xs.window, xs.viewpoint, 48, 36, range(48 * 36))
    return trace_exact(xs, d, rays=rays).id


def _rotate(c):
    if c.kind != "fplane":
        return c
    return dataclasses.replace(c, xdir=c.ydir, ydir=tuple(-x for x in c.xdir))


def _wrong_normal(c):
    if c.kind != "fplane":
        return c
    return dataclasses.replace(c, n=tuple(-x for x in c.n), nq=-c.nq, g=-c.g,
                               xdir=c.ydir, ydir=c.xdir)


def test02_tracer_agrees_with_the_exact_oracle_unmutated():
    assert (_rt_ids(TILTED) == _exact_ids(TILTED)).all()


@pytest.mark.parametrize("mutation", [_rotate, _wrong_normal])
def test03_frame_mutations_are_caught(mutation, monkeypatch):
    bad = _rt_ids(TILTED, mutation, monkeypatch)
    assert (bad != _exact_ids(TILTED)).sum() > 20


def test04_every_table_covers_every_kind():
    from mitsuba_ref import convert, exact, oracle, scenefile
    from rt_core import accel, parser, shapes
    tables = {"shapes.OBJECT_T": shapes.OBJECT_T, "exact._EVAL": exact._EVAL,
              "exact.DECISIONS": exact.DECISIONS, "oracle._PREPARE": oracle._PREPARE,
              "oracle._SURFACE": oracle._SURFACE,
              "convert._SHAPES": convert._SHAPES, "convert._REACH": convert._REACH,
              "accel.LAYOUT": accel.LAYOUT,
              "scenefile.LAYOUT": {k: v for k, v in scenefile.LAYOUT.items() if k in KINDS},
              "parser._GROUPS": {k: v for k, v in parser._GROUPS.items() if k in KINDS},
              "kinds.KIND_CODE": KIND_CODE}
    for name, table in tables.items():
        assert set(table) == set(KINDS), name


def test05_unknown_kind_raises():
    from types import SimpleNamespace
    from rt_core.kinds import dispatch
    from rt_core.shapes import object_t
    with pytest.raises(ValueError, match="cone"):
        object_t(None, None, SimpleNamespace(kind="hyperboloid"), None, 0.0)
    from mitsuba_ref import oracle
    with pytest.raises(ValueError, match="hyperboloid"):
        oracle._prepare(SimpleNamespace(objects=[SimpleNamespace(kind="hyperboloid")]))
    with pytest.raises(ValueError):
        dispatch({}, "sphere")


@pytest.mark.parametrize("name", ["fplane_tilted.txt", "mixed.txt", "numeric_mixed.txt"])
def test06_references_run_on_their_own_reading(name):
    """The float64 oracle and the converter work on a scene read by mitsuba_ref.scenefile,
    whose objects carry only the numbers as written (no unit normal, no frame): a reference
    that took rt_core's normal or frame would fail here.  Their answers equal those on
    rt_core's parsed scene, and the oracle's ids equal rt_core's."""
    from mitsuba_ref import convert, scenefile
    from mitsuba_ref.oracle import render_oracle
    from rt_core.parser import parse_scene
    path = REPO / "scenes" / name
    ours = scenefile.read(path).floats()
    theirs = parse_scene(path)
    W, H = 24, 18
    a = render_oracle(ours, W, H)
    b = render_oracle(theirs, W, H)
    assert (a["object.id"] == b["object.id"]).all()
    assert np.array_equal(a["depth.Z"], b["depth.Z"])
    ids = _rt_ids_of(path, W, H).reshape(H, W)
    assert (ids == a["object.id"]).mean() > 0.97
    assert convert.scene_dict(ours, W, H).keys() == convert.scene_dict(theirs, W, H).keys()


def _rt_ids_of(path, W, H):
    from rt_core import backend
    from rt_core.camera import make_camera
    from rt_core.parser import parse_scene
    from rt_core.render import trace_geometry
    sc = parse_scene(path)
    g = trace_geometry(sc, make_camera(sc, W, H), backend.types("f64"))
    return np.array(g["object.id"]).astype(int)


COMMANDS = {
    "compare": lambda s, o: ["compare", s, "--columns", "16"],
    "compare --shaded": lambda s, o: ["compare", s, "--columns", "16", "--shaded"],
    "validate": lambda s, o: ["validate", s, "--columns", "16", "-o", o],
    "check": lambda s, o: ["check", s, o + ".ppm"],
    "check --run": lambda s, o: ["check", "--run", "false {scene} {out}", "--columns", "16",
                                 s],
    "convert": lambda s, o: ["convert", s, "--columns", "16", "-o", o + ".xml"],
}


@pytest.mark.parametrize("command", COMMANDS)
def test07_a_parser_bug_does_not_pass_a_comparison(command, monkeypatch, tmp_path, capsys):
    """The commands hand rt_core's parsed scene to the references (the converter, the shading
    oracle): a parser that read every radius 1.5 times too large passed compare, compare
    --shaded and validate (a review).  Each command now reads the file with the references'
    own reader too (tools/harness/agree.py) and refuses it where the two differ."""
    import rt_core.parser as P
    from rt_core.scene import Num
    from tools.cli import main
    orig = P.make_sphere
    monkeypatch.setattr(P, "make_sphere",
                        lambda mat, c, r, line=0: orig(mat, c, Num(repr(float(r) * 1.5)), line))
    (tmp_path / "x.ppm").write_bytes(b"P6 16 12 255\n" + bytes(16 * 12 * 3))
    scene = str(REPO / "scenes" / "sphere.txt")
    code = main(COMMANDS[command](scene, str(tmp_path / "x")))
    out = capsys.readouterr()
    assert code == 2 and "sphere.txt:11: rt_core's parser and the references' own reader " \
        "read this file differently (object 1 (sphere, line 11): radius (3) against (2))" in \
        out.out + out.err, out


def test07b_a_course_file_read_differently_fails_validate(monkeypatch):
    """A parser bug that only course files show (a review: numbers written '-.5' read as
    '.5'): validate skipped the files it broke as malformed and passed.  A course file the
    two readers read differently, or that rt_core refuses while the references' reader
    reads it, is a failure of the run ('disagree'); the four files both refuse stay
    skipped as malformed."""
    import rt_core.parser as P
    from rt_core.scene import Num
    from tools.harness.validate import (default_scene_paths, failed_reading, load_supported,
                                        skip_case)
    if not (REPO.parent / "shared" / "course-scenes").is_dir():
        pytest.skip("../shared/course-scenes is not here")
    paths = default_scene_paths()
    _, before = load_supported(paths, explicit=False)
    assert not failed_reading(before) and len(before) == 4, before
    monkeypatch.setattr(P, "Num", lambda text: Num(text.replace("-.", ".")))
    _, after = load_supported(paths, explicit=False)
    failed = failed_reading(after)
    assert len(failed) >= 10, [s.category for s in after]
    assert {s.path for s in after} - {s.path for s in failed} == {s.path for s in before}
    assert all(skip_case(s).failure for s in failed)
    # a parser that refuses such numbers instead: its errors are no 'malformed' skip either
    number = P._Ctx.number

    def refuse(self, tok, what):
        if tok.text.startswith("-."):
            raise self.error(f"{what}: no such number", tok)
        return number(self, tok, what)
    monkeypatch.setattr(P, "Num", Num)
    monkeypatch.setattr(P._Ctx, "number", refuse)
    _, refused = load_supported(paths, explicit=False)
    failed = failed_reading(refused)
    assert len(failed) >= 10 and all("no such number" in s.reason for s in failed)
    assert {s.path for s in refused} - {s.path for s in failed} == {s.path for s in before}


def test07bb_validate_exits_1_on_a_course_file_read_differently(monkeypatch, tmp_path,
                                                                  capsys):
    """The command: such files are failures on stderr and in JUnit, the run exits 1."""
    import rt_core.parser as P
    from rt_core.scene import Num
    from tools.cli import main
    if not (REPO.parent / "shared" / "course-scenes").is_dir():
        pytest.skip("../shared/course-scenes is not here")
    monkeypatch.setattr(P, "Num", lambda text: Num(text.replace("-.", ".")))
    junit = tmp_path / "v.xml"
    code = main(["validate", "--columns", "8", "--shaded-columns", "0", "--mode", "rays",
                 "--precision", "f32", "-o", str(tmp_path / "v"), "--junit", str(junit)])
    err = capsys.readouterr().err
    failed = err.count("FAILED (disagree): ")
    assert code == 1 and failed >= 10, err[-2000:]
    assert f"read differently by rt_core and the references (FAILED)): {failed} failed" in err
    assert junit.read_text().count("<failure") == failed


@pytest.mark.parametrize("command", ["compare", "compare --shaded", "validate"])
def test07c_the_references_count_the_rows_themselves(command, monkeypatch, tmp_path, capsys):
    """rt_core's default row count (its window's width and height swapped in the notes'
    int(h/w·columns), a review) was handed to both sides, and validate passed; the
    references' own rule now has to agree (exit 2, one line, where it does not)."""
    from rt_core.scene import Scene
    from tools.cli import main
    monkeypatch.setattr(Scene, "default_rows",
                        lambda self, columns: int(self.window[0] / self.window[1] * columns))
    scene = str(REPO / "scenes" / "sphere.txt")
    code = main(COMMANDS[command](scene, str(tmp_path / "x")))
    out = capsys.readouterr()
    assert code == 2 and "rt_core's camera gives 16 columns 21 rows where the references' " \
        "own rule gives 12" in out.err, out


def test07d_the_references_read_the_layouts_of_their_own_table(monkeypatch):
    """The references' reader has its own forms and code tables (mitsuba_ref/layouts.py): a
    wrong group order in rt_core's (a review: the geometry-first light's emissivity read
    where its centre is) read both sides the same wrong scene, and nw__a3t7 passed all five
    comparisons.  Now the readers differ there."""
    import rt_core.kinds as K
    from mitsuba_ref import scenefile
    from tools.harness.agree import ReadersDiffer, parse_agreed
    for name in ("CODE_TABLES", "FORMS", "HEADER_FLAGS", "SHARED_CODES"):
        assert getattr(scenefile, name) is not getattr(K, name), name
    path = REPO.parent / "shared" / "course-scenes" / "numeric" / "nw__a3t7.txt"
    if not path.is_file():
        pytest.skip("../shared/course-scenes is not here")
    parse_agreed(path)
    table = dict(K.CODE_TABLES["geometry-first"])
    table[10] = ("pointlight", ("emissivity", "radius", "center"))
    monkeypatch.setitem(K.CODE_TABLES, "geometry-first", table)
    with pytest.raises(ReadersDiffer):
        parse_agreed(path)


def test08_both_readers_agree_on_every_scene():
    """Every bundled, test and course scene: the same numbers, kinds and forms to both."""
    from rt_core.scene import SceneError
    from tools.harness.agree import parse_agreed
    paths = sorted([*REPO.glob("scenes/*.txt"), *REPO.glob("tests/ctracer/scenes/*.txt"),
                    *(REPO.parent / "shared" / "course-scenes").glob("*/*.txt")])
    agreed = 0
    for p in paths:
        try:
            parse_agreed(p)
            agreed += 1
        except SceneError as e:
            assert "read this file differently" not in str(e), e
    assert agreed >= 25


def test05_code27_layout_rule_is_the_references_own(tmp_path, monkeypatch):
    """The references' reader tells code 27's triangle from nw's older disk by a rule of its
    own: with rt_core's rule swapped (3 numbers a disk), the two readers differ and the file
    is refused (it passed every comparison, the triangle traced as a disk: a review)."""
    from rt_core import kinds_planar
    from rt_core.scene import SceneError
    from tools.harness.agree import parse_agreed
    path = tmp_path / "tri27.txt"
    path.write_text("8 6\n0 0 5\n27\n1 1 0\n2 2 1\n0 0 0\n-2 -1 -3\n2 -1.5 -3\n0 1.5 -3\n"
                    "10\n8 8 8\n0 3 1\n")
    assert parse_agreed(path).objects[0].kind == "triangle"
    for force in ("triangle", "disk"):
        assert parse_agreed(path, force).objects[0].kind == force
    monkeypatch.setitem(kinds_planar.SHAPED_CODES, 27, (1, {3: "disk", 1: "triangle"}))
    with pytest.raises(SceneError, match="read this file differently"):
        parse_agreed(path)
