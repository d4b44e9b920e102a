"""Import a Mitsuba 3 scene as a jaxdistill scene with exact per-view ground truth.

Mitsuba 0.5/0.6 files (root `version` below 2, as Bitterli's Rendering Resources ship them) are
upgraded to Mitsuba 3 first by `jaxdistill.datasets.mitsuba.upgrade`; the changes are logged and the
upgraded XML is written to the output folder as `<stem>.mitsuba3.xml`.

`prepare_scene(xml, out_dir, num_views=..., width=..., height=..., spp=...)` does, in order:

1. **Load** the XML with `mi.load_file(optimize=False)` (optimisation would merge shapes that
   share a BSDF), in the `scalar_rgb` variant. Every shape becomes one object of our Mesh, named
   by its Mitsuba id (`<type>_<index>` when it has none). Meshes (obj, ply, serialized, cube,
   ...) give world-space `vertex_positions`, `faces`, `vertex_texcoords` and `vertex_normals`
   through `mi.traverse`. A `rectangle` is a two-triangle mesh in recent Mitsuba 3 (3.9 here)
   and is read through the shape's own accessors (older versions: built here from `to_world`,
   [-1, 1]^2 in xy, uv = (xy + 1) / 2); `disk`, `sphere` and `cylinder` are tessellated here from
   their `to_world` (unit disk in xy / unit sphere / unit open cylinder z in [0, 1]), and their
   original UVs are evaluated analytically at the hit point with Mitsuba's formulas, so they
   stay exact although the tessellation is not. Shapes whose BSDF is `null` are left out (they
   are invisible in the photos); emitters and glass (`dielectric`, `thindielectric`,
   `roughdielectric`) stay in the geometry, since they occlude, but are masked out of the
   ground truth.
2. **Ground-truth materials** (`twosided` is unwrapped to its front BSDF; `principled`,
   `diffuse`, `plastic`, `roughplastic`, `conductor`, `roughconductor`; `mask`, as for foliage:
   its nested BSDF's maps, and pixels where its opacity is below 0.5 masked): see `material_of`.
   Constants and textures of any Mitsuba type are evaluated by Mitsuba itself
   (`Texture.eval` at the original UV), so bitmaps get Mitsuba's own wrap mode, filter and
   sRGB decoding. Unsupported plugins raise one InputError listing every (shape, plugin).
3. **Reconstruction UVs**: an object keeps its UVs when they lie in [0, 1], are not collapsed
   (faces with zero UV area over > 1 % of its surface) and do not overlap (rasterised at
   256^2: < 2 % of covered texels covered twice); otherwise (and always for the tessellated
   analytic shapes) it is re-unwrapped with xatlas, 2-texel padding, for about a 1024^2 page
   (the rules are those of `jaxdistill.render.unwrap`). Layout "pages": one page per object.
4. **Views**: seeded random eyes inside the bounding box of the unmasked geometry (shrunk by
   5 %), kept when 26 probe rays mostly hit, none is closer than a clearance (1 % of the scene
   diagonal) and they see >= 3 distinct objects (inside a closed object they see only it);
   look-at targets are visible random surface points (area-weighted) with a pitch within
   +-50 deg; a 64-pixel-wide preview must be >= 90 % hits, >= 50 % unmasked, with a median
   depth >= 2 clearances. Views are then chosen greedily for surface coverage: a candidate
   earns the surface area it sees (per face, capped at the face area), halved per earlier view
   that saw that face. Horizontal fov uniform in [60, 75] deg, square pixels, principal point
   off-centre by up to 3 % of the image size.
5. **Ground truth per view** in image space: our rays (`compute_fragments` on the
   reconstruction mesh, the same triangles as Mitsuba's) give triangle id and barycentrics;
   the ORIGINAL texcoords of that triangle are interpolated and the material evaluated there,
   so the maps are exact whatever the new layout.
6. **Irradiance** per view (`render_irradiance`): E / pi at each pixel centre's first hit,
   the radiance a white Lambertian surface would reflect there under the scene's own light
   (original materials everywhere else), `spp` samples, in Mitsuba's `llvm_ad_rgb` variant.
   Written as ground truth (HDR) and, scaled by one scene-wide factor into [0, 1], as targets.
7. **Photos**: Mitsuba path traces each view (the scene's own integrator, `spp` samples,
   seed = seed + view index) through `mitsuba_bridge.render`.

scene.json is complete: every view has targets and ground truth for all five maps and its
mask. Conventions of the files written (also in the `import.json` and README.md written beside
scene.json): photos linear EXR + sRGB PNG; targets/albedo linear RGB EXR; roughness and
metallic single-channel EXR; normal = camera-space unit normal as RGB↔X uses it (x right,
y up, z towards the camera), flipped to face the camera, stored as (n + 1) / 2; albedo,
roughness and metallic are 0 outside the mask; masks/<view>.png is 1 where a ray hits a
surface that is neither an emitter nor glass nor cut out (mask BSDF opacity < 0.5). Roughness
is perceptual: GGX alpha = roughness^2, so roughness = sqrt(alpha) (sqrt of the geometric mean
for anisotropic alpha_u, alpha_v).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from jaxdistill.io import exposure as exposure_rule
from jaxdistill.io import images as imageio
from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.scene.cameras import Camera, look_at, rgbx_camera_normals
from jaxdistill.errors import InputError, ProblemList
from jaxdistill.datasets.mitsuba.upgrade import needs_upgrade, upgrade
from jaxdistill.render import fragments as fr
from jaxdistill.scene.model import Mesh, Scene, View, read_scene, write_scene
from jaxdistill.render.unwrap import UVDecision, unwrap_object, uv_problem

log = logging.getLogger(__name__)

IMPORT_FORMAT = "jaxdistill-mitsuba-import"
IMPORT_VERSION = 2
IMPORT_FILE = "import.json"      # not gt.json: that name is per-object GT textures (evaluation.GT_FORMAT)
# Mitsuba class name -> plugin name (as written in the XML), for the plugins we recognise.
BSDF_PLUGINS = {
    "SmoothDiffuse": "diffuse", "SmoothPlastic": "plastic", "RoughPlastic": "roughplastic",
    "SmoothConductor": "conductor", "RoughConductor": "roughconductor", "Principled": "principled",
    "PrincipledThin": "principledthin", "SmoothDielectric": "dielectric",
    "ThinDielectric": "thindielectric", "RoughDielectric": "roughdielectric",
    "TwoSidedBRDF": "twosided", "BlendBSDF": "blendbsdf", "MaskBSDF": "mask", "BumpMap": "bumpmap",
    "NormalMap": "normalmap", "Measured": "measured", "MeasuredPolarized": "measured_polarized",
    "Hair": "hair", "Null": "null", "PolarizedPlastic": "pplastic", "LinearPolarizer": "polarizer",
    "LinearRetarder": "retarder", "CircularPolarizer": "circular",
}
SUPPORTED_BSDFS = ("diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "principled",
                   "principledthin", "mask")
CUTOUT_OPACITY = 0.5     # mask BSDF: pixels whose opacity is below this are masked (out of loss and metrics)
MASKED_BSDFS = ("dielectric", "thindielectric", "roughdielectric")
DROPPED_BSDFS = ("null",)
SHAPE_PLUGINS = {"OBJMesh": "obj", "PLYMesh": "ply", "SerializedMesh": "serialized", "Mesh": "mesh",
                 "Cube": "cube", "Rectangle": "rectangle", "Disk": "disk", "Sphere": "sphere",
                 "Cylinder": "cylinder"}
ANALYTIC_SHAPES = ("disk", "sphere", "cylinder")
TESSELLATION_SEGMENTS = 64

FOV_RANGE = (60.0, 75.0)
PRINCIPAL_OFFSET = 0.03
PREVIEW_WIDTH = 64
MAX_PITCH_DEG = 50.0


# ----------------------------------------------------------------------------- materials


@dataclasses.dataclass(frozen=True, eq=False)
class Field:
    """A ground-truth parameter: `combine` of inputs, each a constant (C,) or a Mitsuba texture.

    inputs: tuple of (value, channels) where value is an np.ndarray (constant) or a
    `mi.Texture`; combine maps the evaluated inputs, each (N, C_i), to (N, channels).
    """

    inputs: tuple
    combine: Callable
    channels: int

    @property
    def constant(self) -> np.ndarray | None:
        """The (channels,) value when no input varies over the surface, else None."""
        if any(not isinstance(value, np.ndarray) for value, _ in self.inputs):
            return None
        return np.asarray(self.combine(*[value[None] for value, _ in self.inputs]), np.float64)[0]

    def evaluate(self, uv: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N, channels) float64 values at Mitsuba texture coordinates uv (N, 2), world points (N, 3)."""
        n = len(uv)
        evaluated = []
        for value, channels in self.inputs:
            if isinstance(value, np.ndarray):
                evaluated.append(np.broadcast_to(value, (n, channels)))
            else:
                evaluated.append(_eval_texture(value, channels, uv, points))
        return np.asarray(self.combine(*evaluated), np.float64).reshape(n, self.channels)


