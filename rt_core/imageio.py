"""Image files through OpenImageIO: reading any format it knows (EXR, PPM, PNG, TIFF, ...),
writing PNG, and binary PPM byte for byte as the course programs write it.

``read_channels`` reads every channel of every part (subimage) of a file with its pixel
types and header attributes; ``read_image`` reads the 8-bit RGB image a course tracer
wrote.  Errors are one line naming the file (OpenImageIO's own message, retrieved from the
library, never from its console output).  Writers take a (rows, columns, 3) uint8 array,
row 0 the top of the image, and write atomically (``outputs.atomic_write``): an error never
leaves a partial file.

PPM header: ``P6 <W> <H> 255`` and one newline, on one line, as five of the six course
programs write it (``"P6 %d %d 255\\n"`` in cblades, scottgigawatt, m4rk4l, coilingdragon and
NickWilsonDev; rocketman768 alone writes ``P6\\n<W>\\n<H>\\n255\\n``).  Pixels follow as RGB
bytes, top row first: byte for byte what those programs output for the same pixels.
OpenImageIO's PPM writer puts the header on three lines (``P6\\n<W> <H>\\n255\\n``), so the
PPM writer stays here; every reader of PPM (OpenImageIO's included) accepts both.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field

import numpy as np

from .inputfile import LIMITS, check_input
from .native import native_output_captured
from .outputs import atomic_write, attr_text
from .usererror import InputError

EXR_MAGIC = b"\x76\x2f\x31\x01"       # the first four bytes of every OpenEXR file


class ImageError(ValueError):
    """An image that cannot be read; ``str(err)`` is one line naming the file."""
    exit_code = 2


def _oiio():
    import OpenImageIO
    return OpenImageIO


# ----------------------------------------------------------------------------- reading

@dataclass
class ImageData:
    """One image file: ``channels`` {name: 2-D array, rows top first} (float32, or uint32
    for an EXR's UINT channels), ``types`` {name: pixel type as exrinfo names it: HALF,
    FLOAT, UINT, UINT8, ...; ``deep FLOAT`` for a deep channel}, ``header`` {attribute:
    value} of the first part with ``parts`` (their names) for a multi-part file.  A deep
    file has ``types`` but no ``channels`` (its pixels are checked, not kept)."""
    path: str
    width: int
    height: int
    channels: dict
    types: dict
    header: dict
    format: str = ""                 # OpenImageIO's name of the file format: openexr, pnm, png
    deep: bool = False
    parts: list = field(default_factory=list)
    data_window: list | None = None       # [[x0, y0], [x1, y1]]
    display_window: list | None = None
    tiled: bool = False


def _error_of(obj) -> str:
    """The pending error message of an OpenImageIO object (or of the module), retrieved, so
    that the library does not print it when the object goes away."""
    try:
        return obj.geterror()
    except UnicodeDecodeError:           # it quotes a damaged header's bytes
        return "its message is not UTF-8 text: the file's header is damaged"


def _reason(text: str, path: str) -> str:
    """OpenImageIO's error text as one short clause: its first line, without the file name
    (the caller's message starts with it)."""
    line = next((ln.strip() for ln in (text or "").splitlines() if ln.strip()), "")
    for form in (f' "{path}"', f" ({path})", f" {path}", path):
        line = line.replace(form, "")
    line = line.replace(" :", ":").replace("  ", " ").strip(" .")
    line = line.split(". ")[0]
    # ('could not find a format reader for "x.dat"', the name taken out)
    return (line + " it" if line.endswith(" for") else line) or "no reason given"


def _needs_bytes(path: str, error, spec, bytes_per_value: int) -> None:
    """Refuse before allocating what this process cannot hold (a damaged header may claim
    any size)."""
    from .memory import available
    have, why = available()
    need = spec.width * spec.height * max(1, spec.nchannels) * bytes_per_value
    if need > 0.9 * have:
        size = lambda n: f"{n / 1e9:.1f} GB" if n >= 1e9 else f"{n / 1e6:.0f} MB"
        raise error(f"{path}: its {spec.width} x {spec.height} pixels need {size(need)}, "
                    f"{size(have)} available ({why}); is the file damaged?")


def open_input(path, what: str = "image", error=ImageError):
    """An open ``ImageInput`` for ``path`` (a regular file within the size limit for
    ``what``), or ``error`` with one line naming the file."""
    oiio = _oiio()
    path = os.fspath(path)
    if not os.path.exists(path):
        raise error(f"{path}: no such file")
    try:
        size = check_input(path, what)
        with open(path, "rb"):              # (OpenImageIO says only "Could not open file")
            pass
        if what == "EXR or other image" and size > LIMITS["image"]:
            with open(path, "rb") as f:         # an EXR's limit only for an EXR
                if f.read(4) != EXR_MAGIC:
                    check_input(path, "image")
    except InputError as exc:
        raise error(str(exc)) from None
    except OSError as exc:
        raise error(f"{path}: cannot read it ({(exc.strerror or str(exc)).lower()})") from None
    if size == 0:
        raise error(f"{path}: the file is empty")
    try:
        path.encode("utf-8")
    except UnicodeEncodeError:
        raise error(f"{attr_text(path)}: the file name is not UTF-8, which OpenImageIO cannot "
                    "open; rename the file") from None
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)    # colours as stored, not premultiplied
    with native_output_captured(fds=(2,)):            # libpng's own "libpng error: ..."
        inp = oiio.ImageInput.open(path, config)
    if inp is None:
        reason = _reason(_error_of(oiio), path)
        said = _text_before_pnm(path) or _pnm_header_problem(path)
        if said:
            raise error(f"{path}: {said}")
        raise error(f"{path}: cannot read it as an image ({reason}); "
                    "rtval reads what OpenImageIO reads: EXR, PPM, PNG, TIFF, ...")
    return inp


