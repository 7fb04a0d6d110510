"""What a relit photo looks like where the probes looked (found by viewing the images): the PNG is the sRGB of
the EXR, scaled down only when much of it is above 1 and never brightened, with one exposure for every frame of
a clip; ``add`` gives the image border and depth cuts the whole added light, not the half a partly covered
pixel's render holds."""
from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import build_procedural
from usdrelight.imageio import display_exposure, linear_to_srgb, read_map, read_photo
from usdrelight.neural.model import write_relit
from usdrelight.relight.session import RelightSession


def _srgb_levels(path) -> np.ndarray:
    """The 8-bit levels of a PNG (read back as linear by read_photo, encoded again)."""
    return np.round(linear_to_srgb(read_photo(path)) * 255.0)


def test_a_few_pixels_above_1_do_not_brighten_the_png(tmp_path):
    """Before: any pixel above 1 made the PNG divide by the 99.5th percentile, 0.56 here: 1.8x brighter than the
    EXR, and 5% more light gave a PNG 36% brighter."""
    rng = np.random.default_rng(0)
    img = (rng.random((40, 50, 3)) * 0.5).astype(np.float32)
    img[0, 0] = img[1, 1] = 1.2  # 2 of 2000 pixels above 1
    assert display_exposure(img) == 1.0
    _, png = write_relit(tmp_path, "relit", img)
    want = np.round(linear_to_srgb(np.clip(img, 0, 1)) * 255.0)
    assert np.abs(_srgb_levels(png) - want).max() <= 1
    bright = img * 4  # most of it above 1: scaled down by its 99.5th percentile
    _, png = write_relit(tmp_path, "bright", bright)
    e = display_exposure(bright)
    assert e == pytest.approx(float(np.percentile(bright, 99.5))) and e > 1
    assert np.abs(_srgb_levels(png) - np.round(linear_to_srgb(np.clip(bright / e, 0, 1)) * 255.0)).max() <= 1


@pytest.fixture(scope="module")
def stage(tmp_path_factory):
    return build_procedural(tmp_path_factory.mktemp("view") / "st", stride=4)


def test_the_frames_of_a_clip_share_one_exposure(stage, tmp_path, cli):
    """Before: each PNG had its own exposure, so a frame under a brighter light could come out darker. Every frame
    is shown at the photo's own exposure (an added light brightens and clips, never darkens the rest)."""
    frames = [[f"point:0.5,1.0,-2.5:{s},{s},{s}"] for s in (40, 60, 80)]
    (tmp_path / "seq.json").write_text(json.dumps(frames))
    rc, _, err = cli("relight", stage, "--mode", "render", "--sequence", tmp_path / "seq.json", "-o", tmp_path / "o")
    assert rc == 0, err
    exrs = [read_map(tmp_path / "o" / f"relit_{i:04d}.exr", 3) for i in range(3)]
    with RelightSession(stage) as session:
        e0 = display_exposure(session.source_photo())
    assert display_exposure(exrs[0]) > e0  # the first frame's own exposure, which set the clip's before, differs
    means = []
    for i, exr in enumerate(exrs):
        png = _srgb_levels(tmp_path / "o" / f"relit_{i:04d}.png")
        assert np.abs(png - np.round(linear_to_srgb(np.clip(exr / e0, 0, 1)) * 255.0)).max() <= 1, i
        means.append(png.mean())
    assert means[0] < means[1] < means[2]


@pytest.fixture(scope="module")
def full_stage(tmp_path_factory):
    """The procedural stage meshed at every pixel (stride 1): its mesh reaches the image's last row and column."""
    return build_procedural(tmp_path_factory.mktemp("view1") / "st")


def test_add_gives_the_border_its_whole_light(full_stage, tmp_path, cli):
    """The last row and column are half covered by the 2.5D mesh (corners a quarter); ``add`` added the render
    as it is there, half the light of the row beside: a thin dark frame round every result."""
    for name, extra in (("none", []), ("lit", ["--light", "point:0,1.2,-2.0:20,20,20"])):
        rc, _, err = cli("relight", full_stage, "--mode", "add", *extra, "-o", tmp_path / name)
        assert rc == 0, err
    added = (read_map(tmp_path / "lit" / "relit.exr", 3) - read_map(tmp_path / "none" / "relit.exr", 3)).mean(2)
    assert added.min() >= 0
    for edge, inner in ((added[-1], added[-2]), (added[:, -1], added[:, -2]), (added[0], added[1]),
                        (added[:, 0], added[:, 1])):
        ratio = np.median(edge[inner > 1e-3] / inner[inner > 1e-3])
        assert 0.8 < ratio < 1.25, ratio  # before: 0.5 on the last row and column
