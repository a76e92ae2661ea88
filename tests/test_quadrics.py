"""Cylinder (22), cone (23) and ellipsoid (rm768 keyword): read as the course files write them,
traced by rt_core (f32, f64 with exact decisions) and checked against the independent
references (mitsuba_ref/quadric.py: the exact oracle and the float64 oracle)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mitsuba_ref import scenefile
from mitsuba_ref.exact import ideal_rays, parse_exact, trace_exact
from mitsuba_ref.oracle import render_oracle
from rt_core import backend
from rt_core.camera import make_camera
from rt_core.parser import parse_scene, parse_text
from rt_core.render import trace_geometry
from rt_core.rules import Rules
from rt_core.scene import SceneError

REPO = Path(__file__).resolve().parents[1]

COURSE = Path(__file__).resolve().parents[2] / "shared" / "course-scenes"
FILES = ["numeric/nw__a3t4.txt", "numeric/nw__cyltest.txt", "numeric/nw__conetest.txt",
         "keyword/rm768__bowling.txt", "keyword/rm768__ellipsoid_bullets.txt"]
from tests.tolerances import U  # noqa: E402
M = "1 1 1\n2 2 2\n0 0 0\n"
# a cylinder of radius 5 around (0, ·, −4), y in [−1, 1]: the ray to the window's (3, ±1)
# meets it exactly on its rim (s = 1, w·a = 0 or h); a cone below, a sphere above
OWN = ("8 6\n0 0 4\n"
       "22 cylinder\n" + M + "0 -1 -4 base\n0 1 0 centerline\n5 2 radius height\n"
       "23 cone\n" + M + "2.5 -4 -1 apex\n0 1 0 centerline\n1.5 2 radius height\n"
       "13\n" + M + "-9 5 -10\n2\n")


def _ids(sc, W, H, precision, rules=Rules()):
    g = trace_geometry(sc, make_camera(sc, W, H), backend.types(precision), rules)
    return np.array(g["object.id"]).astype(int).ravel(), g


def _exact(text, W, H, rules=Rules()):
    xs = parse_exact(text)
    rays, d = ideal_rays(xs.window, xs.viewpoint, W, H, range(W * H))
    return trace_exact(xs, d, rules, rays=rays)


def test01_fields_as_written():
    s = parse_text(OWN, "own.txt")
    cyl, cone, _ = s.objects
    assert (cyl.kind, cyl.center, cyl.axis, cyl.radius, cyl.height) == (
        "cylinder", (0, -1, -4), (0, 1, 0), 5, 2)
    assert (cone.kind, cone.center, cone.axis, cone.radius, cone.height) == (
        "cone", (2.5, -4, -1), (0, 1, 0), 1.5, 2)
    e = parse_text("8 6 0 0 4\nellipsoid 1 1 1 0 0 0 0 0 0  1 2 -5  .5 1.5 .25\n").objects[0]
    assert (e.kind, e.center, e.axes) == ("ellipsoid", (1, 2, -5), (.5, 1.5, .25))
    ref = scenefile.read_text(OWN)
    assert [o.kind for o in ref.objects] == ["cylinder", "cone", "sphere"]
    assert ref.objects[0].radius_height == (5, 2)


def test02_zero_centerline_is_the_y_axis_with_a_note():
    s = parse_scene(COURSE / "numeric" / "nw__cyltest.txt") if COURSE.is_dir() else \
        parse_text("8 6\n0 0 4\n22\n" + M + "4 3 -4\n0 0 0\n2 10\n")
    cyl = next(o for o in s.objects if o.kind == "cylinder")
    assert cyl.axis == (0, 1, 0)
    assert any("centerline (0, 0, 0)" in n and "y axis" in n for n in s.stand_ins())


def test02b_the_references_read_a_zero_centerline_by_their_own_rule(monkeypatch):
    """The references take the centerline as written (checked against their own reader) and
    make a zero one the y axis themselves: with rt_core's rule broken (the x axis), the
    comparison with Mitsuba fails instead of passing on rt_core's own axis (a review)."""
    from rt_core import quadrics
    from tools.harness.compare import compare
    text = "8 6\n0 0 5\n22\n" + M + "-1 -1 -4\n0 0 0\n0.8 2.5\n10\n8 8 8\n0 3 1\n"
    ok = parse_text(text, "cyl0.txt")
    assert ok.objects[0].given_axis == (0, 0, 0)
    assert compare(ok, 40, None, "f64", "rays").ok
    monkeypatch.setattr(quadrics, "Y_AXIS", (1.0, 0.0, 0.0))
    bad = parse_text(text, "cyl0.txt")
    assert bad.objects[0].axis == (1.0, 0.0, 0.0)
    cmp = compare(bad, 40, None, "f64", "rays")
    assert not cmp.ok and cmp.counts["unexplained"] > 20, cmp.counts


