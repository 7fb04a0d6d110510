"""Closed-form renders through the USD -> Mitsuba mapping: point, dome, distant lights."""
import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from usd_scenes import looking_down_at_floor
from usdrelight.mitsuba.render import render_stage
from usdrelight.imageio import read_map


def _centre(path):
    img = read_map(path, 3)
    h, w = img.shape[:2]
    return img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean((0, 1))


def test_point_light(tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda")
    light = UsdLux.SphereLight.Define(stage, "/World/Key")
    light.CreateIntensityAttr(20.0)
    light.CreateTreatAsPointAttr(True)
    UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=16)
    np.testing.assert_allclose(_centre(res.files["color"]), 0.5 * 20 / np.pi, rtol=0.03)


def test_untextured_dome(tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda")
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateIntensityAttr(0.8)
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=64)
    np.testing.assert_allclose(_centre(res.files["color"]), 0.4, rtol=0.03)


def test_distant_light_straight_down(tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda")
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(3.0)
    sun.CreateAngleAttr(0.0)
    UsdGeom.Xformable(sun).AddRotateXOp().Set(-90.0)  # local -Z -> world -Y (pointing down)
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=4)
    np.testing.assert_allclose(_centre(res.files["color"]), 0.5 * 3 / np.pi, rtol=0.03)


@pytest.mark.parametrize("yaw", [0.0, 90.0])
def test_textured_dome_seen_directly_has_usd_orientation(tmp_path, yaw):
    from usd_scenes import asymmetric_latlong, dome_view_stage, expected_dome_view

    tex = asymmetric_latlong()
    dome_view_stage(tmp_path / "s.usda", tex, yaw)
    img = read_map(render_stage(tmp_path / "s.usda", spp=16).files["color"], 3)
    assert np.abs(img - expected_dome_view(tmp_path / "s.usda", tex)).mean() < 0.02
    assert np.abs(img - expected_dome_view(tmp_path / "s.usda", tex[::-1, ::-1])).mean() > 0.1


def test_off_centre_principal_point_lands_geometry_on_the_right_pixels(tmp_path):
    """A unit square at z = -2 must cover exactly the pixels the intrinsics predict (cx, cy far off-centre)."""
    from pxr import UsdShade

    from usd_scenes import camera, diffuse_material, new_stage
    from usdrelight.intrinsics import Intrinsics

    intr = Intrinsics(40.0, 40.0, 14.0, 26.0, 48, 32)  # principal point left of and below the centre
    stage = new_stage(tmp_path / "s.usda")
    m = UsdGeom.Mesh.Define(stage, "/World/Square")
    m.CreatePointsAttr([(0, 0, -2), (0.5, 0, -2), (0.5, 0.25, -2), (0, 0.25, -2)])  # USD frame, +Y up
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(diffuse_material(stage, "/World/M"))
    camera(stage, intr, aovs=("valid",))
    stage.GetRootLayer().Save()
    valid = read_map(render_stage(tmp_path / "s.usda").files["valid"], 1)[..., 0] > 0.5
    # OpenCV frame: x in [0, 0.5], y in [-0.25, 0] at z = 2 -> u in [14, 24], v in [21, 26]
    expected = np.zeros_like(valid)
    expected[21:26, 14:24] = True
    assert np.array_equal(valid, expected)


def test_camera_exposure_scales_the_colour(tmp_path, cli):
    """UsdGeom.Camera exposure (2 stops; exposure:iso 200 doubles again) scales the radiance a USD renderer
    writes: 0.4 x 8 under the 0.8 dome. Before, it was ignored (0.4) and the XML export said nothing."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateIntensityAttr(0.8)
    cam = UsdGeom.Camera(next(p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)))
    cam.CreateExposureAttr(2.0)
    cam.CreateExposureIsoAttr(200.0)
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=64)
    np.testing.assert_allclose(_centre(res.files["color"]), 0.4 * 8, rtol=0.03)
    assert not any("exposure" in w for w in res.warnings), res.warnings  # render applies it
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.xml")
    assert rc == 0 and "camera exposure (x8 on radiance; not carried: the target has none)" in err, err


def test_a_stage_without_light_renders_black_and_says_so(tmp_path):
    """An unfitted stage rendered an all-zero colour AOV with no word."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=1)
    assert read_map(res.files["color"], 3).max() == 0.0
    assert res.warnings.get("no light in the stage (its colour AOVs are black; fit it, or add lights)") == 1
