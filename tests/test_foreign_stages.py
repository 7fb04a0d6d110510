"""``fit`` and ``render`` on stages other tools wrote (found by probing): fit never rewrites a stage it did not
build, a RenderSettings camera naming nothing is one error, a TIFF or .tx texture renders (Mitsuba's bitmap
cannot read them: OpenImageIO does), a UsdLux diffuse multiplier of 0 is warned like any other."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from pxr import Sdf, UsdLux, UsdRender, UsdShade

from usd_scenes import add_closed_form_light, diffuse_material, looking_down_at_floor
from usdrelight.imageio import read_map, write_image


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.mark.parametrize("name", ["scene.usda", "shot.usda"])
def test_fit_refuses_a_stage_it_did_not_build(name, tmp_path, cli):
    """Before, on a hand-written scene.usda: exit 0, the user's file re-exported without its comments, and the
    fitted lights garbage-collected; on shot.usda: the whole fit ran, then 'scene.usda missing'."""
    path = tmp_path / name
    stage = looking_down_at_floor(path)
    add_closed_form_light(stage, "point")
    stage.GetRootLayer().Save()
    text = path.read_text().replace("#usda 1.0", "#usda 1.0\n# hand-written by a TD: keep this comment", 1)
    path.write_text(text)
    before = _sha(path)
    rc, out, err = cli("fit", path, "--lights", "1", "--max-side", "32")
    assert rc == 2 and "is not the scene.usda of a stage `usdrelight build` made" in err, err
    assert _sha(path) == before and sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_a_render_settings_camera_naming_nothing_is_one_error(tmp_path, cli):
    stage = looking_down_at_floor(tmp_path / "s.usda")
    add_closed_form_light(stage, "point")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets([Sdf.Path("/World/Nope")])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out")
    assert rc == 2 and err.strip() == "usdrelight: error: /Render/Settings: camera /World/Nope is not a Camera on " \
        "the stage", err  # before: 'unexpected RuntimeError: Accessed invalid null prim', exit 1
    rc, out, _ = cli("validate", tmp_path / "s.usda", "--json")  # before: 0 errors, exit 0
    report = json.loads(out)
    assert rc == 1 and report["errors"] == 1
    assert report["findings"][-1]["validator"] == "usdrelight:ReadScene" and "/World/Nope" in \
        report["findings"][-1]["message"]


@pytest.mark.parametrize("suffix", [".tif", ".tx"])
def test_a_tiff_or_tx_texture_renders_as_its_png_does(suffix, tmp_path, cli):
    """Mitsuba's bitmap reads PNG, JPEG, EXR, HDR, PFM, PPM, TGA, BMP: a .tif or .tx was 'Unknown file format',
    exit 1. Its texels are read by OpenImageIO and baked."""
    oiio = pytest.importorskip("OpenImageIO")
    tex = np.zeros((8, 8, 3), np.float32)
    tex[:, :4] = (0.8, 0.2, 0.1)
    tex[:, 4:] = (0.1, 0.3, 0.9)
    write_image(tmp_path / "t.png", tex, "uint8")
    if suffix == ".tx":
        assert oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, str(tmp_path / "t.png"), str(tmp_path / "t.tx"))
    else:
        write_image(tmp_path / "t.tif", tex, "uint8")
    colour = {}
    for s in (".png", suffix):
        stage = looking_down_at_floor(tmp_path / f"s{s}.usda")
        add_closed_form_light(stage, "dome")
        mat = diffuse_material(stage, "/World/Looks/Tex", texture=f"./t{s}")
        UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/World/Floor")).Bind(mat)
        stage.GetRootLayer().Save()
        rc, _, err = cli("render", tmp_path / f"s{s}.usda", "-o", tmp_path / f"out{s}", "--spp", "16")
        assert rc == 0, err
        colour[s] = read_map(tmp_path / f"out{s}" / "renders" / "color.exr", 3)
    np.testing.assert_allclose(colour[suffix], colour[".png"], atol=2e-3)
    assert colour[".png"].std() > 0.05  # the texture is seen, not a constant


@pytest.mark.parametrize("value", [0.0, 0.5])
def test_a_diffuse_multiplier_of_zero_is_warned_too(value, tmp_path, cli):
    """``inputs:diffuse = 0`` was read as unset ('x or 1.0') and rendered at full strength in silence."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    add_closed_form_light(stage, "point")
    UsdLux.LightAPI(stage.GetPrimAtPath("/World/L")).CreateDiffuseAttr(value)
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out", "--spp", "4")
    assert rc == 0 and "UsdLux diffuse/specular multipliers (ignored: 1 used)" in err, err
    # time-sampled: read at the frame rendered
    attr = UsdLux.LightAPI(stage.GetPrimAtPath("/World/L")).GetDiffuseAttr()
    attr.Clear()
    attr.Set(1.0, 1.0)
    attr.Set(value, 5.0)
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out5", "--spp", "4", "--time", "5")
    assert rc == 0 and "UsdLux diffuse/specular multipliers" in err, err


