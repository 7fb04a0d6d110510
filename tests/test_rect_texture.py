"""A RectLight's ``inputs:texture:file`` in both renderers (before: ignored with a warning, the light drawn with
its uniform colour): UsdLux puts the file's top-left texel at the light's local (+X, +Y) corner and its
bottom-right at (-X, -Y). Ground truth: where the lit quadrant of the texture must light the floor, Mitsuba's
render of the same stage, and the constant texture's exact scale."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux

from usd_scenes import looking_down_at_floor
from usdrelight.converters.blender_units import light_to_blender
from usdrelight.engine.fast import EngineSettings, FastRenderer
from usdrelight.engine.lights import planar_light, panel_light
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import write_image
from usdrelight.mitsuba.render import render_record
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

W, H = 32, 24


def _stage(tmp_path, texture: np.ndarray | None, name="floor"):
    """The floor seen from 1 m straight above (image right = +X, image top = -Z) and a 0.6 m square RectLight
    0.15 m above it facing down (rotateX -90: local +X = world +X, local +Y = world -Z), intensity 2."""
    stage = looking_down_at_floor(tmp_path / f"{name}.usda", width=W, height=H)
    for prim in stage.Traverse():  # the camera's near plane beyond the light: Mitsuba sees the floor under it
        if prim.IsA(UsdGeom.Camera):
            UsdGeom.Camera(prim).CreateClippingRangeAttr(Gf.Vec2f(0.9, 100.0))
    light = UsdLux.RectLight.Define(stage, "/World/Panel")
    light.CreateIntensityAttr(2.0)
    light.CreateWidthAttr(0.6)
    light.CreateHeightAttr(0.6)
    xf = UsdGeom.Xformable(light)
    xf.AddTranslateOp().Set(Gf.Vec3d(0, 0.15, 0))
    xf.AddRotateXOp().Set(-90.0)
    if texture is not None:
        write_image(tmp_path / f"{name}.exr", texture.astype(np.float32), "float")
        light.CreateTextureFileAttr(Sdf.AssetPath(f"./{name}.exr"))
    stage.GetRootLayer().Save()
    return read_scene(open_stage(tmp_path / f"{name}.usda"))


def _fast(rec, samples=64):
    return FastRenderer(rec, EngineSettings(max_side=None, area_samples=samples, max_depth=2)).render(rec.lights).beauty


def _quadrants(img):
    h, w = img.shape[0] // 2, img.shape[1] // 2
    return {"top_left": img[:h, :w].mean(), "top_right": img[:h, w:].mean(),
            "bottom_left": img[h:, :w].mean(), "bottom_right": img[h:, w:].mean()}


@pytest.fixture(scope="module")
def corner_lit(tmp_path_factory):
    """Texture: its top-left quadrant 4, the rest 0 -> only the light's (+X, +Y) quarter emits."""
    tex = np.zeros((8, 8, 3))
    tex[:4, :4] = 4.0
    return _stage(tmp_path_factory.mktemp("rect"), tex)


def test_the_texture_is_read_without_a_warning(corner_lit):
    (light,) = corner_lit.lights
    assert light.kind == "rect" and light.texture is not None and light.texture.path.endswith("floor.exr")
    assert not any("RectLight" in w for w in corner_lit.warnings)


def test_the_lit_quarter_lights_the_floor_below_the_lights_plus_x_plus_y_corner(corner_lit):
    """Local (+X, +Y) is world (+X, -Z): the image's top-right. The fast renderer and Mitsuba agree on it."""
    fast_img = _fast(corner_lit, 1024)
    ref_img = render_record(corner_lit, {"beauty"}, spp=1024, max_depth=2)["beauty"]
    fast, ref = _quadrants(fast_img.mean(axis=2)), _quadrants(ref_img.mean(axis=2))
    for q in (fast, ref):  # measured: top right 1.50 (Mitsuba 1.47), bottom right 0.39, top left 0.35, bottom left 0.12
        assert q["top_right"] > 3.0 * max(q["top_left"], q["bottom_right"]) > 0, q
        assert q["top_right"] > 8.0 * q["bottom_left"], q
    assert fast_img.mean() == pytest.approx(ref_img.mean(), rel=0.03)
    for k in fast:
        assert fast[k] == pytest.approx(ref[k], rel=0.1), (k, fast, ref)


def test_a_constant_texture_scales_the_uniform_light_exactly(tmp_path):
    """Texels 0.25 everywhere: the untextured light's direct term x 0.25 (the same samples, each weighted 0.25)."""
    rec = _stage(tmp_path, np.full((4, 6, 3), 0.25), "quarter")
    (light,) = rec.lights
    tr = FastRenderer(rec, EngineSettings(max_side=None)).transport
    for sampler in (planar_light, panel_light):
        textured = sampler(tr, light, 64, np.random.default_rng(1), {})
        plain = sampler(tr, replace(light, texture=None), 64, np.random.default_rng(1))
        assert plain.mean() > 0.01
        np.testing.assert_allclose(textured, 0.25 * plain, rtol=1e-12, atol=0)


