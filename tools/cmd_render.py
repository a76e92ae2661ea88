"""rtval render: a scene's primary-ray geometry (and, with --ppm/--png, the shaded image)."""
from __future__ import annotations

import sys

from .options import add_image_options


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="render a course scene to OpenEXR",
                       description="Render the primary-ray geometry AOVs of a course scene "
                                   "(hit.mask, depth.Z, object.id, normal, position, uv) to "
                                   "a float32 OpenEXR file.")
    p.add_argument("scene", help="course scene file (keyword or numeric dialect)")
    add_image_options(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.exr")
    p.set_defaults(func=run)


def run(args) -> int:
    from rt_core.parser import parse_scene
    from rt_core.render import provenance, render_geometry, write_images, nonfinite_count
    from rt_core.camera import make_camera
    from rt_core.rules import Rules

    rules = args.rules or Rules()
    scene = parse_scene(args.scene)
    cam = make_camera(scene, args.columns, args.rows, args.sampling)
    images = render_geometry(scene, cam.columns, cam.rows, args.precision, args.backend,
                             args.sampling, rules)
    write_images(args.output, images, provenance(scene, cam, args.precision, args.backend, rules))
    bad = nonfinite_count(images)
    hits = int(images["hit.mask"].sum())
    print(f"{args.output}: {cam.columns}x{cam.rows} {args.precision} {hits} hits, "
          f"{len(scene.objects)} objects" + (f", {bad} NON-FINITE values" if bad else ""),
          file=sys.stderr)
    return 1 if bad else 0
