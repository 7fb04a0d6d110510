"""Mitsuba XML -> USD -> XML keeps the view of perspective sensors as Mitsuba itself resolves it: fov along
every fov_axis, focal_length strings ("50mm", the default when neither is given), film crop windows.

The check is Mitsuba's own: its x_fov for the original sensor, and renders of the original XML and of the
round trip (a bright off-centre panel must land on the same pixels)."""
import math

import numpy as np
import pytest
from pxr import UsdGeom

from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

DIAG = math.hypot(36.0, 24.0)
SENSORS = {  # name -> sensor properties (XML)
    "fov_x": '<float name="fov" value="40"/>',
    "fov_y": '<float name="fov" value="40"/><string name="fov_axis" value="y"/>',
    "fov_diagonal": '<float name="fov" value="45"/><string name="fov_axis" value="diagonal"/>',
    "fov_smaller": '<float name="fov" value="35"/><string name="fov_axis" value="smaller"/>',
    "fov_larger": '<float name="fov" value="42"/><string name="fov_axis" value="LARGER"/>',
    "focal_50mm": '<string name="focal_length" value="50mm"/>',
    "focal_35": '<string name="focal_length" value="35"/>',
    "default": "",
}
FILMS = [(32, 24), (24, 32), (32, 32)]


def _scene(sensor: str, w: int, h: int, film_extra: str = "") -> str:
    """Camera at the origin looking down +Z; an emitting panel (radiance 5) off centre at z = 5, seen directly."""
    return f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective">{sensor}
        <film type="hdrfilm"><integer name="width" value="{w}"/><integer name="height" value="{h}"/>{film_extra}
            <rfilter type="box"/></film>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><scale x="0.7" y="0.45" z="1"/><rotate y="1" angle="180"/>
            <translate x="0.55" y="0.3" z="5"/></transform>
        <emitter type="area"><rgb name="radiance" value="5"/></emitter>
    </shape>
</scene>
"""


def _round_trip(cli, tmp_path, text: str):
    src, usd, out = tmp_path / "src.xml", tmp_path / "mid.usda", tmp_path / "out" / "back.xml"
    src.write_text(text)
    rc, _, err = cli("convert", src, usd)
    assert rc == 0, err
    rc, _, err = cli("convert", usd, out)
    assert rc == 0, err
    return src, open_stage(usd), out


def _render(path):
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=4))[..., 0]


def _mitsuba_x_fov(text_sensor: str, w: int, h: int) -> float:
    mi = load_mitsuba()
    scene = mi.load_string(_scene(text_sensor, w, h))
    return float(mi.traverse(scene.sensors()[0])["x_fov"][0])


@pytest.mark.parametrize("name", sorted(SENSORS))
@pytest.mark.parametrize("w,h", FILMS)
def test_fov_is_resolved_as_mitsuba_does(cli, tmp_path, name, w, h):
    """Every fov_axis and focal length on landscape, portrait and square films: the USD camera's horizontal
    field of view is Mitsuba's own x_fov; a focal length stays in millimetres, its apertures on the 36 x 24 mm
    film's diagonal."""
    _, stage, _ = _round_trip(cli, tmp_path, _scene(SENSORS[name], w, h))
    rec = read_scene(stage)
    k = rec.camera.intrinsics
    assert (k.width, k.height) == (w, h)
    fov_x = math.degrees(2 * math.atan(w / (2 * k.fx)))
    assert fov_x == pytest.approx(_mitsuba_x_fov(SENSORS[name], w, h), rel=1e-5)
    cam = UsdGeom.Camera(stage.GetPrimAtPath(rec.camera.path))
    f, ha, va = (cam.GetFocalLengthAttr().Get(), cam.GetHorizontalApertureAttr().Get(),
                 cam.GetVerticalApertureAttr().Get())
    if name.startswith("fov"):
        assert ha == pytest.approx(36.0) and va == pytest.approx(36.0 * h / w, rel=1e-6)
        assert f == pytest.approx(18.0 / math.tan(math.radians(fov_x) / 2), rel=1e-5)
    else:  # focal_length: f in mm, the image's diagonal spanning the 36 x 24 mm film's diagonal
        assert f == pytest.approx(35.0 if name == "focal_35" else 50.0)
        assert ha == pytest.approx(DIAG * w / math.hypot(w, h), rel=1e-6)
        assert va == pytest.approx(DIAG * h / math.hypot(w, h), rel=1e-6)


@pytest.mark.parametrize("name,w,h", [("fov_y", 32, 24), ("fov_diagonal", 24, 32), ("fov_smaller", 24, 32),
                                      ("fov_larger", 24, 32), ("focal_50mm", 32, 32), ("focal_35", 24, 32),
                                      ("default", 32, 24)])
