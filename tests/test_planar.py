"""The planar kinds triangle (code 27) and disk (29; 27 in nw's older layout), end to end:
both readers, rt_core's kernels in f32 and f64 against the float64 oracle and the exact
oracle, the exact decisions of f64, and the Mitsuba equivalents (README "Triangle", "Disk")."""
from __future__ import annotations

from pathlib import Path

import pytest

from mitsuba_ref import scenefile
from rt_core.parser import parse_text
from rt_core.scene import SceneError

REPO = Path(__file__).resolve().parents[1]
COURSE = REPO.parent / "shared" / "course-scenes" / "numeric"
NUM = "8 6 window\n0 0 5 eye\n"
MAT = "1 1 1\n2 2 2\n0 0 0\n"
TRI = NUM + "27 triangle\n" + MAT + "1 1 -1  p1\n0 1 -1\n-2 5 -1\n"
DISK27 = NUM + "27 disk\n" + MAT + "0 .6 -2.8 center\n1.8 radius\n1 1 1 normal\n"


def fails(text, **kw) -> SceneError:
    with pytest.raises(SceneError) as info:
        parse_text(text, "s.txt", **kw)
    assert "\n" not in str(info.value)
    return info.value


def test01_code27_by_line_shape():
    """A 27 whose second geometry line has 3 numbers is a triangle, 1 number a disk; both
    readers agree, and 29 is the disk."""
    t = parse_text(TRI).objects[0]
    assert t.kind == "triangle" and t.points == ((1, 1, -1), (0, 1, -1), (-2, 5, -1))
    assert t.normal == (0.0, 0.0, -1.0)          # (P2 − P1) × (P3 − P1) = (0, 0, −4)
    d = parse_text(DISK27).objects[0]
    assert d.kind == "disk" and d.center == (0, 0.6, -2.8) and d.radius == 1.8
    assert d.given_normal == (1, 1, 1)
    d29 = parse_text(DISK27.replace("27 disk", "29 disk")).objects[0]
    assert d29 == d
    # how a 27 was read is recorded with the object (the outputs' rtval.extras)
    assert d.extras == (("code 27 read as", "disk (by the line shape)"),) and d29.extras == ()
    assert [o.kind for o in scenefile.read_text(TRI).objects] == ["triangle"]
    assert [o.kind for o in scenefile.read_text(DISK27).objects] == ["disk"]


def test02_code27_forced():
    """The parse option reads a 27 as the layout it names; the other layout then fails on
    its own field (a triangle's point 2 needs 3 numbers, found 1)."""
    err = fails(DISK27, code27="triangle")
    assert (err.line, "point 2") == (8, err.message.split(" for ")[1][:7]), str(err)
    assert parse_text(TRI, code27="triangle").objects[0].kind == "triangle"
    three_then_one = TRI.replace("0 1 -1\n", "0 1 -1 0\n")   # extra numbers are ignored
    assert parse_text(three_then_one).objects[0].kind == "triangle"
    with pytest.raises(ValueError, match="code27"):
        parse_text(TRI, code27="hexagon")


def test03_code27_malformed():
    """A second geometry line with 2 numbers fits neither layout: one line naming both."""
    err = fails(TRI.replace("0 1 -1\n", "0 1\n"))
    assert (err.line, err.col) == (8, 1)
    assert "3 (triangle) or 1 (disk)" in err.message and "--code27" in err.message
    err = fails(NUM + "27\n" + MAT + "1 1 1\n")
    assert "end of file" in err.message


def test04_geometry_errors():
    err = fails(TRI.replace("-2 5 -1", "2 1 -1"))              # collinear
    assert (err.line, err.col) == (9, 1) and "collinear" in err.message
    err = fails(DISK27.replace("1.8 radius", "0 radius"))
    assert (err.line, err.col) == (8, 1) and "radius" in err.message
    err = fails(DISK27.replace("1 1 1 normal", "0 0 0 normal"))
    assert (err.line, err.col) == (9, 1) and "normal" in err.message


def test05_keywords():
    kw = "8 6\n0 0 5\ntriangle 1 1 1 2 2 2 0 0 0  1 1 -1  0 1 -1  -2 5 -1\n" \
         "disk 1 1 1 2 2 2 0 0 0  0 .6 -2.8  1.8  1 1 1\n"
    s = parse_text(kw)
    assert [o.kind for o in s.objects] == ["triangle", "disk"]
    assert [o.kind for o in scenefile.read_text(kw).objects] == ["triangle", "disk"]


