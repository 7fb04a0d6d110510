"""Cross-renderer agreement on UsdLux scenes in the style of OpenUSD's own UsdLux test scenes: every light kind
with shaping, exposure, normalize and colour temperature, a Y-up and a Z-up stage (in centimetres), lights
under scaled transforms, Cube/Sphere gprims and a floor, a MeshLightAPI panel, and one scene with every light.

For each stage: ``usdrelight convert s.usda s.xml`` rendered by Mitsuba and ``usdrelight convert s.usda s.blend``
rendered by Cycles must have the same mean (5%); the per-pixel relative RMSE is in the message (measured values
in the README, "UsdLux attributes not represented"). A UsdLux attribute one side cannot represent must be named
in that converter's warnings instead (last test).
"""
import math

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade

from usd_scenes import asymmetric_latlong, camera, diffuse_material, floor_quad, new_stage
from usdrelight.converters.blender import render_blend
from usdrelight.imageio import read_map, write_image
from usdrelight.intrinsics import Intrinsics
from usdrelight.mitsuba.runtime import load_mitsuba

W, H = 64, 48
SPP = 64


def _light(stage, cls, path, intensity, exposure=0.0, normalize=None, kelvin=None, color=None):
    light = cls.Define(stage, path)
    light.CreateIntensityAttr(intensity)
    if exposure:
        light.CreateExposureAttr(exposure)
    if normalize is not None:
        light.CreateNormalizeAttr(normalize)
    if kelvin:
        light.CreateEnableColorTemperatureAttr(True)
        light.CreateColorTemperatureAttr(kelvin)
    if color:
        light.CreateColorAttr(Gf.Vec3f(*color))
    return light


def _place(prim, translate=(0, 0, 0), rotate_xyz=None, scale=None):
    x = UsdGeom.Xformable(prim)
    x.AddTranslateOp().Set(Gf.Vec3d(*translate))
    if rotate_xyz is not None:
        x.AddRotateXYZOp().Set(Gf.Vec3f(*rotate_xyz))
    if scale is not None:
        x.AddScaleOp().Set(Gf.Vec3f(*scale))
    return prim


def base_stage(path, up="Y"):
    """Floor (albedo 0.5), a box and a ball (Cube/Sphere gprims), a camera looking down at them at 35 degrees.
    Authored Y-up in metres under /World; ``up='Z'`` turns /World by +90 degrees about X on a Z-up stage
    (:func:`in_centimetres` then rewrites it in centimetres)."""
    stage = new_stage(path)
    UsdGeom.SetStageUpAxis(stage, up)
    world = UsdGeom.Xformable(stage.GetPrimAtPath("/World"))
    if up == "Z":
        world.AddRotateXOp().Set(90.0)
    floor_quad(stage, half=6.0, material=diffuse_material(stage, "/World/Looks/Floor", (0.5, 0.5, 0.5)))
    box = _place(UsdGeom.Cube.Define(stage, "/World/Box").GetPrim(), (-0.5, 0.25, 0.2), (0, 30, 0))
    UsdGeom.Cube(box).CreateSizeAttr(0.5)
    ball = _place(UsdGeom.Sphere.Define(stage, "/World/Ball").GetPrim(), (0.6, 0.3, -0.3))
    UsdGeom.Sphere(ball).CreateRadiusAttr(0.3)
    for prim, albedo in ((box, (0.7, 0.3, 0.2)), (ball, (0.2, 0.5, 0.7))):
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(diffuse_material(stage, f"{prim.GetPath()}Mat", albedo))
    camera(stage, Intrinsics.from_fov_x(55.0, W, H), translate=(0, 2.2, 3.2), rotate_x_deg=-35.0)
    UsdGeom.Xform.Define(stage, "/World/Lights")
    return stage


def in_centimetres(stage):
    """Rewrite a stage authored in metres in plain centimetres: metersPerUnit 0.01 and every length x 100
    (translations, mesh points and extents, Cube size, Sphere radius, light radius/width/height, the camera's
    clipping range); scales, angles and light intensities as they are (the renderers work in metres)."""
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    lengths = ("points", "extent", "size", "radius", "inputs:radius", "inputs:width", "inputs:height",
               "clippingRange")
    for prim in stage.Traverse():
        for attr in prim.GetAttributes():
            name = attr.GetName()
            if (name in lengths or name.startswith("xformOp:translate")) and attr.HasAuthoredValue():
                v = attr.Get()
                attr.Set(type(v)([x * 100 for x in v]) if hasattr(v, "__len__") and not hasattr(v, "GetLength")
                         else v * 100)
    return stage


