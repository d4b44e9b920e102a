"""The prior's training data: procedural rooms path traced with exact intrinsics, into shards.

`main(argv)` is `scripts/make_rgbx_data.py`. Each room (`procedural_rooms.random_room(seed)`)
becomes one shard `room_<seed>.npz` (`shards`) holding its views, all uint8 (V, H, W, C) as
RGB<->X's training images are stored:
- `photo`: path traced (Mitsuba 3, `path` integrator), exposed by Hypersim's rule with one
  exposure for the room (`jaxdistill.io.exposure`, as HDR imports are), sRGB-encoded;
- `albedo` sRGB, `normal` (n + 1) / 2 in RGB<->X camera space (x right, y up, z towards the
  camera), `roughness`, `metallic` (1 channel), exact: our gather sampler on the textures
  Mitsuba renders with, supersampled 2x2 like the photo's pixel box;
- `irradiance` sRGB: diffuse irradiance / pi at the first hit (`mitsuba_bridge.
  intrinsic_integrator`; photo_diffuse = albedo * irradiance in linear light), exposed by the
  same Hypersim rule with its own room-wide exposure (with the photo's, a room's irradiance,
  about twice its photo, would clip);
- `valid`: pixel fully covered by non-emitting geometry (1 channel).
`render_linear` is the same room kept in linear light (the held-out scene folders of
`scripts/make_room_scene.py` are made from it). A rerun skips rooms already written, so a
killed run resumes. Uses Mitsuba's `llvm_ad_rgb` variant when LLVM 19 is installed, else
`scalar_rgb` (slower, same images up to noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.io import exposure, images as imageio
from jaxdistill.models.training.procedural_rooms import Room, material_maps, random_room
from jaxdistill.models.training.room_geometry import build_scene_geometry, preview, rolled_camera
from jaxdistill.models.training.shards import room_seed, write_shard
from jaxdistill.render import fragments as fr
from jaxdistill.render.sampler import sample_pages
from jaxdistill.scene import cameras
from jaxdistill.scene.cameras import camera_normals
from jaxdistill.scene.mesh import face_normals

DESCRIPTION = "Training data for our RGB<->X-family prior: procedural rooms path traced with exact intrinsics."
SUPERSAMPLE = 2


def quantised_textures(room: Room, sizes, seed: int) -> dict[str, list[np.ndarray]]:
    """Per object albedo (linear, from 8-bit sRGB), roughness and metallic (8-bit) pages: what a
    scene's PNG ground truth decodes to, so shards and scene folders agree exactly."""
    rng = np.random.default_rng([seed, 104729])
    out = {"albedo": [], "roughness": [], "metallic": []}
    for (_, _, material), size in zip(room.objects, sizes):
        albedo, rough, metal = material_maps(material, rng, size)
        out["albedo"].append(imageio.srgb_to_linear(np.round(imageio.linear_to_srgb(albedo) * 255) / 255).astype(np.float32))
        out["roughness"].append((np.round(rough * 255) / 255).astype(np.float32)[..., None])
        out["metallic"].append((np.round(metal * 255) / 255).astype(np.float32)[..., None])
    return out


def mitsuba_scene(room: Room, mesh, textures):
    """The loaded Mitsuba scene: principled BSDFs on the textures, emitters, sun and sky."""
    mi = mb.load_mitsuba()
    shapes = {}
    for k, (name, _, material) in enumerate(room.objects):
        sel = mesh.face_object == k
        bsdf = {"type": "principled", "base_color": mb.bitmap(textures["albedo"][k]),
                "roughness": mb.bitmap(textures["roughness"][k]), "metallic": mb.bitmap(textures["metallic"][k])}
        emitter = {"type": "area", "radiance": {"type": "rgb", "value": list(material.emission)}} if material.emission else None
        shapes[name] = mb.mesh_shape(name, mesh.vertices, mesh.faces[sel], mesh.uv[sel], bsdf=bsdf, emitter=emitter)
    if room.sun_irradiance is not None:
        shapes["sun"] = {"type": "directional", "direction": room.sun_direction.tolist(),
                         "irradiance": {"type": "rgb", "value": list(room.sun_irradiance)}}
    if room.sky_radiance is not None:
        shapes["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": list(room.sky_radiance)}}
    return mi.load_dict({"type": "scene", **shapes})


