"""Legal-but-odd inputs end cleanly (issue 25): self-contained stage folders, the source photo under the read
confinement, .usdz stages, huge sample counts, long sequences, control characters in names, and converters that
leave nothing but their outputs. Each asserts the exit status, the one line and the files on disk."""
from __future__ import annotations

import json
from pathlib import Path
import os
import shutil

import numpy as np
import pytest
from pxr import Sdf, Usd

from conftest import EXAMPLES, build_procedural, make_photo

from usdrelight.imageio import read_map


def _one_error(rc, err, *words):
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("usdrelight: error:"), err
    assert "Traceback" not in err and "unexpected" not in err, err
    for w in words:
        assert w in err, (w, err)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """The procedural example built and fitted (small), in a folder of its own."""
    from usdrelight.fit.run import FitSettings, fit

    stage = build_procedural(tmp_path_factory.mktemp("fitted") / "st")
    fit(stage, FitSettings(lights=2, iterations=8, max_side=64, verify_spp=0))
    return stage


def test_the_stage_folder_carries_its_photo_and_moves_as_one(cli, fitted, tmp_path):
    stage = Usd.Stage.Open(str(fitted))
    asset = stage.GetDefaultPrim().GetAttribute("usdrelight:sourcePhoto").Get()
    assert asset.path.startswith("./versions/") and asset.path.endswith("/source/photo.exr"), asset.path
    assert (fitted.parent / asset.path).read_bytes() == (EXAMPLES / "procedural" / "photo.exr").read_bytes()
    moved = tmp_path / "elsewhere" / "st"
    shutil.copytree(fitted.parent, moved, symlinks=True)
    rc, out, err = cli("relight", moved / "scene.usda", "--with-fitted", "--max-side", "48", "-o", tmp_path / "r",
                       "--json")
    assert rc == 0, err
    assert json.loads(out)["mode"] == "add"
    # the fitted lights kept and nothing added: the photo itself comes back
    relit = read_map(tmp_path / "r" / "relit.exr", 3)
    assert relit.shape[:2] == (36, 48) and np.all(np.isfinite(relit)) and relit.mean() > 0


def test_a_source_photo_outside_the_stage_folder_is_refused(cli, fitted, tmp_path):
    work = tmp_path / "st"
    shutil.copytree(fitted.parent, work, symlinks=True)
    outside = make_photo(tmp_path / "outside.png", 24, 32)
    layer = Sdf.Layer.FindOrOpen(str(work / "scene.usda"))
    layer.GetAttributeAtPath("/Scene.usdrelight:sourcePhoto").default = Sdf.AssetPath(str(outside))
    layer.Save()
    rc, _, err = cli("relight", work / "scene.usda", "--with-fitted", "--max-side", "48", "-o", tmp_path / "r")
    _one_error(rc, err, "outside.png", "outside the scene's folder", "--allow-path")
    assert not (tmp_path / "r").exists()
    rc, _, err = cli("relight", work / "scene.usda", "--with-fitted", "--max-side", "48", "-o", tmp_path / "r",
                     "--allow-path", tmp_path)
    assert rc == 0, err


def test_a_usdz_stage_renders_relights_and_converts_and_refuses_fit(cli, fitted, tmp_path):
    from pxr import UsdUtils

    usdz = tmp_path / "pkg" / "scene.usdz"
    usdz.parent.mkdir()
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(fitted)), str(usdz))
    rc, out, err = cli("render", usdz, "--spp", "2", "-o", tmp_path / "aovs", "--json")
    assert rc == 0, err
    files = json.loads(out)["files"]
    assert files and all(str(tmp_path / "aovs") in f for f in files.values())
    rc, out, err = cli("relight", usdz, "--with-fitted", "--max-side", "48", "-o", tmp_path / "r", "--json")
    assert rc == 0, err
    assert (tmp_path / "r" / "relit.png").is_file()
    rc, _, err = cli("convert", usdz, tmp_path / "x" / "scene.xml")
    assert rc == 0, err
    assert (tmp_path / "x" / "scene.xml").is_file()
    before = sorted(p.name for p in usdz.parent.iterdir())
    rc, _, err = cli("fit", usdz)
    _one_error(rc, err, "scene.usdz", "read-only")
    assert sorted(p.name for p in usdz.parent.iterdir()) == before


def test_a_usdz_packages_private_folder_is_gone_after_the_command(fitted, tmp_path):
    """The package is unpacked into a private temporary folder, removed at exit: the folder itself, not only the
    package's folder inside it (an empty usdrelight-usdz-* folder was left per run)."""
    import subprocess
    import sys

    from pxr import UsdUtils

    usdz = tmp_path / "scene.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(fitted)), str(usdz))
    temp = tmp_path / "tmp"
    temp.mkdir()
    p = subprocess.run([sys.executable, "-m", "usdrelight", "convert", str(usdz), str(tmp_path / "x.xml")],
                       capture_output=True, text=True, timeout=300, env={**os.environ, "TMPDIR": str(temp)})
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "x.xml").is_file() and not [q.name for q in temp.iterdir() if "usdz" in q.name]


