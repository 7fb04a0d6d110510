"""Closed-form renders through the USD -> Mitsuba mapping: point, dome, distant lights."""
import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from usd_scenes import looking_down_at_floor
from usdrelight.render import render_stage
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


def _latlong_lookup(img, dirs):
    """Independent OpenEXR latlong lookup: u=0 -> -Z, u=1/4 -> +X, u=1/2 -> +Z, top row -> +Y (bilinear)."""
    h, w = img.shape[:2]
    u = (np.arctan2(dirs[..., 0], -dirs[..., 2]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(dirs[..., 1], -1, 1)) / np.pi
    x, y = u * w - 0.5, np.clip(v * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    y1 = np.minimum(y0 + 1, h - 1)
    x0m, x1m = x0 % w, (x0 + 1) % w
    return ((1 - fy) * ((1 - fx) * img[y0, x0m] + fx * img[y0, x1m]) + fy * ((1 - fx) * img[y1, x0m] + fx * img[y1, x1m]))


@pytest.mark.parametrize("yaw", [0.0, 90.0])
def test_textured_dome_seen_directly_has_usd_orientation(tmp_path, yaw):
    from usd_scenes import camera, new_stage
    from usdrelight.imageio import write_image
    from usdrelight.intrinsics import Intrinsics

    from usd_scenes import asymmetric_latlong

    tex = asymmetric_latlong()
    write_image(tmp_path / "env.exr", tex, "float")
    stage = new_stage(tmp_path / "s.usda")
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr("./env.exr")
    dome.CreateIntensityAttr(2.0)
    if yaw:
        UsdGeom.Xformable(dome).AddRotateYOp().Set(yaw)
    intr = Intrinsics.from_fov_x(100.0, 48, 32)
    cam = camera(stage, intr, rotate_x_deg=20.0)  # looking slightly up, towards -Z
    UsdGeom.Xformable(cam).AddRotateYOp().Set(-60.0)  # and turned towards +X
    stage.GetRootLayer().Save()
    res = render_stage(tmp_path / "s.usda", spp=16)
    img = read_map(res.files["color"], 3)
    # expected: pixel-centre rays through the camera, into the dome's frame, looked up in the latlong map
    from usdrelight.scene_read import read_scene
    from usdrelight.validate import open_stage

    rec = read_scene(open_stage(tmp_path / "s.usda"))
    rays = rec.camera.intrinsics.pixel_rays()
    rays[..., 1:] *= -1
    world = rays @ rec.camera.to_world[:3, :3].T
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    local = world @ rec.lights[0].to_world[:3, :3]  # inverse rotation
    expected = 2.0 * _latlong_lookup(tex, local)
    assert np.abs(img - expected).mean() < 0.02
    flipped = 2.0 * _latlong_lookup(tex[::-1, ::-1], local)
    assert np.abs(img - flipped).mean() > 0.1


def test_off_centre_principal_point_lands_geometry_on_the_right_pixels(tmp_path):
    """A unit square at z = -2 must cover exactly the pixels the intrinsics predict (cx, cy far off-centre)."""
    from pxr import Sdf, UsdShade

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
