"""Both readers of a scene file read the same scene.

rt_core's parser (rt_core/parser.py) makes the scene the tracer traces, and the commands hand
that scene to the references too: the converter that makes Mitsuba's scene, the shading
oracle that excuses boundary pixels.  So that a bug in rt_core's parser or scene model cannot
pass a comparison with them, every command that compares reads the file a second time with
the references' own reader (mitsuba_ref/scenefile.py) and checks here that the two agree
exactly: the header, every light's and object's kind, form and line, every number of every
field (as the exact value of its decimal text), the recorded extras, flags and code table.

This module knows both scene models, so it belongs to neither: it is the harness's.
"""
from __future__ import annotations

from fractions import Fraction

from mitsuba_ref import scenefile
from rt_core.parser import parse_scene
from rt_core.scene import SceneError, exact

_GEN = "code 27 read as"        # rt_core's note of how it read code 27, not a field


def parse_agreed(path, code27: str = "auto"):
    """rt_core's scene of the file at ``path``, once the references' reader has read the
    same scene from it (SceneError, exit 2, where they differ)."""
    scene = parse_scene(path, code27=code27)
    agree(scene, path, code27)
    return scene


def agree(scene, path, code27: str = "auto") -> None:
    """SceneError naming the first field the two readers read differently."""
    try:
        ref = scenefile.read(path, code27)
    except ValueError as exc:
        raise _differ(path, None, f"the references' reader refuses the file ({exc})")
    pairs = [("window", _x(scene.window), _x(ref.window), None),
             ("viewpoint", _x(scene.viewpoint), _x(ref.viewpoint), None),
             ("dialect", scene.dialect, ref.dialect, None),
             ("header flags", tuple(scene.flags), tuple(ref.flags), None),
             ("code table", scene.table, ref.table, None),
             ("lights", len(scene.lights), len(ref.lights), None),
             ("objects", len(scene.objects), len(ref.objects), None)]
    for what, a, b, line in pairs:
        if a != b:
            raise _differ(path, line, f"{what}: {a!r} against {b!r}")
    for name, ours, theirs in (("light", scene.lights, ref.lights),
                               ("object", scene.objects, ref.objects)):
        for k, (o, r) in enumerate(zip(ours, theirs)):
            what = f"{name} {k + 1} ({o.kind}, line {o.line})"
            if (o.kind, o.line) != (r.kind, r.line):
                raise _differ(path, o.line, f"{what}: a {r.kind} on line {r.line} to the "
                                            "references")
            if name == "object" and o.form != r.form:
                raise _differ(path, o.line, f"{what}: form {o.form!r} against {r.form!r}")
            for field, _ in scenefile.LAYOUT[o.kind]:
                a, b = _x(_field(o, field)), _x(r.x[field])
                if a != b:
                    raise _differ(path, o.line, f"{what}: {field} {_show(a)} against "
                                                f"{_show(b)}")
            if name == "object":
                ex = tuple(e for e in o.extras if e[0] != _GEN)
                if _x(ex) != _x(tuple(r.extras)):
                    raise _differ(path, o.line, f"{what}: {ex!r} against {tuple(r.extras)!r}")


class ReadersDiffer(SceneError):
    """The two readers read one file differently: a defect of one of them, not of the
    file (``category`` 'disagree': validate counts it failed, not skipped)."""

    @property
    def category(self) -> str:
        return "disagree"


def _differ(path, line, what: str) -> SceneError:
    return ReadersDiffer(f"rt_core's parser and the references' own reader read this file "
                         f"differently ({what}); rtval cannot check a tracer against "
                         "references that read another scene: please report the file",
                         str(path), line)


def references_read(path, code27: str = "auto") -> bool:
    """Does the references' own reader read the file at ``path``?"""
    try:
        scenefile.read(path, code27)
    except (ValueError, OSError):
        return False
    return True


def _field(o, name: str):
    """Field ``name`` of scenefile.LAYOUT as rt_core's scene model holds it (as written)."""
    if name in ("ambient", "diffuse", "specular"):
        return getattr(o.material, name)
    if name.startswith("bg_"):
        return getattr(o.background, name[3:])
    if name == "radius":
        return (o.radius,)
    if name == "normal" and getattr(o, "given_normal", ()):
        return o.given_normal
    if name == "axis" and o.kind == "torus":
        return o.given_axis
    if name == "centerline":
        return o.given_axis
    if name == "radius_height":
        return (o.radius, o.height)
    if name in ("major", "minor", "theta"):
        return (getattr(o, name),)
    if name.startswith("point") and o.kind == "triangle":
        return o.points[int(name[-1]) - 1]
    return getattr(o, name)


def _x(v):
    """Exact values (Fractions; strings as they are) of a number or nested tuple."""
    if isinstance(v, str):
        return v
    if isinstance(v, (tuple, list)):
        return tuple(_x(c) for c in v)
    return v if isinstance(v, Fraction) else exact(v)


def _show(v) -> str:
    return "(" + ", ".join(_show(c) if isinstance(c, tuple) else str(c) for c in v) + ")" \
        if isinstance(v, tuple) else str(v)


def same_rows(scene, columns: int, rows, cam) -> None:
    """ReadersDiffer where rows were not given and rt_core's camera (``cam``) has another
    count than the references' own rule for the scene's window (mitsuba_ref.convert, the
    notes' int(h/w·columns)): both sides would otherwise be handed rt_core's (a review: its
    window's width and height swapped in that rule passed validate)."""
    from mitsuba_ref.convert import reference_rows
    if rows is not None:
        return
    own = reference_rows(scene, columns)
    if cam.rows != own:
        raise ReadersDiffer(f"rt_core's camera gives {columns} columns {cam.rows} rows where "
                            f"the references' own rule gives {own}: please report the file",
                            str(scene.path))
