"""Procedurally varied rooms for training our RGB<->X-family prior: layout, materials, lights.

One seed gives one room (pure NumPy, no rendering): its size, walls with windows and a door,
furniture placed without overlaps, a material per object drawn from a parametric library
(paint, wallpaper, plaster, tiles, wood, fabric, carpet, stone, plastic, metal, paintings),
and lights (sun and sky through the windows, ceiling panels, lamps with emitting bulbs).
`room_render` renders rooms from here (`scripts/make_rgbx_data.py`); the geometry helpers
(`room_geometry`: rectangles packed into one texture page per object) are shared with the
embedded bedroom (`scripts/make_bedroom.py`), the rooms, materials and lights are not, and the
bedroom is never among the training rooms.
"""

from __future__ import annotations

import colorsys
import dataclasses

import numpy as np

from jaxdistill.models.training.room_geometry import Rect, box, legs, rect, wall
from jaxdistill.models.training.textures import grid, mix, smooth_noise, wood


@dataclasses.dataclass
class Material:
    """A parametric material: `kind` and its drawn parameters; `emission` (linear RGB radiance) for emitters."""

    kind: str
    params: dict
    emission: tuple | None = None


@dataclasses.dataclass
class Room:
    """size (x, y, z) metres, y up; objects (name, rects, Material); lights: sun, sky."""

    size: np.ndarray
    objects: list
    sun_direction: np.ndarray | None
    sun_irradiance: tuple | None
    sky_radiance: tuple | None
    furniture: tuple            # names of objects cameras must not sit inside


# ----------------------------------------------------------------------------- materials


def hsv(h, s, v):
    """Linear RGB of an sRGB-space HSV colour (so hues are drawn evenly as people see them)."""
    c = np.array(colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))
    return tuple(np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4))


def colour(rng, saturation=(0.05, 0.6), value=(0.3, 0.95)):
    return hsv(rng.random(), rng.uniform(*saturation), rng.uniform(*value))


def draw_material(rng, family: str) -> Material:
    """A Material of `family` with randomly drawn parameters."""
    r = rng.uniform
    if family == "paint":
        return Material("paint", {"colour": colour(rng, (0.0, 0.45), (0.45, 0.95)), "rough": r(0.5, 0.95)})
    if family == "wallpaper":
        return Material("wallpaper", {"a": colour(rng, (0.05, 0.5), (0.5, 0.9)), "b": colour(rng, (0.1, 0.7), (0.2, 0.7)),
                                      "stripes": int(rng.integers(6, 40)), "motif": r(0.6, 0.95), "rough": r(0.55, 0.9)})
    if family == "tiles":
        return Material("tiles", {"colour": colour(rng, (0.0, 0.6), (0.3, 0.95)), "grout": colour(rng, (0.0, 0.1), (0.2, 0.8)),
                                  "count": int(rng.integers(4, 16)), "rough": r(0.05, 0.4), "jitter": r(0.0, 0.15)})
    if family == "wood":
        light = np.array(hsv(r(0.04, 0.11), r(0.35, 0.75), r(0.35, 0.9)))
        return Material("wood", {"light": tuple(light), "dark": tuple(light * r(0.25, 0.6)), "rings": r(10, 60),
                                 "planks": int(rng.integers(0, 14)), "rough": r(0.2, 0.75)})
    if family == "fabric":
        a = colour(rng, (0.0, 0.8), (0.1, 0.9))
        return Material("fabric", {"a": a, "b": tuple(np.array(a) * r(0.5, 0.9)), "freq": r(30, 120),
                                   "stripes": r() < 0.3, "rough": r(0.8, 1.0)})
    if family == "carpet":
        return Material("carpet", {"a": colour(rng, (0.1, 0.8), (0.1, 0.8)), "b": colour(rng, (0.1, 0.8), (0.3, 0.9)),
                                   "pattern": int(rng.integers(0, 3)), "rough": r(0.85, 1.0)})
    if family == "stone":
        return Material("stone", {"a": colour(rng, (0.0, 0.2), (0.3, 0.95)), "b": colour(rng, (0.0, 0.3), (0.05, 0.6)),
                                  "veins": r(0.5, 3.0), "rough": r(0.1, 0.6)})
    if family == "plastic":
        return Material("plastic", {"colour": colour(rng, (0.2, 1.0), (0.1, 0.95)), "rough": r(0.05, 0.5)})
    if family == "metal":
        tint = hsv(r(0.05, 0.15), r(0.0, 0.6), r(0.6, 0.95))
        return Material("metal", {"colour": tint, "rough": r(0.1, 0.6), "brushed": r() < 0.5})
    if family == "painting":
        return Material("painting", {"colours": [colour(rng, (0.3, 1.0), (0.1, 0.95)) for _ in range(4)],
                                     "scale": r(4, 16), "gilded": r() < 0.5})
    if family == "emitter":
        temp = r(0.0, 1.0)                                   # warm .. cool white
        tint = np.array([1.0, 0.85 + 0.12 * temp, 0.6 + 0.4 * temp])
        return Material("emitter", {}, emission=tuple(tint * r(4.0, 20.0)))
    raise ValueError(f"unknown material family {family!r}")


