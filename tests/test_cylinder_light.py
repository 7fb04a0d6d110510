"""UsdLux CylinderLight (a tube light, as Houdini, Karma and Omniverse rigs use them): read as a record with its
side's area, rendered by the fast renderer and Mitsuba (the agreement: tests/test_engine.py and, with Cycles,
tests/test_cross_renderer_lux.py), written to Mitsuba XML as a cylinder emitter and read back as the same light."""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from usdrelight.stage.lux import emitted_radiance, world_area
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

TUBE = '''#usda 1.0
(
    metersPerUnit = 0.01
    upAxis = "Y"
)
def Xform "World" {
    def Camera "Cam" {
        float focalLength = 20
        float horizontalAperture = 36
        float verticalAperture = 27
        double3 xformOp:translate = (0, 100, 300)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def Mesh "Floor" {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 3, 2, 1]
        point3f[] points = [(-300, 0, 300), (300, 0, 300), (300, 0, -300), (-300, 0, -300)]
        color3f[] primvars:displayColor = [(0.5, 0.5, 0.5)]
    }
    def CylinderLight "Tube" {
        float inputs:intensity = 4
        bool inputs:normalize = 1
        color3f inputs:color = (1, 0.8, 0.6)
        float inputs:radius = 5
        float inputs:length = 120
        double3 xformOp:translate = (20, 80, -40)
        float3 xformOp:rotateXYZ = (0, 30, 20)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
    }
}
'''


def test_a_cylinder_light_reads_with_its_side_as_its_area(tmp_path):
    """A centimetre stage: radius 5 cm and length 1.2 m in metres, the side's area 2 pi r l normalizing it,
    its axis the light's local X (before: 'light type CylinderLight (not converted)', and it lit nothing)."""
    (tmp_path / "t.usda").write_text(TUBE)
    rec = read_scene(open_stage(tmp_path / "t.usda"))
    (tube,) = rec.lights
    assert not [w for w in rec.warnings if "CylinderLight" in w], rec.warnings
    assert tube.kind == "cylinder" and tube.radius * 0.01 == pytest.approx(0.05)
    area = 2 * math.pi * 0.05 * 1.2
    assert world_area(tube) == pytest.approx(area, rel=1e-6)
    np.testing.assert_allclose(emitted_radiance(tube), np.array([4, 3.2, 2.4]) / area, rtol=1e-6)
    axis = tube.to_world[:3, 0] / np.linalg.norm(tube.to_world[:3, 0])
    c30, s30, c20, s20 = (f(math.radians(a)) for a, f in ((30, math.cos), (30, math.sin), (20, math.cos),
                                                          (20, math.sin)))
    want = np.array([c20 * c30, s20 * c30, -s30])  # X turned 30 degrees about Y, then 20 about Z (rotateXYZ)
    np.testing.assert_allclose(axis, want, atol=1e-6)
    np.testing.assert_allclose(tube.to_world[:3, 3], [0.2, 0.8, -0.4], atol=1e-9)


def test_the_xml_holds_a_cylinder_emitter_and_reads_back_as_the_same_light(tmp_path, cli):
    (tmp_path / "t.usda").write_text(TUBE)
    cli.json("convert", tmp_path / "t.usda", tmp_path / "t.xml")
    shape = next(s for s in ET.parse(tmp_path / "t.xml").getroot().iter("shape") if s.get("type") == "cylinder")
    assert shape.find("emitter").get("type") == "area"
    p0, p1 = (np.array([float(v) for v in shape.find(f"point[@name='{n}']").get("value").split(",")])
              for n in ("p0", "p1"))
    assert np.linalg.norm(p1 - p0) == pytest.approx(1.2, rel=1e-6)
    np.testing.assert_allclose((p0 + p1) / 2, [0.2, 0.8, -0.4], atol=1e-6)
    assert float(shape.find("float[@name='radius']").get("value")) == pytest.approx(0.05, rel=1e-6)
    cli.json("convert", tmp_path / "t.xml", tmp_path / "back.usda")
    (back,) = read_scene(open_stage(tmp_path / "back.usda")).lights
    (orig,) = read_scene(open_stage(tmp_path / "t.usda")).lights
    assert back.kind == "cylinder"
    assert world_area(back) == pytest.approx(world_area(orig), rel=1e-6)
    np.testing.assert_allclose(emitted_radiance(back), emitted_radiance(orig), rtol=1e-5)
    ax_b, ax_o = (l.to_world[:3, 0] / np.linalg.norm(l.to_world[:3, 0]) for l in (back, orig))
    assert abs(ax_b @ ax_o) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(back.to_world[:3, 3], orig.to_world[:3, 3] * 1.0, atol=1e-6)


def test_relight_renders_the_tube_where_it_is(tmp_path, cli):
    """The fast renderer lights the floor under the tube (no 'not converted' warning): the brightest floor
    pixels lie under it, and the light falls off away from it."""
    (tmp_path / "t.usda").write_text(TUBE)
    rc, _, err = cli("relight", tmp_path / "t.usda", "--mode", "render", "--max-side", "64", "-o", tmp_path / "r")
    assert rc == 0 and "CylinderLight" not in err, err
    from usdrelight.imageio import read_map

    img = read_map(tmp_path / "r" / "render_diffuse.exr", 3).mean(-1)
    assert np.all(np.isfinite(img)) and img.min() >= 0 and img.max() > 10 * np.median(img[img > 0])
