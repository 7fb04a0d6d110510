"""Hostile inputs, read confinement (issue 10): files a scene makes usdrelight read stay inside the scene's
folder tree unless ``--allow-path DIR``; errors name the path and never quote the file's content."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd

from usd_scenes import diffuse_material, floor_quad, looking_down_at_floor

from usdrelight.imageio import write_image

SECRET = "API_KEY=hunter2-secret"

TRIANGLE_PLY = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")


def _one_error(rc, err):
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("usdrelight: error:"), err
    assert "Traceback" not in err and "unexpected" not in err and SECRET not in err and "hunter2" not in err


@pytest.fixture
def dirs(tmp_path):
    scene, outside = tmp_path / "scene", tmp_path / "outside"
    scene.mkdir()
    outside.mkdir()
    (outside / "secret.ply").write_text(SECRET + "\n")
    (outside / "mesh.ply").write_text(TRIANGLE_PLY)
    (outside / "lights.xml").write_text('<scene version="3.0.0"><emitter type="point">'
                                        '<rgb name="intensity" value="5"/></emitter></scene>')
    write_image(outside / "tex.exr", np.full((4, 4, 3), 0.5, np.float32), "half")
    return scene, outside


def _ply_scene(scene, filename):
    (scene / "s.xml").write_text(f'<scene version="3.0.0"><shape type="ply">'
                                 f'<string name="filename" value="{filename}"/></shape></scene>')
    return scene / "s.xml"


@pytest.mark.parametrize("how", ["relative", "absolute"])
def test_a_mesh_outside_the_scene_folder_is_refused_unread(cli, dirs, how):
    scene, outside = dirs
    name = "../outside/secret.ply" if how == "relative" else str(outside / "secret.ply")
    rc, _, err = cli("convert", _ply_scene(scene, name), scene / "out.usda")
    _one_error(rc, err)
    assert "secret.ply" in err and "outside the scene's folder" in err and "--allow-path" in err
    assert sorted(p.name for p in scene.iterdir()) == ["s.xml"]


def test_a_malformed_mesh_error_never_quotes_its_content(cli, dirs):
    scene, outside = dirs
    (scene / "inside.ply").write_text(SECRET + "\n")
    rc, _, err = cli("convert", _ply_scene(scene, "inside.ply"), scene / "out.usda")
    _one_error(rc, err)
    assert "inside.ply" in err
    rc, _, err = cli("convert", _ply_scene(scene, "../outside/secret.ply"), scene / "o.usda", "--allow-path", outside)
    _one_error(rc, err)
    assert "secret.ply" in err and "not a valid ply" in err
    assert not (scene / "out.usda").exists() and not (scene / "o.usda").exists()


def test_allow_path_opts_in(cli, dirs):
    scene, outside = dirs
    src = _ply_scene(scene, "../outside/mesh.ply")
    assert cli("convert", src, scene / "out.usda")[0] == 2
    rc, _, err = cli("convert", src, scene / "out.usda", "--allow-path", outside)
    assert rc == 0, err
    assert Usd.Stage.Open(str(scene / "out.usda")).GetPrimAtPath("/World/ply")


def test_an_outside_include_cannot_inject_lights(cli, dirs):
    scene, outside = dirs
    (scene / "s.xml").write_text('<scene version="3.0.0"><include filename="../outside/lights.xml"/></scene>')
    rc, _, err = cli("convert", scene / "s.xml", scene / "out.usda")
    _one_error(rc, err)
    assert "lights.xml" in err and not (scene / "out.usda").exists()
    rc, _, err = cli("convert", scene / "s.xml", scene / "out.usda", "--allow-path", outside)
    assert rc == 0, err


def test_a_non_text_include_names_the_file_only(cli, dirs):
    scene, _ = dirs
    (scene / "bin.xml").write_bytes(b"\xff\xfe\x00" + SECRET.encode())
    (scene / "s.xml").write_text('<scene version="3.0.0"><include filename="bin.xml"/></scene>')
    rc, _, err = cli("convert", scene / "s.xml", scene / "out.usda")
    _one_error(rc, err)
    assert "bin.xml" in err


@pytest.mark.parametrize("body", [
    '<path value="../outside"/><shape type="ply"><string name="filename" value="mesh.ply"/></shape>',
    '<path value="/"/><shape type="ply"><string name="filename" value="etc/passwd"/></shape>',  # found through it
    '<shape type="rectangle"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
    '<string name="filename" value="../outside/tex.exr"/></texture></bsdf></shape>',
    '<emitter type="envmap"><string name="filename" value="../outside/tex.exr"/></emitter>',
    '<shape type="ply"><string name="filename" value="sub/../../outside/mesh.ply"/></shape>',
])
def test_path_entries_bitmaps_and_envmaps_outside_are_refused(cli, dirs, body):
    scene, _ = dirs
    (scene / "sub").mkdir()
    (scene / "s.xml").write_text(f'<scene version="3.0.0">{body}</scene>')
    rc, _, err = cli("convert", scene / "s.xml", scene / "out.usda")
    _one_error(rc, err)
    assert "outside the scene's folder" in err and not (scene / "out.usda").exists()


def test_a_symlink_out_of_the_scene_folder_is_refused(cli, dirs):
    scene, outside = dirs
    (scene / "link.ply").symlink_to(outside / "secret.ply")
    rc, _, err = cli("convert", _ply_scene(scene, "link.ply"), scene / "out.usda")
    _one_error(rc, err)
    assert "link.ply" in err


def _textured_stage(path, texture):
    stage = looking_down_at_floor(path, width=8, height=6)
    mat = diffuse_material(stage, "/World/Looks/Tex", texture=texture)
    floor_quad(stage, "/World/Floor2", material=mat)
    stage.GetRootLayer().Save()
    return path


def test_usd_textures_outside_the_stage_folder_are_refused(cli, dirs):
    scene, outside = dirs
    for i, tex in enumerate(("../outside/tex.exr", str(outside / "tex.exr"))):
        src = _textured_stage(scene / f"s{i}.usda", tex)
        for cmd in (("convert", src, scene / f"o{i}.xml"), ("render", src, "-o", scene / f"r{i}", "--spp", "1")):
            rc, _, err = cli(*cmd)
            _one_error(rc, err)
            assert "tex.exr" in err and "--allow-path" in err
        assert not (scene / f"o{i}.xml").exists() and not (scene / f"r{i}").exists()
    rc, _, err = cli("convert", scene / "s0.usda", scene / "ok.xml", "--allow-path", outside)
    assert rc == 0, err


def test_a_diffuse_target_outside_the_stage_folder_is_refused(cli, tmp_path, moto_stage):
    import shutil

    stage_dir = tmp_path / "st"
    shutil.copytree(moto_stage.parent, stage_dir)
    outside = tmp_path / "elsewhere.exr"
    shutil.copy(stage_dir / "estimates" / "diffuse.exr", outside)
    layer = Sdf.Layer.FindOrOpen(str(stage_dir / "scene.usda"))
    layer.GetAttributeAtPath("/Scene.usdrelight:diffuseTarget").default = Sdf.AssetPath(str(outside))
    layer.Save()
    before = (stage_dir / "lights_fitted.usda").read_bytes()
    rc, _, err = cli("fit", stage_dir / "scene.usda", "--iterations", "1")
    _one_error(rc, err)
    assert "elsewhere.exr" in err and "diffuse target" in err
    assert (stage_dir / "lights_fitted.usda").read_bytes() == before


def test_usdz_textures_are_extracted_for_the_xml_export(cli, tmp_path):
    from pxr import UsdUtils

    write_image(tmp_path / "tex.exr", np.full((4, 4, 3), 0.25, np.float32), "half")
    src = _textured_stage(tmp_path / "s.usda", "./tex.exr")
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(src)), str(tmp_path / "s.usdz"))
    rc, _, err = cli("convert", tmp_path / "s.usdz", tmp_path / "x" / "scene.xml")
    assert rc == 0, err
    xml = (tmp_path / "x" / "scene.xml").read_text()
    assert 'value="textures/tex.exr"' in xml and ".usdz" not in xml
    assert (tmp_path / "x" / "textures" / "tex.exr").read_bytes() == (tmp_path / "tex.exr").read_bytes()
    assert cli("convert", tmp_path / "x" / "scene.xml", tmp_path / "back.usda")[0] == 0


@pytest.mark.parametrize("ext", ["png", "exr", "jpg", "tif", "hdr", "tga", "ppm", "pfm"])
def test_a_malformed_image_error_never_quotes_its_bytes(cli, tmp_path, ext):
    """OpenImageIO's own messages can carry the first bytes (an EXR's "magic 0x5F495041" is "API_")."""
    from conftest import make_photo

    photo = make_photo(tmp_path / "p.png", 24, 32)
    (tmp_path / f"d.{ext}").write_text(SECRET + "\n")
    rc, _, err = cli("build", photo, "--depth", tmp_path / f"d.{ext}", "--fov-x", "60", "-o", tmp_path / "o")
    _one_error(rc, err)
    assert f"d.{ext}" in err and "0x" not in err and "magic" not in err.lower()
    assert not (tmp_path / "o").exists()
