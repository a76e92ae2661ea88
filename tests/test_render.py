"""rtval render: EXR channels, provenance, atomic output, one-line errors, LLVM check."""
from __future__ import annotations

import glob
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rt_core.exrio import read_exr
from rt_core.parser import parse_scene
from rt_core.render import GEOMETRY_CHANNELS, render_geometry

REPO = Path(__file__).resolve().parents[1]
from tests.tolerances import PRECISIONS, U  # noqa: E402


def rtval(*args, env=None):
    return subprocess.run([sys.executable, "-m", "tools.cli", *map(str, args)],
                          capture_output=True, text=True, cwd=REPO,
                          env=None if env is None else {**os.environ, **env})


@pytest.mark.parametrize("precision", PRECISIONS)
def test01_exr_channels_and_provenance(precision, tmp_path):
    out = tmp_path / "seed.exr"
    r = rtval("render", "scenes/seed_fplane.txt", "--columns", 64, "--precision", precision,
              "-o", out)
    assert r.returncode == 0, r.stderr
    ch, hdr = read_exr(out)
    assert set(GEOMETRY_CHANNELS) <= set(ch)
    geometry = {k: v for k, v in ch.items() if k in GEOMETRY_CHANNELS}
    assert all(v.dtype == np.float32 and v.shape == (48, 64) for v in geometry.values())
    # the file holds exactly what the library renders (float32 of it)
    want = render_geometry(parse_scene(REPO / "scenes" / "seed_fplane.txt"), 64,
                           precision=precision)
    for k in GEOMETRY_CHANNELS:
        np.testing.assert_array_equal(ch[k], want[k].astype(np.float32))
    # misses follow the stated convention
    miss = ch["hit.mask"] == 0
    assert miss.any() and (~miss).any()
    assert (ch["object.id"][miss] == -1).all() and (ch["depth.Z"][miss] == 0).all()
    assert all((ch[k][miss] == 0).all() for k in GEOMETRY_CHANNELS if k[:3] in ("nor", "pos",
                                                                                 "uv."))
    sha = __import__("hashlib").sha256((REPO / "scenes/seed_fplane.txt").read_bytes())
    assert hdr["rtval.scene_sha256"] == sha.hexdigest()
    assert hdr["rtval.precision"] == precision and hdr["rtval.backend"] == "llvm"
    assert hdr["rtval.sampling"] == "corners" and "edges=closed" in hdr["rtval.rules"]
    assert "drjit=" in hdr["rtval.versions"] and "mitsuba=" in hdr["rtval.versions"]
    assert "object.id=-1" in hdr["rtval.miss"] and hdr["rtval.nonfinite"] == "0"


def test02_image_orientation_top_row_first():
    """Row 0 of the image is the course's top row y = H-1 (a plane below the window's
    centre shows in the bottom rows only)."""
    img = render_geometry(parse_scene(REPO / "scenes" / "plane.txt"), 40)
    rows_hit = np.nonzero(img["hit.mask"].any(axis=1))[0]
    assert rows_hit.min() > 0 and rows_hit.max() == img["hit.mask"].shape[0] - 1


def test03_rows_default_and_sampling(tmp_path):
    out = tmp_path / "c.exr"
    assert rtval("render", "scenes/sphere.txt", "--columns", 50, "--sampling", "centers",
                 "-o", out).returncode == 0
    ch, hdr = read_exr(out)
    assert ch["depth.Z"].shape == (37, 50)          # int(6/8 * 50)
    assert hdr["rtval.sampling"] == "centers"


BAD = [
    ("missing", None, "no such file"),
    ("empty", "", "empty"),
    ("truncated", "8 6\n0 0 3\nsphere\n1 1 1\n", "end of file"),
    ("parallel", "8 6\n0 0 3\nfplane\n0 0 0\n1 1 1\n0 0 0\n0 0 1\n0 0 -1\n0 0 2\n1 1\n",
     "parallel"),
    ("unsupported", "8 6\n0 0 3\n21 paraboloid\n", "not supported"),
]


@pytest.mark.parametrize("name,text,phrase", BAD, ids=[b[0] for b in BAD])
def test04_bad_input_is_one_line_no_output(name, text, phrase, tmp_path):
    scene = tmp_path / f"{name}.txt"
    if text is not None:
        scene.write_text(text)
    out = tmp_path / "out.exr"
    r = rtval("render", scene, "--columns", 16, "-o", out)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert f"{name}.txt" in lines[0] and phrase in lines[0].lower()
    assert not out.exists() and not glob.glob(str(tmp_path / ".tmp-*"))


