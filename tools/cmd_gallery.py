"""rtval gallery: every supported scene, shaded, as PNGs plus an HTML page and a contact sheet.

Scenes: ``scenes/*.txt`` of the repository and ``../shared/course-scenes/**/*.txt`` beside it
(or the files given).  A file the parser rejects (an object kind out of scope, say) is
skipped and listed on stderr with the parser's one-line message.
"""
from __future__ import annotations

import html
import sys
from pathlib import Path
from urllib.parse import quote

from .options import add_code27, add_texture_dir, positive_int

REPO = Path(__file__).resolve().parents[1]
SOURCES = (("scenes", REPO / "scenes"), ("course", REPO.parent / "shared" / "course-scenes"))
THUMBS_PER_ROW = 6
LABEL_HEIGHT = 14


def add_parser(sub) -> None:
    p = sub.add_parser("gallery", help="render every supported scene to PNGs, an HTML page and "
                                       "a contact sheet",
                       description="Render every supported scene in scenes/ and "
                                   "../shared/course-scenes/ (or the SCENE files given) with "
                                   "the course shading: one PNG each, index.html and "
                                   "contact.png.  Unsupported files are listed on stderr.")
    p.add_argument("scenes", nargs="*", metavar="SCENE",
                   help="scene files (default: every .txt in the two scene folders)")
    p.add_argument("-o", "--output", default="out/gallery", metavar="DIR",
                   help="output folder (default out/gallery)")
    p.add_argument("--columns", type=positive_int, default=160,
                   help="image width in pixels (default 160)")
    p.add_argument("--precision", choices=("f32", "f64"), default="f32")
    add_texture_dir(p, "; in the default list a scene whose texture is not found is shaded "
                       "with its MAT, and its caption says so")
    p.add_argument("--json", action="store_true",
                   help="print what was written as JSON on stdout (each scene's PNG, size "
                        "and reflection bounces, the skipped files and why, provenance) "
                        "instead of the two paths")
    add_code27(p)
    p.set_defaults(func=run)


def scene_files(given: list) -> list[tuple[str, Path]]:
    """(name, path) of the scenes to render; names are unique (a given file's name gains its
    folder when two given files share a stem)."""
    if given:
        stems = [Path(g).stem for g in given]
        return [(Path(g).stem if stems.count(Path(g).stem) == 1 else
                 Path(g).with_suffix("").as_posix().lstrip("./"), Path(g)) for g in given]
    out = []
    for label, root in SOURCES:
        for path in sorted(root.rglob("*.txt")):
            if path.name.lower() != "readme.txt":
                out.append((f"{label}/{path.relative_to(root).with_suffix('').as_posix()}",
                            path))
    return out


