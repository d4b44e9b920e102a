"""Stand-ins for a monocular estimator's per-view maps: ground truth corrupted the way one errs.

`estimate_view` turns a view's exact maps and photo into the per-view targets the `views` prior
distils (gain and tint, shading leaking into albedo, blur, smooth noise, offsets, tilted
normals), with its parameters; `ESTIMATE_MODEL` describes the model in words for the scene
folders' READMEs. Used for the embedded bedroom and the held-out room scenes.
"""

from __future__ import annotations

import math

import numpy as np

from jaxdistill.models.training.textures import gaussian_blur, smooth_noise

ESTIMATE_MODEL = """\
Per view v, with GT maps rendered by our sampler, photo P (linear) and shading
S = lum(P) / max(lum(albedo_gt), 0.02) normalised by its median over hit pixels, clipped to [0.2, 5]:
- albedo     = clip(gain_v * blur(albedo_gt, blur_px_v) * blur(S, 2 px)**leak_v + 0.02 * smooth_noise, 0, 1);
               gain_v = exposure_v * tint_v (per channel, log-normal sigma 0.12 and 0.06).
- roughness  = clip(blur(roughness_gt) + roughness_offset_v + 0.05 * smooth_noise, 0, 1).
- metallic   = clip(blur(metallic_gt) * metallic_scale_v + metallic_offset_v + 0.03 * smooth_noise, 0, 1).
- normal     = normalise(R_v blur(normal_gt) + 0.06 * smooth_noise), R_v a random rotation of normal_tilt_deg_v.
- irradiance = clip(0.9 I / percentile_99(I), 0, 1), I = blur(P / max(albedo_gt, 0.02), blur_px_v + 1.5):
               the shading layer (specular included), exposed into [0, 1] like RGB<->X's LDR output.
smooth_noise: unit-std Gaussian-filtered noise, sigma 8 px, independent per view, map and channel.
"""


def luminance(x):
    """Rec. 709 luminance of (..., 3) linear RGB."""
    return x @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def estimate_view(rng, gt: dict[str, np.ndarray], photo: np.ndarray, hit: np.ndarray):
    """Corrupted per-view maps standing in for a monocular estimator, and their parameters."""
    h, w = hit.shape
    p = {"exposure": float(np.exp(rng.normal(0, 0.12))), "tint": np.exp(rng.normal(0, 0.06, 3)).round(6).tolist(),
         "leak": float(rng.uniform(0.1, 0.3)), "blur_px": float(rng.uniform(0.5, 1.5)),
         "roughness_offset": float(rng.normal(0, 0.1)), "metallic_scale": float(rng.uniform(0.5, 1.0)),
         "metallic_offset": float(rng.uniform(0.0, 0.08)), "normal_tilt_deg": float(abs(rng.normal(0, 4.0))),
         }

    def noise(c):
        return np.stack([smooth_noise(rng, (h, w), 8.0) for _ in range(c)], -1)

    m = hit[..., None]
    albedo = gt["albedo"]
    shading = luminance(photo) / np.maximum(luminance(albedo), 0.02)
    shading = np.clip(shading / np.median(shading[hit]), 0.2, 5.0)[..., None]
    smooth_shading = gaussian_blur(shading, 2.0)
    gain = p["exposure"] * np.asarray(p["tint"])
    est = {"albedo": np.clip(gain * gaussian_blur(albedo, p["blur_px"]) * smooth_shading ** p["leak"] + 0.02 * noise(3), 0, 1)}
    est["roughness"] = np.clip(gaussian_blur(gt["roughness"], p["blur_px"]) + p["roughness_offset"] + 0.05 * noise(1), 0, 1)
    est["metallic"] = np.clip(gaussian_blur(gt["metallic"], p["blur_px"]) * p["metallic_scale"] + p["metallic_offset"]
                              + 0.03 * noise(1), 0, 1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = math.radians(p["normal_tilt_deg"])
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(a) * cross + (1 - math.cos(a)) * cross @ cross
    n = gaussian_blur(gt["normal"], p["blur_px"]) @ rot.T + 0.06 * noise(3)
    est["normal"] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    irradiance = gaussian_blur(photo / np.maximum(albedo, 0.02), p["blur_px"] + 1.5)
    est["irradiance"] = np.clip(0.9 * irradiance / np.percentile(irradiance[hit], 99), 0, 1)
    est = {k: np.where(m, v, 0.0).astype(np.float32) for k, v in est.items()}
    return est, p