@pytest.mark.parametrize("args,phrase", [
    (["--columns", "0"], "positive"),
    (["--columns", "x"], "whole number"),
    (["--columns", "8", "--rules", "edges=ajar"], "edges"),
    (["--columns", "8", "--precision", "f16"], "invalid choice"),
    (["--columns", "8", "--rules", "t_min=inf"], "finite"),
    (["--columns", "8", "--rules", "clip_spheres=maybe"], "true or false"),
    (["--columns", "8", "--rules", "ties=first,ties=last"], "twice"),
])
def test05_bad_options_are_usage_errors(args, phrase, tmp_path):
    r = rtval("render", "scenes/sphere.txt", *args, "-o", tmp_path / "o.exr")
    assert r.returncode == 64 and phrase in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o.exr").exists()


def test06_too_few_rows_for_corner_sampling(tmp_path):
    r = rtval("render", "scenes/sphere.txt", "--columns", 2, "-o", tmp_path / "o.exr")
    assert r.returncode == 2 and "--rows" in r.stderr and "Traceback" not in r.stderr


def test07_unwritable_output_leaves_nothing(tmp_path):
    target = tmp_path / "dir.exr"
    target.mkdir()                                   # rename onto a directory fails
    r = rtval("render", "scenes/sphere.txt", "--columns", 16, "-o", target)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not glob.glob(str(tmp_path / ".tmp-*"))


OLD_LLVM = [sorted(glob.glob(f"/usr/lib/*/libLLVM-{v}.so*")) for v in (14, 15)]


@pytest.mark.parametrize("lib", [p[0] if p else None for p in OLD_LLVM], ids=["llvm14", "llvm15"])
def test08_old_llvm_is_a_clear_error_not_an_abort(lib, tmp_path):
    if lib is None:
        pytest.skip("this LLVM version is not installed here")
    r = rtval("render", "scenes/sphere.txt", "--columns", 16, "-o", tmp_path / "o.exr",
              env={"DRJIT_LIBLLVM_PATH": lib})
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert "libllvm19" in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("k", [-40, -3, 0, 5])
def test09_uv_stays_in_the_rectangle_at_exact_edges(k, precision):
    """Rays exactly through a finite plane's corners and edges (and ±1 ulp) that hit it get
    0 <= u <= w, 0 <= v <= h. (u as (ŷ·c)·rcp(n·d) rounded twice and came out past w.)
    surface() keeps uv inside the rectangle, so the range alone would hold for any u: u and
    v must also be within a few units of rounding of the exact oracle's (mitsuba_ref/exact.py
    margins u >= 0 and v >= 0 are u and v in world units)."""
    from tools.harness.stability import make_case
    from rt_core import backend
    from rt_core.parser import parse_text
    from rt_core.tracer import closest_hit, prepare, surface
    case = make_case("edges", 2.0 ** k)
    scene = parse_text(case.text)
    T = backend.types(precision)
    a = np.asarray(case.rays, np.float32 if precision == "f32" else np.float64)
    d = T.Array3(*(T.Float(a[:, i]) for i in range(3)))
    ks = prepare(scene, T)
    t, oid, hit = closest_hit(ks, d)
    _, u, v = surface(ks, d, t, oid, hit)
    u, v, oid = (np.asarray(x.numpy()) for x in (u, v, oid))
    assert np.count_nonzero(oid >= 0) > 50
    from mitsuba_ref.exact import parse_exact, trace_exact
    ex = trace_exact(parse_exact(case.text), a)
    eps = 64 * U[precision]
    for i, o in enumerate(scene.objects):
        m = oid == i
        w, h = (a.dtype.type(x) for x in o.size)
        assert ((u[m] >= 0) & (u[m] <= w) & (v[m] >= 0) & (v[m] <= h)).all(), (i, u[m].max(), w)
        ue, ve = ex.objects[i].margin["u>=0"][m], ex.objects[i].margin["v>=0"][m]
        scale = float(max(w, h)) + np.abs(np.asarray(o.point)).max()
        assert np.abs(u[m] - ue).max() <= eps * scale, (i, np.abs(u[m] - ue).max())
        assert np.abs(v[m] - ve).max() <= eps * scale, (i, np.abs(v[m] - ve).max())


# --- numbers at the edge of the precision, output paths (review findings) -----------------

SPHERE_AT = "8 6\n0 0 3\nsphere\n1 1 1\n1 1 1\n0 0 0\n0 0 {z}\n{r}\n"


def test10_constants_beyond_float32_are_an_error_not_an_empty_image(tmp_path):
    scene = tmp_path / "big.txt"
    scene.write_text(SPHERE_AT.format(z="-2e20", r="1.5e20"))     # |q|² − r² ~ 1.8e40
    r = rtval("render", scene, "--columns", 16, "-o", tmp_path / "a.exr")
    assert r.returncode == 2 and "big.txt:3" in r.stderr and "--precision f64" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "a.exr").exists()
    r = rtval("render", scene, "--columns", 16, "--precision", "f64", "-o", tmp_path / "b.exr")
    assert r.returncode == 0 and read_exr(tmp_path / "b.exr")[0]["hit.mask"].sum() > 0


