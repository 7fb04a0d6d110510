"""USD <-> Mitsuba XML: real Mitsuba scene files, round trips, bad input."""
import json
import math


import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade

from conftest import SHARED
from usd_scenes import camera, diffuse_material, new_stage
from usdrelight.intrinsics import Intrinsics
from usdrelight.stage.lux import emitted_radiance, light_direction
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.safe_paths import allow_paths
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import errors_only, open_stage, validate_stage

MITSUBA_DATA = SHARED / "mitsuba-data"
SPOT = MITSUBA_DATA / "tests" / "scenes" / "spot_light" / "test_spot_direct.xml"
SPHERES = MITSUBA_DATA / "tests" / "scenes" / "bsdf_spheres" / "test_roughplastic_linear_path.xml"


def _render_xml(path, spp=64):
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=spp))[..., :3]


def test_real_spot_scene_round_trips_through_usd(cli, tmp_path):
    rc, _, err = cli("convert", SPOT, tmp_path / "spot.usda", "--allow-path", MITSUBA_DATA)  # <path> ../../../common
    assert rc == 0, err
    assert "spot emitter texture" in err  # named, not dropped silently
    stage = open_stage(tmp_path / "spot.usda")
    assert errors_only(validate_stage(stage)) == []
    light = UsdLux.SphereLight(stage.GetPrimAtPath("/World/light_1"))
    assert light.GetTreatAsPointAttr().Get()
    # UsdLux has no projected texture: intensity x colour is the texture's mean over the cone (intensity 5 x mean)
    rgb = light.GetIntensityAttr().Get() * np.array(light.GetColorAttr().Get())
    kept = json.loads(light.GetPrim().GetCustomDataByKey("mitsuba"))
    np.testing.assert_allclose(rgb, 5.0 * np.array(kept["texture_mean"]), rtol=1e-5)
    assert 0.1 < min(kept["texture_mean"]) and max(kept["texture_mean"]) < 0.9
    assert UsdLux.ShapingAPI(light).GetShapingConeAngleAttr().Get() == pytest.approx(20.0)
    # the kept texture lies outside the USD file's folder: read only under --allow-path, as every other asset
    rc, _, err = cli("convert", tmp_path / "spot.usda", tmp_path / "spot.xml")
    assert rc == 2 and "spot texture (/World/light_1)" in err and "--allow-path" in err, err
    assert cli("convert", tmp_path / "spot.usda", tmp_path / "spot.xml", "--allow-path", MITSUBA_DATA)[0] == 0
    original, ours = _render_xml(SPOT), _render_xml(tmp_path / "spot.xml")
    ref = np.array(load_mitsuba().Bitmap(str(SPOT.parent / "refs" / "test_spot_ref_rgb.exr")))[..., :3]
    assert ours.mean() == pytest.approx(original.mean(), rel=0.05)
    assert ours.mean() == pytest.approx(ref.mean(), rel=0.05)
    assert np.abs(ours - original).mean() < 0.02 * original.mean()  # per pixel, not only on average
    # What another USD tool sees (the kept texture dropped): an untextured spot of the same power
    light.GetPrim().ClearCustomDataByKey("mitsuba")
    stage.GetRootLayer().Export(str(tmp_path / "spot_usd_only.usda"))
    assert cli("convert", tmp_path / "spot_usd_only.usda", tmp_path / "alone" / "spot.xml")[0] == 0
    alone = _render_xml(tmp_path / "alone" / "spot.xml")
    assert alone.mean() == pytest.approx(original.mean(), rel=0.03)


def test_missing_referenced_file_is_a_clear_error(cli, tmp_path):
    rc, out, err = cli("convert", SPHERES, tmp_path / "s.usda", "--allow-path", MITSUBA_DATA)
    assert rc == 2 and "museum.exr" in err and "not found" in err and "Traceback" not in err
    assert not (tmp_path / "s.usda").exists()


