"""Inspect and compare images the way iinfo, ``oiiotool --stats`` and idiff do, through
OpenImageIO: any format it reads (EXR, PPM, PNG, TIFF, ...).

OpenImageIO does the image work: reading (``rt_core.imageio.read_channels``), the statistics
(``ImageBufAlgo.computePixelStats``), the comparison (``ImageBufAlgo.compare``: mean, RMS,
PSNR, the worst value, failing and warning pixel counts) and the difference image
(``ImageBufAlgo.absdiff``); NVIDIA FLIP (``flip_evaluator``) the perceptual comparison.  What
stays here is rtval's policy around them: the channel selection, idiff's verdict, and
non-finite values, which OpenImageIO's comparison lets pass (a NaN against a number, +Inf
against -Inf) and rtval counts as failing pixels.

Every function returns plain data (dicts of numbers, strings and lists) and raises
:class:`rt_core.exrio.ExrError` for a file that cannot be read or written or a requested
channel that is missing; nothing here prints or exits.  ``tools/cmd_exr.py`` formats the
results and maps them to exit codes.
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from rt_core.exrio import ExrError, write_exr
from rt_core.outputs import WriteError
from tools.harness.flip import flip_colours, flip_map

# idiff's process return codes
PASS, WARN, FAIL, MISMATCH, FILE_ERROR = 0, 1, 2, 3, 4
STATUS_NAMES = {PASS: "PASS", WARN: "WARNING", FAIL: "FAILURE", MISMATCH: "MISMATCH"}

HIT_MASK = "hit.mask"
DIFF_KIND = "diff"          # value of the rtval.kind attribute of a difference image
FLIP_KIND = "flip"          # ... and of a FLIP error map
METRICS = ("idiff", "flip")
FLIP_CHANNELS = ("R", "G", "B")


def _oiio():
    import OpenImageIO
    return OpenImageIO


# ----------------------------------------------------------------------------- loading

@dataclass
class Image:
    """One image file: ``channels`` {name: 2-D array} and ``types`` {name: pixel type},
    sorted by name, its header, and what OpenImageIO says of it (``data``)."""
    path: str
    channels: dict
    header: dict
    types: dict
    data: object = None          # rt_core.imageio.ImageData

    @property
    def height(self) -> int:
        return self.data.height

    @property
    def width(self) -> int:
        return self.data.width

    def hit(self) -> np.ndarray | None:
        """Boolean hit mask from ``hit.mask`` (> 0.5), or None if the file has none."""
        m = self.channels.get(HIT_MASK)
        return None if m is None else np.asarray(m, dtype=np.float64) > 0.5


def load(path, deep_ok: bool = False) -> Image:
    """Read ``path`` (any format OpenImageIO reads); ExrError (one line naming the file) if
    it is unreadable or empty.  Every part of a multi-part file is read (channels
    ``part.channel``); a deep file only with ``deep_ok`` (``info``: no pixels kept)."""
    from rt_core.imageio import read_channels
    path = os.fspath(path)
    data = read_channels(path, deep_ok, "EXR or other image", ExrError)
    if not data.types:
        raise ExrError(f"{path}: the file has no channels")
    # (an EXR's channels by name, as OpenEXR stores them; another image's in its own
    # order, R, G, B)
    order = sorted if data.format == "openexr" else list
    return Image(path, {k: data.channels[k] for k in order(data.channels)}, data.header,
                 {k: data.types[k] for k in order(data.types)}, data)


def select_channels(img: Image, requested=None) -> list[str]:
    """Resolve channel names; a layer name (``normal``) selects all of its channels.

    ``requested`` is None for every channel.  ExrError names the file and the channel.
    """
    if not requested:
        return list(img.channels)
    out: list[str] = []
    for name in requested:
        if name in img.channels:
            found = [name]
        else:
            found = [c for c in img.channels if c.rsplit(".", 1)[0] == name and "." in c]
        if not found:
            raise ExrError(f"{img.path}: no channel {name!r}; the file has "
                           f"{', '.join(img.channels)}")
        out.extend(c for c in found if c not in out)
    return out


def _buf(pixels: np.ndarray):
    """A float ImageBuf of (rows, columns, channels) ``pixels``."""
    oiio = _oiio()
    a = np.ascontiguousarray(pixels, np.float32)
    buf = oiio.ImageBuf(oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2], "float"))
    buf.set_pixels(oiio.ROI(), a)
    return buf


def _stack(img: Image, names) -> np.ndarray:
    """The channels as one (rows, columns, channels) float32 array (a UINT id as its value)."""
    return np.stack([np.asarray(img.channels[n]).astype(np.float32, copy=False)
                     for n in names], -1)


# ----------------------------------------------------------------------------- info

def _plain(value):
    """A header value as JSON-ready data: tuples and arrays as lists."""
    if isinstance(value, (str, bool, int, float)) or value is None:
        return value
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    return str(value)


def _storage(data) -> str:
    """The file's layout in OpenEXR's words (its part ``type``)."""
    return ("deep" + ("tile" if data.tiled else "scanline") if data.deep
            else ("tiledimage" if data.tiled else "scanlineimage"))


def info(path) -> dict:
    """Format, size, windows, compression, channels with pixel types, and every header
    attribute as OpenImageIO names it (``iinfo -v``); the pixels are read, so a truncated
    file is an error.  ``provenance`` repeats the ``rtval.*`` attributes."""
    img = load(path, deep_ok=True)
    d = img.data
    attrs = {k: _plain(v) for k, v in sorted(img.header.items())}
    return {
        "file": img.path,
        "format": d.format,
        "width": img.width,
        "height": img.height,
        "compression": attrs.get("compression"),
        "data_window": d.data_window,
        "display_window": d.display_window,
        "channels": [{"name": n, "type": t} for n, t in img.types.items()],
        "parts": d.parts,
        "storage": _storage(d),
        "layers": _layers(img.types),
        "attributes": attrs,
        "provenance": {k: v for k, v in attrs.items() if k.startswith("rtval.")},
    }


def _layers(names) -> dict:
    """Group ``layer.channel`` names the way tev does: {layer: [channel, ...]}."""
    layers: dict = {}
    for n in names:
        layer, _, chan = n.rpartition(".")
        layers.setdefault(layer, []).append(chan)
    return layers


# ----------------------------------------------------------------------------- stats

def _pixel_stats(pixels: np.ndarray) -> list[dict]:
    """OpenImageIO's computePixelStats of (rows, columns, channels) values: per channel
    min/max/mean/std over the finite values (std: the population standard deviation;
    float32, as ``oiiotool --stats`` prints them) and the NaN/Inf/finite counts."""
    if not pixels.size:                     # (no values: OpenImageIO makes no buffer of them)
        return [{"count": 0, "finite": 0, "nan": 0, "inf": 0, "min": None, "max": None,
                 "mean": None, "std": None} for _ in range(pixels.shape[2])]
    oiio = _oiio()
    st = oiio.ImageBufAlgo.computePixelStats(_buf(pixels))
    out = []
    for c in range(pixels.shape[2]):
        n = int(st.finitecount[c])
        out.append({"count": n + int(st.nancount[c]) + int(st.infcount[c]), "finite": n,
                    "nan": int(st.nancount[c]), "inf": int(st.infcount[c]),
                    "min": float(st.min[c]) if n else None,
                    "max": float(st.max[c]) if n else None,
                    "mean": float(st.avg[c]) if n else None,
                    "std": float(st.stddev[c]) if n else None})
    return out


def _summary(values: np.ndarray) -> dict:
    """The statistics of any set of values (a 1 x N image of them)."""
    return _pixel_stats(np.asarray(values, np.float32).reshape(1, -1, 1))[0]


def stats(path, channels=None) -> dict:
    """Per-channel statistics; ``depth.*`` channels also get ``hit`` stats over hit pixels.

    ``hit`` is None for a depth channel when the file has no ``hit.mask``.
    """
    img = load(path)
    names = select_channels(img, channels)
    hit = img.hit()
    result = {"file": img.path, "width": img.width, "height": img.height, "channels": {}}
    for name, s in zip(names, _pixel_stats(_stack(img, names))):
        s["type"] = img.types[name]
        if name.split(".", 1)[0] == "depth":
            s["hit"] = None if hit is None else _summary(np.asarray(img.channels[name])[hit])
        result["channels"][name] = s
    return result


# ----------------------------------------------------------------------------- diff

@dataclass(frozen=True)
class Thresholds:
    """idiff's limits.  A pixel *fails* when, in any channel, its error exceeds both ``fail``
    (absolute) and ``fail_relative`` times the mean of |a| and |b|; likewise it *warns*.
    As idiff decides: the comparison PASSES when at most ``allow_failures`` pixels fail
    (whatever the warnings and the hard limits); otherwise it FAILS if more pixels fail
    than ``fail_percent`` % of the pixels or an error exceeds ``hard_fail``; otherwise it
    WARNS if more than ``warn_percent`` % of the pixels warn or an error exceeds
    ``hard_warn``; else it PASSES.
    """
    fail: float = 1e-6
    fail_relative: float = 0.0
    fail_percent: float = 0.0
    hard_fail: float = math.inf
    warn: float = 1e-6
    warn_relative: float = 0.0
    warn_percent: float = 0.0
    hard_warn: float = math.inf
    allow_failures: int = 0

    def __post_init__(self):
        for k, v in asdict(self).items():
            if not (v >= 0):          # also rejects NaN
                raise ValueError(f"threshold {k} must be >= 0, got {v}")
        for k in ("fail_percent", "warn_percent"):
            if getattr(self, k) > 100:
                raise ValueError(f"threshold {k} must be <= 100, got {getattr(self, k)}")


def verdict(n_fail: int, n_warn: int, max_err: float, npix: int,
            th: Thresholds) -> tuple[int, list[str]]:
    """(PASS/WARN/FAIL, reasons) from the pixel counts, as idiff decides (Thresholds)."""
    if n_fail <= th.allow_failures:
        if n_fail:
            return PASS, [f"{n_fail} failing pixels allowed (--allow-failures "
                          f"{th.allow_failures})"]
        return PASS, []
    reasons = []
    if n_fail > th.fail_percent / 100.0 * npix:
        reasons.append(f"{n_fail} failing pixels > {th.allow_failures} allowed and > "
                       f"{th.fail_percent:g}% of {npix}")
    if max_err > th.hard_fail:
        reasons.append(f"max error {max_err:g} exceeds the hard-fail limit {th.hard_fail:g}")
    if reasons:
        return FAIL, reasons
    if n_warn > th.warn_percent / 100.0 * npix:
        reasons.append(f"{n_warn} warning pixels > {th.warn_percent:g}% of {npix} "
                       f"({n_fail} failing pixels within --fail-percent)")
    if max_err > th.hard_warn:
        reasons.append(f"max error {max_err:g} exceeds the hard-warn limit {th.hard_warn:g}")
    return (WARN if reasons else PASS), reasons


def _mismatch(a: Image, b: Image, names_a, names_b, requested) -> str | None:
    if (a.width, a.height) != (b.width, b.height):
        return (f"size mismatch: {a.path} is {a.width} x {a.height}, "
                f"{b.path} is {b.width} x {b.height}")
    if not requested and names_a != names_b:
        only_a = [n for n in names_a if n not in names_b]
        only_b = [n for n in names_b if n not in names_a]
        parts = []
        if only_a:
            parts.append(f"only in {a.path}: {', '.join(only_a)}")
        if only_b:
            parts.append(f"only in {b.path}: {', '.join(only_b)}")
        return "channel mismatch: " + "; ".join(parts) + " (compare a subset with --channels)"
    return None


def _scalar(x) -> float | int:
    """A pixel value as a Python number (float for HALF/FLOAT, int for UINT)."""
    return x.item() if isinstance(x, np.generic) else x


def _compare(A, B, th: Thresholds, roi=None):
    """OpenImageIO's CompareResults of two float ImageBufs (idiff's figures)."""
    oiio = _oiio()
    return oiio.ImageBufAlgo.compare(A, B, th.fail, th.warn, th.fail_relative,
                                     th.warn_relative, oiio.ROI() if roi is None else roi)


def diff(path_a, path_b, channels=None, thresholds: Thresholds | None = None,
         diff_out=None, metric: str = "idiff") -> dict:
    """Compare two images channel by channel with idiff's semantics (``metric`` idiff) or
    by NVIDIA FLIP (``metric`` flip: ``flip_diff``).

    Returns a dict with ``status`` (PASS, WARNING, FAILURE or MISMATCH) and ``exit_code``
    (0, 1, 2, 3), OpenImageIO's mean/RMS error and PSNR (over all values, a non-finite
    one counting 0, as idiff reports them), the max error and the worst pixel (x, y,
    channel and both values), failing/warning pixel counts and per-channel errors.
    NaN matches only NaN and Inf only the same-signed Inf; any other pairing with a
    non-finite value is an infinite error, so that pixel fails and warns (OpenImageIO's
    comparison would let it pass).  ``diff_out`` writes |A - B| per channel (0 where
    non-finite values match, Inf where they do not), atomically, unless the images cannot
    be compared (MISMATCH).
    """
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    th = thresholds or Thresholds()
    a, b = load(path_a), load(path_b)
    if metric == "flip":
        channels = channels or list(FLIP_CHANNELS)
    names_a, names_b = select_channels(a, channels), select_channels(b, channels)
    result = {"file_a": a.path, "file_b": b.path, "width": a.width, "height": a.height,
              "metric": metric, "thresholds": asdict(th)}
    why = _mismatch(a, b, names_a, names_b, channels)
    if why:
        result.update(status=STATUS_NAMES[MISMATCH], exit_code=MISMATCH, reason=why,
                      channels_a=names_a, channels_b=names_b)
        return result
    if metric == "flip":
        return _flip_diff(a, b, names_a, th, diff_out, result)
    names = names_a
    A, B = _stack(a, names), _stack(b, names)
    H, W, C = A.shape
    npix = H * W

    # rtval's non-finite policy; every other value goes to OpenImageIO (non-finite ones as 0)
    finite = np.isfinite(A) & np.isfinite(B)
    same_nonfinite = (np.isnan(A) & np.isnan(B)) | (np.isinf(A) & (A == B))
    bad = ~finite & ~same_nonfinite
    A0, B0 = _buf(np.where(finite, A, 0.0)), _buf(np.where(finite, B, 0.0))
    cr = _compare(A0, B0, th)
    n_fail, n_warn = cr.nfail, cr.nwarn
    bad_pix = bad.any(-1)
    if bad_pix.any():
        # a pixel with a non-finite mismatch fails and warns; count the others without it
        keep = ~bad_pix[..., None]
        cr_rest = _compare(_buf(np.where(keep, np.where(finite, A, 0.0), 0.0)),
                           _buf(np.where(keep, np.where(finite, B, 0.0), 0.0)), th)
        n_bad = int(bad_pix.sum())
        n_fail, n_warn = cr_rest.nfail + n_bad, cr_rest.nwarn + n_bad
        y, x, c = np.unravel_index(int(np.argmax(bad)), bad.shape)   # first in scan order
        max_err = math.inf
    else:
        x, y, c, max_err = cr.maxx, cr.maxy, cr.maxc, float(cr.maxerror)
    worst = None
    if max_err > 0:
        va, vb = _scalar(a.channels[names[c]][y, x]), _scalar(b.channels[names[c]][y, x])
        mean_abs = 0.5 * (abs(float(va)) + abs(float(vb)))
        worst = {"x": int(x), "y": int(y), "channel": names[c], "error": max_err,
                 "relative_error": (max_err / mean_abs if mean_abs > 0 and
                                    math.isfinite(mean_abs) else math.inf),
                 "a": va, "b": vb}

    status, reasons = verdict(n_fail, n_warn, max_err, npix, th)
    oiio = _oiio()
    per_channel = {}
    for i, n in enumerate(names):
        ci = _compare(A0, B0, th, oiio.ROI(0, W, 0, H, 0, 1, i, i + 1))
        nb = bad[..., i]
        if nb.any():
            k = int(np.argmax(nb))
            where, cmax = [k % W, k // W], math.inf
        else:
            cmax = float(ci.maxerror)
            where = [int(ci.maxx), int(ci.maxy)] if cmax > 0 else None
        per_channel[n] = {
            "max_error": cmax, "mean_error": float(ci.meanerror),
            "rms_error": float(ci.rms_error), "worst": where,
            "failing_pixels": int(ci.nfail + nb.sum()),
            "warning_pixels": int(ci.nwarn + nb.sum()),
            "nonfinite_mismatches": int(nb.sum()),
        }

    result.update({
        "status": STATUS_NAMES[status], "exit_code": status, "reasons": reasons,
        "channels": names, "pixels": npix,
        "mean_error": float(cr.meanerror), "rms_error": float(cr.rms_error),
        "psnr": float(cr.PSNR), "max_error": max_err, "worst": worst,
        "compared_values": int(finite.sum()), "nonfinite_mismatches": int(bad.sum()),
        "failing_pixels": n_fail, "failing_percent": 100.0 * n_fail / npix if npix else 0.0,
        "warning_pixels": n_warn, "warning_percent": 100.0 * n_warn / npix if npix else 0.0,
        "per_channel": per_channel, "diff_image": None,
    })
    if diff_out is not None:
        err = oiio.ImageBufAlgo.absdiff(A0, B0).get_pixels(oiio.FLOAT)
        err = np.asarray(err, np.float32).reshape(H, W, C)
        # (NaN matches NaN and an infinity the same-signed one: 0 there, as in the counts)
        err[~np.isfinite(err)] = 0.0
        err[bad] = np.inf
        from rt_core.inputfile import file_sha256
        from rt_core.render import versions
        attrs = {"rtval.kind": DIFF_KIND, "rtval.diff.a": a.path, "rtval.diff.b": b.path,
                 "rtval.diff.a_sha256": file_sha256(a.path),
                 "rtval.diff.b_sha256": file_sha256(b.path),
                 "rtval.diff.status": STATUS_NAMES[status],
                 # (as every output: its count of values that are not finite, and what they
                 # mean here)
                 "rtval.nonfinite": str(int(np.count_nonzero(~np.isfinite(err)))),
                 "rtval.diff.nonfinite": "inf where A and B differ in a NaN or infinite value",
                 "rtval.versions": " ".join(f"{k}={v}" for k, v in versions().items())}
        result["diff_image"] = _write_exr(diff_out, {n: err[..., i] for i, n in
                                                     enumerate(names)}, attrs,
                                          "the difference image")
    return result


def _write_exr(out, channels: dict, attrs: dict, what: str) -> str:
    """Write an EXR atomically; ExrError (exit 4) naming ``out`` if it cannot be."""
    out = os.fspath(out)
    try:
        write_exr(out, channels, attrs)
    except ExrError:
        raise
    except WriteError as e:       # one line naming the target already; exr's code 4
        raise ExrError(str(e)) from None
    except Exception as e:
        raise ExrError(f"{out}: cannot write {what} ({_oneline(e)})") from None
    return out


def _oneline(e: BaseException) -> str:
    text = getattr(e, "strerror", None) or str(e) or type(e).__name__
    return text.splitlines()[0]


# ----------------------------------------------------------------------------- FLIP

def write_flip_map(out, err: np.ndarray, attrs: dict) -> str:
    """The FLIP error map: an EXR (channel ``flip``: the raw per-pixel error) or, for any
    other name, a magma-coloured PNG; atomically, with ``attrs`` as provenance."""
    out = os.fspath(out)
    if out.lower().endswith(".exr"):
        return _write_exr(out, {"flip": err}, attrs, "the FLIP error map")
    from rt_core.imageio import write_png
    try:
        write_png(out, flip_colours(err), attrs)
    except WriteError as e:
        raise ExrError(str(e)) from None
    except Exception as e:
        raise ExrError(f"{out}: cannot write the FLIP error map ({_oneline(e)})") from None
    return out


# the largest level of an integer pixel type (OpenImageIO reads level k as about k/M)
INT_LEVELS = {"UINT8": 255, "UINT16": 65535}


def _levels(img: Image, names) -> np.ndarray:
    """``_stack`` for FLIP: an 8- or 16-bit channel's values are levels k/M, which
    OpenImageIO reads within a float32 rounding of k/M, so that the same colour written in
    8 and in 16 bits (k/255 = 257k/65535) can come out an ulp apart, and FLIP, steep near 0,
    turns that ulp into an error of about 1e-4.  Each such value is taken as k/M rounded
    once from float64 instead: equal levels, equal floats."""
    out = _stack(img, names)
    for j, n in enumerate(names):
        m = INT_LEVELS.get(img.types.get(n))
        if m:
            out[..., j] = np.rint(out[..., j].astype(np.float64) * m) / m
    return out


def _flip_diff(a: Image, b: Image, names, th: Thresholds, out, result: dict) -> dict:
    """``diff`` with metric flip: A is the reference, B the test image; a pixel's error is
    its FLIP value, judged by the same thresholds and verdict as idiff's errors."""
    if len(names) != 3:
        raise ValueError(f"FLIP compares three colour channels, got {len(names)}")
    A, B = _levels(a, names), _levels(b, names)
    for img, arr in ((a, A), (b, B)):
        n_bad = int((~np.isfinite(arr)).sum())
        if n_bad:
            raise ExrError(f"{img.path}: FLIP needs finite colours; {n_bad} values of "
                           f"{', '.join(names)} are NaN or Inf (compare with the default "
                           "metric, which counts them)")
        if arr.min() < 0:
            raise ExrError(f"{img.path}: FLIP needs colours >= 0; the smallest of "
                           f"{', '.join(names)} is {float(arr.min()):g}")
    err, mean, params = flip_map(A, B)
    H, W = err.shape
    cr = _compare(_buf(err[..., None]), _buf(np.zeros((H, W, 1), np.float32)), th)
    max_err = float(cr.maxerror)
    status, reasons = verdict(cr.nfail, cr.nwarn, max_err, H * W, th)
    worst = None
    if max_err > 0:
        worst = {"x": int(cr.maxx), "y": int(cr.maxy), "channel": "flip", "error": max_err,
                 "a": [float(v) for v in A[cr.maxy, cr.maxx]],
                 "b": [float(v) for v in B[cr.maxy, cr.maxx]]}
    result.update({
        "status": STATUS_NAMES[status], "exit_code": status, "reasons": reasons,
        "channels": names, "pixels": H * W, "flip_mean": mean, "flip": params,
        "mean_error": mean, "max_error": max_err, "worst": worst,
        "failing_pixels": int(cr.nfail), "failing_percent": 100.0 * cr.nfail / (H * W),
        "warning_pixels": int(cr.nwarn), "warning_percent": 100.0 * cr.nwarn / (H * W),
        "flip_map": None,
    })
    if out is not None:
        attrs = {"rtval.kind": FLIP_KIND, "rtval.flip.reference": a.path,
                 "rtval.flip.test": b.path, "rtval.flip.mean": repr(mean),
                 "rtval.flip.channels": ",".join(names),
                 "rtval.flip.parameters": ", ".join(f"{k}={v}" for k, v in params.items()),
                 "rtval.diff.status": STATUS_NAMES[status]}
        result["flip_map"] = write_flip_map(out, err, attrs)
    return result


