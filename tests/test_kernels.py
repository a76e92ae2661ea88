"""What the tracer's kernels hold, and the many-object path (rt_core/accel.py).

* The loop path (a kind with more than accel.UNROLL_MAX objects: one symbolic loop, screen-space
  bins for rays from the viewpoint) gives bit-identical t and ids to the unrolled code, for
  camera rays, for secondary rays with ``skip`` and for the shadow test, under every rule
  variant, in f32 and f64, also on objects placed to defeat the culling (behind the viewpoint,
  straddling its plane, edge-on, around the window's border).
* A scene's kernel holds code only for the object kinds present, and only the passes asked for.
* Scene numbers are data: scenes that differ only in numbers (and, on the loop path, in object
  counts) reuse the compiled kernels — Dr.Jit's kernel history shows 0 compilations.
"""
from __future__ import annotations

import random

import drjit as dr
import numpy as np
import pytest

from rt_core import accel, backend, tracer
from rt_core.camera import make_camera, primary_directions
from rt_core.jitlog import KernelLog
from rt_core.render import render_geometry
from rt_core.rules import Rules
from rt_core.planar import make_disk
from rt_core.scene import Material, Scene, make_fplane, make_plane, make_sphere, make_tplane
from rt_core.tracer import closest_hit, occluded, prepare
from tests.scenegen import random_scene

from tests.tolerances import PRECISIONS  # noqa: E402
GREY = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))
UNROLLED = 10 ** 6          # accel.UNROLL_MAX that unrolls every object
BRANCH_MIN = dict(tracer.BRANCH_MIN)    # (as imported: tests monkeypatch the module's)
LOOPED = 0                  # ... that loops over every kind


def types(precision):
    try:
        return backend.types(precision, "llvm")
    except backend.BackendError as err:
        pytest.skip(f"llvm backend unavailable: {err}")


def bits(a) -> np.ndarray:
    """The bit patterns of a Dr.Jit or numpy array (exact comparison, NaN-safe)."""
    a = np.asarray(a.numpy() if hasattr(a, "numpy") else a)
    return a.view(np.uint32 if a.dtype == np.float32 else np.uint64 if a.dtype == np.float64
                  else a.dtype)


def hits(scene, T, unroll_max, monkeypatch, d=None, o=None, skip=None, rules=Rules(),
         columns=96, sampling="corners", maxt=None):
    """(t, id) of closest_hit, plus the shadow mask when ``maxt`` is given, as numpy."""
    monkeypatch.setattr(accel, "UNROLL_MAX", unroll_max)
    ks = prepare(scene, T)
    if d is None:
        d = primary_directions(scene, make_camera(scene, columns, None, sampling), T)
    t, oid, _ = closest_hit(ks, d, o, rules, skip)
    out = [t, oid]
    if maxt is not None:
        out.append(occluded(ks, d, o, maxt, rules, skip))
    dr.eval(*out)
    return [bits(x) for x in out]


def assert_same(a, b, what):
    for x, y, name in zip(a, b, ("t", "id", "blocked")):
        bad = np.flatnonzero(x != y)
        assert len(bad) == 0, (f"{what}: {name} differs at {len(bad)} rays, first {bad[0]}: "
                               f"looped {x[bad[0]]} unrolled {y[bad[0]]}")


# --- scenes ---------------------------------------------------------------------------------

def adversarial_scene(seed: int) -> Scene:
    """A random scene plus objects placed where culling by projection could go wrong: behind
    the viewpoint, straddling its z plane, containing it, edge-on to it, across the window's
    border, tiny and far, and exact copies (ties)."""
    base = random_scene(seed, n_objects=24, tie_prob=0.3)
    rng = random.Random(seed)
    vx, vy, vz = base.viewpoint
    extra = [
        make_fplane(GREY, (0, 0, 1), (vx - 1, vy - 1, vz + 2), (1, 0, 0), (2, 2)),      # behind
        make_fplane(GREY, (1, 0, 0.1), (vx + 1, vy - 2, vz - 3), (0, 1, 0), (4, 6)),  # straddles
        make_sphere(GREY, (vx, vy + 0.5, vz), 1.5),                                   # contains V
        make_sphere(GREY, (vx + 3, vy, vz + 1), 1.5),                                 # straddles
        make_sphere(GREY, (vx, vy, vz + 5), 1.0),                                     # behind
        # edge-on: the viewpoint lies in the panel's plane; and one nearly so
        make_fplane(GREY, (1, 0, 0), (vx, -2, -1), (0, 0, -1), (6, 4)),
        make_fplane(GREY, (1, 1e-7, 0), (vx + 1e-6, -2, -1), (0, 0, -1), (6, 4)),
        # across the window border and far off to the side
        make_fplane(GREY, (0, 0, 1), (3.5, 2.5, -2), (1, 0, 0), (3, 3)),
        make_sphere(GREY, (-40, 0, -10), 3.0),
        make_sphere(GREY, (0.5, 0.25, -5000), 0.01),                                  # tiny, far
        make_plane(GREY, (0, 1, 0.2), (0, -3, 0)),
        make_tplane(GREY, (0.1, 1, 0), (0, -2.5, 0), (1, 0, 0), (0.5, 0.7), GREY),
    ]
    objs = list(base.objects) + extra
    rng.shuffle(objs)
    objs += objs[:3]                                        # exact duplicates: ties
    return Scene(base.window, base.viewpoint, base.lights, tuple(objs), path=f"<adv {seed}>")


