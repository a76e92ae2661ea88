"""Reference renders with Mitsuba 3 (llvm_ad_rgb, float32), in rt_core's channel names.

* ``trace_rays``: the exact rays rt_core traces (directions rounded to float32), started on
  the window plane z = 0 like the sensor's near clip, intersected with
  ``ray_intersect_preliminary`` (t, shape) and ``ray_intersect`` (normal, position, uv).
* ``render_camera``: the converted scene through Mitsuba's own ``perspective`` sensor and the
  ``aov`` integrator; depth corrected for the near clip.
"""
from __future__ import annotations

import numpy as np

from rt_core.scene import FPlane, Scene, TPlane
from .convert import (AOVS, course_id, mitsuba, scene_dict, sensor_setup)

CAMERA_AOVS = AOVS + ",id:shape_index"


class MitsubaScene:
    """A loaded Mitsuba scene plus the map from ``scene.shapes()`` index to course id."""

    def __init__(self, scene: Scene, columns: int, rows: int | None, sampling: str = "corners",
                 aovs: str = CAMERA_AOVS):
        mi = mitsuba()
        self.scene = scene
        d = scene_dict(scene, columns, rows, sampling)
        d["integrator"] = {"type": "aov", "aovs": aovs}
        self.mi_scene = mi.load_dict(d, optimize=False)
        shapes = self.mi_scene.shapes()
        self.ids = np.array([course_id(s.id()) for s in shapes], np.int32)
        # the aov 'shape_index' is the shape's registry id (global to the process), not its
        # index in shapes(): map registry id -> course id
        import drjit as dr
        reg = np.asarray(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes)).numpy()) \
            if shapes else np.zeros(0, np.uint32)
        self.registry_to_course = dict(zip(reg.tolist(), self.ids.tolist()))
        self.setup = sensor_setup(scene, columns, rows, sampling)


def window_origins(viewpoint, d: np.ndarray):
    """Ray start on the window plane z = 0: s = vz/(−d.z) along d (float64 on the host).
    Rays that never reach the window (d.z >= 0) get s = nan (a miss)."""
    vz = viewpoint[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(d[:, 2] < 0, vz / -d[:, 2], np.nan)
    o = np.asarray(viewpoint, np.float64)[None, :] + s[:, None] * d
    return o, s


def trace_rays(ms: MitsubaScene, d: np.ndarray, full: bool = True, from_window: bool = True):
    """Intersect rays from the viewpoint along ``d`` ((N, 3) array) with the Mitsuba scene.

    Returns flat numpy arrays: 'hit.mask', 'depth.Z' (distance from the viewpoint),
    'object.id' and, with ``full``, normal/position/uv channels."""
    mi = mitsuba()
    import drjit as dr
    d32 = np.asarray(d, np.float32)
    d64 = d32.astype(np.float64)
    V = ms.scene.viewpoint
    if from_window:
        o, s = window_origins(V, d64)
    else:
        o, s = np.tile(np.asarray(V, np.float64), (len(d64), 1)), np.zeros(len(d64))
    valid = np.isfinite(s)
    o = np.where(valid[:, None], o, 0.0).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(*(o[:, i] for i in range(3))),
                   mi.Vector3f(*(d32[:, i] for i in range(3))))
    sc = ms.mi_scene
    if full:
        si = sc.ray_intersect(ray)
        hit_v, t_v = si.is_valid(), si.t
        pi = sc.ray_intersect_preliminary(ray)
        idx_v = pi.shape_index
        dr.eval(si, pi)
        hit = np.array(hit_v.numpy()) & valid
    else:
        pi = sc.ray_intersect_preliminary(ray)
        dr.eval(pi)
        hit = np.array(pi.is_valid().numpy()) & valid
        t_v, idx_v = pi.t, pi.shape_index
    t = np.asarray(t_v.numpy(), np.float64)
    idx = np.asarray(idx_v.numpy())
    hit &= np.isfinite(t)
    out = {"hit.mask": hit.astype(np.float32),
           "depth.Z": np.where(hit, s + t, 0.0),
           "object.id": np.where(hit, ms.ids[np.minimum(idx, len(ms.ids) - 1)] if len(ms.ids)
                                 else -1, -1).astype(np.float32)}
    if full:
        for name, v in (("normal", si.n), ("position", si.p)):
            a = np.stack([np.asarray(c.numpy()) for c in (v.x, v.y, v.z)], 1)
            for i, c in enumerate("XYZ"):
                out[f"{name}.{c}"] = np.where(hit, a[:, i], 0.0)
        uv = np.stack([np.asarray(si.uv.x.numpy()), np.asarray(si.uv.y.numpy())], 1)
        # Mitsuba uv in [0,1]² -> the course's lasthit (u·w, v·h) for finite planes
        scale = np.zeros((max(len(ms.scene.objects), 1), 2))
        for i, obj in enumerate(ms.scene.objects):
            if isinstance(obj, FPlane):
                scale[i] = obj.size
        oid = out["object.id"].astype(np.int64)
        sc_uv = scale[np.maximum(oid, 0)]
        out["uv.U"] = np.where(hit, uv[:, 0] * sc_uv[:, 0], 0.0)
        out["uv.V"] = np.where(hit, uv[:, 1] * sc_uv[:, 1], 0.0)
    return out


