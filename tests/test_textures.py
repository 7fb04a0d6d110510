"""UsdUVTexture wrapS / wrapT, scale / bias, output channel and a UsdTransform2d on the st, in Mitsuba
(``usdrelight render``) and in Cycles (``convert s.usda s.blend`` + ``render_blend``).

The stage: a camera 1 m above a floor looking straight down, the floor filling the 64 x 64 image exactly (so
pixel centre (row i, column j) sees st = uv_max * ((j + 0.5) / W, 1 - (i + 0.5) / H)), lit only by a
DistantLight of irradiance E = 3 straight down: a Lambertian floor of albedo a has radiance a E / pi. The texture
is a 32 x 32 float EXR with a 2 x 2 checker (0.2 bottom-left / top-right, 0.8 elsewhere; raw). The expected
image is the spec's lookup at each pixel centre (st' = R (scale st) + translation, then the wrap), compared on
"clean" pixels, those whose neighbourhood (+-0.75 px) looks up the same checker cell, so that neither the pixel
filter nor bilinear texel filtering blends two cells there.
"""
import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade

from usd_scenes import camera, new_stage
from usdrelight.converters.blender import render_blend
from usdrelight.imageio import read_map, write_image
from usdrelight.intrinsics import Intrinsics
from usdrelight.mitsuba.runtime import load_mitsuba

W = H = 64
E = 3.0
LOW, HIGH = 0.2, 0.8


def checker(n: int = 32) -> np.ndarray:
    """(n, n) in image rows (row 0 = top = t near 1): 0.2 in the bottom-left and top-right quadrants."""
    img = np.full((n, n), HIGH, np.float32)
    h = n // 2
    img[h:, :h] = LOW  # bottom-left (s < 0.5, t < 0.5)
    img[:h, h:] = LOW  # top-right
    return img


def _wrap(x, mode):
    if mode == "repeat":
        return x - np.floor(x)
    if mode == "mirror":
        y = x - 2.0 * np.floor(x / 2.0)
        return np.where(y <= 1.0, y, 2.0 - y)
    if mode == "clamp":
        return np.clip(x, 0.0, 1.0 - 1e-9)
    raise ValueError(mode)


def expected_cells(uv_max, wrap, xf=None):
    """The checker cell (0 / 1: which of LOW / HIGH) each pixel looks up per the spec, and the clean mask."""
    def cell(di, dj):
        j, i = np.meshgrid(np.arange(W) + 0.5 + dj, np.arange(H) + 0.5 + di)
        s, t = uv_max * j / W, uv_max * (1.0 - i / H)
        if xf:
            a = np.radians(xf.get("rotation", 0.0))
            sx, sy = xf.get("scale", (1.0, 1.0))
            tx, ty = xf.get("translation", (0.0, 0.0))
            s, t = np.cos(a) * sx * s - np.sin(a) * sy * t + tx, np.sin(a) * sx * s + np.cos(a) * sy * t + ty
        u, v = _wrap(s, wrap), _wrap(t, wrap)
        return ((u < 0.5) == (v < 0.5)).astype(int)  # 1: LOW (bottom-left / top-right)
    c = cell(0, 0)
    clean = np.ones_like(c, bool)
    for di in (-0.75, 0.75):
        for dj in (-0.75, 0.75):
            clean &= cell(di, dj) == c
    return c, clean


def make_stage(path, tex_file, uv_max=4.0, wrap=None, xf=None, output="rgb", scale=None, bias=None):
    stage = new_stage(path)
    mat = UsdShade.Material.Define(stage, "/World/Looks/M")
    sh = UsdShade.Shader.Define(stage, "/World/Looks/M/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    sh.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    sh.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    tex = UsdShade.Shader.Define(stage, "/World/Looks/M/Tex")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(tex_file)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    if wrap:
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap)
    if scale is not None:
        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*scale))
    if bias is not None:
        tex.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*bias))
    rd = UsdShade.Shader.Define(stage, "/World/Looks/M/St")
    rd.CreateIdAttr("UsdPrimvarReader_float2")
    rd.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    src = rd.ConnectableAPI()
    if xf:
        t2 = UsdShade.Shader.Define(stage, "/World/Looks/M/Xf")
        t2.CreateIdAttr("UsdTransform2d")
        t2.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(src, "result")
        t2.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*xf.get("scale", (1, 1))))
        t2.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(float(xf.get("rotation", 0.0)))
        t2.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*xf.get("translation", (0, 0))))
        src = t2.ConnectableAPI()
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(src, "result")
    tex.CreateOutput(output, Sdf.ValueTypeNames.Float3 if output == "rgb" else Sdf.ValueTypeNames.Float)
    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), output)
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")

    half = float(np.tan(np.radians(20.0)))  # the floor fills the image of a 40-degree camera 1 m above it
    m = UsdGeom.Mesh.Define(stage, "/World/Floor")
    m.CreatePointsAttr([(-half, 0, half), (half, 0, half), (half, 0, -half), (-half, 0, -half)])
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([(0, 0), (uv_max, 0), (uv_max, uv_max), (0, uv_max)])
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(mat)
    sun = UsdLux.DistantLight.Define(stage, "/World/Sun")
    sun.CreateIntensityAttr(E)
    UsdGeom.Xformable(sun).AddRotateXOp().Set(-90.0)  # shining straight down
    camera(stage, Intrinsics.from_fov_x(40.0, W, H), translate=(0, 1.0, 0), rotate_x_deg=-90.0)
    stage.GetRootLayer().Save()
    return path


