"""USD -> Blender (real bpy 5.0.1 in .venv-blender, Cycles on the CPU) and Blender lights -> USD."""
import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from conftest import EXAMPLES
from usd_scenes import add_closed_form_light, asymmetric_latlong, camera, looking_down_at_floor, new_stage
from usdrelight.converters.blender import blender_lights, render_blend, run_blender
from usdrelight.stage.lux import emitted_radiance
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage
from usdrelight.imageio import read_map
from usdrelight.intrinsics import Intrinsics


def _centre(img):
    h, w = img.shape[:2]
    return img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean((0, 1))


@pytest.mark.parametrize("light", ["point", "dome", "distant"])
def test_closed_forms_in_cycles(cli, tmp_path, light):
    stage = looking_down_at_floor(tmp_path / "s.usda")
    expected = add_closed_form_light(stage, light)
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0, err
    img = read_map(render_blend(tmp_path / "s.blend", tmp_path / "s.exr", spp=32), 3)
    np.testing.assert_allclose(_centre(img), expected, rtol=0.05)


@pytest.mark.parametrize("mirrored", [False, True])
def test_textured_dome_orientation_in_cycles(cli, tmp_path, mirrored):
    """A turned dome, and one mirrored too (a scale of -1: its rotation was read as Euler angles of a
    reflection, and Cycles showed another part of the sky)."""
    from usd_scenes import dome_view_stage, expected_dome_view

    tex = asymmetric_latlong()
    stage = dome_view_stage(tmp_path / "s.usda", tex, yaw_deg=30.0)
    if mirrored:
        UsdGeom.Xformable(stage.GetPrimAtPath("/World/Sky")).AddScaleOp().Set(Gf.Vec3f(-1, 1, 1))
        stage.GetRootLayer().Save()
    assert cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")[0] == 0
    img = read_map(render_blend(tmp_path / "s.blend", tmp_path / "s.exr", spp=16), 3)
    assert np.abs(img - expected_dome_view(tmp_path / "s.usda", tex)).mean() < 0.03
    assert np.abs(img - expected_dome_view(tmp_path / "s.usda", tex[::-1, ::-1])).mean() > 0.1


