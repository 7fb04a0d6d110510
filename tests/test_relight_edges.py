"""Relight cases a probe found wrong: a fitted light edited in the user's layer (Blender's read-back writes such
an ``over``), ``--fitted-scale 1``, light values beyond what an image can carry, and light textures that are
negative or unbounded. Each asserts a number or one clear error line."""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import pytest
from PIL import Image

from conftest import build_procedural
from usdrelight.imageio import display_exposure, linear_to_srgb, read_map, write_image
from usdrelight.relight.session import RelightSession
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.read import read_lights
from usdrelight.stage.records import FitProvenance, PointLightValue
from usdrelight.stage.validate import open_stage


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The procedural stage (stride 2) with one fitted point light and no fitted environment."""
    d = tmp_path_factory.mktemp("edges")
    scene = build_procedural(d / "st", stride=2)
    write_fitted_lights(d / "st", [PointLightValue(np.array([-0.5, 1.0, -2.0]), np.array([3.0, 3.0, 3.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    return scene


def _user_layer(stage_dir, body: str) -> None:
    (stage_dir / USER_LIGHTS).write_text(f'#usda 1.0\nover "Scene" {{\n over "Lights" {{\n{body}\n }}\n}}\n')


@contextmanager
def user_lights(stage_dir, body: str):
    """The stage's lights_user.usda holds ``body`` (under /Scene/Lights) inside the block; restored after."""
    original = (stage_dir / USER_LIGHTS).read_text()
    _user_layer(stage_dir, body)
    try:
        yield
    finally:
        (stage_dir / USER_LIGHTS).write_text(original)


def test_an_edited_fitted_light_is_new_lighting_not_the_photos(cli, fitted, tmp_path):
    """The user's layer triples the fitted light (an ``over`` at its path, as a .blend edited in Blender reads
    back): ratio = photo x (N + k) / (F + k) with N the edited light and F the fit's, up to 3x the photo (before: F
    read the edit too, and ratio returned the photo unchanged)."""
    stage_dir = fitted.parent
    (path,) = [l.path for l in read_lights(open_stage(fitted)) if "Fitted" in l.path]
    name = path.rsplit("/", 1)[1]
    with user_lights(stage_dir, f'  over "Fitted" {{\n   over "{name}" {{\n    float inputs:intensity = 9\n   }}\n  }}'):
        rc, _, err = cli("relight", fitted, "--with-fitted", "--mode", "ratio", "--max-side", "64", "-o",
                         tmp_path / "r")
        assert rc == 0, err
        relit = read_map(tmp_path / "r" / "relit.exr", 3)
        base = tmp_path / "base"
        _user_layer(stage_dir, "")
        assert cli("relight", fitted, "--with-fitted", "--mode", "ratio", "--max-side", "64", "-o", base)[0] == 0
        unchanged = read_map(base / "relit.exr", 3)
        lit = unchanged > 0.02
        gain = relit[lit] / unchanged[lit]  # I (N + k) / (F + k): up to 3, 1 in F's shadows
        assert 1.3 < np.median(gain) and gain.max() <= 3.0 + 1e-4, (np.median(gain), gain.max())  # measured 1.38
        assert gain.min() > 1 - 1e-6


def test_fitted_scale_one_keeps_the_fitted_lights(cli, fitted, tmp_path):
    """--help: --fitted-scale implies --with-fitted, 1 too (before: "no light to relight with")."""
    rc, _, err = cli("relight", fitted, "--fitted-scale", "1", "--max-side", "64", "-o", tmp_path / "a")
    assert rc == 0, err
    rc, _, err = cli("relight", fitted, "--with-fitted", "--max-side", "64", "-o", tmp_path / "b")
    assert rc == 0, err
    np.testing.assert_array_equal(read_map(tmp_path / "a" / "relit.exr", 3), read_map(tmp_path / "b" / "relit.exr", 3))


def test_a_light_beyond_what_an_image_carries_is_one_error(cli, fitted, tmp_path):
    """intensity 3 x 2^200 (exposure 200) was accepted and rendered black, with numpy's overflow warnings."""
    stage_dir = fitted.parent
    with user_lights(stage_dir, '  def Scope "User" {\n   def SphereLight "Hot" {\n    float inputs:intensity = 3\n'
                                '    float inputs:exposure = 200\n    bool treatAsPoint = 1\n   }\n  }'):
        rc, _, err = cli("relight", fitted, "--max-side", "64", "-o", tmp_path / "o")
        lines = [l for l in err.splitlines() if l.strip()]
        assert rc == 2 and len(lines) == 1 and "above 1e30" in lines[0], err


