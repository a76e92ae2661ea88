"""Mitsuba renders the course image: the ``course`` integrator and ``course_material`` plugins
(mitsuba_ref/integrator.py), ``rtval convert --shading``, ``rtval render --mitsuba`` and
``rtval compare --shaded`` (tools/harness/shaded.py).

* Every bundled scene and a sample of course scenes: rt_core's 8-bit image and Mitsuba's
  agree at every pixel except ``rounding`` and ``boundary`` ones (both decided by the float64
  shading oracle with float32's bounds); the sweep over every course scene is ``slow``.
* A real shading error (1/d², a missing shadow, a wrong reflection direction) in the
  integrator is reported ``wrong``.
* The XML that ``rtval convert --shading`` writes renders, through ``rtval render
  --mitsuba``, the same image as the dict.
"""
from __future__ import annotations

import os

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_core.parser import parse_scene, parse_text
from tools.harness.shaded import SHADED_CODE, compare_shaded, mitsuba_course_image
from tools.harness.validate import default_scene_paths

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = sorted((ROOT / "scenes").glob("*.txt"))
COURSE = Path(__file__).resolve().parents[2] / "shared" / "course-scenes"
# course scenes with mirrors, tiles, spotlights, many lights, a plane in z = 0
SAMPLE = ["keyword/rm768__hisworld.txt", "numeric/m4__v1_r06.txt", "numeric/m4__v1_r04.txt",
          "numeric/cbl__specTile.txt", "numeric/cd__spot1.txt"]
W = 32


def _rtval(*args, **kw):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)], cwd=ROOT,
                          capture_output=True, text=True, **kw)


@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test01_bundled_scenes_agree(path):
    cmp = compare_shaded(parse_scene(path), W)
    assert cmp.ok, (cmp.counts, cmp.worst)
    assert cmp.counts["match"] > 0.9 * cmp.columns * cmp.rows


@pytest.mark.skipif(not COURSE.is_dir(), reason="../shared/course-scenes is not there")
@pytest.mark.parametrize("name", SAMPLE)
def test02_course_scenes_agree(name):
    path = COURSE / name
    if not path.exists():
        pytest.skip(f"{name} is not in this corpus")
    cmp = compare_shaded(parse_scene(path), W)
    assert cmp.ok, (cmp.counts, cmp.worst)


@pytest.mark.slow
@pytest.mark.skipif(not COURSE.is_dir(), reason="../shared/course-scenes is not there")
def test03_every_supported_scene_agrees():
    from tools.harness.validate import load_supported
    scenes, _ = load_supported(default_scene_paths(), explicit=False)
    bad = {}
    for sc in scenes:
        cmp = compare_shaded(sc, W)
        if not cmp.ok:
            bad[sc.path] = (cmp.counts, cmp.worst[:2])
    assert not bad, bad


# --- a real shading error is reported wrong --------------------------------------------------

def _broken(kind: str):
    """A course integrator with one deliberate shading error, registered under its own name."""
    from mitsuba_ref.convert import mitsuba
    from mitsuba_ref.integrator import classes
    mi = mitsuba()
    base = classes(mi)[1]
    dr = __import__("drjit")

    class Broken(base):
        def light_term(self, dif, E, c, ld):
            if kind == "inverse_square":
                return dif * E * (c / (ld * ld))
            return base.light_term(self, dif, E, c, ld)

        def reflected(self, d, N):
            if kind == "reflection":
                return dr.normalize(d + 2 * dr.dot(d, N) * N)     # through the surface
            return base.reflected(self, d, N)

        def blocked(self, scene, p, L, ld, leave, cast):
            if kind == "no_shadow":
                return mi.Bool(False)
            return base.blocked(self, scene, p, L, ld, leave, cast)

        def _normal(self, att, p):
            N = base._normal(self, att, p)
            if kind == "cylinder_normal":                       # inward on every cylinder
                return dr.select(att("cylinder") > 0.5, -N, N)
            return N

    name = f"course_broken_{kind}"
    mi.register_integrator(name, lambda props: Broken(props))
    return name


SHADOWS = ROOT / "scenes" / "shade_shadows.txt"
MIRRORS = ROOT / "scenes" / "shade_mirrors.txt"
CYLINDERS = ROOT / "scenes" / "cylinders.txt"


@pytest.mark.parametrize("kind, path", [("inverse_square", SHADOWS), ("no_shadow", SHADOWS),
                                        ("reflection", MIRRORS)])
def test04_a_shading_error_is_wrong(kind, path):
    cmp = compare_shaded(parse_scene(path), W, integrator=_broken(kind))
    assert not cmp.ok
    assert cmp.counts["wrong"] > 20, cmp.counts
    # FLIP sees it too: its mean is positive and its hottest pixel is one that differs
    assert cmp.summary()["flip_mean"] == cmp.flip_mean > 0
    y, x = np.unravel_index(int(np.argmax(cmp.flip)), cmp.flip.shape)
    assert (cmp.ours[y, x] != cmp.theirs[y, x]).any()


