"""Photos and side files a probe found misread or answered badly: an EXR whose colour is a layer, depth and
point maps of the wrong channel count, side files of strings or huge numbers (exit 1, 'unexpected'), and
messages that quoted a foreign file's content. Each builds (or fails) through the CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import make_photo
from usdrelight.imageio import read_photo

SECRET = "SECRET_API_KEY=sk-live-0123"


def _one_error(rc, err, needle):
    assert rc == 2 and err.count("\n") == 1 and err.startswith("usdrelight: error:"), err
    assert "unexpected" not in err and SECRET not in err and needle in err, err


def test_an_exr_photo_whose_colour_is_a_layer_reads_that_layer(tmp_path):
    """Channels diffuse.R, diffuse.G, diffuse.B and Z: OpenImageIO lists Z first, and the photo was (Z, R, G):
    its red was the depth (5.0)."""
    import OpenImageIO as oiio

    rgb = np.zeros((8, 12, 3), np.float32) + [0.2, 0.4, 0.6]
    spec = oiio.ImageSpec(12, 8, 4, oiio.FLOAT)
    spec.channelnames = ("diffuse.R", "diffuse.G", "diffuse.B", "Z")
    out = oiio.ImageOutput.create(str(tmp_path / "p.exr"))
    out.open(str(tmp_path / "p.exr"), spec)
    out.write_image(np.concatenate([rgb, np.full((8, 12, 1), 5.0, np.float32)], -1))
    out.close()
    np.testing.assert_allclose(read_photo(tmp_path / "p.exr"), rgb, rtol=1e-6)


def test_depth_and_point_maps_of_the_wrong_channel_count_are_refused(cli, tmp_path):
    """A point map given as --depth (its X was read as depth: a garbage mesh, exit 0), a one-channel map as
    --points (replicated to X = Y = Z); a grey depth PNG saved as RGB (channels alike) is still taken."""
    photo = make_photo(tmp_path / "p.png", 16, 20)
    v, u = np.mgrid[0:16, 0:20]
    pts = np.stack([(u - 9.5) / 20.0 * 2, (v - 7.5) / 20.0 * 2, np.full((16, 20), 2.0)], -1).astype(np.float32)
    np.save(tmp_path / "pts.npy", pts)
    np.save(tmp_path / "depth1.npy", pts[..., 2:])
    rc, _, err = cli("build", photo, "--depth", tmp_path / "pts.npy", "-o", tmp_path / "a")
    _one_error(rc, err, "3 channels that differ, where one value per pixel is wanted")
    rc, _, err = cli("build", photo, "--points", tmp_path / "depth1.npy", "-o", tmp_path / "b")
    _one_error(rc, err, "expected 3 channels (X, Y, Z), got 1")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    np.save(tmp_path / "grey3.npy", np.repeat(pts[..., 2:], 3, -1))
    assert cli("build", photo, "--depth", tmp_path / "grey3.npy", "-o", tmp_path / "c")[0] == 0


def test_strings_huge_numbers_and_foreign_content_are_one_error_that_quotes_nothing(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 16, 20)
    np.save(tmp_path / "s.npy", np.array([["a"] * 20] * 16))
    rc, _, err = cli("build", photo, "--depth", tmp_path / "s.npy", "-o", tmp_path / "o")
    _one_error(rc, err, "not real numbers")  # was exit 1, 'unexpected ValueError'
    (tmp_path / "bad.npy").write_bytes(b"\x93NUMPY\x01\x00v\x00{'descr': '" + SECRET.encode() +
                                       b"', 'fortran_order': False, 'shape': (16, 20), }" + b" " * 40 + b"\n")
    rc, _, err = cli("build", photo, "--depth", tmp_path / "bad.npy", "-o", tmp_path / "o")
    _one_error(rc, err, "not a NumPy .npy array")
    (tmp_path / "bad.pfm").write_bytes(b"Pf\n" + SECRET.encode() + b" 3\n-1\n")
    rc, _, err = cli("build", photo, "--depth", tmp_path / "bad.pfm", "-o", tmp_path / "o")
    _one_error(rc, err, "not a valid PFM header")
    for bad, needle in (({"fx": SECRET, "cx": 9.5, "cy": 7.5}, "fx must be a number, got str"),
                        ('{"fx": 1' + "0" * 400 + ', "cx": 9.5, "cy": 7.5}', "fx must be finite"),
                        ({"fx": True, "cx": 9.5, "cy": 7.5}, "fx must be a number, got bool"),
                        ({"K": [[20, 0, 9.5], [0, 20, 7.5], [SECRET, 0, 1]]}, "K[2][0] must be a number"),
                        ({"K": [[20, 0, 9.5], [0, 20, 7.5], [0, 0, 0]]}, "last row (0, 0, 1)"),
                        ([SECRET], "expected fx, fy, cx, cy, a 3x3 matrix K")):
        (tmp_path / "k.json").write_text(bad if isinstance(bad, str) else json.dumps(bad))
        rc, _, err = cli("build", photo, "--intrinsics", tmp_path / "k.json", "-o", tmp_path / "o")
        _one_error(rc, err, needle)  # 1e400: exit 1 'unexpected OverflowError'; the string was quoted back
    assert not (tmp_path / "o").exists()
    (tmp_path / "bom.json").write_bytes(b"\xef\xbb\xbf" + json.dumps({"fx": 20, "cx": 9.5, "cy": 7.5}).encode())
    assert cli("build", photo, "--intrinsics", tmp_path / "bom.json", "-o", tmp_path / "bom")[0] == 0  # Notepad's


@pytest.mark.parametrize("k", [{"fx": 20, "fy": 20, "cx": 9.5, "cy": 7.5}, {"fx": 20, "cx": 9.5, "cy": 7.5},
                               {"K": [[20, 0, 9.5], [0, 20, 7.5], [0, 0, 1]]}, [[20, 0, 9.5], [0, 20, 7.5], [0, 0, 1]]])
def test_the_intrinsics_forms_still_read_alike(cli, tmp_path, k):
    photo = make_photo(tmp_path / "p.png", 16, 20)
    (tmp_path / "k.json").write_text(json.dumps(k))
    rep = cli.json("build", photo, "--intrinsics", tmp_path / "k.json", "-o", tmp_path / "o")
    assert rep["intrinsics_opencv"]["fx"] == pytest.approx(20) and rep["intrinsics_opencv"]["fy"] == pytest.approx(20)
    assert rep["intrinsics_opencv"]["cx"] == pytest.approx(9.5) and rep["intrinsics_opencv"]["cy"] == pytest.approx(7.5)


@pytest.mark.parametrize("fy, max_side, size", [(80.0, None, (32, 48)), (404.0, None, (240, 320)),
                                                (80.0, 20, (32, 48)), (40.0, 21, (32, 48))])
def test_non_square_pixels_are_traced_where_the_stage_camera_puts_them(cli, tmp_path, fy, max_side, size):
    """fx 40, fy 80 (and 1% apart, as calibrations give; also at a reduced size): the stage's camera was right
    but the fast renderer
    (and so fit and relight) traced square pixels of fx: its surface landed 4 px (up to 7.5) from its pixel and
    half the pixels saw nothing. Now every pixel's hit reprojects onto its own centre (the 1/64 px nudge)."""
    from usdrelight.relight.session import RelightSession

    h, w = size
    photo = make_photo(tmp_path / "p.png", h, w)
    np.save(tmp_path / "d.npy", np.full((h, w), 2.0, np.float32))
    fx = 40.0 * w / 48
    (tmp_path / "k.json").write_text(json.dumps({"fx": fx, "fy": fy, "cx": w / 2 - 0.5, "cy": h / 2 - 0.5}))
    assert cli("build", photo, "--depth", tmp_path / "d.npy", "--intrinsics", tmp_path / "k.json",
               "-o", tmp_path / "s")[0] == 0
    with RelightSession(tmp_path / "s" / "scene.usda", mode="render", max_side=max_side) as s:
        k, surf = s.scene.camera.intrinsics, s.engine.surface
        p = surf.p * [1.0, -1.0, -1.0]  # the camera at the origin looking down -Z: OpenCV's frame
        err = np.hypot(k.cx + k.fx * p[:, 0] / p[:, 2] - (surf.idx[:, 1] + 0.5),
                       k.cy + k.fy * p[:, 1] / p[:, 2] - (surf.idx[:, 0] + 0.5))
    w, h = k.width, k.height  # at 20 or 21 px the rounded size makes even square pixels slightly non-square
    assert len(p) >= (w - 1) * (h - 1) and err.max() < 0.05, (len(p), err.max())  # the mesh ends at the centres