@pytest.mark.parametrize("text, line, col", [
    ("8 6\n0 0 4\n22\n" + M + "0 0 -4\n0 1 0\n0 2\n", 9, 1),
    ("8 6\n0 0 4\n23\n" + M + "0 0 -4\n0 1 0\n1 -2\n", 9, 3),
    ("8 6 0 0 4\nellipsoid 1 1 1 0 0 0 0 0 0  1 2 -5  .5 0 .25\n", 2, 41),
])
def test03_degenerate_sizes_are_errors_at_their_group(text, line, col):
    with pytest.raises(SceneError) as e:
        parse_text(text, "bad.txt")
    assert (e.value.line, e.value.col) == (line, col)
    assert "must be positive" in str(e.value)


def _check(text, sc, W, H, rules=Rules()):
    """rt_core f64 equals the exact oracle on every pixel; f32 disagrees only where rounding
    can explain it; the float64 oracle equals the exact one, on both readers' scenes."""
    ex = _exact(text, W, H, rules)
    ids64, g64 = _ids(sc, W, H, "f64", rules)
    wrong = np.flatnonzero(ids64 != ex.id)
    assert not len(wrong), f"f64 differs from exact at pixels {wrong[:8]}"
    ids32, g32 = _ids(sc, W, H, "f32", rules)
    assert ex.explained(ids32, U["f32"]).all()
    o = render_oracle(scenefile.read_text(text).floats(), W, H, rules=rules)
    oid = o["object.id"].astype(int).ravel()
    # depth, position, normal on the quadrics' hits: within the oracle's rounding-error bound
    # (u·err; measured at most 0.2 of it on the course files)
    quads = np.array([k.kind in ("cylinder", "cone", "ellipsoid") for k in sc.objects] + [0])
    for prec, ids, g in (("f32", ids32, g32), ("f64", ids64, g64)):
        same = (ids == oid) & (ids >= 0) & quads[ids].astype(bool)
        for k in ("depth.Z", "position.X", "position.Y", "position.Z", "normal.X",
                  "normal.Y", "normal.Z"):
            err = np.abs(np.array(g[k], np.float64).ravel() - o[k].ravel())[same]
            assert (err <= U[prec] * o["err." + k].ravel()[same]).all(), (prec, k)
    # (judged where a quadric is involved: on ellipsoid_bullets the float64 oracle misses
    # a floor hit at exactly z = 0, a plane matter outside this file's scope)
    quad = np.array([k.kind in ("cylinder", "cone", "ellipsoid") for k in sc.objects] + [False])
    inv = quad[ex.id] | quad[oid]
    assert inv.any() and ex.explained(oid, U["f64"])[inv].all()
    return ex


