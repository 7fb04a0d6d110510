"""Intrinsics <-> UsdGeom.Camera: checked against USD's own projection (Gf.Camera), not our formulas."""
import json
import math

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

from usdrelight.stage.camera import intrinsics_from_usd_camera, usd_camera_params
from usdrelight.errors import UsdRelightError
from usdrelight.intrinsics import Intrinsics


def _gf_project(intr: Intrinsics, pts_cv: np.ndarray) -> np.ndarray:
    """Project OpenCV points to corner-origin pixels through a Gf.Camera built from the USD params."""
    p = usd_camera_params(intr)
    cam = Gf.Camera(Gf.Matrix4d(1), Gf.Camera.Perspective, p["horizontalAperture"], p["verticalAperture"],
                    p["horizontalApertureOffset"], p["verticalApertureOffset"], p["focalLength"])
    proj = cam.frustum.ComputeProjectionMatrix()
    out = []
    for x, y, z in pts_cv:
        ndc = proj.Transform(Gf.Vec3d(x, -y, -z))  # OpenCV -> USD camera frame
        out.append(((ndc[0] + 1) / 2 * intr.width, (1 - ndc[1]) / 2 * intr.height))
    return np.array(out)


@pytest.mark.parametrize("intr", [
    Intrinsics(994.978, 994.978, 311.693, 255.377, 741, 500),   # Middlebury, off-centre principal point
    Intrinsics(1200.0, 900.0, 700.0, 300.0, 1280, 720),          # non-square pixels
    Intrinsics.from_fov_x(90.0, 64, 48),
])
def test_usd_camera_reprojects_like_the_intrinsics(intr):
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [intr.width, intr.height], size=(50, 2))
    z = rng.uniform(0.1, 100.0, size=50)
    pts = np.stack([(uv[:, 0] - intr.cx) / intr.fx * z, (uv[:, 1] - intr.cy) / intr.fy * z, z], 1)
    np.testing.assert_allclose(_gf_project(intr, pts), uv, atol=1e-3)


def test_intrinsics_survive_a_usd_round_trip(tmp_path):
    intr = Intrinsics(1200.0, 900.0, 700.0, 300.0, 1280, 720)
    stage = Usd.Stage.CreateNew(str(tmp_path / "cam.usda"))
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    p = usd_camera_params(intr)
    for k in ("focalLength", "horizontalAperture", "verticalAperture", "horizontalApertureOffset",
              "verticalApertureOffset"):
        cam.GetPrim().GetAttribute(k).Set(p[k])
    stage.GetRootLayer().Save()
    reopened = Usd.Stage.Open(str(tmp_path / "cam.usda"))
    cam = UsdGeom.Camera(reopened.GetPrimAtPath("/Cam"))
    back = intrinsics_from_usd_camera(cam, 1280, 720, pixel_aspect=p["pixelAspectRatio"])
    for k in ("fx", "fy", "cx", "cy"):
        assert getattr(back, k) == pytest.approx(getattr(intr, k), rel=1e-6)
    assert p["pixelAspectRatio"] == pytest.approx(0.75)
    # without the pixel aspect the RenderSettings carry, USD's fallback policy widens the aperture to 16:9
    square = intrinsics_from_usd_camera(cam, 1280, 720)
    assert square.fx == pytest.approx(square.fy) == pytest.approx(900.0, rel=1e-6)


def test_intrinsics_json_forms(tmp_path):
    f = tmp_path / "k.json"
    f.write_text(json.dumps({"fx": 500, "fy": 510, "cx": 319.5, "cy": 239.5}))
    k = Intrinsics.from_json(f, 640, 480)
    assert (k.fx, k.fy, k.cx, k.cy) == (500, 510, 320.0, 240.0)  # OpenCV centres -> corner origin
    f.write_text(json.dumps([[0.8, 0, 0.5], [0, 1.1, 0.5], [0, 0, 1]]))  # MoGe normalized
    k = Intrinsics.from_json(f, 640, 480)
    assert (k.fx, k.fy, k.cx, k.cy) == pytest.approx((512, 528, 320, 240))
    f.write_text(json.dumps({"K": [[500, 0, 319.5], [0, 500, 239.5], [0, 0, 1]]}))
    assert Intrinsics.from_json(f, 640, 480).cx == pytest.approx(320.0)
    assert Intrinsics.from_fov_x(90.0, 640, 480).fx == pytest.approx(320.0)


@pytest.mark.parametrize("text", [
    '{"fx": NaN, "fy": 1, "cx": 1, "cy": 1}', '{"fx": -5, "fy": 5, "cx": 1, "cy": 1}',
    '{"fx": 0, "fy": 5, "cx": 1, "cy": 1}', '{"fx": 1e999, "fy": 5, "cx": 1, "cy": 1}',
    '{"fx": 5}', "[[1, 2], [3, 4]]", "not json",
    '{"fx": 5, "fy": 5, "cx": 1, "cy": 1, "width": 10, "height": 10}',
])
def test_bad_intrinsics_are_rejected(tmp_path, text):
    f = tmp_path / "k.json"
    f.write_text(text)
    with pytest.raises(UsdRelightError):
        Intrinsics.from_json(f, 640, 480)


def test_fit_to_points_recovers_intrinsics():
    intr = Intrinsics(400.0, 420.0, 150.0, 110.0, 320, 240)
    rng = np.random.default_rng(0)
    pts = intr.unproject(rng.uniform(1, 5, size=(240, 320)))
    fit = Intrinsics.fit_to_points(pts, np.ones((240, 320), bool))
    assert (fit.fx, fit.fy, fit.cx, fit.cy) == pytest.approx((400, 420, 150, 110), rel=1e-4)
    assert math.isclose(Intrinsics.from_fov_x(60, 100, 50).fov_x_deg, 60.0)
