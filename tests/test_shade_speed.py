"""What makes shaded images faster without changing them (docs/speed.md "Shaded images").

* One reflection bounce in the primary rays' kernel (rt_core/shading.py ``_one_bounce``,
  max_bounces = 1): the image, the bounce count and the cap are those of the compacted
  wavefront, bit for bit, in f32 and f64, on the bundled scenes with reflections and on a
  generated mirror scene.
* The bounding-sphere cull of the unrolled closest-hit search of reflection rays
  (rt_core/cull.py): the answers of rays grazing sphere outlines and aimed at finite-plane
  corners are those without the cull; without its widening they are not (so the rays do
  probe the bounding spheres' borders).
"""
from __future__ import annotations

from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from rt_core import accel, backend, bvh, cull, shading
from rt_core.camera import make_camera, primary_directions
from rt_core.parser import parse_scene
from rt_core.rules import Rules
from rt_core.scene import Material, PointLight, Scene, make_fplane, make_plane, make_sphere
from rt_core.shading import shade
from rt_core.tracer import closest_hit, prepare

REPO = Path(__file__).resolve().parents[1]
from tests.tolerances import PRECISIONS  # noqa: E402
MIRROR = Material((0.2, 0.2, 0.2), (1.0, 1.0, 1.0), (0.5, 0.5, 0.5))


def bits(a) -> np.ndarray:
    a = np.ascontiguousarray(a)
    return a.view(np.uint8).reshape(a.shape + (-1,)) if a.dtype != bool else a


def mirrors() -> Scene:
    """Mirror spheres and finite planes facing each other (reflections hit, some rays would
    go on past the one bounce), the spheres over a large mirror floor panel (reflection rays
    that hit it ahead of them while its centre lies behind), a matte floor, two lights."""
    objs = [make_sphere(MIRROR, (x, 0.0, -6.0 - abs(x)), 0.9) for x in (-2.0, 0.0, 2.0)]
    objs.append(make_fplane(MIRROR, (0, 1, 0), (-6.0, -0.95, -2.0), (1, 0, 0), (12.0, 12.0)))
    objs += [make_fplane(MIRROR, (0.3, 0, 1), (-3.5, -1.5, -9.0), (1, 0, -0.3), (7.0, 3.0)),
             make_fplane(MIRROR, (1, 0.1, 0.2), (-4.0, -1.0, -4.0), (0, 0, -1), (5.0, 2.5)),
             make_plane(Material((0.3, 0.3, 0.3), (1, 1, 1), (0, 0, 0)), (0, 1, 0),
                        (0, -1.2, 0))]
    lights = (PointLight((3, 3, 3), (1.0, 3.0, -2.0)), PointLight((2, 2, 2), (-3.0, 1.0, 0.0)))
    return Scene((8.0, 6.0), (0.0, 0.5, 4.0), lights, tuple(objs), path="<mirrors>")


def one_bounce(scene, precision, fused: bool, monkeypatch, columns=48):
    monkeypatch.setattr(shading, "FUSE_ONE_BOUNCE", fused)
    T = backend.types(precision)
    cam = make_camera(scene, columns)
    res = shade(prepare(scene, T), primary_directions(scene, cam, T), Rules(), cam=cam,
                max_bounces=1)
    rgb = np.stack([np.asarray(getattr(res.rgb, c).numpy()) for c in "xyz"], 1)
    return rgb, (res.bounces, res.capped, res.left_active)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("slots_in_if, sums_in_slots", [(True, True), (False, False)])
