"""Mitsuba XML as other people write it -> USD -> XML renders as the original does (Mitsuba renders both, same
spp and seed): ``flip_normals`` on emitters (rectangle, disk, ply mesh), a ``<lookat>`` without ``up`` (Mitsuba
picks its own up, not +Y), several ``<sensor>``s (Mitsuba renders the first), and a bitmap ``radiance`` on a
rectangle (RectLight ``inputs:texture:file``), disk or sphere (its mean in USD, the texture kept for the export).
"""
import json

import numpy as np
import pytest
from pxr import Gf, UsdGeom, UsdLux

from usdrelight.imageio import write_image
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.mitsuba.scene_dict import CAMERA_FLIP
from usdrelight.stage.validate import open_stage

QUAD_UP_PLY = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 2
property list uchar int vertex_indices
end_header
-1 -1 0
1 -1 0
1 1 0
-1 1 0
3 0 1 2
3 0 2 3
"""  # a 2 x 2 quad in z = 0 wound to face +Z


def _scene(body: str, sensor: str | None = None, w: int = 24, h: int = 18, spp: int = 8) -> str:
    """A one-sided diffuse floor (6 x 6 m, z = 0) seen from above, the emitter(s) of ``body`` over it."""
    sensor = sensor or f"""<sensor type="perspective"><float name="fov" value="60"/>
        <transform name="to_world"><lookat origin="0, -4, 3" target="0, 0, 0" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/>
            <rfilter type="box"/></film></sensor>"""
    return f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    {sensor}
    <shape type="rectangle"><transform name="to_world"><scale value="3"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
    {body}
</scene>
"""


def _round_trip(cli, folder, text: str, name: str = "scene"):
    """(original XML, its USD stage, the XML written back); the USD next to the XML (its textures inside the
    stage's folder), the XML written back into a sub-folder."""
    src, usd, back = folder / f"{name}.xml", folder / f"{name}.usda", folder / "back" / f"{name}.xml"
    src.write_text(text)
    rc, _, err = cli("convert", src, usd)
    assert rc == 0, err
    rc, _, err2 = cli("convert", usd, back)
    assert rc == 0, err2
    return src, open_stage(usd), back, err


def _render(path, spp: int = 8) -> np.ndarray:
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=spp, seed=0), np.float64)[..., :3]


