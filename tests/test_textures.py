"""Textures (README "Textures"): rt_core's textured ambient against the float64 shading oracle
and Mitsuba's course integrator, where textures are looked for, and the one-line errors.

Textures are generated here (a 4×3 P6, a 6×5 P3 with maxval 15, a 16-bit P6) or are the
tiny generated files under scenes/textures/ that the bundled scenes name."""
from __future__ import annotations

import os

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_core import backend, textures
from rt_core.camera import make_camera
from rt_core.imageio import ImageError
from rt_core.parser import parse_scene
from rt_core.render import render_image
from rt_core.shading import quantize

REPO = Path(__file__).resolve().parents[1]
BUNDLED = [REPO / "scenes" / "textured.txt", REPO / "scenes" / "textured_numeric.txt"]
COURSE = REPO.parent / "shared" / "course-scenes"
RNG = np.random.default_rng(2024)


def ppm6(path, a, maxval=255):
    a = np.asarray(a)
    body = a.astype(np.uint8 if maxval < 256 else ">u2").tobytes()
    Path(path).write_bytes(b"P6\n%d %d\n%d\n" % (a.shape[1], a.shape[0], maxval) + body)


def ppm3(path, a, maxval):
    rows = "\n".join(" ".join(map(str, r.reshape(-1))) for r in np.asarray(a))
    Path(path).write_text(f"P3\n# a comment\n{a.shape[1]} {a.shape[0]}\n{maxval}\n{rows}\n")


def cli(*args):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=300)


def shaded(scene, columns, precision):
    cam = make_camera(scene, columns)
    ims, _ = render_image(scene, cam, backend.types(precision), geometry=False, shade=True)
    return quantize(np.stack([ims[c] for c in "RGB"], -1))


def test01_ppm_readers_give_value_over_maxval(tmp_path):
    from mitsuba_ref.ppm import texels
    a6 = RNG.integers(0, 256, (3, 4, 3))
    a3 = RNG.integers(0, 16, (5, 6, 3))
    a16 = RNG.integers(0, 65536, (2, 3, 3))
    ppm6(tmp_path / "a.ppm", a6)
    ppm3(tmp_path / "b.ppm", a3, 15)
    ppm6(tmp_path / "c.ppm", a16, 65535)
    for name, a, m in (("a", a6, 255), ("b", a3, 15), ("c", a16, 65535)):
        p = str(tmp_path / f"{name}.ppm")
        assert np.array_equal(textures.read_ppm(p), a / m)       # rt_core's reader
        assert np.array_equal(texels(p), a / m)                  # the references' own
    (tmp_path / "grey.pgm").write_bytes(b"P5\n2 2\n255\n\0\0\0\0")
    with pytest.raises(ImageError, match="does not start with P6 or P3"):
        textures.read_ppm(str(tmp_path / "grey.pgm"))


@pytest.mark.parametrize("data, why", [
    (b"P6 2 1 255#c\n" + bytes([10, 20, 30, 40, 50, 60]), "after the maxval"),
    (b"P64 1 255\n" + bytes(12), "no whitespace after P6"),
    (b"P3 1 1 9#c\n1 2 3\n", "after the maxval"),
])
def test01c_headers_the_references_refuse_are_errors(tmp_path, data, why):
    """A header without the format's separators (none after the magic number; a comment,
    not one whitespace byte, after maxval) is one line of error: rt_core read 'c\\n' as
    texels, or a width of 4 from 'P64', where the references' reader refuses the file, so
    `compare --shaded` ended in a traceback (a review).  Both readers agree on what they
    accept: every case here is refused by both."""
    from mitsuba_ref.ppm import texels
    p = tmp_path / "t.ppm"
    p.write_bytes(data)
    with pytest.raises(ImageError, match=why):
        textures.read_ppm(str(p))
    with pytest.raises(ValueError):
        texels(str(p))
    ok = tmp_path / "ok.ppm"              # comments between the numbers stay allowed
    ok.write_bytes(b"P6#a\n2 #b\n1\n#c\n255\n" + bytes([10, 20, 30, 40, 50, 60]))
    assert np.array_equal(textures.read_ppm(str(ok)) * 255, texels(str(ok)) * 255)


