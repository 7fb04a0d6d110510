"""Loud failures (issue 10): a stage whose layers do not compose (a syntax error in lights_user.usda, a missing
or cyclic sublayer, a missing referenced asset or texture) makes every command that reads it exit 2 with one
line naming the layer, and write nothing; USD's own warnings do not pile up on stderr."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pxr import Sdf

from conftest import make_photo, write_plane_depth
from usdrelight.stage.versions import version_folder

USDRELIGHT = Path(sys.executable).with_name("usdrelight")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from usdrelight.cli import main

    d = tmp_path_factory.mktemp("built")
    photo = make_photo(d / "p.png", 24, 32)
    write_plane_depth(d / "d.npy", 24, 32)
    assert main(["build", str(photo), "--depth", str(d / "d.npy"), "-o", str(d / "stage")]) == 0
    return d / "stage"


def _break(folder: Path, how: str) -> str:
    """Break the copied stage in ``folder``; returns a word the error must contain."""
    if how == "syntax":
        (folder / "lights_user.usda").write_text('#usda 1.0\ndef Xform "Scene" {\n  def SphereLight "L" {\n')
        return "lights_user.usda:4"
    root = Sdf.Layer.FindOrOpen(str(folder / "scene.usda"))
    if how == "missing":
        root.subLayerPaths.append("./nowhere.usda")
        root.Save()
        return "nowhere.usda"
    if how == "cycle":
        user = Sdf.Layer.FindOrOpen(str(folder / "lights_user.usda"))
        user.subLayerPaths.append("./scene.usda")
        user.Save()
        return "cycle"
    if how == "reference":
        root.GetPrimAtPath("/Scene").referenceList.Prepend(Sdf.Reference("./gone.usda"))
        root.Save()
        return "gone.usda"
    (version_folder(folder) / "textures" / "albedo.exr").unlink()
    return "albedo.exr"


COMMANDS = {
    "render": lambda s, o: ["render", s, "-o", o, "--spp", "1"],
    "convert": lambda s, o: ["convert", s, o / "scene.xml"],
    "fit": lambda s, o: ["fit", s, "--report", o, "--iterations", "1"],
    "relight": lambda s, o: ["relight", s, "--light", "point:0,1,0:1,1,1", "-o", o],
    "neural": lambda s, o: ["neural", s, "-o", o, "--render-missing", "--spp", "1"],
    "validate": lambda s, o: ["validate", s],
}


@pytest.mark.parametrize("how", ["syntax", "missing", "cycle", "reference", "texture"])
def test_a_broken_layer_stack_fails_every_command_loudly(cli, built, tmp_path, how):
    folder = tmp_path / "stage"
    shutil.copytree(built, folder)
    needle = _break(folder, how)
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    for name, argv in COMMANDS.items():
        if how == "texture" and name == "validate":
            continue  # validate checks the layers, not the files textures name
        out = tmp_path / f"out_{name}"
        rc, stdout, err = cli(*argv(folder / "scene.usda", out))
        assert rc == 2, (name, err)
        assert err.count("\n") == 1 and err.startswith("usdrelight: error:"), (name, err)
        assert needle in err and "unexpected" not in err, (name, err)
        assert not out.exists() or not any(out.iterdir()), name
    after = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert after == before  # nothing rewritten (lights_fitted.usda, the user's layer ...)


def test_one_stderr_line_from_the_real_process(built, tmp_path):
    folder = tmp_path / "stage"
    shutil.copytree(built, folder)
    _break(folder, "syntax")
    p = subprocess.run([str(USDRELIGHT), "render", str(folder / "scene.usda"), "--json"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.count("\n") == 1 and "lights_user.usda:4" in p.stderr and "Warning" not in p.stderr


def test_a_layer_at_zero_time_codes_per_second_is_one_error_not_a_hang(tmp_path):
    """USD itself spins forever reading the time samples of a sublayer whose timeCodesPerSecond is 0 (every command
    hung at 100% CPU); the layer is refused when the stage opens."""
    (tmp_path / "sub.usda").write_text('#usda 1.0\n(\n    timeCodesPerSecond = 0\n)\ndef Xform "A" {\n'
                                       '    double3 xformOp:translate.timeSamples = { 1: (0, 0, 0), 2: (1, 0, 0) }\n'
                                       '    uniform token[] xformOpOrder = ["xformOp:translate"]\n}\n')
    (tmp_path / "root.usda").write_text('#usda 1.0\n(\n    subLayers = [@./sub.usda@]\n)\n')
    for cmd in (["validate", "root.usda"], ["convert", "root.usda", "out.xml"]):
        p = subprocess.run([sys.executable, "-m", "usdrelight", *cmd], cwd=tmp_path, capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 2 and p.stderr == ("usdrelight: error: layer sub.usda of root.usda authors "
                                                  "timeCodesPerSecond 0.0: it must be finite and positive\n"), p.stderr
    assert not (tmp_path / "out.xml").exists()
