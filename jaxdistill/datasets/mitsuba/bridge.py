"""Mitsuba 3 interop for ground truth: our cameras and meshes as Mitsuba sensors and shapes.

Mitsuba is an optional extra (`pip install -e ".[scenes]"`), used by the scene-generation
scripts and their tests, never by the distillation itself. Everything here runs in the
`scalar_rgb` variant, which needs no LLVM and renders deterministically for a given seed.

Conventions bridged:
- Camera: ours is OpenCV (x right, y down, z forward); Mitsuba's perspective sensor looks
  down +z with x left, y up, so `to_world = c2w @ diag(-1, -1, 1, 1)`. Its principal point
  offsets are fractions of the film size: offset_x = 0.5 - cx / W, offset_y = 0.5 - cy / H
  (the inverse of `cameras.from_mitsuba`). Mitsuba pixels are square: fx must equal fy.
- UVs: ours have v up and texture row 0 at v = 1; a Mitsuba bitmap puts row 0 at v = 0, so
  shapes get texcoords (u, 1 - v) and bitmaps are passed unflipped (row 0 = top).
- Bitmaps are float32 linear values (`raw`), so Mitsuba applies no sRGB decoding.
"""

from __future__ import annotations

import numpy as np

from jaxdistill.scene.cameras import Camera

VARIANT = "scalar_rgb"
SQUARE_PIXEL_TOLERANCE = 1e-6


def load_mitsuba(variant: str | None = None):
    """Returns the `mitsuba` module with `variant` set; a clear ImportError when it is absent.

    variant=None keeps the variant the process already chose (a script may pick the faster
    `llvm_ad_rgb`, see `llvm_variant`), else sets `scalar_rgb`.
    """
    try:
        import mitsuba as mi
    except ImportError as e:
        raise ImportError("Mitsuba 3 is needed to render ground truth: install the 'scenes' extra "
                          "with  pip install -e \".[scenes]\"") from e
    variant = variant or mi.variant() or VARIANT
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


LLVM_LIBRARY = "/usr/lib/x86_64-linux-gnu/libLLVM-19.so"
"""Debian's libllvm19 (`apt-get install libllvm19`); LLVM 15/16 fail with a codegen error."""


def llvm_variant() -> str:
    """'llvm_ad_rgb' when an LLVM 19 library is found (vectorised, several times faster for
    many small renders), else 'scalar_rgb'. Sets DRJIT_LIBLLVM_PATH if it is unset."""
    import os
    path = os.environ.get("DRJIT_LIBLLVM_PATH") or (LLVM_LIBRARY if os.path.exists(LLVM_LIBRARY) else "")
    if not path:
        return VARIANT
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return "llvm_ad_rgb"


def to_world(camera: Camera) -> np.ndarray:
    """(4, 4) Mitsuba sensor to_world (camera x left, y up, z forward) of an OpenCV camera."""
    return camera.c2w @ np.diag([-1.0, -1.0, 1.0, 1.0])


def sensor_dict(camera: Camera, *, spp: int = 1, centre_samples: bool = False,
                pixel_format: str = "rgb") -> dict:
    """A `perspective` sensor dict reproducing `camera` exactly.

    centre_samples=True takes one sample at each pixel centre (stratified sampler, no jitter):
    the Mitsuba analogue of our one-ray-per-pixel-centre fragments. Otherwise an independent
    sampler with `spp` samples. The reconstruction filter is a box (each sample lands in exactly
    one pixel): with Mitsuba's default Gaussian, image blocks overlap at their borders and the
    order in which threads add them changes the last bits, so renders would not be reproducible.
    Raises ValueError when fx != fy (Mitsuba's sensor has square pixels).
    """
    mi = load_mitsuba()
    K, W, H = camera.K, camera.width, camera.height
    if abs(K[0, 0] - K[1, 1]) > SQUARE_PIXEL_TOLERANCE * K[0, 0]:
        raise ValueError(f"camera has fx={K[0, 0]} != fy={K[1, 1]}: Mitsuba's perspective sensor "
                         "has square pixels; use equal focal lengths")
    fov_x = float(np.degrees(2.0 * np.arctan(W / (2.0 * K[0, 0]))))
    film = {"type": "hdrfilm", "width": W, "height": H, "pixel_format": pixel_format,
            "component_format": "float32", "rfilter": {"type": "box"}}
    if centre_samples:
        sampler = {"type": "stratified", "sample_count": 1, "jitter": False}
    else:
        sampler = {"type": "independent", "sample_count": int(spp)}
    return {"type": "perspective", "fov": fov_x, "fov_axis": "x",
            "principal_point_offset_x": 0.5 - K[0, 2] / W,
            "principal_point_offset_y": 0.5 - K[1, 2] / H,
            "near_clip": 1e-3, "far_clip": 1e5,
            "to_world": mi.ScalarTransform4f(to_world(camera).tolist()),
            "film": film, "sampler": sampler}


