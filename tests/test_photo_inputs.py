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
