"""Blender converter defects found by a probe, each checked in Blender (bpy 5.0.1 in .venv-blender) against USD:
a light invisible at the start frame, lights whose Blender values are not linear in USD's between samples
(exposure, colour temperature, held booleans), Blender's eased keys read back, the camera's lens for a portrait
image, and the objects a .blend -> USD conversion leaves out (warned). Powers in W, frames = time codes."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from usdrelight.converters.blender import read_from_file, run_blender, write_to_file
from usdrelight.converters.blender_units import light_to_blender
from usdrelight.converters.convert import convert
from usdrelight.stage.read import read_camera, read_lights
from usdrelight.stage.validate import open_stage

LIGHTS = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 1
    endTimeCode = 9
)
def Camera "Cam" {
    double3 xformOp:translate = (0, 1, 4)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Scope "Lights" {
    def DomeLight "Sky" {
        float inputs:intensity = 0.5
        token visibility.timeSamples = { 1: "inherited", 3: "invisible" }
    }
    def SphereLight "Late" {
        float inputs:intensity = 3
        bool treatAsPoint = 1
        token visibility.timeSamples = { 1: "invisible", 3: "inherited" }
        double3 xformOp:translate = (0.5, 0.5, -1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def SphereLight "Exp" {
        float inputs:intensity = 2
        float inputs:exposure.timeSamples = { 1: 0, 9: 4 }
        bool treatAsPoint = 1
        double3 xformOp:translate = (-0.5, 0.5, -1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def SphereLight "Temp" {
        float inputs:intensity = 1
        bool inputs:enableColorTemperature = 1
        float inputs:colorTemperature.timeSamples = { 1: 1500, 9: 10000 }
        bool treatAsPoint = 1
        double3 xformOp:translate = (0.5, 0.5, 1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def SphereLight "Warm" {
        float inputs:intensity = 1
        bool inputs:enableColorTemperature.timeSamples = { 1: 0, 5: 1 }
        float inputs:colorTemperature = 2000
        bool treatAsPoint = 1
        double3 xformOp:translate = (0, -0.5, -1)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
}
'''

LIGHT_PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
bg = next(n for n in sc.world.node_tree.nodes if n.type == "BACKGROUND")
out = {}
for f in json.loads(args[2]):
    sc.frame_set(int(f // 1), subframe=f - f // 1)
    out[repr(f)] = {o["usd_path"]: {"energy": o.data.energy, "color": list(o.data.color),
                                    "hide_render": o.hide_render, "hide_viewport": o.hide_viewport}
                    for o in sc.objects if o.type == "LIGHT"}
    out[repr(f)]["world"] = list(bg.inputs["Color"].default_value)[:3]
json.dump(out, open(args[1], "w"))
'''
FRAMES = [1.0, 2.0, 2.5, 3.0, 4.0, 4.5, 5.0, 7.0, 9.0]


@pytest.fixture(scope="module")
def keyed(tmp_path_factory):
    """LIGHTS converted to a .blend, and its lights as Blender evaluates them at FRAMES."""
    d = tmp_path_factory.mktemp("probe_lights")
    (d / "s.usda").write_text(LIGHTS)
    convert(d / "s.usda", d / "s.blend")
    (d / "probe.py").write_text(LIGHT_PROBE)
    run_blender(d / "probe.py", str(d / "s.blend"), str(d / "p.json"), json.dumps(FRAMES))
    got = {float(k): v for k, v in json.loads((d / "p.json").read_text()).items()}
    return open_stage(d / "s.usda"), got


def _usd_emission(stage, path: str, f: float):
    """What Blender should show of the USD light at time code ``f``: power x colour (W), or None where invisible."""
    rec = next((l for l in read_lights(stage, f) if l.path == path), None)
    if rec is None:
        return None
    d = light_to_blender(rec)
    return d["power"] * np.asarray(d["color"])


def test_a_light_invisible_at_the_start_frame_is_in_the_blend_keyed_hidden(keyed):
    """visibility {1: invisible, 3: inherited}: the light was left out of the .blend (no object, no warning); now
    it is there, hidden in render and viewport at frames 1 to 2.5, shown from 3 with USD's 4 pi 3 = 37.70 W."""
    stage, got = keyed
    for f in FRAMES:
        late = got[f]["/Lights/Late"]
        assert late["hide_render"] is (f < 3) and late["hide_viewport"] is (f < 3), f
    assert got[3.0]["/Lights/Late"]["energy"] == pytest.approx(4 * math.pi * 3, rel=1e-6)
    np.testing.assert_allclose(got[5.0]["/Lights/Late"]["energy"] * np.asarray(got[5.0]["/Lights/Late"]["color"]),
                               _usd_emission(stage, "/Lights/Late", 5.0), rtol=1e-5)