def _text_before_pnm(path: str) -> str | None:
    """Text, then a PNM header (within the first 8 KiB): a tracer that printed messages to
    standard output before its image (> {out} took both)."""
    try:
        with open(path, "rb") as f:
            data = f.read(1 << 13)
    except OSError:
        return None
    for m in re.finditer(rb"P[1-6]\s", data):
        k = m.start()
        if not k or _pnm_header(data[k:]) is None:
            continue
        text = _text(data[:k])
        if text is None:
            return None
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        first = f", the first {lines[0][:40]!r}" if lines else ""
        return (f"{k} bytes of text before the PPM header (P{chr(data[k + 1])} at byte {k})"
                f"{first}: the tracer printed messages to standard output, where the image "
                "goes? (print them to stderr, or remove them)")
    return None


# a PNM file's extensions: a file named so that does not start with a PNM magic is said
# to be no PPM (OpenImageIO: "Could not parse spec for file")
PNM_SUFFIXES = (".ppm", ".pnm", ".pgm", ".pbm")
_FIELDS = ("width", "height", "maxval")


def _pnm_header_problem(path: str) -> str | None:
    """What is wrong with the header of a file OpenImageIO could not open as a PNM, in the
    course programs' words: a magic number the course does not write ('p6', 'P7'), a field
    that is not a number, no maxval, or no whitespace byte after the maxval (the samples
    written right after it).  None where the file does not look like a PNM (its first byte
    not 'P' or 'p', and its name not .ppm, .pnm, .pgm, .pbm)."""
    try:
        with open(path, "rb") as f:
            data = f.read(1 << 12)
    except OSError:
        return None
    named = os.path.splitext(path)[1].lower() in PNM_SUFFIXES
    magic = data[:2]
    if not re.fullmatch(rb"P[1-6]", magic):
        course = "a PPM starts with 'P6' (binary samples) or 'P3' (ASCII)"
        if re.fullmatch(rb"p[1-6]", magic):
            return f"the magic number is {magic.decode()!r}, lower case; {course}"
        if re.fullmatch(rb"[Pp][0-9A-Za-z]", magic):
            return f"the magic number is {magic.decode()!r}, not a PPM's; {course}"
        if named:
            shown = data[:16].decode("latin-1")
            return (f"not a PPM: {course}, this file with {shown!r}"
                    + (" (text)" if _text(data[:64]) is not None else ""))
        return None
    if magic in (b"P1", b"P4"):              # (bitmaps: no maxval; left to OpenImageIO)
        return None
    header = f"a {magic.decode()} header is '{magic.decode()} width height maxval' and one " \
        "whitespace byte (a newline) before the samples"
    i, n = 2, len(data)
    for name in _FIELDS:
        while i < n and (data[i:i + 1].isspace() or data[i:i + 1] == b"#"):
            if data[i:i + 1] == b"#":            # a comment, to the line's end
                while i < n and data[i:i + 1] not in (b"\n", b"\r"):
                    i += 1
            else:
                i += 1
        if i >= n:
            return f"the header ends before its {name}; {header}"
        j = i
        while j < n and data[j:j + 1].isdigit():
            j += 1
        if j == i:                       # not a number where the field goes
            tok = re.match(rb"[^\s#]{1,12}", data[i:])
            if name == "maxval" and not _text_token(tok):
                return (f"no maxval after the height (byte {i} is 0x{data[i]:02x}, not a "
                        f"digit: the samples start there?); {header}")
            return (f"the header's {name} is {tok.group().decode('latin-1')!r}, not a "
                    f"number; {header}")
        if name == "maxval" and j < n and not data[j:j + 1].isspace():
            return (f"no whitespace byte after the maxval {data[i:j].decode()} (byte {j} is "
                    f"0x{data[j]:02x}): the samples were written right after it; {header}")
        i = j
    return None


