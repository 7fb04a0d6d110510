"""glTF as JSON (``.gltf``, Blender's "glTF Separate": the JSON, a .bin and PNG textures beside it), read and
written. Before: "no converter for '.gltf' files". Its URIs are percent-decoded (glTF URIs are RFC 3986: Blender
writes a space as %20), read only inside the file's folder or an --allow-path one, and a missing image is warned
(trimesh dropped it in silence)."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade

from test_gltf_extras import _glb
from usdrelight.imageio import read_map, write_image

TEXTURE = np.zeros((4, 4, 3), np.float32)
TEXTURE[:, :2] = (0.8, 0.2, 0.1)
TEXTURE[:, 2:] = (0.1, 0.3, 0.9)


def _textured_quad(image: dict) -> tuple[dict, bytes]:
    """A 2 x 2 m quad facing +Y with UVs over the whole texture, its material's base colour the ``image``."""
    pts = np.array([[0, 0, 0], [2, 0, 0], [2, 0, -2], [0, 0, -2]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    binary = pts.tobytes() + uv.tobytes() + idx.tobytes()
    doc = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "quad", "translation": [1, 0, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"name": "Paint", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                                                 "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "textures": [{"source": 0}], "images": [image],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48}, {"buffer": 0, "byteOffset": 48,
                                                                            "byteLength": 32},
                        {"buffer": 0, "byteOffset": 80, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, -2],
                       "max": [2, 0, 0]},
                      {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
                      {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}],
    }
    return doc, binary


def _separate(folder, bin_name="my mesh.bin", png_name="tex a.png", quote=True) -> None:
    """The quad as Blender's glTF Separate writes it: JSON, .bin and PNG, names with spaces percent-encoded."""
    folder.mkdir(parents=True, exist_ok=True)
    enc = (lambda n: n.replace(" ", "%20")) if quote else (lambda n: n)
    doc, binary = _textured_quad({"uri": enc(png_name), "mimeType": "image/png"})
    doc["buffers"][0]["uri"] = enc(bin_name)
    (folder / "q.gltf").write_text(json.dumps(doc))
    if not bin_name.startswith(("/", "http")) and ".." not in bin_name:
        (folder / bin_name).write_bytes(binary)
    write_image(folder / png_name, TEXTURE, "uint8")


def _mesh_and_texture(usda):
    stage = Usd.Stage.Open(str(usda))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    points = np.array(mesh.GetPointsAttr().Get())
    surf = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
    source = surf.GetInput("diffuseColor").GetConnectedSources()[0]
    texture = None
    if source:
        tex = UsdShade.Shader(source[0].source.GetPrim())
        texture = read_map(str(usda.parent / tex.GetInput("file").Get().path), 3)
    return points, texture


def test_a_separate_gltf_reads_as_its_glb_does(tmp_path, cli):
    _separate(tmp_path / "sep")
    doc, binary = _textured_quad({"bufferView": 3, "mimeType": "image/png"})
    png = (tmp_path / "sep" / "tex a.png").read_bytes()
    doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary) + (-len(binary) % 4), "byteLength": len(png)})
    binary += b"\0" * (-len(binary) % 4) + png
    doc["buffers"][0]["byteLength"] = len(binary)
    _glb(tmp_path / "q.glb", doc, binary)
    out = {}
    for name, src in (("gltf", tmp_path / "sep" / "q.gltf"), ("glb", tmp_path / "q.glb")):
        rc, _, err = cli("convert", src, tmp_path / name / "q.usda")
        assert rc == 0 and "WARNING" not in err, err
        out[name] = _mesh_and_texture(tmp_path / name / "q.usda")
    np.testing.assert_allclose(out["gltf"][0], out["glb"][0])
    np.testing.assert_allclose(out["gltf"][0].min(0), [1, 0, -2])  # the node's translation applied
    np.testing.assert_allclose(out["gltf"][1], out["glb"][1])
    np.testing.assert_allclose(out["gltf"][1], TEXTURE, atol=1 / 255)  # the texture as written, not white


def test_a_usd_stage_round_trips_through_one_self_contained_gltf(tmp_path, cli):
    _separate(tmp_path / "sep")
    assert cli("convert", tmp_path / "sep" / "q.gltf", tmp_path / "a" / "q.usda")[0] == 0
    rc, _, err = cli("convert", tmp_path / "a" / "q.usda", tmp_path / "g" / "q.gltf")
    assert rc == 0, err
    assert [p.name for p in (tmp_path / "g").iterdir()] == ["q.gltf"]  # buffers and texture embedded
    assert all(b["uri"].startswith("data:") for b in json.loads((tmp_path / "g" / "q.gltf").read_text())["buffers"])
    shutil.move(tmp_path / "g" / "q.gltf", tmp_path / "moved.gltf")  # nothing beside it is needed
    assert cli("convert", tmp_path / "moved.gltf", tmp_path / "b" / "q.usda")[0] == 0
    (pa, ta), (pb, tb) = _mesh_and_texture(tmp_path / "a" / "q.usda"), _mesh_and_texture(tmp_path / "b" / "q.usda")
    np.testing.assert_allclose(np.sort(pb, 0), np.sort(pa, 0), atol=1e-6)
    np.testing.assert_allclose(tb, ta, atol=1 / 255)


@pytest.mark.parametrize("bin_name, needle", [
    ("../outside.bin", "is outside the scene's folder"),
    ("http://example.com/q.bin", "is not a file beside it"),
    ("/etc/hostname", "is not a file beside it"),
    ("missing.bin", "buffer missing.bin not found beside it"),
])
def test_a_buffer_outside_the_folder_or_missing_is_one_error(bin_name, needle, tmp_path, cli):
    _separate(tmp_path / "sep", bin_name=bin_name)
    if bin_name == "missing.bin":
        (tmp_path / "sep" / "missing.bin").unlink()
    if bin_name.startswith(".."):
        (tmp_path / "outside.bin").write_bytes((tmp_path / "sep" / "q.gltf").read_bytes()[:0] + b"\0" * 92)
    rc, _, err = cli("convert", tmp_path / "sep" / "q.gltf", tmp_path / "o" / "q.usda")
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_an_allowed_folder_is_read_and_a_missing_image_is_warned(tmp_path, cli):
    _separate(tmp_path / "sep")
    shutil.move(tmp_path / "sep" / "my mesh.bin", tmp_path / "shared.bin")
    doc = json.loads((tmp_path / "sep" / "q.gltf").read_text())
    doc["buffers"][0]["uri"] = "../shared.bin"
    (tmp_path / "sep" / "q.gltf").write_text(json.dumps(doc))
    rc, _, err = cli("convert", tmp_path / "sep" / "q.gltf", tmp_path / "o" / "q.usda", "--allow-path", tmp_path)
    assert rc == 0, err
    (tmp_path / "sep" / "tex a.png").unlink()
    rc, _, err = cli("convert", tmp_path / "sep" / "q.gltf", tmp_path / "o2" / "q.usda", "--allow-path", tmp_path)
    assert rc == 0 and "glTF image not found (its material untextured): tex a.png" in err, err
    points, texture = _mesh_and_texture(tmp_path / "o2" / "q.usda")
    assert texture is None and len(points) == 4