def object_bounds(mesh, names):
    """{name: (lower corner, upper corner)} axis-aligned bounds of the named objects."""
    tri = mesh.triangles()
    return {n: (tri[mesh.face_object == mesh.object_names.index(n)].reshape(-1, 3).min(0),
                tri[mesh.face_object == mesh.object_names.index(n)].reshape(-1, 3).max(0)) for n in names}


def place_cameras(room: Room, mesh, rng, count: int, width: int, height: int, max_tries: int = 4000):
    """`count` cameras inside the room aimed at its objects in turn, about a third close-ups;
    horizontal fov 50-80 degrees, off-centre principal point, a little roll. A candidate is kept
    when its eye is 0.2 m outside every piece of furniture and a preview sees geometry in
    >= 97 % of pixels (no view out of a window) at a median depth >= 0.5 m."""
    bounds = object_bounds(mesh, mesh.object_names)
    emitters = {name for name, _, m in room.objects if m.emission}
    targets = [n for n in mesh.object_names if n not in emitters and not n.startswith("window_")]
    caster = fr.RayCaster(mesh)
    out = []
    for attempt in range(max_tries):
        if len(out) == count:
            break
        name = targets[int(rng.integers(len(targets)))]
        lo, hi = bounds[name]
        target = lo + rng.uniform(0.2, 0.8, 3) * (hi - lo)
        close = name in room.furniture and rng.random() < 0.35
        if close:
            d = rng.normal(size=3)
            d[1] = abs(d[1]) + 0.3
            eye = target + d / np.linalg.norm(d) * rng.uniform(0.7, 1.3)
        else:
            eye = rng.uniform([0.3, 0.8, 0.3], room.size - [0.3, 0.6, 0.3])
        if not (np.all(eye > 0.15) and np.all(eye < room.size - 0.15)):
            continue
        if any(np.all(eye > bounds[n][0] - 0.2) and np.all(eye < bounds[n][1] + 0.2) for n in room.furniture):
            continue
        forward = target - eye
        if np.linalg.norm(forward) < 0.3 or abs(forward[1]) > 0.9 * np.linalg.norm(forward):
            continue
        fov = rng.uniform(50.0, 80.0)
        fx = width / (2 * math.tan(math.radians(fov) / 2))
        K = np.array([[fx, 0, width / 2 + rng.normal(0, 0.02 * width)], [0, fx, height / 2 + rng.normal(0, 0.02 * height)], [0, 0, 1.0]])
        cam = rolled_camera(eye, target, K, width, height, math.radians(rng.normal(0, 3.0)))
        coverage, depth = preview(caster, cam, 4)
        if coverage < 0.97 or depth < 0.5:
            continue
        out.append(cam)
    if len(out) < count:
        raise RuntimeError(f"placed only {len(out)} of {count} cameras in {max_tries} tries")
    return out


def remove_fireflies(image: np.ndarray, ratio: float = 4.0) -> np.ndarray:
    """Pixels brighter than `ratio` x the median of their 3x3 neighbourhood's brightness (isolated
    Monte Carlo outliers of small lights seen through glossy paths) take the neighbourhood's
    median colour; edges and highlights wider than one pixel keep theirs."""
    lum = exposure.brightness(image)
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    stack = np.stack([padded[i:i + image.shape[0], j:j + image.shape[1]] for i in range(3) for j in range(3)])
    order = np.argsort(exposure.brightness(stack), axis=0)[4]                    # median by brightness
    median = np.take_along_axis(stack, order[None, ..., None], axis=0)[0]
    outlier = lum > ratio * np.maximum(exposure.brightness(median), 1e-6)
    return np.where(outlier[..., None], median, image).astype(np.float32)


