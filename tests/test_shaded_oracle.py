"""validate's and compare's course image of scenes with objects Mitsuba has no shape for
(cones, ellipsoids, the torus) against the float64 shading oracle, every object (mode
``shaded-oracle``, tools/harness/shaded.py ``compare_shaded(.., reference="oracle")``).

The Mitsuba shaded comparison leaves those objects out on both sides, so a fault in their
normals, the shadows they cast or the reflections in them passed it."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import drjit as dr
import pytest

from rt_core import tracer
from tools.harness.html_report import compare_command
from tools.harness.shaded import compare_shaded, write_shaded_evidence

REPO = Path(__file__).resolve().parents[1]
CONES = REPO / "tests" / "scenes" / "cones.txt"
CONETEST = REPO.parent / "shared" / "course-scenes" / "numeric" / "nw__conetest.txt"


def _rtval(*args):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=600)


def test01_validate_compares_such_scenes_with_the_shading_oracle(tmp_path):
    r = _rtval("validate", "scenes/torus.txt", "scenes/sphere.txt", CONES, "--columns", "16",
               "--shaded-columns", "0", "--exact-columns", "0", "--oracle-columns", "16",
               "-o", tmp_path / "v", "--json", "--junit", tmp_path / "j.xml")
    assert r.returncode == 0, r.stderr
    rows = [x for x in json.loads(r.stdout)["results"] if x["mode"] == "shaded-oracle"]
    # the torus and cone scenes (the sphere scene has nothing Mitsuba lacks), every pixel
    assert [Path(x["scene"]).name for x in rows] == ["torus.txt", "cones.txt"]
    for x in rows:
        assert x["ok"] and x["precision"] == "f64 / oracle f64"
        assert sum(x["classes"].values()) == x["pixels"] == 16 * 12
        assert x["classes"]["match"] > x["pixels"] // 2
        assert x["seconds"]["oracle"] > 0 and x["seconds"]["mitsuba"] == 0
    junit = (tmp_path / "j.xml").read_text()
    assert 'name="torus.shaded-oracle.f64"' in junit and 'name="cones.shaded-oracle.f64"' in junit
    assert "rtval compare --shaded --reference oracle" in compare_command(rows[0])
    r = _rtval("validate", "scenes/torus.txt", "--columns", "16", "--shaded-columns", "0",
               "--exact-columns", "0", "--oracle-columns", "0", "-o", tmp_path / "v",
               "--json")
    assert r.returncode == 0 and not [x for x in json.loads(r.stdout)["results"]
                                      if x["mode"] == "shaded-oracle"]


def test02_a_fault_in_a_cones_normal_fails_here_and_passes_mitsubas(monkeypatch, tmp_path):
    from rt_core.parser import parse_scene
    if not CONETEST.exists():
        pytest.skip(f"{CONETEST} is not here (../shared/course-scenes)")
    scene = parse_scene(str(CONETEST))          # (two cones, a sphere)
    assert compare_shaded(scene, 24, reference="oracle").ok
    real = tracer.quadric_normal

    def tilted(ks, d, t, idx, hit, o=None):        # every quadric's normal tilted a little
        n = real(ks, d, t, idx, hit, o)
        return dr.normalize(n + type(n)(0.0, 0.0, 0.2))

    monkeypatch.setattr(tracer, "quadric_normal", tilted)
    bad = compare_shaded(scene, 24, reference="oracle")
    assert not bad.ok and bad.counts["wrong"] > 0
    # Mitsuba's comparison leaves the cones out on both sides: it cannot see the fault
    assert compare_shaded(scene, 24).ok
    paths = write_shaded_evidence(bad, str(tmp_path), "cs")
    assert sorted(Path(p).name for p in paths) == [
        "cs.shaded-oracle.classes.png", "cs.shaded-oracle.flip.png",
        "cs.shaded-oracle.oracle.png", "cs.shaded-oracle.ours.png"]


@pytest.mark.parametrize("args,code,phrase", [
    (["compare", "scenes/torus.txt", "--reference", "oracle", "--columns", "24"], 64, "--reference goes with "
                                                                    "--shaded"),
    (["compare", "scenes/torus.txt", "--shaded", "--reference", "oracle", "--columns", "400"],
     2, "more than the shading oracle's 20,000"),
    (["validate", "scenes/torus.txt", "--oracle-columns", "400"], 2,
     "--oracle-columns 400: 400 x 300 pixels is more than the shading oracle's"),
    (["validate", "scenes/torus.txt", "--oracle-columns", "1"], 2,
     "--oracle-columns 1: give 0 (off) or a width of at least 2")])
def test03_bad_requests_are_one_line(args, code, phrase, tmp_path):
    r = _rtval(*args, *(["-o", tmp_path / "v"] if args[0] == "validate" else []))
    assert r.returncode == code, r.stderr
    assert phrase in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "v").exists() or not any((tmp_path / "v").iterdir())
