"""Code 25: cd's lens (a sphere with a stand-in note) and nw's torus.

The lens: both readers decide the 25 layout the same way (cd's header flags, or one number
after the centre) and read it as the sphere (centre, radius), with the lens's stand-in note
in the scene's provenance lines."""
from __future__ import annotations

from pathlib import Path

import pytest

from mitsuba_ref import scenefile
from rt_core.parser import parse_scene, parse_text

HERE = Path(__file__).resolve()
REPO = HERE.parents[1]
COURSE = HERE.parents[2] / "shared" / "course-scenes" / "numeric"
_M = "1 1 1\n1 1 1\n0 0 0\n"
NUM = "8 6\n0 0 5\n"


def _course(name):
    path = COURSE / name
    if not path.is_file():
        pytest.skip(f"real course scenes not found at {COURSE}")
    return path


def test01_cd_lens_is_read_as_a_sphere_with_a_stand_in():
    path = _course("cd__lens.txt")
    s = parse_scene(path)
    lens = s.objects[-1]
    assert (lens.kind, lens.form, lens.center, lens.radius, lens.line) == \
        ("sphere", "lens", (0.0, 0.0, -1.0), 1.0, 33)
    assert dict(lens.extras) == {"transparency": 0.9, "refraction index": 1.33}
    assert any(line.startswith("line 33: cd's lens (code 25): traced as the sphere")
               for line in s.stand_ins())
    r = scenefile.read(path).objects[-1]
    assert (r.kind, r.form, r.center, r.radius) == ("sphere", "lens", (0.0, 0.0, -1.0), 1.0)


def test02_lens_without_flags_by_its_line_shape():
    text = NUM + "25\n" + _M + "0 0 -4 centre\n1.5 radius\n"
    s = parse_text(text)
    assert (s.objects[0].kind, s.objects[0].form, s.objects[0].radius) == ("sphere", "lens", 1.5)
    r = scenefile.read_text(text).objects[0]
    assert (r.kind, r.form, r.radius) == ("sphere", "lens", 1.5)


# --- nw's torus ---------------------------------------------------------------------------------

import random
from fractions import Fraction

import numpy as np

from mitsuba_ref.exact import K_ROUNDING, U, ideal_rays, parse_exact, trace_exact
from rt_core import accel, backend
from rt_core.camera import make_camera, primary_directions
from rt_core.render import trace_geometry
from rt_core.scene import SceneError

from tests.tolerances import PRECISIONS  # noqa: E402
# A ring in the plane x = -0.15 and the viewpoint straight above the samples x = 0.85 (64
# columns): every ray of column 40 lies in the plane x = 0.85 = -0.15 + r, tangent to the
# tube's top circle (a double root: a miss) or missing it; torus B is seen through its hole.
GRAZE = """6.3 4.8
0.85 2.4 10
14
2 2 2
3 3 3
0 0 0
0 0 1
0 0 -12
25
3 1 1
5 2 2
0 0 0
-0.15 1 -4
1 0 0
2
1
25
1 1 3
2 2 5
0 0 0
-1.2 -0.6 -3
0 0.3 1
1.6
0.5
10
20 20 20
-3 6 8
"""