def _eval_texture(texture, channels: int, uv: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, channels) values of a spatially varying Mitsuba texture, one scalar eval per point."""
    mi = mb.load_mitsuba()
    out = np.empty((len(uv), channels), np.float64)
    si = mi.SurfaceInteraction3f()
    for i in range(len(uv)):
        si.uv = mi.Point2f(float(uv[i, 0]), float(uv[i, 1]))
        si.p = mi.Point3f(float(points[i, 0]), float(points[i, 1]), float(points[i, 2]))
        if channels == 1:
            out[i, 0] = texture.eval_1(si)
        else:
            c = texture.eval(si)
            out[i] = (c[0], c[1], c[2])
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class GTMaterial:
    """Ground truth of one BSDF: plugin name, whether it is masked (glass), and its fields.

    opacity: the `mask` BSDF's opacity (1 channel), None without one; where it is below
    CUTOUT_OPACITY the pixel is masked out of loss and metrics (the photo shows what is behind).
    """

    plugin: str
    masked: bool
    albedo: Field | None = None
    roughness: Field | None = None
    metallic: Field | None = None
    opacity: Field | None = None

    def describe(self) -> dict:
        """JSON summary: constants as lists, varying fields as "texture"."""
        out = {"bsdf": self.plugin}
        for name in ("albedo", "roughness", "metallic", "opacity"):
            field = getattr(self, name)
            if field is not None:
                const = field.constant
                out[name] = "texture" if const is None else [round(float(x), 6) for x in const]
        return out


class _Children:
    """Collects the direct child objects and value names of a Mitsuba object (one traverse level)."""

    def __init__(self, obj):
        mi = mb.load_mitsuba()
        collector = self

        class Callback(mi.TraversalCallback):
            def put(self, name, value, flags, cpptype=None):
                if isinstance(value, mi.Object):
                    collector.objects[name] = value
                else:
                    collector.values.add(name)

            def put_object(self, name, value, flags):
                collector.objects[name] = value

            def put_value(self, name, value, flags, cpptype=None):
                collector.values.add(name)

        self.objects: dict = {}
        self.values: set = set()
        obj.traverse(Callback())


def _plugin_name(obj) -> str:
    """The XML plugin name of a Mitsuba BSDF/shape object (its class name when unknown)."""
    name = obj.class_name()
    return BSDF_PLUGINS.get(name, SHAPE_PLUGINS.get(name, name))


def _unwrap_twosided(bsdf):
    """The front BSDF of a (possibly nested) `twosided`, else `bsdf` itself."""
    while _plugin_name(bsdf) == "twosided":
        children = _Children(bsdf).objects
        front = children.get("brdf_0")
        if front is None:
            break
        back = children.get("brdf_1")
        if back is not None and back is not front:
            log.warning("twosided BSDF %r has different front and back BSDFs: the front one is used",
                        bsdf.id())
        bsdf = front
    return bsdf


def _input(bsdf, name: str, channels: int, default=None):
    """(value, channels) of attribute `name`: a constant array, or the Mitsuba texture if it varies."""
    mi = mb.load_mitsuba()
    child = _Children(bsdf).objects.get(name)
    si = mi.SurfaceInteraction3f()
    if child is not None and isinstance(child, mi.Texture):
        if child.is_spatially_varying():
            return child, channels
        value = [child.eval_1(si)] if channels == 1 else list(child.eval(si))
        return np.asarray(value, np.float64).reshape(channels), channels
    if bsdf.has_attribute(name):
        value = [bsdf.eval_attribute_1(name, si)] if channels == 1 else list(bsdf.eval_attribute(name, si))
        return np.asarray(value, np.float64).reshape(channels), channels
    if default is None:
        raise KeyError(name)
    return np.asarray(default, np.float64).reshape(channels), channels


def _const(value, channels: int = 1) -> Field:
    return Field(((np.full(channels, float(value)), channels),), lambda x: x, channels)


def _conductor_f0(eta: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Fresnel reflectance at normal incidence of a conductor with complex IOR eta + i k."""
    return ((eta - 1.0) ** 2 + k ** 2) / ((eta + 1.0) ** 2 + k ** 2)