def test01b_the_references_reader_sees_a_rewritten_texture(tmp_path):
    """mitsuba_ref.ppm.texels keeps what it read, but reads a file again once it has changed
    (a long-lived validate worker); what it returns cannot be written to."""
    from mitsuba_ref.ppm import texels
    p = tmp_path / "t.ppm"
    a, b = RNG.integers(0, 256, (3, 4, 3)), RNG.integers(0, 256, (3, 4, 3))
    ppm6(p, a)
    first = texels(str(p))
    assert np.array_equal(first, a / 255) and not first.flags.writeable
    ppm6(p, b)
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10 ** 9))   # (the same size)
    assert np.array_equal(texels(str(p)), b / 255)


def _oracle_check(scene, columns):
    """rt_core f32 and f64 against the shading oracle: no 8-bit difference outside the
    oracle's flags; returns the oracle's 8-bit image."""
    from mitsuba_ref.shade_oracle import flags, quantize as oq, render_shade_oracle
    orc = render_shade_oracle(scene, columns)
    ref = oq(orc["I"])
    for p in ("f32", "f64"):
        diff = (shaded(scene, columns, p) != ref).any(-1)
        bad = diff & ~flags(orc, p)["any"]
        assert not bad.any(), f"{scene.path} {p}: {int(bad.sum())} pixels differ unflagged"
    return ref


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.stem)
def test02_rt_core_agrees_with_the_shading_oracle(path):
    scene = textures.attach(parse_scene(path))
    assert not scene.stand_ins()            # the texture is applied: no stand-in note
    ref = _oracle_check(scene, 40)
    # the texture changes the image (the MAT's ambient would give another one)
    plain = shaded(parse_scene(path), 40, "f64")
    assert (plain != ref).any(-1).sum() > 100


@pytest.mark.parametrize("path", BUNDLED, ids=lambda p: p.stem)
def test03_rt_core_agrees_with_mitsuba(path):
    from tools.harness.shaded import compare_shaded
    cmp = compare_shaded(textures.attach(parse_scene(path)), 48)
    assert cmp.ok and cmp.counts["match"] > 0.99 * cmp.columns * cmp.rows, cmp.counts


def _stand_ins(scene, folder):
    """Generated textures of the names ``scene`` uses, alternating P6 and P3 (maxval 15)."""
    for k, (_, o) in enumerate(textures.textured(scene)):
        name = next(v for f, v in o.extras if f == "texture")
        if k % 2:
            ppm3(folder / name, RNG.integers(0, 16, (5, 7, 3)), 15)
        else:
            ppm6(folder / name, RNG.integers(0, 256, (3, 4, 3)))


@pytest.mark.skipif(not COURSE.is_dir(), reason="no ../shared/course-scenes")
@pytest.mark.parametrize("name", ["numeric/nw__earth.txt", "keyword/rm768__bowling.txt"])
def test04_course_scenes_with_generated_textures(tmp_path, name):
    path = COURSE / name
    _stand_ins(parse_scene(path), tmp_path)
    out = tmp_path / "out.ppm"
    r = cli("render", path, "--columns", 32, "--ppm", out, "--texture-dir", tmp_path)
    assert r.returncode == 0, r.stderr
    assert out.stat().st_size > 0 and "not applied" not in r.stderr
    _oracle_check(textures.attach(parse_scene(path), [tmp_path]), 16)


def _scene_copy(tmp_path):
    """scenes/textured.txt copied alone (its textures not next to it)."""
    d = tmp_path / "scene"
    d.mkdir()
    shutil.copy(BUNDLED[0], d / "textured.txt")
    return d / "textured.txt"