def test04b_flip_map_in_the_evidence(tmp_path):
    from PIL import Image
    from tools.harness.flip import flip_colours
    from tools.harness.shaded import write_shaded_evidence
    cmp = compare_shaded(parse_scene(SHADOWS), W, integrator=_broken("no_shadow"))
    paths = write_shaded_evidence(cmp, str(tmp_path), "s")
    assert [os.path.basename(p) for p in paths] == [f"s.shaded.{n}.png" for n in
                                                    ("ours", "mitsuba", "classes", "flip")]
    with Image.open(paths[-1]) as im:
        assert float(im.text["rtval.flip.mean"]) == cmp.flip_mean
        pic = np.asarray(im.convert("RGB"))
    np.testing.assert_array_equal(pic, flip_colours(cmp.flip))       # the map, pixel for pixel
    same = (cmp.ours == cmp.theirs).all(-1)
    bright = pic.astype(int).sum(-1)
    assert bright[~same].mean() > bright[same].mean()  # the differing pixels are hotter


def test05_clip_inside_one_scene():
    """Spheres are not clipped and planes are: a sphere between the viewpoint and the window
    shows, a plane's part in front of the window does not (the plane behind it shows
    through), all in one Mitsuba scene."""
    sc = parse_text("8 6  0 0 5\n"
                    "pointlight 9 9 9  2 3 4\n"
                    "sphere 1 0 0  4 0 0  0 0 0  -1.5 0 2.5  0.6\n"
                    "plane 0 1 0  0 3 0  0 0 0  1 0 1  0 0 0\n"
                    "plane 0 0 1  0 0 3  0 0 0  0 0 1  0 0 -6\n")
    cmp = compare_shaded(sc, W)
    assert cmp.ok, (cmp.counts, cmp.worst)
    I = mitsuba_course_image(sc, W, cmp.rows)
    # the sphere (red, in front of the window) and the clipped plane's far part (green)
    # and the back wall (blue, where the tilted plane is clipped) are all in the image
    assert (I[..., 0] > I[..., 1] + 0.05).any()
    assert (I[..., 2] > 0.05).any() and (I[..., 1] > 0.05).any()


@pytest.mark.parametrize("name", ["shade_tiles", "textured", "cylinders"])
def test06_xml_renders_like_the_dict(tmp_path, name):
    """rtval convert --shading writes XML that rtval render --mitsuba renders to the same
    8-bit image as the dict scene (compare_shaded's), with provenance in the PNG; a textured
    scene's texels go to EXR files beside the XML."""
    from rt_core.textures import attach
    from tools.harness.shaded import quantize32
    path = ROOT / "scenes" / f"{name}.txt"
    xml = tmp_path / "tiles.xml"
    r = _rtval("convert", path, "--columns", W, "--shading", "-o", xml)
    assert r.returncode == 0, r.stderr
    assert 'type="course"' in xml.read_text() and 'type="course_material"' in xml.read_text()
    ppm, png = tmp_path / "m.ppm", tmp_path / "m.png"
    r = _rtval("render", "--mitsuba", xml, "--ppm", ppm, "--png", png)
    assert r.returncode == 0, r.stderr
    from rt_core.imageio import read_image
    sc = attach(parse_scene(path))
    want = quantize32(mitsuba_course_image(sc, W, sc.default_rows(W)))
    assert np.array_equal(read_image(str(ppm)), want)
    assert b"rtval.integrator" in png.read_bytes()
    assert len(list(tmp_path.glob("tiles.xml.*_texture.exr"))) == 2 * (name == "textured")


def test07_render_mitsuba_refuses_what_it_cannot_do(tmp_path):
    xml = tmp_path / "aov.xml"
    assert _rtval("convert", ROOT / "scenes" / "sphere.txt", "--columns", 16, "-o",
                  xml).returncode == 0
    r = _rtval("render", "--mitsuba", xml, "--ppm", tmp_path / "x.ppm")
    assert r.returncode == 2 and "not 'course'" in r.stderr and len(r.stderr.splitlines()) == 1
    assert not (tmp_path / "x.ppm").exists()
    r = _rtval("render", "--mitsuba", xml, "--columns", 8, "--ppm", tmp_path / "x.ppm")
    assert r.returncode != 0 and "--columns does not apply" in r.stderr
    r = _rtval("render", ROOT / "scenes" / "sphere.txt", "--ppm", tmp_path / "x.ppm")
    assert r.returncode != 0 and "--columns" in r.stderr
    # refused before the XML is read or Mitsuba started (it was after loading the scene)
    r = _rtval("render", "--mitsuba", tmp_path / "none.xml", "--explain", "--ppm",
               tmp_path / "x.ppm")
    assert r.returncode == 64 and "--explain and --shade do not apply" in r.stderr, r.stderr
    # an XML whose materials lack their course ids (hand-made, or an older convert)
    shaded = tmp_path / "s.xml"
    assert _rtval("convert", ROOT / "scenes" / "mixed.txt", "--columns", 16, "--shading",
                  "-o", shaded).returncode == 0
    old = tmp_path / "old.xml"
    old.write_text("\n".join(ln for ln in shaded.read_text().splitlines()
                             if "course_id" not in ln))
    r = _rtval("render", "--mitsuba", old, "--ppm", tmp_path / "x.ppm")
    assert r.returncode == 2 and "course_id" in r.stderr and len(r.stderr.splitlines()) == 1
    assert not (tmp_path / "x.ppm").exists()
    r = _rtval("validate", ROOT / "scenes" / "sphere.txt", "--shaded-columns", 1, "-o",
               tmp_path / "v")
    assert r.returncode == 2 and "at least 2" in r.stderr
    r = _rtval("compare", ROOT / "scenes" / "sphere.txt", "--columns", 8, "--max-dist", 5)
    assert r.returncode == 64 and "--max-dist goes with --shaded" in r.stderr


