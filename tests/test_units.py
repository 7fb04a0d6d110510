"""Stage units: a stage in centimetres (metersPerUnit 0.01) renders as the same stage in metres.

``read_scene`` applies metersPerUnit once (a root scale on every world matrix), so every renderer and converter
works in metres: a treatAsPoint light's intensity [W/sr] lights a floor 100 cm below it with I / 1 m^2, and
``normalize`` divides by the emitting area in m^2 (README "Light and camera units"). The scene: an albedo-0.5
floor, a light 1 m above it, a camera 0.5 m above the floor looking straight down (under the light, outside
it). Closed forms of the floor's radiance under the light, at the image centre:

* point (treatAsPoint SphereLight, intensity I):   0.5 I / pi            (E = I / 1 m^2)
* sphere (radius 0.1 m, normalize, I):            0.5 I / (4 pi)        (E = pi L r^2 / d^2, L = I / (4 pi r^2))
* rect (0.4 m x 0.4 m, normalize, I):             0.5 / pi * E          (E of a Lambertian rectangle on its axis)

Each is checked through ``usdrelight render``, through convert -> Mitsuba XML -> Mitsuba, and through
convert -> .blend -> Cycles, on a Z-up centimetre stage and a Y-up metre stage (and the point light on a Z-up
metre stage, and a Y-up centimetre stage through ``usdrelight render``).
"""
import math

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux, UsdShade

from usd_scenes import camera, diffuse_material
from usdrelight.converters.blender import render_blend
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import read_map
from usdrelight.intrinsics import Intrinsics
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.read import read_scene

W = H = 32
FOV = 20.0
ALBEDO = 0.5
I_POINT, I_SPHERE, I_RECT = 2.0, 8.0, 3.0
RECT = 0.4  # metres, each side
SPHERE_R = 0.1  # metres


def rect_irradiance(L: float, a: float, b: float, d: float) -> float:
    """Irradiance on the axis of a Lambertian rectangle of radiance L, half-sides a, b, at distance d (four
    corner rectangles of the classic form factor)."""
    ra, rb = math.hypot(a, d), math.hypot(b, d)
    return 2.0 * L * (a / ra * math.atan(b / ra) + b / rb * math.atan(a / rb))


EXPECTED = {"point": ALBEDO * I_POINT / math.pi,
            "sphere": ALBEDO * I_SPHERE / (4.0 * math.pi),
            "rect": ALBEDO / math.pi * rect_irradiance(I_RECT / RECT ** 2, RECT / 2, RECT / 2, 1.0)}


def unit_stage(path, kind: str, cm: bool, up: str = "Z"):
    """The floor scene of ``kind`` authored in centimetres (values x 100, metersPerUnit 0.01) or metres."""
    u = 100.0 if cm else 1.0  # stage units per metre

    def at(height_m):  # a point ``height_m`` metres above the floor's centre, in stage units
        return (0.0, height_m * u, 0.0) if up == "Y" else (0.0, 0.0, height_m * u)

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0 / u)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/World").GetPrim())
    h = 5.0 * u
    floor = UsdGeom.Mesh.Define(stage, "/World/Floor")
    floor.CreatePointsAttr([(-h, 0, h), (h, 0, h), (h, 0, -h), (-h, 0, -h)] if up == "Y" else
                           [(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)])  # counter-clockwise from above
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdShade.MaterialBindingAPI.Apply(floor.GetPrim()).Bind(
        diffuse_material(stage, "/World/Looks/Floor", (ALBEDO,) * 3))
    camera(stage, Intrinsics.from_fov_x(FOV, W, H), translate=at(0.5), rotate_x_deg=-90.0 if up == "Y" else 0.0)
    if kind == "rect":
        light = UsdLux.RectLight.Define(stage, "/World/Light")
        light.CreateWidthAttr(RECT * u)
        light.CreateHeightAttr(RECT * u)
        light.CreateIntensityAttr(I_RECT)
    else:
        light = UsdLux.SphereLight.Define(stage, "/World/Light")
        if kind == "point":
            light.CreateTreatAsPointAttr(True)
            light.CreateIntensityAttr(I_POINT)
        else:
            light.CreateRadiusAttr(SPHERE_R * u)
            light.CreateIntensityAttr(I_SPHERE)
    if kind != "point":
        light.CreateNormalizeAttr(True)
    x = UsdGeom.Xformable(light.GetPrim())
    x.AddTranslateOp().Set(Gf.Vec3d(*at(1.0)))
    if up == "Y":
        x.AddRotateXOp().Set(-90.0)  # UsdLux lights emit along -Z: down
    stage.GetRootLayer().Save()
    return path