def test01_one_bounce_in_one_kernel_is_the_wavefront(precision, slots_in_if, sums_in_slots,
                                                      monkeypatch):
    """(The reflection hits' slots taken in a symbolic if, shading.SLOTS_IN_IF, or not;
    their pixels' values so far in the slots, shading.SUMS_IN_SLOTS, or read from the
    image.)"""
    monkeypatch.setattr(shading, "SLOTS_IN_IF", slots_in_if)
    monkeypatch.setattr(shading, "SUMS_IN_SLOTS", sums_in_slots)
    scenes = [parse_scene(REPO / "scenes" / f"{n}.txt")
              for n in ("mixed", "shade_mirrors", "shade_tiles")] + [mirrors()]
    capped = 0
    for scene in scenes:
        wave, wave_stats = one_bounce(scene, precision, False, monkeypatch)
        fused, fused_stats = one_bounce(scene, precision, True, monkeypatch)
        assert np.array_equal(bits(wave), bits(fused)), \
            f"{scene.path}: pixels {np.flatnonzero((bits(wave) != bits(fused)).any((1, 2)))[:5]}"
        assert fused_stats == wave_stats, scene.path
        assert wave_stats[0] == 1, f"{scene.path}: reflects"
        capped += wave_stats[1]
    assert capped >= 2                       # rays that would go on are counted too


@pytest.mark.parametrize("precision", PRECISIONS)
def test01b_one_bounce_through_the_reflection_bins_is_the_wavefront(precision, monkeypatch):
    """Scenes of many mirrors, whose reflection rays go through the reflection bins (from
    a prepared scene's second image on; the fused bounce finds their cells from the
    reflection before its normalization) or the BVH: the fused bounce's image is the
    wavefront's, bit for bit, and the bins were used."""
    from rt_core import reflectbins
    from tools.harness.bench_shaded import shaded_scene
    T = backend.types(precision)
    for kind in ("spheres", "fplanes", "mixed"):
        scene = shaded_scene(kind, 40)
        cam = make_camera(scene, 96)
        d = primary_directions(scene, cam, T)
        images = {}
        for fused in (False, True):
            monkeypatch.setattr(shading, "FUSE_ONE_BOUNCE", fused)
            ks = prepare(scene, T)
            for _ in range(reflectbins.AFTER_IMAGES):
                res = shade(ks, d, Rules(), cam=cam, max_bounces=1)
            images[fused] = np.stack([np.asarray(getattr(res.rgb, c).numpy())
                                      for c in "xyz"], 1)
            assert ks.__dict__["_accel"].get("reflectbins"), kind
        assert np.array_equal(bits(images[False]), bits(images[True])), kind


@pytest.mark.parametrize("sums_in_slots", [True, False])
def test02_one_bounce_shades_reflection_hits_densely(sums_in_slots, monkeypatch):
    """The fused bounce is two JIT kernels: the primary rays with their reflection rays'
    closest hits, then the shading of the reflection rays that hit, one lane each (the
    wavefront: two kernels over every reflection ray, and a compaction), which writes the
    sums to their pixels, their values so far read from the slots (shading.SUMS_IN_SLOTS;
    without, a third kernel, as narrow, writes the sums).  The image is never copied (a
    scatter into an array its own kernel gathers from would copy it whole:
    shading._scatter_sums)."""
    monkeypatch.setattr(shading, "SUMS_IN_SLOTS", sums_in_slots)
    scene = mirrors()
    T = backend.types("f32")
    cam = make_camera(scene, 32)
    ks = prepare(scene, T)
    d = primary_directions(scene, cam, T)
    dr.eval(d)
    sizes = {}
    for fused in (True, False):
        monkeypatch.setattr(shading, "FUSE_ONE_BOUNCE", fused)
        shade(ks, d, max_bounces=1)                 # compiled
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            dr.eval(shade(ks, d, max_bounces=1).rgb)
            hist = dr.kernel_history()
            sizes[fused] = [k["size"] for k in hist
                            if k["type"] == dr.KernelType.JIT and k["size"] > 1]
            copies = [k["size"] for k in hist if k["type"] == dr.KernelType.Memcpy]
            assert max(copies, default=0) < cam.columns * cam.rows, (fused, copies)
    # the reflection rays (primary hits on a specular object) and their closest hits,
    # traced apart
    from rt_core.tracer import surface
    t, oid, hit = closest_hit(ks, d)
    normal = surface(ks, d, t, oid, hit)[0]
    mirror = np.array([any(c != 0 for c in o.material.specular) for o in scene.objects])
    ids = oid.numpy()
    idx = np.flatnonzero(hit.numpy() & mirror[np.maximum(ids, 0)])
    k = T.UInt32(idx.astype(np.uint32).tolist())
    dd, tt, nn = (dr.gather(type(x), x, k) for x in (d, t, normal))
    R = dr.normalize(dr.fma(nn, -2 * dr.dot(dd, nn), dd))
    hits = int(np.count_nonzero(closest_hit(ks, R, dd * tt, Rules(),
                                            dr.gather(T.Int32, oid, k))[2].numpy()))
    assert 0 < hits < len(idx) < cam.columns * cam.rows
    assert sizes[True] == [cam.columns * cam.rows, hits] + ([] if sums_in_slots else [hits])
    assert sizes[False][0] == cam.columns * cam.rows and sizes[False][-1] == len(idx)


