"""rtval gallery: PNGs of every supported scene, an HTML page, a contact sheet; unsupported
files listed on stderr with the parser's one-line message."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from tools.cmd_gallery import scene_files

REPO = Path(__file__).resolve().parents[1]
COURSE = REPO.parent / "shared" / "course-scenes"


def rtval(*args):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO)


def _check_listing(out, rc, stdout, stderr, files, unsupported_too: bool = True):
    """A gallery of ``files`` (scene_files' (name, path)): every file rendered or listed as
    skipped with its category and the parser's line, the page, the textures' notes, the sheet.
    ``unsupported_too``: some file is of a kind rtval does not implement (no course file
    is: every one is read, or malformed)."""
    assert rc == 0, stderr
    assert stdout.split() == [str(out / "index.html"), str(out / "contact.png")]
    skipped = [ln for ln in stderr.splitlines() if ln.startswith("rtval gallery: skipped")]
    # each with its category and the parser's one line: file:line:col: message
    assert skipped and all(":" in ln.split(") ", 1)[1] for ln in skipped)
    unsupported = [ln for ln in skipped if ln.startswith("rtval gallery: skipped (unsupported)")]
    malformed = [ln for ln in skipped if ln.startswith("rtval gallery: skipped (malformed)")]
    assert malformed and len(unsupported) + len(malformed) == len(skipped)
    assert bool(unsupported) == unsupported_too
    assert all("is not supported" in ln for ln in unsupported)
    assert not any("is not supported" in ln for ln in malformed)
    pngs = sorted(p.name for p in out.glob("*.png") if p.name != "contact.png")
    assert len(pngs) + len(skipped) == len(files)
    bundled = sorted(p.stem for p in (REPO / "scenes").glob("*.txt"))
    assert {f"scenes__{b}.png" for b in bundled} <= set(pngs)
    assert any(p.startswith("course__numeric__") for p in pngs)
    page = (out / "index.html").read_text()
    assert all(f'src="{p}"' in page for p in pngs) and page.count("<li>") == len(skipped)
    assert f"{len(pngs)} scenes rendered, {len(skipped)} skipped" in stderr
    # the course files' textures are not in the corpus: those scenes still render, with their
    # MAT, and say so on stderr and in their caption; the bundled ones find theirs
    missing = [ln for ln in stderr.splitlines() if ln.endswith(": shaded with its MAT")]
    assert any("nw__earth.txt" in ln and "earth2.ppm' not found" in ln for ln in missing)
    assert "course__numeric__nw__earth.png" in pngs
    assert page.count(": shaded with its MAT</i>") == len(missing)
    assert not any("scenes/textured" in ln for ln in missing)
    sheet = np.asarray(Image.open(out / "contact.png"))
    assert sheet.shape[1] == 6 * 24 and sheet.shape[0] >= (len(pngs) // 6) * 18


@pytest.mark.slow
def test01_every_scene(tmp_path):
    """Every bundled and course scene (about 150 renders: the default run renders a sample,
    test01b)."""
    out = tmp_path / "g"
    r = rtval("gallery", "-o", out, "--columns", 24)
    _check_listing(out, r.returncode, r.stdout, r.stderr, scene_files([]), unsupported_too=False)


# course files of each kind of outcome: textured without its texture, numeric and keyword,
# quadrics; and one unsupported and one malformed file written here
SAMPLE = ["numeric/nw__earth.txt", "numeric/cbl__specTile.txt", "numeric/m4__v1_a04.txt",
          "keyword/rm768__bowling.txt"]


def test01b_a_sample_of_scenes(tmp_path, monkeypatch, capsys):
    """The gallery's default sources (the bundled scenes and a sample of course files) in
    this process, as test01 renders every one."""
    import tools.cmd_gallery as gallery
    from tools.cli import main
    course = tmp_path / "course"
    for name in SAMPLE:
        src = COURSE / name
        if not src.is_file():
            pytest.skip(f"{src} is not there")
        (course / name).parent.mkdir(parents=True, exist_ok=True)
        (course / name).write_bytes(src.read_bytes())
    (course / "numeric" / "spot.txt").write_text("8 6\n0 0 5\n21\n1 1 1\n")
    (course / "keyword" / "bad.txt").write_text("8 6\n0 0 5\nsphere 1 1\n")
    monkeypatch.setattr(gallery, "SOURCES", (("scenes", REPO / "scenes"), ("course", course)))
    out = tmp_path / "g"
    rc = main(["gallery", "-o", str(out), "--columns", "24"])
    said = capsys.readouterr()
    _check_listing(out, rc, said.out, said.err, gallery.scene_files([]))


def test02_given_files(tmp_path):
    """A scene named on the command line must render (as in validate): an unsupported one is
    an error, not a skip; two named files with one stem get distinct images."""
    bad = tmp_path / "spot.txt"
    bad.write_text("8 6\n0 0 5\n21\n1 1 1\n")
    r = rtval("gallery", "-o", tmp_path / "g", "--columns", 16, REPO / "scenes" / "sphere.txt",
              bad)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().endswith(f"{bad}:3:1: 21 (paraboloid) is not supported "
                                     "(supported codes: 10 point light, 11 spotlight, 13 sphere, "
                                     "14 plane, 15 finite plane, 16 tiled plane, 17 textured "
                                     "plane, 19 procedural sphere, 20 procedural plane, "
                                     "22 cylinder, 23 cone, 25 torus (cd: lens), 26 textured "
                                     "sphere, 27 triangle (a disk in nw's older layout), "
                                     "28 displacement sphere, 29 disk)")
    for sub, src in (("a", "sphere.txt"), ("b", "plane.txt")):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "s.txt").write_text((REPO / "scenes" / src).read_text())
    r = rtval("gallery", "-o", tmp_path / "g2", "--columns", 16, tmp_path / "a" / "s.txt",
              tmp_path / "b" / "s.txt")
    assert r.returncode == 0, r.stderr
    pngs = sorted(p.name for p in (tmp_path / "g2").glob("*s.png"))
    assert len(pngs) == 2, pngs



def test03_json(tmp_path):
    """--json: what was written, on stdout, instead of the two paths."""
    import json
    out = tmp_path / "g"
    r = rtval("gallery", "-o", out, "--columns", 20, "--json", REPO / "scenes" / "sphere.txt",
              REPO / "scenes" / "mixed.txt")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    assert [s["name"] for s in data["scenes"]] == ["sphere", "mixed"]
    for s in data["scenes"]:
        with Image.open(s["png"]) as im:
            assert im.size == (s["columns"], s["rows"]) == (20, 15)
    assert [s["reflection_bounces"] for s in data["scenes"]] == [0, 1]
    assert data["page"] == str(out / "index.html") and Path(data["contact_sheet"]).is_file()
    assert data["skipped"] == [] and data["meta"]["drjit"] and data["meta"]["columns"] == 20


def test03_every_scene_its_own_png_and_working_links(tmp_path):
    """A scene named contact, d1/s beside d1__s, and names with '#': each PNG was not its
    own (the contact sheet replaced contact.png, d1__s.png held the other scene) and the
    page's links broke on '#' (a review).  Each gets its own file, the page links each by
    its URL-quoted name, and every link resolves."""
    import html.parser
    from urllib.parse import unquote
    root = Path(__file__).resolve().parents[1] / "scenes"
    for rel, src in (("contact.txt", "sphere.txt"), ("a#1.txt", "sphere.txt"),
                     ("d1/s.txt", "plane.txt"), ("d2/s.txt", "sphere.txt"),
                     ("d1__s.txt", "plane.txt")):
        (tmp_path / rel).parent.mkdir(exist_ok=True)
        (tmp_path / rel).write_text((root / src).read_text())
    out = tmp_path / "OUT"
    r = subprocess.run([sys.executable, "-m", "tools.cli", "gallery", "contact.txt", "a#1.txt",
                        "d1/s.txt", "d2/s.txt", "d1__s.txt", "--columns", "16", "-o", str(out)],
                       cwd=tmp_path, capture_output=True, text=True,
                       env={**__import__("os").environ, "PYTHONPATH": str(root.parent)})
    assert r.returncode == 0, r.stderr

    class Imgs(html.parser.HTMLParser):
        srcs: list = []

        def handle_starttag(self, tag, attrs):
            if tag == "img":
                self.srcs.append(dict(attrs)["src"])
    p = Imgs()
    p.feed((out / "index.html").read_text())
    files = [unquote(s) for s in p.srcs]
    assert len(files) == 5 == len(set(files)) and "contact.png" not in files
    assert all((out / f).is_file() for f in files)
    scenes = {Image.open(out / f).text["rtval.scene"] for f in files}
    assert len(scenes) == 5
    # --json names each PNG's scene and its hash (it named the PNG alone: a review)
    r = subprocess.run([sys.executable, "-m", "tools.cli", "gallery", "a#1.txt", "--columns",
                        "16", "-o", str(tmp_path / "J"), "--json"], cwd=tmp_path,
                       capture_output=True, text=True,
                       env={**__import__("os").environ, "PYTHONPATH": str(root.parent)})
    import hashlib
    import json
    got = json.loads(r.stdout)["scenes"][0]
    assert got["scene"] == "a#1.txt" and got["scene_sha256"] == hashlib.sha256(
        (tmp_path / "a#1.txt").read_bytes()).hexdigest()
