"""glTF files written by hand as other tools write them (a probe found them misread in silence): sparse accessors,
8-bit base colours, a second texture coordinate set, float vertex colours."""
from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from usdrelight.converters.convert import convert
from usdrelight.stage.read import read_scene

QUAD = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], np.float32)
FACES = np.array([0, 1, 2, 0, 2, 3], np.uint16)


def _gltf(path, material: dict, extra_attributes: dict | None = None, sparse: bool = False):
    """A quad (POSITION, indices, optional float COLOR_0 / TEXCOORD_0) with ``material``, buffers as data URIs."""
    blobs = [QUAD.tobytes(), FACES.tobytes()]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0],
                  "max": [1, 0, 1]},
                 {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]
    attributes = {"POSITION": 0}
    for name, (values, kind) in (extra_attributes or {}).items():
        blobs.append(np.asarray(values, np.float32).tobytes())
        accessors.append({"bufferView": len(blobs) - 1, "componentType": 5126, "count": len(values), "type": kind})
        attributes[name] = len(accessors) - 1
    if sparse:  # vertex 2 moved to (1, 1, 1)
        blobs += [np.array([2], np.uint16).tobytes(), np.array([1, 1, 1], np.float32).tobytes()]
        accessors[0]["sparse"] = {"count": 1, "indices": {"bufferView": len(blobs) - 2, "componentType": 5123},
                                  "values": {"bufferView": len(blobs) - 1}}
    offsets = np.cumsum([0] + [len(b) for b in blobs])
    data = b"".join(blobs)
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": attributes, "indices": 1, "material": 0}]}],
           "materials": [material], "accessors": accessors,
           "bufferViews": [{"buffer": 0, "byteOffset": int(o), "byteLength": len(b)} for o, b in zip(offsets, blobs)],
           "buffers": [{"byteLength": len(data),
                        "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}]}
    path.write_text(json.dumps(doc))
    return path


def test_sparse_accessors_are_refused_not_misread(cli, tmp_path):
    """trimesh ignores sparse substitutions: vertex 2 came out at (1, 0, 1), not (1, 1, 1), exit 0."""
    _gltf(tmp_path / "s.gltf", {"name": "M"}, sparse=True)
    rc, _, err = cli("convert", tmp_path / "s.gltf", tmp_path / "s.usda")
    assert rc == 2 and "sparse accessors" in err and not (tmp_path / "s.usda").exists(), err


def test_a_dark_base_colour_keeps_its_value(tmp_path):
    """baseColorFactor 0.003: read through trimesh's 8 bits as 0.0039 (+31%)."""
    _gltf(tmp_path / "d.gltf", {"name": "Dark", "pbrMetallicRoughness": {"baseColorFactor": [0.003, 0.01, 0.1, 1],
                                                                         "metallicFactor": 0}})
    convert(tmp_path / "d.gltf", tmp_path / "d.usda")
    (mesh,) = read_scene(tmp_path / "d.usda").meshes
    np.testing.assert_allclose(mesh.material.diffuse, [0.003, 0.01, 0.1], rtol=1e-6)


def test_a_second_uv_set_and_float_vertex_colours_are_warned(tmp_path):
    uv = [[0, 0], [1, 0], [1, 1], [0, 1]]
    _gltf(tmp_path / "t.gltf", {"name": "T", "pbrMetallicRoughness": {"metallicFactor": 0,
                                                                      "baseColorTexture": {"index": 0, "texCoord": 1}}},
          {"TEXCOORD_0": (uv, "VEC2"), "TEXCOORD_1": (uv, "VEC2"), "COLOR_0": ([[0.5, 0.25, 0.002]] * 4, "VEC3")})
    doc = json.loads((tmp_path / "t.gltf").read_text())
    png = base64.b64encode(bytes.fromhex("89504e470d0a1a0a0000000d4948445200000001000000010806000000"
                                         "1f15c4890000000d49444154789c6360f8cfc0f01f0005000201e2c7d6"
                                         "9c0000000049454e44ae426082")).decode()
    doc.update(images=[{"uri": "data:image/png;base64," + png}], textures=[{"source": 0}])
    (tmp_path / "t.gltf").write_text(json.dumps(doc))
    warnings = convert(tmp_path / "t.gltf", tmp_path / "t.usda").read_warnings
    assert warnings.get("glTF texture of texCoord 1 or above (TEXCOORD_0 used)") == 1, warnings
    assert warnings.get("glTF COLOR_0 of floats (read through 8 bits: within 0.002)") == 1, warnings


def test_gprims_go_to_mesh_files_as_meshes(tmp_path):
    """A Mitsuba scene's sphere and cube are Sphere / Cube gprims in USD: a .glb left them out ('gprims in a .glb
    file (not exported)'), so they vanished. Now tessellated as Blender gets them (a sphere: an icosphere)."""
    (tmp_path / "s.usda").write_text('''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Sphere "Ball" {
    double radius = 0.5
    double3 xformOp:translate = (2, 0, 0)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Cube "Box" {
    double size = 1
}
''')
    for suffix in (".glb", ".obj"):
        report = convert(tmp_path / "s.usda", tmp_path / f"s{suffix}")
        assert not any("gprims" in w for w in report.write_warnings), report.write_warnings
        back = read_scene(convert(tmp_path / f"s{suffix}", tmp_path / f"back{suffix}.usda") and
                          tmp_path / f"back{suffix}.usda").meshes
        pts = np.concatenate([m.points for m in back])
        ball = pts[pts[:, 0] > 1.0]
        np.testing.assert_allclose(np.linalg.norm(ball - [2, 0, 0], axis=1), 0.5, rtol=1e-5)
        box = pts[pts[:, 0] < 1.0]
        np.testing.assert_allclose(np.abs(box).max(0), [0.5, 0.5, 0.5], rtol=1e-6)