def mesh_shape(name: str, vertices, faces, uv, *, bsdf=None, emitter=None, flip_normals=False):
    """A Mitsuba mesh from (Nv, 3) vertices, (F, 3) faces and per-corner uv (F, 3, 2) (ours, v up).

    Corners are unshared (3F vertices) so per-corner UVs survive seams; there are no vertex
    normals, so Mitsuba shades with face normals, like our fragments. `bsdf` and `emitter`
    are loaded Mitsuba objects or plugin dicts.
    """
    import drjit as dr
    mi = load_mitsuba()
    faces = np.asarray(faces, np.int64)
    corners = np.asarray(vertices, np.float64)[faces].reshape(-1, 3)
    tex = np.asarray(uv, np.float64).reshape(-1, 2).copy()
    tex[:, 1] = 1.0 - tex[:, 1]
    props = mi.Properties()
    for key, obj in (("bsdf", bsdf), ("emitter", emitter)):
        if obj is not None:
            props[key] = mi.load_dict(obj) if isinstance(obj, dict) else obj
    if flip_normals:
        props["flip_normals"] = True
    shape = mi.Mesh(name, len(corners), len(faces), props, has_vertex_texcoords=True)
    params = mi.traverse(shape)
    params["vertex_positions"] = dr.scalar.ArrayXf(corners.astype(np.float32).ravel())
    params["faces"] = dr.scalar.ArrayXu(np.arange(3 * len(faces), dtype=np.uint32))
    params["vertex_texcoords"] = dr.scalar.ArrayXf(tex.astype(np.float32).ravel())
    params.update()
    return shape


def bitmap(values, *, filter_type: str = "bilinear", wrap_mode: str = "clamp") -> dict:
    """A `bitmap` texture dict from a linear float image (H, W) or (H, W, C), row 0 on top."""
    mi = load_mitsuba()
    array = np.ascontiguousarray(np.asarray(values, np.float32))
    if array.ndim == 2:
        array = array[..., None]
    return {"type": "bitmap", "bitmap": mi.Bitmap(array), "raw": True,
            "filter_type": filter_type, "wrap_mode": wrap_mode}


def render(scene, camera: Camera, *, spp: int = 1, seed: int = 0, integrator=None,
           centre_samples: bool = False) -> np.ndarray:
    """(H, W, C) float32 image of a loaded Mitsuba `scene` from `camera` (linear radiance or AOVs)."""
    mi = load_mitsuba()
    sensor = mi.load_dict(sensor_dict(camera, spp=spp, centre_samples=centre_samples))
    if isinstance(integrator, dict):
        integrator = mi.load_dict(integrator)
    image = mi.render(scene, sensor=sensor, integrator=integrator, seed=int(seed),
                      spp=1 if centre_samples else int(spp))
    return np.array(image, dtype=np.float32)


def aov_integrator(*aovs: str) -> dict:
    """An `aov` integrator dict; each aov is 'name:type' (e.g. 'albedo:albedo', 'obj:shape_index')."""
    return {"type": "aov", "aovs": ",".join(aovs)}


INTRINSIC_INTEGRATOR = "jaxdistill_intrinsic"
IRRADIANCE_CHANNELS = slice(3, 6)