def _text_token(tok) -> bool:
    """Is a header token's match printable text (a word), not sample bytes?"""
    return tok is not None and all(32 < b < 127 for b in tok.group())


def _text(data: bytes) -> str | None:
    """``data`` as text, if it is text a program printed: UTF-8, printable characters and
    white space, two letters at least; else None."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if sum(c.isalpha() for c in text) < 2 or \
            not all(c.isprintable() or c in "\t\r\n" for c in text):
        return None
    return text


def _type_name(t) -> str:
    return str(t).upper()


def _read_part(inp, path: str, error, index: int, deep_ok: bool):
    """(spec, {channel: 2-D array}, {channel: type}) of subimage ``index``."""
    if not inp.seek_subimage(index, 0):
        raise error(f"{path}: cannot read part {index} ({_reason(_error_of(inp), path)})")
    spec = inp.spec()
    names = list(spec.channelnames)
    formats = list(spec.channelformats) or [spec.format] * len(names)
    types = {n: ("deep " if spec.deep else "") + _type_name(t) for n, t in zip(names, formats)}
    if spec.deep:
        if not deep_ok:
            raise error(f"{path}: a deep {'EXR' if inp.format_name() == 'openexr' else 'image'}"
                        ": rtval compares flat images only; flatten it first "
                        "(oiiotool IN --flatten -o OUT)")
        if inp.read_native_deep_image(index, 0) is None:      # read to check it is whole
            raise error(f"{path}: cannot read the deep pixels, truncated or corrupt "
                        f"({_reason(_error_of(inp), path)})")
        return spec, {}, types
    _needs_bytes(path, error, spec, 4)
    with native_output_captured(fds=(2,)):
        px = inp.read_image(index, 0, 0, len(names), "float")
    if px is None:
        said = _pnm_diagnosis(path, spec) if inp.format_name() == "pnm" else None
        raise error(f"{path}: {said}" if said else
                    f"{path}: cannot read the pixels, truncated or corrupt "
                    f"({_reason(_error_of(inp), path)})")
    px = np.asarray(px, np.float32).reshape(spec.height, spec.width, len(names))
    chans = {n: px[..., i] for i, n in enumerate(names)}
    if inp.format_name() == "openexr":
        # an EXR's UINT channel holds integers (ids); read as float, OpenImageIO would
        # normalise them to [0, 1] as it does 8-bit colours
        for i, (n, t) in enumerate(zip(names, formats)):
            if str(t) == "uint":
                u = inp.read_image(index, 0, i, i + 1, "uint")
                if u is None:
                    raise error(f"{path}: cannot read channel {n} "
                                f"({_reason(_error_of(inp), path)})")
                chans[n] = np.asarray(u, np.uint32).reshape(spec.height, spec.width)
    return spec, chans, types


def read_channels(path, deep_ok: bool = False, what: str = "image",
                  error=ImageError) -> ImageData:
    """Every channel of every part of an image file (OpenImageIO reads it).

    A multi-part file's channels are named ``part.channel`` (the part's name, or
    ``part<i>``) and its parts must share one size.  A deep file is refused unless
    ``deep_ok`` (``rtval exr info``).  Integer formats (PPM, PNG) come as OpenImageIO's
    normalised floats (0..1), as idiff and oiiotool see them; an EXR's UINT channels as
    uint32.  ``error`` (one line naming the file) for anything unreadable."""
    path = os.fspath(path)
    inp = open_input(path, what, error)
    try:
        fmt = inp.format_name()
        nparts = max(1, inp.spec().get_int_attribute("oiio:subimages", 1))
        parts = [_read_part(inp, path, error, i, deep_ok) for i in range(nparts)]
    finally:
        inp.close()
    spec0 = parts[0][0]
    if fmt == "pnm":
        _pnm_checks(path, spec0, error)
    header = {a.name: a.value for a in spec0.extra_attribs if a.name != "oiio:subimages"}
    data = ImageData(path, spec0.width, spec0.height, {}, {}, header, fmt,
                     deep=any(s.deep for s, _, _ in parts), tiled=spec0.tile_width > 0,
                     data_window=[[spec0.x, spec0.y],
                                  [spec0.x + spec0.width - 1, spec0.y + spec0.height - 1]],
                     display_window=[[spec0.full_x, spec0.full_y],
                                     [spec0.full_x + spec0.full_width - 1,
                                      spec0.full_y + spec0.full_height - 1]])
    if nparts == 1:
        data.channels, data.types = parts[0][1], parts[0][2]
        return data
    data.parts = [s.get_string_attribute("oiio:subimagename") or f"part{i}"
                  for i, (s, _, _) in enumerate(parts)]
    header["parts"] = data.parts
    for pname, (s, ch, ty) in zip(data.parts, parts):
        if (s.width, s.height) != (spec0.width, spec0.height):
            raise error(f"{path}: a multi-part file whose parts differ in size ({pname} is "
                        f"{s.width} x {s.height}, part 0 is {spec0.width} x {spec0.height}); "
                        "rtval reads parts of one size")
        data.types.update({f"{pname}.{k}": v for k, v in ty.items()})
        data.channels.update({f"{pname}.{k}": v for k, v in ch.items()})
    return data


def read_image(path: str) -> np.ndarray:
    """A (rows, columns, 3) uint8 image, row 0 the top, from any file OpenImageIO reads
    (the course tracers write binary or ASCII PPM; PNG works too).  Grey images are
    repeated into R, G and B, alpha is dropped; 16-bit and other maxvals are scaled to 8
    bits by OpenImageIO."""
    path = os.fspath(path)
    inp = open_input(path, "image", ImageError)
    try:
        spec = inp.spec()
        if spec.deep:
            raise ImageError(f"{path}: a deep image; expected the 8-bit image a tracer writes")
        _needs_bytes(path, ImageError, spec, 1)
        if str(spec.format) in ("float", "half", "double"):
            _finite_samples(path, inp, spec)
        with native_output_captured(fds=(2,)):
            px = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
        if px is None:
            said = _pnm_diagnosis(path, spec) if inp.format_name() == "pnm" else None
            raise ImageError(f"{path}: {said}" if said else
                             f"{path}: cannot read the pixels, truncated or corrupt "
                             f"({_reason(_error_of(inp), path)})")
        if inp.format_name() == "pnm":
            _pnm_checks(path, spec, ImageError)
    finally:
        inp.close()
    px = np.asarray(px, np.uint8).reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels < 3:
        return np.repeat(px[..., :1], 3, -1)
    return np.ascontiguousarray(px[..., :3])


def _finite_samples(path: str, inp, spec) -> None:
    """A floating-point image (EXR, PFM, HDR) with a NaN or infinite sample is bad input:
    OpenImageIO's conversion to 8 bits makes NaN 0, so a tracer's NaN would pass as black.
    The first such pixel is named."""
    with native_output_captured(fds=(2,)):
        px = inp.read_image(0, 0, 0, spec.nchannels, "float")
    if px is None:
        return                          # (unreadable: the caller says so)
    px = np.asarray(px, np.float32).reshape(spec.height, spec.width, spec.nchannels)
    bad = ~np.isfinite(px[..., :3])
    if bad.any():
        y, x, c = (int(v[0]) for v in np.nonzero(bad))
        raise ImageError(f"{path}: {int(bad.sum())} samples are NaN or infinite (the first at "
                         f"column {x}, row {y}: {px[y, x, c]}); a course image has a colour "
                         "0..255 in every sample")


def _pnm_header(data: bytes):
    """(magic, width, height, maxval, offset of the first sample) of a PNM file's bytes, or
    None: four tokens, '#' comments to the line's end, then one whitespace byte."""
    toks, i, n = [], 0, len(data)
    while len(toks) < 4 and i < n:
        c = data[i:i + 1]
        if c == b"#":
            while i < n and data[i:i + 1] not in (b"\n", b"\r"):
                i += 1
        elif c.isspace():
            i += 1
        else:
            j = i
            while j < n and not data[j:j + 1].isspace() and data[j:j + 1] != b"#":
                j += 1
            toks.append(data[i:j])
            i = j
    if len(toks) < 4 or not all(t.isdigit() for t in toks[1:]):
        return None
    return toks[0].decode("latin-1"), int(toks[1]), int(toks[2]), int(toks[3]), i + 1


