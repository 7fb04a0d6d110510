"""Reading general USD meshes: polygons, orientation, primvar interpolation, subsets, transforms."""
import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux, UsdShade

from usd_scenes import add_closed_form_light, diffuse_material, looking_down_at_floor, new_stage
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.read import read_scene


def _tri_normal(p, f):
    return np.cross(p[f[1]] - p[f[0]], p[f[2]] - p[f[0]])


def test_polygons_orientation_facevarying_and_subsets(tmp_path):
    stage = new_stage(tmp_path / "s.usda")
    red = diffuse_material(stage, "/World/Red", (0.8, 0.1, 0.1))
    blue = diffuse_material(stage, "/World/Blue", (0.1, 0.1, 0.8))
    m = UsdGeom.Mesh.Define(stage, "/World/M")
    # a pentagon and a quad in the z = 0 plane, wound clockwise seen from +Z, declared leftHanded:
    # so their front faces +Z
    m.CreatePointsAttr([(0, 0, 0), (0, 1, 0), (1, 1.5, 0), (2, 1, 0), (2, 0, 0), (3, 1, 0), (3, 0, 0)])
    m.CreateFaceVertexCountsAttr([5, 4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3, 4, 4, 3, 5, 6])
    m.CreateOrientationAttr("leftHanded")
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, "faceVarying")
    st.Set([(i / 10, 0) for i in range(9)])
    m.CreateNormalsAttr([(0, 0, 1), (0, 0, 1)])
    m.SetNormalsInterpolation("uniform")
    UsdGeom.Xformable(m).AddScaleOp().Set(Gf.Vec3f(2, 2, 2))
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(red)
    sub = UsdShade.MaterialBindingAPI(m.GetPrim()).CreateMaterialBindSubset("quad", [1])
    UsdShade.MaterialBindingAPI.Apply(sub.GetPrim()).Bind(blue)
    rec = read_scene(stage)
    assert len(rec.meshes) == 2
    by_mat = {r.material.path: r for r in rec.meshes}
    pent, quad = by_mat["/World/Red"], by_mat["/World/Blue"]
    assert len(pent.faces) == 3 and len(quad.faces) == 2  # fan triangulation
    for r in (pent, quad):
        for f in r.faces:
            assert _tri_normal(r.points, f)[2] > 0  # leftHanded flipped to counter-clockwise
        np.testing.assert_allclose(r.normals, np.tile([0, 0, 1], (len(r.points), 1)))
    assert pent.points[:, 0].max() == pytest.approx(4.0)  # the scale is applied
    # faceVarying st: the quad's corners carry st.x = 0.5 .. 0.8 (one per corner, not per point)
    assert sorted(np.round(quad.uv[:, 0], 3).tolist()) == [0.5, 0.5, 0.6, 0.7, 0.7, 0.8]
    # the fallback subdivisionScheme (catmullClark, unauthored): drawn as the control mesh, as usdview does at its
    # default complexity, without a line for every exported polygon mesh (an authored one is warned:
    # tests/test_foreign_usd_materials.py)
    assert dict(rec.warnings) == {}


def test_invisible_guides_and_unsupported_prims_are_named(tmp_path):
    stage = new_stage(tmp_path / "s.usda")
    UsdGeom.Sphere.Define(stage, "/World/Hidden").CreateVisibilityAttr("invisible")
    g = UsdGeom.Cube.Define(stage, "/World/Guide")
    g.CreatePurposeAttr("guide")
    UsdGeom.Cylinder.Define(stage, "/World/Cyl")
    UsdLux.PortalLight.Define(stage, "/World/Window")
    rec = read_scene(stage)
    assert rec.shapes == () and rec.meshes == () and rec.lights == ()
    assert rec.warnings["gprim type Cylinder (not converted)"] == 1
    assert rec.warnings["light type PortalLight (not converted)"] == 1


@pytest.mark.parametrize("light", ["point", "dome", "distant"])
def test_closed_forms_through_the_xml_converter(cli, tmp_path, light):
    """Convert the closed-form scenes to Mitsuba XML and render the XML with Mitsuba itself."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    expected = add_closed_form_light(stage, light)
    stage.GetRootLayer().Save()
    assert cli("convert", tmp_path / "s.usda", tmp_path / "x" / "s.xml")[0] == 0
    mi = load_mitsuba()
    img = np.array(mi.render(mi.load_file(str(tmp_path / "x" / "s.xml")), spp=64))
    h, w = img.shape[:2]
    assert img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1, :3].mean() == pytest.approx(expected, rel=0.03)


def test_malformed_material_values_fall_back_with_a_warning(cli, tmp_path):
    """Another tool's stage with ior -1 and a 3-component UsdUVTexture scale: read with warnings (ior 1.5, scale 1),
    and `convert` to XML succeeds (it used to raise ZeroDivisionError / IndexError)."""
    from usdrelight.imageio import write_image

    write_image(tmp_path / "t.exr", np.full((4, 4, 3), 0.5, np.float32), "float")
    stage = looking_down_at_floor(tmp_path / "s.usda")
    add_closed_form_light(stage, "dome")
    sh = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Grey/Surface"))
    sh.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.04, 0.04, 0.04))
    sh.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(-1.0)
    tex = UsdShade.Shader.Define(stage, "/World/Looks/Grey/Tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./t.exr")
    tex.CreateInput("scale", Sdf.ValueTypeNames.Float3).Set(Gf.Vec3f(2, 2, 2))
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    stage.GetRootLayer().Save()
    rec = read_scene(stage)
    mat = rec.meshes[0].material
    assert mat.ior == 1.5 and mat.diffuse.scale == (1.0, 1.0, 1.0, 1.0)
    assert any("ior -1.0" in w for w in rec.warnings) and any("scale with 3" in w for w in rec.warnings)
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "x" / "s.xml")
    assert rc == 0 and "ior -1.0" in err, err
