"""The public API at the package top: loaded lazily, documented, typed, and not hidden by sub-packages of the
same name."""
from __future__ import annotations

import inspect
import re
import json
import pydoc
import subprocess
import sys

import numpy as np
import pytest

import usdrelight
from usdrelight.imageio import read_raw
from usdrelight.errors import UsdRelightError

from conftest import EXAMPLES


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
    on_disk = {p.relative_to(res.stage.parent).as_posix(): p.stat().st_size
               for p in res.stage.parent.rglob("*") if p.is_file() and not p.is_symlink()}
    assert res.files == on_disk  # every file, relative to the stage folder (lights_user.usda was missing)
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


@pytest.fixture(scope="module")
def api_stage(tmp_path_factory):
    from conftest import EXAMPLES

    ex = EXAMPLES / "procedural"
    out = tmp_path_factory.mktemp("api") / "st"
    res = usdrelight.build(ex / "photo.exr", out, usdrelight.BuildOptions(
        depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json", albedo=ex / "albedo.exr"))
    usdrelight.fit(res.stage, usdrelight.FitSettings(lights=1, max_side=32, verify_spp=0))
    return res.stage


BAD_CALLS = {  # found by probing the API: each was accepted (a 1 x 1 fit written over the good one, a render that
    # never ended) or raised a bare TypeError / AttributeError / MemoryError / a Mitsuba binding error
    "fit max_side -4": (lambda s: usdrelight.fit(s, usdrelight.FitSettings(max_side=-4, verify_spp=0)),
                        "max_side (--max-side) must be an integer >= 1, got -4"),
    "fit lights nan": (lambda s: usdrelight.fit(s, usdrelight.FitSettings(lights=float("nan"), verify_spp=0)),
                       "lights (--lights) must be an integer in [0, 256]"),
    "fit env_res tuple": (lambda s: usdrelight.fit(s, usdrelight.FitSettings(verify_spp=0, env_res=(1000, 1000))),
                          "1000000 cells, over this method's limit"),
    "fit seed -1": (lambda s: usdrelight.fit(s, usdrelight.FitSettings(seed=-1, verify_spp=0)),
                    "seed (--seed) must be an integer"),
    "fit a dict": (lambda s: usdrelight.fit(s, {"lights": 1}), "settings must be a FitSettings, got dict"),
    "session max_depth 1e9": (lambda s: usdrelight.RelightSession(s, max_side=32, max_depth=10 ** 9),
                              "max_depth (--max-depth) must be an integer in [2, 1024]"),
    "session max_side -5": (lambda s: usdrelight.RelightSession(s, max_side=-5), "max_side (--max-side) must be"),
    "session cache str": (lambda s: usdrelight.RelightSession(s, cache="/tmp/c"), "cache must be a TransportCache"),
    "render seed -1": (lambda s: usdrelight.render(s, s.parent / "x", aovs=["diffuse"], spp=1, seed=-1),
                       "seed (--seed) must be an integer in [0, 4294967295], got -1"),
    "read_scene nan": (lambda s: usdrelight.read_scene(s, float("nan")), "a time code must be a finite number"),
    "read_scene None": (lambda s: usdrelight.read_scene(None), "a stage is a path (str or Path), got None"),
    "fit verify_spp -1": (lambda s: usdrelight.fit(s, usdrelight.FitSettings(verify_spp=-1)),
                          "verify_spp (--verify-spp) must be an integer in [0, "),  # named the CLI flag only
    "session render mode ''": (lambda s: usdrelight.RelightSession(s, max_side=32, mode="render").render(
        ["point:0.5,1,-2:3,3,3"], mode=""), "unknown mode ''"),  # '' rendered in the session's mode
    "relight fitted_scale str": (lambda s: usdrelight.relight(s, ["point:0.5,1,-2:3,3,3"], out=s.parent / "r",
                                                              fitted_scale="0.5"),
                                 "fitted_scale (--fitted-scale) must be a finite number >= 0, got '0.5'"),
}


@pytest.mark.parametrize("name", sorted(BAD_CALLS))
def test_bad_api_arguments_are_one_usdrelight_error(api_stage, name):
    call, needle = BAD_CALLS[name]
    before = (api_stage.parent / "lights_fitted.usda").read_bytes()
    with pytest.raises(usdrelight.UsdRelightError, match=re.escape(needle)):
        call(api_stage)
    assert (api_stage.parent / "lights_fitted.usda").read_bytes() == before  # the good fit is still there
    assert not (api_stage.parent / "x").exists() and not (api_stage.parent / "r").exists()


def test_one_light_string_is_one_light_and_a_light_record_is_checked(api_stage):
    """A str was read letter by letter ('bad --light 'p''); a LightRecord of negative radiance rendered black."""
    from dataclasses import replace

    from usdrelight.stage.light_specs import parse_light

    spec = "point:0.5,1,-2:3,3,3"
    with usdrelight.RelightSession(api_stage, max_side=32, mode="render") as s:
        np.testing.assert_array_equal(s.render(spec).image, s.render([spec]).image)
        np.testing.assert_array_equal(s.render(spec, mode="auto").image, s.render([spec]).image)
        with pytest.raises(usdrelight.UsdRelightError, match="radiance must be 3 finite numbers >= 0"):
            s.render([replace(parse_light(spec), radiance=np.full(3, -5.0))])
    files = usdrelight.render(api_stage, api_stage.parent / "aov", aovs="diffuse", spp=1).files
    assert sorted(files) == ["diffuse"]  # one AOV name, not its letters


def test_a_sequence_list_and_a_small_adam_environment(api_stage, tmp_path):
    """relight(sequence=[[...], [...]]) was a pathlib TypeError; the adam fit's environment pruning took the mean
    of empty 8 x 16 cells for a 4 x 8 map (NaN: 'Mean of empty slice', the environment always kept)."""
    import warnings

    spec = "point:0.5,1,-2:3,3,3"
    res = usdrelight.relight(api_stage, sequence=[[spec], ["point:-0.5,1,-2:3,3,3"]], out=tmp_path / "seq",
                             max_side=32, mode="render")
    assert len(res.frames) == 2
    a, b = (np.asarray(read_raw(f.exr)[0]) for f in res.frames)
    assert np.abs(a - b).mean() > 1e-4  # the light moved
    from usdrelight.fit.problem import load_problem
    from usdrelight.fit.result import FitResult
    from usdrelight.fit.run import prune_by_contribution

    prob = load_problem(api_stage, 16)
    dark = FitResult("adam", 0.0, 0.0, 0.0, 1, (), np.zeros((4, 8, 3)), [], prob.width, prob.height)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's empty-slice warnings fail the test
        assert prune_by_contribution(prob, dark).env is None  # a black environment contributes nothing: dropped


def test_values_that_worked_before_the_checks_still_do(api_stage):
    """The checks refuse what the CLI refuses, not what the API took before: max_side 0 (full resolution), a whole
    float, a 0-d array scale, iterations 0 (the default), an empty aovs (every AOV)."""
    with usdrelight.RelightSession(api_stage, max_side=0, mode="render", fitted_scale=np.array(0.5)) as s:
        assert s.engine.resolution == (256, 192)
    with usdrelight.RelightSession(api_stage, max_side=32.0, mode="render") as s:
        assert max(s.engine.resolution) == 32
    rep = usdrelight.fit(api_stage, usdrelight.FitSettings(lights=1, max_side=32.0, iterations=0, verify_spp=0))
    assert rep.lights_kept <= 1


def test_a_library_users_wrong_types_are_one_error_naming_the_parameter(api_stage, tmp_path):
    """None, an int, bytes or an open file where a path goes, a path string where a stage goes, "no" for a flag,
    a string field of BuildOptions: each raised a raw TypeError/ValueError/AttributeError from deep inside
    (pathlib, timing.py), or was taken ("60" as 60 degrees, True as 1 degree, "no" as True)."""
    import io

    from usdrelight.converters import converter_for, mitsuba_xml
    from usdrelight.converters.convert import convert

    ex = EXAMPLES / "procedural"
    cases = [
        (lambda: usdrelight.build(None, tmp_path / "a"), "photo_path must be a path (str or Path), got NoneType"),
        (lambda: usdrelight.build(ex / "photo.exr", 5), "outdir must be a path (str or Path), got int"),
        (lambda: usdrelight.fit(None), "stage_path must be a path"),
        (lambda: usdrelight.relight(5), "stage_path must be a path"),
        (lambda: usdrelight.RelightSession(None), "stage_path must be a path"),
        (lambda: usdrelight.RelightSession(api_stage, with_fitted="no"), "with_fitted (--with-fitted) must be True"),
        (lambda: convert(api_stage, io.BytesIO()), "dst must be a path (str or Path), got BytesIO"),
        (lambda: convert(bytes(str(api_stage), "utf-8"), tmp_path / "b.glb"), "src must be a path"),
        (lambda: converter_for(None), "path must be a path"),
        (lambda: converter_for("a.usda"), "'.usda' is USD"),
        (lambda: mitsuba_xml.write_to_file(str(api_stage), tmp_path / "c.xml"), "stage must be a Usd.Stage"),
        (lambda: mitsuba_xml.read_from_file(io.StringIO("<scene/>")), "path must be a path"),
    ] + [(lambda o=o: usdrelight.build(ex / "photo.exr", tmp_path / "d", usdrelight.BuildOptions(**o)), msg)
         for o, msg in ((dict(fov_x="60"), "fov_x (--fov-x) must be a number in (0, 180)"),
                        (dict(fov_x=True), "fov_x (--fov-x) must be a number in (0, 180)"),
                        (dict(fov_x=200.0), "fov_x (--fov-x) must be a number in (0, 180)"),
                        (dict(depth_scale=0.0), "depth_scale (--depth-scale) must be > 0"),
                        (dict(device="tpu"), "device (--device) must be None or one of"))]
    for call, message in cases:
        with pytest.raises(UsdRelightError, match=re.escape(message)):
            call()
    (tmp_path / "s.py").write_text("print('hi')")
    with pytest.raises(UsdRelightError, match="a .py file is a Blender script usdrelight writes"):
        convert(tmp_path / "s.py", tmp_path / "e.usda")  # was: Blender started, then 'File format is not supported'
    assert not (tmp_path / "a").exists() and not (tmp_path / "d").exists()


def test_a_usdz_round_trip_does_not_grow_the_texture_names(api_stage, tmp_path):
    """stage -> .usdz -> .usda: the textures came back as albedo_76f5b688_76f5b688.exr (one more hash each trip)."""
    from usdrelight.converters.convert import convert

    convert(api_stage, tmp_path / "s.usdz")
    convert(tmp_path / "s.usdz", tmp_path / "back" / "s.usda")
    names = sorted(p.name for p in (tmp_path / "back" / "textures").iterdir())
    assert names and all(re.fullmatch(r"[a-z_]+?_[0-9a-f]{8}\.\w+", n) for n in names), names


def test_relight_reports_progress_to_a_callable_instead_of_a_bar(api_stage, tmp_path):
    seen = []
    usdrelight.relight(api_stage, ["point:0,1,-2:2,2,2"], tmp_path / "r", frames="1:3", max_side=32,
                       progress=lambda done, total: seen.append((done, total)))
    assert seen == [(1, 3), (2, 3), (3, 3)]
    with pytest.raises(UsdRelightError, match="progress must be None, True, False or a callable"):
        usdrelight.relight(api_stage, out=tmp_path / "s", progress="yes")


def test_a_closed_session_renders_nothing(api_stage):
    s = usdrelight.RelightSession(api_stage, max_side=32, mode="render")
    s.render(["point:0,1,-2:2,2,2"])
    s.close()
    s.close()  # twice is fine
    with pytest.raises(UsdRelightError, match="this RelightSession is closed"):
        s.render(["point:0,1,-2:2,2,2"])  # it rendered on, through a renderer that had let its cache go