def _alpha_roughness(bsdf) -> Field:
    """roughness = sqrt(alpha) (GGX alpha = roughness^2); sqrt of sqrt(alpha_u alpha_v) if anisotropic."""
    children = _Children(bsdf)
    if "alpha_u" in children.objects or "alpha_u" in children.values:
        au, av = _input(bsdf, "alpha_u", 1), _input(bsdf, "alpha_v", 1)
        return Field((au, av), lambda a, b: np.sqrt(np.sqrt(np.clip(a * b, 0.0, None))), 1)
    return Field((_input(bsdf, "alpha", 1),), lambda a: np.sqrt(np.clip(a, 0.0, None)), 1)


def material_of(bsdf) -> GTMaterial:
    """GTMaterial of a loaded Mitsuba BSDF; ValueError naming the plugin when unsupported.

    diffuse: albedo = reflectance, roughness 1, metallic 0. plastic: diffuse_reflectance,
    roughness 0, metallic 0. roughplastic: diffuse_reflectance, sqrt(alpha), 0. principled(thin):
    base_color, roughness, metallic. conductor: albedo = specular_reflectance x F0(eta, k)
    (Fresnel reflectance at normal incidence), roughness 0, metallic 1; roughconductor: the same
    with sqrt(alpha). dielectrics: masked. mask: the nested BSDF's ground truth, with its opacity.
    """
    inner = _unwrap_twosided(bsdf)
    plugin = _plugin_name(inner)
    if plugin == "mask":
        material = material_of(_Children(inner).objects["nested_bsdf"])   # Mitsuba requires one
        return dataclasses.replace(material, plugin=f"mask({material.plugin})",
                                   opacity=Field((_input(inner, "opacity", 1),), lambda x: x, 1))
    if plugin in MASKED_BSDFS:
        return GTMaterial(plugin, True)
    if plugin not in SUPPORTED_BSDFS:
        raise ValueError(plugin)
    identity = lambda x: x  # noqa: E731
    if plugin == "diffuse":
        albedo = Field((_input(inner, "reflectance", 3),), identity, 3)
        return GTMaterial(plugin, False, albedo, _const(1.0), _const(0.0))
    if plugin in ("plastic", "roughplastic"):
        albedo = Field((_input(inner, "diffuse_reflectance", 3),), identity, 3)
        rough = _const(0.0) if plugin == "plastic" else _alpha_roughness(inner)
        return GTMaterial(plugin, False, albedo, rough, _const(0.0))
    if plugin in ("principled", "principledthin"):
        return GTMaterial(plugin, False, Field((_input(inner, "base_color", 3),), identity, 3),
                          Field((_input(inner, "roughness", 1),), identity, 1),
                          Field((_input(inner, "metallic", 1, default=0.0),), identity, 1))
    # conductor / roughconductor
    albedo = Field((_input(inner, "specular_reflectance", 3, default=[1.0] * 3), _input(inner, "eta", 3),
                    _input(inner, "k", 3)), lambda s, e, k: s * _conductor_f0(e, k), 3)
    rough = _const(0.0) if plugin == "conductor" else _alpha_roughness(inner)
    return GTMaterial(plugin, False, albedo, rough, _const(1.0))


# ----------------------------------------------------------------------------- shapes


@dataclasses.dataclass(eq=False)
class SourceObject:
    """One Mitsuba shape as triangles in world space, with what its ground truth needs.

    texcoords (Nv, 2) are Mitsuba's (as its textures see them) or None (Mitsuba then uses the
    barycentrics b1, b2); normals (Nv, 3) are shading normals or None (face normals);
    uv_function maps world points (N, 3) to Mitsuba's exact UV for analytic shapes.
    """

    name: str
    shape: str
    vertices: np.ndarray
    faces: np.ndarray
    texcoords: np.ndarray | None
    normals: np.ndarray | None
    emitter: bool
    material: GTMaterial | None
    uv_function: Callable | None = None

    @property
    def masked(self) -> bool:
        return self.emitter or self.material is None or self.material.masked


def _array(params, key, width):
    if key not in params.keys():
        return None
    a = np.array(params[key], np.float64).reshape(-1, width)
    return a if len(a) else None


def _transform_points(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def _tessellate(kind: str, to_world: np.ndarray):
    """(vertices, faces, texcoords, normals, uv_function) of a rectangle, disk, sphere or cylinder."""
    s = TESSELLATION_SEGMENTS
    phi = 2.0 * np.pi * np.arange(s) / s
    inv = np.linalg.inv(to_world)
    normal_m = np.linalg.inv(to_world[:3, :3]).T

    def angle(x, y):
        return np.mod(np.arctan2(y, x), 2.0 * np.pi) / (2.0 * np.pi)

    if kind == "rectangle":
        local = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
        faces = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
        vertices = _transform_points(to_world, local)
        return vertices, faces, 0.5 * (local[:, :2] + 1.0), None, None  # affine uv: interpolation is exact
    if kind == "disk":
        local = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.cos(phi), np.sin(phi), np.zeros(s)], 1)])
        faces = np.stack([np.zeros(s, np.int64), 1 + np.arange(s), 1 + (np.arange(s) + 1) % s], 1)
        normals = np.tile([0.0, 0.0, 1.0], (len(local), 1))

        def uv_function(p):
            q = _transform_points(inv, p)
            return np.stack([np.hypot(q[:, 0], q[:, 1]), angle(q[:, 0], q[:, 1])], 1)
    elif kind == "sphere":
        import trimesh
        ico = trimesh.creation.icosphere(subdivisions=3)
        local, faces = np.asarray(ico.vertices, np.float64), np.asarray(ico.faces, np.int64)
        normals = local.copy()

        def uv_function(p):
            q = _transform_points(inv, p)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            return np.stack([angle(q[:, 0], q[:, 1]), np.arccos(np.clip(q[:, 2], -1, 1)) / np.pi], 1)
    else:  # cylinder: radius 1, z in [0, 1], open
        ring = np.stack([np.cos(phi), np.sin(phi), np.zeros(s)], 1)
        local = np.concatenate([ring, ring + [0.0, 0.0, 1.0]])
        i = np.arange(s)
        j = (i + 1) % s
        faces = np.concatenate([np.stack([i, j, j + s], 1), np.stack([i, j + s, i + s], 1)])
        normals = np.concatenate([ring, ring])

        def uv_function(p):
            q = _transform_points(inv, p)
            return np.stack([angle(q[:, 0], q[:, 1]), q[:, 2]], 1)
    vertices = _transform_points(to_world, local)
    normals = normals @ normal_m.T
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    texcoords = uv_function(vertices)
    return vertices, faces, texcoords, normals, uv_function