def test07d_an_edited_xml_says_why_and_what_it_rendered(tmp_path):
    """A porter's edits to a --shading XML (a helper's review): a directional emitter was a
    KeyError traceback (exit 1), now one line, exit 2, nothing written; the integrator's own
    refusal (screen_clip 'x') was cut to 'Traceback (most recent call last):', now its
    reason; sampling 'centers', rtval's own spelling, is taken; and the outputs of an XML
    whose max_dist was edited recorded the converted 1000, now the 3 rendered, with the
    XML's own hash."""
    from rt_core.exrio import read_exr
    base = tmp_path / "base.xml"
    assert _rtval("convert", ROOT / "scenes" / "mixed.txt", "--columns", 16, "--shading",
                  "-o", base).returncode == 0
    text = base.read_text()
    cases = [("dir", text.replace("</scene>", '<emitter type="directional"><vector '
                                  'name="direction" value="0,-1,0"/></emitter>\n</scene>'),
              "the emitter DirectionalEmitter is not a course light"),
             ("clip", text.replace('name="screen_clip" value="&gt;"', 'name="screen_clip" '
                                   'value="x"'), "screen_clip must be '>', '>=' or 'off'")]
    for name, edited, said in cases:
        xml = tmp_path / f"{name}.xml"
        xml.write_text(edited)
        assert edited != text
        r = _rtval("render", "--mitsuba", xml, "--ppm", tmp_path / f"{name}.ppm")
        assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
        assert said in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / f"{name}.ppm").exists()
    xml = tmp_path / "edited.xml"
    xml.write_text(text.replace('name="sampling" value="corners"',
                                'name="sampling" value="centers"').replace(
        'name="max_dist" value="1000.0"', 'name="max_dist" value="3.0"'))
    r = _rtval("render", "--mitsuba", xml, "-o", tmp_path / "e.exr")
    assert r.returncode == 0, r.stderr
    _, hdr = read_exr(tmp_path / "e.exr")
    assert hdr["rtval.max_dist"] == "3" and "max_dist=3" in hdr["rtval.integrator"]
    import hashlib
    assert hdr["rtval.scene_xml_sha256"] == hashlib.sha256(xml.read_bytes()).hexdigest()


def test07b_porting_outputs_say_what_they_came_from(tmp_path):
    """A porting user's review: convert's XML and render --mitsuba's outputs did not record
    the course scene (its sha256, the rules, the stand-ins), convert counted objects it left
    out as shapes, a non-square grid's WARNING stood in --shading XML (whose integrator
    samples the course's grid), and options that do not apply were taken silently."""
    from rt_core.camera import make_camera
    from rt_core.imageio import read_channels
    from rt_core.render import provenance
    from rt_core.rules import Rules
    path = ROOT / "scenes" / "torus.txt"            # a torus: left out of the Mitsuba scene
    xml = tmp_path / "t.xml"
    r = _rtval("convert", path, "--columns", 16, "--shading", "-o", xml)
    assert r.returncode == 0, r.stderr
    sc = parse_scene(path)
    n = len(sc.objects) - sum(o.kind == "torus" for o in sc.objects)
    assert f"t.xml: {n} shapes" in r.stderr and "WARNING" not in xml.read_text()
    exr = tmp_path / "t.exr"
    r = _rtval("render", "--mitsuba", xml, "-o", exr)
    assert r.returncode == 0, r.stderr
    head = read_channels(str(exr)).header
    ours = provenance(sc, make_camera(sc, 16), "f64", "llvm", Rules())
    for key in ("rtval.scene_sha256", "rtval.dialect", "rtval.sampling", "rtval.resolution",
                "rtval.rules"):
        assert head[key] == ours[key], key
    assert head["rtval.source_scene"] == str(path) and head["rtval.max_dist"] == "1000"
    assert head["rtval.scene"] == str(xml) and "commit=" in head["rtval.versions"]
    # options that do not apply: usage errors, nothing written
    for args, why in ((("convert", path, "--columns", 16, "-o", tmp_path / "x.png"),
                       "name it .xml"),
                      (("convert", path, "--columns", 16, "--shading", "--aovs", "-o",
                        tmp_path / "y.xml"), "not allowed with"),
                      (("render", "--mitsuba", xml, "--precision", "f64", "-o",
                        tmp_path / "z.exr"), "--precision and --backend do not apply"),
                      (("compare", "--shaded", path, "--columns", 16, "--precision", "f32"),
                       "--precision does not apply with --shaded")):
        r = _rtval(*args)
        assert r.returncode == 64 and why in r.stderr, (args, r.stderr)
    assert not {"x.png", "y.xml", "z.exr"} & {p.name for p in tmp_path.iterdir()}
    # compare --shaded says what it left out, as compare does
    r = _rtval("compare", "--shaded", path, "--columns", 16, "--evidence", tmp_path)
    assert "rtval compare: note: " in r.stderr and "torus" in r.stderr, r.stderr


@pytest.mark.parametrize("rows, said", [("0", "image is 16x0; the course's corner sampling"),
                                        ("99999", "needs ~")])
def test07c_render_mitsuba_guards_the_xmls_image(tmp_path, rows, said):
    """A hand-edited XML: an image too small for the course's samples, or too large for
    memory (99999 x 99999 took numpy to 74.5 GiB, a traceback), refused before tracing."""
    xml = tmp_path / "s.xml"
    assert _rtval("convert", ROOT / "scenes" / "sphere.txt", "--columns", 16, "--shading",
                  "-o", xml).returncode == 0
    text = xml.read_text()
    assert '<integer name="rows" value="12"/>' in text
    text = text.replace('<integer name="rows" value="12"/>', f'<integer name="rows" value="{rows}"/>')
    if rows == "99999":
        text = text.replace('<integer name="columns" value="16"/>',
                            '<integer name="columns" value="99999"/>')
    xml.write_text(text)
    r = _rtval("render", "--mitsuba", xml, "--png", tmp_path / "m.png")
    assert r.returncode == 2 and said in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr
    assert not (tmp_path / "m.png").exists()