def _compare(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mean of b / mean of a, rel. RMSE of b against a)."""
    return float(b.mean() / a.mean()), float(np.sqrt(((a - b) ** 2).mean()) / a.mean())


def _emits_along(stage, path: str) -> np.ndarray:
    """The world direction a UsdLux RectLight/DiskLight emits along (its local -Z)."""
    m = np.array(UsdGeom.Xformable(stage.GetPrimAtPath(path)).ComputeLocalToWorldTransform(0)).T
    d = m[:3, :3] @ np.array([0.0, 0.0, -1.0])
    return d / np.linalg.norm(d)


# ---- A. flip_normals -------------------------------------------------------------------------------------------
FLIPPED = {  # emitters 1 m above the floor, flipped so that they light it (unflipped they face up: floor black)
    "disk": ('<shape type="disk" id="lamp"><boolean name="flip_normals" value="true"/>'
             '<transform name="to_world"><scale value="0.5"/><translate x="0.5" z="1"/></transform>'
             '<emitter type="area"><rgb name="radiance" value="2"/></emitter></shape>'),
    "rectangle": ('<shape type="rectangle" id="lamp"><boolean name="flip_normals" value="true"/>'
                  '<transform name="to_world"><scale x="0.6" y="0.3"/><rotate z="1" angle="30"/>'
                  '<translate z="1"/></transform><emitter type="area"><rgb name="radiance" value="2"/></emitter>'
                  '</shape>'),
    "ply": ('<shape type="ply" id="lamp"><string name="filename" value="quad_up.ply"/>'
            '<boolean name="flip_normals" value="true"/>'
            '<transform name="to_world"><scale value="0.5"/><translate z="1"/></transform>'
            '<emitter type="area"><rgb name="radiance" value="2"/></emitter></shape>'),
}


@pytest.mark.parametrize("kind", sorted(FLIPPED))
def test_flip_normals_emitter_lights_the_same_side_after_the_round_trip(cli, tmp_path, kind):
    """Before: the reader ignored flip_normals, so the light came back facing up and the floor went black
    (disk_flip_only.xml: floor mean 0.0169 -> 0 with the emitter hidden; ply_flip.xml: 0.0239 -> 0)."""
    (tmp_path / "quad_up.ply").write_text(QUAD_UP_PLY)
    body = FLIPPED[kind].replace("<emitter", '<bsdf type="diffuse"><rgb name="reflectance" value="0"/></bsdf>'
                                 "<emitter") if kind == "ply" else FLIPPED[kind]
    text = _scene(body).replace('<integer name="max_depth" value="2"/>',
                                '<integer name="max_depth" value="2"/><boolean name="hide_emitters" value="true"/>')
    src, stage, back, _ = _round_trip(cli, tmp_path, text)
    a, b = _render(src, 64), _render(back, 64)
    assert a.mean() > 0.005  # the flipped emitter does light the floor
    ratio, _ = _compare(a, b)  # (the ply's triangles come back wound the other way: other samples, ~1% noise)
    assert abs(ratio - 1) < 0.03, (kind, a.mean(), b.mean())
    if kind == "ply":  # the mesh itself faces down: winding reversed, normals negated
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/lamp"))
        assert np.allclose(np.array(mesh.GetNormalsAttr().Get()), [0, 0, -1], atol=1e-6)
        p = np.array(mesh.GetPointsAttr().Get(), np.float64)
        f = np.array(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
        n = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
        assert np.all(n[:, 2] < 0)
    else:  # the UsdLux light emits along world -Z (down)
        assert np.allclose(_emits_along(stage, "/World/lamp"), [0, 0, -1], atol=1e-6)


def test_flip_normals_on_a_plain_rectangle_turns_its_mesh_over(cli, tmp_path):
    """A flipped one-sided rectangle (no emitter), seen and lit from below, reflects (before: its mesh faced +Z
    and came back black from below: mean 0)."""
    text = """<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective"><float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="0, -1, -2" target="0, 0, 1" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="18"/></film></sensor>
    <shape type="rectangle" id="card"><boolean name="flip_normals" value="true"/>
        <transform name="to_world"><scale value="2"/><translate z="1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf></shape>
    <emitter type="point"><point name="position" value="0, -1, -0.5"/><rgb name="intensity" value="5"/></emitter>
</scene>
"""
    src, stage, back, _ = _round_trip(cli, tmp_path, text)
    normals = np.array(UsdGeom.Mesh(stage.GetPrimAtPath("/World/card")).GetNormalsAttr().Get())
    assert np.allclose(normals, [0, 0, -1])
    a, b = _render(src, 4), _render(back, 4)
    ratio, rmse = _compare(a, b)
    assert a.mean() > 0.05 and abs(ratio - 1) < 0.02 and rmse < 0.05, (a.mean(), b.mean(), rmse)


# ---- B. <lookat> without up --------------------------------------------------------------------------------------
@pytest.mark.parametrize("origin, up", [("1, 2, 5", None), ("0, 3, 0", None), ("0, 0, -4", None),
                                        ("2, -1, 3", "0, 0, 0")])
def test_lookat_without_up_gives_mitsubas_camera(cli, tmp_path, origin, up):
    """Before: a missing up was taken as +Y; Mitsuba makes its own from the view direction
    (lookat_noup2.xml came back rolled by 92 degrees). The USD camera, and the round trip's sensor, have
    Mitsuba's own to_world."""
    up_attr = f' up="{up}"' if up else ""
    sensor = f"""<sensor type="perspective"><float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="{origin}" target="0.1, 0.2, 0"{up_attr}/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="18"/></film></sensor>"""
    text = _scene('<emitter type="constant"/>', sensor=sensor)
    src, stage, back, _ = _round_trip(cli, tmp_path, text)
    mi = load_mitsuba()
    want = np.array(mi.load_file(str(src)).sensors()[0].world_transform().matrix, np.float64).reshape(4, 4)
    cam = stage.GetPrimAtPath("/World/Camera")
    have = np.array(UsdGeom.Xformable(cam).ComputeLocalToWorldTransform(0)).T @ CAMERA_FLIP
    assert np.allclose(have, want, atol=1e-5), (have, want)
    again = np.array(mi.load_file(str(back)).sensors()[0].world_transform().matrix, np.float64).reshape(4, 4)
    assert np.allclose(again, want, atol=1e-5)


