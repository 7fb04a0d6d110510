"""Mesh area emitters <-> UsdLux MeshLightAPI: a Mitsuba shape (obj/ply/serialized/cube) with a nested
``area`` emitter becomes one Mesh carrying MeshLightAPI (radiance as intensity * color, normalize off, its
material kept), read back as a light of kind ``mesh`` and written back as the same shape with its emitter.

Closed forms, rendered by Mitsuba from the original XML and from XML -> USD -> XML: a camera looking at the
emitter sees its radiance L; a diffuse floor of albedo rho under a 2a x 2a emitter at height h has radiance
rho * L * F at the point below its centre (F: the point-to-rectangle view factor)."""
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from usd_scenes import camera, diffuse_material, floor_quad, new_stage
from usdrelight.imageio import read_photo
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.lux import emitted_radiance
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import errors_only, open_stage, validate_stage

L = (2.0, 3.0, 4.0)
ALBEDO = 0.5
QUAD_OBJ = """v -1 1 -1
v 1 1 -1
v 1 1 1
v -1 1 1
f 1 2 3
f 1 3 4
"""  # y = 1, 2 x 2, wound to face down (-y)


def _view_factor(a: float, h: float) -> float:
    """Point-to-parallel-square view factor: a square of side 2a centred at height h above the point."""
    x = a / h
    s = math.sqrt(1 + x * x)
    return 4 * (2 * x / s * math.atan(x / s)) / (2 * math.pi)


def _scene(look: str, emitter_shape: str) -> str:
    """Camera halfway up looking down at the floor (look='floor') or up at the emitter (look='up')."""
    target = "0, 0, 0" if look == "floor" else "0, 1, 0"
    return f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <sensor type="perspective"><float name="fov" value="8"/>
        <transform name="to_world"><lookat origin="0, 0.5, 0" target="{target}" up="0, 0, 1"/></transform>
        <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="12"/><rfilter type="box"/></film>
        <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
    </sensor>
    {emitter_shape}
    <shape type="rectangle">
        <transform name="to_world"><scale value="20"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="{ALBEDO}"/></bsdf>
    </shape>
