"""Lights animated by USD splines (animation curves, usd-core 25.05+) instead of time samples: where they change,
what a single frame reads, Blender's keys at every frame of a curve, the web app keeping them as written."""
from __future__ import annotations

import numpy as np
import pytest

from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.read import read_lights
from usdrelight.stage.records import FitProvenance, PointLightValue
from usdrelight.stage.timing import frame_time, light_time_codes, spline_motion, value_times
from usdrelight.stage.validate import open_stage

from conftest import build_procedural


def _spline(type_name: str, knots, interp="linear", pre="held", post="held"):
    """A Ts.Spline of (time, value) knots, every segment ``interp`` (linear, held or curve: Bezier with
    auto-ease tangents), extrapolated ``pre`` / ``post`` (held, linear, loop)."""
    from pxr import Ts

    modes = {"held": Ts.ExtrapHeld, "linear": Ts.ExtrapLinear, "loop": Ts.ExtrapLoopRepeat}
    spline = Ts.Spline(type_name)
    spline.SetCurveType(Ts.CurveTypeBezier)
    for t, v in knots:
        k = Ts.Knot(type_name)
        k.SetTime(t)
        k.SetValue(v)
        k.SetNextInterpolation({"linear": Ts.InterpLinear, "held": Ts.InterpHeld, "curve": Ts.InterpCurve}[interp])
        if interp == "curve":  # flat tangents a third of the way to the neighbours: an ease in and out
            k.SetPreTanWidth(1.0)
            k.SetPostTanWidth(1.0)
            k.SetPreTanSlope(0.0)
            k.SetPostTanSlope(0.0)
        spline.SetKnot(k)
    spline.SetPreExtrapolation(Ts.Extrapolation(modes[pre]))
    spline.SetPostExtrapolation(Ts.Extrapolation(modes[post]))
    return spline


def _light_stage(range_=None):
    from pxr import Usd, UsdLux

    stage = Usd.Stage.CreateInMemory()
    if range_:
        stage.SetStartTimeCode(range_[0])
        stage.SetEndTimeCode(range_[1])
    light = UsdLux.SphereLight.Define(stage, "/L")
    light.CreateTreatAsPointAttr(True)
    return stage, light


def test_where_a_spline_changes():
    stage, light = _light_stage()
    attr = light.CreateIntensityAttr(7.0)
    attr.SetSpline(_spline("float", [(1, 1.0), (4, 4.0), (10, 2.0)]))
    assert value_times(attr) == [1.0, 4.0, 10.0] and spline_motion(attr) == (False, set())
    assert light_time_codes(stage) == [1.0, 4.0, 10.0]
    attr.SetSpline(_spline("float", [(1, 1.0), (4, 4.0), (10, 2.0)], interp="held"))
    assert spline_motion(attr) == (False, {4.0, 10.0})  # the value steps at the next knot
    attr.SetSpline(_spline("float", [(1, 1.0), (4, 4.0)], interp="curve"))
    assert spline_motion(attr)[0] is True
    assert attr.Get(2.0) == pytest.approx(1.0 + 3.0 * 7 / 27, abs=1e-5)  # flat tangents: not linear (2.0)
    attr.SetSpline(_spline("float", [(1, 1.0), (4, 4.0)], post="linear"))
    assert spline_motion(attr)[0] is True and value_times(attr) == [1.0, 4.0]  # no range: its knots
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(20)
    assert value_times(attr) == [1.0, 4.0, 20.0]  # it keeps changing to the end of the range
    assert value_times(light.CreateExposureAttr(0.0)) == [] and spline_motion(light.GetExposureAttr()) is None


