"""Reference renders with Mitsuba 3 (llvm_ad_rgb, float32), in rt_core's channel names.

The course clips planes at the window (a plane hit with z > 0 is a miss) but not spheres.
Mitsuba clips whole rays, so the reference keeps two Mitsuba scenes: the plane kinds, traced
on the z <= 0 side of the window only, and the spheres, traced whole; each ray takes the
nearer hit of the two (an exact tie goes to the earlier object, as in the course).

* ``trace_rays``: the exact rays rt_core traces (directions rounded to float32): planes from
  the window plane z = 0 (viewpoint in front of it) or up to it (``maxt``, viewpoint behind);
  ``ray_intersect_preliminary`` (t, shape) and ``ray_intersect`` (normal, position, uv).
* ``render_camera``: the converted scene(s) through Mitsuba's own ``perspective`` sensor and
  the ``aov`` integrator (near/far clip = the screen clip); depth corrected for the near clip.
"""
from __future__ import annotations
from typing import Any as Scene         # a parsed course scene (duck-typed)

import numpy as np

from .convert import AOVS, course_id, mitsuba, scene_dict, sensor_setup
from .jitdata import jit_array, jit_vectors

CAMERA_AOVS = AOVS + ",id:shape_index"
GROUPS = (("planes", {"plane", "fplane", "tplane", "triangle", "disk"}, True),
          ("spheres", {"sphere", "cylinder"}, False))      # unclipped (clip_spheres: clipped)
CHANNELS = ("hit.mask", "depth.Z", "object.id", "normal.X", "normal.Y", "normal.Z",
            "position.X", "position.Y", "position.Z", "uv.U", "uv.V")


class Group:
    """One loaded Mitsuba scene (a subset of the objects) and its id maps and sensor."""

    def __init__(self, scene: Scene, columns, rows, sampling, kinds, clip: bool, aovs: str):
        mi = mitsuba()
        import drjit as dr
        d = scene_dict(scene, columns, rows, sampling, only=kinds, clip=clip,
                       from_viewpoint=True)
        d["integrator"] = {"type": "aov", "aovs": aovs}
        self.clip = clip
        self.mi_scene = mi.load_dict(d, optimize=False)
        shapes = self.mi_scene.shapes()
        self.ids = np.array([course_id(s.id()) for s in shapes], np.int32)
        # the aov 'shape_index' is the shape's registry id (global to the process), not its
        # index in shapes(): map registry id -> course id
        reg = np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes)).numpy())
        self.registry_to_course = dict(zip(reg.tolist(), self.ids.tolist()))
        self.setup = sensor_setup(scene, columns, rows, sampling, clip)


class MitsubaScene:
    """The course scene as Mitsuba scenes: clipped plane kinds, unclipped spheres."""

    def __init__(self, scene: Scene, columns: int, rows: int | None, sampling: str = "corners",
                 aovs: str = CAMERA_AOVS, clip_spheres: bool = False):
        self.scene = scene
        self.setup = sensor_setup(scene, columns, rows, sampling)
        present = {o.kind for o in scene.objects}
        self.groups = [Group(scene, columns, rows, sampling, kinds,
                             clip or clip_spheres, aovs)
                       for _, kinds, clip in GROUPS if kinds & present]
        # uv scale: Mitsuba's uv in [0,1]² -> the course's lasthit (u·w, v·h)
        self.uv_scale = np.zeros((len(scene.objects) + 1, 2))
        for i, obj in enumerate(scene.objects):
            if obj.kind == "fplane":
                self.uv_scale[i] = obj.size
            if obj.kind == "triangle":          # barycentric in both (convert_planar.py)
                self.uv_scale[i] = (1.0, 1.0)


