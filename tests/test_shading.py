"""rt_core.shading: hand-computed pixels, the per-pixel float64 oracle, and what runs.

* hand-computed cases: ambient, diffuse c/d, shadow, back side, tile parity, reflection;
* every scene in scenes/*.txt against tests/shade_oracle.py in f32 and f64: 8-bit images
  identical except at pixels the oracle flags (a decision or an 8-bit level within reach of
  rounding), and those must be few;
* the passes a render runs, from Dr.Jit's kernel history: no lights, no shadow kernels; no
  specular, no reflection pass; geometry only, no shading; the same scene structure with other
  numbers compiles nothing new; the bounce cap is reported.
"""
from __future__ import annotations

import functools
import math
import os
import tempfile
from pathlib import Path

import drjit as dr
import numpy as np
import pytest

from rt_core import backend
from rt_core.camera import make_camera, primary_directions
from rt_core.exrio import write_exr
from rt_core.jitlog import KernelLog
from rt_core.parser import parse_scene, parse_text
from rt_core.render import render_image, to_images, trace_geometry
from rt_core.rules import Rules
from rt_core.scene import (Material, PointLight, Scene, make_plane, make_sphere,
                           make_tplane)
from rt_core.shading import DEFAULT_MAX_DIST, MAX_BOUNCES, quantize, shade
from rt_core.tracer import prepare
from tests import shade_oracle
from tests.tolerances import PRECISIONS, SHADED, U

REPO = Path(__file__).resolve().parents[1]
SCENES = sorted((REPO / "scenes").glob("*.txt"))
COLUMNS = 40


# The oracle's first-order bounds compound with every bounce: in shade_mirrors.txt at the
# default MAX_DIST (~90 bounces) they flag most of the corridor.  Its oracle run stops paths
# at 60 units (about 5 bounces), where the bound is still tight; the default MAX_DIST is
# checked against Mitsuba (test_secondary.py) and below.
ORACLE_MAX_DIST = {"shade_mirrors": 60.0}


def render(scene, columns, precision="f32", **kw):
    T = backend.types(precision)
    cam = make_camera(scene, columns, kw.pop("rows", None))
    images, res = render_image(scene, cam, T, kw.pop("rules", Rules()), geometry=False,
                               shade=True, **kw)
    return np.stack([images[c] for c in "RGB"], -1), res


def mat(amb=(0, 0, 0), dif=(0, 0, 0), spec=(0, 0, 0)):
    return Material(tuple(map(float, amb)), tuple(map(float, dif)), tuple(map(float, spec)))


# --- hand-computed pixels ---------------------------------------------------------------------
# Window 2 x 2, viewpoint (0, 0, 1), 3 x 3 pixels: the centre pixel's ray runs straight down
# -z and meets the plane z = -1 at H = (0, 0, -1), t = 2.

WALL = dict(normal=(0, 0, 1), point=(0, 0, -1))


def centre(scene, precision, **kw):
    rgb, res = render(scene, 3, precision, rows=3, **kw)
    return rgb[1, 1].astype(np.float64), res


@pytest.mark.parametrize("precision", PRECISIONS)
def test01_ambient_and_diffuse(precision):
    # light at the viewpoint: D = (0, 0, 2), d = 2, c = 1; I = (a + k·E·c/d) / t
    light = PointLight((1.0, 2.0, 4.0), (0.0, 0.0, 1.0))
    s = Scene((2.0, 2.0), (0.0, 0.0, 1.0), (light,),
              (make_plane(mat((0.25, 0.5, 1.0), (0.5, 0.25, 0.0)), **WALL),))
    I, res = centre(s, precision)
    want = np.array([(0.25 + 0.5 * 1 / 2) / 2, (0.5 + 0.25 * 2 / 2) / 2, 1.0 / 2])
    np.testing.assert_array_equal(I, want)             # all exact binary fractions
    assert res.bounces == 0
    # 1/d, not 1/d²: the light twice as far (D = (0, 0, 4)) halves the diffuse term
    far = Scene(s.window, s.viewpoint, (PointLight((1.0, 2.0, 4.0), (0.0, 0.0, 3.0)),),
                s.objects)
    I2, _ = centre(far, precision)
    np.testing.assert_array_equal(I2, [(0.25 + 0.5 / 4) / 2, (0.5 + 0.25 * 2 / 4) / 2, 0.5])