def run(args) -> int:
    import numpy as np
    from rt_core import backend
    from rt_core.camera import make_camera
    from rt_core.errors import InputError
    from rt_core.exrio import atomic_write
    from rt_core.imageio import write_png
    from rt_core.memory import guard, render_bytes
    from tools.harness.agree import parse_agreed
    from tools.harness.validate import free_name
    from rt_core.render import provenance, render_image, versions
    from rt_core.rules import Rules
    from rt_core.shading import DEFAULT_MAX_DIST
    from rt_core.scene import SceneError
    from rt_core.shading import quantize
    from rt_core.imageio import ImageError
    from rt_core.textures import attach

    from rt_core.outputs import check_dir_target, together
    outdir = Path(args.output)
    check_dir_target(str(outdir))           # refused before any render, not after
    T = backend.types(args.precision)
    done, skipped = [], []
    # every PNG, the page and the sheet are renamed into place at the end, or none is (a
    # scene named on the command line that fails leaves no partial gallery)
    # the PNGs' names: each its own, none the contact sheet's (a scene named contact, d1/s
    # and d1__s wrote over each other: a review)
    used = {"contact.png"}
    sources = {}                        # PNG -> (scene file, its sha256), for --json
    with together():
        for name, path in scene_files(args.scenes):
            note = ""
            try:
                scene = parse_agreed(str(path), args.code27)
                try:
                    scene = attach(scene, args.texture_dir)
                except (SceneError, ImageError) as e:
                    if args.scenes:
                        raise          # a scene named on the command line renders as asked
                    # the default list: the geometry still renders; the MAT stands in (its
                    # stand-in note stays in the PNG's provenance) and the caption says why
                    note = f"{e}: shaded with its MAT"
                    print(f"rtval gallery: {note}", file=sys.stderr)
                cam = make_camera(scene, args.columns)
                guard(lambda px: render_bytes(px, args.precision, True, False, px), "render",
                      cam.columns, cam.rows)
                images, res = render_image(scene, cam, T, geometry=False, shade=True)
            except (SceneError, InputError, ImageError) as e:
                if args.scenes:
                    raise              # a scene named on the command line must render
                why = str(e) if isinstance(e, SceneError) else f"{path}: {e}"
                category = e.category if isinstance(e, SceneError) else "too large"
                skipped.append((name, f"{category}: {why}"))
                print(f"rtval gallery: skipped ({category}) {why}", file=sys.stderr)
                continue
            pixels = quantize(np.stack([images[c] for c in "RGB"], -1))
            file = free_name(name.replace("/", "__"), used, ".png")
            write_png(str(outdir / file), pixels,
                      provenance(scene, cam, args.precision, "llvm", Rules(), shading="on",
                                 max_dist=repr(DEFAULT_MAX_DIST)))
            done.append((name, file, pixels, res.bounces, note))
            sources[file] = (str(path), scene.sha256)
        page = outdir / "index.html"
        sheet = outdir / "contact.png"
        atomic_write(str(page), lambda tmp: Path(tmp).write_text(_html(done, skipped, args)))
        write_png(str(sheet), _contact_sheet(done, args.columns),
                  {"rtval.gallery": f"{len(done)} scenes", "rtval.precision": args.precision,
                   "rtval.backend": "llvm", "rtval.columns": str(args.columns),
                   "rtval.versions": " ".join(f"{k}={v}" for k, v in versions().items())})
    print(f"rtval gallery: {len(done)} scenes rendered, {len(skipped)} skipped", file=sys.stderr)
    if args.json:
        from rt_core.outputs import json_text
        print(json_text({
            "meta": {"columns": args.columns, "precision": args.precision, "backend": "llvm",
                     **versions()},
            "page": str(page), "contact_sheet": str(sheet),
            "scenes": [{"name": n, "png": str(outdir / f), "scene": sources[f][0],
                        "scene_sha256": sources[f][1], "columns": int(p.shape[1]),
                        "rows": int(p.shape[0]), "reflection_bounces": int(b),
                        **({"texture_missing": t} if t else {})}
                       for n, f, p, b, t in done],
            "skipped": [{"name": n, "reason": e} for n, e in skipped]}), end="")
        return 0
    print(page)
    print(sheet)
    return 0


def _html(done, skipped, args) -> str:
    """One page: a figure per image, then the skipped files with their reason."""
    figs = "\n".join(
        f'<figure><img src="{html.escape(quote(f))}" alt="{html.escape(n)}">'
        f"<figcaption>{html.escape(n)}<br>{p.shape[1]}×{p.shape[0]}, "
        f"{b} reflection bounces" + (f"<br><i>{html.escape(t)}</i>" if t else "")
        + "</figcaption></figure>" for n, f, p, b, t in done)
    skips = "\n".join(f"<li><b>{html.escape(n)}</b>: {html.escape(e)}</li>" for n, e in skipped)
    return f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>rtval gallery</title>
<style>body{{font-family:sans-serif;background:#222;color:#ddd}}
figure{{display:inline-block;margin:6px;vertical-align:top}}
figcaption{{font-size:12px;max-width:{args.columns}px;overflow-wrap:anywhere}}
img{{image-rendering:pixelated}}</style></head><body>
<h1>rtval gallery</h1>
<p>{len(done)} scenes, {args.columns} columns, {args.precision}: ambient, diffuse with shadows,
reflections, tiled planes (the course shading).</p>
{figs}
<h2>Skipped ({len(skipped)})</h2>
<ul>{skips}</ul>
</body></html>
"""


def _contact_sheet(done, columns: int):
    """All images on one grid, each with its name under it (uint8 array)."""
    import numpy as np
    from PIL import Image, ImageDraw
    n = max(len(done), 1)
    per_row = min(THUMBS_PER_ROW, n)
    cell_h = max((p.shape[0] for _, _, p, *_ in done), default=1) + LABEL_HEIGHT
    sheet = Image.new("RGB", (per_row * columns, ((n + per_row - 1) // per_row) * cell_h),
                      (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    for i, (name, _, pixels, *_) in enumerate(done):
        x, y = (i % per_row) * columns, (i // per_row) * cell_h
        sheet.paste(Image.fromarray(pixels), (x, y))
        label = name.rsplit("/", 1)[-1]
        draw.text((x + 2, y + pixels.shape[0] + 1), label[: max(columns // 6, 4)],
                  fill=(220, 220, 220))
    return np.asarray(sheet)