def box_down(x: np.ndarray, f: int) -> np.ndarray:
    """(H*f, W*f, C) -> (H, W, C) mean over f x f blocks."""
    h, w = x.shape[0] // f, x.shape[1] // f
    return x.reshape(h, f, w, f, -1).mean((1, 3))


def to_u8(x: np.ndarray) -> np.ndarray:
    """[0, 1] values (clipped) as rounded 8-bit integers."""
    return np.round(np.clip(x, 0.0, 1.0) * 255).astype(np.uint8)


@dataclasses.dataclass
class RoomRender:
    """A room rendered in linear light. Per view: `photos` (H, W, 3) radiance, isolated fireflies
    removed; `irradiance` (H, W, 3) E / pi at the first hit (photo units); `gt` {albedo (linear),
    normal (RGB<->X camera space), roughness, metallic, valid}, our gather sampler supersampled
    SUPERSAMPLE x SUPERSAMPLE and averaged like the photo's pixel box; `valid` (H, W, 1) bool:
    pixel fully covered by non-emitting geometry."""

    room: Room
    mesh: object
    sizes: list
    textures: dict
    cameras: list
    photos: list
    irradiance: list
    gt: dict
    emitter_ids: list


def render_linear(seed: int, *, views: int, width: int, height: int, spp: int, max_depth: int = 5,
                  progress: bool = False) -> RoomRender:
    """The room of `seed` rendered in linear light (`RoomRender`); a progress bar with `progress`."""
    room = random_room(seed)
    mesh, sizes = build_scene_geometry(room.objects)
    textures = quantised_textures(room, sizes, seed)
    rng = np.random.default_rng([seed, 15485863])
    cams = place_cameras(room, mesh, rng, views, width, height)
    f = SUPERSAMPLE
    fine = [cameras.Camera(np.diag([f, f, 1.0]) @ c.K, c.c2w, c.width * f, c.height * f) for c in cams]
    frags = fr.compute_fragments(mesh, fine, cache_dir=False, progress=progress)
    stacked = [np.concatenate([textures[k][o] for k in ("albedo", "roughness", "metallic")], -1) for o in range(len(sizes))]
    sampled = sample_pages(stacked, frags, range(len(sizes)))
    normals_world = face_normals(mesh)
    emitter_ids = [k for k, (_, _, m) in enumerate(room.objects) if m.emission]

    scene = mitsuba_scene(room, mesh, textures)
    integrator = mb.load_mitsuba().load_dict(mb.intrinsic_integrator(max_depth))
    photos, irradiance, gt = [], [], {k: [] for k in ("albedo", "normal", "roughness", "metallic", "valid")}
    bar = tqdm(list(zip(cams, frags, sampled)), desc=f"render room {seed} ({spp} spp)", unit="view", disable=not progress)
    for i, (cam, frag, g) in enumerate(bar):
        image = mb.render(scene, cam, spp=spp, seed=seed * 1009 + i, integrator=integrator)
        photos.append(remove_fireflies(image[..., :3]))
        irradiance.append(image[..., mb.IRRADIANCE_CHANNELS])
        n = box_down(camera_normals(normals_world, frag.triangle, cam), f)
        gt["normal"].append(n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6))
        gt["albedo"].append(box_down(g[..., :3], f))
        gt["roughness"].append(box_down(g[..., 3:4], f))
        gt["metallic"].append(box_down(g[..., 4:5], f))
        valid = (frag.object_id >= 0) & ~np.isin(frag.object_id, emitter_ids)
        gt["valid"].append(box_down(valid[..., None].astype(np.float32), f) > 0.999)
    return RoomRender(room=room, mesh=mesh, sizes=sizes, textures=textures, cameras=cams, photos=photos,
                      irradiance=irradiance, gt=gt, emitter_ids=emitter_ids)


