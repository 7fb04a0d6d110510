"""Coverage-correct fast render: a partly covered pixel is shaded over its covered part, as Mitsuba's box filter
does, so no pixel that Mitsuba renders lit is black (depth cuts, the image border)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from usdrelight.engine import open_renderer
from usdrelight.imageio import write_image
from usdrelight.stage.build import BuildOptions, build
from usdrelight.stage.light_specs import parse_lights
from usdrelight.stage.read import read_scene

W, H = 64, 48


@pytest.fixture(scope="module")
def step_stage(tmp_path_factory):
    """A photo stage no other test uses: a wall at 4 m with a box 2.5 m in front of it (depth cuts all round the
    box), a textured albedo, 60 degrees field of view."""
    d = tmp_path_factory.mktemp("cov")
    depth = np.full((H, W), 4.0, np.float32)
    depth[14:36, 18:42] = 1.5
    yy, xx = np.mgrid[0:H, 0:W]
    albedo = np.stack([0.3 + 0.4 * ((xx // 6 + yy // 6) % 2), np.full((H, W), 0.5), 0.4 + 0.2 * (yy / H)], -1)
    np.save(d / "depth.npy", depth)
    write_image(d / "albedo.exr", albedo.astype(np.float32), "float")
    write_image(d / "photo.exr", (albedo * 0.5).astype(np.float32), "float")
    build(d / "photo.exr", d / "st", BuildOptions(depth=d / "depth.npy", fov_x=60.0, albedo=d / "albedo.exr"))
    return read_scene(d / "st" / "scene.usda")


def test_fast_render_matches_mitsuba_box_filter_at_cuts_and_borders(step_stage):
    lights = parse_lights(["point:0.6,0.8,-0.5:3,3,3", "dome:0.08,0.08,0.1"])
    fast = open_renderer(step_stage, "fast", max_side=W).render(lights)
    ref = open_renderer(step_stage, "mitsuba", max_side=W, spp=4096, max_depth=3).render(lights)
    lum_f, lum_r = fast.beauty.mean(-1), ref.beauty.mean(-1)
    lit = lum_r > 0.02 * np.percentile(lum_r, 99)
    # the centre ray alone leaves the outline of every cut and the half-covered last row and column black
    assert (lit & ~fast.valid).mean() > 0.03
    # coverage-correct: no pixel that Mitsuba renders lit is black
    assert (lit & (lum_f <= 1e-6)).mean() <= 0.001
    # the fringe carries the coverage Mitsuba's box filter sees
    np.testing.assert_allclose(fast.coverage, ref.coverage, atol=0.13)
    assert fast.coverage[~fast.valid].max() > 0.2
    # radiance: close away from silhouettes, and the partly covered pixels themselves close on average
    sil = binary_dilation((ref.coverage > 0) & (ref.coverage < 1), iterations=1)
    sel = ~sil & (ref.coverage > 0)
    rel = np.sqrt(np.mean((fast.beauty[sel] - ref.beauty[sel]) ** 2)) / np.sqrt(np.mean(ref.beauty[sel] ** 2))
    assert rel <= 0.03, rel
    fringe = (ref.coverage > 0) & ~fast.valid
    assert fast.beauty[fringe].mean() == pytest.approx(ref.beauty[fringe].mean(), rel=0.1)
    assert np.all(np.isfinite(fast.beauty)) and fast.beauty.min() >= 0