@pytest.mark.parametrize("precision", PRECISIONS)
def test02_shadow_and_back_side(precision):
    # light at (2, 0, 1): D = (2, 0, 2), d = 2√2, c = 1/√2; a ball centred on the shadow ray's
    # midpoint (1, 0, 0) blocks it (the view ray passes 1 unit from it)
    light = PointLight((4.0, 4.0, 4.0), (2.0, 0.0, 1.0))
    wall = make_plane(mat((0.5, 0.5, 0.5), (1.0, 1.0, 1.0)), **WALL)
    ball = make_sphere(mat((1, 1, 1)), (1.0, 0.0, 0.0), 0.3)
    lit = Scene((2.0, 2.0), (0.0, 0.0, 1.0), (light,), (wall,))
    I, _ = centre(lit, precision)
    c, d = 1 / math.sqrt(2), 2 * math.sqrt(2)
    tol = 4 * U[precision]
    np.testing.assert_allclose(I, (0.5 + 4 * c / d) / 2, rtol=tol)
    shadowed = Scene(lit.window, lit.viewpoint, (light,), (wall, ball))
    I, _ = centre(shadowed, precision)
    np.testing.assert_array_equal(I, [0.25, 0.25, 0.25])      # ambient / t only
    # the same wall with its normal pointing away: seen from the back, ambient only
    back = make_plane(mat((0.5, 0.5, 0.5), (1.0, 1.0, 1.0)), (0, 0, -1), (0, 0, -1))
    I, _ = centre(Scene(lit.window, lit.viewpoint, (light,), (back,)), precision)
    np.testing.assert_array_equal(I, [0.25, 0.25, 0.25])


@pytest.mark.parametrize("precision", PRECISIONS)
def test03_tile_parity(precision):
    # a tiled wall z = -1 facing the viewer, tiles 0.5 x 0.5 along x and y: the pixel at
    # window (x, y) sees lasthit (2x, 2y) (the wall is twice as far as the window)
    fg, bg = mat((1, 0, 0)), mat((0, 0, 1))
    tiles = make_tplane(fg, (0, 0, 1), (0, 0, -1), (1, 0, 0), (0.5, 0.5), bg)
    s = Scene((4.0, 4.0), (0.0, 0.0, 1.0), (), (tiles,))
    rgb, _ = render(s, 41, precision)
    x = np.linspace(-2, 2, 41)
    u, v = 2 * x[None, :], 2 * x[::-1, None]          # image row 0 is the top
    odd = (np.floor(10000 + u / 0.5) + np.floor(10000 + v / 0.5)) % 2 == 1
    inside = (np.abs(u / 0.5 - np.round(u / 0.5)) > 1e-3) & \
             (np.abs(v / 0.5 - np.round(v / 0.5)) > 1e-3)
    is_fg = rgb[..., 0] > 0
    assert np.array_equal(is_fg[inside], odd[inside])
    assert np.array_equal(rgb[..., 2] > 0, ~is_fg)
    assert inside.sum() > 1000 and odd[inside].any() and (~odd[inside]).any()


@pytest.mark.parametrize("precision", PRECISIONS)
def test04_reflection(precision):
    # a mirror wall reflects the centre ray back up +z into a ball behind the viewer (spheres
    # are not screen-clipped): I = a_wall/2 + s ⊙ a_ball/(2 + 1.5)
    mirror = make_plane(mat((0.25, 0.25, 0.25), spec=(0.5, 0.5, 0.5)), **WALL)
    ball = make_sphere(mat((0.5, 1.0, 0.25)), (0.0, 0.0, 3.0), 0.5)
    s = Scene((2.0, 2.0), (0.0, 0.0, 1.0), (), (mirror, ball))
    I, res = centre(s, precision)
    # the ball: the reflected ray from H = (0, 0, -1) meets it at z = 2.5, 3.5 from H
    u = U[precision]
    np.testing.assert_allclose(I, [0.125 + 0.25 / 5.5, 0.125 + 0.5 / 5.5, 0.125 + 0.125 / 5.5],
                               rtol=8 * u)
    assert res.bounces == 1
    # total_dist 2 >= MAX_DIST 2: no reflection
    I, res = centre(s, precision, max_dist=2.0)
    np.testing.assert_array_equal(I, [0.125] * 3)
    assert res.bounces == 0


# --- against the per-pixel oracle -------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def oracle_of(path: str):
    scene = parse_scene(path)
    md = ORACLE_MAX_DIST.get(Path(path).stem, DEFAULT_MAX_DIST)
    return scene, md, shade_oracle.render_shade_oracle(scene, COLUMNS, max_dist=md)