@pytest.mark.parametrize("rules", [Rules(), Rules(clip_spheres=True)], ids=["notes", "clip"])
def test04_own_scene_exact_on_the_rim(rules, monkeypatch):
    from rt_core import decide
    W, H = 9, 7                          # window samples x = −4..4, y = −3..3, step 1
    sc = parse_text(OWN, "own.txt")
    calls = []
    real = decide._quadric
    monkeypatch.setattr(decide, "_quadric", lambda *a: calls.append(1) or real(*a))
    ex = _check(OWN, sc, W, H, rules)
    assert calls, "f64 certified every ray: the exact quadric decision never ran"
    # the ray to the window's (3, 1) meets the cylinder exactly on its top rim: a hit
    assert ex.id[2 * W + 7] == 0 and ex.id[4 * W + 7] == 0
    assert (ex.id == 0).sum() > 5 and (ex.id == 1).any()


@pytest.mark.skipif(not COURSE.is_dir(), reason="../shared/course-scenes is not there")
@pytest.mark.parametrize("name", FILES)
def test05_course_files(name):
    path = COURSE / name
    sc = parse_scene(path)
    W = 24
    H = max(2, sc.default_rows(W))
    ex = _check(path.read_text(), sc, W, H)
    assert ex.hit.any()


def test06_normals_are_outward_and_unit():
    """Normals of the quadric hits: unit, and the gradient's direction (the oracle's)."""
    sc = parse_text(OWN, "own.txt")
    W, H = 33, 25
    _, g = _ids(sc, W, H, "f64")
    o = render_oracle(sc, W, H)
    ids = np.array(g["object.id"]).astype(int).ravel()
    sel = (ids >= 0) & (ids <= 1) & (o["object.id"].ravel() == ids)
    n = np.stack([np.array(g[f"normal.{a}"]).ravel() for a in "XYZ"], -1)[sel]
    on = np.stack([o[f"normal.{a}"].ravel() for a in "XYZ"], -1)[sel]
    assert sel.sum() > 50 and (ids[sel] == 1).sum() > 5     # both quadrics
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-12)
    assert np.allclose(n, on, atol=1e-9)


