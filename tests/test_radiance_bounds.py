"""Extreme radiance and bad lights at every door: what a probe of stiff inputs found getting through (a negative
dome rendered, a fit writing Inf or lights every reader refuses, a layer usdrelight wrote refused by itself, XML
lights converted that nothing could read, a glTF spot its own importer refused, empty folders after a failure)."""
from __future__ import annotations

import json
import warnings

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Usd, UsdLux

import usdrelight
from usdrelight.estimate.geometry import MIN_DEPTH, from_depth
from usdrelight.intrinsics import Intrinsics
from usdrelight.imageio import read_map, srgb_to_linear, write_image
from usdrelight.stage.build import BuildOptions, build
from usdrelight.stage.read import read_lights, read_scene

from usd_scenes import color_product_settings
from conftest import EXAMPLES, build_procedural

CARD = '''#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
)
def Mesh "Card" {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-5,-5,-3), (5,-5,-3), (5,5,-3), (-5,5,-3)]
}
def Camera "Cam" {
}
'''


SETTINGS = color_product_settings((32, 24), 'color.exr')


def test_a_dome_textures_negative_texels_are_zero_in_every_renderer_and_inf_is_refused(tmp_path, cli):
    """Mitsuba's render wrote negative radiance from a dome with negative texels (a processed HDRI's noise: the
    CC0 forest.exr holds 826 texels down to -0.002); the fast renderer refused the file. Both read them as 0
    now, warned; an Inf texel is refused by validate and render alike."""
    env = np.full((8, 16, 3), 0.5, np.float32)
    env[:, :] = -1.0  # all negative: the dome gives no light
    env[0, 0] = 0.5
    write_image(tmp_path / "env.exr", env, "float")
    (tmp_path / "s.usda").write_text(CARD + SETTINGS + 'def DomeLight "Sky" {\n    asset inputs:texture:file = '
                                     '@./env.exr@\n    float inputs:intensity = 2\n}\n')
    scene = read_scene(tmp_path / "s.usda")
    assert scene.lights[0].texture.negative_texels and any("negative texels" in w for w in scene.warnings)
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out", "--spp", 4, "--max-depth", 2)
    assert rc == 0, err
    img = read_map(tmp_path / "out" / "color.exr", 3)
    assert img.min() >= 0.0 and img.max() < 0.05  # one texel of 128 lights it; -1 x 2 everywhere else before
    assert cli("convert", tmp_path / "s.usda", tmp_path / "x" / "s.xml")[0] == 0
    baked = [f for f in (tmp_path / "x" / "textures").iterdir() if "tinted" in f.name]
    assert len(baked) == 1 and read_map(baked[0], 3).min() == 0.0
    env[0, 0] = np.inf  # written past usdrelight's writer, which refuses it
    out = oiio.ImageOutput.create(str(tmp_path / "env.exr"))
    out.open(str(tmp_path / "env.exr"), oiio.ImageSpec(16, 8, 3, "float"))
    out.write_image(env)
    out.close()
    rc, out, _ = cli("validate", tmp_path / "s.usda")
    assert rc == 1 and "NaN, Inf or above 1e30 texels" in out
    rc, _, err = cli("render", tmp_path / "s.usda", "-o", tmp_path / "out2", "--spp", 1)
    assert rc == 2 and err.count("\n") == 1 and not (tmp_path / "out2" / "color.exr").exists()