@pytest.mark.parametrize("doc", [
    '<?xml version="1.0"?>\n<!DOCTYPE scene [<!ENTITY xxe SYSTEM "file:///etc/passwd">]>\n'
    '<scene version="3.0.0"><string name="x" value="&xxe;"/></scene>',
    '<!DOCTYPE lolz [<!ENTITY lol "lol"><!ENTITY lol2 "&lol;&lol;&lol;&lol;">]><scene>&lol2;</scene>',
])
def test_entities_are_never_expanded(cli, tmp_path, doc):
    (tmp_path / "evil.xml").write_text(doc)
    rc, out, err = cli("convert", tmp_path / "evil.xml", tmp_path / "o.usda")
    assert rc == 2 and "entity" in err.lower() and "root:" not in err
    assert not (tmp_path / "o.usda").exists()


@pytest.mark.parametrize("doc,needle", [
    ("<scene><shape type='obj'>", "malformed XML"),
    ("<notascene/>", "root element"),
    ("<scene><shape type='obj'><string name='filename' value='nope.obj'/></shape></scene>", "nope.obj"),
    ("<scene><emitter type='point'><rgb name='intensity' value='$power'/></emitter></scene>", "$power"),
    ("<scene><shape type='sphere'><ref id='nothing'/></shape></scene>", "nothing"),
])
def test_bad_xml_inputs(cli, tmp_path, doc, needle):
    (tmp_path / "bad.xml").write_text(doc)
    rc, out, err = cli("convert", tmp_path / "bad.xml", tmp_path / "o.usda")
    assert rc == 2 and needle in err and len(err.strip().splitlines()) >= 1 and "Traceback" not in err


def test_unknown_suffix_and_bad_usd(cli, tmp_path):
    (tmp_path / "a.txt").write_text("x")
    rc, _, err = cli("convert", tmp_path / "a.txt", tmp_path / "b.usda")
    assert rc == 2 and "no converter" in err
    (tmp_path / "bad.usda").write_text("#usda 1.0\ndef X \"A\" {\n")
    rc, _, err = cli("convert", tmp_path / "bad.usda", tmp_path / "b.xml")
    assert rc == 2 and "cannot open stage" in err


FEATURE_XML = """<scene version="3.0.0">
    <default name="spp" value="32"/>
    <default name="albedo" value="0.6"/>
    <path value="{common}"/>
    <integrator type="moment"><integrator type="path"><integer name="max_depth" value="3"/></integrator></integrator>
    <bsdf type="diffuse" id="white"><rgb name="reflectance" value="$albedo"/></bsdf>
    <sensor type="perspective">
        <float name="fov" value="45"/><string name="fov_axis" value="y"/>
        <transform name="to_world"><lookat origin="0, 1, 6" target="0, 0.5, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="40"/><integer name="height" value="30"/><rfilter type="box"/></film>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/></transform>
        <ref id="white"/>
    </shape>
    <shape type="obj">
        <string name="filename" value="meshes/sphere.obj"/>
        <transform name="to_world"><scale value="0.5"/><translate x="-1" y="0.5" z="0"/></transform>
        <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.5, 0.3"/></bsdf></bsdf>
    </shape>
    <include filename="fragment.xml"/>
    <shape type="cube">
        <transform name="to_world"><matrix value="0.4 0 0 1  0 0.4 0 0.4  0 0 0.4 0  0 0 0 1"/></transform>
        <ref id="white"/>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><scale x="0.5" y="0.5" z="1"/><rotate x="1" angle="90"/><translate y="3"/></transform>
        <emitter type="area"><rgb name="radiance" value="8, 7, 6"/></emitter>
    </shape>
    <emitter type="point"><point name="position" x="2" y="2" z="2"/><rgb name="intensity" value="6"/></emitter>
    <emitter type="directional"><vector name="direction" value="0.3, -1, -0.2"/><rgb name="irradiance" value="0.8"/></emitter>
    <emitter type="constant"><rgb name="radiance" value="0.05"/></emitter>
</scene>
"""
FRAGMENT_XML = """<scene version="3.0.0">
    <shape type="sphere"><point name="center" value="0, 0.35, 1"/><float name="radius" value="0.35"/><ref id="white"/></shape>
    <shape type="disk"><transform name="to_world"><scale value="0.3"/><rotate x="1" angle="-90"/><translate x="1.5" y="0.01" z="1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.2, 0.2"/></bsdf></shape>
</scene>
"""


