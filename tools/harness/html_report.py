"""The HTML report of ``rtval validate``, ``rtval compare`` and ``rtval check`` (``--report DIR``).

One page, ``DIR/index.html``, with a row per comparison, failures first: the reference, ours
(or theirs, for check) and the class image side by side as PNGs, the classes in named colours
with a legend.  Clicking an image flips it (reference <-> ours in one slot, as tev's A/B
flip; classes <-> the difference).  Each row has the evidence files it left (EXRs, PNGs) as
links and the command that reproduces it; the skipped scenes are listed with their reasons;
the page records its provenance (rtval's version and commit, the packages, the date, the
command line).  Inline CSS and JavaScript only: the page needs no network.

Pictures are made where the comparison is (``comparison_pictures``, ``check_pictures``) and
kept as PNG bytes (a few kB each), so a run of hundreds of comparisons holds little memory.

The directory is written whole or not at all: everything goes into a temporary directory
beside it (``.tmp-rtval-TAG-PID-*``), which is then renamed into place; an earlier report in
``DIR`` is replaced, any other non-empty directory is refused (``check_target``).
"""
from __future__ import annotations

import datetime
import errno
import functools
import io
import os
import re
import shlex
import shutil
import sys
import tempfile
import urllib.parse
from dataclasses import dataclass, field
from html import escape
from pathlib import Path

import numpy as np

GENERATOR = "rtval report"          # <meta name="generator">: marks a directory as a report

# --- class palettes: (class, colour name, RGB, meaning) ---------------------------------------

GEOMETRY_PALETTE = (
    ("agree", "dark grey", (48, 48, 48), "same hit, object and depth"),
    ("edge", "yellow", (240, 200, 40), "within float32's bound of a finite plane's edge"),
    ("tie", "cyan", (40, 190, 210), "two objects at the same depth within the bound"),
    ("clip", "blue", (70, 110, 230), "within the bound of the window plane z = 0 (screen clip)"),
    ("extent", "purple", (150, 80, 200), "beyond the far end of Mitsuba's stand-in plane"),
    ("silhouette", "orange", (245, 130, 40), "within the bound of a sphere's outline"),
    ("graze", "green", (60, 180, 75), "within the bound of parallel to a plane"),
    ("unexplained", "red", (230, 30, 30), "a disagreement no bound explains: fails"),
)


def _shaded_palette():
    from .shaded import SHADED_CLASSES, SHADED_COLOUR_NAMES, SHADED_COLOURS
    meaning = {"match": "the same three 8-bit values",
               "rounding": "a channel off by one at an 8-bit level",
               "boundary": "a decision of the pixel's rays within float32's bound",
               "wrong": "anything else: fails"}
    return tuple((c, SHADED_COLOUR_NAMES[c], SHADED_COLOURS[c], meaning[c])
                 for c in SHADED_CLASSES)


def _check_palette():
    from .check import CLASSES, COLORS
    meaning = {"match": "the same 8-bit colour",
               "rounding": "a channel off by one: an intensity truncated on the other side",
               "boundary": "a ray within a float64 error bound of a decision",
               "variant": "right under a rule variant of real course programs",
               "wrong": "anything else: fails"}
    return tuple((c, COLORS[c][0], COLORS[c][1], meaning[c]) for c in CLASSES)


@functools.lru_cache(None)
def palette(name: str) -> tuple:
    """The classes of a kind of comparison ("geometry", "shaded", "check") in code order."""
    if name in ("geometry", "exact"):
        from mitsuba_ref.explain import CLASSES
        assert tuple(c for c, *_ in GEOMETRY_PALETTE) == CLASSES
        return GEOMETRY_PALETTE
    return {"shaded": _shaded_palette, "shaded-oracle": _shaded_palette,
            "check": _check_palette}[name]()


# --- pictures ------------------------------------------------------------------------------------

# colours of object ids in the geometry pictures (brightness: depth, black: a miss)
OBJECT_COLOURS = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                           (148, 103, 189), (140, 86, 75), (227, 119, 194), (188, 189, 34),
                           (23, 190, 207), (174, 199, 232), (255, 187, 120), (152, 223, 138)],
                          np.float64)


@functools.lru_cache(None)
def _versions() -> dict:
    from rt_core.render import versions
    return versions()


