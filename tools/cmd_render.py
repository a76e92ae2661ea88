"""rtval render: a scene's primary-ray geometry (EXR) and/or its shaded image (PPM, PNG, EXR).

What runs is what the outputs need: ``-o`` alone writes the geometry channels and skips
shading entirely; ``--ppm``/``--png`` (or ``--shade``) shade the image, and an EXR written
beside them also gets ``R``, ``G``, ``B``: the unclamped intensity, whose
floor(255·clamp(I, 0, 1)) is the 8-bit image.
"""
from __future__ import annotations

import os
import sys

from .options import (Defaulted, add_code27, add_image_options, add_max_dist, add_texture_dir,
                      positive_int)


def add_parser(sub) -> None:
    p = sub.add_parser("render", help="render a course scene: geometry EXR and/or shaded image",
                       description="Render a course scene.  -o writes the primary-ray geometry "
                                   "AOVs (hit.mask, depth.Z, object.id, normal, position, uv) "
                                   "as float32 OpenEXR; --ppm/--png write the shaded 8-bit "
                                   "image (ambient, diffuse with shadows, reflections, tiled "
                                   "planes), and then the EXR also gets R, G, B (unclamped).")
    p.add_argument("scene", help="course scene file (keyword or numeric dialect); with "
                                 "--mitsuba a Mitsuba XML scene from rtval convert --shading")
    add_image_options(p, columns_required=False)
    add_code27(p)
    for a in p._actions:        # required, except with --mitsuba (checked in run)
        if a.dest == "columns":
            a.default, a.help = None, "image width in pixels (required unless --mitsuba)"
    p.add_argument("--mitsuba", action="store_true",
                   help="SCENE is a Mitsuba 3 XML scene with the 'course' integrator (rtval "
                        "convert --shading): Mitsuba renders the course image (--ppm/--png, "
                        "-o: R, G, B), with rtval's plugins registered")
    p.add_argument("-o", "--output", metavar="OUT.exr",
                   help="float32 OpenEXR: geometry channels (+ R, G, B when shaded)")
    p.add_argument("--ppm", metavar="OUT.ppm",
                   help="shaded image as binary PPM, as the course programs write it "
                        "(header 'P6 W H 255', top row first)")
    p.add_argument("--png", metavar="OUT.png", help="shaded image as PNG")
    p.add_argument("--shade", action="store_true",
                   help="shade even when only -o is given (adds R, G, B to the EXR)")
    add_max_dist(p, "reflections stop once a path is this long (the notes' MAX_DIST; "
                    "default 1000)")
    add_texture_dir(p)
    p.add_argument("--compression", choices=("piz", "zip", "zstd", "htj2k", "none"),
                   default=Defaulted("piz"), help="EXR compression, all lossless (default piz: read by "
                                       "every OpenEXR; zstd and htj2k are faster and smaller "
                                       "but need OpenEXR 3.4 or later to read)")
    p.add_argument("--tile", type=positive_int, default=None, metavar="ROWS",
                   help="trace the image in bands of ROWS rows, so that memory grows with the "
                        "outputs only (default: bands of about 2 million pixels); the image "
                        "is the same")
    p.add_argument("--json", action="store_true",
                   help="print a summary of what was written as JSON on stdout: the outputs, "
                        "size, hits, reflection bounces, non-finite count, stand-ins, "
                        "provenance (not with --mitsuba)")
    p.add_argument("--explain", action="store_true",
                   help="print on stderr the object kinds, the passes that ran and the Dr.Jit "
                        "kernels they compiled and launched")
    p.set_defaults(func=run, usage_error=p.error)