def write_evidence(stem, ours, orc, fl) -> list[str]:
    """EXR of ours, the oracle, |difference| and the flags; returns the path."""
    d = tempfile.mkdtemp(prefix=f"rtval-shade-{stem}-")
    ch = {}
    for i, c in enumerate("RGB"):
        ch[f"ours.{c}"] = ours[..., i]
        ch[f"oracle.{c}"] = orc["I"][..., i]
        ch[f"diff.{c}"] = np.abs(ours[..., i] - orc["I"][..., i])
    for k, v in fl.items():            # (a per-channel flag: one EXR channel each)
        v = np.asarray(v, np.float32)
        ch.update({f"flag.{k}": v} if v.ndim == 2 else
                  {f"flag.{k}.{c}": v[..., i] for i, c in enumerate("RGB")})
    path = os.path.join(d, f"{stem}.exr")
    write_exr(path, ch)
    return [path]


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test05_scene_against_oracle(path, precision):
    scene, md, orc = oracle_of(str(path))
    rgb, res = render(scene, COLUMNS, precision, max_dist=md)
    ours8, want8 = quantize(rgb), shade_oracle.quantize(orc["I"])
    fl = shade_oracle.flags(orc, precision)
    differs = np.any(ours8 != want8, -1)
    step = np.abs(ours8.astype(int) - want8.astype(int)).max(-1)
    err = np.abs(rgb.astype(np.float64) - orc["I"])
    over = np.any(err > shade_oracle.K_VALUE * shade_oracle.U[precision] * orc["err"], -1)
    bad = {"differs unflagged": differs & ~fl["any"],
           "quantization only, but more than one level": (step > 1) & ~fl["jump"],
           "intensity beyond its bound, no decision flagged": over & ~fl["jump"]}
    n = differs.size
    if any(m.any() for m in bad.values()) or fl["any"].sum() > SHADED[precision] * n:
        paths = write_evidence(f"{path.stem}-{precision}", rgb, orc, fl)
        lines = [f"{k}: {int(m.sum())} px, first at (row, col) {np.argwhere(m)[:3].tolist()}"
                 for k, m in bad.items() if m.any()]
        pytest.fail(f"{path.name} {precision}: " + "; ".join(lines)
                    + f"; flagged {int(fl['any'].sum())}/{n} (at most "
                    f"{SHADED[precision]:.1%}); evidence: {paths}")
    # the comparison compared something: lit, shadowed and (where the scene has it) reflected
    assert (want8 > 0).any()
    if any(o.material.specular != (0, 0, 0) for o in scene.objects):
        assert res.bounces >= 1 and (orc["bounces"] > 0).any()


def test05a_oracle_sphere_margins_as_written():
    """The oracle's sphere outline margins (_hit_margin) skip, by a plain-float test, the
    spheres behind the ray or beyond what decides it: the margins are those of the loop
    that computes every sphere in EF numbers first."""
    from mitsuba_ref.oracle import diff3, dot3, length3, scale3, trace, vec
    from mitsuba_ref.shade_oracle import _hit_margin, _margin, _sphere_inputs
    rng = np.random.default_rng(5)
    spheres = tuple(make_sphere(mat(amb=(0.2, 0.2, 0.2)), tuple(rng.uniform(-4, 4, 2)) +
                                (float(rng.uniform(-12, -3)),), float(rng.uniform(0.3, 1.5)))
                    for _ in range(12))
    scene = Scene((8.0, 6.0), (0.0, 0.0, 5.0), (), spheres)

    def literal(h, base, d, skip, tmax):
        m = min(h.edge_margin, h.clip_margin, h.tmin_margin, h.graze, h.tie_gap)
        tw = h.t if h.hit else math.inf
        for i, o in enumerate(scene.objects):
            if i == skip:
                continue
            c, r = _sphere_inputs(tuple(o.center), o.radius)
            q = diff3(c, base)
            along = dot3(q, d)
            if along.v + r.v < 0 or along.v - r.v > min(tw, tmax):
                continue
            p = length3(diff3(q, scale3(along, d)))
            m = min(m, _margin(p.v - r.v, p.e + r.e))
        return m

    misses = 0
    for k in range(300):
        # rays from the viewpoint towards the spheres (some graze their outlines), and from
        # points among them in every direction (spheres behind them)
        if k % 2:
            base = vec(scene.viewpoint)
            aim = spheres[k % 12].center
            d = vec(tuple(a - b + rng.normal(0, 0.3) for a, b in zip(aim, scene.viewpoint)))
        else:
            base = vec(tuple(rng.uniform(-4, 4, 2)) + (float(rng.uniform(-12, -3)),))
            d = vec(tuple(rng.normal(size=3)))
        skip = int(rng.integers(-1, 12))
        h = trace(scene, base, d, Rules(), skip)
        tmax = math.inf if k % 3 else float(rng.uniform(0.5, 10))
        got = _hit_margin(scene, h, base, d, skip, True, tmax)
        assert got == literal(h, base, d, skip, tmax), k
        misses += not h.hit
    assert 0 < misses < 300           # hits and misses both