def test_xml_features_round_trip_renders_alike(cli, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    (src / "scene.xml").write_text(FEATURE_XML.format(common=MITSUBA_DATA / "common"))
    (src / "fragment.xml").write_text(FRAGMENT_XML)
    allow = ("--allow-path", MITSUBA_DATA / "common")  # the scene's <path> and its meshes/textures
    rc, _, err = cli("convert", src / "scene.xml", tmp_path / "usd" / "scene.usda", *allow)
    assert rc == 0, err
    stage = open_stage(tmp_path / "usd" / "scene.usda")
    assert errors_only(validate_stage(stage)) == []
    with allow_paths([MITSUBA_DATA / "common"]):
        rec = read_scene(stage)
    kinds = sorted(l.kind for l in rec.lights)
    assert kinds == ["distant", "dome", "rect", "sphere"]
    assert len(rec.meshes) == 3 and sorted(s.kind for s in rec.shapes) == ["cube", "sphere"]
    assert rec.camera.intrinsics.fy == pytest.approx(30 / (2 * math.tan(math.radians(22.5))), rel=1e-5)
    assert cli("convert", tmp_path / "usd" / "scene.usda", tmp_path / "out" / "scene.xml", *allow)[0] == 0
    a, b = _render_xml(src / "scene.xml", 128), _render_xml(tmp_path / "out" / "scene.xml", 128)
    assert b.mean() == pytest.approx(a.mean(), rel=0.05)
    assert np.abs(a - b).mean() < 0.1 * a.mean()


def _rich_stage(path, tex):
    stage = new_stage(path)
    looks = "/World/Looks"
    UsdGeom.Scope.Define(stage, looks)
    mat = diffuse_material(stage, looks + "/Tex", texture=str(tex))
    m = UsdGeom.Mesh.Define(stage, "/World/Quad")
    m.CreatePointsAttr([(-1, 0, 1), (1, 0, 1), (1, 0, -1), (-1, 0, -1)])
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    m.CreateNormalsAttr([(0, 1, 0)] * 4)
    m.SetNormalsInterpolation("vertex")
    UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, "vertex").Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    x = UsdGeom.Xformable(m)
    x.AddTranslateOp().Set(Gf.Vec3d(0.5, -1, 0))
    x.AddScaleOp().Set(Gf.Vec3f(2, 1, 3))
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(mat)
    metal = UsdShade.Material.Define(stage, looks + "/Metal")
    sh = UsdShade.Shader.Define(stage, looks + "/Metal/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.9, 0.6, 0.3))
    sh.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(1.0)
    sh.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.3)
    metal.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    ball = UsdGeom.Sphere.Define(stage, "/World/Ball")
    ball.CreateRadiusAttr(0.5)
    UsdGeom.Xformable(ball).AddTranslateOp().Set(Gf.Vec3d(0, 0.5, -1))
    UsdShade.MaterialBindingAPI.Apply(ball.GetPrim()).Bind(metal)
    s = UsdLux.SphereLight.Define(stage, "/World/Bulb")
    s.CreateRadiusAttr(0.25)
    s.CreateIntensityAttr(30)
    s.CreateExposureAttr(1.0)
    s.CreateColorAttr((1.0, 0.8, 0.6))
    s.CreateNormalizeAttr(True)
    UsdGeom.Xformable(s).AddTranslateOp().Set(Gf.Vec3d(1, 2, 0))
    p = UsdLux.SphereLight.Define(stage, "/World/Spot")
    p.CreateTreatAsPointAttr(True)
    p.CreateIntensityAttr(12)
    p.CreateEnableColorTemperatureAttr(True)
    p.CreateColorTemperatureAttr(3500)
    sh = UsdLux.ShapingAPI.Apply(p.GetPrim())
    sh.CreateShapingConeAngleAttr(30)
    sh.CreateShapingConeSoftnessAttr(0.2)
    x = UsdGeom.Xformable(p)
    x.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    x.AddRotateXOp().Set(-80)
    d = UsdLux.DiskLight.Define(stage, "/World/Disk")
    d.CreateRadiusAttr(0.3)
    d.CreateIntensityAttr(5)
    UsdGeom.Xformable(d).AddTranslateOp().Set(Gf.Vec3d(-2, 1, 0))
    r = UsdLux.RectLight.Define(stage, "/World/Panel")
    r.CreateWidthAttr(1.5)
    r.CreateHeightAttr(0.5)
    r.CreateIntensityAttr(4)
    x = UsdGeom.Xformable(r)
    x.AddTranslateOp().Set(Gf.Vec3d(0, 2, 2))
    x.AddRotateYOp().Set(30)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.5)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-60, 20, 0))
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(str(SHARED / "hdri" / "forest.exr"))
    dome.CreateIntensityAttr(0.7)
    UsdGeom.Xformable(dome).AddRotateYOp().Set(45)
    camera(stage, Intrinsics(50.0, 50.0, 36.0, 22.0, 64, 48), translate=(0.2, 1.0, 5.0), rotate_x_deg=-10)
    stage.GetRootLayer().Save()
    return stage