def test_exposure_colour_temperature_and_a_held_bool_match_usd_between_samples(keyed):
    """Keyed at the samples alone (here 1, 3, 5, 9: every light's sample times), Blender interpolated what USD does
    not interpolate linearly: exposure {1: 0, 9: 4} at intensity 2 gave 251.3 W at frame 7 (USD 2^3 x 2 x 4 pi =
    201.1 W; 213.6 W at 5 against 100.5 W with samples at 1 and 9 alone); colorTemperature {1: 1500, 9: 10000} a
    tint at 7 (blue / red 1.127, USD's 7875 K 1.282); enableColorTemperature {1: 0, 5: 1} warm at frame 4 (blue /
    red 0.50) instead of white; a dome's visibility {1: inherited, 3: invisible} faded it from 2 to 3. Now equal
    to USD at every whole frame, and the held values held between frames."""
    stage, got = keyed
    exp = got[7.0]["/Lights/Exp"]
    assert exp["energy"] == pytest.approx(2 * 2 ** 3 * 4 * math.pi, rel=1e-5)  # 201.06 W (was 251.3)
    temp = np.asarray(got[7.0]["/Lights/Temp"]["color"])
    want = _usd_emission(stage, "/Lights/Temp", 7.0)
    assert temp[1] / temp[0] == pytest.approx(want[1] / want[0], rel=1e-4)  # 1.040 (was 0.975)
    assert temp[2] / temp[0] == pytest.approx(want[2] / want[0], rel=1e-4)  # 1.282 (was 1.127)
    for f in (1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 9.0):
        for path in ("/Lights/Exp", "/Lights/Temp", "/Lights/Warm"):
            b = got[f][path]
            np.testing.assert_allclose(b["energy"] * np.asarray(b["color"]), _usd_emission(stage, path, f),
                                       rtol=1e-5, err_msg=f"{path} at {f}")
    for f in (1.0, 2.0, 2.5, 3.0, 4.5):  # the dome's visibility is held too: its colour 0.5 until 3 (was 0.125 at 2.5)
        assert got[f]["world"] == pytest.approx([0.5 if f < 3 else 0.0] * 3, abs=1e-6), f
    for f in (4.0, 4.5):  # USD holds enableColorTemperature 0 until 5: white (blue / red was 0.50 at 4)
        warm = got[f]["/Lights/Warm"]
        np.testing.assert_allclose(warm["color"], [1.0, 1.0, 1.0], rtol=1e-6, err_msg=str(f))
        np.testing.assert_allclose(warm["energy"] * np.asarray(warm["color"]),
                                   _usd_emission(stage, "/Lights/Warm", f), rtol=1e-5)


EASED = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
sc.frame_start, sc.frame_end = 1, 21
ease = bpy.data.lights.new("Ease", "POINT")
ob = bpy.data.objects.new("Ease", ease)
sc.collection.objects.link(ob)
for f, x, p in ((1, -1.0, 10.0), (21, 1.0, 100.0)):  # Blender's default keys: Bezier, auto-clamped handles
    ob.location = (x, 1.0, 0.5)
    ob.keyframe_insert("location", frame=f)
    ease.energy = p
    ease.keyframe_insert("energy", frame=f)
step = bpy.data.lights.new("Step", "POINT")
st = bpy.data.objects.new("Step", step)
sc.collection.objects.link(st)
for f, p in ((1, 10.0), (11, 100.0)):
    step.energy = p
    step.keyframe_insert("energy", frame=f)
from bpy_extras import anim_utils
ad = step.animation_data
for fc in anim_utils.action_get_channelbag_for_slot(ad.action, ad.action_slot).fcurves:
    for kp in fc.keyframe_points:
        kp.interpolation = "CONSTANT"