def test03_nw_torus_is_read_by_every_reader():
    path = _course("nw__t.txt")
    t = parse_scene(path).objects[1]
    assert (t.kind, t.center, t.axis, t.major, t.minor, t.line) == \
        ("torus", (0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 10.0, 3.0, 12)
    r = scenefile.read(path).objects[1]
    assert (r.kind, r.center, r.axis, r.major, r.minor) == \
        ("torus", (0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 10.0, 3.0)
    x = parse_exact(path.read_text()).objects[1]
    assert (x.kind, x.center, x.normal, x.size) == ("torus", (0, 0, -1), (0, 0, 1), (10, 3))


def test04_a_three_number_line_after_the_centre_is_the_torus():
    text = NUM + "25\n" + _M + "0 0 -4 centre\n0 1 0 axis\n2\n0.5\n"
    t = parse_text(text).objects[0]
    assert (t.kind, t.major, t.minor) == ("torus", 2.0, 0.5)
    assert scenefile.read_text(text).objects[0].kind == "torus"


@pytest.mark.parametrize("fields, line, col, phrase", [
    ("0 0 0\n2\n0.5\n", 8, 1, "axis (0, 0, 0) has no direction"),
    ("0 1 0\n2\n2\n", 10, 1, "minor radius 2 must be below the major radius 2"),
    ("0 1 0\n-1\n0.5\n", 9, 1, "major radius -1 must be positive"),
])
def test05_torus_geometry_errors_name_the_field(fields, line, col, phrase):
    with pytest.raises(SceneError) as info:
        parse_text(NUM + "25\n" + _M + "0 0 -4\n" + fields, "t.txt")
    err = info.value
    assert (err.line, err.col) == (line, col) and phrase in err.message, str(err)


def _exact_all(text, W, H, pixels):
    xs = parse_exact(text)
    rays, d = ideal_rays(xs.window, xs.viewpoint, W, H, pixels)
    ex = trace_exact(xs, d, rays=rays)
    length = np.array([np.linalg.norm(np.array(E, float)) / L for E, L in rays])
    return ex, ex.t * length


def _check_against_exact(text, W, H, pixels, precision):
    """rt_core's ids at ``pixels`` equal the exact oracle's in f64; in f32 every difference
    is within reach of rounding (ExactResult.explained); depths of agreeing hits within
    K·u·κ_t (the exact oracle's condition of t).  Returns rt_core's ids there."""
    from rt_core.parser import parse_text as parse
    sc = parse(text)
    g = trace_geometry(sc, make_camera(sc, W, H), backend.types(precision))
    ids = np.array(g["object.id"]).astype(int).ravel()[pixels]
    dep = np.array(g["depth.Z"]).ravel()[pixels]
    ex, t = _exact_all(text, W, H, pixels)
    u = U[precision]
    if precision == "f64":
        wrong = np.flatnonzero(ids != ex.id)
        assert not len(wrong), [(pixels[k], ids[k], ex.id[k]) for k in wrong[:8]]
    else:
        assert ex.explained(ids, u).all()
    same = ex.hit & (ids == ex.id)
    rel = np.abs(dep[same] - t[same]) / t[same]
    assert (rel <= K_ROUNDING * u * ex.kappa_t[same]).all(), rel.max()
    assert same.sum() > 0
    return ids, ex


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name, W, H", [("torus.txt", 32, 24), ("nw__t.txt", 32, 26)])
def test06_every_pixel_against_the_exact_oracle(name, W, H, precision):
    path = REPO / "scenes" / name if name == "torus.txt" else _course(name)
    ids, ex = _check_against_exact(path.read_text(), W, H, list(range(W * H)), precision)
    # the torus is hit (scenes/torus.txt), or seen through: nw__t's view is its hole
    torus = [o.index for o in parse_exact(path.read_text()).objects if o.kind == "torus"][0]
    assert ((ex.id == torus).sum() > 100) == (name == "torus.txt")


@pytest.mark.parametrize("precision", PRECISIONS)
def test07_tangent_rays_are_decided_exactly(precision):
    """Column 40 of GRAZE: every ray touches torus A without crossing, or misses it (exact:
    never a hit on A); f64 flags them and decides them exactly, f32 is within reach."""
    W, H = 64, 48
    column = [r * W + 40 for r in range(H)]
    rng = random.Random(13)
    pixels = sorted(set(column) | set(range(0, 4 * W)) | set(rng.sample(range(W * H), 150)))
    ids, ex = _check_against_exact(GRAZE, W, H, pixels, precision)
    on_column = np.isin(pixels, column)
    assert not (ex.id[on_column] == 1).any()
    if precision == "f64":
        from rt_core.tracer import closest_hit, prepare
        sc = parse_text(GRAZE)
        cam = make_camera(sc, W, H)
        T = backend.types("f64")
        ks = prepare(sc, T)
        closest_hit(ks, primary_directions(sc, cam, T), None, cam=cam)
        assert ks.decided >= 30                     # the tangent rays, decided exactly


def test08_exact_roots_compare_exactly():
    """Both exact root isolations (rt_core/decide_torus.py, mitsuba_ref/torus_exact.py): a
    tangency (double root) is no hit, and roots compare exactly with rationals, with
    α + β√D and with each other."""
    from mitsuba_ref import torus_exact as te
    from rt_core import decide_torus as dt
    F = lambda *fs: _poly_product(*fs)
    tangent_then_3 = F([1, -1], [1, -1], [-3, 1], [5, 1])          # (s−1)²(s−3)(s+5)
    r = dt.first_crossing(tangent_then_3)
    assert r.cmp_number(Fraction(3)) == 0
    x = te.first_crossing(tangent_then_3)
    assert not te.less(x, (3, 1)) and not te.less((3, 1), x)
    sqrt2 = F([-2, 0, 1], [-5, 1], [1, 1])                          # (s² − 2)(s − 5)(s + 1)
    sqrt2b = F([-2, 0, 1], [-7, 1], [2, 1])
    sqrt3 = F([-3, 0, 1], [-5, 1], [1, 1])
    a, b, c = (dt.first_crossing(p) for p in (sqrt2, sqrt2b, sqrt3))
    assert a.cmp_number(Fraction(0), Fraction(1), Fraction(2)) == 0     # √2 = 0 + 1·√2
    assert a.cmp_number(Fraction(141, 100)) > 0 > a.cmp_number(Fraction(142, 100))
    assert a.cmp_root(b) == 0 and a.cmp_root(c) < 0 < c.cmp_root(b)
    xa, xb, xc = (te.first_crossing(p) for p in (sqrt2, sqrt2b, sqrt3))
    assert not te.less(xa, xb) and not te.less(xb, xa) and te.less(xa, xc)
    assert te.less((141, 100), xa) and te.less(xa, (142, 100))
    assert dt.first_crossing(F([1, -1], [1, -1], [4, 1])) is None   # only a tangency
    assert te.first_crossing(F([1, -1], [1, -1], [4, 1])) is None


def test08b_oracle_polynomial_in_integers():
    """mitsuba_ref/torus_exact.py computes F in integers (G = K·F, K > 0) and takes G as its
    own square-free part where gcd(G, G') is 1 modulo a prime: G/K is the equation written
    in Fractions, and the square-free part is Euclid's in Fractions, with repeated factors
    and without."""
    from mitsuba_ref import torus_exact as te
    rnd = random.Random(8)

    def dec():
        return Fraction(rnd.randint(-3000, 3000), rnd.choice([1, 10, 100, 1000]))

    for _ in range(200):
        Q, A = tuple(dec() for _ in range(3)), tuple(dec() or 1 for _ in range(3))
        R, r = abs(dec()) + 1, abs(dec()) / 7 + Fraction(1, 10)
        D = tuple(rnd.randint(-2 ** 40, 2 ** 40) for _ in range(3))
        Dd = rnd.randint(1, 2 ** 45)
        d = [Fraction(c, Dd) for c in D]
        w2 = [sum(c * c for c in Q), -2 * sum(q * c for q, c in zip(Q, d)),
              sum(c * c for c in d)]
        wa = [-sum(q * a for q, a in zip(Q, A)), sum(c * a for c, a in zip(d, A))]
        AA = sum(c * c for c in A)
        s = [w2[0] + R * R - r * r, w2[1], w2[2]]
        want = [AA * c for c in _poly_product(s, s)]
        for i in range(3):
            want[i] += -4 * R * R * AA * w2[i] + 4 * R * R * _poly_product(wa, wa)[i]
        G, K = te.torus_poly(Q, A, R, r, D, Dd)
        assert K > 0 and all(isinstance(c, int) for c in G)
        assert [Fraction(c, K) for c in G] == want
    for factors in ([[1, -1], [1, -1], [-3, 1], [5, 1]], [[-2, 0, 1], [-5, 1], [1, 1]],
                    [[7, 3], [7, 3], [7, 3], [-1, 2]], [[-2, 0, 1], [-2, 0, 1]]):
        G = [int(c) for c in _poly_product(*factors)]
        dG = [i * G[i] for i in range(1, len(G))]
        want = te._divmod([Fraction(c) for c in G], te._gcd(G, dG))[0]
        got = te._squarefree(G)
        # the same polynomial up to a positive factor
        assert len(got) == len(want) and all(
            Fraction(g) * want[-1] == w * got[-1] for g, w in zip(got, want))


def test08c_oracle_viewpoint_on_the_torus_and_ray_signs():
    """The exact oracle with the viewpoint on the torus (F(0) = 0: its bisection never ended,
    a helper's fuzzing found) takes the next crossing; a ray whose denominator is negative
    is the same ray; a ray of no direction is refused as before."""
    from mitsuba_ref import torus_exact as te
    from rt_core.rules import Rules
    # R = 2, r = 1 about the z axis at (0, 0, -4); the viewpoint on the outer equator,
    # looking in along -x: out of the tube at x = 1 (t = 2)
    G, _ = te.torus_poly((Fraction(-3), 0, 0), (0, 0, 1), Fraction(2), Fraction(1),
                         (-1, 0, 0), 1)
    assert G[0] == 0
    hit = te.first_crossing(G)
    assert Fraction(hit[0], hit[1]) == 2 and hit.cmp(Fraction(2)) == 0
    tor = parse_exact("8 6\n0 0 5\n25\n1 1 1\n1 1 1\n0 0 0\n0 0 -4\n0 1 0\n2\n0.5\n")
    d = np.array([[0.0, 0.0, -1.0]])
    a = trace_exact(tor, d, Rules(), rays=[((0, 0, -1), 1)])
    b = trace_exact(tor, d, Rules(), rays=[((0, 0, 1), -1)])
    assert a.hit[0] and b.hit[0] and a.t[0] == b.t[0] == 6.5
    # a ray of no direction (a sample at the viewpoint): a decided miss, as a course
    # program's NaN direction misses (it raised ZeroDivisionError, a traceback from
    # compare --mode exact)
    z = trace_exact(tor, d, Rules(), rays=[((0, 0, 0), 1)])
    assert not z.hit[0] and z.id[0] == -1


def _poly_product(*factors):
    out = [Fraction(1)]
    for f in factors:
        nxt = [Fraction(0)] * (len(out) + len(f) - 1)
        for i, a in enumerate(out):
            for j, b in enumerate(f):
                nxt[i + j] += a * Fraction(b)
        out = nxt
    return out


def _many_tori() -> str:
    """A 4 x 3 grid of tori (more than accel.UNROLL_MAX: the loop, its bins and the BVH)."""
    out = "8 6\n0 0 8\n14\n" + _M + "0 0 1\n0 0 -8\n"
    for k in range(12):
        x, y = -3 + 2 * (k % 4), -2 + 2 * (k // 4)
        out += f"25\n{_M}{x} {y} -{2 + k % 3}\n{k % 2} 1 {1 + k % 3}\n0.7\n0.25\n"
    return out + "10\n9 9 9\n-2 5 6\n"


@pytest.mark.parametrize("precision", PRECISIONS)
def test09_loop_bins_and_bvh_equal_the_unrolled_code(precision):
    from rt_core.tracer import closest_hit, occluded, prepare
    sc = parse_text(_many_tori())
    T = backend.types(precision)
    cam = make_camera(sc, 48, 36)
    d = primary_directions(sc, cam, T)
    looped, unrolled = prepare(sc, T), accel.configure(prepare(sc, T), unroll_max=100)
    assert accel.looped(looped, "torus", camera=True)
    assert not accel.looped(unrolled, "torus")
    a, b = closest_hit(looped, d), closest_hit(unrolled, d)
    assert np.array_equal(a[1].numpy(), b[1].numpy()) and (a[1].numpy() >= 1).sum() > 200
    assert np.array_equal(a[0].numpy(), b[0].numpy())
    # shadow rays from the hits toward the light: the BVH against every object
    H = d * a[0]
    L = T.Array3(-2.0, 5.0, -2.0) - H                    # the light, relative to the viewpoint
    dist = np.sqrt(sum(np.asarray(c.numpy()) ** 2 for c in (L.x, L.y, L.z)))
    Ld = L / T.Float(dist)
    blocked = [occluded(accel.configure(prepare(sc, T), bvh=flag), Ld, H, T.Float(dist),
                        skip=a[1]).numpy() for flag in (True, False)]
    assert np.array_equal(*blocked) and 10 < blocked[0].sum() < len(dist)


def test10_convert_leaves_the_torus_out_and_says_so():
    from mitsuba_ref.convert import mitsuba_subset, oracle_only, scene_dict, scene_xml
    sc = parse_scene(REPO / "scenes" / "torus.txt")
    d = scene_dict(sc, 32, 24)
    assert [k for k in d if k.startswith("obj")] == ["obj0_plane", "obj2_sphere"]
    assert oracle_only(sc) == ["line 11: torus has no Mitsuba shape; left out of the Mitsuba "
                               "scene (checked against rtval's oracles only)"]
    assert "<!-- line 11: torus has no Mitsuba shape" in scene_xml(sc, 32, 24)
    reduced, note = mitsuba_subset(sc)
    assert [o.kind for o in reduced.objects] == ["plane", "sphere"] and "torus" in note


def _random_tori(seed: int) -> str:
    """Two tori of random centre, axis and radii, a sphere and a plane behind."""
    rng = random.Random(seed)
    r = lambda a, b: round(rng.uniform(a, b), 2)
    out = f"8 6\n{r(-1, 1)} {r(-1, 1)} {r(4, 9)}\n14\n{_M}0 0 1\n0 0 -9\n"
    for _ in range(2):
        R = r(1, 2.5)
        out += (f"25\n{_M}{r(-2, 2)} {r(-2, 2)} {r(-5, -1)}\n{r(-1, 1)} {r(-1, 1)} {r(-1, 1)}\n"
                f"{R}\n{r(0.2, R - 0.1)}\n")
    return out + f"13\n{_M}{r(-2, 2)} {r(-2, 2)} {r(-5, -1)}\n{r(0.3, 1)}\n"


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("seed", [1, 6])
def test11_random_tori_against_the_exact_oracle(seed, precision):
    """Random axes and radii, tori in front of and behind each other and the sphere: f64
    exact on every pixel, f32 within reach of rounding (8 seeds at 24x18 checked once)."""
    ids, ex = _check_against_exact(_random_tori(seed), 20, 15, list(range(300)), precision)
    assert np.isin(ex.id, [1, 2]).sum() > 30


def test_a_ray_that_touches_the_tube_is_a_miss_exactly():
    """tests/scenes/torus_tangent.txt: the 17 x 13 image's row y = 2 touches the top of the
    tube.  The exact oracle's isolating interval ended at another root of F (t = 2), whose
    sign 0 it read as a crossing: two hits where rt_core and the float64 oracle have none
    (a helper's fuzzing)."""
    import subprocess
    import sys
    r = subprocess.run([sys.executable, "-m", "tools.cli", "compare",
                        str(REPO / "tests" / "scenes" / "torus_tangent.txt"), "--columns", "17",
                        "--rows", "13", "--mode", "exact", "--precision", "f64"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "agree=221" in r.stdout, (r.stdout, r.stderr)


@pytest.mark.parametrize("scale", ["1", "1e-4", "1e4", "1e8"])
def test_the_float64_oracle_is_the_same_at_any_scale(scale, tmp_path, monkeypatch):
    """tests/scenes/torus_tiny.txt (a torus 1e-4 across) and the same scene scaled: rt_core's
    float64 course image passes the float64 shading oracle at every scale.  Its steps and
    tolerances were absolute, 1e-6·(|t| + 1): at the first two, a sign test's step spanned
    the tube, and two pixels of the correct image were wrong (a helper's fuzzing)."""
    from decimal import Decimal
    from tools.cli import main
    lines = (REPO / "tests" / "scenes" / "torus_tiny.txt").read_text().splitlines()
    # every group but the codes, the light's colour, the materials and the axis is a length
    keep = {2, 3, 5, 6, 7, 8, 10}
    k = Decimal(scale)
    text = "\n".join(line if i in keep else " ".join(str(Decimal(x) * k) for x in line.split())
                     for i, line in enumerate(lines))
    scene = tmp_path / "t.txt"
    scene.write_text(text + "\n")
    monkeypatch.chdir(tmp_path)
    assert main(["compare", str(scene), "--columns", "21", "--rows", "16", "--shaded",
                 "--reference", "oracle"]) == 0
