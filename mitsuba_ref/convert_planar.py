"""Mitsuba equivalents of the planar kinds (mitsuba_ref/convert.py), from the numbers as
written (mitsuba_ref/oracle_planar.py's own normal and frame):

* disk -> Mitsuba's ``disk`` (the unit disk in z = 0, normal +z) with ``to_world`` columns
  r·x̂, r·ŷ, n̂, centre: the same disk, normal and frame (Mitsuba's own uv is polar; the
  course integrator's AOVs write rtval's, the frame coordinates, from x̂ and ŷ);
* triangle -> a one-triangle mesh P1 P2 P3 (Mitsuba's face normal is (P2 − P1) × (P3 − P1),
  the course's; texture coordinates (0, 0), (1, 0), (0, 1), so Mitsuba's uv is the
  barycentric uv rtval writes).  In the XML a PLY file beside it (``rtval convert`` writes
  ``<OUT>.obj<id>_triangle.ply``); for ``mi.load_dict`` the same PLY, loaded.
"""
from __future__ import annotations

import os
import tempfile

from .oracle_planar import disk_frame, points, triangle_normal

# convert.py takes the triangle's points and normal from here too
__all__ = ["disk_matrix", "disk_to_world", "triangle_spec", "ply_text", "realize", "ply_files",
           "points", "triangle_normal", "disk_frame"]



TEXCOORDS = (0.0, 0.0, 1.0, 0.0, 0.0, 1.0)


def disk_matrix(o) -> list:
    """4×4 ``to_world`` of the Mitsuba disk equal to the course disk."""
    x, y, n = disk_frame(o)
    r = float(o.radius)
    c = tuple(float(v) for v in o.center)
    return [[r * x[0], r * y[0], n[0], c[0]], [r * x[1], r * y[1], n[1], c[1]],
            [r * x[2], r * y[2], n[2], c[2]], [0.0, 0.0, 0.0, 1.0]]


def disk_to_world(o):
    """The disk's ``to_world`` as Mitsuba's XML reader makes it from the matrix we write
    (numbers read as float32, the transform and its inverse kept in double), so that the
    dict renders exactly as the XML: a float32 transform inverts in float32, which moves
    the disk's polar uv by an ulp."""
    import numpy as np
    from .convert import loaded             # (Mitsuba in the variant being built for)
    mi = loaded()
    m = np.array(disk_matrix(o), np.float32).astype(np.float64)
    return mi.ScalarTransform4d(m.tolist())


def triangle_spec(o) -> dict:
    """The triangle as a ``ply`` shape whose file is still to be written (``_points``)."""
    pts = [tuple(float(c) for c in p) for p in points(o)]
    return {"type": "ply", "face_normals": True, "_points": pts}


def ply_text(pts) -> str:
    """An ASCII PLY of one triangle with the barycentric texture coordinates."""
    head = ["ply", "format ascii 1.0", "element vertex 3", "property float x",
            "property float y", "property float z", "property float u", "property float v",
            "element face 1", "property list uchar int vertex_indices", "end_header"]
    rows = [f"{p[0]!r} {p[1]!r} {p[2]!r} {TEXCOORDS[2 * i]!r} {TEXCOORDS[2 * i + 1]!r}"
            for i, p in enumerate(pts)]
    return "\n".join(head + rows + ["3 0 1 2"]) + "\n"


def realize(d: dict, mi) -> dict:
    """``scene_dict``'s triangle specs as loaded Mitsuba shapes (id and BSDF kept), for
    ``mi.load_dict``: each loaded from its PLY text in a temporary directory (removed at
    once), so that the dict renders exactly as the XML with its PLY files does."""
    specs = [(k, v) for k, v in d.items() if isinstance(v, dict) and "_points" in v]
    if not specs:
        return d
    with tempfile.TemporaryDirectory(prefix="rtval-triangles-") as tmp:
        for key, v in specs:
            path = os.path.join(tmp, f"{v['id']}.ply")
            with open(path, "w") as f:
                f.write(ply_text(v["_points"]))
            spec = {k: x for k, x in v.items() if k not in ("_points", "id")}
            spec["filename"] = path
            shape = mi.load_dict(spec)
            shape.set_id(v["id"])
            d[key] = shape
    return d


def ply_files(d: dict, stem: str) -> dict:
    """For the XML: each triangle spec's file name (``<stem>.<id>.ply``) set in place;
    returns {file name: PLY text}."""
    out = {}
    for v in d.values():
        if isinstance(v, dict) and "_points" in v:
            name = f"{stem}.{v['id']}.ply"
            out[name] = ply_text(v.pop("_points"))
            v["filename"] = name
    return out
