"""``rtval exr``: inspect and compare images (iinfo, oiiotool --stats, idiff, FLIP).

Only argument parsing and formatting live here; the work is in :mod:`tools.exrtool`
(OpenImageIO and NVIDIA FLIP underneath).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import textwrap

from .options import count, nonneg, percent

METRICS = ("idiff", "flip")          # tools.exrtool.METRICS (not imported: it loads numpy)

EXIT_CODES = """\
exit codes:
  0   PASS: the images match within the warning and failure limits
  1   WARNING: some pixels differ, but within the failure limits
  2   FAILURE: too many pixels fail, or one exceeds --hard-fail
  3   the images differ in size or in their channels and were not compared
  4   file error: a file is missing, truncated or not an image OpenImageIO reads, a
      requested channel is missing, or the difference image, FLIP map or standard
      output cannot be written
  64  usage error: unknown option, bad or negative option value
"""

DIFF_RULES = """\
A pixel fails when, in any of its channels, the error |a - b| exceeds both --fail
(absolute) and --fail-relative (relative to the mean of |a| and |b|); it warns likewise
with --warn and --warn-relative.  NaN matches only NaN and Inf only the same-signed Inf;
a non-finite value against anything else is an infinite error: that pixel fails and warns
(idiff lets such pixels pass).

As idiff decides: the comparison PASSES when at most --allow-failures pixels fail
(default 0: a comparison in which no pixel fails passes, however many pixels warn; the
hard limits are not consulted).  Otherwise it FAILS if more pixels fail than
--fail-percent of all pixels allow, or an error exceeds --hard-fail; otherwise it is a
WARNING if more than --warn-percent of the pixels warn or an error exceeds --hard-warn,
else it PASSES.  So a WARNING needs failing pixels tolerated by --fail-percent.
Mean and RMS error and the PSNR are OpenImageIO's (idiff's): over all values, a value
non-finite in either image counting as 0.