bpy.ops.wm.save_as_mainfile(filepath=args[0])
out = {}
for f in range(1, 22):
    sc.frame_set(f)
    out[f] = {"x": ob.matrix_world.translation.x, "ease": ease.energy, "step": step.energy}
json.dump(out, open(args[1], "w"))
'''


def test_eased_and_constant_blender_keys_come_back_as_blender_shows_them_at_every_frame(tmp_path):
    """Blender's default (Bezier) keys x -1 -> 1, 10 -> 100 W at frames 1 and 21 were read at the two keys
    alone: USD gave x -0.5 and 32.5 W at frame 6 where Blender shows -0.6875 and 24.06 W; CONSTANT keys 10 -> 100 W
    at 1 and 11 gave 91 W at frame 10 where Blender holds 10 W. Now sampled at every whole frame of the keys."""
    (tmp_path / "make.py").write_text(EASED)
    run_blender(tmp_path / "make.py", str(tmp_path / "k.blend"), str(tmp_path / "k.json"))
    shown = {int(k): v for k, v in json.loads((tmp_path / "k.json").read_text()).items()}
    read = read_from_file(tmp_path / "k.blend")
    assert not any("not read: .blend" in w for w in read.warnings)  # lights only: nothing left out
    stage = read.stage
    for f in range(1, 22):
        got = {l.path.rsplit("/", 1)[1]: l for l in read_lights(stage, f)}
        assert got["Ease"].to_world[0, 3] == pytest.approx(shown[f]["x"], abs=1e-5), f
        for name in ("Ease", "Step"):  # a point light of P W: I = P / (4 pi) W/sr
            assert got[name].radiance[0] * 4 * math.pi == pytest.approx(shown[f][name.lower()], rel=1e-5), (name, f)
    assert shown[6]["x"] == pytest.approx(-0.6875, abs=1e-4) and shown[6]["ease"] == pytest.approx(24.0625, rel=1e-4)
    assert shown[10]["step"] == pytest.approx(10.0)


def _camera_stage(width: int, height: int, focal: float, h_ap: float, v_ap: float) -> str:
    return f'''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    renderSettingsPrimPath = "/Render/Settings"
)
def Mesh "Tri" {{
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    uniform token subdivisionScheme = "none"
}}
def Camera "Cam" {{
    float focalLength = {focal}
    float horizontalAperture = {h_ap}
    float verticalAperture = {v_ap}
    float horizontalApertureOffset = 1.5
    float verticalApertureOffset = -2.5
    float2 clippingRange = (0.5, 50)
    double3 xformOp:translate = (0.3, 0.2, 5)
    float xformOp:rotateY = 10
    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateY"]
}}
def Scope "Render" {{
    def RenderSettings "Settings" {{
        rel camera = </Cam>
        int2 resolution = ({width}, {height})
    }}
}}
'''


CAMERA_PROBE = r'''
import bpy, json, sys
from bpy_extras.object_utils import world_to_camera_view
from mathutils import Vector
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
cam = sc.camera
W, H = sc.render.resolution_x, sc.render.resolution_y
uv = [list(world_to_camera_view(sc, cam, Vector(p))) for p in json.loads(args[2])]
json.dump({"lens": cam.data.lens, "sensor_width": cam.data.sensor_width, "sensor_fit": cam.data.sensor_fit,
           "pixels": [[x * W, (1 - y) * H] for x, y, _ in uv]}, open(args[1], "w"))
