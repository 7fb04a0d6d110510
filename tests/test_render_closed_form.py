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
