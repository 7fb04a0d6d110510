"""UsdPreviewSurface opacity and sidedness <-> Mitsuba, with real renders (48 x 48, 64 spp).

Opacity follows the UsdPreviewSurface spec: opacityThreshold 0 and opacity < 1 is translucency (opacity 0 is
clear glass of ``ior``: a Mitsuba dielectric, a blendbsdf in between); opacityThreshold > 0 is presence, cut to 0
below the threshold (a Mitsuba mask). A bare (one-sided) Mitsuba BSDF is black from behind; ``twosided`` becomes
doubleSided. Renders are compared by their means (5%), the per-pixel relative RMSE in the message.
"""
import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

from usdrelight.errors import UsdRelightError
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.create import author_lambertian, define_preview_material

SCENE = """<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="8"/>
    <boolean name="hide_emitters" value="true"/></integrator>
  <sensor type="perspective"><float name="fov" value="28"/>
    <transform name="to_world"><lookat origin="0, 0, {z}" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="64"/></sampler>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="48"/><rfilter type="box"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <emitter type="directional"><vector name="direction" value="0.3, -1, {dz}"/><rgb name="irradiance" value="2"/></emitter>
  {shapes}
</scene>"""
BACKDROP = """
  <shape type="rectangle"><transform name="to_world"><scale x="1.5" y="3"/><translate x="-1.5" z="-2"/></transform>
    <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.1, 0.1"/></bsdf></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale x="1.5" y="3"/><translate x="1.5" z="-2"/></transform>
    <bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.1, 0.2, 0.8"/></bsdf></bsdf></shape>"""
SPHERE = '<shape type="sphere" id="ball">{bsdf}</shape>'
DIFFUSE = '<bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.6"/></bsdf></bsdf>'


def _render(path):
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path))))[..., :3]


def _scene(tmp_path, name, shapes, z=5, dz=-1):
    path = tmp_path / f"{name}.xml"
    path.write_text(SCENE.format(shapes=shapes, z=z, dz=dz))
    return path


def _compare(a, b, rtol=0.05):
    """Means within rtol; the message has the per-pixel relative RMSE."""
    rmse = float(np.sqrt(np.mean((a - b) ** 2)) / max(b.mean(), 1e-9))
    print(f"means {a.mean():.4f} vs {b.mean():.4f}, rel RMSE {rmse:.3f}")
    assert a.mean() == pytest.approx(b.mean(), rel=rtol), f"means {a.mean():.4f} vs {b.mean():.4f}, rel RMSE {rmse:.3f}"
    return rmse


def _usd_with_sphere_material(cli, tmp_path, author):
    """The backdrop + sphere scene through XML -> USD, then the sphere's material replaced by one authored with
    pxr (``author(surface_shader)``), exported back to XML; returns (xml path, warnings JSON text)."""
    src = _scene(tmp_path, "src", BACKDROP + SPHERE.format(bsdf=DIFFUSE))
    assert cli("convert", src, tmp_path / "src.usda")[0] == 0
    stage = Usd.Stage.Open(str(tmp_path / "src.usda"))
    sphere = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Sphere))
    mat, surf = define_preview_material(stage, "/World/Looks/Edited")
    author(surf)
    UsdShade.MaterialBindingAPI.Apply(sphere).Bind(mat)
    stage.GetRootLayer().Export(str(tmp_path / "edited.usda"))
    rc, out, err = cli("convert", tmp_path / "edited.usda", tmp_path / "edited.xml", "--json")
    assert rc == 0, err
    return tmp_path / "edited.xml", out


def _glass(surf):
    surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.0)
    surf.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.5)
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.0)


def test_usd_glass_renders_as_a_mitsuba_dielectric(cli, tmp_path):
    """A pxr-authored glass (opacity 0, ior 1.5, threshold 0) is clear glass, not an invisible mask."""
    xml, _ = _usd_with_sphere_material(cli, tmp_path, _glass)
    assert 'type="dielectric"' in xml.read_text() and 'type="mask"' not in xml.read_text()
    ours = _render(xml)
    glass = _render(_scene(tmp_path, "glass", BACKDROP + SPHERE.format(
        bsdf='<bsdf type="dielectric"><float name="int_ior" value="1.5"/><float name="ext_ior" value="1"/></bsdf>')))
    empty = _render(_scene(tmp_path, "empty", BACKDROP))
    # the refracted backdrop is flipped left/right inside the sphere: far from the empty scene there
    centre = (slice(16, 32), slice(16, 32))
    assert np.abs(ours[centre] - empty[centre]).mean() > 0.3 * empty[centre].mean()
    rmse = _compare(ours, glass)
    assert rmse < 0.3


