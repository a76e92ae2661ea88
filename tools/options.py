"""Argument types and option groups shared by the subcommands (argparse only)."""
from __future__ import annotations

import argparse


def positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive whole number, got {v}")
    return v


def number(text: str) -> float:
    """A float that is not NaN (inf allowed: 'no limit')."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if v != v:
        raise argparse.ArgumentTypeError("must be a number, not NaN")
    return v


def nonneg(text: str) -> float:
    v = number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def nonneg_float(text: str) -> float:
    """A finite number >= 0."""
    v = nonneg(text)
    if v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return v


def positive_float(text: str) -> float:
    """A finite number > 0."""
    v = number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    if v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return v


MAX_TIMEOUT = 1e6     # seconds (11 days): above, Python's waits overflow (a traceback)


def timeout_seconds(text: str) -> float:
    """A timeout: a number > 0 and at most MAX_TIMEOUT seconds."""
    v = positive_float(text)
    if v > MAX_TIMEOUT:
        raise argparse.ArgumentTypeError(f"at most {MAX_TIMEOUT:g} seconds, got {text}")
    return v


def at_most(limit: int, why: str):
    """An argparse type: a whole number > 0 and at most ``limit`` (``why``: what the limit
    keeps from happening, said when it is exceeded)."""
    def parse(text: str) -> int:
        v = positive_int(text)
        if v > limit:
            raise argparse.ArgumentTypeError(f"at most {limit}, got {v} ({why})")
        return v
    return parse


def scheduler_address(text: str) -> str:
    """--scheduler: a Dask scheduler's address, tcp://HOST:PORT or HOST:PORT (rtval's
    clusters speak plain TCP: tls:// needs certificates rtval does not take, ucx:// a
    library it does not install; either was a TypeError traceback from Dask)."""
    scheme, sep, _ = text.partition("://")
    if sep and scheme != "tcp":
        raise argparse.ArgumentTypeError(f"{text!r}: rtval connects to Dask schedulers over "
                                         "tcp:// only; give tcp://HOST:PORT")
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty address; give tcp://HOST:PORT")
    return text


def worker_count(text: str) -> int:
    """--workers: 0 and up, at most MAX_WORKERS (each is a process of its own)."""
    v = count(text)
    if v > MAX_WORKERS:
        raise argparse.ArgumentTypeError(f"at most {MAX_WORKERS} local worker processes, got "
                                         f"{v}; for more, start a Dask cluster and give "
                                         "--scheduler")
    return v


MAX_WORKERS = 64


def existing_dir(text: str) -> str:
    """A directory that exists (a typo in it would otherwise go unnoticed)."""
    import os
    if not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"no directory {text!r}" if not os.path.exists(text)
                                         else f"{text!r} is not a directory")
    return text


def percent(text: str) -> float:
    v = nonneg(text)
    if v > 100:
        raise argparse.ArgumentTypeError(f"must be a percentage in [0, 100], got {text}")
    return v


def count(text: str) -> int:
    """A whole number >= 0."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


def rules_arg(text: str):
    from rt_core.rules import Rules
    try:
        return Rules.parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


class Defaulted(str):
    """An option's default value, told apart from the same value given (``given``)."""


def given(value) -> bool:
    """Was this option value given on the command line (not its Defaulted default)?"""
    return not isinstance(value, Defaulted)


def add_image_options(p: argparse.ArgumentParser, columns_required: bool = True) -> None:
    """--columns/--rows/--precision/--backend/--sampling/--rules."""
    p.add_argument("--columns", type=positive_int, required=columns_required,
                   default=None if columns_required else 160,
                   help="image width in pixels" + ("" if columns_required else " (default 160)"))
    p.add_argument("--rows", type=positive_int, default=None,
                   help="image height (default: int(world_h / world_w * columns))")
    p.add_argument("--precision", choices=("f32", "f64"), default=Defaulted("f32"))
    p.add_argument("--backend", choices=("llvm", "cuda"), default="llvm")
    p.add_argument("--sampling", choices=("corners", "centers"), default="corners",
                   help="course corner grid (default) or pixel centres")
    add_rules(p)


RULES_HELP = ("rule variants of real course programs: t_min=1e-4, screen_clip='>'|'>='|off, "
              "clip_spheres=true, edges=closed|open, ties=first|last, "
              "reflect=total|segment, rows=course|shifted, tile_add_first=true, "
              "tile_project=false")


def add_rules(p: argparse.ArgumentParser, help: str = RULES_HELP) -> None:
    """--rules NAME=VALUE,... (rt_core.rules.Rules.parse)."""
    p.add_argument("--rules", type=rules_arg, default=None, metavar="NAME=VALUE,...", help=help)