</scene>
"""


EMITTER_OBJ = f"""<shape type="obj" id="panel"><string name="filename" value="quad.obj"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>
        <emitter type="area"><rgb name="radiance" value="{', '.join(map(str, L))}"/></emitter>
    </shape>"""


def _render(path, spp=64):
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=spp))[..., :3]


def _round_trip(cli, tmp_path, text, name="scene"):
    src = tmp_path / f"{name}.xml"
    src.write_text(text)
    (tmp_path / "quad.obj").write_text(QUAD_OBJ)
    rc, _, err = cli("convert", src, tmp_path / "usd" / f"{name}.usda")
    assert rc == 0, err
    assert "emission dropped" not in err
    rc, _, err = cli("convert", tmp_path / "usd" / f"{name}.usda", tmp_path / "back" / f"{name}.xml")
    assert rc == 0, err
    return src, open_stage(tmp_path / "usd" / f"{name}.usda"), tmp_path / "back" / f"{name}.xml"


def test_obj_emitter_becomes_one_mesh_light_and_renders_alike(cli, tmp_path):
    src, stage, back = _round_trip(cli, tmp_path, _scene("floor", EMITTER_OBJ))
    assert errors_only(validate_stage(stage)) == []
    # USD: the panel is one Mesh with MeshLightAPI (radiance L, not normalized), no separate light prim
    prim = stage.GetPrimAtPath("/World/panel")
    assert prim.IsA(UsdGeom.Mesh) and prim.HasAPI(UsdLux.MeshLightAPI)
    light = UsdLux.LightAPI(prim)
    rgb = light.GetIntensityAttr().Get() * np.asarray(light.GetColorAttr().Get())
    np.testing.assert_allclose(rgb, L, rtol=1e-6)
    assert light.GetNormalizeAttr().Get() is False
    assert [p.GetPath().name for p in stage.Traverse() if p.HasAPI(UsdLux.LightAPI)] == ["panel"]
    rec = read_scene(stage)
    (ml,) = rec.lights
    assert ml.kind == "mesh" and ml.path == "/World/panel" and ml.area == pytest.approx(4.0)
    assert [m.path for m in rec.meshes].count("/World/panel") == 1
    # XML again: one shape with the emitter nested (one PLY), the same radiance
    shapes = ET.parse(back).getroot().findall("shape")
    emitting = [s for s in shapes if s.find("emitter") is not None]
    assert len(shapes) == 2 and len(emitting) == 1 and emitting[0].find("emitter").get("type") == "area"
    assert emitting[0].find("emitter/rgb").get("value") == "2.0, 3.0, 4.0"
    assert "panel" in emitting[0].find("string[@name='filename']").get("value")
    assert len(list((back.parent / "meshes").glob("*.ply"))) == 2  # the panel and the floor, once each
    # the floor below the panel's centre: rho * L * F, from the original and from the round trip
    expect = ALBEDO * np.asarray(L) * _view_factor(1.0, 1.0)
    for path in (src, back):
        img = _render(path)
        np.testing.assert_allclose(img.mean(axis=(0, 1)), expect, rtol=0.03, err_msg=str(path))


def test_camera_looking_at_the_mesh_light_sees_its_radiance(cli, tmp_path):
    src, _, back = _round_trip(cli, tmp_path, _scene("up", EMITTER_OBJ), "up")
    for path in (src, back):
        img = _render(path, spp=4)
        np.testing.assert_allclose(img.reshape(-1, 3), np.tile(L, (144, 1)), rtol=1e-4, err_msg=str(path))


def test_emitting_cube_is_a_mesh_light(cli, tmp_path):
    shape = ('<shape type="cube"><transform name="to_world"><scale value="0.1"/><translate y="1"/></transform>'
             '<emitter type="area"><rgb name="radiance" value="7"/></emitter></shape>')
    _, stage, back = _round_trip(cli, tmp_path, _scene("floor", shape), "cube")
    (ml,) = read_scene(stage).lights
    assert ml.kind == "mesh" and ml.area == pytest.approx(6 * 0.2 * 0.2, rel=1e-5)
    np.testing.assert_allclose(emitted_radiance(ml), 7.0)
    assert back.read_text().count('type="area"') == 1


def _mesh_light_stage(path, normalize: bool):
    stage = new_stage(path)
    floor_quad(stage, material=diffuse_material(stage, "/World/Looks/Grey", (ALBEDO,) * 3))
    m = UsdGeom.Mesh.Define(stage, "/World/Panel")
    m.CreatePointsAttr([(-1, 1, -1), (1, 1, -1), (1, 1, 1), (-1, 1, 1)])  # faces down (-y)
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.Xformable(m).AddScaleOp().Set(Gf.Vec3f(0.5, 1, 0.5))  # 1 x 1 m in the world
    UsdLux.MeshLightAPI.Apply(m.GetPrim())
    light = UsdLux.LightAPI(m.GetPrim())
    light.CreateIntensityAttr(3.0)
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))
    light.CreateNormalizeAttr(normalize)
    return stage


def test_usdrelight_render_renders_a_mesh_light(cli, tmp_path):
    """A USD stage with a MeshLightAPI mesh (authored with pxr): `usdrelight render` shows its emission; with
    normalize the radiance is divided by the mesh's world area (1 m^2 here: unchanged; 0.25 m^2 below)."""
    from usdrelight.intrinsics import Intrinsics

    stage = _mesh_light_stage(tmp_path / "s.usda", normalize=False)
    intr = Intrinsics(24 / (2 * math.tan(math.radians(4))), 24 / (2 * math.tan(math.radians(4))), 12, 12, 24, 24)
    camera(stage, intr, translate=(0, 0.5, 0), rotate_x_deg=-90)  # looking down at the floor
    stage.GetRootLayer().Save()
    rc, _, err = cli("render", tmp_path / "s.usda", "--spp", "64", "--max-depth", "2")
    assert rc == 0, err
    img = read_photo(tmp_path / "renders" / "color.exr")
    L_rgb = 3.0 * np.array([1.0, 0.5, 0.25])
    np.testing.assert_allclose(img.mean(axis=(0, 1)), ALBEDO * L_rgb * _view_factor(0.5, 1.0), rtol=0.03)
    m = stage.GetPrimAtPath("/World/Panel")
    UsdGeom.Xformable(m).GetOrderedXformOps()[0].Set(Gf.Vec3f(0.25, 1, 0.25))
    UsdLux.LightAPI(m).GetNormalizeAttr().Set(True)
    (ml,) = read_scene(stage).lights
    assert ml.area == pytest.approx(0.25) and emitted_radiance(ml) == pytest.approx(L_rgb / 0.25)