# ----------------------------------------------------------------------------- preview

PREVIEW_MIN_WIDTH = 256     # small images are enlarged by an integer factor to this width
PREVIEW_MAX_SIDE = 8192     # ... unless that makes them taller than this
LEGEND_HEIGHT = 40          # the colour bar strip below the image
NONFINITE_RGB = (255, 0, 255)       # NaN/Inf where a value was expected
NONFINITE_DIFF_RGB = (0, 255, 255)  # ...and in a difference image (inferno has magentas)


def preview_kind(img: Image, channel: str) -> str:
    """How a channel is shown: diff, depth, id, normal, mask, rgb or scalar."""
    if str(img.header.get("rtval.kind", "")) == DIFF_KIND:
        return "diff"
    layer = channel.rsplit(".", 1)[0] if "." in channel else ""
    if channel == HIT_MASK:
        return "mask"
    if layer == "depth":
        return "depth"
    if channel == "object.id":
        return "id"
    if layer == "normal" and all(f"normal.{k}" in img.channels for k in "XYZ"):
        return "normal"
    if channel in ("R", "G", "B") and all(k in img.channels for k in "RGB"):
        return "rgb"
    return "scalar"


def _id_colours(ids: np.ndarray) -> np.ndarray:
    """Distinct categorical colours: tab10, then tab20's light shades, then golden-ratio hues."""
    import matplotlib
    from matplotlib.colors import hsv_to_rgb
    tab20 = np.asarray(matplotlib.colormaps["tab20"].colors)
    table = np.concatenate([tab20[0::2], tab20[1::2]])
    ids = ids.astype(np.int64)
    out = np.empty(ids.shape + (3,))
    small = ids < len(table)
    out[small] = table[ids[small]]
    big = ids[~small]
    hue = (big * 0.6180339887498949) % 1.0
    out[~small] = hsv_to_rgb(np.stack([hue, np.full_like(hue, 0.7), np.full_like(hue, 0.95)], -1))
    return (out * 255 + 0.5).astype(np.uint8)