def test10b_range_checked_for_each_precision_in_one_process():
    """The constants' checks are kept with them (tracer._CONSTS), but the range is each
    precision's: the scene of test10 prepares in float64, is refused in float32, after
    either, and a scene whose constants overflow float64 is refused every time."""
    from rt_core import backend
    from rt_core.parser import parse_text
    from rt_core.scene import SceneError
    from rt_core.tracer import prepare
    sc = parse_text(SPHERE_AT.format(z="-2e20", r="1.5e20"))
    for precision in ("f64", "f32", "f64", "f32"):
        if precision == "f64":
            prepare(sc, backend.types(precision))
        else:
            with pytest.raises(SceneError, match="exceeds the f32 range"):
                prepare(sc, backend.types(precision))
    huge = parse_text(SPHERE_AT.format(z="-1e200", r="1"))
    for _ in range(2):
        with pytest.raises(SceneError, match="overflows float64"):
            prepare(huge, backend.types("f64"))


def test11_float64_overflow_is_one_line(tmp_path):
    scene = tmp_path / "huge.txt"
    scene.write_text(SPHERE_AT.format(z="-1e200", r="1"))          # |q|² overflows float64
    r = rtval("render", scene, "--columns", 16, "--precision", "f64", "-o", tmp_path / "a.exr")
    # at the number at fault: the centre's z (line 7, column 5), not just the object's line
    assert r.returncode == 2 and "huge.txt:7:5: sphere" in r.stderr and "Traceback" not in r.stderr
    # a viewpoint far off is the viewpoint's fault: its column in the header
    scene.write_text(SPHERE_AT.format(z="-1", r="1").replace("0 0 3", "0 0 1e300"))
    r = rtval("render", scene, "--columns", 16, "--precision", "f64", "-o", tmp_path / "a.exr")
    assert r.returncode == 2 and "huge.txt:2:5: header: the viewpoint" in r.stderr
    # a radius whose square overflows is the radius's fault (it blamed the viewpoint, 9
    # units from the centre: a robustness review)
    scene.write_text(SPHERE_AT.format(z="-1", r="1e200"))
    r = rtval("render", scene, "--columns", 16, "--precision", "f64", "-o", tmp_path / "a.exr")
    assert r.returncode == 2 and "huge.txt:8:1: sphere: its radius 1e+200" in r.stderr, r.stderr


def test12_values_beyond_float32_in_an_f64_render_are_counted(tmp_path):
    scene = tmp_path / "far.txt"
    scene.write_text("8 6\n0 0 3\nplane\n1 1 1\n1 1 1\n0 0 0\n0 1 1\n0 0 -1e300\n")
    out = tmp_path / "far.exr"
    r = rtval("render", scene, "--columns", 16, "--precision", "f64", "-o", out)
    ch, hdr = read_exr(out)
    n = sum(int(np.count_nonzero(~np.isfinite(v))) for v in ch.values())
    assert n > 0 and hdr["rtval.nonfinite"] == str(n)                 # the file's own count
    assert r.returncode == 1 and "NON-FINITE" in r.stderr
    # named by channel and cause, and no numpy warning with its source line (a review)
    assert "Warning" not in r.stderr and "values not finite in the EXR's float32 (in " \
        "depth.Z, position.X, position.Y, position.Z)" in r.stderr, r.stderr
    # an 8-bit image of a finite float64 intensity beyond float32 holds 255, correctly:
    # no NON-FINITE, exit 0 (it said '125 NON-FINITE values', exit 1, a review)
    hot = tmp_path / "hot.txt"
    hot.write_text("8 6\n0 0 5\npointlight\n3e38 3e38 3e38\n-4 4 2\nsphere\n1 0.5 0.5\n"
                   "800 300 300\n0 0 0\n0 0 -4\n2\n")
    r = rtval("render", hot, "--columns", 16, "--precision", "f64", "--ppm", tmp_path / "h.ppm",
              "--png", tmp_path / "h.png")
    assert r.returncode == 0 and "NON-FINITE" not in r.stderr, r.stderr
    from rt_core.imageio import read_channels
    assert read_channels(str(tmp_path / "h.png")).header["rtval.nonfinite"] == "0"


