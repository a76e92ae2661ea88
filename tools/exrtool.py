"""Inspect and compare OpenEXR outputs the way exrinfo, ``oiiotool --stats`` and idiff do.

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

from rt_core.exrio import ExrError, atomic_write, read_exr, write_exr
from rt_core.outputs import WriteError

# idiff's process return codes
PASS, WARN, FAIL, MISMATCH, FILE_ERROR = 0, 1, 2, 3, 4
STATUS_NAMES = {PASS: "PASS", WARN: "WARNING", FAIL: "FAILURE", MISMATCH: "MISMATCH"}

HIT_MASK = "hit.mask"
DIFF_KIND = "diff"          # value of the rtval.kind attribute of a difference image
PIXEL_TYPES = {np.dtype(np.float16): "HALF", np.dtype(np.float32): "FLOAT",
               np.dtype(np.uint32): "UINT"}


# ----------------------------------------------------------------------------- loading

@dataclass
class Image:
    """One EXR file: ``channels`` {name: 2-D array}, sorted by name, and its header."""
    path: str
    channels: dict
    header: dict

    @property
    def height(self) -> int:
        return next(iter(self.channels.values())).shape[0] if self.channels else 0

    @property
    def width(self) -> int:
        return next(iter(self.channels.values())).shape[1] if self.channels else 0

    def hit(self) -> np.ndarray | None:
        """Boolean hit mask from ``hit.mask`` (> 0.5), or None if the file has none."""
        m = self.channels.get(HIT_MASK)
        return None if m is None else np.asarray(m, dtype=np.float64) > 0.5


def load(path, deep_ok: bool = False) -> Image:
    """Read ``path``; ExrError (one line naming the file) if it is unreadable or empty.
    Every part of a multi-part file is read (channels ``part.channel``); a deep file only
    with ``deep_ok`` (``info``)."""
    path = os.fspath(path)
    chans, header = read_exr(path, deep_ok=deep_ok)
    if not chans:
        raise ExrError(f"{path}: the file has no channels")
    return Image(path, {k: chans[k] for k in sorted(chans)}, header)


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


# ----------------------------------------------------------------------------- info

def _plain(value):
    """A header value as JSON-ready data: enums by name, arrays as lists."""
    if isinstance(value, (str, bool, int)) or value is None:
        return value
    if isinstance(value, float):
        return value
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    name = getattr(value, "name", None)   # pybind11 enums: Compression.ZIP_COMPRESSION
    if isinstance(name, str) and hasattr(value, "value"):
        return name
    return str(value)


def _window(value):
    try:
        (x0, y0), (x1, y1) = (tuple(int(v) for v in corner) for corner in value)
        return [[x0, y0], [x1, y1]]
    except (TypeError, ValueError):
        return _plain(value)


def info(path) -> dict:
    """Size, windows, compression, channels with pixel types, and every header attribute.

    ``attributes`` holds all header attributes except the channel list (given as
    ``channels``); ``provenance`` repeats the ``rtval.*`` ones.
    """
    img = load(path, deep_ok=True)
    hdr = img.header
    attrs = {k: _plain(v) for k, v in sorted(hdr.items()) if k != "channels"}
    for key in ("dataWindow", "displayWindow"):
        if key in hdr:
            attrs[key] = _window(hdr[key])
    sampling = {getattr(c, "name", None): (getattr(c, "xSampling", 1), getattr(c, "ySampling", 1))
                for c in hdr.get("channels", []) or []}
    channels = []
    for name, arr in img.channels.items():
        xs, ys = sampling.get(name, (1, 1))
        channels.append({"name": name, "type": _pixel_type(arr),
                         "x_sampling": int(xs), "y_sampling": int(ys)})
    return {
        "file": img.path,
        "width": img.width,
        "height": img.height,
        "compression": attrs.get("compression"),
        "data_window": attrs.get("dataWindow"),
        "display_window": attrs.get("displayWindow"),
        "channels": channels,
        "parts": hdr.get("parts", []),
        "storage": _plain(hdr.get("type", "scanlineimage")),
        "layers": _layers(img.channels),
        "attributes": attrs,
        "provenance": {k: v for k, v in attrs.items() if k.startswith("rtval.")},
    }


def _pixel_type(arr) -> str:
    """HALF/FLOAT/UINT; a deep channel (per-pixel sample arrays) as ``deep FLOAT``."""
    if arr.dtype == object:
        first = next((a for a in arr.flat if getattr(a, "size", 0)), None)
        return "deep " + (PIXEL_TYPES.get(first.dtype, str(first.dtype)) if first is not None
                          else "(no samples)")
    return PIXEL_TYPES.get(arr.dtype, str(arr.dtype))


def _layers(names) -> dict:
    """Group ``layer.channel`` names the way tev does: {layer: [channel, ...]}."""
    layers: dict = {}
    for n in names:
        layer, _, chan = n.rpartition(".")
        layers.setdefault(layer, []).append(chan)
    return layers


# ----------------------------------------------------------------------------- stats

def _summary(values: np.ndarray) -> dict:
    """min/max/mean/std over the finite values, and NaN/Inf/finite counts (oiiotool --stats)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    nan = np.isnan(v)
    inf = np.isinf(v)
    fin = v[~(nan | inf)]
    out = {"count": int(v.size), "finite": int(fin.size), "nan": int(nan.sum()),
           "inf": int(inf.sum()), "min": None, "max": None, "mean": None, "std": None}
    if fin.size:
        mean = float(fin.mean())
        out.update(min=float(fin.min()), max=float(fin.max()), mean=mean,
                   std=float(np.sqrt(np.mean((fin - mean) ** 2))))
    return out


