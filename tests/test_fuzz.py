"""Fuzzing: mutated real scenes and damaged EXRs never raise anything but the one-line errors.

Scenes (the bundled ones and the 140 course files) are mutated by hypothesis (tokens deleted,
duplicated or replaced by extreme numbers and junk, lines cut, bytes inserted).  Each outcome
is a parsed scene that also gets a camera and the kernels' host constants, or a SceneError
``file:line:col: ...`` / InputError: never another exception.  EXRs (truncated, bytes flipped,
deep, multi-part, tiled, half and uint channels) go through ``rtval exr``'s readers: a result
or an ExrError.

The default run is seeded (``derandomize``) and small; ``-m slow`` runs thousands of cases;
``RTVAL_FUZZ_EXAMPLES=100000 python -m pytest -m slow tests/test_fuzz.py`` runs a long
session (README: "What happens when things go wrong").
"""
from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings, strategies as st  # noqa: E402

from rt_core import backend  # noqa: E402
from rt_core.camera import make_camera  # noqa: E402
from rt_core.exrio import ExrError, write_exr  # noqa: E402
from rt_core.parser import parse_text  # noqa: E402
from rt_core.scene import SceneError  # noqa: E402
from rt_core.tracer import prepare  # noqa: E402
from rt_core.usererror import InputError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
COURSE = REPO.parent / "shared" / "course-scenes"
SCENES = sorted(REPO.glob("scenes/*.txt")) + sorted(COURSE.glob("*/*.txt"))
TEXTS = {p: p.read_bytes() for p in SCENES}
LONG = int(os.environ.get("RTVAL_FUZZ_EXAMPLES", "3000"))

WHERE = re.compile(r"^fuzz\.txt:\d+:\d+: \S")
# extreme numbers (they parse: the trouble comes later) and junk (it must not parse)
NUMBERS = ["1e308", "-1e308", "1e-320", "-1e-320", "1e300", "1e-300", "0", "-0", "0.0", "1e154",
           "3e38", "1e-45", "9" * 400, "15", "13", "10", "16", "2"]
JUNK = ["nan", "inf", "-inf", "1e400", "x", "#", "\x00", "-", ".", "1e", "+", "fplane",
        "sphere", "pointlight", "99", "\ufeff", "\r", "é", "1,5", "0x10"]


def _parses(data: bytes) -> bool:
    try:
        parse_text(data, "x")
        return True
    except SceneError:
        return False


READABLE = [p for p in SCENES if _parses(TEXTS[p])]


def _words(data: bytes) -> list:
    """Alternating [space, word, space, word, ...] pieces of the file; the odd ones are words."""
    return re.split(rb"(\S+)", data)


@st.composite
def mutated(draw):
    """A real scene's bytes with a few random edits, a third of them in the header (the world
    window and viewpoint: every number of the image depends on them)."""
    path = draw(st.sampled_from(READABLE if READABLE and draw(st.integers(0, 4)) else SCENES))
    toks = _words(TEXTS[path])
    for _ in range(draw(st.integers(1, 4))):
        words = [i for i in range(1, len(toks), 2)
                 if toks[i] and not toks[i].startswith(b"#")]
        if not words:
            break
        header = words[:5]
        i = draw(st.sampled_from(header) if header and draw(st.integers(0, 2)) == 0
                 else st.sampled_from(words))
        op = draw(st.sampled_from(["delete", "duplicate", "number", "number", "line", "line",
                                   "junk", "cut", "insert"]))
        if op == "delete":
            toks[i] = b""
        elif op == "duplicate":
            toks[i] = toks[i] + b" " + toks[i]
        elif op in ("number", "junk"):
            toks[i] = draw(st.sampled_from(NUMBERS if op == "number" else JUNK)).encode()
        elif op == "line":      # every number on the word's line: a whole point or centre
            value = draw(st.sampled_from(NUMBERS)).encode()
            j = i
            while j < len(toks) and b"\n" not in toks[j - 1 if j == i else j]:
                if j % 2 and re.fullmatch(rb"[-+.0-9eE]+", toks[j]):
                    toks[j] = value
                j += 1
            k = i - 1
            while k > 0 and b"\n" not in toks[k]:
                if k % 2 and re.fullmatch(rb"[-+.0-9eE]+", toks[k]):
                    toks[k] = value
                k -= 1
        elif op == "cut":
            toks = toks[:i]
        else:
            toks[i] = toks[i] + draw(st.binary(min_size=1, max_size=6))
    return b"".join(toks)


def _check_scene(data: bytes) -> None:
    try:
        scene = parse_text(data, "fuzz.txt")
    except SceneError as e:
        assert WHERE.match(str(e)) and "\n" not in str(e), str(e)
        return
    T = backend.types("f64", "llvm")
    try:
        cam = make_camera(scene, 8)             # the default rows: int(h/w·8)
        assert cam.columns == 8
        if scene.objects:
            prepare(scene, T)                  # host constants only: nothing is traced
    except SceneError as e:
        assert WHERE.match(str(e)) and "\n" not in str(e), str(e)
    except InputError as e:
        assert "\n" not in str(e)