@pytest.mark.parametrize("value, ok", [(0.5, True), (-5.0, True), (3e38, False)])  # a negative texel: read as 0
def test_a_dome_texture_must_be_a_finite_radiance(cli, fitted, tmp_path, value, ok):
    stage_dir = fitted.parent
    sky = np.full((8, 16, 3), 0.5, np.float32)
    sky[2, 3] = value
    write_image(stage_dir / "sky.exr", sky, "float")
    try:
        with user_lights(stage_dir, '  def Scope "User" {\n   def DomeLight "Sky" {\n'
                                    '    asset inputs:texture:file = @./sky.exr@\n   }\n  }'):
            rc, _, err = cli("relight", fitted, "--mode", "render", "--max-side", "64", "-o", tmp_path / "o")
        if ok:
            assert rc == 0, err
            img = read_map(tmp_path / "o" / "relit.exr", 3)
            assert np.isfinite(img).all() and img.min() >= 0 and img.max() > 0
        else:
            lines = [l for l in err.splitlines() if l.strip()]
            assert rc == 2 and len(lines) == 1 and "Inf or above 1e30 texels" in lines[0], err
    finally:
        (stage_dir / "sky.exr").unlink()


def test_two_domes_render_in_mitsuba_as_the_sum_of_each(tmp_path, cli):
    """Mitsuba takes one environment emitter per scene: a user's HDRI dome beside the fitted environment made
    render / relight --renderer mitsuba / the XML fail ("Only one environment emitter"), exit 1. The domes are
    merged into one world-frame map: the render of both equals the sum of the renders of each (same seed)."""
    from usd_scenes import asymmetric_latlong

    from usdrelight.mitsuba.render import render_record
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.records import LightRecord, TextureRecord
    from usdrelight.stage.lux import frame_pointing_along

    scene = build_procedural(tmp_path / "st", stride=4)
    write_image(scene.parent / "sky.exr", (asymmetric_latlong(16, 32) * 0.8 + 0.1).astype(np.float32), "float")
    (scene.parent / USER_LIGHTS).write_text('#usda 1.0\nover "Scene" {\n def Scope "Lights" {\n  def Scope "User" {\n'
                                            '   def DomeLight "A" {\n    float inputs:intensity = 0.5\n   }\n'
                                            '   def DomeLight "B" {\n    asset inputs:texture:file = @./sky.exr@\n'
                                            '   }\n  }\n }\n}\n')
    rec = read_scene(scene).with_lights([])
    rot = np.eye(4)
    rot[:3, :3] = frame_pointing_along([1, 0, 0.3])[:3, :3]
    sky = LightRecord("/sky", "dome", rot, np.array([1.0, 0.9, 0.7]), texture=TextureRecord(str(scene.parent / "sky.exr"), "raw"))
    fill = LightRecord("/fill", "dome", np.eye(4), np.array([0.2, 0.3, 0.4]))

    def render(lights):
        return render_record(rec.with_lights(lights), {"beauty"}, spp=256, max_depth=2, hide_emitters=True)["beauty"]

    both, a, b = render([sky, fill]), render([sky]), render([fill])
    np.testing.assert_allclose(both.mean((0, 1)), (a + b).mean((0, 1)), rtol=0.02)
    rel = np.sqrt(np.mean((both - a - b) ** 2)) / np.sqrt(np.mean((a + b) ** 2))
    assert rel < 0.08, rel  # 256-spp noise of three renders
    two = render([fill, LightRecord("/fill2", "dome", np.eye(4), np.array([0.1, 0.1, 0.1]))])
    np.testing.assert_allclose(two.mean((0, 1)), render([LightRecord("/f", "dome", np.eye(4), np.array([0.3, 0.4, 0.5]))]).mean((0, 1)), rtol=1e-6)
    # the XML export of the stage's two domes (the user's layer) writes the merged map, and Mitsuba loads it
    rc, _, err = cli("convert", scene, tmp_path / "x" / "scene.xml")
    assert rc == 0, err
    merged = list((tmp_path / "x" / "textures").glob("domes_merged_*.exr"))
    assert len(merged) == 1
    from usdrelight.mitsuba.runtime import load_mitsuba

    assert load_mitsuba().load_file(str(tmp_path / "x" / "scene.xml")) is not None


def test_a_frame_whose_lights_are_all_invisible_is_dark_not_the_end_of_the_clip(cli, fitted, tmp_path):
    """Every user light invisible at time code 2 of 3 (fitted lights off): that frame is rendered without light
    (black), the others as lit (before: "no light to relight with" and no frame at all)."""
    stage_dir = fitted.parent
    with user_lights(stage_dir, '  def Scope "User" {\n   def SphereLight "Blink" {\n    float inputs:intensity = 5\n'
                                '    bool treatAsPoint = 1\n    token visibility.timeSamples = { 1: "inherited", '
                                '2: "invisible", 3: "inherited" }\n    double3 xformOp:translate = (0.3, 0.8, -2.2)\n'
                                '    uniform token[] xformOpOrder = ["xformOp:translate"]\n   }\n  }'):
        rep = cli.json("relight", fitted, "--frames", "1:3", "--mode", "render", "--max-side", "48", "-o",
                       tmp_path / "o")
        means = [read_map(f["exr"], 3).mean() for f in rep["frames"]]
        assert [f["lights"] for f in rep["frames"]] == [1, 0, 1]
        assert means[1] == 0.0 and means[0] == pytest.approx(means[2]) and means[0] > 0.01, means
        rc, _, err = cli("relight", fitted, "--time", "2", "--mode", "render", "-o", tmp_path / "one")
        assert rc == 2 and "no light to relight with" in err  # a single frame without light stays an error