def test08_compare_shaded_cli(tmp_path):
    r = _rtval("compare", "--shaded", ROOT / "scenes" / "mixed.txt", "--columns", 24,
               "--evidence", tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.splitlines()[-1].startswith("PASS") and "match=" in r.stdout


def test09_classes_are_decided():
    """Every pixel that differs is classed by the oracle: rounding only where a channel is
    off by one, and no class without the oracle's flag (a scene whose decisions lie far
    from float32's bounds has only matches)."""
    cmp = compare_shaded(parse_scene(ROOT / "scenes" / "fplane_tilted.txt"), W)
    d = np.abs(cmp.ours.astype(int) - cmp.theirs.astype(int)).max(-1)
    assert (d[cmp.classes == SHADED_CODE["rounding"]] == 1).all()
    assert (d[cmp.classes == SHADED_CODE["match"]] == 0).all()


def test10_validate_lists_the_shaded_comparison(tmp_path):
    import json
    r = _rtval("validate", ROOT / "scenes" / "sphere.txt", "--columns", 16, "--precision",
               "f32", "--mode", "rays", "--shaded-columns", 16, "-o", tmp_path)
    assert r.returncode == 0, r.stderr
    rows = json.loads((tmp_path / "report.json").read_text())["results"]
    assert [x["mode"] for x in rows] == ["rays", "shaded"] and rows[1]["ok"]
    assert "The course image" in (tmp_path / "report.md").read_text()


@pytest.mark.parametrize("name", ["fplane_tilted", "planar"])
def test11_aovs_diff_with_rtvals_exr(tmp_path, name):
    """rtval convert --aovs + rtval render --mitsuba -o: a float32 EXR with rtval's channel
    names and conventions, which rtval exr diff compares with rtval render's EXR directly
    (the README's command passes; on triangles and disks too, whose uv Mitsuba's AOVs left
    at 0); a plane moved by 1e-3 fails it."""
    import OpenEXR
    path = ROOT / "scenes" / f"{name}.txt"
    ours, theirs = tmp_path / "ours.exr", tmp_path / "mitsuba.exr"
    assert _rtval("render", path, "--columns", W, "-o", ours).returncode == 0

    def mitsuba_exr(scene_path, out):
        xml = tmp_path / "aovs.xml"
        assert _rtval("convert", scene_path, "--columns", W, "--aovs", "-o", xml
                      ).returncode == 0
        r = _rtval("render", "--mitsuba", xml, "-o", out)
        assert r.returncode == 0, r.stderr
    mitsuba_exr(path, theirs)
    with OpenEXR.File(str(ours)) as a, OpenEXR.File(str(theirs)) as b:
        assert set(a.channels()) == set(b.channels())
    diff = ["exr", "diff", ours, theirs, "--fail", "1e-4", "--warn", "1e-4", "--fail-relative",
            "1e-5", "--warn-relative", "1e-5", "--fail-percent", "1"]
    r = _rtval(*diff)
    assert r.returncode == 0 and "PASS" in r.stdout, r.stdout
    if name != "fplane_tilted":
        return
    moved = tmp_path / "moved.txt"
    moved.write_text(path.read_text().replace("-5.5 -2 -9", "-5.5 -2 -9.001"))
    mitsuba_exr(moved, theirs)
    r = _rtval(*diff)
    assert r.returncode != 0 and "FAIL" in r.stdout, r.stdout


def test12_plugins_registered_on_import(tmp_path):
    """With Mitsuba already in rtval's variant, ``import mitsuba_ref`` registers the plugins:
    a converted scene then loads with plain ``mi.load_file``; without Mitsuba imported,
    importing mitsuba_ref does not import it."""
    xml = tmp_path / "s.xml"
    assert _rtval("convert", ROOT / "scenes" / "sphere.txt", "--columns", 8, "--shading",
                  "-o", xml).returncode == 0
    code = ("import mitsuba as mi; mi.set_variant('llvm_ad_rgb'); import mitsuba_ref; "
            f"s = mi.load_file({str(xml)!r}); print(type(s.integrator()).__name__)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.stdout.strip() == "CourseIntegrator", r.stderr
    code = "import sys, mitsuba_ref, mitsuba_ref.convert; print('mitsuba' in sys.modules)"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.stdout.strip() == "False", r.stderr


TIE = ("8 6\n0 0 5\npointlight\n5 5 5\n0 4 0\n"
       "plane\n1 0 0\n0 0 0\n0 0 0\n0 0 1\n0 0 -5\n"         # red, first
       "plane\n0 1 0\n0 0 0\n0 0 0\n0 0 1\n0 0 -5\n")        # green, the same plane


def test12b_a_users_own_script_renders_the_xml_as_compare_does(tmp_path):
    """A review, porting to Mitsuba with the XML's own steps: mi.render(mi.load_file(xml))
    crashed the process (the image was evaluated after the scene it reads was freed); and
    Mitsuba's default optimize reordered the shapes, so two coincident planes showed the
    second's colour where rtval compare (and the course's first-object tie) say the first's.
    The XML now says to load with optimize=False, rtval render --mitsuba does, and the
    image is the course's; a scene whose every object Mitsuba lacks renders black, not a
    traceback."""
    scene = tmp_path / "tie.txt"
    scene.write_text(TIE)
    xml, ppm = tmp_path / "tie.xml", tmp_path / "tie.ppm"
    r = _rtval("convert", scene, "--columns", 16, "--shading", "-o", xml)
    assert r.returncode == 0 and "mi.load_file(path, optimize=False)" in xml.read_text()
    # the planes' stand-ins said on stderr too, as the README says (in the XML only before)
    assert "note: infinite and tiled planes: rectangles of half-size" in r.stderr
    r = _rtval("render", "--mitsuba", xml, "--ppm", ppm)
    assert r.returncode == 0, r.stderr
    from rt_core.imageio import read_image
    img = read_image(str(ppm))
    assert (img[..., 0] > 0).all() and (img[..., 1:] == 0).all(), np.unique(img.reshape(-1, 3),
                                                                          axis=0)
    mixed = tmp_path / "mixed.xml"
    assert _rtval("convert", ROOT / "scenes" / "mixed.txt", "--columns", 16, "--shading", "-o",
                  mixed).returncode == 0
    for path, want in ((xml, "(12, 16, 3) 1"), (mixed, "(12, 16, 3) 0")):
        # (the image evaluated after the scene is gone: the README's one-liner)
        code = ("import sys, numpy as np, mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
                "import mitsuba_ref; "
                f"img = mi.render(mi.load_file({str(path)!r}, optimize=False)); "
                "a = np.asarray(img); "
                "print(a.shape, int((a[..., 0] > 0).all() and (a[..., 1:] == 0).all()))")
        r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                           text=True)
        assert r.returncode == 0 and r.stdout.strip() == want, (path, r.returncode, r.stderr)
    # Mitsuba's own integrators on the XML: the course material is black to them (it
    # raised on an uninitialised sample)
    code = ("import numpy as np, mitsuba as mi; mi.set_variant('llvm_ad_rgb'); "
            f"import mitsuba_ref; sc = mi.load_file({str(mixed)!r}, optimize=False); "
            "a = np.asarray(mi.render(sc, integrator=mi.load_dict({'type': 'path'}), spp=4)); "
            "print(a.shape, float(a.max()))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip().endswith("(12, 16, 3) 0.0"), r.stderr
    # nothing Mitsuba has a shape for: black, as rt_core draws it
    lone = tmp_path / "lone.txt"
    lone.write_text("8 6\n0 0 5\npointlight\n5 5 5\n0 4 0\n"
                    "ellipsoid\n3 3 3\n1 1 1\n0 0 0\n0 0 -5\n1 2 1\n")
    for mode in ("--shading", "--aovs"):
        r = _rtval("convert", lone, "--columns", 8, mode, "-o", tmp_path / "lone.xml")
        assert r.returncode == 0, r.stderr
        out = tmp_path / ("lone.ppm" if mode == "--shading" else "lone.exr")
        r = _rtval("render", "--mitsuba", tmp_path / "lone.xml",
                   *(("--ppm", out) if mode == "--shading" else ("-o", out)))
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert (read_image(str(tmp_path / "lone.ppm")) == 0).all()
    # and rtval compare says in its verdict that its one object was not compared (on
    # stderr only, the review read 'PASS')
    for extra in ((), ("--shaded",)):
        r = _rtval("compare", *extra, lone, "--columns", 8)
        last = r.stdout.strip().splitlines()[-1]
        assert r.returncode == 0 and last.startswith("PASS") and \
            "; 1 of its 1 objects not compared" in last, (r.stdout, r.stderr)


@pytest.mark.parametrize("path, columns, why", [
    (ROOT / "scenes" / "shade_mirrors.txt", 64, "beyond"),
    (COURSE / "numeric" / "nw__spotlight.txt", 64, "tile")])
def test12c_boundary_pixels_say_which_decision(path, columns, why):
    """compare --shaded said 'boundary=58' and nothing more (a porting user's review found
    by hand a tile border and the far tiles): each boundary pixel is counted under the
    first of its near decisions, and the counts are printed."""
    if not path.is_file():
        pytest.skip(f"{path} not in the corpus")
    cmp = compare_shaded(parse_scene(path), columns)
    assert cmp.counts["boundary"] > 0
    assert cmp.boundary_reasons == {why: cmp.counts["boundary"]}, cmp.boundary_reasons
    r = _rtval("compare", "--shaded", path, "--columns", columns)
    from tools.harness.shaded import BOUNDARY_REASONS
    assert f"{dict(BOUNDARY_REASONS)[why]}: {cmp.counts['boundary']}" in r.stdout, r.stdout


def test13_the_oracle_and_the_geometry_classifier_find_the_stand_ins_end(tmp_path):
    """A bright floor far below a level camera: rt_core sees the infinite plane out to the
    horizon, Mitsuba's stand-in square (64 × the scene's scale) ends before it.  The shading
    oracle's ``reach`` puts those primary hits beyond the square, so its classes alone make
    them boundary, not wrong; and the geometry classifier names the same pixels, each
    "extent"."""
    from mitsuba_ref.explain import CLASS_CODE
    from tools.harness.compare import compare
    from tools.harness.shaded import classify_shaded
    sc = parse_text("8 6  0 0 5\npointlight 9 9 9  0 4 0\n"
                    "plane 5000 5000 5000  0 0 0  0 0 0  0 1 0  0 -100 0\n")
    cmp = compare_shaded(sc, 64)
    assert cmp.ok and cmp.counts["boundary"] > 0, cmp.counts
    oracle_only = classify_shaded(sc, cmp.ours, cmp.theirs, "corners", cmp.rules, cmp.max_dist)
    boundary = oracle_only == SHADED_CODE["boundary"]
    assert boundary.sum() == cmp.counts["boundary"]
    geo = compare(sc, 64, cmp.rows, "f64", "rays").classes
    assert (geo[boundary] == CLASS_CODE["extent"]).all()


@pytest.mark.parametrize("path,kinds", [(CYLINDERS, ("cylinder",)),
                                        (ROOT / "scenes" / "planar.txt", ("triangle", "disk"))])
def test14_the_kind_is_in_the_shaded_comparison(path, kinds):
    """Issue 13: the course integrator shades the cylinder, the triangle and the disk, so the
    shaded comparison keeps them on both sides: the note names nothing, Mitsuba's image
    differs from the one without them (where they are seen, their shadows and reflections),
    and those pixels agree with rt_core's."""
    import dataclasses
    from tools.harness.shaded import quantize32
    sc = parse_scene(path)
    cmp = compare_shaded(sc, W)
    assert cmp.ok and cmp.note == "", (cmp.counts, cmp.note)
    bare = dataclasses.replace(sc, objects=tuple(o for o in sc.objects if o.kind not in kinds))
    without = quantize32(mitsuba_course_image(bare, W, cmp.rows))
    changed = (without != cmp.theirs).any(-1)
    assert changed.sum() > 0.05 * W * cmp.rows, changed.sum()      # 55 of 768 here
    assert (cmp.classes[changed] == SHADED_CODE["match"]).mean() > 0.9, cmp.counts


def test15_a_cylinder_shading_error_is_wrong():
    """The cylinder's normal turned inward (lit and unlit sides swap): wrong pixels."""
    cmp = compare_shaded(parse_scene(CYLINDERS), 2 * W, integrator=_broken("cylinder_normal"))
    assert not cmp.ok and cmp.counts["wrong"] >= 5, cmp.counts


def test16_host_arrays_reach_dr_jit_aligned():
    """mitsuba_ref.jitdata: a numpy view at an address 4 bytes off a vector boundary gives
    the same kernel as an aligned one (Dr.Jit maps host arrays without copying and generates
    unaligned loads, another kernel to compile, for an unaligned one)."""
    import drjit as dr
    from mitsuba_ref.convert import mitsuba
    from mitsuba_ref.jitdata import jit_array
    mi = mitsuba()
    raw = np.zeros(4096, np.uint8)
    start = -raw.ctypes.data % 64
    base = raw[start:start + 2048].view(np.float32)       # at a multiple of 64 bytes
    hashes = []
    for off in (0, 1):
        a = base[off:off + 256]
        with _history() as h:
            dr.eval(jit_array(mi.Float, a) * 3 + 1)
        hashes.append(h)
    assert base[1:].ctypes.data % 32 == 4 and hashes[0] == hashes[1] and hashes[0]


def test17_course_image_kernels_read_no_unaligned_input():
    """Whatever address numpy's allocator gives the rays (the heap moved between renders),
    the course integrator's kernels load every array input as an aligned vector: an
    unaligned one (``align 1``) is another kernel, compiled again (4–30 s a scene in
    validate).  (The kernels' hashes themselves can still differ between processes: README
    "Mitsuba renders the course image".)"""
    import re
    import drjit as dr
    unaligned = re.compile(r"load <\d+ x [a-z0-9]+>, ptr %[\w.]+, align 1\b")
    scene = parse_scene(ROOT / "scenes" / "cylinders.txt")
    junk, saved = [], dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for k in range(4):
            junk.append(np.empty(3 + 5 * k))        # moves the next allocations' addresses
            dr.kernel_history()
            mitsuba_course_image(scene, 24, 18)
            irs = [e["ir"].getvalue() for e in dr.kernel_history()
                   if e["type"] == dr.KernelType.JIT and e.get("ir") is not None]
            assert irs and not any(unaligned.search(ir) for ir in irs), k
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, saved)


class _history:
    """The hashes of the JIT kernels launched inside the block (a list, in order)."""

    def __enter__(self):
        import drjit as dr
        self.dr, self.saved = dr, dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        self.hashes = []
        return self.hashes

    def __exit__(self, *exc):
        dr = self.dr
        self.hashes += [e["hash"] for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, self.saved)
        return False


def test18_secondary_rays_keep_the_course_line():
    """A shadow ray from the floor passes 5.5e-4 below the tilted cylinder's base rim on its
    way to the light (exact: unblocked).  The integrator's shadow and reflection rays start
    their search a little along themselves (``_along``), not off the surface along the
    normal as Mitsuba's spawn_ray_to does: that moved the whole line up by
    (1 + |p|∞)·RayEpsilon = 5.7e-4, past the rim, and the pixel came out shadowed, wrong."""
    cmp = compare_shaded(parse_scene(ROOT / "scenes" / "cylinder_rim_shadow.txt"), 160)
    assert cmp.classes[48, 105] == SHADED_CODE["match"], (cmp.ours[48, 105], cmp.theirs[48, 105])
    assert cmp.ok, cmp.counts


def test19_a_stepped_over_hit_keeps_the_course_line():
    """Primary rays cross a tilted plane in front of the window (z > 0: clipped, not counted)
    and go on to the back wall.  Every search the integrator starts, the first and the one
    after the step over the clipped hit, starts on the ray's own line (within float32
    rounding), not off the skipped surface along its normal as Mitsuba's spawn_ray puts it
    (0.6 × 5.7e-4 off the line here)."""
    import drjit as dr
    from mitsuba_ref.convert import mitsuba, scene_dict
    mi = mitsuba()
    sc = parse_text("8 6\n0 0 5\n"
                    "10\n9 9 9\n0 4 3\n"
                    "14\n1 1 1\n4 4 4\n0 0 0\n0 0.6 0.8\n0 0 2\n"      # clipped where z > 0
                    "14\n1 1 1.5\n3 3 4\n0 0 0\n0 0 1\n0 0 -6\n")
    ms = mi.load_dict(scene_dict(sc, 16, 12, shading=True), optimize=False)
    integ = ms.integrator()
    integ.tab = integ._tables(ms)

    class Recorded:
        """The scene, recording the origin of every search on the lanes it runs."""
        def __init__(self):
            self.origins = []

        def ray_intersect(self, ray, active=True):
            o = np.stack([np.asarray(c) for c in (ray.o.x, ray.o.y, ray.o.z)], 1)
            on = np.asarray(dr.select(mi.Bool(active), mi.Float(1), mi.Float(0))) > 0
            self.origins.append((o, np.broadcast_to(on, len(o))))
            return ms.ray_intersect(ray, active)

    V = np.array(sc.viewpoint)
    xs, ys = np.meshgrid(np.linspace(-3.5, 3.5, 8), np.linspace(-2.5, 2.5, 6))
    D = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1) - V
    D /= np.linalg.norm(D, axis=1)[:, None]
    o = mi.Point3f(*(mi.Float(np.full(len(D), c, np.float32)) for c in V))
    d = mi.Vector3f(*(mi.Float(D[:, i].astype(np.float32)) for i in range(3)))
    rec = Recorded()
    _, t, p, hit = integ._closest(rec, o, d, mi.Bool(True))
    assert len(rec.origins) >= 2 and rec.origins[1][1].all(), "no hit was stepped over"
    assert np.asarray(hit).all() and (np.asarray(p.z) < 0).all()       # the back wall
    for got, on in rec.origins:
        off = np.linalg.norm(np.cross(got[on] - V, D[on]), axis=1)     # distance from the line
        assert off.max() < 1e-5, off.max()


