"""The course's shading as a Mitsuba 3 integrator plugin (``course``), and the material plugin
(``course_material``) that carries each shape's course MAT into it.

Registered by ``mitsuba_ref.convert.mitsuba()`` (every use of Mitsuba in mitsuba_ref goes
through it), so a converted XML loads with ``mi.load_file`` once mitsuba_ref has loaded
Mitsuba.  The shading is the notes' recursion (shared/notes/course-format.md, "Shading"),
written here with Mitsuba's own queries and nothing from rt_core:

    I  = ambient(O) + Σ_lights [c > 0, unshadowed] diffuse(O) ⊙ E · c / d     (1/d)
    I /= total_dist                                   (or this segment's t: reflect="segment")
    I += specular(O) ⊙ trace(H, reflect(dir, N))      while total_dist < max_dist

* **Closest hit** (``_closest``): ``scene.ray_intersect``; a hit the course does not count is
  stepped over and the ray goes on from it (``si.spawn_ray``): plane kinds with the hit in
  front of the window (z > 0, or z >= 0 with screen_clip=">=") or t <= t_min, and spheres
  and cylinders only with clip_spheres.  One scene: spheres and planes clip differently
  inside it.  A reflection ray steps over the object it leaves, as the course skips it (a
  cylinder's inside wall reflects back into the cylinder).
* **Shadows**: one ray per light toward it, the course's line from the hit point (its search
  starts a little along the ray, ``_along``, and steps over the object it leaves, as the
  course skips it), blocked by the first counted hit.
* **Hit points and normals**: Mitsuba decides which surface a ray meets; where on it comes
  from the course geometry its material carries (``_point``): a plane's equation, a
  sphere's centre and radius, a cylinder's base centre, unit axis and radius (the root
  nearer Mitsuba's own t: Mitsuba decides near or far wall, and the axial range).  A
  plane kind's normal is as given in the file (never flipped), a sphere's and a cylinder's
  the outward one (the gradient: on a cylinder's inside wall too, as the course).  A tiled plane picks its MAT by the parity of
  floor(u/w) + floor(v/h), with u, v from its point and frame.
* **Camera**: one ray per pixel from the viewpoint through the course's sample (corner grid
  or centres), built here from the integrator's parameters: the course image itself, also
  for sample grids Mitsuba's square pixels cannot make.  ``sample`` serves Mitsuba's own
  render loop (square grids): it takes the sensor's ray direction from the viewpoint.

What Mitsuba decides its own way (the harness classifies these pixels ``boundary``): the
finite-plane edges (closed), exact ties, float32 arithmetic, and infinite planes as
rectangles of half-size 64 × the scene's scale (``convert.plane_extent``).
"""
from __future__ import annotations

import math

from .oracle import OFF       # the notes' tile-parity offset

MATERIAL_FIELDS = ("ambient", "diffuse", "specular")
# the channels of the integrator's AOV mode, rtval render's names and order (rt_core's
# GEOMETRY_CHANNELS, written out here: the reference does not import the tracer's renderer)
GEOMETRY = ("hit.mask", "depth.Z", "object.id", "normal.X", "normal.Y", "normal.Z",
            "position.X", "position.Y", "position.Z", "uv.U", "uv.V")
# a tiled plane's second MAT (the course's background: even parity)
BACKGROUND_FIELDS = tuple("background_" + k for k in MATERIAL_FIELDS)
MAX_BOUNCES = 10_000
# hits stepped over per query at most (clipped planes in front of the window, t <= t_min)
MAX_SKIPS = 64

_REGISTERED = set()


_CLASSES: dict = {}


def register(mi) -> None:
    """Register ``course`` and ``course_material`` with Mitsuba (once per variant)."""
    if mi.variant() in _REGISTERED:
        return
    _REGISTERED.add(mi.variant())
    material, integrator = classes(mi)
    mi.register_bsdf("course_material", lambda props: material(props))
    mi.register_integrator("course", lambda props: integrator(props))


def classes(mi) -> tuple:
    """(CourseMaterial, CourseIntegrator) of Mitsuba's current variant (made once)."""
    if mi.variant() not in _CLASSES:
        _CLASSES[mi.variant()] = _classes(mi)
    return _CLASSES[mi.variant()]


