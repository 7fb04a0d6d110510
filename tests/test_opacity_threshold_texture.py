"""UsdPreviewSurface opacityThreshold with a TEXTURED opacity (the spec's cutout: presence = opacity where
opacity >= threshold, else 0) rendered by Mitsuba, in memory (`usdrelight render`) and through the XML export
(the thresholded map baked into ``textures/``), against a closed form built from two Mitsuba renders.

The scene (64 x 16 px, 128 spp): a diffuse plane filling the view exactly (column j sees u in [j/64, (j+1)/64]) in front of
an emitting backdrop, lit by a constant environment. A pixel through presence p is p A + (1 - p) B with A the
render with the opaque plane and B the render without it (same seed). The opacity map is a 16-texel gradient,
texel i = (i + 0.5) / 16, so its bilinear filtering is opacity(u) = u (clamped to the texel centres at the ends);
threshold 0.5: the backdrop alone where u < 0.5, presence u elsewhere. The cut at u = 0.5 lies mid-way between
two texel centres (the texture is magnified 4x: the hard case for a filtered, thresholded map).
"""
import json
import math

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade

from conftest import ROOT
from usdrelight.imageio import read_photo, read_raw, write_image
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.stage.create import author_lambertian, author_uv_texture, define_preview_material

W, H, N, SPP, D = 64, 16, 16, 128, 4.0
SCENE = f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective"><float name="fov" value="{2 * math.degrees(math.atan(1 / D))!r}"/>
    <string name="fov_axis" value="x"/>
    <transform name="to_world"><lookat origin="0, 0, {D}" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="{SPP}"/></sampler>
    <film type="hdrfilm"><integer name="width" value="{W}"/><integer name="height" value="{H}"/>
      <rfilter type="box"/></film>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
  <shape type="rectangle"><transform name="to_world"><scale value="10"/><translate z="-2"/></transform>
    <emitter type="area"><rgb name="radiance" value="0.1, 0.2, 0.8"/></emitter></shape>
  {{plane}}
</scene>"""
PLANE = ('<shape type="rectangle" id="plane"><bsdf type="twosided"><bsdf type="diffuse">'
         '<rgb name="reflectance" value="0.8, 0.3, 0.1"/></bsdf></bsdf></shape>')


def _render(path) -> np.ndarray:
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), seed=0), np.float64)[..., :3]


def _presence() -> np.ndarray:
    """Closed form per column: the mean over the column of presence(u) = op(u) if op(u) >= 0.5 else 0,
    op the bilinear filtering (clamped) of the 16 gradient texels."""
    u = (np.arange(W * 256) + 0.5) / (W * 256)
    op = (np.clip(u * N - 0.5, 0, N - 1) + 0.5) / N
    return np.where(op >= 0.5, op, 0.0).reshape(W, 256).mean(1)


@pytest.fixture(scope="module")
def cutout(tmp_path_factory):
    """(A, B, the USD stage path): the plane's material replaced by a pxr-authored one whose opacity reads the
    gradient's red channel (``grad.png``, raw), opacityThreshold 0.5."""
    from usdrelight.cli import main

    tmp = tmp_path_factory.mktemp("cutout")
    (tmp / "a.xml").write_text(SCENE.format(plane=PLANE))
    (tmp / "b.xml").write_text(SCENE.format(plane=""))
    src = tmp / "src"
    src.mkdir()
    assert main(["convert", str(tmp / "a.xml"), str(src / "a.usda")]) == 0
    grad = np.tile(((np.arange(N) + 0.5) / N)[None, :, None], (4, 1, 3)).astype(np.float32)
    grad[..., 1:] = 1.0 - grad[..., 1:]  # green and blue run the other way: only red may be used
    write_image(src / "grad.png", grad, "uint16")
    stage = Usd.Stage.Open(str(src / "a.usda"))
    plane = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    mat, surf = define_preview_material(stage, "/World/Looks/Cut")
    author_lambertian(surf)
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.8, 0.3, 0.1))
    author_uv_texture(stage, surf, "opacity", "grad.png", "raw", "/World/Looks/Cut/Opacity",
                      "/World/Looks/Cut/St", output="r")
    surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.5)
    UsdShade.MaterialBindingAPI.Apply(plane).Bind(mat)
    stage.GetRootLayer().Export(str(src / "cut.usda"))
    return _render(tmp / "a.xml"), _render(tmp / "b.xml"), src / "cut.usda"