def secondary_rays(scene, T, n, seed):
    """Random origins (relative to the viewpoint) near the objects, unit directions, and a
    skip id per ray (-1 for none)."""
    rng = np.random.default_rng(seed)
    o = rng.normal(0, 3, (n, 3)) + np.array([0, 0, -scene.viewpoint[2] - 4])
    d = rng.normal(0, 1, (n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    skip = rng.integers(-1, len(scene.objects), n)
    A = T.Array3
    return (A(*(d[:, i] for i in range(3))), A(*(o[:, i] for i in range(3))),
            T.Int32(skip.astype(np.int32)), T.Float(rng.uniform(0.5, 30, n)))


# --- loops vs unrolled ----------------------------------------------------------------------

@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("seed", range(4))
def test01_camera_rays_loop_equals_unrolled(seed, precision, monkeypatch):
    scene = adversarial_scene(seed)
    T = types(precision)
    sampling = "corners" if seed % 2 == 0 else "centers"
    a = hits(scene, T, LOOPED, monkeypatch, sampling=sampling)
    b = hits(scene, T, UNROLLED, monkeypatch, sampling=sampling)
    assert_same(a, b, f"adversarial {seed} {precision}")
    assert (a[1] >= 0).mean() > 0.3, "the scene should cover a good part of the image"


@pytest.mark.parametrize("seed", range(4))
def test01c_certified_camera_rays_loop_equals_unrolled(seed):
    """float64 with exact decisions, whose unrolled spheres and finite planes branch on cone
    tests (certified: shapes.sphere_cone_cert, plane_cone) and whose camera rays unroll
    up to CAMERA_FACTOR × UNROLL_MAX objects: on the adversarial scenes (a sphere holding
    the viewpoint, edge-on and nearly edge-on finite planes, ties), unrolled with the
    branches and looped without them give the same t and ids bit for bit, and decide the
    same rays exactly."""
    scene = adversarial_scene(seed)
    T = types("f64")
    cam = make_camera(scene, 96, None, "corners" if seed % 2 == 0 else "centers")
    d = primary_directions(scene, cam, T)
    out = []
    for unroll in (LOOPED, UNROLLED):
        ks = accel.configure(prepare(scene, T), unroll)
        t, oid, _ = closest_hit(ks, d, cam=cam)
        out.append((bits(t), bits(oid), ks.decided))
    assert out[0][2] == out[1][2]
    assert_same(out[0][:2], out[1][:2], f"certified adversarial {seed}")
    assert (out[0][1] >= 0).mean() > 0.3


@pytest.mark.parametrize("precision", PRECISIONS)
def test01b_a_kind_no_camera_ray_can_hit(precision, monkeypatch):
    """The viewpoint inside the only sphere (and a second scene: on its surface): no camera
    ray hits it (accel.never_hit), so its bins list no row.  The loop over the kind is left
    out; it used to gather from the empty table and fail as the kernel was traced
    (RuntimeError from dr.while_loop, float64 renders of 9 bounded objects)."""
    T = types(precision)
    for centre, r in (((0, 0, 4), 1.0), ((0, 0, 6), 2.0)):
        panels = [make_fplane(GREY, (0, 0, 1), (x, y, -4), (1, 0, 0), (1, 1))
                  for x, y in [(-3, 0), (-2, 0), (-1, 0), (0, 0), (1, 0), (2, 0), (3, 0),
                               (0, 2)]]
        scene = Scene((8, 6), (0, 0, 4), (), (make_sphere(GREY, centre, r), *panels),
                      path="<inside>")
        a = hits(scene, T, LOOPED, monkeypatch, columns=17)
        b = hits(scene, T, UNROLLED, monkeypatch, columns=17)
        assert_same(a, b, f"viewpoint in a sphere {precision}")
        assert ((a[1] >= 1) | (a[1] == -1)).all() and (a[1] >= 1).any()
        # the renders, certified in float64: looped as unrolled
        ids = []
        for unroll in (LOOPED, UNROLLED):
            monkeypatch.setattr(accel, "UNROLL_MAX", unroll)
            ids.append(render_geometry(scene, 17, None, precision)["object.id"])
        assert np.array_equal(*ids), precision


@pytest.mark.parametrize("precision", PRECISIONS)
def test02_secondary_rays_loop_equals_unrolled(precision, monkeypatch):
    scene = adversarial_scene(7)
    T = types(precision)
    d, o, skip, maxt = secondary_rays(scene, T, 20000, 7)
    a = hits(scene, T, LOOPED, monkeypatch, d=d, o=o, skip=skip, maxt=maxt)
    b = hits(scene, T, UNROLLED, monkeypatch, d=d, o=o, skip=skip, maxt=maxt)
    assert_same(a, b, f"secondary rays {precision}")
    assert 0.05 < (a[1] >= 0).mean() and 0.05 < a[2].mean() < 0.95


RULES = {"ties-last": Rules(ties="last"), "edges-open": Rules(edges="open"),
         "t_min": Rules(t_min=1e-4), "clip>=": Rules(screen_clip=">="),
         "clip-off": Rules(screen_clip="off"), "clip_spheres": Rules(clip_spheres=True)}


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("name", list(RULES))
def test03_rule_variants_loop_equals_unrolled(name, precision, monkeypatch):
    scene = adversarial_scene(11)
    T = types(precision)
    rules = RULES[name]
    a = hits(scene, T, LOOPED, monkeypatch, rules=rules, columns=64)
    b = hits(scene, T, UNROLLED, monkeypatch, rules=rules, columns=64)
    assert_same(a, b, f"{name} camera {precision}")
    d, o, skip, maxt = secondary_rays(scene, T, 4000, 11)
    a = hits(scene, T, LOOPED, monkeypatch, d=d, o=o, skip=skip, maxt=maxt, rules=rules)
    b = hits(scene, T, UNROLLED, monkeypatch, d=d, o=o, skip=skip, maxt=maxt, rules=rules)
    assert_same(a, b, f"{name} secondary {precision}")


def test04_mixed_loop_and_unrolled_kinds(monkeypatch):
    """A looped kind next to unrolled ones (the default threshold): ties across kinds still go
    by id."""
    T = types("f32")
    objs = [make_fplane(GREY, (0, 0, 1), (-4 + 0.5 * i, -3, -2 - 0.1 * i), (1, 0, 0), (1, 5))
            for i in range(12)]
    objs.insert(3, make_plane(GREY, (0, 0, 1), (0, 0, -2.3)))         # ties with fplane 3
    objs.append(make_sphere(GREY, (0, 0, -4), 1.0))
    scene = Scene((8.0, 6.0), (0.0, 0.0, 3.0), (), tuple(objs))
    # (float32 camera rays loop over the 13 bounded objects above CAMERA_FACTOR × 6)
    monkeypatch.setattr(accel, "UNROLL_MAX", 6)
    ks = prepare(scene, T)
    assert accel.looped(ks, "fplane", camera=True) and not accel.looped(ks, "plane", camera=True)
    for ties in ("first", "last"):
        a = hits(scene, T, 6, monkeypatch, rules=Rules(ties=ties))
        b = hits(scene, T, UNROLLED, monkeypatch, rules=Rules(ties=ties))
        assert_same(a, b, f"ties={ties}")


def test05_bins_are_conservative_where_objects_project(monkeypatch):
    """Every object that some camera ray hits is listed in that ray's bin."""
    monkeypatch.setattr(accel, "UNROLL_MAX", LOOPED)
    T = types("f32")
    scene = adversarial_scene(3)
    cam = make_camera(scene, 200)
    d = primary_directions(scene, cam, T)
    ks = prepare(scene, T)
    grid, tabs = accel.binned(ks, cam.size)
    b = accel.ray_bins(ks, grid, d).numpy()
    t, oid, hit = closest_hit(ks, d)
    oid = oid.numpy()
    assert (b < grid.nbins).mean() > 0.99, "almost every camera ray falls in a grid bin"
    listed = {}
    for kind, tab in tabs.items():
        start, end = tab.offsets.numpy().reshape(-1, 4)[:, :2].T
        rows = tab.rows.numpy().reshape(-1, accel.stride(kind))
        idcol = accel.LAYOUT[kind].index("id")
        for k in range(grid.nbins + 1):
            listed.setdefault(k, set()).update(rows[start[k]:end[k], idcol].astype(int))
    hit = np.flatnonzero(oid >= 0)
    assert len(hit) > 0.3 * len(oid)
    missing = [i for i in hit if oid[i] not in listed[b[i]]]
    assert not missing, f"{len(missing)} rays hit an object their bin does not list"


# --- what the kernels hold ----------------------------------------------------------------------

def jit_launches(fn):
    """Run fn with Dr.Jit's kernel history on; its JIT kernel launches."""
    with KernelLog():
        fn()
        return [e for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT]


def hit_kernel(scene, T, exact: bool = True):
    """The one kernel of closest_hit (t, id) on evaluated camera directions (``exact``:
    float64's exact decisions, as the KernelScene says; the call itself certifies nothing)."""
    d = primary_directions(scene, make_camera(scene, 64), T)
    dr.eval(d)
    ks = prepare(scene, T)
    ks.exact_decisions = exact

    def run():
        t, oid, _ = closest_hit(ks, d)
        dr.eval(t, oid)
    (k,) = jit_launches(run)
    return k


def spheres(n, seed=0):
    rng = random.Random(seed)
    return [make_sphere(GREY, (rng.uniform(-3, 3), rng.uniform(-2, 2), rng.uniform(-9, -3)),
                        rng.uniform(0.3, 1.5)) for _ in range(n)]


def fplanes(n, seed=0):
    rng = random.Random(seed)
    return [make_fplane(GREY, (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 1),
                        (rng.uniform(-4, 2), rng.uniform(-3, 1), rng.uniform(-9, -2)),
                        (1, rng.uniform(-0.5, 0.5), 0), (rng.uniform(0.5, 3), rng.uniform(0.5, 3)))
            for _ in range(n)]


def scene_of(objs, seed=0):
    rng = random.Random(seed)
    vp = (rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(3, 6))
    return Scene((8.0, 6.0), vp, (), tuple(objs))


@pytest.mark.parametrize("counts", [(3, 0), (20, 0)], ids=["unrolled", "looped"])
def test06_kernel_holds_only_the_kinds_present(counts):
    """A sphere-only scene compiles sphere code only: its kernel is not the one of a scene with
    a finite plane added, and has fewer operations; a plane-only kernel has no square root
    (the sphere test's) — the IR shows it."""
    T = types("f32")
    n, _ = counts
    only = hit_kernel(scene_of(spheres(n)), T)
    same = hit_kernel(scene_of(spheres(n, seed=5), seed=5), T)
    more = hit_kernel(scene_of(spheres(n) + fplanes(1 if n < 8 else 12)), T)
    assert same["hash"] == only["hash"]
    assert more["hash"] != only["hash"]
    assert only["operation_count"] < more["operation_count"]
    planes = hit_kernel(scene_of(fplanes(n)), T)
    assert "sqrt" not in planes["ir"].getvalue()
    assert "sqrt" in only["ir"].getvalue()


def test07_only_the_passes_asked_for():
    """The geometry render is one kernel; the closest hit alone (t, id: what a preliminary
    intersection returns) is a smaller one."""
    T = types("f32")
    scene = scene_of(spheres(2) + fplanes(2))
    full = jit_launches(lambda: render_geometry(scene, 64))
    assert len(full) == 1
    prelim = hit_kernel(scene, T)
    assert prelim["operation_count"] < full[0]["operation_count"]


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("layout", ["unrolled", "looped"])
def test08_scenes_differing_in_numbers_reuse_kernels(layout, precision):
    """Ten scenes with the same kinds (and, unrolled, the same counts) but other numbers: after
    the first, 0 kernels compiled (every launch found in the in-memory cache).  On the loop
    path the object counts differ too."""
    types(precision)
    scenes = []
    for i in range(10):
        if layout == "unrolled":
            objs = spheres(2, i) + fplanes(3, i) + [make_plane(GREY, (0, 1, 0.1 * i), (0, -3, 0))]
        else:
            objs = spheres(9 + i, i) + fplanes(12 + 2 * i, i) + \
                [make_plane(GREY, (0, 1, 0.1 * i), (0, -3, 0))]
        scenes.append(scene_of(objs, i))
    with KernelLog() as log:
        for i, scene in enumerate(scenes):
            render_geometry(scene, 48, precision=precision)
            log.mark(f"scene {i}", "primary", 0, 48 * scene.default_rows(48))
    first, rest = log.passes[0], log.passes[1:]
    assert first.kernels >= 1
    assert all(p.kernels == first.kernels for p in rest)
    assert sum(p.compiled + p.disk for p in rest) == 0, [(p.compiled, p.disk) for p in rest]
    assert len({h for p in log.passes for h in p.hashes}) == first.kernels


@pytest.mark.parametrize("precision", PRECISIONS)
def test09_looped_rows_and_bins_are_packet_gathers(precision):
    """A looped kind reads each table row, and each ray its bin's (start, end), with packet
    gathers (one vector load per lane, Dr.Jit's gather_NxT functions): no scalar
    llvm.masked.gather, which LLVM's znver3 target scalarizes into 8 branches
    (docs/speed.md).  Dr.Jit falls back to scalar gathers from a table at an unaligned address, so
    this also checks accel.device_array's alignment."""
    T = types(precision)
    ir = hit_kernel(scene_of(spheres(12) + fplanes(12)), T)["ir"].getvalue()
    assert "call fastcc" in ir and "@gather_" in ir
    assert "llvm.masked.gather" not in ir


@pytest.mark.parametrize("precision", PRECISIONS)
def test10_unrolled_spheres_branch_past_certain_misses(precision, monkeypatch):
    """Unrolled sphere tests of camera rays sit behind a packet-wide branch (tracer.closest_hit
    on shapes.sphere_cone), one per sphere, from tracer.BRANCH_MIN spheres on (float32 4,
    float64 1); a looped sphere kind has none (its bins' rays mostly hit).  That the branch
    drops no hit is test01's and test11b's."""
    T = types(precision)
    n = tracer.BRANCH_MIN[("sphere", precision)]
    assert n == (4 if precision == "f32" else 1)
    ir = hit_kernel(scene_of(spheres(n)), T)["ir"].getvalue()
    assert ir.count("Symbolic conditional: sphere_object") == n
    if n > 1:
        ir = hit_kernel(scene_of(spheres(n - 1) + fplanes(1)), T)["ir"].getvalue()
        assert "sphere_object" not in ir
    monkeypatch.setattr(accel, "UNROLL_MAX", LOOPED)
    ir = hit_kernel(scene_of(spheres(n)), T)["ir"].getvalue()
    assert "sphere_object" not in ir and "closest_sphere" in ir


def certified_kernel(scene):
    """The IR of float64's certified closest-hit kernel on camera directions."""
    T = types("f64")
    d = primary_directions(scene, make_camera(scene, 64), T)
    dr.eval(d)
    ks = prepare(scene, T)

    def run():
        t, oid, _ = closest_hit(ks, d, cam="rays")
        dr.eval(t, oid)
    return max(jit_launches(run), key=lambda k: k["size"])["ir"].getvalue()


def test10d_camera_rays_branch_on_balls():
    """Each unrolled finite plane of camera rays sits behind its branch on its bounding
    ball (shapes.plane_cone) from BRANCH_MIN bounded objects of any kind on, certified
    float64 or not; certified float64's spheres each behind theirs from one sphere on
    (shapes.sphere_cone_cert).  That the branches change no answer is test11c's, test11d's
    and test01's."""
    n = tracer.BRANCH_MIN[("fplane", "f64")]
    assert n == tracer.BRANCH_MIN[("fplane", "f32")] == 4
    ir = certified_kernel(scene_of(spheres(1)))
    assert ir.count("Symbolic conditional: sphere_object") == 1
    ir = certified_kernel(scene_of(fplanes(n - 2) + spheres(2)))
    assert ir.count("Symbolic conditional: fplane_object") == n - 2
    assert ir.count("Symbolic conditional: sphere_object") == 2
    assert "fplane_object" not in certified_kernel(scene_of(fplanes(n - 1)))
    for precision in ("f32", "f64"):
        T = types(precision)
        ir = hit_kernel(scene_of(fplanes(n)), T, exact=False)["ir"].getvalue()
        assert ir.count("Symbolic conditional: fplane_object") == n
        ir = hit_kernel(scene_of(fplanes(n - 1)), T, exact=False)["ir"].getvalue()
        assert "fplane_object" not in ir


@pytest.mark.parametrize("precision,exact", [("f32", True), ("f64", True), ("f64", False)])
def test10b_float32_camera_rays_unroll_more(precision, exact):
    """float32 camera rays, and float64's with exact decisions (with at most
    CAMERA_SPHERES_F64 spheres), unroll up to CAMERA_FACTOR × UNROLL_MAX bounded objects,
    each sphere behind its branch; float64 without exact decisions loops above UNROLL_MAX.
    (That both give the same hits is test01's and test01c's.)  float64 with exact decisions:
    the certified kernel."""
    T = types(precision)

    def kernel(objs):
        if precision == "f64" and exact:
            return certified_kernel(scene_of(objs))
        return hit_kernel(scene_of(objs), T, exact)["ir"].getvalue()
    n = int(accel.UNROLL_MAX * accel.camera_factor(T.backend))
    for objs in (spheres(n), spheres(n // 2) + fplanes(n - n // 2)):
        ir = kernel(objs)
        many = len([o for o in objs if o.kind == "sphere"]) > accel.CAMERA_SPHERES_F64
        if not exact or (precision == "f64" and many):
            assert "closest_sphere" in ir and "sphere_object" not in ir
        else:
            assert "closest_" not in ir
            assert ir.count("Symbolic conditional: sphere_object") == len(
                [o for o in objs if o.kind == "sphere"])
    ir = kernel(spheres(n + 1))
    assert "closest_sphere" in ir and "sphere_object" not in ir
    ir = kernel(spheres(accel.UNROLL_MAX))
    assert "closest_sphere" not in ir
    # another bounded kind among them (not measured unrolled): the loop above UNROLL_MAX
    disk = make_disk(GREY, (0, 0, -6), 1.0, (0, 0, 1))
    ir = kernel(spheres(accel.UNROLL_MAX) + [disk])
    assert "closest_sphere" in ir and "closest_disk" in ir


def test10e_the_camera_unroll_limit_follows_the_backend_not_the_host(monkeypatch):
    """The LLVM backend's camera rays unroll up to 16 bounded objects on a CPU with AVX-512
    and 12 without (measured on each); CUDA's limit is its own, whatever the host's CPU
    (it followed the host's vectors)."""
    from types import SimpleNamespace
    for flags in ("fpu sse avx2 fma", "fpu sse avx2 fma avx512f avx512dq"):
        monkeypatch.setattr(accel, "host_cpu", lambda flags=flags: {"flags": flags})
        for name in ("llvm", "cuda"):
            T = SimpleNamespace(backend=name, precision="f32")
            unrolled = [n for n in range(1, 40) if not accel.looped(
                SimpleNamespace(T=T, by_kind={"sphere": [None] * n}), "sphere", camera=True)]
            assert unrolled == list(range(1, max(unrolled) + 1))
            want = {"llvm": 16 if "avx512f" in flags else 12, "cuda": 16}[name]
            assert max(unrolled) == want, (name, flags)


def test10f_host_cpu_reads_the_first_processor(tmp_path, monkeypatch):
    """backend.host_cpu: the first processor's block of /proc/cpuinfo (bench's machine and
    accel.wide_vectors both read it)."""
    import builtins
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: CPU A\nflags\t\t: fpu avx2\n\n"
                    "processor\t: 1\nmodel name\t: CPU B\nflags\t\t: fpu avx512f\n")
    real = builtins.open
    monkeypatch.setattr(builtins, "open", lambda path, *a, **k: real(
        info if path == "/proc/cpuinfo" else path, *a, **k))
    backend.host_cpu.cache_clear()
    try:
        got = backend.host_cpu()
        assert got["model name"] == "CPU A" and got["flags"] == "fpu avx2"
        assert not accel.wide_vectors()
        info.unlink()
        backend.host_cpu.cache_clear()
        assert backend.host_cpu() == {} and not accel.wide_vectors()
    finally:
        monkeypatch.undo()
        backend.host_cpu.cache_clear()


def test10c_shadow_rays_from_the_viewpoint_loop_without_bins(monkeypatch):
    """Shadow rays from the viewpoint loop over a kind that camera rays unroll (float32, 10
    spheres beside 9 looped planes, whose bins list only the planes): the kind's whole
    table, with the unrolled code's answers."""
    T = types("f32")
    objs = spheres(10) + [make_plane(GREY, (0.1 * i, 1, 0), (0, -3 - 0.1 * i, 0))
                          for i in range(9)]
    scene = scene_of(objs)
    ks = prepare(scene, T)
    assert accel.looped(ks, "sphere") and not accel.looped(ks, "sphere", camera=True)
    assert accel.looped(ks, "plane", camera=True)
    d = primary_directions(scene, make_camera(scene, 64), T)
    maxt = T.Float(np.linspace(1, 12, dr.width(d)))
    got = occluded(ks, d, None, maxt)
    monkeypatch.setattr(accel, "UNROLL_MAX", UNROLLED)
    want = occluded(prepare(scene, T), d, None, maxt)
    assert np.array_equal(bits(got), bits(want)) and 0 < bits(got).mean() < 1


@pytest.mark.parametrize("branch", ["cone", "live"])
def test11_certified_cull_keeps_unsure_rays(branch, monkeypatch):
    """float64 with exact decisions: rays within a few ulps of a sphere's outline are unsure
    (flagged, then decided exactly); the unrolled test's branch must not take them for
    certain misses: its cone test (shapes.sphere_cone_cert), or sphere_live's where there
    is no cone (``live``: sphere_cone_cert made to give none).  Unrolled and looped without
    bins (the same per-sphere bounds, no branch) flag the same rays and give the same
    answers."""
    from rt_core import shapes
    if branch == "live":
        monkeypatch.setattr(tracer, "sphere_cone_cert", lambda *a: None)
    assert shapes.sphere_cone_cert is not None
    T = types("f64")
    sphere = make_sphere(GREY, (0.3, -0.2, -5.0), 1.3)
    # and spheres away from these rays
    others = tuple(make_sphere(GREY, (4.0 * k, 30.0, -5.0), 1.0)
                   for k in range(tracer.SPHERE_BRANCH_MIN - 1))
    scene = Scene((8.0, 6.0), (0.0, 0.0, 10.0), (), (sphere,) + others)
    q = np.array(sphere.center) - np.array(scene.viewpoint)
    L = np.linalg.norm(q)
    u = q / L
    e1 = np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    alpha = np.arcsin(sphere.radius / L) * (1 + np.arange(-40, 41)[:, None] * 2.0 ** -44)
    phi = np.linspace(0, 2 * np.pi, 50)[None]
    d = (np.cos(alpha)[..., None] * u + np.sin(alpha)[..., None] *
         (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)).reshape(-1, 3)
    D = T.Array3(*(T.Float(c) for c in d.T))
    out = {}
    for name, unroll in (("unrolled", UNROLLED), ("looped", LOOPED)):
        ks = accel.configure(prepare(scene, T), unroll, bins=False)
        t, oid, _ = closest_hit(ks, D, cam="rays")
        out[name] = (bits(t), bits(oid), ks.decided)
    assert out["looped"][2] > 100, "the outline's rays are unsure"
    assert out["unrolled"][2] == out["looped"][2]
    assert_same(out["unrolled"][:2], out["looped"][:2], "tangent rays")


@pytest.mark.parametrize("precision", PRECISIONS)
def test11b_cone_cull_drops_no_hit(precision, monkeypatch):
    """Without certification the unrolled camera-ray spheres branch on shapes.sphere_cone
    (one dot product against the cone of directions that hold the sphere).  Rays probing
    each sphere's outline, from 2⁻⁴⁰ to 2⁻² of its angular radius inside and outside, for
    spheres 2, 8, 40, 3000 and 10⁵ radii away (where |q|²/r² makes the cone's rounding
    margin matter): the answers with the branch are those without it, bit for bit, and the probes
    straddle the outline (hits and misses on every sphere)."""
    from rt_core import shapes
    T = types(precision)
    V = np.array([0.0, 0.0, 10.0])
    # (directions 45° or more apart: no sphere hides another's outline)
    spheres_ = [make_sphere(GREY, tuple(V + np.array(c) / np.linalg.norm(c) * 12.0), 12.0 / k)
                for c, k in (((0.7, 0.0, -0.714), 2), ((-0.5, 0.3, -0.81), 8),
                             ((0.0, 0.5, -0.866), 40), ((-0.2, -0.4, -0.894), 3000),
                             ((0.3, -0.6, -0.74), 100000))]
    scene = Scene((8.0, 6.0), tuple(V), (), tuple(spheres_))
    rays = []
    for sp in spheres_:
        q = np.array(sp.center) - V
        L = np.linalg.norm(q)
        u = q / L
        e1 = np.cross(u, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        s = 2.0 ** -np.arange(2, 41)
        alpha = np.arcsin(sp.radius / L) * (1 + np.r_[-s, 0.0, s])[:, None]
        phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)[None]
        rays.append((np.cos(alpha)[..., None] * u + np.sin(alpha)[..., None] *
                     (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2))
                    .reshape(-1, 3))
    d = np.concatenate(rays)
    D = T.Array3(*(T.Float(c) for c in d.T))
    ks = accel.configure(prepare(scene, T), UNROLLED)
    with_cone = closest_hit(ks, D)
    assert all(shapes.cone_k(sp.q, sp.radius, precision) is not None for sp in ks.consts)
    monkeypatch.setattr(tracer, "BRANCH_MIN", {})
    plain = closest_hit(accel.configure(prepare(scene, T), UNROLLED), D)
    assert_same(tuple(bits(x) for x in with_cone[:2]), tuple(bits(x) for x in plain[:2]),
                "outline probes")
    ids = plain[1].numpy().reshape(len(spheres_), -1)
    for k in range(len(spheres_)):
        assert (ids[k] == k).any() and (ids[k] != k).any(), f"sphere {k}: probes straddle"


def outline_probes(centre, radius, scales, turns=24):
    """Unit directions from the viewpoint (the origin here) at (1 ± s) times the angular
    radius of the ball (``centre``, ``radius``) from its centre's direction, for each s of
    ``scales`` and 0, ``turns`` around."""
    q = np.asarray(centre, np.float64)
    L = np.linalg.norm(q)
    u = q / L
    e1 = np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    alpha = np.arcsin(radius / L) * (1 + np.r_[-scales, 0.0, scales])[:, None]
    phi = np.linspace(0, 2 * np.pi, turns, endpoint=False)[None]
    return (np.cos(alpha)[..., None] * u + np.sin(alpha)[..., None] *
            (np.cos(phi)[..., None] * e1 + np.sin(phi)[..., None] * e2)).reshape(-1, 3)


def certified(scene, d, branches: bool, monkeypatch, precision="f64", cert=True):
    """float64's certified (t, id) bits of the unrolled search along directions ``d``
    (the exact rays), and how many rays it decided exactly; with or without the branches.
    (``cert=False``: ``precision``'s uncertified search, and None decided.)"""
    T = types(precision)
    monkeypatch.setattr(tracer, "BRANCH_MIN", dict(BRANCH_MIN) if branches else {})
    ks = accel.configure(prepare(scene, T), UNROLLED)
    ks.exact_decisions = cert
    t, oid, _ = closest_hit(ks, T.Array3(*(T.Float(c) for c in d.T)),
                            cam="rays" if cert else None)
    return bits(t), bits(oid), ks.__dict__.get("decided") if cert else None


def test11c_certified_sphere_cone_drops_no_unsure_ray(monkeypatch):
    """float64 with exact decisions branches on shapes.sphere_cone_cert from one sphere on.
    Rays probing each sphere's outline, from 2⁻² down to 2⁻⁵² of its angular radius inside
    and outside (through the band the certified test cannot decide), spheres 2 to 10⁵ radii
    away: the answers and the rays decided exactly are those without the branch, bit for
    bit; some rays are decided exactly, and the probes straddle every outline."""
    V = np.array([0.0, 0.0, 10.0])
    balls = [(np.array(c) / np.linalg.norm(c) * 12.0, 12.0 / k)
             for c, k in (((0.7, 0.0, -0.714), 2), ((-0.5, 0.3, -0.81), 8),
                          ((0.0, 0.5, -0.866), 40), ((-0.2, -0.4, -0.894), 3000),
                          ((0.3, -0.6, -0.74), 100000))]
    scene = Scene((8.0, 6.0), tuple(V), (),
                  tuple(make_sphere(GREY, tuple(V + c), r) for c, r in balls))
    d = np.concatenate([outline_probes(c, r, 2.0 ** -np.arange(2, 53, 2.0), 12)
                        for c, r in balls])
    got = certified(scene, d, True, monkeypatch)
    want = certified(scene, d, False, monkeypatch)
    assert want[2] > 20, "the outlines' rays are unsure"
    assert got[2] == want[2]
    assert_same(got[:2], want[:2], "outline probes")
    ids = want[1].reshape(len(balls), -1)
    for k in range(len(balls)):
        assert (ids[k] == k).any() and (ids[k] != k).any(), f"sphere {k}: probes straddle"


@pytest.mark.parametrize("precision,cert", [("f64", True), ("f64", False), ("f32", False)])
def test11d_finite_planes_branch_on_their_balls(precision, cert, monkeypatch):
    """Camera rays branch past finite planes on their bounding balls (shapes.plane_cone),
    whose surface their corners lie on, widened by plane_ball.  Rays toward points near each corner of four tilted finite planes, 2⁻¹ to
    2⁻⁴⁰ of the plane's size inside and outside along its edges and diagonal: the answers
    (and the rays decided exactly) are those without the branch, bit for bit, and the
    probes straddle every plane's edges."""
    V = np.array([0.0, 0.0, 10.0])
    planes = [make_fplane(GREY, n, p, x, s) for n, p, x, s in (
        ((0.2, 0.1, 1), (-6.0, 2.0, -5.0), (1, 0.3, 0), (2.0, 1.5)),
        ((-0.3, 0.0, 1), (3.0, 2.5, -20.0), (1, -0.2, 0.3), (4.0, 3.0)),
        ((0.0, 0.4, 1), (-7.0, -6.0, -2.0), (1, 0, 0), (1.0, 0.5)),
        ((0.1, -0.2, 1), (5.0, -5.0, -60.0), (1, 0.5, 0), (9.0, 5.0)))]
    scene = Scene((8.0, 6.0), tuple(V), (), tuple(planes))
    ks = prepare(scene, types("f64"))
    s = 2.0 ** -np.arange(1, 41, 3.0)
    points = []
    for c in ks.consts:
        q, x, y = (np.array(v) for v in (c.q, c.xdir, c.ydir))
        w, h = c.size
        for cu, cv in ((0, 0), (1, 0), (0, 1), (1, 1)):
            corner = q + cu * w * x + cv * h * y
            out_u, out_v = (1 if cu else -1) * x, (1 if cv else -1) * y
            for k in np.r_[-s, 0, s]:
                for e in (out_u * w, out_v * h, out_u * w + out_v * h):
                    points.append(corner + k * e)
    d = np.array(points)
    d /= np.linalg.norm(d, axis=1)[:, None]
    got = certified(scene, d, True, monkeypatch, precision, cert)
    want = certified(scene, d, False, monkeypatch, precision, cert)
    assert got[2] == want[2]
    assert_same(got[:2], want[:2], "corner probes")
    ids = want[1].reshape(len(planes), -1)
    for k in range(len(planes)):
        assert (ids[k] == k).any() and (ids[k] != k).any(), f"plane {k}: probes straddle"


def test11e_branches_keep_edge_on_planes_and_tiny_rays(monkeypatch):
    """Two cases a reviewer's fuzzing found (certified float64, with and without the
    branches, bit for bit, and the same rays decided exactly): rays just outside the ball of
    a nearly edge-on finite plane, whose certified edge test is unsure there (its bound over
    n·d is far wider than the ball's 2⁻¹⁰: shapes.plane_ball widens it by that, or leaves
    the plane without a branch); and rays of length 10⁻¹⁶⁵, whose |d|² underflows, so that
    the cone test would drop them whatever their direction (cone_rays keeps CONE_MIN² as
    its lower limit).  (What the kernel answers for the tiny rays, a hit or not, depends on
    how denormals are handled in the process; the test asks that the branch changes it
    not.)"""
    from rt_core import cull
    V = np.array([0.0, 0.0, 10.0])
    n = np.array([0.0, 1.0, 1e-10])
    xh = np.array([1.0, 0, 0])
    yh = np.cross(n / np.linalg.norm(n), xh)
    w, h = 2.0, 0.002
    P = V + np.array([0.0, 0.0, -1000.0]) - w / 2 * xh - h / 2 * yh
    objs = (make_fplane(GREY, tuple(n), tuple(P), (1, 0, 0), (w, h)),
            make_fplane(GREY, (0, 0, 1), (50.0, 50.0, -5.0), (1, 0, 0), (1.0, 1.0)),
            make_fplane(GREY, (0, 0, 1), (-50.0, 50.0, -5.0), (1, 0, 0), (1.0, 1.0)),
            make_fplane(GREY, (0.001, 0.0013, 1), (-100.0, -100.0, -2000.0), (1, 0, 0),
                        (200.0, 200.0)))
    scene = Scene((8.0, 6.0), tuple(V), (), objs)
    centre, R = cull.bounding(prepare(scene, types("f64")))[0]
    d = np.array([np.array(centre) + R * (1 + k) * xh for k in np.geomspace(3e-3, 3e-2, 64)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    got = certified(scene, d, True, monkeypatch)
    want = certified(scene, d, False, monkeypatch)
    assert want[2] > 0 and got[2] == want[2]
    assert_same(got[:2], want[:2], "edge-on plane")
    scene = Scene((8.0, 6.0), tuple(V), (), (make_sphere(GREY, (0.0, 0.0, 0.0), 1.0),))
    d = np.array([[0.0, 0.0, -1.0], [0.05, 0.0, -1.0], [0.0, 0.099, -1.0], [0.3, 0, -1]])
    for s, rays in ((1e-165, d[:1]), (1e-165, d), (1e-300, d)):
        T = types("f64")
        D = T.Array3(*(T.Float(np.ascontiguousarray(c)) for c in (rays * s).T))
        out = []
        for branches in (True, False):
            monkeypatch.setattr(tracer, "BRANCH_MIN", dict(BRANCH_MIN) if branches else {})
            ks = accel.configure(prepare(scene, T), UNROLLED)
            t, oid, _ = closest_hit(ks, D, cam="rays",
                                    dmax=s * float(np.linalg.norm(rays, axis=1).max()))
            out.append((bits(t), bits(oid), ks.decided))
        assert out[0][2] == out[1][2]
        assert_same(out[0][:2], out[1][:2], f"rays of length {s}")


def test11f_branch_keeps_small_scenes_unsure_rays(monkeypatch):
    """A second reviewer's case: in a small scene (a nearly edge-on 0.01 finite plane 0.03
    from the viewpoint) the certified finite plane's den bound, which does not shrink with
    the scene, dwarfs its edges' bound, and the test takes its decisions' least against the
    largest of their bounds; plane_ball widening by the edges' bound alone let unsure rays
    be dropped (their t then the kernel's, not the exact decision's).  Rays in the plane's
    directions from 10⁻⁶ to 100 times its ball's radius outside, of lengths 1 and 0.26 of
    dmax: the same answers and exact decisions with the branches as without."""
    from rt_core import cull
    V = np.array([0.0, 0.0, 0.01])
    w = 0.01
    objs = (make_fplane(GREY, (1.0, 0.0, 3e-12), tuple(V + np.array([0.0, -w / 2, -0.03])),
                        (0, 1, 0), (w, w)),
            make_fplane(GREY, (0, 0, 1), (50.0, 50.0, -5.0), (1, 0, 0), (1.0, 1.0)),
            make_fplane(GREY, (0, 0, 1), (-50.0, 50.0, -5.0), (1, 0, 0), (1.0, 1.0)),
            make_fplane(GREY, (0, 0, 1), (50.0, -50.0, -5.0), (1, 0, 0), (1.0, 1.0)))
    scene = Scene((8.0, 6.0), tuple(V), (), objs)
    ks = prepare(scene, types("f64"))
    centre, R = cull.bounding(ks)[0]
    x, y = np.array(ks.consts[0].xdir), np.array(ks.consts[0].ydir)
    d = np.array([np.array(centre) + R * (1 + k) * (np.cos(p) * x + np.sin(p) * y)
                  for p in np.linspace(0, 2 * np.pi, 32, endpoint=False)
                  for k in np.geomspace(1e-6, 100, 40)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    for length in (1.0, 0.26):
        got = certified(scene, d * length, True, monkeypatch)
        want = certified(scene, d * length, False, monkeypatch)
        assert want[2] > 0, "rays near the plane are unsure"
        assert got[2] == want[2]
        assert_same(got[:2], want[:2], f"small scene, length {length}")


def test12_a_scenes_constants_are_computed_once(monkeypatch):
    """tracer.prepare keeps the exact-arithmetic constants of the scenes it prepared last: a
    second precision or render of the same (frozen) scene reuses them, another scene gets its
    own, and the constants are the ones object_constants gives."""
    calls = []
    real = tracer.object_constants
    monkeypatch.setattr(tracer, "object_constants", lambda s: calls.append(s) or real(s))
    a, b = scene_of(spheres(3) + fplanes(2)), scene_of(spheres(2))
    ka = tracer.prepare(a, types("f32"))
    kb = tracer.prepare(a, types("f64"))
    kc = tracer.prepare(b, types("f32"))
    assert calls == [a, b]
    assert ka.consts == kb.consts == real(a) and kc.consts == real(b)


@pytest.mark.parametrize("precision", PRECISIONS)
def test13_camera_rays_find_their_bins_by_their_window_offsets(precision, monkeypatch):
    """Camera rays whose directions the kernel computes look their bins up by the pixels'
    window offsets (tracer.BIN_BY_OFFSETS: the unnormalized directions, the same line), and
    evaluated directions by themselves: the hits, and float64's exactly decided rays, are
    those of the bins by direction, bit for bit, on looped scenes seen from off-centre
    viewpoints, with corner and centre sampling and a band of rows."""
    import dataclasses
    from tools.harness.bench import bench_scene
    T = types(precision)
    given = []
    ray_bins = accel.ray_bins
    monkeypatch.setattr(accel, "ray_bins", lambda ks, grid, d: given.append(d) or
                        ray_bins(ks, grid, d))
    scenes = [bench_scene(k, 40) for k in ("spheres", "fplanes", "mixed")]
    scenes.append(random_scene(13, 30))
    for i, scene in enumerate(scenes):
        scene = scene.__class__(**{**scene.__dict__,
                                   "viewpoint": (0.7 * i - 1, 0.4 - 0.3 * i, 9.0 + i)})
        ks = prepare(scene, T)
        assert accel.camera_loops(ks)
        for sampling, rows in (("corners", None), ("centers", None)):
            cam = make_camera(scene, 61 + 14 * i, rows, sampling)
            if i == 3:                      # a band of rows, shifted (a course variant)
                cam = dataclasses.replace(cam, row0=5, band=17, row_shift=1)
            got = []
            for on in (False, True):
                monkeypatch.setattr(tracer, "BIN_BY_OFFSETS", on)
                given.clear()
                d = primary_directions(scene, cam, T)
                t, oid, _ = closest_hit(ks, d, cam=cam)
                got.append((t.numpy().copy(), oid.numpy().copy(), ks.__dict__.get("decided")))
                # the offsets (their z a constant: one opaque number, not a normalized one)
                assert given and all((v is not d) == on for v in given)
            assert np.array_equal(got[0][0], got[1][0]) and np.array_equal(got[0][1],
                                                                             got[1][1])
            assert got[0][2] == got[1][2]
    # evaluated directions are their own bins' vectors
    monkeypatch.setattr(tracer, "BIN_BY_OFFSETS", True)
    given.clear()
    d = primary_directions(scenes[0], make_camera(scenes[0], 40), T)
    dr.eval(d)
    closest_hit(prepare(scenes[0], T), d, cam=make_camera(scenes[0], 40))
    assert given and all(v is d for v in given)


@pytest.mark.parametrize("precision", PRECISIONS)
def test14_traced_without_value_numbering(precision, monkeypatch):
    """rt_core's entry points (closest_hit, shade, render_image) trace with Dr.Jit's value
    numbering off (backend.traced: its table, once grown by a large scene, slows every
    later operation) and restore the caller's setting; the hits and the shaded image are bit
    for bit those traced with it on (LLVM merges the same expressions either way); and
    every entry point (occluded, render's others) is wrapped so."""
    from pathlib import Path
    from rt_core import backend as backend_mod, shading
    from rt_core.parser import parse_scene
    from rt_core.render import camera_rays, render_image
    seen = []
    for mod in (tracer, shading):           # (each entry point widens its directions first)
        monkeypatch.setattr(mod, "widened", lambda T, d, real=mod.widened: seen.append(
            dr.flag(dr.JitFlag.ValueNumbering)) or real(T, d))
    T = types(precision)
    repo = Path(__file__).resolve().parents[1]
    for name in ("mixed", "shade_mirrors"):
        scene = parse_scene(repo / "scenes" / f"{name}.txt")
        cam = make_camera(scene, 40)
        out = {}
        for vn in (True, False):
            monkeypatch.setattr(backend_mod, "VALUE_NUMBERING", vn)
            ks = prepare(scene, T)
            d = camera_rays(ks, cam)
            got = []
            for call in (lambda: closest_hit(ks, d, cam=cam),
                         lambda: (shading.shade(ks, d, cam=cam).rgb,),
                         lambda: tuple(render_image(scene, cam, T, shade=True)[0].values())):
                seen.clear()
                assert dr.flag(dr.JitFlag.ValueNumbering)
                res = call()
                assert dr.flag(dr.JitFlag.ValueNumbering)       # the caller's, restored
                assert seen and set(seen) == {vn}, (name, vn, seen)
                got += [np.asarray(r.numpy() if isinstance(r, dr.ArrayBase) else r)
                        for r in res]
            out[vn] = got
        for a, b in zip(out[True], out[False]):
            assert np.array_equal(np.ascontiguousarray(a).view(np.uint8),
                                  np.ascontiguousarray(b).view(np.uint8)), name
    # every entry point is wrapped, also those only reached through another here
    from rt_core import render
    for fn in (closest_hit, occluded, shading.shade, camera_rays, render.trace_geometry,
               render_image, render.render_tiled):
        assert fn.__code__ is backend_mod.traced(len).__code__, fn.__name__
