"""Reading and writing images through OpenImageIO (rt_core/imageio.py): the course tracers'
PPMs in their variants, PNG, EXR channels with their types, and one-line errors."""
from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from rt_core.exrio import write_exr
from rt_core.imageio import (ImageError, ppm_bytes, read_channels, read_image, write_png,
                             write_ppm)

PX = np.array([[[255, 0, 7], [1, 2, 3]], [[10, 20, 30], [200, 100, 50]]], np.uint8)  # 2 x 2


@pytest.mark.parametrize("name, data, expected", [
    ("course.ppm", b"P6 2 2 255\n" + PX.tobytes(), PX),
    ("lines.ppm", b"P6\n2\n2\n255\n" + PX.tobytes(), PX),           # rocketman768's header
    ("ascii.ppm", b"P3\n# a comment\n2 2\n255\n" + " ".join(map(str, PX.ravel())).encode(),
     PX),
    ("wide.ppm", b"P6 2 2 65535\n" + (PX.astype(">u2") * 257).tobytes(), PX),   # 16 bits
    ("grey.pgm", b"P5 2 2 255\n" + PX[..., 0].tobytes(), np.repeat(PX[..., :1], 3, -1)),
])
def test01_read_image_variants(tmp_path, name, data, expected):
    p = tmp_path / name
    p.write_bytes(data)
    img = read_image(str(p))
    assert img.dtype == np.uint8 and img.shape == (2, 2, 3)
    np.testing.assert_array_equal(img, expected)


def test02_png_round_trip_with_provenance(tmp_path):
    p = tmp_path / "a.png"
    write_png(str(p), PX, {"rtval.scene": "scenes/x.txt", "rtval.version": "0.1.0"})
    with Image.open(p) as im:              # read back by another library
        assert im.format == "PNG" and im.text["rtval.scene"] == "scenes/x.txt"
        np.testing.assert_array_equal(np.asarray(im.convert("RGB")), PX)
    np.testing.assert_array_equal(read_image(str(p)), PX)
    rgba = tmp_path / "rgba.png"
    Image.fromarray(np.concatenate([PX, np.full((2, 2, 1), 9, np.uint8)], -1)).save(rgba)
    np.testing.assert_array_equal(read_image(str(rgba)), PX)    # as stored; alpha dropped


def test03_course_ppm_bytes_and_channels_of_each_format(tmp_path):
    ppm = tmp_path / "a.ppm"
    write_ppm(str(ppm), PX)
    assert ppm.read_bytes() == b"P6 2 2 255\n" + PX.tobytes() == ppm_bytes(PX)
    d = read_channels(str(ppm))
    assert d.format == "pnm" and sorted(d.channels) == ["B", "G", "R"]
    assert set(d.types.values()) == {"UINT8"}
    # integer formats come as OpenImageIO's normalised floats, as idiff compares them
    np.testing.assert_array_equal(d.channels["R"], PX[..., 0] * np.float32(1 / 255))
    exr = tmp_path / "a.exr"
    ids = np.array([[7, 0], [2 ** 32 - 1, 3]], np.uint32)
    write_exr(str(exr), {"object.id": ids, "depth.Z": np.ones((2, 2))}, {"rtval.x": "y"})
    d = read_channels(str(exr))
    assert d.types == {"object.id": "UINT", "depth.Z": "FLOAT"}
    assert d.channels["object.id"].dtype == np.uint32          # an EXR's UINT: the integers
    np.testing.assert_array_equal(d.channels["object.id"], ids)
    assert d.header["rtval.x"] == "y" and d.header["compression"] == "piz"