def test_round_trip_renders_the_same_pixels(cli, tmp_path, name, w, h):
    """Mitsuba renders the original sensor and the XML -> USD -> XML one alike: the panel on the same pixels."""
    src, _, out = _round_trip(cli, tmp_path, _scene(SENSORS[name], w, h))
    a, b = _render(src), _render(out)
    assert a.shape == b.shape == (h, w)
    full_a, full_b = a > 4.99, b > 4.99  # pixels entirely inside the panel (radiance 5)
    assert 6 < full_a.sum() < 0.8 * w * h
    assert (full_a != full_b).sum() <= 1
    assert b.mean() == pytest.approx(a.mean(), rel=0.02)


def test_crop_window_renders_the_same_pixels(cli, tmp_path):
    """A film crop window (with a principal point offset on the full film) becomes a camera of the crop's size
    whose principal point moved by the crop offset."""
    crop = ('<integer name="crop_offset_x" value="10"/><integer name="crop_offset_y" value="4"/>'
            '<integer name="crop_width" value="20"/><integer name="crop_height" value="16"/>')
    sensor = SENSORS["focal_35"] + '<float name="principal_point_offset_x" value="0.1"/>'
    src, stage, out = _round_trip(cli, tmp_path, _scene(sensor, 40, 30, crop))
    k = read_scene(stage).camera.intrinsics
    assert (k.width, k.height) == (20, 16)
    assert (k.cx, k.cy) == pytest.approx((40 * 0.4 - 10, 15 - 4))
    a, b = _render(src), _render(out)
    assert a.shape == b.shape == (16, 20)
    assert ((a > 4.99) != (b > 4.99)).sum() <= 1 and (a > 4.99).sum() > 6
    assert b.mean() == pytest.approx(a.mean(), rel=0.02)


@pytest.mark.parametrize("sensor,film,needle", [
    ('<float name="fov" value="40"/><string name="focal_length" value="50mm"/>', "", "not both"),
    ('<string name="focal_length" value="fifty"/>', "", "<x>mm"),
    ('<string name="focal_length" value="-5mm"/>', "", "positive"),
    ('<float name="fov" value="40"/><string name="fov_axis" value="z"/>', "", "fov_axis"),
    ('<string name="focal_length" value="0mm"/>', "", "positive"),
    ("", '<integer name="crop_offset_x" value="8"/>', "crop window"),
])
def test_sensors_mitsuba_refuses_are_one_line_errors(cli, tmp_path, sensor, film, needle):
    (tmp_path / "bad.xml").write_text(_scene(sensor, 32, 16, film))
    rc, _, err = cli("convert", tmp_path / "bad.xml", tmp_path / "o.usda")
    assert rc == 2 and needle in err and "Traceback" not in err
    assert not (tmp_path / "o.usda").exists()


SHEARED = """#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
)
def Xform "World"
{
    def Sphere "Ball"
    {
        double radius = 0.2
    }
    def Xform "Rig"
    {
        float3 xformOp:scale = (1, 2, 1)
        uniform token[] xformOpOrder = ["xformOp:scale"]
        def Camera "Cam"
        {
            float focalLength = 35
            float horizontalAperture = 36
            float verticalAperture = 27
            double3 xformOp:translate = (0, 0, 5)
            float3 xformOp:rotateXYZ = (0, 0, 45)
            uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
        }
    }
}
"""


def test_a_camera_under_a_stretched_parent_is_warned_and_rigid(cli, tmp_path):
    """A rotated camera under a non-uniform scale: its axes were normalised one by one, leaving a shear (dot
    product -0.6) that Mitsuba refuses ('Scale factors ... not allowed': the XML did not load, render failed with
    exit 1, Blender aimed elsewhere), with no warning. Now: its position, view direction and up, unstretched."""
    (tmp_path / "shear.usda").write_text(SHEARED)
    rc, _, err = cli("convert", tmp_path / "shear.usda", tmp_path / "shear.xml")
    assert rc == 0 and "camera under a non-uniform scale or shear" in err, err
    mi = load_mitsuba()
    m = np.array(mi.load_file(str(tmp_path / "shear.xml")).sensors()[0].world_transform().matrix, np.float64)
    m = m.reshape(4, 4)
    np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-6)
    np.testing.assert_allclose(m[:3, 3], [0, 0, 5], atol=1e-6)
    np.testing.assert_allclose(m[:3, 2], [0, 0, -1], atol=1e-6)  # still looking at the origin
    np.testing.assert_allclose(m[:3, 1], np.array([-1, 2, 0]) / math.sqrt(5), atol=1e-6)  # USD's up: Rig x Rz(45) Y
