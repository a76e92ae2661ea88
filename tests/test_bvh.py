"""The acceleration structures of secondary rays: the BVH (rt_core/bvh.py) and the light
bins of shadow rays (rt_core/lightbins.py).

* The shaded image and every recorded secondary ray (each bounce's hits: t, id, normal,
  position; each shadow ray's verdict) are bit-identical to the plain loop over every object
  (``accel.configure(bvh=False)``), in f32 and f64: on the bundled scenes, on a sample of
  ../shared/course-scenes, and on generated scenes with ties (duplicate objects), coplanar
  touching tiles, grazing mirror reflections, objects between the window and the viewpoint
  and behind it, and lights next to or inside objects.  Every scene traces with
  UNROLL_MAX = 0, so that each bounded kind goes through the structures.
* Rays aimed at the edges and corners of axis-aligned finite planes (flat boxes) and at
  sphere outlines: the BVH finds what the loop finds, and without its box widening it does
  not (so these rays do reach the boxes' borders).
* The builder: every object in exactly one leaf, each box holds its subtree, the skip
  links walk each octant's order depth-first.
"""
from __future__ import annotations

import dataclasses
import random
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from rt_core import accel, backend, bvh, lightbins, reflectbins
from rt_core.camera import make_camera, primary_directions
from rt_core.parser import parse_scene
from rt_core.rules import Rules
from rt_core.scene import (Material, PointLight, Scene, make_fplane, make_plane, make_sphere,
                           make_tplane)
from rt_core.shading import shade
from rt_core.tracer import closest_hit, occluded, prepare
from tests.scenegen import random_scene
from tools.harness.validate import COURSE_SCENES

REPO = Path(__file__).resolve().parents[1]
BUNDLED = sorted((REPO / "scenes").glob("*.txt"))
from tests.tolerances import PRECISIONS  # noqa: E402
MIRROR = Material((0.2, 0.2, 0.2), (1.0, 1.0, 1.0), (0.5, 0.5, 0.5))
GREY = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))


def bits(a) -> np.ndarray:
    a = np.ascontiguousarray(a)
    return a.view(np.uint8).reshape(a.shape + (-1,)) if a.dtype != bool else a


def shaded(scene, T, on: bool, columns: int, bins: bool = True):
    # (with the structures on, the reflection rays through their bins from the first image,
    # or the BVH walk, as a KernelScene's first image takes it: rt_core/reflectbins.py)
    ks = accel.configure(prepare(scene, T), bvh=on, reflectbins=on and bins)
    cam = make_camera(scene, columns)
    res = shade(ks, primary_directions(scene, cam, T), Rules(), cam=cam, record=3,
                max_bounces=6)
    return ks, res


