"""mitsuba_ref.shade_batch: the shading oracle's first pass on arrays gives the per-pixel
oracle's numbers, bit for bit.

* every pixel of every scene shade_batch covers (bundled and course scenes, 12 columns): the
  intensities, their bounds, the bounces, the five margins, the colours and the set of near
  decisions equal shade_oracle.ray_trace's (the per-pixel oracle, run with shade_pixels'
  BATCH_MIN out of reach);
* the same under every rule variant, on the bundled scenes (all course scenes: ``slow``);
* shade_pixels runs the batch from BATCH_MIN pixels on, and leaves to the per-pixel oracle what
  the batch does not cover (a cylinder, a texture) and a pixel whose numbers are not all
  numbers (a light on the surface: the per-pixel oracle's division by zero, a course
  program's NaN: every margin 0, no path);
* seeded random scenes, and _at_risk's ties and NaNs against the scalar function;
* decisions taken the other way (flips, at float64's and at the float hint's limit): each
  path as the per-pixel code traces it, and other_sides_of's answers other_sides', also at
  the edges of its ``runs`` and ``bounces``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mitsuba_ref import shade_batch, shade_oracle
from rt_core.parser import parse_text
from rt_core.rules import Rules
from tools.harness.validate import default_scene_paths, load_supported
from tests.tolerances import U

REPO = Path(__file__).resolve().parents[1]
OUT = ("I", "err", "bounces", "reach", *shade_oracle.MARGINS)
VARIANTS = [Rules(ties="last", edges="open"), Rules(screen_clip=">=", clip_spheres=True),
            Rules(screen_clip="off", reflect="segment"),
            Rules(tile_add_first=True, tile_project=False, rows="shifted", t_min=0.01)]


def _scenes(bundled_only: bool = False):
    paths = [p for p in default_scene_paths()
             if not bundled_only or p.parent == REPO / "scenes"]
    scenes, _ = load_supported(paths, False)
    return [s for s in scenes if shade_batch.supported(s)]


def _per_pixel(scene, W, H, pixels, rules, md, monkeypatch):
    with monkeypatch.context() as m:
        m.setattr(shade_oracle, "BATCH_MIN", 10 ** 9)
        return shade_oracle.shade_pixels(scene, W, H, pixels, "corners", rules, md)


def _same(scene, columns, rules, md, monkeypatch, sampling="corners", rows=None):
    W = columns
    H = scene.default_rows(W) if rows is None else rows
    px = np.arange(W * H)
    base, d = shade_batch.rays(scene, W, H, px, sampling, rules)
    got = shade_batch.shade(scene, base, d, rules, md)
    ref = _per_pixel(scene, W, H, px, rules, md, monkeypatch)
    ok = shade_batch.usable(got)
    assert ok.all(), f"{scene.path}: {int((~ok).sum())} pixels left to the per-pixel oracle"
    for k in OUT:
        bad = np.flatnonzero((got[k] != ref[k]).reshape(len(px), -1).any(-1))
        assert not len(bad), (f"{scene.path} {rules.describe()}: '{k}' differs at "
                              f"{len(bad)} pixels, first {bad[0]}: {got[k][bad[0]]} against "
                              f"{ref[k][bad[0]]}")
    colours = shade_batch.colours(got["I"])
    for p, (seen, (colour, near, _)) in enumerate(zip(got["seen"], ref["paths"])):
        assert colours[p] == colour
        assert set(seen) == set(near), (scene.path, p, seen, near)
    return got


SCENES = _scenes()
CYLINDER = ("8 6\n0 3 5\n10\n4 3 2\n5 1 -1\n"          # numeric dialect: a light, a cylinder
            "22\n0.5 1 0.5\n2 6 2\n0 0 0\n2.5 -0.9 -5\n-0.4 0.3 1\n0.9 2.2\n")


def test01_covers_most_scenes():
    """The kinds shade_batch takes are those of most scenes: without them it would speed
    nothing up (and the equality tests below would test little)."""
    assert len(SCENES) >= 100
    assert not shade_batch.supported(parse_text(CYLINDER))


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: Path(s.path).stem)
def test02_every_pixel_the_same_numbers(scene, monkeypatch):
    got = _same(scene, 12, Rules(), 1000.0, monkeypatch)
    assert np.isfinite(got["I"]).all()


@pytest.mark.parametrize("rules", VARIANTS, ids=lambda r: r.describe().replace(",", " "))
@pytest.mark.parametrize("scene", _scenes(bundled_only=True), ids=lambda s: Path(s.path).stem)
def test03_rule_variants_and_cut_off(scene, rules, monkeypatch):
    _same(scene, 10, rules, 1000.0, monkeypatch)
    _same(scene, 10, rules, 25.0, monkeypatch)


def test04_near_decisions_found():
    """The equality above is not of empty sets: at 12 columns the scenes have pixels with
    near decisions (within float64's bound) of each kind: a primary and a reflection ray's
    hit, a shadow test at a primary and at a reflection's hit, a tile's parity, the cut-off."""
    kinds = set()
    for scene in SCENES:
        W = 12
        H = scene.default_rows(W)
        base, d = shade_batch.rays(scene, W, H, np.arange(W * H), "corners", Rules())
        for seen in shade_batch.shade(scene, base, d, Rules(), 1000.0)["seen"]:
            kinds |= {(b > 0, what) for b, what, _ in seen}
    assert {(False, "geo"), (True, "geo"), (False, "shadow"), (True, "shadow"),
            (False, "tile"), (True, "maxdist")} <= kinds


@pytest.mark.slow
@pytest.mark.parametrize("rules", VARIANTS, ids=lambda r: r.describe().replace(",", " "))
def test05_course_scenes_under_variants(rules, monkeypatch):
    for scene in SCENES:
        _same(scene, 16, rules, 1000.0, monkeypatch)


def test06_centre_sampling(monkeypatch):
    for scene in _scenes(bundled_only=True)[:6]:
        W = 11
        H = scene.default_rows(W)
        px = np.arange(W * H)
        base, d = shade_batch.rays(scene, W, H, px, "centers", Rules())
        got = shade_batch.shade(scene, base, d, Rules(), 1000.0)
        with monkeypatch.context() as m:
            m.setattr(shade_oracle, "BATCH_MIN", 10 ** 9)
            ref = shade_oracle.shade_pixels(scene, W, H, px, "centers")
        for k in OUT:
            assert np.array_equal(got[k], ref[k]), (scene.path, k)


def test07_shade_pixels_uses_the_batch(monkeypatch):
    """From BATCH_MIN pixels on, shade_pixels' answer is the batch's (the per-pixel code is
    not run), below it the per-pixel oracle's; the two are equal."""
    scene = SCENES[0]
    W, H = 16, SCENES[0].default_rows(16)
    px = np.arange(0, W * H, 2)
    calls = []
    real = shade_oracle.ray_trace
    monkeypatch.setattr(shade_oracle, "ray_trace", lambda *a, **k: calls.append(1) or real(*a, **k))
    got = shade_oracle.shade_pixels(scene, W, H, px)
    assert calls == []
    small = shade_oracle.shade_pixels(scene, W, H, px[:shade_oracle.BATCH_MIN - 1])
    assert len(calls) == shade_oracle.BATCH_MIN - 1
    for k in OUT:
        assert np.array_equal(got[k][:len(small[k])], small[k])
    assert [p[1] and set(p[1]) for p in got["paths"][:len(small["paths"])]] == \
        [p[1] and set(p[1]) for p in small["paths"]]


def test08_left_to_the_per_pixel_oracle(monkeypatch):
    """A scene the batch does not cover runs per pixel; a pixel whose light lies on the point
    it lights divides by zero in the per-pixel oracle: shade_pixels gives it every margin 0
    (flagged) and no path (any colour), and the other pixels their numbers.  (It raised
    the ZeroDivisionError, and rtval check stopped with a traceback.)"""
    cyl = parse_text(CYLINDER)
    calls = []
    real = shade_oracle.ray_trace
    monkeypatch.setattr(shade_oracle, "ray_trace", lambda *a, **k: calls.append(1) or real(*a, **k))
    shade_oracle.shade_pixels(cyl, 8, 6, np.arange(48))
    assert len(calls) == 48
    # the middle pixel of 3 x 3 looks straight down -z, at the light on the plane z = −1
    on = parse_text("2 2\n0 0 1\nplane\n1 1 1\n1 1 1\n0 0 0\n0 0 1\n0 0 -1\n"
                    "pointlight\n1 1 1\n0 0 -1\n")
    px = np.arange(9)
    base, d = shade_batch.rays(on, 3, 3, px, "corners", Rules())
    got = shade_batch.shade(on, base, d, Rules(), 1000.0)
    assert list(np.flatnonzero(got["raised"])) == [4]
    assert list(np.flatnonzero(~shade_batch.usable(got))) == [4]
    with pytest.raises(ZeroDivisionError):
        shade_oracle.ray_trace(on, *shade_oracle.pixel_ray(on, 3, 3, 4, "corners", Rules()),
                               shade_oracle.EF(0.0, 0.0), None, Rules(), 1000.0,
                               shade_oracle._Pixel())
    whole = shade_oracle.shade_pixels(on, 3, 3, px)
    assert whole["paths"][4] is None and all(whole[m][4] == 0 for m in shade_oracle.MARGINS)
    assert shade_oracle.flags(whole, "f64")["jump"][4]
    assert shade_oracle.other_sides(on, 3, 3, 4) is None
    rest = [p for p in px if p != 4]
    ref = _per_pixel(on, 3, 3, rest, Rules(), 1000.0, monkeypatch)
    for k in OUT:
        assert np.array_equal(np.delete(whole[k], 4, axis=0), ref[k]), k


def test09_at_risk_ties_and_nan():
    """oracle._at_risk's choice among equal margins (by diagnostic name) and past NaN margins
    (Python's tuple min and max, in the tests' order), lane by lane, against the scalar
    function on made-up tests: scenes almost never tie two diagnostics exactly."""
    from mitsuba_ref import oracle
    rng = np.random.default_rng(5)
    names = ["tmin_margin", "graze", "clip_margin", "edge_margin"]
    values = np.array([0.5, 0.5, 2.0, np.inf, np.nan, 0.0])
    n = 400
    for order in (names, names[::-1], names[1:] + names[:1]):
        m = values[rng.integers(0, len(values), (len(order), n))]
        passed = rng.random((len(order), n)) < 0.5
        valid = passed.all(0)
        tests = [(k, passed[i], m[i], True) for i, k in enumerate(order)]
        idx, got = shade_batch._at_risk(tests, valid, n)
        for j in range(n):
            key, want = oracle._at_risk([(k, bool(passed[i, j]), m[i, j])
                                         for i, k in enumerate(order)], bool(valid[j]))
            assert order[idx[j]] == key and (got[j] == want or np.isnan(got[j]) and
                                             np.isnan(want)), (j, order, m[:, j], passed[:, j])


@pytest.mark.parametrize("seed", range(24))
def test10_random_scenes(seed, monkeypatch):
    """Seeded random scenes (tests/scenegen.py: planes that copy an earlier plane's equation
    and tie exactly, tilted finite and tiled planes, spheres, mirrors), a spotlight added to
    every third, under the rules of the seed: the per-pixel oracle's numbers."""
    import dataclasses
    from rt_core.scene import SpotLight
    from tests.scenegen import random_scene
    scene = random_scene(seed, n_objects=6 + seed % 5, tie_prob=0.4)
    if seed % 3 == 0:
        spot = SpotLight((5.0, 5.0, 5.0), (0.5, 4.0, 1.0), (0.0, -1.0, -8.0), 25.0)
        scene = dataclasses.replace(scene, lights=scene.lights + (spot,))
    rules = (VARIANTS + [Rules()])[seed % (len(VARIANTS) + 1)]
    _same(scene, 12, rules, 1000.0 if seed % 2 else 40.0, monkeypatch)


F32_LIMIT = shade_oracle.K_DECISION * 4 * U["f32"]     # check.py's float hint asks this


def _near_pixels(scene, W, H, rules, limit):
    base, d = shade_batch.rays(scene, W, H, np.arange(W * H), "corners", rules)
    got = shade_batch.shade(scene, base, d, rules, 1000.0, limit=limit)
    return [p for p in range(W * H) if got["seen"][p]], got


def _scenes_with_near_pixels(scenes, rules, limit, W: int = 12):
    """(scene, W, H, its near pixels, _near_pixels' shade) of each of ``scenes`` that has
    any, at W columns."""
    for scene in scenes:
        H = scene.default_rows(W)
        pick, got = _near_pixels(scene, W, H, rules, limit)
        if pick:
            yield scene, W, H, pick, got


@pytest.mark.parametrize("limit", [None, F32_LIMIT], ids=["f64", "f32"])
def test11_paths_with_decisions_flipped(limit):
    """Each near decision of a pixel taken the other way, alone and all together: the batch's
    path (colour, near decisions, bounces) is the per-pixel code's, and where that raises
    (no hit to take: a sphere's discriminant, a plane parallel to the ray) the batch says so
    ('raised')."""
    lanes, raised = [], 0
    for scene, W, H, pick, got in _scenes_with_near_pixels(SCENES[::3], Rules(), limit):
        todo = [(p, frozenset([k])) for p in pick for k in got["seen"][p]] + \
            [(p, frozenset(got["seen"][p])) for p in pick]
        px = np.array([p for p, _ in todo])
        base, d = shade_batch.rays(scene, W, H, px, "corners", Rules())
        out = shade_batch.shade(scene, base, d, Rules(), 1000.0, [f for _, f in todo], limit)
        for j, ((p, flips), path) in enumerate(zip(todo, shade_batch.paths(out))):
            ref = shade_oracle._path(scene, W, H, p, "corners", Rules(), 1000.0, flips, limit)
            assert bool(out["raised"][j]) == (ref is None), (scene.path, p, flips)
            if path is None:
                raised += 1
                continue            # (shade_pixels and other_sides_of ask the per-pixel code)
            assert (path[0], set(path[1]), path[2]) == (ref[0], set(ref[1]), ref[2]), \
                (scene.path, p, flips)
            lanes.append(j)
    assert len(lanes) > 300 and (raised > 0 or limit is None)


@pytest.mark.parametrize("limit,rules,scenes", [
    (None, Rules(), slice(1, None, 4)), (F32_LIMIT, VARIANTS[0], slice(1, None, 8)),
    (F32_LIMIT, VARIANTS[3], slice(5, None, 8))], ids=["f64", "f32-a", "f32-b"])
def test12_other_sides_of(limit, rules, scenes, monkeypatch):
    """other_sides_of (the paths of many pixels traced together, a round at a time) gives
    other_sides' answer for each pixel: its colours, or None; also for fewer pixels than
    BATCH_MIN, whose rounds may still hold BATCH_MIN paths (``few``: such rounds ran).
    The two float32 rule variants take alternate scenes of every 4th (27 s in all when
    both took every 4th)."""
    answers, few = set(), 0
    calls = []
    shade = shade_batch.shade
    monkeypatch.setattr(shade_batch, "shade", lambda *a, **k: calls.append(1) or shade(*a, **k))
    for scene, W, H, pick, _ in _scenes_with_near_pixels(SCENES[scenes], rules, limit):
        firsts = None
        if limit is None:
            firsts = shade_oracle.shade_pixels(scene, W, H, pick, "corners", rules)["paths"]
        many = shade_oracle.other_sides_of(scene, W, H, pick, "corners", rules, 1000.0,
                                           firsts=firsts, limit=limit)
        for p, a in zip(pick, many):
            assert a == shade_oracle.other_sides(scene, W, H, p, "corners", rules, 1000.0,
                                                 limit=limit), (scene.path, p)
            answers.add("none" if a is None else "several" if len(a) > 1 else "one")
        # the same pixels a few at a time: the same answers
        for k in range(0, len(pick), 5):
            calls.clear()
            some = shade_oracle.other_sides_of(scene, W, H, pick[k:k + 5], "corners", rules,
                                               1000.0, firsts=firsts and firsts[k:k + 5],
                                               limit=limit)
            assert some == many[k:k + 5], (scene.path, pick[k:k + 5])
            few += bool(calls)
    assert answers == {"none", "several", "one"} and few > 0


@pytest.mark.parametrize("limit", [None, F32_LIMIT], ids=["f64", "f32"])
def test12b_other_sides_of_with_targets(limit, monkeypatch):
    """With ``targets`` (the colours classify_shaded asks about), a pixel whose colours found
    so far hold all of them is True and traces no more paths; otherwise the answer is the
    one without (the colour set, or None).  True only where the whole set holds them, or
    where it cannot be enumerated (None) and ``reaches`` finds them; the per-pixel
    other_sides the same; fewer paths traced in all."""
    lanes = []
    paths = shade_oracle._paths
    monkeypatch.setattr(shade_oracle, "_paths",
                        lambda *a: lanes.append(len(a[7])) or paths(*a))
    kinds, traced = set(), {}
    for scene, W, H, pick, _ in _scenes_with_near_pixels(SCENES[::2], Rules(), limit):
        lanes.clear()
        full = shade_oracle.other_sides_of(scene, W, H, pick, limit=limit)
        traced["full"] = traced.get("full", 0) + sum(lanes)
        own = [shade_oracle._path(scene, W, H, p, "corners", Rules(), 1000.0, frozenset(),
                                  limit)[0] for p in pick]
        # both sides' colours where a pixel has two; where its sides cannot all be
        # enumerated, its own and the colour of its first near decision taken the other way
        # (found early: then the answer rests on reaches); else its own and one no side gives
        def aim(p, o, a):
            if a is None:
                first = shade_oracle._path(scene, W, H, p, "corners", Rules(), 1000.0,
                                           frozenset(), limit)
                one = shade_oracle._path(scene, W, H, p, "corners", Rules(), 1000.0,
                                         frozenset(first[1][:1]), limit) if first[1] else None
                return (o, one[0]) if one else (o, (1, 2, 3))
            return (o, next(iter(a - {o}))) if len(a) > 1 else (o, (1, 2, 3))
        aims = [aim(p, o, a) for p, o, a in zip(pick, own, full)]
        lanes.clear()
        got = shade_oracle.other_sides_of(scene, W, H, pick, limit=limit, targets=aims)
        traced["aimed"] = traced.get("aimed", 0) + sum(lanes)
        for p, a, t, g in zip(pick, full, aims, got):
            if g is True:
                assert a is None or set(t) <= a, (scene.path, p, t, a)
                if a is None:
                    assert shade_oracle.reaches(scene, W, H, p, t, limit=limit) is True
            else:
                assert g == a and (a is None or not set(t) <= a), (scene.path, p, t, a, g)
            # per pixel the same, except that it takes a round's paths one at a time within
            # ``runs`` where other_sides_of takes a round whole or not: it may find the
            # targets where other_sides_of answers None (reaches then finds them too)
            one = shade_oracle.other_sides(scene, W, H, p, limit=limit, targets=t)
            assert one == g or (g is None and one is True), (scene.path, p, one, g)
            kinds.add("found" if g is True else "none" if g is None else "set")
            if g is True and a is None:
                kinds.add("found where none")
    assert kinds == {"found", "none", "set", "found where none"}, kinds
    assert traced["aimed"] < traced["full"], traced


@pytest.mark.parametrize("name", ["deep_decisions", "deep_decisions_batched"])
def test12c_targets_found_deep_do_not_excuse(name):
    """A review's scene (tests/scenes/): pixel 51's edge decision, taken the other way, leads
    to 12 more near decisions (spotlight cones), and Mitsuba's colour stands 4 cones deep
    on the other branch.  The levels above hold more paths than ``reaches``' budget, so
    the pixel was not excused (the sides cannot all be enumerated, and the search gives
    up); the per-pixel other_sides, depth first, found both colours after 5 paths and
    excused it.  Breadth first (as reaches and other_sides_of's rounds) it answers None,
    and the pixel stays wrong, with the early out and without; also where shade_batch
    traces it (the disk a finite plane)."""
    from tools.harness import shaded
    sc = parse_text((REPO / "tests" / "scenes" / f"{name}.txt").read_text())
    assert shade_batch.supported(sc) == name.endswith("batched")
    W, H, pixel = 12, 9, 51
    root = shade_oracle._path(sc, W, H, pixel, "corners", Rules(), 1000.0, frozenset(),
                              F32_LIMIT)
    spots = [k for k in root[1] if k[1] == "spot"]
    deep = shade_oracle._path(sc, W, H, pixel, "corners", Rules(), 1000.0,
                              frozenset(spots), F32_LIMIT)
    assert len(spots) == 4 and deep[0] != root[0]
    aims = (deep[0], root[0])                       # (Mitsuba's, rt_core's)
    assert shade_oracle.reaches(sc, W, H, pixel, aims, limit=F32_LIMIT) is None
    assert shade_oracle.reaches(sc, W, H, pixel, aims, limit=F32_LIMIT, runs=10 ** 4)
    assert shade_oracle.other_sides(sc, W, H, pixel, limit=F32_LIMIT, targets=aims) is None
    assert shade_oracle.other_sides_of(sc, W, H, [pixel], limit=F32_LIMIT,
                                       targets=[aims]) == [None]
    ours = np.zeros((H, W, 3), np.uint8)
    theirs = ours.copy()
    ours.reshape(-1, 3)[pixel], theirs.reshape(-1, 3)[pixel] = root[0], deep[0]
    for early in (True, False):
        shaded.EARLY_OUT = early
        try:
            got = shaded.classify_shaded(sc, ours, theirs, "corners", Rules(), 1000.0)
        finally:
            shaded.EARLY_OUT = True
        assert got.reshape(-1)[pixel] == shaded.SHADED_CODE["wrong"], early


def test13_other_sides_of_limits():
    """other_sides' limits, at their edges: as many paths as ``runs`` and no more, as many
    bounces as ``bounces``: other_sides_of answers as other_sides does at each."""
    scene = next(s for s in SCENES if Path(s.path).stem == "nw__spec3")
    W, H = 12, scene.default_rows(12)
    pick, _ = _near_pixels(scene, W, H, Rules(), F32_LIMIT)
    kinds = set()
    for runs in (1, 2, 3, 4):
        for bounces in (0, 1, 2, 3, 5):
            many = shade_oracle.other_sides_of(scene, W, H, pick, runs=runs, bounces=bounces,
                                               limit=F32_LIMIT)
            for p, a in zip(pick, many):
                assert a == shade_oracle.other_sides(scene, W, H, p, runs=runs,
                                                     bounces=bounces, limit=F32_LIMIT)
                kinds.add(a is None)
    assert kinds == {True, False}


TILE_GRAZE = """8 6
0 0 5
pointlight
2 10 5
0 1 2
tplane
0 0.25 1
0 6 2
0 0 0
2 1 1
0 -2 -4
1 0 0
0.5 3
1 0.5 1
1 4 6
0 0 0
"""


def test14_review_cases(monkeypatch):
    """What a review found: a tile index past 2^52 (a ray all but parallel to a tilted tiled
    plane, a plane far off, tiles of 1e-16), where the float sum of the two floors rounds
    to even; a scene without objects; pixel_ray's divisions by zero that numpy makes NaN or
    inf (a viewpoint a hair from the window plane, one row of pixels): the per-pixel
    oracle's numbers, or where it divides by zero every margin 0 and no path."""
    _same(parse_text(TILE_GRAZE), 9, Rules(), 1000.0, monkeypatch, rows=7)
    far = (REPO / "scenes" / "tplane.txt").read_text().replace(
        "0 -3.2 0        # a point", "1e17 -3.2 0     # a point").replace(
        "0 0 0           # background specular", "1 1 1           # background specular")
    _same(parse_text(far), 16, Rules(), 1000.0, monkeypatch, rows=12)
    tiny = (REPO / "scenes" / "tplane.txt").read_text().replace("1 1.5           # tile",
                                                                 "1e-16 1.5       # tile")
    _same(parse_text(tiny), 8, Rules(), 1000.0, monkeypatch, rows=8)
    empty = parse_text("8 6\n0 0 4\n")
    got = shade_oracle.shade_pixels(empty, 8, 8, np.arange(64))
    assert not got["I"].any() and got["paths"][0] == ((0, 0, 0), (), 0)
    near = parse_text((REPO / "scenes" / "shade_spot.txt").read_text().replace(
        "0 0 4\n", "0 0 1e-170\n", 1))
    for got in (shade_oracle.shade_pixels(near, 9, 9, np.arange(81)),
                shade_oracle.shade_pixels(SCENES[0], 64, 1, np.arange(64),
                                          rules=Rules(rows="shifted"))):
        undone = [k for k, p in enumerate(got["paths"]) if p is None]
        assert undone and all((got[m][undone] == 0).all() for m in shade_oracle.MARGINS)


@pytest.mark.parametrize("tail", [0, 10 ** 6], ids=["arrays", "handed-over"])
def test15_long_paths_handed_over(tail, monkeypatch):
    """The last few lanes of long paths go on in the per-pixel code from where they are
    (TAIL_LANES): the same numbers and near decisions whether every path is handed over
    after its first bounce or none is, with decisions flipped too."""
    monkeypatch.setattr(shade_batch, "TAIL_LANES", tail)
    calls = []
    real = shade_oracle.ray_trace
    monkeypatch.setattr(shade_oracle, "ray_trace",
                        lambda *a, **k: calls.append(k.get("bounce", 0)) or real(*a, **k))
    mirrors = next(s for s in _scenes(bundled_only=True) if Path(s.path).stem == "shade_mirrors")
    _same(mirrors, 12, Rules(), 200.0, monkeypatch)
    assert (max(calls) > 0) == bool(tail)
    spec = next(s for s in SCENES if Path(s.path).stem == "nw__spec3")
    W, H = 12, spec.default_rows(12)
    pick, _ = _near_pixels(spec, W, H, Rules(), F32_LIMIT)
    many = shade_oracle.other_sides_of(spec, W, H, pick, limit=F32_LIMIT)
    with monkeypatch.context() as m:
        m.setattr(shade_oracle, "BATCH_MIN", 10 ** 9)
        assert many == [shade_oracle.other_sides(spec, W, H, p, limit=F32_LIMIT) for p in pick]


@pytest.mark.parametrize("batch", [False, True])
def test16_reach_counts_hits_and_shadow_blockers(batch, monkeypatch):
    """``reach``: the farthest a path's hit on an infinite plane lies from the viewpoint's
    foot point along its stand-in square's axes, its closest hits and the blockers of its
    shadow rays both.  The floor's points are shadowed by the roof on the way to a light far
    down -z, and the blocker lies farther out than the hit: the reach is the blocker's,
    computed here from the ray (per-pixel oracle and batch alike)."""
    from mitsuba_ref.convert import stand_in_frame
    sc = parse_text("8 6\n0 0 5\n"
                    "pointlight\n9 9 9\n0 5 -200\n"
                    "plane\n1 1 1\n4 4 4\n0 0 0\n0 1 0\n0 -10 0\n"     # floor
                    "plane\n0 0 0\n1 1 1\n0 0 0\n0 -1 0\n0 3 0\n")    # roof
    W, H = 16, 12
    pixels = [11 * W + 3, 10 * W + 12] * (8 if batch else 1)  # the bottom rows: the floor
    if not batch:
        monkeypatch.setattr(shade_oracle, "BATCH_MIN", 10 ** 9)
    out = shade_oracle.shade_pixels(sc, W, H, pixels, "corners", Rules())
    V = np.array(sc.viewpoint)
    for k, p in enumerate(pixels[:2]):
        r, x = divmod(p, W)
        E = np.array([x / (W - 1) * 8 - 4, (H - 1 - r) / (H - 1) * 6 - 3, 0.0]) - V
        Hf = V + E * (-10 - V[1]) / E[1]                     # on the floor, y = -10
        L = np.array([0.0, 5.0, -200.0])
        B = Hf + (L - Hf) * (3 - Hf[1]) / (L[1] - Hf[1])     # on the roof, y = 3
        want = []
        for obj, P in ((sc.objects[0], Hf), (sc.objects[1], B)):
            ax, ay, foot = (np.array(a) for a in stand_in_frame(obj, sc.viewpoint))
            want.append(max(abs((P - foot) @ ax), abs((P - foot) @ ay)))
        assert want[1] > want[0]
        assert out["reach"][k] == pytest.approx(want[1], rel=1e-9), (out["reach"][k], want)


def test17_a_light_in_a_plane_adds_its_term_to_the_bound(monkeypatch):
    """A light lying in the tiled plane's plane: c = 0 there, and the term a tracer's c
    rounded above 0 may add joins the bound (shade_oracle.FACING), on arrays as per pixel,
    bit for bit; where c is exactly 0 the pixel's bound is that term's, not 0."""
    sc = parse_text(
        "0.0000012 0.0000012\n0 1.5E-7 3E-7\n"
        "fplane 0.5 1 0.5 0 0 2 0.5 1 1  0.25 0 0 -3E-7 0 4.5E-7 -4 -4 2 6E-7 1.5E-7\n"
        "fplane 1 0 2 2 8 8 0 0 0  0 1 0 6E-7 0 -6E-7 0 -4 1 9E-7 6E-7\n"
        "tplane 0 1 2 8 8 2 0 0 0  0 1 0 -3E-7 0 6E-7 2 2 1 9E-7 0.0000012  1 1 1 1 8 8 0 0 0\n"
        "pointlight 5 3 4  -3E-7 0 6E-7\n")
    got = _same(sc, 33, Rules(), 50000.0, monkeypatch, rows=33)
    p = 15 * 33 + 10
    assert got["I"][p, 0] == 0 and got["err"][p, 0] > 1e12


@pytest.mark.parametrize("batch", [False, True])
def test18_paths_recorded_at_a_limit_are_other_sides_first(batch, monkeypatch):
    """shade_pixels(limit=L)'s unflipped paths are the ones other_sides traces at L (so the
    shaded comparison hands them over as ``first`` instead of tracing them again): per
    pixel and on arrays, at float32's limit, where more decisions are near."""
    L = shade_oracle.K_DECISION * shade_oracle.U["f32"]
    scene = parse_text((REPO / "scenes" / "mixed.txt").read_text())
    W, H = 24, 18
    px = list(range(0, W * H, 7))
    if not batch:
        monkeypatch.setattr(shade_oracle, "BATCH_MIN", 10 ** 9)
    got = shade_oracle.shade_pixels(scene, W, H, px, "corners", Rules(), 1000.0, limit=L)
    want = [shade_oracle._path(scene, W, H, p, "corners", Rules(), 1000.0, frozenset(), L)
            for p in px]
    assert got["paths"] == want
    assert any(len(w[1]) for w in want)         # (some decision is near at that limit)
    default = shade_oracle.shade_pixels(scene, W, H, px, "corners", Rules(), 1000.0)
    assert default["paths"] != want
