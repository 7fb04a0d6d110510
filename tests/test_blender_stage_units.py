"""USD (any metersPerUnit, Y-up or Z-up) -> .blend -> lights layer -> sublayered into the original stage: every
light where it was, emitting what it emitted.

The .blend is built in metres, Z-up (read_scene applies metersPerUnit; blender_units turns Y-up into Z-up); the
writer records the source stage's metersPerUnit and upAxis in the Blender scene (``scene["usdrelight_stage"]``)
and the lights layer read back is written in them (USD ignores a sublayer's own metadata). Compared after
read_scene (world matrices in metres): to_world and emitted radiance within 1e-5, sizes (stage units) within 1e-5
relative, the cone within 1e-4. One Blender run per stage for the .blend, one for the lights (~3 s each).
"""
import math

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from usdrelight.converters.blender_units import stage_units
from usdrelight.errors import UsdRelightError
from usdrelight.stage.lux import emitted_radiance
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage


def _stage(path, up: str, mpu: float):
    """A point light, a rect light (normalize on) and a soft-edged spot (a sphere of radius 5 cm) under a moved
    rig, lengths authored in stage units (``mpu`` metres each); a Y-up layout turned Z-up for ``up`` "Z"."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    k = 1.0 / mpu  # metres -> stage units
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    rig.AddTranslateOp().Set(Gf.Vec3d(0.2 * k, -0.1 * k, 0.3 * k))
    if up == "Z":  # the same layout, its up (Y) turned to Z
        rig.AddRotateXOp().Set(90.0)
    key = UsdLux.SphereLight.Define(stage, "/World/Rig/Key")
    key.CreateIntensityAttr(12.0)
    key.CreateColorAttr((1.0, 0.5, 0.25))
    key.CreateTreatAsPointAttr(True)
    key.AddTranslateOp().Set(Gf.Vec3d(1.0 * k, 2.0 * k, 0.5 * k))
    panel = UsdLux.RectLight.Define(stage, "/World/Rig/Panel")
    panel.CreateWidthAttr(0.5 * k)
    panel.CreateHeightAttr(0.2 * k)
    panel.CreateIntensityAttr(3.0)
    panel.CreateNormalizeAttr(True)
    x = UsdGeom.Xformable(panel)
    x.AddTranslateOp().Set(Gf.Vec3d(-0.4 * k, 1.5 * k, -1.0 * k))
    x.AddRotateXYZOp().Set(Gf.Vec3f(-60.0, 20.0, 10.0))
    spot = UsdLux.SphereLight.Define(stage, "/World/Rig/Spot")
    spot.CreateRadiusAttr(0.05 * k)
    spot.CreateIntensityAttr(40.0)
    sh = UsdLux.ShapingAPI.Apply(spot.GetPrim())
    sh.CreateShapingConeAngleAttr(30.0)
    sh.CreateShapingConeSoftnessAttr(0.3)
    x = UsdGeom.Xformable(spot)
    x.AddTranslateOp().Set(Gf.Vec3d(0.0, 3.0 * k, 0.7 * k))
    x.AddRotateXOp().Set(-70.0)
    stage.GetRootLayer().Save()
    return stage


@pytest.mark.parametrize("up, mpu", [("Z", 0.01), ("Y", 1.0), ("Y", 0.01)])
def test_lights_layer_sublayered_into_the_source_stage_puts_every_light_back(cli, tmp_path, up, mpu):
    _stage(tmp_path / "s.usda", up, mpu)
    assert cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")[0] == 0
    rc, _, err = cli("convert", tmp_path / "s.blend", tmp_path / "lights.usda")
    assert rc == 0, err
    layer_stage = open_stage(tmp_path / "lights.usda")
    assert UsdGeom.GetStageUpAxis(layer_stage) == up
    assert UsdGeom.GetStageMetersPerUnit(layer_stage) == pytest.approx(mpu, rel=1e-12)
    # a copy of the source stage without its lights, the layer sublayered (as README says)
    composed = Sdf.Layer.CreateNew(str(tmp_path / "composed.usda"))
    composed.TransferContent(Sdf.Layer.FindOrOpen(str(tmp_path / "s.usda")))
    for name in ("Key", "Panel", "Spot"):
        del composed.GetPrimAtPath("/World/Rig").nameChildren[name]
    composed.subLayerPaths.append("lights.usda")
    composed.Save()
    a = {l.path.rsplit("/", 1)[-1]: l for l in read_scene(open_stage(tmp_path / "s.usda")).lights}
    b = {l.path.rsplit("_", 1)[-1]: l for l in read_scene(open_stage(tmp_path / "composed.usda")).lights}
    assert sorted(a) == sorted(b) == ["Key", "Panel", "Spot"]
    for k in a:
        np.testing.assert_allclose(b[k].to_world, a[k].to_world, atol=1e-5, err_msg=k)
        np.testing.assert_allclose(emitted_radiance(b[k]), emitted_radiance(a[k]), rtol=1e-5, err_msg=k)
        for size in ("width", "height") if a[k].treat_as_point else ("radius", "width", "height"):
            assert getattr(b[k], size) == pytest.approx(getattr(a[k], size), rel=1e-5), (k, size)
        assert b[k].treat_as_point == a[k].treat_as_point, k
    assert b["Key"].to_world[:3, 3] == pytest.approx(a["Key"].to_world[:3, 3], abs=1e-5)
    assert b["Spot"].cone_angle_deg == pytest.approx(30.0, rel=1e-5)
    assert b["Spot"].cone_softness == pytest.approx(0.3, abs=1e-4)
    # the Key light's world position in metres: the rig's offset plus its own (Y-up) or turned (Z-up)
    want = [1.2, 1.9, 0.8] if up == "Y" else [1.2, -0.6, 2.3]
    np.testing.assert_allclose(b["Key"].to_world[:3, 3], want, atol=1e-5)


def test_stage_units_of_a_blend_made_elsewhere_and_malformed_records():
    assert stage_units(None) == ("Y", 1.0)  # no recorded metadata: today's layer, Y-up metres
    assert stage_units({"upAxis": "Z", "metersPerUnit": 0.01}) == ("Z", 0.01)
    for bad in ({"upAxis": "X", "metersPerUnit": 1.0}, {"upAxis": "Y", "metersPerUnit": 0.0},
                {"upAxis": "Y", "metersPerUnit": math.inf}, {"upAxis": "Y"}, "Y"):
        with pytest.raises(UsdRelightError, match="usdrelight_stage"):
            stage_units(bad)


def test_the_standalone_script_records_the_stage_units_too(tmp_path):
    """``convert s.usda s.py`` then the user's Blender runs it: the .blend it saves carries the same record."""
    from usdrelight.converters.blender import blender_lights, run_blender, write_to_file

    write_to_file(_stage(tmp_path / "s.usda", "Z", 0.01), tmp_path / "s.py")
    run_blender(tmp_path / "s.py", str(tmp_path / "s.blend"))
    lights = blender_lights(tmp_path / "s.blend")
    assert len(lights) == 3 and lights.stage == {"metersPerUnit": 0.01, "upAxis": "Z", "timeCodesPerSecond": 24.0,
                                                 "lights": ["/World/Rig/Key", "/World/Rig/Panel", "/World/Rig/Spot"]}
