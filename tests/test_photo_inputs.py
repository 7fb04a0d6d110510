"""Photos and maps as cameras and other tools write them (a probe of `build` found each case): integer depth
maps, truncated JPEGs, alpha, EXR display windows, masks, output paths that cannot be used. Each case: the
number it must give, or one clear line on stderr and exit 2 with nothing written."""
from __future__ import annotations

import numpy as np
import pytest

from conftest import make_photo
from usdrelight.imageio import write_image
from usdrelight.stage.read import read_scene


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _write_uint16(path, values: np.ndarray) -> None:
    oiio = _oiio()
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(values.shape[1], values.shape[0], 1, oiio.UINT16))
    out.write_image(np.ascontiguousarray(values.astype(np.uint16)[:, :, None]))
    out.close()


def _one_error(rc, err):
    lines = [l for l in err.splitlines() if l.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("usdrelight: error: "), (rc, err)
    return lines[0]


def _mesh_depths(scene_usda):
    pts = read_scene(scene_usda).meshes[0].points
    return -pts[:, 2]  # the camera looks down -Z from the origin


@pytest.fixture
def photo(tmp_path):
    return make_photo(tmp_path / "photo.png", 24, 32)


def test_an_integer_depth_map_needs_its_unit(cli, tmp_path, photo):
    """A 16-bit PNG of millimetres (3000 = 3 m; Kinect, RealSense, NYU) was read as 3000 / 65535 = 0.046 m."""
    _write_uint16(tmp_path / "mm.png", np.full((24, 32), 3000))
    rc, _, err = cli("build", photo, "--depth", tmp_path / "mm.png", "--fov-x", "60", "-o", tmp_path / "a")
    assert "give --depth-scale" in _one_error(rc, err) and not (tmp_path / "a").exists()
    rc, _, err = cli("build", photo, "--depth", tmp_path / "mm.png", "--depth-scale", "0.001", "--fov-x", "60",
                     "-o", tmp_path / "b")
    assert rc == 0, err
    np.testing.assert_allclose(_mesh_depths(tmp_path / "b" / "scene.usda"), 3.0, rtol=1e-6)
    np.save(tmp_path / "mm.npy", np.full((24, 32), 2500, np.uint16))  # an integer array names no unit either
    rc, _, err = cli("build", photo, "--depth", tmp_path / "mm.npy", "--fov-x", "60", "-o", tmp_path / "c")
    assert "stores integers (uint16)" in _one_error(rc, err)
    write_image(tmp_path / "cm.exr", np.full((24, 32, 1), 250.0, np.float32), "float")  # float centimetres
    rc, _, err = cli("build", photo, "--depth", tmp_path / "cm.exr", "--depth-scale", "0.01", "--fov-x", "60",
                     "-o", tmp_path / "d")
    assert rc == 0, err
    np.testing.assert_allclose(_mesh_depths(tmp_path / "d" / "scene.usda"), 2.5, rtol=1e-6)
    rc, _, err = cli("build", photo, "--depth-scale", "0.01", "-o", tmp_path / "e")
    assert "--depth-scale goes with --depth or --points" in _one_error(rc, err)
    for bad in ("0", "-1", "inf", "nan"):  # argparse refuses them before anything runs: one line, exit 2
        with pytest.raises(SystemExit) as exc:
            cli("build", photo, "--depth", tmp_path / "cm.exr", "--depth-scale", bad, "-o", tmp_path / "f")
        assert exc.value.code == 2 and not (tmp_path / "f").exists()


def _write_uint8(path, img: np.ndarray, **attrs) -> None:
    oiio = _oiio()
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], img.shape[2], oiio.UINT8)
    for k, v in attrs.items():
        spec.attribute(k, v)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ascontiguousarray(img))
    out.close()


@pytest.mark.parametrize("orientation, turn", [(1, lambda a: a), (3, lambda a: np.rot90(a, 2)),
                                               (6, lambda a: np.rot90(a, -1)), (8, lambda a: np.rot90(a, 1)),
                                               (2, lambda a: a[:, ::-1])])
