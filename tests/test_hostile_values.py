"""Finite, non-negative physics (issue 10): NaN/Inf and negative radiance never pass through a converter or a
renderer. Each case: exit 2, one line naming the problem, nothing written (or, for huge depth placeholders,
a documented rule: such pixels are invalid)."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from conftest import make_photo
from usd_scenes import looking_down_at_floor


def _one_error(rc, err, *needles):
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("usdrelight: error:"), err
    assert "Traceback" not in err and "unexpected" not in err, err
    for n in needles:
        assert n in err, err


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


PLY_NAN = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
           "element face 1\nproperty list uchar int vertex_indices\nend_header\nnan 0 0\n1 0 0\n0 inf 0\n3 0 1 2\n")


@pytest.mark.parametrize("body, needle", [
    ('<emitter type="point"><rgb name="intensity" value="nan"/></emitter>', "non-finite"),
    ('<emitter type="point"><rgb name="intensity" value="inf, 1, 1"/></emitter>', "non-finite"),
    ('<emitter type="constant"><spectrum name="radiance" value="inf"/></emitter>', "non-finite"),
    ('<emitter type="point"><point name="position" value="0, nan, 0"/></emitter>', "non-finite"),
    ('<emitter type="point"><transform name="to_world"><matrix value="1 0 0 nan 0 1 0 0 0 0 1 0 0 0 0 1"/>'
     '</transform></emitter>', "non-finite"),
    ('<emitter type="point"><transform name="to_world"><lookat origin="0,0,0" target="0,0,0"/></transform>'
     '</emitter>', "non-finite"),
    ('<emitter type="point"><rgb name="intensity" value="-5"/></emitter>', "negative"),
    ('<emitter type="directional"><rgb name="irradiance" value="1, -1, 1"/></emitter>', "negative"),
    ('<shape type="rectangle"><emitter type="area"><rgb name="radiance" value="-1"/></emitter></shape>', "negative"),
    ('<shape type="ply"><string name="filename" value="nan.ply"/></shape>', "nan.ply"),  # Mitsuba refuses it
    ('<sensor type="perspective"><float name="fov" value="0"/></sensor>', "fov"),
    ('<sensor type="perspective"><float name="fov" value="180"/></sensor>', "fov"),
    ('<sensor type="perspective"><float name="near_clip" value="5"/><float name="far_clip" value="1"/></sensor>',
     "clipping range"),
    ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="1000000000"/></film></sensor>',
     "megapixels"),
    ('<sensor type="perspective"><film type="hdrfilm"><integer name="width" value="0"/></film></sensor>',
     "at least 1x1"),
])
def test_xml_values_that_would_leak_nan_inf_or_negative_light(cli, tmp_path, body, needle):
    (tmp_path / "nan.ply").write_text(PLY_NAN)
    (tmp_path / "s.xml").write_text(f'<scene version="3.0.0">{body}</scene>')
    rc, _, err = cli("convert", tmp_path / "s.xml", tmp_path / "out" / "s.usda")
    _one_error(rc, err, needle)
    assert not (tmp_path / "out" / "s.usda").exists()


#: Cases whose stage holds NaN/Inf itself: even a USD -> USD flattening refuses them.
FLAT_CASES = ("points", "normals", "light_inf", "light_xform", "clip_nan", "sphere_inf")


def _stage(tmp_path, name="s.usda"):
    stage = looking_down_at_floor(tmp_path / name, width=8, height=6)
    return stage


@pytest.mark.parametrize("case, needle", [
    ("points", "non-finite"), ("normals", "non-finite"), ("light_inf", "non-finite"),
    ("exposure", "non-finite"), ("light_negative", "negative"), ("color_negative", "negative"),
    ("light_xform", "non-finite transform"), ("radius", "negative or non-finite size"),
    ("clip_zero", "clipping range"), ("clip_inverted", "clipping range"), ("clip_nan", "clipping range"),
    ("focal_zero", "focalLength"), ("resolution", "megapixels"), ("sphere_inf", "non-finite size"),
])
def test_usd_values_that_would_leak_nan_inf_or_negative_light(cli, tmp_path, case, needle):
    stage = _stage(tmp_path)
    floor = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Floor"))
    light = UsdLux.SphereLight.Define(stage, "/World/L")
    light.CreateIntensityAttr(5.0)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/World/Camera"))
    nan, inf = float("nan"), float("inf")
    if case == "points":
        floor.GetPointsAttr().Set([(nan, 0, 0), (1, 0, 0), (1, 0, -1), (0, inf, -1)])
    elif case == "normals":
        floor.CreateNormalsAttr([(0, nan, 0)] * 4)
    elif case == "light_inf":
        light.GetIntensityAttr().Set(inf)
    elif case == "exposure":
        light.CreateExposureAttr(5000.0)  # 2^5000 overflows
    elif case == "light_negative":
        light.GetIntensityAttr().Set(-5.0)
    elif case == "color_negative":
        light.CreateColorAttr(Gf.Vec3f(1, -1, 1))
    elif case == "light_xform":
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, nan, 0))
    elif case == "radius":
        light.CreateRadiusAttr(-1.0)
    elif case == "clip_zero":
        cam.GetClippingRangeAttr().Set(Gf.Vec2f(0, 0))
    elif case == "clip_inverted":
        cam.GetClippingRangeAttr().Set(Gf.Vec2f(10, 1))
    elif case == "clip_nan":
        cam.GetClippingRangeAttr().Set(Gf.Vec2f(0.1, inf))
    elif case == "focal_zero":
        cam.GetFocalLengthAttr().Set(0.0)
    elif case == "resolution":
        stage.GetPrimAtPath("/Render/Settings").GetAttribute("resolution").Set(Gf.Vec2i(1000000000, 1000000000))
    elif case == "sphere_inf":
        UsdGeom.Sphere.Define(stage, "/World/Ball").CreateRadiusAttr(inf)
    stage.GetRootLayer().Save()
    src = tmp_path / "s.usda"
    for argv in (("convert", src, tmp_path / "x" / "s.xml"), ("convert", src, tmp_path / "x" / "s.ply"),
                 ("convert", src, tmp_path / "x" / "flat.usda"), ("render", src, "-o", tmp_path / "r", "--spp", "1")):
        if str(argv[2]).endswith(".ply") and case not in ("points", "normals"):
            continue
        if str(argv[2]).endswith(".usda") and case not in FLAT_CASES:
            continue  # valid USD values that only a renderer or converter cannot use
        rc, _, err = cli(*argv)
        _one_error(rc, err, "NaN/Inf" if str(argv[2]).endswith(".usda") else needle)
    assert not (tmp_path / "x").exists() or _files(tmp_path / "x") == []
    assert not (tmp_path / "r").exists()


def test_blend_lights_with_nan_inf_are_refused_and_zero_size_or_negative_ones_left_out(cli, tmp_path, monkeypatch):
    """NaN / Inf / a negative colour: one error, nothing written. A zero-size area light or a negative power
    (Blender allows both: nothing rendered, light taken away) aborted the whole file; now left out, warned,
    beside the file's other lights."""
    from usdrelight.converters import blender

    good = {"name": "L", "type": "POINT", "matrix": np.eye(4).tolist(), "color": [1, 1, 1], "power": 10.0,
            "radius": 0.0}
    (tmp_path / "x.blend").write_bytes(b"BLENDER")
    for bad, needle in (({"matrix": [[float("nan")] * 4] * 4}, "non-finite"),
                        ({"power": float("inf")}, "non-finite intensity"),
                        ({"color": [1, -1, 1]}, "negative color")):
        monkeypatch.setattr(blender, "blender_lights", lambda path, b=bad: [{**good, **b}])
        rc, _, err = cli("convert", tmp_path / "x.blend", tmp_path / "lights.usda")
        _one_error(rc, err, needle)
        assert not (tmp_path / "lights.usda").exists()
    for i, bad in enumerate(({"power": -3.0}, {"type": "AREA", "shape": "SQUARE", "size": 0.0},
                             {"type": "AREA", "shape": "RECTANGLE", "size": 1.0, "size_y": 1.0,
                              "matrix": np.diag([1.0, 0.0, 1.0, 1.0]).tolist()})):
        monkeypatch.setattr(blender, "blender_lights", lambda path, b=bad: [{**good, **b, "name": "Z"}, good])
        rc, _, err = cli("convert", tmp_path / "x.blend", tmp_path / f"lights{i}.usda")
        assert rc == 0 and "zero size or zero scale, or of negative power" in err, err
        text = (tmp_path / f"lights{i}.usda").read_text()
        assert '"L"' in text and '"Z"' not in text
    monkeypatch.setattr(blender, "blender_lights", lambda path: [good])
    assert cli("convert", tmp_path / "x.blend", tmp_path / "lights.usda")[0] == 0