def _outputs(args) -> list[tuple[str, str]]:
    """(option, path) of every output asked for; usage errors for none or a repeated file."""
    outs = [(opt, path) for opt, path in (("-o", args.output), ("--ppm", args.ppm),
                                          ("--png", args.png)) if path]
    if not outs:
        args.usage_error("nothing to write: give -o OUT.exr, --ppm OUT.ppm and/or --png OUT.png")
    # an output's name must say what it holds (x.png holding EXR bytes helps nobody)
    want = {"-o": (".exr",), "--ppm": (".ppm", ".pnm"), "--png": (".png",)}
    for opt, path in outs:
        ext = os.path.splitext(path)[1].lower()
        if ext and ext not in want[opt]:
            other = next((o for o, e in want.items() if ext in e), None)
            args.usage_error(f"{opt} {path}: {opt} writes {want[opt][0][1:].upper()}; name "
                             f"it {want[opt][0]}" + (f" or use {other}" if other else ""))
    seen = {}
    for opt, path in outs:
        key = os.path.abspath(path)
        if key in seen:
            args.usage_error(f"{seen[key]} and {opt} name the same file {path}")
        seen[key] = opt
    return outs


def run(args) -> int:
    import contextlib
    import time
    clock = [time.perf_counter()]
    phases = {}

    def phase(name):            # wall time since the previous mark (rtval bench --command)
        now = time.perf_counter()
        phases[name] = phases.get(name, 0.0) + now - clock[0]
        clock[0] = now

    import numpy as np
    from rt_core import backend
    from rt_core.camera import make_camera
    from rt_core.errors import InputError
    from rt_core.imageio import write_png, write_ppm
    from rt_core.jitlog import KernelLog
    from rt_core.outputs import WriteError, check_file_target, together
    from rt_core.parser import parse_scene
    from rt_core.memory import band_that_fits, guard, render_bytes
    from rt_core.render import (TILE_PIXELS, nonfinite_by_channel, provenance, render_tiled,
                                write_images)
    from rt_core.rules import Rules
    from rt_core import shading
    from rt_core.shading import DEFAULT_MAX_DIST, quantize

    phase("import")             # (the imports above: rt_core, Dr.Jit, numpy, OpenEXR)
    outs = _outputs(args)
    if args.mitsuba:
        if args.json:
            args.usage_error("--json does not apply with --mitsuba")
        with together():                # (its outputs too: all of them or none)
            code, said = _run_mitsuba(args, outs)
        for line in said:               # each file named only once all are in place
            print(line, file=sys.stderr)
        return code
    if args.columns is None:
        args.usage_error("the following arguments are required: --columns")
    # options that would do nothing: said, as bench says them (a review: accepted, no effect)
    from .options import given
    shading_asked = bool(args.ppm or args.png or args.shade)
    unused = [o for o, v in (("--max-dist", args.max_dist is not None),
                             ("--texture-dir", bool(args.texture_dir))) if v and not shading_asked]
    if given(args.compression) and not args.output:
        unused.append("--compression")
    if unused:
        args.usage_error(f"{', '.join(unused)} not used: --max-dist and --texture-dir go with "
                         "the shaded image (--ppm, --png or --shade), --compression with the "
                         "EXR (-o)")
    rules = args.rules or Rules()
    max_dist = DEFAULT_MAX_DIST if args.max_dist is None else args.max_dist
    shade = bool(args.ppm or args.png or args.shade)
    for _, path in outs:
        check_file_target(path, make_dirs=False)
    scene = parse_scene(args.scene, code27=args.code27)
    if shade:                   # textures are read only where shading needs them
        from rt_core.textures import attach
        scene = attach(scene, args.texture_dir)
    phase("parse")
    T = backend.types(args.precision, args.backend)
    cam = make_camera(scene, args.columns, args.rows, args.sampling, rules)
    need = lambda px, band: render_bytes(px, args.precision, shade, bool(args.output), band)
    band = (args.tile * cam.columns if args.tile else
            band_that_fits(lambda b: need(cam.columns * cam.rows, b), TILE_PIXELS))
    guard(lambda px: need(px, band), "render", cam.columns, cam.rows, "or fewer outputs")
    with (KernelLog() if args.explain else contextlib.nullcontext()) as log:
        images, res = render_tiled(scene, cam, T, rules, tile_pixels=band,
                                   geometry=bool(args.output), shade=shade, max_dist=max_dist,
                                   log=log)
    phase("kernel")
    if shade:
        for note in scene.stand_ins():
            print(f"rtval render: note: {note}", file=sys.stderr)
    if args.explain:
        for line in explain_lines(scene, log, res, max_dist):
            print(f"rtval render: explain: {line}", file=sys.stderr)

    extra = {"shading": "on" if shade else "off"}
    if shade:
        extra.update(max_dist=repr(max_dist), reflection_bounces=res.bounces)
    attrs = provenance(scene, cam, args.precision, args.backend, rules, **extra)
    pixels = None
    if shade:                   # channel by channel: no (rows, columns, 3) float temporary
        pixels = np.empty((cam.rows, cam.columns, 3), np.uint8)
        for k, c in enumerate("RGB"):
            pixels[..., k] = quantize(images[c])
    exr = any(opt == "-o" for opt, _ in outs)
    by_channel = nonfinite_by_channel(images, as_float32=exr)
    bad = sum(by_channel.values())
    report = None
    if args.json:
        from rt_core.outputs import json_text
        report = json_text({
            "outputs": [{"option": opt, "path": path} for opt, path in outs],
            "columns": cam.columns, "rows": cam.rows, "precision": args.precision,
            "objects": len(scene.objects), "hits": int(images["hit.mask"].sum())
            if "hit.mask" in images else None, "shaded": shade,
            "reflection_bounces": res.bounces if shade else None,
            "max_dist": max_dist if shade else None, "nonfinite": bad,
            "stand_ins": scene.stand_ins() if shade else [], "provenance": attrs})
    # everything is computed: write each output (atomically; all of them or none, and the
    # --json report with them: standard output that cannot take it keeps the files out)
    with together():
        for opt, path in outs:
            try:
                if opt == "-o":
                    write_images(path, images, attrs, args.compression)
                elif opt == "--ppm":
                    write_ppm(path, pixels)
                else:       # (its count of non-finite intensities, as the EXR's)
                    write_png(path, pixels, {**attrs, "rtval.nonfinite": str(bad)})
            except WriteError:
                raise                       # one line naming the target already
            except OSError as e:
                raise InputError(f"{path}: cannot write ({e.strerror or e})") from None
        if report is not None:
            print(report, end="")
            sys.stdout.flush()
    phase("write")
    if os.environ.get("RTVAL_PHASES"):      # where rtval bench --command wants the split
        import json
        with open(os.environ["RTVAL_PHASES"], "w") as f:     # (ended_at: exit = the rest)
            json.dump({**phases, "ended_at": time.time()}, f)
    size = f"{cam.columns}x{cam.rows} {args.precision}"
    for opt, path in outs:
        if opt == "-o":
            hits = int(images["hit.mask"].sum())
            msg = (f"{path}: {size} {hits} hits, {len(scene.objects)} objects"
                   + (", shaded R G B" if shade else ""))
        else:
            msg = (f"{path}: {size} shaded, {_n(res.bounces, 'reflection bounce')} "
                   f"(max-dist {max_dist:g})")
        print(msg + (f", {bad} NON-FINITE values" if bad else ""), file=sys.stderr)
    if bad and exr:
        print(f"rtval render: warning: {bad} values not finite in the EXR's float32 (in "
              f"{', '.join(k for k, n in by_channel.items() if n)}): beyond float32's range "
              "(3.4e38), "
              "or NaN; scale the scene down, or write only --ppm or --png", file=sys.stderr)
    if shade and res.capped:
        print(f"rtval render: warning: reflections stopped at the safety cap of "
              f"{shading.MAX_BOUNCES} bounces with {res.left_active} rays still short of "
              f"max-dist {max_dist:g}", file=sys.stderr)
    return 1 if bad else 0


