"""Animated lights through Blender: UsdLux time samples -> keyframed Blender lights -> Cycles at those frames agrees
with Mitsuba at those time codes; keyframes of a .blend -> USD time samples equal to them."""
from __future__ import annotations

import json

import numpy as np
import pytest

from usdrelight.converters.blender import blender_lights, read_from_file, render_blend, run_blender
from usdrelight.converters.blender_units import blender_light_to_usd
from usdrelight.converters.convert import convert
from usdrelight.engine import open_renderer
from usdrelight.imageio import read_map
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.read import read_lights, read_scene
from usdrelight.stage.records import FitProvenance, PointLightValue
from usdrelight.stage.validate import open_stage

from conftest import build_procedural

FRAMES = 12
SPP = 32


def _path(i: int) -> tuple[float, float, float]:
    return float(np.linspace(-1.2, 1.2, FRAMES)[i]), -0.6, -2.4


@pytest.fixture(scope="module")
def animated(tmp_path_factory):
    """The procedural photo stage (stride 2), a fitted point light, and a user point light moving along 12 time
    samples (24 fps) whose intensity also changes; converted to a .blend."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    d = tmp_path_factory.mktemp("blender_anim")
    scene = build_procedural(d / "st", stride=2)
    write_fitted_lights(d / "st", [PointLightValue(np.array([-0.5, 1.0, -2.0]), np.array([3.0, 3.0, 3.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    layer = Sdf.Layer.FindOrOpen(str(d / "st" / USER_LIGHTS))
    stage = Usd.Stage.Open(layer)
    stage.OverridePrim("/Scene")
    UsdGeom.Scope.Define(stage, "/Scene/Lights/User")
    light = UsdLux.SphereLight.Define(stage, "/Scene/Lights/User/Mover")
    light.CreateTreatAsPointAttr(True)
    light.CreateRadiusAttr(0.0)
    light.CreateNormalizeAttr(False)
    op = UsdGeom.Xformable(light).AddTranslateOp()
    intensity = light.CreateIntensityAttr()
    for i in range(FRAMES):
        op.Set(Gf.Vec3d(*_path(i)), Usd.TimeCode(1 + i))
        intensity.Set(2.0 + 0.25 * i, Usd.TimeCode(1 + i))
    layer.GetPrimAtPath("/Scene").specifier = Sdf.SpecifierOver
    layer.Save()
    convert(scene, d / "scene.blend", spp=SPP)
    return {"dir": d, "stage": scene, "blend": d / "scene.blend"}


def test_time_samples_become_keyframes(animated):
    lights = {b["name"]: b for b in blender_lights(animated["blend"])}
    mover = next(b for b in lights.values() if b.get("usd_path") == "/Scene/Lights/User/Mover")
    assert [f for f, _ in mover["keys"]] == [float(1 + i) for i in range(FRAMES)]
    for i, (f, key) in enumerate(mover["keys"]):
        u = blender_light_to_usd(key, "Y", 1.0)
        np.testing.assert_allclose(np.asarray(u["matrix"])[:3, 3], _path(i), atol=1e-5)
        assert u["intensity"] == pytest.approx(2.0 + 0.25 * i, rel=1e-5)
    fitted = next(b for b in lights.values() if b.get("usd_path", "").startswith("/Scene/Lights/Fitted/"))
    assert "keys" not in fitted  # a light without samples gets no keyframes
    assert lights and blender_lights(animated["blend"]).animation == {"frame_start": 1, "frame_end": 12,
                                                                         "fps": 24.0}


def test_keyframes_come_back_as_time_samples(animated, tmp_path):
    """.blend -> lights_user.usda: the animated light's samples at the keyframes' time codes, equal to them."""
    read = read_from_file(animated["blend"], usd_path=str(tmp_path / "back.usda"))
    stage = read.stage
    lights = {l.path.rsplit("/", 1)[1]: l for l in read_lights(stage, 5)}
    mover = next(n for n in lights if "Mover" in n)
    prim = stage.GetPrimAtPath(f"/Scene/Lights/User/{mover}")
    assert prim.GetAttribute("xformOp:transform").GetTimeSamples() == [float(1 + i) for i in range(FRAMES)]
    for i in range(FRAMES):
        rec = next(l for l in read_lights(stage, 1 + i) if mover in l.path)
        np.testing.assert_allclose(rec.to_world[:3, 3], _path(i), atol=1e-5)
        np.testing.assert_allclose(rec.radiance, 2.0 + 0.25 * i, rtol=1e-5)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetFramesPerSecond()) == (1, 12, 24)


def test_cycles_at_frames_agrees_with_mitsuba_at_time_codes(animated):
    d = animated["dir"]
    rec = read_scene(animated["stage"])
    for frame in (1, FRAMES):
        cyc = read_map(render_blend(animated["blend"], d / f"cycles_{frame}.exr", frame=frame), 4)[..., :3]
        lights = read_lights(open_stage(animated["stage"]), frame)
        mit = open_renderer(rec, "mitsuba", max_side=max(rec.resolution), spp=SPP, max_depth=3).render(lights)
        assert cyc.shape == mit.beauty.shape
        assert cyc.mean() == pytest.approx(mit.beauty.mean(), rel=0.05), frame


def test_a_keyframed_blend_gives_time_samples_equal_to_its_keys(tmp_path):
    """A .blend keyed in Blender itself (no usdrelight stage behind it): location and power at frames 1, 5, 9
    (Blender's default Bezier keys: read at every frame from 1 to 9, so USD's linear interpolation follows the
    easing; tests/test_blender_probe_fixes.py checks the frames between)."""
    script = tmp_path / "make.py"
    script.write_text(r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
scene.render.fps = 30
light = bpy.data.lights.new("Key", "POINT")
obj = bpy.data.objects.new("Key", light)
scene.collection.objects.link(obj)
for f, x, p in ((1, 0.0, 100.0), (5, 1.0, 200.0), (9, 3.0, 50.0)):
    obj.location = (x, 2.0, 1.5)
    obj.keyframe_insert("location", frame=f)
    light.energy = p
    light.keyframe_insert("energy", frame=f)
scene.frame_start, scene.frame_end = 1, 9
bpy.ops.wm.save_as_mainfile(filepath=args[0])
''')
    run_blender(script, str(tmp_path / "keyed.blend"))
    stage = read_from_file(tmp_path / "keyed.blend").stage
    prim = stage.GetPrimAtPath("/Scene/Lights/User/Key")
    assert prim.GetAttribute("xformOp:transform").GetTimeSamples() == [float(f) for f in range(1, 10)]
    for f, x, p in ((1, 0.0, 100.0), (5, 1.0, 200.0), (9, 3.0, 50.0)):
        rec = read_lights(stage, f)[0]
        # Blender Z-up (x, 2, 1.5) -> USD Y-up (x, 1.5, -2); a point light of P watts: I = P / (4 pi) W/sr
        np.testing.assert_allclose(rec.to_world[:3, 3], [x, 1.5, -2.0], atol=1e-6)
        np.testing.assert_allclose(rec.radiance, p / (4 * np.pi), rtol=1e-6)
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetFramesPerSecond()) == (1, 9, 30)


PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
out = {}
for f in (1, 13, 24):
    sc.frame_set(f)
    cube = next(o for o in sc.objects if o.type == "MESH")
    vs = [cube.matrix_world @ v.co for v in cube.data.vertices]
    out[f] = {"camera": list(sc.camera.matrix_world.translation),
              "cube": [sum(v[i] for v in vs) / len(vs) for i in range(3)],
              "size": max(v[0] for v in vs) - min(v[0] for v in vs)}
json.dump(out, open(args[1], "w"))
'''


def test_the_camera_and_a_rigid_mesh_follow_their_transform_samples_in_blender(cli, tmp_path):
    """An animated camera (dolly in) and a cube that slides and grows, in a Y-up stage in centimetres: the .blend
    keys both (they were frozen at frame 1 while only the lights moved); Blender is Z up, in metres."""
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 0.01
    startTimeCode = 1
    endTimeCode = 24
)
def Camera "Cam" {
    double3 xformOp:translate.timeSamples = { 1: (0, 100, 500), 24: (0, 100, 200) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Xform "Rig" {
    double3 xformOp:translate.timeSamples = { 1: (-200, 0, 0), 24: (200, 0, 0) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
    def Cube "Box" {
        double size = 50
        float3 xformOp:scale.timeSamples = { 1: (1, 1, 1), 24: (2, 2, 2) }
        uniform token[] xformOpOrder = ["xformOp:scale"]
    }
}
def SphereLight "Lamp" {
    float inputs:intensity = 10
    bool treatAsPoint = 1
}
''')
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0, err
    probe = tmp_path / "probe.py"
    probe.write_text(PROBE)
    run_blender(probe, str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = {int(k): v for k, v in json.loads((tmp_path / "p.json").read_text()).items()}
    # USD (x, y, z) cm, Y up -> Blender (x, -z, y) m, Z up
    np.testing.assert_allclose(got[1]["camera"], [0, -5.0, 1.0], atol=1e-4)
    np.testing.assert_allclose(got[24]["camera"], [0, -2.0, 1.0], atol=1e-4)
    np.testing.assert_allclose(got[13]["camera"], [0, -5.0 + 3.0 * 12 / 23, 1.0], atol=1e-4)  # linear
    np.testing.assert_allclose(got[1]["cube"], [-2.0, 0, 0], atol=1e-4)
    np.testing.assert_allclose(got[24]["cube"], [2.0, 0, 0], atol=1e-4)
    assert got[1]["size"] == pytest.approx(0.5, rel=1e-4) and got[24]["size"] == pytest.approx(1.0, rel=1e-4)


def test_a_camera_under_a_scope_under_a_turning_xform_follows_the_turn_in_blender(cli, tmp_path):
    """Samples at frames 1 and 24 only, a rotation between: USD turns the camera along the circle, so Blender
    needs a key per frame (keys at the samples alone cut the chord: radius 1.41 halfway); an animated Xform above
    a Scope still moves what is below it (it was not keyed at all)."""
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Xform "World" {
    float xformOp:rotateY.timeSamples = { 1: 0, 24: 90 }
    uniform token[] xformOpOrder = ["xformOp:rotateY"]
    def Scope "Geo" {
        def Camera "Cam" {
            double3 xformOp:translate = (2, 0, 0)
            uniform token[] xformOpOrder = ["xformOp:translate"]
        }
    }
}
''')
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0, err
    probe = tmp_path / "probe.py"
    probe.write_text("import bpy, json, sys\nargs = sys.argv[sys.argv.index('--') + 1:] if '--' in sys.argv "
                     "else sys.argv[1:]\nbpy.ops.wm.open_mainfile(filepath=args[0])\nsc = bpy.context.scene\n"
                     "out = {}\nfor f in (1, 12, 24):\n    sc.frame_set(f)\n"
                     "    out[f] = list(sc.camera.matrix_world.translation)\njson.dump(out, open(args[1], 'w'))\n")
    run_blender(probe, str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = {int(k): np.asarray(v) for k, v in json.loads((tmp_path / "p.json").read_text()).items()}
    for f in (1, 12, 24):  # USD: rotateY(a) of (2, 0, 0) = (2 cos a, 0, -2 sin a); Blender (x, -z, y)
        a = np.radians(90.0 * (f - 1) / 23)
        np.testing.assert_allclose(got[f], [2 * np.cos(a), 2 * np.sin(a), 0.0], atol=1e-4, err_msg=str(f))


ZOOM_PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
nodes = sc.world.node_tree.nodes
mapping = next(n for n in nodes if n.type == "MAPPING")
tint = next(n for n in nodes if n.type == "VECT_MATH")
spot = next(o for o in sc.objects if o.type == "LIGHT")
out = {}
for f in (1, 4, 7, 10):
    sc.frame_set(f)
    out[f] = {"lens": sc.camera.data.lens, "shift_x": sc.camera.data.shift_x,
              "rotation": [list(r) for r in mapping.inputs["Rotation"].default_value.to_matrix()],
              "rgb": list(tint.inputs[1].default_value), "spot": list(spot.matrix_world.to_3x3().col[2])}
sc.render.resolution_x, sc.render.resolution_y, sc.cycles.samples = 8, 6, 16
sc.render.image_settings.file_format, sc.render.image_settings.color_depth = "OPEN_EXR", "32"
for f in (1, 10):
    sc.frame_set(f)
    sc.render.filepath = args[2] + f"{f}.exr"
    bpy.ops.render.render(write_still=True)
json.dump(out, open(args[1], "w"))
'''


def test_a_zoom_a_turning_textured_dome_and_a_turning_spot_are_keyed_in_blender(cli, tmp_path):
    """A camera zooming (focalLength 20 -> 40 mm, an aperture offset too), a textured dome brightening (1 -> 3)
    while it turns half round about Y, a spot turning from straight down to horizontal, two samples each: the
    .blend has them at every frame, equal to what the stage gives there (before: the lens and the dome kept their
    first sample, warned; a turning light was keyed at its two samples only). Cycles' floor under the dome alone
    (the spot at 0 W): 3x as bright at frame 10 as at frame 1 (a turn about the vertical keeps the floor's
    irradiance)."""
    from usd_scenes import asymmetric_latlong

    from usdrelight.converters.blender_units import camera_lens, focal_length
    from usdrelight.converters.blender_units import Y_UP_TO_Z_UP, light_to_blender
    from usdrelight.imageio import write_image
    from usdrelight.stage.lux import light_direction
    from usdrelight.stage.read import read_camera

    write_image(tmp_path / "sky.exr", asymmetric_latlong(16, 32).astype(np.float32), "float")
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 1
    endTimeCode = 10
)
def Mesh "Floor" {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-5, 0, 5), (5, 0, 5), (5, 0, -5), (-5, 0, -5)]
    uniform token subdivisionScheme = "none"
}
def Camera "Cam" {
    float focalLength.timeSamples = { 1: 20, 10: 40 }
    float horizontalAperture = 36
    float verticalAperture = 27
    float horizontalApertureOffset.timeSamples = { 1: 0, 10: 2 }
    double3 xformOp:translate = (0, 1, 0)
    float xformOp:rotateX = -90
    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateX"]
}
def DomeLight "Sky" {
    asset inputs:texture:file = @./sky.exr@
    float inputs:intensity.timeSamples = { 1: 1, 10: 3 }
    float xformOp:rotateY.timeSamples = { 1: 0, 10: 180 }
    uniform token[] xformOpOrder = ["xformOp:rotateY"]
}
def SphereLight "Spot" (prepend apiSchemas = ["ShapingAPI"]) {
    float inputs:intensity = 0
    bool treatAsPoint = 1
    float inputs:shaping:cone:angle = 30
    double3 xformOp:translate = (0, 2, 0)
    float xformOp:rotateX.timeSamples = { 1: -90, 10: 0 }
    uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateX"]
}
''')
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0 and "first" not in err, err
    (tmp_path / "probe.py").write_text(ZOOM_PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"), str(tmp_path / "c_"))
    got = {int(k): v for k, v in json.loads((tmp_path / "p.json").read_text()).items()}
    stage = open_stage(tmp_path / "s.usda")
    for f, g in got.items():
        want = camera_lens(read_camera(stage, f), focal_length(stage, "/Cam", f))
        assert g["lens"] == pytest.approx(want["lens"], rel=1e-5) and g["lens"] == pytest.approx(20 + 20 * (f - 1) / 9)
        assert g["shift_x"] == pytest.approx(want["shift_x"], abs=1e-5), f
        lights = {l.kind: l for l in read_lights(stage, f)}
        dome = light_to_blender(lights["dome"])
        np.testing.assert_allclose(g["rgb"], dome["rgb"], rtol=1e-5, err_msg=str(f))
        np.testing.assert_allclose(g["rotation"], dome["rotation"], atol=1e-4, err_msg=str(f))
        # Blender's light points along its -Z, as the USD spot: its direction turned Z up
        np.testing.assert_allclose(-np.asarray(g["spot"]), Y_UP_TO_Z_UP[:3, :3] @ light_direction(lights["sphere"]),
                                   atol=1e-4, err_msg=str(f))
    assert got[4]["lens"] == pytest.approx(20 + 20 * 3 / 9, rel=1e-5)  # between the samples: linear, as USD
    first, last = (read_map(tmp_path / f"c_{f}.exr", 4)[..., :3].mean() for f in (1, 10))
    assert last / first == pytest.approx(3.0, rel=0.03), (first, last)
