"""UsdLux CylinderLight (a tube light, as Houdini, Karma and Omniverse rigs use them): read as a record with its
side's area, rendered by the fast renderer and Mitsuba (the agreement: tests/test_engine.py and, with Cycles,
tests/test_cross_renderer_lux.py), written to Mitsuba XML as a cylinder emitter and read back as the same light."""
from __future__ import annotations

import json
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


EMISSION_PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc, out = bpy.context.scene, {}
for f in (1, 2, 3, 4, 5):
    sc.frame_set(f)
    out[f] = {m.name: list(n.inputs["Color"].default_value)[:3] for m in bpy.data.materials if m.node_tree
              for n in m.node_tree.nodes if n.type == "EMISSION"}
json.dump(out, open(args[1], "w"))
'''


def test_an_animated_tube_and_mesh_light_keep_their_emission_in_blender(tmp_path, cli):
    """The emissive mesh Blender gets for a CylinderLight (and a MeshLightAPI mesh) had its emission of the first
    frame for the whole clip: now its Emission colour follows USD at every frame, exposure's 2^x included."""
    from usdrelight.converters.blender_run import run_blender
    from usdrelight.stage.read import read_lights

    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    startTimeCode = 1
    endTimeCode = 5
    metersPerUnit = 1
    upAxis = "Y"
)
def CylinderLight "Tube" {
    float inputs:intensity.timeSamples = { 1: 2, 5: 10 }
    float inputs:radius = 0.05
    float inputs:length = 1
}
def Mesh "Panel" (
    prepend apiSchemas = ["MeshLightAPI"]
) {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(0,0,-2), (1,0,-2), (1,1,-2), (0,1,-2)]
    float inputs:exposure.timeSamples = { 1: 0, 5: 2 }
    float inputs:intensity = 3
}
def Camera "Cam" {
}
''')
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0, err
    (tmp_path / "probe.py").write_text(EMISSION_PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = {int(k): v for k, v in json.loads((tmp_path / "p.json").read_text()).items()}
    stage = open_stage(tmp_path / "s.usda")
    for f in range(1, 6):
        want = {l.path: emitted_radiance(l) for l in read_lights(stage, f)}
        tube = next(v for k, v in got[f].items() if "Tube" in k)
        panel = next(v for k, v in got[f].items() if "Panel" in k)
        np.testing.assert_allclose(tube, want["/Tube"], rtol=1e-5, err_msg=str(f))
        np.testing.assert_allclose(panel, want["/Panel"], rtol=1e-5, err_msg=str(f))
    panel3 = next(v for k, v in got[3].items() if "Panel" in k)
    assert panel3[0] == pytest.approx(3 * 2.0, rel=1e-5)  # exposure 1 at frame 3: 3 x 2^1, not (3 + 12) / 2
