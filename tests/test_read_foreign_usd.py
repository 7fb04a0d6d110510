"""USD files as other tools write them, read into records: each test asserts numbers that came out wrong before
(from a probe of the converters on files others wrote). The scenes are USD text, as an exporter writes it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pxr import Usd

from usdrelight.stage.camera import conformed_apertures
from usdrelight.stage.read import read_lights, read_scene
from usdrelight.stage.read_lux import OLD_LUX_NAMES


def _stage(tmp_path: Path, body: str, up: str = "Y", mpu: float = 1.0, extra: str = "") -> Path:
    path = tmp_path / "s.usda"
    path.write_text(f'#usda 1.0\n(\n    upAxis = "{up}"\n    metersPerUnit = {mpu}\n{extra})\n\n{body}\n')
    return path


def test_mesh_points_are_read_at_the_time_asked_for(tmp_path):
    """A deforming cache (points time-sampled only) and a mesh with a rest pose plus samples, under an animated
    translate: at t = 10 both are where frame 10 puts them, not dropped or frozen at the rest pose."""
    path = _stage(tmp_path, '''
def Mesh "Cache" {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points.timeSamples = { 0: [(0,0,0), (1,0,0), (0,1,0)], 10: [(0,0,0), (4,0,0), (0,1,0)] }
}
def Xform "Rig" {
    double3 xformOp:translate.timeSamples = { 0: (0,0,0), 10: (10,0,0) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
    def Mesh "Tri" {
        int[] faceVertexCounts = [3]
        int[] faceVertexIndices = [0, 1, 2]
        point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
        point3f[] points.timeSamples = { 0: [(0,0,0), (1,0,0), (0,1,0)], 10: [(0,0,0), (3,0,0), (0,1,0)] }
    }
}''')
    meshes = {m.path: m for m in read_scene(path, time=10).meshes}
    assert meshes["/Cache"].points[:, 0].max() == pytest.approx(4.0)
    assert meshes["/Rig/Tri"].points[:, 0].min() == pytest.approx(10.0)
    assert meshes["/Rig/Tri"].points[:, 0].max() == pytest.approx(13.0)
    rest = {m.path: m for m in read_scene(path, Usd.TimeCode.Default()).meshes}  # the rest pose, no cache
    assert set(rest) == {"/Rig/Tri"} and rest["/Rig/Tri"].points[:, 0].max() == pytest.approx(1.0)
    first = {m.path: m for m in read_scene(path).meshes}  # no time given: what render reads, the first samples
    assert set(first) == {"/Cache", "/Rig/Tri"} and first["/Cache"].points[:, 0].max() == pytest.approx(1.0)


def test_a_dome_with_the_scene_pole_on_a_z_up_stage_is_turned_like_a_z_pole(tmp_path):
    body = 'def DomeLight_1 "Sky" {{\n    token poleAxis = "{}"\n}}'
    scene_pole = read_lights(Usd.Stage.Open(str(_stage(tmp_path, body.format("scene"), up="Z"))))[0]
    (tmp_path / "s.usda").unlink()
    z_pole = read_lights(Usd.Stage.Open(str(_stage(tmp_path, body.format("Z"), up="Z"))))[0]
    np.testing.assert_allclose(scene_pole.to_world, z_pole.to_world)
    assert scene_pole.to_world[:3, 1] == pytest.approx([0, 0, 1])  # the map's pole (+Y) is the stage's up, +Z


WIDENED = np.degrees(2 * np.arctan(15.29 * 16 / 9 / 2 / 50))  # 30.41: the width made 16:9 of the height
CROPPED = np.degrees(2 * np.arctan(20.955 / 2 / 50))  # 23.67: the width kept, the height cropped to 16:9


@pytest.mark.parametrize("policy, hfov", [("expandAperture", WIDENED), ("cropAperture", CROPPED),
                                          ("adjustApertureWidth", WIDENED), ("adjustApertureHeight", CROPPED)])
def test_the_camera_is_conformed_to_the_image_as_the_render_settings_say(tmp_path, policy, hfov):
    """Houdini's default 20.955 x 15.29 mm aperture rendered at 1280 x 720: USD widens (or crops) the aperture
    to 16:9; the pixels stay square (before: 23.67 deg wide with non-square pixels, whatever the policy)."""
    path = _stage(tmp_path, f'''
def Camera "Cam" {{
    float focalLength = 50
    float horizontalAperture = 20.955
    float verticalAperture = 15.29
}}
def Scope "Render" {{
    def RenderSettings "Settings" {{
        rel camera = </Cam>
        uniform int2 resolution = (1280, 720)
        uniform token aspectRatioConformPolicy = "{policy}"
    }}
}}''', extra='    renderSettingsPrimPath = "/Render/Settings"\n')
    scene = read_scene(path)
    intr = scene.camera.intrinsics
    assert np.degrees(2 * np.arctan(1280 / 2 / intr.fx)) == pytest.approx(hfov, abs=1e-4)
    assert intr.fy == pytest.approx(intr.fx, rel=1e-6)  # square pixels
    assert not any("non-square" in w for w in scene.warnings)


def test_conforming_leaves_apertures_that_agree_and_the_pixel_aspect_policy_alone():
    assert conformed_apertures(36.0, 24.0, 600, 400) == (36.0, 24.0)
    assert conformed_apertures(36.0, 24.0, 1280, 720, policy="adjustPixelAspectRatio") == (36.0, 24.0)
    ha, va = conformed_apertures(36.0, 24.0, 640, 480, pixel_aspect=2.0)  # 8:3 image: widened
    assert (ha, va) == pytest.approx((64.0, 24.0))


def test_lights_with_the_names_before_usdlux_21_02_are_read(tmp_path):
    path = _stage(tmp_path, '''
def SphereLight "Old" {
    float intensity = 200
    color3f color = (1, 0.5, 0.25)
    float radius = 0.1
}''')
    scene = read_scene(path)
    light = scene.lights[0]
    assert light.radiance == pytest.approx([200, 100, 50]) and light.radius == pytest.approx(0.1)
    assert scene.warnings[OLD_LUX_NAMES] > 0


def test_a_point_instancers_prototypes_are_drawn_where_it_places_them_and_only_there(tmp_path):
    """Positions, orientations (quaternions), scales, the prototype root's own transform and the instancer's,
    a masked instance (invisibleIds), a mirroring scale (winding kept counter-clockwise) and a Sphere prototype
    stretched into an ellipsoid; the prototypes are not drawn where they stand, their light is warned."""
    path = _stage(tmp_path, '''
def Mesh "Ground" {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,0,1)]
}
def PointInstancer "Scatter" {
    double3 xformOp:translate = (0, 10, 0)
    uniform token[] xformOpOrder = ["xformOp:translate"]
    point3f[] positions = [(5, 0, 0), (6, 0, 0), (7, 0, 0), (8, 0, 0)]
    quath[] orientations = [(1, 0, 0, 0), (0.70710677, 0, 0, 0.70710677), (1, 0, 0, 0), (1, 0, 0, 0)]
    float3[] scales = [(1, 1, 1), (2, 2, 2), (-1, 1, 1), (1, 1, 1)]
    int64[] invisibleIds = [3]
    int[] protoIndices = [0, 0, 0, 1]
    rel prototypes = [</Scatter/Protos/Lamp>, </Scatter/Protos/Ball>]
    def Scope "Protos" {
        def Xform "Lamp" {
            double3 xformOp:translate = (0, 0, 1)
            uniform token[] xformOpOrder = ["xformOp:translate"]
            def Mesh "Shade" {
                int[] faceVertexCounts = [3]
                int[] faceVertexIndices = [0, 1, 2]
                point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
            }
            def SphereLight "Bulb" {
                float inputs:intensity = 7
                bool treatAsPoint = 1
            }
        }
        def Sphere "Ball" {
            double radius = 0.5
        }
    }
}
def PointInstancer "Stretched" {
    point3f[] positions = [(0, 0, -5)]
    float3[] scales = [(1, 3, 1)]
    int[] protoIndices = [0]
    rel prototypes = </Stretched/Ball>
    def Sphere "Ball" {
        double radius = 0.5
    }
}''')
    scene = read_scene(path)
    meshes = {m.path: m for m in scene.meshes}
    assert set(meshes) == {"/Ground", "/Scatter/Protos/Lamp/Shade/instances", "/Stretched/Ball/instance0"}
    shade = [(0, 0, 0), (1, 0, 0), (0, 1, 0)]
    placed = meshes["/Scatter/Protos/Lamp/Shade/instances"]  # the three instances as one record (one shape)
    assert placed.points.shape == (9, 3) and placed.faces.shape == (3, 3)
    np.testing.assert_allclose(placed.points[:3], np.add(shade, (5, 10, 1)), atol=1e-6)
    # turned 90 degrees about z and scaled 2: (x, y, z) -> (-2y, 2x, 2z), the root's (0, 0, 1) too
    np.testing.assert_allclose(placed.points[3:6], [(6, 10, 2), (6, 12, 2), (4, 10, 2)], atol=1e-3)  # quath
    np.testing.assert_allclose(placed.points[6:], [(7, 10, 1), (6, 10, 1), (7, 11, 1)], atol=1e-6)  # mirrored
    for face in placed.faces:
        a, b, c = placed.points[face]
        assert np.cross(b - a, c - a)[2] > 0  # counter-clockwise seen from +z: the mirrored one's winding flipped
    assert scene.shapes == ()  # the masked instance's Ball is not drawn; the stretched one is a mesh
    egg = meshes["/Stretched/Ball/instance0"].points
    assert np.ptp(egg[:, 1]) == pytest.approx(3.0, rel=1e-3) and np.ptp(egg[:, 0]) == pytest.approx(1.0, rel=1e-3)
    assert scene.lights == () and any("light inside a PointInstancer" in w for w in scene.warnings)
    assert read_lights(Usd.Stage.Open(str(path))) == ()


def test_the_primvar_reader_varname_picks_the_uv_set_and_a_preview_binding_is_used(tmp_path):
    """A quad with two UV sets whose material reads ``st1``, bound for preview only: its UVs are st1's and its
    material is that one, not the grey default."""
    path = _stage(tmp_path, '''
def Mesh "Quad" (
    prepend apiSchemas = ["MaterialBindingAPI"]
) {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(0,0,0), (1,0,0), (1,1,0), (0,1,0)]
    texCoord2f[] primvars:st = [(0,0), (1,0), (1,1), (0,1)] (interpolation = "vertex")
    texCoord2f[] primvars:st1 = [(0,0), (0.5,0), (0.5,0.5), (0,0.5)] (interpolation = "vertex")
    rel material:binding:preview = </Mat>
}
def Material "Mat" {
    token outputs:surface.connect = </Mat/Surface.outputs:surface>
    def Shader "Surface" {
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:diffuseColor = (0.8, 0.1, 0.1)
        token outputs:surface
    }
    def Shader "Reader" {
        uniform token info:id = "UsdPrimvarReader_float2"
        string inputs:varname = "st1"
        float2 outputs:result
    }
}''')
    mesh = read_scene(path).meshes[0]
    assert mesh.material.diffuse == pytest.approx((0.8, 0.1, 0.1)) and mesh.material.st_primvar == "st1"
    assert mesh.uv.max() == pytest.approx(0.5)


def test_a_sphere_under_a_non_uniform_scale_is_an_ellipsoid_in_mitsuba(tmp_path):
    """Mitsuba's analytic sphere cannot stretch (a (2, 0.5, 1) scale came out as a radius-2 sphere): the reader
    gives the ellipsoid as a mesh. Its bounding box, its area against Knud Thomsen's formula (within 1%) and the
    normal at the tip of its long axis are the ellipsoid's."""
    from usdrelight.mitsuba.runtime import load_mitsuba
    from usdrelight.mitsuba.scene_dict import scene_dict, to_mitsuba
    from usdrelight.stage.read_geometry import mesh_area

    path = _stage(tmp_path, '''
def Sphere "Egg" {
    double radius = 1
    float3 xformOp:scale = (2, 0.5, 1)
    uniform token[] xformOpOrder = ["xformOp:scale"]
}
def Sphere "Ball" {
    double radius = 0.25
    double3 xformOp:translate = (5, 0, 0)
    uniform token[] xformOpOrder = ["xformOp:translate"]
}''')
    scene = read_scene(path)
    assert [s.path for s in scene.shapes] == ["/Ball"]  # a uniform sphere stays analytic
    egg = scene.meshes[0]
    np.testing.assert_allclose(egg.points.min(0), [-2, -0.5, -1], atol=1e-3)
    np.testing.assert_allclose(egg.points.max(0), [2, 0.5, 1], atol=1e-3)
    p = 1.6075
    a, b, c = 2.0, 0.5, 1.0
    thomsen = 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)
    assert mesh_area(egg) == pytest.approx(thomsen, rel=0.01)
    tri = egg.points[egg.faces]
    outward = (np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) * tri.mean(1)).sum(1)
    assert outward.min() >= -1e-12 and (outward > 0).mean() > 0.97  # counter-clockwise seen from outside
    tip = np.argmax(egg.points[:, 0])
    np.testing.assert_allclose(egg.normals[tip], [1, 0, 0], atol=1e-6)
    mi = load_mitsuba()
    d = scene_dict(scene)
    d.pop("sensor", None)
    shapes = mi.load_dict(to_mitsuba(d)).shapes()
    boxes = sorted((np.array(s.bbox().max) - np.array(s.bbox().min)).round(3).tolist() for s in shapes)
    assert boxes == [[0.5, 0.5, 0.5], [4.0, 1.0, 2.0]]