def full_render(scene, precision, tail: bool, monkeypatch, columns=48, log=None, **kw):
    monkeypatch.setattr(shading, "TAIL", tail)
    T = backend.types(precision)
    cam = make_camera(scene, columns)
    res = shade(prepare(scene, T), primary_directions(scene, cam, T), Rules(), cam=cam,
                log=log, **kw)
    rgb = np.stack([np.asarray(getattr(res.rgb, c).numpy()) for c in "xyz"], 1)
    return rgb, (res.bounces, res.capped, res.left_active)


def deep_mirrors() -> Scene:
    """Two facing mirror walls with a sphere between them, one NaN-free path bouncing
    hundreds of times, and the ``mirrors`` scene's objects."""
    wall = Material((0.05, 0.05, 0.05), (0.5, 0.5, 0.5), (0.9, 0.9, 0.9))
    base = mirrors()
    objs = base.objects + (make_plane(wall, (1, 0, 0), (-5.0, 0, 0)),
                           make_plane(wall, (-1, 0, 0), (5.0, 0, 0)),
                           make_sphere(MIRROR, (0.3, 1.5, -3.0), 0.6))
    return Scene(base.window, base.viewpoint, base.lights, objs, path="<deep mirrors>")


@pytest.mark.parametrize("precision", PRECISIONS)
def test01b_tail_in_one_kernel_is_the_wavefront(precision, monkeypatch):
    """The bounces after the first wavefront in one kernel (``_tail``): the image, the
    bounce count and the cap are the wavefront's, bit for bit, in scenes of a few bounces
    and of hundreds, with the cap reached or not."""
    scenes = [parse_scene(REPO / "scenes" / f"{n}.txt")
              for n in ("mixed", "shade_mirrors", "shade_tiles")] + [mirrors(), deep_mirrors()]
    deepest, capped = 0, set()
    for scene in scenes:
        for kw in ({}, {"max_bounces": 3}, {"max_dist": 40.0}):
            wave, wave_stats = full_render(scene, precision, False, monkeypatch, **kw)
            tail, tail_stats = full_render(scene, precision, True, monkeypatch, **kw)
            assert np.array_equal(bits(wave), bits(tail)), \
                f"{scene.path} {kw}: pixels " \
                f"{np.flatnonzero((bits(wave) != bits(tail)).any((1, 2)))[:5]}"
            assert tail_stats == wave_stats, (scene.path, kw)
            if wave_stats[1]:
                capped.add(scene.path)
            else:
                deepest = max(deepest, wave_stats[0])
    assert deepest > 50                      # hundreds of bounces in one kernel
    assert {"<deep mirrors>", str(REPO / "scenes" / "shade_mirrors.txt")} <= capped


