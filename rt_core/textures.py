"""Textures of the textured forms (kinds.FORMS: nw's texplane 17 and texsphere 26, rm768's
fplanetex and sphere_pixmap): finding the PPM file a scene names, reading it, and the mapping
of a hit to a texel that rt_core.shading evaluates (README "Textures").

Where a texture is looked for: each ``--texture-dir`` in the order given, then the scene
file's own directory.  Textures are needed only where shading is computed: ``attach`` is
called by the commands that shade, and a geometry-only render never opens the file.

Reading: PPM P6 (binary) and P3 (ASCII), maxval 1..65535, texel = value / maxval.  The
file is read here rather than through OpenImageIO because OpenImageIO rescales a maxval
other than 255 or 65535 to 8 or 16 bits first (measured: value 1 of maxval 100 reads as
2/255), which is not value / maxval.
"""
from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from dataclasses import dataclass, field

import numpy as np

from .imageio import ImageError
from .inputfile import check_input
from .scene import SceneError, fmt
from .usererror import InputError

TEXTURED = ("texplane", "texsphere", "fplanetex", "sphere_pixmap")
# how s, t come from a hit (shading.material): a plane's frame coordinates over ``scale``,
# clamped to the last texel ('fit') or wrapped ('repeat'); a sphere's longitude and latitude
MODE_CODE = {"fit": 1, "repeat": 2, "sphere": 3}


@dataclass(frozen=True)
class Texture:
    name: str                 # as written in the scene
    path: str                 # the file read (absolute)
    sha256: str               # of the file's bytes
    width: int
    height: int
    mode: str                 # MODE_CODE key
    scale: tuple = (1.0, 1.0)  # planes: world units along x̂, ŷ per repeat of the texture
    brightness: float = 1.0
    forward: tuple = (0.0, 0.0, 1.0)   # spheres: unit forward in the xz plane (s = 0)
    side: tuple = (-1.0, 0.0, 0.0)     # spheres: unit(−f.z, 0, f.x) (s = 1/4)
    texels: np.ndarray = field(default=None, compare=False, repr=False)  # (H, W, 3) float64

    def describe(self) -> str:
        return f"{self.path} ({self.width}x{self.height}, sha256 {self.sha256})"


def textured(scene) -> list:
    """(object id, object) of every object written in a textured form."""
    return [(i, o) for i, o in enumerate(scene.objects) if o.form in TEXTURED]


def _field(obj, name):
    return next(v for k, v in obj.extras if k == name)


def _error(scene, obj, word, message: str) -> SceneError:
    return SceneError(message, scene.path if scene.path != "<memory>" else None,
                      getattr(word, "line", None) or obj.line, getattr(word, "col", None))


def find(scene, obj, dirs=()) -> str:
    """The file of ``obj``'s texture: the first of ``dirs`` then the scene's directory that
    has it; a SceneError at the name (one line) when none has."""
    name = _field(obj, "texture")
    places = [os.fspath(d) for d in dirs]
    if scene.path != "<memory>":
        places.append(os.path.dirname(os.path.abspath(scene.path)))
    if os.path.isabs(name):
        places = [""]
    # each place's NAME; a --texture-dir also holding the file by its bare name, where the
    # scene names a folder (textures/tiles.ppm: a review's --texture-dir of that folder
    # was 'not found', its message naming the folder that held it)
    tried = [os.path.join(d, name) for d in places]
    base = os.path.basename(name)
    if base != name and not os.path.isabs(name):
        tried[len(dirs):len(dirs)] = [os.path.join(os.fspath(d), base) for d in dirs]
    tried = list(dict.fromkeys(tried))
    folder = None
    for p in tried:
        if os.path.isfile(p):
            return os.path.abspath(p)
        folder = folder or (p if os.path.isdir(p) else None)
    if folder:
        raise _error(scene, obj, name, f"texture '{name}' is a directory ({folder}), not a PPM "
                                       "file; give the image file's name")
    looked = ", ".join(tried)
    raise _error(scene, obj, name, f"texture '{name}' not found (looked for: {looked}); put it "
                                   "next to the scene or pass --texture-dir DIR")


def _tokens(data: bytes, count: int, pos: int):
    """The next ``count`` whitespace-separated header tokens (``#`` comments skipped) from
    ``pos``; returns (tokens, position just after the last one)."""
    out = []
    n = len(data)
    while len(out) < count:
        while pos < n and data[pos:pos + 1].isspace():
            pos += 1
        if pos < n and data[pos:pos + 1] == b"#":
            while pos < n and data[pos:pos + 1] not in (b"\n", b"\r"):
                pos += 1
            continue
        start = pos
        while pos < n and not data[pos:pos + 1].isspace() and data[pos:pos + 1] != b"#":
            pos += 1
        if start == pos:
            break
        out.append(data[start:pos])
    return out, pos


def read_ppm(path: str) -> np.ndarray:
    """The texels of a PPM file (P6 or P3, maxval 1..65535): (H, W, 3) float64 value /
    maxval, row 0 the file's first row.  ImageError (one line naming the file) otherwise."""
    return _read_ppm(path)[0]