# ---- C. several sensors --------------------------------------------------------------------------------------------
def test_the_first_of_several_sensors_is_the_one_rendered(cli, tmp_path):
    """Before: the last <sensor> became the RenderSettings camera (env_sensors.xml came back 64 x 64 from the
    witness camera); Mitsuba renders the first."""
    first = """<sensor type="perspective" id="main"><float name="fov" value="50"/>
        <transform name="to_world"><lookat origin="0, -4, 3" target="0, 0, 0" up="0, 0, 1"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="18"/></film></sensor>
    <sensor type="perspective" id="witness"><float name="fov" value="20"/>
        <transform name="to_world"><lookat origin="10, 0, 1" target="0, 0, 0" up="0, 0, 1"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film></sensor>"""
    text = _scene('<emitter type="constant"><rgb name="radiance" value="0.7"/></emitter>', sensor=first)
    src, stage, back, err = _round_trip(cli, tmp_path, text)
    assert "more than one <sensor>" in err
    assert {p.GetName() for p in stage.Traverse() if p.IsA(UsdGeom.Camera)} == {"main", "witness"}
    mi = load_mitsuba()
    want, have = mi.load_file(str(src)).sensors()[0], mi.load_file(str(back)).sensors()[0]
    assert tuple(have.film().size()) == tuple(want.film().size()) == (24, 18)
    assert np.allclose(np.array(have.world_transform().matrix), np.array(want.world_transform().matrix), atol=1e-5)
    a, b = _render(src, 4), _render(back, 4)
    assert a.shape == b.shape and abs(b.mean() / a.mean() - 1) < 0.01


# ---- D. textured radiance on rectangle / disk / sphere -----------------------------------------------------------
def _emit_texture(path):
    """An 8 x 16 linear EXR: left half (u < 0.5) 3, right half 0.25 (mean 1.625), a red top row (v = 0)."""
    img = np.full((8, 16, 3), 0.25, np.float32)
    img[:, :8] = 3.0
    img[0] = (4.0, 0.5, 0.5)
    write_image(path, img, "float")
    return img


TEXTURED = {  # emitters seen by the camera and lighting the floor; the texture makes them asymmetric
    "rectangle": ('<shape type="rectangle" id="lamp"><transform name="to_world"><scale x="0.8" y="0.5"/>'
                  '<rotate x="1" angle="150"/><translate z="1.2"/></transform>'
                  '<emitter type="area"><texture type="bitmap" name="radiance">'
                  '<string name="filename" value="emit.exr"/></texture></emitter></shape>'),
    "disk": ('<shape type="disk" id="lamp"><transform name="to_world"><scale value="0.6"/><rotate x="1" '
             'angle="150"/><translate z="1.2"/></transform><emitter type="area"><texture type="bitmap" '
             'name="radiance"><string name="filename" value="emit.exr"/></texture></emitter></shape>'),
    "sphere": ('<shape type="sphere" id="lamp"><float name="radius" value="0.3"/><point name="center" '
               'value="0.4, 0, 1"/><emitter type="area"><texture type="bitmap" name="radiance">'
               '<string name="filename" value="emit.exr"/></texture></emitter></shape>'),
}


@pytest.mark.parametrize("kind", sorted(TEXTURED))
def test_textured_area_emitter_round_trip_renders_the_same(cli, tmp_path, kind):
    """Before: the texture was dropped silently and the radiance became 1 (area_tex_only.xml: mean 1.625 ->
    1, the floor 35% dark). Now the round trip renders the very same image (same paths: rel. RMSE ~0)."""
    _emit_texture(tmp_path / "emit.exr")
    src, stage, back, err = _round_trip(cli, tmp_path, _scene(TEXTURED[kind]))
    a, b = _render(src), _render(back)
    ratio, rmse = _compare(a, b)
    assert abs(ratio - 1) < 0.005 and rmse < 0.02, (kind, a.mean(), b.mean(), rmse)
    light = stage.GetPrimAtPath("/World/lamp")
    if kind.startswith("rectangle"):  # UsdLux holds it: the RectLight's texture, colour x intensity 1
        file = UsdLux.RectLight(light).GetTextureFileAttr().Get().path
        # an unflipped Mitsuba rectangle shows its texture mirrored, seen from the side it lights
        assert file.startswith("textures/emit_mirrored_")
        assert UsdLux.LightAPI(light).GetIntensityAttr().Get() == pytest.approx(1.0)
    else:  # not in UsdLux: its colour is the texture's mean, warned naming the light
        assert "textured radiance on the" in err and "/World/lamp" in err
        kept = json.loads(light.GetCustomDataByKey("mitsuba"))["area_texture"]
        assert kept["file"] == "emit.exr"


