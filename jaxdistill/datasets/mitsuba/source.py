"""Loading a Mitsuba scene XML: checks the files it names, upgrades a Mitsuba 0.5/0.6 file
(`upgrade.py`), loads it with Mitsuba and turns every kept shape into a `SourceObject` with its
ground-truth material (`MitsubaSource`); one InputError lists every problem found.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from jaxdistill.datasets.mitsuba import bridge as mb
from jaxdistill.datasets.mitsuba.materials import (DROPPED_BSDFS, MASKED_BSDFS, SUPPORTED_BSDFS, material_of,
                                                   plugin_name, unwrap_twosided)
from jaxdistill.datasets.mitsuba.shapes import SourceObject, shape_geometry
from jaxdistill.datasets.mitsuba.upgrade import needs_upgrade, upgrade
from jaxdistill.errors import InputError, ProblemList

log = logging.getLogger(__name__)


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
        plugin = plugin_name(shape)
        name = shape.id() or f"{plugin}_{index:03d}"
        while name in names:
            name += "_"
        names.add(name)
        if shape.is_sensor():
            dropped.append(f"{name} (sensor)")
            continue
        geometry = shape_geometry(shape, plugin)
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
        inner_plugin = plugin_name(unwrap_twosided(bsdf)) if bsdf is not None else "none"
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
