"""The procedural ground-truth scene: Mitsuba units checked in closed form; the build sits on its geometry."""

import numpy as np
import pytest
from pxr import UsdGeom

from conftest import EXAMPLES
from usdrelight.mitsuba.procedural import (PointLight, SceneSpec, load_spec, pixel_centre_rays, point_light_radiance,
                                   render_ground_truth)
from usdrelight.stage.validate import errors_only, open_stage, validate_stage


def test_point_light_on_floor_matches_closed_form():
    """Floor (albedo 0.5) 1 m below a 20 W/sr point light: L = 0.5/pi * 20 * cos / r^2 at every pixel."""
    spec = SceneSpec(width=48, height=36, fov_x_deg=60.0, seed=1, env_radiance=(0, 0, 0),
                     point_lights=[PointLight((0.0, 0.0, -3.0), (20.0, 20.0, 20.0))],
                     shapes=[{"kind": "floor", "y": -1.0, "albedo": [0.5, 0.5, 0.5], "checker": None}])
    gt = render_ground_truth(spec, spp=64)
    dirs = pixel_centre_rays(gt.intrinsics).reshape(36, 48, 3)
    pos = dirs * (gt.depth / -dirs[..., 2])[..., None]  # world hit points from the true z-depth
    to_light = np.array([0.0, 0.0, -3.0]) - pos
    r2 = np.sum(to_light ** 2, -1)
    cos = to_light[..., 1] / np.sqrt(r2)  # floor normal is +Y
    expected = 0.5 / np.pi * 20.0 * cos / r2
    rows = gt.valid.any(1)
    sel = gt.valid & (np.arange(36)[:, None] > np.nonzero(rows)[0].min() + 1)  # skip the horizon rows
    ratio = gt.image[..., 1][sel] / expected[sel]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.02)
    assert point_light_radiance(0.5, 20.0, 1.0) == pytest.approx(0.5 * 20 / np.pi)
    np.testing.assert_allclose(gt.albedo[gt.valid], 0.5, atol=1e-6)
    np.testing.assert_allclose(gt.normal[gt.valid], np.tile([0, 1, 0], (gt.valid.sum(), 1)), atol=1e-5)


def test_procedural_example_builds_onto_its_true_geometry(cli, tmp_path):
    ex = EXAMPLES / "procedural"
    res = cli.json("build", ex / "photo.exr", "--depth", ex / "depth.exr", "--intrinsics", ex / "intrinsics.json",
                   "--albedo", ex / "albedo.exr", "--shading", ex / "shading.exr", "-o", tmp_path / "p")
    stage = open_stage(tmp_path / "p" / "scene.usda")
    assert errors_only(validate_stage(stage)) == []
    spec = load_spec(ex / "scene.json")
    assert (res["width"], res["height"]) == (spec.width, spec.height)
    pts = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Photo/Mesh")).GetPointsAttr().Get(), np.float64)
    # every vertex lies on the pixel-centre ray of some pixel at the true depth: check against the
    # analytic geometry of the scene (floor plane y = -1, wall z = -6, spheres) for the vertices on them
    on_floor = np.abs(pts[:, 1] + 1.0) < 1e-3
    on_wall = np.abs(pts[:, 2] + 6.0) < 1e-3
    sphere_hits = np.zeros(len(pts), bool)
    for s in spec.shapes:
        if s["kind"] == "sphere":
            d = np.linalg.norm(pts - np.array(s["center"]), axis=1)
            sphere_hits |= np.abs(d - s["radius"]) < 1e-3 * s["radius"] * 10
    explained = on_floor | on_wall | sphere_hits
    assert explained.mean() > 0.8  # the rest are the boxes
    assert res["vertex_fraction"] > 0.9