def test_display_color_without_a_material_and_the_unrendered_camera_and_light_controls(tmp_path):
    path = _stage(tmp_path, '''
def Mesh "Red" {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,0), (1,0,0), (0,1,0)]
    color3f[] primvars:displayColor = [(0.8, 0.1, 0.1)]
}
def Camera "Cam" {
    float fStop = 2.8
    float focusDistance = 300
}
def LightFilter "Gobo" {
}
def SphereLight "Key" {
    float inputs:intensity = 5
    rel light:filters = </Gobo>
}''')
    scene = read_scene(path)
    assert scene.meshes[0].material.diffuse == pytest.approx((0.8, 0.1, 0.1))  # as USD viewers show it
    assert any("fStop" in w for w in scene.warnings) and any("light filters" in w for w in scene.warnings)


def test_multipliers_and_shadow_controls_under_the_old_names_are_warned(tmp_path):
    path = _stage(tmp_path, '''
def SphereLight "Old" {
    float intensity = 5
    float diffuse = 0.5
    bool shadow:enable = 0
}''')
    w = read_scene(path).warnings
    assert any("diffuse/specular multipliers" in k for k in w) and any("shadow:enable off" in k for k in w)


def test_material_inputs_are_followed_through_interfaces_and_node_graphs(tmp_path):
    """tests/data/material_interfaces.usda: diffuseColor connected to the Material's own input baseColor; a
    UsdUVTexture whose file is connected to a Material input; diffuseColor connected to a NodeGraph output
    wrapping a UsdUVTexture (scale 2, 1, 1, 1). All three were read as the grey default (0.18) with a warning
    about a shader 'None'; UsdShade resolves them to the colour and the textures."""
    import shutil

    from usdrelight.imageio import write_image
    from usdrelight.stage.records import TextureRecord

    shutil.copy(Path(__file__).parent / "data" / "material_interfaces.usda", tmp_path / "m.usda")
    write_image(tmp_path / "grey128.png", np.full((4, 4, 3), 0.5, np.float32))
    scene = read_scene(tmp_path / "m.usda")
    mats = {m.path: m.material for m in scene.meshes}
    assert mats["/World/A"].diffuse == pytest.approx((0.8, 0.2, 0.1))
    for path, scale in (("/World/B", (1.0, 1.0, 1.0, 1.0)), ("/World/C", (2.0, 1.0, 1.0, 1.0))):
        tex = mats[path].diffuse
        assert isinstance(tex, TextureRecord) and Path(tex.path) == tmp_path / "grey128.png" and tex.scale == scale
    assert not any("shader 'None'" in w or "without a file" in w for w in scene.warnings)


