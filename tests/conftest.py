"""Shared fixtures: the bundled examples, small synthetic photos, a CLI runner."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import usdrelight  # noqa: F401  (configures drjit's libLLVM before any Mitsuba import)
from usdrelight.cli import main
from usdrelight.imageio import write_image

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
MOTO = EXAMPLES / "motorcycle"
# CI clones the project with shared/ beside it; USDRELIGHT_TESTDATA points elsewhere when needed.
SHARED = Path(os.environ.get("USDRELIGHT_TESTDATA", ROOT.parent / "shared" / "testdata"))


@pytest.fixture(scope="session")
def moto_paths():
    return {"photo": MOTO / "photo.png", "depth": MOTO / "depth.exr", "intrinsics": MOTO / "intrinsics.json"}


@pytest.fixture(scope="session")
def moto_stage(tmp_path_factory, moto_paths):
    out = tmp_path_factory.mktemp("moto") / "scene"
    rc = main(["build", str(moto_paths["photo"]), "--depth", str(moto_paths["depth"]),
               "--intrinsics", str(moto_paths["intrinsics"]), "-o", str(out)])
    assert rc == 0
    return out / "scene.usda"


class Cli:
    """Runs ``usdrelight`` in-process and captures exit code, stdout and stderr."""

    def __init__(self, capsys):
        self.capsys = capsys

    def __call__(self, *args):
        self.capsys.readouterr()
        rc = main([str(a) for a in args])
        out, err = self.capsys.readouterr()
        return rc, out, err

    def json(self, *args):
        rc, out, err = self(*args, "--json")
        assert rc == 0, err
        return json.loads(out)


@pytest.fixture
def cli(capsys):
    return Cli(capsys)


def make_photo(path: Path, h: int = 24, w: int = 32, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    img = np.clip(rng.random((h, w, 3)) * 0.5 + 0.25, 0, 1).astype(np.float32)
    write_image(path, img, "uint8", srgb=True)
    return path


@pytest.fixture
def small_photo(tmp_path):
    return make_photo(tmp_path / "photo.png")


def write_plane_depth(path: Path, h: int, w: int, z: float = 2.0) -> Path:
    np.save(path, np.full((h, w), z, np.float32))
    return path


def build_procedural(out: Path, stride: int = 1) -> Path:
    """Build the procedural example (exact depth, intrinsics and albedo) into ``out``; returns its scene.usda."""
    from usdrelight.stage.build import BuildOptions, build

    ex = EXAMPLES / "procedural"
    build(ex / "photo.exr", out, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                              albedo=ex / "albedo.exr", stride=stride))
    return out / "scene.usda"
