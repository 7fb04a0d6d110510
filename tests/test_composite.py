"""Compositing modes: closed-form definitions and the relight session end to end."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from usdrelight.imageio import read_photo, resize_image
from usdrelight.relight.composite import (add_composite, ratio_composite, ratio_guard, transfer_apply,
                                          transfer_reference)
from usdrelight.relight.light_match import match_angles, match_weight
from usdrelight.relight.session import RelightSession
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.records import FitProvenance, PointLightValue

from conftest import EXAMPLES, build_procedural

RNG = np.random.default_rng(3)
PHOTO = RNG.random((12, 16, 3)).astype(np.float32)
VALID = np.ones((12, 16), bool)
VALID[:3, :4] = False


def test_ratio_of_identical_renders_gives_the_photo_back():
    f = RNG.random((12, 16, 3)).astype(np.float32)
    f[5, 5] = 0.0  # a black pixel of the fitted render stays finite and exact
    np.testing.assert_allclose(ratio_composite(PHOTO, f, f, VALID), PHOTO, rtol=1e-6, atol=1e-7)


def test_ratio_scales_by_the_light_change_and_never_darkens_when_light_is_added():
    f = RNG.random((12, 16, 3)).astype(np.float32) + 0.5
    k_up, k_down = ratio_guard(PHOTO, f, VALID)
    # brightening is guarded by twice the fit's RMS error (here large: PHOTO and f are unrelated), dimming by 1%
    np.testing.assert_allclose(k_up, 2 * np.sqrt(((PHOTO - f)[VALID] ** 2).mean(0)), rtol=1e-6)
    np.testing.assert_allclose(k_down, 0.01 * f[VALID].mean(0), rtol=1e-6)
    np.testing.assert_allclose(ratio_composite(PHOTO, 2 * f, f, VALID)[VALID],
                               (PHOTO * (2 * f + k_up) / (f + k_up))[VALID], rtol=1e-5)
    np.testing.assert_allclose(ratio_composite(PHOTO, 0.5 * f, f, VALID)[VALID],
                               (PHOTO * (0.5 * f + k_down) / (f + k_down))[VALID], rtol=1e-5)
    np.testing.assert_allclose(ratio_composite(PHOTO, 2 * f, f, VALID, k=(1e-9, 1e-9))[VALID], 2 * PHOTO[VALID],
                               rtol=1e-5)
    # continuous across N = F: the two guards meet at a gain of 1
    eps = np.float32(1e-4)
    below, above = (ratio_composite(PHOTO, f * (1 + s * eps), f, VALID) for s in (-1, 1))
    assert np.max(np.abs(above - below)[VALID]) < 1e-3
    added = f + RNG.random(f.shape).astype(np.float32)
    assert np.all(ratio_composite(PHOTO, added, f, VALID) >= PHOTO - 1e-6)
    assert np.all(np.isfinite(ratio_composite(PHOTO, f * 0, f * 0, VALID)))


def test_add_with_no_added_light_gives_the_photo_and_never_darkens():
    np.testing.assert_array_equal(add_composite(PHOTO, np.zeros_like(PHOTO)), PHOTO)
    assert np.all(add_composite(PHOTO, RNG.random(PHOTO.shape)) >= PHOTO)


def _shading(h=48, w=64, x0=0.3):
    """A smooth Lambertian-like shading pool centred at x0 (fraction of the width)."""
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    s = 1.0 / (1.0 + 20 * ((xx - x0) ** 2 + (yy - 0.5) ** 2))
    return np.repeat(s[..., None], 3, 2).astype(np.float32)


def test_transfer_is_the_render_when_the_photo_adds_nothing_and_the_photo_when_the_light_is_the_fit():
    f = _shading(x0=0.3) * np.array([0.5, 0.4, 0.3], np.float32)
    valid = np.ones(f.shape[:2], bool)
    new = _shading(x0=0.8) * np.array([0.2, 0.5, 0.6], np.float32)
    # a photo the fit explains exactly: r = 0, the transfer is the new render itself, whatever the light, when the
    # renders' own fine shading is kept (b = 1) or does not change between them (N~ = 2 F~)
    np.testing.assert_allclose(transfer_apply(new, transfer_reference(f, f, valid), 1.0, render_detail=1.0), new,
                               rtol=1e-6)
    np.testing.assert_allclose(transfer_apply(2 * f, transfer_reference(f, f, valid), 0.3), 2 * f, rtol=1e-3)
    # a photo with texture the fit does not explain; lit by the photo's own light (w = 1, nothing clipped):
    # F exp(L(r) + H(r)) = F (I + k) / (F + k), i.e. the photo up to the 1% guard k
    tex = (1.0 + 0.3 * np.sign(np.sin(np.arange(64) * 1.3)))[None, :, None].astype(np.float32)
    photo = f * tex
    ref = transfer_reference(photo, f, valid, sigma=2.0, clip=7.0)
    k = 0.01 * f.reshape(-1, 3).mean(0)
    np.testing.assert_allclose(transfer_apply(2.0 * f, ref, 1.0, render_detail=1.0), 2.0 * f * (photo + k) / (f + k),
                               rtol=1e-5)


def test_transfer_takes_the_fine_scale_from_the_photo_and_the_coarse_scale_from_the_new_render():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(3)
    f = _shading(x0=0.25)
    valid = np.ones(f.shape[:2], bool)
    tex = np.exp(0.2 * rng.standard_normal(f.shape[:2]))[..., None].astype(np.float32)  # the photo's texture
    noise = np.exp(0.2 * rng.standard_normal(f.shape[:2]))[..., None].astype(np.float32)  # the new render's own
    new = _shading(x0=0.75) * noise  # fine shading (mesh noise, renderer noise): not in the photo
    ref = transfer_reference(f * tex, f, valid, sigma=2.0)
    hp = lambda a: np.log(a.mean(-1)) - gaussian_filter(np.log(a.mean(-1)), 2.0)  # noqa: E731
    corr = lambda a, b: np.corrcoef(hp(a)[4:-4, 4:-4].ravel(), hp(b)[4:-4, 4:-4].ravel())[0, 1]  # noqa: E731
    kept, dropped = transfer_apply(new, ref, 0.0, render_detail=1.0), transfer_apply(new, ref, 0.0, render_detail=0.0)
    assert corr(kept, noise.repeat(3, 2)) > 0.5 and corr(dropped, noise.repeat(3, 2)) < 0.1  # the render's detail
    assert corr(dropped, tex.repeat(3, 2)) > 0.95 > corr(kept, tex.repeat(3, 2))  # the photo's detail
    # the coarse scale is the new light's either way
    smooth = _shading(x0=0.75)
    for out in (kept, dropped):
        lo = gaussian_filter(out.mean(-1), 4) / gaussian_filter(smooth.mean(-1), 4)
        assert np.all(np.abs(lo[8:-8, 8:-8] - 1.0) < 0.08)
    # bounded: never below e^-c of the render, whatever b
    from usdrelight.relight.composite import TRANSFER_CLIP

    for b in (0.0, 0.5, 1.0, float("nan")):
        o = transfer_apply(new, ref, 0.0, render_detail=b)
        assert np.all(np.isfinite(o)) and np.all(o >= np.exp(-TRANSFER_CLIP) * new * (1 - 1e-5))


def test_transfer_keeps_the_photo_detail_not_the_old_light_under_a_moved_light():
    from scipy.ndimage import gaussian_filter

    f = _shading(x0=0.25)
    new = _shading(x0=0.75)
    valid = np.ones(f.shape[:2], bool)
    rng = np.random.default_rng(0)
    tex = np.exp(0.2 * rng.standard_normal(f.shape[:2]))[..., None].astype(np.float32)
    photo = f * tex * 1.2  # the fit 20% too dark: a low-frequency residual that belongs to the old light
    out = transfer_apply(new, transfer_reference(photo, f, valid, sigma=2.0), 0.0)  # a light from elsewhere
    assert np.all(np.isfinite(out)) and out.min() >= 0
    hp = lambda a: np.log(a.mean(-1)) - gaussian_filter(np.log(a.mean(-1)), 2.0)  # noqa: E731
    assert np.corrcoef(hp(out).ravel(), hp(tex[..., 0:1].repeat(3, 2)).ravel())[0, 1] > 0.8  # the texture is kept
    # low frequencies: the new light's pool, not the old one's 20% (the fit's error under the old light)
    lo = gaussian_filter(out.mean(-1), 4) / gaussian_filter(new.mean(-1), 4)
    # (up to 6%: below the split scale the shading itself is the photo's, and so is the old light's curvature there)
    assert np.all(np.abs(lo[8:-8, 8:-8] - 1.0) < 0.08)
    # extreme inputs: a black photo, a black fit, huge values: finite and >= 0
    for p_, f_ in ((np.zeros_like(f), f), (photo, np.zeros_like(f)), (photo * 1e30, f), (photo, f * 1e-30)):
        for w in (0.0, 1.0, float("nan")):
            o = transfer_apply(new, transfer_reference(p_, f_, valid), w)
            assert np.all(np.isfinite(o)) and o.min() >= 0
    # a light from elsewhere (w = 0): the photo's detail never takes a pixel below e^-c (> 5%) of the render
    from usdrelight.relight.composite import TRANSFER_CLIP

    speckled = photo * np.where(rng.random(f.shape[:2]) < 0.1, 1e-6, 1.0)[..., None]
    o = transfer_apply(new, transfer_reference(speckled, f, valid, sigma=2.0), 0.0)
    assert np.exp(-TRANSFER_CLIP) > 0.05 and np.all(o >= np.exp(-TRANSFER_CLIP) * new * (1 - 1e-5))
    # nor does the photo's own low-frequency darkness under a matching light (w = 1): a photo 1000x darker
    # than its fit in a blob (a shadow the fit missed) stays at e^-c of the render there, and is the photo
    # (up to the guard) where the fit explains it
    yy, xx = np.mgrid[0:f.shape[0], 0:f.shape[1]]
    dist = np.hypot(yy - 24, xx - 32)
    blob = np.where(dist < 12, 1e-3, 1.0)[..., None]
    o = transfer_apply(new, transfer_reference(f * blob, f, valid, sigma=2.0), 1.0, render_detail=1.0)
    assert np.all(o >= np.exp(-TRANSFER_CLIP) * new * (1 - 1e-5))
    inside, outside = dist < 4, dist > 24
    assert inside.sum() > 20 and outside.sum() > 20
    np.testing.assert_allclose(o[inside], (np.exp(-TRANSFER_CLIP) * new)[inside], rtol=1e-4)
    np.testing.assert_allclose(o[outside], new[outside], rtol=1e-3)


def test_light_match_weighs_each_light_by_its_share_and_its_angle_to_the_photo_lights():
    from usdrelight.stage.light_specs import parse_lights

    photo = parse_lights(["point:0,2,-3:1,1,1", "dome:0.1,0.1,0.1"])
    centre = np.array([0.0, 0.0, -3.0])
    same, moved, sun_above = parse_lights(["point:0,4,-3:5,1,1", "point:2,0,-3:1,1,1", "sun:0,-1,0:1,1,1"])
    angles = match_angles([same, moved, sun_above, photo[1]], photo, centre)
    np.testing.assert_allclose(angles, [0.0, 90.0, 0.0, 0.0], atol=1e-9)  # a dome matches the photo's dome
    assert match_angles([photo[1]], photo[:1], centre) == [180.0]  # no dome in the photo
    assert match_weight([0.0, 90.0], [3.0, 1.0]) == pytest.approx(0.75)
    a = 5.0  # halfway in cosine between 0 and 10 degrees is not 5 degrees: linear in the cosine
    c = lambda deg: np.cos(np.radians(deg))  # noqa: E731
    assert match_weight([a], [1.0], 10.0) == pytest.approx((c(a) - c(10.0)) / (1 - c(10.0)))
    assert match_weight([], []) == 0.0 and match_weight([0.0], [0.0]) == 0.0


@pytest.fixture(scope="module")
def fitted_stage(tmp_path_factory):
    out = tmp_path_factory.mktemp("comp") / "st"
    scene = build_procedural(out)
    write_fitted_lights(out, [PointLightValue(np.array([-0.5, 1.0, -2.0]), np.array([4.0, 4.0, 4.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    return scene


@pytest.mark.parametrize("mode", ["ratio", "add"])
def test_session_modes_on_a_stage(fitted_stage, mode):
    session = RelightSession(fitted_stage, max_side=96, with_fitted=True, mode=mode)
    photo = resize_image(read_photo(EXAMPLES / "procedural" / "photo.exr"), *session.photo.shape[1::-1])
    same = session.render([])
    np.testing.assert_allclose(same.image, photo, rtol=1e-5, atol=1e-6)  # nothing changed: the photo itself
    lit = session.render(["point:0.5,1.0,-2.5:3,3,3"])
    assert np.all(lit.image >= photo - 1e-6) and lit.image.mean() > photo.mean() * 1.02
    assert np.all(np.isfinite(lit.image))


def test_ratio_without_fitted_lights_or_photo_is_a_clear_error(cli, fitted_stage, tmp_path):
    stage = tmp_path / "st"
    shutil.copytree(fitted_stage.parent, stage, symlinks=True)  # its links into versions/current stay links
    (stage / "lights_fitted.usda").write_text("#usda 1.0\n")
    rc, _, err = cli("relight", stage / "scene.usda", "--mode", "ratio", "--light", "point:0,1,-2:1,1,1",
                     "--max-side", "64", "-o", tmp_path / "o")
    assert rc == 2 and "fitted lights" in err


def test_fitted_scale_dims_the_photo_by_the_closed_form(fitted_stage):
    # no added light, fitted lights at scale s: I' = I (s F + k) / (F + k), F the fitted render, k = 1% of mean F
    full = RelightSession(fitted_stage, max_side=96, with_fitted=True, mode="ratio")
    dim = RelightSession(fitted_stage, max_side=96, with_fitted=True, mode="ratio", fitted_scale=0.25)
    f = full.render([]).diffuse.astype(np.float64)
    out = dim.render([]).image
    valid = full.render([]).valid
    _, k_down = ratio_guard(full.photo, f, valid)  # dimming everywhere: the 1% guard
    expected = full.photo * (0.25 * f + k_down) / (f + k_down)
    np.testing.assert_allclose(out[valid], expected[valid], rtol=2e-3, atol=1e-6)
    assert out[valid].mean() < 0.3 * full.photo[valid].mean()


def test_relight_cli_default_mode_fitted_scale_and_contact_sheet(cli, fitted_stage, tmp_path):
    from usdrelight.imageio import read_map

    rep = cli.json("relight", fitted_stage, "--fitted-scale", "0.2", "--light", "point:0.5,1.0,-2.5:3,2,1",
                   "--max-side", "64", "--contact-sheet", "-o", tmp_path / "night")
    assert rep["mode"] == "transfer" and rep["contact_sheet"].endswith("contact_sheet.png")  # auto: fitted light scaled
    kept = cli.json("relight", fitted_stage, "--with-fitted", "--light", "point:0.5,1.0,-2.5:3,2,1", "--max-side",
                    "48", "-o", tmp_path / "kept")
    assert kept["mode"] == "add"  # auto: the photo's light kept as it is, a light added
    off = cli.json("relight", fitted_stage, "--light", "point:0.5,1.0,-2.5:3,2,1", "--max-side", "48",
                   "-o", tmp_path / "off")
    assert off["mode"] == "residual"  # auto: the photo's light is switched off (and a fit exists)
    from usdrelight.neural.model import hole_fill
    from usdrelight.relight.session import RelightSession
    from usdrelight.stage.light_specs import parse_lights as s_lights

    with RelightSession(fitted_stage, max_side=None, mode="render") as s:  # render: D~ as a photo shows it
        frame = s.render(["point:0.5,1.0,-2.5:3,2,1"])
        cov = s.engine.render(list(s.base_lights) + s_lights(["point:0.5,1.0,-2.5:3,2,1"])).coverage
        seen = cov > 0
        expected = hole_fill(np.where(seen[..., None], frame.diffuse / np.maximum(cov, 1e-6)[..., None], 0.0)
                             .astype(np.float32), seen)
        np.testing.assert_allclose(frame.image, expected, rtol=1e-6, atol=1e-7)
        # the half-covered first and last rows and columns are not darker than their neighbours
        assert 0.4 < cov[0].mean() < 0.9 and 0.4 < cov[:, -1].mean() < 0.9
        lum = frame.image.mean(-1)
        for edge, inner in ((lum[0], lum[1]), (lum[-1], lum[-2]), (lum[:, 0], lum[:, 1]), (lum[:, -1], lum[:, -2])):
            assert edge.mean() == pytest.approx(inner.mean(), rel=0.1)
    with RelightSession(fitted_stage, max_side=48, mode="residual") as s:  # what the command wrote
        np.testing.assert_allclose(read_map(off["exr"], 3), s.render(["point:0.5,1.0,-2.5:3,2,1"]).image,
                                   rtol=1e-6, atol=1e-7)
    sheet = read_photo(rep["contact_sheet"])
    assert sheet.shape[1] > 5 * sheet.shape[0] / 2  # photo, D~ and four modes side by side
    img = read_map(rep["exr"], 3)
    assert np.all(np.isfinite(img)) and img.min() >= 0
    rc, _, err = cli("relight", fitted_stage, "--fitted-scale", "nan", "--light", "point:0,1,-2:1,1,1")
    assert rc == 2 and "scale" in err and len(err.strip().splitlines()) == 1