def png_bytes(pixels: np.ndarray, text: dict) -> bytes:
    """An 8-bit RGB image as PNG bytes, ``text`` in tEXt chunks (provenance)."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo
    info = PngInfo()
    from rt_core.outputs import attr_text
    for k, v in text.items():
        info.add_text(k, attr_text(v))       # (a path's bytes that are not UTF-8: \xNN)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels, np.uint8), "RGB").save(buf, format="PNG",
                                                                        pnginfo=info)
    return buf.getvalue()


def geometry_picture(img: dict, lo: float, hi: float) -> np.ndarray:
    """Primary-ray geometry as an 8-bit picture: the object id's colour, brighter nearer
    (log depth over [lo, hi], shared by the two pictures compared), black on a miss."""
    hit = np.asarray(img["hit.mask"]) > 0
    ids = np.asarray(img["object.id"]).astype(np.int64)
    t = np.asarray(img["depth.Z"], np.float64)
    t = np.where(hit & np.isfinite(t) & (t > 0), t, hi)
    span = np.log(hi) - np.log(lo)
    near = 1.0 - (np.log(np.clip(t, lo, hi)) - np.log(lo)) / span if span > 0 else np.ones_like(t)
    colour = OBJECT_COLOURS[np.mod(ids, len(OBJECT_COLOURS))] * (0.35 + 0.65 * near)[..., None]
    return np.where(hit[..., None], np.rint(colour), 0).astype(np.uint8)


def class_picture(classes: np.ndarray, kind: str) -> np.ndarray:
    """Class codes as their named colours."""
    lut = np.array([rgb for _, _, rgb, _ in palette(kind)], np.uint8)
    return lut[np.asarray(classes, np.int64)]


def difference_picture(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| of two 8-bit pictures, the largest channel, as grey: 0 black, any difference
    at least 64 (a rounding difference of 1 stays visible), 255 white."""
    d = np.abs(a.astype(np.int16) - b.astype(np.int16)).max(-1)
    v = np.where(d > 0, 64 + (191 * d) // 255, 0).astype(np.uint8)
    return np.repeat(v[..., None], 3, -1)


@dataclass
class Pictures:
    """A comparison's pictures as PNG bytes: reference, ours, classes, difference (and a
    magnified view of the largest group of failing pixels, ``zoom``)."""
    kind: str                          # the class palette: geometry, shaded, check
    width: int
    height: int
    png: dict                          # name -> bytes
    zoom: tuple | None = None          # (width, height, caption) of png["zoom"]

    @classmethod
    def make(cls, kind: str, reference, ours, classes, text: dict) -> "Pictures":
        prov = {**text, "rtval.versions": " ".join(f"{k}={v}" for k, v in _versions().items())}
        legend = ", ".join(f"{c}={name}" for c, name, _, _ in palette(kind))
        images = {"reference": reference, "ours": ours,
                  "classes": class_picture(classes, kind),
                  "difference": difference_picture(reference, ours)}
        extra = {"classes": {"rtval.classes": legend},
                 "difference": {"rtval.difference": "|reference - ours|, largest channel; "
                                                     "0 black, else 64 + 191*d/255"}}
        png = {name: png_bytes(img, {**prov, "rtval.image": name, **extra.get(name, {})})
               for name, img in images.items()}
        return cls(kind, int(reference.shape[1]), int(reference.shape[0]), png)


def comparison_pictures(cmp) -> Pictures:
    """The pictures of a ``compare`` comparison (tools/harness/compare.py: the geometry, in
    object colours) or a shaded one (tools/harness/shaded.py: the 8-bit course images);
    the reference is Mitsuba's, or the exact oracle's (tools/harness/exact_compare.py)."""
    text = {"rtval.scene": str(cmp.scene.path), "rtval.scene_sha256": cmp.scene.sha256 or ""}
    if hasattr(cmp, "theirs"):                          # ShadedComparison
        from .shaded import ORACLE_MODE
        oracle = cmp.reference == "oracle"
        kind = ORACLE_MODE if oracle else "shaded"
        return Pictures.make(kind, cmp.theirs, cmp.ours, cmp.classes,
                             {**text, "rtval.mode": kind,
                              "rtval.reference": "float64 shading oracle" if oracle else
                              "mitsuba course integrator",
                              "rtval.ours": "rt_core f64"})
    ts = [np.asarray(im["depth.Z"], np.float64)[np.asarray(im["hit.mask"]) > 0]
          for im in (cmp.ref, cmp.ours)]
    ts = np.concatenate([t[np.isfinite(t) & (t > 0)] for t in ts])
    lo, hi = (float(ts.min()), float(ts.max())) if len(ts) else (1.0, 1.0)
    exact = cmp.mode == "exact"             # (tools/harness/exact_compare.py)
    if exact:
        from .exact_compare import REFERENCE
    return Pictures.make("exact" if exact else "geometry", geometry_picture(cmp.ref, lo, hi),
                         geometry_picture(cmp.ours, lo, hi), cmp.classes,
                         {**text, "rtval.mode": cmp.mode, "rtval.precision": cmp.precision,
                          "rtval.reference": REFERENCE if exact else "mitsuba llvm_ad_rgb",
                          "rtval.picture": "object id colour, brighter nearer (log depth), "
                                           "black: miss"})


def check_pictures(r) -> Pictures | None:
    """The pictures of an ``rtval check`` result (tools/harness/check.py): rt_core's image
    is the reference, the tracer's is "ours" (shown as theirs); None without images.  A
    failing one gets its largest group of wrong pixels magnified (``zoom_picture``)."""
    if r.classes is None:
        return None
    text = {"rtval.scene": str(r.scene), "rtval.image_checked": str(r.image),
            "rtval.reference": "rt_core f64", "rtval.rules": r.rules}
    pics = Pictures.make("check", r.ours, r.theirs, r.classes, text)
    if r.worst:
        img, k, (y0, y1, x0, x1), part = zoom_picture(
            [r.ours, r.theirs, class_picture(r.classes, "check")], r.worst)
        pics.png["zoom"] = png_bytes(img, {**text, "rtval.image": "zoom",
                                           "rtval.zoom": f"rows {y0}-{y1}, columns {x0}-{x1}, "
                                                         f"x{k}: rt_core | theirs | classes"})
        what = "part of the largest group" if part else "the largest group"
        pics.zoom = (img.shape[1], img.shape[0],
                     f"{what} of wrong pixels, rows {y0}–{y1}, columns {x0}–{x1}, "
                     f"magnified {k}×: rt_core · theirs · classes")
    return pics


ZOOM_PAD = 3            # pixels around the group
ZOOM_SIZE = 120         # the magnified crop's longer side, about
ZOOM_MAX = 30           # a crop's longer side at most (magnified 4× at least)


def zoom_picture(images: list, worst: dict) -> tuple:
    """(picture, factor, (first row, last row, first column, last column), part): the same
    crop of each image, magnified by a whole factor to about ZOOM_SIZE pixels, side by side
    with a grey gap.  The crop is the largest wrong group (check.worst_region) with ZOOM_PAD
    around it; a group wider or taller than ZOOM_MAX gives a ZOOM_MAX square around its
    pixel nearest its centre (``middle``) instead (``part``)."""
    H, W = images[0].shape[:2]
    y0, y1 = worst["rows"][0] - ZOOM_PAD, worst["rows"][1] + ZOOM_PAD
    x0, x1 = worst["columns"][0] - ZOOM_PAD, worst["columns"][1] + ZOOM_PAD
    part = max(y1 - y0, x1 - x0) + 1 > ZOOM_MAX
    if part:
        cy, cx = worst["middle"]
        y0, x0 = cy - ZOOM_MAX // 2, cx - ZOOM_MAX // 2
        y1, x1 = y0 + ZOOM_MAX - 1, x0 + ZOOM_MAX - 1
    # moved inside the image, keeping its size where the image is large enough
    h, w = y1 - y0 + 1, x1 - x0 + 1
    y0, x0 = max(0, min(y0, H - h)), max(0, min(x0, W - w))
    y1, x1 = min(H - 1, y0 + h - 1), min(W - 1, x0 + w - 1)
    k = max(2, min(16, ZOOM_SIZE // max(y1 - y0 + 1, x1 - x0 + 1)))
    crops = [np.repeat(np.repeat(im[y0:y1 + 1, x0:x1 + 1], k, 0), k, 1) for im in images]
    gap = np.full((crops[0].shape[0], 4, 3), 128, np.uint8)
    parts = [crops[0]]
    for c in crops[1:]:
        parts += [gap, c]
    return np.concatenate(parts, 1).astype(np.uint8), k, (y0, y1, x0, x1), part


# --- rows ----------------------------------------------------------------------------------------

STATUS_ORDER = {"fail": 0, "error": 1, "pass": 2}


@dataclass
class Row:
    """One comparison on the page."""
    title: str
    status: str                        # fail, error (could not run) or pass
    summary: str                       # one line
    details: list = field(default_factory=list)
    pictures: Pictures | None = None
    counts: dict = field(default_factory=dict)
    evidence: list = field(default_factory=list)       # paths of files the run left
    command: str = ""                  # reproduces this row


@dataclass
class Skip:
    path: str
    category: str                      # unsupported, malformed, ...
    reason: str


def _q(*words) -> str:
    return " ".join(shlex.quote(str(w)) for w in words)


def compare_command(row: dict, rows_given: int | None = None) -> str:
    """The ``rtval compare`` command that redoes one comparison of validate or compare."""
    from rt_core.rules import Rules
    from .shaded import ORACLE_MODE, SHADED_MODES
    shaded = row["mode"] in SHADED_MODES
    words = ["rtval", "compare"] + (["--shaded"] if shaded else []) + (
        ["--reference", "oracle"] if row["mode"] == ORACLE_MODE else []) + [
        row["scene"], "--columns", row["columns"]]
    if rows_given:
        words += ["--rows", rows_given]
    if not shaded:
        words += ["--mode", row["mode"], "--precision", row["precision"]]
        if row.get("backend", "llvm") != "llvm":
            words += ["--backend", row["backend"]]
    if row.get("sampling", "corners") != "corners":
        words += ["--sampling", row["sampling"]]
    if row.get("rules") and row["rules"] != Rules().describe():
        words += ["--rules", row["rules"]]
    if shaded:
        from rt_core.shading import DEFAULT_MAX_DIST
        if row.get("max_dist", DEFAULT_MAX_DIST) != DEFAULT_MAX_DIST:
            words += ["--max-dist", repr(row["max_dist"])]
    return _q(*words)


def comparison_row(row: dict, rows_given: int | None = None) -> Row:
    """A Row of a validate/compare result (its summary dict; "pictures" if it has them)."""
    from .validate import row_stem
    counts = {k: v for k, v in row["classes"].items()}
    listed = ", ".join(f"{k} {v}" for k, v in counts.items() if v)
    from .shaded import ORACLE_MODE, SHADED_MODES
    oracle = row["mode"] == ORACLE_MODE
    if row["mode"] in SHADED_MODES:
        them = "the shading oracle" if oracle else "Mitsuba"
        title = f"{row_stem(row)} · {row['mode']}"
        summary = (f"{row['columns']}×{row['rows']} 8-bit, rt_core f64 / "
                   f"{'oracle f64' if oracle else 'Mitsuba f32'}: {listed}")
        details = [f"wrong pixel (column {x}, row {y}): rt_core {o}, {them} {t}"
                   for x, y, o, t in row.get("worst", [])]
    else:
        d = row["depth"]
        title = f"{row_stem(row)} · {row['mode']} · {row['precision']}"
        summary = (f"{row['columns']}×{row['rows']}: {listed}; depth: max rel error "
                   f"{d['max_rel']:.3g} on {d['pixels']} same-object pixels, "
                   f"{d['over_bound']} over their bound"
                   + (f", {d['other_root']} at an open quadric's other root within reach"
                      if d.get("other_root") else ""))
        details = [row["note"]] if row.get("note") else []
    reference = {"exact": "the exact oracle", ORACLE_MODE: "the shading oracle"}.get(
        row["mode"], "Mitsuba")
    details.append(f"rt_core {row['rt_core_ms']:.1f} ms, {reference} {row['mitsuba_ms']:.1f} ms")
    return Row(title, "pass" if row["ok"] else "fail", summary, details,
               row.get("pictures"), counts, list(row.get("evidence", [])),
               compare_command(row, rows_given))


def check_command(r, run: str | None = None, rows: int | None = None, rules=None,
                  max_dist=None, hits: str | None = None, timeout: float | None = None,
                  texture_dirs=(), code27: str = "auto", columns: int | None = None) -> str:
    """The ``rtval check`` command that redoes one scene's check."""
    if run:
        words = ["rtval", "check", "--run", run, "--columns", r.columns or columns or "N"]
        if rows:
            words += ["--rows", rows]
        if timeout is not None and timeout != 60.0:
            words += ["--timeout", f"{timeout:g}"]
        words.append(r.scene)
    else:
        words = ["rtval", "check", r.scene, r.image]
        if hits:
            words += ["--hits", hits]
    if rules is not None:
        words += ["--rules", rules.describe()]
    if max_dist is not None:
        words += ["--max-dist", repr(max_dist)]
    for d in texture_dirs:
        words += ["--texture-dir", d]
    if code27 != "auto":
        words += ["--code27", code27]
    return _q(*words)


def check_rows(results, **command) -> tuple[list, list]:
    """(rows, skipped) of ``rtval check`` results: a refused scene (one rtval cannot read)
    is skipped; a run that failed (a crash, a bad image) is an error row.  ``command``:
    check_command's options."""
    from .check import CLASSES, details as check_details
    rows, skipped = [], []
    for r in results:
        if r.status == "refused":
            skipped.append(Skip(r.scene, "refused", r.reason))
            continue
        if r.status == "error":
            rows.append(Row(Path(r.scene).name, "error", r.reason,
                            command=check_command(r, **command)))
            continue
        listed = ", ".join(f"{c} {r.counts.get(c, 0)}" for c in CLASSES if r.counts.get(c))
        details = check_details(r)
        image = "" if r.image in (None, "(--run)") else f" ({r.image})"
        rows.append(Row(f"{Path(r.scene).name}{image}", r.status,
                        f"{r.columns}×{r.rows}: {listed}", details, check_pictures(r),
                        dict(r.counts), [], check_command(r, **command)))
    return rows, skipped


# --- the page ------------------------------------------------------------------------------------

LEGEND_TITLES = {"geometry": "classes of the geometry comparisons (mask, object id, depth)",
                 "exact": "classes of the comparisons with the exact oracle (mask, object "
                          "id, depth)",
                 "shaded": "classes of the shaded comparisons (8-bit course image)",
                 "shaded-oracle": "classes of the course images against the shading oracle "
                                  "(8-bit)",
                 "check": "classes of your tracer's pixels"}
LABELS = {   # (reference, ours) per kind of comparison
    "geometry": ("Mitsuba (reference)", "rt_core (ours)"),
    "exact": ("exact oracle (reference)", "rt_core (ours)"),
    "shaded": ("Mitsuba course integrator (reference)", "rt_core f64 (ours)"),
    "shaded-oracle": ("float64 shading oracle (reference)", "rt_core f64 (ours)"),
    "check": ("rt_core f64 (reference)", "your tracer (theirs)"),
}

CSS = """
body{font-family:system-ui,sans-serif;margin:1em 2em;color:#222;background:#fafafa}
h1{margin-bottom:.2em} .verdict{font-size:1.2em;font-weight:bold}
.verdict.fail{color:#b00000} .verdict.pass{color:#006000}
p.provenance{font-size:.9em;color:#444}
dl.provenance{display:grid;grid-template-columns:max-content auto;gap:0 1em;font-size:.85em}
dl.provenance dt{font-weight:bold} dl.provenance dd{margin:0}
#legends h3{font-size:1em;margin:.4em 0 0}
table{border-collapse:collapse} td,th{vertical-align:top;padding:6px;border-bottom:1px solid #ddd}
tr.fail td.status{color:#fff;background:#c00000} tr.error td.status{color:#fff;background:#b06000}
tr.pass td.status{color:#fff;background:#2a7a2a} td.status{font-weight:bold;text-align:center}
td.info{max-width:38em;overflow-wrap:anywhere} td.info ul{margin:.3em 0;padding-left:1.2em;font-size:.9em}
figure{margin:0} figcaption{font-size:.8em;color:#555}
img.flip{image-rendering:pixelated;cursor:pointer;border:1px solid #999;background:#000}
img.flip:focus{outline:2px solid #36c}
figure.zoom{margin-top:.5em} figure.zoom img{image-rendering:pixelated;border:1px solid #999}
code{background:#eee;padding:1px 3px;overflow-wrap:anywhere}
.swatch{display:inline-block;width:1em;height:1em;border:1px solid #888;vertical-align:middle;
 margin-right:.3em}
ul.legend,ul.counts{list-style:none;padding:0;margin:.3em 0} ul.counts{font-size:.85em}
ul.legend{display:flex;flex-wrap:wrap;gap:.2em 1.5em} ul.legend li{font-size:.9em}
body.failures-only tr.pass{display:none}
"""

JS = """
function flip(img){
  var b = img.dataset.showing !== 'b';
  img.src = b ? img.dataset.b : img.dataset.a;
  img.alt = (b ? img.dataset.bLabel : img.dataset.aLabel) + (img.dataset.of || '');
  img.dataset.showing = b ? 'b' : 'a';
  var cap = img.parentNode.querySelector('figcaption');
  cap.textContent = (b ? img.dataset.bLabel : img.dataset.aLabel) + ' · click: ' +
                    (b ? img.dataset.aLabel : img.dataset.bLabel);
}
document.querySelectorAll('img.flip').forEach(function(img){
  img.addEventListener('click', function(){ flip(img); });
  img.addEventListener('keydown', function(e){
    if (e.key === 'Enter' || e.key === ' '){ e.preventDefault(); flip(img); } });
});
document.getElementById('failures-only').addEventListener('change', function(e){
  document.body.classList.toggle('failures-only', e.target.checked); });
"""


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text)[:80]


def _flip(src_a, src_b, label_a, label_b, w, h, scale, of: str = "") -> str:
    """An image that flips between two pictures; its alt text names the picture shown and
    the comparison (``of``)."""
    of = f" of {of}" if of else ""
    return (f'<figure><img class="flip" tabindex="0" src="{escape(src_a)}" '
            f'data-a="{escape(src_a)}" data-b="{escape(src_b)}" '
            f'data-a-label="{escape(label_a)}" data-b-label="{escape(label_b)}" '
            f'data-of="{escape(of)}" data-showing="a" alt="{escape(label_a + of)}" '
            f'width="{w * scale}" height="{h * scale}"><figcaption>{escape(label_a)} · click: '
            f'{escape(label_b)}</figcaption></figure>')


def _legend(kind: str, counts: dict | None = None) -> str:
    items = []
    for c, name, rgb, meaning in palette(kind):
        if counts is not None and not counts.get(c):
            continue
        tail = f" {counts[c]}" if counts is not None else f" ({name}): {escape(meaning)}"
        items.append(f'<li data-class="{c}"><span class="swatch" style="background:'
                     f'rgb{rgb}" title="{name}"></span><b>{c}</b>{tail}</li>')
    return f'<ul class="{"counts" if counts is not None else "legend"}">{"".join(items)}</ul>'


def _row_html(k: int, row: Row, directory: str, files: dict) -> str:
    """One <tr>; ``files`` collects the PNGs to write (name -> bytes)."""
    info = [f"<b>{escape(row.title)}</b>", f"<div>{escape(row.summary)}</div>"]
    if row.details:
        info.append("<ul>" + "".join(f"<li>{escape(d)}</li>" for d in row.details) + "</ul>")
    links = []
    for p in row.evidence:
        if os.path.isfile(p):
            rel = os.path.relpath(os.path.abspath(p), directory)
            href = urllib.parse.quote(Path(rel).as_posix())     # ('#', '?', '%' in names)
            links.append(f'<a href="{escape(href)}">{escape(Path(p).name)}</a>')
    if links:
        info.append(f'<div class="evidence">evidence: {" · ".join(links)}</div>')
    if row.command:
        info.append(f'<div class="repro">reproduce: <code>{escape(row.command)}</code></div>')
    cells = [f'<td class="status">{row.status.upper()}</td>',
             f'<td class="info">{"".join(info)}</td>']
    pics = row.pictures
    if pics is None:
        cells.append('<td colspan="3">no images</td>')
    else:
        stem = f"{k:03d}-{_safe(row.title)}"
        names = {n: f"{stem}.{n}.png" for n in pics.png}
        files.update({names[n]: data for n, data in pics.png.items()})
        ref, ours = LABELS[pics.kind]
        scale = max(1, 240 // max(pics.width, 1))
        size = (pics.width, pics.height, scale, row.title)
        cells.append(f'<td class="reference">{_flip(names["reference"], names["ours"], ref, ours, *size)}</td>')
        zoom = ""
        if pics.zoom:                   # under the tracer's image
            zw, zh, caption = pics.zoom
            zoom = (f'<figure class="zoom"><img src="{escape(names["zoom"])}" width="{zw}" '
                    f'height="{zh}" alt="{escape(caption + " of " + row.title)}">'
                    f'<figcaption>{escape(caption)}</figcaption></figure>')
        cells.append(f'<td class="ours">'
                     f'{_flip(names["ours"], names["reference"], ours, ref, *size)}{zoom}</td>')
        cells.append(f'<td class="classes">'
                     f'{_flip(names["classes"], names["difference"], "classes", "difference", *size)}'
                     f'{_legend(pics.kind, row.counts)}</td>')
    return (f'<tr class="{row.status}" id="row{k}" data-status="{row.status}">'
            + "".join(cells) + "</tr>")


def page(title: str, rows: list, skipped: list, directory: str, command: str | None = None,
         meta: dict | None = None, skipped_fail: bool = False) -> tuple[str, dict]:
    """(index.html's text, the PNG files it names: name -> bytes).  ``skipped_fail``: a
    skipped file fails the run (check's refused scenes: exit 2), so the verdict says FAIL."""
    rows = sorted(rows, key=lambda r: STATUS_ORDER.get(r.status, 1))
    files: dict = {}
    body = [_row_html(k, r, directory, files) for k, r in enumerate(rows)]
    bad = sum(r.status != "pass" for r in rows)
    fails = sum(r.status == "fail" for r in rows)
    errors = sum(r.status == "error" for r in rows)
    bad_run = bad or (skipped_fail and len(skipped))
    verdict = ("PASS" if not bad_run else "FAIL") + f": {len(rows) - bad} of {len(rows)} pass"
    if fails:
        verdict += f", {fails} fail"
    if errors:
        verdict += f", {errors} could not run"
    if skipped:
        verdict += f"; {len(skipped)} {'refused' if skipped_fail else 'skipped'}"
    kinds = list(dict.fromkeys(r.pictures.kind for r in rows if r.pictures))
    prov = {"rtval": _versions().get("rtval", "unknown"),
            "commit": _versions().get("commit", "(not a git checkout)"),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "command": command if command is not None else _q("rtval", *sys.argv[1:]),
            **{k: v for k, v in _versions().items() if k not in ("rtval", "commit")},
            **{k: v for k, v in (meta or {}).items() if k not in _versions()}}
    legends = "".join(f"<h3>{escape(LEGEND_TITLES[k])}</h3>{_legend(k)}" for k in kinds)
    pictures = ("<p>Geometry pictures: each object in its own colour, brighter nearer (log "
                "depth, one scale for both pictures of a row), black where the ray misses.</p>"
                if "geometry" in kinds else "")
    skips = ""
    if skipped:
        skips = ("<section id=\"skipped\"><h2>Skipped (" + str(len(skipped)) + ")</h2><table>"
                 "<tr><th>file</th><th>why</th><th>reason</th></tr>"
                 + "".join(f"<tr><td>{escape(s.path)}</td><td>{escape(s.category)}</td>"
                           f"<td>{escape(s.reason)}</td></tr>" for s in skipped)
                 + "</table></section>")
    html = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="generator" content="{GENERATOR}">
<title>{escape(title)}: {escape(verdict)}</title>
<style>{CSS}</style></head><body>
<h1>{escape(title)}</h1>
<p class="verdict {'pass' if not bad_run else 'fail'}" id="verdict">{escape(verdict)}</p>
<p class="provenance">rtval {escape(prov["rtval"])}, commit {escape(prov["commit"])},
{escape(prov["date"])}: <code>{escape(prov["command"])}</code></p>
<details><summary>provenance</summary><dl class="provenance" id="provenance">{"".join(
    f"<dt>{escape(str(k))}</dt><dd>{escape(str(v))}</dd>" for k, v in prov.items())}</dl>
</details>
<section id="legends">{legends}{pictures}
<p>Click an image (or focus it and press Enter) to flip it: the reference and ours trade
places, the class image shows the difference (|reference − ours|, grey: any difference at
least dark grey).</p></section>
<p><label><input type="checkbox" id="failures-only"> show only what did not pass</label></p>
<table id="results"><thead><tr><th></th><th>comparison</th><th>reference</th>
<th>{'theirs' if kinds == ['check'] or title.startswith('rtval check') else 'ours'}</th><th>classes</th></tr></thead><tbody>
{chr(10).join(body)}
</tbody></table>
{skips}
<script>{JS}</script>
</body></html>
"""
    return html, files


# --- writing the directory, whole or not at all --------------------------------------------------

def _is_report(directory: str) -> bool:
    try:
        with open(os.path.join(directory, "index.html"), encoding="utf-8") as f:
            return f'<meta name="generator" content="{GENERATOR}">' in f.read(4096)
    except (OSError, UnicodeDecodeError):
        return False


# what a report directory holds: its page and the pictures _row_html names
_OWN = re.compile(r"index\.html\Z|\d{3}-.*\.(?:reference|ours|classes|difference|zoom)\.png\Z")


def _foreign(directory: str) -> list:
    """The entries of an earlier report that rtval did not write (an input image put there,
    notes): replacing the report would delete them."""
    return sorted(n for n in os.listdir(directory)
                  if not _OWN.match(n) or not os.path.isfile(os.path.join(directory, n)))


def check_target(directory: str, keep: dict | None = None) -> None:
    """Refuse up front (WriteError, one line) a ``--report DIR`` that would lose something:
    DIR may be new, empty, or an earlier report holding only what rtval wrote (which is
    replaced), and must not be or hold a file or directory the run reads or writes
    (``keep``: what -> path, e.g. {"-o": "out/validate", "--junit": "j.xml"}; None skipped)."""
    from rt_core.outputs import WriteError
    mine = os.path.realpath(directory)
    for opt, other in (keep or {}).items():
        if not other:
            continue
        theirs = os.path.realpath(other)
        if theirs == mine or theirs.startswith(mine.rstrip(os.sep) + os.sep):
            raise WriteError(directory, f"it holds the {opt} {other}, which the report "
                                        "would replace",
                             "give --report a directory of its own" + (
                                 f", e.g. {os.path.join(other, 'report')}"
                                 if os.path.isdir(other) else ", not the one that holds it"))
    if os.path.exists(directory) and not os.path.isdir(directory):
        raise WriteError(directory, "exists and is not a directory",
                         "give --report a directory name")
    if os.path.isdir(directory) and os.listdir(directory) and not _is_report(directory):
        raise WriteError(directory, "is a directory with other files in it, not an rtval "
                                    "report", "give --report a new or empty directory")
    if os.path.isdir(directory) and _is_report(directory) and _foreign(directory):
        names = _foreign(directory)
        raise WriteError(directory, "is an earlier rtval report that also holds "
                                    f"{', '.join(names[:3])}{', ...' if len(names) > 3 else ''}"
                                    ", which replacing it would delete",
                         "move them out, or give --report another directory")
    from rt_core.outputs import check_dir_target
    check_dir_target(directory)         # (writable: refused before the run, not after it)


def _remove_stale_dirs(parent: str) -> None:
    """Remove temporary report directories that killed rtval runs left in ``parent``."""
    from rt_core.outputs import _SPACE, TMP_PREFIX, left_by_killed_runs
    for name in left_by_killed_runs(parent, f"{TMP_PREFIX}{_SPACE}-"):
        path = os.path.join(parent, name)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
            print(f"rtval: removed {path}, left by a killed run", file=sys.stderr)


def _write(path: str, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
    if os.path.getsize(path) != len(data):
        raise OSError(errno.ENOSPC, "No space left on device")


def write_report(directory: str, title: str, rows: list, skipped: list = (),
                 command: str | None = None, meta: dict | None = None,
                 skipped_fail: bool = False) -> str:
    """Write the report into ``directory`` (new, empty or an earlier report); returns the
    path of its index.html.  On any failure nothing is left: no directory, no temporary."""
    from rt_core.outputs import _SPACE, TMP_PREFIX, WriteError, _reason, attr_text, signals_held
    check_target(directory)
    final = os.path.realpath(directory)
    parent = os.path.dirname(final)
    created, d = [], parent                   # parents this write creates, deepest first
    while not os.path.exists(d) and d != os.path.dirname(d):
        created.append(d)
        d = os.path.dirname(d)
    stage = old = None
    try:
        os.makedirs(parent, exist_ok=True)
        _remove_stale_dirs(parent)
        with signals_held():             # no handler between mkdtemp's mkdir and `stage =`
            stage = tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{_SPACE}-{os.getpid()}-", dir=parent)
        html, files = page(title, rows, skipped, final, command, meta, skipped_fail)
        for name, data in files.items():
            _write(os.path.join(stage, name), data)
        # (a scene's or student's name in bytes that are not UTF-8, which Python holds as
        # surrogate escapes: written \xNN, as the JUnit file and the provenance write them;
        # an instructor's review: a traceback, exit 1, the student's pass read as a failure)
        _write(os.path.join(stage, "index.html"), attr_text(html).encode("utf-8"))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(stage, 0o777 & ~umask)
        if os.path.isdir(final):             # an earlier report or an empty directory
            with signals_held():
                old = tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{_SPACE}-{os.getpid()}-", dir=parent)
            os.rename(final, os.path.join(old, "report"))
            try:
                os.rename(stage, final)
            except OSError:
                os.rename(os.path.join(old, "report"), final)
                raise
        else:
            os.rename(stage, final)
        stage = None
    except OSError as exc:
        reason, hint = _reason(exc, stage or "", directory)
        _cleanup(stage, old, created)
        raise WriteError(directory, reason, hint) from None
    except BaseException:                     # Ctrl-C, SIGTERM: nothing half-written stays
        _cleanup(stage, old, created)
        raise
    if old:
        shutil.rmtree(old, ignore_errors=True)
    return os.path.join(directory, "index.html")


def _cleanup(stage, old, created) -> None:
    for d in (stage, old if old and not os.listdir(old) else None):
        if d:
            shutil.rmtree(d, ignore_errors=True)
    for d in created:
        try:
            os.rmdir(d)
        except OSError:
            break


# --- the three commands' reports ----------------------------------------------------------------

def comparisons_report(directory: str, title: str, results, skipped=(), rows_given=None,
                       meta: dict | None = None) -> str:
    """The report of ``rtval validate`` or ``rtval compare``: ``results`` their summary rows
    (with "pictures"), ``skipped`` validate's Skipped files."""
    return write_report(directory, title, [comparison_row(r, rows_given) for r in results],
                        [Skip(s.path, s.category, s.reason) for s in skipped], meta=meta)


def check_report(directory: str, results, name: str | None = None, **command) -> str:
    """The report of ``rtval check`` (``command``: check_command's options; ``name``: whose
    tracer, in the title)."""
    rows, skipped = check_rows(results, **command)
    return write_report(directory, "rtval check" + (f": {name}" if name else ""), rows,
                        skipped, skipped_fail=True)