def _many():
    """Twelve quadrics (cylinders, cones, ellipsoids, tilted) over a mirror floor, two lights."""
    from rt_core.quadrics import make_cone, make_cylinder, make_ellipsoid
    from rt_core.scene import Material, PointLight, Scene, make_plane
    mirror = Material((0.2, 0.2, 0.2), (1.0, 1.0, 1.0), (0.5, 0.5, 0.5))
    objs = [make_plane(mirror, (0, 1, 0), (0, -3, 0))]
    for k in range(12):
        x, y, z = -4.5 + 3 * (k % 4), -2 + 2 * (k // 4), -6 - (k % 3)
        if k % 3 == 0:
            objs.append(make_cylinder(mirror, (x, y, z), (1, 2, k % 2), (0.5, 1.5)))
        elif k % 3 == 1:
            objs.append(make_cone(mirror, (x, y + 1, z), (0, -1, 0.5), (0.7, 1.5)))
        else:
            objs.append(make_ellipsoid(mirror, (x, y, z), (0.9, 0.5, 0.7)))
    lights = (PointLight((5, 5, 5), (2, 6, 2)), PointLight((3, 3, 3), (-6, 2, -3)))
    return Scene((8, 6), (0, 0, 4), lights, tuple(objs), path="<many quadrics>")


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test07_loops_bins_and_bvh_match_unrolled(precision, monkeypatch):
    """Many quadrics: the symbolic loop over their table rows (with screen-space bins for the
    camera's rays) gives the unrolled code's ids and depths bit for bit, and the shaded image
    with reflections through their BVH and light bins equals the plain loop's."""
    from rt_core import accel
    from tests.test_bvh import assert_identical, used
    sc = _many()
    W, H = 40, 30
    ids, g = _ids(sc, W, H, precision)
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    ids_loop, g_loop = _ids(sc, W, H, precision)
    assert (ids == ids_loop).all() and len(set(ids.tolist())) > 12
    assert np.array_equal(np.array(g["depth.Z"]), np.array(g_loop["depth.Z"]))
    ks, _ = assert_identical(sc, precision, monkeypatch, columns=24)
    assert used(ks) == {"bvh", "lightbins", "reflectbins"}


def test08_mitsuba_cylinder_and_the_oracle_only_kinds(tmp_path):
    """The cylinder converts to Mitsuba's (open) ``cylinder`` and agrees with rt_core under
    the classifier; the cone (no Mitsuba shape) is left out of the comparison, saying so."""
    from mitsuba_ref.convert import scene_xml
    from tools.harness.compare import compare
    sc = parse_text(OWN, "own.txt")
    cmp = compare(sc, 40, 30, "f32", "rays")
    assert cmp.ok, (cmp.counts, cmp.depth)
    assert "line 10 cone" in cmp.note and "oracles only" in cmp.note
    assert (cmp.ref["object.id"] == 0).sum() > 100          # Mitsuba hits its cylinder
    assert cmp.counts["agree"] == 40 * 30 - cmp.explained
    xml = scene_xml(sc, 40)
    assert 'type="cylinder"' in xml and "cone has no Mitsuba shape" in xml
    assert '<point name="p1" value="0.0, 1.0, -4.0"/>' in xml
    # the XML loads in Mitsuba, and its cylinder is where rt_core's is
    from mitsuba_ref.convert import mitsuba
    mi = mitsuba()
    path = tmp_path / "own.xml"
    path.write_text(xml)
    shapes = mi.load_file(str(path)).shapes()
    assert [s.id() for s in shapes] == ["obj0_cylinder", "obj2_sphere"]
    box = shapes[0].bbox()
    assert np.allclose([box.min.y, box.max.y], [-1, 1], atol=1e-5)


def test09_few_rays_are_decided_exactly():
    """The certified bounds are tight enough that the quadrics' rays are almost all certain
    in float64: 19 of 19481 here, the rays exactly on the rim or tangent among them (a
    bound 10⁹ times looser flags 107)."""
    from rt_core.camera import primary_directions
    from rt_core.tracer import closest_hit, prepare
    sc = parse_text(OWN, "own.txt")
    cam = make_camera(sc, 161, 121)     # samples every 0.05: the rim rays among them
    T = backend.types("f64")
    ks = prepare(sc, T)
    closest_hit(ks, primary_directions(sc, cam, T), cam=cam)
    assert 2 <= ks.decided <= 40


# generic decimals: nothing lines up by accident
NEAR = ("8 6\n0.13 -0.07 4.3\n"
        "22\n" + M + "-1.7 -1.1 -5.3\n0.3 1.1 -0.2\n1.3 2.1\n"
        "23\n" + M + "2.1 1.9 -4.7\n-0.4 -1.3 0.35\n0.9 1.7\n")
NEAR_ELL = "8 6 0.13 -0.07 4.3\nellipsoid 1 1 1 0 0 0 0 0 0  0.3 -0.2 -6.1  1.7 0.9 1.3\n"


def _rim_and_outline_rays(text: str, n: int, seed: int = 5) -> np.ndarray:
    """Rays from the viewpoint to points within a few ulps of each quadric's rims (open
    kinds) and of its outline as seen from the viewpoint (cylinder, ellipsoid), float64."""
    rng = np.random.default_rng(seed)
    xs = parse_exact(text)
    V = np.array([float(c) for c in xs.viewpoint])
    pts = []
    for o in xs.objects:
        c = np.array([float(x) for x in o.center])
        if o.kind == "ellipsoid":
            s = np.array([float(x) for x in o.axes])
            Vs = (V - c) / s                          # the unit sphere's frame
            k = Vs / (Vs @ Vs)
            w = rng.normal(size=(n, 3))
            w -= np.outer(w @ Vs, Vs) / (Vs @ Vs)
            w /= np.linalg.norm(w, axis=1, keepdims=True)
            X = k + np.sqrt(1 - 1 / (Vs @ Vs)) * w    # X·Vs = 1: tangent from V
            pts.append(c + X * s)
            continue
        a = np.array([float(x) for x in o.centerline])
        a /= np.linalg.norm(a)
        r, h = (float(x) for x in o.radius_height)
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.6 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        th = rng.uniform(0, 2 * np.pi, n)
        ring = np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2
        pts.append(c + h * a + r * ring)                        # the far rim
        if o.kind == "cylinder":
            pts.append(c + r * ring)                            # the base rim
            q = V - c
            ql = np.array([q @ e1, q @ e2])
            rho, phi = np.hypot(*ql), np.arctan2(ql[1], ql[0])
            side = phi + rng.choice([-1, 1], n) * np.arccos(r / rho)
            y = rng.uniform(0, h, n)[:, None]
            pts.append(c + y * a + r * (np.cos(side)[:, None] * e1 + np.sin(side)[:, None] * e2))
    d = np.concatenate(pts) - V
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d + rng.integers(-64, 65, d.shape) * np.spacing(d)


@pytest.mark.parametrize("text", [NEAR, NEAR_ELL], ids=["cylinder-cone", "ellipsoid"])
@pytest.mark.parametrize("rules", [Rules(), Rules(clip_spheres=True)], ids=["notes", "clip"])
def test10_rays_at_the_rims_and_outlines_are_decided_exactly(text, rules):
    """Rays within a few ulps of every rim and outline (where the rounded values' signs are
    often wrong): rt_core f64, certified, answers as exact arithmetic does on the same rays,
    and it had to ask the exact decision for some of them."""
    from rt_core.tracer import closest_hit, prepare
    d = _rim_and_outline_rays(text, 150)
    T = backend.types("f64")
    ks = prepare(parse_text(text), T)
    _, oid, _ = closest_hit(ks, T.Array3(*(T.Float(c) for c in d.T)), None, rules,
                            cam="rays", dmax=float(np.linalg.norm(d, axis=1).max()))
    ids = np.asarray(oid.numpy())
    ex = trace_exact(parse_exact(text), d, rules)
    wrong = np.flatnonzero(ids != ex.id)
    assert not len(wrong), f"{len(wrong)} of {len(d)} rays wrong: {wrong[:8]}"
    assert ks.decided > 0.05 * len(d) and ex.hit.any() and (~ex.hit).any()


@pytest.mark.parametrize("axis", ["1e308 0.3 1", "1e-320 0 0", "-1e-310 1e-311 0",
                                  "1e-160 0 0", "0 1e-160 1e-161"])
def test_extreme_centerlines_are_directions(axis):
    """A centerline is a direction whatever its length: one whose |axis|² overflows or
    underflows float64 (found by test_fuzz's long run: a ZeroDivisionError in rt_core's
    frame, and in the classifier's float64 view) renders and compares like any other."""
    from tools.harness.compare import compare
    text = (REPO / "scenes" / "cylinder_rim_shadow.txt").read_text()
    old = next(ln for ln in text.splitlines() if "centerline" in ln)
    scene = parse_text(text.replace(old, axis + "   centerline"), "extreme.txt")
    for precision in ("f32", "f64"):
        cmp = compare(scene, 24, None, precision, "rays")
        assert cmp.ok, cmp.summary()
    # the frame rt_core builds is orthonormal (1e-160: |axis|² underflowed to a subnormal
    # and g2 came out 1.0000056 long)
    from rt_core.shapes_quadric import _frame
    g = np.array(_frame(tuple(float(c) for c in axis.split())))
    np.testing.assert_allclose(g @ g.T, np.eye(3), atol=4e-16)


@pytest.mark.parametrize("scale", ["1e-150", "1e-155", "1e-200", "1e-300"])
@pytest.mark.parametrize("code", [22, 23])
def test11_tiny_scenes_are_decided_exactly(code, scale):
    """A cylinder (22) or cone (23) in a scene scaled to 1e-155 and below: its squares are
    subnormal, the discriminant's relative bound underflowed to 0, and every ray was
    certified a miss (a second reader's exact checker: 6 and 2 hits lost, rt_core's own
    decide.py right).  Now such rays are decided exactly; the normals stay finite (their
    squared norm underflowed to 0 too); and the exact oracle does not overflow on t."""
    f = float(scale)
    text = (f"{8 * f!r} {6 * f!r}\n0 0 {4 * f!r}\n{code}\n1 1 1\n1 1 1\n0 0 0\n"
            f"0 {2 * f!r} {-3 * f!r}\n0 -1 0\n{2 * f!r} {3 * f!r}\n")
    sc = parse_text(text, "tiny.txt")
    W, H = 9, 7
    ids, g = _ids(sc, W, H, "f64")
    ex = _exact(text, W, H)
    assert (ids == ex.id).all(), (ids.reshape(H, W), ex.id.reshape(H, W))
    assert (ids == 0).sum() == (6 if code == 22 else 2)
    n = np.stack([np.array(g[f"normal.{a}"]).ravel() for a in "XYZ"], -1)[ids == 0]
    assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-12)