@pytest.mark.parametrize("precision", PRECISIONS)
def test01d_tail_after_wavefronts_is_the_wavefront(precision, monkeypatch):
    """Many objects (reflection rays through the BVH): the first bounces of more than
    TAIL_FRACTION of the pixels stay wavefronts, the rest runs in one kernel; the image and
    the counts are the wavefront's, bit for bit."""
    from tools.harness.bench_shaded import shaded_scene
    scene = shaded_scene("mixed", 40)
    T = backend.types(precision)
    assert any(accel.looped(prepare(scene, T), k, True) for k in scene.kinds())
    from rt_core.jitlog import KernelLog
    monkeypatch.setattr(shading, "TAIL_FRACTION", 0.05)
    wave, wave_stats = full_render(scene, precision, False, monkeypatch, columns=96)
    with KernelLog() as log:
        tail, tail_stats = full_render(scene, precision, True, monkeypatch, columns=96,
                                       log=log)
    assert np.array_equal(bits(wave), bits(tail))
    assert tail_stats == wave_stats and wave_stats[0] >= 3
    # reflection wavefronts first, then the tail
    passes = [(p.name, p.group, p.bounce) for p in log.passes]
    assert passes[:2] == [("bounce", "primary", 0), ("bounce", "reflection", 1)], passes
    assert passes[-1][0] == "tail" and 1 < passes[-1][2] < wave_stats[0], passes


def test01c_tail_is_one_kernel(monkeypatch):
    """A render of a mirror corridor: one kernel for the primary rays, one for the first
    reflection wavefront's rays to their ends, and a narrow one that writes their sums to
    their pixels (the wavefront: two kernels a bounce)."""
    from rt_core.jitlog import KernelLog
    from rt_core.render import render_image
    scene = parse_scene(REPO / "scenes" / "shade_mirrors.txt")
    T = backend.types("f32")
    cam = make_camera(scene, 32)
    for tail in (True, False):
        monkeypatch.setattr(shading, "TAIL", tail)
        with KernelLog() as log:
            _, res = render_image(scene, cam, T, geometry=False, shade=True, log=log)
        bounces = [p for p in log.passes if p.name in ("bounce", "tail")]
        assert res.bounces > 20
        if tail:
            assert [(p.name, p.bounce) for p in bounces] == [("bounce", 0), ("tail", 1)]
            assert [p.kernels for p in bounces] == [1, 2]
        else:
            assert len(bounces) == res.bounces + 1


# --- the bounding-sphere cull ---------------------------------------------------------------

def cull_scene() -> Scene:
    """Unit tiles touching in z = -6, panels in x = const and spheres (few enough to unroll
    for reflection rays)."""
    grey = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))
    objs = [make_fplane(grey, (0, 0, 1), (i, j, -6), (1, 0, 0), (1, 1))
            for i in range(-1, 2) for j in range(-1, 1)]
    for k in range(-1, 2):
        objs.append(make_fplane(grey, (1, 0, 0), (k + 0.5, -2, -7), (0, 1, 0), (3, 3)))
        objs.append(make_sphere(grey, (k + 0.3, 0.5, -9), 0.5 + 0.2 * k))
    return Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), tuple(objs), path="<cull>")