def material_maps(material: Material, rng, size: int):
    """(albedo (S, S, 3) linear, roughness (S, S), metallic (S, S)) textures of a material."""
    p, kind = material.params, material.kind
    u, v = grid(size)
    n_low = smooth_noise(rng, size, size / 8)
    metal = np.zeros((size, size))
    rough = np.full((size, size), p.get("rough", 0.5)) + 0.04 * n_low
    if kind in ("paint", "plastic"):
        albedo = np.asarray(p["colour"])[None, None] * (1 + 0.04 * n_low + 0.02 * smooth_noise(rng, size, 2.0))[..., None]
    elif kind == "wallpaper":
        stripe = (np.sin(2 * np.pi * u * p["stripes"]) > 0.5).astype(float)
        motif = ((np.sin(2 * np.pi * u * 2 * p["stripes"]) * np.sin(2 * np.pi * v * 1.3 * p["stripes"])) > p["motif"]).astype(float)
        albedo = mix(p["a"], p["b"], np.clip(0.6 * stripe + motif, 0, 1)) * (1 + 0.03 * n_low)[..., None]
        rough = rough - 0.2 * motif
    elif kind == "tiles":
        k = p["count"]
        gu, gv = u * k, v * k
        grout = (np.minimum(np.abs(gu - np.round(gu)), np.abs(gv - np.round(gv))) < 0.04).astype(float)
        cell = (np.floor(gu) * 7 + np.floor(gv) * 13).astype(int) % 17
        shade = 1 + p["jitter"] * (np.random.default_rng(int(rng.integers(1 << 31))).random(17) - 0.5)[cell]
        albedo = mix(p["colour"], p["grout"], grout) * np.where(grout > 0, 1.0, shade)[..., None]
        rough = np.where(grout > 0, 0.9, rough)
    elif kind == "wood":
        albedo, t = wood(rng, size, p["light"], p["dark"], p["rings"])
        if p["planks"]:
            plank = np.floor(u * p["planks"]).astype(int)
            albedo *= (0.85 + 0.3 * np.random.default_rng(int(rng.integers(1 << 31))).random(p["planks"] + 1))[plank][..., None]
            albedo *= np.where(np.abs(u * p["planks"] - np.round(u * p["planks"])) < 0.02, 0.45, 1.0)[..., None]
        rough = rough + 0.15 * t
    elif kind == "fabric":
        f = p["freq"]
        weave = 0.5 + 0.5 * np.sin(2 * np.pi * u * f) * np.sin(2 * np.pi * v * f)
        albedo = mix(p["a"], p["b"], np.clip(weave + 0.2 * n_low, 0, 1))
        if p["stripes"]:
            albedo = np.where((np.sin(2 * np.pi * v * 6) > 0.6)[..., None], albedo * 0.55, albedo)
    elif kind == "carpet":
        d = np.minimum(np.minimum(u, 1 - u), np.minimum(v, 1 - v))
        if p["pattern"] == 0:
            t = np.clip(0.5 + 0.5 * smooth_noise(rng, size, size / 20), 0, 1)
        elif p["pattern"] == 1:
            t = ((np.abs((u * 8) % 1 - 0.5) + np.abs((v * 6) % 1 - 0.5)) < 0.3).astype(float)
        else:
            t = (d < 0.08).astype(float)
        albedo = mix(p["a"], p["b"], t) * (1 + 0.08 * smooth_noise(rng, size, 0.8))[..., None]
    elif kind == "stone":
        veins = np.abs(np.sin(p["veins"] * 6 * (u + 0.4 * smooth_noise(rng, size, size / 6))))
        albedo = mix(p["a"], p["b"], np.clip((0.15 - veins) / 0.15, 0, 1) + 0.05 * n_low)
    elif kind == "metal":
        brushed = smooth_noise(rng, size, 0.6, aspect=12.0) if p["brushed"] else n_low
        albedo = np.asarray(p["colour"])[None, None] * (1 + 0.04 * brushed)[..., None]
        metal = np.ones((size, size))
        rough = p["rough"] + 0.06 * brushed
    elif kind == "painting":
        cols = np.array(p["colours"])
        fields = np.stack([smooth_noise(rng, size, size / p["scale"]) for _ in cols])
        w = np.exp(2.5 * fields)
        albedo = np.einsum("kij,kc->ijc", w / w.sum(0), cols)
        rough = np.full((size, size), 0.6)
        if p["gilded"]:
            frame = np.minimum(np.minimum(u, 1 - u), np.minimum(v, 1 - v)) < 0.08
            albedo[frame] = (0.85, 0.65, 0.3)
            metal, rough = frame.astype(float), np.where(frame, 0.3, rough)
    elif kind == "emitter":
        albedo = np.full((size, size, 3), 0.9)
        rough = np.full((size, size), 0.3)
    else:
        raise ValueError(f"unknown material kind {kind!r}")
    return np.clip(albedo, 0.02, 0.95), np.clip(rough, 0.02, 1.0), np.clip(metal, 0.0, 1.0)