def test05_missing_texture_one_line_exit_2(tmp_path):
    scene = _scene_copy(tmp_path)
    out = tmp_path / "o.ppm"
    r = cli("render", scene, "--columns", 16, "--ppm", out)
    assert r.returncode == 2
    assert r.stderr.strip() == (
        f"rtval render: {scene}:16:1: texture 'textures/tiles4x3.ppm' not found (looked for: "
        f"{scene.parent / 'textures' / 'tiles4x3.ppm'}); put it next to the scene or pass "
        "--texture-dir DIR")
    assert not out.exists() and sorted(p.name for p in scene.parent.iterdir()) == [scene.name]
    # a --texture-dir holding the file by its bare name finds it (a review: 'not found',
    # naming that folder); one that does not is named with the paths tried
    textures = BUNDLED[0].parent / "textures"
    r = cli("render", scene, "--columns", 16, "--ppm", out, "--texture-dir", textures)
    assert r.returncode == 0 and out.exists(), r.stderr
    os.remove(out)
    r = cli("render", scene, "--columns", 16, "--ppm", out, "--texture-dir", tmp_path)
    assert r.returncode == 2 and f"(looked for: {tmp_path / 'textures' / 'tiles4x3.ppm'}, " \
        f"{tmp_path / 'tiles4x3.ppm'}, {scene.parent / 'textures' / 'tiles4x3.ppm'})" \
        in r.stderr, r.stderr
    # geometry needs no texture
    r = cli("render", scene, "--columns", 16, "-o", tmp_path / "g.exr")
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("scene, old, new, says", [
    ("textured.txt", "2 1.5            # texture size", "2 0 # texture size",
     "fplanetex: texture size (2, 0) must be positive"),
    ("textured_numeric.txt", "1           tile mode (fit)", "1.0000000001",
     "texplane: tile mode 1.0000000001; expected 1 (fit) or 2 (tile)"),
    ("textured_numeric.txt", "2           tile mode (repeat", "7 (",
     "texplane: tile mode 7; expected"),
])
@pytest.mark.parametrize("command", [("render", "-o", "{out}.exr"), ("compare",)])
def test05c_invalid_mapping_fields_are_errors_for_every_command(tmp_path, scene, old, new,
                                                                   says, command):
    """A texture size <= 0 or a tile mode other than 1 or 2 is one line and exit 2 when
    the file is read, also for commands that trace geometry only (they exited 0: the fields
    were checked only where textures are applied; a review); the number as written (a tile
    mode of 1.0000000001 read "tile mode 1")."""
    text = (REPO / "scenes" / scene).read_text()
    assert old in text
    path = tmp_path / scene
    path.write_text(text.replace(old, new))
    shutil.copytree(REPO / "scenes" / "textures", tmp_path / "textures")
    args = [a.format(out=tmp_path / "out") for a in command]
    r = cli(args[0], path, "--columns", 16, *args[1:])
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and str(path) in lines[0], lines
    assert not list(tmp_path.glob("out*"))


def test05b_texture_name_of_a_directory_says_so(tmp_path):
    """A texture name that names a directory is not reported missing: one line saying it is a
    directory, exit 2, nothing written."""
    scene = _scene_copy(tmp_path)
    (scene.parent / "textures" / "tiles4x3.ppm").mkdir(parents=True)
    out = tmp_path / "o.ppm"
    r = cli("render", scene, "--columns", 16, "--ppm", out)
    assert r.returncode == 2 and not out.exists()
    assert r.stderr.strip() == (
        f"rtval render: {scene}:16:1: texture 'textures/tiles4x3.ppm' is a directory "
        f"({scene.parent / 'textures' / 'tiles4x3.ppm'}), not a PPM file; give the image "
        "file's name")


def test06_unreadable_texture_one_line_exit_2(tmp_path):
    scene = _scene_copy(tmp_path)
    (scene.parent / "textures").mkdir()
    shutil.copy(REPO / "scenes" / "textures" / "globe6x5_p3.ppm", scene.parent / "textures")
    (scene.parent / "textures" / "tiles4x3.ppm").write_bytes(b"P6\n4 3\n255\n" + b"\0" * 10)
    out = tmp_path / "o.png"
    r = cli("render", scene, "--columns", 16, "--png", out)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "tiles4x3.ppm: not a readable PPM texture" in lines[0]
    assert "truncated" in lines[0] and not out.exists()


def test07_texture_dir_comes_before_the_scene_dir(tmp_path):
    from rt_core.imageio import read_channels
    scene = _scene_copy(tmp_path)
    shutil.copytree(REPO / "scenes" / "textures", scene.parent / "textures")
    other = tmp_path / "other"
    (other / "textures").mkdir(parents=True)
    ppm6(other / "textures" / "tiles4x3.ppm", np.full((3, 4, 3), 200))
    shutil.copy(REPO / "scenes" / "textures" / "globe6x5_p3.ppm", other / "textures")
    outs = {}
    for key, extra in (("scene", []), ("dir", ["--texture-dir", other])):
        outs[key] = tmp_path / f"{key}.png"
        r = cli("render", scene, "--columns", 32, "--png", outs[key], *extra)
        assert r.returncode == 0, r.stderr
    used = read_channels(str(outs["dir"])).header["rtval.textures"]
    assert str(other / "textures" / "tiles4x3.ppm") in used
    assert "(4x3, sha256 " in used
    assert str(scene.parent / "textures" / "tiles4x3.ppm") in \
        read_channels(str(outs["scene"])).header["rtval.textures"]


