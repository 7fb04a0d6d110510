"""Issue 26: a fitted photo stage opened in Mitsuba (.xml) and Blender (.blend) renders like the fast renderer's
D~ (no environment through the depth cuts), and F12 in Blender gives the relit photo of ``relight --mode ratio``.
The measurement functions are benchmarks/bench_photo_stage.py's (which runs the same on the motorcycle)."""
import json
import sys

import numpy as np
import pytest

from conftest import EXAMPLES, ROOT
from usdrelight.converters.blender import read_from_file, render_blend, run_blender
from usdrelight.converters.convert import convert
from usdrelight.imageio import read_map
from usdrelight.relight.composite import ratio_guard
from usdrelight.stage.backplate import HIDE_EMITTERS, hides_emitters
from usdrelight.stage.lux import emitted_radiance
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_photo_stage import compare, fast_fitted, mitsuba_render, moved_light, psnr, relight_ratio  # noqa: E402

SPP = 16


@pytest.fixture(scope="module")
def photo_stage(tmp_path_factory):
    """The procedural photo built at stride 2 (256 x 192) with fitted lights: two points and an environment bright
    enough to show through every cut if camera rays saw it; converted to .xml and .blend."""
    from usdrelight.stage.build import BuildOptions, build
    from usdrelight.stage.lights_layer import write_fitted_lights
    from usdrelight.stage.records import FitProvenance, PointLightValue

    ex, tmp = EXAMPLES / "procedural", tmp_path_factory.mktemp("photo_stage")
    build(ex / "photo.exr", tmp / "stage", BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                        albedo=ex / "albedo.exr", stride=2))
    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = [0.4, 0.5, 0.7]  # a sky above the horizon, brighter than the scene
    env[2:4, 10:14] = [3.0, 2.8, 2.4]
    write_fitted_lights(tmp / "stage", [PointLightValue(np.array([-1.0, 0.5, -1.8]), np.array([5.5, 5.4, 4.9])),
                                        PointLightValue(np.array([1.0, 1.0, -3.5]), np.array([1.0, 1.5, 2.0]))],
                        env, FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    stage = tmp / "stage" / "scene.usda"
    convert(stage, tmp / "xml" / "scene.xml", spp=SPP)
    convert(stage, tmp / "scene.blend", spp=SPP)
    aovs, fitted = fast_fitted(stage)
    return {"dir": tmp, "stage": stage, "aovs": aovs, "fitted": fitted}


def test_build_and_fit_author_the_setting_and_the_xml_honours_it(photo_stage):
    stage = open_stage(photo_stage["stage"])
    assert hides_emitters(stage)
    assert stage.GetPrimAtPath("/Render/Settings").GetAttribute(HIDE_EMITTERS).Get() is True
    xml = (photo_stage["dir"] / "xml" / "scene.xml").read_text()
    assert '<boolean name="hide_emitters" value="true" />' in xml and '<rfilter type="box" />' in xml


@pytest.mark.parametrize("renderer", ["mitsuba", "cycles"])
def test_converted_stage_renders_like_the_fast_renderer(photo_stage, renderer):
    """Same camera, resolution and path length: no environment through the cuts, image mean within 3% of D~."""
    d = photo_stage["dir"]
    if renderer == "mitsuba":
        img = mitsuba_render(d / "xml" / "scene.xml", 2 * SPP)
        seen = compare(mitsuba_render(d / "xml" / "scene.xml", 2 * SPP, hide=False), photo_stage["aovs"])
        assert seen["show_through"] > 0.005  # the measure sees the environment when camera rays do
    else:
        rgba = read_map(render_blend(d / "scene.blend", d / "cycles.exr"), 4)
        assert (rgba[..., 3] == 0).mean() > 0.005  # the cuts are transparent (the compositor's backplate shows)
        img = rgba[..., :3]
    got = compare(img, photo_stage["aovs"])
    print(renderer, got)
    assert got["show_through"] <= 0.001
    assert got["mean_ratio"] == pytest.approx(1.0, abs=0.03)


def test_f12_gives_the_relit_photo(photo_stage):
    """Unchanged lights: the photo itself (F was baked by the same Cycles render); one fitted light moved in the
    .blend: what `usdrelight relight --mode ratio` gives with the same lights; the lights still come back."""
    d, stage = photo_stage["dir"], photo_stage["stage"]
    from usdrelight.relight.session import RelightSession

    with RelightSession(stage, max_side=None) as s:
        photo = s.source_photo()
    same = read_map(render_blend(d / "scene.blend", d / "same.exr", composite=True), 3)
    assert np.abs(same - photo).max() < 1e-5
    point = [l for l in photo_stage["fitted"] if l.kind != "dome"][0]
    blend, moved = moved_light(d / "scene.blend", point, (1.2, 0.4, 0.6), d)
    f12 = read_map(render_blend(blend, d / "f12.exr", composite=True), 3)
    ref = relight_ratio(stage, [moved if l.path == point.path else l for l in photo_stage["fitted"]])
    print(f"F12 vs relight --mode ratio: mean {f12.mean() / ref.mean():.4f}, PSNR {psnr(f12, ref):.1f} dB "
          f"(relit vs photo {psnr(ref, photo):.1f} dB)")
    assert psnr(ref, photo) < 30  # the move is visible
    assert f12.mean() == pytest.approx(ref.mean(), rel=0.03)
    assert psnr(f12, ref) >= 35
    # back as lights_user.usda: the moved fitted light as an override of itself, the unchanged ones left out, so
    # the stage has each fitted light once, the moved one where Blender has it (they came back as user lights
    # too, and lit the scene twice)
    import shutil

    copy = d / "stage_copy"
    shutil.copytree(stage.parent, copy, symlinks=True)
    rep = read_from_file(blend, usd_path=str(d / "back.usda"))
    rep.stage.GetRootLayer().Save()
    shutil.copyfile(d / "back.usda", copy / "lights_user.usda")
    got = {l.path: l for l in read_scene(open_stage(copy / "scene.usda")).lights}
    assert sorted(got) == sorted(l.path for l in photo_stage["fitted"])
    np.testing.assert_allclose(got[point.path].to_world[:3, 3], moved.to_world[:3, 3], atol=1e-4)
    np.testing.assert_allclose(emitted_radiance(got[point.path]), emitted_radiance(point), rtol=1e-4)
    assert sum("edited in Blender" in w for w in rep.warnings) == 1
    # the guard k in the node tree is usdrelight's, computed from the photo and the baked F
    script = d / "k.py"
    script.write_text("import bpy, sys\nbpy.ops.wm.open_mainfile(filepath=sys.argv[-2])\n"
                      "open(sys.argv[-1], 'w').write(bpy.context.scene['usdrelight_ratio_k'])\n")
    run_blender(script, str(d / "scene.blend"), str(d / "k.json"))
    k = json.loads((d / "k.json").read_text())
    f = read_map(render_blend(d / "scene.blend", d / "raw.exr"), 4)  # no user lights: the raw render is F
    k_up, k_down = ratio_guard(photo, f[..., :3], f[..., 3] > 0)
    np.testing.assert_allclose(k["k_up"], k_up, rtol=1e-4)
    np.testing.assert_allclose(k["k_down"], k_down, rtol=1e-4)


def test_mitsuba_user_gets_the_relit_photo_from_a_render_of_the_xml(photo_stage):
    """scripts/relit_from_render.py on Mitsuba renders of the converted XML: F as converted, N with one light moved
    in the XML; unchanged lights give the photo back, the moved light what `relight --mode ratio` gives."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from relit_from_render import relit_from_render

    d, stage = photo_stage["dir"], photo_stage["stage"]
    point = [l for l in photo_stage["fitted"] if l.kind != "dome"][0]
    xml = (d / "xml" / "scene.xml").read_text()
    old = '<point name="position" value="%s" />' % ", ".join(repr(float(v)) for v in point.to_world[:3, 3])
    assert old in xml
    delta = np.array([1.2, 0.4, 0.6])
    new = '<point name="position" value="%s" />' % ", ".join(repr(float(v)) for v in point.to_world[:3, 3] + delta)
    (d / "xml" / "moved.xml").write_text(xml.replace(old, new))
    f = mitsuba_render(d / "xml" / "scene.xml", 4 * SPP)
    n = mitsuba_render(d / "xml" / "moved.xml", 4 * SPP)
    from usdrelight.relight.session import RelightSession

    with RelightSession(stage, max_side=None) as s:
        photo = s.source_photo()
    np.testing.assert_allclose(relit_from_render(stage, f, f), photo, atol=1e-6)
    m = point.to_world.copy()
    m[:3, 3] += delta
    from dataclasses import replace

    ref = relight_ratio(stage, [replace(point, to_world=m) if l.path == point.path else l
                                for l in photo_stage["fitted"]])
    got = relit_from_render(stage, n, f)
    print(f"Mitsuba ratio vs relight --mode ratio: mean {got.mean() / ref.mean():.4f}, PSNR {psnr(got, ref):.1f} dB")
    assert got.mean() == pytest.approx(ref.mean(), rel=0.03)
    assert psnr(got, ref) >= 35


def test_a_shot_layer_and_the_xml_round_trip_keep_emitters_hidden(photo_stage, tmp_path, cli):
    """A shot layer that sublayers scene.usda carries no renderSettingsPrimPath (USD reads stage metadata from
    the root layer only): its RenderSettings, the one every reader takes, still hides emitters (before: the
    setting was read only through the metadata, so render and .blend showed the lights while relight hid them);
    scene.xml read back into USD keeps it (before: only in customData, so the stage rendered its emitters)."""
    shot = photo_stage["stage"].parent / "shot.usda"  # beside scene.usda, as a TD's shot layer sits
    shot.write_text('#usda 1.0\n(\n    subLayers = [@./scene.usda@]\n)\n')
    assert hides_emitters(open_stage(shot))
    cli.json("convert", shot, tmp_path / "shot.xml")
    assert '<boolean name="hide_emitters" value="true" />' in (tmp_path / "shot.xml").read_text()
    cli.json("convert", photo_stage["dir"] / "xml" / "scene.xml", tmp_path / "back.usda")
    assert hides_emitters(open_stage(tmp_path / "back.usda"))


def test_cycles_hides_a_mesh_lights_emission_from_the_camera(tmp_path, cli):
    """A MeshLightAPI panel facing the camera on a stage that hides emitters: Cycles shows the panel black, as
    Mitsuba does (before: its emission, 2.5x the image mean); the floor it lights keeps its light."""
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
    renderSettingsPrimPath = "/Render"
)
def Camera "Cam" {
    float focalLength = 20
    float horizontalAperture = 36
    float verticalAperture = 27
}
def RenderSettings "Render" {
    rel camera = </Cam>
    int2 resolution = (32, 24)
    uniform bool usdrelight:hideEmitters = 1
}
def Mesh "Panel" (prepend apiSchemas = ["MeshLightAPI"]) {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-0.5, -0.3, -2), (0.5, -0.3, -2), (0.5, 0.3, -2), (-0.5, 0.3, -2)]
    float inputs:intensity = 10
    color3f[] primvars:displayColor = [(0, 0, 0)]
}
def Mesh "Floor" {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 3, 2, 1]
    point3f[] points = [(-3, -1, 0), (3, -1, 0), (3, -1, -6), (-3, -1, -6)]
    color3f[] primvars:displayColor = [(0.5, 0.5, 0.5)]
}
''')
    cli.json("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    img = read_map(render_blend(tmp_path / "s.blend", tmp_path / "c.exr", spp=16), 3)
    panel = img[10:14, 12:20].mean()  # the panel spans x 8-24, y 7-17 of the 32 x 24 image
    floor = img[20:, :].mean()
    assert panel < 0.05 and floor > 0.05, (panel, floor)