def rig(stage, scale=2.0):
    """An Xform /World/Lights/Rig scaled by ``scale``: lights under it are authored at 1/scale size."""
    prim = stage.GetPrimAtPath("/World/Lights/Rig")
    return prim if prim else _place(UsdGeom.Xform.Define(stage, "/World/Lights/Rig").GetPrim(), scale=(scale,) * 3)


def mesh_panel(stage, path, centre, half, intensity, normalize=False, facing_down=True):
    """A square Mesh at height centre[1] with MeshLightAPI, wound to face down (or up)."""
    cx, y, cz = centre
    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr([(cx - half, y, cz - half), (cx + half, y, cz - half), (cx + half, y, cz + half),
                        (cx - half, y, cz + half)])
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3] if facing_down else [0, 3, 2, 1])
    UsdLux.MeshLightAPI.Apply(m.GetPrim())
    api = UsdLux.LightAPI(m.GetPrim())
    api.CreateIntensityAttr(intensity)
    api.CreateNormalizeAttr(normalize)
    api.CreateColorAttr(Gf.Vec3f(1.0, 0.85, 0.7))
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(diffuse_material(stage, path + "Mat", (0.1, 0.1, 0.1)))
    return m


# ---- the scenes ------------------------------------------------------------------------------------------
def point(stage, k=1.0):
    l = _light(stage, UsdLux.SphereLight, "/World/Lights/Bulb", 6.0 * k, exposure=1.0, kelvin=3200)
    l.CreateTreatAsPointAttr(True)
    _place(l.GetPrim(), (0.3, 1.6, 0.8))


def spot(stage, k=1.0, softness=0.4):
    l = _light(stage, UsdLux.SphereLight, "/World/Lights/Spot", 30.0 * k, color=(1.0, 0.9, 0.8))
    l.CreateRadiusAttr(0.0)
    sh = UsdLux.ShapingAPI.Apply(l.GetPrim())
    sh.CreateShapingConeAngleAttr(28.0)
    sh.CreateShapingConeSoftnessAttr(softness)
    _place(l.GetPrim(), (-0.4, 2.2, 0.6), (-75, -10, 0))


def sphere(stage, k=1.0):
    rig(stage)
    l = _light(stage, UsdLux.SphereLight, "/World/Lights/Rig/Globe", 12.0 * k, normalize=True, kelvin=5000)
    l.CreateRadiusAttr(0.06)  # 0.12 m in the world
    _place(l.GetPrim(), (-0.4, 0.4, 0.5))  # (-0.8, 0.8, 1.0) in the world, in view


def disk(stage, k=1.0):
    rig(stage)
    l = _light(stage, UsdLux.DiskLight, "/World/Lights/Rig/Disk", 40.0, exposure=-1.0, color=(0.8, 0.9, 1.0))
    l.CreateRadiusAttr(0.15)
    _place(l.GetPrim(), (0.4, 0.9, -0.3), (-80, 0, 0), (1.5, 0.8, 1.0))  # an ellipse 0.9 x 0.48 m


def rect(stage, k=1.0):
    l = _light(stage, UsdLux.RectLight, "/World/Lights/Softbox", 6.0 * k, normalize=True, kelvin=8000)
    l.CreateWidthAttr(0.8)
    l.CreateHeightAttr(0.4)
    _place(l.GetPrim(), (1.0, 1.3, 1.2), (-70, 20, 0), (1.5, 1.0, 1.0))  # non-uniform scale: 1.2 x 0.4 m


def distant(stage, k=1.0):
    l = _light(stage, UsdLux.DistantLight, "/World/Lights/Sun", 2.5, kelvin=5800)
    l.CreateAngleAttr(0.53)
    _place(l.GetPrim(), rotate_xyz=(-50, 35, 0))


def dome(stage, k=1.0, tex=None):
    l = _light(stage, UsdLux.DomeLight, "/World/Lights/Sky", 0.6, exposure=0.5)
    if tex is not None:
        l.CreateTextureFileAttr(tex)
        l.CreateTextureFormatAttr("latlong")
    _place(l.GetPrim(), rotate_xyz=(0, 40, 0))


def mesh(stage, k=1.0):
    mesh_panel(stage, "/World/Lights/Panel", (0.0, 1.4, 0.3), 0.35, 1.5 * k, normalize=True)