@pytest.mark.skipif(not COURSE.is_dir(), reason="no ../shared/course-scenes")
def test08_validate_skips_the_shaded_comparison_without_texture(tmp_path):
    from tools.harness.validate import attach_textures, jobs, skip_counts
    earth = parse_scene(COURSE / "numeric" / "nw__earth.txt")
    scenes, skipped = attach_textures([earth, parse_scene(BUNDLED[0])])
    assert [s.category for s in skipped] == ["texture"]
    assert "texture 'earth2.ppm' not found" in skipped[0].reason
    assert "1 shaded comparisons without their texture file" in skip_counts(skipped)
    modes = [(Path(j.scene.path).stem, j.mode) for j in jobs(scenes, 16, ("f32",), ("rays",),
                                                               shaded_columns=16)]
    assert modes == [("nw__earth", "rays"), ("textured", "rays"), ("textured", "shaded")]
    _stand_ins(earth, tmp_path)
    scenes, skipped = attach_textures([earth], [tmp_path])
    assert not skipped
    assert [j.mode for j in jobs(scenes, 16, ("f32",), ("rays",), shaded_columns=16)] == \
        ["rays", "shaded"]


def test09_check_and_gallery_need_the_textures(tmp_path):
    """rtval check compares a tracer's image with the textured course image, so it needs the
    textures: without them, an error naming the file (the tracer is not even run); with
    --texture-dir, the check passes.  gallery: a named scene without its texture is an
    error; --texture-dir finds it."""
    scene = tmp_path / "textured.txt"
    shutil.copy(BUNDLED[0], scene)              # its textures stay in scenes/textures
    img = tmp_path / "ours.ppm"
    assert cli("render", BUNDLED[0], "--columns", 40, "--ppm", img).returncode == 0
    r = cli("check", BUNDLED[0], img)
    assert r.returncode == 0 and "pass" in r.stdout, r.stdout + r.stderr
    r = cli("check", scene, img)
    assert r.returncode == 2 and "not found" in r.stderr and "--texture-dir" in r.stderr, \
        r.stdout + r.stderr
    r = cli("check", scene, img, "--texture-dir", REPO / "scenes")
    assert r.returncode == 0 and "pass" in r.stdout, r.stdout + r.stderr
    # the check's verdict rests on the texture: another texture of the same name fails it
    other = tmp_path / "other" / "textures"
    other.mkdir(parents=True)
    for f in (REPO / "scenes" / "textures").iterdir():
        shutil.copy(f, other / f.name)
    tiles = other / "tiles4x3.ppm"
    ppm6(tiles, 255 - (textures.read_ppm(str(tiles)) * 255).round().astype(int))
    r = cli("check", scene, img, "--texture-dir", other.parent)
    assert r.returncode == 1 and "FAIL" in r.stdout, r.stdout + r.stderr
    ran = tmp_path / "ran"
    r = cli("check", "--run", f"touch {ran}; cp {img} {{out}} # {{scene}}", "--columns", 40,
            scene)
    # (rtval's input is missing, not the tracer's fault: refused, exit 2, as a malformed
    # scene is; a failing scene beside it still makes it 1)
    assert r.returncode == 2 and "not found" in r.stdout and "REFUSED" in r.stdout, \
        r.stdout + r.stderr
    assert not ran.exists()                     # the tracer was not run for nothing
    r = cli("check", "--run", f"cp {img} {{out}} # {{scene}}", "--columns", 40, scene,
            REPO / "scenes" / "fplane_tilted.txt")
    assert r.returncode == 1 and "REFUSED" in r.stdout, r.stdout + r.stderr
    r = cli("gallery", "-o", tmp_path / "g", "--columns", 16, scene)
    assert r.returncode == 2 and "not found" in r.stderr.strip().splitlines()[-1]
    r = cli("gallery", "-o", tmp_path / "g", "--columns", 16, scene,
            "--texture-dir", REPO / "scenes")
    assert r.returncode == 0, r.stderr