def test_a_light_of_1e30_stored_as_a_float_reads_back(tmp_path):
    """--save-lights and the web app store the cap, 1e30, as a float: 1.000000015e30, refused before."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "l.usda"))
    UsdLux.SphereLight.Define(stage, "/L").CreateIntensityAttr(1e30)
    stage.Save()
    (light,) = read_lights(Usd.Stage.Open(str(tmp_path / "l.usda")))
    assert light.radiance.max() == pytest.approx(1e30, rel=1e-6)
    UsdLux.SphereLight(stage.GetPrimAtPath("/L")).GetIntensityAttr().Set(1.01e30)
    with pytest.raises(usdrelight.UsdRelightError, match="above 1e30"):
        read_lights(stage)


XML = '''<scene version="3.0.0">
    <shape type="rectangle"><bsdf type="diffuse"/></shape>
    {}
</scene>'''


@pytest.mark.parametrize("emitter, says", [
    ('<shape type="sphere"><float name="radius" value="-1"/><emitter type="area"><rgb name="radiance" '
     'value="1"/></emitter></shape>', "negative or non-finite size"),
    ('<emitter type="point"><rgb name="intensity" value="2e30"/></emitter>', "above 1e30"),
    ('<emitter type="directional"><vector name="direction" value="0,0,0"/></emitter>', "direction is zero"),
    ('<emitter type="spot"><float name="cutoff_angle" value="0"/></emitter>', "cutoff_angle must be in (0, 180]")])
def test_xml_lights_every_reader_refuses_are_refused_by_convert(tmp_path, cli, emitter, says):
    (tmp_path / "s.xml").write_text(XML.format(emitter))
    rc, _, err = cli("convert", tmp_path / "s.xml", tmp_path / "s.usda")
    assert rc == 2 and says in err and err.count("\n") == 1, err  # one line: no numpy warning before it
    assert not (tmp_path / "s.usda").exists()


def test_a_hard_spot_goes_to_gltf_and_back(tmp_path, cli):
    """innerConeAngle == outerConeAngle broke the glTF spec (inner < outer): the importer refused the export."""
    (tmp_path / "s.usda").write_text(CARD + '''def SphereLight "Spot" (
    prepend apiSchemas = ["ShapingAPI"]
) {
    float inputs:intensity = 10
    float inputs:radius = 0
    bool treatAsPoint = 1
    float inputs:shaping:cone:angle = 30
}
''')
    assert cli("convert", tmp_path / "s.usda", tmp_path / "s.gltf")[0] == 0
    spot = json.loads((tmp_path / "s.gltf").read_text())["extensions"]["KHR_lights_punctual"]["lights"][0]["spot"]
    assert spot["innerConeAngle"] < spot["outerConeAngle"] == pytest.approx(np.radians(30))
    rc, _, err = cli("convert", tmp_path / "s.gltf", tmp_path / "back.usda")
    assert rc == 0, err
    (light,) = read_lights(Usd.Stage.Open(str(tmp_path / "back.usda")))
    assert light.cone_angle_deg == pytest.approx(30, abs=1e-4) and light.cone_softness < 1e-5


@pytest.fixture(scope="module")
def bright_stages(tmp_path_factory):
    """The procedural example's photo at 1e24 and 9e29 times its radiance (legal photos: <= 1e30)."""
    ex, root = EXAMPLES / "procedural", tmp_path_factory.mktemp("bright")
    photo = read_map(ex / "photo.exr", 3)
    out = {}
    for scale in (1.0, 1e24, 9e29):
        write_image(root / f"p{scale:g}.exr", photo * np.float32(scale), "float")
        build(root / f"p{scale:g}.exr", root / f"s{scale:g}", BuildOptions(
            depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json", albedo=ex / "albedo.exr"))
        out[scale] = root / f"s{scale:g}" / "scene.usda"
    return out


def test_a_photo_in_physical_units_fits_as_the_same_photo_scaled(bright_stages, cli):
    """A peak of ~1e24: the fit wrote usdrelight:fit:mse = inf; now it fits at a peak of 1 and scales back."""
    fits = {s: cli.json("fit", bright_stages[s], "--max-side", 32, "--lights", 2, "--verify-spp", 0)
            for s in (1.0, 1e24)}
    assert fits[1e24]["psnr_db"] == pytest.approx(fits[1.0]["psnr_db"], abs=0.5)
    text = (bright_stages[1e24].parent / "lights_fitted.usda").read_text()
    assert "inf" not in text.lower()
    lights = {s: read_lights(Usd.Stage.Open(str(bright_stages[s]))) for s in (1.0, 1e24)}
    power = {s: sum(float(l.radiance.sum()) for l in lights[s] if l.kind != "dome") for s in lights}
    assert power[1e24] / 1e24 == pytest.approx(power[1.0], rel=0.2)


def test_a_fit_whose_lights_would_pass_the_cap_writes_nothing(bright_stages, cli):
    layer = bright_stages[9e29].parent / "lights_fitted.usda"
    before = layer.read_text()
    rc, _, err = cli("fit", bright_stages[9e29], "--max-side", 32, "--lights", 2, "--verify-spp", 0)
    assert rc == 2 and "above 1e+30" in err and "nothing was written" in err
    assert layer.read_text() == before


def test_a_failed_clip_leaves_no_empty_video_folder(tmp_path, cli):
    stage = build_procedural(tmp_path / "s", stride=4)
    (stage.parent / "lights_user.usda").write_text('''#usda 1.0
def Xform "Scene" {
    def Scope "Lights" {
        def Scope "User" {
            def SphereLight "L" {
                float inputs:intensity.timeSamples = { 1: 1, 3: 9e29 }
                float inputs:exposure.timeSamples = { 1: 0, 3: 1 }
                double3 xformOp:translate = (0.5, 1, -2)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
        }
    }
}
''')
    rc, _, err = cli("relight", stage, "--frames", "1:3", "--max-side", 16, "-o", tmp_path / "out",
                     "--video", tmp_path / "vid" / "deep" / "clip.mp4")
    assert rc == 2 and "above 1e30" in err
    assert not (tmp_path / "vid").exists() and not (tmp_path / "out").exists()


def test_fitted_scale_out_of_range_is_one_line_before_any_warning(tmp_path, cli):
    stage = build_procedural(tmp_path / "s", stride=4)
    rc, _, err = cli("relight", stage, "--fitted-scale", 1e9, "--mode", "add", "--light", "point:0,1,-2:1,1,1",
                     "-o", tmp_path / "out")
    assert rc == 2 and err.count("\n") == 1 and "fitted_scale (--fitted-scale) must be" in err


def test_signed_photos_decode_without_numpy_warnings_and_depth_at_the_minimum_is_valid():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert srgb_to_linear(np.array([-0.5, 0.0, 0.5], np.float32))[2] == pytest.approx(0.2140, abs=1e-4)
    depth = np.full((4, 4), np.float32(MIN_DEPTH))  # 1e-6 stored as a float32 is 9.9999997e-7
    assert from_depth(depth, Intrinsics(100.0, 100.0, 2.0, 2.0, 4, 4)).valid.all()


def test_fit_iterations_are_bounded(tmp_path):
    with pytest.raises(usdrelight.UsdRelightError, match="iterations"):
        usdrelight.fit(build_procedural(tmp_path / "s", stride=4), usdrelight.FitSettings(iterations=10 ** 9))