def test_a_ray_along_a_cylinders_axis_is_decided(tmp_path, capsys):
    """The centre ray runs exactly along the cylinder's axis (tests/scenes/
    cylinder_along_axis.txt: A = B = 0 in the course's quadratic).  The float64 oracle
    divided by A: check excused any colour there (a PASS with the pixel painted red) and
    report ended in a traceback (a helper's fuzzing).  Now the wrong colour fails."""
    from rt_core.imageio import read_image, write_ppm
    from tools.cli import main
    scene = REPO / "tests" / "scenes" / "cylinder_along_axis.txt"
    ppm = tmp_path / "c.ppm"
    assert main(["render", str(scene), "--columns", "13", "--precision", "f64", "--ppm",
                 str(ppm)]) == 0
    img = read_image(str(ppm))
    assert img.shape[:2] == (9, 13)
    assert main(["check", str(scene), str(ppm)]) == 0
    img[4, 6] = (200, 10, 10)
    write_ppm(str(ppm), img)
    capsys.readouterr()
    assert main(["check", str(scene), str(ppm)]) == 1
    assert "wrong 1" in capsys.readouterr().out
    assert main(["report", str(scene), "--columns", "13", "--reps", "1", "-o",
                 str(tmp_path / "r")]) == 0


def test_a_far_root_on_the_rim_is_judged_with_the_near_one(tmp_path, capsys, monkeypatch):
    """tests/scenes/cylinder_far_rim.txt at 21x16: the ray of column 4, row 14 (from the
    top) misses the near root (above the rim by 0.68) and meets the far one exactly on the
    base rim.  The references judged one root: the float64 oracle reported the near root's
    margins, so the shaded comparison called rt_core's float64 image wrong there (a
    helper's fuzzing).  A wrong colour there still fails check."""
    from rt_core.imageio import read_image, write_ppm
    from tools.cli import main
    scene = REPO / "tests" / "scenes" / "cylinder_far_rim.txt"
    monkeypatch.chdir(tmp_path)
    assert main(["compare", str(scene), "--columns", "21", "--rows", "16", "--shaded",
                 "--reference", "oracle"]) == 0
    ppm = tmp_path / "c.ppm"
    assert main(["render", str(scene), "--columns", "21", "--rows", "16", "--precision",
                 "f64", "--ppm", str(ppm)]) == 0
    assert main(["check", str(scene), str(ppm)]) == 0
    img = read_image(str(ppm))
    img[14, 4] = (200, 10, 10)          # a colour no answer at that pixel gives
    write_ppm(str(ppm), img)
    capsys.readouterr()
    assert main(["check", str(scene), str(ppm)]) == 1
    assert "wrong 1" in capsys.readouterr().out