def assert_identical(scene, precision, monkeypatch, columns=40):
    """The image and the records of the first three bounces, structures against the loop
    (reflection rays through the BVH, then through their bins); returns the accelerated
    KernelScene of the second (to see what it built)."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    monkeypatch.setattr(reflectbins, "MAX_UNSTOPPED", 1.0)     # every kind binned
    T = backend.types(precision)
    _, loop = shaded(scene, T, False, columns)
    for bins in (False, True):
        ks, fast = shaded(scene, T, True, columns, bins)
        name = f"{scene.path} {precision} {'reflection bins' if bins else 'BVH'}"
        for c in "xyz":
            a, b = (np.asarray(getattr(r.rgb, c).numpy()) for r in (loop, fast))
            assert np.array_equal(bits(a), bits(b)), f"{name}: image differs at " \
                f"{np.flatnonzero((bits(a) != bits(b)).any(-1))[:5]}"
        assert loop.bounces == fast.bounces and len(loop.records) == len(fast.records)
        for k, (ra, rb) in enumerate(zip(loop.records, fast.records)):
            assert ra.keys() == rb.keys()
            for key in ra:
                same = np.array_equal(bits(ra[key]), bits(rb[key]))
                assert same, f"{name}: bounce {k} {key} differs"
    return ks, fast


def used(ks) -> set:
    """What the accelerated KernelScene built: 'bvh' and/or 'lightbins'."""
    cache = ks.__dict__.get("_accel", {})
    return {k for k in ("bvh", "lightbins", "reflectbins") if cache.get(k)
            and any(v is not None for v in cache[k].values())}


# --- scenes -------------------------------------------------------------------------------------

def mirror_hall(seed: int) -> Scene:
    """A mirror floor of coplanar tiles that touch (a tie across every shared edge), seen
    from just above it (grazing reflections), spheres resting on it, duplicate objects,
    objects between the window and the viewpoint and behind the viewpoint, a small sphere
    next to a light (in the light's every cell) and a light inside a sphere."""
    rng = random.Random(seed)
    objs = []
    for i in range(-4, 4):
        for j in range(0, 6):
            objs.append(make_fplane(MIRROR, (0, 1, 0), (i, -1, -1.0 - j), (1, 0, 0), (1, 1)))
    for k in range(6):
        objs.append(make_sphere(MIRROR, (rng.uniform(-3, 3), -0.5, -rng.uniform(1.5, 6)), 0.5))
    objs += objs[3:5]                                       # exact duplicates: ties
    objs.append(make_fplane(MIRROR, (0.2, 0.1, 1), (-1, 0.2, 0.5), (1, 0, 0), (1.5, 1.0)))
    objs.append(make_sphere(GREY, (0.6, 0.3, 1.4), 0.3))   # between window and viewpoint
    objs.append(make_sphere(GREY, (0.0, 0.0, 4.0), 1.0))   # behind the viewpoint
    objs.append(make_sphere(GREY, (2.02, 1.5, -2.0), 0.01))     # next to light 0
    objs.append(make_sphere(GREY, (-3.0, 2.0, -8.0), 1.0))      # holds light 1
    objs.append(make_plane(GREY, (0, 0, 1), (0, 0, -12)))
    objs.append(make_tplane(MIRROR, (1, 0, 0.05), (-5, 0, 0), (0, 1, 0), (0.7, 0.7), GREY))
    rng.shuffle(objs)
    lights = (PointLight((4, 4, 4), (2.0, 1.5, -2.0)), PointLight((3, 3, 3), (-3.0, 2.2, -8.0)),
              PointLight((5, 5, 5), (0.5, 3.0, 2.0)))
    # the viewpoint just above the floor plane y = -1: the floor is hit at grazing angles
    return Scene((8.0, 6.0), (0.0, -0.97, 3.0), lights, tuple(objs), path=f"<hall {seed}>")


def crowd(seed: int) -> Scene:
    """A random scene of 60 objects (a third of the plane kinds copy an earlier plane: exact
    ties), every material a mirror, three lights."""
    base = random_scene(seed, n_objects=60, tie_prob=0.3)
    objs = tuple(dataclasses.replace(o, material=MIRROR) for o in base.objects)
    lights = base.lights + (PointLight((2, 2, 2), (0.0, 4.0, -3.0)),)
    return Scene(base.window, base.viewpoint, lights, objs, path=f"<crowd {seed}>")


def course_sample() -> list[Path]:
    """Every 16th course scene (by name), when ../shared/course-scenes is here."""
    paths = sorted(COURSE_SCENES.glob("*/*.txt")) if COURSE_SCENES.is_dir() else []
    return paths[::16]


# --- images and secondary rays: the structures against the loop ------------------------------

# the light bins' cells as fine as a small image's rays ask (lightbins.side_for), and as
# fine as a 1920-column image's: the same answers
SIDES = [None, lightbins.SIDE]


def cells(monkeypatch, side):
    if side is not None:
        monkeypatch.setattr(lightbins, "side_for", lambda rays: side)


@pytest.mark.parametrize("side", SIDES, ids=["rays", "finest"])
@pytest.mark.parametrize("precision", PRECISIONS)
def test01_bundled_scenes(precision, side, monkeypatch):
    cells(monkeypatch, side)
    built = set()
    for path in BUNDLED:
        ks, _ = assert_identical(parse_scene(path), precision, monkeypatch)
        built |= used(ks)
    assert built == {"bvh", "lightbins", "reflectbins"}


@pytest.mark.parametrize("precision", PRECISIONS)
def test02_course_scenes_sample(precision, monkeypatch):
    from tools.harness.validate import load_supported
    paths = course_sample()
    if not paths:
        pytest.skip("../shared/course-scenes is not here")
    scenes, _ = load_supported(paths, explicit=False)
    assert len(scenes) >= 6
    for scene in scenes:
        assert_identical(scene, precision, monkeypatch, columns=24)


@pytest.mark.parametrize("side", SIDES, ids=["rays", "finest"])
@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("make", [mirror_hall, crowd], ids=["hall", "crowd"])
def test03_generated_scenes(make, precision, side, monkeypatch):
    cells(monkeypatch, side)
    for seed in range(2):
        scene = make(seed)
        ks, res = assert_identical(scene, precision, monkeypatch, columns=48)
        assert used(ks) == {"bvh", "lightbins", "reflectbins"}
        built = ks.__dict__["_accel"]["lightbins"].values()
        assert {lb.side for lb in built} == {side or lightbins.MIN_SIDE}   # (48 columns)
        assert res.bounces >= 2 and len(res.records) == 3
        # the secondary rays hit things and the shadow rays are blocked, some of them
        hits = res.records[1]["hit"]
        assert 0.05 < hits.mean() < 0.99
        blocked = np.concatenate([r[k] for r in res.records for k in r
                                  if k.endswith(".blocked")])
        assert 0.02 < blocked.mean() < 0.98


@pytest.mark.parametrize("precision", PRECISIONS)
def test03b_light_cells_from_the_direction_too(precision, monkeypatch):
    """The light-bin cells found from −L (``CELL_BY_OFFSET`` off: the code before the
    offset H − C) against the plain loop as well, so both lookups stay checked."""
    monkeypatch.setattr(lightbins, "CELL_BY_OFFSET", False)
    ks, _ = assert_identical(crowd(0), precision, monkeypatch, columns=48)
    assert "lightbins" in used(ks)


def spheres_on_a_floor(n: int) -> Scene:
    """``n`` spheres in two rows above a floor plane, two lights above: their shadows fall
    on the floor and on each other."""
    objs = [make_sphere(MIRROR if k % 2 else GREY, (-2.5 + 1.3 * (k % 5), -0.4 + 0.5 * (k // 5),
                                                    -4.0 - 0.9 * (k // 5)), 0.55)
            for k in range(n)]
    objs.append(make_plane(GREY, (0, 1, 0), (0, -1, 0)))
    # (low lights to the sides: long shadows across the floor and onto the neighbours)
    lights = (PointLight((4, 4, 4), (6.0, 0.2, -4.5)), PointLight((3, 3, 3), (-5.0, 0.5, -3.0)))
    return Scene((8.0, 6.0), (0.0, 0.3, 4.0), lights, tuple(objs), path=f"<floor {n}>")


@pytest.mark.parametrize("precision", PRECISIONS)
def test03c_few_spheres_shadow_rays_go_through_the_light_bins(precision, monkeypatch):
    """From more than SHADOW_SPHERES · UNROLL_MAX spheres on (5 of 8), shadow rays search the
    spheres through the light bins while every other ray still unrolls them: the image and
    the shadow rays' records are the unrolled search's, bit for bit; at 4 spheres they
    unroll."""
    T = backend.types(precision)
    calls = []
    search = lightbins.occluded_kind
    monkeypatch.setattr(lightbins, "occluded_kind", lambda *a, **k: calls.append(a[1]) or
                        search(*a, **k))
    for n, binned in ((4, False), (7, True)):
        scene = spheres_on_a_floor(n)
        calls.clear()
        ks, res = shaded(scene, T, True, 48)
        assert bool(calls) == binned, n
        assert not accel.looped(ks, "sphere") and not accel.looped(ks, "sphere", True)
        blocked = np.concatenate([r[k] for r in res.records for k in r
                                  if k.endswith(".blocked")])
        assert blocked.sum() > 40, (n, blocked.sum())      # shadows to find
        with monkeypatch.context() as m:
            m.setattr(accel, "SHADOW_SPHERES", 1e9)         # unrolled
            calls.clear()
            _, res2 = shaded(scene, T, True, 48)
            assert not calls
        for c in "xyz":
            a, b = (np.asarray(getattr(r.rgb, c).numpy()) for r in (res, res2))
            assert np.array_equal(bits(a), bits(b)), (n, c)
        for ra, rb in zip(res.records, res2.records):
            for key in ra:
                assert np.array_equal(bits(ra[key]), bits(rb[key])), (n, key)


def test04_hall_has_grazing_reflections_and_duplicates(monkeypatch):
    """What mirror_hall is for: reflections off the floor within a few degrees of it, and
    duplicate objects (exact ties)."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types("f32")
    scene = mirror_hall(0)
    _, res = shaded(scene, T, True, 48)
    r1 = res.records[1]
    floor_y = np.abs(r1["dir"][:, 1])
    assert (floor_y[r1["hit"]] < 0.05).sum() > 20         # grazing: within ~3 degrees
    copies = {id(o) for o in scene.objects}
    assert len(copies) < len(scene.objects)                 # duplicates present


# --- rays at the boxes' borders ----------------------------------------------------------------

def border_scene() -> Scene:
    """Axis-aligned unit tiles touching in z = -6 (flat boxes), panels in x = const, and
    spheres: every border at an exactly representable coordinate."""
    objs = []
    for i in range(-3, 3):
        for j in range(-3, 3):
            objs.append(make_fplane(GREY, (0, 0, 1), (i, j, -6), (1, 0, 0), (1, 1)))
    for k in range(-3, 3):
        objs.append(make_fplane(GREY, (1, 0, 0), (k + 0.5, -3, -6), (0, 1, 0), (6, 6)))
        objs.append(make_sphere(GREY, (k + 0.5, 0.5, -9), 0.5))
    return Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), tuple(objs), path="<borders>")


def border_rays(scene, T, n: int, seed: int):
    """Rays from random origins aimed at points on the tiles' edges and corners."""
    rng = np.random.default_rng(seed)
    V = np.array(scene.viewpoint)
    o = rng.uniform(-4, 4, (n, 3)) + np.array([0, 0, -2]) - V
    i, j = rng.integers(-3, 4, n), rng.integers(-3, 4, n)
    f = rng.choice([0.0, 0.25, 0.5, 0.75], n)
    pick = rng.integers(0, 3, n)
    target = np.stack([np.where(pick == 0, i, i + f), np.where(pick == 1, j, j + f),
                       np.full(n, -6.0)], 1) - V
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = T.Array3
    return (A(*(d[:, k] for k in range(3))), A(*(o[:, k] for k in range(3))),
            T.Float(np.full(n, 50.0)))


def border_differences(precision: str, monkeypatch) -> list[int]:
    """Rays whose (t, id, blocked) differ between the BVH and the loop."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types(precision)
    scene = border_scene()
    d, o, maxt = border_rays(scene, T, 40000, 1)
    out = []
    for on in (False, True):
        ks = accel.configure(prepare(scene, T), bvh=on)
        t, oid, _ = closest_hit(ks, d, o, Rules())
        b = occluded(ks, d, o, maxt, Rules())
        dr.eval(t, oid, b)
        out.append([np.asarray(x.numpy()) for x in (t, oid, b)])
    assert (out[0][1] >= 0).mean() > 0.9
    return [int(np.count_nonzero(bits(x) != bits(y))) for x, y in zip(*out)]


@pytest.mark.parametrize("precision", PRECISIONS)
def test05_rays_through_borders(precision, monkeypatch):
    assert border_differences(precision, monkeypatch) == [0, 0, 0]


@pytest.mark.parametrize("precision", PRECISIONS)
def test06_without_the_widening_the_border_rays_differ(precision, monkeypatch):
    """The box widening (PAD) and pbrt's far-distance factor removed: the same rays lose
    hits, so test05's rays do probe the borders."""
    monkeypatch.setattr(bvh, "PAD", {"f32": 0.0, "f64": 0.0})
    init = bvh._Rays.__init__

    def exact_far(self, *a, **kw):
        init(self, *a, **kw)
        self.far = 1.0
    monkeypatch.setattr(bvh._Rays, "__init__", exact_far)
    assert sum(border_differences(precision, monkeypatch)) > 100


# --- the builder ---------------------------------------------------------------------------------

def random_boxes(n: int, seed: int):
    """Boxes of every shape: cubes, flat (axis-aligned finite planes), thin, duplicates."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-20, 20, (n, 3))
    e = rng.uniform(0.01, 3, (n, 3))
    e[rng.random(n) < 0.3, rng.integers(0, 3)] = 0.0        # flat
    lo, hi = c - e, c + e
    dup = rng.integers(0, n, n // 5)
    lo[: len(dup)], hi[: len(dup)] = lo[dup], hi[dup]        # exact duplicates
    return lo, hi


def walk(nodes):
    """The leaves reached by following one octant's rows depth-first: (first, count) in
    order, checking each inner node's skip link ends its subtree."""
    leaves = []

    def sub(k):
        lo, hi, a, b = nodes[k, :3], nodes[k, 3:6], int(nodes[k, 6]), int(nodes[k, 7])
        if b > 0:
            leaves.append((a, b))
            return k + 1
        nxt = k + 1
        for _ in range(2):                                   # two children
            clo, chi = nodes[nxt, :3], nodes[nxt, 3:6]
            assert (clo >= lo).all() and (chi <= hi).all(), "a box holds its children"
            nxt = sub(nxt)
        assert a == nxt, "the skip link is the node after the subtree"
        return nxt

    assert sub(0) == len(nodes)
    return leaves


@pytest.mark.parametrize("n", [1, 3, 4, 5, 17, 300])
def test07_builder_invariants(n):
    lo, hi = random_boxes(n, n)
    tree = bvh.build(lo, hi)
    assert sorted(tree.order.tolist()) == list(range(n)), "every object in exactly one leaf"
    assert tree.nodes.shape == (8, tree.count, bvh.NODE)
    orders = [walk(tree.nodes[octant]) for octant in range(8)]
    assert all(sorted(o) == sorted(orders[0]) for o in orders), "each octant: the same leaves"
    rows = sorted(orders[0])
    assert rows[0][0] == 0 and all(a + b == c for (a, b), (c, _) in zip(rows, rows[1:]))
    assert rows[-1][0] + rows[-1][1] == n, "the leaves' rows tile the table"
    for octant in range(8):
        for node in tree.nodes[octant]:
            a, b = int(node[6]), int(node[7])
            if b > 0:
                assert b <= bvh.LEAF_SIZE
                objs = tree.order[a:a + b]
                assert (lo[objs] >= node[:3]).all() and (hi[objs] <= node[3:6]).all()
    # a ray octant's first child is the near one along the split axis
    if n > bvh.LEAF_SIZE:
        root0, root7 = tree.nodes[0], tree.nodes[7]
        assert not np.array_equal(root0[1], root7[1])
    # f32 rows hold the float64 boxes (rounded outward)
    f = bvh.outward(tree.nodes, "f32")
    assert (f[..., :3] <= tree.nodes[..., :3]).all() and (f[..., 3:6] >= tree.nodes[..., 3:6]).all()


def test08_light_bins_list_nearest_first():
    """A cell's rows are ordered by their distance from the light (a shadow ray stops at the
    first row beyond its length), and the bound is below each object's true distance."""
    T = backend.types("f32")
    scene = crowd(0)
    ks = prepare(scene, T)
    centre = tuple(c - v for c, v in zip(scene.lights[0].center, scene.viewpoint))
    lb = lightbins.build(ks, "fplane", centre)
    near = np.asarray(lb.near.numpy())
    cells = np.asarray(lb.cells.numpy()).astype(np.int64).reshape(-1, 4)
    off = np.append(cells[:, 0], cells[-1, 1])
    rows = np.asarray(lb.rows.numpy()).reshape(len(near), -1)
    lo, hi = bvh.object_boxes("fplane", ks.by_kind["fplane"])
    ids = [c.id for c in ks.by_kind["fplane"]]
    C = np.array(centre, np.float32).astype(np.float64)
    true = np.sqrt(((np.clip(C, lo, hi) - C) ** 2).sum(1))
    pos = {oid: k for k, oid in enumerate(ids)}
    listed = [pos[int(i)] for i in rows[:, bvh.ROW["fplane"].index("id")]]
    assert (near <= true[listed]).all()
    assert off[-1] == len(near) and (np.diff(off) >= 0).all()
    assert (cells[:-1, 1] == cells[1:, 0]).all()
    # each cell names the object of its first row (the nearest to the light), or none
    first = np.where(cells[:, 0] < cells[:, 1], rows[np.minimum(cells[:, 0], len(near) - 1),
                                                     bvh.ROW["fplane"].index("id")], -1)
    assert (cells[:, 2].astype(np.uint32).view(np.int32) == first).all()
    for b in np.flatnonzero(np.diff(off) > 1):
        assert (np.diff(near[off[b]:off[b + 1]]) >= 0).all()


@pytest.mark.parametrize("ties", ["first", "last"])
@pytest.mark.parametrize("precision", PRECISIONS)
def test09_ties_across_leaves(ties, precision, monkeypatch):
    """Nine copies of a panel and of a sphere (more than a leaf holds, so in two leaves and
    more): every ray ties among the copies, and the tie rule's winner may be in the leaf
    walked second; the box pruning must still let the walk reach it."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 0)
    T = backend.types(precision)
    objs = [make_fplane(GREY, (0.1, 0.2, 1), (-2, -2, -5), (1, 0, 0), (4, 4))] * 9 + \
        [make_sphere(GREY, (0.5, 0.3, -3), 1.0)] * 9
    scene = Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), tuple(objs), path="<copies>")
    rng = np.random.default_rng(5)
    n = 4000
    o = rng.uniform(-3, 3, (n, 3)) + np.array([0, 0, 6.0]) - np.array(scene.viewpoint)
    target = rng.uniform(-1.5, 1.5, (n, 3)) * np.array([1, 1, 0]) + \
        np.array([0, 0, -4.0]) - np.array(scene.viewpoint)
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = T.Array3
    d, o = A(*(d[:, k] for k in range(3))), A(*(o[:, k] for k in range(3)))
    out = []
    for on in (False, True):
        ks = accel.configure(prepare(scene, T), bvh=on)
        t, oid, _ = closest_hit(ks, d, o, Rules(ties=ties))
        dr.eval(t, oid)
        out.append((np.asarray(t.numpy()), np.asarray(oid.numpy())))
    tree = bvh.trees(ks)
    assert all(len(b.tree.nodes[0]) > 1 for b in tree.values())      # several leaves
    ids = out[0][1]
    assert set(np.unique(ids)) == ({0, 9, -1} if ties == "first" else {8, 17, -1})
    assert np.array_equal(bits(out[0][0]), bits(out[1][0]))
    assert np.array_equal(ids, out[1][1])


def test10_shadow_rays_of_inactive_lanes_answer_false(monkeypatch):
    """occluded(active=...): the lanes that cast get the unmasked answer, the others False
    (loop, BVH and unrolled objects alike)."""
    T = backend.types("f32")
    scene = crowd(1)
    rng = np.random.default_rng(2)
    n = 3000
    o = rng.normal(0, 3, (n, 3)) + np.array([0, 0, -scene.viewpoint[2] - 4])
    d = rng.normal(0, 1, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    A = T.Array3
    d, o = A(*(d[:, k] for k in range(3))), A(*(o[:, k] for k in range(3)))
    maxt = T.Float(rng.uniform(0.5, 30, n))
    active = rng.random(n) < 0.5
    for unroll in (0, 10 ** 6):
        monkeypatch.setattr(accel, "UNROLL_MAX", unroll)
        ks = prepare(scene, T)
        full = np.asarray(occluded(ks, d, o, maxt, Rules()).numpy())
        part = np.asarray(occluded(ks, d, o, maxt, Rules(), None, T.Bool(active)).numpy())
        assert 0.2 < full.mean() < 0.9
        assert np.array_equal(part, full & active)
