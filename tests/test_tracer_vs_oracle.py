"""The Dr.Jit tracer against the per-ray float64 oracle (tests/oracle.py), pixel by pixel.

Every scene in scenes/*.txt and seeded random scenes, in f32 and f64: identical hit mask and
object ids, and every value within a tolerance derived from the oracle's own error bound, except
at pixels the oracle flags as within reach of rounding of a hit/miss decision.  The excused
pixels must be few, so the excuse cannot hide a broken tracer.  Each rule variant gets a scene
built so that the variant changes exactly-decided pixels.
"""
from __future__ import annotations

import functools
import glob
import os
import tempfile
import numpy as np
import pytest

from rt_core.rules import Rules
from rt_core.scene import Material, Scene, make_fplane, make_plane, make_sphere
from tests.oracle import DIAG_KEYS, GEOMETRY_KEYS, render_oracle
from tests.scenegen import random_scene
from tests.tolerances import GEOMETRY, PRECISIONS, Tol

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


TOL = GEOMETRY
COLUMNS = 64
VALUE_KEYS = tuple(k for k in GEOMETRY_KEYS if k not in ("hit.mask", "object.id"))


def _render_geometry():
    try:
        from rt_core.render import render_geometry
    except ImportError as err:          # the fast tracer is not written yet
        pytest.skip(f"rt_core.render.render_geometry is not available: {err}")
    return render_geometry


def tracer(scene, columns, rows, precision, sampling="corners", rules=Rules()):
    from rt_core.backend import BackendError
    try:
        out = _render_geometry()(scene, columns, rows, precision=precision, backend="llvm",
                                 sampling=sampling, rules=rules)
    except BackendError as err:
        pytest.skip(f"llvm backend unavailable: {err}")
    assert sorted(out) == sorted(GEOMETRY_KEYS)
    return out


@functools.lru_cache(maxsize=64)
def oracle(scene, columns, rows, sampling="corners", rules=Rules()):
    return render_oracle(scene, columns, rows, sampling, rules)


def excused_mask(orc: dict, tol: Tol) -> np.ndarray:
    return np.any(np.stack([orc[k] < tol.flag for k in DIAG_KEYS]), axis=0)


def write_evidence(name: str, ours: dict, orc: dict, mismatch: dict) -> str:
    """Both images, their difference, the mismatch masks and the diagnostics: an EXR (for tev)
    and an .npz (float64, exact); returns the directory."""
    from rt_core.exrio import write_exr
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in name)
    out = tempfile.mkdtemp(prefix=f"rtval-oracle-{safe}-")
    chans = {}
    for k in GEOMETRY_KEYS:
        chans[f"ours.{k}"] = np.asarray(ours[k], np.float64)
        chans[f"oracle.{k}"] = orc[k]
        chans[f"diff.{k}"] = np.asarray(ours[k], np.float64) - orc[k]
        chans[f"oracle_err.{k}"] = orc["err." + k]
    for k, m in mismatch.items():
        chans[f"mismatch.{k}"] = m.astype(np.float64)
    for k in DIAG_KEYS:
        chans[f"diag.{k}"] = orc[k]
    np.savez(os.path.join(out, "evidence.npz"), **chans)
    write_exr(os.path.join(out, "evidence.exr"), chans)
    return out


def compare(name: str, ours: dict, orc: dict, tol: Tol) -> np.ndarray:
    """Assert agreement; return the excused mask.  On failure, write evidence first."""
    exc = excused_mask(orc, tol)
    mism = {}
    mism["mask_or_id"] = ((ours["hit.mask"] != orc["hit.mask"])
                          | (ours["object.id"] != orc["object.id"])) & ~exc
    both = ~exc & ~mism["mask_or_id"]
    worst = []
    for k in VALUE_KEYS:
        ref = orc[k]
        diff = np.abs(np.asarray(ours[k], np.float64) - ref)
        allowed = tol.value * tol.u * (orc["err." + k] + np.abs(ref))
        bad = both & ~(diff <= allowed)
        mism[k] = bad
        if bad.any():
            r, c = np.argwhere(bad)[np.argmax((diff / np.maximum(allowed, 1e-300))[bad])]
            worst.append(f"{k}: {bad.sum()} px, worst at row {r} col {c}: ours "
                         f"{ours[k][r, c]!r} oracle {ref[r, c]!r} allowed {allowed[r, c]:.3g}")
    n_exc, n = int(exc.sum()), exc.size
    problems = []
    if mism["mask_or_id"].any():
        r, c = np.argwhere(mism["mask_or_id"])[0]
        problems.append(f"mask/id differ at {mism['mask_or_id'].sum()} unflagged px, first at "
                        f"row {r} col {c}: ours id {ours['object.id'][r, c]:g}, oracle id "
                        f"{orc['object.id'][r, c]:g}; margins "
                        + ", ".join(f"{k}={orc[k][r, c]:.3g}" for k in DIAG_KEYS))
    problems += worst
    if n_exc > tol.excused * n:
        problems.append(f"{n_exc} of {n} px excused (> {tol.excused:.0%}): "
                        + ", ".join(f"{k}={int((orc[k] < tol.flag).sum())}" for k in DIAG_KEYS))
    if problems:
        where = write_evidence(name, ours, orc, mism)
        print(f"evidence: {where}/evidence.exr and evidence.npz")
        pytest.fail(f"{name}: " + "; ".join(problems) + f" (evidence in {where})")
    return exc


# --- scenes ---------------------------------------------------------------------------------

