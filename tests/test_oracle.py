"""Self-checks of the per-ray oracle on hand-computed cases."""
import math

import numpy as np
import pytest

from rt_core.rules import Rules
from rt_core.scene import Material, Scene, make_fplane, make_plane, make_sphere, make_tplane
from tests import oracle
from tests.oracle import primary_ray, render_oracle, trace
from tests.scenegen import random_scene

M = Material((0, 0, 0), (0, 6, 6), (0, 0, 0))
B = Material((1, 1, 1), (1, 1, 1), (0, 0, 0))


def scene_of(*objects, viewpoint=(0.0, 0.0, 3.0), window=(8.0, 6.0)):
    return Scene(window, viewpoint, (), tuple(objects))


# --- the seed's finite plane: normal (1,0,3), point (4,1,-3), orient (1,2,0), size 5 x 5 ------
# orient projected: (1,2,0) - (1/10)(1,0,3) = (0.9, 2, -0.3), |.| = sqrt(4.9)
# y = n x x = (-6, 3, 2) / (sqrt(10) sqrt(4.9)) = (-6, 3, 2) / 7
SEED_X = tuple(c / math.sqrt(4.9) for c in (0.9, 2.0, -0.3))
SEED_Y = (-6 / 7, 3 / 7, 2 / 7)
SEED_P = (4.0, 1.0, -3.0)
EYE = (0.0, 0.0, 3.0)


def seed_fplane():
    return make_fplane(M, (1, 0, 3), SEED_P, (1, 2, 0), (5, 5))


def seed_point(u, v):
    return tuple(SEED_P[i] + u * SEED_X[i] + v * SEED_Y[i] for i in range(3))


def ray_to(p, base=EYE):
    d = tuple(a - b for a, b in zip(p, base))
    n = math.sqrt(sum(c * c for c in d))
    return base, tuple(c / n for c in d)


def test01_seed_frame():
    f = seed_fplane()
    assert f.xdir == pytest.approx(SEED_X, abs=1e-15)
    assert f.ydir == pytest.approx(SEED_Y, abs=1e-15)


def test02_seed_centre_hit():
    s = scene_of(seed_fplane())
    c = seed_point(2.5, 2.5)
    h = trace(s, *ray_to(c))
    assert h.hit and h.id == 0
    assert h.t == pytest.approx(math.dist(EYE, c), rel=1e-14)
    assert h.position == pytest.approx(c, abs=1e-13)
    assert h.uv == pytest.approx((2.5, 2.5), abs=1e-13)
    assert h.normal == pytest.approx(tuple(x / math.sqrt(10) for x in (1, 0, 3)), abs=1e-15)
    assert h.edge_margin > 1e-3 and h.tie_gap == math.inf


@pytest.mark.parametrize("u,v", [(-1e-6, 2.5), (5 + 1e-6, 2.5), (2.5, -1e-6), (2.5, 5 + 1e-6)],
                         ids=["left", "right", "bottom", "top"])
def test03_seed_just_outside_each_edge(u, v):
    s = scene_of(seed_fplane())
    h = trace(s, *ray_to(seed_point(u, v)))
    assert not h.hit and h.id == -1 and h.t == 0.0
    # the verdict is ~1e-6 from flipping: far above float64 rounding, within float32's
    assert 1e-12 < h.edge_margin < 1e-5
    h = trace(s, *ray_to(seed_point(min(max(u, 1e-6), 5 - 1e-6), min(max(v, 1e-6), 5 - 1e-6))))
    assert h.hit


# --- exact edges: axis-aligned so every quantity is exact -----------------------------------

@pytest.mark.parametrize("corner_x,w", [(0.0, 2.0), (-2.0, 2.0)], ids=["u=0", "u=w"])
def test04_closed_vs_open_edges(corner_x, w):
    f = make_fplane(M, (0, 0, 1), (corner_x, -1.0, -3.0), (1, 0, 0), (w, 2.0))
    s = scene_of(f)
    base, d = ray_to((0.0, 0.5, -3.0))       # d.x == 0: hitloc.x == 0 exactly
    assert d[0] == 0.0
    h = trace(s, base, d, Rules(edges="closed"))
    assert h.hit and h.uv[0] == -corner_x
    assert not trace(s, base, d, Rules(edges="open")).hit
    # u = 1*(0 - P.x) + 0*(...) + 0*(...) is exact: the verdict is not at risk.  (At u = w that
    # holds for the notes' formula only: a tracer that forms u as y.(q x d)/(n.d) rounds there,
    # so rule-variant scenes put their exact edges at u = 0, where every formula gives 0.)
    assert h.edge_margin > 1e-3


# --- ties -----------------------------------------------------------------------------------

def test05_tie_order():
    p = make_plane(B, (0, 0, 1), (0, 0, -5))
    f = make_fplane(M, (0, 0, 1), (0, 0, -5), (1, 0, 0), (1, 1))
    s = scene_of(p, f)
    base, d = ray_to((0.5, 0.5, -5.0))
    h = trace(s, base, d, Rules(ties="first"))
    assert h.hit and h.id == 0 and h.uv == (0.0, 0.0)
    h = trace(s, base, d, Rules(ties="last"))
    assert h.hit and h.id == 1 and h.uv == pytest.approx((0.5, 0.5), abs=1e-14)
    assert h.tie_gap == math.inf            # the same plane equation: exact, the rule decides