def _render(img: Image, channel: str, kind: str):
    """(H x W x 3 uint8 image, legend dict, ids shown or None) for one channel."""
    import matplotlib
    H, W = img.height, img.width
    rgb = np.zeros((H, W, 3), np.uint8)
    hit = img.hit() if kind not in ("diff", "mask", "rgb") else None
    shown = np.ones((H, W), bool) if hit is None else hit
    legend = {"kind": kind, "channel": channel}

    if kind in ("rgb", "normal"):
        keys = ["R", "G", "B"] if kind == "rgb" else [f"normal.{k}" for k in "XYZ"]
        v = np.stack([np.asarray(img.channels[k], np.float64) for k in keys], -1)
        fin = np.isfinite(v).all(-1)
        col = np.clip(v if kind == "rgb" else (v + 1.0) / 2.0, 0.0, 1.0)
        col = np.nan_to_num(col)
        sel = shown & fin
        rgb[sel] = (col[sel] * 255 + 0.5).astype(np.uint8)
        rgb[shown & ~fin] = NONFINITE_RGB
        vals = v[sel]
        legend.update(channels=keys,
                      min=[float(x) for x in vals.min(0)] if vals.size else None,
                      max=[float(x) for x in vals.max(0)] if vals.size else None,
                      caption=("RGB clamped to [0, 1]" if kind == "rgb"
                               else "normal XYZ -> RGB (n+1)/2; misses black"))
        return rgb, legend, None

    v = np.asarray(img.channels[channel], np.float64)
    if kind == "id":
        raw = img.channels[channel]
        miss = ~np.isfinite(v) | (v < 0)
        if raw.dtype == np.uint32:
            miss |= raw == np.iinfo(np.uint32).max      # -1 stored as UINT
        sel = shown & ~miss
        ids = np.unique(v[sel]).astype(np.int64)
        rgb[sel] = _id_colours(v[sel])
        legend.update(ids=ids.size, min=int(ids.min()) if ids.size else None,
                      max=int(ids.max()) if ids.size else None,
                      caption=f"{channel}: {ids.size} ids; -1/misses black")
        return rgb, legend, ids

    fin = np.isfinite(v)
    sel = shown & fin
    vals = v[sel]
    lo = float(vals.min()) if vals.size else 0.0
    hi = float(vals.max()) if vals.size else 0.0
    nonfinite = NONFINITE_RGB
    if kind == "mask":
        cmap, span, caption = "grey", (0.0, 1.0), f"{channel} (grey, 0..1)"
    elif kind == "diff":
        cmap, span, nonfinite = "inferno", (0.0, hi), NONFINITE_DIFF_RGB
        caption = f"|A-B| of {channel}" + ("; cyan: non-finite mismatch" if (~fin).any() else "")
    else:
        cmap, span = "viridis", (lo, hi)
        caption = channel + ("; misses black" if hit is not None else "")
    # normalise to [0, 1] over the shown range; a constant image maps to the bar's middle
    # (a zero difference to its start)
    if span[1] > span[0]:
        t = np.clip((np.where(fin, v, span[0]) - span[0]) / (span[1] - span[0]), 0.0, 1.0)
    else:
        t = np.full_like(v, 0.0 if kind == "diff" else 0.5)
    if cmap == "grey":
        col = np.repeat(t[..., None], 3, -1)
    else:
        col = matplotlib.colormaps[cmap](t)[..., :3]
    rgb[sel] = (col[sel] * 255 + 0.5).astype(np.uint8)
    rgb[shown & ~fin] = nonfinite
    if (shown & ~fin).any() and kind != "diff":
        caption += "; magenta: NaN/Inf"
    legend.update(cmap=cmap, min=lo if vals.size else None, max=hi if vals.size else None,
                  map_range=list(span), caption=caption)
    return rgb, legend, None