def test20_a_reflection_beyond_the_stand_in_is_boundary():
    """A mirror floor and a bright ceiling, both infinite.  Row 18's rays meet the floor
    about 250 units away, within the half-size 640 of the squares that stand in for the
    planes in Mitsuba's scene, and their reflections the ceiling about 750 away, beyond its
    square: rt_core sees the ceiling (white), Mitsuba nothing (black).  The oracle's
    ``reach`` finds those hits beyond the square, so the pixels are ``boundary`` (as the
    geometry classifier's "extent" for a primary ray), not ``wrong``; every other pixel
    matches.  (Found on scenes/shade_mirrors.txt at 1200 columns: 12 pixels down the
    corridor of mirrors.)"""
    from mitsuba_ref.convert import plane_extent
    sc = parse_text("8 6\n0 -0.0657 5\n"
                    "plane\n0 0 0\n0 0 0\n1 1 1\n0 1 0\n0 -1 0\n"
                    "plane\n5000 5000 5000\n0 0 0\n0 0 0\n0 -1 0\n0 1 0\n")
    cmp = compare_shaded(sc, 49)
    assert 600 < plane_extent(sc) < 700
    row = cmp.classes[18]
    assert (row == SHADED_CODE["boundary"]).all(), row
    assert (cmp.ours[18] == 255).all() and (cmp.theirs[18] == 0).all()
    others = np.delete(cmp.classes, 18, axis=0)
    assert (others == SHADED_CODE["match"]).all(), cmp.counts
    assert cmp.ok, cmp.counts
    # beyond the square Mitsuba's colour is excused, not rt_core's: the oracle traces the
    # ceiling itself (a review: any rt_core colour passed there)
    from tools.harness.shaded import classify_shaded
    moved = cmp.ours.copy()
    moved[18] = 128
    got = classify_shaded(sc, moved, cmp.theirs, "corners", cmp.rules, cmp.max_dist)
    assert (got[18] == SHADED_CODE["wrong"]).all(), got[18]