def _shape_geometry(shape, plugin: str):
    """(vertices, faces, texcoords, normals, uv_function) in world space, or None if unsupported."""
    mi = mb.load_mitsuba()
    params = mi.traverse(shape)
    if shape.is_mesh() and "vertex_positions" in params.keys():
        vertices = _array(params, "vertex_positions", 3)
        faces = np.array(params["faces"], np.int64).reshape(-1, 3)
        texcoords = _array(params, "vertex_texcoords", 2)
        normals = _array(params, "vertex_normals", 3)
        return vertices, faces, texcoords, normals, None
    if shape.is_mesh():  # rectangle (a two-triangle mesh in Mitsuba 3.6+) and other built-in meshes
        nv, nf = shape.vertex_count(), shape.face_count()
        vertices = np.array([list(shape.vertex_position(i)) for i in range(nv)], np.float64)
        faces = np.array([list(shape.face_indices(i)) for i in range(nf)], np.int64)
        texcoords = (np.array([list(shape.vertex_texcoord(i)) for i in range(nv)], np.float64)
                     if shape.has_vertex_texcoords() else None)
        return vertices, faces, texcoords, None, None
    if plugin in ANALYTIC_SHAPES or plugin == "rectangle":
        return _tessellate(plugin, np.array(params["to_world"].matrix, np.float64))
    return None


@dataclasses.dataclass(eq=False)
class MitsubaSource:
    """A loaded Mitsuba scene: the scene object, one SourceObject per kept shape, the up vector."""

    path: Path
    scene: object
    objects: list[SourceObject]
    up: np.ndarray
    dropped: list[str]
    integrator: str
    upgrade_changes: tuple[str, ...] = ()      # what the Mitsuba 0.x -> 3 upgrade changed (empty: none)
    xml_text: str | None = None                # the upgraded XML of a Mitsuba 0.x file (None: load `path`)


def _check_files(xml_path: Path, problems: ProblemList) -> None:
    """Adds a problem for every `filename` the XML names that does not exist (relative to it)."""
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError:
        return  # Mitsuba reports the syntax error with its position
    parents = {child: parent for parent in root.iter() for child in parent}
    for element in root.iter("string"):
        if element.get("name") != "filename":
            continue
        value = element.get("value", "")
        if "$" in value:
            continue
        path = Path(value) if Path(value).is_absolute() else xml_path.parent / value
        if not path.is_file():
            parent = parents.get(element)
            where = "?" if parent is None else (f"<{parent.tag} type={parent.get('type')!r}"
                                                 + (f" id={parent.get('id')!r}" if parent.get("id") else "") + ">")
            problems.add(xml_path, f"{where}.filename", f"file not found: {path}")


def _load_upgraded(xml_path: Path, upgraded_dir):
    """(text, changes, written path) of a Mitsuba 0.5/0.6 file upgraded to Mitsuba 3 (text None
    for a Mitsuba 2/3 file); changes logged and, when upgraded_dir is given, the text written
    there as <stem>.mitsuba3.xml."""
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError:
        return None, (), None      # Mitsuba reports the syntax error with its position
    if not needs_upgrade(root):
        return None, (), None
    result = upgrade(root, source=os.fspath(xml_path), base_dir=xml_path.parent.resolve())
    text = result.to_string()
    log.info("%s is Mitsuba %s XML: upgraded to Mitsuba 3 with %d changes", xml_path, result.source_version,
             len(result.changes))
    for change in result.changes:
        (log.warning if change.warning else log.info)("upgrade: %s: %s", change.where, change.what)
    target = None
    if upgraded_dir is not None:
        target = Path(upgraded_dir) / f"{xml_path.stem}.mitsuba3.xml"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
        log.info("upgraded XML written to %s", target)
    return text, result.changes, target


def load_source(xml_path, *, up=None, upgraded_dir=None) -> MitsubaSource:
    """Loads a Mitsuba scene XML into SourceObjects; InputError for every problem found.

    A Mitsuba 0.5/0.6 file (root version < 2) is upgraded first (`jaxdistill.datasets.mitsuba.upgrade`):
    the changes are logged, kept in `MitsubaSource.upgrade_changes`, and the upgraded XML is
    written to `upgraded_dir` (when given) for inspection.
    """
    mi = mb.load_mitsuba()
    xml_path = Path(xml_path)
    if not xml_path.is_file():
        raise InputError.single(xml_path, "--mitsuba", "scene file not found")
    problems = ProblemList()
    _check_files(xml_path, problems)
    problems.raise_if_any()
    upgraded, changes, upgraded_path = _load_upgraded(xml_path, upgraded_dir)
    try:
        if upgraded is None:
            scene = mi.load_file(os.fspath(xml_path), optimize=False)
        else:
            scene = mi.load_string(upgraded, optimize=False)
    except Exception as err:  # Mitsuba raises RuntimeError with its parser's message
        message = re.sub(r"^\[[\w.]+:\d+\]\s*", "", str(err)).strip()
        if upgraded is None:
            raise InputError.single(xml_path, "(load)", f"Mitsuba cannot load it: {message}") from err
        where = f"; line numbers refer to the upgraded XML {upgraded_path}" if upgraded_path else ""
        raise InputError.single(xml_path, "(load)", f"Mitsuba 3 cannot load it after the upgrade from Mitsuba 0.x: "
                                f"{message}{where}; fix or remove that element in the source file") from err
    if not isinstance(scene, mi.Scene):
        raise InputError.single(xml_path, "(root)", f"not a Mitsuba scene: the root element is a "
                                f"{scene.class_name()} (expected <scene version=...>)")
    shapes = list(scene.shapes())
    if not shapes:
        raise InputError.single(xml_path, "shapes", "the scene has no shapes")

    objects, dropped, names = [], [], set()
    for index, shape in enumerate(shapes):
        plugin = _plugin_name(shape)
        name = shape.id() or f"{plugin}_{index:03d}"
        while name in names:
            name += "_"
        names.add(name)
        if shape.is_sensor():
            dropped.append(f"{name} (sensor)")
            continue
        geometry = _shape_geometry(shape, plugin)
        if geometry is None:
            problems.add(xml_path, f"shape {name!r}", f"unsupported shape plugin {plugin!r}; supported: "
                         "meshes (obj, ply, serialized, cube, ...), rectangle, disk, sphere, cylinder")
            continue
        vertices, faces, texcoords, normals, uv_function = geometry
        if len(faces) == 0:
            dropped.append(f"{name} (no faces)")
            continue
        emitter = bool(shape.is_emitter())
        bsdf = shape.bsdf()
        inner_plugin = _plugin_name(_unwrap_twosided(bsdf)) if bsdf is not None else "none"
        if inner_plugin in DROPPED_BSDFS and not emitter:
            dropped.append(f"{name} (null BSDF: invisible)")
            continue
        material = None
        if not emitter:  # an emitter is masked: its BSDF does not matter
            try:
                material = material_of(bsdf)
            except KeyError as err:
                problems.add(xml_path, f"shape {name!r} bsdf", f"{inner_plugin} BSDF has no attribute {err}")
                continue
            except ValueError as err:
                problems.add(xml_path, f"shape {name!r} bsdf", f"unsupported BSDF plugin {str(err)!r}; supported: "
                             f"{', '.join(SUPPORTED_BSDFS + MASKED_BSDFS)} (inside twosided or not)")
                continue
        objects.append(SourceObject(name=name, shape=plugin, vertices=vertices, faces=faces, texcoords=texcoords,
                                    normals=normals, emitter=emitter, material=material, uv_function=uv_function))
    problems.raise_if_any()
    if not objects:
        raise InputError.single(xml_path, "shapes", "no shape with triangles is left")
    if up is None:
        sensors = list(scene.sensors())
        if sensors:
            m = np.array(sensors[0].world_transform().matrix, np.float64)
            up = m[:3, :3] @ [0.0, 1.0, 0.0]
        else:
            up = np.array([0.0, 1.0, 0.0])
    up = np.asarray(up, np.float64)
    integrator = scene.integrator()
    return MitsubaSource(path=xml_path, scene=scene, objects=objects, up=up / np.linalg.norm(up), dropped=dropped,
                         integrator=integrator.class_name() if integrator is not None else "default",
                         upgrade_changes=tuple(str(c) for c in changes), xml_text=upgraded)