def _check(img, A, B):
    """Column means against p A + (1 - p) B, errors as fractions of |A - B|: the backdrop exactly where
    u < 0.5; elsewhere within 5% but the column just after the cut (presence ramps up over 2/8 texel = 1 px there)."""
    p = _presence()[:, None]
    a, b, got = A.mean(0), B.mean(0), img.mean(0)
    err = (np.abs(got - (p * a + (1 - p) * b)) / np.abs(a - b)).max(1)
    print("column errors:", np.round(err, 3).tolist())
    assert np.abs(got[:W // 2] - b[:W // 2]).max() < 1e-4 * b.max()  # u < 0.5: the backdrop alone
    assert err[W // 2 + 1:].max() < 0.05
    assert err[W // 2] < 0.3
    assert got[W // 2 + 1:, 0].min() > 1.5 * b[0, 0]  # the plane's red is there, at presence u >= 0.5


def test_render_cuts_a_textured_opacity_at_the_threshold(cli, cutout, tmp_path):
    A, B, stage = cutout
    rc, out, err = cli("render", stage, "-o", tmp_path, "--spp", str(SPP), "--seed", "0", "--json")
    assert rc == 0, err
    assert "opacityThreshold" not in out
    _check(read_photo(tmp_path / "renders" / "color.exr").astype(np.float64), A, B)


def test_xml_export_bakes_the_thresholded_map_and_nothing_else(cli, cutout, tmp_path):
    A, B, stage = cutout
    rc, out, err = cli("convert", stage, tmp_path / "cut.xml", "--json")
    assert rc == 0, err
    assert "opacityThreshold" not in out
    files = {str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file()}
    (baked,) = [f for f in files if f.startswith("textures/")]
    assert baked.startswith("textures/grad_cutout_") and baked.endswith(".exr")
    assert files == {"cut.xml", baked} | {f for f in files if f.startswith("meshes/")}
    assert {str(tmp_path / f) for f in files} == set(json.loads(out)["files"])
    texels, is_float = read_raw(tmp_path / baked)
    assert is_float and texels.shape == (8 * 4, 8 * N, 1)  # one float channel, 8x finer
    assert set(np.unique(texels[:, :4 * N])) == {0.0} and texels[:, 4 * N + 2:].min() >= 0.5
    _check(_render(tmp_path / "cut.xml"), A, B)


def test_mitsuba_leaf_mask_round_trip_renders_the_same(cli, tmp_path):
    """bsdf_mask.xml (Mitsuba's leaf_mask.png on a quad) -> USD (opacity from red, threshold 0.5) -> XML with the
    thresholded map: texels of the leaf's soft edge below 0.5 are now cut, the rest of the image is unchanged."""
    corpus = ROOT / "tests" / "data" / "mitsuba_corpus"
    assert cli("convert", corpus / "bsdf_mask.xml", tmp_path / "m.usda")[0] == 0
    rc, out, err = cli("convert", tmp_path / "m.usda", tmp_path / "m.xml", "--allow-path", corpus)
    assert rc == 0, err
    text = (tmp_path / "m.xml").read_text()
    assert "_cutout_" in text and "leaf_mask.png" not in text
    a, b = _render(corpus / "bsdf_mask.xml"), _render(tmp_path / "m.xml")
    rmse = float(np.sqrt(np.mean((a - b) ** 2)) / a.mean())
    print(f"means {a.mean():.5f} vs {b.mean():.5f}, rel RMSE {rmse:.4f}")
    assert b.mean() == pytest.approx(a.mean(), rel=0.01) and rmse < 0.1