def test_huge_depth_placeholders_are_invalid_pixels_and_clipping_stays_finite(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 24, 32)
    depth = np.full((24, 32), 2.0, np.float32)
    depth[:8] = 3e38  # a "sky" placeholder: 2 x 3e38 overflows float32
    np.save(tmp_path / "d.npy", depth)
    rc, _, err = cli("build", photo, "--depth", tmp_path / "d.npy", "-o", tmp_path / "out")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "out" / "scene.usda"))
    near, far = stage.GetPrimAtPath("/Scene/Camera").GetAttribute("clippingRange").Get()
    assert np.isfinite([near, far]).all() and 0 < near < far <= 4.0 + 1e-6
    pts = np.asarray(stage.GetPrimAtPath("/Scene/Photo/Mesh").GetAttribute("points").Get())
    assert np.isfinite(pts).all() and np.abs(pts).max() < 100
    np.save(tmp_path / "all.npy", np.full((24, 32), 3e38, np.float32))
    rc, _, err = cli("build", photo, "--depth", tmp_path / "all.npy", "--fov-x", "60", "-o", tmp_path / "none")
    _one_error(rc, err, "no valid pixel")
    assert not (tmp_path / "none").exists()


def test_the_xml_export_never_writes_a_non_finite_number(tmp_path):
    from usdrelight.converters.mitsuba_xml.write import _fmt
    from usdrelight.errors import UsdRelightError

    for x in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(UsdRelightError):
            _fmt(x)
    assert _fmt(0.5) == "0.5"
    assert Sdf  # noqa: imported for stage edits above


