"""A USD camera's depth of field (fStop, focusDistance): read as a thin lens, rendered by Mitsuba's thinlens
sensor (a blur of the size optics give), written to and read from Mitsuba XML, and set on Blender's camera."""
from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

W, H = 64, 48
FOCAL_MM, APERTURE_MM = 50.0, 36.0
FX = W * FOCAL_MM / APERTURE_MM  # focal length in pixels


def _stage(path, f_stop: float, focus: float | None, mpu: float = 1.0):
    """A camera at the origin looking down -Z at a plane 2 m away, white left of x = 0 and black right of it
    (an edge through the image's centre column), under a white dome."""
    u = 1.0 / mpu  # one metre in stage units
    lens = f"    float fStop = {f_stop}\n" + (f"    float focusDistance = {focus * u}\n" if focus else "")
    quads = ""
    for name, x0, x1, c in (("White", -3, 0, 1.0), ("Black", 0, 3, 0.0)):
        quads += f'''
def Mesh "{name}" {{
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [({x0 * u}, {-3 * u}, {-2 * u}), ({x1 * u}, {-3 * u}, {-2 * u}), ({x1 * u}, {3 * u}, {-2 * u}),
                        ({x0 * u}, {3 * u}, {-2 * u})]
    color3f[] primvars:displayColor = [({c}, {c}, {c})]
}}
'''
    path.write_text(f'''#usda 1.0
(
    metersPerUnit = {mpu}
    upAxis = "Y"
)
def Camera "Cam" {{
    float focalLength = {FOCAL_MM}
    float horizontalAperture = {APERTURE_MM}
    float verticalAperture = {APERTURE_MM * H / W}
    float2 clippingRange = ({0.01 * u}, {100 * u})
{lens}}}
def RenderSettings "Render" {{
    rel camera = </Cam>
    int2 resolution = ({W}, {H})
}}
def DomeLight "Sky" {{
    float inputs:intensity = 1
}}
{quads}''')
    return path


def test_the_camera_reads_as_a_thin_lens(tmp_path):
    """f = 50 mm at f/2.5 is an aperture of radius 10 mm; focusDistance in stage units -> metres."""
    scene = read_scene(open_stage(_stage(tmp_path / "cm.usda", 2.5, 1.5, mpu=0.01)))
    assert scene.camera.aperture_radius == pytest.approx(0.01)
    assert scene.camera.focus_distance == pytest.approx(1.5)
    assert any("depth of field" in w for w in scene.warnings)
    pinhole = read_scene(open_stage(_stage(tmp_path / "p.usda", 0.0, 1.5))).camera
    assert (pinhole.aperture_radius, pinhole.focus_distance) == (0.0, 0.0)
    unfocused = read_scene(open_stage(_stage(tmp_path / "u.usda", 2.0, None)))
    assert unfocused.camera.aperture_radius == 0.0 and any("focusDistance" in w for w in unfocused.warnings)


def _edge_width(img: np.ndarray) -> int:
    """Pixels of the middle rows' mean profile strictly between the white and black sides (5% to 95%)."""
    row = img[H // 2 - 6:H // 2 + 6, :, :3].mean(axis=(0, 2))
    white, black = row[:8].mean(), row[-8:].mean()
    v = (row - black) / (white - black)
    return int(np.count_nonzero((v > 0.05) & (v < 0.95)))


@pytest.mark.parametrize("f_stop, focus", [(0.0, None), (0.5, 2.0), (0.5, 0.5)])
def test_mitsuba_blurs_the_edge_by_the_circle_of_confusion(tmp_path, cli, f_stop, focus):
    """The edge 2 m away through a 50 mm f/0.5 lens (radius 50 mm): sharp at a pinhole and in focus at 2 m;
    focused at 0.5 m, each point spreads over a disk of diameter 2 r fx |1/2 - 1/0.5| = 13.3 px. Through the
    exported XML (Mitsuba's thinlens) and the stage read back from it (its fStop and focusDistance)."""
    import mitsuba as mi

    from usdrelight.mitsuba.runtime import load_mitsuba

    load_mitsuba()
    stage = _stage(tmp_path / "s.usda", f_stop, focus)
    cli.json("convert", stage, tmp_path / "s.xml")
    sensor = ET.parse(tmp_path / "s.xml").getroot().find("sensor")
    assert sensor.get("type") == ("thinlens" if f_stop else "perspective")
    img = np.asarray(mi.render(mi.load_file(str(tmp_path / "s.xml")), spp=256))
    width = _edge_width(img)
    if f_stop and focus != 2.0:
        c = 2 * (FOCAL_MM * 1e-3 / (2 * f_stop)) * FX * abs(1 / 2.0 - 1 / focus)
        assert 0.75 * c <= width <= c + 2, (width, c)
    else:
        assert width <= 2, width
    cli.json("convert", tmp_path / "s.xml", tmp_path / "back.usda")
    cam = read_scene(open_stage(tmp_path / "back.usda")).camera
    want = read_scene(open_stage(stage)).camera
    assert cam.aperture_radius == pytest.approx(want.aperture_radius, rel=1e-6)
    assert cam.focus_distance == pytest.approx(want.focus_distance, rel=1e-6)


BLEND_PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
d = bpy.context.scene.camera.data
json.dump({"use_dof": d.dof.use_dof, "fstop": d.dof.aperture_fstop, "focus": d.dof.focus_distance,
           "lens": d.lens}, open(args[1], "w"))
'''


def test_blender_camera_gets_the_same_thin_lens(tmp_path, cli):
    """.blend: depth of field on, Cycles' aperture radius lens / 1000 / (2 f-number) = the stage's 10 mm, focus
    at 1.5 m (a centimetre stage: in metres)."""
    from usdrelight.converters.blender import run_blender

    cli.json("convert", _stage(tmp_path / "cm.usda", 2.5, 1.5, mpu=0.01), tmp_path / "s.blend")
    (tmp_path / "probe.py").write_text(BLEND_PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = json.loads((tmp_path / "p.json").read_text())
    assert got["use_dof"] is True
    assert got["lens"] * 1e-3 / (2 * got["fstop"]) == pytest.approx(0.01, rel=1e-5)
    assert got["focus"] == pytest.approx(1.5, rel=1e-5)
    assert math.isclose(got["lens"], FOCAL_MM, rel_tol=1e-5)