def test06_near_tie_is_flagged():
    s = scene_of(make_plane(B, (0, 0, 1), (0, 0, -5)),
                 make_plane(B, (0, 0, 1), (0, 0, -5 - 1e-7)))
    h = trace(s, *ray_to((0.1, 0.2, -5.0)))
    assert h.id == 0 and 1e-12 < h.tie_gap < 1e-5


# --- screen clip ------------------------------------------------------------------------------

def test07_screen_clip_z_zero():
    # viewpoint and ray in z = 0: hitloc.z = 0 + t * 0 = 0 exactly
    s = scene_of(make_plane(B, (1, 0, 0), (-10, 0, 0)), viewpoint=(0.0, 0.0, 0.0))
    base, d = (0.0, 0.0, 0.0), (-1.0, 0.0, 0.0)
    h = trace(s, base, d, Rules(screen_clip=">"))
    assert h.hit and h.t == 10.0 and h.position == (-10.0, 0.0, 0.0)
    assert h.clip_margin == math.inf                     # exact zero: cannot flip
    assert not trace(s, base, d, Rules(screen_clip=">=")).hit
    assert trace(s, base, d, Rules(screen_clip="off")).hit


def test08_screen_clip_z_positive():
    s = scene_of(make_plane(B, (0, 0, 1), (0, 0, 1)))
    base, d = EYE, (0.0, 0.0, -1.0)
    assert not trace(s, base, d, Rules(screen_clip=">")).hit
    assert not trace(s, base, d, Rules(screen_clip=">=")).hit
    h = trace(s, base, d, Rules(screen_clip="off"))
    assert h.hit and h.t == 2.0


# --- spheres ------------------------------------------------------------------------------------

def test09_sphere_near_root():
    s = scene_of(make_sphere(M, (0, 0, -5), 1.0))
    h = trace(s, EYE, (0.0, 0.0, -1.0))
    assert h.hit and h.t == 7.0 and h.normal == (0.0, 0.0, 1.0)
    assert h.position == (0.0, 0.0, -4.0) and h.uv == (0.0, 0.0)
    # from inside, only the near root counts: it is behind, so a miss
    assert not trace(s, (0.0, 0.0, -5.0), (0.0, 0.0, -1.0)).hit
    # tangent ray: discriminant 0 is a miss
    assert not trace(s, (1.0, 0.0, 3.0), (0.0, 0.0, -1.0)).hit


def test10_sphere_clip_only_if_asked():
    s = scene_of(make_sphere(M, (0, 0, 0.5), 1.0))
    h = trace(s, EYE, (0.0, 0.0, -1.0))
    assert h.hit and h.t == 1.5
    assert not trace(s, EYE, (0.0, 0.0, -1.0), Rules(clip_spheres=True)).hit


# --- planes -------------------------------------------------------------------------------------

def test11_parallel_ray_misses():
    s = scene_of(make_plane(B, (0, 1, 0), (0, 0, 0)))
    assert not trace(s, (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)).hit    # even lying in the plane
    assert not trace(s, (0.0, 1.0, -1.0), (1.0, 0.0, 0.0)).hit


def test12_t_min():
    s = scene_of(make_plane(B, (0, 0, 1), (0, 0, 3 - 5e-5)))
    off = Rules(screen_clip="off")
    h = trace(s, EYE, (0.0, 0.0, -1.0), off)
    assert h.hit and h.t == pytest.approx(5e-5, rel=1e-9)
    assert not trace(s, EYE, (0.0, 0.0, -1.0), Rules(t_min=1e-4, screen_clip="off")).hit
    assert not trace(s, EYE, (0.0, 0.0, -1.0)).hit          # z > 0: screen-clipped
    assert not trace(s, EYE, (0.0, 0.0, 1.0), off).hit      # behind the viewpoint


@pytest.mark.parametrize("u,v,fg", [(0.5, 0.5, False), (1.5, 0.5, True), (0.5, 1.5, True),
                                    (1.5, 1.5, False), (-0.5, 0.5, True), (-0.5, -0.5, False),
                                    (2.5, -3.5, False), (2.5, -2.5, True)])
def test13_tplane_parity(u, v, fg):
    tp = make_tplane(M, (0, 0, 1), (0, 0, -5), (1, 0, 0), (1.0, 2.0), B)
    s = scene_of(tp)
    h = trace(s, *ray_to((u, 2 * v, -5.0)))             # tile 1 wide, 2 high
    assert h.hit and h.uv == pytest.approx((u, 2 * v), abs=1e-13)
    assert oracle.tile_foreground(tp, *h.uv) == fg


# --- camera -------------------------------------------------------------------------------------