SETTINGS = dict(deadline=None, suppress_health_check=list(HealthCheck), database=None)


@pytest.mark.skipif(not SCENES, reason="no scenes")
@settings(max_examples=1000, derandomize=True, **SETTINGS)
@given(mutated())
def test01_mutated_scenes_parse_or_fail_in_one_line(data):
    _check_scene(data)


@pytest.mark.slow
@settings(max_examples=LONG, **SETTINGS)
@given(mutated())
def test02_mutated_scenes_long(data):
    _check_scene(data)


# --- EXRs -------------------------------------------------------------------------------------

def _exr_variants(d: Path) -> list[Path]:
    import OpenEXR
    from tests.exrgen import write_deep, write_parts
    rng = np.random.default_rng(7)
    out = []
    write_exr(str(d / "plain.exr"), {"hit.mask": rng.random((12, 9)) > 0.5,
                                     "depth.Z": rng.random((12, 9))})
    out.append(d / "plain.exr")
    td = OpenEXR.TileDescription()
    td.xSize, td.ySize = 8, 8
    td.mode, td.roundingMode = OpenEXR.ONE_LEVEL, OpenEXR.ROUND_DOWN
    OpenEXR.File({"type": OpenEXR.tiledimage, "tiles": td,
                  "compression": OpenEXR.ZIP_COMPRESSION},
                 {"R": rng.random((20, 30)).astype(np.float16),
                  "id": np.arange(600, dtype=np.uint32).reshape(20, 30)}).write(
        str(d / "tiled.exr"))
    out.append(d / "tiled.exr")
    write_deep(d / "deep.exr")
    out.append(d / "deep.exr")
    write_parts(d / "multi.exr", [(c, c, rng.random((5, 6))) for c in ("a", "b")],
                OpenEXR.PIZ_COMPRESSION)
    out.append(d / "multi.exr")
    return out


@pytest.fixture(scope="module")
def exr_bytes(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_exr")
    return [p.read_bytes() for p in _exr_variants(d)]


def _check_exr(path: Path) -> None:
    from tools import exrtool
    for fn in (exrtool.info, exrtool.stats):
        try:
            fn(str(path))
        except ExrError as e:
            assert str(e).startswith(str(path)) and "\n" not in str(e), str(e)


@pytest.mark.parametrize("k", range(4))
def test03_every_exr_kind_reads_or_fails_in_one_line(exr_bytes, tmp_path, k):
    p = tmp_path / "f.exr"
    p.write_bytes(exr_bytes[k])
    _check_exr(p)


@st.composite
def damaged(draw, sources):
    data = bytearray(draw(st.sampled_from(sources)))
    op = draw(st.sampled_from(["truncate", "flip", "zero"]))
    i = draw(st.integers(0, max(0, len(data) - 1)))
    if op == "truncate":
        del data[i:]
    elif op == "flip":
        for _ in range(draw(st.integers(1, 8))):
            j = draw(st.integers(0, max(0, len(data) - 1)))
            data[j] ^= 1 << draw(st.integers(0, 7))
    else:
        data[i:i + draw(st.integers(1, 64))] = b"\0" * len(data[i:i + 64][:64])
    return bytes(data)


def _damaged_exrs(exr_bytes, tmp_path, **how) -> None:
    @settings(**how, **SETTINGS)
    @given(damaged(exr_bytes))
    def run(data):
        p = tmp_path / "d.exr"
        p.write_bytes(data)
        _check_exr(p)
    run()


def test04_damaged_exrs_read_or_fail_in_one_line(exr_bytes, tmp_path):
    _damaged_exrs(exr_bytes, tmp_path, max_examples=150, derandomize=True)


@pytest.mark.slow
def test05_damaged_exrs_long(exr_bytes, tmp_path):
    _damaged_exrs(exr_bytes, tmp_path, max_examples=LONG)


# --- images a course tracer wrote (rtval check) ----------------------------------------------

@pytest.fixture(scope="module")
def image_bytes(tmp_path_factory):
    from rt_core.imageio import ppm_bytes, write_png
    d = tmp_path_factory.mktemp("fuzz_img")
    px = np.random.default_rng(3).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    write_png(str(d / "a.png"), px)
    p3 = "P3\n# a comment\n9 7\n255\n" + " ".join(map(str, px.ravel())) + "\n"
    return [ppm_bytes(px), (d / "a.png").read_bytes(), p3.encode()]


def test06_damaged_images_read_or_fail_in_one_line(image_bytes, tmp_path):
    from rt_core.imageio import ImageError, read_image

    @settings(max_examples=300, derandomize=True, **SETTINGS)
    @given(damaged(image_bytes))
    def run(data):
        p = tmp_path / "t.img"
        p.write_bytes(data)
        try:
            img = read_image(str(p))
        except ImageError as e:
            assert str(e).startswith(str(p)) and "\n" not in str(e), str(e)
            return
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
    run()