def test_usd_xml_usd_keeps_values(cli, tmp_path):
    tex = tmp_path / "albedo.exr"
    from usdrelight.imageio import write_image

    write_image(tex, np.random.default_rng(0).random((8, 8, 3)), "half")
    _rich_stage(tmp_path / "a.usda", tex)
    hdri = ("--allow-path", SHARED / "hdri")  # the dome's texture lies outside the stage's folder
    assert cli("convert", tmp_path / "a.usda", tmp_path / "x" / "scene.xml", *hdri)[0] == 0
    assert cli("convert", tmp_path / "x" / "scene.xml", tmp_path / "b.usda")[0] == 0  # textures copied beside it
    with allow_paths([SHARED / "hdri"]):
        a, b = read_scene(open_stage(tmp_path / "a.usda")), read_scene(open_stage(tmp_path / "b.usda"))
    # camera: intrinsics and pose
    for k in ("fx", "fy", "cx", "cy", "width", "height"):
        assert getattr(b.camera.intrinsics, k) == pytest.approx(getattr(a.camera.intrinsics, k), rel=1e-5)
    np.testing.assert_allclose(b.camera.to_world, a.camera.to_world, atol=1e-5)
    # lights: same kinds, emitted radiance, positions and directions
    la = {l.kind + str(l.treat_as_point): l for l in a.lights}
    lb = {l.kind + str(l.treat_as_point): l for l in b.lights}
    assert sorted(la) == sorted(lb)
    for k, l in la.items():
        m = lb[k]
        np.testing.assert_allclose(emitted_radiance(m), emitted_radiance(l), rtol=1e-5, err_msg=k)
        np.testing.assert_allclose(m.to_world[:3, 3], l.to_world[:3, 3], atol=1e-5, err_msg=k)
        if l.kind in ("disk", "rect", "distant") or l.cone_angle_deg is not None:
            np.testing.assert_allclose(light_direction(m), light_direction(l), atol=1e-5, err_msg=k)
    assert lb["sphereTrue"].cone_angle_deg == pytest.approx(30.0)
    assert lb["sphereTrue"].cone_softness == pytest.approx(0.2, abs=1e-6)
    assert lb["sphereFalse"].radius == pytest.approx(0.25, rel=1e-5)
    assert lb["rectFalse"].width * np.linalg.norm(lb["rectFalse"].to_world[:3, 0]) == pytest.approx(1.5, rel=1e-5)
    np.testing.assert_allclose(lb["domeFalse"].to_world[:3, :3], la["domeFalse"].to_world[:3, :3], atol=1e-6)
    assert lb["domeFalse"].texture is not None
    # mesh: world-space points, uvs, material
    ma, mb = a.meshes[0], b.meshes[0]
    np.testing.assert_allclose(np.sort(mb.points, 0), np.sort(ma.points, 0), atol=1e-5)
    np.testing.assert_allclose(np.sort(mb.uv, 0), np.sort(ma.uv, 0), atol=1e-6)
    assert mb.material.is_lambertian and mb.material.diffuse.path.endswith("albedo.exr")
    ball_a, ball_b = a.shapes[0], b.shapes[0]
    np.testing.assert_allclose(ball_b.to_world, ball_a.to_world, atol=1e-6)
    assert ball_b.material.metallic == 1.0 and ball_b.material.roughness == pytest.approx(0.3, rel=1e-5)
    np.testing.assert_allclose(ball_b.material.diffuse, (0.9, 0.6, 0.3), rtol=1e-6)