def _read_ppm(path: str):
    """(texels, the file's bytes) of read_ppm: one read serves the texels and the hash."""
    try:
        check_input(path, "texture")
        with open(path, "rb") as f:
            data = f.read()
    except InputError as exc:
        raise ImageError(str(exc)) from None
    except OSError as exc:
        raise ImageError(f"{path}: cannot read the texture "
                         f"({(exc.strerror or str(exc)).lower()})") from None
    bad = lambda why: ImageError(f"{path}: not a readable PPM texture ({why}); expected a "
                                 "P6 or P3 PPM file with maxval 1..65535")
    magic = data[:2]
    if magic not in (b"P6", b"P3"):
        raise bad("the file does not start with P6 or P3" if data else "the file is empty")
    # (the format's separators, as the references' reader requires them: whitespace or a
    # comment after the magic number, and one whitespace byte, not a comment, after maxval)
    if not (data[2:3].isspace() or data[2:3] == b"#"):
        raise bad(f"no whitespace after {magic.decode()}")
    head, pos = _tokens(data, 3, 2)
    if len(head) < 3 or not all(t.isdigit() for t in head):
        raise bad("its header lacks the width, height and maxval")
    if not data[pos:pos + 1].isspace():
        raise bad("no whitespace byte after the maxval (a comment there is not allowed: the "
                  "pixels start after one whitespace byte)")
    w, h, maxval = (int(t) for t in head)
    if w < 1 or h < 1 or not 1 <= maxval <= 65535:
        raise bad(f"width {w}, height {h}, maxval {maxval}")
    n = w * h * 3
    if magic == b"P6":
        size = 1 if maxval < 256 else 2
        body = data[pos + 1:pos + 1 + n * size]        # one whitespace byte after maxval
        if len(body) < n * size:
            raise bad(f"{len(body)} bytes of pixels, {w}x{h} needs {n * size}: truncated")
        vals = np.frombuffer(body, np.uint8 if size == 1 else ">u2")
    else:
        toks = data[pos:].split()
        if len(toks) < n or not all(t.isdigit() for t in toks[:n]):
            raise bad(f"{w}x{h} needs {n} numbers after the header")
        vals = np.array([int(t) for t in toks[:n]], np.int64)
    if int(vals.max(initial=0)) > maxval:
        raise bad(f"a value above its maxval {maxval}")
    return (vals.astype(np.float64) / maxval).reshape(h, w, 3), data


def _mapping(scene, obj, word) -> dict:
    """Texture's mapping fields of one object, from the fields as written."""
    err = lambda msg: _error(scene, obj, word, msg)
    if obj.form == "texplane":
        mode = _field(obj, "tile mode")
        if mode == 1:
            return {"mode": "fit", "scale": tuple(float(c) for c in obj.size)}
        if mode == 2:                       # repeat every window size in world units
            return {"mode": "repeat", "scale": tuple(float(c) for c in scene.window)}
        raise err(f"texplane: tile mode {fmt((mode,))[1:-1]}; expected 1 (fit) or 2 (tile)")
    if obj.form == "fplanetex":
        size = tuple(float(c) for c in _field(obj, "texture size"))
        if not (size[0] > 0 and size[1] > 0):
            raise err(f"fplanetex: texture size {fmt(_field(obj, 'texture size'))} must be "
                      "positive")
        return {"mode": "repeat", "scale": size,
                "brightness": float(_field(obj, "brightness"))}
    if obj.form == "sphere_pixmap":
        f = [float(c) for c in _field(obj, "forward")]
        m = math.hypot(f[0], f[2])
        if not m > 0:
            raise err("sphere_pixmap: the forward vector has no x or z component; expected "
                      "a direction off the y axis")
        return {"mode": "sphere", "forward": (f[0] / m, 0.0, f[2] / m),
                "side": (-f[2] / m, 0.0, f[0] / m),
                "brightness": float(_field(obj, "brightness"))}
    return {"mode": "sphere"}                # texsphere: forward +z


def check_mappings(scene) -> None:
    """SceneError (one line) for the first textured object whose mapping fields are invalid
    (a tile mode other than 1 or 2, a texture size <= 0, a forward along y): the parser
    checks them as it reads the file, for every command, not only where textures are
    applied (the texture files themselves are looked for only then)."""
    for _, o in textured(scene):
        _mapping(scene, o, _field(o, "texture"))


def load(scene, obj, dirs=()) -> Texture:
    """``obj``'s texture, found and read."""
    word = _field(obj, "texture")
    mapping = _mapping(scene, obj, word)
    path = find(scene, obj, dirs)
    texels, data = _read_ppm(path)
    sha = hashlib.sha256(data).hexdigest()
    return Texture(str(word), path, sha, texels.shape[1], texels.shape[0], texels=texels,
                   **mapping)


def attach(scene, dirs=()):
    """The scene with every textured object's texture loaded (``obj.texture``); SceneError
    or ImageError (one line) for the first that cannot be found or read."""
    objs = list(scene.objects)
    for i, o in textured(scene):
        if o.texture is None:
            objs[i] = dataclasses.replace(o, texture=load(scene, o, dirs))
    return dataclasses.replace(scene, objects=tuple(objs)) if objs != list(scene.objects) \
        or any(a is not b for a, b in zip(objs, scene.objects)) else scene


def provenance_text(scene) -> str:
    """Which texture each textured object was shaded with (path, size, hash)."""
    return "; ".join(f"line {o.line} {o.form}: {o.texture.describe()}"
                     for _, o in textured(scene) if o.texture is not None)