@pytest.mark.parametrize("name, data, why", [
    ("short.ppm", b"P6 40 30 255\n" + b"\0" * 100,
     "the header says 40x30 pixels, 3600 bytes of samples; the file holds 100"),
    # a course program's header mistakes, in its words (a student's review found them
    # reported as 'Premature end of file' and 'no reason given')
    ("max256.ppm", b"P6\n4 3\n256\n" + bytes(36), "maxval 256 means two bytes a sample, "
     "but the file holds 36 bytes for 4x3 pixels, one a sample: write maxval 255"),
    ("p3bin.ppm", b"P3\n4 3\n255\n" + bytes(range(200, 236)),
     "a P3 (ASCII) header over binary samples: write P6 for bytes"),
    ("short.png", None, "truncated or corrupt"),
    ("header.png", 500, "cannot read it as an image ("),      # cut in its text chunk
    ("text.ppm", b"P6 garbage\n", "the header's width is 'garbage', not a number; a P6 "
     "header is 'P6 width height maxval' and one whitespace byte"),
    # header mistakes OpenImageIO said only 'Could not parse spec for file' about (a
    # student's review): the maxval's newline left out, no maxval, a magic in lower case,
    # a magic the course does not write, a text file named .ppm
    ("nows.ppm", b"P6\n4 3\n255" + bytes(36), "no whitespace byte after the maxval 255 "
     "(byte 10 is 0x00): the samples were written right after it"),
    ("nomax.ppm", b"P6\n4 3\n" + bytes(36), "no maxval after the height (byte 7 is 0x00"),
    ("lower.ppm", b"p6\n4 3\n255\n" + bytes(36), "the magic number is 'p6', lower case; a "
     "PPM starts with 'P6' (binary samples) or 'P3' (ASCII)"),
    ("p7.ppm", b"P7\n4 3\n255\n" + bytes(36), "the magic number is 'P7', not a PPM's"),
    ("hello.ppm", b"hello\n", "not a PPM: a PPM starts with 'P6' (binary samples) or 'P3' "
     "(ASCII), this file with 'hello\\n' (text)"),
    # samples printed as numbers under a binary header: it read as rows too many, or too
    # few bytes (a student's review)
    ("p6ascii.ppm", b"P6\n4 3\n255\n" + b"0 0 0 " * 12, "a P6 (binary) header over ASCII "
     "samples (numbers written as text): write P3 for numbers, or the samples as bytes"),
    ("p6ascii2.ppm", b"P6\n4 3\n255\n12 34 56 78\n", "a P6 (binary) header over ASCII"),
    # a binary sample above a maxval below 255, which OpenImageIO scaled and clamped: a
    # tracer's 255 under maxval 1 read as white (an ASCII one is refused: over.ppm)
    ("max1.ppm", b"P6\n2 1\n1\n" + bytes([0, 1, 0, 0, 255, 1]),
     "sample 255 above the maxval 1 (column 1, row 0; 1 samples in all)"),
    ("max1000.ppm", b"P5\n2 1\n1000\n" + np.array([5, 1001], ">u2").tobytes(),
     "sample 1001 above the maxval 1000 (column 1, row 0"),
    ("maxval0.ppm", b"P6 4 3 0\n" + bytes(36), "maxval is 0; expected 1 to 65535"),
    ("over.ppm", b"P3\n# c\n2 1\n255\n1 2 3\n300 0 0\n", "ppm:6: sample 300 above the maxval 255"),
    # on the maxval's own line, after a comment naming a larger number
    ("over1.ppm", b"P3 2 1 255 256 2 3 # 999\n0 0 0\n", "ppm:1: sample 256 above the maxval"),
    ("over2.ppm", b"P3 2 1 255\n# 999\n1 2 3 0 0\n0 7 400\n", "ppm:4: sample 400 above"),
    # OpenImageIO read a negative sample, or a float image's NaN, as 0: black that matched
    # (a helper's review)
    ("neg.ppm", b"P3 2 1 255\n1 2 3\n0 -1 0\n", "ppm:3: sample -1 below 0"),
    ("nan.pfm", b"PF\n2 1\n-1.0\n" + np.array([0.5, 0.5, 0.5, np.nan, 0, 0],
                                                 "<f4").tobytes(),
     "1 samples are NaN or infinite (the first at column 1, row 0: nan)"),
    ("empty.png", b"", "the file is empty"),
    # more samples than the header says, which OpenImageIO read without a word (a student's
    # review: an extra row passed, a text-mode file was wrong at every pixel with no hint)
    # an ASCII PPM's samples that OpenImageIO could not read ('no reason given')
    ("p3short.ppm", b"P3\n2 2\n255\n255 0 0 0 255 0\n0 0 255\n",
     "truncated: the header says 2x2 pixels, 12 samples; the file holds 9"),
    ("p3float.ppm", b"P3\n2 2\n255\n255 0 0\n# 1.5\n0 255 12.0\n0 0 255 1 1 1\n",
     "line 6: sample 6 is '12.0'; an ASCII PPM's samples are whole numbers"),
    ("p3comma.ppm", b"P3 2 1 255\n255,0,0 0,0,0\n", "line 2: sample 1 is '255,0,0'"),
    ("crlf.ppm", b"P6\r\n4 3\r\n255\r\n" + bytes(36), "the header's lines end in CR LF"),
    ("row.ppm", b"P6\n4 3\n255\n" + bytes(48), "the file holds 48, 1 row more"),
    ("rows16.ppm", b"P6 4 3 65535\n" + bytes(72 + 48), "the file holds 120, 2 rows more"),
    # OpenImageIO's 'could not find a format reader for "x"' without the name read 'for)'
    ("notimg.dat", b"hello\n", "could not find a format reader for it)"),
    # a tracer's debugging output before its image on standard output (an instructor's
    # review: 'Could not parse spec for file' sent the student looking at the format)
    ("done.ppm", b"P6 4 3 255\n" + bytes(36) + b"done in 0.2 s\n",
     "14 bytes after the pixels end in text ('done in 0.2 s'): the tracer printed messages"),
    ("debug.ppm", b"DEBUG x=3\nrows 3\nP6 4 3 255\n" + bytes(36),
     "17 bytes of text before the PPM header (P6 at byte 17), the first 'DEBUG x=3': the "
     "tracer printed messages to standard output"),
    # (a review: without a newline, or not ASCII, it was the old message)
    ("nonl.ppm", "Rendering… ✓P6 4 3 255\n".encode() + bytes(36),
     "16 bytes of text before the PPM header (P6 at byte 16), the first 'Rendering… ✓'"),
    ("done2.ppm", b"P6 4 3 255\n" + bytes(36) + b"Done.",
     "5 bytes after the pixels end in text ('Done.')"),
])
def test04_unreadable_images_are_one_line(tmp_path, name, data, why, capfd):
    p = tmp_path / name
    if data is None or isinstance(data, int):   # a PNG cut in half, or after ``data`` bytes
        write_png(str(tmp_path / "whole.png"),
                  np.random.default_rng(0).integers(0, 256, (40, 30, 3), np.uint8),
                  {"rtval.note": "x" * 1000})
        whole = (tmp_path / "whole.png").read_bytes()
        data = whole[: len(whole) // 2 if data is None else data]
    p.write_bytes(data)
    capfd.readouterr()
    with pytest.raises(ImageError) as e:
        read_image(str(p))
    msg = str(e.value)
    assert msg.startswith(f"{p}:") and why in msg and "\n" not in msg, msg
    # nothing printed besides (libpng's own "libpng error: ..." on descriptor 2)
    assert capfd.readouterr() == ("", "")


def test04b_a_final_newline_or_a_cr_sample_is_fine(tmp_path):
    """A byte or so beyond the samples (a final newline) is no error, nor a header whose
    last byte is CR before a first sample of 10."""
    for data in (b"P6\n4 3\n255\n" + bytes(36) + b"\n",
                 b"P6\n4 3\n255\r" + bytes([10]) + bytes(35),
                 # an extra pixel or two whose bytes happen to be letters: not taken for
                 # text printed after the image (a review)
                 b"P6 4 3 255\n" + bytes(36) + b"ddd",
                 b"P6 4 3 255\n" + bytes(36) + b"dddddd"):
        p = tmp_path / "ok.ppm"
        p.write_bytes(data)
        assert read_image(str(p)).shape == (3, 4, 3), data[-8:]
    p.write_bytes(b"P5 4 3 255\n" + bytes(12) + b"AB")
    assert read_image(str(p)).shape == (3, 4, 3)


def test05_a_size_beyond_memory_is_refused_before_reading(tmp_path, monkeypatch):
    import rt_core.memory as memory
    p = tmp_path / "big.ppm"
    p.write_bytes(b"P6 3000 2000 255\n" + b"\0" * 10)          # claims 18 MB of pixels
    monkeypatch.setattr(memory, "available", lambda: (1e6, "a test"))
    with pytest.raises(ImageError, match=r"big\.ppm: its 3000 x 2000 pixels need 18 MB, 1 MB "
                                         r"available \(a test\); is the file damaged\?"):
        read_image(str(p))


def test06_header_bytes_that_are_not_utf8_are_one_line(tmp_path):
    """A damaged header whose names are not UTF-8: OpenImageIO's message quotes them, and
    reading that message must not raise (hypothesis found it in tests/test_fuzz.py)."""
    p = tmp_path / "a.exr"
    write_exr(str(p), {"depth.Z": np.ones((3, 4))})
    data = p.read_bytes()
    assert data.count(b"compression\x00compression") == data.count(b"channels\x00chlist") == 1
    # (hypothesis's case: the channel list renamed, the next name run into its type)
    data = data.replace(b"channels\x00chlist", b"bhannels\x00chlist")
    p.write_bytes(data.replace(b"compression\x00compression", b"compression\x80compression"))
    for read in (read_channels, read_image):
        with pytest.raises(ImageError) as e:
            read(str(p))
        assert str(e.value).startswith(f"{p}: ") and "\n" not in str(e.value)
