"""Output folders and destinations that someone else prepared: a symbolic link planted where usdrelight writes,
a USD layer of a stage or a folder of foreign USD files as the destination, a path under a regular file. Each is
one line on stderr and exit 2, nothing is written outside the output folder, no file of the user changes and a
failed command leaves no folder behind (from a hostile-input probe of the command line)."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from conftest import build_procedural

LIGHT = "point:0.5,1.0,-2.5:3,2.5,2"


@pytest.fixture(scope="module")
def stage(tmp_path_factory) -> Path:
    return build_procedural(tmp_path_factory.mktemp("links") / "st", stride=2)


def _tree(folder: Path) -> dict:
    """Every path under ``folder`` (links not followed) -> its bytes' digest ('' for folders and links)."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for name in dirs + files:
            p = Path(root) / name
            out[str(p.relative_to(folder))] = "" if p.is_dir() or p.is_symlink() else \
                hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _refused(cli, *args, words: str) -> str:
    rc, out, err = cli(*args)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err and words in err, (args, err)
    return err


@pytest.mark.parametrize("planted", [".results", ".results/current"])
def test_relight_never_writes_through_a_link_planted_in_its_output_folder(cli, stage, tmp_path, planted):
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / ".results").mkdir(parents=True) if planted != ".results" else out.mkdir()
    (out / planted).symlink_to(elsewhere, target_is_directory=True)
    _refused(cli, "relight", stage, "--light", LIGHT, "--mode", "render", "--max-side", "32", "-o", out,
             words="symbolic link")
    assert _tree(elsewhere) == {} and sorted(p.name for p in out.iterdir()) == [".results"]
    rc, _, err = cli("relight", stage, "--light", LIGHT, "--mode", "render", "--max-side", "32", "-o", tmp_path / "ok")
    assert rc == 0 and (tmp_path / "ok" / "relit.exr").is_file(), err  # the same command into a clean folder


def test_convert_never_writes_through_a_planted_meshes_link(cli, stage, tmp_path):
    out, elsewhere = tmp_path / "xml", tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir()
    (out / "meshes").symlink_to(elsewhere, target_is_directory=True)
    _refused(cli, "convert", stage, out / "scene.xml", words="symbolic link")
    assert _tree(elsewhere) == {} and not (out / "scene.xml").exists()


def test_convert_and_build_never_write_over_the_users_layers(cli, stage, tmp_path, small_photo):
    before = _tree(stage.parent)
    version = next(p for p in (stage.parent / "versions").iterdir() if not p.is_symlink())
    for dst in ("lights_user.usda", "lights_fitted.usda", "geometry.usdc", version / "lights_fitted.usda"):
        _refused(cli, "convert", stage, stage.parent / dst, words="layer of a usdrelight stage")
    assert _tree(stage.parent) == before
    theirs = tmp_path / "their_project"  # a folder of someone else's USD files is not a stage to build into
    theirs.mkdir()
    (theirs / "scene.usda").write_text("#usda 1.0\n")
    (theirs / "lights_fitted.usda").write_text("#usda 1.0\n(doc = \"mine\")\n")
    mine = _tree(theirs)
    _refused(cli, "build", small_photo, "-o", theirs, words="is not a usdrelight stage but holds scene.usda")
    assert _tree(theirs) == mine
    rc, _, err = cli("convert", stage, tmp_path / "copy.usda")  # a new file is fine
    assert rc == 0 and (tmp_path / "copy.usda").is_file(), err


def test_paths_under_a_regular_file_fail_first_with_one_line(cli, stage, tmp_path):
    afile = tmp_path / "afile.txt"
    afile.write_text("x")
    for dst in ("x.xml", "x.glb", "x.usda"):
        _refused(cli, "convert", stage, afile / dst, words="is not a folder")
    _refused(cli, "relight", stage, "--light", LIGHT, "--mode", "render", "--max-side", "32", "--video",
             afile / "v.mp4", "-o", tmp_path / "out", words="is not a folder")
    assert not (tmp_path / "out").exists()  # refused before anything rendered
    before = (stage.parent / "scene.usda").read_bytes()
    _refused(cli, "fit", stage, "--max-side", "32", "--report", afile / "rep", words="is not a folder")
    assert (stage.parent / "scene.usda").read_bytes() == before  # nothing published by the failed command


def test_a_failed_conversion_leaves_no_empty_folder(cli, tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type=")
    _refused(cli, "convert", bad, tmp_path / "new" / "deeper" / "scene.usda", words="")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("args", [["fit", "s.usda", "--max-side", "-5"], ["relight", "s.usda", "--max-side", "0"],
                                  ["serve", "s.usda", "--port", "99999"], ["relight"], ["no-such-command"]])
def test_argument_errors_are_one_line(cli, args):
    with pytest.raises(SystemExit) as exc:
        cli(*args)
    assert exc.value.code == 2
    err = cli.capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and err.startswith("usdrelight: error: usdrelight") and "usage" not in err


def test_a_bad_model_fails_before_neural_renders_into_the_stage(cli, stage, tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_text("not a model")
    before = _tree(stage.parent)
    rc, _, err = cli("neural", stage, "--model", bad, "--render-missing", "--spp", "1", "-o", tmp_path / "n")
    assert rc == 2 and len(err.strip().splitlines()) == 1, err
    assert _tree(stage.parent) == before and not (tmp_path / "n").exists()  # no AOV rendered, nothing written