def test_relight_session_falls_back_to_mitsuba_for_mesh_lights(tmp_path, caplog):
    """The fast renderer refuses a stage with a mesh light; RelightSession renders it with Mitsuba (one warning)."""
    import logging

    from usdrelight.intrinsics import Intrinsics
    from usdrelight.relight.session import RelightSession

    stage = _mesh_light_stage(tmp_path / "s.usda", normalize=False)
    camera(stage, Intrinsics(60.0, 60.0, 8.0, 6.0, 16, 12), translate=(0, 0.5, 0), rotate_x_deg=-90)
    stage.GetRootLayer().Save()
    logger = logging.getLogger("usdrelight")  # the CLI tests turn its propagation off: listen on it directly
    logger.addHandler(caplog.handler)
    try:
        with caplog.at_level("WARNING", logger="usdrelight"):
            session = RelightSession(tmp_path / "s.usda", max_side=None, spp=16, max_depth=2, mode="neural")
    finally:
        logger.removeHandler(caplog.handler)
    assert session.renderer == "mitsuba"
    # (a record reaches caplog once or twice, through the usdrelight logger and through root propagation)
    assert len({id(r) for r in caplog.records if "mesh lights" in r.getMessage()
                and "rendering with Mitsuba" in r.getMessage()}) == 1
    frame = session.render()  # no added light: the panel's emission alone lights the floor
    expect = ALBEDO * 3.0 * np.array([1.0, 0.5, 0.25]) * _view_factor(0.5, 1.0)
    np.testing.assert_allclose(frame.diffuse.mean(axis=(0, 1)), expect, rtol=0.1)


def test_sampled_spectra_become_the_rgb_mitsuba_uses(cli, tmp_path):
    """A sampled <spectrum> (an emitter's radiance: unbounded; a reflectance: bounded, D65) becomes exactly the
    RGB Mitsuba's RGB variants render with (read back from Mitsuba's own scene)."""
    spectral = EMITTER_OBJ.replace('<rgb name="reflectance" value="0"/>',
                                   '<spectrum name="reflectance" value="400:0.2, 500:0.5, 600:0.7, 700:0.9"/>')
    spectral = spectral.replace(f'<rgb name="radiance" value="{", ".join(map(str, L))}"/>',
                                '<spectrum name="radiance" value="400:0, 500:8, 600:15.6, 700:18.4"/>')
    src, stage, _ = _round_trip(cli, tmp_path, _scene("floor", spectral), "spectral")
    params = load_mitsuba().traverse(load_mitsuba().load_file(str(src)))
    key = next(k for k in params.keys() if k.endswith("emitter.radiance.value"))
    mitsuba_radiance = np.array(params[key]).reshape(-1)
    mitsuba_albedo = np.array(params[key.replace("emitter.radiance", "bsdf.reflectance")]).reshape(-1)
    (ml,) = read_scene(stage).lights
    np.testing.assert_allclose(ml.radiance, mitsuba_radiance, rtol=1e-5)
    assert mitsuba_radiance[0] > 2 * mitsuba_radiance[2]  # red-heavy, not a grey
    mesh = next(m for m in read_scene(stage).meshes if m.path == ml.path)
    np.testing.assert_allclose(mesh.material.diffuse, mitsuba_albedo, rtol=1e-5)


def test_negative_or_non_finite_mesh_light_is_a_one_line_error(cli, tmp_path):
    for i, value in enumerate((-2.0, float("nan"))):
        stage = _mesh_light_stage(tmp_path / f"bad{i}.usda", normalize=False)
        UsdLux.LightAPI(stage.GetPrimAtPath("/World/Panel")).GetIntensityAttr().Set(value)
        stage.GetRootLayer().Save()
        rc, _, err = cli("convert", tmp_path / f"bad{i}.usda", tmp_path / f"bad{i}" / "s.xml")
        assert rc == 2 and "/World/Panel" in err and "Traceback" not in err
        assert not (tmp_path / f"bad{i}" / "s.xml").exists()