def test14_camera_corners_and_centers():
    s = scene_of(viewpoint=(0.0, 0.0, 3.0))
    W, H = 5, 4
    base, d = primary_ray(s, 0, 0, W, H, "corners")
    assert base == (0.0, 0.0, 3.0)
    assert d == pytest.approx(ray_to((-4.0, -3.0, 0.0))[1], abs=1e-15)
    _, d = primary_ray(s, W - 1, H - 1, W, H, "corners")
    assert d == pytest.approx(ray_to((4.0, 3.0, 0.0))[1], abs=1e-15)
    _, d = primary_ray(s, 0, 0, W, H, "centers")
    assert d == pytest.approx(ray_to((0.5 / W * 8 - 4, 0.5 / H * 6 - 3, 0.0))[1], abs=1e-15)


def test15_image_row0_is_top():
    s = scene_of(make_plane(B, (0, 0, 1), (0, 0, -1)))
    img = render_oracle(s, 5, 4)
    assert img["hit.mask"].shape == (4, 5)
    # row 0 = world y = +wh/2 at the window; the hit lies further along the same ray
    assert np.all(img["position.Y"][0] > 0) and np.all(img["position.Y"][-1] < 0)
    assert img["position.X"][0, 0] < 0 < img["position.X"][0, -1]
    assert img["position.Y"][0, 2] == pytest.approx(3.0 * 4 / 3, rel=1e-14)
    assert img["depth.Z"][1, 2] > img["depth.Z"][0, 2] * 0  # filled


def test16_misses_are_zero():
    s = scene_of(make_sphere(M, (0, 0, -5), 0.5))
    img = render_oracle(s, 9, 7)
    miss = img["hit.mask"] == 0
    assert miss.any() and (~miss).any()
    assert np.all(img["object.id"][miss] == -1)
    for k in oracle.GEOMETRY_KEYS:
        if k not in ("object.id",):
            assert np.all(img[k][miss] == 0), k
    assert img["hit.mask"][3, 4] == 1 and img["depth.Z"][3, 4] == pytest.approx(7.5)


def test17_random_scenes_are_seen():
    seen = set()
    for seed in range(4):
        s = random_scene(seed)
        assert len(s.objects) == 8
        assert all(o.point[2] < 0 for o in s.objects if o.kind != "sphere")
        assert all(c[2] < 0 for o in s.objects if o.kind == "fplane" for c in o.corners())
        assert random_scene(seed) == s                    # deterministic
        ids = np.unique(render_oracle(s, 24)["object.id"])
        assert len(ids) >= 2
        seen.update((seed, int(i)) for i in ids)
    assert len(seen) >= 12


@pytest.mark.parametrize("columns, rows, sampling", [(17, 12, "corners"), (44, 33, "centers")])
def test_an_orient_near_the_normal_widens_the_edge_bound(columns, rows, sampling):
    """tests/scenes/fplane_orient_near_normal.txt: the orient 1e-4 off the normal, so
    x̂ = unit(ô − (ô·n̂)n̂) cancels 4 digits.  The oracle took its frame as rounded once
    (error u), and decided 8 pixels (23 at 44 columns) against the exact oracle with an
    edge margin 2-100× over f64's u: unflagged.  Every pixel it decides otherwise than the
    exact oracle must be flagged."""
    from pathlib import Path
    from mitsuba_ref.exact import U, ideal_rays, parse_exact, trace_exact
    from rt_core.parser import parse_scene
    path = Path(__file__).parent / "scenes" / "fplane_orient_near_normal.txt"
    rules = Rules(edges="open")
    o = render_oracle(parse_scene(path), columns, rows, sampling=sampling, rules=rules)
    xs = parse_exact(path.read_text())
    rays, d = ideal_rays(xs.window, xs.viewpoint, columns, rows, range(columns * rows),
                         sampling)
    ex = trace_exact(xs, d, rules, rays=rays)
    assert ex.hit.sum() > 20
    bad = np.flatnonzero((o["hit.mask"].ravel() > 0) != ex.hit)
    assert (o["edge_margin"].ravel()[bad] < U["f64"]).all(), o["edge_margin"].ravel()[bad]


def test_a_huge_normal_and_orient_frame_as_their_unit_ones(tmp_path):
    """A finite plane's normal and orient written 1e200 times larger (or 1e-200 times
    smaller) give the same image: the oracle scales each by a power of two before its
    squared length (geometry.pow2_scaled), which overflowed to inf (or underflowed to 0)
    otherwise."""
    from pathlib import Path
    from rt_core.parser import parse_scene
    lines = (Path(__file__).parent / "scenes" / "fplane_orient_near_normal.txt").read_text() \
        .splitlines()
    got = []
    for factor in (1.0, 1e200, 1e-200):
        scaled = list(lines)
        for k in (6, 8):                    # the normal and the orient
            scaled[k] = " ".join(repr(float(x) * factor) for x in lines[k].split())
        path = tmp_path / f"x{factor}.txt"
        path.write_text("\n".join(scaled) + "\n")
        got.append(render_oracle(parse_scene(path), 17, 12))
    assert got[0]["hit.mask"].sum() > 20
    for o in got[1:]:
        np.testing.assert_array_equal(o["hit.mask"], got[0]["hit.mask"])
        np.testing.assert_allclose(o["depth.Z"], got[0]["depth.Z"], rtol=1e-12)