def test_outputs_are_not_empty_nor_inside_the_stages_versions(cli, tmp_path):
    """-o '' wrote into the current folder; a relight -o inside versions/current (or the textures link) was
    taken, and the next fit removed its files and left dangling links. One error each, nothing written."""
    photo = make_photo(tmp_path / "p.png", 16, 20)
    with pytest.raises(SystemExit) as exc:  # argparse refuses it (one line, exit 2), before anything runs
        cli("build", photo, "-o", "")
    assert exc.value.code == 2
    assert cli("build", photo, "-o", tmp_path / "s")[0] == 0
    stage = tmp_path / "s" / "scene.usda"
    for inside in (tmp_path / "s" / "textures" / "r", tmp_path / "s" / "versions" / "current" / "r"):
        rc, _, err = cli("relight", stage, "--light", "point:0,1,-2:3,3,3", "--mode", "render", "-o", inside)
        _one_error(rc, err, "inside the stage's versions/ folder")
        assert not inside.exists()
        rc, _, err = cli("render", stage, "--spp", "1", "-o", inside)
        _one_error(rc, err, "inside the stage's versions/ folder")


def test_a_black_photo_an_albedo_above_one_and_a_nan_grazing_angle_are_said(cli, tmp_path):
    """Built in silence before: an all-black photo (its relight stays black), an albedo map above 1 (clamped);
    --max-grazing-deg nan ended in 'no triangle survives', which did not name it."""
    from usdrelight.imageio import write_image

    write_image(tmp_path / "black.exr", np.zeros((16, 20, 3), np.float32), "float")
    rc, _, err = cli("build", tmp_path / "black.exr", "-o", tmp_path / "a")
    assert rc == 0 and "is black (every pixel 0 or below)" in err, err
    # its fit kept two lights of 3e-9 and a dome, at "22.4 dB": now none, exactly (99 dB, what renders black)
    res = cli.json("fit", tmp_path / "a" / "scene.usda", "--max-side", "16", "--lights", "2", "--verify-spp", "0")
    assert (res["lights_kept"], res["environment_kept"], res["psnr_db"]) == (0, False, 99.0), res
    photo = make_photo(tmp_path / "p.png", 16, 20)
    albedo = np.full((16, 20, 3), 0.5, np.float32)
    albedo[:4] = 2.0  # a quarter of the pixels
    write_image(tmp_path / "alb.exr", albedo, "float")
    rc, _, err = cli("build", photo, "--albedo", tmp_path / "alb.exr", "-o", tmp_path / "b")
    assert rc == 0 and "albedo above 1 in 25.00% of the pixels" in err, err
    with pytest.raises(SystemExit) as exc:
        cli("build", photo, "--max-grazing-deg", "nan", "-o", tmp_path / "c")
    assert exc.value.code == 2
    rc, _, err = cli("build", photo, "--max-grazing-deg", "120", "-o", tmp_path / "c")
    _one_error(rc, err, "max_grazing_deg (--max-grazing-deg) must be in (0, 90] degrees, got 120")


