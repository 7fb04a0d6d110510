"""What users install: the wheel built from this tree, installed non-editable into a fresh virtual environment,
used from outside the checkout.

The fresh environment has no pip packages of its own: a ``.pth`` line makes the development environment's
site-packages visible *after* its own, for the dependencies only. Python appends such a line to ``sys.path``
without processing the ``.pth`` files inside it, so the editable install's import hook (which would supply a
module the wheel lacks from the checkout) is not active there; the test asserts that too.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Source folder -> the package it installs as (pyproject's package-dir).
SOURCES = {ROOT / "usdrelight": "usdrelight", ROOT / "converters": "usdrelight/converters",
           ROOT / "schemas": "usdrelight/schemas"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(out),
                        str(ROOT)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    (whl,) = out.glob("usdrelight-*.whl")
    return whl


def _expected_files() -> set[str]:
    """Every module and data file of the source tree, as its path inside the wheel."""
    out = set()
    for folder, prefix in SOURCES.items():
        for path in folder.rglob("*"):
            rel = path.relative_to(folder)
            if path.is_file() and "__pycache__" not in rel.parts and not (prefix == "usdrelight" and
                                                                          rel.parts[0] in ("schemas", "converters")):
                if path.suffix in (".py", ".json", ".usda", ".onnx", ".md", ".txt"):
                    out.add(f"{prefix}/{rel.as_posix()}")
    return out


def test_every_module_and_data_file_is_in_the_wheel(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(_expected_files() - names)
    assert not missing, f"not in the wheel (add the package to pyproject.toml): {missing}"
    assert "usdrelight/engine/fast.py" in names and "usdrelight/models/relight_unet.onnx" in names
    assert "usdrelight/models/transfer_residual.onnx" in names
    assert not any(n.startswith(("converters/", "schemas/", "tests/")) for n in names)


def test_wheel_in_a_fresh_venv_builds_fits_and_relights_from_outside_the_checkout(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
                        "--no-index", str(wheel)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    site = Path(subprocess.check_output([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                        text=True).strip())
    (site / "zz_dev_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    work = tmp_path / "work"  # outside the checkout: nothing of the source tree is importable from here
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    exe = venv / "bin" / "usdrelight"

    def run(*args):
        r = subprocess.run([str(a) for a in args], capture_output=True, text=True, cwd=work, env=env, timeout=600)
        assert r.returncode == 0, f"{args[1:3]}: {r.stderr[-3000:]}"
        return r.stdout

    probe = textwrap.dedent("""
        import json, sys, usdrelight
        import usdrelight.fit.run, usdrelight.relight.session  # sub-packages named like API functions, loaded first
        from pxr import Usd
        names = {n: getattr(usdrelight, n).__module__ for n in usdrelight.API}
        stage = Usd.Stage.CreateInMemory(); p = stage.DefinePrim("/A", "Xform")
        p.AddAppliedSchema("RelightProvenanceAPI")
        print(json.dumps({"file": usdrelight.__file__, "names": names,
                          "hooks": [type(f).__name__ for f in sys.meta_path],
                          "fallback": p.GetAttribute("usdrelight:fit:psnrDb").Get()}))
    """)
    info = json.loads(run(py, "-c", probe))
    assert info["file"].startswith(str(site)), info["file"]
    assert not any("editable" in h.lower() for h in info["hooks"]), info["hooks"]
    assert set(info["names"]) == {"build", "BuildOptions", "BuildResult", "fit", "FitSettings", "FitReport", "render",
                                  "RenderResult", "RelightSession", "RelitFrame", "relight", "RelightResult", "convert",
                                  "ConvertReport", "read_scene", "SceneRecord", "validate", "Finding", "allow_paths"}
    assert info["fallback"] == -1.0  # the schema plugin registered from the installed package

    ex = ROOT / "examples" / "procedural"
    run(exe, "build", ex / "photo.exr", "--depth", ex / "depth.exr", "--intrinsics", ex / "intrinsics.json",
        "--albedo", ex / "albedo.exr", "-o", "stage")
    fit = json.loads(run(exe, "fit", "stage/scene.usda", "--lights", "4", "--verify-spp", "0", "--json"))
    assert fit["lights_kept"] >= 1 and fit["psnr_db"] > 20
    rel = json.loads(run(exe, "relight", "stage/scene.usda", "--with-fitted", "--max-side", "64",
                         "--light", "point:0.5,1,-2.5:3,3,3", "-o", "relit", "--json"))
    assert rel["renderer"] == "fast" and rel["mode"] == "add"
    off = json.loads(run(exe, "relight", "stage/scene.usda", "--max-side", "64", "--light", "point:0.5,1,-2.5:3,3,3",
                         "-o", "relit_off", "--json"))
    assert off["mode"] == "residual"  # the photo's light off: the shipped residual network, from the wheel
    # area lights from the installed package (4 shadow rays): a rect whose width is keyed, saved as a time-sampled layer
    (work / "area.json").write_text(json.dumps([["rect:0.3,1.6,-3:0,-1,0.2:6,6,6:0.5,0.25"],
                                                ["rect:0.3,1.6,-3:0,-1,0.2:6,6,6:0.75,0.25"]]))
    area = json.loads(run(exe, "relight", "stage/scene.usda", "--with-fitted", "--max-side", "64", "--sequence",
                          "area.json", "--save-lights", "area_lights.usda", "--area-samples", "4", "-o", "relit_area",
                          "--json"))
    assert len(area["frames"]) == 2 and area["lights_layer"].endswith("area_lights.usda")
    layer = (work / "area_lights.usda").read_text()
    assert "RectLight" in layer and "float inputs:width.timeSamples" in layer
    assert (work / "relit" / "relit.png").is_file() and (work / "stage" / "cache").is_dir()
    assert not (ROOT / "stage").exists()  # nothing was written into the checkout
