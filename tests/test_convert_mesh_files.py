"""USD <-> glTF binary / PLY / OBJ through trimesh: the photo mesh survives the round trip."""
from __future__ import annotations

import numpy as np
import pytest

from usdrelight.imageio import linear_to_srgb, read_map, read_photo
from usdrelight.stage.read import read_scene
from usdrelight.stage.records import TextureRecord
from usdrelight.stage.validate import open_stage

from conftest import build_procedural


@pytest.fixture(scope="module")
def small_stage(tmp_path_factory):
    out = tmp_path_factory.mktemp("mesh") / "st"
    scene = build_procedural(out, stride=4)
    return scene


def test_glb_round_trip_keeps_geometry_uvs_and_albedo(cli, small_stage, tmp_path):
    rc, out, err = cli("convert", small_stage, tmp_path / "m.glb", "--json")
    assert rc == 0, err
    assert cli("convert", tmp_path / "m.glb", tmp_path / "back.usda")[0] == 0
    a = read_scene(open_stage(small_stage)).meshes[0]
    b = read_scene(open_stage(tmp_path / "back.usda")).meshes[0]
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_allclose(a.points, b.points, atol=1e-6)
    np.testing.assert_allclose(a.uv, b.uv, atol=1e-6)
    np.testing.assert_allclose(a.normals, b.normals, atol=1e-3)
    assert b.material.is_lambertian
    # the albedo texture comes back as an sRGB PNG, equal to the EXR up to 8-bit quantisation
    assert isinstance(a.material.diffuse, TextureRecord) and isinstance(b.material.diffuse, TextureRecord)
    assert not b.material.diffuse.linear
    src = linear_to_srgb(np.clip(read_map(a.material.diffuse.path, 3), 0, 1))
    back = linear_to_srgb(read_photo(b.material.diffuse.path))
    assert src.shape == back.shape and np.abs(src - back).max() <= 0.5 / 255 + 1e-4


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_ply_and_obj_keep_the_geometry(cli, small_stage, tmp_path, suffix):
    rc, _, err = cli("convert", small_stage, tmp_path / f"m{suffix}")
    assert rc == 0, err
    assert cli("convert", tmp_path / f"m{suffix}", tmp_path / "back.usda")[0] == 0
    a = read_scene(open_stage(small_stage)).meshes[0]
    b = read_scene(open_stage(tmp_path / "back.usda")).meshes[0]
    assert len(b.faces) == len(a.faces)
    # the same triangles in world space (OBJ may reorder vertices: compare triangle corner positions)
    np.testing.assert_allclose(np.sort(a.points[a.faces].reshape(-1, 9), 0),
                               np.sort(b.points[b.faces].reshape(-1, 9), 0), atol=1e-5)


def test_a_stage_without_meshes_is_a_clear_error(cli, tmp_path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(tmp_path / "empty.usda"))
    UsdGeom.Xform.Define(stage, "/World")
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "empty.usda", tmp_path / "m.glb")
    assert rc == 2 and "no mesh" in err and not (tmp_path / "m.glb").exists()