# The kinds Mitsuba has no shape for (cones, ellipsoids, the torus): validate compares their
# geometry with the exact oracle and their shading (normals, shadows they cast, reflections)
# with this oracle in f64 (mode shaded-oracle); here in both precisions, every object
ORACLE_ONLY = [REPO / "tests" / "scenes" / "cones.txt", REPO / "scenes" / "torus.txt",
               *(REPO.parent / "shared" / "course-scenes" / p for p in (
                   "keyword/rm768__bowling.txt", "keyword/rm768__ellipsoid_bullets.txt",
                   "numeric/nw__cone-sphere.txt", "numeric/nw__conetest.txt"))]
# (nw__t's torus lies outside its window: only its plane is seen)


@functools.lru_cache(maxsize=None)
def _oracle_image(path):
    scene = parse_scene(str(path))
    return scene, shade_oracle.render_shade_oracle(scene, COLUMNS)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("path", ORACLE_ONLY, ids=[p.stem for p in ORACLE_ONLY])
def test05c_kinds_without_a_mitsuba_shape_against_oracle(path, precision):
    if not path.exists():
        pytest.skip(f"{path} is not here (../shared/course-scenes)")
    scene, orc = _oracle_image(path)
    rgb, _ = render(scene, COLUMNS, precision)
    ours8, want8 = quantize(rgb), shade_oracle.quantize(orc["I"])
    fl = shade_oracle.flags(orc, precision)
    bad = np.any(ours8 != want8, -1) & ~fl["any"]
    if bad.any():
        paths = write_evidence(f"{path.stem}-{precision}", rgb, orc, fl)
        pytest.fail(f"{path.name} {precision}: {int(bad.sum())} pixels differ unflagged, "
                    f"first at (row, col) {np.argwhere(bad)[:3].tolist()}; evidence: {paths}")
    # the comparison compared those kinds: pixels whose closest hit is one, lit or not
    T = backend.types(precision)
    cam = make_camera(scene, COLUMNS)
    g = to_images(trace_geometry(scene, cam, T), cam)         # (rows, columns), top row first
    hit = g["hit.mask"] > 0
    kinds = np.array([o.kind for o in scene.objects] + ["none"])
    on = hit & np.isin(kinds[np.where(hit, g["object.id"].astype(int), -1)],
                       ("cone", "ellipsoid", "torus"))
    assert on.sum() >= 4 and (want8[on] > 0).any()


@pytest.mark.slow
@pytest.mark.parametrize("precision", PRECISIONS)
def test05b_course_scenes_against_oracle(precision):
    # every supported course scene with at most 8 lights (the oracle is slow per light), at
    # 24 columns: no 8-bit difference outside the flags
    from tools.harness.validate import default_scene_paths, load_supported
    scenes, _ = load_supported(default_scene_paths(), explicit=False)
    for scene in (s for s in scenes if len(s.lights) <= 8):
        orc = shade_oracle.render_shade_oracle(scene, 24)
        rgb, _ = render(scene, 24, precision)
        fl = shade_oracle.flags(orc, precision)
        differs = np.any(quantize(rgb) != shade_oracle.quantize(orc["I"]), -1)
        assert not (differs & ~fl["any"]).any(), (scene.path, np.argwhere(differs & ~fl["any"]))


# --- what runs: passes and kernels ------------------------------------------------------------

def logged(scene, columns=32, precision="f32", shade_=True, **kw):
    T = backend.types(precision)
    cam = make_camera(scene, columns)
    with KernelLog() as log:
        _, res = render_image(scene, cam, T, geometry=True, shade=shade_, log=log, **kw)
    return log, res


def without_lights(scene):
    return Scene(scene.window, scene.viewpoint, (), scene.objects, scene.path)


