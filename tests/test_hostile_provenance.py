"""AOV provenance (issue 10): ``render`` stamps every AOV file with the stage state it was rendered from;
``neural`` refuses AOV files of another state (a rebuild of another size, a fit, edited lights, another tool)
and re-renders them with ``--render-missing``."""
from __future__ import annotations

import numpy as np

from conftest import make_photo, write_plane_depth
from usdrelight.imageio import image_attribute, read_map, write_image
from usdrelight.mitsuba.render import STAMP_KEY

AOVS = ("diffuse", "albedo", "valid")


def _build(cli, tmp_path, h, w, seed=0):
    photo = make_photo(tmp_path / f"p{h}.png", h, w, seed=seed)
    write_plane_depth(tmp_path / f"d{h}.npy", h, w)
    rc, _, err = cli("build", photo, "--depth", tmp_path / f"d{h}.npy", "--fov-x", "60", "-o", tmp_path / "s")
    assert rc == 0, err
    return tmp_path / "s" / "scene.usda"


def _stale_error(cli, stage, out):
    rc, _, err = cli("neural", stage, "-o", out)
    assert rc == 2 and err.count("\n") == 1 and "were not rendered from" in err, err
    assert not out.exists()


def test_neural_refuses_aovs_of_another_stage_state(cli, tmp_path):
    stage = _build(cli, tmp_path, 24, 32)
    assert cli("render", stage, "--aov", *AOVS, "--spp", "1")[0] == 0
    renders = stage.parent / "renders"
    assert all(image_attribute(renders / f"{a}.exr", STAMP_KEY) for a in AOVS)
    assert cli("neural", stage, "-o", tmp_path / "n0")[0] == 0
    # a rebuild of another size: the old AOV files are stale (and of the wrong size)
    stage = _build(cli, tmp_path, 36, 48, seed=1)
    before = {a: (renders / f"{a}.exr").read_bytes() for a in AOVS}
    _stale_error(cli, stage, tmp_path / "n1")
    assert {a: (renders / f"{a}.exr").read_bytes() for a in AOVS} == before  # refused, not touched
    res = cli.json("neural", stage, "--render-missing", "--spp", "1", "-o", tmp_path / "n2")
    assert read_map(res["exr"], 3).shape == (36, 48, 3)
    # the user's lights edited since the render
    (stage.parent / "lights_user.usda").write_text(
        '#usda 1.0\nover "Scene"\n{\n    def Scope "Lights"\n    {\n        def Scope "User"\n        {\n'
        '            def DomeLight "Sky"\n            {\n                float inputs:intensity = 2\n'
        '            }\n        }\n    }\n}\n')
    _stale_error(cli, stage, tmp_path / "n3")
    # an AOV file of the right size written by another tool (no stamp)
    assert cli("render", stage, "--aov", *AOVS, "--spp", "1")[0] == 0
    assert cli("neural", stage, "-o", tmp_path / "n4")[0] == 0
    write_image(renders / "albedo.exr", np.full((36, 48, 3), 0.5, np.float32), "float")
    _stale_error(cli, stage, tmp_path / "n5")
