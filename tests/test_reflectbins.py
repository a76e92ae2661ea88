"""The direction bins of reflection rays (rt_core/reflectbins.py) and the cones of the light
bins (rt_core/lightbins.py) against the BVH walk they replace.  (tests/test_bvh.py compares
whole shaded images, with the bins in use, against the plain loop.)

* Rays from the corners, edges and surface points of the objects (where reflection rays
  start), aimed at the other objects' corners, edges and outlines (the borders of each
  source–target difference box and ball, and so of the cells): t and id bit-identical to
  the BVH's, f32 and f64; without the cells' margin and the two widenings together they are
  not (so the rays do reach the cells' borders; no one of the three alone changes them).
* Rays the bins cannot take (an origin outside its source's box, or in a sphere's box but
  outside the sphere, a source that is an unbounded plane, no source, a NaN direction) walk
  the BVH: the same answers, and without that walk they would differ.
* A ray stops at a row beyond its closest hit: with the bound's slack made negative, answers
  change.
* The builder: each (source, cell) list is sorted by its distance bound, the bound is below
  the distance between sampled points of the source and of the row's object, no object
  lists itself, and a scene over MAX_PAIRS or MAX_ROWS keeps the BVH.
* Light bins: shadow rays through the objects' borders (and just inside them) get the BVH's
  verdicts, and would not with the cells' radius halved in the cone test.
"""
from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

from rt_core import accel, backend, bvh, lightbins, reflectbins
from rt_core.rules import Rules
from rt_core.scene import Scene, make_fplane, make_plane, make_sphere
from rt_core.shapes_planar import planar_corners
from rt_core.tracer import closest_hit, prepare
from tests.test_bvh import GREY, bits

from tests.tolerances import PRECISIONS  # noqa: E402


@pytest.fixture(autouse=True)
def every_kind_binned(monkeypatch):
    """These scenes are made of coplanar tiles, whose rows are mostly never stopped before:
    the bins would leave them to the BVH (MAX_UNSTOPPED, test13); here they are binned."""
    monkeypatch.setattr(reflectbins, "MAX_UNSTOPPED", 1.0)


def edge_scene() -> Scene:
    """Axis-aligned unit tiles (flat boxes) in two walls, panels, spheres of several sizes and
    a mirror plane: every border at an exactly representable coordinate."""
    objs = []
    for i in range(-3, 3):
        for j in range(-2, 2):
            objs.append(make_fplane(GREY, (0, 0, 1), (i, j, -6), (1, 0, 0), (1, 1)))
            objs.append(make_fplane(GREY, (1, 0, 0), (4, j, -6 + i), (0, 1, 0), (1, 1)))
    for k in range(-3, 3):
        objs.append(make_fplane(GREY, (0, 1, 0), (k, -3, -5), (1, 0, 0), (1, 2)))
        objs.append(make_sphere(GREY, (k + 0.5, 0.5, -3.5 + 0.25 * k), 0.25 + 0.125 * (k % 3)))
    objs.append(make_plane(GREY, (0, 1, 0), (0, -4, 0)))
    return Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), tuple(objs), path="<edges>")


def _border_points(ks, rng, n):
    """n points on the bounded objects' borders (tile corners and edges, sphere surfaces)
    and each one's object id, relative to the viewpoint (float64)."""
    fp = ks.by_kind["fplane"]
    corners = planar_corners("fplane", fp)[:, [0, 1, 3, 2]]    # (objects, 4, 3), in turn
    sp = ks.by_kind["sphere"]
    q = np.array([c.q for c in sp])
    r = np.array([c.radius for c in sp])
    pts, ids = np.zeros((n, 3)), np.zeros(n, np.int64)
    on_sphere = rng.random(n) < 0.3
    k = rng.integers(0, len(fp), n)
    e = rng.integers(0, 4, n)
    f = rng.choice([0.0, 0.0, 0.25, 0.5, rng.random()], n)
    a, b = corners[k, e], corners[k, (e + 1) % 4]
    pts[:] = a + f[:, None] * (b - a)
    ids[:] = [fp[j].id for j in k]
    s = rng.integers(0, len(sp), n)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts[on_sphere] = (q[s] + r[s, None] * u)[on_sphere]
    ids[on_sphere] = np.array([sp[j].id for j in s])[on_sphere]
    return pts, ids, q, r, sp


