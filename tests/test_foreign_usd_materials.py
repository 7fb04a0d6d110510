"""Materials, geometry and render set-up of USD files as DCCs write them (Houdini, Maya, Substance, usdview's
samples): each test asserts a number that came out wrong before, from a probe of stages written by other tools."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdrelight.imageio import read_map, write_image
from usdrelight.mitsuba.scene_dict import scene_dict
from usdrelight.stage.read import read_scene

from usd_scenes import color_product_settings


def _stage(tmp_path: Path, body: str, extra: str = "") -> Path:
    path = tmp_path / "s.usda"
    path.write_text(f'#usda 1.0\n(\n    upAxis = "Y"\n    metersPerUnit = 1\n{extra})\n\n{body}\n')
    return path


QUAD = '''
def Mesh "Quad" (
    prepend apiSchemas = ["MaterialBindingAPI"]
) {{
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-1,-1,0), (1,-1,0), (1,1,0), (-1,1,0)]
    {st}
    rel material:binding = </M>
}}
def Material "M" {{
    token outputs:surface.connect = </M/S.outputs:surface>
    def Shader "S" {{
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:diffuseColor.connect = </M/T.outputs:rgb>
        token outputs:surface
    }}
    def Shader "T" {{
        uniform token info:id = "UsdUVTexture"
        asset inputs:file = @./{file}@
        {extra}
        float3 outputs:rgb
    }}
}}'''
ST = 'texCoord2f[] primvars:st = [(0,0), (1,0), (1,1), (0,1)] (interpolation = "vertex")'


@pytest.mark.parametrize("name, dtype, channels, srgb", [
    ("rgb8.tif", "uint8", 3, True),  # an 8-bit TIFF (Substance) is sRGB, as Hio decides: was read linear
    ("rgba8.png", "uint8", 4, True),
    ("rgb16.png", "uint16", 3, False),  # 16 bits: raw (was decoded as sRGB)
    ("grey8.png", "uint8", 1, False),  # one channel: raw (a mask; was decoded)
    ("half.tx", "half", 3, False),  # maketx's float .tx: raw (was decoded: suffix not known)
    ("float.exr", "float", 3, False)])
def test_source_color_space_auto_is_decided_by_the_files_data_as_hio_does(tmp_path, name, dtype, channels, srgb):
    write_image(tmp_path / name, np.full((4, 4, channels), 0.5, np.float32).squeeze(), dtype)
    tex = read_scene(_stage(tmp_path, QUAD.format(st=ST, file=name, extra=""))).meshes[0].material.diffuse
    assert tex.linear is (not srgb) and tex.color_space == ("sRGB" if srgb else "raw")


def test_an_authored_source_color_space_wins_and_an_unknown_one_is_read_as_auto(tmp_path):
    write_image(tmp_path / "rgb16.png", np.full((4, 4, 3), 0.5, np.float32), "uint16")
    forced = QUAD.format(st=ST, file="rgb16.png", extra='token inputs:sourceColorSpace = "sRGB"')
    assert read_scene(_stage(tmp_path, forced)).meshes[0].material.diffuse.linear is False
    odd = read_scene(_stage(tmp_path, QUAD.format(st=ST, file="rgb16.png",
                                                  extra='token inputs:sourceColorSpace = "lin_rec709"')))
    assert odd.meshes[0].material.diffuse.linear is True
    assert any("sourceColorSpace 'lin_rec709'" in w for w in odd.warnings)


def test_time_sampled_material_inputs_and_display_color_follow_the_frame(tmp_path):
    """Solaris / Maya frame-range exports: a diffuseColor and a displayColor written only as time samples were
    read at the default time (the 0.18 grey fallback) whatever the frame."""
    path = _stage(tmp_path, '''
def Mesh "Shaded" (
    prepend apiSchemas = ["MaterialBindingAPI"]
) {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    rel material:binding = </M>
}
def Mesh "Painted" {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    color3f[] primvars:displayColor.timeSamples = { 1: [(0, 1, 0)], 2: [(1, 1, 0)] }
}
def Material "M" {
    token outputs:surface.connect = </M/S.outputs:surface>
    def Shader "S" {
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:diffuseColor.timeSamples = { 1: (1, 0, 0), 2: (0, 0, 1) }
        token outputs:surface
    }
}''', extra="    startTimeCode = 1\n    endTimeCode = 2\n")
    for t, shaded, painted in ((None, (1, 0, 0), (0, 1, 0)), (2, (0, 0, 1), (1, 1, 0)), (1.5, (0.5, 0, 0.5), (0.5, 1, 0))):
        mats = {m.path: m.material.diffuse for m in read_scene(path, t).meshes}
        assert mats["/Shaded"] == pytest.approx(shaded) and mats["/Painted"] == pytest.approx(painted), t


def test_display_color_is_inherited_from_an_ancestor_as_a_constant_primvar(tmp_path):
    path = _stage(tmp_path, '''
def Xform "Red" {
    color3f[] primvars:displayColor = [(1, 0, 0)]
    def Mesh "Child" {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    }
    def Mesh "Own" {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
        color3f[] primvars:displayColor = [(0, 0, 1)]
    }
}''')
    mats = {m.path: m.material.diffuse for m in read_scene(path).meshes}
    assert mats["/Red/Child"] == pytest.approx((1, 0, 0)) and mats["/Red/Own"] == pytest.approx((0, 0, 1))


def test_hole_faces_are_cut_and_unauthored_subdivision_is_not_warned(tmp_path):
    path = _stage(tmp_path, '''
def Mesh "Grid" {
    int[] faceVertexCounts = [4, 4, 3]
    int[] faceVertexIndices = [0, 1, 4, 3, 1, 2, 5, 4, 3, 4, 6]
    point3f[] points = [(0,0,0), (1,0,0), (2,0,0), (0,1,0), (1,1,0), (2,1,0), (0,2,0)]
    int[] holeIndices = [1]
}
def Mesh "Smooth" {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    uniform token subdivisionScheme = "catmullClark"
}''')
    scene = read_scene(path)
    grid = next(m for m in scene.meshes if m.path == "/Grid")
    assert len(grid.faces) == 3 and grid.points[:, 0].max() == pytest.approx(1.0)  # the x in [1, 2] quad cut
    assert scene.warnings["subdivision surfaces (rendered as the control mesh)"] == 1  # "Smooth" only


def test_a_plane_along_x_has_its_width_along_z_as_the_schema_says(tmp_path):
    path = _stage(tmp_path, '''
def Plane "P" {
    uniform token axis = "X"
    double width = 4
    double length = 1
}''')
    m = read_scene(path).shapes[0].to_world
    assert np.abs(m[:3, 0]) == pytest.approx([0, 0, 2]) and np.abs(m[:3, 1]) == pytest.approx([0, 0.5, 0])
    assert m[:3, 2] == pytest.approx([1, 0, 0]) and np.linalg.det(m[:3, :3]) > 0


def test_a_textured_mesh_without_st_reads_every_texel_at_the_origin_and_says_so(tmp_path):
    write_image(tmp_path / "t.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    scene = read_scene(_stage(tmp_path, QUAD.format(st="", file="t.png", extra="")))
    assert np.all(scene.meshes[0].uv == 0.0)  # Mitsuba read barycentrics where no uv was given
    assert any("without texture coordinates" in w for w in scene.warnings)


@pytest.mark.parametrize("uv_scale, warned", [(1.0, 0), (2.0, 1)])
def test_a_black_wrap_is_warned_only_where_a_lookup_leaves_the_unit_square(tmp_path, uv_scale, warned):
    write_image(tmp_path / "t.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    st = ST.replace("(1,0), (1,1), (0,1)", f"({uv_scale},0), ({uv_scale},{uv_scale}), (0,{uv_scale})")
    scene = read_scene(_stage(tmp_path, QUAD.format(st=st, file="t.png", extra="")))
    scene_dict(scene)
    assert sum(v for k, v in scene.warnings.items() if "wrap 'black'" in k) == warned


def test_validate_takes_allow_path_as_its_message_says(tmp_path, cli):
    assets, shot = tmp_path / "assets", tmp_path / "shot"
    assets.mkdir()
    shot.mkdir()
    write_image(assets / "wood.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    head = '#usda 1.0\n(\n    defaultPrim = "Chair"\n    metersPerUnit = 1\n    upAxis = "Y"\n)\n'
    chair = QUAD.format(st=ST, file="wood.png", extra="").replace("</M", "</Chair/M").replace("\n", "\n    ")
    (assets / "chair.usda").write_text(head + 'def Xform "Chair" {' + chair + "\n}\n")
    (shot / "shot.usda").write_text(head + 'def Xform "Chair" (prepend references = @../assets/chair.usda@)\n{\n}\n')
    rc, out, _ = cli("validate", shot / "shot.usda")
    assert rc == 1 and "--allow-path" in out
    rc, out, err = cli("validate", shot / "shot.usda", "--allow-path", assets)
    assert rc == 0, out + err


CARD = '''
def Mesh "Card" {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(-5,-5,-3), (5,-5,-3), (5,5,-3), (-5,5,-3)]
    color3f[] primvars:displayColor = [(0.5, 0.5, 0.5)]
}
def DomeLight "Sky" {
    float inputs:intensity = 1
}
def Camera "Cam" {
    float horizontalAperture = 20
    float verticalAperture = 15
    float focalLength = 20
}'''
SETTINGS = color_product_settings((640, 480), 'beauty.exr')


def test_render_writes_the_beauty_of_a_stage_without_render_settings(tmp_path, cli):
    """usdview's samples and most DCC exports declare no RenderProducts: render was one error; now the beauty,
    as a stage declaring a colour product at the camera's 640 x 480 renders it, bit for bit."""
    bare = _stage(tmp_path, CARD)
    rc, out, err = cli("render", bare, "-o", tmp_path / "out", "--spp", 4, "--max-depth", 2)
    assert rc == 0 and "no RenderProducts declared" in err, err
    (tmp_path / "declared").mkdir()
    declared = _stage(tmp_path / "declared", CARD + SETTINGS)
    assert cli("render", declared, "-o", tmp_path / "ref", "--spp", 4, "--max-depth", 2)[0] == 0
    img, ref = read_map(tmp_path / "out" / "color.exr", 3), read_map(tmp_path / "ref" / "beauty.exr", 3)
    assert img.shape == (480, 640, 3) and np.array_equal(img, ref) and 0.45 < img.mean() < 0.6
    write_image(tmp_path / "mine" / "color.exr", np.zeros((2, 2, 3), np.float32), "float")  # a user's own file
    rc, _, err = cli("render", bare, "-o", tmp_path / "mine", "--spp", 1)
    assert rc == 2 and "is not a usdrelight render" in err
    assert read_map(tmp_path / "mine" / "color.exr", 3).shape == (2, 2, 3)