# ----------------------------------------------------------------------------- UV layout


def reconstruction_mesh(objects: Sequence[SourceObject], *, progress: bool = False, cache_dir=False,
                        source_file: str = "mitsuba scene") -> tuple[Mesh, list[UVDecision]]:
    """Our Mesh (same triangles, in order) with UVs in [0, 1] per object, and the UV decisions.

    Objects are checked with `unwrap.uv_problem` and re-unwrapped with `unwrap.unwrap_object`
    (no cameras yet: about a DEFAULT_RESOLUTION page each; cache_dir as there, off by default);
    an object too large to unwrap is an InputError naming `source_file`.
    """
    vertices, faces, uvs, face_object, decisions = [], [], [], [], []
    offset = 0
    for object_id, obj in enumerate(tqdm(objects, desc="uv layout", unit="object", disable=not progress)):
        start = time.perf_counter()
        result = None
        if obj.uv_function is not None:
            reason = f"analytic {obj.shape} (tessellated)"
        elif obj.texcoords is None:
            reason = "no texture coordinates"
        else:
            ours = obj.texcoords[obj.faces].copy()
            ours[..., 1] = 1.0 - ours[..., 1]        # Mitsuba (v down) -> ours (v up)
            reason = uv_problem(ours, obj.vertices[obj.faces])
        if reason is None:
            uv = ours
        else:
            result = unwrap_object(obj.vertices, obj.faces, name=obj.name, cache_dir=cache_dir, progress=progress,
                                   mesh_file=source_file)
            uv = result.uv
            reason += f"; {result.note}" if result.note else ""
        decisions.append(UVDecision(obj.name, reason is not None, reason or "kept", time.perf_counter() - start,
                                    page_size=result.page_size if result else None,
                                    texels_per_unit=result.texels_per_unit if result else None,
                                    cached=bool(result and result.cached), faces=len(obj.faces)))
        vertices.append(obj.vertices)
        faces.append(obj.faces + offset)
        uvs.append(uv)
        face_object.append(np.full(len(obj.faces), object_id, np.int32))
        offset += len(obj.vertices)
    mesh = Mesh(vertices=np.concatenate(vertices), faces=np.concatenate(faces).astype(np.int64),
                uv=np.concatenate(uvs), face_object=np.concatenate(face_object),
                object_names=tuple(o.name for o in objects))
    return mesh, decisions


# ----------------------------------------------------------------------------- view placement


def _probe_directions() -> np.ndarray:
    """(26, 3) unit directions: the faces, edges and corners of a cube."""
    d = np.array([(x, y, z) for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1) if (x, y, z) != (0, 0, 0)],
                 np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _intrinsics(fov_deg: float, offset: np.ndarray, width: int, height: int) -> np.ndarray:
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, width * (0.5 + offset[0])], [0.0, f, height * (0.5 + offset[1])], [0.0, 0.0, 1.0]])


@dataclasses.dataclass(frozen=True)
class _Candidate:
    eye: np.ndarray
    target: np.ndarray
    fov: float
    offset: np.ndarray
    seen: np.ndarray      # (F,) surface area seen per face (capped at the face area)


def place_views(mesh: Mesh, masked_face: np.ndarray, num_views: int, width: int, height: int, *, up: np.ndarray,
                seed: int = 0, progress: bool = False) -> tuple[list[Camera], dict]:
    """`num_views` cameras inside the scene chosen for surface coverage; (cameras, statistics)."""
    rng = np.random.default_rng(seed)
    caster = fr.RayCaster(mesh)
    tri = mesh.triangles()
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    face_area = 0.5 * np.linalg.norm(cross, axis=1)
    face_normal = cross / np.maximum(2.0 * face_area, 1e-300)[:, None]
    solid = ~masked_face & (face_area > 0)
    if not solid.any():
        raise InputError.single("scene", "shapes", "every surface is an emitter or glass: nothing to view")
    pts = tri[solid].reshape(-1, 3)
    lo, hi = pts.min(0), pts.max(0)
    extent = hi - lo
    diagonal = float(np.linalg.norm(extent))
    clearance = 0.01 * diagonal
    box_lo, box_hi = lo + 0.05 * extent, hi - 0.05 * extent
    probes = _probe_directions()
    target_p = np.where(solid, face_area, 0.0)
    target_p /= target_p.sum()
    max_pitch = math.sin(math.radians(MAX_PITCH_DEG))
    pw = PREVIEW_WIDTH
    ph = max(1, round(pw * height / width))
    pool = max(6 * num_views, 24)
    candidates: list[_Candidate] = []
    eyes_tried = eyes_ok = 0
    bar = tqdm(total=pool, desc="view candidates", unit="view", disable=not progress)
    for _ in range(200):                                  # batches of eyes
        if len(candidates) >= pool:
            break
        eyes = rng.uniform(box_lo, box_hi, (128, 3))
        eyes_tried += len(eyes)
        o = np.repeat(eyes, len(probes), axis=0)
        d = np.tile(probes, (len(eyes), 1))
        hit_tri, _, dist = caster.intersect(o, d)
        hit_tri, dist = hit_tri.reshape(len(eyes), -1), dist.reshape(len(eyes), -1)
        for e in range(len(eyes)):
            hits = hit_tri[e] >= 0
            if hits.mean() < 0.9 or dist[e][hits].min() < clearance:
                continue
            if len(np.unique(mesh.face_object[hit_tri[e][hits]])) < min(3, len(mesh.object_names)):
                continue
            eyes_ok += 1
            candidate = _try_eye(eyes[e], rng, caster, mesh, tri, face_area, face_normal, masked_face, target_p, up,
                                 clearance, max_pitch, pw, ph)
            if candidate is not None:
                candidates.append(candidate)
                bar.update(1)
                if len(candidates) >= pool:
                    break
    bar.close()
    if len(candidates) < num_views:
        raise InputError.single("scene", "--views", f"found only {len(candidates)} acceptable viewpoints "
                                f"({eyes_ok} of {eyes_tried} random eyes had clearance); ask for fewer views or "
                                "check that the scene is an enclosed interior with its up axis given (--up)")
    # Greedy coverage: gain = seen area, halved per earlier view that saw the face.
    seen = np.stack([c.seen for c in candidates])          # (C, F)
    looks = np.zeros(len(face_area))
    chosen = []
    for _ in range(num_views):
        gains = seen @ (0.5 ** looks)
        gains[chosen] = -1.0
        best = int(np.argmax(gains))
        chosen.append(best)
        looks += np.minimum(1.0, seen[best] / np.maximum(face_area, 1e-300))
    cams = []
    for i in chosen:
        c = candidates[i]
        cams.append(look_at(c.eye, c.target, up, _intrinsics(c.fov, c.offset, width, height), width, height))
    seen_any = (seen[chosen] > 0).any(axis=0)
    stats = {"candidates": len(candidates), "eyes_tried": eyes_tried, "eyes_with_clearance": eyes_ok,
             "clearance": clearance, "scene_diagonal": diagonal,
             "unmasked_area_seen_fraction": float(face_area[seen_any & solid].sum() / face_area[solid].sum())}
    return cams, stats