'''
POINTS = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -1.0], [-0.5, -0.3, 2.0], [0.3, 0.8, 1.0], [0.9, -0.7, 0.5]])


@pytest.mark.parametrize("name, size, focal, h_ap, v_ap, lens_before", [
    ("landscape", (64, 36), 30.0, 24.0, 13.5, 45.0),
    ("portrait", (36, 64), 30.0, 20.25, 36.0, 53.333)])
def test_camera_lens_is_the_focal_length_and_projects_as_usd(cli, tmp_path, name, size, focal, h_ap, v_ap,
                                                            lens_before):
    """lens = focalLength (mm), sensor_width = horizontalAperture, sensor fit HORIZONTAL: the portrait's lens
    was 53.33 mm on a 36 mm sensor (the view right, the lens 1.78x focalLength), the landscape's 45 mm. Five
    points projected by Blender (world_to_camera_view, shifts included) land where the USD camera puts them.
    The .blend's mesh and camera, the stage's own, are not read back and not warned (lights only)."""
    (tmp_path / "s.usda").write_text(_camera_stage(*size, focal, h_ap, v_ap))
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / f"{name}.blend")
    assert rc == 0, err
    (tmp_path / "probe.py").write_text(CAMERA_PROBE)
    blender_points = POINTS[:, [0, 2, 1]] * [1, -1, 1]  # Y-up (x, y, z) -> Z-up (x, -z, y)
    run_blender(tmp_path / "probe.py", str(tmp_path / f"{name}.blend"), str(tmp_path / "p.json"),
                json.dumps(blender_points.tolist()))
    got = json.loads((tmp_path / "p.json").read_text())
    assert got["lens"] == pytest.approx(focal, rel=1e-6) and got["lens"] != pytest.approx(lens_before, rel=1e-3)
    assert got["sensor_width"] == pytest.approx(h_ap, rel=1e-6) and got["sensor_fit"] == "HORIZONTAL"
    cam = read_camera(open_stage(tmp_path / "s.usda"))
    k = cam.intrinsics
    q = POINTS @ np.linalg.inv(cam.to_world)[:3, :3].T + np.linalg.inv(cam.to_world)[:3, 3]  # looks down -Z
    want = np.stack([k.cx + k.fx * q[:, 0] / -q[:, 2], k.cy - k.fy * q[:, 1] / -q[:, 2]], -1)
    np.testing.assert_allclose(got["pixels"], want, atol=1e-3)
    # made from a stage: its mesh and camera are the stage's own, not warned on the way back
    assert read_from_file(tmp_path / f"{name}.blend").warnings == {}


FOREIGN = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
for name, data in (("Lamp", bpy.data.lights.new("Lamp", "POINT")), ("Cam", bpy.data.cameras.new("Cam")),
                   ("Box", bpy.data.meshes.new("Box")), ("Box2", bpy.data.meshes.new("Box2"))):
    sc.collection.objects.link(bpy.data.objects.new(name, data))
bpy.ops.wm.save_as_mainfile(filepath=args[0])
'''


def test_a_foreign_blends_meshes_and_camera_are_named_as_not_read(tmp_path):
    """.blend -> USD carries lights only; a .blend made in Blender with meshes and a camera came back as its light
    alone with no warning at all."""
    (tmp_path / "make.py").write_text(FOREIGN)
    run_blender(tmp_path / "make.py", str(tmp_path / "f.blend"))
    read = read_from_file(tmp_path / "f.blend")
    assert read.warnings == {"2 mesh objects and 1 camera in f.blend are not read: .blend -> USD carries lights "
                             "only": 1}, read.warnings
    assert [p.GetName() for p in read.stage.Traverse() if p.GetTypeName() == "SphereLight"] == ["Lamp"]