# ----------------------------------------------------------------------------- furniture

FURNITURE_FAMILIES = {
    "frame": ("wood", "wood", "metal", "plastic", "paint"),
    "soft": ("fabric", "fabric", "carpet"),
    "top": ("wood", "stone", "plastic", "wood"),
}


def furniture_piece(kind: str, x0: float, z0: float, w: float, d: float, rng):
    """[(suffix, rects, family)] of one piece standing on the floor over [x0, x0+w] x [z0, z0+d]."""
    x1, z1 = x0 + w, z0 + d
    pick = lambda role: FURNITURE_FAMILIES[role][int(rng.integers(len(FURNITURE_FAMILIES[role])))]  # noqa: E731
    if kind == "table":
        h = rng.uniform(0.45, 0.8)
        return [("", box((x0, h - 0.04, z0), (x1, h, z1)) + legs(x0, x1, z0, z1, h - 0.04, 0.05), pick("top"))]
    if kind == "cabinet":
        h = rng.uniform(0.5, 2.1)
        parts = [("", box((x0, 0.0, z0), (x1, h, z1), skip=("-y",)), pick("frame"))]
        knob = (0.5 * (x0 + x1), 0.6 * h)
        parts.append(("_knob", box((knob[0] - 0.03, knob[1] - 0.02, z0 - 0.03), (knob[0] + 0.03, knob[1] + 0.02, z0),
                                   skip=("+z",)), "metal"))
        return parts
    if kind == "bed":
        frame = box((x0, 0.1, z0), (x1, 0.35, z1), skip=("-y",)) + legs(x0, x1, z0, z1, 0.1, 0.06)
        return [("", frame, pick("frame")),
                ("_mattress", box((x0 + 0.03, 0.35, z0 + 0.03), (x1 - 0.03, 0.55, z1 - 0.03), skip=("-y",)), "fabric"),
                ("_pillow", box((x0 + 0.1, 0.55, z1 - 0.5), (x1 - 0.1, 0.68, z1 - 0.12), skip=("-y",)), "fabric")]
    if kind == "sofa":
        return [("", box((x0, 0.0, z0), (x1, 0.42, z1), skip=("-y",))
                 + box((x0, 0.42, z1 - 0.2), (x1, 0.85, z1), skip=("-y",))
                 + box((x0, 0.42, z0), (x0 + 0.15, 0.62, z1 - 0.2), skip=("-y",))
                 + box((x1 - 0.15, 0.42, z0), (x1, 0.62, z1 - 0.2), skip=("-y",)), pick("soft"))]
    if kind == "shelf":
        h = rng.uniform(1.0, 2.0)
        boards = [r for k in range(int(h / 0.4) + 1)
                  for r in box((x0, k * 0.38, z0), (x1, k * 0.38 + 0.03, z1), skip=("-y",) if k == 0 else ())]
        sides = box((x0 - 0.03, 0.0, z0), (x0, h, z1), skip=("-y",)) + box((x1, 0.0, z0), (x1 + 0.03, h, z1), skip=("-y",))
        return [("", boards + sides, pick("frame"))]
    if kind == "chair":
        h = rng.uniform(0.42, 0.5)
        return [("", box((x0, h, z0), (x1, h + 0.04, z1)) + box((x0, h, z1 - 0.04), (x1, h + 0.5, z1))
                 + legs(x0, x1, z0, z1, h, 0.035), pick("frame"))]
    if kind == "crate":
        h = rng.uniform(0.2, 0.6)
        return [("", box((x0, 0.0, z0), (x1, h, z1), skip=("-y",)), pick("frame"))]
    if kind == "lamp":
        cx, cz, h = 0.5 * (x0 + x1), 0.5 * (z0 + z1), rng.uniform(1.1, 1.7)
        return [("", box((cx - 0.14, 0.0, cz - 0.14), (cx + 0.14, 0.03, cz + 0.14), skip=("-y",))
                 + box((cx - 0.015, 0.03, cz - 0.015), (cx + 0.015, h, cz + 0.015), skip=("-y",)), "metal"),
                ("_shade", box((cx - 0.2, h - 0.1, cz - 0.2), (cx + 0.2, h + 0.18, cz + 0.2), skip=("-y", "+y")), "fabric"),
                ("_bulb", box((cx - 0.05, h - 0.05, cz - 0.05), (cx + 0.05, h + 0.07, cz + 0.05)), "emitter")]
    raise ValueError(kind)