def test_exif_orientation_is_applied(tmp_path, orientation, turn):
    """A camera's stored pixels turned as its Orientation tag says (6: a quarter turn clockwise to display)."""
    from usdrelight.imageio import read_photo, srgb_to_linear

    img = np.random.default_rng(0).integers(0, 256, (6, 10, 3), dtype=np.uint8)
    _write_uint8(tmp_path / "o.tif", img, Orientation=orientation)
    np.testing.assert_allclose(read_photo(tmp_path / "o.tif"), turn(srgb_to_linear(img / 255.0)), atol=1e-6)


def test_alpha_is_dropped_not_multiplied_in(tmp_path):
    """Alpha 0 on the left half: the colour there is the stored colour (before: 0, OpenImageIO's associated
    alpha applied, so a cut-out PNG's albedo and fit target went black, and alpha 128 made a photo 4x dark)."""
    from usdrelight.imageio import read_photo, srgb_to_linear

    rgba = np.full((4, 6, 4), 200, np.uint8)
    rgba[:, :3, 3] = 0
    rgba[:, 3:, 3] = 128
    _write_uint8(tmp_path / "a.png", rgba, **{"oiio:UnassociatedAlpha": 1})  # stored as given
    np.testing.assert_allclose(read_photo(tmp_path / "a.png"), srgb_to_linear(200 / 255.0), rtol=1e-5)