def test_blender_gets_the_textures_mean(tmp_path):
    """Cycles' area light takes no texture here: uniform, the texture's mean radiance (power kept)."""
    tex = np.full((4, 4, 3), 0.3)
    tex[0, 0] = (2.7, 0.3, 0.3)  # mean (0.45, 0.3, 0.3)
    (light,) = _stage(tmp_path, tex, "mean").lights
    d = light_to_blender(light)
    assert d["power"] == pytest.approx(np.pi * 2.0 * 0.45 * 0.6 * 0.6)  # pi L max(mean) w h
    np.testing.assert_allclose(d["color"], (1.0, 0.3 / 0.45, 0.3 / 0.45), rtol=1e-6)
    assert light_to_blender(replace(light, texture=None))["power"] == pytest.approx(np.pi * 2.0 * 0.6 * 0.6)


def test_a_missing_texture_is_one_clear_error(tmp_path, cli):
    stage = looking_down_at_floor(tmp_path / "gone.usda", width=W, height=H)
    light = UsdLux.RectLight.Define(stage, "/World/Panel")
    light.CreateTextureFileAttr(Sdf.AssetPath("./nowhere.exr"))
    stage.GetRootLayer().Save()
    with pytest.raises(UsdRelightError, match="RectLight texture not found: ./nowhere.exr"):
        read_scene(open_stage(tmp_path / "gone.usda"))
    rc, out, err = cli("render", tmp_path / "gone.usda", "-o", tmp_path / "out")
    assert rc == 2 and "RectLight texture not found" in err and len(err.strip().splitlines()) == 1, err


def test_a_light_textures_encoding_follows_what_the_file_stores(tmp_path):
    """An 8-bit TIFF is sRGB like an 8-bit PNG (its suffix made it 'linear': a mid-grey dome lit 2.3x too bright),
    an EXR linear; the engine reads the texels so."""
    import OpenImageIO as oiio

    from usdrelight.engine.lights import light_texels
    from usdrelight.imageio import srgb_to_linear

    out = oiio.ImageOutput.create(str(tmp_path / "grey.tif"))
    out.open(str(tmp_path / "grey.tif"), oiio.ImageSpec(4, 2, 3, oiio.UINT8))
    out.write_image(np.full((2, 4, 3), 128, np.uint8))
    out.close()
    write_image(tmp_path / "grey.exr", np.full((2, 4, 3), 0.5, np.float32), "float")
    for name, space, value in (("grey.tif", "sRGB", float(srgb_to_linear(128 / 255))), ("grey.exr", "raw", 0.5)):
        stage = looking_down_at_floor(tmp_path / f"{name}.usda", width=8, height=6)
        UsdLux.DomeLight.Define(stage, "/World/Sky").CreateTextureFileAttr(Sdf.AssetPath(f"./{name}"))
        stage.GetRootLayer().Save()
        (dome,) = read_scene(open_stage(tmp_path / f"{name}.usda")).lights
        assert dome.texture.color_space == space
        np.testing.assert_allclose(light_texels(dome.texture, {}), value, rtol=1e-6)


def test_the_xml_export_writes_one_mirrored_texture_per_scaled_rect(cli, tmp_path):
    """Two RectLights sharing one texture at different radiances: two mirrored files, each scaled (before, a
    separate baked copy was written too, unused; and the name would not tell the scales apart)."""
    stage = looking_down_at_floor(tmp_path / "two.usda", width=8, height=6)
    write_image(tmp_path / "t.exr", np.full((2, 4, 3), 0.5, np.float32), "float")
    for name, k in (("A", 2.0), ("B", 3.0)):
        light = UsdLux.RectLight.Define(stage, f"/World/{name}")
        light.CreateIntensityAttr(k)
        light.CreateTextureFileAttr(Sdf.AssetPath("./t.exr"))
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "two.usda", tmp_path / "x" / "two.xml")
    assert rc == 0, err
    files = sorted((tmp_path / "x" / "textures").glob("*.exr"))
    assert len(files) == 2 and all("_mirrored_" in f.name for f in files), files
    from usdrelight.imageio import read_photo

    assert sorted(float(read_photo(f).mean()) for f in files) == pytest.approx([1.0, 1.5])


def test_radiance_times_texel_beyond_float32_is_one_error(tmp_path):
    """Each factor within its bound (1e30), their product is not: an error, not an Inf turned into black."""
    tex = np.full((2, 2, 3), 1e20)
    rec = _stage(tmp_path, tex, "hot")
    (light,) = rec.lights
    hot = replace(light, radiance=np.full(3, 1e20))
    with pytest.raises(UsdRelightError, match="beyond what a float32 image carries"):
        FastRenderer(rec, EngineSettings(max_side=None)).render([hot])
