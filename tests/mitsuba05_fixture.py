"""A tiny hand-written Mitsuba 0.5 scene, in the style of Bitterli's Rendering Resources.

camelCase parameters (`toWorld`, `diffuseReflectance`, `intIOR`, `filterType`, `fovAxis`,
`sampleCount`, `maxDepth`), `<srgb>`, a hex `<rgb>`, a constant `<spectrum>`, `<lookAt>`,
`ldrfilm`, a `sobol` sampler, `strictNormals`, a `phong` BSDF, and a `mask` BSDF (foliage) whose
opacity is a 2x1 bitmap: 0 for u < 0.5, 1 for u >= 0.5 (nearest filtering).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxdistill.io import images as imageio

WALL_SRGB_HEX = "#8040c0"
FLOOR_RGB = (0.3, 0.2, 0.1)
FLOOR_ALPHA = 0.2
PHONG_EXPONENT = 48.0
LEAF_RGB = (0.1, 0.6, 0.2)
LIGHT_RADIANCE = 5.0
LEAF_CENTRE = np.array([0.0, 1.0, 1.0])     # leaf: x in [-0.5, 0.5], y in [0.5, 1.5], z = 1, normal +z
FOV = 45.0


def matrix(m) -> str:
    return " ".join(f"{x:.9g}" for x in np.asarray(m, float).ravel())


def write_scene05(folder: Path) -> Path:
    """Writes scene.xml (version 0.5.0), floor.obj and leaf_alpha.png into `folder`; the XML path."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "floor.obj").write_text("v -2 0 -1\nv 2 0 -1\nv 2 0 3\nv -2 0 3\n"
                                      "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 4/4 3/3\nf 1/1 3/3 2/2\n")
    imageio.write_image(folder / "leaf_alpha.png", np.array([[[0.0], [1.0]]], np.float32), encode_srgb=False)
    leaf = np.diag([0.5, 0.5, 1.0, 1.0])
    leaf[:3, 3] = LEAF_CENTRE
    wall = np.diag([2.0, 2.0, 1.0, 1.0])
    wall[:3, 3] = (0.0, 1.0, 0.0)
    xml = f"""<?xml version="1.0" encoding="utf-8"?>
<scene version="0.5.0">
	<integrator type="path">
		<integer name="maxDepth" value="4"/>
		<boolean name="strictNormals" value="true"/>
	</integrator>
	<sensor type="perspective">
		<float name="fov" value="{FOV}"/>
		<string name="fovAxis" value="x"/>
		<transform name="toWorld">
			<lookAt origin="0, 1, 3" target="0, 1, 1" up="0, 1, 0"/>
		</transform>
		<sampler type="sobol">
			<integer name="sampleCount" value="16"/>
		</sampler>
		<film type="ldrfilm">
			<integer name="width" value="64"/>
			<integer name="height" value="48"/>
			<string name="fileFormat" value="png"/>
			<float name="gamma" value="2.2"/>
			<boolean name="banner" value="false"/>
			<rfilter type="gaussian"/>
		</film>
	</sensor>
	<bsdf type="twosided" id="Wall">
		<bsdf type="diffuse">
			<srgb name="diffuseReflectance" value="{WALL_SRGB_HEX}"/>
		</bsdf>
	</bsdf>
	<bsdf type="roughplastic" id="Floor">
		<float name="alpha" value="{FLOOR_ALPHA}"/>
		<string name="distribution" value="ggx"/>
		<float name="intIOR" value="1.5"/>
		<float name="extIOR" value="1"/>
		<boolean name="nonlinear" value="true"/>
		<rgb name="diffuseReflectance" value="{", ".join(map(str, FLOOR_RGB))}"/>
	</bsdf>
	<bsdf type="phong" id="Old">
		<float name="exponent" value="{PHONG_EXPONENT}"/>
		<rgb name="diffuseReflectance" value="#402010"/>
	</bsdf>
	<bsdf type="mask" id="Leaves">
		<texture name="opacity" type="bitmap">
			<string name="filename" value="leaf_alpha.png"/>
			<string name="filterType" value="nearest"/>
			<float name="gamma" value="1"/>
		</texture>
		<bsdf type="twosided">
			<bsdf type="diffuse">
				<rgb name="reflectance" value="{", ".join(map(str, LEAF_RGB))}"/>
			</bsdf>
		</bsdf>
	</bsdf>
	<shape type="obj" id="floor">
		<string name="filename" value="floor.obj"/>
		<boolean name="faceNormals" value="true"/>
		<ref id="Floor"/>
	</shape>
	<shape type="rectangle" id="wall">
		<transform name="toWorld">
			<matrix value="{matrix(wall)}"/>
		</transform>
		<ref id="Wall"/>
	</shape>
	<shape type="rectangle" id="leaf">
		<transform name="toWorld">
			<matrix value="{matrix(leaf)}"/>
		</transform>
		<ref id="Leaves"/>
	</shape>
	<shape type="sphere" id="ball">
		<point name="center" x="1.2" y="0.3" z="1.5"/>
		<float name="radius" value="0.3"/>
		<ref id="Old"/>
	</shape>
	<shape type="rectangle" id="light">
		<transform name="toWorld">
			<scale x="0.3" y="0.3"/>
			<rotate x="1" angle="90"/>
			<translate x="0" y="2" z="1"/>
		</transform>
		<emitter type="area">
			<spectrum name="radiance" value="{LIGHT_RADIANCE}"/>
			<float name="samplingWeight" value="1"/>
		</emitter>
	</shape>
</scene>
"""
    path = folder / "scene.xml"
    path.write_text(xml)
    return path