def _try_eye(eye, rng, caster, mesh, tri, face_area, face_normal, masked_face, target_p, up, clearance, max_pitch,
             pw, ph) -> _Candidate | None:
    """A candidate view from `eye` at a visible random surface point, or None (3 target tries)."""
    for _ in range(3):
        f = rng.choice(len(face_area), p=target_p)
        r1, r2 = rng.random(2)
        s = math.sqrt(r1)
        target = (1 - s) * tri[f, 0] + s * (1 - r2) * tri[f, 1] + s * r2 * tri[f, 2]
        to = target - eye
        dist = float(np.linalg.norm(to))
        if dist < 2 * clearance or abs(to @ up) / dist > max_pitch:
            continue
        hit, _, hit_dist = caster.intersect(eye[None], (to / dist)[None])
        if hit[0] < 0 or hit_dist[0] < 0.98 * dist:
            continue
        fov = float(rng.uniform(*FOV_RANGE))
        offset = rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET, 2)
        cam = look_at(eye, target, up, _intrinsics(fov, offset, pw, ph), pw, ph)
        o, d = cam.pixel_rays()
        t, _, t_dist = caster.intersect(o, d)
        hits = t >= 0
        if hits.mean() < 0.9 or (hits & ~masked_face[np.maximum(t, 0)]).mean() < 0.5:
            continue
        depth = t_dist[hits] * (d[hits] @ cam.c2w[:3, 2])
        if np.median(depth) < 2 * clearance:
            continue
        # Surface area per pixel: dist^2 * (pixel solid angle) / |cos(incidence)|.
        cos_axis = d[hits] @ cam.c2w[:3, 2]
        solid_angle = cos_axis ** 3 / (cam.K[0, 0] * cam.K[1, 1])
        cos_in = np.maximum(np.abs(np.einsum("nc,nc->n", face_normal[t[hits]], d[hits])), 0.2)
        footprint = t_dist[hits] ** 2 * solid_angle / cos_in
        valid = ~masked_face[t[hits]]
        seen = np.bincount(t[hits][valid], weights=footprint[valid], minlength=len(face_area))
        return _Candidate(eye=eye, target=target, fov=fov, offset=offset, seen=np.minimum(seen, face_area))
    return None


# ----------------------------------------------------------------------------- ground truth


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


# ----------------------------------------------------------------------------- irradiance


IRRADIANCE_VARIANT = "llvm_ad_rgb"
IRRADIANCE_TARGET_PERCENTILE = 99.0     # targets: scene-wide scale putting this percentile at 0.9