def _legend_strip(width: int, legend: dict, ids=None):
    """The colour bar (or swatches) with min/max labels and a caption, as a PIL image."""
    import matplotlib
    from PIL import Image as PILImage, ImageDraw, ImageFont
    strip = PILImage.new("RGB", (width, LEGEND_HEIGHT), (32, 32, 32))
    draw = ImageDraw.Draw(strip)
    font = ImageFont.load_default()
    pad, bar_top, bar_h = 4, 16, 10
    bar_w = max(1, width - 2 * pad)
    kind = legend["kind"]
    t = np.linspace(0.0, 1.0, bar_w)
    if kind == "id":
        ids = ids if ids is not None and ids.size else np.zeros(1, np.int64)
        idx = np.minimum((t * len(ids)).astype(int), len(ids) - 1)
        bar = _id_colours(ids[idx])
    elif kind in ("rgb", "normal"):
        bar = np.zeros((bar_w, 3), np.uint8)
        thirds = np.minimum((t * 3).astype(int), 2)
        bar[np.arange(bar_w), thirds] = (255 * (t * 3 - thirds)).astype(np.uint8)
    elif legend.get("cmap") == "grey":
        bar = np.repeat((t * 255 + 0.5).astype(np.uint8)[:, None], 3, -1)
    else:
        bar = (matplotlib.colormaps[legend["cmap"]](t)[:, :3] * 255 + 0.5).astype(np.uint8)
    strip.paste(PILImage.fromarray(np.repeat(bar[None], bar_h, 0)), (pad, bar_top))

    def fmt(v):
        if v is None:
            return "-"
        if isinstance(v, list):
            return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"
        return f"{v:.6g}" if isinstance(v, float) else str(v)

    draw.text((pad, 2), legend["caption"], fill=(230, 230, 230), font=font)
    lo, hi = f"min {fmt(legend['min'])}", f"max {fmt(legend['max'])}"
    y = bar_top + bar_h + 1
    draw.text((pad, y), lo, fill=(230, 230, 230), font=font)
    hi_w = draw.textlength(hi, font=font)
    draw.text((max(pad, width - pad - hi_w), y), hi, fill=(230, 230, 230), font=font)
    return strip