def render_camera(ms: MitsubaScene):
    """Render through Mitsuba's own sensor; returns (rows, columns) arrays, rt_core names.

    The sensor starts rays on the near-clip plane z = 0, so the aov depth is |P − V| − s
    with s = near_clip/cos θ; we add s back, θ being the pixel ray's angle to −z."""
    mi = mitsuba()
    img = np.asarray(mi.render(ms.mi_scene), np.float64)      # (rows, columns, 10)
    dd, pos, nrm, uv, sidx = (img[..., 0], img[..., 1:4], img[..., 4:7], img[..., 7:9],
                              img[..., 9])
    s = ms.setup
    V = np.asarray(ms.scene.viewpoint)
    hit = dd > 0
    # pixel-centre ray of the sensor: window point in z = 0 (course corner grid, square pixels)
    rows, cols = dd.shape
    spacing = (V[2] * 2 * np.tan(np.radians(s.fov) / 2)) / cols
    x = np.arange(cols)[None, :]
    y = (rows - 1 - np.arange(rows))[:, None]
    wx = (x + 0.5) * spacing - cols * spacing / 2 + (-s.ppo_x * cols * spacing)
    wy = (y + 0.5) * spacing - rows * spacing / 2 + (s.ppo_y * rows * spacing)
    cos = V[2] / np.sqrt((wx - V[0]) ** 2 + (wy - V[1]) ** 2 + V[2] ** 2)
    depth = np.where(hit, dd + V[2] / cos, 0.0)
    lookup = np.vectorize(lambda r: ms.registry_to_course.get(int(r), -2), otypes=[np.int64])
    oid = np.where(hit, lookup(np.rint(sidx)), -1)
    out = {"hit.mask": hit.astype(np.float32), "depth.Z": depth,
           "object.id": oid.astype(np.float32)}
    for i, c in enumerate("XYZ"):
        out[f"normal.{c}"] = np.where(hit, nrm[..., i], 0.0)
        out[f"position.{c}"] = np.where(hit, pos[..., i], 0.0)
    scale = np.zeros((max(len(ms.scene.objects), 1), 2))
    for i, obj in enumerate(ms.scene.objects):
        if isinstance(obj, FPlane):
            scale[i] = obj.size
    sc_uv = scale[np.maximum(oid, 0)]
    out["uv.U"] = np.where(hit, uv[..., 0] * sc_uv[..., 0], 0.0)
    out["uv.V"] = np.where(hit, uv[..., 1] * sc_uv[..., 1], 0.0)
    return out