def test_the_exact_oracle_weighs_both_roots_of_a_miss():
    """The same ray turned by 1e-14: both roots fail, exactly, the far one by 1e-13 below
    the rim.  The exact oracle weighed the near root's failure (0.68 off): a float tracer
    hitting the far root was unexplained.  Now the far root's axial test is within reach."""
    from mitsuba_ref.exact import U
    xs = parse_exact((REPO / "tests" / "scenes" / "cylinder_far_rim.txt").read_text())
    W, H = 21, 16
    _, d = ideal_rays(xs.window, xs.viewpoint, W, H, [14 * W + 4])
    d = d + np.array([[-1e-14, 0.0, 0.0]])
    ex = trace_exact(xs, d)
    cyl = ex.objects[1]
    assert ex.id[0] == 0 and not cyl.valid[0]
    assert not cyl.passed["axis<=h"][0] and cyl.margin["axis<=h"][0] < -0.5   # the near root
    for precision, most in (("f32", 1e-6), ("f64", 2.0)):
        risk, which = cyl.risk_by(U[precision])
        assert risk[0] <= most and which[0] == "axis>=0", (precision, risk, which)
    assert ex.reasons(np.array([1]), U["f32"], reach=True)[0] == "axis>=0"
    assert -1e-12 < cyl.margin["other axis>=0"][0] < 0                          # the far one


