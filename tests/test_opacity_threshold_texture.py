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


def _leaf_round_trip(cli, tmp_path, coverage: bool):
    """bsdf_mask.xml -> USD -> XML with the leaf material's customData ``"mask": "coverage"`` set (the XML
    reader's mark) or cleared (the USD alone); returns (the original render, the round trip's, the XML text)."""
    corpus = ROOT / "tests" / "data" / "mitsuba_corpus"
    assert cli("convert", corpus / "bsdf_mask.xml", tmp_path / "m.usda")[0] == 0
    stage = Usd.Stage.Open(str(tmp_path / "m.usda"))
    (leaf,) = [p for p in stage.Traverse() if p.IsA(UsdShade.Material) and p.GetChild("opacityTexture")]
    extra = json.loads(leaf.GetCustomDataByKey("mitsuba") or "{}")
    extra = {**extra, "mask": "coverage"} if coverage else {k: v for k, v in extra.items() if k != "mask"}
    leaf.SetCustomDataByKey("mitsuba", json.dumps(extra))
    stage.GetRootLayer().Export(str(tmp_path / "e.usda"))
    rc, _, err = cli("convert", tmp_path / "e.usda", tmp_path / "m.xml", "--allow-path", corpus)
    assert rc == 0, err
    mi = load_mitsuba()
    a, b = (np.array(mi.render(mi.load_file(str(x)), spp=64, seed=0), np.float64)[..., :3]
            for x in (corpus / "bsdf_mask.xml", tmp_path / "m.xml"))
    return a, b, (tmp_path / "m.xml").read_text()


def test_mitsuba_leaf_mask_round_trip_keeps_the_coverage(cli, tmp_path):
    """bsdf_mask.xml (Mitsuba's leaf_mask.png on a quad) -> USD (opacity from red, threshold 0.5, the material
    marked ``"mask": "coverage"``) -> XML: the texture is the mask's coverage again, the same image (same paths)."""
    a, b, text = _leaf_round_trip(cli, tmp_path, coverage=True)
    assert "leaf_mask.png" in text and "_cutout_" not in text
    rmse = float(np.sqrt(np.mean((a - b) ** 2)) / a.mean())
    print(f"means {a.mean():.5f} vs {b.mean():.5f}, rel RMSE {rmse:.4f}")
    assert b.mean() == pytest.approx(a.mean(), rel=1e-3) and rmse < 0.005


def test_leaf_mask_from_the_usd_alone_is_cut_at_the_threshold(cli, tmp_path):
    """The same stage without the mark (what another USD tool would hand over): the spec's cutout, the leaf's soft
    edge texels below 0.5 cut; the rest of the image unchanged (measured at 64 spp: means +0.13%, rel RMSE 0.013)."""
    a, b, text = _leaf_round_trip(cli, tmp_path, coverage=False)
    assert "_cutout_" in text and "leaf_mask.png" not in text
    rmse = float(np.sqrt(np.mean((a - b) ** 2)) / a.mean())
    print(f"means {a.mean():.5f} vs {b.mean():.5f}, rel RMSE {rmse:.4f}")
    assert b.mean() == pytest.approx(a.mean(), rel=0.01) and rmse < 0.05


TEXELS = np.uint8([51, 153, 230, 179])  # RGBA 0.2, 0.6, 0.902, 0.702 as stored (PNG alpha is unassociated)