def _run_mitsuba(args, outs) -> tuple[int, list]:
    """Mitsuba renders a converted XML scene with its integrator (the course image with
    'course'); the outputs are written as rtval render writes them."""
    import numpy as np
    from rt_core.errors import InputError
    from rt_core.imageio import write_png, write_ppm
    from rt_core.inputfile import check_input, file_sha256
    from rt_core.outputs import check_file_target
    from rt_core.render import write_images, versions
    from mitsuba_ref.convert import mitsuba
    from tools.harness.shaded import quantize32

    for flag in ("columns", "rows", "rules", "max_dist", "tile"):
        if getattr(args, flag, None) is not None:
            args.usage_error(f"--{flag.replace('_', '-')} does not apply with --mitsuba: the "
                             "XML scene holds the camera, the rules and max_dist (give them "
                             "to rtval convert)")
    from .options import given
    if given(args.precision) or args.backend != "llvm":
        args.usage_error("--precision and --backend do not apply with --mitsuba: Mitsuba "
                         "renders in float32 on its llvm_ad_rgb variant")
    if args.explain or args.shade:
        args.usage_error("--explain and --shade do not apply with --mitsuba")
    for _, path in outs:
        check_file_target(path, make_dirs=False)
    check_input(args.scene, "scene")
    mi = mitsuba()
    try:
        # (not optimize: merged and reordered shapes give an exact tie to another object
        # than compare's Mitsuba scene, loaded the same way)
        ms = mi.load_file(args.scene, optimize=False)
    except Exception as e:          # Mitsuba's parser: one line of its message
        lines = [ln.strip() for ln in str(e).strip().splitlines() if ln.strip()]
        msg = lines[0] if lines else type(e).__name__
        if msg.endswith("Traceback (most recent call last):"):
            # a Python plugin raised (the course integrator refusing a value): its own
            # last line says why
            msg = msg[:-len("Traceback (most recent call last):")].rstrip() + " " + lines[-1]
        raise InputError(f"{args.scene}: Mitsuba cannot load it: {msg}") from None
    integ = ms.integrator()
    name = type(integ).__name__
    if name != "CourseIntegrator":
        raise InputError(f"{args.scene}: its integrator is not 'course' ({name}); convert the "
                         "course scene with rtval convert --shading")
    # the XML's image: too small for the course's samples, or too large for memory, refused
    # before Mitsuba traces (a hand-edited 99999 x 99999 took numpy to 74.5 GiB)
    W, H = integ.columns, integ.rows
    if W < 2 or H < 2:
        raise InputError(f"{args.scene}: the course integrator's image is {W}x{H}; the "
                         "course's corner sampling needs 2 columns and 2 rows at least")
    from rt_core.memory import compare_bytes, guard
    guard(lambda px: compare_bytes(px, "f32"), f"{args.scene}: render --mitsuba", W, H,
          "(convert the scene again with fewer --columns)")
    try:
        I = np.asarray(integ.render(ms, 0), np.float32)
    except ValueError as e:         # the integrator's own refusals: one line
        raise InputError(f"{args.scene}: {e}") from None
    bad = int(np.count_nonzero(~np.isfinite(I)))
    said = []                       # the lines naming each file written
    # the course scene's provenance, as rtval convert recorded it in the XML
    from mitsuba_ref.convert import read_provenance
    with open(args.scene, encoding="utf-8", errors="replace") as f:
        source = read_provenance(f.read())
    attrs = {**source, "rtval.source": "mitsuba course integrator",
             "rtval.scene": os.path.abspath(args.scene),
             "rtval.scene_xml_sha256": file_sha256(args.scene),
             "rtval.integrator": str(integ.to_string()),
             "rtval.versions": " ".join(f"{k}={v}" for k, v in versions().items())}
    # the rules and cut-off the integrator rendered with (the XML may have been edited since
    # rtval convert wrote its provenance); the others (edges, ties, the tile projection)
    # as converted
    import dataclasses
    from rt_core.rules import Rules
    try:
        base = Rules.parse(source.get("rtval.rules", ""))
    except (ValueError, TypeError):
        base = Rules()
    attrs["rtval.rules"] = dataclasses.replace(
        base, t_min=integ.t_min, screen_clip=integ.screen_clip, clip_spheres=integ.clip_spheres,
        reflect=integ.reflect, tile_add_first=integ.tile_add_first,
        rows="shifted" if integ.row_shift else "course").describe()
    if not integ.aovs:
        attrs["rtval.max_dist"] = f"{integ.max_dist:g}"
    if integ.aovs:          # rtval's geometry channels, names and conventions
        from mitsuba_ref.integrator import GEOMETRY
        if any(opt != "-o" for opt, _ in outs):
            args.usage_error("this scene's course integrator renders AOVs (convert --aovs): "
                             "write them with -o OUT.exr")
        images = {name: I[..., k] for k, name in enumerate(GEOMETRY)}
        for _, path in outs:
            write_images(path, images, {**attrs, "rtval.image": "geometry AOVs"},
                         args.compression)
            said.append(f"{path}: {I.shape[1]}x{I.shape[0]} geometry AOVs by Mitsuba's "
                        f"course integrator, {int(images['hit.mask'].sum())} hits"
                        + (f", {bad} NON-FINITE values" if bad else ""))
        return (1 if bad else 0), said
    pixels = quantize32(I)
    for opt, path in outs:
        if opt == "-o":
            write_images(path, {c: I[..., k] for k, c in enumerate("RGB")}, attrs,
                         args.compression)
        elif opt == "--ppm":
            write_ppm(path, pixels)
        else:
            write_png(path, pixels, {**attrs, "rtval.nonfinite": str(bad)})
        said.append(f"{path}: {I.shape[1]}x{I.shape[0]} shaded by Mitsuba's course "
                    f"integrator, {_n(integ.stats.get('bounces', 0), 'reflection bounce')}"
                    + (f", {bad} NON-FINITE values" if bad else ""))
    return (1 if bad else 0), said


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}" + ("" if count == 1 else "es" if noun.endswith("s") else "s")