def render_irradiance(xml_path, cameras: Sequence[Camera], *, spp: int, seed: int = 0,
                      xml_text: str | None = None) -> list[np.ndarray]:
    """Per view (H, W, 3) float32 diffuse irradiance E / pi at each pixel centre's first hit (0 on misses).

    E / pi is the radiance a white Lambertian surface would reflect there (so a diffuse pixel is
    albedo x irradiance): the cosine-weighted mean of the incident radiance of the ORIGINAL scene
    over the hemisphere of the shading normal turned towards the camera. Only the first hit is
    white; light arriving there keeps every original material, emitter and interreflection. (A
    render of the scene with all materials white would not: its interreflections are brighter.)
    Estimator per sample: emitter sampling and a cosine-sampled direction combined by MIS (balance
    heuristic); beyond the first bounce Mitsuba's `path` integrator, one bounce shorter than the
    scene integrator's max_depth (so E / pi x albedo is what the photos show on diffuse surfaces).
    Runs in Mitsuba's vectorised `llvm_ad_rgb` variant (one wavefront per view and sample), then
    switches back. The scene is loaded again in that variant from `xml_text` when given (an
    upgraded Mitsuba 0.x file, with absolute file names), else from `xml_path`.
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
        for v, cam in enumerate(cameras):
            origins, directions = cam.pixel_rays()
            total = np.zeros((len(origins), 3))
            for s in range(spp):
                sampler.seed(dr.opaque(mi.UInt32, ((seed * 7919 + v) * 65537 + s) % 2 ** 32), len(origins))
                total += _irradiance_sample(mi, dr, scene, nested, sampler, origins, directions)
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


# ----------------------------------------------------------------------------- the whole import


def _check_arguments(xml_path, num_views, width, height, spp) -> None:
    """InputError listing every bad argument (and a missing scene file) at once."""
    problems = ProblemList()
    if not Path(xml_path).is_file():
        problems.add(xml_path, "--mitsuba", "scene file not found")
    for flag, value, low in (("--views", num_views, 1), ("--width", width, 4), ("--height", height, 4),
                             ("--spp", spp, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            problems.add("command line", flag, f"must be an integer >= {low}, got {value!r}")
        elif flag in ("--width", "--height") and value > 16384:
            problems.add("command line", flag, f"must be <= 16384, got {value!r}")
    problems.raise_if_any()


def _remove_stale_gt_json(out: Path) -> None:
    """Deletes the gt.json an earlier version of this import wrote (its metadata, no GT textures):
    evaluation reads gt.json as per-object GT textures and would refuse it."""
    path = out / "gt.json"
    if not path.is_file():
        return
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return
    if isinstance(doc, dict) and "textures" not in doc and isinstance(doc.get("source"), dict) \
            and "mitsuba" in doc["source"]:
        path.unlink()
        log.warning("removed %s written by an earlier import (its metadata is now %s)", path, IMPORT_FILE)


def _licence_text(xml_path: Path) -> str | None:
    for name in ("LICENSE.txt", "LICENSE", "LICENSE.md", "COPYING"):
        path = xml_path.parent / name
        if path.is_file():
            return path.read_text(errors="replace").strip()
    return None


def prepare_scene(xml_path, out_dir, *, num_views: int, width: int, height: int, spp: int, seed: int = 0,
                  up=None, command: str | None = None, progress: bool = True) -> dict:
    """Imports a Mitsuba 3 scene into `out_dir` (scene.json, mesh, photos, targets, ground truth,
    masks, import.json, README.md).

    Returns a summary (also in import.json): objects, UV decisions, view statistics, timings.
    """
    _check_arguments(xml_path, num_views, width, height, spp)
    previous = mb.load_mitsuba().variant()
    irradiance_mitsuba()                       # before any compute: the irradiance needs LLVM
    mb.load_mitsuba(previous)
    out = Path(out_dir)
    if out.is_dir() and any(out.iterdir()):
        log.warning("%s is not empty: files of an earlier import that this one does not rewrite stay there", out)
    timings = {}
    t0 = time.perf_counter()
    source = load_source(xml_path, up=up, upgraded_dir=out)
    timings["load_s"] = time.perf_counter() - t0
    log.info("loaded %s: %d objects (%d faces), dropped %s in %.1f s", xml_path, len(source.objects),
             sum(len(o.faces) for o in source.objects), source.dropped or "none", timings["load_s"])

    t = time.perf_counter()
    mesh, decisions = reconstruction_mesh(source.objects, progress=progress, source_file=os.fspath(xml_path))
    timings["uv_layout_s"] = time.perf_counter() - t
    reunwrapped = [d for d in decisions if d.reunwrapped]
    log.info("UV layout in %.1f s: re-unwrapped %d of %d objects: %s", timings["uv_layout_s"], len(reunwrapped),
             len(decisions), ", ".join(f"{d.name} ({d.reason}, {d.seconds:.2f} s)" for d in reunwrapped) or "none")

    gt_eval = GroundTruthEvaluator(source.objects, mesh)
    t = time.perf_counter()
    cams, view_stats = place_views(mesh, gt_eval.masked_face, num_views, width, height, up=source.up, seed=seed,
                                   progress=progress)
    timings["view_placement_s"] = time.perf_counter() - t
    log.info("placed %d views in %.1f s (%d candidates)", len(cams), timings["view_placement_s"],
             view_stats["candidates"])

    _remove_stale_gt_json(out)
    t = time.perf_counter()
    frags = fr.compute_fragments(mesh, cams, cache_dir=False, progress=progress)
    names = [f"view_{i:03d}" for i in range(len(cams))]
    per_view, masks = [], []
    for name, cam, frag in zip(tqdm(names, desc="ground truth", unit="view", disable=not progress), cams, frags):
        gt = gt_eval.evaluate(cam, frag)
        imageio.write_image(out / "targets" / "albedo" / f"{name}.exr", gt.albedo)
        imageio.write_image(out / "targets" / "roughness" / f"{name}.exr", gt.roughness)
        imageio.write_image(out / "targets" / "metallic" / f"{name}.exr", gt.metallic)
        imageio.write_image(out / "targets" / "normal" / f"{name}.exr", gt.normal)
        imageio.write_image(out / "masks" / f"{name}.png", gt.mask.astype(np.float32), encode_srgb=False)
        masks.append(gt.mask)
        per_view.append({"name": name, "hit_fraction": float(gt.hit.mean()), "valid_fraction": float(gt.mask.mean()),
                         "fov_x_deg": float(np.degrees(2 * np.arctan(cam.width / (2 * cam.K[0, 0]))))})
    timings["ground_truth_s"] = time.perf_counter() - t
    log.info("ground truth for %d views in %.1f s", len(cams), timings["ground_truth_s"])

    t = time.perf_counter()
    irradiance = [np.where(m[..., None], e, 0.0) for e, m in zip(render_irradiance(source.path, cams, spp=spp, seed=seed,
                                                                                   xml_text=source.xml_text),
                                                                 masks)]
    scale = irradiance_target_scale(irradiance, masks)
    for name, image in zip(names, irradiance):
        imageio.write_image(out / "ground_truth" / "irradiance" / f"{name}.exr", image)
        imageio.write_image(out / "targets" / "irradiance" / f"{name}.exr", np.clip(image * scale, 0.0, 1.0))
    timings["irradiance_s"] = time.perf_counter() - t
    log.info("irradiance (E / pi, %s) of %d views in %.1f s", IRRADIANCE_VARIANT, len(cams), timings["irradiance_s"])

    t = time.perf_counter()
    bar = tqdm(list(zip(names, cams)), desc=f"render (spp {spp})", unit="view", disable=not progress)
    for i, (name, cam) in enumerate(bar):
        image = mb.render(source.scene, cam, spp=spp, seed=seed + i)[..., :3]
        image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
        imageio.write_image(out / "photos" / f"{name}.exr", image, half=True)
        imageio.write_image(out / "photos" / f"{name}.png", image)
    timings["render_s"] = time.perf_counter() - t
    log.info("rendered %d views at %dx%d, spp %d in %.1f s", len(cams), width, height, spp, timings["render_s"])

    # the photos as RGB<->X sees them: one scene-wide exposure by Hypersim's rule over the valid
    # pixels, measured on the EXR files as written (half float), as the dataset loaders do
    stops = exposure_rule.scene_exposure((imageio.read_image(out / "photos" / f"{n}.exr")[..., :3] for n in names),
                                         masks)
    log.info("exposure: %+.2f stops (Hypersim's rule: 90th-percentile brightness to 0.8 after gamma)", stops)
    exact = ("albedo", "normal", "roughness", "metallic")     # the targets of these maps ARE the ground truth
    views = tuple(View(name=name, camera=cam, photo=out / "photos" / f"{name}.exr", exposure=stops,
                       targets={m: out / "targets" / m / f"{name}.exr" for m in exact + ("irradiance",)},
                       mask=out / "masks" / f"{name}.png",
                       ground_truth={**{m: out / "targets" / m / f"{name}.exr" for m in exact},
                                     "irradiance": out / "ground_truth" / "irradiance" / f"{name}.exr"})
                  for name, cam in zip(names, cams))
    scene_name = source.path.parent.name or source.path.stem
    write_scene(Scene(name=scene_name, mesh=mesh, views=views, texture_layout="pages"), out)
    timings["total_s"] = time.perf_counter() - t0

    summary = {
        "format": IMPORT_FORMAT, "version": IMPORT_VERSION,
        "source": {"mitsuba": os.fspath(Path(xml_path).resolve()), "integrator": source.integrator,
                   "up": source.up.tolist(), "dropped_shapes": source.dropped},
        "settings": {"views": num_views, "width": width, "height": height, "spp": spp, "seed": seed},
        "command": command,
        "conventions": {
            "photos": "photos/<view>.exr linear RGB radiance (half float); photos/<view>.png the same, sRGB-encoded",
            "albedo": "targets/albedo/<view>.exr linear RGB; 0 outside the mask",
            "roughness": "targets/roughness/<view>.exr one channel, perceptual roughness = sqrt(GGX alpha); "
                         "0 outside the mask",
            "metallic": "targets/metallic/<view>.exr one channel; 0 outside the mask",
            "normal": "targets/normal/<view>.exr camera-space unit normal, x right, y up, z towards the camera "
                      "(RGB<->X), flipped to face the camera, stored as (n + 1) / 2; (0.5, 0.5, 0.5) where no "
                      "surface is hit; defined on emitters and glass too",
            "irradiance": "ground_truth/irradiance/<view>.exr linear RGB E / pi (the radiance a white Lambertian "
                          "surface would reflect: photo = albedo x irradiance on diffuse surfaces), HDR, same units as "
                          "the photos; targets/irradiance/<view>.exr the same x irradiance_target_scale, clipped to "
                          "[0, 1] (RGB<->X's output range); 0 outside the mask",
            "mask": "masks/<view>.png 1 where a ray hits a surface that is neither an emitter nor glass; "
                    "scene.json references it as each view's mask (out of loss and metrics)",
            "ground_truth": "scene.json views[].ground_truth: albedo, normal, roughness, metallic are the targets' "
                            "files (exact), irradiance ground_truth/irradiance/<view>.exr",
            "materials": "diffuse: albedo = reflectance, roughness 1, metallic 0; plastic: diffuse_reflectance, 0, "
                         "0; roughplastic: diffuse_reflectance, sqrt(alpha), 0; principled: base_color, roughness, "
                         "metallic; conductor: albedo = specular_reflectance x F0(eta, k), roughness 0 "
                         "(roughconductor: sqrt(alpha)), metallic 1; twosided: its front BSDF",
        },
        "irradiance_target_scale": scale,
        "objects": [{"name": o.name, "shape": o.shape, "faces": int(len(o.faces)), "emitter": o.emitter,
                     "masked": o.masked, "uv": d.reason if d.reunwrapped else "kept",
                     "uv_seconds": round(d.seconds, 3), **(o.material.describe() if o.material else {})}
                    for o, d in zip(source.objects, decisions)],
        "reunwrapped": [d.name for d in reunwrapped],
        "view_placement": view_stats,
        "views": per_view,
        "statistics": {"hit_fraction": float(np.mean([v["hit_fraction"] for v in per_view])),
                       "valid_fraction": float(np.mean([v["valid_fraction"] for v in per_view]))},
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }
    (out / IMPORT_FILE).write_text(json.dumps(summary, indent=1))
    _write_readme(out, source, summary, mesh)
    read_scene(out)          # self-check: the written scene validates
    return summary


def _write_readme(out: Path, source: MitsubaSource, summary: dict, mesh: Mesh) -> None:
    licence = _licence_text(source.path)
    s, st, tm = summary["settings"], summary["statistics"], summary["timings"]
    lines = [
        f"# {out.name}: imported from a Mitsuba 3 scene",
        "",
        f"Source: `{summary['source']['mitsuba']}`, imported by `jaxdistill.datasets.mitsuba.importer`"
        " (`scripts/prepare_scene.py`).",
        "",
        "## Source and licence",
        "",
    ]
    if licence:
        lines += ["The source scene comes with this licence notice, which applies to everything derived from it "
                  "here (mesh, photos, ground truth):", "", *["> " + line for line in licence.splitlines()], ""]
    else:
        lines += ["No licence file was found beside the source XML: check its terms before sharing this folder.", ""]
    lines += [
        "## Command",
        "",
        "```",
        summary["command"] or (f"prepare_scene(--mitsuba={summary['source']['mitsuba']} --views={s['views']} "
                               f"--width={s['width']} --height={s['height']} --spp={s['spp']} --seed={s['seed']})"),
        "```",
        "",
        "Distil it (from the jaxdistill checkout; all five maps have targets and ground truth):",
        "",
        "```",
        f"python -m jaxdistill.main --flagfile=configs/bedroom.cfg --scene={out} --out_dir={out}_run "
        f"--views_per_step={min(8, s['views'])}",
        "```",
        "",
        "## Contents",
        "",
        f"- `scene.json`, `mesh.glb`: {len(mesh.object_names)} objects, {mesh.num_faces} triangles, texture layout "
        "`pages` (one page per object). Reconstruction UVs lie in [0, 1]; re-unwrapped with xatlas: "
        f"{', '.join(summary['reunwrapped']) or 'none'}.",
        f"- {s['views']} views at {s['width']}x{s['height']}, path traced by Mitsuba "
        f"({summary['source']['integrator']}, {s['spp']} spp).",
        "- `targets/<map>/<view>.exr` (albedo, normal, roughness, metallic: the exact ground truth; irradiance: "
        "scaled into [0, 1]), `ground_truth/irradiance/<view>.exr`, `masks/<view>.png` (each view's `mask` in "
        "scene.json), `import.json` (conventions, per-object materials and UV decisions, per-view statistics, "
        "timings).",
        "- The targets of albedo, normal, roughness and metallic are the ground truth itself: a run with the "
        "`views` prior on them is an upper bound, not a method result; for a real test, replace them with "
        "estimates (`python -m jaxdistill.estimate`) or use `--prior=rgbx`.",
        "",
        "## Conventions",
        "",
        *[f"- {k}: {v}" for k, v in summary["conventions"].items()],
        "- Cameras: OpenCV (x right, y down, z forward), square pixels, off-centre principal points.",
        "- Ground truth is evaluated per pixel at the ORIGINAL texture coordinates of the triangle our ray hits, "
        "so it is exact whatever the reconstruction UV layout.",
        "",
        "## Statistics and timings",
        "",
        f"- Mean hit fraction {st['hit_fraction']:.3f}, mean valid (unmasked) fraction {st['valid_fraction']:.3f}.",
        f"- Unmasked surface area seen by some view (low-res estimate): "
        f"{summary['view_placement']['unmasked_area_seen_fraction']:.3f}.",
        "- " + ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in tm.items()) + ".",
        "",
    ]
    (out / "README.md").write_text("\n".join(lines))
