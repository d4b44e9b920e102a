"""The rules of the Mitsuba 0.5/0.6 -> 3 upgrade (`upgrade.py`): the Mitsuba 3 plugin tables,
the name and value conversions, and `Upgrader`, which rewrites an XML tree in place pass by pass
(names, values, then one handler per plugin) and records every `Change` it makes.
"""

from __future__ import annotations

import dataclasses
import math
import re
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

from jaxdistill.errors import ProblemList

TARGET_VERSION = "3.0.0"
OBJECT_TAGS = ("scene", "bsdf", "shape", "texture", "emitter", "sensor", "film", "sampler", "integrator", "rfilter",
               "medium", "phase", "volume", "spectrum")

# Mitsuba 3 plugins (src/<kind>/*.cpp|py of mitsuba3) for the object kinds the upgrade maps.
M3_PLUGINS = {
    "bsdf": {"blendbsdf", "bumpmap", "circular", "conductor", "dielectric", "diffuse", "hair", "mask", "measured",
             "measured_polarized", "normalmap", "null", "plastic", "polarizer", "pplastic", "principled",
             "principledthin", "retarder", "roughconductor", "roughdielectric", "roughplastic", "thindielectric",
             "twosided"},
    "emitter": {"area", "constant", "directional", "directionalarea", "envmap", "point", "projector", "spot",
                "sunsky", "timed_sunsky"},
    "film": {"hdrfilm", "specfilm"},
    "integrator": {"aov", "depth", "direct", "moment", "path", "ptracer", "stokes", "volpath", "volpathmis", "prb",
                   "prb_basic", "prbvolpath", "direct_projective", "prb_projective"},
    "rfilter": {"box", "catmullrom", "gaussian", "lanczos", "mitchell", "tent"},
    "sampler": {"independent", "ldsampler", "multijitter", "orthogonal", "stratified"},
    "sensor": {"batch", "distant", "irradiancemeter", "orthographic", "perspective", "radiancemeter", "thinlens"},
    "shape": {"bsplinecurve", "cube", "cylinder", "disk", "ellipsoids", "ellipsoidsmesh", "instance", "linearcurve",
              "merge", "obj", "ply", "rectangle", "sdfgrid", "serialized", "shapegroup", "sphere"},
    "texture": {"bitmap", "checkerboard", "mesh_attribute", "volume"},
}
# 0.6 parameters (after snake_case) that Mitsuba 3 does not read, per (tag, plugin); "*" = any plugin.
DROPPED = {
    ("integrator", "*"): {"strict_normals"},
    ("film", "*"): {"banner", "attach_log", "gamma", "exposure", "tonemap_method", "key", "burn", "reinhard_key",
                    "reinhard_burn"},
    ("sampler", "*"): {"dimension", "scramble"},
    ("texture", "bitmap"): {"max_anisotropy", "cache"},
    ("shape", "*"): {"max_smooth_angle", "collapse", "recenter"},
    ("emitter", "envmap"): {"gamma", "cache"},
    ("emitter", "sunsky"): {"stretch", "resolution", "sun_radius_scale", "extend"},
    ("bsdf", "conductor"): {"ext_eta"},
    ("bsdf", "roughconductor"): {"ext_eta"},
    ("bsdf", "diffuse"): {"use_fast_approx"},
}
UNSUPPORTED_HELP = {
    "bsdf": "replace it by a Mitsuba 3 BSDF (diffuse, plastic, roughplastic, conductor, roughconductor, principled, "
            "dielectric, ...)",
    "texture": "bake it into a bitmap",
    "shape": "convert it to a mesh (obj or ply)",
}


@dataclasses.dataclass(frozen=True)
class Change:
    """One change made by the upgrade: where (an element), what, and whether it alters the look."""

    where: str
    what: str
    warning: bool = False

    def __str__(self) -> str:
        return f"{'WARNING: ' if self.warning else ''}{self.where}: {self.what}"


