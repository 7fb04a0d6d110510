"""A glTF binary's content beyond trimesh's meshes, read from its own JSON (files written by hand here, as glTF
2.0 lays them out): KHR_materials_emissive_strength applied (a Blender export of a 10x emitter came out 10x too
dark), doubleSided carried, a mirroring node's winding kept, and animations and other extensions named in
warnings instead of dropped in silence (lights and cameras: tests/test_gltf_lights.py)."""
from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdShade


def _glb(path, doc: dict, binary: bytes) -> None:
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = 12 + 8 + len(js) + 8 + len(binary)
    path.write_bytes(struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
                     + struct.pack("<II", len(binary), 0x004E4942) + binary)


def _triangle_doc(**extra) -> tuple[dict, bytes]:
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 0, -1]], np.float32)  # counter-clockwise seen from +Y
    idx = np.array([0, 1, 2], np.uint16)
    binary = pts.tobytes() + idx.tobytes()
    doc = {
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0, 1]}],
        "nodes": [{"mesh": 0, "name": "plain"}, {"mesh": 0, "name": "mirrored", "scale": [-1, 1, 1],
                                                 "translation": [3, 0, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "material": 0}]}],
        "materials": [{"name": "Glow", "doubleSided": True, "emissiveFactor": [1.0, 0.5, 0.25],
                       "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 10.0}}}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                        {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, -1], "max": [1, 0, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
        "extensionsUsed": ["KHR_materials_emissive_strength"],
    }
    for k, v in extra.items():
        doc[k] = v
    return doc, binary


def test_emission_strength_two_sides_and_a_mirrored_node(tmp_path, cli):
    doc, binary = _triangle_doc()
    _glb(tmp_path / "t.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "t.glb", tmp_path / "t.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "t.usda"))
    meshes = {p.GetName(): UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)}
    assert set(meshes) == {"plain", "mirrored"}
    for name, mesh in meshes.items():
        assert mesh.GetDoubleSidedAttr().Get() is True
        p = np.array(mesh.GetPointsAttr().Get())
        f = np.array(mesh.GetFaceVertexIndicesAttr().Get())
        winding = np.cross(p[f[1]] - p[f[0]], p[f[2]] - p[f[0]])
        assert winding[1] > 0, name  # before: the mirrored copy's front face pointed down
        mat, _ = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()
        surf = mat.ComputeSurfaceSource()[0]
        np.testing.assert_allclose(surf.GetInput("emissiveColor").Get(), [10.0, 5.0, 2.5], rtol=1e-6)


def test_what_usd_does_not_get_is_named(tmp_path, cli):
    doc, binary = _triangle_doc(
        extensions={"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 1000.0}]}},
        cameras=[{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.1}}],
        animations=[{"channels": [], "samplers": []}],
        extensionsUsed=["KHR_materials_emissive_strength", "KHR_lights_punctual", "KHR_texture_transform"])
    doc["nodes"].append({"camera": 0, "name": "cam"})
    doc["scenes"][0]["nodes"].append(2)
    _glb(tmp_path / "t.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "t.glb", tmp_path / "t.usda")
    assert rc == 0, err
    assert "glTF animations (not converted: the meshes at rest): 1" in err, err
    assert "emissive_strength" not in err and "KHR_lights_punctual" not in err  # applied, not warned
    assert "KHR_texture_transform" not in err  # applied to a base colour texture (none here), not warned
    stage = Usd.Stage.Open(str(tmp_path / "t.usda"))
    assert stage.GetPrimAtPath("/World/cam").IsA(UsdGeom.Camera)  # converted (tests/test_gltf_lights.py)


@pytest.mark.parametrize("strength", [-2.0, float("nan")])
def test_a_negative_or_nan_strength_is_not_applied(strength, tmp_path, cli):
    """A negative one made trimesh's emissiveFactor setter raise (exit 1); JSON's NaN went into the stage."""
    doc, binary = _triangle_doc()
    doc["materials"][0]["extensions"]["KHR_materials_emissive_strength"]["emissiveStrength"] = strength
    _glb(tmp_path / "t.glb", doc, binary)
    rc, _, err = cli("convert", tmp_path / "t.glb", tmp_path / "t.usda")
    assert rc == 0, err
    stage = Usd.Stage.Open(str(tmp_path / "t.usda"))
    mesh = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    surf = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
    np.testing.assert_allclose(surf.GetInput("emissiveColor").Get(), [1.0, 0.5, 0.25], rtol=1e-6)