def stats(path, channels=None) -> dict:
    """Per-channel statistics; ``depth.*`` channels also get ``hit`` stats over hit pixels.

    std is the population standard deviation (as oiiotool reports it).  ``hit`` is None for
    a depth channel when the file has no ``hit.mask``.
    """
    img = load(path)
    names = select_channels(img, channels)
    hit = img.hit()
    result = {"file": img.path, "width": img.width, "height": img.height, "channels": {}}
    for name in names:
        arr = img.channels[name]
        s = _summary(arr)
        s["type"] = PIXEL_TYPES.get(arr.dtype, str(arr.dtype))
        if name.split(".", 1)[0] == "depth":
            s["hit"] = None if hit is None else _summary(np.asarray(arr)[hit])
        result["channels"][name] = s
    return result


# ----------------------------------------------------------------------------- diff

@dataclass(frozen=True)
class Thresholds:
    """idiff's limits.  A pixel *fails* when, in any channel, its error exceeds both ``fail``
    (absolute) and ``fail_relative`` (error / mean of |a| and |b|); likewise for *warn*.
    The comparison FAILS if any pixel's error exceeds ``hard_fail``, or if more pixels fail
    than both ``allow_failures`` and ``fail_percent`` % of the pixels allow.  Failing pixels
    within ``allow_failures`` are excused entirely; failing pixels within ``fail_percent``
    still count as warnings.  Otherwise it WARNS if more than ``warn_percent`` % of pixels
    warn or any error exceeds ``hard_warn``.
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


def diff(path_a, path_b, channels=None, thresholds: Thresholds | None = None,
         diff_out=None) -> dict:
    """Compare two EXRs channel by channel with idiff's semantics.

    Returns a dict with ``status`` (PASS, WARNING, FAILURE or MISMATCH) and ``exit_code``
    (0, 1, 2, 3), the mean/RMS/max error over values finite in both files, the worst pixel
    (x, y, channel and both values), failing/warning pixel counts and per-channel errors.
    NaN matches only NaN and Inf only the same-signed Inf; any other pairing with a
    non-finite value is an infinite error, so that pixel fails and warns.  ``diff_out``
    writes |A - B| per channel (0 where non-finite values match, Inf where they do not),
    atomically, unless the images cannot be compared (MISMATCH).
    """
    th = thresholds or Thresholds()
    a, b = load(path_a), load(path_b)
    names_a, names_b = select_channels(a, channels), select_channels(b, channels)
    result = {"file_a": a.path, "file_b": b.path, "width": a.width, "height": a.height,
              "thresholds": asdict(th)}
    why = _mismatch(a, b, names_a, names_b, channels)
    if why:
        result.update(status=STATUS_NAMES[MISMATCH], exit_code=MISMATCH, reason=why,
                      channels_a=names_a, channels_b=names_b)
        return result
    names = names_a
    A = np.stack([np.asarray(a.channels[n], dtype=np.float64) for n in names], axis=-1)
    B = np.stack([np.asarray(b.channels[n], dtype=np.float64) for n in names], axis=-1)
    H, W, C = A.shape
    npix = H * W

    # per-value error: |a-b| where both are finite, 0 / Inf where a non-finite value matches / not
    finite = np.isfinite(A) & np.isfinite(B)
    same_nonfinite = (np.isnan(A) & np.isnan(B)) | (np.isinf(A) & (A == B))
    bad = ~finite & ~same_nonfinite
    with np.errstate(invalid="ignore", over="ignore"):
        err = np.where(finite, np.abs(A - B), 0.0)
        meanabs = np.where(finite, 0.5 * (np.abs(A) + np.abs(B)), 0.0)
        rel = np.divide(err, meanabs, out=np.zeros_like(err), where=meanabs > 0)
    err[bad] = np.inf
    rel[bad] = np.inf

    chan_fail = ((err > th.fail) & (rel > th.fail_relative)) | bad
    chan_warn = ((err > th.warn) & (rel > th.warn_relative)) | bad
    pix_fail, pix_warn = chan_fail.any(axis=-1), chan_warn.any(axis=-1)
    pix_err = err.max(axis=-1)
    n_fail, n_warn = int(pix_fail.sum()), int(pix_warn.sum())

    # idiff's summary numbers, over the values that are finite in both files
    n_cmp = int(finite.sum())
    fe = err[finite]
    mean_err = float(fe.sum() / n_cmp) if n_cmp else 0.0
    rms_err = float(np.sqrt((fe ** 2).sum() / n_cmp)) if n_cmp else 0.0
    flat = int(np.argmax(err)) if err.size else 0
    y, x, c = np.unravel_index(flat, err.shape) if err.size else (0, 0, 0)
    max_err = float(err[y, x, c]) if err.size else 0.0
    worst = None
    if max_err > 0:
        worst = {"x": int(x), "y": int(y), "channel": names[c], "error": max_err,
                 "relative_error": float(rel[y, x, c]),
                 "a": _scalar(a.channels[names[c]][y, x]),
                 "b": _scalar(b.channels[names[c]][y, x])}

    # the verdict
    reasons = []
    fail_quota = th.fail_percent / 100.0 * npix
    excused = 0 < n_fail <= th.allow_failures
    if max_err > th.hard_fail:
        status = FAIL
        reasons.append(f"max error {max_err:g} exceeds the hard-fail limit {th.hard_fail:g}")
    elif n_fail > th.allow_failures and n_fail > fail_quota:
        status = FAIL
        reasons.append(f"{n_fail} failing pixels > {th.allow_failures} allowed and > "
                       f"{th.fail_percent:g}% of {npix}")
    else:
        if excused:
            reasons.append(f"{n_fail} failing pixels excused (up to {th.allow_failures} "
                           f"allowed)")
        warn_mask = pix_warn & ~pix_fail if excused else pix_warn
        n_warn_eff = int(warn_mask.sum())
        rest = pix_err[~pix_fail] if excused else pix_err
        max_rest = float(rest.max()) if rest.size else 0.0
        status = PASS
        if n_warn_eff > th.warn_percent / 100.0 * npix:
            status = WARN
            reasons.append(f"{n_warn_eff} warning pixels > {th.warn_percent:g}% of {npix}")
        if max_rest > th.hard_warn:
            status = WARN
            reasons.append(f"max error {max_rest:g} exceeds the hard-warn limit {th.hard_warn:g}")

    per_channel = {}
    for i, n in enumerate(names):
        e = err[..., i]
        f = finite[..., i]
        k = int(np.argmax(e))
        cy, cx = divmod(k, W)
        per_channel[n] = {
            "max_error": float(e.max()),
            "mean_error": float(e[f].mean()) if f.any() else 0.0,
            "rms_error": float(np.sqrt((e[f] ** 2).mean())) if f.any() else 0.0,
            "worst": [int(cx), int(cy)] if e.max() > 0 else None,
            "failing_pixels": int(chan_fail[..., i].sum()),
            "warning_pixels": int(chan_warn[..., i].sum()),
            "nonfinite_mismatches": int(bad[..., i].sum()),
        }

    result.update({
        "status": STATUS_NAMES[status], "exit_code": status, "reasons": reasons,
        "channels": names, "pixels": npix,
        "mean_error": mean_err, "rms_error": rms_err, "max_error": max_err, "worst": worst,
        "compared_values": n_cmp, "nonfinite_mismatches": int(bad.sum()),
        "failing_pixels": n_fail, "failing_percent": 100.0 * n_fail / npix if npix else 0.0,
        "warning_pixels": n_warn, "warning_percent": 100.0 * n_warn / npix if npix else 0.0,
        "per_channel": per_channel, "diff_image": None,
    })
    if diff_out is not None:
        out = os.fspath(diff_out)
        attrs = {"rtval.kind": DIFF_KIND, "rtval.diff.a": a.path, "rtval.diff.b": b.path,
                 "rtval.diff.status": STATUS_NAMES[status]}
        try:
            write_exr(out, {n: err[..., i].astype(np.float32) for i, n in enumerate(names)}, attrs)
        except ExrError:
            raise
        except WriteError as e:       # one line naming the target already; exr's code 4
            raise ExrError(str(e)) from None
        except Exception as e:
            raise ExrError(f"{out}: cannot write the difference image ({_oneline(e)})") from None
        result["diff_image"] = out
    return result


def _oneline(e: BaseException) -> str:
    text = getattr(e, "strerror", None) or str(e) or type(e).__name__
    return text.splitlines()[0]


# ----------------------------------------------------------------------------- preview

PREVIEW_MIN_WIDTH = 256     # small images are enlarged by an integer factor to this width
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
    from PIL import Image as PILImage
    img = load(path)
    if channel is None:
        channel = "depth.Z" if "depth.Z" in img.channels else next(iter(img.channels))
    elif channel not in img.channels:
        channel = select_channels(img, [channel])[0]      # a layer name, e.g. "normal"
    kind = preview_kind(img, channel)
    rgb, legend, ids = _render(img, channel, kind)
    H, W = img.height, img.width
    scale = max(1, math.ceil(PREVIEW_MIN_WIDTH / W))
    pic = PILImage.fromarray(rgb).resize((W * scale, H * scale), PILImage.NEAREST)
    canvas = PILImage.new("RGB", (W * scale, H * scale + LEGEND_HEIGHT))
    canvas.paste(pic, (0, 0))
    canvas.paste(_legend_strip(W * scale, legend, ids), (0, H * scale))
    out = os.fspath(out)
    try:
        # provenance: the source file and its own rtval.* header attributes
        from PIL.PngImagePlugin import PngInfo
        info = PngInfo()
        info.add_text("rtval.preview_of", f"{os.path.abspath(path)} channel {channel}")
        for k, v in img.header.items():
            if str(k).startswith("rtval."):
                info.add_text(str(k), str(v))
        atomic_write(out, lambda tmp: canvas.save(tmp, format="PNG", pnginfo=info))
    except WriteError as e:
        raise ExrError(str(e)) from None
    except Exception as e:
        raise ExrError(f"{out}: cannot write the PNG ({_oneline(e)})") from None
    legend.update(file=img.path, output=out, width=canvas.width, height=canvas.height,
                  scale=scale)
    return legend