def _usdz_asset(folder: Path, sky: np.ndarray) -> None:
    """asset.usdz: a quad textured with a 16-bit PNG and a dome of ``sky`` (an EXR written past usdrelight's own
    writer, which refuses Inf), referenced by shot/s.usda."""
    import zipfile

    import OpenImageIO as oiio

    write_image(folder / "rgb16.png", np.full((4, 4, 3), 0.5, np.float32), "uint16")
    out = oiio.ImageOutput.create(str(folder / "sky.exr"))
    out.open(str(folder / "sky.exr"), oiio.ImageSpec(sky.shape[1], sky.shape[0], 3, "float"))
    out.write_image(sky)
    out.close()
    mesh, material = QUAD.format(st=ST, file="rgb16.png", extra="").split('def Material "M" {', 1)
    body = ('#usda 1.0\n(\n    defaultPrim = "Asset"\n)\ndef Xform "Asset" {\n' + mesh.replace("</M", "</Asset/M")
            + 'def Material "M" {' + material.replace("</M", "</Asset/M")
            + '\ndef DomeLight "Sky" {\n    asset inputs:texture:file = @sky.exr@\n}\n}\n')
    with zipfile.ZipFile(folder / "asset.usdz", "w", zipfile.ZIP_STORED) as z:
        z.writestr("asset.usda", body)
        z.write(folder / "rgb16.png", "rgb16.png")
        z.write(folder / "sky.exr", "sky.exr")
    (folder / "shot").mkdir(exist_ok=True)
    (folder / "shot" / "s.usda").write_text('#usda 1.0\ndef Xform "A" (prepend references = @../asset.usdz@)\n{\n}\n')


def test_textures_inside_a_referenced_usdz_are_decided_and_checked_as_loose_files(tmp_path):
    """A .usdz asset referenced by a shot: its 16-bit PNG was decoded as sRGB (by suffix) and its dome's Inf
    texel accepted; loose, the same files were raw and refused."""
    from usdrelight.errors import UsdRelightError
    from usdrelight.safe_paths import allow_paths

    sky = np.full((4, 8, 3), 0.5, np.float32)
    _usdz_asset(tmp_path, sky)
    with allow_paths([tmp_path]):
        scene = read_scene(tmp_path / "shot" / "s.usda")
    tex = scene.meshes[0].material.diffuse
    assert tex.path.endswith("asset.usdz[rgb16.png]") and tex.color_space == "raw" and tex.linear
    assert scene.lights[0].texture.color_space == "raw"
    sky[1, 2] = np.inf
    _usdz_asset(tmp_path, sky)
    with allow_paths([tmp_path]), pytest.raises(UsdRelightError, match="NaN, Inf or above 1e30 texels"):
        read_scene(tmp_path / "shot" / "s.usda")