def _classes(mi):
    import drjit as dr

    class CourseMaterial(mi.BSDF):
        """A course MAT (ambient, diffuse, specular: RGB, unbounded) and what the integrator
        needs of the shape: ``kind`` ("sphere", "cylinder", "plane", "fplane", "tplane",
        "disk", "triangle"), its ``course_id``, a sphere's centre and radius, a cylinder's
        base centre (``center``), unit ``axis`` and radius, a plane kind's normal as given (unit)
        and point, a finite or tiled plane's frame (and size, or tile size and background
        MAT).  The integrator reads these values once per render into tables by course id
        (``_tables``) and, per hit, only ``eval_attribute_1("course_id")``; other code can
        read any of them with ``eval_attribute_3``/``_1``.  It scatters nothing."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            vec = lambda k: mi.Color3f(props.get(k, mi.ScalarColor3f(0.0)))
            self.vals = {k: vec(k) for k in MATERIAL_FIELDS + BACKGROUND_FIELDS +
                         ("normal", "point", "xdir", "ydir", "tile_size", "size", "center",
                          "axis")}
            # opaque: scene numbers are kernel data, so the next scene reuses the kernels
            dr.make_opaque(*self.vals.values())
            kind = props.get("kind", "sphere")
            self.kind = kind
            # a textured object: its ambient is brightness × its ``texture`` (a Mitsuba
            # bitmap, nearest texel, whose to_uv maps the shape's uv to the course's s, t)
            self.texture = props.get("texture", None) if "texture" in props \
                else None
            self.brightness = float(props.get("brightness", 1.0))
            # clipped: a plane kind (the screen clip always, t_min); spheres and cylinders
            # are clipped only with clip_spheres
            self.ones = {"clipped": float(kind not in ("sphere", "cylinder")),
                         "cylinder": float(kind == "cylinder"),
                         "tiled": float(kind == "tplane"), "finite": float(kind == "fplane"),
                         # uv: the frame coordinates (a triangle's: its barycentric pair)
                         "framed": float(kind in ("fplane", "tplane", "triangle", "disk")),
                         "radius": float(props.get("radius", 0.0)),
                         "course_id": float(props.get("course_id", -1))}
            self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [self.m_flags]

        def sample(self, ctx, si, s1, s2, active=True):
            # (no sample: zeros, not an uninitialised one, which Mitsuba's own integrators
            # rejected: "callable 0 returned an empty/uninitialized Dr.Jit array", a review)
            return dr.zeros(mi.BSDFSample3f), mi.Color3f(0.0)

        def eval(self, ctx, si, wo, active=True):
            return mi.Color3f(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Color3f(0.0), mi.Float(0.0)

        def has_attribute(self, name, active=True):
            return name in self.vals or name in self.ones

        def eval_attribute_3(self, name, si, active=True):
            return self.vals[name]

        def eval_attribute_1(self, name, si, active=True):
            return dr.opaque(mi.Float, self.ones[name])

        def eval_diffuse_reflectance(self, si, active=True):
            return self.vals["diffuse"]

        def traverse(self, cb):
            pass

        def to_string(self):
            return f"CourseMaterial[kind={self.kind}]"

    class CourseIntegrator(mi.SamplingIntegrator):
        """The course's shading (module docstring).  Parameters: the camera (``viewpoint``,
        ``window_width``, ``window_height``, ``columns``, ``rows``, ``sampling``
        "corners"/"centres", ``row_shift``), the rules (``screen_clip`` ">"/">="/"off",
        ``t_min``, ``clip_spheres``, ``reflect`` "total"/"segment", ``tile_add_first``) and
        ``max_dist`` (the notes' MAX_DIST), ``max_bounces``."""

        def __init__(self, props):
            mi.SamplingIntegrator.__init__(self, props)
            v = props.get("viewpoint", mi.ScalarPoint3f(0.0, 0.0, 1.0))
            self.viewpoint = (float(v[0]), float(v[1]), float(v[2]))
            self.window = (float(props.get("window_width", 1.0)),
                           float(props.get("window_height", 1.0)))
            self.columns = int(props.get("columns", 0))
            self.rows = int(props.get("rows", 0))
            self.sampling = props.get("sampling", "corners")
            self.row_shift = int(props.get("row_shift", 0))
            self.screen_clip = props.get("screen_clip", ">")
            self.t_min = float(props.get("t_min", 0.0))
            self.clip_spheres = bool(props.get("clip_spheres", False))
            self.reflect = props.get("reflect", "total")
            self.tile_add_first = bool(props.get("tile_add_first", False))
            self.max_dist = float(props.get("max_dist", 1000.0))
            self.max_bounces = int(props.get("max_bounces", MAX_BOUNCES))
            # aovs: render the primary rays' geometry channels (GEOMETRY) instead of the image
            self.aovs = bool(props.get("aovs", False))
            if self.screen_clip not in (">", ">=", "off"):
                raise ValueError(f"course integrator: screen_clip must be '>', '>=' or 'off', "
                                 f"not {self.screen_clip!r}")
            if self.sampling == "centers":      # (rtval's own spelling: --sampling centers)
                self.sampling = "centres"
            if self.sampling not in ("corners", "centres"):
                raise ValueError(f"course integrator: sampling must be 'corners' or 'centres', "
                                 f"not {self.sampling!r}")
            self.stats = {}

        # --- Mitsuba's interfaces ------------------------------------------------------------

        def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
            """The course image: (rows, columns, 3) unclamped intensities, row 0 the top."""
            W, H = self.columns, self.rows
            if W < 1 or H < 1:
                film = (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).film()
                W, H = film.crop_size()
            o, d = self.camera_rays(W, H)
            if not scene.shapes():
                # nothing to hit (every kind left out, or none): black, a miss everywhere
                # (its material tables would be empty); rt_core draws the same
                z = dr.zeros(mi.Float, W * H)
                chans = [z] * 3 if not self.aovs else \
                    [z, z, z - 1.0] + [z] * (len(GEOMETRY) - 3)
            else:
                chans = self.geometry(scene, o, d) if self.aovs else \
                    list(self.shade(scene, o, d))
            out = dr.zeros(mi.TensorXf, (H, W, len(chans)))
            idx = dr.arange(mi.UInt32, W * H)
            for c, v in enumerate(chans):
                dr.scatter(out.array, v, idx * len(chans) + c)
            # evaluated here whatever ``evaluate`` says (mi.render passes False): the kernel
            # reads the scene's shapes, and mi.render(mi.load_file(...)) frees the scene on
            # return (a review: the image, evaluated afterwards, crashed the process)
            dr.eval(out)
            return out

        def geometry(self, scene, o, d):
            """The primary rays' channels in GEOMETRY's order and rtval's conventions:
            depth = distance from the viewpoint, a plane's normal as given or the sphere's or
            cylinder's outward one, the world position, a finite or tiled plane's lasthit as uv (a
            finite plane's kept in [0, w] × [0, h]), a triangle's barycentric pair, a disk's
            frame coordinates; zeros and id −1 on a miss."""
            n = dr.width(d)
            o = mi.Point3f(o) + dr.zeros(mi.Vector3f, n)
            self.tab = self._tables(scene)
            si, t, p, hit = self._closest(scene, o, d, dr.full(mi.Bool, True, n))
            idx = self._ids(si, hit)
            att = one = lambda k: self._get(k, idx, hit)
            planar = one("clipped") > 0.5
            N = self._normal(att, p)
            rel = p - mi.Point3f(att("point"))
            lasthit = planar & (one("framed") > 0.5)
            u = dr.select(lasthit, dr.dot(rel, att("xdir")), 0.0)
            v = dr.select(lasthit, dr.dot(rel, att("ydir")), 0.0)
            size = att("size")
            finite = one("finite") > 0.5
            u = dr.select(finite, dr.clip(u, 0.0, size.x), u)
            v = dr.select(finite, dr.clip(v, 0.0, size.y), v)
            z = lambda x: dr.select(hit, x, 0.0)
            return [dr.select(hit, 1.0, 0.0), z(t), dr.select(hit, one("course_id"), -1.0),
                    z(N.x), z(N.y), z(N.z), z(p.x), z(p.y), z(p.z), z(u), z(v)]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            """Mitsuba's render loop: the sensor's ray direction, from the viewpoint (the
            sensor moves its origin to the near clip)."""
            o = mi.Point3f(*(dr.opaque(mi.Float, c) for c in self.viewpoint))
            rgb = self.shade(scene, o, dr.normalize(mi.Vector3f(ray.d)), active)
            return mi.Spectrum(rgb), mi.Bool(active), []

        def aov_names(self):
            return []

        def to_string(self):
            return (f"CourseIntegrator[{self.columns}x{self.rows}, {self.sampling}, "
                    f"screen_clip={self.screen_clip}, max_dist={self.max_dist}]")

        # --- the camera ----------------------------------------------------------------------

        def camera_rays(self, W: int, H: int):
            """(origin, unit directions) of the course's samples, image order (row 0 the
            top): the window point x/(W−1)·ww − ww/2 (corners) or (2x+1)/(2W)·ww − ww/2
            (centres), in float64 on the host, one rounding to float32."""
            import numpy as np
            from .jitdata import jit_array
            ww, wh = self.window
            vx, vy, vz = self.viewpoint
            x = np.arange(W, dtype=np.float64)
            y = (H - 1 - np.arange(H, dtype=np.float64)) + self.row_shift
            if self.sampling == "corners":
                wx = x / (W - 1) * ww - ww / 2 if W > 1 else np.zeros(1) - ww / 2
                wy = y / (H - 1) * wh - wh / 2 if H > 1 else np.zeros(1) - wh / 2
            else:
                wx = (2 * x + 1) / (2 * W) * ww - ww / 2
                wy = (2 * y + 1) / (2 * H) * wh - wh / 2
            dx = np.tile(wx - vx, H)
            dy = np.repeat(wy - vy, W)
            dz = np.full(W * H, -vz)
            n = np.sqrt(dx * dx + dy * dy + dz * dz)
            d = mi.Vector3f(*(jit_array(mi.Float, c / n) for c in (dx, dy, dz)))
            return mi.Point3f(*(dr.opaque(mi.Float, c) for c in self.viewpoint)), d

        # --- the shapes' materials as tables ---------------------------------------------------

        def _tables(self, scene):
            """Every shape's course_material values as arrays by course id (read once per
            render from the scene's own BSDFs): a hit then costs one call through the BSDF
            pointer (its course id) and gathers, not one call per value."""
            mats = {}
            for sh in scene.shapes():
                b = sh.bsdf()
                cid = int(b.ones["course_id"]) if hasattr(b, "ones") else -1
                if cid < 0 or cid in mats:
                    raise ValueError(f"shape {sh.id()!r} has no course_material BSDF with its "
                                     "own course_id; convert the course scene again with "
                                     "rtval convert --shading")
                mats[cid] = b
            n = max(mats, default=-1) + 1
            first = next(iter(mats.values()), None)
            tab = {}
            for k in (first.vals if first else {}):
                cols = [[float(mats[i].vals[k][c][0]) if i in mats else 0.0 for i in range(n)]
                        for c in range(3)]
                tab[k] = mi.Vector3f(*(mi.Float(col) for col in cols))
            for k in (first.ones if first else {}):
                tab[k] = mi.Float([float(mats[i].ones[k]) if i in mats else 0.0
                                   for i in range(n)])
            dr.make_opaque(*tab.values())
            self.textured = [(i, b) for i, b in sorted(mats.items())
                             if getattr(b, "texture", None) is not None]
            return tab

        def _ids(self, si, hit):
            """The course id of each hit (one call through the BSDF pointer); 0 on a miss."""
            cid = si.bsdf().eval_attribute_1("course_id", si, hit)
            return mi.UInt32(dr.select(hit, cid, 0.0))

        def _get(self, name, idx, hit):
            return dr.gather(type(self.tab[name]), self.tab[name], idx, hit)

        # --- the course's hit rule -----------------------------------------------------------

        def _normal(self, att, p):
            """The course normal at hit points p (att: the hits' material values): a plane
            kind's as given; a sphere's or cylinder's the outward one, the part of p − centre
            across the axis (a sphere's axis is 0), on a cylinder's inside wall too."""
            w = p - mi.Point3f(att("center"))
            a = att("axis")
            return dr.select(att("clipped") > 0.5, att("normal"),
                             dr.normalize(w - dr.dot(w, a) * a))

        def _cylinder_t(self, get, o, d, t_mitsuba):
            """t of a cylinder hit from its base centre c, unit axis â and radius r, the
            root nearer Mitsuba's ``t_mitsuba`` (Mitsuba decides the wall and the axial
            range).  Across the axis (q = c − o, x⊥ = x − (x·â)â): A t² − 2B t + C = 0 with
            A = |d⊥|², B = d⊥·q⊥, C = (|q⊥| − r)(|q⊥| + r), and the discriminant without
            cancellation, B² − AC = (r√A − |d⊥×q⊥|)(r√A + |d⊥×q⊥|); roots C/q' and q'/A,
            q' = B + sign(B)·√disc (Mitsuba's float32 roots in its own frame cancel near the
            outline)."""
            a = get("axis")
            q = get("center") - mi.Vector3f(o)
            qp, dp = q - dr.dot(q, a) * a, d - dr.dot(d, a) * a
            r = get("radius")
            A, B = dr.dot(dp, dp), dr.dot(dp, qp)
            ra, cn, qn = r * dr.sqrt(A), dr.norm(dr.cross(dp, qp)), dr.norm(qp)
            qq = B + dr.mulsign(dr.sqrt(dr.maximum((ra - cn) * (ra + cn), 0)), B)
            r1, r2 = ((qn - r) * (qn + r)) / qq, qq / A
            t = dr.select(dr.abs(r1 - t_mitsuba) <= dr.abs(r2 - t_mitsuba), r1, r2)
            return dr.select(dr.isfinite(t) & (t > 0), t, t_mitsuba)

        def _point(self, si, o, d):
            """(t, hit point, is a plane kind, course id) of a hit: for plane kinds from the
            plane's equation, t = n·(P − o)/(n·d) with the material's point and normal, rather
            than Mitsuba's point on the rectangle, which for the large stand-in of an infinite
            plane is off by ~2⁻²⁴ of its half-size (R = 64 × the scene's scale): Mitsuba
            decides which surface the ray meets, the plane equation where on it; a sphere's
            and a cylinder's t likewise from their centre, (axis) and radius."""
            valid = si.is_valid()
            idx = self._ids(si, valid)
            get = lambda k: self._get(k, idx, valid)
            planar = get("clipped") > 0.5
            N = get("normal")
            P = mi.Point3f(get("point"))
            t_plane = dr.dot(N, P - o) / dr.dot(N, d)
            # a sphere: the root from its centre and radius in a form that does not cancel
            # (Mitsuba's float32 root loses ~√u of the radius near the outline):
            # disc = (r − |q×d|)(r + |q×d|), near root c/(q·d + √disc), c = (|q|−r)(|q|+r),
            # far root q·d + √disc when the origin is inside (c <= 0)
            q = get("center") - mi.Vector3f(o)
            r = get("radius")
            b, cn, qn = dr.dot(q, d), dr.norm(dr.cross(q, d)), dr.norm(q)
            sd = dr.sqrt(dr.maximum((r - cn) * (r + cn), 0))
            c = (qn - r) * (qn + r)
            t_mitsuba = dr.dot(si.p - o, d)
            t_sphere = dr.select(c > 0, c / (b + sd), b + sd)
            t_sphere = dr.select(dr.isfinite(t_sphere) & (t_sphere > 0), t_sphere, t_mitsuba)
            t_cyl = self._cylinder_t(get, o, d, t_mitsuba)
            t = dr.select(planar, t_plane, dr.select(get("cylinder") > 0.5, t_cyl, t_sphere))
            return t, dr.fma(d, t, o), planar, idx

        def _counts(self, t, p, planar):
            """Does the course count this hit (the screen clip, t > t_min for plane kinds)?"""
            ok = mi.Bool(True)
            if self.screen_clip != "off":
                front = (p.z > 0) if self.screen_clip == ">" else (p.z >= 0)
                ok &= ~(front & (planar | self.clip_spheres))
            if self.t_min > 0:
                ok &= ~(planar & (t <= dr.opaque(mi.Float, self.t_min)))
            return ok

        def _closest(self, scene, o, d, active, maxt=None, start=None, leave=None):
            """The closest counted hit along o + t·d (t < maxt): (si, t, p, hit).  A hit not
            counted is stepped over: the search goes on from a little beyond it along the
            same line (``_along``; never from Mitsuba's ``spawn_ray``, which moves the line
            off the surface); t is measured from o.  ``start``: where the search begins (a
            point of the line a little beyond o), default o; ``leave``: the course id of the
            object the ray leaves (stepped over, as the course skips it), default none."""
            start = o if start is None else start
            ray = mi.Ray3f(start, d)
            if maxt is not None:
                # (measured from o, as t is; Ray3f's third argument is the time)
                ray.maxt = maxt - dr.dot(start - o, d)
            si = scene.ray_intersect(ray, active)
            hit = active & si.is_valid()
            t, p, planar, idx = self._point(si, o, d)
            for _ in range(MAX_SKIPS):
                skip = hit & ~self._counts(t, p, planar)
                if leave is not None:
                    skip |= hit & (idx == leave)
                if not dr.any(skip):
                    break
                # on from the skipped hit, never back behind where this search started
                reach = dr.maximum(t, dr.dot(ray.o - o, d))
                on = _along(mi.Point3f(dr.fma(d, reach, o)), d)
                nxt = mi.Ray3f(dr.select(skip, on, ray.o), d)
                if maxt is not None:
                    nxt.maxt = maxt - dr.dot(nxt.o - o, d)
                ray = nxt
                si2 = scene.ray_intersect(nxt, skip)
                si = dr.select(skip, si2, si)
                hit = dr.select(skip, si2.is_valid(), hit)
                t, p, planar, idx = self._point(si, o, d)
            return si, t, p, hit

        # --- the shading ---------------------------------------------------------------------

        def _lights(self, scene):
            """(position, emissivity, spot) of each emitter: spot = (unit axis, cos θ)."""
            out = []
            for e in scene.emitters():
                p = mi.traverse(e)
                if "intensity.value" not in p or not ("position" in p or
                                                      "cutoff_angle" in p):
                    raise ValueError(f"course integrator: the emitter {str(e).split('[')[0]} "
                                     "is not a course light: give 'point' or 'spot' emitters")
                # (opaque: scene numbers are kernel data, so other scenes reuse the kernels)
                E = mi.Color3f(p["intensity.value"])
                if "position" in p:
                    pos = mi.Point3f(p["position"])
                    dr.make_opaque(pos, E)
                    out.append((pos, E, None))
                    continue
                m = p["to_world"].matrix
                pos = mi.Point3f(m[0, 3], m[1, 3], m[2, 3])
                axis = dr.normalize(mi.Vector3f(m[0, 2], m[1, 2], m[2, 2]))
                cos_t = mi.Float(math.cos(math.radians(float(p["cutoff_angle"][0]))))
                dr.make_opaque(pos, E, axis, cos_t)
                out.append((pos, E, (axis, cos_t)))
            return out

        def blocked(self, scene, p, L, ld, leave, cast):
            """Is a counted hit on the shadow ray p + t·L, 0 < t < ld·(1 − ShadowEpsilon),
            other than on the object ``leave`` it leaves?  (The course's test is t < ld, the
            light's distance.  The ray ends ShadowEpsilon, 8.9e-4 of ld, short of the light,
            as spawn_ray_to's does: a blocker exactly at the light, a light lying in a plane
            as in nw__modelTwoup, is a tie the course's t < d leaves unblocked, which
            float32 would decide at random; a blocker that near the light is missed.)"""
            short = ld * dr.opaque(mi.Float, 1 - mi.math.ShadowEpsilon)
            return self._closest(scene, p, L, cast, short, _along(p, L), leave)[3]

        def light_term(self, dif, E, c, ld):
            """One light's diffuse term: diffuse ⊙ E · c / d (1/d, not 1/d²)."""
            return dif * E * (c / ld)

        def reflected(self, d, N):
            """reflect(dir, N) = dir − 2(dir·N)N, normalised."""
            return dr.normalize(d - 2 * dr.dot(d, N) * N)

        def _material(self, si, p, hit):
            """(ambient, diffuse, specular, normal) at the hits (p: the hit points)."""
            idx = self._ids(si, hit)
            att = lambda k: self._get(k, idx, hit)
            amb, dif, spec = (mi.Color3f(att(k)) for k in MATERIAL_FIELDS)
            N = self._normal(att, p)
            tiled = att("tiled") > 0.5
            if dr.any(tiled & hit):
                rel = p - mi.Point3f(att("point"))
                size = att("tile_size")
                u = dr.dot(rel, att("xdir"))
                v = dr.dot(rel, att("ydir"))
                if self.tile_add_first:         # (size.z: OFF, over |p| unprojected)
                    u, v = u + size.z, v + OFF
                odd = (_odd(dr.floor(u / size.x)) + _odd(dr.floor(v / size.y))) == 1
                back = tiled & ~odd
                bg = [mi.Color3f(att(k)) for k in BACKGROUND_FIELDS]
                amb, dif, spec = (dr.select(back, b, f) for b, f in zip(bg, (amb, dif, spec)))
            for cid, b in self.textured:
                # the texture at Mitsuba's own uv of the hit (shape uv -> to_uv -> texel)
                on = hit & (idx == cid)
                if dr.any(on):
                    texel = mi.Color3f(b.texture.eval(si, on))
                    amb = dr.select(on, dr.opaque(mi.Float, b.brightness) * texel, amb)
            return amb, dif, spec, N

        def shade(self, scene, o, d, active=True):
            """Unclamped course intensity of the rays o + t·d (o: the viewpoint)."""
            n = dr.width(d)
            self.tab = self._tables(scene)
            lights = self._lights(scene)
            image = dr.zeros(mi.Color3f, n)
            weight = mi.Color3f(1.0)
            total = dr.zeros(mi.Float, n)
            live = mi.Bool(active) & dr.full(mi.Bool, True, n)
            o = mi.Point3f(o) + dr.zeros(mi.Vector3f, n)
            start = o
            leave = None
            bounces = 0
            while True:
                si, t, p, hit = self._closest(scene, o, d, live, start=start, leave=leave)
                total_here = total + t
                amb, dif, spec, N = self._material(si, p, hit)
                I = mi.Color3f(amb)
                for Lp, E, spot in lights:
                    D = Lp - p
                    ld = dr.norm(D)
                    L = D / ld
                    c = dr.dot(L, N)
                    cast = hit & (c > 0)
                    if spot is not None:
                        cast &= -dr.dot(L, spot[0]) > spot[1]
                    if dr.any(cast):
                        blocked = self.blocked(scene, p, L, ld, self._ids(si, cast), cast)
                        I += dr.select(cast & ~blocked, self.light_term(dif, E, c, ld), 0.0)
                div = t if self.reflect == "segment" else total_here
                image = image + dr.select(hit, weight * I / div, 0.0)
                go = hit & dr.any(spec != 0) & (total_here < dr.opaque(mi.Float, self.max_dist))
                if not dr.any(go) or bounces >= self.max_bounces:
                    self.stats = {"bounces": bounces, "capped": bool(dr.any(go))}
                    break
                R = self.reflected(d, N)
                # the next segment starts at the hit point (its t is measured from there);
                # the search starts a little along the ray (_along), and steps over the
                # surface it leaves (the course skips it)
                start = dr.select(go, _along(p, R), start)
                leave = self._ids(si, go)
                o, d = dr.select(go, p, o), dr.select(go, R, d)
                weight = weight * spec
                total = total_here
                live = go
                bounces += 1
                # one evaluation per bounce: the next bounce's kernels start from data
                dr.eval(image, weight, total, o, d, start, live, leave)
            return image

    def _odd(f):
        return f - 2 * dr.floor(0.5 * f)

    def _along(p, d):
        """Where a secondary ray from the hit point p along d starts its search: p moved
        (1 + |p|∞)·RayEpsilon along the ray itself, so the ray is still the course's line
        H + t·d.  (Mitsuba's spawn_ray moves it as far off the surface, along the normal:
        that shifts the whole line, and a shadow ray passing 5.5e-4 below a cylinder's rim
        on the other side was blocked: README "Mitsuba renders the course image".)"""
        off = (1 + dr.max(dr.abs(p))) * mi.math.RayEpsilon
        return p + d * off

    return CourseMaterial, CourseIntegrator
