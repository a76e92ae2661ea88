"""rt_core on Dr.Jit's CUDA backend (skipped where Dr.Jit finds no CUDA device): every bundled
scene's geometry and course image agree with the LLVM backend's.

float64 decides every pixel exactly on both backends (certified bounds, then exact
arithmetic), so its object ids are identical and its t agrees to a few ulps; float32's hit
tests may round differently on the GPU (fused multiply-adds the PTX compiler chooses), so
its pixels may differ only where the float64 oracle's error bound straddles a decision,
which tests/test_tracer_vs_oracle.py checks for the LLVM backend: here, at most 0.5% of the
pixels, and the course image (8 bits) in at most as many.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = sorted(p for p in (ROOT / "scenes").glob("*.txt"))


def _has_cuda() -> bool:
    import drjit as dr
    return dr.has_backend(dr.JitBackend.CUDA)


pytestmark = pytest.mark.skipif(not _has_cuda(), reason="no CUDA device here")
W = 96


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test01_geometry_agrees_with_llvm(path, precision):
    from rt_core.parser import parse_scene
    from rt_core.render import render_geometry
    scene = parse_scene(path)
    a = render_geometry(scene, W, precision=precision, backend="llvm")
    b = render_geometry(scene, W, precision=precision, backend="cuda")
    ida, idb = a["object.id"], b["object.id"]
    if precision == "f64":
        assert np.array_equal(ida, idb)
        both = ida >= 0
        np.testing.assert_allclose(b["depth.Z"][both], a["depth.Z"][both], rtol=1e-12)
    else:
        assert np.count_nonzero(ida != idb) <= 0.005 * ida.size


@pytest.mark.parametrize("path", BUNDLED, ids=[p.stem for p in BUNDLED])
def test02_course_image_agrees_with_llvm(path):
    from rt_core.camera import make_camera
    from rt_core.parser import parse_scene
    from rt_core.render import render_image
    from rt_core import backend
    from rt_core.shading import quantize
    scene = parse_scene(path)
    cam = make_camera(scene, W)
    img = {}
    for name in ("llvm", "cuda"):
        ims, _ = render_image(scene, cam, backend.types("f64", name), geometry=False, shade=True)
        img[name] = quantize(np.stack([ims[c] for c in "RGB"], -1)).astype(np.int16)
    differ = np.abs(img["llvm"] - img["cuda"]).max(-1) > 1
    assert np.count_nonzero(differ) <= 0.005 * differ.size