def test13_nan_in_shading_reaches_the_image_and_is_counted(tmp_path):
    """inf·0 in the diffuse term is NaN; Dr.Jit's scatter_add would drop it silently."""
    scene = tmp_path / "nan.txt"
    scene.write_text("8 6\n0 0 3\npointlight\n1e30 1e30 1e30\n0 0 2\npointlight\n"
                     "-1e30 -1e30 -1e30\n0 1 2\nplane\n0 0 0\n1e30 1e30 1e30\n0 0 0\n"
                     "0 0 1\n0 0 -5\n")
    r = rtval("render", scene, "--columns", 16, "--png", tmp_path / "n.png",
              "-o", tmp_path / "n.exr")
    assert r.returncode == 1 and "NON-FINITE" in r.stderr and "Warning" not in r.stderr
    ch, hdr = read_exr(tmp_path / "n.exr")
    assert np.isnan(ch["R"]).any() and int(hdr["rtval.nonfinite"]) > 0
    # the PNG records the same count (it had none: a robustness review)
    from rt_core.imageio import read_channels
    assert read_channels(str(tmp_path / "n.png")).header["rtval.nonfinite"] == \
        hdr["rtval.nonfinite"]
    # a NaN is one in the 8-bit image's own count too, without the EXR
    r = rtval("render", scene, "--columns", 16, "--png", tmp_path / "m.png")
    assert r.returncode == 1 and "NON-FINITE" in r.stderr


def test14_output_paths(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    for out in (afile / "x.exr", tmp_path):                       # under a file; a directory
        r = rtval("render", "scenes/sphere.txt", "--columns", 8, "-o", out)
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    # a symlink is written through; a new file gets 0666 less the umask
    target, link = tmp_path / "target.exr", tmp_path / "link.exr"
    link.symlink_to(target)
    old = os.umask(0o022)
    try:
        assert rtval("render", "scenes/sphere.txt", "--columns", 8, "-o", link).returncode == 0
    finally:
        os.umask(old)
    assert link.is_symlink() and target.is_file()
    assert (target.stat().st_mode & 0o777) == 0o644
    assert not glob.glob(str(tmp_path / ".tmp-*"))


def test15_usage_errors_are_one_line():
    r = rtval("render", "scenes/sphere.txt", "--columns", "nan", "-o", "x.exr")
    assert r.returncode == 64 and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux /proc")
def test16_one_unwritable_output_leaves_no_other(tmp_path):
    """-o good.exr --png <where no file can be created>: refused before rendering, so the
    good EXR is not written either (outputs are all or nothing)."""
    good = tmp_path / "good.exr"
    r = rtval("render", "scenes/sphere.txt", "--columns", 8, "-o", good, "--png", "/proc/x.png")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert not good.exists() and not glob.glob(str(tmp_path / ".tmp-*"))


@pytest.mark.parametrize("compression", ["zip", "zstd", "htj2k", "none"])
def test30_every_compression_is_lossless(tmp_path, compression):
    """--compression changes the file, never a pixel (the default is PIZ)."""
    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    assert rtval("render", "scenes/mixed.txt", "--columns", 48, "--ppm", tmp_path / "a.ppm",
                 "-o", a).returncode == 0
    assert rtval("render", "scenes/mixed.txt", "--columns", 48, "--ppm", tmp_path / "b.ppm",
                 "-o", b, "--compression", compression).returncode == 0
    (ca, ha), (cb, hb) = read_exr(a), read_exr(b)
    assert ha["compression"] == "piz"                     # as OpenImageIO names them
    assert hb["compression"] == {"htj2k": "htj2k256"}.get(compression, compression)
    assert sorted(ca) == sorted(cb)
    for k in ca:
        assert np.array_equal(ca[k].view(np.uint32), cb[k].view(np.uint32)), k


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test20_looped_camera_rays_are_evaluated_first_same_images(precision, monkeypatch):
    """Where float32 camera rays loop over bins (accel.camera_loops), their directions are
    evaluated by a kernel of their own before the trace (render.camera_rays: faster than
    fused into the loop's kernel); float64's, and unrolled scenes', stay fused.  Either way
    the geometry and the shaded image are the same, bit for bit."""
    import drjit as dr
    from rt_core import accel, backend, render
    from rt_core.camera import make_camera
    from rt_core.tracer import prepare
    from tools.harness.bench_shaded import shaded_scene
    T = backend.types(precision)
    for n, loops in ((4, False), (40, True)):
        scene = shaded_scene("mixed", n)
        cam = make_camera(scene, 64)
        ks = prepare(scene, T)
        assert accel.camera_loops(ks) == loops
        d = render.camera_rays(ks, cam)
        assert (d.x.state == dr.VarState.Evaluated) == (loops and precision == "f32")
        got = {}
        for on in (False, True):
            monkeypatch.setattr(render, "EVAL_LOOPED_DIRECTIONS", on)
            geo = render.to_images(render.trace_geometry(scene, cam, T), cam)
            img, _ = render.render_image(scene, cam, T, shade=True, geometry=False)
            got[on] = {**geo, **img}
        for k in got[False]:
            assert np.array_equal(got[False][k], got[True][k], equal_nan=True), (n, k)