def test_an_unbound_geom_subset_keeps_its_meshs_display_color(tmp_path):
    """A displayColor mesh (no material) with a materialBind GeomSubset bound to nothing: the subset's faces were
    the grey default (0.18) while the rest was the mesh's yellow."""
    path = _stage(tmp_path, '''
def Mesh "DC" (
    prepend apiSchemas = ["MaterialBindingAPI"]
)
{
    int[] faceVertexCounts = [4, 4]
    int[] faceVertexIndices = [0, 1, 5, 4, 4, 5, 2, 3]
    point3f[] points = [(0, -1, 0), (1, -1, 0), (1, 1, 0), (0, 1, 0), (0, 0, 0), (1, 0, 0)]
    color3f[] primvars:displayColor = [(0.9, 0.9, 0.1)]
    def GeomSubset "top"
    {
        uniform token elementType = "face"
        uniform token familyName = "materialBind"
        int[] indices = [1]
    }
}''', up="Z")
    meshes = read_scene(path).meshes
    assert sorted(m.path for m in meshes) == ["/DC", "/DC/top"]
    for m in meshes:
        assert m.material.diffuse == pytest.approx((0.9, 0.9, 0.1)), m.path


def test_a_time_sampled_product_name_is_read_at_the_render_time(tmp_path):
    """Solaris samples productName per frame (render/beauty.$F4.exr): it was read as '' ('must be a relative
    path inside ...', whatever --time said)."""
    path = _stage(tmp_path, '''
def Camera "Cam" {
}
def Scope "Render" {
    def RenderSettings "Settings" {
        rel camera = </Cam>
        rel products = </Render/Beauty>
        uniform int2 resolution = (8, 8)
    }
    def RenderProduct "Beauty" {
        token productName.timeSamples = { 1: "render/beauty.0001.exr", 2: "render/beauty.0002.exr" }
        rel orderedVars = </Render/Color>
    }
    def RenderVar "Color" {
        uniform string sourceName = "color"
    }
}''')
    assert [p.product_name for p in read_scene(path, 2.0).products] == ["render/beauty.0002.exr"]
    assert [p.product_name for p in read_scene(path).products] == ["render/beauty.0001.exr"]  # the first frame