def grazing_rays(scene, n: int, seed: int):
    """Rays from random origins (relative to the viewpoint) tangent to the spheres'
    outlines, or aimed at the tiles' corners and edges; each skips a random object."""
    rng = np.random.default_rng(seed)
    V = np.array(scene.viewpoint)
    o = rng.uniform(-3, 3, (n, 3)) + np.array([0, 0, -1.0]) - V
    spheres = [ob for ob in scene.objects if ob.kind == "sphere"]
    k = rng.integers(0, len(spheres), n)
    C = np.array([spheres[i].center for i in k]) - V
    r = np.array([spheres[i].radius for i in k])
    a = C - o
    dist = np.linalg.norm(a, axis=1, keepdims=True)
    a /= dist
    u = np.cross(a, rng.normal(size=(n, 3)))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    sin = r[:, None] / dist
    tangent = np.sqrt(1 - sin ** 2) * a + sin * u
    i, j = rng.integers(-1, 3, n), rng.integers(-1, 2, n)
    f = rng.choice([0.0, 0.5], n)
    corner = np.stack([i + f * (rng.random(n) < 0.5), j.astype(float), np.full(n, -6.0)],
                      1) - V - o
    corner /= np.linalg.norm(corner, axis=1, keepdims=True)
    d = np.where((rng.random(n) < 0.5)[:, None], tangent, corner)
    skip = rng.integers(-1, len(scene.objects), n)
    return d, o, skip