def explain_lines(scene, log, res, max_dist: float) -> list[str]:
    """What the render did: object kinds, the passes that ran, the kernels they launched."""
    from collections import Counter
    from rt_core.shading import any_specular
    kinds = Counter(o.kind for o in scene.objects)
    lines = [f"scene {scene.path}: {_n(len(scene.objects), 'object')}"
             + (" (" + ", ".join(f"{k} {kinds[k]}" for k in scene.kinds()) + ")" if kinds else "")
             + f", {_n(len(scene.lights), 'light')}, "
             + ("specular surfaces" if any_specular(scene) else "no specular surface")]
    if res is None:
        lines.append("shading: off (geometry only): no shadow or reflection pass")
    else:
        stop = ("no ray left" if not res.capped else
                f"SAFETY CAP reached with {res.left_active} rays active")
        n = len(scene.lights)
        reflects = any_specular(scene) and max_dist > 0
        lines.append("shading: one kernel per bounce (hit, shadow rays, shading)"
                     + (", the reflection rays to their ends in one ('tail')"
                        if any(p.name == "tail" for p in log.passes) else "") + "; "
                     + (f"up to {_n(n, 'shadow ray')} per hit (one per light it faces)" if n else
                        "no lights: no shadow rays") + "; "
                     + (f"{_n(res.bounces, 'reflection bounce')} (max-dist {max_dist:g}; "
                        f"stopped: {stop})" if reflects else "no reflection pass"))
    lines.append(f"{'bounce':<9}{'pass':<12}{'rays':>9}{'kernels':>9}{'compiled':>10}"
                 f"{'disk':>6}{'memory':>8}  other launches")
    # the primary rays and the first reflection pass by pass; deeper bounces summed
    rows: dict = {}
    # the wavefront bounces before the tail (or to the end), and the tail's
    tail = next((p.bounce for p in log.passes if p.name == "tail"), res.bounces + 1
                if res is not None else 1)
    span = lambda a, b: str(a) if b <= a else f"{a}-{b}"
    for p in log.passes:
        label = ("primary" if p.bounce == 0 else
                 span(p.bounce, res.bounces) if p.name == "tail"
                 else str(p.bounce) if p.bounce == 1 else span(2, tail - 1))
        rows.setdefault((label, p.name), []).append(p)
    for (label, name), ps in rows.items():
        k, c, dk = (sum(getattr(p, a) for p in ps) for a in ("kernels", "compiled", "disk"))
        other = Counter()
        for p in ps:
            other.update(p.other)
        lines.append(f"{label:<9}{name:<12}{sum(p.rays for p in ps):>9}{k:>9}{c:>10}{dk:>6}"
                     f"{k - c - dk:>8}  " + ", ".join(f"{n} {v}" for n, v in sorted(other.items())))
    tot = log.total()
    lines.append(f"kernels: {tot.kernels} launched, {tot.compiled} compiled, {tot.disk} loaded "
                 f"from the disk cache, {tot.memory} reused from memory; "
                 f"{len(set(tot.hashes))} distinct; {sum(tot.other.values())} other launches")
    return lines