def test21_rounding_is_of_the_channel_that_differs():
    """scenes/mixed.txt at 160 columns, pixel (97, 7): 255·I is (68.0012, 64.6895, 72.58).
    Red one level down is rounding (68.0012 lies within float32's bound of 68); green one
    level up is wrong, though red is near its level (a review: a broken Mitsuba side had 69
    of 223 'rounding' pixels differ in a channel far from any level)."""
    from tools.harness.shaded import classify_shaded
    sc = parse_scene(ROOT / "scenes" / "mixed.txt")
    cmp = compare_shaded(sc, 160)
    y, x = 7, 97
    for ch, step, want in ((0, -1, "rounding"), (1, 1, "wrong")):
        theirs = cmp.ours.copy()
        theirs[y, x, ch] = int(theirs[y, x, ch]) + step
        got = classify_shaded(sc, cmp.ours, theirs, "corners", cmp.rules, cmp.max_dist)
        assert got[y, x] == SHADED_CODE[want], (ch, got[y, x])


def test22_a_boundary_pixel_has_mitsubas_colour_on_a_side(monkeypatch):
    """A decision near its threshold excuses Mitsuba's colour only where taking the near
    decisions either way gives it (within a level).  A review scaled Mitsuba's green by
    1.005 (every material's diffuse and ambient): 268 pixels were boundary, 223 of them with
    a colour no side gives, where the unbroken comparison has 54.  Broken, a pixel is
    boundary by the oracle only where it is unbroken too, or where its path meets a plane
    beyond the stand-in square, and the break is found.  (Within a level of a side's colour
    was taken, as rtval check takes a float64 tracer's: 134 of those pixels were.)"""
    import mitsuba_ref.convert as cv
    sc = parse_scene(ROOT / "scenes" / "mixed.txt")
    clean = compare_shaded(sc, 160)
    real = cv._mat

    def greener(m, prefix=""):
        d = real(m, prefix)
        for k in d:
            if k.endswith("diffuse") or k.endswith("ambient"):
                d[k] = [c * (1.005 if i == 1 else 1) for i, c in enumerate(d[k])]
        return d
    monkeypatch.setattr(cv, "_mat", greener)
    broken = compare_shaded(sc, 160)
    assert not broken.ok and clean.ok
    # (the oracle's classes: where pixels are wrong, the geometry classifier then excuses
    # the primary rays' own disagreements too, edges of objects hit either side)
    from tools.harness.shaded import classify_shaded
    oracle = classify_shaded(sc, broken.ours, broken.theirs, "corners", broken.rules,
                             broken.max_dist)
    # each pixel's combinations enumerated whole (no early out): the same classes
    import tools.harness.shaded as sh
    monkeypatch.setattr(sh, "EARLY_OUT", False)
    whole = classify_shaded(sc, broken.ours, broken.theirs, "corners", broken.rules,
                            broken.max_dist)
    assert (whole == oracle).all() and (oracle == SHADED_CODE["boundary"]).sum() > 50
    # boundary only where the unbroken comparison has it, or where rounding excuses the
    # pixel too (each differing channel one level off and near its level: not asked), or
    # where the path meets a plane beyond its stand-in square (the reach: structural)
    from mitsuba_ref.convert import plane_extent
    from mitsuba_ref.shade_oracle import flags, shade_pixels
    new = np.flatnonzero(((oracle == SHADED_CODE["boundary"]) &
                          (clean.classes != SHADED_CODE["boundary"])).ravel())
    orc = shade_pixels(sc, 160, broken.rows, new)
    ours, theirs = (a.reshape(-1, 3)[new].astype(int) for a in (broken.ours, broken.theirs))
    rounding = (np.abs(ours - theirs).max(-1) <= 1) & \
        ~((ours != theirs) & ~flags(orc, "f32")["quant_rgb"]).any(-1)
    beyond = orc["reach"] > plane_extent(sc) * (1 - 1e-6)
    # and where the decisions' sides cannot all be enumerated (any colour)
    from mitsuba_ref.shade_oracle import K_DECISION, U, other_sides_of
    rest = new[~(rounding | beyond)]
    sides = other_sides_of(sc, 160, broken.rows, rest, limit=K_DECISION * U["f32"])
    assert all(s is None for s in sides), (len(rest), broken.counts)
    assert len(rest) <= 2