def _pnm_start(path: str):
    """(first 8 KiB, file size, _pnm_header of them) of a PNM file; None if it cannot be
    read or has no PNM header (the size tells about the samples the bytes do not hold)."""
    try:
        with open(path, "rb") as f:
            data = f.read(1 << 13)
        size = os.path.getsize(path)
    except OSError:
        return None
    head = _pnm_header(data)
    return None if head is None else (data, size, head)


# samples a pixel, per PNM kind the course writes
_CHANNELS = {"P3": 3, "P6": 3, "P2": 1, "P5": 1}


def _pnm_diagnosis(path: str, spec) -> str | None:
    """What is wrong with a PNM whose pixels OpenImageIO could not read, in the course
    programs' words, where the header and the size tell: a maxval above 255 over one-byte
    samples, a P3/P2 header over binary samples, or too few bytes for the header's size."""
    got = _pnm_start(path)
    if got is None:
        return None
    data, size, (magic, w, h, maxval, start) = got
    ch = _CHANNELS.get(magic)
    if ch is None:
        return None
    body = size - start                 # bytes of samples
    if magic in ("P3", "P2"):
        if any(b > 126 or (b < 32 and b not in b"\t\n\r\x0b\x0c") for b in data[start:]):
            return (f"a {magic} (ASCII) header over binary samples: write "
                    f"{'P6' if magic == 'P3' else 'P5'} for bytes, or the samples as numbers")
        return _ascii_diagnosis(path, start - 1, w, h, w * h * ch)
    one = w * h * ch
    said = _ascii_under_binary(magic, data, start)
    if said and body != one * (2 if maxval > 255 else 1):
        return said
    if maxval > 255 and one <= body < 2 * one:
        return (f"maxval {maxval} means two bytes a sample, but the file holds {body} "
                f"bytes for {w}x{h} pixels, one a sample: write maxval 255")
    need = one * (2 if maxval > 255 else 1)
    if body < need:
        return (f"truncated: the header says {w}x{h} pixels, {need} bytes of samples; the "
                f"file holds {body}")
    return None