def test_a_photo_too_bright_for_float32_is_one_line_about_the_photo(cli, tmp_path):
    """A float photo x 3e38 ended in 'refusing to write non-finite pixels to .../versions/.<tmp>/estimates/
    diffuse.exr' (a temporary path, and not about the photo); a 1e6 x photo still builds."""
    from usdrelight.imageio import write_image

    photo = np.random.default_rng(0).uniform(0.1, 1.0, (16, 20, 3)).astype(np.float32)
    write_image(tmp_path / "huge.exr", photo * np.float32(3e38), "float")
    rc, _, err = cli("build", tmp_path / "huge.exr", "-o", tmp_path / "a")
    _one_error(rc, err, "holds values up to 3e+38: at most 1e+30")
    assert not (tmp_path / "a").exists() and "versions" not in err
    write_image(tmp_path / "bright.exr", photo * np.float32(1e6), "float")
    rc, _, err = cli("build", tmp_path / "bright.exr", "-o", tmp_path / "b")
    assert rc == 0, err


def test_an_empty_photo_file_says_it_is_empty(cli, tmp_path):
    (tmp_path / "empty.jpg").write_bytes(b"")  # was 'not a valid JPG file (damaged, or another format)'
    rc, _, err = cli("build", tmp_path / "empty.jpg", "-o", tmp_path / "a")
    _one_error(rc, err, "empty.jpg: empty file (0 bytes)")