def test_translucent_opacity_is_a_blend_of_glass_and_the_opaque_surface(cli, tmp_path):
    def half(surf):
        author_lambertian(surf)
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.6, 0.6, 0.6))
        surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.5)
        surf.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.5)
        surf.GetInput("roughness").Set(0.0)  # smooth glass (roughness also roughens the translucent part)

    xml, _ = _usd_with_sphere_material(cli, tmp_path, half)
    text = xml.read_text()
    assert 'type="blendbsdf"' in text and 'name="weight" value="0.5"' in text and 'type="dielectric"' in text
    ours = _render(xml)[16:32, 16:32].mean()
    glass = _render(_scene(tmp_path, "glass", BACKDROP + SPHERE.format(
        bsdf='<bsdf type="dielectric"><float name="int_ior" value="1.5"/><float name="ext_ior" value="1"/></bsdf>')))
    opaque = _render(_scene(tmp_path, "opaque", BACKDROP + SPHERE.format(bsdf=DIFFUSE)))
    lo, hi = sorted((glass[16:32, 16:32].mean(), opaque[16:32, 16:32].mean()))
    assert lo < ours < hi, (lo, ours, hi)


def test_blend_of_glass_and_diffuse_round_trips_as_translucency(cli, tmp_path):
    """Mitsuba blendbsdf(dielectric, diffuse, 0.3) -> USD opacity 0.3, ior 1.5, roughness 0 -> the same blend."""
    bsdf = ('<bsdf type="blendbsdf"><float name="weight" value="0.3"/><bsdf type="dielectric"><float name="int_ior" '
            'value="1.5"/><float name="ext_ior" value="1"/></bsdf>' + DIFFUSE + '</bsdf>')
    src = _scene(tmp_path, "a", BACKDROP + SPHERE.format(bsdf=bsdf))
    rc, _, err = cli("convert", src, tmp_path / "a.usda")
    assert rc == 0 and "blendbsdf of a dielectric and an opaque BSDF" in err, err
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    sphere = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Sphere))
    surf = UsdShade.MaterialBindingAPI(sphere).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
    inputs = {i.GetBaseName(): i.Get() for i in surf.GetInputs()}
    assert inputs["opacity"] == pytest.approx(0.3) and inputs["ior"] == pytest.approx(1.5)
    assert inputs["roughness"] == 0.0 and "opacityThreshold" not in inputs
    assert cli("convert", tmp_path / "a.usda", tmp_path / "b.xml")[0] == 0
    assert 'type="blendbsdf"' in (tmp_path / "b.xml").read_text()
    assert _compare(_render(tmp_path / "b.xml"), _render(src)) < 0.3


@pytest.mark.parametrize("opacity, visible", [(0.3, False), (0.7, True)])
def test_opacity_threshold_is_a_cutout(cli, tmp_path, opacity, visible):
    """opacityThreshold 0.5: opacity 0.3 is no surface at all; 0.7 is presence 0.7 (a Mitsuba mask of 0.7)."""
    def cut(surf):
        author_lambertian(surf)
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.6, 0.6, 0.6))
        surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(opacity)
        surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
        surf.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.5)

    xml, _ = _usd_with_sphere_material(cli, tmp_path, cut)
    ours = _render(xml)
    if visible:
        ref = _render(_scene(tmp_path, "ref", BACKDROP + SPHERE.format(
            bsdf=f'<bsdf type="mask"><float name="opacity" value="{opacity}"/>{DIFFUSE}</bsdf>')))
        assert _compare(ours, ref) < 0.3
    else:
        empty = _render(_scene(tmp_path, "empty", BACKDROP))
        assert _compare(ours, empty, rtol=0.02) < 0.3
        assert np.abs(ours[16:32, 16:32] - empty[16:32, 16:32]).mean() < 0.05 * empty.mean()


def test_textured_mask_becomes_a_threshold_cutout_and_round_trips(cli, tmp_path):
    """A leaf-style mask texture -> USD opacity (red channel) with opacityThreshold 0.5 -> the same mask."""
    from usdrelight.imageio import write_image

    stripes = np.zeros((16, 16, 3), np.float32)
    stripes[:, ::4] = 1.0
    stripes[:, 1::4] = 1.0
    write_image(tmp_path / "leaf_mask.png", stripes, "uint8", srgb=False)
    bsdf = ('<bsdf type="mask"><texture type="bitmap" name="opacity"><string name="filename" value="leaf_mask.png"/>'
            '<boolean name="raw" value="true"/></texture>' + DIFFUSE + '</bsdf>')
    src = _scene(tmp_path, "a", BACKDROP + SPHERE.format(bsdf=bsdf))
    assert cli("convert", src, tmp_path / "a.usda")[0] == 0
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    sphere = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Sphere))
    surf = UsdShade.MaterialBindingAPI(sphere).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
    assert surf.GetInput("opacityThreshold").Get() == 0.5
    assert surf.GetInput("opacity").GetConnectedSource()[1] == "r"
    assert cli("convert", tmp_path / "a.usda", tmp_path / "b.xml")[0] == 0
    assert '<bsdf type="mask"' in (tmp_path / "b.xml").read_text()
    a, b = _render(src), _render(tmp_path / "b.xml")
    assert _compare(b, a) < 0.3
    full = _render(_scene(tmp_path, "opaque", BACKDROP + SPHERE.format(bsdf=DIFFUSE)))
    assert np.abs(a - full).mean() > 0.05 * full.mean()  # the stripes cut holes