def bounce_kernels(scene, precision="f32"):
    """The JIT kernels of each bounce of a render at 32 columns (kernel history records)."""
    T = backend.types(precision)
    cam = make_camera(scene, 32)
    out = []
    with KernelLog():
        class Log:
            def mark(self, *a):
                out.append([e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT])
        render_image(scene, cam, T, geometry=False, shade=True, log=Log())
    return out


def test06_one_kernel_per_bounce_no_lights_no_shadow_code():
    # Each bounce is one kernel: closest hit, surface, one shadow ray per light, shading and
    # the next rays, nothing in between going through memory.  (It used to be one pass per
    # light plus a hit and a shade pass, each evaluated: 2.5x slower at 1-16 objects, every
    # pass writing and re-reading the hit data; docs/speed.md.)  The reflection bounces
    # after it run in one kernel too (the tail), and a narrow one writes their sums to their
    # pixels (shading._scatter_sums)
    scene = parse_scene(REPO / "scenes" / "mixed.txt")
    log, res = logged(scene)
    assert res.bounces >= 1
    assert [(p.name, p.group) for p in log.passes] == \
        [("bounce", "primary"), ("tail", "reflection")]
    assert [p.kernels for p in log.passes] == [1, 2]
    # no lights: the same bounce without shadow code, a smaller kernel
    lit, dark = bounce_kernels(scene)[0], bounce_kernels(without_lights(scene))[0]
    assert len(lit) == len(dark) == 1
    assert dark[0]["hash"] != lit[0]["hash"]
    assert dark[0]["operation_count"] < lit[0]["operation_count"]


def test07_no_specular_no_reflection_pass():
    log, res = logged(parse_scene(REPO / "scenes" / "shade_shadows.txt"))
    assert "reflection" not in log.groups() and res.bounces == 0
    log, res = logged(parse_scene(REPO / "scenes" / "mixed.txt"), max_dist=0.0)
    assert "reflection" not in log.groups() and res.bounces == 0
    log, res = logged(parse_scene(REPO / "scenes" / "mixed.txt"))
    assert "reflection" in log.groups() and res.bounces >= 1


def test08_geometry_only_skips_shading():
    log, res = logged(parse_scene(REPO / "scenes" / "mixed.txt"), shade_=False)
    assert res is None
    assert [(p.name, p.group) for p in log.passes] == [("hit", "primary")]
    assert log.total().kernels == 1


def renumbered(text: str) -> str:
    """The same scene structure with other numbers (viewpoint, materials, lights, geometry).
    The window stays: its aspect sets the row count, which the camera kernel bakes in."""
    out, window = [], True
    for line in text.splitlines():
        head, _, rest = line.partition("#")
        toks = head.split()
        if len(toks) >= 2 and all(t.lstrip("-").replace(".", "").isdigit() for t in toks):
            if window:
                window = False
                out.append(head)
                continue
            # zero stays zero (no specular where there was none)
            toks = [repr(float(t) * 1.03 + (0.01 if i == 0 and float(t) else 0.0))
                    for i, t in enumerate(toks)]
        out.append(" ".join(toks))
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", ["mixed", "shade_tiles", "shade_mirrors", "sphere"])
def test09_other_numbers_compile_nothing(name, precision):
    text = (REPO / "scenes" / f"{name}.txt").read_text()
    a, b = parse_text(text, f"{name}.txt"), parse_text(renumbered(text), f"{name}-2.txt")
    assert a.kinds() == b.kinds() and len(a.lights) == len(b.lights)
    assert a.objects != b.objects and a.lights != b.lights
    logged(a, precision=precision)
    log, res = logged(b, precision=precision)
    tot = log.total()
    assert tot.kernels > 0 and tot.compiled == 0 and tot.disk == 0, \
        [(p.bounce, p.name, p.compiled, p.disk) for p in log.passes if p.compiled or p.disk]


def test10_wavefront_shrinks_and_kernels_repeat(monkeypatch):
    # (the compacted wavefront, as it runs the bounces validation records: renders run the
    # reflection bounces in one kernel, test_shade_speed.py test01c)
    from rt_core import shading
    monkeypatch.setattr(shading, "TAIL", False)
    log, res = logged(parse_scene(REPO / "scenes" / "shade_mirrors.txt"), columns=64)
    hits = [p for p in log.passes if p.name == "bounce"]
    assert len(hits) == res.bounces + 1 > 20
    # compaction: each bounce traces only the rays still going; deeper bounces reuse the
    # first reflection bounce's kernels (the bounce's, and the narrow one writing its sums
    # to their pixels)
    assert all(a.rays >= b.rays for a, b in zip(hits, hits[1:]))
    assert hits[1].rays < hits[0].rays
    assert len({h for p in hits[1:] for h in p.hashes}) == 2