def window_distance(viewpoint, d: np.ndarray):
    """Distance s along d from the viewpoint to the window plane z = 0 (float64, host);
    inf for rays that never reach it."""
    vz = viewpoint[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -vz / d[:, 2]
    return np.where((s > 0) & np.isfinite(s), s, np.inf)


def _numpy3(v):
    return np.stack([np.asarray(c.numpy(), np.float64) for c in (v.x, v.y, v.z)], 1)


def group_rays(g: Group, V, d32):
    """Mitsuba rays of one group for directions d32 from the viewpoint V: plane kinds on the
    z <= 0 side of the window only (from the window when V is in front of it, else ending
    there with maxt), spheres whole.  Returns (ray, s, valid): s is the distance from V to
    the ray's origin, valid is False for rays that never reach the window's far side."""
    mi = mitsuba()
    d64 = d32.astype(np.float64)
    n = len(d64)
    s = window_distance(V, d64)
    maxt = None
    if g.clip and V[2] > 0:
        # start on z = 0: rays that never get there are misses
        valid = np.isfinite(s)
        o = np.where(valid[:, None], V[None, :] + s[:, None] * d64, 0.0).astype(np.float32)
    else:
        valid = np.ones(n, bool)
        o = np.tile(V.astype(np.float32), (n, 1))
        if g.clip:                               # viewpoint behind the window: end on z = 0
            maxt = s.astype(np.float32)
        s = np.zeros(n)
    ray = mi.Ray3f(jit_vectors(mi.Point3f, o), jit_vectors(mi.Vector3f, d32))
    if maxt is not None:
        ray.maxt = jit_array(mi.Float, maxt)
    return ray, s, valid


def _trace_group(g: Group, V, d32, full: bool):
    """Flat channels of one group for rays from the viewpoint along d32."""
    import drjit as dr
    ray, s, valid = group_rays(g, V, d32)
    pi = g.mi_scene.ray_intersect_preliminary(ray)
    si = g.mi_scene.ray_intersect(ray) if full else None
    dr.eval(pi, si) if full else dr.eval(pi)
    hit = np.asarray(pi.is_valid().numpy()) & valid
    t = np.asarray(pi.t.numpy(), np.float64)
    hit &= np.isfinite(t)
    idx = np.minimum(np.asarray(pi.shape_index.numpy()), len(g.ids) - 1)
    out = {"hit.mask": hit, "depth.Z": np.where(hit, s + t, np.inf),
           "object.id": np.where(hit, g.ids[idx], -1)}
    if full:
        for name, v in (("normal", si.n), ("position", si.p)):
            a = _numpy3(v)
            for i, c in enumerate("XYZ"):
                out[f"{name}.{c}"] = a[:, i]
        out["uv.U"] = np.asarray(si.uv.x.numpy(), np.float64)
        out["uv.V"] = np.asarray(si.uv.y.numpy(), np.float64)
    return out


def _merge(ms: MitsubaScene, parts: list, shape) -> dict:
    """Nearest hit over the groups; misses: mask 0, depth 0, id -1, other channels 0."""
    best = parts[0]
    for p in parts[1:]:
        nearer = (p["depth.Z"] < best["depth.Z"]) | (
            (p["depth.Z"] == best["depth.Z"]) & (p["object.id"] >= 0) &
            ((best["object.id"] < 0) | (p["object.id"] < best["object.id"])))
        best = {k: np.where(nearer, p[k], best[k]) for k in best}
    hit = best["hit.mask"].astype(bool)
    out = {}
    for k in CHANNELS:
        if k not in best:
            continue
        v = best[k]
        if k == "object.id":
            v = np.where(hit, v, -1)
        elif k == "uv.U" or k == "uv.V":
            oid = np.where(hit, best["object.id"], -1).astype(np.int64)
            v = v * ms.uv_scale[oid, 0 if k == "uv.U" else 1]
        v = np.where(hit, v, 0.0) if k != "object.id" else v
        out[k] = v.astype(np.float32 if k in ("hit.mask", "object.id") else np.float64)\
            .reshape(shape)
    return out


def trace_rays(ms: MitsubaScene, d: np.ndarray, full: bool = True) -> dict:
    """Intersect rays from the viewpoint along ``d`` ((N, 3)) with the Mitsuba scene(s).

    Returns flat numpy arrays: 'hit.mask', 'depth.Z' (distance from the viewpoint),
    'object.id' and, with ``full``, normal/position/uv channels."""
    d32 = np.asarray(d, np.float32)
    V = np.asarray(ms.scene.viewpoint, np.float64)
    if not ms.groups:
        z = np.zeros(len(d32))
        return {"hit.mask": z, "depth.Z": z, "object.id": z - 1}
    return _merge(ms, [_trace_group(g, V, d32, full) for g in ms.groups], (len(d32),))


def _render_group(g: Group, V, cos):
    """One group through its own sensor: the aov channels, depth from the viewpoint."""
    mi = mitsuba()
    img = np.asarray(mi.render(g.mi_scene), np.float64)      # (rows, columns, 10)
    if g.setup.facing > 0:       # the sensor faces +z: its image is mirrored in x
        img = img[:, ::-1]
    dd = img[..., 0]
    hit = dd > 0
    # Mitsuba's shape registry ids -> course object ids, by one table lookup (unknown: -2)
    reg = np.rint(img[..., 9]).astype(np.int64)
    keys = np.fromiter(g.registry_to_course, np.int64, len(g.registry_to_course))
    vals = np.fromiter(g.registry_to_course.values(), np.int64, len(g.registry_to_course))
    size = int(max(keys.max(initial=0), reg.max(initial=0))) + 2
    table = np.full(size, -2, np.int64)
    table[keys[keys >= 0]] = vals[keys >= 0]
    ids = np.where(reg >= 0, table[np.clip(reg, 0, size - 1)], -2)
    out = {"hit.mask": hit, "depth.Z": np.where(hit, dd + g.setup.near_clip / cos, np.inf),
           "object.id": np.where(hit, ids, -1)}
    for i, c in enumerate("XYZ"):
        out[f"position.{c}"] = img[..., 1 + i]
        out[f"normal.{c}"] = img[..., 4 + i]
    out["uv.U"], out["uv.V"] = img[..., 7], img[..., 8]
    return out


def render_camera(ms: MitsubaScene, d: np.ndarray) -> dict:
    """Render through Mitsuba's own sensor(s); (rows, columns) arrays, rt_core names.

    The sensor starts rays on its near-clip plane, so the aov depth is |P − V| − s with
    s = near_clip/cos θ; we add s back.  The sensor's pixel centres are the course samples
    (convert.sensor_setup), so θ is the angle to the z axis of the course ray ``d`` ((N, 3),
    image order) of that pixel.  (Not from Mitsuba's hit position: its ``si.p`` is
    interpolated from the rectangle's vertices, off by about 2⁻²⁴·R on a large stand-in.)"""
    shape = (ms.setup.rows, ms.setup.columns)
    cos = np.abs(np.asarray(d, np.float64)[:, 2]).reshape(shape)
    if not ms.groups:
        z = np.zeros(shape)
        return {"hit.mask": z, "depth.Z": z, "object.id": z - 1}
    V = np.asarray(ms.scene.viewpoint, np.float64)
    return _merge(ms, [_render_group(g, V, cos) for g in ms.groups], shape)