def test_uvs_and_normals_of_the_wrong_count_are_warned(tmp_path):
    """faceVarying st of 3 values for 4 corners, vertex normals of 2 for 4 points: dropped in silence (the
    texture rendered as one texel)."""
    path = _stage(tmp_path, '''
def Mesh "Quad" {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    uniform token subdivisionScheme = "none"
    normal3f[] normals = [(0, 0, 1), (0, 0, 1)] (interpolation = "vertex")
    texCoord2f[] primvars:st = [(0, 0), (1, 0), (1, 1)] (interpolation = "faceVarying")
}''')
    scene = read_scene(path)
    (mesh,) = scene.meshes
    assert mesh.uv is None and mesh.normals is None
    assert scene.warnings == {
        "normals with a count their vertex interpolation does not match (the mesh read without them)": 1,
        "primvar st with a count its faceVarying interpolation does not match (the mesh read without it)": 1}


def test_a_referenced_layer_of_other_units_is_warned(tmp_path):
    """A centimetre Z-up asset referenced into a metre Y-up stage: USD does not rescale it (100x too large) and
    no command said so."""
    (tmp_path / "asset.usda").write_text('#usda 1.0\n(\n    upAxis = "Z"\n    metersPerUnit = 0.01\n    '
                                         'defaultPrim = "A"\n)\ndef Sphere "A" {\n    double radius = 50\n}\n')
    path = _stage(tmp_path, 'def Xform "Ref" (\n    references = @./asset.usda@\n)\n{\n}')
    assert read_scene(path).warnings == {"layer asset.usda authors metersPerUnit 0.01 and upAxis Z, the stage 1 "
                                         "and Y (USD composes it unscaled and unturned)": 1}