def test_a_truncated_jpeg_is_refused(cli, tmp_path):
    """Half a JPEG decoded as grey rows below the cut (before: accepted, the grey became albedo and target)."""
    img = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    _write_uint8(tmp_path / "full.jpg", img)
    data = (tmp_path / "full.jpg").read_bytes()
    (tmp_path / "half.jpg").write_bytes(data[:len(data) // 2])
    rc, _, err = cli("build", tmp_path / "half.jpg", "-o", tmp_path / "out")
    assert "truncated file" in _one_error(rc, err) and not (tmp_path / "out").exists()
    assert cli("build", tmp_path / "full.jpg", "-o", tmp_path / "ok")[0] == 0


def test_an_overscan_exr_is_cropped_to_its_display_window(cli, tmp_path):
    """Display window 32 x 24, data window 40 x 30 at (-4, -3): the photo is the display window (before: the
    camera was 40 x 30, its focal length in pixels 25% off the field of view asked for)."""
    import json

    oiio = _oiio()
    rng = np.random.default_rng(2)
    data = rng.uniform(0.1, 0.9, (30, 40, 3)).astype(np.float32)
    spec = oiio.ImageSpec(40, 30, 3, oiio.FLOAT)
    spec.x, spec.y = -4, -3
    spec.full_x, spec.full_y, spec.full_width, spec.full_height = 0, 0, 32, 24
    out = oiio.ImageOutput.create(str(tmp_path / "o.exr"))
    out.open(str(tmp_path / "o.exr"), spec)
    out.write_image(data)
    out.close()
    from usdrelight.imageio import read_photo

    np.testing.assert_array_equal(read_photo(tmp_path / "o.exr"), data[3:27, 4:36])
    rep = cli.json("build", tmp_path / "o.exr", "--fov-x", "60", "-o", tmp_path / "s")
    assert json.dumps(rep) and read_scene(tmp_path / "s" / "scene.usda").resolution == (32, 24)
    cam = read_scene(tmp_path / "s" / "scene.usda").camera.intrinsics
    assert cam.fx == pytest.approx(16 / np.tan(np.radians(30)), rel=1e-6)
    spec.x, spec.y, spec.width, spec.height = 5, 5, 20, 10  # a crop: the display window is not covered
    out = oiio.ImageOutput.create(str(tmp_path / "c.exr"))
    out.open(str(tmp_path / "c.exr"), spec)
    out.write_image(data[:10, :20].copy())
    out.close()
    rc, _, err = cli("build", tmp_path / "c.exr", "-o", tmp_path / "t")
    assert "does not cover its display window" in _one_error(rc, err)


def test_a_folder_given_as_the_photo_is_named_as_one(cli, tmp_path):
    (tmp_path / "shots.jpg").mkdir()
    rc, _, err = cli("build", tmp_path / "shots.jpg", "-o", tmp_path / "out")
    assert "is a folder, not an image file" in _one_error(rc, err)


def test_a_mask_keeps_every_non_zero_pixel(cli, tmp_path, photo):
    """As --help says, non-zero = keep (before: above half the mask's maximum, so an 8-bit 1 beside a 255 was
    dropped, and one Inf pixel dropped everything with a misleading error)."""
    np.save(tmp_path / "d.npy", np.full((24, 32), 2.0, np.float32))
    m = np.zeros((24, 32), np.float32)
    m[:, :8], m[:, 8:16], m[:, 16:24] = 1.0, 255.0, 0.004  # the right quarter 0: dropped
    m[0, 0] = np.inf
    m[1, 0] = np.nan
    np.save(tmp_path / "m.npy", m)
    rep = cli.json("build", photo, "--depth", tmp_path / "d.npy", "--fov-x", "60", "--mask", tmp_path / "m.npy",
                   "-o", tmp_path / "s")
    assert rep
    pts = read_scene(tmp_path / "s" / "scene.usda").meshes[0].points
    u = pts[:, 0] / -pts[:, 2] * (16 / np.tan(np.radians(30))) + 16  # column of each vertex (pixel centres + 0.5)
    assert u.min() < 0.6 and 23.4 < u.max() < 24.6  # the three kept quarters, to the edge of the zero quarter


def test_an_output_that_cannot_be_a_folder_fails_before_any_work(cli, tmp_path, photo, monkeypatch):
    """-o naming a file (or a path under one) fails at once (before: after the geometry, albedo and mesh)."""
    import usdrelight.stage.build as build_module

    def no_work(*a, **k):
        raise AssertionError("work started")

    monkeypatch.setattr(build_module, "estimate_geometry", no_work)
    (tmp_path / "afile").write_text("x")
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        rc, _, err = cli("build", photo, "-o", out)
        assert "exists and is not a folder" in _one_error(rc, err)
    assert (tmp_path / "afile").read_text() == "x"


def test_a_lights_layer_that_is_not_usd_fails_before_any_work(cli, tmp_path, photo):
    """The folder's lights_user.usda is the user's and is kept; one that is not USD would make the published
    stage fail to open (before: build exited 0 with USD's multi-line warning, and every later command failed)."""
    out = tmp_path / "u"
    out.mkdir()
    (out / "lights_user.usda").write_text("my notes")
    rc, _, err = cli("build", photo, "-o", out)
    assert "lights_user.usda is not a USD layer" in _one_error(rc, err)
    assert (out / "lights_user.usda").read_text() == "my notes" and not (out / "scene.usda").exists()


def test_a_depth_of_1e_30_is_invalid_not_a_stage_nothing_renders(cli, tmp_path, photo):
    """Depths below a micrometre underflowed float32 (a stage with a 5e-31 clipping range that fit refused and
    render drew black), with numpy's divide-by-zero warning on stderr; now they are invalid pixels."""
    np.save(tmp_path / "tiny.npy", np.full((24, 32), 1e-30, np.float32))
    rc, _, err = cli("build", photo, "--depth", tmp_path / "tiny.npy", "--fov-x", "60", "-o", tmp_path / "a")
    assert "no valid pixel" in _one_error(rc, err) and "RuntimeWarning" not in err
    np.save(tmp_path / "mm.npy", np.full((24, 32), 1e-3, np.float32))  # a millimetre away: a (macro) stage
    rc, _, err = cli("build", photo, "--depth", tmp_path / "mm.npy", "--fov-x", "60", "-o", tmp_path / "b")
    assert rc == 0 and "RuntimeWarning" not in err, err
    np.testing.assert_allclose(_mesh_depths(tmp_path / "b" / "scene.usda"), 1e-3, rtol=1e-5)


def test_a_damaged_png_is_one_line_not_libpngs_too(tmp_path, capfd):
    """libpng printed 'libpng error: IDAT: Read error' lines of its own before ours (capfd: the process's real
    stderr, where a C library writes)."""
    from usdrelight.cli import main

    img = np.random.default_rng(3).integers(0, 256, (40, 50, 3), dtype=np.uint8)
    _write_uint8(tmp_path / "full.png", img)
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[:len(data) * 2 // 3])
    capfd.readouterr()
    rc = main(["build", str(tmp_path / "cut.png"), "-o", str(tmp_path / "out")])
    err = capfd.readouterr().err
    lines = [l for l in err.splitlines() if l.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("usdrelight: error: "), err