PLANE = '<shape type="rectangle">{bsdf}</shape>'


@pytest.mark.parametrize("two", [False, True])
def test_one_sided_plane_is_black_from_behind_in_both(cli, tmp_path, two):
    """A bare diffuse plane (normal +Z) seen and lit from -Z: black in Mitsuba, and after XML -> USD -> XML
    (doubleSided false, no twosided written); wrapped in twosided: lit in both, doubleSided true."""
    diffuse = '<bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf>'
    src = _scene(tmp_path, "a", PLANE.format(bsdf=f'<bsdf type="twosided">{diffuse}</bsdf>' if two else diffuse),
                 z=-5, dz=1)
    rc, _, err = cli("convert", src, tmp_path / "a.usda")
    assert rc == 0 and (("one-sided BSDF 'diffuse'" in err) != two), err
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    mesh = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    assert UsdGeom.Mesh(mesh).GetDoubleSidedAttr().Get() == two
    assert cli("convert", tmp_path / "a.usda", tmp_path / "b.xml")[0] == 0
    assert ('type="twosided"' in (tmp_path / "b.xml").read_text()) == two
    a, b = _render(src), _render(tmp_path / "b.xml")
    if two:
        assert a.mean() > 0.1 and _compare(b, a) < 0.3
    else:
        assert a.max() == 0.0 and b.max() == 0.0
    # a USD edit that makes the gprim doubleSided renders it two-sided again
    if not two:
        UsdGeom.Mesh(mesh).GetDoubleSidedAttr().Set(True)
        stage.GetRootLayer().Export(str(tmp_path / "ds.usda"))
        assert cli("convert", tmp_path / "ds.usda", tmp_path / "ds.xml")[0] == 0
        assert _render(tmp_path / "ds.xml").mean() > 0.1


def test_wrapper_bsdfs_use_the_nested_one(cli, tmp_path):
    bsdf = ('<bsdf type="normalmap"><texture type="bitmap" name="normalmap"><string name="filename" value="n.png"/>'
            '</texture><bsdf type="twosided"><bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/>'
            '</bsdf></bsdf></bsdf>')
    from usdrelight.imageio import write_image

    write_image(tmp_path / "n.png", np.full((4, 4, 3), 0.5, np.float32), "uint8", srgb=False)
    src = _scene(tmp_path, "a", SPHERE.format(bsdf=bsdf))
    rc, _, err = cli("convert", src, tmp_path / "a.usda")
    assert rc == 0 and "normalmap (the perturbed normals ignored" in err and "grey" not in err, err
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    sphere = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Sphere))
    surf = UsdShade.MaterialBindingAPI(sphere).ComputeBoundMaterial()[0].ComputeSurfaceSource()[0]
    np.testing.assert_allclose(surf.GetInput("diffuseColor").Get(), (0.2, 0.4, 0.6), atol=1e-6)
    assert UsdGeom.Gprim(sphere).GetDoubleSidedAttr().Get() is True


def test_fast_engine_refuses_translucent_materials(cli, tmp_path):
    from usdrelight.engine.fast import FastRenderer
    from usdrelight.stage.read import read_scene

    def half(surf):
        author_lambertian(surf)
        surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(0.5)

    _usd_with_sphere_material(cli, tmp_path, half)
    rec = read_scene(Usd.Stage.Open(str(tmp_path / "edited.usda")))
    with pytest.raises(UsdRelightError, match="opaque Lambertian materials only"):
        FastRenderer(rec)


def test_doublesided_edit_on_a_sphere_wraps_its_one_sided_bsdf(cli, tmp_path):
    """Analytic gprims carry doubleSided too (ShapeRecord.double_sided): a one-sided conductor sphere is written
    bare, and in twosided once the sphere is made doubleSided."""
    src = _scene(tmp_path, "a", SPHERE.format(bsdf='<bsdf type="conductor"/>'))
    assert cli("convert", src, tmp_path / "a.usda")[0] == 0
    assert cli("convert", tmp_path / "a.usda", tmp_path / "b.xml")[0] == 0
    assert 'type="twosided"' not in (tmp_path / "b.xml").read_text()
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    sphere = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Sphere))
    assert UsdGeom.Gprim(sphere).GetDoubleSidedAttr().Get() is False
    UsdGeom.Gprim(sphere).GetDoubleSidedAttr().Set(True)
    stage.GetRootLayer().Export(str(tmp_path / "ds.usda"))
    assert cli("convert", tmp_path / "ds.usda", tmp_path / "ds.xml")[0] == 0
    assert 'type="twosided"' in (tmp_path / "ds.xml").read_text()
