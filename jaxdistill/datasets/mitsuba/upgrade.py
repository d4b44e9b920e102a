"""Upgrades Mitsuba 0.5/0.6 scene XML (as Bitterli's Rendering Resources ship it) to Mitsuba 3.

Pure XML -> XML with ElementTree: `upgrade(root)` returns the upgraded tree and the list of
human-readable changes; `needs_upgrade(root)` tells a Mitsuba 0.x tree (root `version` below
2.0) from a Mitsuba 2/3 one. `source.load_source` upgrades 0.x files on import. Everything that has
no Mitsuba 3 equivalent is either mapped to the nearest plugin with a warning naming the
element, or refused: one InputError lists every refused element (`file: <element>: what is
wrong; what to do`). Nothing is dropped silently.

What changes (from Mitsuba 3's own `transform_upgrade` in src/core/parser.cpp, the 0.6
documentation and the Mitsuba 3 plugin sources):

- root `version` -> 3.0.0;
- parameter names camelCase -> snake_case by Mitsuba 3's rule (`toWorld` -> `to_world`,
  `intIOR` -> `int_ior`, `sampleCount` -> `sample_count`), and diffuse `diffuseReflectance`
  -> `reflectance`; `uoffset/voffset/uscale/vscale` -> a `to_uv` transform;
- values: `<srgb>` (sRGB-encoded, also `#rrggbb`) -> linear `<rgb>`; `<rgb value="#rrggbb">`
  -> its linear numbers (0.6 read hex `<rgb>` as linear / 255); a one-value `<spectrum>` ->
  `<rgb>` of three equal values (what the RGB build of 0.6 computed; Mitsuba 3 would tint a
  constant emitter spectrum by D65); `<blackbody temperature=...>` -> `<spectrum
  type="blackbody">`; the `intent` attribute is removed; `<lookAt>` -> `<lookat>` (also the
  oldest `ox oy oz tx ...` form);
- plugins: `ldrfilm` -> `hdrfilm` (tone mapping dropped: photos are rendered linear anyway),
  `sobol`/`halton`/`hammersley` -> `independent`, `volpath_simple` -> `volpath`, other
  integrators without a Mitsuba 3 counterpart (bdpt, mlt, pssmlt, erpt, photon mappers, ao)
  -> `path`; `irrcache`/`adaptive`/`multichannel` wrappers -> their nested integrator;
  `roughdiffuse` -> `diffuse`; `phong` -> `roughplastic` (Beckmann alpha = sqrt(2 / (exponent
  + 2))), `ward` -> `roughplastic` (alpha = sqrt(alphaU alphaV)); `coating`/`roughcoating` ->
  the coated BSDF; `mixturebsdf` of two BSDFs -> `blendbsdf` (weight = w2 / (w1 + w2));
  microfacet `distribution` `phong`/`as` -> `beckmann`; a `scale` texture inside `bumpmap`
  -> the bump map's `scale`; `sun`/`sky` -> `sunsky` with the other part switched off;
  `perspective_rdist` -> `perspective` (no lens distortion);
- parameters Mitsuba 3 does not have (it refuses unreferenced properties) are removed, each
  listed: e.g. `strictNormals`, film `banner`/`gamma`, bitmap `maxAnisotropy`/`cache`,
  conductor `extEta`; bitmap `filterType` trilinear/ewa -> bilinear, `gamma` 1 -> `raw`.

Relative file names can be made absolute (`base_dir`), so that the upgraded XML, written
anywhere for inspection, loads with the source's meshes and textures. `<include>`d files are
not upgraded (Mitsuba 3 renames their camelCase parameters itself; nothing else).

This module is the entry point (version check, `upgrade`, the `Upgrade` result); the rules
themselves are in `upgrade_rules.py`.
"""

from __future__ import annotations

import copy
import dataclasses
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from jaxdistill.datasets.mitsuba.upgrade_rules import TARGET_VERSION, Change, Upgrader


@dataclasses.dataclass(frozen=True)
class Upgrade:
    """An upgraded scene: the Mitsuba 3 tree, the source version and the changes made."""

    root: ET.Element
    source_version: str
    changes: tuple[Change, ...]

    def to_string(self) -> str:
        """The upgraded XML, with the change list as a comment at its top."""
        root = copy.deepcopy(self.root)
        note = "\n".join([f" Upgraded by jaxdistill.datasets.mitsuba.upgrade from Mitsuba {self.source_version} to "
                          f"{TARGET_VERSION}; {len(self.changes)} changes:"]
                         + ["   " + str(c).replace("--", "- -") for c in self.changes]) + "\n"
        root.insert(0, ET.Comment(note))
        ET.indent(root, space="\t")
        return ET.tostring(root, encoding="unicode") + "\n"


def parse_version(text: str | None) -> tuple[int, ...] | None:
    """(major, minor, patch) of a version attribute, None when it is missing or not numbers."""
    if not text or not re.fullmatch(r"\d+(\.\d+){0,2}", text.strip()):
        return None
    return tuple(int(x) for x in text.strip().split("."))


def needs_upgrade(root: ET.Element) -> bool:
    """True when the root's version attribute is a version below 2.0 (Mitsuba 0.x)."""
    version = parse_version(root.get("version"))
    return version is not None and version < (2,)


def upgrade(root: ET.Element, *, source: str = "scene", base_dir=None) -> Upgrade:
    """The Mitsuba 3 version of a Mitsuba 0.x tree (the input is not modified) and its changes.

    source names the file in messages; base_dir, when given, makes relative file names absolute.
    InputError lists every element that has no Mitsuba 3 equivalent.
    """
    version = root.get("version", "")
    tree = copy.deepcopy(root)
    up = Upgrader(tree, source, None if base_dir is None else Path(base_dir))
    up.run()
    up.problems.raise_if_any()
    return Upgrade(tree, version, tuple(up.changes))