def test_a_frame_without_a_range_reads_the_first_knot_not_minus_infinity():
    """At Usd.TimeCode.EarliestTime a spline extrapolated linearly before its first knot is -inf (a light at
    -1.8e308 m): a stage without an authored range reads every attribute at its first sample or knot."""
    from pxr import UsdGeom

    stage, light = _light_stage()
    light.CreateIntensityAttr().SetSpline(_spline("float", [(3, 2.0), (9, 8.0)], pre="linear"))
    UsdGeom.Xformable(light).AddTranslateXOp().GetAttr().SetSpline(
        _spline("double", [(5, 1.0), (9, 5.0)], pre="linear"))
    t = frame_time(stage)
    assert t.GetValue() == 3.0
    (rec,) = read_lights(stage, t)
    # translateX at time 3, extrapolated back from its knot at 5: -1 cm (no metersPerUnit: centimetres)
    assert rec.to_world[0, 3] == pytest.approx(-0.01)
    assert np.all(np.isfinite(rec.radiance)) and rec.radiance.max() > 0


@pytest.fixture(scope="module")
def spline_stage(tmp_path_factory):
    """The procedural room (stride 2), a fitted point light, and a user point light whose translateX (metres)
    eases along a Bezier spline from -1.2 to 1.2 over time codes 1 to 7 and whose intensity rises on a linear
    one: what an animation package's USD export of curves looks like."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    d = tmp_path_factory.mktemp("splines")
    scene = build_procedural(d / "st", stride=2)
    write_fitted_lights(d / "st", [PointLightValue(np.array([-0.5, 1.0, -2.0]), np.array([3.0, 3.0, 3.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    layer = Sdf.Layer.FindOrOpen(str(d / "st" / USER_LIGHTS))
    stage = Usd.Stage.Open(layer)
    stage.OverridePrim("/Scene")
    UsdGeom.Scope.Define(stage, "/Scene/Lights/User")
    light = UsdLux.SphereLight.Define(stage, "/Scene/Lights/User/Eased")
    light.CreateTreatAsPointAttr(True)
    light.CreateRadiusAttr(0.0)
    light.CreateNormalizeAttr(False)
    xf = UsdGeom.Xformable(light)
    xf.AddTranslateOp().Set(Gf.Vec3d(0.0, -0.6, -2.4))
    xf.AddTranslateXOp().GetAttr().SetSpline(_spline("double", [(1, -1.2), (7, 1.2)], interp="curve"))
    light.CreateIntensityAttr(1.0).SetSpline(_spline("float", [(1, 2.0), (7, 5.0)]))
    layer.GetPrimAtPath("/Scene").specifier = Sdf.SpecifierOver
    layer.Save()
    return scene


def _eased_x(t: float) -> float:
    from pxr import Usd

    stage = open_stage(_eased_x.scene)
    return stage.GetAttributeAtPath("/Scene/Lights/User/Eased.xformOp:translateX").Get(Usd.TimeCode(t))


def test_blender_keys_a_curve_at_every_frame(spline_stage, tmp_path):
    """USD -> .blend: the eased light is keyed at every whole frame of its curve, each key where USD evaluates
    the spline (without spline support: no keys at all, the light standing at its default value)."""
    from usdrelight.converters.blender import blender_lights
    from usdrelight.converters.blender_units import blender_light_to_usd
    from usdrelight.converters.convert import convert

    convert(spline_stage, tmp_path / "scene.blend", spp=1)
    lights = blender_lights(tmp_path / "scene.blend")
    eased = next(b for b in lights if b.get("usd_path") == "/Scene/Lights/User/Eased")
    assert [f for f, _ in eased["keys"]] == [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    _eased_x.scene = spline_stage
    xs = [_eased_x(f) for f, _ in eased["keys"]]
    assert abs(xs[1] - (-1.2 + 2.4 / 6)) > 0.1  # the curve is not linear: keys at the knots alone would miss it
    for (f, key), x in zip(eased["keys"], xs):
        u = blender_light_to_usd(key, "Y", 1.0)
        np.testing.assert_allclose(np.asarray(u["matrix"])[:3, 3], [x, -0.6, -2.4], atol=1e-5)
        assert u["intensity"] == pytest.approx(2.0 + 0.5 * (f - 1), rel=1e-5)
    assert lights.animation["frame_start"] == 1 and lights.animation["frame_end"] == 7


def test_relight_follows_the_curve_and_the_web_app_keeps_it(spline_stage, tmp_path, cli):
    """relight --frames renders the light where the spline puts it (the pool's centroid moves as the eased x);
    the web app lists the light as one it does not edit and its Save writes the spline back unchanged."""
    from pxr import Sdf

    from usdrelight.serve.files import read_user_states
    from usdrelight.serve.saving import write_user_layer

    res = cli.json("relight", spline_stage, "--frames", "1:7:3", "--mode", "render", "--max-side", "64",
                   "-o", tmp_path / "frames")
    assert [f["time"] for f in res["frames"]] == [1, 4, 7]
    stage = open_stage(spline_stage)
    for f in res["frames"]:
        (eased,) = [l for l in read_lights(stage, f["time"]) if l.path.endswith("Eased")]
        _eased_x.scene = spline_stage
        assert eased.to_world[0, 3] == pytest.approx(_eased_x(f["time"]))
    assert light_time_codes(stage) == [1.0, 7.0]
    states, others = read_user_states(stage, {})
    assert others == ["/Scene/Lights/User/Eased"] and states == []
    before = Sdf.Layer.FindOrOpen(str(spline_stage.parent / USER_LIGHTS)).ExportToString()
    write_user_layer(spline_stage.parent, [], managed=())
    after = Sdf.Layer.FindOrOpen(str(spline_stage.parent / USER_LIGHTS))
    after.Reload()
    assert after.GetAttributeAtPath("/Scene/Lights/User/Eased.inputs:intensity").HasSpline()
    assert "translateX.spline" in after.ExportToString() and after.ExportToString().count(".spline") == \
        before.count(".spline") == 2


def test_a_zoom_on_a_spline_is_keyed_where_it_curves():
    """A camera's focal length on an eased spline: Blender's lens keys at every whole frame of the curve, at
    the knots alone for a linear one."""
    from pxr import Usd, UsdGeom

    from usdrelight.converters.blender_animation import attribute_frames

    stage = Usd.Stage.CreateInMemory()
    cam = UsdGeom.Camera.Define(stage, "/Cam")
    lens = ("focalLength", "horizontalAperture")
    cam.CreateFocalLengthAttr().SetSpline(_spline("float", [(1, 35.0), (5, 50.0)], interp="curve"))
    assert attribute_frames(cam.GetPrim(), lens) == [1.0, 2.0, 3.0, 4.0, 5.0]
    cam.GetFocalLengthAttr().SetSpline(_spline("float", [(1, 35.0), (5, 50.0)]))
    assert attribute_frames(cam.GetPrim(), lens) == [1.0, 5.0]


def test_a_blocked_value_and_a_one_knot_spline(tmp_path):
    """A spline's value-block segment (and a ValueBlock time sample) reads as no opinion, the schema's fallback
    (intensity 1), not a TypeError from float(None); a spline of one knot is a constant, not an animation."""
    from pxr import Sdf, Ts

    stage, light = _light_stage(range_=(0, 10))
    attr = light.CreateIntensityAttr()
    spline = _spline("float", [(1, 4.0), (5, 6.0), (8, 2.0)])
    knot = spline.GetKnots()[5.0]
    knot.SetNextInterpolation(Ts.InterpValueBlock)
    spline.SetKnot(knot)
    attr.SetSpline(spline)
    assert attr.Get(6.0) is None
    (rec,) = read_lights(stage, 6.0)
    assert rec.radiance[0] == pytest.approx(1.0)
    (rec,) = read_lights(stage, 3.0)
    assert rec.radiance[0] == pytest.approx(5.0)
    exposure = light.CreateExposureAttr()
    exposure.Set(1.0, 1.0)
    exposure.Set(Sdf.ValueBlock(), 4.0)
    (rec,) = read_lights(stage, 4.0)
    assert rec.radiance[0] == pytest.approx(5.5)  # the spline's 5.5 x 2^0 (the blocked exposure's fallback)
    one = light.CreateRadiusAttr()
    one.SetSpline(_spline("float", [(3, 0.2)], pre="linear", post="linear"))
    from usdrelight.stage.timing import is_time_varying

    assert value_times(one) == [3.0] and not is_time_varying(one)