def render_room(seed: int, *, views: int, width: int, height: int, spp: int, max_depth: int = 5):
    """(arrays {name: (V, H, W, C) uint8}, metadata) of the room of `seed`."""
    r = render_linear(seed, views=views, width=width, height=height, spp=spp, max_depth=max_depth)
    room, mesh, cams, photos, irradiance, gt, emitter_ids = r.room, r.mesh, r.cameras, r.photos, r.irradiance, r.gt, r.emitter_ids
    masks = [v[..., 0] for v in gt["valid"]]
    stops = exposure.scene_exposure(photos, masks)
    irradiance_stops = exposure.scene_exposure(irradiance, masks)
    scale, irradiance_scale = np.float32(2.0 ** stops), np.float32(2.0 ** irradiance_stops)
    arrays = {
        "photo": np.stack([to_u8(imageio.linear_to_srgb(np.clip(p * scale, 0, 1))) for p in photos]),
        "albedo": np.stack([to_u8(imageio.linear_to_srgb(a)) for a in gt["albedo"]]),
        "normal": np.stack([to_u8(0.5 * (n + 1.0)) for n in gt["normal"]]),
        "roughness": np.stack([to_u8(r) for r in gt["roughness"]]),
        "metallic": np.stack([to_u8(m) for m in gt["metallic"]]),
        "irradiance": np.stack([to_u8(imageio.linear_to_srgb(np.clip(e * irradiance_scale, 0, 1))) for e in irradiance]),
        "valid": np.stack(gt["valid"]).astype(np.uint8),
    }
    meta = {"seed": seed, "room_size": room.size.tolist(), "objects": len(room.objects), "faces": int(mesh.num_faces),
            "exposure_stops": stops, "irradiance_exposure_stops": irradiance_stops, "sun": room.sun_irradiance is not None, "sky": room.sky_radiance is not None,
            "emitters": len(emitter_ids), "spp": spp, "max_depth": max_depth,
            "cameras": [{"K": c.K.tolist(), "c2w": c.c2w.tolist()} for c in cams]}
    return arrays, meta


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=DESCRIPTION)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--split", choices=("train", "heldout"), default="train")
    parser.add_argument("--rooms", type=int, default=400)
    parser.add_argument("--first", type=int, default=0, help="index of the first room (seeds first .. first+rooms-1)")
    parser.add_argument("--views", type=int, default=12, help="views per room")
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=96)
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel (isolated outliers are filtered)")
    parser.add_argument("--max_depth", type=int, default=5, help="path length of the photo and the irradiance's rays")
    parser.add_argument("--variant", choices=("auto", "llvm_ad_rgb", "scalar_rgb"), default="auto")
    args = parser.parse_args(argv)
    for name in ("rooms", "views", "spp", "max_depth"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1")
    if args.width % 8 or args.height % 8:
        parser.error("--width and --height must be multiples of 8 (the VAE's downsampling)")
    try:
        room_seed(args.split, args.first), room_seed(args.split, args.first + args.rooms - 1)
    except ValueError as err:
        parser.error(f"--first/--rooms: {err}")
    mb.load_mitsuba(mb.llvm_variant() if args.variant == "auto" else args.variant)
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = [room_seed(args.split, args.first + i) for i in range(args.rooms)]
    todo = [s for s in seeds if not (args.out / f"room_{s:07d}.npz").exists()]
    print(f"{args.split}: {len(seeds)} rooms x {args.views} views at {args.width}x{args.height}, {args.spp} spp; "
          f"{len(seeds) - len(todo)} already written in {args.out}; Mitsuba {mb.load_mitsuba().variant()}")
    start = time.perf_counter()
    for seed in tqdm(todo, desc="rooms", unit="room"):
        arrays, meta = render_room(seed, views=args.views, width=args.width, height=args.height, spp=args.spp,
                                   max_depth=args.max_depth)
        write_shard(args.out / f"room_{seed:07d}.npz", arrays, meta)
    print(f"wrote {len(todo)} rooms in {(time.perf_counter() - start) / 60:.1f} min")
    return 0