def cull_differences(precision: str, monkeypatch) -> int:
    """Rays whose (t, id) differ with the cull and without."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 100)
    T = backend.types(precision)
    scene = cull_scene()
    d, o, skip = grazing_rays(scene, 40000, 1)
    A = T.Array3
    d, o = A(*(d[:, k] for k in range(3))), A(*(o[:, k] for k in range(3)))
    skip = T.Int32(skip.astype(np.int32))
    out = []
    for on in (False, True):
        ks = cull.configure(prepare(scene, T), on)
        t, oid, _ = closest_hit(ks, d, o, Rules(), skip)
        dr.eval(t, oid)
        out.append([np.asarray(x.numpy()) for x in (t, oid)])
    assert (out[0][1] >= 0).mean() > 0.5
    return sum(int(np.count_nonzero(bits(x) != bits(y))) for x, y in zip(*out))


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("const", [True, False])
def test03_cull_keeps_grazing_hits(precision, const, monkeypatch):
    """With the widening a constant of each object (cull.CONST_E) and a term of each ray."""
    monkeypatch.setattr(cull, "CONST_E", const)
    assert cull_differences(precision, monkeypatch) == 0


def test03d_cull_keeps_a_ray_of_subnormal_length():
    """A reviewer's ray: from the viewpoint, |d|² subnormal in float32 (a ray of one lane,
    whose arithmetic keeps subnormals), aimed at a sphere.  The culls leave rays with |d|²
    outside cull.A_RANGE alone: it hits as without them (the per-ray form lost it)."""
    grey = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))
    scene = Scene((8.0, 6.0), (0.0, 0.0, 4.0), (), (make_sphere(grey, (0.3, 0.5, -9), 0.5),
                                                   make_sphere(grey, (3, 3, -9), 0.5)), "<x>")
    T = backend.types("f32")
    got = []
    for on in (False, True):
        ks = cull.configure(prepare(scene, T), on)
        O = T.Array3(*[T.Float([0.0])] * 3)
        D = T.Array3(*[T.Float([x]) for x in (3e-24, 5.49e-24, -9e-23)])
        t, oid, _ = closest_hit(ks, D, O, Rules(), T.Int32([1]))
        got.append((float(t.numpy()[0]), int(oid.numpy()[0])))
    assert got[0][1] == 0 and got[1] == got[0]


@pytest.mark.parametrize("const", [True, False])
def test04_without_the_widening_grazing_hits_are_lost(const, monkeypatch):
    monkeypatch.setattr(cull, "CONST_E", const)
    monkeypatch.setattr(cull, "GROW", 0.0)
    monkeypatch.setattr(cull, "SLACK", 0.0)
    monkeypatch.setattr(bvh, "PAD", {"f32": 0.0, "f64": 0.0})
    assert cull_differences("f32", monkeypatch) > 50


@pytest.mark.parametrize("precision", PRECISIONS)
def test05_cull_keeps_images(precision, monkeypatch):
    """Shaded with every object unrolled, cull on and off: the same image."""
    monkeypatch.setattr(accel, "UNROLL_MAX", 100)
    T = backend.types(precision)
    for scene in (mirrors(), parse_scene(REPO / "scenes" / "shade_mirrors.txt")):
        cam = make_camera(scene, 40)
        d = primary_directions(scene, cam, T)
        imgs = []
        for on in (False, True):
            ks = cull.configure(prepare(scene, T), on)
            res = shade(ks, d, Rules(), cam=cam, max_bounces=6)
            imgs.append(np.stack([np.asarray(getattr(res.rgb, c).numpy()) for c in "xyz"]))
        assert res.bounces >= 2
        assert np.array_equal(bits(imgs[0]), bits(imgs[1])), scene.path


# --- long shadow rays: light bins hand them to the BVH --------------------------------------

@pytest.mark.parametrize("wall", ["plane", "fplane"])
def test06_long_shadow_rays_take_the_bvh(wall, monkeypatch):
    """Spheres next to a light cast shadows on a far wall: those shadow rays are longer
    than the light bins' dmax, so they walk the BVH (inside a symbolic if that packets
    without one skip); the image and every shadow verdict are the plain loop's, and some
    of those long rays are blocked.  The wall an infinite plane or a finite one (every
    object bounded, but not within the spheres' bins' reach: lightbins.within_reach)."""
    from rt_core import lightbins
    from tests.test_bvh import assert_identical
    grey = Material((0.1, 0.1, 0.1), (1, 1, 1), (0, 0, 0))
    objs = tuple(make_sphere(grey, (x, y, -5.6), 0.25) for x in (-0.4, 0.4) for y in (-0.4, 0.4))
    objs += (make_plane(grey, (0, 0, 1), (0, 0, -300)) if wall == "plane" else
             make_fplane(grey, (0, 0, 1), (-900, -900, -300), (1, 0, 0), (1800, 1800)),)
    centre = (0.0, 0.0, -5.0)
    scene = Scene((8.0, 6.0), (0.0, 0.0, 4.0), (PointLight((9, 9, 9), centre),), objs,
                  path="<long shadows>")
    ks, res = assert_identical(scene, "f32", monkeypatch, columns=64)
    rel = tuple(c - v for c, v in zip(centre, scene.viewpoint))
    dmax = lightbins.light_bins(ks, "sphere", rel).dmax
    r = res.records[0]
    long_ = r["L0.cast"] & (r["L0.dist"] > dmax)
    assert long_.sum() > 100 and (long_ & r["L0.blocked"]).sum() > 20
    assert not lightbins.within_reach(ks, rel, dmax)


def test06b_no_walk_where_every_point_is_within_reach(monkeypatch):
    """Bounded objects only, every one within the light bins' reach of each light: no BVH
    walk is traced for long shadow rays (there are none: the kernels' code has no
    ``lightbins_sphere_far``, which it has with ``NO_FAR`` off), and the image and every
    shadow verdict are the plain loop's."""
    from rt_core import lightbins
    from tests.test_bvh import assert_identical
    from tools.harness.bench_shaded import shaded_scene
    scene = shaded_scene("spheres", 12)
    ks, _ = assert_identical(scene, "f32", monkeypatch, columns=64)
    for light in scene.lights:
        rel = tuple(c - v for c, v in zip(light.center, scene.viewpoint))
        assert lightbins.within_reach(ks, rel, lightbins.light_bins(ks, "sphere", rel).dmax)
    T = backend.types("f32")
    cam = make_camera(scene, 64)
    d = primary_directions(scene, cam, T)
    for no_far in (True, False):
        monkeypatch.setattr(lightbins, "NO_FAR", no_far)
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            dr.kernel_history()
            dr.eval(shade(ks, d, cam=cam, max_bounces=1).rgb)
            code = [k["ir"].read() for k in dr.kernel_history()
                    if k["type"] == dr.KernelType.JIT]
        assert any("lightbins_sphere" in c for c in code)
        assert any("lightbins_sphere_far" in c for c in code) != no_far
