"""Output folders and destinations that someone else prepared: a symbolic link planted where usdrelight writes,
a USD layer of a stage or a folder of foreign USD files as the destination, a path under a regular file. Each is
one line on stderr and exit 2, nothing is written outside the output folder, no file of the user changes and a
failed command leaves no folder behind (from a hostile-input probe of the command line)."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
from pathlib import Path

import pytest

from conftest import EXAMPLES, build_procedural

EXAMPLE = EXAMPLES / "procedural"
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
    # a destination through ``..`` makes two folders (``new`` and ``x``): both go
    _refused(cli, "convert", bad, f"{tmp_path}/new/../x/scene.usda", words="")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.xml"]
    (tmp_path / "mine").mkdir()  # a folder the user had, reached through a name that did not exist: kept
    _refused(cli, "convert", bad, f"{tmp_path}/new/../mine/scene.usda", words="")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.xml", "mine"]


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


def test_links_planted_in_a_stage_folder_are_refused(cli, tmp_path):
    st = build_procedural(tmp_path / "st", stride=4).parent
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "versions").mkdir(parents=True)
    for name in ("relit", "cache"):  # relight's default output, the transport cache
        shutil.rmtree(st / name, ignore_errors=True)
        (st / name).symlink_to(elsewhere, target_is_directory=True)
        _refused(cli, "relight", st / "scene.usda", "--light", LIGHT, "--mode", "render", "--max-side", "16",
                 words="leads outside")
        (st / name).unlink()
    out = tmp_path / "out"
    (out / ".results").mkdir(parents=True)  # current -> a sibling that is itself a link out of the folder
    (out / ".results" / "sib").symlink_to(elsewhere, target_is_directory=True)
    (out / ".results" / "current").symlink_to("sib")
    (out / "relit.exr").write_text("an older run's plain file")
    _refused(cli, "relight", st / "scene.usda", "--light", LIGHT, "--mode", "render", "--max-side", "16", "-o", out,
             words="symbolic link")
    for dst in ("textures/../lights_fitted.usda", "versions/current/lights_fitted.usda", "versions/current/new.usda"):
        _refused(cli, "convert", st / "scene.usda", st / dst, words="layer of a usdrelight stage")
    (tmp_path / "bl").mkdir()
    (tmp_path / "bl" / "scene_data").symlink_to(elsewhere, target_is_directory=True)
    _refused(cli, "convert", st / "scene.usda", tmp_path / "bl" / "scene.py", words="symbolic link")
    shutil.rmtree(st / "versions")  # a stage whose versions/ is a planted link: build never writes through it
    (st / "versions").symlink_to(elsewhere / "versions", target_is_directory=True)
    _refused(cli, "build", EXAMPLE / "photo.exr", "--depth", EXAMPLE / "depth.exr", "-o", st, words="symbolic link")
    assert _tree(elsewhere) == {"versions": ""}


def test_a_build_killed_before_its_first_publish_can_be_built_over(cli, tmp_path):
    out = tmp_path / "st"
    (out / "versions" / ".20260101T000000-deadbeef.tmp-1").mkdir(parents=True)  # what a SIGKILL leaves
    rc, _, err = cli("build", EXAMPLE / "photo.exr", "--depth", EXAMPLE / "depth.exr", "-o", out)
    assert rc == 0 and (out / "scene.usda").is_file(), err
    flat = tmp_path / "flat"  # a flattened copy of a stage carries its provenance, but is not a stage
    flat.mkdir()
    rc, _, err = cli("convert", out / "scene.usda", flat / "scene.usda")
    assert rc == 0, err
    _refused(cli, "build", EXAMPLE / "photo.exr", "--depth", EXAMPLE / "depth.exr", "-o", flat,
             words="is not a usdrelight stage")


def test_the_web_apps_export_and_upload_folders_stay_in_the_stage(tmp_path):
    import numpy as np

    from usdrelight.errors import UsdRelightError
    from usdrelight.serve.files import EXPORTS, UPLOADS, export_relit, video_path

    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "st" / "serve").mkdir(parents=True)
    (tmp_path / "st" / EXPORTS).symlink_to(elsewhere, target_is_directory=True)
    (tmp_path / "st" / UPLOADS).symlink_to(elsewhere, target_is_directory=True)
    for call in (lambda: export_relit(tmp_path / "st", np.ones((4, 4, 3), np.float32)),
                 lambda: video_path(tmp_path / "st")):
        with pytest.raises(UsdRelightError, match="leads outside"):
            call()
    assert _tree(elsewhere) == {}


def test_names_in_the_way_fail_before_anything_is_published(cli, stage, tmp_path):
    """A folder where a result file goes, or a file where its folder goes: one line, exit 2, nothing published
    (no broken links, no leftover version); with --video the old video stays with the old frames."""
    out = tmp_path / "r"
    (out / "renders" / "diffuse.exr").mkdir(parents=True)
    _refused(cli, "render", stage, "--spp", "1", "-o", out, words="in the way")
    assert not (out / ".results" / "current").exists() and not list((out / ".results").glob("v-*"))
    out2 = tmp_path / "r2"
    out2.mkdir()
    (out2 / "renders").write_text("a file")
    _refused(cli, "render", stage, "--spp", "1", "-o", out2, words="is not a folder")
    assert not list((out2 / ".results").glob("v-*")) and (out2 / "renders").read_text() == "a file"
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps([[LIGHT], ["point:-0.5,1.0,-2.5:2,3,2"]]))
    rel = tmp_path / "rel"
    args = ("relight", stage, "--sequence", seq, "--mode", "render", "--max-side", "16", "--video", rel / "v.mp4")
    rc, _, err = cli(*args, "-o", rel)
    assert rc == 0, err
    video, frame = (rel / "v.mp4").read_bytes(), (rel / "relit_0000.exr").read_bytes()
    (rel / "contact_sheet.png").mkdir()
    rc, _, err = cli(*args, "--contact-sheet", "-o", rel)  # (the unfitted stage logs the modes it leaves out)
    assert rc == 2 and [ln for ln in err.splitlines() if "error" in ln] == [err.strip().splitlines()[-1]], err
    assert "in the way" in err and "Traceback" not in err
    assert (rel / "v.mp4").read_bytes() == video and (rel / "relit_0000.exr").read_bytes() == frame
    conv = tmp_path / "conv"
    (conv / "scene_0001.xml").mkdir(parents=True)
    _refused(cli, "convert", stage, conv / "scene.xml", "--frames", "1:2", words="in the way")
    assert not (conv / "scene_0000.xml").exists()
    afile = tmp_path / "afile"
    afile.write_text("x")
    _refused(cli, "relight", stage, "--sequence", seq, "--save-lights", afile / "l.usda", "--mode", "render",
             "--max-side", "16", "-o", tmp_path / "sl", words="is not a folder")


def test_neural_default_folder_batch_manifest_and_a_rerun_keep_to_the_rules(cli, tmp_path):
    from usdrelight.batch.manifest import RECORD, read_manifest
    from usdrelight.batch.task import _replace
    from usdrelight.errors import UsdRelightError

    st = build_procedural(tmp_path / "st", stride=4).parent
    (tmp_path / "elsewhere").mkdir()
    (st / "neural").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    _refused(cli, "neural", st / "scene.usda", "--render-missing", "--spp", "1", words="leads outside")
    assert _tree(tmp_path / "elsewhere") == {}
    (tmp_path / "b" / "manifest.jsonl").mkdir(parents=True)
    with pytest.raises(UsdRelightError, match="is not a file"):
        read_manifest(tmp_path / "b")  # batch reads it first, before any photo is processed
    final, tmp = tmp_path / "b" / "a", tmp_path / "b" / ".a.tmp"
    for folder, lights in ((final, "#usda 1.0\n(doc = \"my own lights\")\n"), (tmp, "#usda 1.0\n")):
        folder.mkdir()
        (folder / RECORD).write_text("{}")
        (folder / "lights_user.usda").write_text(lights)
    _replace(tmp, final)  # a re-run of the photo: the new stage keeps the user's own lights
    assert "my own lights" in (final / "lights_user.usda").read_text()


def test_render_product_names_never_land_on_the_stages_own_files(cli, tmp_path):
    from pxr import Usd

    st = build_procedural(tmp_path / "st", stride=4)
    before = _tree(st.parent / "versions")
    for name in ("versions/current/estimates/diffuse.exr", "estimates/diffuse.exr", "source/photo.exr"):
        stage = Usd.Stage.Open(str(st))
        stage.GetPrimAtPath("/Render/Products/diffuse").GetAttribute("productName").Set(name)
        stage.GetRootLayer().Save()
        rc, _, err = cli("render", st, "--spp", "1", "--aov", "diffuse")
        assert rc == 2 and len(err.strip().splitlines()) == 1 and "stage's own files" in err, (name, err)
        assert _tree(st.parent / "versions") == before


def test_a_planted_lock_link_and_links_inside_a_previous_result_are_not_trusted(cli, stage, tmp_path):
    from usdrelight.atomic import LOCK_NAME, RESULTS_DIR

    out = tmp_path / "o"
    out.mkdir()
    (out / LOCK_NAME).symlink_to(tmp_path / "nowhere")  # a dangling link where the lock goes
    _refused(cli, "render", stage, "--spp", "1", "-o", out, words="not a lock usdrelight made")
    (out / LOCK_NAME).unlink()
    rc, _, err = cli("render", stage, "--spp", "1", "-o", out)
    assert rc == 0, err
    secret = tmp_path / "secret.txt"
    secret.write_text("not yours")
    current = out / RESULTS_DIR / os.readlink(out / RESULTS_DIR / "current")
    (current / "renders" / "normal.exr").unlink()
    (current / "renders" / "normal.exr").symlink_to(secret)  # planted inside the previous result
    rc, _, err = cli("render", stage, "--spp", "1", "--aov", "diffuse", "-o", out)  # keeps the other AOVs
    assert rc == 0, err
    normal = out / "renders" / "normal.exr"
    assert not normal.exists() or secret not in (normal.resolve(), *normal.resolve().parents)
    assert (out / "renders" / "albedo.exr").is_file()  # the previous result's own files are carried


def test_a_failed_build_never_removes_a_stage_another_build_published_meanwhile(cli, tmp_path, monkeypatch):
    """Two builds into one new folder: the second checks the folder, then waits for the lock while the first
    publishes. If the second then fails, it must not remove the folder as if it had made it."""
    import usdrelight.stage.write as write

    theirs = tmp_path / "theirs"
    rc, _, err = cli("build", EXAMPLE / "photo.exr", "--depth", EXAMPLE / "depth.exr", "-o", theirs)
    assert rc == 0, err
    out = tmp_path / "st"
    real_lock = write.stage_lock

    @contextlib.contextmanager
    def lock_after_the_other_build(folder):
        shutil.copytree(theirs, out, symlinks=True)  # the other build published while this one waited
        with real_lock(folder) as f:
            yield f

    def full_disk(*_):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(write, "stage_lock", lock_after_the_other_build)
    monkeypatch.setattr(write, "_write_version", full_disk)
    assert not out.exists()
    rc, _, err = cli("build", EXAMPLE / "photo.exr", "--depth", EXAMPLE / "depth.exr", "-o", out)
    assert rc == 2 and err.strip().splitlines()[-1].endswith("No space left on device"), err
    assert _tree(out) == _tree(theirs)  # the published stage is untouched
