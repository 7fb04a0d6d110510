"""Mesh files as other tools write and read them: Z-up centimetre stages written Y up in metres, OBJ/MTL
colours and textures, tinted / emissive / vertex-coloured glTF, UsdUVTexture scale and bias in a .glb."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from usdrelight.converters import mesh_files
from usdrelight.imageio import srgb_to_linear, write_image
from usdrelight.stage.create import author_uv_texture, create_stage, define_preview_material
from usdrelight.stage.read import read_scene
from usdrelight.stage.records import TextureRecord

# a 10 m x 10 m floor at z = 0 and a 2 m pole along +Z (centimetres, Z up)
FLOOR = [(-500, -500, 0), (500, -500, 0), (500, 500, 0), (-500, 500, 0)]
POLE = [(0, 0, 0), (10, 0, 0), (0, 0, 200)]
#: Z up -> Y up: (x, y, z) -> (x, z, -y)
TO_Y_UP = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])


def _mesh(stage, path, points, counts, st=None):
    from pxr import Sdf, UsdGeom

    m = UsdGeom.Mesh.Define(stage, path)
    m.CreateSubdivisionSchemeAttr("none")
    m.CreatePointsAttr(points)
    m.CreateFaceVertexCountsAttr(counts)
    m.CreateFaceVertexIndicesAttr(list(range(sum(counts))))
    if st is not None:
        UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, "vertex").Set(st)
    return m


def _zup_cm_stage():
    stage = create_stage(None, "/World", up_axis="Z", meters_per_unit=0.01)
    _mesh(stage, "/World/floor", FLOOR, [4])
    _mesh(stage, "/World/pole", POLE, [3])
    return stage


@pytest.mark.parametrize("suffix", [".glb", ".obj", ".ply"])
def test_a_z_up_centimetre_stage_is_written_y_up_in_metres(tmp_path, suffix):
    mesh_files.write_to_file(_zup_cm_stage(), tmp_path / f"m{suffix}")
    lo, hi = trimesh.load(tmp_path / f"m{suffix}", force="scene", process=False).bounds
    # the floor lies in y = 0, the pole stands 2 m up +Y; the floor's +Y (cm) edge is now at z = -5 m
    np.testing.assert_allclose(lo, [-5, 0, -5], atol=1e-6)
    np.testing.assert_allclose(hi, [5, 2, 5], atol=1e-6)


def test_z_up_cm_to_glb_and_back_gives_the_same_shapes_in_metres_y_up(tmp_path):
    src = read_scene(_zup_cm_stage())
    mesh_files.write_to_file(_zup_cm_stage(), tmp_path / "m.glb")
    back = read_scene(mesh_files.read_from_file(tmp_path / "m.glb").stage)
    assert back.up_axis == "Y" and back.meters_per_unit == 1.0
    by_name = {m.path.rsplit("/", 1)[1]: m for m in back.meshes}
    for m in src.meshes:
        b = by_name[m.path.strip("/").replace("/", "_")]
        np.testing.assert_allclose(b.points, m.points @ TO_Y_UP.T, atol=1e-5)
    floor = by_name["World_floor"].points
    assert np.ptp(floor[:, 1]) < 1e-6 and np.ptp(floor[:, 0]) == pytest.approx(10.0)  # horizontal again
    assert by_name["World_pole"].points[:, 1].max() == pytest.approx(2.0)


def _quad_obj(tmp_path, mtl: str):
    (tmp_path / "quad.mtl").write_text(mtl)
    (tmp_path / "quad.obj").write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\n"
                                       "vt 1 1\nvt 0 1\nusemtl m\nf 1/1 2/2 3/3 4/4\n")
    return tmp_path / "quad.obj"


def _tex_png(path):
    img = np.zeros((8, 8, 3), np.uint8)
    img[:, :4], img[:, 4:] = 255, 128
    Image.fromarray(img).save(path)
    return Image.fromarray(img)


def test_obj_kd_colour_and_kd_times_map_kd_reach_the_usd_material(tmp_path):
    _tex_png(tmp_path / "tex.png")
    obj = _quad_obj(tmp_path, "newmtl m\nKd 0.8 0.1 0.1\nmap_Kd tex.png\nKe 0.5 0.5 0\n")
    mat = read_scene(mesh_files.read_from_file(obj, usd_path=tmp_path / "a.usda").stage).meshes[0].material
    assert isinstance(mat.diffuse, TextureRecord)  # Kd multiplies the texture (MTL spec): scale = Kd
    np.testing.assert_allclose(mat.diffuse.scale, (0.8, 0.1, 0.1, 1.0), atol=1e-6)
    np.testing.assert_allclose(mat.emissive, (0.5, 0.5, 0.0), atol=1e-6)
    obj = _quad_obj(tmp_path, "newmtl m\nKd 0.1 0.7 0.1\nKs 0.5 0.5 0.5\nmap_Bump n.png\n")
    res = mesh_files.read_from_file(obj)
    np.testing.assert_allclose(read_scene(res.stage).meshes[0].material.diffuse, (0.1, 0.7, 0.1), atol=1e-6)
    assert res.warnings == {"OBJ specular Ks/Ns (a Lambertian surface used)": 1,
                            "OBJ material statement 'map_bump' (not converted)": 1}


def test_glb_base_colour_factor_multiplies_its_texture_and_emissive_is_kept(tmp_path):
    q = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    mat = trimesh.visual.material.PBRMaterial(baseColorFactor=[1.0, 0.2, 0.2, 1.0],
                                              baseColorTexture=_tex_png(tmp_path / "t.png"), metallicFactor=0.0,
                                              roughnessFactor=0.7, emissiveFactor=[1.0, 1.0, 0.0])
    q.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1], [0, 1]], material=mat)
    q.export(tmp_path / "tinted.glb")
    back = read_scene(mesh_files.read_from_file(tmp_path / "tinted.glb", usd_path=tmp_path / "t.usda").stage)
    m = back.meshes[0].material
    assert isinstance(m.diffuse, TextureRecord)
    np.testing.assert_allclose(m.diffuse.scale, (1.0, 0.2, 0.2, 1.0), atol=0.5 / 255)
    np.testing.assert_allclose(m.emissive, (1.0, 1.0, 0.0))
    # in memory: the texture's mean colour times the factor
    mem = read_scene(mesh_files.read_from_file(tmp_path / "tinted.glb").stage).meshes[0].material
    mean = (srgb_to_linear(1.0) + srgb_to_linear(128 / 255)) / 2
    np.testing.assert_allclose(mem.diffuse, np.array([1.0, 0.2, 0.2]) * mean, atol=2e-3)


@pytest.mark.parametrize("suffix, expect", [(".glb", 128 / 255), (".ply", float(srgb_to_linear(128 / 255)))])
def test_vertex_colours_become_display_color_and_the_diffuse_mean(tmp_path, suffix, expect):
    from pxr import UsdGeom

    cols = [[255, 0, 0, 255], [255, 0, 0, 255], [0, 0, 128, 255], [0, 0, 128, 255]]
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False,
                    vertex_colors=cols).export(tmp_path / f"v{suffix}")
    res = mesh_files.read_from_file(tmp_path / f"v{suffix}")  # glTF COLOR_0 linear, PLY 8-bit colours sRGB
    np.testing.assert_allclose(read_scene(res.stage).meshes[0].material.diffuse, [0.5, 0, expect / 2], atol=1e-6)
    mesh = next(p for p in res.stage.Traverse() if p.IsA(UsdGeom.Mesh))
    dc = np.array(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("displayColor").Get())
    np.testing.assert_allclose(dc, [[1, 0, 0], [1, 0, 0], [0, 0, expect], [0, 0, expect]], atol=1e-6)
    assert res.warnings == {"vertex colours (primvars:displayColor; usdrelight's renderers use their mean)": 1}


def _textured_stage(tmp_path, scale=None, bias=None, st_transform=None, emissive=None):
    from pxr import Gf, Sdf, UsdShade

    write_image(tmp_path / "white08.exr", np.full((4, 4, 3), 0.8, np.float32), "float")
    stage = create_stage(tmp_path / "s.usda", "/World")
    m = _mesh(stage, "/World/q", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [4],
              st=[(0, 0), (1, 0), (1, 1), (0, 1)])
    mat, surf = define_preview_material(stage, "/World/M")
    tex = author_uv_texture(stage, surf, "diffuseColor", "./white08.exr", "raw", "/World/M/Tex", "/World/M/St",
                            st_transform=st_transform)
    for name, v in (("scale", scale), ("bias", bias)):
        if v is not None:
            tex.CreateInput(name, Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*v))
    if emissive is not None:
        surf.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*emissive))
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(mat)
    return stage


def _glb_base_colour(path):
    """(linear texel values x baseColorFactor, the uv) of the first mesh of a .glb, as a viewer computes it."""
    geom = next(iter(trimesh.load(path, force="scene", process=False).geometry.values()))
    pbr = geom.visual.material
    texels = srgb_to_linear(np.asarray(pbr.baseColorTexture.convert("RGB"), np.float64) / 255.0)
    factor = np.ones(3) if pbr.baseColorFactor is None else np.asarray(pbr.baseColorFactor[:3]) / 255.0
    return texels * factor, np.asarray(geom.visual.uv), pbr


@pytest.mark.parametrize("scale, bias, want", [((0.25, 0.25, 0.25, 1), None, 0.2),
                                               ((1, 0.5, 0.25, 1), None, (0.8, 0.4, 0.2)),
                                               ((0.5, 0.5, 0.5, 1), (0.1, 0.1, 0.1, 0), 0.5),
                                               ((2, 2, 2, 1), None, 1.0)])
def test_glb_writer_applies_uv_texture_scale_and_bias(tmp_path, scale, bias, want):
    out = mesh_files.write_to_file(_textured_stage(tmp_path, scale, bias), tmp_path / "s.glb")
    colour, _, _ = _glb_base_colour(tmp_path / "s.glb")
    np.testing.assert_allclose(colour, np.broadcast_to(want, colour.shape), atol=3e-3)
    assert ("base colour texels outside [0, 1] in glTF (clipped)" in out.warnings) == (want == 1.0)


def test_glb_writer_bakes_the_st_transform_into_uvs_and_writes_emissive(tmp_path):
    stage = _textured_stage(tmp_path, st_transform={"scale": (2.0, 2.0), "translation": (0.5, 0.0)},
                            emissive=(0.5, 0.25, 0.0))
    out = mesh_files.write_to_file(stage, tmp_path / "s.glb")
    _, uv, pbr = _glb_base_colour(tmp_path / "s.glb")
    np.testing.assert_allclose(np.sort(uv, 0), [[0.5, 0], [0.5, 0], [2.5, 2], [2.5, 2]], atol=1e-6)
    np.testing.assert_allclose(pbr.emissiveFactor, (0.5, 0.25, 0.0))
    assert out.warnings == {}


def test_two_files_with_one_material_name_keep_their_own_textures_in_one_folder(tmp_path):
    """Textures were written as textures/<material>_baseColor.png: a second file whose material has the same
    name overwrote the first one's texture, and the first USD file showed the second's colours."""
    from usdrelight.imageio import read_map

    means = {}
    for name, colour in (("green", (0, 255, 0)), ("red", (255, 0, 0))):
        q = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 1, 2]], process=False)
        img = Image.new("RGB", (4, 4), colour)
        q.visual = trimesh.visual.TextureVisuals(uv=[[0, 0], [1, 0], [1, 1]], material=trimesh.visual.material.
                                                 PBRMaterial(name="q", baseColorTexture=img))
        q.export(tmp_path / f"{name}.glb")
        (tmp_path / "out").mkdir(exist_ok=True)
        read = mesh_files.read_from_file(tmp_path / f"{name}.glb", usd_path=tmp_path / "out" / f"{name}.usda")
        read.stage.GetRootLayer().Save()
    for name in ("green", "red"):
        tex = read_scene(tmp_path / "out" / f"{name}.usda").meshes[0].material.diffuse
        means[name] = read_map(tex.path, 3).reshape(-1, 3).mean(0)
    assert means["green"][1] > 0.9 > means["green"][0] and means["red"][0] > 0.9 > means["red"][1]


def _glb_without(path, drop: str) -> None:
    """A quad .glb (roughness 0.5, metallicFactor 0 as trimesh writes it), then its JSON edited: ``metallic``
    removes metallicFactor (as Blender's exporter writes a metal: defaults left out), ``pbr`` the whole
    pbrMetallicRoughness."""
    import json
    import struct

    q = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    q.visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(
        baseColorFactor=[1.0, 0.5, 0.25, 1.0], metallicFactor=0.0, roughnessFactor=0.5))
    glb = trimesh.Scene(q).export(file_type="glb")
    n = struct.unpack("<I", glb[12:16])[0]
    doc = json.loads(glb[20:20 + n])
    for mat in doc["materials"]:
        if drop == "metallic":
            mat["pbrMetallicRoughness"].pop("metallicFactor")
        elif drop == "pbr":
            mat.pop("pbrMetallicRoughness")
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + glb[20 + n:]
    path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)


@pytest.mark.parametrize("drop, metallic, roughness", [("none", 0.0, 0.5), ("metallic", 1.0, 0.5), ("pbr", 1.0, 1.0)])
def test_glb_metallic_factor_defaults_to_one_as_gltf_says(tmp_path, drop, metallic, roughness):
    """glTF 2.0: metallicFactor and roughnessFactor default to 1 (before: an absent metallicFactor read as 0, so
    a metal exported from Blender came in as a dielectric)."""
    _glb_without(tmp_path / "q.glb", drop)
    res = mesh_files.read_from_file(tmp_path / "q.glb")
    mat = read_scene(res.stage).meshes[0].material
    assert (float(mat.metallic), float(mat.roughness)) == pytest.approx((metallic, roughness))
    assert ("glTF metallicFactor absent (1, the glTF default: a metal)" in res.warnings) == (drop != "none")