SCENE_FILES = sorted(glob.glob(os.path.join(ROOT, "scenes", "*.txt")))


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("path", SCENE_FILES or [pytest.param(None, marks=pytest.mark.skip(
    reason="no scenes/*.txt"))], ids=lambda p: os.path.basename(p) if p else "none")
def test01_scene_files(path, precision):
    from rt_core.parser import parse_scene
    scene = parse_scene(path)
    rows = scene.default_rows(COLUMNS)
    compare(f"{os.path.basename(path)}-{precision}", tracer(scene, COLUMNS, rows, precision),
            oracle(scene, COLUMNS, rows), TOL[precision])


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("seed", range(12))
def test02_random_scenes(seed, precision):
    scene = random_scene(seed)
    sampling = "corners" if seed % 2 == 0 else "centers"
    rows = scene.default_rows(COLUMNS)
    compare(f"random{seed}-{sampling}-{precision}",
            tracer(scene, COLUMNS, rows, precision, sampling),
            oracle(scene, COLUMNS, rows, sampling), TOL[precision])


# --- rule variants, on scenes built so the variant decides pixels exactly ----------------------

GREY = Material((1, 1, 1), (2, 2, 2), (0, 0, 0))


def _scene(objects, viewpoint):
    return Scene((8.0, 6.0), viewpoint, (), tuple(objects), path="<variant>")


def edges_scene():
    # 65 x 33 pixels: x/(W-1) and y/(H-1) are exact binary fractions, so the centre column and
    # row have world x = 0 and y = 0 exactly, and the rays through them hit the panel at
    # u = 0 and v = 0 exactly (1*(0 - 0) + 0*...); in front of a wall.
    return _scene([make_plane(GREY, (0, 0, 1), (0, 0, -8)),
                   make_fplane(GREY, (0, 0, 1), (0, 0, -3), (1, 0, 0), (2.0, 1.5))],
                  (0.0, 0.0, 3.0)), 65, 33


def clip_scene():
    # viewpoint in z = 0: every ray has d.z = 0 exactly, so every hit has z = 0 exactly:
    # kept by 'z > 0 misses', lost by 'z >= 0 misses' (planes only; spheres are not clipped)
    return _scene([make_plane(GREY, (1, 0, 0), (-6, 0, 0)),
                   make_fplane(GREY, (-1, 0, 0), (5, -4, 1), (0, 1, 0), (8.0, 2.0)),
                   make_sphere(GREY, (0, 2.5, 0), 0.5)],
                  (0.0, 0.0, 0.0)), 64, 48


def ties_scene():
    # the same plane equation twice (a plane and a panel), and two identical spheres: exact
    # ties in any precision
    return _scene([make_plane(GREY, (0, 0.2, 1), (0, 0, -6)),
                   make_fplane(GREY, (0, 0.2, 1), (0, 0, -6), (1, 0.3, 0), (3.0, 2.0)),
                   make_sphere(GREY, (-2, -1, -4), 1.0),
                   make_sphere(GREY, (-2, -1, -4), 1.0)],
                  (0.0, 0.0, 3.0)), 64, 48


def tmin_scene():
    # viewpoint in z = 0 (hits at z = 0 are not clipped) and a wall 2^-14 to its left: left-
    # going rays hit it at t = 2^-14/|d.x| in (6.1e-5, 1.2e-4]: below 1e-4 where |d.x| > 0.61.
    # Behind it a second wall.
    return _scene([make_plane(GREY, (1, 0, 0), (-2.0 ** -14, 0, 0)),
                   make_plane(GREY, (1, 0, 0), (-5, 0, 0)),
                   make_sphere(GREY, (3, 0, 0), 1.0)],
                  (0.0, 0.0, 0.0)), 64, 48


def sphere_clip_scene():
    # a sphere through the window: its near root lies at z > 0 near the middle, at z < 0 at
    # the rim; a wall behind
    return _scene([make_plane(GREY, (0, 0, 1), (0, 0, -6)),
                   make_sphere(GREY, (1, 0.5, -0.5), 1.5)],
                  (0.0, 0.0, 3.0)), 64, 48


VARIANTS = {
    "edges-open": (edges_scene, Rules(edges="open")),
    "screen_clip->=": (clip_scene, Rules(screen_clip=">=")),
    "ties-last": (ties_scene, Rules(ties="last")),
    "t_min-1e-4": (tmin_scene, Rules(t_min=1e-4)),
    "clip_spheres": (sphere_clip_scene, Rules(clip_spheres=True)),
}


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("variant", list(VARIANTS))
def test03_rule_variants(variant, precision):
    make, rules = VARIANTS[variant]
    scene, W, H = make()
    tol = TOL[precision]
    name = f"{variant}-{precision}"
    o0, o1 = oracle(scene, W, H), oracle(scene, W, H, "corners", rules)
    r0 = tracer(scene, W, H, precision)
    r1 = tracer(scene, W, H, precision, rules=rules)
    e0 = compare(name + "-default", r0, o0, tol)
    e1 = compare(name, r1, o1, tol)
    changed_o = o0["object.id"] != o1["object.id"]
    changed_r = r0["object.id"] != r1["object.id"]
    robust = ~e0 & ~e1
    assert (changed_o & robust).sum() > 0, f"{name}: the variant changed no (unflagged) pixel"
    assert np.array_equal(changed_o[robust], changed_r[robust]), \
        f"{name}: tracer and oracle disagree on which pixels the variant changes"