def test_a_near_root_on_the_rim_flags_the_far_hit():
    """Rays from outside through the top rim point (1, 2, 0) of a cylinder, on into its
    open end: the near root lies on the rim exactly, so float64 puts it either side.  Where
    the float64 oracle's near root came out above the rim it took the far root with that
    root's margins alone (unflagged: 1e-4 against u = 1.1e-16; depth 6 % off); now the near
    root's axial test flags the hit."""
    import math
    from mitsuba_ref import oracle
    sc = parse_text("8 6\n0 0 5\n22\n" + M + "0 0 0\n0 1 0\n1 2\n", "c.txt")
    far = 0
    for k in range(30, 60):
        base = (1 + 4 * k / 7, 2 + 2 * k / 7, 0.0)
        n = math.hypot(1 - base[0], 2 - base[1])
        h = oracle.trace(sc, base, ((1 - base[0]) / n, (2 - base[1]) / n, 0.0))
        assert h.hit
        if abs(h.t - n) > 1e-9 * n:     # the far root taken
            far += 1
            assert h.edge_margin < U["f64"], (k, h.t / n, h.edge_margin)
    assert far >= 3


def test_the_classifier_weighs_both_roots():
    """The classifier's float64 view (quadric.classify_eval, behind compare's classes) of
    that ray turned by 1e-12: a miss whose nearest change is the far root's rim, 1e-11 off
    (it weighed the near root's, 0.58: rt_core float32 hitting the far root there against
    Mitsuba's miss was unexplained)."""
    from mitsuba_ref.quadric import classify_eval
    sc = parse_scene(REPO / "tests" / "scenes" / "cylinder_far_rim.txt")
    xs = parse_exact((REPO / "tests" / "scenes" / "cylinder_far_rim.txt").read_text())
    _, d = ideal_rays(xs.window, xs.viewpoint, 21, 16, [14 * 21 + 4])
    d = d + np.array([[-1e-12, 0.0, 0.0]])
    O = np.array([sc.viewpoint], np.float64)
    t, valid, margin, _ = classify_eval(sc.objects[1], O, d, Rules())
    assert not valid[0] and 0 < margin[0] < 1e-10, margin
    # the unturned ray: its far root exactly on the rim, which float64 puts either side
    _, d0 = ideal_rays(xs.window, xs.viewpoint, 21, 16, [14 * 21 + 4])
    t, valid, margin, _ = classify_eval(sc.objects[1], O, d0, Rules())
    assert margin[0] < 1e-11
