"""Shadow rays and first-bounce reflections of rt_core's shading against Mitsuba 3, ray by ray
(tools/harness/secondary.py): no unexplained disagreement on any bundled or supported course
scene, in either precision; and broken shadows or reflections *are* reported."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rt_core import shading
from rt_core.parser import parse_scene
from rt_core.rules import Rules
from mitsuba_ref.convert import plane_extent
from tools.harness.secondary import (CLASS_CODE, SkipScenes, classify_hits, compare_secondary,
                                    reference_hits)
from tools.harness.validate import COURSE_SCENES, default_scene_paths, load_supported

REPO = Path(__file__).resolve().parents[1]
BUNDLED = sorted((REPO / "scenes").glob("*.txt"))
from tests.tolerances import PRECISIONS  # noqa: E402
COLUMNS = 80


def check(scene, precision, columns=COLUMNS):
    cmp = compare_secondary(scene, columns, precision=precision)
    lines = [e for c in cmp.checks for e in c.examples()]
    assert cmp.unexplained == 0, f"{scene.path} {precision}: {cmp.summary()['rays']}\n" + \
        "\n".join(lines)
    return cmp


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test01_bundled_scene(path, precision):
    scene = parse_scene(path)
    cmp = check(scene, precision)
    names = [c.name for c in cmp.checks]
    # every light's shadow rays from the primary hits were compared, and the reflections
    assert [n for n in names if n.endswith("bounce 0")] == \
        [f"shadow L{j} bounce 0" for j in range(len(scene.lights))]
    assert all(len(c.classes) > 0 for c in cmp.checks if c.name.endswith("bounce 0"))
    if shading.any_specular(scene):
        refl = [c for c in cmp.checks if c.name == "reflection"]
        assert refl and len(refl[0].classes) > 0
    # nearly all agree outright; the explained ones are the exception
    for c in cmp.checks:
        assert c.counts["agree"] >= 0.97 * len(c.classes), (c.name, c.counts)


def _course_scenes(every: int = 1):
    """The supported course scenes of validate's default set (the bundled ones are
    test01's), every ``every``-th by path."""
    paths = [p for p in default_scene_paths() if p.parent.parent == COURSE_SCENES]
    if not paths:
        pytest.skip(f"no course scenes at {COURSE_SCENES}")
    scenes, _ = load_supported(sorted(paths)[::every], explicit=False)
    return scenes


@pytest.mark.parametrize("precision", PRECISIONS)
def test02_course_scenes(precision):
    """A sample of the course scenes (every one: test02b, slow, 3 minutes)."""
    scenes = _course_scenes(6)
    assert len(scenes) >= 15
    for scene in scenes:
        check(scene, precision, columns=64)


@pytest.mark.slow
@pytest.mark.parametrize("precision", PRECISIONS)
def test02b_every_course_scene(precision):
    for scene in _course_scenes():
        check(scene, precision, columns=64)


def test03_broken_shadows_are_reported(monkeypatch):
    # shadow rays that never find a blocker: rt_core lights what Mitsuba shadows
    real = shading.occluded
    monkeypatch.setattr(shading, "occluded", lambda *a: real(*a) & False)
    cmp = compare_secondary(parse_scene(REPO / "scenes" / "shade_shadows.txt"), 64)
    assert cmp.unexplained > 100


def test04_wrong_reflection_ids_are_reported():
    cmp = compare_secondary(parse_scene(REPO / "scenes" / "shade_tiles.txt"), 64)
    refl = next(c for c in cmp.checks if c.name == "reflection")
    assert refl.unexplained == 0 and np.any(refl.ours >= 0)
    # our ids swapped for another object's: every changed ray is unexplained, except where
    # the wrong id is the surface the ray leaves ('origin': it is at distance 0 there)
    wrong = np.where(refl.ours >= 0, (refl.ours + 1) % 3, -1)
    cls = classify_hits(cmp.scene, refl.O, refl.d, wrong, refl.ref, Rules(),
                        plane_extent(cmp.scene))
    changed = np.count_nonzero(wrong != refl.ref)
    assert changed > 50
    explained = cls[wrong != refl.ref]
    assert set(np.unique(explained)) <= {CLASS_CODE["unexplained"], CLASS_CODE["origin"]}
    assert np.count_nonzero(explained == CLASS_CODE["unexplained"]) > 0.8 * changed


def test05_screen_clip_applies_to_plane_kinds_only():
    # a ray from below the floor's z > 0 part: Mitsuba alone would hit the floor at z > 0,
    # the course's screen clip makes that a miss, so the ray finds the ball behind it
    scene = parse_scene(REPO / "scenes" / "shade_shadows.txt")
    refs = SkipScenes(scene, 32, None, "corners")
    O = np.array([[0.0, 0.0, 3.0], [-1.0, 3.0, -6.0]])
    d = np.array([[0.0, -1.0, 0.0], [0.0, -1.0, 0.0]])
    hit, oid, s = reference_hits(refs, Rules(), O, d, np.full(2, np.inf), np.full(2, -1))
    assert list(hit) == [False, True] and oid[1] == 1          # floor clipped; ball at x=-1
    np.testing.assert_allclose(s[1], 3.0 - (-0.8 + 1.2), rtol=1e-6)
    hit, oid, _ = reference_hits(refs, Rules(screen_clip="off"), O, d, np.full(2, np.inf),
                                 np.full(2, -1))
    assert list(hit) == [True, True] and oid[0] == 0
