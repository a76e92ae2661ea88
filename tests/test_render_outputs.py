"""rtval render's shaded outputs: PPM as the course writes it, PNG, R G B in the EXR, what
runs for which outputs (--explain), atomic writes, one-line errors."""
from __future__ import annotations

import glob
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rt_core import backend
from rt_core.camera import make_camera
from rt_core.exrio import read_exr
from rt_core.parser import parse_scene
from rt_core.render import GEOMETRY_CHANNELS, render_image
from rt_core.shading import DEFAULT_MAX_DIST, quantize

REPO = Path(__file__).resolve().parents[1]
from tests.tolerances import PRECISIONS  # noqa: E402


def rtval(*args):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO)


def library_image(name, columns, precision, **kw):
    scene = parse_scene(REPO / "scenes" / name)
    cam = make_camera(scene, columns)
    images, res = render_image(scene, cam, backend.types(precision), shade=True, **kw)
    return images, res


@pytest.mark.parametrize("precision", PRECISIONS)
def test01_ppm_png_exr(precision, tmp_path):
    ppm, png, exr = tmp_path / "a.ppm", tmp_path / "a.png", tmp_path / "a.exr"
    r = rtval("render", "scenes/mixed.txt", "--columns", 64, "--precision", precision,
              "--ppm", ppm, "--png", png, "-o", exr)
    assert r.returncode == 0, r.stderr
    images, _ = library_image("mixed.txt", 64, precision)
    want = quantize(np.stack([images[c] for c in "RGB"], -1))
    # PPM: the course programs' header on one line, then RGB bytes, top row first
    data = ppm.read_bytes()
    header = b"P6 64 48 255\n"
    assert data[:len(header)] == header and len(data) == len(header) + 64 * 48 * 3
    assert np.array_equal(np.frombuffer(data[len(header):], np.uint8).reshape(48, 64, 3), want)
    assert np.array_equal(np.asarray(Image.open(png).convert("RGB")), want)
    assert Image.open(png).text["rtval.scene"].endswith("mixed.txt")
    # EXR: geometry and the unclamped intensity, as float32
    ch, hdr = read_exr(exr)
    assert set(GEOMETRY_CHANNELS) | {"R", "G", "B"} <= set(ch)
    for c in "RGB":
        np.testing.assert_array_equal(ch[c], images[c].astype(np.float32))
    assert ch["R"].max() > 1.0                     # unclamped: mixed.txt saturates somewhere
    assert hdr["rtval.shading"] == "on" and float(hdr["rtval.max_dist"]) == DEFAULT_MAX_DIST
    assert "1 reflection bounce (max-dist 1000)" in r.stderr and "Traceback" not in r.stderr


def test02_exr_alone_is_geometry_only(tmp_path):
    r = rtval("render", "scenes/mixed.txt", "--columns", 32, "-o", tmp_path / "g.exr",
              "--explain")
    assert r.returncode == 0, r.stderr
    ch, hdr = read_exr(tmp_path / "g.exr")
    assert not {"R", "G", "B"} & set(ch) and hdr["rtval.shading"] == "off"
    assert "shading: off" in r.stderr and "primary  bounce" not in r.stderr
    r = rtval("render", "scenes/mixed.txt", "--columns", 32, "-o", tmp_path / "s.exr",
              "--shade")
    assert r.returncode == 0, r.stderr
    assert {"R", "G", "B"} <= set(read_exr(tmp_path / "s.exr")[0])


def test03_explain_names_passes_and_kernels(tmp_path):
    r = rtval("render", "scenes/mixed.txt", "--columns", 32, "--png", tmp_path / "m.png",
              "--explain")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if "explain:" in ln]
    text = "\n".join(lines)
    assert "sphere 1, plane 1, fplane 1, tplane 1" in text and "2 lights" in text
    # one kernel per bounce (hit, shadows, shading): the primary one and the reflection
    # bounces' (the tail)
    for row in ("primary  bounce", "1        tail"):
        assert row in text, text
    assert "up to 2 shadow rays per hit" in text
    assert "launched" in text and "compiled" in text
    # a scene without specular: no reflection pass; a scene with one light: one shadow ray
    r = rtval("render", "scenes/sphere.txt", "--columns", 32, "--png", tmp_path / "s.png",
              "--explain")
    assert "no reflection pass" in r.stderr and "up to 1 shadow ray per hit" in r.stderr
    assert "tail" not in r.stderr


def test04_usage_errors(tmp_path):
    r = rtval("render", "scenes/sphere.txt", "--columns", 16)
    assert r.returncode == 64 and "nothing to write" in r.stderr
    r = rtval("render", "scenes/sphere.txt", "--columns", 16, "--ppm", tmp_path / "x",
              "--png", tmp_path / "x")
    assert r.returncode == 64 and "same file" in r.stderr
    assert not list(tmp_path.iterdir())
    r = rtval("render", "scenes/sphere.txt", "--columns", 16, "--ppm", tmp_path / "x",
              "--max-dist", "-1")
    assert r.returncode == 64
    assert str(int(DEFAULT_MAX_DIST)) in rtval("render", "--help").stdout


def test05_errors_leave_no_file(tmp_path):
    outs = ["--ppm", tmp_path / "a.ppm", "--png", tmp_path / "a.png", "-o", tmp_path / "a.exr"]
    bad = tmp_path / "bad.txt"
    bad.write_text("8 6\n0 0 5\nsphere 1 1 1\n")
    r = rtval("render", bad, "--columns", 16, *outs)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "bad.txt:" in r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.txt"]
    # an output that cannot be a file: refused before rendering, nothing else written
    (tmp_path / "d.png").mkdir()
    r = rtval("render", "scenes/sphere.txt", "--columns", 16, "--ppm", tmp_path / "b.ppm",
              "--png", tmp_path / "d.png")
    assert r.returncode == 2 and "is a directory" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "b.ppm").exists()
    assert not glob.glob(str(tmp_path / ".tmp-*")) and not glob.glob(str(tmp_path / "*/.tmp-*"))


def test06_bounce_cap_is_a_warning(tmp_path, monkeypatch, capsys):
    from rt_core import shading
    from tools.cli import main
    monkeypatch.setattr(shading, "MAX_BOUNCES", 3)
    assert main(["render", "scenes/shade_mirrors.txt", "--columns", "32", "--png",
                 str(tmp_path / "m.png"), "--explain"]) == 0
    err = capsys.readouterr().err
    assert "warning: reflections stopped at the safety cap of 3 bounces with" in err
    assert "SAFETY CAP reached" in err and (tmp_path / "m.png").exists()


def test07_json_summary(tmp_path):
    """--json: a summary of what was written on stdout (and nothing else there)."""
    import json
    png = tmp_path / "a.png"
    r = rtval("render", "scenes/mixed.txt", "--columns", 32, "--png", png, "--json")
    assert r.returncode == 0, r.stderr
    data = json.loads(r.stdout)
    assert data["outputs"] == [{"option": "--png", "path": str(png)}] and png.is_file()
    assert (data["columns"], data["rows"], data["objects"]) == (32, 24, 4)
    assert data["reflection_bounces"] == 1 and data["nonfinite"] == 0 and data["shaded"]
    assert data["provenance"]["rtval.scene"].endswith("mixed.txt")
    r = rtval("render", "scenes/mixed.txt", "--columns", 32, "-o", tmp_path / "g.exr", "--json")
    data = json.loads(r.stdout)
    assert data["hits"] == 32 * 24 and not data["shaded"] and data["reflection_bounces"] is None