def _ascii_diagnosis(path: str, start: int, w: int, h: int, need: int) -> str | None:
    """What is wrong with the samples of an ASCII PNM (from byte ``start``): the first one
    that is not a whole number (12.0, 255,0,0, [255), named by line, or too few of them."""
    import re
    try:
        with open(path, "rb") as f:
            text = f.read().decode("latin-1")
    except OSError:
        return None
    line0 = text.count("\n", 0, start) + 1
    body = re.sub(r"#[^\n\r]*", "", text[start:])
    count = 0
    for m in re.finditer(r"\S+", body):
        if not m.group().isdigit():
            line = line0 + body.count("\n", 0, m.start())
            return (f"line {line}: sample {count + 1} is {m.group()[:20]!r}; an ASCII PPM's "
                    "samples are whole numbers apart by spaces")
        count += 1
        if count >= need:
            return None
    return f"truncated: the header says {w}x{h} pixels, {need} samples; the file holds {count}"


def pnm_maxval(path: str) -> int | None:
    """A PNM file's maxval (None for other files, or an unreadable header)."""
    got = _pnm_start(path)
    return got[2][3] if got and got[2][0] in _CHANNELS else None


def _ascii_under_binary(magic: str, data: bytes, start: int) -> str | None:
    """A binary PNM header (P6, P5) over samples written as numbers in text (printf's
    "%d "): its bytes digits and white space only, a few of each."""
    body = data[start:start + 4096]
    if magic not in ("P6", "P5") or len(body) < 8 or \
            body.strip(b"0123456789 \t\r\n") or not re.search(rb"\d\s+\d", body):
        return None
    return (f"a {magic} (binary) header over ASCII samples (numbers written as text): write "
            f"{'P3' if magic == 'P6' else 'P2'} for numbers, or the samples as bytes "
            "(fwrite, putc)")