def test_two_products_of_one_file_and_a_udim_texture_are_one_error_each(tmp_path, cli):
    """Before: the second product wrote over the first in silence (beauty.exr held the albedo); a UDIM texture
    was 'texture not found' with no word of UDIM."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    add_closed_form_light(stage, "point")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets([Sdf.Path("/World/Camera")])
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    for name, source in (("a", "color"), ("b", "albedo")):
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateSourceNameAttr(source)
        prod = UsdRender.Product.Define(stage, f"/Render/P{name}")
        prod.CreateProductNameAttr("beauty.exr")
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        settings.CreateProductsRel().AddTarget(prod.GetPath())
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out")
    assert rc == 2 and "RenderProducts Pa and Pb both write beauty.exr" in err, err
    assert not (tmp_path / "out" / "beauty.exr").exists()

    stage = looking_down_at_floor(tmp_path / "u.usda")
    add_closed_form_light(stage, "dome")
    mat = diffuse_material(stage, "/World/Looks/Tex", texture="./tex.<UDIM>.png")
    UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/World/Floor")).Bind(mat)
    stage.GetRootLayer().Save()
    write_image(tmp_path / "tex.1001.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    rc, _, err = cli("render", tmp_path / "u.usda", "-o", tmp_path / "out2")
    assert rc == 2 and "UDIM tiles are not read" in err, err


@pytest.mark.parametrize("interpolation", ["vertex", "faceVarying"])
@pytest.mark.parametrize("mirrored", [False, True])
def test_zero_length_normals_shade_as_the_surface_does(interpolation, mirrored, tmp_path):
    """Authored zero-length normals rendered black in Mitsuba and the fast engine (which then said no pixel saw
    geometry). They take the surface's own front normal, under a mirroring transform too: the floor's centre
    is the closed form albedo / pi * I / r^2 in both renderers."""
    from collections import Counter

    from pxr import Gf, UsdGeom
    from usdrelight.engine import open_renderer
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.read_geometry import read_mesh
    from usdrelight.stage.validate import open_stage

    stage = looking_down_at_floor(tmp_path / "s.usda")
    expected = add_closed_form_light(stage, "point")
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Floor"))
    mesh.CreateNormalsAttr([(0, 0, 0)] * 4)
    mesh.SetNormalsInterpolation(interpolation)
    if mirrored:
        UsdGeom.Xformable(mesh).AddScaleOp().Set(Gf.Vec3f(-1, 1, 1))
    stage.GetRootLayer().Save()
    stage = open_stage(tmp_path / "s.usda")
    warnings = Counter()
    xf = np.diag([-1.0 if mirrored else 1.0, 1, 1, 1])
    (rec,) = read_mesh(stage.GetPrimAtPath("/World/Floor"), xf, read_material_of(stage), warnings)
    np.testing.assert_allclose(rec.normals, np.tile([0.0, 1.0, 0.0], (len(rec.normals), 1)))
    assert warnings["zero-length normals (the surface's own normal used)"] == 1
    scene = read_scene(stage)
    for engine in ("fast", "mitsuba"):
        beauty = open_renderer(scene, engine, max_side=32, spp=16).render(scene.lights).beauty
        centre = beauty[11:13, 15:17].mean()
        assert centre == pytest.approx(expected, rel=0.02), (engine, centre, expected)


def read_material_of(stage):
    from collections import Counter

    from usdrelight.stage.read_geometry import read_material

    return read_material(stage.GetPrimAtPath("/World/Floor"), Counter())


def test_what_render_products_ask_beyond_usdrelight_is_named_and_the_rest_rendered(tmp_path, cli):
    """A Houdini-like stage: a beauty (Ci), a depth product of sourceName 'Pz' and a product with its own
    resolution. Before: 'unsupported RenderVar sourceName Pz' failed the whole render, the product's own
    resolution and a dangling renderSettingsPrimPath went unmentioned."""
    from pxr import Gf

    stage = looking_down_at_floor(tmp_path / "s.usda")  # its RenderSettings: a color product
    add_closed_form_light(stage, "point")
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    for name, source in (("pz", "Pz"), ("big", "albedo")):
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateSourceNameAttr(source)
        prod = UsdRender.Product.Define(stage, f"/Render/Products/{name}")
        prod.CreateProductNameAttr(f"renders/{name}.exr")
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        settings.GetProductsRel().AddTarget(prod.GetPath())
    UsdRender.Product(stage.GetPrimAtPath("/Render/Products/big")).CreateResolutionAttr(Gf.Vec2i(64, 48))
    settings.GetProductsRel().AddTarget("/Render/Products/gone")
    UsdRender.Settings.Define(stage, "/Render/Other")
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Nope")
    stage.GetRootLayer().Save()
    rc, out, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out", "--spp", "4", "--json")
    assert rc == 0, err
    for line in ("RenderProduct pz: unsupported RenderVar sourceName 'Pz' (sourceType raw) (not rendered): 1",
                 "RenderProduct's own resolution (the RenderSettings' used): 1",
                 "RenderSettings products naming no RenderProduct (skipped): 1",
                 "renderSettingsPrimPath /Render/Nope names no RenderSettings (/Render/Settings used): 1"):
        assert line in err, err
    assert sorted(json.loads(out)["files"]) == ["big", "color"]
    albedo = read_map(tmp_path / "out" / "renders" / "big.exr", 3)
    assert albedo.shape == (24, 32, 3) and np.allclose(albedo, 0.5, atol=1e-3)  # the settings' 32 x 24
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out2", "--aov", "pz")  # asked for: an error
    assert rc == 2 and "unsupported RenderVar sourceName 'Pz'" in err, err
    for name in ("color", "big"):  # nothing renderable left: one error, not an empty render
        settings.GetProductsRel().RemoveTarget(f"/Render/Products/{name}")
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out3")
    assert rc == 2 and "no declared RenderProduct can be rendered (RenderProduct pz: unsupported RenderVar " \
        "sourceName 'Pz'" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out3").exists()


def test_several_render_settings_without_a_choice_are_named(tmp_path):
    from usdrelight.stage.read import read_scene

    stage = looking_down_at_floor(tmp_path / "s.usda")
    UsdRender.Settings.Define(stage, "/Render/Zother")
    stage.SetMetadata("renderSettingsPrimPath", "")
    assert read_scene(stage).warnings["2 RenderSettings and no renderSettingsPrimPath to choose (/Render/Settings "
                                      "used)"] == 1
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    assert not [k for k in read_scene(stage).warnings if "RenderSettings" in k]


@pytest.mark.parametrize("mpu", [1.0, 0.01])
def test_the_depth_aov_is_in_the_stages_own_units(mpu, tmp_path, cli):
    """The camera 1 stage unit above the floor: depth 1 in a metre stage and in a centimetre one (before: 0.01,
    metres, though the AOV's doc says scene units, as USD renderers write it)."""
    from pxr import UsdGeom

    stage = looking_down_at_floor(tmp_path / "s.usda", aovs=("color", "depth"))
    add_closed_form_light(stage, "point")
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out", "--spp", "4")
    assert rc == 0, err
    depth = read_map(tmp_path / "out" / "renders" / "depth.exr", 1)
    assert depth[12, 16] == pytest.approx(1.0, rel=1e-3) and depth.min() > 0.99
