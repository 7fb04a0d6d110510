"""glTF and OBJ files as other tools write them (gltfpack, Sketchfab, three.js, scanners, Windows DCCs): each test
asserts what came out wrong before, from a probe: compressed or quantized geometry read as zeros or raw integers
(exit 0), smooth normals where glTF asks for flat, a 16-bit texture turned white, lost emissive strength and
double-sidedness on a round trip, silent OBJ textures, a node named Looks holding every material."""
from __future__ import annotations

import base64
import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pxr import Usd, UsdGeom

BOX = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)


def gltf(path: Path, *, uv: np.ndarray | None = None, uv_type: int = 5126, normals: bool = True, mode: int = 4,
         extensions: list | None = None, required: bool = False, version: str = "2.0", image: bytes | None = None, sampler: dict | None = None,
         node_name: str = "Quad") -> Path:
    """A one-quad .gltf with its buffer as a data URI: positions (+ normals, + TEXCOORD_0 of ``uv_type``)."""
    blobs, views, accessors = [], [], []

    def add(arr: np.ndarray, kind: str, ctype: int, normalized: bool = False, target: int | None = 34962):
        data = arr.tobytes()
        views.append({"buffer": 0, "byteOffset": sum(len(b) for b in blobs), "byteLength": len(data),
                      **({"target": target} if target else {})})
        blobs.append(data + b"\0" * (-len(data) % 4))
        acc = {"bufferView": len(views) - 1, "componentType": ctype, "count": len(arr), "type": kind}
        if normalized:
            acc["normalized"] = True
        if kind == "VEC3" and ctype == 5126:
            acc.update(min=arr.min(0).tolist(), max=arr.max(0).tolist())
        accessors.append(acc)
        return len(accessors) - 1

    attrs = {"POSITION": add(BOX, "VEC3", 5126)}
    if normals:
        attrs["NORMAL"] = add(np.tile(np.float32([0, 0, 1]), (4, 1)), "VEC3", 5126)
    if uv is not None:
        attrs["TEXCOORD_0"] = add(uv, "VEC2", uv_type, normalized=uv_type != 5126)
    prim = {"attributes": attrs, "indices": add(np.uint16([0, 1, 2, 0, 2, 3]), "SCALAR", 5123, target=34963),
            "mode": mode}
    doc = {"asset": {"version": version}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0, "name": node_name}], "meshes": [{"primitives": [prim]}], "accessors": accessors,
           "bufferViews": views}
    if image is not None:
        doc.update(images=[{"uri": "data:image/png;base64," + base64.b64encode(image).decode()}],
                   samplers=[sampler or {}], textures=[{"source": 0, "sampler": 0}],
                   materials=[{"name": "M", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}])
        prim["material"] = 0
    if extensions:
        doc["extensionsUsed"] = extensions
        if required:  # the file cannot be read without them (no uncompressed fallback)
            doc["extensionsRequired"] = extensions
    buf = b"".join(blobs)
    doc["buffers"] = [{"byteLength": len(buf), "uri": "data:application/octet-stream;base64," +
                       base64.b64encode(buf).decode()}]
    path.write_text(json.dumps(doc))
    return path


UV = np.float32([[0, 0], [1, 0], [1, 1], [0, 1]])


@pytest.mark.parametrize("kw, says", [
    (dict(extensions=["KHR_draco_mesh_compression"], required=True), "KHR_draco_mesh_compression compressed"),
    (dict(extensions=["EXT_meshopt_compression"], required=True), "EXT_meshopt_compression compressed geometry"),
    (dict(uv=(UV * 65535).astype(np.uint16), uv_type=5123), "TEXCOORD_0 stored as normalized integers"),
    (dict(version="1.0"), "a glTF 1.0 file")])
def test_geometry_the_reader_would_get_wrong_is_one_clear_error(tmp_path, cli, kw, says):
    """Draco: every vertex at the origin, exit 0; normalized uint16 UVs: st up to 65535."""
    rc, _, err = cli("convert", gltf(tmp_path / "f.gltf", **kw), tmp_path / "f.usda")
    assert rc == 2 and says in err and err.count("\n") == 1, err
    assert not (tmp_path / "f.usda").exists()


def test_compression_only_used_reads_its_fallback(tmp_path, cli):
    """Draco named in extensionsUsed alone: the file holds uncompressed geometry, which is read."""
    rc, _, err = cli("convert", gltf(tmp_path / "f.gltf", extensions=["KHR_draco_mesh_compression"]),
                     tmp_path / "f.usda")
    assert rc == 0 and "KHR_draco_mesh_compression (not converted)" in err, err