def edge_rays(ks, n: int, seed: int):
    """Rays from border points of one object (the skip: the surface it leaves) aimed at
    border points of another, or grazing a sphere's outline: (d, o, skip) as numpy."""
    rng = np.random.default_rng(seed)
    o, src, q, r, sp = _border_points(ks, rng, n)
    target, tid = _border_points(ks, rng, n)[:2]
    # a third of the rays graze a sphere's outline instead: o + (q − o) ± r·(a unit normal)
    graze = rng.random(n) < 0.3
    s = rng.integers(0, len(sp), n)
    v = q[s] - o
    w = np.cross(v, rng.normal(size=(n, 3)))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    target[graze] = (q[s] + r[s, None] * w)[graze]
    d = target - o
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d /= np.where(norm > 0, norm, 1)
    keep = ((src != tid) | graze) & (norm[:, 0] > 0)
    return d[keep], o[keep], src[keep]


def trace(ks, d, o, skip, on: bool):
    T = ks.T
    accel.configure(ks, reflectbins=on)
    A = T.Array3
    t, oid, _ = closest_hit(ks, A(*(T.Float(d[:, k]) for k in range(3))),
                            A(*(T.Float(o[:, k]) for k in range(3))), Rules(),
                            T.Int32(skip.astype(np.int32)))
    dr.eval(t, oid)
    return np.asarray(t.numpy()), np.asarray(oid.numpy())


