"""Moving lights the USD way: time-sampled UsdLux in the user's layer -> relit frames, an MP4, per-frame Mitsuba
XML; a --sequence saved as a time-sampled layer gives the same frames."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from usdrelight.imageio import read_raw
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.records import FitProvenance, PointLightValue
from usdrelight.stage.lights_layer import write_fitted_lights

from conftest import build_procedural

av = pytest.importorskip("av", reason="PyAV (the video extra) is installed by scripts/setup.sh")

FRAMES = 12
#: the moving light's path: left to right over the floor (y = -1) of the procedural room, metres
XS = np.linspace(-1.2, 1.2, FRAMES)


def _path(i: int) -> tuple[float, float, float]:
    return float(XS[i]), -0.6, -2.4


@pytest.fixture(scope="module")
def animated_stage(tmp_path_factory) -> Path:
    """The procedural room, fitted, with a point light moving along 12 time samples (time codes 1..12) authored
    in lights_user.usda the way a DCC writes them (translate samples on the light's xformOp)."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    out = tmp_path_factory.mktemp("anim") / "st"
    scene = build_procedural(out)
    write_fitted_lights(out, [PointLightValue(np.array([-0.5, 1.0, -2.0]), np.array([4.0, 4.0, 4.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    layer = Sdf.Layer.FindOrOpen(str(out / USER_LIGHTS))
    stage = Usd.Stage.Open(layer)
    stage.OverridePrim("/Scene")
    UsdGeom.Scope.Define(stage, "/Scene/Lights")
    UsdGeom.Scope.Define(stage, "/Scene/Lights/User")
    light = UsdLux.SphereLight.Define(stage, "/Scene/Lights/User/Mover")
    light.CreateTreatAsPointAttr(True)
    light.CreateRadiusAttr(0.0)
    light.CreateNormalizeAttr(False)
    light.CreateIntensityAttr(2.5)
    op = UsdGeom.Xformable(light).AddTranslateOp()
    for i in range(FRAMES):
        op.Set(Gf.Vec3d(*_path(i)), Usd.TimeCode(1 + i))
    layer.GetPrimAtPath("/Scene").specifier = Sdf.SpecifierOver
    layer.Save()
    return scene


def _centroid_x(img: np.ndarray) -> float:
    """x of the centroid of the brightest 2% of pixels (luminance)."""
    lum = img[..., :3].astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    ys, xs = np.nonzero(lum >= np.percentile(lum, 98))
    return float(xs.mean())


def test_frames_video_and_single_time(animated_stage, tmp_path, cli):
    video = tmp_path / "out.mp4"
    res = cli.json("relight", animated_stage, "--frames", "1:12", "--video", video, "--mode", "add",
                   "-o", tmp_path / "frames")
    assert [f["time"] for f in res["frames"]] == list(range(1, 13))
    assert res["video"] == str(video)
    with av.open(str(video)) as c:
        s = c.streams.video[0]
        assert (s.width, s.height) == (256, 192)
        assert float(s.average_rate) == pytest.approx(24.0)
        assert s.codec_context.name == "h264"
        decoded = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(decoded) == FRAMES
    # the pool of the moving light travels left to right, frame after frame, in the video and in the EXRs
    cx_video = [_centroid_x(f) for f in decoded]
    exrs = [read_raw(f["exr"])[0] for f in res["frames"]]
    cx_exr = [_centroid_x(e) for e in exrs]
    assert np.all(np.diff(cx_video) > 0), cx_video
    assert np.all(np.diff(cx_exr) > 0), cx_exr
    assert cx_exr[-1] - cx_exr[0] > 100  # pixels: it crosses most of the 256-pixel frame
    # a frame equals the single-frame relight at its time: exactly for the EXR, within H.264 error for the MP4
    single = cli.json("relight", animated_stage, "--time", "5", "--mode", "add", "-o", tmp_path / "single")
    assert single["frames"][0]["time"] == 5
    one = read_raw(single["exr"])[0]
    np.testing.assert_array_equal(one, exrs[4])
    from usdrelight.relight.session import RelightSession
    from usdrelight.relight.video import video_frame

    with RelightSession(animated_stage, max_side=None) as session:  # the clip is shown at the photo's exposure
        exposure = max(1.0, float(np.percentile(session.source_photo(), 99.5)))
    err = np.abs(decoded[4].astype(np.float64) - video_frame(one, exposure)).mean()
    assert err < 2.5, err  # mean absolute error in 8-bit levels
    # between samples the light is interpolated: time 5.5 lies between frames 5 and 6
    half = cli.json("relight", animated_stage, "--time", "5.5", "--mode", "add", "-o", tmp_path / "half")
    assert cx_exr[4] < _centroid_x(read_raw(half["exr"])[0]) < cx_exr[5]


def test_unchanged_lights_are_not_rendered_again(animated_stage):
    from usdrelight.relight.session import RelightSession

    with RelightSession(animated_stage, max_side=64, with_fitted=True, mode="ratio") as s:
        s.render(time_code=1)
        kept = s.engine.terms_kept
        assert kept == 2  # the fitted point light and the mover at time 1
        s.render(time_code=2)
        assert s.engine.terms_kept == 3  # only the mover's new position was rendered; the fitted light reused
        a = s.render(time_code=1).diffuse
        assert s.engine.terms_kept == 3
        np.testing.assert_array_equal(a, s.render(time_code=1).diffuse)


def test_default_time_is_first_sample(animated_stage):
    """No --time: a stage with no authored range reads each attribute's first sample (not the fallback)."""
    from usdrelight.stage.read import read_lights
    from usdrelight.stage.timing import frame_time
    from usdrelight.stage.validate import open_stage

    stage = open_stage(animated_stage)
    mover = [l for l in read_lights(stage, frame_time(stage)) if l.path.endswith("Mover")][0]
    np.testing.assert_allclose(mover.to_world[:3, 3], _path(0))
    mover = [l for l in read_lights(stage, frame_time(stage, 12)) if l.path.endswith("Mover")][0]
    np.testing.assert_allclose(mover.to_world[:3, 3], _path(11))


@pytest.mark.parametrize("tcps", [None, 48.0])
def test_sequence_saved_as_layer_gives_the_same_frames(animated_stage, tmp_path, cli, tcps):
    """--sequence LIGHTS.json --save-lights LAYER: that layer, sublayered, renders the same frames via --frames;
    on a stage of 48 time codes per second and 12 frames per second too (before: the layer had 12, so USD
    rescaled its samples to time codes 4, 8, 12 and frames 1-3 all showed frame 0's lights)."""
    from pxr import Sdf

    specs = [[f"spot:{x:.3f},-0.4,-3.0:0,-1,-0.2:{2 + i},{1 + i},1:35:0.3", "point:-0.5,0.5,-2.5:1,1,1"]
             for i, x in enumerate(np.linspace(-1, 1, 4))]
    specs[2] = specs[2][:1]  # the second light is absent from frame 2: invisible there
    seq = tmp_path / "lights.json"
    seq.write_text(json.dumps(specs))
    # the user's own stage: a copy of the folder without the mover, whose lights_user.usda will sublayer the layer
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(animated_stage.parent, copy, symlinks=True)
    if tcps is not None:
        root = Sdf.Layer.FindOrOpen(str(copy / "scene.usda"))
        root.timeCodesPerSecond, root.framesPerSecond = tcps, 12.0
        root.Save()
    user = Sdf.Layer.FindOrOpen(str(copy / USER_LIGHTS))
    edit = Sdf.BatchNamespaceEdit()
    edit.Add("/Scene/Lights/User/Mover", Sdf.Path.emptyPath)
    assert user.Apply(edit)
    user.Save()
    layer = copy / "anim_lights.usda"
    a = cli.json("relight", copy / "scene.usda", "--sequence", seq, "--save-lights", layer, "--max-side", "96",
                 "--mode", "add", "-o", tmp_path / "a")
    assert a["lights_layer"] == str(layer) and layer.is_file()
    # a second save never overwrites the layer
    rc, _, err = cli("relight", copy / "scene.usda", "--sequence", seq, "--save-lights", layer, "-o", tmp_path / "c")
    assert rc == 2 and "exists" in err and err.count("\n") == 1
    user.subLayerPaths.append("./anim_lights.usda")
    user.Save()
    b = cli.json("relight", copy / "scene.usda", "--frames", "1:4", "--max-side", "96", "--mode", "add",
                 "-o", tmp_path / "b")
    assert len(b["frames"]) == len(a["frames"]) == 4
    assert [f["lights"] for f in b["frames"]] == [2, 2, 1, 2]
    for fa, fb in zip(a["frames"], b["frames"]):
        # float32 colour in the layer: equal to rounding
        np.testing.assert_allclose(read_raw(fb["diffuse"])[0], read_raw(fa["diffuse"])[0], rtol=1e-5, atol=1e-7)


def test_convert_frames_writes_one_mitsuba_xml_per_time(animated_stage, tmp_path, cli):
    res = cli.json("convert", animated_stage, tmp_path / "scene.xml", "--frames", "1:12:5")
    xmls = sorted(tmp_path.glob("scene_*.xml"))
    assert [p.name for p in xmls] == ["scene_0000.xml", "scene_0001.xml", "scene_0002.xml"]
    assert str(xmls[0]) in res["files"]
    rc, stdout, _ = cli("convert", animated_stage, tmp_path / "again.xml", "--frames", "1:12:5")
    assert rc == 0 and stdout.startswith(f"wrote {tmp_path / 'again_0000.xml'} and ")  # names a file it wrote
    for path, i in zip(xmls, (0, 5, 10)):
        assert _point_positions(path).get("Scene_Lights_User_Mover") == pytest.approx(_path(i))
    one = cli.json("convert", animated_stage, tmp_path / "t7.xml", "--time", "7")
    assert _point_positions(one["files"][0])["Scene_Lights_User_Mover"] == pytest.approx(_path(6))


def _point_positions(path) -> dict:
    """Mitsuba XML: point emitter id -> its position."""
    import xml.etree.ElementTree as ET

    out = {}
    for e in ET.parse(path).getroot().iter("emitter"):
        pos = e.find("point[@name='position']")
        if e.get("type") == "point" and pos is not None:
            out[e.get("id")] = tuple(float(v) for v in pos.get("value").split(","))
    return out


@pytest.mark.parametrize("args, message", [
    (["--frames", "5:1"], "END must not be before START"),
    (["--frames", "1:5:0"], "STEP must be > 0"),
    (["--frames", "1:1000000"], "at most"),
    (["--frames"], "no time range"),
    (["--video", "out.avi"], ".mp4"),
    (["--frames", "1:3", "--time", "2"], "give one"),
    (["--time", "nan"], "finite"),
])
def test_bad_time_input_is_one_line(animated_stage, tmp_path, cli, args, message):
    out = tmp_path / "o"
    rc, stdout, err = cli("relight", animated_stage, "--with-fitted", "-o", out, *args)
    assert rc == 2 and message in err and err.count("\n") == 1, err
    assert not out.exists()


def test_area_lights_of_a_sequence_survive_the_saved_layer(tmp_path):
    """rect, disk and sphere --light specs (sizes, positions and directions changing per frame) written as a
    time-sampled layer and read back at each frame's time code: the same records (float32 attributes: to
    rounding), normalize authored off."""
    from pxr import Sdf, Usd, UsdGeom

    from usdrelight.stage.animated_lights import write_sequence_layer
    from usdrelight.stage.light_specs import parse_lights
    from usdrelight.stage.read import read_lights

    specs = [[f"rect:{0.3 + 0.1 * i},1.6,-3.0:{0.1 * i},-1,0.2:6,{6 - i},6:{0.5 + 0.25 * i},0.5",
              f"disk:-0.6,1.5,-2.5:0.3,-1,{0.1 * i}:4,4,4:{0.25 * (i + 1)}",
              f"sphere:-0.5,{1.0 + 0.2 * i},-2.0:20,20,20:{0.125 * (i + 1)}"] for i in range(3)]
    frames = [parse_lights(f) for f in specs]
    layer = write_sequence_layer(tmp_path / "area.usda", frames)
    root = Sdf.Layer.CreateNew(str(tmp_path / "root.usda"))
    root.subLayerPaths.append("./area.usda")
    stage = Usd.Stage.Open(root)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.DefinePrim("/Scene", "Xform")
    text = layer.read_text()
    assert "RectLight" in text and "DiskLight" in text and text.count("bool inputs:normalize = 0") == 3
    for i, want in enumerate(frames):
        got = sorted(read_lights(stage, 1.0 + i), key=lambda l: l.path)
        assert [g.kind for g in got] == ["rect", "disk", "sphere"]
        for g, w in zip(got, want):
            assert g.path == w.path and not g.normalize and not g.treat_as_point
            assert (g.radius, g.width, g.height) == (w.radius, w.width, w.height)  # exact in float32
            np.testing.assert_allclose(g.to_world, w.to_world, atol=1e-6)
            np.testing.assert_allclose(g.radiance, w.radiance, rtol=1e-6)
    # the kinds stay apart in a sequence: a rect may not turn into a disk
    from usdrelight.errors import UsdRelightError

    with pytest.raises(UsdRelightError, match="changes kind"):
        write_sequence_layer(tmp_path / "bad.usda", [frames[0][:1], parse_lights([specs[0][1]])])
    assert not (tmp_path / "bad.usda").exists()


def test_contact_sheet_of_a_clip_shows_its_first_frame(animated_stage, tmp_path, cli):
    """Before: the used mode's panel was the first frame and every other panel the last frame's lights."""
    cli.json("relight", animated_stage, "--frames", "1:3", "--contact-sheet", "--mode", "add", "-o", tmp_path / "c")
    cli.json("relight", animated_stage, "--time", "1", "--contact-sheet", "--mode", "add", "-o", tmp_path / "s")
    clip, single = read_raw(tmp_path / "c" / "contact_sheet.png")[0], read_raw(tmp_path / "s" / "contact_sheet.png")[0]
    assert clip.shape == single.shape
    np.testing.assert_array_equal(clip, single)


def test_a_reversed_authored_range_is_one_line(animated_stage, tmp_path, cli):
    """Before: 'no light to relight with at any frame', 'no frame to encode' or an UnboundLocalError."""
    import shutil

    from pxr import Sdf

    stage = tmp_path / "st" / animated_stage.name
    shutil.copytree(animated_stage.parent, stage.parent)
    layer = Sdf.Layer.FindOrOpen(str(stage))
    layer.startTimeCode, layer.endTimeCode = 5, 1
    layer.Save()
    for extra in ([], ["--with-fitted"], ["--video", str(tmp_path / "v.mp4")]):
        rc, _, err = cli("relight", stage, "--frames", "-o", tmp_path / "o", *extra)
        assert rc == 2 and "endTimeCode (1) is before its startTimeCode (5)" in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists() and not (tmp_path / "v.mp4").exists()


def test_visibility_keyed_on_a_scope_is_a_light_time_code():
    """A Scope's visibility hides the lights below it (USD and relight read no light there), but only Xformable
    ancestors were searched for samples: the Blender converter keyed nothing and kept the light on."""
    from pxr import Usd, UsdGeom, UsdLux

    from usdrelight.stage.read import read_lights
    from usdrelight.stage.timing import light_time_codes

    stage = Usd.Stage.CreateInMemory()
    scope = UsdGeom.Scope.Define(stage, "/Group")
    for t, v in ((1, "inherited"), (3, "invisible"), (5, "inherited")):
        scope.CreateVisibilityAttr().Set(v, Usd.TimeCode(t))
    UsdLux.SphereLight.Define(stage, "/Group/Lamp").CreateIntensityAttr(3.0)
    assert light_time_codes(stage) == [1.0, 3.0, 5.0]
    assert [len(read_lights(stage, Usd.TimeCode(t))) for t in (1, 3, 5)] == [1, 0, 1]


@pytest.mark.parametrize("frames, rate", [("1:5", 48.0), ("1:5:2", 24.0)])
def test_video_plays_in_the_stages_seconds(animated_stage, tmp_path, cli, frames, rate):
    """A video of frames STEP time codes apart plays at timeCodesPerSecond / STEP, whatever framesPerSecond says
    (before: framesPerSecond, one time code per video frame: a 48-codes-per-second stage at 24 fps played at half
    speed, and --frames 1:48:2 twice as fast)."""
    import shutil

    from pxr import Sdf

    stage = tmp_path / "st" / animated_stage.name
    shutil.copytree(animated_stage.parent, stage.parent)
    layer = Sdf.Layer.FindOrOpen(str(stage))
    layer.timeCodesPerSecond, layer.framesPerSecond = 48, 24
    layer.Save()
    video = tmp_path / "v.mp4"
    res = cli.json("relight", stage, "--frames", frames, "--video", video, "--max-side", "64", "--mode", "add",
                   "-o", tmp_path / "o")
    with av.open(str(video)) as c:
        assert float(c.streams.video[0].average_rate) == pytest.approx(rate)
        assert c.streams.video[0].frames == len(res["frames"])


@pytest.mark.parametrize("h, w", [(48, 64), (47, 63)])
def test_video_is_tagged_bt709_and_decodes_to_its_pngs(tmp_path, h, w):
    """The MP4 carried no colour tags (players guess BT.709 for HD, BT.601 for SD) and was encoded with BT.601:
    decoded as BT.709, red (231, 63, 63) came back (246, 79, 60); truncating conversion made it 1 level darker."""
    from usdrelight.relight.video import Mp4Writer, video_frame

    img = np.zeros((h, w, 3), np.float32)
    for i, c in enumerate([(0.8, 0.05, 0.05), (0.05, 0.6, 0.05), (0.2, 0.2, 0.2), (0.05, 0.05, 0.7)]):
        img[:, i * w // 4:(i + 1) * w // 4] = c
    with Mp4Writer(tmp_path / "v.mp4", 24) as mp4:
        mp4.add(img)
    want = video_frame(img, mp4.exposure).astype(np.float64)
    with av.open(str(tmp_path / "v.mp4")) as c:
        cc = c.streams.video[0].codec_context
        assert (cc.colorspace, cc.color_primaries, cc.color_trc, cc.color_range) == (1, 1, 1, 1)  # BT.709, MPEG range
        frame = next(c.decode(video=0))
        got = frame.reformat(format="rgb24", src_colorspace="ITU709", src_color_range="MPEG").to_ndarray()
    inner = (slice(2, -2), slice(None))  # away from the colour edges (4:2:0 blends two pixels of chroma)
    err = got.astype(np.float64) - want
    assert np.abs(err).mean() < 1.5 and abs(err.mean()) < 0.8, (np.abs(err).mean(), err.mean())
    for i in range(4):  # each stripe's centre column within 2 levels in every channel, median over its rows (BT.601: 5-23)
        x = i * w // 4 + w // 8
        assert np.abs(np.median(err[inner][:, x], axis=0)).max() <= 2, (i, np.median(err[inner][:, x], axis=0))


def test_a_range_saved_in_the_lights_layer_is_the_stages(animated_stage, tmp_path, cli):
    """The web app saves its range into lights_user.usda; USD reads a range from the root layer only, so a bare
    --frames said 'the stage authors no time range'. Now the strongest sublayer's range counts, in stage time
    codes (a 48-codes-per-second layer's 2..10 is 1..5 of this 24-codes stage)."""
    import shutil

    from pxr import Sdf

    from usdrelight.stage.layout import USER_LIGHTS

    stage = tmp_path / "st" / animated_stage.name
    shutil.copytree(animated_stage.parent, stage.parent)
    layer = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    layer.startTimeCode, layer.endTimeCode, layer.timeCodesPerSecond = 2, 10, 48
    layer.Save()
    res = cli.json("relight", stage, "--frames", "--max-side", "32", "--mode", "add", "-o", tmp_path / "o")
    assert [f["time"] for f in res["frames"]] == [1, 2, 3, 4, 5]


def test_a_range_in_a_layer_sublayered_into_the_lights_layer_is_the_stages(animated_stage, tmp_path, cli):
    """A relight --save-lights layer sublayered into lights_user.usda (as animation.md says to): its range sits
    a level below the root's sublayers, and a bare --frames said 'the stage authors no time range'. The layer
    stack is searched depth first (a 48-codes layer's 2..10, offset by 1 in its parent: 2..6)."""
    import shutil

    from pxr import Sdf

    from usdrelight.stage.layout import USER_LIGHTS

    stage = tmp_path / "st" / animated_stage.name
    shutil.copytree(animated_stage.parent, stage.parent)
    saved = Sdf.Layer.CreateNew(str(stage.parent / "saved.usda"))
    saved.startTimeCode, saved.endTimeCode, saved.timeCodesPerSecond = 2, 10, 48
    saved.Save()
    user = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    user.subLayerPaths.append("./saved.usda")
    user.subLayerOffsets[len(user.subLayerPaths) - 1] = Sdf.LayerOffset(1.0, 1.0)
    user.Save()
    res = cli.json("relight", stage, "--frames", "--max-side", "32", "--mode", "add", "-o", tmp_path / "o")
    assert [f["time"] for f in res["frames"]] == [2, 3, 4, 5, 6]


def test_a_pre_roll_range_is_read(animated_stage, tmp_path, cli):
    """'--frames -2:0' was 'unrecognized arguments: -2:0' (argparse takes '-2:0' for an option)."""
    res = cli.json("relight", animated_stage, "--frames", "-2:0", "--max-side", "32", "--mode", "add",
                   "-o", tmp_path / "o")
    assert [f["time"] for f in res["frames"]] == [-2, -1, 0]


def test_a_lights_layer_at_another_rate_is_warned(animated_stage, tmp_path, cli):
    """A Houdini-style lights layer at 30 time codes per second in a 24 stage: USD reads its sample at 30 at 24,
    and relight said nothing (the light stopped at frame 24 of a 1:30 clip)."""
    import shutil

    from pxr import Sdf

    from usdrelight.stage.layout import USER_LIGHTS

    stage = tmp_path / "st" / animated_stage.name
    shutil.copytree(animated_stage.parent, stage.parent)
    layer = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    layer.timeCodesPerSecond = 30
    layer.Save()
    rc, _, err = cli("relight", stage, "--time", "3", "--max-side", "32", "--mode", "add", "-o", tmp_path / "o")
    assert rc == 0 and f"layer {USER_LIGHTS} has 30 time codes per second, the stage 24 (USD reads its time " \
        "samples scaled by 0.8)" in err, err
    rc, _, err = cli("relight", animated_stage, "--time", "3", "--max-side", "32", "--mode", "add", "-o",
                     tmp_path / "p")
    assert rc == 0 and "time codes per second" not in err, err


def test_a_fine_step_without_video_is_no_error(animated_stage, tmp_path, cli):
    """The video's frame rate (at most 1000) was checked for every --frames run: 0.01 time codes apart at 24 codes a
    second failed with '2400 fps video' though no video was asked for."""
    res = cli.json("relight", animated_stage, "--frames", "1:1.02:0.01", "--max-side", "32", "--mode", "add",
                   "-o", tmp_path / "o")
    assert [f["time"] for f in res["frames"]] == [1, 1.01, 1.02]


CM_STAGE = '''#usda 1.0
(
    upAxis = "Z"
    metersPerUnit = 0.01
    defaultPrim = "World"
)
def Xform "World" {
    def Mesh "Floor" {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-300, -300, 0), (300, -300, 0), (300, 300, 0), (-300, 300, 0)]
        color3f[] primvars:displayColor = [(0.5, 0.5, 0.5)]
    }
    def Camera "Cam" {
        float focalLength = 24
        float horizontalAperture = 36
        float verticalAperture = 27
        double3 xformOp:translate = (0, -400, 200)
        float3 xformOp:rotateXYZ = (70, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
    }
}
def RenderSettings "Render" {
    uniform int2 resolution = (64, 48)
}
'''


def test_saved_lights_of_a_foreign_centimetre_stage_light_it_as_rendered(cli, tmp_path):
    """A Z-up centimetre stage rooted at /World: the --save-lights layer was `over "Scene"` (nothing defined
    there: 'no light to relight with') in metres without metersPerUnit (sublayered, the light came 100x too
    close). Now a typeless def in the stage's unit and up axis: read back, the lights are the --light ones, and
    the stage relit from the layer alone is the relight that wrote it."""
    from usdrelight.imageio import read_map
    from usdrelight.stage.light_specs import parse_lights
    from usdrelight.stage.read import read_lights
    from usdrelight.stage.validate import open_stage

    (tmp_path / "shot.usda").write_text(CM_STAGE)
    specs = [["point:0.3,0.2,1:20,20,20", "rect:0,0,1.5:0,0,-1:5,5,5:0.5,0.3"]]
    (tmp_path / "seq.json").write_text(json.dumps(specs))
    rc, _, err = cli("relight", tmp_path / "shot.usda", "--sequence", tmp_path / "seq.json", "--mode", "render",
                     "--save-lights", tmp_path / "saved.usda", "-o", tmp_path / "a")
    assert rc == 0, err
    (tmp_path / "lit.usda").write_text('#usda 1.0\n(\n    upAxis = "Z"\n    metersPerUnit = 0.01\n'
                                       '    subLayers = [@./saved.usda@, @./shot.usda@]\n)\n')
    got = sorted(read_lights(open_stage(tmp_path / "lit.usda"), 1.0), key=lambda l: l.path)
    want = parse_lights(specs[0])
    assert [g.kind for g in got] == ["sphere", "rect"]
    for g, w in zip(got, want):  # read in metres: the stage's 0.01 scale on the light's axes and sizes
        np.testing.assert_allclose(g.to_world[:3, 3], w.to_world[:3, 3], atol=1e-5)
        np.testing.assert_allclose(g.to_world[:3, :3] / 0.01, w.to_world[:3, :3], atol=1e-5)
        np.testing.assert_allclose((g.width * 0.01, g.height * 0.01), (w.width, w.height), rtol=1e-6)
        np.testing.assert_allclose(g.radiance, w.radiance, rtol=1e-6)
    rc, _, err = cli("relight", tmp_path / "lit.usda", "--mode", "render", "--time", "1", "-o", tmp_path / "b")
    assert rc == 0, err
    np.testing.assert_allclose(read_map(tmp_path / "b" / "relit.exr", 3),
                               read_map(tmp_path / "a" / "relit_0000.exr", 3), rtol=1e-4, atol=1e-6)