def mitsuba_image(cli, usda):
    rc, _, err = cli("render", usda, "--spp", "16")
    assert rc == 0, err
    return read_map(usda.parent / "renders" / "color.exr", 3)


def cycles_image(cli, usda):
    blend = usda.with_suffix(".blend")
    assert cli("convert", usda, blend)[0] == 0
    return read_map(render_blend(blend, usda.with_suffix(".cycles.exr"), spp=16), 3)


def check_checker(img, uv_max, wrap, xf=None, rtol=0.03, what=""):
    cells, clean = expected_cells(uv_max, wrap, xf)
    want = np.where(cells == 1, LOW, HIGH) * E / np.pi
    got = img.mean(-1)
    err = np.abs(got - want)[clean] / want[clean]
    msg = f"{what}: {clean.sum()} clean px, max rel. error {err.max():.4f}, mean {err.mean():.4f}"
    print(msg)
    assert clean.sum() > 0.3 * W * H, msg
    assert err.max() < rtol, msg
    return msg


@pytest.fixture
def checker_file(tmp_path):
    write_image(tmp_path / "checker.exr", np.repeat(checker()[..., None], 3, -1), "float")
    return "./checker.exr"


CASES = {  # name -> (wrap, UsdTransform2d)
    "repeat": ("repeat", None),
    "mirror": ("mirror", None),
    "clamp": ("clamp", None),
    "transform": ("repeat", {"scale": (2.0, 2.0), "translation": (0.25, 0.25)}),
    "rotated": ("mirror", {"scale": (1.5, 1.0), "rotation": 30.0, "translation": (0.1, -0.2)}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_wrap_and_st_transform_in_mitsuba(cli, tmp_path, checker_file, case):
    """UVs 0..4: repeat gives 4 x 4 checker tiles (8 cells, 7 edges along a row), mirror reflects every other
    tile, clamp holds the edge texels beyond st = 1; a UsdTransform2d scale 2 + translation 0.25 shifts the cells
    by a quarter of a tile (in st') and doubles their count; scale (1.5, 1), rotation 30 deg, translation
    (0.1, -0.2) turns them counter-clockwise (in st); every clean pixel is a E / pi of its cell."""
    wrap, xf = CASES[case]
    uv_max = 2.0 if xf else 4.0
    usda = make_stage(tmp_path / "s.usda", checker_file, uv_max, wrap, xf)
    img = mitsuba_image(cli, usda)
    check_checker(img, uv_max, wrap, xf, what=f"Mitsuba {case}")
    if case == "repeat":  # 4 x 4 tiles of a 2 x 2 checker: 7 light/dark edges along the middle row
        row = img[H // 2 + 2].mean(-1) > 0.5 * (LOW + HIGH) * E / np.pi
        assert int(np.count_nonzero(row[1:] != row[:-1])) == 7


@pytest.mark.parametrize("case", ["repeat", "mirror", "transform", "rotated"])
def test_wrap_and_st_transform_in_cycles(cli, tmp_path, checker_file, case):
    """The same stages as .blend in Cycles: Image Texture extension REPEAT / MIRROR, a Mapping node for the
    UsdTransform2d; the same clean pixels, and the image mean within 5% of Mitsuba's."""
    wrap, xf = CASES[case]
    uv_max = 2.0 if xf else 4.0
    usda = make_stage(tmp_path / "s.usda", checker_file, uv_max, wrap, xf)
    c = cycles_image(cli, usda)
    check_checker(c, uv_max, wrap, xf, rtol=0.05, what=f"Cycles {case}")
    m = mitsuba_image(cli, usda)
    assert abs(c.mean() / m.mean() - 1) < 0.05, (c.mean(), m.mean())


def test_scale_bias_and_channel_closed_form(cli, tmp_path):
    """A constant texel (0.9, 0.6, 0.3): rgb x scale 0.5 + bias 0.1 -> (0.55, 0.4, 0.25) x E / pi; output 'g'
    (a grey colour) x scale 0.5 + bias 0.1 -> 0.4 x E / pi in every channel; Mitsuba (render, and the XML export
    with its baked texture) and Cycles."""
    write_image(tmp_path / "const.exr", np.broadcast_to(np.float32([0.9, 0.6, 0.3]), (8, 8, 3)).copy(), "float")
    sc, bi = (0.5, 0.5, 0.5, 1.0), (0.1, 0.1, 0.1, 0.0)
    for output, want in (("rgb", np.array([0.55, 0.4, 0.25])), ("g", np.full(3, 0.4))):
        d = tmp_path / output
        d.mkdir()
        (d / "const.exr").write_bytes((tmp_path / "const.exr").read_bytes())
        usda = make_stage(d / "s.usda", "./const.exr", 1.0, "clamp", output=output, scale=sc, bias=bi)
        xml = usda.with_suffix(".xml")  # the XML export bakes the scaled texture into textures/
        assert cli("convert", usda, xml)[0] == 0
        assert list((d / "textures").glob("const_baked_*.exr"))
        mi = load_mitsuba()
        from_xml = np.array(mi.render(mi.load_file(str(xml)), spp=4), np.float64)[..., :3]
        for name, img in (("Mitsuba", mitsuba_image(cli, usda)), ("Cycles", cycles_image(cli, usda)),
                          ("Mitsuba XML", from_xml)):
            got = img[8:-8, 8:-8].reshape(-1, 3).mean(0)
            rel = np.abs(got / (want * E / np.pi) - 1)
            print(f"{name} {output}: {got} vs {want * E / np.pi} (max rel. {rel.max():.4f})")
            assert rel.max() < 0.03, (name, output, got, want * E / np.pi)


def test_black_and_mixed_wraps(cli, tmp_path, checker_file):
    """wrap 'black' (and an unauthored wrap: useMetadata, the spec's fallback black): Cycles' CLIP is black
    beyond st = 1; Mitsuba has no black wrap (clamp, warned); wrapS != wrapT: wrapS used, warned."""
    usda = make_stage(tmp_path / "s.usda", checker_file, 2.0, "black")
    c = cycles_image(cli, usda)
    beyond = c[4:H // 2 - 4, W // 2 + 4:-4]  # s in (1, 2), t in (1, 2): outside the texture
    assert beyond.max() < 1e-3, beyond.max()
    inside = c[H // 2 + 4:-4, 4:W // 2 - 4].mean()  # s, t in (0, 1): the checker, mean (0.2 + 0.8) / 2 E / pi
    assert abs(inside / (0.5 * (LOW + HIGH) * E / np.pi) - 1) < 0.15, inside
    w = cli.json("convert", usda, tmp_path / "s.xml")["write_warnings"]
    assert any("wrap 'black'" in k for k in w), w
    stage = Usd.Stage.Open(str(usda))
    tex = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/M/Tex"))
    tex.GetInput("wrapT").Set("repeat")
    stage.Save()
    w = cli.json("convert", usda, tmp_path / "t.xml")["write_warnings"]
    assert any("wrapS 'black' != wrapT 'repeat'" in k for k in w), w


@pytest.mark.parametrize("mode", ["repeat", "mirror", "clamp"])
def test_cutout_upsampling_follows_the_wrap(mode):
    """The cutout's baked presence map (mitsuba/cutout.py) is upsampled at Mitsuba's sample positions with the
    texture's wrap: equal to Mitsuba's own bilinear lookup of the source with that wrap_mode (2.4e-7 measured)."""
    from usdrelight.mitsuba.cutout import _upsample

    mi = load_mitsuba()
    v = np.random.default_rng(0).random((5, 7)).astype(np.float32)
    up = _upsample(v, 4, mode == "repeat")
    tex = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(v[..., None]), "raw": True, "wrap_mode": mode})
    si = mi.SurfaceInteraction3f()
    j, i = np.meshgrid((np.arange(up.shape[1]) + 0.5) / up.shape[1], (np.arange(up.shape[0]) + 0.5) / up.shape[0])
    si.uv = mi.Point2f(j.ravel().astype(np.float32), i.ravel().astype(np.float32))
    got = np.array(tex.eval_1(si)).reshape(up.shape)
    assert np.abs(got - up).max() < 1e-5, np.abs(got - up).max()