# --- geometry: rt_core f32/f64 against the float64 oracle and the exact oracle ----------------

import numpy as np  # noqa: E402

from mitsuba_ref.exact import ideal_rays, parse_exact, trace_exact  # noqa: E402
from rt_core import accel  # noqa: E402
from rt_core.parser import parse_scene  # noqa: E402
from rt_core.rules import Rules  # noqa: E402
from mitsuba_ref.oracle import render_oracle  # noqa: E402
from tests.test_tracer_vs_oracle import compare, tracer  # noqa: E402
from tests.tolerances import GEOMETRY as TOL, U  # noqa: E402

SCENES = [REPO / "scenes" / "planar.txt", COURSE / "nw__tritest.txt", COURSE / "nw__disk1.txt"]
IDS = ["planar", "nw__tritest", "nw__disk1"]
M0 = "1 1 1 0 0 0 0 0 0"
# rays through the corner samples of a 17 x 13 image (0.5 apart on the window, at (−4 + c/2,
# 3 − r/2)) hit the plane z = −5 at twice the window point and z = −4 at 1.8 times it: two
# triangles in z = −5 share the edge x + y = 2 (an exact tie on it), and have samples exactly
# on it and on their other edges; a disk of radius 4.5 in z = −4 has samples exactly on its
# rim (window points at distance 2.5: (1.5, 2), (2.5, 0), ...), and a smaller disk on its
# plane (an exact tie)
EDGES = f"""8 6
0 0 5
triangle {M0}  -8 -6 -5  8 -6 -5  -8 10 -5
triangle {M0}  8 -6 -5  8 6 -5  -6 8 -5
disk {M0}  0 0 -4  4.5  0 0 2
disk {M0}  0.9 0 -4  1.8  0 0 -1
"""


def _exact_ids(path, W, H, rules=Rules(), text=None):
    xs = parse_exact(text if text is not None else Path(path).read_text())
    rays, d = ideal_rays(xs.window, xs.viewpoint, W, H, range(W * H))
    return trace_exact(xs, d, rules, rays=rays)


def _scene_ok(path):
    if not path.is_file():
        pytest.skip(f"{path} is not there")
    return parse_scene(path)


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("path", SCENES, ids=IDS)
def test06_tracer_against_float64_oracle(path, precision):
    """Mask, id, depth, normal, position and uv (barycentric; the disk's frame) of rt_core
    within the oracle's own error bound (tests/test_tracer_vs_oracle.py's tolerances), the
    oracle reading the file itself."""
    sc = _scene_ok(path)
    W = 48
    H = max(2, sc.default_rows(W))
    orc = render_oracle(scenefile.read(path).floats(), W, H)
    ours = tracer(sc, W, H, precision)
    compare(f"{path.stem}-{precision}", ours, orc, TOL[precision])
    kinds = {o.kind for o in sc.objects}
    assert ({"triangle", "disk"} & kinds) and (orc["object.id"] >= 0).any()
    planar = [i for i, o in enumerate(sc.objects) if o.kind in ("triangle", "disk")]
    assert np.isin(orc["object.id"], planar).sum() >= 5      # the objects are really seen


@pytest.mark.parametrize("layout", ["unrolled", "looped", "looped-no-bins"])
@pytest.mark.parametrize("path", SCENES, ids=IDS)
def test07_f64_decides_exactly(path, layout, monkeypatch):
    """Every pixel of rt_core f64 (unrolled, or looped over tables with and without bins) is
    the exact oracle's object."""
    from rt_core.render import render_geometry
    sc = _scene_ok(path)
    if layout != "unrolled":
        monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    if layout == "looped-no-bins":
        monkeypatch.setattr(accel, "binned", lambda ks, rays=0: None)
    W = 48
    H = max(2, sc.default_rows(W))
    out = render_geometry(sc, W, H, precision="f64", backend="llvm")
    ids = np.where(out["hit.mask"] > 0, out["object.id"], -1).ravel()
    ex = _exact_ids(path, W, H)
    assert (ids == ex.id).all(), np.argwhere(ids != ex.id)[:8].ravel()