def test_flipped_textured_rectangle_keeps_its_texture_the_right_way_round(cli, tmp_path):
    """A flipped rectangle shows its texture unmirrored from the side it lights: the RectLight takes the file as
    it is, turned half round. (Mitsuba 3.9 renders such an emitter nearly black through emitter sampling, so the
    reference is the same light made without flip_normals: the rectangle turned about y, the bitmap mirrored by
    to_uv.)"""
    _emit_texture(tmp_path / "emit.exr")
    flipped = ('<shape type="rectangle" id="lamp"><boolean name="flip_normals" value="true"/>'
               '<transform name="to_world"><scale x="0.8" y="0.5"/><rotate x="1" angle="-30"/>'
               '<translate z="1.2"/></transform><emitter type="area"><texture type="bitmap" name="radiance">'
               '<string name="filename" value="emit.exr"/></texture></emitter></shape>')
    same = ('<shape type="rectangle"><transform name="to_world"><rotate y="1" angle="180"/><scale x="0.8" y="0.5"/>'
            '<rotate x="1" angle="-30"/><translate z="1.2"/></transform><emitter type="area"><texture type="bitmap" '
            'name="radiance"><string name="filename" value="mirrored.exr"/></texture></emitter></shape>')
    write_image(tmp_path / "mirrored.exr", np.ascontiguousarray(_emit_texture(tmp_path / "emit.exr")[:, ::-1]),
                "float")
    src, stage, back, _ = _round_trip(cli, tmp_path, _scene(flipped))
    (tmp_path / "same.xml").write_text(_scene(same))
    assert UsdLux.RectLight(stage.GetPrimAtPath("/World/lamp")).GetTextureFileAttr().Get().path == "emit.exr"
    a, b = _render(tmp_path / "same.xml", 16), _render(back, 16)
    ratio, rmse = _compare(a, b)
    assert abs(ratio - 1) < 0.01 and rmse < 0.05, (a.mean(), b.mean(), rmse)


def test_textured_disk_in_usd_alone_sends_the_textures_power(cli, tmp_path):
    """What other USD tools see (customData dropped): a DiskLight of the texture's mean over the disk's area,
    Mitsuba's polar uv (r, phi / 2 pi) weighting each texel by its radius: (1.32, 0.88, 0.88) here, where the
    plain texel mean is (1.92, 1.48, 1.48) and the reader used to give 1. A disk facing down 0.5 m over the floor
    lights it as the textured disk does (measured -2.3% at 256 spp: the same power, spread a little otherwise)."""
    img = _emit_texture(tmp_path / "emit.exr").astype(np.float64)
    body = ('<shape type="disk" id="lamp"><transform name="to_world"><scale value="0.6"/><rotate x="1" '
            'angle="180"/><translate z="0.5"/></transform><emitter type="area"><texture type="bitmap" '
            'name="radiance"><string name="filename" value="emit.exr"/></texture></emitter></shape>')
    text = _scene(body).replace('<integer name="max_depth" value="2"/>',
                                '<integer name="max_depth" value="2"/><boolean name="hide_emitters" value="true"/>')
    src, stage, back, _ = _round_trip(cli, tmp_path, text)
    light = stage.GetPrimAtPath("/World/lamp")
    rgb = np.array(UsdLux.LightAPI(light).GetColorAttr().Get()) * UsdLux.LightAPI(light).GetIntensityAttr().Get()
    u = (np.arange(16) + 0.5) / 16  # texel columns: u = r
    want = (img * u[None, :, None]).sum((0, 1)) / (u.sum() * 8)
    assert np.allclose(rgb, want, rtol=1e-4) and np.allclose(want, (1.3203125, 0.8828125, 0.8828125))
    light.ClearCustomDataByKey("mitsuba")
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "scene.usda", tmp_path / "alone" / "scene.xml")
    assert rc == 0, err
    a, b = _render(src, 32), _render(tmp_path / "alone" / "scene.xml", 32)
    assert abs(b.mean() / a.mean() - 1) < 0.05, (a.mean(), b.mean())