def test_built_stage_with_fitted_lights_renders_like_mitsuba(cli, tmp_path):
    """A `build` stage with fitted lights (point lights + environment): Cycles vs Mitsuba."""
    from usdrelight.stage.build import BuildOptions, build
    from usdrelight.stage.lights_layer import write_fitted_lights
    from usdrelight.stage.records import FitProvenance, PointLightValue
    from usdrelight.mitsuba.render import render_stage

    ex = EXAMPLES / "procedural"
    out = tmp_path / "stage"
    build(ex / "photo.exr", out, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                              albedo=ex / "albedo.exr", shading=ex / "shading.exr", stride=2))
    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = [0.05, 0.06, 0.08]  # a sky above the horizon
    env[2:4, 10:14] = [1.5, 1.4, 1.2]  # and a bright patch
    write_fitted_lights(out, [PointLightValue(np.array([-1.0, 0.5, -1.8]), np.array([5.5, 5.4, 4.9])),
                              PointLightValue(np.array([1.0, 1.0, -3.5]), np.array([1.0, 1.5, 2.0]))], env,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    mitsuba = read_map(render_stage(out / "scene.usda", tmp_path / "m", aovs=["diffuse", "valid"], spp=256).files["diffuse"], 3)
    valid = read_map(tmp_path / "m" / "renders" / "valid.exr", 1)[..., 0] > 0.5
    assert cli("convert", out / "scene.usda", tmp_path / "s.blend")[0] == 0
    cycles = read_map(render_blend(tmp_path / "s.blend", tmp_path / "c.exr", spp=256), 3)
    assert cycles.shape == mitsuba.shape
    m, c = mitsuba[valid].mean(), cycles[valid].mean()
    assert c == pytest.approx(m, rel=0.05)
    rel_rmse = np.sqrt(np.mean((cycles[valid] - mitsuba[valid]) ** 2)) / m
    print(f"Cycles vs Mitsuba: mean {c:.4f} vs {m:.4f}, per-pixel relative RMSE {rel_rmse:.3f}")
    assert rel_rmse < 0.15  # two noisy renders (256 spp each) of the same scene; measured 0.06
    # Back from Blender for lights_user.usda: the stage's fitted lights are not read again (they would light
    # the scene twice); a copy of one made in Blender (Shift D copies its custom properties) is the user's.
    copy = tmp_path / "copy.py"
    copy.write_text("import bpy, sys\nargs = sys.argv[sys.argv.index('--') + 1:] if '--' in sys.argv else sys.argv[1:]\n"
                    "bpy.ops.wm.open_mainfile(filepath=args[0])\n"
                    "ob = next(o for o in bpy.context.scene.objects if o.type == 'LIGHT')\n"
                    "dup = ob.copy(); dup.data = ob.data.copy(); dup.location.x += 1.0\n"
                    "ob.users_collection[0].objects.link(dup)\n"
                    "bpy.ops.wm.save_as_mainfile(filepath=args[1])\n")
    run_blender(copy, str(tmp_path / "s.blend"), str(tmp_path / "copied.blend"))
    rc, _, err = cli("convert", tmp_path / "copied.blend", tmp_path / "back.usda")  # the fitted ones + a copy
    assert rc == 0 and "fitted light of the stage, unchanged (left out" in err, err
    back = read_scene(open_stage(tmp_path / "back.usda")).lights
    assert len(back) == 1 and back[0].path.startswith("/Scene/Lights/User/")
    fitted = [l for l in read_scene(open_stage(out / "scene.usda")).lights if l.kind == "sphere"]
    mine = back[0]
    assert any(np.allclose(mine.to_world[:3, 3] - [1.0, 0, 0], f.to_world[:3, 3], atol=1e-5) and
               np.allclose(emitted_radiance(mine), emitted_radiance(f), rtol=1e-4) for f in fitted)


def test_blender_lights_come_back_to_usd(cli, tmp_path):
    stage = new_stage(tmp_path / "s.usda")
    p = UsdLux.SphereLight.Define(stage, "/World/Key")
    p.CreateIntensityAttr(12.0)
    p.CreateColorAttr((1.0, 0.5, 0.25))
    p.CreateTreatAsPointAttr(True)
    UsdGeom.Xformable(p).AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    s = UsdLux.SphereLight.Define(stage, "/World/Spot")
    s.CreateIntensityAttr(7.0)
    s.CreateTreatAsPointAttr(True)
    sh = UsdLux.ShapingAPI.Apply(s.GetPrim())
    sh.CreateShapingConeAngleAttr(25.0)
    sh.CreateShapingConeSoftnessAttr(0.3)
    x = UsdGeom.Xformable(s)
    x.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
    x.AddRotateXOp().Set(-70.0)
    r = UsdLux.RectLight.Define(stage, "/World/Panel")
    r.CreateWidthAttr(2.0)
    r.CreateHeightAttr(0.5)
    r.CreateIntensityAttr(3.0)
    UsdGeom.Xformable(r).AddTranslateOp().Set(Gf.Vec3d(0, 2, -1))
    d = UsdLux.DiskLight.Define(stage, "/World/Disk")
    d.CreateRadiusAttr(0.4)
    d.CreateIntensityAttr(2.0)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(2.5)
    sun.CreateAngleAttr(1.0)
    UsdGeom.Xformable(sun).AddRotateXYZOp().Set(Gf.Vec3f(-50, 30, 0))
    camera(stage, Intrinsics.from_fov_x(50, 32, 24))
    stage.GetRootLayer().Save()
    assert cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")[0] == 0
    assert len(blender_lights(tmp_path / "s.blend")) == 5
    rc, _, err = cli("convert", tmp_path / "s.blend", tmp_path / "lights.usda")
    assert rc == 0, err
    from usdrelight.stage.lux import emitted_radiance, light_direction
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.validate import open_stage

    a = {l.path.split("/")[-1]: l for l in read_scene(open_stage(tmp_path / "s.usda")).lights}
    b = {l.path.split("/")[-1].replace("World_", ""): l for l in read_scene(open_stage(tmp_path / "lights.usda")).lights}
    assert sorted(a) == sorted(b)
    for k in a:
        np.testing.assert_allclose(emitted_radiance(b[k]), emitted_radiance(a[k]), rtol=1e-4, err_msg=k)
        np.testing.assert_allclose(b[k].to_world[:3, 3], a[k].to_world[:3, 3], atol=1e-5, err_msg=k)
        np.testing.assert_allclose(light_direction(b[k]), light_direction(a[k]), atol=1e-5, err_msg=k)
    assert b["Spot"].cone_angle_deg == pytest.approx(25.0, rel=1e-5)
    assert b["Panel"].width == pytest.approx(2.0, rel=1e-5) and b["Sun"].angle_deg == pytest.approx(1.0, rel=1e-4)
    assert "/Scene/Lights/User/" in b["Key"].path


def test_standalone_script_builds_the_same_blend(cli, tmp_path):
    from usdrelight.converters.blender import run_blender

    stage = looking_down_at_floor(tmp_path / "s.usda")
    UsdLux.DomeLight.Define(stage, "/World/L").CreateIntensityAttr(0.8)
    stage.GetRootLayer().Save()
    assert cli("convert", tmp_path / "s.usda", tmp_path / "scene.py")[0] == 0
    assert (tmp_path / "scene_data" / "mesh0.npz").is_file()
    run_blender(tmp_path / "scene.py", str(tmp_path / "from_script.blend"))
    img = read_map(render_blend(tmp_path / "from_script.blend", tmp_path / "x.exr", spp=16), 3)
    np.testing.assert_allclose(_centre(img), 0.4, rtol=0.05)


@pytest.mark.parametrize("kind", ["rect", "disk", "sphere"])
def test_area_lights_agree_between_cycles_and_mitsuba(cli, tmp_path, kind):
    from usdrelight.mitsuba.render import render_stage

    stage = looking_down_at_floor(tmp_path / "s.usda", width=24, height=18)
    if kind == "rect":
        l = UsdLux.RectLight.Define(stage, "/World/L")
        l.CreateWidthAttr(1.0)
        l.CreateHeightAttr(0.5)
    elif kind == "disk":
        l = UsdLux.DiskLight.Define(stage, "/World/L")
        l.CreateRadiusAttr(0.4)
    else:
        l = UsdLux.SphereLight.Define(stage, "/World/L")
        l.CreateRadiusAttr(0.2)
    l.CreateIntensityAttr(4.0)
    x = UsdGeom.Xformable(l)
    x.AddTranslateOp().Set(Gf.Vec3d(1.0, 0.5, 0.0))  # outside the camera's view cone
    x.AddRotateXOp().Set(-90.0)  # emit downwards
    stage.GetRootLayer().Save()
    mitsuba = read_map(render_stage(tmp_path / "s.usda", tmp_path / "m", spp=512).files["color"], 3)
    assert cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")[0] == 0
    cycles = read_map(render_blend(tmp_path / "s.blend", tmp_path / "c.exr", spp=512), 3)
    assert cycles.mean() == pytest.approx(mitsuba.mean(), rel=0.05)