def camel_to_snake(name: str) -> str:
    """Mitsuba 3's rule: '_' + lower case before an upper case letter that follows a lower case
    one, and the upper case letters right after it lower-cased too (`intIOR` -> `int_ior`)."""
    out, i = [], 0
    while i < len(name):
        c = name[i]
        if i > 0 and name[i - 1].islower() and c.isupper():
            out.append("_" + c.lower())
            while i + 1 < len(name) and name[i + 1].isupper():
                i += 1
                out.append(name[i].lower())
        else:
            out.append(c)
        i += 1
    return "".join(out)


def srgb_to_linear(c: float) -> float:
    """The sRGB transfer function's inverse (IEC 61966-2-1)."""
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


def _fmt(x: float) -> str:
    return f"{x:.9g}"


def _number(text) -> float:
    """The float in `text`, NaN when it is not one (a `$parameter`, a typo)."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


class Upgrader:
    def __init__(self, root: ET.Element, source: str, base_dir: Path | None):
        self.root = root
        self.source = source
        self.base_dir = base_dir
        self.changes: list[Change] = []
        self.renames: Counter = Counter()
        self.problems = ProblemList()
        self.parents = {child: parent for parent in root.iter() for child in parent}

    # ------------------------------------------------------------------ helpers

    def where(self, el: ET.Element) -> str:
        """`<tag type=... id=...>`, with the nearest ancestor that has an id (or a filename)."""
        def one(e):
            attrs = "".join(f' {k}="{e.get(k)}"' for k in ("type", "id", "name") if e.get(k))
            fname = next((c.get("value") for c in e if c.tag == "string" and c.get("name") == "filename"), None)
            return f"<{e.tag}{attrs}>" + (f" ({fname})" if fname and e.tag != "texture" else "")
        text = one(el)
        parent = self.parents.get(el)
        while parent is not None and parent.tag != "scene":
            named = parent.get("id") or any(c.tag == "string" and c.get("name") == "filename" for c in parent)
            if named or self.parents.get(parent) is self.root:
                return f"{one(parent)} {text}"
            parent = self.parents.get(parent)
        return text

    def change(self, el, what: str, warning: bool = False) -> None:
        self.changes.append(Change(self.where(el), what, warning))

    def refuse(self, el, what: str) -> None:
        self.problems.add(self.source, self.where(el), what)

    @staticmethod
    def prop(el: ET.Element, name: str) -> ET.Element | None:
        """The child named `name` (a value or a nested texture), None when absent."""
        return next((c for c in el if c.get("name") == name), None)

    def float_prop(self, el, name: str, default: float | None) -> float | None:
        p = self.prop(el, name)
        if p is None:
            return default
        if p.tag in ("float", "integer"):
            return _number(p.get("value"))
        return math.nan   # a texture or a parameter: no constant

    def remove(self, el, child, why: str, warning: bool = False) -> None:
        el.remove(child)
        self.parents.pop(child, None)
        self.change(el, f"removed parameter {child.get('name')!r} ({why})", warning)

    def set_prop(self, el, tag: str, name: str, value: str) -> None:
        old = self.prop(el, name)
        if old is not None:
            el.remove(old)
        new = ET.SubElement(el, tag, {"name": name, "value": value})
        self.parents[new] = el

    def replace_with_child(self, el, child, what: str) -> None:
        """Puts `child` where `el` is, taking over el's id and name; records `what` as a warning."""
        parent = self.parents[el]
        self.change(el, what, True)
        for key in ("id", "name"):
            if el.get(key) is not None:
                child.set(key, el.get(key))
        index = list(parent).index(el)
        parent.remove(el)
        del self.parents[el]
        parent.insert(index, child)
        self.parents[child] = parent

    # ------------------------------------------------------------------ passes

    def run(self) -> None:
        self.change(self.root, f"version {self.root.get('version')} -> {TARGET_VERSION}")
        self.root.set("version", TARGET_VERSION)
        for el in list(self.root.iter()):
            self.names(el)
        for el in list(self.root.iter()):
            self.values(el)
        for el in list(self.root.iter()):           # parents before children
            if el.tag in OBJECT_TAGS and el.tag != "scene" and el.get("type"):
                self.plugin(el)
        if self.base_dir is not None:
            self.absolute_filenames()
        for (old, new), n in sorted(self.renames.items()):
            times = f" ({n} times)" if n > 1 else ""
            self.changes.append(Change("parameters", f"renamed {old!r} -> {new!r}{times}"))

    def names(self, el) -> None:
        name = el.get("name")
        if name and el.tag not in ("default",):
            new = camel_to_snake(name)
            if new != name:
                el.set("name", new)
                self.renames[(name, new)] += 1

    def values(self, el) -> None:
        where = self.where(el)             # described as it was, before its tag changes

        def change(what: str) -> None:
            self.changes.append(Change(where, what))

        if "intent" in el.attrib:
            del el.attrib["intent"]
            change("removed the 'intent' attribute (Mitsuba 3 infers it)")
        if el.tag in ("lookAt", "lookat"):
            self.lookat(el)
        elif el.tag == "srgb":
            rgb = self.rgb_numbers(el, srgb=True)
            if rgb is not None:
                el.tag = "rgb"
                el.set("value", ", ".join(_fmt(x) for x in rgb))
                change(f"<srgb> -> linear <rgb value=\"{el.get('value')}\">")
        elif el.tag == "rgb" and el.get("value", "").strip().startswith("#"):
            rgb = self.rgb_numbers(el, srgb=False)
            if rgb is not None:
                el.set("value", ", ".join(_fmt(x) for x in rgb))
                change(f"hexadecimal <rgb> -> value=\"{el.get('value')}\" (linear, / 255 as in 0.6)")
        elif el.tag == "spectrum" and el.get("type") is None:
            tokens = [t for t in re.split(r"[,\s]+", el.get("value", "").strip()) if t]
            if len(tokens) == 1 and ":" not in tokens[0]:
                el.tag = "rgb"
                el.set("value", ", ".join([tokens[0]] * 3))
                change(f"constant <spectrum value=\"{tokens[0]}\"> -> <rgb value=\"{el.get('value')}\"> "
                                "(as 0.6's RGB build; Mitsuba 3 would tint a constant emitter spectrum by D65)")
        elif el.tag == "blackbody":
            temperature = el.get("temperature", "").strip().rstrip("kK")
            multiplier = el.get("multiplier", "1")
            if math.isnan(_number(temperature)) or _number(multiplier) != 1.0:
                self.refuse(el, "a <blackbody> needs a numeric temperature and no multiplier in Mitsuba 3; "
                                "give the emitter's radiance as <rgb> instead")
                return
            el.tag = "spectrum"
            el.attrib = {"name": el.get("name"), "type": "blackbody"}
            t = ET.SubElement(el, "float", {"name": "temperature", "value": temperature})
            self.parents[t] = el
            change(f"<blackbody temperature=\"{temperature}\"> -> <spectrum type=\"blackbody\">")

    def rgb_numbers(self, el, *, srgb: bool) -> list[float] | None:
        text = el.get("value", "").strip()
        try:
            if re.fullmatch(r"#[0-9a-fA-F]{6}", text):
                values = [int(text[i:i + 2], 16) / 255.0 for i in (1, 3, 5)]
            else:
                values = [float(t) for t in re.split(r"[,\s]+", text) if t]
                values = values * 3 if len(values) == 1 else values
            if len(values) != 3:
                raise ValueError
        except ValueError:
            self.refuse(el, f"cannot read the colour {text!r}; give three numbers or #rrggbb")
            return None
        return [srgb_to_linear(v) for v in values] if srgb else values

    def lookat(self, el) -> None:
        if el.get("origin") is None and el.get("ox") is not None:   # the oldest form: ox oy oz tx ty tz ux uy uz
            try:
                o, t, u = ([float(el.get(k + a, "0")) for a in "xyz"] for k in "otu")
            except ValueError:
                self.refuse(el, "cannot read the look-at numbers")
                return
            el.attrib = {"origin": ", ".join(map(_fmt, o)), "target": ", ".join(map(_fmt, t)),
                         **({"up": ", ".join(map(_fmt, u))} if any(u) else {})}
        if el.tag != "lookat":
            el.tag = "lookat"
            self.change(el, "<lookAt> -> <lookat>")

    def absolute_filenames(self) -> None:
        n = 0
        for el in self.root.iter():
            if (el.tag == "string" and el.get("name") == "filename") or el.tag == "include":
                value = el.get("value" if el.tag == "string" else "filename", "")
                if value and "$" not in value and not Path(value).is_absolute():
                    el.set("value" if el.tag == "string" else "filename", str(self.base_dir / value))
                    n += 1
        if n:
            self.changes.append(Change("file names", f"{n} relative file names made absolute (relative to "
                                                     f"{self.base_dir}) so the upgraded XML loads from anywhere"))

    # ------------------------------------------------------------------ plugins

    def retype(self, el, new: str, why: str, warning: bool = True) -> None:
        old, where = el.get("type"), self.where(el)
        el.set("type", new)
        self.changes.append(Change(where, f"plugin {old!r} -> {new!r} ({why})", warning))

    def plugin(self, el) -> None:
        if el not in self.parents and el is not self.root:
            return                                    # removed by an earlier mapping
        tag, kind = el.tag, el.get("type")
        handler = getattr(self, f"_{tag}_{kind}", None) or getattr(self, f"_{tag}", None)
        if handler is not None:
            refused = len(self.problems.problems)
            handler(el)
            if el not in self.parents or len(self.problems.problems) > refused:
                return                                # replaced by a child, or refused with a reason
            tag, kind = el.tag, el.get("type")
        for key in ((tag, "*"), (tag, kind)):
            for child in list(el):
                if child.get("name") in DROPPED.get(key, ()):
                    self.remove(el, child, "Mitsuba 3 has no such parameter")
        if tag in M3_PLUGINS and kind not in M3_PLUGINS[tag] and "$" not in kind:
            self.refuse(el, f"plugin {kind!r} has no Mitsuba 3 equivalent; "
                            + UNSUPPORTED_HELP.get(tag, f"use one of {', '.join(sorted(M3_PLUGINS[tag]))}"))

    # films, samplers, integrators, sensors

    def _film_ldrfilm(self, el) -> None:
        self.retype(el, "hdrfilm", "Mitsuba 3 has no LDR film; tone mapping parameters are removed", warning=False)
        self._film_hdrfilm(el)

    def _film_hdrfilm(self, el) -> None:
        fmt = self.prop(el, "file_format")
        if fmt is not None and fmt.get("value", "").lower() not in ("openexr", "exr", "rgbe", "hdr", "pfm"):
            self.remove(el, fmt, f"{fmt.get('value')!r} is not an HDR format; Mitsuba 3 writes OpenEXR")
        pix = self.prop(el, "pixel_format")
        if pix is not None:
            value = pix.get("value", "")
            new = {"luminancealpha": "luminance_alpha", "spectrum": "rgb", "spectrumalpha": "rgba"}.get(value.lower(),
                                                                                                         value)
            if new != value:
                pix.set("value", new)
                self.change(el, f"pixel_format {value!r} -> {new!r}")
        edges = self.prop(el, "high_quality_edges")
        if edges is not None:
            edges.set("name", "sample_border")
            self.change(el, "high_quality_edges -> sample_border")

    def _sampler(self, el) -> None:
        if el.get("type") in ("sobol", "halton", "hammersley"):
            self.retype(el, "independent", "low-discrepancy sampler not in Mitsuba 3; noise differs, not the image")

    def _integrator(self, el) -> None:
        kind = el.get("type")
        nested = [c for c in el if c.tag == "integrator"]
        if kind in ("irrcache", "adaptive", "multichannel") and nested:
            self.replace_with_child(el, nested[0], f"integrator wrapper {kind!r} -> its nested "
                                                   f"{nested[0].get('type')!r} integrator")
            return
        if kind == "volpath_simple":
            self.retype(el, "volpath", "same estimator", warning=False)
        elif kind == "direct":
            shading = self.prop(el, "shading_samples")
            if shading is not None:
                el.remove(shading)
                for name in ("emitter_samples", "bsdf_samples"):
                    if self.prop(el, name) is None:
                        self.set_prop(el, "integer", name, shading.get("value"))
                self.change(el, "shading_samples -> emitter_samples and bsdf_samples")
        elif kind not in M3_PLUGINS["integrator"] and "$" not in kind:
            keep = {"max_depth", "rr_depth", "hide_emitters"}
            for child in list(el):
                if child.get("name") not in keep:
                    el.remove(child)
            self.retype(el, "path", "not in Mitsuba 3; the photos are path traced (same converged image, "
                                    "other noise); its other parameters are removed")

    def _sensor_perspective_rdist(self, el) -> None:
        for child in list(el):
            if child.get("name") == "kc":
                self.remove(el, child, "Mitsuba 3's perspective camera has no lens distortion", True)
        self.retype(el, "perspective", "no radial distortion in Mitsuba 3")
        self._sensor(el)

    def _sensor(self, el) -> None:
        duration = self.prop(el, "shutter_open_time")
        if duration is not None:
            end = self.float_prop(el, "shutter_open", 0.0) + self.float_prop(el, "shutter_open_time", 0.0)
            if math.isnan(end):
                self.refuse(el, "shutterOpen and shutterOpenTime must be numbers to convert them to Mitsuba 3's "
                                "shutter_open and shutter_close")
                return
            el.remove(duration)
            self.set_prop(el, "float", "shutter_close", _fmt(end))
            self.change(el, "shutter_open_time -> shutter_close = shutter_open + shutter_open_time")

    # emitters

    def _emitter_sun(self, el) -> None:
        self.retype(el, "sunsky", "the sun of Mitsuba 3's sunsky, its sky switched off", warning=False)
        self.set_prop(el, "float", "sky_scale", "0")
        self._emitter_sunsky(el)

    def _emitter_sky(self, el) -> None:
        self.retype(el, "sunsky", "the sky of Mitsuba 3's sunsky, its sun switched off", warning=False)
        self.set_prop(el, "float", "sun_scale", "0")
        self._emitter_sunsky(el)

    def _emitter_sunsky(self, el) -> None:
        scale = self.prop(el, "scale")
        if scale is not None:
            s = self.float_prop(el, "scale", 1.0)
            if math.isnan(s):
                self.refuse(el, "a sunsky 'scale' must be a number (it becomes Mitsuba 3's sun_scale and sky_scale)")
                return
            el.remove(scale)
            for name in ("sun_scale", "sky_scale"):
                self.set_prop(el, "float", name, _fmt(self.float_prop(el, name, 1.0) * s))
            self.change(el, "scale -> sun_scale and sky_scale")
        self.change(el, "Mitsuba 3's sun and sky model (Hosek-Wilkie, as 0.6) differs in details: check the "
                        "photos' brightness", True)

    # BSDFs

    def _bsdf_diffuse(self, el) -> None:
        p = self.prop(el, "diffuse_reflectance")
        if p is not None:
            p.set("name", "reflectance")
            self.change(el, "diffuse_reflectance -> reflectance")

    def _bsdf_roughdiffuse(self, el) -> None:
        for child in list(el):
            if child.get("name") in ("alpha", "use_fast_approx", "distribution"):
                self.remove(el, child, "no Oren-Nayar roughness in Mitsuba 3", False)
        self.retype(el, "diffuse", "Mitsuba 3 has no rough (Oren-Nayar) diffuse BSDF")
        self._bsdf_diffuse(el)

    def _microfacet(self, el) -> None:
        dist = self.prop(el, "distribution")
        if dist is not None and dist.get("value", "").lower() not in ("beckmann", "ggx"):
            old = dist.get("value")
            dist.set("value", "beckmann")
            self.change(el, f"distribution {old!r} -> 'beckmann' (Mitsuba 3 has beckmann and ggx)", True)

    _bsdf_roughplastic = _bsdf_roughdielectric = _bsdf_roughconductor = _microfacet

    def _bsdf_phong(self, el) -> None:
        exponent = self.float_prop(el, "exponent", 30.0)
        if math.isnan(exponent):
            self.refuse(el, "a textured Phong exponent has no Mitsuba 3 equivalent; give a constant <float "
                            "name=\"exponent\"> or replace the BSDF by roughplastic")
            return
        alpha = math.sqrt(2.0 / (exponent + 2.0))
        for child in list(el):
            if child.get("name") == "exponent":
                el.remove(child)
        self.set_prop(el, "float", "alpha", _fmt(alpha))
        self.set_prop(el, "string", "distribution", "beckmann")
        self.retype(el, "roughplastic", f"no Phong BSDF in Mitsuba 3: nearest microfacet plastic, Beckmann alpha = "
                                        f"sqrt(2 / (exponent + 2)) = {alpha:.4g} for exponent {exponent:g}")

    def _bsdf_ward(self, el) -> None:
        au, av = self.float_prop(el, "alpha_u", 0.1), self.float_prop(el, "alpha_v", 0.1)
        if math.isnan(au) or math.isnan(av):
            self.refuse(el, "textured Ward roughness has no Mitsuba 3 equivalent; give constant alphaU/alphaV or "
                            "replace the BSDF by roughplastic")
            return
        for child in list(el):
            if child.get("name") in ("alpha_u", "alpha_v", "variant"):
                el.remove(child)
        alpha = math.sqrt(au * av)
        self.set_prop(el, "float", "alpha", _fmt(alpha))
        self.set_prop(el, "string", "distribution", "beckmann")
        self.retype(el, "roughplastic", f"no Ward BSDF in Mitsuba 3: nearest isotropic microfacet plastic, Beckmann "
                                        f"alpha = sqrt(alphaU alphaV) = {alpha:.4g}")

    def _bsdf_coating(self, el) -> None:
        nested = [c for c in el if c.tag == "bsdf" or (c.tag == "ref" and c.get("name") is None)]
        if len(nested) != 1:
            self.refuse(el, f"a {el.get('type')} needs exactly one nested BSDF, found {len(nested)}")
            return
        self.replace_with_child(el, nested[0], f"{el.get('type')!r} (no Mitsuba 3 equivalent) -> the coated BSDF: "
                                               "the clear coat's reflection is lost")

    _bsdf_roughcoating = _bsdf_coating

    def _bsdf_mixturebsdf(self, el) -> None:
        nested = [c for c in el if c.tag in ("bsdf", "ref")]
        weights = self.prop(el, "weights")
        try:
            w = [float(x) for x in re.split(r"[,\s]+", weights.get("value", "").strip()) if x]
        except (AttributeError, ValueError):
            w = []
        if len(nested) != 2 or len(w) != 2 or sum(w) <= 0:
            self.refuse(el, "only a mixturebsdf of two BSDFs with two constant weights maps to Mitsuba 3's blendbsdf "
                            f"(found {len(nested)} BSDFs, weights "
                            f"{weights.get('value') if weights is not None else None!r})")
            return
        el.remove(weights)
        self.set_prop(el, "float", "weight", _fmt(w[1] / (w[0] + w[1])))
        self.retype(el, "blendbsdf", f"weights {w} -> blendbsdf weight w2 / (w1 + w2); the sum {sum(w):g} is "
                                     "normalised away" if abs(sum(w) - 1) > 1e-6 else f"weights {w} -> weight w2",
                    warning=abs(sum(w) - 1) > 1e-6)

    def _bsdf_bumpmap(self, el) -> None:
        textures = [c for c in el if c.tag == "texture"]
        if len(textures) == 1 and textures[0].get("type") == "scale":
            scaled = textures[0]
            inner = [c for c in scaled if c.tag == "texture"]
            factor = self.float_prop(scaled, "scale", 1.0) * self.float_prop(el, "scale", 1.0)
            if len(inner) != 1 or math.isnan(factor):
                self.refuse(scaled, "a bump map's scale texture needs one nested texture and a constant scale")
                return
            self.replace_with_child(scaled, inner[0], "bump map <texture type=\"scale\"> -> its nested texture")
            self.changes[-1] = dataclasses.replace(self.changes[-1], warning=False)
            self.set_prop(el, "float", "scale", _fmt(factor))
            self.change(el, f"bump map scale = {factor:g}")

    # textures

    def _texture_bitmap(self, el) -> None:
        channel = self.prop(el, "channel")
        if channel is not None:
            self.refuse(el, f"channel {channel.get('value')!r}: Mitsuba 3 bitmaps have no channel selection (alpha "
                            "is dropped); save that channel as a grey image of its own and name it in 'filename'")
            return
        filt = self.prop(el, "filter_type")
        if filt is not None and filt.get("value") not in ("bilinear", "nearest"):
            old = filt.get("value")
            filt.set("value", "bilinear")
            self.change(el, f"filter_type {old!r} -> 'bilinear' (Mitsuba 3 has no MIP-mapping)")
        wraps = [c for c in el if c.get("name") in ("wrap_mode", "wrap_mode_u", "wrap_mode_v")]
        modes = {c.get("value") for c in wraps}
        for c in wraps:
            el.remove(c)
        if modes:
            mode = next(iter(modes)) if len(modes) == 1 else "repeat"
            new = {"zero": "clamp", "one": "clamp"}.get(mode, mode)
            self.set_prop(el, "string", "wrap_mode", new)
            if len(modes) > 1 or new != mode or any(c.get("name") != "wrap_mode" for c in wraps):
                self.change(el, f"wrap modes {sorted(modes)} -> wrap_mode {new!r} (one mode for u and v in "
                                "Mitsuba 3)", warning=len(modes) > 1 or new != mode)
        gamma = self.prop(el, "gamma")
        if gamma is not None:
            g = self.float_prop(el, "gamma", -1.0)
            el.remove(gamma)
            if g == 1.0:
                self.set_prop(el, "boolean", "raw", "true")
                self.change(el, "gamma 1 -> raw (linear values)")
            else:
                self.change(el, f"removed gamma {g:g}: Mitsuba 3 decodes 8-bit images as sRGB unless raw",
                            warning=g not in (-1.0, 2.2))
        self.uv_transform(el)

    def _texture_checkerboard(self, el) -> None:
        self.uv_transform(el)

    def _texture_scale(self, el) -> None:
        self.refuse(el, "Mitsuba 3 has no 'scale' texture outside a bump map; scale the bitmap's values instead")

    def uv_transform(self, el) -> None:
        found = {k: self.float_prop(el, k, None) for k in ("uoffset", "voffset", "uscale", "vscale")}
        if all(v is None for v in found.values()):
            return
        if any(v is not None and math.isnan(v) for v in found.values()):
            self.refuse(el, "uoffset, voffset, uscale and vscale must be numbers to become Mitsuba 3's to_uv transform")
            return
        for child in list(el):
            if child.get("name") in found:
                el.remove(child)
        ou, ov = found["uoffset"] or 0.0, found["voffset"] or 0.0
        su = 1.0 if found["uscale"] is None else found["uscale"]
        sv = 1.0 if found["vscale"] is None else found["vscale"]
        tr = ET.SubElement(el, "transform", {"name": "to_uv"})
        ET.SubElement(tr, "translate", {"x": _fmt(ou), "y": _fmt(ov)})   # to_uv = scale * translate, as Mitsuba 3
        ET.SubElement(tr, "scale", {"x": _fmt(su), "y": _fmt(sv)})
        self.parents[tr] = el
        self.change(el, f"uoffset/voffset/uscale/vscale -> to_uv (translate {ou:g}, {ov:g}, then scale {su:g}, {sv:g})")