def test11_bounce_cap_is_reported():
    scene = parse_scene(REPO / "scenes" / "shade_mirrors.txt")
    T = backend.types("f32")
    cam = make_camera(scene, 32)
    ks = prepare(scene, T)
    d = primary_directions(scene, cam, T)
    res = shade(ks, d, max_bounces=3)
    assert res.capped and res.bounces == 3 and res.left_active > 0
    full = shade(ks, d)
    assert not full.capped and 3 < full.bounces < MAX_BOUNCES
    # the deeper bounces add light: the capped image is nowhere brighter
    a, b = np.asarray(res.rgb.numpy()), np.asarray(full.rgb.numpy())
    assert np.all(a <= b) and np.any(a < b)


def test12_max_dist_bounds_the_path():
    scene = parse_scene(REPO / "scenes" / "shade_mirrors.txt")
    counts = [render(scene, 32, max_dist=m)[1].bounces for m in (0.0, 30.0, 100.0, 1000.0)]
    assert counts[0] == 0 and counts == sorted(counts) and counts[-1] > counts[-2]
    # the mirror walls are 9 apart: a path of k bounces is at least 9(k - 1) long
    assert counts[-1] <= 1000 / 9 + 1


def test13_material_tables_built_once_per_tile_rule(monkeypatch):
    """shade() builds a scene's material tables once per KernelScene and tile rule (the only
    rule they depend on), and the image is that of a fresh KernelScene under each rule."""
    from rt_core import shading
    # a tiled floor whose xdir leaves its plane (the tile rule then changes the tiles' width)
    red, blue = (Material((0.8, 0.1, 0.1), (1, 1, 1), (0, 0, 0)),
                 Material((0.1, 0.1, 0.8), (1, 1, 1), (0, 0, 0)))
    scene = Scene((8.0, 6.0), (0.0, 1.0, 6.0), (PointLight((2, 2, 2), (0.0, 4.0, 2.0)),),
                  (make_tplane(red, (0, 1, 0), (0, -1, 0), (1, 0.6, 0.2), (0.7, 0.7), blue),))
    T = backend.types("f32")
    cam = make_camera(scene, 24)
    d = primary_directions(scene, cam, T)
    built = []
    real = shading._build_material_tables
    monkeypatch.setattr(shading, "_build_material_tables",
                        lambda ks, rules: built.append(rules.tile_project) or real(ks, rules))
    ks = prepare(scene, T)
    rgb = lambda res: np.asarray(res.rgb.numpy())
    other = Rules(tile_project=False)
    images = [rgb(shade(ks, d, r)) for r in (Rules(), Rules(), other, other, Rules())]
    assert built == [True, False]
    fresh = [rgb(shade(prepare(scene, T), d, r)) for r in (Rules(), other)]
    assert np.array_equal(images[0], fresh[0]) and np.array_equal(images[2], fresh[1])
    assert np.array_equal(images[4], fresh[0])
    assert not np.array_equal(fresh[0], fresh[1]), "the tile rule changes this scene"


def test14_shade_oracle_follows_thousands_of_bounces():
    """The shading oracle's bounces run in a loop, not Python's recursion: a pixel of the
    mirror corridor under MAX_DIST 50000 bounces some 250 times, and one looking along the
    corridor thousands (recursing, it died at 1000, in `rtval check`'s cut-off inference);
    its intensity is still the recursion's, the fold running from the last bounce back."""
    from mitsuba_ref.shade_oracle import shade_pixels
    scene = parse_scene(REPO / "scenes" / "shade_mirrors.txt")
    W, H = 65, 48
    px = [2630, 19 * W]             # (row 19 looks up a little: no floor to end it)
    far = shade_pixels(scene, W, H, px, max_dist=50000.0)
    near = shade_pixels(scene, W, H, px, max_dist=1000.0)
    assert far["bounces"].max() > 1000 and (far["bounces"] > near["bounces"]).all()
    assert np.isfinite(far["I"]).all() and (far["I"] >= near["I"]).all()
    # 2630: the C course tracer's value (247 levels, printed to 17 digits)
    assert far["I"][0] * 255 == pytest.approx([0.80295325107786342, 0.72596709809387094,
                                               1.0119644941568138], rel=1e-12)