def test_a_texture_input_fed_by_another_node_keeps_its_own_value(tmp_path):
    """UsdUVTexture scale connected to a UsdPrimvarReader_float4's output: 'unexpected AttributeError' (the
    resolver's output name was read as a value); its own authored value is used, as before."""
    from usdrelight.imageio import write_image
    from usdrelight.stage.records import TextureRecord

    write_image(tmp_path / "t.png", np.full((4, 4, 3), 0.5, np.float32))
    path = _stage(tmp_path, '''
def Mesh "Quad" (
    prepend apiSchemas = ["MaterialBindingAPI"]
) {
    int[] faceVertexCounts = [4]
    int[] faceVertexIndices = [0, 1, 2, 3]
    point3f[] points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]
    uniform token subdivisionScheme = "none"
    rel material:binding = </M>
}
def Material "M" {
    token outputs:surface.connect = </M/PS.outputs:surface>
    def Shader "PS" {
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:diffuseColor.connect = </M/Tex.outputs:rgb>
        token outputs:surface
    }
    def Shader "Tex" {
        uniform token info:id = "UsdUVTexture"
        asset inputs:file = @t.png@
        float4 inputs:scale = (0.5, 0.5, 0.5, 1)
        float4 inputs:scale.connect = </M/Fade.outputs:result>
        float3 outputs:rgb
    }
    def Shader "Fade" {
        uniform token info:id = "UsdPrimvarReader_float4"
        float4 outputs:result
    }
}''')
    tex = read_scene(path).meshes[0].material.diffuse
    assert isinstance(tex, TextureRecord) and tex.scale == (0.5, 0.5, 0.5, 1.0)