def _pnm_surplus(path: str) -> str | None:
    """What is wrong with a binary PNM that holds more samples than its header says, which
    OpenImageIO reads without a word: a header whose lines end in CR LF (written in text
    mode: the samples start a byte late, every pixel off), or a row or more beyond the
    header's size (a loop that writes one row too many).  A few bytes more (a final
    newline) are fine."""
    got = _pnm_start(path)
    if got is None or got[2][0] not in ("P6", "P5"):
        return None
    data, size, (magic, w, h, maxval, start) = got
    ch = _CHANNELS[magic]
    row = w * ch * (2 if maxval > 255 else 1)
    need, body = row * h, size - start
    said = _ascii_under_binary(magic, data, start) if body != need else None
    if said:
        return said
    if body > need and data[start - 1:start + 1] == b"\r\n":
        return ("the header's lines end in CR LF (a file written in text mode?): after "
                "maxval a PPM takes one byte, so its samples would start a byte late; write "
                "the file in binary mode, lines ending in \\n")
    extra = body - need
    if extra >= 2:
        # text after the samples: messages printed to standard output after the image
        try:
            with open(path, "rb") as f:
                f.seek(size - min(extra, 1 << 12))
                tail = f.read()
        except OSError:
            tail = b""
        # (words, not a few extra pixels whose bytes happen to be letters: white space in
        # it, or four letters and more than one character)
        text = _text(tail[len(tail) - extra:] if extra <= len(tail) else tail)
        if text is not None and (any(c.isspace() for c in text) or (
                sum(c.isalpha() for c in text) >= 4 and len(set(text)) > 1)):
            last = [ln.strip() for ln in text.splitlines() if ln.strip()][-1]
            return (f"{extra} bytes after the pixels end in text ({last[:40]!r}): the tracer "
                    "printed messages to standard output after the image? (print them to "
                    "stderr, or remove them)")
    if body - need >= row:
        return (f"the header says {w}x{h} pixels, {need} bytes of samples; the file holds "
                f"{body}, {(body - need) / row:.3g} row{'s' if body - need != row else ''} more: "
                "write as many rows as the header says")
    return None


def _pnm_checks(path: str, spec, error) -> None:
    """What read_image and read_channels refuse in a PNM that OpenImageIO reads without a
    word: a maxval of 0 (read as full white), samples above the maxval (scaled and clamped)
    or below 0 (read as 0), more samples than the header says (``rtval exr`` read them as
    check refuses them, a review: a PPM with a row too many passed exr diff)."""
    if spec.get_int_attribute("oiio:BitsPerSample", 8) == 0:
        raise error(f"{path}: a PPM whose maxval is 0; expected 1 to 65535 (255 for the "
                    "course's 8-bit image)")
    if not spec.get_int_attribute("pnm:binary", 1):
        try:
            _ascii_samples_in_range(path)
        except ImageError as exc:
            raise error(str(exc)) from None
        return
    said = _pnm_surplus(path) or _binary_samples_over(path)
    if said:
        raise error(f"{path}: {said}")


def _binary_samples_over(path: str) -> str | None:
    """A binary PPM or PGM (P6, P5) with a sample above its maxval (a maxval other than 255
    or 65535, the largest a sample's bytes hold), as _ascii_samples_in_range for ASCII
    ones: OpenImageIO scales the samples by 255/maxval and clamps, so a tracer's 255 under
    maxval 1 would read as white.  The first such sample is named by its pixel."""
    got = _pnm_start(path)
    if got is None or got[2][0] not in ("P6", "P5") or got[2][3] in (255, 65535):
        return None
    _, _, (magic, w, h, maxval, start) = got
    ch = _CHANNELS[magic]
    dt = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)
    try:
        px = np.fromfile(path, dt, w * h * ch, offset=start)
    except (OSError, ValueError):
        return None
    over = np.flatnonzero(px > maxval)
    if not len(over):
        return None
    k = int(over[0]) // ch
    return (f"sample {int(px[over[0]])} above the maxval {maxval} (column {k % w}, row "
            f"{k // w}; {len(over)} samples in all); clamp each colour to 0..{maxval} before "
            f"writing it, or write maxval 255")


