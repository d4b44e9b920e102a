"""Per-view ground truth of an imported scene: the material maps in image space
(`GroundTruthEvaluator`: the original materials at the original UV of the triangle our ray hits)
and the irradiance E / pi rendered by Mitsuba in its `llvm_ad_rgb` variant (`render_irradiance`).
"""

from __future__ import annotations

import dataclasses
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba.materials import CUTOUT_OPACITY
from jaxdistill.datasets.mitsuba.shapes import SourceObject
from jaxdistill.errors import InputError
from jaxdistill.render import fragments as fr
from jaxdistill.scene.cameras import Camera, rgbx_camera_normals
from jaxdistill.scene.model import Mesh


@dataclasses.dataclass(frozen=True, eq=False)
class GroundTruth:
    """Per-view maps (H, W, C) float32 and the valid mask (H, W) bool."""

    albedo: np.ndarray
    roughness: np.ndarray
    metallic: np.ndarray
    normal: np.ndarray
    mask: np.ndarray
    hit: np.ndarray


class GroundTruthEvaluator:
    """Evaluates the original materials at our ray hits, per view (see the module docstring)."""

    def __init__(self, objects: Sequence[SourceObject], mesh: Mesh):
        self.objects = list(objects)
        self.mesh = mesh
        corner_uv, corner_n = [], []
        for obj in objects:
            f = obj.faces
            if obj.texcoords is not None:
                corner_uv.append(obj.texcoords[f])
            else:  # Mitsuba's uv of a mesh without texcoords is (b1, b2)
                corner_uv.append(np.broadcast_to([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], (len(f), 3, 2)))
            if obj.normals is not None:
                corner_n.append(obj.normals[f])
            else:
                t = obj.vertices[f]
                n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
                corner_n.append(np.repeat(n[:, None], 3, axis=1))
        self.corner_uv = np.concatenate(corner_uv).astype(np.float64)
        self.corner_normal = np.concatenate(corner_n).astype(np.float64)
        self.masked_object = np.array([o.masked for o in objects])
        self.masked_face = self.masked_object[mesh.face_object]

    def evaluate(self, camera: Camera, frag: fr.Fragments) -> GroundTruth:
        """GroundTruth of one view from its fragments (computed on `self.mesh`)."""
        h, w = frag.shape
        hit = frag.hit
        tri = frag.triangle[hit]
        b = frag.barycentric[hit].astype(np.float64)
        weights = np.stack([1.0 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], axis=1)
        directions = camera.pixel_directions().reshape(h, w, 3)[hit]       # camera z = 1
        points = camera.center + frag.depth[hit][:, None].astype(np.float64) * directions
        uv = np.einsum("nk,nkc->nc", weights, self.corner_uv[tri])
        obj_ids = self.mesh.face_object[tri]

        albedo = np.zeros((h * w, 3))
        rough = np.zeros((h * w, 1))
        metal = np.zeros((h * w, 1))
        cutout = np.zeros(h * w, bool)       # mask BSDF opacity < CUTOUT_OPACITY
        flat = np.flatnonzero(hit.ravel())
        for object_id in np.unique(obj_ids):
            obj = self.objects[object_id]
            if obj.masked:
                continue
            sel = obj_ids == object_id
            p, t = points[sel], uv[sel]
            if obj.uv_function is not None:
                t = obj.uv_function(p)
            idx = flat[sel]
            albedo[idx] = obj.material.albedo.evaluate(t, p)
            rough[idx] = obj.material.roughness.evaluate(t, p)
            metal[idx] = obj.material.metallic.evaluate(t, p)
            if obj.material.opacity is not None:
                cutout[idx] = obj.material.opacity.evaluate(t, p)[:, 0] < CUTOUT_OPACITY

        n = np.einsum("nk,nkc->nc", weights, self.corner_normal[tri])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        n *= np.where(np.einsum("nc,nc->n", n, directions) > 0, -1.0, 1.0)[:, None]   # face the camera
        n_cam = rgbx_camera_normals(n, camera)             # RGB<->X: x right, y up, z towards the camera
        normal = np.full((h * w, 3), 0.5)
        normal[flat] = 0.5 * (n_cam + 1.0)

        mask = hit.copy()
        mask[hit] = ~self.masked_face[tri]
        mask &= ~cutout.reshape(h, w)
        keep = mask.ravel()[:, None]
        shape = (h, w, -1)
        return GroundTruth(albedo=(albedo * keep).reshape(shape).astype(np.float32),
                           roughness=(rough * keep).reshape(shape).astype(np.float32),
                           metallic=(metal * keep).reshape(shape).astype(np.float32),
                           normal=normal.reshape(shape).astype(np.float32), mask=mask, hit=hit)