def preview(path, out, channel: str | None = None) -> dict:
    """Write a false-colour PNG of one channel with a colour bar; returns what was drawn.

    Default channel: ``depth.Z`` if present, else the first channel.  ``normal`` (or any
    ``normal.*``) shows the XYZ triple, ``R``/``G``/``B`` the clamped colour image.  The
    image keeps its pixel grid (enlarged by an integer ``scale`` when narrower than
    PREVIEW_MIN_WIDTH pixels), with a LEGEND_HEIGHT-pixel legend strip below it.  The PNG
    is written atomically.
    """
    img = load(path)
    if channel is None:
        channel = "depth.Z" if "depth.Z" in img.channels else next(iter(img.channels))
    elif channel not in img.channels:
        channel = select_channels(img, [channel])[0]      # a layer name, e.g. "normal"
    kind = preview_kind(img, channel)
    rgb, legend, ids = _render(img, channel, kind)
    W = img.width
    # (not past PREVIEW_MAX_SIDE rows: a tall, narrow image stays within PNG's limits)
    scale = max(1, min(math.ceil(PREVIEW_MIN_WIDTH / W), PREVIEW_MAX_SIDE // img.height))
    pic = np.repeat(np.repeat(rgb, scale, 0), scale, 1)          # each pixel a scale² block
    canvas = np.concatenate([pic, np.asarray(_legend_strip(W * scale, legend, ids))], 0)
    out = os.fspath(out)
    # provenance: the source file and its own rtval.* header attributes
    text = {"rtval.preview_of": f"{os.path.abspath(path)} channel {channel}"}
    text.update({str(k): str(v) for k, v in img.header.items() if str(k).startswith("rtval.")})
    from rt_core.imageio import write_png
    try:
        write_png(out, canvas, text)
    except WriteError as e:
        raise ExrError(str(e)) from None
    except Exception as e:
        raise ExrError(f"{out}: cannot write the PNG ({_oneline(e)})") from None
    legend.update(file=img.path, output=out, width=canvas.shape[1], height=canvas.shape[0],
                  scale=scale)
    return legend

