"""Ground-truth materials of Mitsuba 3 BSDFs: which plugin a loaded object is, and what its
albedo, roughness, metallic (and mask opacity) are, evaluated by Mitsuba itself.

`material_of(bsdf)` gives the `GTMaterial` of a BSDF (`twosided` unwrapped to its front BSDF);
its `Field`s evaluate constants and any Mitsuba texture at the original UV. The conventions
(perceptual roughness = sqrt(GGX alpha), conductor albedo = specular reflectance x F0) are
those of the import (`prepare.py`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

import numpy as np

from jaxdistill.datasets.mitsuba import bridge as mb

log = logging.getLogger(__name__)

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


def plugin_name(obj) -> str:
    """The XML plugin name of a Mitsuba BSDF/shape object (its class name when unknown)."""
    name = obj.class_name()
    return BSDF_PLUGINS.get(name, SHAPE_PLUGINS.get(name, name))


def unwrap_twosided(bsdf):
    """The front BSDF of a (possibly nested) `twosided`, else `bsdf` itself."""
    while plugin_name(bsdf) == "twosided":
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
    inner = unwrap_twosided(bsdf)
    plugin = plugin_name(inner)
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