@pytest.mark.parametrize("channel, space, scale, bias, expect", [
    ("r", "auto", 1.0, 0.0, "cut"),  # 0.2 sRGB-decoded to 0.033: below 0.3
    ("g", "auto", 1.0, 0.0, "srgb"),  # 0.6 decoded to 0.319: kept
    ("g", "raw", 1.0, 0.0, "value"),
    ("g", "raw", 0.5, 0.1, "value"),  # scale and bias of the channel used: 0.4
    ("b", "raw", 0.3, 0.0, "cut"),  # 0.27 after scale
    ("a", "sRGB", 1.0, 0.0, "value"),  # alpha is never decoded
    ("rgb", "raw", 1.0, 0.0, "cut"),  # red
])
def test_presence_map_uses_the_channel_colour_space_scale_and_bias(tmp_path, channel, space, scale, bias, expect):
    """A constant 8-bit RGBA texture, threshold 0.3: the baked map is the UsdUVTexture output of the channel
    (texel decoded from sRGB unless raw, alpha never; times scale plus bias) where it is >= 0.3, else 0."""
    from usdrelight.imageio import srgb_to_linear
    from usdrelight.mitsuba.cutout import cutout_spec, presence_map
    from usdrelight.stage.records import TextureRecord

    mi = load_mitsuba()
    mi.Bitmap(np.tile(TEXELS, (2, 3, 1)), mi.Bitmap.PixelFormat.RGBA).write(str(tmp_path / "t.png"))
    tex = TextureRecord(str(tmp_path / "t.png"), space, (scale,) * 4, (bias,) * 4, channel)
    got = presence_map(cutout_spec(tex, 0.3))
    v = TEXELS[{"r": 0, "g": 1, "b": 2, "a": 3, "rgb": 0}[channel]] / 255.0
    want = {"cut": 0.0, "srgb": float(srgb_to_linear(np.float32(v))), "value": v * scale + bias}[expect]
    assert got.shape == (2 * 8, 3 * 8, 1) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_presence_map_cuts_a_step_in_alpha_without_a_fringe_on_the_cut_side(tmp_path):
    """Alpha 0.2 0.2 0.9 0.9 (a 4-texel row), threshold 0.5: the map, 8x finer, is the opacity where it is >= 0.5
    except the sample next to the cut (0), so Mitsuba's bilinear filtering of it is exactly 0 wherever the
    filtered opacity is below 0.5, and exactly the opacity from 2/8 texel past the cut on (but next to the
    opacity's kinks at texel centres, where the fine samples' filtering rounds the corner)."""
    from usdrelight.mitsuba.cutout import cutout_spec, presence_map
    from usdrelight.stage.records import TextureRecord

    rgba = np.ones((1, 4, 4), np.float32)
    rgba[..., 3] = [0.2, 0.2, 0.9, 0.9]
    write_image(tmp_path / "t.exr", rgba, "float")
    row = presence_map(cutout_spec(TextureRecord(str(tmp_path / "t.exr"), "raw", channel="a"), 0.5))[0, :, 0]

    def opacity(u):  # Mitsuba's bilinear filtering of the 4 texels, clamped
        return np.interp(u * 4 - 0.5, [0, 1, 2, 3], [0.2, 0.2, 0.9, 0.9])

    u = (np.arange(32) + 0.5) / 32
    below = opacity(u) < 0.5
    near = below | np.r_[False, below[:-1]] | np.r_[below[1:], False]
    np.testing.assert_allclose(row, np.where(near, 0.0, opacity(u)), atol=1e-6)
    fine = (np.arange(32 * 64) + 0.5) / (32 * 64)
    filtered = np.interp(fine * 32 - 0.5, np.arange(32), row)
    assert np.all(filtered[opacity(fine) < 0.5] == 0.0)
    cut = fine[opacity(fine) >= 0.5][0]
    # past the cut, but within one fine sample of the kinks at the texel centres u = 5/8 and 7/8 (0.02 off there)
    past = (fine >= cut + 2 / 32) & (np.abs(fine - 0.625) > 1 / 32) & (np.abs(fine - 0.875) > 1 / 32)
    np.testing.assert_allclose(filtered[past], opacity(fine[past]), atol=1e-6)


def test_a_dip_below_the_threshold_at_a_texel_centre_is_cut(tmp_path):
    """A 3 x 3 opacity of 0.9 with a centre texel of 0.3, threshold 0.32: the filtered opacity dips below the
    threshold only right at the centre texel, between the fine samples; the presence map is 0 there all the same."""
    from usdrelight.mitsuba.cutout import cutout_spec, presence_map
    from usdrelight.stage.records import TextureRecord

    t = np.full((3, 3, 3), 0.9, np.float32)
    t[1, 1] = 0.3
    write_image(tmp_path / "t.exr", t, "float")
    pm = presence_map(cutout_spec(TextureRecord(str(tmp_path / "t.exr"), "raw", channel="r"), 0.32))[..., 0]
    h, w = pm.shape
    assert pm[h // 2, w // 2] == 0.0 and pm[h // 3:2 * h // 3, w // 3:2 * w // 3].max() == 0.0
    assert pm.max() == pytest.approx(0.9, abs=1e-6)