@pytest.mark.parametrize("name, shift", [("scenes/mixed.txt", 40),
                                         ("course:numeric/cbl__spec3.txt", 25)])
def test22b_a_boundary_pixel_has_rt_cores_colour_on_a_side(name, shift):
    """A near decision excuses a pixel only where both colours are ones its decisions give:
    rt_core's too, not Mitsuba's alone.  A review's mutations of rt_core's shading (the
    reflection weighted twice, the distance cut-off inverted, bounces dropped) put rt_core
    1 to 250 levels off on pixels whose other sides held Mitsuba's colour, and passed as
    boundary, also where the combinations could not all be enumerated (cbl__spec3).  Here
    rt_core's colour is moved on every boundary pixel of a clean comparison: none stays
    boundary but where a path has no colour to name (a flip with no hit to take: any
    colour, by design)."""
    from tools.harness.shaded import classify_shaded
    path = ROOT.parent / "shared" / "course-scenes" / name.split(":")[1] \
        if name.startswith("course:") else ROOT / name
    if not path.is_file():
        pytest.skip("the course scenes are not here")
    sc = parse_scene(path)
    clean = compare_shaded(sc, 48)
    assert clean.ok
    bnd = clean.classes == SHADED_CODE["boundary"]
    assert bnd.sum() >= 10, clean.counts
    ours = clean.ours.astype(int)
    moved = np.where(bnd[..., None], (ours + shift) % 256, ours).astype(np.uint8)
    got = classify_shaded(sc, moved, clean.theirs, "corners", clean.rules, clean.max_dist)
    stays = np.flatnonzero((bnd & (got == SHADED_CODE["boundary"])).ravel())
    from mitsuba_ref.shade_oracle import K_DECISION, U, reaches
    for p in stays:                 # a colour no path can have is 'found' only there
        assert reaches(sc, 48, clean.rows, int(p), [(999, 999, 999)],
                       limit=K_DECISION * U["f32"]) is True, p
    assert len(stays) <= 0.3 * bnd.sum(), (len(stays), int(bnd.sum()))
    # and the clean ones stay boundary (both colours are sides of their decisions)
    again = classify_shaded(sc, clean.ours, clean.theirs, "corners", clean.rules,
                            clean.max_dist)
    assert (again == clean.classes).all()
