"""Stages from `usdrelight build` convert to Mitsuba XML and render their declared AOVs."""
import numpy as np
import pytest

from usdrelight.imageio import read_map, read_photo
from usdrelight.mitsuba.runtime import load_mitsuba


def test_build_stage_renders_albedo_equal_to_texture(cli, moto_stage, tmp_path, moto_paths):
    res = cli.json("render", moto_stage, "-o", tmp_path / "r", "--aov", "albedo", "valid", "depth", "normal")
    assert sorted(res["files"]) == ["albedo", "depth", "normal", "valid"]
    assert not (tmp_path / "r" / "renders" / "diffuse.exr").exists()  # only what was asked for
    alb = read_map(tmp_path / "r" / "renders" / "albedo.exr", 3)
    valid = read_map(tmp_path / "r" / "renders" / "valid.exr", 1)[..., 0] > 0.5
    tex = read_photo(moto_stage.parent / "textures" / "albedo.exr")
    assert alb.shape == tex.shape and valid.mean() > 0.85
    diff = np.abs(alb - tex).max(-1)[valid]
    assert np.median(diff) < 1e-3 and np.percentile(diff, 95) < 0.02
    # depth AOV reproduces the true depth where the mesh is hit
    true = read_map(moto_paths["depth"], 1)[..., 0]
    depth = read_map(tmp_path / "r" / "renders" / "depth.exr", 1)[..., 0]
    ok = valid & (true > 0)
    rel = np.abs(depth[ok] - true[ok]) / true[ok]
    assert np.median(rel) < 1e-4 and np.percentile(rel, 95) < 0.02
    normal = read_map(tmp_path / "r" / "renders" / "normal.exr", 3)
    assert np.all(np.isfinite(normal)) and np.median(normal[valid][:, 2]) > 0.5  # facing the camera (+Z)


def test_build_stage_converts_to_xml_that_mitsuba_loads(cli, moto_stage, tmp_path):
    rc, _, err = cli("convert", moto_stage, tmp_path / "x" / "scene.xml")
    assert rc == 0, err
    assert (tmp_path / "x" / "meshes").is_dir()
    mi = load_mitsuba()
    scene = mi.load_file(str(tmp_path / "x" / "scene.xml"))
    sensor = scene.sensors()[0]
    assert tuple(sensor.film().size()) == (741, 500)
    shape = scene.shapes()[0]
    assert shape.vertex_count() > 300000


def test_render_beauty_of_built_stage_under_a_user_light(cli, tmp_path):
    """End to end: build from a flat plane, add a point light in the user layer, render the diffuse AOV."""
    from conftest import make_photo

    h, w = 24, 32
    photo = make_photo(tmp_path / "p.png", h, w)
    np.save(tmp_path / "d.npy", np.full((h, w), 2.0, np.float32))
    np.save(tmp_path / "a.npy", np.full((h, w, 3), 0.5, np.float32))
    cli.json("build", photo, "--depth", tmp_path / "d.npy", "--fov-x", "60", "--albedo", tmp_path / "a.npy",
             "-o", tmp_path / "s")
    (tmp_path / "s" / "lights_user.usda").write_text(
        '#usda 1.0\nover "Scene"\n{\n    def Scope "Lights"\n    {\n        def Scope "User"\n        {\n'
        '            def SphereLight "Key"\n            {\n                float inputs:intensity = 20\n'
        '                bool treatAsPoint = 1\n                double3 xformOp:translate = (0, 0, -1)\n'
        '                uniform token[] xformOpOrder = ["xformOp:translate"]\n            }\n        }\n    }\n}\n')
    res = cli.json("render", tmp_path / "s" / "scene.usda", "--aov", "diffuse", "--spp", "16")
    img = read_map(res["files"]["diffuse"], 3)
    # the plane z = -2 is 1 m from the light; at the image centre L = 0.5 / pi * 20 / 1^2
    assert img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean() == pytest.approx(0.5 * 20 / np.pi, rel=0.03)


def test_render_bad_inputs(cli, moto_stage, tmp_path):
    rc, _, err = cli("render", moto_stage, "--aov", "bogus", "-o", tmp_path)
    assert rc == 2 and "bogus" in err and "declared" in err
    rc, _, err = cli("render", tmp_path / "missing.usda")
    assert rc == 2 and "not found" in err