@pytest.mark.parametrize("layout", ["unrolled", "looped"])
@pytest.mark.parametrize("rules", [Rules(), Rules(edges="open", ties="last")],
                         ids=["closed-first", "open-last"])
def test08_samples_exactly_on_the_edges(rules, layout, monkeypatch):
    """Samples exactly on a triangle's edge and on a disk's rim: f64 decides each as exact
    arithmetic does (closed edges: a hit, the tie to the first triangle; open: a miss), and
    the edge samples are really there (the rules change the answer at them).  f32's
    differences, if any, are all within reach of its rounding."""
    from rt_core.render import render_geometry
    sc = parse_text(EDGES)
    if layout == "looped":
        monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    W, H = 17, 13
    ex = _exact_ids(None, W, H, rules, EDGES)
    other = _exact_ids(None, W, H, Rules(edges="open" if rules.edges == "closed" else
                                          "closed", ties=rules.ties), EDGES)
    assert (ex.id != other.id).sum() >= 8                 # edge and rim samples
    assert ex.id[2 * W + 11] == (2 if rules.edges == "closed" else 1)   # (1.5, 2): the rim
    for precision in ("f32", "f64"):
        out = render_geometry(sc, W, H, precision=precision, backend="llvm", rules=rules)
        ids = np.where(out["hit.mask"] > 0, out["object.id"], -1).ravel()
        if precision == "f64":
            assert (ids == ex.id).all(), np.argwhere(ids != ex.id)[:8].ravel()
        else:
            # f32 traces rounded unit directions (no exact re-decision): a sample exactly on
            # an edge is within reach of that rounding even where the scene's numbers are
            # exact in f32 (trace_exact on the ideal rays counts none as representable)
            assert ex.explained(ids, U["f32"]).all()
            assert (ids != ex.id).sum() < 0.25 * W * H


# generic decimals: tilted triangles and disks, and a small far triangle (|q| >> its size)
NEAR = f"""8 6  0.3 -0.2 4.7
triangle {M0}  -3.1 -2.3 -2.9  0.7 -1.9 -1.3  -2.2 1.7 -3.3
triangle {M0}  0.3 0.1 -1.7  3.3 -2.1 -2.9  2.1 2.3 -0.9
disk {M0}  1.9 1.3 -2.3  1.1  0.3 0.2 1
disk {M0}  -1.3 -0.4 -3.1  0.9  -0.2 0.7 0.6
triangle {M0}  -0.53 0.31 -40.3  0.61 0.13 -41.1  0.17 1.23 -39.7
"""


