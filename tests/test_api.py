"""The public API at the package top: loaded lazily, documented, typed, and not hidden by sub-packages of the
same name."""
from __future__ import annotations

import inspect
import json
import pydoc
import subprocess
import sys

import numpy as np

import usdrelight


def test_import_and_help_load_no_renderer():
    code = ("import sys, usdrelight, usdrelight.cli; print(sorted(m for m in ('mitsuba', 'drjit', 'usdrelight.api', "
            "'usdrelight.engine', 'usdrelight.fit', 'onnxruntime') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_every_api_name_is_documented_and_functions_are_typed():
    for name in usdrelight.API:
        obj = getattr(usdrelight, name)
        assert inspect.getdoc(obj) and len(inspect.getdoc(obj)) > 40, name
        if inspect.isfunction(obj):
            sig = inspect.signature(obj)
            assert sig.return_annotation is not inspect.Signature.empty, name
    text = pydoc.render_doc(usdrelight.RelightSession, renderer=pydoc.plaintext)
    for words in ("max_side", "with_fitted", "stage_lights", "render(self", "close(self", "pixels"):
        assert words in text, words
    assert set(dir(usdrelight)) >= set(usdrelight.API)


def test_sub_packages_named_like_functions_do_not_hide_them():
    code = ("import usdrelight.fit.run, usdrelight.relight.session, usdrelight; "
            "from usdrelight.fit import run; import inspect, json; "
            "print(json.dumps([inspect.isfunction(usdrelight.fit), inspect.isfunction(usdrelight.relight), "
            "run.__name__]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert json.loads(out) == [True, True, "usdrelight.fit.run"]


def test_the_readme_python_example_runs_through_the_api(tmp_path):
    """build -> fit -> RelightSession.render on the procedural example, through the package top only."""
    from conftest import EXAMPLES

    ex = EXAMPLES / "procedural"
    res = usdrelight.build(ex / "photo.exr", tmp_path / "st", usdrelight.BuildOptions(
        depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json", albedo=ex / "albedo.exr"))
    assert usdrelight.validate(res.stage) is not None
    rep = usdrelight.fit(res.stage, usdrelight.FitSettings(lights=4, verify_spp=0))
    assert rep.lights_kept >= 1 and rep.psnr_db > 20
    scene = usdrelight.read_scene(res.stage)
    assert len(scene.lights) == rep.lights_kept + (1 if rep.environment_kept else 0)
    with usdrelight.RelightSession(res.stage, max_side=64, with_fitted=True) as session:
        same = session.render()
        brighter = session.render(["point:0.5,1,-2.5:3,3,3"])
    assert session.mode == "add"  # auto: the photo's light kept as it is
    np.testing.assert_allclose(same.image, session.photo, rtol=1e-5, atol=1e-6)  # the photo's own light: itself
    assert brighter.image.mean() > same.image.mean() and np.all(brighter.image >= same.image - 1e-6)