def test_rect_light_texture_from_usd_is_written_in_usdlux_orientation(cli, tmp_path):
    """A RectLight with inputs:texture:file made in USD (not from XML): UsdLux puts the file's first texel
    (top-left) at the light's (+X, +Y) corner, the last at (-X, -Y). A camera on the side the light faces (-Z),
    looking back at it with +Y up, has +X on its left: it sees the image as it is (red top half at the top,
    green left half on the left)."""
    from usdrelight.stage.create import create_stage

    img = np.zeros((8, 8, 3), np.float32)
    img[:4, :, 0] = 2.0  # top half red
    img[:, :4, 1] = 1.0  # left half green
    write_image(tmp_path / "t.exr", img, "float")
    stage = create_stage(tmp_path / "rect.usda", "/World")
    light = UsdLux.RectLight.Define(stage, "/World/Rect")
    light.CreateWidthAttr(2.0)
    light.CreateHeightAttr(2.0)
    light.CreateTextureFileAttr("t.exr")
    UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, 0, -3))  # emits along -Z, towards z = -inf ...
    cam = UsdGeom.Camera.Define(stage, "/World/Cam")  # ... and a camera at z = -6 looking back along +Z
    cam.CreateFocalLengthAttr(40.0)  # 28 degrees: the 2 x 2 light at 3 m fills the view
    cam.CreateHorizontalApertureAttr(20.0)
    cam.CreateVerticalApertureAttr(20.0)
    UsdGeom.Xformable(cam).AddTransformOp().Set(Gf.Matrix4d(np.diag([-1.0, 1.0, -1.0, 1.0]).tolist())
                                                * Gf.Matrix4d().SetTranslate(Gf.Vec3d(0, 0, -6)))
    from usdrelight.stage.create import author_render_settings
    from usdrelight.stage.aovs import AOVS
    author_render_settings(stage, "/World/Cam", 16, 16, [AOVS["color"]])
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "rect.usda", tmp_path / "rect.xml")
    assert rc == 0, err
    assert "RectLight texture" not in err
    im = _render(tmp_path / "rect.xml", 4)
    top, bottom = im[:8, 4:12, 0].mean(), im[8:, 4:12, 0].mean()
    left, right = im[4:12, :8, 1].mean(), im[4:12, 8:, 1].mean()
    assert top > 1.5 and bottom < 0.1, (top, bottom)  # the file's top rows at the light's +Y, up in view
    assert left > 0.8 and right < 0.1, (left, right)  # st s = 0 at +X: the viewer's left when facing the light


OLD_SCENE = """<scene version="{version}">
  <integrator type="path"><integer name="{max_depth}" value="2"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <string name="{fov_axis}" value="y"/>
    <transform name="{to_world}"><{lookat} origin="0, 1, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
  <emitter type="point"><point name="position" x="2" y="3" z="2"/><rgb name="intensity" value="20"/></emitter>
</scene>"""


def test_a_mitsuba_0_5_scene_is_read_with_mitsuba_3s_names(cli, tmp_path):
    """A Mitsuba 0.5-era file (camelCase names, toWorld, lookAt) reads as its Mitsuba 3 spelling does: the same
    camera (at (0, 1, 5), 45 degrees vertically) and light; it used to lose its camera transform and field of
    view with only "lookAt ignored"."""
    from usdrelight.stage.read import read_scene

    old = OLD_SCENE.format(version="0.5.0", max_depth="maxDepth", fov_axis="fovAxis", to_world="toWorld",
                           lookat="lookAt")
    new = OLD_SCENE.format(version="3.0.0", max_depth="max_depth", fov_axis="fov_axis", to_world="to_world",
                           lookat="lookat")
    scenes = {}
    for name, text in (("old", old), ("new", new)):
        (tmp_path / f"{name}.xml").write_text(text)
        rc, _, err = cli("convert", tmp_path / f"{name}.xml", tmp_path / f"{name}.usda")
        assert rc == 0, err
        assert ("names upgraded to Mitsuba 3's" in err) == (name == "old"), err
        scenes[name] = read_scene(open_stage(tmp_path / f"{name}.usda"))
    a, b = scenes["old"], scenes["new"]
    np.testing.assert_allclose(a.camera.to_world, b.camera.to_world, atol=1e-9)
    np.testing.assert_allclose(a.camera.to_world[:3, 3], [0, 1, 5], atol=1e-9)
    k = a.camera.intrinsics
    assert np.degrees(2 * np.arctan(k.height / 2 / k.fy)) == pytest.approx(45.0, abs=1e-4)
    assert k == b.camera.intrinsics
    np.testing.assert_allclose(a.lights[0].radiance, b.lights[0].radiance)
    np.testing.assert_allclose(a.lights[0].to_world[:3, 3], [2, 3, 2])