def test_a_huge_sample_count_is_one_clear_line(cli, fitted, tmp_path):
    rc, _, err = cli("render", fitted, "--spp", "100000000", "-o", tmp_path / "aovs")
    _one_error(rc, err, "--spp", "100000000")
    assert not (tmp_path / "aovs").exists()
    rc, _, err = cli("relight", fitted, "--renderer", "mitsuba", "--spp", "100000000", "--with-fitted",
                     "-o", tmp_path / "r")
    _one_error(rc, err, "100000000")
    assert not (tmp_path / "r").exists()


def test_a_long_sequence_is_refused_before_anything_is_written(cli, fitted, tmp_path):
    seq = tmp_path / "lights.json"
    seq.write_text(json.dumps([["point:0,1,-2:1,1,1"]] * 100_000))
    rc, _, err = cli("relight", fitted, "--sequence", seq, "-o", tmp_path / "r")
    _one_error(rc, err, "100000 frames", "10000")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("name", ["new\nline.png", "tab\there.png", "bell\x07.png"])
def test_control_characters_in_a_photo_name_are_handled(cli, tmp_path, name):
    """A photo whose name has a control character builds (the name is only ever a file name) or is refused with one
    line that does not print the raw control character."""
    photo = make_photo(tmp_path / name, 24, 32)
    rc, _, err = cli("build", photo, "--fov-x", "60", "-o", tmp_path / "o")
    if rc == 0:
        assert (tmp_path / "o" / "scene.usda").is_file()
    else:
        _one_error(rc, err)
        assert not any(c in err[:-1] for c in "\t\x07") and not (tmp_path / "o").exists()


def test_a_blend_export_leaves_no_backup_or_hidden_file(cli, fitted, tmp_path):
    out = tmp_path / "b"
    for _ in range(2):  # the second run replaces the first .blend
        rc, _, err = cli("convert", fitted, out / "y.blend")
        assert rc == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["y.blend"]


def test_usd_packages_are_written_and_unpacked_ones_are_copied_not_referenced(cli, fitted, tmp_path):
    """.usdz as a destination was an unexpected exception (exit 1): it is now the flattened layer packaged with
    every file it references, and it opens, validates and reads as its source does. A .usdz source converted to
    .usda pointed at files in the private folder removed at exit: they are now copied beside the copy."""
    import subprocess
    import sys

    from usdrelight.stage.read import read_scene
    from usdrelight.stage.validate import open_stage

    pkg = tmp_path / "out" / "scene.usdz"
    rc, out, err = cli("convert", fitted, pkg, "--json")
    assert rc == 0, err
    assert json.loads(out)["files"] == [str(pkg)]
    src, back = read_scene(open_stage(fitted)), read_scene(open_stage(pkg))
    assert [m.points.shape for m in back.meshes] == [m.points.shape for m in src.meshes]
    tex = Path(back.meshes[0].material.diffuse.path)  # the albedo texture came inside the package
    assert tex.parent.name == "textures" and tex.name.startswith("albedo_") and tex.is_file()
    np.testing.assert_allclose([l.radiance for l in back.lights], [l.radiance for l in src.lights])
    copy = tmp_path / "copy" / "scene.usda"
    p = subprocess.run([sys.executable, "-m", "usdrelight", "convert", str(pkg), str(copy)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert "usdrelight-usdz" not in copy.read_text()  # nothing points into the removed folder
    assert list((copy.parent / "textures").iterdir())
    for path in (pkg, copy):  # in a fresh process: every dependency resolves
        p = subprocess.run([sys.executable, "-m", "usdrelight", "validate", str(path), "--json"],
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0 and json.loads(p.stdout)["errors"] == 0, (path, p.stdout[-800:], p.stderr)


def test_a_package_never_takes_in_a_file_from_outside_the_scene_folder(cli, tmp_path):
    """A stage naming /some/other/place/secret.png as a texture: convert to .usdz would copy that file into the
    package. It is refused as every scene read outside the scene's folder is, unless --allow-path allows it."""
    from PIL import Image

    outside = tmp_path / "outside"
    outside.mkdir()
    Image.new("RGB", (2, 2), (200, 10, 10)).save(outside / "secret.png")
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "s.usda").write_text(f'''#usda 1.0
def Material "M" {{
    def Shader "T" {{
        uniform token info:id = "UsdUVTexture"
        asset inputs:file = @{outside / "secret.png"}@
    }}
}}
''')
    rc, _, err = cli("convert", scene / "s.usda", tmp_path / "out" / "s.usdz")
    _one_error(rc, err, "secret.png", "outside")
    assert not (tmp_path / "out").exists()
    rc, _, err = cli("convert", scene / "s.usda", tmp_path / "out" / "s.usdz", "--allow-path", outside)
    assert rc == 0, err
    import zipfile
    assert any(n.endswith(".png") for n in zipfile.ZipFile(tmp_path / "out" / "s.usdz").namelist())
