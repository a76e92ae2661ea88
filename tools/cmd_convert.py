"""rtval convert: a course scene as a Mitsuba 3 XML scene."""
from __future__ import annotations

import sys
import os
from pathlib import Path

from .options import add_code27, add_max_dist, add_rules, add_texture_dir, positive_int


def add_parser(sub) -> None:
    p = sub.add_parser("convert", help="write the equivalent Mitsuba 3 XML scene",
                       description="Write the Mitsuba 3 scene equivalent to a course scene: "
                                   "finite planes as rectangles, planes as large rectangles, "
                                   "spheres, and a perspective sensor (its pixels are square, "
                                   "so it makes the course's rays only where the course's "
                                   "sample grid is square: said when it is not); --shading "
                                   "and --aovs make the course's own rays in any case.")
    p.add_argument("scene", help="course scene file (keyword or numeric dialect)")
    p.add_argument("--columns", type=positive_int, required=True,
                   help="image width in pixels (the sensor's film)")
    p.add_argument("--rows", type=positive_int, default=None,
                   help="image height (default: int(world_h / world_w * columns))")
    p.add_argument("--sampling", choices=("corners", "centers"), default="corners",
                   help="course corner grid (default) or pixel centres")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--shading", "--shade", action="store_true", dest="shading",
                   help="the course image: each shape's course MAT as a 'course_material' BSDF, "
                        "the lights as point/spot emitters and the 'course' integrator with the "
                        "camera and rules (render it with rtval render --mitsuba)")
    mode.add_argument("--aovs", action="store_true",
                   help="the 'course' integrator in its AOV mode: rtval render --mitsuba -o "
                        "OUT.exr writes rtval's geometry channels (hit.mask, depth.Z, "
                        "object.id, normal, position, uv), so rtval exr diff compares them "
                        "with rtval render's EXR")
    add_rules(p, "--shading/--aovs: the hit-rule variants the integrator uses (as in rtval "
                 "render; not ties or edges, which Mitsuba's intersection decides)")
    add_max_dist(p, "--shading: reflections stop at this path length (default 1000)")
    add_code27(p)
    add_texture_dir(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.xml",
                   help="the Mitsuba 3 XML scene to write")
    p.set_defaults(func=run, usage_error=p.error)


def run(args) -> int:
    from rt_core.exrio import atomic_write
    from rt_core.outputs import together
    from rt_core.render import scene_provenance
    from tools.harness.agree import parse_agreed
    from mitsuba_ref.convert import (DEFAULT_MAX_DIST, inside_notes, oracle_only,
                                      planes_note, scene_xml, sensor_setup)

    from rt_core.outputs import check_file_target
    if not args.output.lower().endswith(".xml"):
        args.usage_error(f"-o {args.output}: convert writes Mitsuba XML; name it .xml")
    check_file_target(args.output, make_dirs=False)
    parent = os.path.dirname(os.path.abspath(args.output))
    scene = parse_agreed(args.scene, code27=args.code27)
    if args.rows is None:
        # a window whose rows no image can have: the line render and compare give (a review:
        # a traceback at 1e-320, an XML of 1.9e32 rows that Mitsuba cannot read at 1e-30)
        scene.default_rows(args.columns)
    setup = sensor_setup(scene, args.columns, args.rows, args.sampling)
    course = args.shading or args.aovs
    # (said once the files are written: a failed write is then the one line on stderr)
    said = [f"rtval convert: warning: {setup.note}"] if setup.note and not course else []
    if not course and (args.rules or args.max_dist is not None):
        args.usage_error("--rules and --max-dist go with --shading or --aovs")
    if args.max_dist is not None and not args.max_dist <= 3.4028234663852886e38:
        args.usage_error(f"--max-dist {args.max_dist:g}: beyond float32, the course "
                         "integrator's precision (Mitsuba's llvm_ad_rgb); at most 3.4e38")
    # rules the course integrator has no parameter for: refused, not recorded as applied
    # (a review: ties=last gave the same Mitsuba image as ties=first, and the XML's
    # rtval.rules said ties=last)
    fixed = {"ties": "first", "edges": "closed"}
    given = [f"{k}={getattr(args.rules, k)}" for k, v in fixed.items()
             if args.rules is not None and getattr(args.rules, k) != v]
    if given:
        args.usage_error(f"--rules {', '.join(given)}: the course integrator has no "
                         "parameter for it (Mitsuba's own intersection decides exact ties "
                         "and finite-plane edges); convert without it, and check such a "
                         "tracer with rtval check")
    if args.shading:                        # the course image needs the textures
        from rt_core.textures import attach
        scene = attach(scene, args.texture_dir)
    plys: dict = {}                         # triangles, textures: a file each, beside the XML
    xml = scene_xml(scene, args.columns, args.rows, args.sampling, args.shading,
                    rules=args.rules, max_dist=DEFAULT_MAX_DIST if args.max_dist is None else args.max_dist,
                    aovs=args.aovs, files=plys, stem=Path(args.output).name,
                    source=scene_provenance(scene))
    left_out = oracle_only(scene)
    said += [f"rtval convert: note: {note}" for note in left_out + scene.stand_ins()]
    if (planes := planes_note(scene)):
        # (the README's "stand-ins are said on stderr": these were in the XML only)
        said.append(f"rtval convert: note: {planes}")
    # a sphere that holds the viewpoint: out of the sensor's scene, kept in the course image's
    held = inside_notes(scene, course)
    said += [f"rtval convert: note: {note}" for note in held]
    shapes = len(scene.objects) - len(left_out) - (0 if course else len(held))
    with together():                        # the XML and its side files, or none of them
        for name, data in plys.items():
            if isinstance(data, str):
                atomic_write(os.path.join(parent, name),
                             lambda tmp, text=data: Path(tmp).write_text(text))
            else:                           # a texture's texels (mi.Bitmap)
                atomic_write(os.path.join(parent, name),
                             lambda tmp, bm=data: bm.write(tmp, type(bm).FileFormat.OpenEXR))
        atomic_write(args.output, lambda tmp: Path(tmp).write_text(xml))
    for line in said:
        print(line, file=sys.stderr)
    print(f"{args.output}: {shapes} shapes, "
          f"{setup.columns}x{setup.rows}", file=sys.stderr)
    return 0