def _near_rays(seed: int = 5, n: int = 960) -> np.ndarray:
    """Directions from the viewpoint to points on NEAR's triangle edges and disk rims (in
    float64, a few ulps off), each component then moved by up to 8 ulps: rays on both
    sides of every extent decision, where rounding decides a margin's sign unless the
    certified bound flags the ray, and rays beyond the bounds."""
    rng = np.random.default_rng(seed)
    xs = parse_exact(NEAR)
    V = np.array([float(c) for c in xs.viewpoint])
    fl = lambda v: np.array([float(c) for c in v])
    pts = []
    for o in xs.objects:
        if o.kind == "triangle":
            P = [fl(p) for p in o.points]
            for A, B in ((P[0], P[1]), (P[1], P[2]), (P[2], P[0])):
                s = rng.random((n // 12, 1))
                pts.append(A + s * (B - A))
        else:
            C, r, N = fl(o.center), float(o.radius), fl(o.normal)
            N /= np.linalg.norm(N)
            x = np.cross(N, [1.0, 0.0, 0.0])
            x /= np.linalg.norm(x)
            y = np.cross(N, x)
            a = rng.uniform(0, 2 * np.pi, (n // 4, 1))
            pts.append(C + r * (np.cos(a) * x + np.sin(a) * y))
    d = np.concatenate(pts) - V
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # half the rays a few ulps off (rounding decides unless flagged), half 1e-9 off (beyond
    # every bound: certain, decided by the kernel alone)
    far = rng.random((len(d), 1)) < 0.5
    step = np.where(far, 3e-8 * np.abs(d) + np.spacing(d), np.spacing(d))
    return xs, d + rng.integers(-8, 9, d.shape) * step


@pytest.mark.parametrize("rules, layout", [(Rules(), "unrolled"),
                                           (Rules(edges="open", ties="last"), "looped"),
                                           (Rules(screen_clip=">=", t_min=1e-4), "unrolled")],
                         ids=["closed-first-unrolled", "open-last-looped", "variant-unrolled"])
def test09_rounding_cannot_decide_an_edge(rules, layout, monkeypatch):
    """Rays within a few ulps of every triangle edge and disk rim: rt_core f64's answer is
    exact arithmetic's on the same rays (the certified bounds at work), with some rays
    flagged and decided exactly."""
    from rt_core import backend
    from rt_core.tracer import closest_hit, prepare
    xs, d = _near_rays()
    T = backend.types("f64")
    if layout == "looped":
        monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    ks = prepare(parse_text(NEAR), T)
    _, oid, _ = closest_hit(ks, T.Array3(*(T.Float(c) for c in d.T)), None, rules,
                            cam="rays", dmax=float(np.linalg.norm(d, axis=1).max()))
    ids = np.asarray(oid.numpy())
    ex = trace_exact(xs, d, rules)
    wrong = np.flatnonzero(ids != ex.id)
    assert not len(wrong), f"{len(wrong)} wrong of {len(d)}"
    assert 0 < ks.decided < len(d)
    assert len(set(ex.id.tolist())) == 6             # every object and the background


def test10_mitsuba_equivalents(tmp_path):
    """rtval convert: the disk as Mitsuba's ``disk``, each triangle as a PLY beside the XML
    (barycentric texture coordinates); Mitsuba loads the XML, and from the scene read by
    mitsuba_ref alone the same shapes come out."""
    from tools.cli import main
    out = tmp_path / "planar.xml"
    assert main(["convert", str(REPO / "scenes" / "planar.txt"), "--columns", "32",
                 "-o", str(out)]) == 0
    xml = out.read_text()
    assert xml.count('type="disk"') == 2 and xml.count('type="ply"') == 3
    plys = sorted(p.name for p in tmp_path.glob("*.ply"))
    assert plys == [f"planar.xml.obj{i}_triangle.ply" for i in range(3)]
    ply = (tmp_path / plys[0]).read_text().splitlines()
    assert ply[-4:] == ["-3.0 -2.0 -1.0 0.0 0.0", "0.0 -2.0 -1.0 1.0 0.0",
                        "-3.0 1.0 -1.0 0.0 1.0", "3 0 1 2"]
    from mitsuba_ref.convert import mitsuba, scene_dict
    mi = mitsuba()
    ms = mi.load_file(str(out))
    assert sorted(s.id() for s in ms.shapes()) == sorted(
        f"obj{i}_{k}" for i, k in enumerate(["triangle"] * 3 + ["disk"] * 2 + ["plane"]))
    ours = scenefile.read(REPO / "scenes" / "planar.txt").floats()
    theirs = parse_scene(REPO / "scenes" / "planar.txt")
    assert scene_dict(ours, 32).keys() == scene_dict(theirs, 32).keys()


def test11_classifier_explains_edges_only():
    """validate's classifier: an answer flipped at a sample exactly on a triangle's edge or a
    disk's rim is 'edge'; flipped well inside them it is 'unexplained'."""
    from mitsuba_ref.explain import CLASS_CODE, classify
    W, H = 17, 13
    ex = _exact_ids(None, W, H, Rules(), EDGES)
    xs = parse_exact(EDGES)
    rays, d = ideal_rays(xs.window, xs.viewpoint, W, H, range(W * H))
    sc = scenefile.read_text(EDGES).floats()
    # column c, row r sample the window at (−4 + c/2, 3 − r/2)
    on_edge = 1 * W + 5                 # window (−1.5, 2.5): the hit (−3, 5) on x + y = 2
    rim = 2 * W + 11                    # window (1.5, 2): on the big disk's rim
    inside = 9 * W + 3                  # window (−2.5, −1.5): well inside triangle 0
    ours = {"hit.mask": (ex.id >= 0).astype(float), "object.id": ex.id.astype(float)}
    assert [ex.id[p] for p in (on_edge, rim, inside)] == [0, 2, 0]
    ref = {k: v.copy() for k, v in ours.items()}
    for p in (on_edge, rim, inside):            # the other tracer saw nothing there
        ref["object.id"][p], ref["hit.mask"][p] = -1, 0
    cls = classify(sc, d, ours, ref, Rules(), extent=1e3)
    assert cls[on_edge] == CLASS_CODE["edge"] and cls[rim] == CLASS_CODE["edge"]
    assert cls[inside] == CLASS_CODE["unexplained"]


@pytest.mark.parametrize("path", SCENES, ids=IDS)
def test12_mitsuba_agrees(path):
    """rt_core f32 against Mitsuba (its disk and triangle mesh) on the same rays: every
    differing pixel explained by the classifier, depth within its bound, and the objects
    really hit by both."""
    from tools.harness.compare import compare
    sc = _scene_ok(path)
    cmp = compare(sc, 48, None, "f32", "rays")
    assert cmp.unexplained == 0 and cmp.depth["over_bound"] == 0, cmp.counts
    assert cmp.counts["agree"] >= 0.98 * sum(cmp.counts.values())


def test13_code27_option(tmp_path, capsys):
    """rtval render --code27: 'disk' reads nw__disk1's 27 as the file means it (recorded in
    the output's provenance); 'triangle' is refused with one line naming the file, line and
    field (exit 2), and no output."""
    from tools.cli import main
    scene = tmp_path / "d.txt"
    scene.write_text(DISK27)
    out = tmp_path / "d.exr"
    assert main(["render", str(scene), "--columns", "16", "--code27", "disk",
                 "-o", str(out)]) == 0 and out.is_file()
    import OpenEXR
    extras = OpenEXR.File(str(out)).header()["rtval.extras"]
    assert extras == "line 3 disk: code 27 read as=disk (by the code27 option)"
    out.unlink()
    capsys.readouterr()
    assert main(["render", str(scene), "--columns", "16", "--code27", "triangle",
                 "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{scene}:8:5: triangle: expected 3 numbers for point 2" in err
    assert not out.exists() and list(tmp_path.iterdir()) == [scene]


def test14_check_infers_open_edges(tmp_path, capsys):
    """rtval check on a course-style image of EDGES rendered with open edges: the triangle
    and disk edge samples determine the rule (edges=open), and the image passes under it."""
    import json
    from tools.cli import main
    scene, ppm = tmp_path / "edges.txt", tmp_path / "edges.ppm"
    scene.write_text(EDGES)
    # (in float64, which decides the samples on the edges exactly: float32 rounds them to
    # either side, and by the CPU: its directions are normalised with Dr.Jit's approximate
    # rsqrt.  In float32 this test passed on AVX-512 machines and failed on an AVX2 one)
    assert main(["render", str(scene), "--columns", "17", "--rules", "edges=open",
                 "--precision", "f64", "--ppm", str(ppm), "-o", str(tmp_path / "edges.exr")]) == 0
    capsys.readouterr()
    assert main(["check", str(scene), str(ppm), "--json"]) == 0
    (r,) = json.loads(capsys.readouterr().out)
    edges = next(f for f in r["findings"] if f["rule"] == "edges")
    assert (edges["value"], edges["determined"], r["status"]) == ("open", True, "pass")


# a triangle and a disk tilted through the window's plane z = 0: the parts in front of it are
# clipped (the notes' screen clip), the plane behind seen through them
THROUGH = f"""8 6
0 0 5
triangle {M0}  -4 -3 -2  1 -3 2  -4 3 2
disk {M0}  2 0 0  1.5  1 0 1
plane {M0}  0 0 1  0 0 -6
"""


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test15_clipped_in_front_of_the_window(precision):
    """The float64 oracle clips triangles and disks in front of the window as its hit test
    does (it asserted on its own verdict's tests there: a traceback from `rtval report` and
    `check`), and agrees with the exact oracle and rt_core."""
    W, H = 32, 24
    orc = render_oracle(scenefile.read_text(THROUGH).floats(), W, H)
    ex = _exact_ids(None, W, H, Rules(), THROUGH)
    unclipped = _exact_ids(None, W, H, Rules(screen_clip="off"), THROUGH)
    seen_through = (unclipped.id != ex.id)
    assert seen_through.sum() >= 20 and set(unclipped.id[seen_through]) == {0, 1}
    assert (orc["object.id"].ravel() == ex.id).all()
    compare(f"through-{precision}", tracer(parse_text(THROUGH, "s.txt"), W, H, precision),
            orc, TOL[precision])