# rt_core.kinds_planar's CODE27_CHOICES, written out: importing rt_core loads Dr.Jit (0.2 s),
# which building the parser need not (rtval --help, usage errors); tests/test_cli.py checks
# that they agree
CODE27_CHOICES = ("auto", "triangle", "disk")


def add_code27(p: argparse.ArgumentParser) -> None:
    """--code27 auto|triangle|disk: how the numeric code 27 is read (rt_core/kinds_planar.py)."""
    p.add_argument("--code27", choices=CODE27_CHOICES, default="auto",
                   help="numeric code 27: a triangle (nw's final program) or a disk (nw's "
                        "older layout); default auto: by the line shape (README \"Triangle\")")


def add_texture_dir(p: argparse.ArgumentParser, more: str = "") -> None:
    """--texture-dir DIR (repeatable): where the textures a scene names are looked for
    first; then the scene file's own directory (rt_core/textures.py)."""
    p.add_argument("--texture-dir", action="append", default=[], metavar="DIR",
                   type=existing_dir,
                   help="look for the scene's texture files (PPM) here first, then next to "
                        "the scene; repeatable; needed only for shaded outputs" + more)


def add_max_dist(p: argparse.ArgumentParser, help: str) -> None:
    """--max-dist D: the notes' MAX_DIST, where reflections stop (None: the default, 1000)."""
    p.add_argument("--max-dist", type=nonneg_float, default=None, metavar="D", help=help)


def add_parallel(p: argparse.ArgumentParser, what: str) -> None:
    """--workers N | --serial | --scheduler ADDRESS, and --verbose: where ``what`` run
    (tools/harness/parallel.py; ``parallel.plan_of(args)`` reads them)."""
    g = p.add_argument_group("where the work runs (Dask)")
    x = g.add_mutually_exclusive_group()
    x.add_argument("--workers", type=worker_count, default=None, metavar="N",
                   help=f"run the {what} on a local Dask cluster of N worker processes "
                        "(default: one per core when the run would take 30 s or more in "
                        "this process); 0 or 1: in this process")
    x.add_argument("--serial", action="store_true",
                   help=f"run the {what} in this process, without Dask (= --workers 0)")
    x.add_argument("--scheduler", metavar="ADDRESS", type=scheduler_address,
                   help=f"run the {what} on the Dask cluster at ADDRESS (e.g. "
                        "tcp://HOST:8786, started with `dask scheduler` and `dask worker "
                        "ADDRESS`; its workers need the same rtval, Dr.Jit and Mitsuba)")
    g.add_argument("--verbose", action="store_true",
                   help="show Dask's warnings, and each worker's cases, set-ups and kernels "
                        "(check --run and --images: also each scene's verdict as it is "
                        "known, as on a terminal)")


# what the commands read (positional arguments) and the files they write (options)
INPUT_DESTS = ("scene", "scenes", "inputs", "file", "files", "a", "b", "hits")
OUTPUT_DESTS = ("output", "junit", "ppm", "png", "json")


def outputs_over_inputs(args) -> list[tuple[str, str, str]]:
    """(option, output, why) for each output file option of ``args`` that names a file
    the command reads: writing it would replace the input (``rtval check S.txt I.ppm
    --junit S.txt`` replaced the scene, ``exr diff A B -o A`` the image A); with ``check
    --images DIR``, a scene's image there (``--junit DIR/S.ppm`` replaced a submission).
    This is the refusal before any work; a file read on the way (a scene's texture) is
    refused when the output is written (rt_core.inputfile.tracking_inputs)."""
    import os
    ins = []
    for dest in INPUT_DESTS:
        v = getattr(args, dest, None)
        ins += [x for x in (v if isinstance(v, list) else [v]) if isinstance(x, str)]
    ins = [x for x in ins if os.path.isfile(x)]
    # (check --images DIR reads the scenes' images there, STEM.ppm, .pnm or .png: an output
    # named so replaced one)
    images = getattr(args, "images", None)
    taken = set()
    if isinstance(images, str) and os.path.isdir(images):
        from pathlib import Path
        taken = {os.path.realpath(os.path.join(images, Path(x).stem + ext))
                 for x in ins for ext in (".ppm", ".pnm", ".png")}   # (check.IMAGE_SUFFIXES)
    found = []
    for dest in OUTPUT_DESTS:
        out = getattr(args, dest, None)
        if not isinstance(out, str) or out == "-":
            continue
        opt = "--" + dest if dest != "output" else "-o"
        if os.path.realpath(out) in taken:
            found.append((opt, out, f"is the image of a scene in the --images directory "
                                    f"{images}, which the check reads"))
            continue
        if not os.path.isfile(out):
            continue
        same = next((x for x in ins if os.path.samefile(x, out)), None)
        if same is not None:
            found.append((opt, out, f"names the input {same}, which writing it would "
                                    "replace"))
    return found