def test_a_beauty_beside_aov_layers_and_a_depth_z_beside_a_preview(tmp_path):
    """R, G, B, A beside diffuse.R/G/B (an Arnold or Nuke EXR) reads the beauty (it was refused as 'several
    colour layers'); a depth EXR of R, G, B (a preview) and Z reads its Z (it was refused, and before that read R)."""
    import OpenImageIO as oiio

    from usdrelight.imageio import read_map

    def exr(name, channels, values):
        spec = oiio.ImageSpec(6, 4, len(channels), oiio.FLOAT)
        spec.channelnames = channels
        out = oiio.ImageOutput.create(str(tmp_path / name))
        out.open(str(tmp_path / name), spec)
        out.write_image(np.broadcast_to(np.asarray(values, np.float32), (4, 6, len(channels))).copy())
        out.close()
        return tmp_path / name

    beauty = exr("b.exr", ("R", "G", "B", "A", "diffuse.R", "diffuse.G", "diffuse.B"), [1, 2, 3, 1, 7, 8, 9])
    np.testing.assert_allclose(read_photo(beauty)[0, 0], [1, 2, 3])
    depth = exr("d.exr", ("R", "G", "B", "Z"), [0.2, 0.5, 0.9, 2.5])
    np.testing.assert_allclose(read_map(depth, 1, exact=True)[..., 0], 2.5)


def test_a_very_wide_photo_relit_small_gets_its_light(cli, tmp_path):
    """2000 x 3 relit at --max-side 64 (64 x 1: the rounded row is 10x taller than the camera's square pixel):
    the sensor saw past the mesh, coverage 0, the added light gave a black image (max 0.0)."""
    from usdrelight.imageio import read_map

    photo = make_photo(tmp_path / "wide.png", 3, 2000)
    assert cli("build", photo, "-o", tmp_path / "s")[0] == 0
    rc, _, err = cli("relight", tmp_path / "s" / "scene.usda", "--mode", "render", "--max-side", "64",
                     "--light", "point:0.5,0.5,-1.5:3,2.6,2", "-o", tmp_path / "r")
    assert rc == 0, err
    relit = read_map(tmp_path / "r" / "relit.exr", 3)
    assert relit.shape == (1, 64, 3) and (relit.max(-1) > 0).mean() > 0.9


def test_a_photo_whose_icc_profile_is_not_srgb_is_warned(tmp_path, caplog):
    """A Display P3 or Rec. 2020 photo (as phones write) was decoded as sRGB in silence; an sRGB one stays quiet."""
    import logging
    import struct

    from PIL import Image

    def profile(desc: str) -> bytes:  # a minimal ICC v4 header + one 'desc' (mluc) tag
        text = desc.encode("utf-16-be")
        tag = b"mluc" + b"\0" * 4 + struct.pack(">II", 1, 12) + b"enUS" + struct.pack(">II", len(text), 28) + text
        body = struct.pack(">I", 1) + b"desc" + struct.pack(">II", 144, len(tag))
        head = struct.pack(">I", 144 + len(tag)) + b"\0" * 32 + b"acsp" + b"\0" * 88
        return head + body + tag

    rgb = (np.random.default_rng(0).random((8, 8, 3)) * 255).astype(np.uint8)
    for name, desc in (("p3.jpg", "Display P3"), ("srgb.jpg", "sRGB IEC61966-2.1")):
        Image.fromarray(rgb).save(tmp_path / name, icc_profile=profile(desc))
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            read_photo(tmp_path / name)
        warned = any("embeds the colour profile" in r.getMessage() for r in caplog.records)
        assert warned == (desc == "Display P3"), (name, caplog.text)


def test_a_side_map_of_the_unrotated_photo_says_the_photo_is_read_upright(cli, tmp_path):
    """A JPEG stored 20 x 16 with EXIF orientation 6 is read upright (16 x 20); a depth map made from the stored
    pixels was refused as '20x16 but the photo is 16x20' without saying why."""
    from PIL import Image

    img = Image.fromarray((np.random.default_rng(0).random((16, 20, 3)) * 255).astype(np.uint8))
    exif = Image.Exif()
    exif[0x0112] = 6
    img.save(tmp_path / "p.jpg", exif=exif)
    np.save(tmp_path / "d.npy", np.full((16, 20), 2.0, np.float32))
    rc, _, err = cli("build", tmp_path / "p.jpg", "--depth", tmp_path / "d.npy", "-o", tmp_path / "o")
    _one_error(rc, err, "is 20x16 but the photo is 16x20 (the photo is read upright, its EXIF orientation applied")