def _ascii_samples_in_range(path: str) -> None:
    """An ASCII PPM or PGM (P3, P2) whose samples exceed its maxval is bad input: OpenImageIO
    clamps them, so a tracer that writes 300 where the notes clamp to 255 would look right.
    The first such sample is named by line.  (Anything else odd is left to OpenImageIO.)
    The samples are parsed in one pass (numpy's text parser: 0.15 s for a 1920x1080 P3,
    where a line at a time took 4 s); the lines are walked only to name the bad one."""
    import re
    import warnings
    with open(path, "rb") as f:
        text = f.read().decode("latin-1")
    lines = text.splitlines()
    header, maxval = [], None
    for start, ln in enumerate(lines):      # the header: magic, width, height, maxval
        toks = ln.split("#", 1)[0].split()
        take = 4 - len(header)
        header += toks[:take]
        if len(header) == 4:
            if header[0] not in ("P2", "P3"):
                return
            try:
                maxval = int(header[3])
            except ValueError:
                return
            first = " ".join(toks[take:])
            break
    else:
        return
    body = first + "\n" + re.sub(r"#[^\n]*", "", "\n".join(lines[start + 1:]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")      # (a token that is not a number: not ours)
        try:
            vals = np.fromstring(body, dtype=np.int64, sep=" ")
        except (ValueError, DeprecationWarning):
            return
    if not vals.size or (vals.max() <= maxval and vals.min() >= 0):
        return
    for no in range(start + 1, len(lines) + 1):     # the first line holding one, named
        toks = (first if no == start + 1 else lines[no - 1].split("#", 1)[0]).split()
        got = [int(t) for t in toks if t.lstrip("-").isdigit()]
        big = [v for v in got if v > maxval]
        if big:
            raise ImageError(f"{path}:{no}: sample {max(big)} above the maxval "
                             f"{maxval}; clamp each colour to 0..{maxval} before writing it")
        neg = [v for v in got if v < 0]
        if neg:     # (OpenImageIO reads them as 0: a tracer's NaN or negative colour black)
            raise ImageError(f"{path}:{no}: sample {min(neg)} below 0; clamp each colour to "
                             f"0..{maxval} before writing it")


# ----------------------------------------------------------------------------- writing

def _check(pixels) -> np.ndarray:
    a = np.asarray(pixels)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected a (rows, columns, 3) uint8 image, got {a.dtype} {a.shape}")
    return np.ascontiguousarray(a)


def ppm_bytes(pixels) -> bytes:
    """The binary PPM (P6) file of an image, as the course programs write it."""
    a = _check(pixels)
    return b"P6 %d %d 255\n" % (a.shape[1], a.shape[0]) + a.tobytes()


def write_ppm(path: str, pixels) -> None:
    data = ppm_bytes(pixels)

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(data)
    atomic_write(path, write)


def write_image(path: str, pixels, text: dict | None = None, fmt: str = "png") -> None:
    """Write ``pixels`` ((rows, columns, channels) uint8 or float32) in OpenImageIO's format
    ``fmt`` (png, whatever the file name's extension), with ``text`` as string attributes
    (PNG text chunks: provenance)."""
    oiio = _oiio()
    a = np.ascontiguousarray(pixels)
    if a.ndim == 2:
        a = a[..., None]
    spec = oiio.ImageSpec(a.shape[1], a.shape[0], a.shape[2],
                          "uint8" if a.dtype == np.uint8 else "float")
    for k, v in (text or {}).items():
        spec.attribute(str(k), attr_text(v))

    def write(tmp):
        out = oiio.ImageOutput.create(fmt)
        if out is None:
            raise RuntimeError(_reason(_error_of(oiio), tmp))
        ok = out.open(tmp, spec) and out.write_image(a)
        ok = out.close() and ok
        if not ok:
            raise RuntimeError(_reason(_error_of(out), tmp))
    atomic_write(path, write)


def write_png(path: str, pixels, text: dict | None = None) -> None:
    """PNG with ``text`` as tEXt chunks (provenance)."""
    write_image(path, _check(pixels), text, "png")
