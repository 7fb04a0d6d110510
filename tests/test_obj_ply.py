"""USD -> OBJ / PLY keeps the authored normals and UVs (trimesh's export recomputed the normals, left OBJ's vt out
and packed two meshes' UVs into an atlas); OBJ / PLY -> USD names what is missing instead of making it up (a
missing MTL, trimesh's 2x2 grey placeholder texture for UVs without a material, a file with no mesh)."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from converters.obj_ply import obj_bytes, ply_bytes
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

TWO = """#usda 1.0
(
    defaultPrim = "World"
    metersPerUnit = 1
    upAxis = "Y"
)
def Xform "World"
{
    def Mesh "tilted"
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-1, 0, 1), (1, 0, 1), (1, 0, -1), (-1, 0, -1)]
        normal3f[] normals = [(0, 0.8, 0.6), (0, 0.8, 0.6), (0, 0.8, -0.6), (0, 0.8, -0.6)] (interpolation = "vertex")
        texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1), (0, 1)] (interpolation = "vertex")
        uniform token subdivisionScheme = "none"
    }
    def Mesh "up"
    {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0, 1, 0), (1, 1, 0), (0, 1, -1)]
        normal3f[] normals = [(0, 1, 0), (0, 1, 0), (0, 1, 0)] (interpolation = "vertex")
        texCoord2f[] primvars:st = [(0.25, 0.5), (0.75, 0.5), (0.25, 1)] (interpolation = "vertex")
        uniform token subdivisionScheme = "none"
    }
}
"""


def _meshes(path):
    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh):
            m = UsdGeom.Mesh(prim)
            st = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
            out[prim.GetName()] = (np.asarray(m.GetPointsAttr().Get()), np.asarray(m.GetNormalsAttr().Get()),
                                   np.asarray(st.Get()) if st and st.HasValue() else None)
    return out


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_normals_and_uvs_survive_a_round_trip(suffix, tmp_path, cli):
    (tmp_path / "two.usda").write_text(TWO)
    rc, _, err = cli("convert", tmp_path / "two.usda", tmp_path / f"two{suffix}")
    assert rc == 0, err
    rc, _, err = cli("convert", tmp_path / f"two{suffix}", tmp_path / "back.usda")
    assert rc == 0, err
    got = _meshes(tmp_path / "back.usda")
    points = np.concatenate([p for p, _, _ in got.values()])
    normals = np.concatenate([n for _, n, _ in got.values()])
    uvs = np.concatenate([t for _, _, t in got.values()])
    # each source vertex, found by its position, has its own authored normal and st
    want = {(-1, 0, 1): ((0, .8, .6), (0, 0)), (1, 0, -1): ((0, .8, -.6), (1, 1)), (1, 1, 0): ((0, 1, 0), (.75, .5))}
    for p, (n, st) in want.items():
        i = int(np.argmin(np.linalg.norm(points - np.array(p), axis=1)))
        np.testing.assert_allclose(normals[i], n, atol=1e-6)
        np.testing.assert_allclose(uvs[i], st, atol=1e-6)


def test_the_writers_bytes(tmp_path):
    (tmp_path / "two.usda").write_text(TWO)
    rec = read_scene(open_stage(tmp_path / "two.usda"))
    text = obj_bytes(rec.meshes, np.eye(3)).decode()
    assert text.count("\nvt ") == 7 and text.count("\nvn ") == 7 and text.count("\nf ") == 3
    assert "f 5/5/5 6/6/6 7/7/7" in text  # the second mesh's triangle, absolute 1-based indices
    data = ply_bytes(rec.meshes, np.eye(3))
    head, body = data.split(b"end_header\n")
    assert b"element vertex 7" in head and b"property float s" in head and b"element face 3" in head
    assert len(body) == 7 * 8 * 4 + 3 * 13


def test_what_a_mesh_file_lacks_is_named_not_made_up(tmp_path, cli):
    (tmp_path / "uv.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n")
    rc, _, err = cli("convert", tmp_path / "uv.obj", tmp_path / "uv.usda")
    assert rc == 0 and "mesh with UVs and no material" in err, err
    assert not (tmp_path / "textures").exists()  # before: an invented 2x2 grey texture, albedo 0.13
    (tmp_path / "gone.obj").write_text("mtllib missing.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    rc, _, err = cli("convert", tmp_path / "gone.obj", tmp_path / "gone.usda")
    assert rc == 0 and "OBJ mtllib 'missing.mtl' not found" in err, err
    (tmp_path / "my scene.mtl").write_text("newmtl red\nKd 0.8 0.1 0.1\n")  # Blender writes such names unquoted
    (tmp_path / "spaced.obj").write_text("mtllib my scene.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    rc, _, err = cli("convert", tmp_path / "spaced.obj", tmp_path / "spaced.usda")
    assert rc == 0 and "not found" not in err, err
    (tmp_path / "sub").mkdir()  # a library outside the OBJ's folder: trimesh does not read it (was: no word)
    (tmp_path / "sub" / "up.obj").write_text("mtllib ../my scene.mtl\nusemtl red\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"
                                             "f 1 2 3\n")
    rc, _, err = cli("convert", tmp_path / "sub" / "up.obj", tmp_path / "up.usda")
    assert rc == 0 and "OBJ mtllib '../my scene.mtl' not found in the file's folder" in err, err
    for body in ("", "SECRET TEXT\n"):
        (tmp_path / "none.obj").write_text(body)
        rc, _, err = cli("convert", tmp_path / "none.obj", tmp_path / "none.usda")
        assert rc == 2 and "no mesh in the file" in err and "SECRET" not in err, err
        assert not (tmp_path / "none.usda").exists()