def centre(img) -> float:
    """Mean of the central 4 x 4 pixels (within 1.3 degrees of the axis: the closed forms hold to 0.03%)."""
    return float(img[H // 2 - 2:H // 2 + 2, W // 2 - 2:W // 2 + 2, :3].mean())


def _mitsuba_cli(cli, usda, spp):
    out = usda.parent / (usda.stem + "_renders")
    cli.json("render", usda, "-o", out, "--spp", spp)
    return read_map(out / "renders" / "color.exr", 3)


def _mitsuba_xml(cli, usda, spp):
    xml = usda.with_suffix(".xml")
    cli.json("convert", usda, xml)
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(xml)), spp=spp))[..., :3]


def _cycles(cli, usda, spp):
    blend = usda.with_suffix(".blend")
    cli.json("convert", usda, blend)
    return read_map(render_blend(blend, usda.with_suffix(".cycles.exr"), spp=spp), 3)


@pytest.mark.parametrize("kind", ["point", "sphere", "rect"])
def test_centimetre_stage_renders_as_metres_in_mitsuba(cli, tmp_path, kind):
    """``usdrelight render`` and convert -> XML -> Mitsuba: cm (Z-up) = m (Y-up) = the closed form."""
    spp = 16 if kind == "point" else 64
    cm = unit_stage(tmp_path / "cm.usda", kind, cm=True)
    m = unit_stage(tmp_path / "m.usda", kind, cm=False, up="Y")
    msgs = []
    for how in (_mitsuba_cli, _mitsuba_xml):
        a, b = how(cli, cm, spp), how(cli, m, spp)
        msg = (f"{kind} via {how.__name__}: centre cm {centre(a):.5f}, m {centre(b):.5f}, closed form "
               f"{EXPECTED[kind]:.5f}; image means {a.mean():.5f} / {b.mean():.5f}")
        msgs.append(msg)
        assert centre(a) == pytest.approx(EXPECTED[kind], rel=0.02), msg
        assert centre(b) == pytest.approx(EXPECTED[kind], rel=0.02), msg
        assert a.mean() == pytest.approx(b.mean(), rel=0.01), msg
    print("\n".join(msgs))  # after the last CLI call (the cli fixture reads what was printed before it)


@pytest.mark.parametrize("kind", ["point", "sphere", "rect"])
def test_centimetre_stage_renders_as_metres_in_cycles(cli, tmp_path, kind):
    """convert -> .blend -> Cycles: cm (Z-up) = m (Y-up) within noise, both at the closed form."""
    cm = unit_stage(tmp_path / "cm.usda", kind, cm=True)
    m = unit_stage(tmp_path / "m.usda", kind, cm=False, up="Y")
    a, b = _cycles(cli, cm, 16), _cycles(cli, m, 16)
    msg = (f"{kind} via Cycles: centre cm {centre(a):.5f}, m {centre(b):.5f}, closed form {EXPECTED[kind]:.5f}; "
           f"image means {a.mean():.5f} / {b.mean():.5f}")
    print(msg)
    assert centre(a) == pytest.approx(EXPECTED[kind], rel=0.02), msg
    assert centre(b) == pytest.approx(EXPECTED[kind], rel=0.02), msg
    assert a.mean() == pytest.approx(b.mean(), rel=0.01), msg


def test_up_axis_and_units_do_not_change_the_point_light(cli, tmp_path):
    """The point light's closed form 0.5 I / pi on all four combinations of Y/Z-up and cm/m."""
    for up in ("Y", "Z"):
        for cm in (False, True):
            img = _mitsuba_cli(cli, unit_stage(tmp_path / f"{up}{cm}.usda", "point", cm=cm, up=up), 4)
            assert centre(img) == pytest.approx(EXPECTED["point"], rel=0.02), (up, cm, centre(img))


