"""Time as USD composes it, carried into Blender and the messages: from a probe of Houdini / Omniverse style
animation (value-clip steps, negative time codes, framesPerSecond != timeCodesPerSecond, referenced caches of
another rate, lights invisible at the time asked for). Each test asserts a number that came out wrong before."""
from __future__ import annotations

import json

import pytest

from usdrelight.converters.blender_run import run_blender
from usdrelight.stage.read import read_scene

from conftest import build_procedural

PROBE = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
out = {"fps": sc.render.fps / sc.render.fps_base, "range": [sc.frame_start, sc.frame_end]}
light = next(o for o in sc.objects if o.type == "LIGHT")
for f in (15.0, 19.9, 20.0):
    sc.frame_set(int(f), subframe=f - int(f))
    out[str(f)] = list(light.matrix_world.translation)
json.dump(out, open(args[1], "w"))
'''

STEP = '''#usda 1.0
(
    timeCodesPerSecond = 24
    framesPerSecond = 30
    metersPerUnit = 1
    upAxis = "Y"
)
def SphereLight "Key" {
    float inputs:intensity = 5
    double3 xformOp:translate.timeSamples = { -4: (0, 0, 0), 10: (0, 0, 0), 19.999999995: (2, 0, 0), 20: (10, 0, 0) }
    uniform token[] xformOpOrder = ["xformOp:translate"]
}
def Camera "Cam" {
}
'''


def test_a_step_written_as_two_close_samples_stays_a_step_in_blender(tmp_path, cli):
    """A value clip's end (19.999999995, then 20): Blender merged the two keys into a ramp from 10 (x = 9.82 at
    19.9 where USD gives 1.98); the .blend played at framesPerSecond (30) where a frame is a time code of a
    24-codes stage (1.25x fast); negative time codes were cut from the range without a word."""
    (tmp_path / "s.usda").write_text(STEP)
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "s.blend")
    assert rc == 0 and "time codes below 0" in err, err
    (tmp_path / "probe.py").write_text(PROBE)
    run_blender(tmp_path / "probe.py", str(tmp_path / "s.blend"), str(tmp_path / "p.json"))
    got = json.loads((tmp_path / "p.json").read_text())
    # USD Y-up (x, y, z) -> Blender Z-up (x, -z, y)
    assert got["15.0"][0] == pytest.approx(1.0, abs=1e-3)  # linear from (0, 0, 0) at 10 to (2, 0, 0) at 20-
    assert got["19.9"][0] == pytest.approx(1.98, abs=5e-3)
    assert got["20.0"][0] == pytest.approx(10.0, abs=1e-6)
    assert got["fps"] == pytest.approx(24.0)


def test_a_referenced_cache_of_another_rate_is_warned(tmp_path):
    (tmp_path / "asset.usda").write_text('''#usda 1.0
(
    timeCodesPerSecond = 30
)
def SphereLight "L" {
    float inputs:intensity.timeSamples = { 0: 10, 30: 20 }
}
''')
    (tmp_path / "s.usda").write_text('#usda 1.0\n(\n    timeCodesPerSecond = 24\n)\n'
                                     'def "Rig" (prepend references = @./asset.usda@</L>)\n{\n}\n')
    scene = read_scene(tmp_path / "s.usda", 12)
    assert scene.lights[0].radiance[0] == pytest.approx(15.0)  # USD: the 30-codes sample at 30 read at 24
    assert any("asset.usda has 30 time codes per second" in w for w in scene.warnings)


def test_a_light_invisible_at_the_time_asked_for_is_named(tmp_path, cli):
    stage = build_procedural(tmp_path / "s", stride=4)
    (stage.parent / "lights_user.usda").write_text('''#usda 1.0
def Xform "Scene" {
    def Scope "Lights" {
        def Scope "User" {
            token visibility.timeSamples = { 1: "inherited", 2: "invisible" }
            def SphereLight "Key" {
                float inputs:intensity = 5
            }
        }
    }
}
''')
    rc, _, err = cli("relight", stage, "--time", 2, "--max-side", 16, "-o", tmp_path / "o")
    assert rc == 2 and "at time code 2: /Scene/Lights/User/Key is invisible then" in err and err.count("\n") == 1
    assert cli("relight", stage, "--time", 1, "--max-side", 16, "-o", tmp_path / "o1")[0] == 0
