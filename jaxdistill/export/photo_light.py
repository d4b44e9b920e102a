"""The albedo's overall scale from the photos' own light (`--anchor=traced`).

Score distillation and the re-rendering term fix albedo ⊙ irradiance, not the split: a brighter
albedo under a dimmer light renders the same photos. The photos themselves do fix it where they
show the light: the irradiance at a surface point is the radiance of everything it sees, and
the photos record that radiance (`render.light_trace`). So at points p seen by the photos,

    albedo(p) = L(p) / (E(p)/π),   E(p)/π traced through the mesh from the photos' radiance,

with no prior and no exposure (raw linear photo values: the exposure cancels). The run's albedo
a(p) gets one gain per channel, g_c = Σ_p L_c / Σ_p a_c E_c/π over each object's points (a
ratio of sums: one point's trace is noisy and skewed), then the median over objects weighted by
their points (one sun-lit floor does not decide it).

What the trace cannot see biases g upwards (the traced light is too weak, the albedo too
bright): a directional sun and point lights (no photo shows them), and light through windows
and openings whose outside no photo shows (the rays leave the mesh with no radiance to take).
`traced_albedo_gain` reports the fraction of such rays (`escaped_unseen`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxdistill.io.view_images import read_mask, read_photo_linear
from jaxdistill.render import light_trace
from jaxdistill.render.fragments import RayCaster, compute_depths
from jaxdistill.scene.model import Scene

TRACE_VIEWS = 64            # --anchor=traced: views whose photos give the radiance (evenly spaced)
TRACE_POINTS = 128          # points per view where the albedo is measured
TRACE_RAYS = 64             # hemisphere rays per point
TRACE_KNOWN = 0.9           # a point counts when at least this fraction of its rays have a known radiance
BACKGROUND_PIXELS = 0.001   # the photos show a background when this fraction of their pixels hit nothing
TRACE_MIN_POINTS = 50       # fewer counted points than this: no gain (a warning says why)


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value at which half the weight lies below (the lower one on a tie)."""
    order = np.argsort(values)
    cumulative = np.cumsum(np.asarray(weights, np.float64)[order])
    return float(np.asarray(values)[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


@dataclasses.dataclass(frozen=True)
class TracedPoints:
    """Surface points (N, 3) seen by the photos, their normals (N, 3) towards the views, and
    what the trace found there: radiance (N, 3) the photos' mean over the views that see the
    point (views (N,)), albedo (N, 3) the run's render, irradiance (N, 3) traced (E/π), known /
    escaped (N,) fractions of its rays, emitter (N,) on an emitter's face, object (N,) the mesh
    object; background (3,) or None: what the photos show where they hit nothing."""

    points: np.ndarray
    normals: np.ndarray
    radiance: np.ndarray
    views: np.ndarray
    albedo: np.ndarray
    irradiance: np.ndarray
    known: np.ndarray
    escaped: np.ndarray
    emitter: np.ndarray
    object: np.ndarray
    background: np.ndarray | None
    record: dict


@dataclasses.dataclass(frozen=True)
class PhotoRadiance:
    """What the photos show, for the trace: the views' cameras, camera depths (H, W) (inf on a
    miss) and raw linear photos (H, W, 3); per face the mean radiance and pixel count, per object
    the mean; the emitters (`light_trace.find_emitters`) and the background radiance (3,) the
    photos show where they hit nothing (None when they show none)."""

    cameras: list
    depths: list
    photos: list
    face_mean: np.ndarray
    face_pixels: np.ndarray
    object_mean: np.ndarray
    object_pixels: np.ndarray
    emitters: light_trace.Emitters | None
    background: np.ndarray | None

    def lookup(self, y: np.ndarray, tri: np.ndarray, face_object: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(radiance (M, 3), known (M,)) at hit points y on faces tri: the mean over the views that
        see the point, else over its face's pixels, else over its object's (a ceiling no view
        looks at); unknown where none of these has a pixel."""
        radiance, seen = light_trace.visible_radiance(y, self.cameras, self.depths, self.photos)
        face_seen = self.face_pixels[tri] > 0
        obj = face_object[tri]
        radiance = np.where((seen > 0)[:, None], radiance,
                            np.where(face_seen[:, None], self.face_mean[tri], self.object_mean[obj]))
        return radiance, (seen > 0) | face_seen | (self.object_pixels[obj] > 0)


def read_photo_radiance(scene: Scene, chosen: np.ndarray) -> PhotoRadiance:
    """The photos of the views `chosen`, linear and exposed as the scene says (a shared exposure
    cancels in radiance / irradiance), with each pixel's triangle and depth (the set-up's cached ray casts);
    unusable pixels (an LDR photo's clipped ones, a mask's empty ones) are seen by no one."""
    mesh = scene.mesh
    cams = [scene.views[v].camera for v in chosen]
    depths, photos, triangles, background = [], [], [], []
    hits = compute_depths(mesh, cams)      # the set-up's ray casts, from the cache: the triangle and depth a pixel
    for k, (v, cam) in enumerate(zip(chosen, cams)):
        view = scene.views[v]
        tri, depth = hits[k]
        photo, usable = read_photo_linear(view.photo, view.exposure, cam.height, cam.width)
        # a mask drops emitters from the loss, but their light is what the trace needs: a masked
        # pixel counts unless it holds no light at all (an undistortion's unfilled border)
        empty = ~read_mask(view.mask, cam.height, cam.width) & ~(photo > 0).any(axis=-1) if view.mask \
            else np.zeros(usable.shape, bool)
        tri[(usable < 0.5) | empty] = -2                         # seen by no pixel of this view
        depths.append(np.where(tri >= 0, depth, np.inf).astype(np.float32))
        photos.append(photo)
        triangles.append(tri)
        background.append(photo[tri == -1])
    background = np.concatenate(background)
    sky = (background.mean(axis=0, dtype=np.float64)
           if len(background) >= BACKGROUND_PIXELS * sum(d.size for d in depths) else None)
    face_mean, face_pixels, face_peak = light_trace.face_radiance(len(mesh.faces), triangles, photos)
    emitters = light_trace.find_emitters(mesh.vertices, mesh.faces, mesh.face_object, face_mean, face_pixels,
                                         face_peak)
    objects = len(mesh.object_names)
    object_pixels = np.bincount(mesh.face_object, weights=face_pixels, minlength=objects)
    object_mean = np.stack([np.bincount(mesh.face_object, weights=face_mean[:, c] * face_pixels, minlength=objects)
                            for c in range(3)], axis=1) / np.maximum(object_pixels, 1)[:, None]
    return PhotoRadiance(cams, depths, photos, face_mean, face_pixels, object_mean, object_pixels, emitters, sky)


def surface_points(mesh, caster: RayCaster, cameras, views, hits, renders, count: int, rng: np.random.Generator):
    """(points (N, 3), normals (N, 3) towards the camera, faces (N,), albedo (N, 3)) at `count`
    random covered pixels (hits[v] (H, W)) of each camera of views v, albedo from
    renders[v]["albedo"] (read a view at a time: renders may be lazy)."""
    out = [], [], [], []
    for cam, v in zip(cameras, views):
        rows, cols = np.nonzero(np.asarray(hits[v]))
        if not len(rows):
            continue
        pick = rng.choice(len(rows), min(count, len(rows)), replace=False)
        r, c = rows[pick], cols[pick]
        o, d = cam.pixel_rays(np.stack([c + 0.5, r + 0.5], axis=1))
        tri, _, dist = caster.intersect(o, d)
        keep = tri >= 0
        corners = mesh.vertices[mesh.faces[tri[keep]]]
        n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        n *= -np.sign(np.einsum("nc,nc->n", n, d[keep]))[:, None]
        albedo = np.asarray(renders[v]["albedo"], np.float64)[r[keep], c[keep], :3]
        for part, value in zip(out, (o[keep] + dist[keep, None] * d[keep], n, tri[keep], albedo)):
            part.append(value)
    if not out[0]:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
    return tuple(np.concatenate(part) for part in out)


def trace_points(scene: Scene, renders, hits, *, seed: int = 0, views: int = TRACE_VIEWS,
                 points: int = TRACE_POINTS, rays: int = TRACE_RAYS) -> TracedPoints:
    """The albedo's evidence from the photos' own light at `points` covered pixels (hits[v]
    (H, W) bool) of each of `views` evenly spaced views, whose photos also give the radiance;
    renders: per view {"albedo": (H, W, 3)} file space, the run's albedo. The light reaching a
    point (`render.light_trace`): rays over the hemisphere, each taking the radiance the photos
    show where it lands (`PhotoRadiance.lookup`), plus the emitters' faces sampled directly."""
    rng = np.random.default_rng(seed)
    chosen = np.unique(np.linspace(0, len(scene.views) - 1, min(views, len(scene.views))).round().astype(int))
    mesh = scene.mesh
    caster = RayCaster(mesh)
    light = read_photo_radiance(scene, chosen)
    p, n, face, albedo = surface_points(mesh, caster, light.cameras, chosen, hits, renders, points, rng)
    radiance, seen = light_trace.visible_radiance(p, light.cameras, light.depths, light.photos)
    irradiance, known, escaped = light_trace.traced_irradiance(
        caster.intersect, p, n, lambda y, tri: light.lookup(y, tri, mesh.face_object), rays=rays, rng=rng,
        offset=1e-4 * caster.scale, background=light.background, emitters=light.emitters, emitter_samples=rays)
    emitting = np.zeros(len(mesh.faces), bool)
    if light.emitters is not None:
        emitting[light.emitters.faces] = True
    record = {"points": int(len(p)), "views": len(chosen), "rays": rays,
              "known_median": float(np.median(known)) if len(known) else 0.0,
              "escaped_mean": float(escaped.mean()) if len(escaped) else 0.0,
              "background": None if light.background is None else np.round(light.background, 5).tolist(),
              "emitter_faces": 0 if light.emitters is None else int(len(light.emitters.faces))}
    return TracedPoints(p, n, radiance, seen, albedo, irradiance, known, escaped, emitting[face], mesh.face_object[face],
                        light.background, record)


def traced_albedo_gain(scene: Scene, renders, hits, *, seed: int = 0, views: int = TRACE_VIEWS,
                       points: int = TRACE_POINTS, rays: int = TRACE_RAYS) -> tuple[np.ndarray | None, dict]:
    """(g (3,) or None, what was measured): per channel, the gain that takes the run's albedo to
    the photos' radiance over the irradiance traced from them (`trace_points`),

        g_c = Σ_p L_c(p) / Σ_p a_c(p) E_c(p)/π      over each object's points,

    a ratio of sums (one point's trace is noisy and skewed, a median of ratios is biased), then
    the median over the objects weighted by their points (a sun-lit floor does not decide it).
    A point counts where at least TRACE_KNOWN of its rays met a known radiance, some view sees
    it, and it is not on an emitter. None when fewer than TRACE_MIN_POINTS count."""
    return gain_from_points(trace_points(scene, renders, hits, seed=seed, views=views, points=points, rays=rays))


def counted_points(t: TracedPoints) -> np.ndarray:
    """(N,) bool: the points that count: at least TRACE_KNOWN of their rays met a known radiance,
    some view sees them, they are not on an emitter and the albedo there is not black."""
    return (t.known >= TRACE_KNOWN) & (t.views > 0) & ~t.emitter & (t.albedo > 1.0 / 255.0).all(axis=1)


def gain_from_points(t: TracedPoints) -> tuple[np.ndarray | None, dict]:
    """`traced_albedo_gain` from the traced points."""
    ok = counted_points(t)
    record = {**t.record, "counted": int(ok.sum()),
              "escaped_unseen": float(t.escaped.mean()) if len(t.escaped) and t.background is None else 0.0}
    if ok.sum() < TRACE_MIN_POINTS:
        return None, record
    ids, inverse, count = np.unique(t.object[ok], return_inverse=True, return_counts=True)
    top = np.stack([np.bincount(inverse, weights=t.radiance[ok, c]) for c in range(3)], axis=1)
    bottom = np.stack([np.bincount(inverse, weights=t.albedo[ok, c] * t.irradiance[ok, c]) for c in range(3)], axis=1)
    usable = (bottom > 0).all(axis=1) & (top > 0).all(axis=1)
    if not usable.any():
        return None, record
    ratio, weight = top[usable] / bottom[usable], count[usable]
    gain = np.array([weighted_median(ratio[:, c], weight) for c in range(3)])
    record["objects"] = int(usable.sum())
    return gain, record