def test_blend_light_paths_that_are_no_prim_paths_and_a_light_named_world(cli, tmp_path, monkeypatch):
    """A .blend's usd_path property holding 'bad name' or 'x.y:z' was an 'unexpected ErrorException'; a
    Blender light named World replaced the World's DomeLight of a .blend made in Blender."""
    from usdrelight.converters import blender
    from usdrelight.converters.blender_units import BlenderLights
    from usdrelight.stage.read import read_lights
    from usdrelight.stage.validate import open_stage

    good = {"name": "World", "type": "POINT", "matrix": np.eye(4).tolist(), "color": [1, 1, 1], "power": 10.0,
            "radius": 0.0}
    (tmp_path / "x.blend").write_bytes(b"BLENDER")
    for i, path in enumerate(("/Scene/Lights/Fitted/bad name", "/Scene/Lights/User/x.y:z")):
        monkeypatch.setattr(blender, "blender_lights", lambda p, q=path: BlenderLights(
            [{**good, "usd_path": q, "as_written": True, "edited": True}]))
        rc, _, err = cli("convert", tmp_path / "x.blend", tmp_path / f"l{i}.usda")
        assert rc == 0, err  # read as a new light of the user's
    lights = BlenderLights([good])
    lights.world = {"kind": "color", "rgb": [0.1, 0.2, 0.3], "strength": 1.0}
    monkeypatch.setattr(blender, "blender_lights", lambda p: lights)
    assert cli("convert", tmp_path / "x.blend", tmp_path / "w.usda")[0] == 0
    kinds = sorted(l.kind for l in read_lights(open_stage(tmp_path / "w.usda")))
    assert kinds == ["dome", "sphere"]