def test_records_are_in_metres(tmp_path):
    """read_scene hands over metres: camera position and clipping range, mesh points, light frames and areas;
    a metre stage's record is untouched (its matrices as USD computes them)."""
    cm = read_scene(Usd.Stage.Open(str(unit_stage(tmp_path / "cm.usda", "rect", cm=True))))
    m = read_scene(Usd.Stage.Open(str(unit_stage(tmp_path / "m.usda", "rect", cm=False))))
    assert cm.meters_per_unit == pytest.approx(0.01) and m.meters_per_unit == 1.0
    np.testing.assert_allclose(cm.camera.to_world[:3, 3], [0, 0, 0.5], atol=1e-12)
    assert (cm.camera.near, cm.camera.far) == pytest.approx((m.camera.near / 100, m.camera.far / 100))
    assert cm.camera.intrinsics == m.camera.intrinsics
    np.testing.assert_allclose(cm.meshes[0].points, m.meshes[0].points, atol=1e-12)
    from usdrelight.stage.lux import world_area

    assert world_area(cm.lights[0]) == pytest.approx(RECT ** 2) == world_area(m.lights[0])
    np.testing.assert_array_equal(m.lights[0].to_world[:3, 3], [0, 0, 1.0])


def test_bad_meters_per_unit_is_one_clear_error(tmp_path):
    stage = Usd.Stage.Open(str(unit_stage(tmp_path / "s.usda", "point", cm=False)))
    UsdGeom.SetStageMetersPerUnit(stage, -1.0)
    with pytest.raises(UsdRelightError, match="metersPerUnit must be finite and positive"):
        read_scene(stage)


def test_serve_refuses_a_stage_not_in_metres(tmp_path):
    """The web app writes edited light positions back as they are: a stage in other units is refused."""
    from usdrelight.serve.live import check_servable

    stage = Usd.Stage.Open(str(unit_stage(tmp_path / "s.usda", "point", cm=True)))
    with pytest.raises(UsdRelightError, match="metersPerUnit 0.01"):
        check_servable(stage, tmp_path / "s.usda")
    check_servable(Usd.Stage.Open(str(unit_stage(tmp_path / "m.usda", "point", cm=False))), tmp_path / "m.usda")


def test_fit_writes_its_lights_in_stage_units(tmp_path):
    """The fit works in metres (read_scene) and writes the fitted-lights layer in the stage's units: a built
    stage rewritten in centimetres finds the light that lit it at 100 x its position in metres."""
    from test_fit import _render_target, _room_depth, _synthetic_stage
    from usdrelight.fit.run import FitSettings, fit
    from usdrelight.imageio import write_image
    from usdrelight.stage.records import PointLightValue

    stage = _synthetic_stage(tmp_path, _room_depth())
    true = np.array([0.3, 0.2, -3.0])
    img, _ = _render_target(stage, [PointLightValue(true, np.array([6.0, 5.0, 4.0]))])
    write_image(stage.parent / "estimates" / "diffuse.exr", img, "float")
    _built_stage_in_centimetres(stage)
    fit(stage, FitSettings(lights=9, iterations=25, verify_spp=0))
    s = Usd.Stage.Open(str(stage))
    assert UsdGeom.GetStageMetersPerUnit(s) == pytest.approx(0.01)
    lights = [p for p in s.Traverse() if p.GetTypeName() == "SphereLight"]
    strongest = max(lights, key=lambda p: p.GetAttribute("inputs:intensity").Get())
    pos = np.array(strongest.GetAttribute("xformOp:translate").Get())
    assert np.linalg.norm(pos - 100 * true) < 30.0, pos  # centimetres


def _built_stage_in_centimetres(path):
    """metersPerUnit 0.01 and the mesh and camera clipping range x 100, authored in scene.usda (the stage is
    let go before the fit opens it again: USD's layer cache would hand back this version's layers)."""
    s = Usd.Stage.Open(str(path))
    UsdGeom.SetStageMetersPerUnit(s, 0.01)
    for prim in s.Traverse():
        for name in ("points", "extent", "clippingRange"):
            attr = prim.GetAttribute(name)
            if attr and attr.HasAuthoredValue():
                v = attr.Get()
                attr.Set(v * 100 if name == "clippingRange" else type(v)([x * 100 for x in v]))
    s.GetRootLayer().Save()