def cylinder(stage, k=1.0):
    rig(stage)  # a 1 m tube of radius 6 cm in the world, turned 30 degrees, over the box and the ball
    l = _light(stage, UsdLux.CylinderLight, "/World/Lights/Rig/Tube", 3.0 * k, normalize=True, color=(1.0, 0.9, 0.8))
    l.CreateRadiusAttr(0.03)
    l.CreateLengthAttr(0.5)
    _place(l.GetPrim(), (0.1, 0.45, 0.0), (0, 30, 0))


SCENES = {"point": point, "spot": spot, "sphere": sphere, "disk": disk, "rect": rect, "distant": distant,
          "dome": dome, "mesh": mesh, "cylinder": cylinder}


def render_both(cli, usda):
    """(Mitsuba image of the XML, Cycles image of the .blend, XML warnings, .blend warnings)."""
    xml, blend = usda.with_suffix(".xml"), usda.with_suffix(".blend")
    wx = cli.json("convert", usda, xml)["write_warnings"]
    wb = cli.json("convert", usda, blend)["write_warnings"]
    mi = load_mitsuba()
    m = np.array(mi.render(mi.load_file(str(xml)), spp=SPP))[..., :3]
    c = read_map(render_blend(blend, usda.with_suffix(".exr"), spp=SPP), 3)
    return m, c, wx, wb


def assert_agree(m, c, what):
    rel_rmse = float(np.sqrt(np.mean((c - m) ** 2)) / m.mean())
    cap = 2.0 * m.mean()  # a light seen directly: a few bright pixels whose edges are noise
    clipped = float(np.sqrt(np.mean((np.minimum(c, cap) - np.minimum(m, cap)) ** 2)) / np.minimum(m, cap).mean())
    msg = (f"{what}: Cycles mean {c.mean():.4f} vs Mitsuba {m.mean():.4f} ({c.mean() / m.mean() - 1:+.1%}), "
           f"per-pixel relative RMSE {rel_rmse:.3f} ({clipped:.3f} below twice the mean)")
    print(msg)
    assert m.mean() > 0.02, msg  # the scene is lit
    assert c.mean() == pytest.approx(m.mean(), rel=0.05), msg
    assert clipped < 0.35, msg  # the same picture (64 spp each): a mirrored or misplaced light fails this


@pytest.mark.parametrize("kind", list(SCENES))
def test_each_light_alone_agrees(cli, tmp_path, kind):
    stage = base_stage(tmp_path / f"{kind}.usda")
    if kind == "dome":
        write_image(tmp_path / "sky.exr", asymmetric_latlong(32, 64).astype(np.float32), "float")
        dome(stage, tex="./sky.exr")
    else:
        SCENES[kind](stage)
    stage.GetRootLayer().Save()
    m, c, wx, wb = render_both(cli, tmp_path / f"{kind}.usda")
    assert not [w for w in wb if "not converted" in w or "ignored" in w], wb
    assert_agree(m, c, kind)


def test_every_light_on_a_z_up_stage_in_centimetres(cli, tmp_path):
    """All kinds at once (untextured dome), on a Z-up stage in plain centimetres (metersPerUnit 0.01, every
    length authored x 100): the same intensities as in metres, since both converters work in metres."""
    stage = base_stage(tmp_path / "all.usda", up="Z")
    for kind, fn in SCENES.items():
        fn(stage)
    # light shapes are geometry in Mitsuba (they shadow the sun and the sky), not in Cycles: the rect and the
    # disk go behind the camera, where neither they nor their shadows are seen (README, not represented)
    for path, t, r in (("/World/Lights/Softbox", (0.0, 2.7, 4.3), (-35, 0, 0)),
                       ("/World/Lights/Rig/Disk", (0.6, 1.3, 2.2), (-35, 0, 0))):
        stage.GetPrimAtPath(path).GetAttribute("xformOp:translate").Set(Gf.Vec3d(*t))
        stage.GetPrimAtPath(path).GetAttribute("xformOp:rotateXYZ").Set(Gf.Vec3f(*r))
    in_centimetres(stage)
    stage.GetRootLayer().Save()
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.validate import open_stage

    rec = read_scene(open_stage(tmp_path / "all.usda"))
    assert rec.up_axis == "Z" and rec.meters_per_unit == pytest.approx(0.01) and len(rec.lights) == 9
    np.testing.assert_allclose(rec.camera.to_world[:3, 3], [0, -3.2, 2.2], atol=1e-9)  # metres, Z-up
    m, c, _, _ = render_both(cli, tmp_path / "all.usda")
    assert_agree(m, c, "all lights, Z-up, cm")