def test_a_light_relight_cannot_draw_is_named(cli, fitted, tmp_path):
    """A PortalLight (a CylinderLight before it was drawn) was dropped by relight without a word (render warned)."""
    stage_dir = fitted.parent
    with user_lights(stage_dir, '  def Scope "User" {\n   def PortalLight "Window" {\n    float inputs:intensity = 5\n'
                                '   }\n  }'):
        rc, _, err = cli("relight", fitted, "--with-fitted", "--max-side", "48", "-o", tmp_path / "o")
        assert rc == 0 and "light type PortalLight (not converted)" in err, err


def test_a_relight_keeps_a_renders_aovs_in_its_folder_and_replaces_its_own_frames(cli, fitted, tmp_path):
    """render then relight into one folder: renders/diffuse.exr stays (before: the relight removed it, and
    `neural` then failed on the stage folder); a 3-frame relight after a 4-frame one leaves 3 frames."""
    out = tmp_path / "mix"
    assert cli("render", fitted, "--spp", "1", "--aov", "diffuse", "-o", out)[0] == 0
    aov = (out / "renders" / "diffuse.exr").read_bytes()
    assert cli("relight", fitted, "--with-fitted", "--max-side", "48", "-o", out)[0] == 0
    assert (out / "renders" / "diffuse.exr").read_bytes() == aov and (out / "relit.exr").is_file()
    seq = tmp_path / "seq.json"
    seq.write_text('[["point:0,1,-2:1,1,1"], ["point:0.2,1,-2:1,1,1"], ["point:0.4,1,-2:1,1,1"], '
                   '["point:0.6,1,-2:1,1,1"]]')
    assert cli("relight", fitted, "--sequence", seq, "--max-side", "48", "-o", out)[0] == 0
    assert len(list(out.glob("relit_*.exr"))) == 4 and not (out / "relit.exr").exists()
    seq.write_text('[["point:0,1,-2:1,1,1"], ["point:0.2,1,-2:1,1,1"], ["point:0.4,1,-2:1,1,1"]]')
    assert cli("relight", fitted, "--sequence", seq, "--max-side", "48", "-o", out)[0] == 0
    assert sorted(p.name for p in out.glob("relit_*.exr")) == ["relit_0000.exr", "relit_0001.exr", "relit_0002.exr"]
    assert (out / "renders" / "diffuse.exr").read_bytes() == aov


def test_frame_steps_and_numbers_are_read_as_written(cli, fitted, tmp_path):
    """--frames 0:0.3:0.1 ends at 0.3 (not 0.30000000000000004, past END); 1_0 is not a number here (Python's
    float reads it as 10)."""
    from usdrelight.stage.timing import parse_frames

    assert parse_frames("0:0.3:0.1") == [0.0, 0.1, 0.2, 0.3]
    assert parse_frames("1:2:0.25")[-1] == 2.0 and len(parse_frames("0:1:0.1")) == 11
    rc, _, err = cli("relight", fitted, "--light", "point:1_0,1,-2:1,1,1", "-o", tmp_path / "a")
    assert rc == 2 and "comma-separated numbers" in err and err.count("\n") == 1, err
    with pytest.raises(SystemExit) as exc:  # argparse refuses it before anything runs
        cli("relight", fitted, "--time", "1_0", "-o", tmp_path / "b")
    assert exc.value.code == 2


def test_a_clip_without_any_light_is_still_an_error(cli, fitted, tmp_path):
    """Dark frames are allowed inside a clip that has light somewhere, not a whole clip with none (nothing is
    published)."""
    rc, _, err = cli("relight", fitted, "--frames", "1:3", "--mode", "render", "--max-side", "32", "-o", tmp_path / "o")
    assert rc == 2 and "no light to relight with at any frame" in err and err.count("\n") == 1, err
    assert not list((tmp_path / "o").glob("relit*")) if (tmp_path / "o").exists() else True


def test_adding_a_small_bright_light_never_darkens_the_relit_png(tmp_path, cli):
    """The PNG was divided by the relit image's own 99.5th percentile: a small bright pool pushed it to 1.7 and
    the rest of the photo came out at 0.57x. It is shown at the photo's exposure now: brighter, clipped, never
    darker than the photo."""
    stage = build_procedural(tmp_path / "s")
    res = cli.json("relight", stage, "--mode", "add", "--max-side", 128, "-o", tmp_path / "o",
                   "--light", "rect:0,-0.9,-2.5:0,-1,0:400,400,400:0.3,0.3")
    png = np.asarray(Image.open(res["png"]), np.float64)
    with RelightSession(stage, max_side=128) as session:
        photo = session.source_photo()
    view = np.round(linear_to_srgb(photo / display_exposure(photo)) * 255.0)
    assert np.percentile(read_map(res["exr"], 3), 99.5) > 1.5  # the pool would have set the exposure before
    assert (png < view - 1).mean() == 0.0