def differences(precision: str, monkeypatch, d=None, o=None, skip=None, on=True) -> int:
    """Rays whose (t, id) differ between the bins (``on``) and the BVH."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types(precision)
    ks = prepare(edge_scene(), T)
    if d is None:
        d, o, skip = edge_rays(ks, 60000, 3)
    (t0, i0), (t1, i1) = trace(ks, d, o, skip, False), trace(ks, d, o, skip, on)
    assert (i0 >= 0).mean() > 0.5
    assert all(reflectbins.reflect_bins(ks, k) is not None for k in ("fplane", "sphere"))
    return int(np.count_nonzero((bits(t0) != bits(t1)).any(-1) | (i0 != i1)))


@pytest.mark.parametrize("precision", PRECISIONS)
def test01_border_rays_match_the_bvh(precision, monkeypatch):
    assert differences(precision, monkeypatch) == 0


@pytest.mark.parametrize("precision", PRECISIONS)
def test02_without_margin_and_widening_border_rays_differ(precision, monkeypatch):
    """The cells' margin, the targets' widening and the sources' widening removed together,
    the border rays lose hits.  (No one of them alone changes these rays' answers, nor the
    first two together: each covers for the others here, so this guards them as a whole.)"""
    monkeypatch.setattr(lightbins, "MARGIN", 0.0)
    monkeypatch.setattr(reflectbins, "PAD", {"f32": 0.0, "f64": 0.0})
    monkeypatch.setattr(reflectbins, "SOURCE_PAD", 0.0)
    assert differences(precision, monkeypatch) > 0


def odd_rays(precision):
    """Rays the bins cannot take, each aimed at an object: origins 0.3 to 1 away from their
    source's box, in a sphere's box but outside the sphere (its box's corners), from the
    unbounded plane, with no source, and a NaN direction."""
    T = backend.types(precision)
    ks = prepare(edge_scene(), T)
    d, o, skip = edge_rays(ks, 5000, 5)
    rng = np.random.default_rng(6)
    off = rng.normal(size=o.shape)
    off *= rng.uniform(0.3, 1.0, (len(o), 1)) / np.linalg.norm(off, axis=1, keepdims=True)
    target = o + d
    o = o - off
    sp = ks.by_kind["sphere"]
    s = rng.integers(0, len(sp), len(o))
    corner = (np.array([c.q for c in sp])[s]
              + 0.9 * np.array([c.radius for c in sp])[s, None]
              * rng.choice([-1.0, 1.0], (len(o), 3)))
    plane = next(c.id for c in ks.consts if c.kind == "plane")
    kind = rng.integers(0, 5, len(o))
    o[kind == 4] = corner[kind == 4]
    skip = np.where(kind == 1, plane, np.where(kind == 2, -1, skip))
    skip[kind == 4] = np.array([c.id for c in sp])[s][kind == 4]
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[kind == 3, 0] = np.nan
    return d, o, skip


@pytest.mark.parametrize("precision", PRECISIONS)
def test03_other_rays_walk_the_bvh(precision, monkeypatch):
    d, o, skip = odd_rays(precision)
    assert differences(precision, monkeypatch, d, o, skip) == 0


def test04_without_the_walk_the_other_rays_differ(monkeypatch):
    """The fallback's walk turned off (its rays keep no hit): test03's rays lose hits."""
    d, o, skip = odd_rays("f32")
    walk = bvh.closest_kind

    def nothing(ks, kind, d, o, rules, skip, st, active=None):
        return st if active is not None else walk(ks, kind, d, o, rules, skip, st)
    monkeypatch.setattr(bvh, "closest_kind", nothing)
    assert differences("f32", monkeypatch, d, o, skip) > 500


def test05_a_ray_stops_only_beyond_its_closest_hit(monkeypatch):
    """With the stop's slack negative (rows up to 1.6% nearer than the closest hit count as
    beyond it), border rays lose their hits: the stop test is exercised."""
    monkeypatch.setattr(reflectbins, "KAPPA", -2.0 ** -7)
    assert differences("f32", monkeypatch) > 20


def surface_points(ks, ids, rng, k: int = 48) -> dict:
    """{id: (k, 3) points on the object}: a sphere's surface, a tile's corners and inside."""
    out = {}
    for c in ks.consts:
        if c.id not in ids:
            continue
        if c.kind == "sphere":
            u = rng.normal(size=(k, 3))
            out[c.id] = np.array(c.q) + c.radius * u / np.linalg.norm(u, axis=1, keepdims=True)
        else:
            P = planar_corners("fplane", [c])[0]
            f = rng.random((k, 2))
            f[:4] = [[0, 0], [1, 0], [0, 1], [1, 1]]
            out[c.id] = P[0] + f[:, :1] * (P[1] - P[0]) + f[:, 1:] * (P[2] - P[0])
    return out


@pytest.mark.parametrize("precision", PRECISIONS)
def test06_lists_sorted_bounded_and_without_their_source(precision, monkeypatch):
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types(precision)
    ks = prepare(edge_scene(), T)
    sources = [c for k in accel.BOUNDED for c in ks.by_kind.get(k, ())]
    sids = np.array([c.id for c in sources])
    pts = surface_points(ks, set(sids.tolist()), np.random.default_rng(7))
    for kind in ("fplane", "sphere"):
        rb = reflectbins.build(ks, kind)
        off = np.asarray(rb.offsets.numpy()).astype(np.int64)
        near = np.asarray(rb.near.numpy()).astype(np.float64)
        index = np.asarray(rb.index.numpy()).astype(np.int64)
        tids = np.array([c.id for c in ks.by_kind[kind]])
        cells = 6 * rb.side ** 2
        assert len(off) == len(sources) * cells + 1 and off[-1] == len(index)
        per = np.repeat(np.arange(len(sources) * cells), np.diff(off))
        src = per // cells
        # sorted within each list, no source lists itself
        same = per[1:] == per[:-1]
        assert (near[1:][same] >= near[:-1][same]).all()
        assert (tids[index] != sids[src]).all()
        # the bound is at most the distance between any point of the source and the row's
        # object (sampled)
        for s_, t_ in set(zip(sids[src].tolist(), tids[index].tolist())):
            gap = np.sqrt(((pts[s_][:, None] - pts[t_][None]) ** 2).sum(-1)).min()
            rows = (sids[src] == s_) & (tids[index] == t_)
            assert (near[rows] <= gap).all(), (s_, t_)
        # the lists are short against the kind's count (what the bins are for)
        assert 0 < rb.counts.mean() < 0.5 * len(tids)


def test07_too_many_pairs_keep_the_bvh(monkeypatch):
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types("f32")
    ks = prepare(edge_scene(), T)
    n = len(ks.by_kind["sphere"]) * sum(len(ks.by_kind[k]) for k in ("fplane", "sphere"))
    monkeypatch.setattr(reflectbins, "MAX_PAIRS", n - 1)
    assert reflectbins.build(ks, "sphere") is None
    monkeypatch.setattr(reflectbins, "MAX_PAIRS", n)
    assert reflectbins.build(ks, "sphere") is not None
    monkeypatch.setattr(reflectbins, "MAX_ROWS", 10)
    assert reflectbins.build(ks, "sphere") is None


# --- the light bins' cone (rt_core/lightbins.py) -------------------------------------------------

LIGHT = (0.3, 2.5, 1.0)             # relative to the viewpoint


def shadow_rays(ks, n: int, seed: int):
    """Shadow rays as the shading makes them, toward LIGHT, through border points of the
    objects (tile edges and corners, sphere outlines seen from the light), half of them
    moved 0.5-3% inside (toward the tile's centre, or the outline's): origins beyond those
    points, 1.05 to 3 times as far from the light.  (d, o, maxt) as numpy."""
    rng = np.random.default_rng(seed)
    p, ids, q, r, sp = _border_points(ks, rng, n)
    C = np.array(LIGHT)
    mid = {c.id: planar_corners("fplane", [c])[0].mean(0) for c in ks.by_kind["fplane"]}
    centre = np.array([mid.get(i, np.zeros(3)) for i in ids])
    # a third aimed at a sphere's outline seen from the light
    graze = rng.random(n) < 0.3
    s = rng.integers(0, len(sp), n)
    w = np.cross(q[s] - C, rng.normal(size=(n, 3)))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    p[graze] = (q[s] + r[s, None] * w)[graze]
    centre[graze] = q[s][graze]
    inset = np.where(rng.random(n) < 0.5, rng.uniform(0.005, 0.03, n), 0.0)
    tile = (np.array([i in mid for i in ids]) | graze)
    p = np.where(tile[:, None], p + inset[:, None] * (centre - p), p)
    o = C + rng.uniform(1.05, 3.0, (n, 1)) * (p - C)
    D = C - o
    maxt = np.linalg.norm(D, axis=1)
    return D / maxt[:, None], o, maxt


def shadow_differences(precision: str, monkeypatch, side: int = lightbins.SIDE) -> int:
    """Shadow rays whose verdict differs between the light bins (``side`` cells a face
    side) and the BVH."""
    from rt_core.tracer import occluded
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    monkeypatch.setattr(lightbins, "side_for", lambda rays: side)
    T = backend.types(precision)
    ks = prepare(edge_scene(), T)
    d, o, maxt = shadow_rays(ks, 60000, 8)
    A = T.Array3
    args = (A(*(T.Float(d[:, k]) for k in range(3))), A(*(T.Float(o[:, k]) for k in range(3))),
            T.Float(maxt), Rules())
    bins = occluded(ks, *args, toward=LIGHT)
    walk = occluded(ks, *args)
    dr.eval(bins, walk)
    a, b = np.asarray(bins.numpy()), np.asarray(walk.numpy())
    assert 0.5 < b.mean() < 0.995          # (through the borders: most are blocked)
    assert ks.__dict__["_accel"]["lightbins"]
    return int(np.count_nonzero(a != b))


SIDES = (lightbins.MIN_SIDE, lightbins.SIDE)     # the coarsest cells and the finest


@pytest.mark.parametrize("side", SIDES)
@pytest.mark.parametrize("precision", PRECISIONS)
def test08_light_bins_border_rays_match_the_bvh(precision, side, monkeypatch):
    assert shadow_differences(precision, monkeypatch, side) == 0


def test08b_cells_as_fine_as_the_rays_ask():
    """A light's bins get SIDE cells a face side for a 1920-column image (the bench's: as
    before), coarser ones for fewer rays, never below MIN_SIDE, and SIDE when the count is
    not known; a cell holds at most RAYS_PER_CELL rays where the side is below SIDE."""
    side_for = lightbins.side_for
    assert side_for(1920 * 1080) == side_for(None) == lightbins.SIDE
    assert side_for(1) == side_for(48 * 36) == lightbins.MIN_SIDE
    sides = [side_for(n) for n in (10 ** 3, 10 ** 4, 10 ** 5, 10 ** 6, 10 ** 7)]
    assert sides == sorted(sides) and len(set(sides)) > 2
    for n in (120000, 480000):
        s = side_for(n)
        assert lightbins.MIN_SIDE < s < lightbins.SIDE
        assert s * s * lightbins.RAYS_PER_CELL >= n > (s // 2) ** 2 * lightbins.RAYS_PER_CELL


@pytest.mark.parametrize("side", SIDES)
@pytest.mark.parametrize("precision", PRECISIONS)
def test09_without_the_cones_margin_light_bins_differ(precision, side, monkeypatch):
    """The cells' angular radius halved in the cone test: test08's rays lose blockers.
    (MARGIN is left alone: without it every shadow ray is 'long' and walks the BVH.)"""
    centres = lightbins.cell_centres

    def half(side):
        c, rad = centres(side)
        return c, 0.5 * rad
    monkeypatch.setattr(lightbins, "cell_centres", half)
    assert shadow_differences(precision, monkeypatch, side) > 0


# --- grazing tilted planes: t is rounding noise, and no row is stopped before ----------------------

def grazing_rays(T, n: int, seed: int, split: bool = False):
    """Two coplanar tiles A (the source) and B in a tilted plane, a sphere C between them,
    and rays leaving A toward B within ~1e-7 rad (f32; 1e-16 in f64) of the plane: B's t is
    then noise, often below C's (found by a second reader of rt_core/reflectbins.py).
    ``split``: four small tiles off the plane, three behind A and one beyond B, so that the
    BVH puts A and B in different leaves (and prunes B's by its box, unlike the plain
    loop)."""
    nrm = np.array([1.0, 2.0, 2.0]) / 3
    u1 = np.cross(nrm, [0, 0, 1.0])
    u1 /= np.linalg.norm(u1)
    u2 = np.cross(nrm, u1)
    P0 = np.array([-2.0, 0.5, -6.0])
    objs = [make_fplane(GREY, tuple(nrm), tuple(P0), tuple(u1), (1.0, 1.0)),
            make_fplane(GREY, tuple(nrm), tuple(P0 + 6 * u1), tuple(u1), (1.0, 1.0)),
            make_sphere(GREY, tuple(P0 + 3 * u1 + 0.5 * u2), 0.3)]
    if split:
        objs += [make_fplane(GREY, (0, 0, 1), tuple(P0 + x * u1 + 0.5 * nrm), (1, 0, 0),
                             (0.2, 0.2)) for x in (-2, -3, -4, 9)]
    scene = Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), tuple(objs), path="<grazing>")
    ks = prepare(scene, T)
    PA, PB = planar_corners("fplane", ks.by_kind["fplane"])[:2]
    rng = np.random.default_rng(seed)
    f, g = rng.random((n, 2)), rng.uniform(-0.5, 1.5, (n, 2))
    o = PA[0] + f[:, :1] * (PA[1] - PA[0]) + f[:, 1:] * (PA[2] - PA[0])
    d = PB[0] + g[:, :1] * (PB[1] - PB[0]) + g[:, 1:] * (PB[2] - PB[0]) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d += rng.normal(size=(n, 1)) * (3e-8 if T.precision == "f32" else 1e-16) * nrm
    return ks, d, o, np.full(n, ks.by_kind["fplane"][0].id)


def grazing_differences(precision: str, monkeypatch, split: bool = False) -> tuple:
    """(rays where the bins differ from the plain loop, where the BVH does)."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    ks, d, o, skip = grazing_rays(backend.types(precision), 100000, 0, split)
    (t0, i0), (t1, i1) = trace(ks, d, o, skip, False), trace(ks, d, o, skip, True)
    accel.configure(ks, bvh=False)
    (t2, i2) = trace(ks, d, o, skip, False)
    assert (i2 == ks.by_kind["fplane"][1].id).sum() > 100         # B is hit
    return tuple(int(np.count_nonzero((bits(t2) != bits(t)).any(-1) | (i2 != i)))
                 for t, i in ((t1, i1), (t0, i0)))