--metric flip compares the colours (R,G,B, or the three --channels) by NVIDIA FLIP
instead: A is the reference, a pixel's error is its FLIP value in [0, 1] (0: identical),
judged by the same absolute limits and rules; the report gives the FLIP mean, and -o writes
the FLIP error map (.exr: the raw values; other names: a magma-coloured PNG).  Images
within [0, 1] are compared as LDR (sRGB-encoded, as PPM and PNG are), others as HDR.
"""


def _wrap(text: str) -> str:
    return textwrap.fill(text, 88)


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "exr", help="inspect and compare images (info, stats, diff, preview)",
        description=_wrap("Inspect and compare the EXR files rtval writes and the images "
                          "the course tracer writes (any format OpenImageIO reads: EXR, PPM, "
                          "PNG, TIFF, ...), the way iinfo, oiiotool --stats and idiff do, "
                          "with OpenImageIO underneath; FLIP for the perceptual difference."),
        epilog="`rtval exr diff` exits like idiff:\n" + EXIT_CODES
               + "info, stats and preview exit 0, 4 or 64.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="exr_command", required=True, metavar="COMMAND",
                           parser_class=type(p))

    q = sub.add_parser("info", help="size, channels and pixel types, compression, attributes",
                       description=_wrap("Print each file's format, size, windows, "
                                         "compression, channels with pixel types and every "
                                         "header attribute as OpenImageIO names it, rtval.* "
                                         "provenance included (like iinfo -v).  The pixels "
                                         "are read too, so a truncated file is an error."),
                       epilog="exit codes: 0 ok, 4 a file cannot be read or standard output "
                              "cannot be written, 64 usage error",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("files", nargs="+", metavar="FILE")
    q.add_argument("--json", action="store_true", help="print a JSON list, one object per file")
    q.set_defaults(func=run_info)

    q = sub.add_parser("stats", help="per-channel min/max/mean/std and NaN/Inf/finite counts",
                       description=_wrap("Per-channel statistics by OpenImageIO, as "
                                         "`oiiotool --stats` prints them: min, max, mean and "
                                         "std (float32) over the finite values, and NaN, Inf "
                                         "and finite counts.  depth.* channels are also "
                                         "summarised over hit pixels only "
                                         "(hit.mask > 0.5)."),
                       epilog="exit codes: 0 ok, 4 the file or a channel cannot be read or "
                              "standard output cannot be written, 64 usage error",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("file", metavar="FILE")
    _channels_option(q)
    q.add_argument("--json", action="store_true", help="print JSON")
    q.set_defaults(func=run_stats)

    q = sub.add_parser("diff", help="compare two images with idiff's thresholds and exit "
                                    "codes, or by FLIP",
                       description=_wrap("Compare A and B channel by channel with idiff's "
                                         "semantics (OpenImageIO's comparison) and report "
                                         "mean, RMS and max error, PSNR, the worst pixel and "
                                         "the failing and warning pixel counts.")
                       + "\n\n" + DIFF_RULES,
                       epilog=EXIT_CODES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("a", metavar="A")
    q.add_argument("b", metavar="B")
    _channels_option(q)
    q.add_argument("--fail", type=nonneg, default=1e-6, metavar="ABS",
                   help="absolute error a failing pixel exceeds (default 1e-6)")
    q.add_argument("--fail-relative", type=nonneg, default=0.0, metavar="R",
                   help="relative error a failing pixel also exceeds (default 0)")
    q.add_argument("--fail-percent", type=percent, default=0.0, metavar="P",
                   help="percentage of pixels allowed to fail (default 0)")
    q.add_argument("--hard-fail", type=nonneg, default=math.inf, metavar="H",
                   help="fail if any error exceeds H, whatever else is allowed (default inf)")
    q.add_argument("--warn", type=nonneg, default=1e-6, metavar="ABS",
                   help="absolute error a warning pixel exceeds (default 1e-6)")
    q.add_argument("--warn-relative", type=nonneg, default=0.0, metavar="R",
                   help="relative error a warning pixel also exceeds (default 0)")
    q.add_argument("--warn-percent", type=percent, default=0.0, metavar="P",
                   help="percentage of pixels allowed to warn (default 0)")
    q.add_argument("--hard-warn", type=nonneg, default=math.inf, metavar="H",
                   help="warn if any error exceeds H (default inf)")
    q.add_argument("--allow-failures", type=count, default=0, metavar="N",
                   help="N pixels may fail by any amount below --hard-fail (default 0)")
    q.add_argument("--metric", choices=METRICS, default="idiff",
                   help="idiff: |A-B| per value (default); flip: NVIDIA FLIP of the colours")
    q.add_argument("-o", "--output", metavar="DIFF.exr",
                   help="write |A-B| per channel to this EXR, or with --metric flip the "
                        "FLIP error map (.exr or .png); atomically")
    q.add_argument("--json", action="store_true", help="print the report as JSON")
    q.set_defaults(func=run_diff, usage_error=q.error)

    q = sub.add_parser("preview", help="false-colour PNG of one channel with a colour bar",
                       description=_wrap("Write a false-colour PNG of one channel with a "
                                         "colour bar and its min/max: depth in viridis over "
                                         "hit pixels (misses black), object.id in "
                                         "categorical colours (-1 black), normal XYZ as RGB "
                                         "(n+1)/2, hit.mask grey, R/G/B clamped, a difference "
                                         "image (from `diff -o`) in inferno.  NaN/Inf pixels "
                                         "are magenta.  Images narrower than 256 pixels are "
                                         "enlarged by an integer factor."),
                       epilog="exit codes: 0 ok, 4 the file or channel cannot be read or the "
                              "PNG cannot be written, 64 usage error",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    q.add_argument("file", metavar="FILE")
    q.add_argument("-o", "--output", required=True, metavar="OUT.png", help="PNG to write")
    q.add_argument("--channel", metavar="NAME",
                   help="channel or layer to show (default depth.Z, else the first channel)")
    q.add_argument("--json", action="store_true", help="print what was drawn as JSON")
    q.set_defaults(func=run_preview, usage_error=q.error)


# ----------------------------------------------------------------------------- option types

def _channel_list(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",")]
    if not all(names):
        raise argparse.ArgumentTypeError(f"empty channel name in {text!r}")
    return names


def _channels_option(p) -> None:
    p.add_argument("--channels", type=_channel_list, action="append", metavar="LIST",
                   help="comma-separated channels or layers (normal = normal.X,Y,Z); "
                        "may be repeated (default: all)")


def _channels(args):
    return [n for group in args.channels for n in group] if args.channels else None


# ----------------------------------------------------------------------------- output

def _print_json(data) -> None:
    from rt_core.outputs import json_text
    print(json_text(data, indent=2), end="")


def _distinct(a, b) -> str:
    """'a vs b' with as many digits as it takes to tell them apart (up to round-trip)."""
    if isinstance(a, float) and isinstance(b, float):
        for digits in (6, 9, 12, 17):
            sa, sb = f"{a:.{digits}g}", f"{b:.{digits}g}"
            if sa != sb or a == b:
                return f"{sa} vs {sb}"
    return f"{_g(a)} vs {_g(b)}"


def _g(v, width: int = 0) -> str:
    s = "-" if v is None else (f"{v:.6g}" if isinstance(v, float) else str(v))
    return s.rjust(width) if width else s


def _fmt_attr(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "(" + ", ".join(_fmt_attr(x) for x in v) + ")"
    return _g(v)


# ----------------------------------------------------------------------------- commands

def _error(e) -> None:
    print(f"rtval exr: {e}", file=sys.stderr)


def _named(path: str, ext: str) -> bool:
    """``path`` ends in ``ext``, or is a device or pipe (``/dev/null``: no name to check)."""
    import os
    return path.lower().endswith(ext) or (os.path.exists(path) and not os.path.isfile(path)
                                          and not os.path.isdir(path))


def _file_error_is_4(run):
    """exr's exit 4 for an output it refuses or cannot write, standard output included: the
    command line's general 2 is exr diff's FAILURE (a missing directory, /dev/full/x.exr,
    ``> /dev/full`` read as 'too many pixels fail')."""
    import functools

    @functools.wraps(run)
    def wrapped(args) -> int:
        from rt_core.usererror import InputError
        try:
            code = run(args)
            if sys.stdout is not None:
                sys.stdout.flush()          # (a full disk shows here)
            return code
        except BrokenPipeError:
            raise
        except (InputError, OSError) as e:
            e.exit_code = 4                 # (the command line says it, as for any command)
            raise
    return wrapped


@_file_error_is_4
def run_info(args) -> int:
    from rt_core.exrio import ExrError
    from tools import exrtool
    results, code = [], 0
    for path in args.files:
        try:
            results.append(exrtool.info(path))
        except ExrError as e:
            _error(e)
            code = e.exit_code
    if args.json:
        _print_json(results)
        return code
    for r in results:
        (x0, y0), (x1, y1) = r["data_window"] or ((0, 0), (r["width"] - 1, r["height"] - 1))
        print(f"file {r['file']}:")
        print(f"  format          {r['format']}")
        print(f"  size            {r['width']} x {r['height']}")
        print(f"  data window     ({x0}, {y0}) - ({x1}, {y1})")
        if r["display_window"]:
            (dx0, dy0), (dx1, dy1) = r["display_window"]
            print(f"  display window  ({dx0}, {dy0}) - ({dx1}, {dy1})")
        if r["compression"] is not None:
            print(f"  compression     {r['compression']}")
        print(f"  storage         {r['storage']}")
        if r["parts"]:
            print(f"  parts ({len(r['parts'])})       {', '.join(r['parts'])} "
                  "(channels named part.channel; header attributes of part 0)")
        print(f"  channels ({len(r['channels'])}):")
        w = max(len(c["name"]) for c in r["channels"])
        for c in r["channels"]:
            print(f"    {c['name']:<{w}}  {c['type']}")
        print("  attributes:" + ("" if r["attributes"] else " (none)"))
        w = max((len(k) for k in r["attributes"]), default=0)
        for k, v in r["attributes"].items():
            print(f"    {k:<{w}}  {_fmt_attr(v)}")
    return code


_STAT_COLS = ("min", "max", "mean", "std")


@_file_error_is_4
def run_stats(args) -> int:
    from tools import exrtool
    r = exrtool.stats(args.file, _channels(args))
    if args.json:
        _print_json(r)
        return 0
    print(f"{r['file']}: {r['width']} x {r['height']}, {len(r['channels'])} channels")
    w = max(14, *(len(n) + 2 for n in r["channels"]))
    head = f"{'channel':<{w}}" + "".join(f"{c:>14}" for c in _STAT_COLS) \
        + f"{'nan':>9}{'inf':>9}{'finite':>10}"
    print(head)
    for name, s in r["channels"].items():
        rows = [(name, s)]
        if "hit" in s:
            rows.append(("  (hit only)", s["hit"]))
        for label, t in rows:
            if t is None:
                print(f"{label:<{w}}  no hit.mask in the file")
                continue
            print(f"{label:<{w}}" + "".join(_g(t[c], 14) for c in _STAT_COLS)
                  + f"{t['nan']:>9}{t['inf']:>9}{t['finite']:>10}")
    return 0


@_file_error_is_4
def run_diff(args) -> int:
    from tools import exrtool
    if args.metric == "idiff" and args.output and not _named(args.output, ".exr"):
        args.usage_error(f"-o {args.output}: the difference image is an EXR; name it .exr "
                         "(--metric flip writes its map as .exr or .png)")
    if args.metric == "flip":
        if args.fail_relative or args.warn_relative:
            args.usage_error("--metric flip takes absolute limits only: a FLIP error is "
                             "already relative (0 to 1); drop --fail-relative/--warn-relative")
        chans = _channels(args)
        if chans is not None and len(chans) != 3:
            args.usage_error(f"--metric flip compares three colour channels; --channels "
                             f"names {len(chans)} ({','.join(chans)})")
    th = exrtool.Thresholds(
        fail=args.fail, fail_relative=args.fail_relative, fail_percent=args.fail_percent,
        hard_fail=args.hard_fail, warn=args.warn, warn_relative=args.warn_relative,
        warn_percent=args.warn_percent, hard_warn=args.hard_warn,
        allow_failures=args.allow_failures)
    if args.output:
        # (a missing directory is refused, as render's: it made the tree, a review)
        from rt_core.outputs import check_file_target
        check_file_target(args.output, make_dirs=False)
    r = exrtool.diff(args.a, args.b, _channels(args), th, args.output, args.metric)
    if r["exit_code"] == exrtool.MISMATCH:
        _error(r["reason"])
        if args.json:
            _print_json(r)
        return r["exit_code"]
    if args.json:
        _print_json(r)
        return r["exit_code"]
    flip = args.metric == "flip"
    print(f'Comparing "{r["file_a"]}" and "{r["file_b"]}" '
          f'({r["width"]} x {r["height"]}, '
          + (f'FLIP of {",".join(r["channels"])}, {r["flip"]["dynamic_range"]}, '
             f'{r["flip"]["ppd"]:.4g} pixels per degree)' if flip
             else f'{len(r["channels"])} channels)'))
    wst = r["worst"]
    if flip:
        print(f"  FLIP mean = {_g(r['flip_mean'])}")
        print(f"  Max FLIP  = {_g(r['max_error'])}"
              + (f" @ ({wst['x']}, {wst['y']})  colours are "
                 f"{_triple(wst['a'])} vs {_triple(wst['b'])}" if wst else ""))
    else:
        print(f"  Mean error = {_g(r['mean_error'])}")
        print(f"  RMS error = {_g(r['rms_error'])}")
        print(f"  Peak SNR = {_g(r['psnr'])}")
        if wst:
            print(f"  Max error  = {_g(r['max_error'])} @ ({wst['x']}, {wst['y']}, "
                  f"{wst['channel']})  values are {_distinct(wst['a'], wst['b'])}")
        else:
            print("  Max error  = 0")
        if r["nonfinite_mismatches"]:
            print(f"  {r['nonfinite_mismatches']} values non-finite in one image only")
    th = r["thresholds"]
    print(f"  {r['warning_pixels']} pixels ({r['warning_percent']:.3g}%) over {_g(th['warn'])}"
          + (f" and relative {_g(th['warn_relative'])}" if th["warn_relative"] else ""))
    print(f"  {r['failing_pixels']} pixels ({r['failing_percent']:.3g}%) over {_g(th['fail'])}"
          + (f" and relative {_g(th['fail_relative'])}" if th["fail_relative"] else ""))
    differing = {n: c for n, c in r.get("per_channel", {}).items() if c["max_error"] > 0}
    if len(r["channels"]) > 1 and differing:
        w = max(len(n) for n in differing) + 2
        print(f"  {'channel':<{w}}{'max':>12}{'mean':>12}{'rms':>12}{'failing':>9}  worst")
        for n, c in differing.items():
            where = f"({c['worst'][0]}, {c['worst'][1]})" if c["worst"] else "-"
            print(f"  {n:<{w}}{_g(c['max_error'], 12)}{_g(c['mean_error'], 12)}"
                  f"{_g(c['rms_error'], 12)}{c['failing_pixels']:>9}  {where}")
        if len(differing) < len(r["channels"]):
            print(f"  ({len(r['channels']) - len(differing)} other channels identical)")
    for reason in r["reasons"]:
        print(f"  {reason}")
    if r.get("diff_image"):
        print(f"  difference image: {r['diff_image']}")
    if r.get("flip_map"):
        print(f"  FLIP error map: {r['flip_map']}")
    print(r["status"])
    return r["exit_code"]


def _triple(v) -> str:
    return "(" + ", ".join(_g(x) for x in v) + ")"


@_file_error_is_4
def run_preview(args) -> int:
    from tools import exrtool
    if not _named(args.output, ".png"):
        args.usage_error(f"-o {args.output}: the preview is a PNG; name it .png")
    from rt_core.outputs import check_file_target
    check_file_target(args.output, make_dirs=False)
    r = exrtool.preview(args.file, args.output, args.channel)
    if args.json:
        _print_json(r)
    else:
        shown = ",".join(r.get("channels") or [r["channel"]])
        print(f"{r['output']}: {r['width']} x {r['height']} PNG of {shown} "
              f"({r['kind']}; min {_fmt_attr(r['min'])}, max {_fmt_attr(r['max'])})")
    return 0