IRRADIANCE_VARIANT = "llvm_ad_rgb"
IRRADIANCE_LANES = 1 << 20              # rays a wavefront at most when a view's samples are batched (fewer pixels)
IRRADIANCE_TARGET_PERCENTILE = 99.0     # targets: scene-wide scale putting this percentile at 0.9


def render_irradiance(xml_path, cameras: Sequence[Camera], *, spp: int, seed: int = 0,
                      xml_text: str | None = None, progress: bool = False) -> list[np.ndarray]:
    """Per view (H, W, 3) float32 diffuse irradiance E / pi at each pixel centre's first hit (0 on misses).

    E / pi is the radiance a white Lambertian surface would reflect there (so a diffuse pixel is
    albedo x irradiance): the cosine-weighted mean of the incident radiance of the ORIGINAL scene
    over the hemisphere of the shading normal turned towards the camera. Only the first hit is
    white; light arriving there keeps every original material, emitter and interreflection. (A
    render of the scene with all materials white would not: its interreflections are brighter.)
    Estimator per sample: emitter sampling and a cosine-sampled direction combined by MIS (balance
    heuristic); beyond the first bounce Mitsuba's `path` integrator, one bounce shorter than the
    scene integrator's max_depth (so E / pi x albedo is what the photos show on diffuse surfaces).
    Runs in Mitsuba's vectorised `llvm_ad_rgb` variant (one wavefront per view and sample, or
    several samples of a view's pixels in one wavefront of up to IRRADIANCE_LANES rays when it
    has fewer pixels), then switches back. The scene is loaded again in that variant from `xml_text` when given (an
    upgraded Mitsuba 0.x file, with absolute file names), else from `xml_path`. progress: a bar per view.
    """
    depth = _integrator_max_depth(Path(xml_path), xml_text)
    previous = mb.load_mitsuba().variant()
    mi, dr = irradiance_mitsuba()
    try:
        if xml_text is None:
            scene = mi.load_file(os.fspath(xml_path), optimize=False)
        else:
            scene = mi.load_string(xml_text, optimize=False)
        nested = mi.load_dict({"type": "path", "max_depth": max(depth - 1, 1) if depth > 0 else -1})
        sampler = mi.load_dict({"type": "independent"})
        out = []
        bar = tqdm(cameras, desc=f"irradiance (spp {spp})", unit="view", disable=not progress, dynamic_ncols=True)
        for v, cam in enumerate(bar):
            origins, directions = cam.pixel_rays()
            n = len(origins)
            # k samples of every pixel in one wavefront of up to IRRADIANCE_LANES rays: each wavefront costs
            # Mitsuba a trace of the integrator (about 0.2 s), which small images would otherwise pay per sample
            per = max(1, min(spp, IRRADIANCE_LANES // max(n, 1)))
            total = np.zeros((n, 3))
            for first in range(0, spp, per):
                k = min(per, spp - first)
                sampler.seed(dr.opaque(mi.UInt32, ((seed * 7919 + v) * 65537 + first) % 2 ** 32), n * k)
                samples = _irradiance_sample(mi, dr, scene, nested, sampler, np.tile(origins, (k, 1)),
                                             np.tile(directions, (k, 1)))
                total += samples.reshape(k, n, 3).sum(axis=0)
            out.append((total / spp).reshape(cam.height, cam.width, 3).astype(np.float32))
        return out
    finally:
        mb.load_mitsuba(previous)                       # back to the variant of everything else


def irradiance_mitsuba():
    """(mitsuba, drjit) with the IRRADIANCE_VARIANT set and its JIT started; InputError saying how
    to install LLVM when it cannot start (the variant set before is set back then)."""
    previous = mb.load_mitsuba().variant()
    try:
        import drjit as dr
        mi = mb.load_mitsuba(IRRADIANCE_VARIANT)
        dr.eval(mi.Float(0.0))                          # Dr.Jit starts its LLVM backend on first use
    except (ImportError, RuntimeError, AttributeError) as err:   # no LLVM library found by Dr.Jit
        mb.load_mitsuba(previous)
        raise InputError.single("mitsuba", IRRADIANCE_VARIANT, f"the irradiance ground truth needs Mitsuba's "
                                f"{IRRADIANCE_VARIANT} variant, which cannot start here ({err}); install LLVM "
                                "19 (e.g. apt-get install libllvm19; older LLVMs may fail to compile), or set "
                                "DRJIT_LIBLLVM_PATH to its libLLVM .so file") from None
    return mi, dr


def _integrator_max_depth(xml_path: Path, xml_text: str | None = None) -> int:
    """The max_depth of the XML's top-level integrator (`$name` resolved from <default>); -1 when unset."""
    try:
        root = ET.fromstring(xml_text) if xml_text is not None else ET.parse(xml_path).getroot()
    except (ET.ParseError, OSError):
        return -1
    defaults = {d.get("name"): d.get("value") for d in root.findall("default")}
    integrator = root.find("integrator")
    for element in integrator.iter("integer") if integrator is not None else ():
        if element.get("name") in ("max_depth", "maxDepth"):
            value = element.get("value", "-1")
            value = defaults.get(value[1:], "-1") if value.startswith("$") else value
            try:
                return int(value)
            except ValueError:
                return -1
    return -1


def _irradiance_sample(mi, dr, scene, nested, sampler, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, 3) one-sample estimates of E / pi at the first hits of rays (origins, directions)."""
    ray = mi.Ray3f(mi.Point3f(*[origins[:, i].astype(np.float32) for i in range(3)]),
                   mi.Vector3f(*[directions[:, i].astype(np.float32) for i in range(3)]))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    n = si.sh_frame.n
    n = dr.select(dr.dot(n, ray.d) > 0, -n, n)          # the side the camera sees
    inv_pi = 1.0 / math.pi
    # emitter sampling
    ds, weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, valid)
    cos_e = dr.maximum(dr.dot(n, ds.d), 0.0)
    w_e = dr.select(ds.delta, 1.0, ds.pdf / dr.maximum(ds.pdf + cos_e * inv_pi, 1e-30))
    estimate = weight * (cos_e * inv_pi * w_e)
    # a cosine-sampled direction; the path integrator's first vertex adds the emission it hits
    local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
    wo = mi.Frame3f(n).to_world(local)
    pdf = local.z * inv_pi
    ray2 = si.spawn_ray(wo)
    si2 = scene.ray_intersect(ray2, valid)
    ds2 = mi.DirectionSample3f(scene, si2, si)
    emitted = dr.select(valid & (ds2.emitter != None), ds2.emitter.eval(si2, valid), 0.0)  # noqa: E711
    pdf_e = scene.pdf_emitter_direction(si, ds2, valid)
    w_b = pdf / dr.maximum(pdf + pdf_e, 1e-30)
    radiance, _, _ = nested.sample(scene, sampler, mi.RayDifferential3f(ray2), None, valid)
    estimate += (radiance - emitted) + w_b * emitted    # f cos / pdf = 1 for a white Lambertian
    estimate = dr.select(valid & (local.z > 0), estimate, 0.0)
    return np.stack([np.array(estimate[i], np.float64) for i in range(3)], axis=1)


def irradiance_target_scale(images: Sequence[np.ndarray], masks: Sequence[np.ndarray]) -> float:
    """One scene-wide factor putting the IRRADIANCE_TARGET_PERCENTILE of the masked irradiance at 0.9."""
    values = np.concatenate([im[m].max(axis=-1) for im, m in zip(images, masks)]) if images else np.zeros(0)
    peak = float(np.percentile(values, IRRADIANCE_TARGET_PERCENTILE)) if values.size else 0.0
    return 0.9 / peak if peak > 0 else 1.0