@pytest.mark.parametrize("precision", PRECISIONS)
def test10_grazing_a_tilted_plane_matches_the_plain_loop(precision, monkeypatch):
    """The bins give the plain loop's answers, where A and B share a BVH leaf (the BVH
    agrees too) and where they do not (the BVH prunes B's leaf by its box, its documented
    exception: it departs from the loop there, the bins do not)."""
    assert grazing_differences(precision, monkeypatch) == (0, 0)
    bins, walk = grazing_differences(precision, monkeypatch, split=True)
    assert bins == 0 and walk > 0


@pytest.mark.parametrize("precision", PRECISIONS)
def test11_without_the_grazing_rows_the_stop_skips_hits(precision, monkeypatch):
    monkeypatch.setattr(reflectbins, "PLANAR", ())
    assert grazing_differences(precision, monkeypatch)[0] > 0


# --- when the bins are built ----------------------------------------------------------------------

def test12_built_for_the_second_image_only(monkeypatch):
    """By default a KernelScene's first shaded image walks the BVH (the bins' build costs
    more than one image saves: rt_core/reflectbins.py), the second builds and uses them, and
    the two images are the same bit for bit."""
    from rt_core.camera import make_camera, primary_directions
    from rt_core.shading import shade
    from tests.test_bvh import crowd
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types("f32")
    scene = crowd(0)
    ks = prepare(scene, T)
    cam = make_camera(scene, 40)
    d = primary_directions(scene, cam, T)

    def image():
        rgb = shade(ks, d, Rules(), cam=cam).rgb
        return np.stack([np.asarray(c.numpy()) for c in (rgb.x, rgb.y, rgb.z)])
    accel.configure(ks, reflectbins=True)
    accel.configure(ks, reflectbins="auto")             # back to the default
    first = image()
    assert not ks.__dict__["_accel"].get("reflectbins")
    second = image()
    assert any(v is not None for v in ks.__dict__["_accel"]["reflectbins"].values())
    assert np.array_equal(bits(first), bits(second))


def test13_mostly_unstopped_kinds_keep_the_bvh(monkeypatch):
    """edge_scene's finite planes are walls of coplanar tiles: most of their rows lie in the
    grazing cells (bound 0), so by default they keep the BVH; its spheres are binned."""
    monkeypatch.undo()
    T = backend.types("f32")
    ks = prepare(edge_scene(), T)
    assert reflectbins.build(ks, "fplane") is None
    assert reflectbins.build(ks, "sphere") is not None
    monkeypatch.setattr(reflectbins, "MAX_UNSTOPPED", 1.0)
    rb = reflectbins.build(ks, "fplane")
    assert (np.asarray(rb.near.numpy()) == 0).mean() > 0.5