FOOTPRINTS = {"table": ((0.7, 1.8), (0.6, 1.1)), "cabinet": ((0.5, 1.6), (0.35, 0.65)), "bed": ((1.0, 1.8), (1.9, 2.1)),
              "sofa": ((1.4, 2.4), (0.8, 1.0)), "shelf": ((0.6, 1.4), (0.25, 0.4)), "chair": ((0.42, 0.5), (0.42, 0.5)),
              "crate": ((0.3, 0.7), (0.3, 0.7)), "lamp": ((0.4, 0.4), (0.4, 0.4))}
AGAINST_WALL = {"cabinet", "bed", "sofa", "shelf"}


def place_furniture(rng, size, count: int):
    """[(kind, x0, z0, w, d, turned)] without overlaps (0.1 m apart), some against walls."""
    X, _, Z = size
    placed = []
    for _ in range(count * 30):
        if len(placed) >= count:
            break
        kind = list(FOOTPRINTS)[int(rng.integers(len(FOOTPRINTS)))]
        (w0, w1), (d0, d1) = FOOTPRINTS[kind]
        w, d = rng.uniform(w0, w1), rng.uniform(d0, d1)
        if w + 0.2 > X or d + 0.2 > Z:
            continue
        turned = kind in AGAINST_WALL and rng.random() < 0.5
        if kind in AGAINST_WALL:                                # back against z = Z (or z = 0 when turned)
            x0 = rng.uniform(0.05, X - w - 0.05)
            z0 = 0.02 if turned else Z - d - 0.02
        else:
            x0, z0 = rng.uniform(0.1, X - w - 0.1), rng.uniform(0.1, Z - d - 0.1)
        if any(x0 < b[1] + b[3] + 0.1 and b[1] < x0 + w + 0.1 and z0 < b[2] + b[4] + 0.1 and b[2] < z0 + d + 0.1 for b in placed):
            continue
        placed.append((kind, x0, z0, w, d, turned))
    return placed