def test_a_file_without_normals_is_flat_and_fans_are_named(tmp_path, cli):
    rc, _, err = cli("convert", gltf(tmp_path / "f.gltf", normals=False), tmp_path / "f.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "f.usda"))  # held: its prims live as long as it does
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Quad"))
    assert not mesh.GetNormalsAttr().HasAuthoredValue()  # glTF 3.7.2.1: flat normals, which renderers compute
    rc, _, err = cli("convert", gltf(tmp_path / "fan.gltf", mode=6), tmp_path / "fan.usda")
    assert rc == 2 and "triangle fans are not read" in err
    doc = json.loads(gltf(tmp_path / "m.gltf").read_text())
    doc["meshes"][0]["primitives"][0]["targets"] = [{"POSITION": 0}]  # a morph target (the base positions)
    (tmp_path / "m.gltf").write_text(json.dumps(doc))
    rc, _, err = cli("convert", tmp_path / "m.gltf", tmp_path / "m.usda")
    assert rc == 0 and "glTF morph targets (the base shape" in err, err


def test_a_16_bit_texture_keeps_its_values_and_a_clamping_sampler_is_warned(tmp_path, cli):
    png = io.BytesIO()
    Image.fromarray(np.full((4, 4), 32768, np.uint16)).save(png, format="PNG")  # a 16-bit grey PNG: 0.5
    src = gltf(tmp_path / "f.gltf", uv=UV, image=png.getvalue(), sampler={"wrapS": 33071, "wrapT": 33071})
    rc, _, err = cli("convert", src, tmp_path / "f.usda")
    assert rc == 0 and "sampler clamping or mirroring" in err
    (tex,) = (tmp_path / "textures").iterdir()
    assert np.asarray(Image.open(tex)).mean() == pytest.approx(128, abs=1)  # was 255: PIL clipped it


def test_emissive_strength_and_double_sided_survive_usd_gltf_usd(tmp_path, cli):
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    metersPerUnit = 1
    upAxis = "Y"
)
def Mesh "Lamp" (
    prepend apiSchemas = ["MaterialBindingAPI"]
) {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    uniform bool doubleSided = 1
    rel material:binding = </Glow>
}
def Material "Glow" {
    token outputs:surface.connect = </Glow/S.outputs:surface>
    def Shader "S" {
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:emissiveColor = (3, 1.5, 0)
        token outputs:surface
    }
}
''')
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.gltf")
    assert rc == 0 and "emissiveColor" not in err, err
    (mat,) = json.loads((tmp_path / "s.gltf").read_text())["materials"]
    assert mat["doubleSided"] is True and mat["emissiveFactor"] == pytest.approx([1, 0.5, 0])
    assert mat["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] == pytest.approx(3.0)
    assert cli("convert", tmp_path / "s.gltf", tmp_path / "back.usda")[0] == 0
    from usdrelight.stage.read import read_scene

    (mesh,) = read_scene(tmp_path / "back.usda").meshes
    assert mesh.material.emissive == pytest.approx((3, 1.5, 0)) and mesh.double_sided


def test_obj_textures_it_cannot_read_are_named_and_a_node_called_looks_keeps_its_materials_apart(tmp_path, cli):
    (tmp_path / "tex").mkdir()
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(tmp_path / "tex" / "wood.png")
    (tmp_path / "m.mtl").write_text("newmtl Wood\nKd 1 1 1\nmap_Kd tex\\wood.png\n")
    (tmp_path / "m.obj").write_text("mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nusemtl Wood\n"
                                    "f 1/1 2/2 3/3\n")
    rc, _, err = cli("convert", tmp_path / "m.obj", tmp_path / "m.usda")
    assert rc == 0 and "map_Kd 'tex\\wood.png' not found (a Windows path: write it with /)" in err, err
    png = io.BytesIO()
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(png, format="PNG")
    rc, _, err = cli("convert", gltf(tmp_path / "l.gltf", uv=UV, image=png.getvalue(), node_name="Looks"),
                     tmp_path / "l.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "l.usda"))
    assert stage.GetPrimAtPath("/World/Looks_mesh").IsA(UsdGeom.Mesh)
    assert not stage.GetPrimAtPath("/World/Looks").IsA(UsdGeom.Mesh)  # the materials' scope, not a mesh


def test_a_texture_transform_becomes_a_usd_transform2d_that_reads_the_same_texels(tmp_path, cli):
    """KHR_texture_transform (tiling, offset, rotation: Sketchfab and three.js files) was warned and dropped."""
    from usdrelight.stage.read import read_scene

    png = io.BytesIO()
    Image.fromarray(np.full((2, 2, 3), 200, np.uint8)).save(png, format="PNG")
    src = gltf(tmp_path / "t.gltf", uv=UV, image=png.getvalue())
    doc = json.loads(src.read_text())
    r, (sx, sy), (ox, oy) = 0.3, (2.0, 0.5), (0.1, 0.2)
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["extensions"] = {
        "KHR_texture_transform": {"offset": [ox, oy], "rotation": r, "scale": [sx, sy]}}
    doc["extensionsUsed"] = ["KHR_texture_transform"]
    src.write_text(json.dumps(doc))
    rc, _, err = cli("convert", src, tmp_path / "t.usda")
    assert rc == 0 and "KHR_texture_transform" not in err, err
    (mesh,) = read_scene(tmp_path / "t.usda").meshes
    m = mesh.material.diffuse.st_matrix()
    st_looked = mesh.uv @ m[:2, :2].T + m[:2, 2]
    # glTF: uv' = T R(r) S uv with v down; USD st = (u, 1 - v) of the same texel
    uv = np.stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]], 1)
    rot = np.array([[np.cos(r), np.sin(r)], [-np.sin(r), np.cos(r)]])  # the extension's matrix (its spec)
    uv_looked = uv @ (rot @ np.diag([sx, sy])).T + [ox, oy]
    np.testing.assert_allclose(st_looked, np.stack([uv_looked[:, 0], 1.0 - uv_looked[:, 1]], 1), atol=1e-6)
    # the spec's example: offset (0, 1), rotation pi/2, scale 0.5 reads the image's lower-left quadrant
    doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["extensions"]["KHR_texture_transform"] = {
        "offset": [0, 1], "rotation": np.pi / 2, "scale": [0.5, 0.5]}
    src.write_text(json.dumps(doc))
    assert cli("convert", src, tmp_path / "e.usda")[0] == 0
    (mesh,) = read_scene(tmp_path / "e.usda").meshes
    m = mesh.material.diffuse.st_matrix()
    centre = m[:2, :2] @ [0.5, 0.5] + m[:2, 2]  # st; the image's lower-left quadrant is s < 0.5, t < 0.5
    np.testing.assert_allclose(centre, [0.25, 0.25], atol=1e-6)
    doc["materials"].append({"name": "M"})  # a second material of the same name, without a transform
    src.write_text(json.dumps(doc))
    rc, _, err = cli("convert", src, tmp_path / "c.usda")
    assert rc == 0 and "KHR_texture_transform on an unnamed or same-named material (not applied)" in err, err


def test_alpha_mask_and_blend_become_opacity(tmp_path, cli):
    """glTF alphaMode MASK (foliage cards) and BLEND were warned and rendered opaque."""
    from usdrelight.stage.read import read_scene

    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[..., :3], rgba[:, 1, 3] = 200, 255  # the left column transparent
    png = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(png, format="PNG")
    src = gltf(tmp_path / "m.gltf", uv=UV, image=png.getvalue())
    doc = json.loads(src.read_text())
    doc["materials"][0].update(alphaMode="MASK", alphaCutoff=0.3)
    src.write_text(json.dumps(doc))
    rc, _, err = cli("convert", src, tmp_path / "m.usda")
    assert rc == 0 and "alphaMode" not in err, err
    mat = read_scene(tmp_path / "m.usda").meshes[0].material
    assert mat.opacity_threshold == pytest.approx(0.3) and mat.opacity.channel == "r" and mat.opacity.linear
    alpha = np.asarray(Image.open(mat.opacity.path))
    assert alpha.ndim == 2 and alpha[:, 0].max() == 0 and alpha[:, 1].min() == 255
    doc["materials"][0].pop("alphaCutoff")
    doc["materials"][0].update(alphaMode="BLEND", pbrMetallicRoughness={"baseColorFactor": [1, 1, 1, 0.4]})
    src.write_text(json.dumps(doc))
    assert cli("convert", src, tmp_path / "b.usda")[0] == 0
    mat = read_scene(tmp_path / "b.usda").meshes[0].material
    assert mat.opacity == pytest.approx(0.4) and mat.opacity_threshold == 0.0 and mat.ior == 1.0  # no glass pane