EXPOSED = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Camera "Cam" {
    float exposure = 2
    float exposure:iso = 200
    double3 xformOp:translate = (0, 1, 4)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Camera "Witness" {
    double3 xformOp:translate = (3, 1, 4)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Sphere "Ball" {
}
'''

FILM_PROBE = '''import bpy, json, sys
argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=argv[0])
s = bpy.context.scene
json.dump({"film_exposure": s.cycles.film_exposure, "cameras": sorted(o.name for o in s.objects
                                                                      if o.type == "CAMERA")}, open(argv[1], "w"))
'''


def test_camera_exposure_is_cycles_film_exposure_and_other_cameras_are_named(tmp_path):
    """The USD camera's exposure (2 stops, iso 200: x8 on radiance) was dropped in the .blend (film exposure 1) and
    a second camera left out, both in silence."""
    (tmp_path / "s.usda").write_text(EXPOSED)
    res = convert(tmp_path / "s.usda", tmp_path / "s.blend")
    assert res.write_warnings.get("cameras other than the render camera /Cam (not converted: the target holds one)") == 1
    (tmp_path / "probe.py").write_text(FILM_PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = json.loads((tmp_path / "p.json").read_text())
    assert got["film_exposure"] == pytest.approx(8.0, rel=1e-6) and got["cameras"] == ["Cam"]


HELD = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 1
    endTimeCode = 5
)
def Camera "Cam" {
    double3 xformOp:translate.timeSamples = { 1: (0, 1, 4), 5: (2, 1, 4) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def SphereLight "Key" {
    float inputs:intensity.timeSamples = { 1: 1, 5: 5 }
    bool treatAsPoint = 1
    double3 xformOp:translate.timeSamples = { 1: (0, 2, 0), 5: (4, 2, 0) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
'''

HELD_PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
out = {}
for f in (1, 3, 5):
    sc.frame_set(f)
    light = next(o for o in sc.objects if o.type == "LIGHT")
    out[f] = {"light_x": light.matrix_world.translation.x, "energy": light.data.energy,
              "camera_x": sc.camera.matrix_world.translation.x}
json.dump(out, open(args[1], "w"))
'''


@pytest.mark.parametrize("interpolation", ["held", "linear"])
def test_a_held_stage_holds_every_key_in_blender(tmp_path, interpolation):
    """A stage set to Held interpolation (Usd.Stage.SetInterpolationType: a setting of the open stage, which a
    tool passes to the writer; a file cannot author it): USD keeps frame 1's light (x 0, 4 pi W) and camera (x 0)
    until frame 5; Blender interpolated its linear keys to x 2 / x 1 at frame 3. Now CONSTANT keys, as USD reads
    it; a linear stage keeps linear keys."""
    from pxr import Usd

    (tmp_path / "s.usda").write_text(HELD)
    stage = open_stage(tmp_path / "s.usda")
    if interpolation == "held":
        stage.SetInterpolationType(Usd.InterpolationTypeHeld)
    write_to_file(stage, tmp_path / "s.blend")
    (tmp_path / "probe.py").write_text(HELD_PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = json.loads((tmp_path / "p.json").read_text())["3"]
    light = next(l for l in read_lights(stage, 3.0) if l.path == "/Key")
    cam = read_camera(stage, 3.0)
    light_x, cam_x = float(light.to_world[0, 3]), float(cam.to_world[0, 3])
    assert (light_x, cam_x) == ((0.0, 0.0) if interpolation == "held" else (2.0, 1.0))
    assert got["light_x"] == pytest.approx(light_x, abs=1e-5)
    assert got["camera_x"] == pytest.approx(cam_x, abs=1e-5)
    assert got["energy"] == pytest.approx(light_to_blender(light)["power"], rel=1e-5)


def test_display_color_meshes_keep_their_own_colours(tmp_path):
    """Three meshes with only primvars:displayColor (red, green, blue): the .blend gave all three the first
    one's material (one key for every mesh without a bound material; Cycles rendered the green quad red)."""
    from usdrelight.converters.blender import scene_payload

    quads = "".join(f'''
def Mesh "Q{i}" {{
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [({i}, 0, 0), ({i + 1}, 0, 0), ({i + 1}, 1, 0), ({i}, 1, 0)]
    color3f[] primvars:displayColor = [({rgb})]
}}''' for i, rgb in enumerate(("0.8, 0.1, 0.1", "0.1, 0.8, 0.1", "0.1, 0.1, 0.8")))
    (tmp_path / "s.usda").write_text('#usda 1.0\n(\n    upAxis = "Y"\n    metersPerUnit = 1\n)\n' + quads + '''
def Camera "Cam" {
    double3 xformOp:translate = (1.5, 0.5, 4)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
''')
    payload, _ = scene_payload(open_stage(tmp_path / "s.usda"), tmp_path / "data")
    mats = {m["name"]: m for m in payload["materials"]}
    got = {m["usd_path"]: mats[m["material"]]["diffuse"] for m in payload["meshes"]}
    np.testing.assert_allclose(got["/Q0"], [0.8, 0.1, 0.1], rtol=1e-5)
    np.testing.assert_allclose(got["/Q1"], [0.1, 0.8, 0.1], rtol=1e-5)
    np.testing.assert_allclose(got["/Q2"], [0.1, 0.1, 0.8], rtol=1e-5)
