"""A glTF file's punctual lights and cameras become UsdLux lights and a USD camera (before: warned and dropped).
glTF lights are photometric (candela, lux), usdrelight's UsdLux radiometric: / 683 lm/W. Checked against the
closed form: a floor of albedo 0.5 under a point light 1 m above, seen by the file's own camera, gives
0.5 / pi * I / r^2 at the image centre in both renderers; a sun straight down gives 0.5 / pi * E."""
from __future__ import annotations

import math

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdLux

from test_gltf_extras import _glb
from usdrelight.engine import open_renderer
from usdrelight.stage.read import read_scene

DOWN = [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]  # -90 degrees about X: local -Z looks down world -Y


def _floor_doc(lights: list, light_nodes: list, camera: dict | None = None) -> tuple[dict, bytes]:
    pts = np.array([[-50, 0, 50], [50, 0, 50], [50, 0, -50], [-50, 0, -50]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    binary = pts.tobytes() + idx.tobytes()
    nodes = [{"mesh": 0, "name": "Floor"}] + light_nodes
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes,
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [{"name": "Grey", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0],
                                                                "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [-50, 0, -50],
                       "max": [50, 0, 50]},
                      {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
        "extensionsUsed": ["KHR_lights_punctual"],
        "extensions": {"KHR_lights_punctual": {"lights": lights}},
    }
    if camera is not None:
        doc["cameras"] = [camera]
        doc["nodes"].append({"name": "Cam", "camera": 0, "translation": [0, 1, 0], "rotation": DOWN})
        doc["scenes"][0]["nodes"].append(len(doc["nodes"]) - 1)
    return doc, binary


CAMERA = {"type": "perspective", "perspective": {"yfov": 0.6, "aspectRatio": 4 / 3, "znear": 0.01, "zfar": 100}}


@pytest.mark.parametrize("kind, expected", [("point", 0.5 / math.pi * 20.0), ("directional", 0.5 / math.pi * 3.0)])
def test_a_gltf_light_lights_the_floor_as_the_closed_form_says(kind, expected, tmp_path, cli):
    light = {"type": kind, "intensity": (20.0 if kind == "point" else 3.0) * 683.0, "color": [1, 1, 1]}
    node = {"name": "Lamp", "translation": [0, 1, 0], "rotation": DOWN,
            "extensions": {"KHR_lights_punctual": {"light": 0}}}
    doc, binary = _floor_doc([light], [node], CAMERA)
    _glb(tmp_path / "f.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "f.glb", tmp_path / "f.usda")
    assert rc == 0 and "not converted" not in err, err
    rec = read_scene(tmp_path / "f.usda")
    (lamp,) = rec.lights
    assert lamp.kind == ("sphere" if kind == "point" else "distant") and lamp.path == "/World/Lamp"
    k = rec.camera.intrinsics
    assert k.width / k.height == pytest.approx(4 / 3, rel=1e-3)
    assert 2 * math.degrees(math.atan(k.height / (2 * k.fy))) == pytest.approx(math.degrees(0.6), rel=1e-5)
    for engine in ("fast", "mitsuba"):
        beauty = open_renderer(rec, engine, max_side=32, spp=16).render(rec.lights).beauty
        h, w = beauty.shape[:2]
        centre = beauty[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean()
        assert centre == pytest.approx(expected, rel=0.02), (engine, centre, expected)


def test_a_spot_keeps_its_cones_and_names_never_collide(tmp_path, cli):
    spot = {"type": "spot", "intensity": 683.0, "color": [1.0, 0.5, 0.25],
            "spot": {"innerConeAngle": 0.2, "outerConeAngle": 0.5}, "range": 10.0}
    node = {"name": "Floor", "translation": [0, 2, 0], "rotation": DOWN,  # the mesh's name too
            "extensions": {"KHR_lights_punctual": {"light": 0}}}
    ortho = {"type": "orthographic", "orthographic": {"xmag": 1, "ymag": 1, "znear": 0.1, "zfar": 10}}
    doc, binary = _floor_doc([spot], [node], ortho)
    _glb(tmp_path / "s.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "s.glb", tmp_path / "s.usda")
    assert rc == 0, err
    assert "glTF light range (a cut-off hint: not kept" in err and "glTF 'orthographic' camera (not converted" in err
    stage = Usd.Stage.Open(str(tmp_path / "s.usda"))
    assert stage.GetPrimAtPath("/World/Floor").IsA(UsdGeom.Mesh)
    light = UsdLux.SphereLight(stage.GetPrimAtPath("/World/Floor_2"))
    shaping = UsdLux.ShapingAPI(light.GetPrim())
    assert shaping.GetShapingConeAngleAttr().Get() == pytest.approx(math.degrees(0.5))
    assert shaping.GetShapingConeSoftnessAttr().Get() == pytest.approx(1 - 0.2 / 0.5)
    (rec_light,) = read_scene(stage).lights
    from usdrelight.stage.lux import emitted_radiance, light_direction

    np.testing.assert_allclose(emitted_radiance(rec_light), [1.0, 0.5, 0.25], rtol=1e-6)  # 683 cd -> 1 W/sr
    np.testing.assert_allclose(light_direction(rec_light), [0, -1, 0], atol=1e-6)
    np.testing.assert_allclose(rec_light.to_world[:3, 3], [0, 2, 0], atol=1e-6)


@pytest.mark.parametrize("change, needle", [
    (lambda d: d["extensions"]["KHR_lights_punctual"]["lights"][0].update(intensity=-1), "intensity must be"),
    (lambda d: d["nodes"][1]["extensions"]["KHR_lights_punctual"].update(light=5), "names light 5"),
    (lambda d: d["nodes"][1].update(children=[1]), "reached twice"),
    (lambda d: d["nodes"][1].update(rotation=[0, 0, float("nan"), 1]), "not 4 finite numbers"),
])
def test_bad_light_values_are_one_error(change, needle, tmp_path, cli):
    node = {"name": "Lamp", "translation": [0, 1, 0], "extensions": {"KHR_lights_punctual": {"light": 0}}}
    doc, binary = _floor_doc([{"type": "point", "intensity": 10.0}], [node])
    change(doc)
    _glb(tmp_path / "b.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "b.glb", tmp_path / "b.usda")
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "b.usda").exists()


@pytest.mark.parametrize("suffix, z_up_cm", [(".glb", False), (".gltf", False), (".glb", True)])
def test_lights_and_camera_round_trip_through_gltf(suffix, z_up_cm, tmp_path, cli):
    """USD -> glTF -> USD keeps the point, spot and distant lights (radiant intensity, colour, place, direction,
    cone) and the camera's field of view; a rect light is named, not exported; a Z-up centimetre stage comes back
    in metres, Y up, with every light where it was."""
    from pxr import Gf

    from usd_scenes import looking_down_at_floor
    from usdrelight.stage.lux import emitted_radiance, light_direction

    stage = looking_down_at_floor(tmp_path / "a.usda", width=64, height=48)
    point = UsdLux.SphereLight.Define(stage, "/World/Bulb")
    point.CreateTreatAsPointAttr(True)
    point.CreateIntensityAttr(20.0)
    point.CreateColorAttr(Gf.Vec3f(1.0, 0.8, 0.5))
    UsdGeom.Xformable(point).AddTranslateOp().Set(Gf.Vec3d(0.5, 2, -1))
    spot = UsdLux.SphereLight.Define(stage, "/World/Spot")
    spot.CreateTreatAsPointAttr(True)
    spot.CreateIntensityAttr(5.0)
    UsdLux.ShapingAPI.Apply(spot.GetPrim()).CreateShapingConeAngleAttr(30.0)
    UsdLux.ShapingAPI(spot.GetPrim()).CreateShapingConeSoftnessAttr(0.25)
    UsdGeom.Xformable(spot).AddTranslateOp().Set(Gf.Vec3d(-1, 3, 0))
    UsdGeom.Xformable(spot).AddRotateXOp().Set(-60.0)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(3.0)
    sun.CreateAngleAttr(0.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-50, 20, 0))
    UsdLux.RectLight.Define(stage, "/World/Panel")
    if z_up_cm:
        UsdGeom.SetStageUpAxis(stage, "Z")
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "a.usda", tmp_path / f"b{suffix}")
    assert rc == 0 and "rect lights in a glTF file (not exported" in err and "camera in a" not in err, err
    rc, _, err = cli("convert", tmp_path / f"b{suffix}", tmp_path / "c.usda")
    assert rc == 0, err
    a, c = read_scene(tmp_path / "a.usda"), read_scene(tmp_path / "c.usda")  # both in metres
    turn = np.eye(4)
    if z_up_cm:  # glTF is Y-up: (x, y, z) -> (x, z, -y)
        turn[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]
    assert c.up_axis == "Y" and c.meters_per_unit == 1.0
    la = {l.path.rsplit("/", 1)[-1]: l for l in a.lights if l.kind != "rect"}
    lc = {l.path.rsplit("/", 1)[-1]: l for l in c.lights}
    assert sorted(la) == sorted(lc) == ["Bulb", "Spot", "Sun"]
    for name, l in la.items():
        m = lc[name]
        np.testing.assert_allclose(emitted_radiance(m), emitted_radiance(l), rtol=1e-6, err_msg=name)
        np.testing.assert_allclose(m.to_world[:3, 3], turn[:3, :3] @ l.to_world[:3, 3], atol=1e-6, err_msg=name)
        np.testing.assert_allclose(light_direction(m), turn[:3, :3] @ light_direction(l), atol=1e-6, err_msg=name)
        assert m.kind == l.kind and m.cone_angle_deg == pytest.approx(l.cone_angle_deg) and \
            m.cone_softness == pytest.approx(l.cone_softness), name
    ka, kc = a.camera.intrinsics, c.camera.intrinsics
    assert kc.fy / kc.height == pytest.approx(ka.fy / ka.height, rel=1e-5)
    assert kc.width / kc.height == pytest.approx(ka.width / ka.height, rel=1e-5)
    rigid = a.camera.to_world.copy()
    rigid[:3, :3] /= np.linalg.norm(rigid[:3, :3], axis=0)
    np.testing.assert_allclose(c.camera.to_world, turn @ rigid, atol=1e-6)


def test_a_camera_without_aspect_ratio_is_warned(tmp_path, cli):
    """glTF leaves a missing aspectRatio to the viewport; it was read as 3:2 in silence."""
    cam = {"type": "perspective", "perspective": {"yfov": 0.6, "znear": 0.01}}
    doc, binary = _floor_doc([], [], cam)
    _glb(tmp_path / "a.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "a.glb", tmp_path / "a.usda")
    assert rc == 0 and "glTF camera without aspectRatio (the viewport's: read as 3:2" in err, err
    k = read_scene(tmp_path / "a.usda").camera.intrinsics
    assert k.width / k.height == pytest.approx(1.5, rel=1e-3)
    assert 2 * math.atan(k.height / (2 * k.fy)) == pytest.approx(0.6, rel=1e-3)  # yfov kept