def flip_z(rects, Z):
    """Rects mirrored through the plane z = Z/2, u reversed so each still faces outwards."""
    out = []
    for r in rects:
        o = np.array([r.origin[0], r.origin[1], Z - r.origin[2]])
        eu, ev = r.edge_u * [1, 1, -1], r.edge_v * [1, 1, -1]
        out.append(Rect(o + eu, -eu, ev, r.uv))     # reflected, then u reversed: winding restored
    return out


# ----------------------------------------------------------------------------- room

UP = np.array([0.0, 1.0, 0.0])


def facing(origin, a, b, normal) -> Rect:
    """The rectangle origin + [0,1] a + [0,1] b with its edges ordered so it faces `normal`."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return rect(origin, a, b) if np.dot(np.cross(a, b), normal) > 0 else rect(origin, b, a)


def random_room(seed: int) -> Room:
    """The room of `seed` (deterministic)."""
    rng = np.random.default_rng([seed, 7919])
    X, Y, Z = rng.uniform(3.0, 6.5), rng.uniform(2.4, 3.2), rng.uniform(3.0, 6.5)
    size = np.array([X, Y, Z])
    objects = []
    add = lambda name, rects, family: objects.append((name, rects, draw_material(rng, family)))  # noqa: E731

    wall_family = lambda: ("paint", "paint", "wallpaper", "tiles", "wood", "stone")[int(rng.integers(6))]  # noqa: E731
    add("floor", [rect((0, 0, Z), (X, 0, 0), (0, 0, -Z), (0, 0, 1, 1))],
        ("wood", "wood", "tiles", "carpet", "stone")[int(rng.integers(5))])
    add("ceiling", [rect((0, Y, 0), (X, 0, 0), (0, 0, Z), (0, 0, 1, 1))], "paint")
    windows = rng.random() < 0.8
    win_wall = int(rng.integers(4))
    walls = [((0, 0, 0), (X, 0, 0), Z), ((X, 0, Z), (-X, 0, 0), X), ((0, 0, Z), (0, 0, -Z), X), ((X, 0, 0), (0, 0, Z), Z)]
    same = wall_family()
    for k, (origin, edge, _) in enumerate(walls):
        length = np.linalg.norm(edge)
        hole = None
        if windows and k == win_wall:
            ww, wh = rng.uniform(0.8, min(2.4, length - 0.6)), rng.uniform(0.9, Y - 1.2)
            a0 = rng.uniform(0.3, length - ww - 0.3) / length
            b0 = rng.uniform(0.7, Y - wh - 0.2) / Y
            hole = (a0, a0 + ww / length, b0, b0 + wh / Y)
        add(f"wall_{k}", wall(origin, edge, (0, Y, 0), hole=hole), same if rng.random() < 0.7 else wall_family())
        if hole is not None:                                    # reveal, so the opening has thickness
            eu = np.asarray(edge, float) / length
            out_ = -np.cross(eu, UP) * 0.15                      # through the wall, outwards
            p0 = np.asarray(origin, float) + hole[0] * np.asarray(edge, float)
            du, lo, hi = (hole[1] - hole[0]) * length * eu, UP * hole[2] * Y, UP * hole[3] * Y
            add(f"window_{k}", [facing(p0 + lo, du, out_, UP), facing(p0 + hi, du, out_, -UP),
                                facing(p0 + lo, hi - lo, out_, eu), facing(p0 + du + lo, hi - lo, out_, -eu)], "paint")
    door_wall = (win_wall + 1 + int(rng.integers(3))) % 4       # never the window's wall
    origin, edge, _ = walls[door_wall]
    length = np.linalg.norm(edge)
    eu = np.asarray(edge, float) / length
    p0 = np.asarray(origin, float) + rng.uniform(0.2, length - 1.1) * eu + np.cross(eu, UP) * 0.005
    add("door", [facing(p0, eu * 0.9, UP * 2.05, np.cross(eu, UP))], ("wood", "paint", "plastic")[int(rng.integers(3))])

    furniture = []
    for k, (kind, x0, z0, w, d, turned) in enumerate(place_furniture(rng, size, int(rng.integers(3, 9)))):
        for suffix, rects, family in furniture_piece(kind, x0, Z - z0 - d if turned else z0, w, d, rng):
            rects = flip_z(rects, Z) if turned else rects
            name = f"{kind}_{k}{suffix}"
            add(name, rects, family)
            furniture.append(name)
    if rng.random() < 0.7:                                      # rug
        w, d = rng.uniform(1.0, X - 0.6), rng.uniform(1.0, Z - 0.6)
        x0, z0 = rng.uniform(0.3, X - w - 0.3 + 1e-6), rng.uniform(0.3, Z - d - 0.3 + 1e-6)
        add("rug", box((x0, 0.0, z0), (x0 + w, 0.01, z0 + d), skip=("-y",)), "carpet")
    for k in range(int(rng.integers(0, 4))):                     # pictures on the z = Z wall, or on x = 0
        w, h = rng.uniform(0.3, 1.2), rng.uniform(0.3, 0.9)
        y0 = rng.uniform(1.0, max(1.05, Y - h - 0.2))
        if k % 2 == 0:
            x0 = rng.uniform(0.2, X - w - 0.2)
            rects = box((x0, y0, Z - 0.03), (x0 + w, y0 + h, Z), skip=("+z",))
        else:
            z0 = rng.uniform(0.2, Z - w - 0.2)
            rects = box((0.0, y0, z0), (0.03, y0 + h, z0 + w), skip=("-x",))
        add(f"picture_{k}", rects, "painting")
    lit = False
    if rng.random() < 0.65 or not windows:                       # ceiling panels
        for k in range(int(rng.integers(1, 3))):
            cx, cz, s = rng.uniform(0.8, X - 0.8), rng.uniform(0.8, Z - 0.8), rng.uniform(0.3, 0.9)
            add(f"ceiling_light_{k}", box((cx - s / 2, Y - 0.04, cz - s / 2), (cx + s / 2, Y - 0.005, cz + s / 2),
                                          skip=("+y",)), "emitter")
            lit = True
    sun_dir = sun_irr = sky = None
    if windows:
        origin, edge, _ = walls[win_wall]
        inward = np.cross(np.asarray(edge, float) / np.linalg.norm(edge), [0.0, 1.0, 0.0])
        tangent = np.asarray(edge, float) / np.linalg.norm(edge)
        d = inward * rng.uniform(0.5, 1.0) + tangent * rng.uniform(-0.8, 0.8) - np.array([0, rng.uniform(0.3, 1.2), 0])
        sun_dir = d / np.linalg.norm(d)
        day = rng.random() < 0.85
        sun_irr = tuple(np.array([1.0, 0.93, 0.82]) * rng.uniform(2.0, 9.0)) if day else None
        sky = tuple(np.array(hsv(rng.uniform(0.55, 0.62), rng.uniform(0.1, 0.5), 1.0)) * rng.uniform(0.2, 1.2))
        lit = True
    if not lit:
        add("ceiling_light_0", box((X / 2 - 0.3, Y - 0.04, Z / 2 - 0.3), (X / 2 + 0.3, Y - 0.005, Z / 2 + 0.3), skip=("+y",)),
            "emitter")
    return Room(size=size, objects=objects, sun_direction=sun_dir, sun_irradiance=sun_irr, sky_radiance=sky,
                furniture=tuple(furniture))