def test_mesh_light_emits_its_radiance_on_the_front_side_only(cli, tmp_path):
    """A camera under a MeshLightAPI panel sees L = intensity * color in Cycles as in Mitsuba when the panel
    faces it, and nothing (its black-ish BSDF, no other light) when it faces away."""
    for facing_down in (True, False):
        stage = new_stage(tmp_path / f"panel{facing_down}.usda")
        mesh_panel(stage, "/World/Panel", (0.0, 1.0, 0.0), 0.5, 3.0, facing_down=facing_down)
        camera(stage, Intrinsics.from_fov_x(20.0, 8, 6), rotate_x_deg=90.0)
        stage.GetRootLayer().Save()
        m, c, _, _ = render_both(cli, tmp_path / f"panel{facing_down}.usda")
        expected = np.array([3.0, 2.55, 2.1]) if facing_down else np.zeros(3)
        np.testing.assert_allclose(m.reshape(-1, 3).mean(0), expected, atol=1e-3)
        np.testing.assert_allclose(c.reshape(-1, 3).mean(0), expected, atol=1e-3)


def test_unrepresented_usdlux_attributes_are_warned(cli, tmp_path):
    """Each UsdLux control a target cannot represent is named once (one line per kind) by that converter."""
    stage = base_stage(tmp_path / "odd.usda")
    spot(stage, softness=0.9)  # Cycles' softest spot_blend still sends more light
    s = UsdLux.ShapingAPI(stage.GetPrimAtPath("/World/Lights/Spot"))
    s.CreateShapingFocusAttr(2.0)
    s.CreateShapingIesFileAttr(Sdf.AssetPath("./lamp.ies"))
    rect(stage)
    r = stage.GetPrimAtPath("/World/Lights/Softbox")
    UsdLux.ShapingAPI.Apply(r).CreateShapingConeAngleAttr(40.0)  # shaping on an area light
    UsdLux.ShadowAPI.Apply(r).CreateShadowEnableAttr(False)
    UsdLux.LightAPI(r).CreateDiffuseAttr(0.5)
    UsdLux.LightAPI(r).GetLightLinkCollectionAPI().GetExcludesRel().AddTarget("/World/Box")
    cyl = _light(stage, UsdLux.CylinderLight, "/World/Lights/Tube", 5.0)
    _place(cyl.GetPrim(), (0, 1.5, 0))
    sun = _light(stage, UsdLux.DistantLight, "/World/Lights/Sun", 1.0)
    sun.CreateAngleAttr(2.0)
    stage.GetRootLayer().Save()
    wx = cli.json("convert", tmp_path / "odd.usda", tmp_path / "odd.xml")["write_warnings"]
    wb = cli.json("convert", tmp_path / "odd.usda", tmp_path / "odd.blend")["write_warnings"]
    both = ("ShapingAPI focus", "ShapingAPI IES", "ShadowAPI", "light/shadow linking", "diffuse/specular multipliers")
    assert not any("CylinderLight" in k for k in wx), wx  # a Mitsuba cylinder emitter now
    assert [v for k, v in wb.items() if "CylinderLight as an emissive mesh" in k] == [1], wb
    for key in both:
        for name, w in (("xml", wx), ("blend", wb)):
            assert [v for k, v in w.items() if key in k] == [1], (name, key, w)
    assert any("ShapingAPI on a disk, rect" in k for k in wx), wx
    assert any("ShapingAPI on a disk, rect" in k for k in wb), wb
    assert any("DistantLight angle" in k for k in wx), wx
    assert any("coneSoftness above" in k for k in wb), wb
    assert any("coneSoftness above 0.8" in k for k in wx), wx


def test_spot_softness_maps_to_the_same_cone_power():
    """Cycles' spot_blend chosen for coneSoftness s sends the power UsdLux's smoothstep-in-angle fade sends."""
    from usdrelight.converters.blender_units import _cone_power, _smoothstep, cone_softness, spot_blend

    tc = math.radians(28.0)
    c = math.cos(tc)
    for s in (0.1, 0.4, 0.6):
        b = spot_blend(tc, s)
        start = tc * (1 - s)
        usd = _cone_power(tc, lambda th: 1 - _smoothstep((th - start) / (tc - start)))
        cyc = _cone_power(tc, lambda th: _smoothstep((np.cos(th) - c) / ((1 - c) * b)))
        assert cyc == pytest.approx(usd, rel=1e-4)
        assert cone_softness(tc, b) == pytest.approx(s, abs=1e-6)