def intrinsic_integrator(max_depth: int = 6, *, photo: bool = True) -> dict:
    """An integrator dict whose render is (H, W, 6): the path-traced photo (RGB) and the diffuse
    irradiance over pi at the first hit (RGB, the `IRRADIANCE_CHANNELS`), in one pass.
    photo=False leaves the photo channels 0 and skips its path (the irradiance alone, about half
    the time); the irradiance is the same estimator either way.

    Irradiance/pi is what a white Lambertian surface at the hit would reflect:
    photo_diffuse = albedo * (E / pi), the intrinsic-image convention (Hypersim's diffuse
    illumination, RGB<->X's irradiance). Estimated like the `path` integrator's first bounce
    with a white Lambertian BSDF there: emitter sampling (all lights, delta ones included) and a
    cosine-sampled ray traced on by `path` (so inter-reflections see the real materials), the
    two combined by multiple importance sampling (power heuristic) for the light the sampled
    ray hits directly. The hit's normal faces the camera; misses are 0.
    """
    mi = load_mitsuba()
    import drjit as dr

    def power(a, b):
        a2, b2 = dr.square(a), dr.square(b)
        return dr.detach(a2 / dr.maximum(a2 + b2, 1e-30))

    class Intrinsic(mi.SamplingIntegrator):
        def __init__(self, props):
            super().__init__(props)
            self.path = mi.load_dict({"type": "path", "max_depth": props.get("max_depth", 6)})
            self.photo = props.get("photo", True)

        def aov_names(self):
            return ["irradiance.R", "irradiance.G", "irradiance.B"]

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, active)
            hit = active & si.is_valid()
            if self.photo:
                photo, valid, _ = self.path.sample(scene, sampler, ray, medium, active)
            else:
                photo, valid = mi.Spectrum(0.0), mi.Bool(active)
            n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
            # emitter sampling
            ds, weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, hit)
            cos_l = dr.maximum(dr.dot(n, ds.d), 0.0)
            mis_em = dr.select(ds.delta, 1.0, power(ds.pdf, cos_l / dr.pi))
            e = weight * cos_l / dr.pi * mis_em
            # cosine-sampled ray: everything it gathers, its directly hit light MIS-weighted
            d = mi.Frame3f(n).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
            ray2 = si.spawn_ray(d)
            incident, _, _ = self.path.sample(scene, sampler, ray2, medium, hit)
            si2 = scene.ray_intersect(ray2, hit)
            emitter = si2.emitter(scene, hit)
            # scalar variants give None for no emitter; vectorised ones a pointer array (null lanes eval to 0)
            if emitter is not None:
                direct = emitter.eval(si2, hit)
                pdf_em = scene.pdf_emitter_direction(si, mi.DirectionSample3f(scene, si2, si), hit)
                e += incident - direct + direct * power(dr.maximum(dr.dot(n, d), 0.0) / dr.pi, pdf_em)
            else:
                e += incident
            e = dr.select(hit, e, 0.0)
            return photo, valid, [e[0], e[1], e[2]]

    mi.register_integrator(INTRINSIC_INTEGRATOR, lambda props: Intrinsic(props))
    return {"type": INTRINSIC_INTEGRATOR, "max_depth": int(max_depth), "photo": bool(photo)}


def render_irradiance(scene, cameras, *, spp: int, seeds, max_depth: int = 5, progress: bool = False) -> list:
    """Per camera (H, W, 3) float32 diffuse irradiance E / pi at the first hit of a loaded Mitsuba
    `scene` (0 on misses), in the scene's units: `intrinsic_integrator(max_depth, photo=False)`
    with `spp` samples per pixel (box filter) and `seeds[i]` for camera i.

    max_depth is the length of the paths traced on from the first hit: a scene whose photos were
    path traced with max depth D has its diffuse pixels equal to albedo x E / pi for D - 1.
    """
    from tqdm import tqdm

    mi = load_mitsuba()
    integrator = mi.load_dict(intrinsic_integrator(max_depth, photo=False))
    out = []
    for cam, seed in tqdm(list(zip(cameras, seeds)), desc=f"irradiance ({spp} spp)", unit="view", disable=not progress):
        image = render(scene, cam, spp=spp, seed=int(seed), integrator=integrator)
        out.append(np.ascontiguousarray(image[..., IRRADIANCE_CHANNELS]))
    return out


def principled_shapes(mesh, pages: dict, *, emitters: dict | None = None, object_ids=None,
                      two_sided: bool = False) -> dict:
    """{object name: Mitsuba mesh} of a page-textured mesh (`Mesh`: vertices, faces, per-corner
    uv, face_object, object_names), each object with a `principled` BSDF whose base_color,
    roughness and metallic are its pages (pages[map][k], linear, row 0 on top; bilinear lookup
    through the mesh's UVs); `emitters` {object name: linear RGB radiance} makes those objects area
    lights; `object_ids` limits the shapes to these objects (default: every object with faces).
    The principled BSDF is one-sided (black from behind): two_sided=True wraps it in `twosided`
    for meshes whose faces do not all face the viewer (boxes modelled from outside, imports).
    """
    emitters = emitters or {}
    out = {}
    ids = range(len(mesh.object_names)) if object_ids is None else object_ids
    for k in ids:
        name = mesh.object_names[k]
        sel = mesh.face_object == k
        if not sel.any():
            continue
        bsdf = {"type": "principled", "base_color": bitmap(pages["albedo"][k]),
                "roughness": bitmap(pages["roughness"][k]), "metallic": bitmap(pages["metallic"][k])}
        if two_sided:
            bsdf = {"type": "twosided", "material": bsdf}
        radiance = emitters.get(name)
        emitter = {"type": "area", "radiance": {"type": "rgb", "value": list(radiance)}} if radiance is not None else None
        out[name] = mesh_shape(name, mesh.vertices, mesh.faces[sel], mesh.uv[sel], bsdf=bsdf, emitter=emitter)
    return out
