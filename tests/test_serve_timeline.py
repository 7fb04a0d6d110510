"""The web app's timeline (issue 24): keys -> the interpolation USD reads -> time samples in lights_user.usda ->
keys again; the app at a frame, the range, "Export video" (an MP4 of every frame, in the fixed export folder);
and a real headless Chromium that keys a light at two frames and saves.

Stages: test_serve's (the procedural example at stride 4, one fitted light, 96 px live frames).
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from test_serve import SIDE, app_page, base_stage, position_inputs, stage  # noqa: F401  (fixtures)
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.read import read_lights
from usdrelight.stage.validate import open_stage
from usdrelight.errors import UsdRelightError
from usdrelight.serve.files import read_user_states
from usdrelight.serve.saving import write_user_layer
from usdrelight.serve.live import LiveRelight
from usdrelight.serve.state import LightState, quat_pointing_along
from usdrelight.serve.timeline import DEFAULT_RANGE, Timeline

POINT = "/Scene/Lights/User/P"


def _keys():
    """A point light moving x 0 -> 1 between frames 1 and 11 (intensity 2 -> 4), and a spot turning."""
    p1 = LightState("P", "point", intensity=2.0, color=(1.0, 0.5, 0.25), position=(0.0, 0.8, -2.0))
    p11 = p1.with_(intensity=4.0, position=(1.0, 0.8, -2.0))
    s1 = LightState("S", "spot", intensity=9.0, position=(-0.5, 1.0, -1.5), rotation=quat_pointing_along([0, -1, -1]),
                    cone_angle=30.0, softness=0.25)
    s11 = s1.with_(rotation=quat_pointing_along([1, -1, -0.2]), cone_angle=40.0, enabled=False)
    return {"P": {1.0: p1, 11.0: p11}, "S": {1.0: s1, 11.0: s11}}


def _attr(stage_, path, name):
    return stage_.GetPrimAtPath(path).GetAttribute(name)


def test_keys_interpolate_as_usd_reads_the_saved_layer_and_read_back_exactly(stage):
    from pxr import Gf, Sdf

    folder = stage.parent
    keys = _keys()
    still = LightState("Still", "sun", intensity=2.0, rotation=quat_pointing_along([0.2, -1, -0.4]), angle=0.53)
    tl = Timeline(open_stage(stage), folder, {}, keys)
    assert (tl.start, tl.end, tl.fps) == (*DEFAULT_RANGE, 24.0)  # the stage authors no range
    mid = tl.state_at("P", 6.0)
    assert mid.position == (0.5, 0.8, -2.0) and mid.intensity == 3.0 and mid.color == (1.0, 0.5, 0.25)
    assert tl.state_at("P", 0.0) == keys["P"][1.0] and tl.state_at("P", 20.0) == keys["P"][11.0]  # held outside
    assert tl.state_at("P", 11.0) == keys["P"][11.0] and tl.state_at("Still", 6.0) is None
    spot = tl.state_at("S", 6.0)
    want = Gf.Slerp(0.5, Gf.Quatd(*keys["S"][1.0].rotation), Gf.Quatd(*keys["S"][11.0].rotation))
    np.testing.assert_allclose(spot.rotation, (want.GetReal(), *want.GetImaginary()), atol=1e-12)
    assert spot.cone_angle == 35.0 and spot.enabled  # visibility is held until the key that switches it off

    tl.set_range(1, 11)
    write_user_layer(folder, [keys["P"][11.0], keys["S"][1.0], still], keys=tl.snapshot(), timing=tl.timing())
    layer = Sdf.Layer.FindOrOpen(str(folder / USER_LIGHTS))
    assert (layer.startTimeCode, layer.endTimeCode, layer.timeCodesPerSecond, layer.framesPerSecond) == (1, 11, 24, 24)
    saved = open_stage(stage)
    translate = _attr(saved, POINT, "xformOp:translate")
    assert translate.GetTimeSamples() == [1.0, 11.0]
    assert _attr(saved, POINT, "inputs:intensity").GetTimeSamples() == [1.0, 11.0]
    for same in ("inputs:color", "inputs:exposure", "xformOp:orient"):  # equal in both keys: a default only
        assert not _attr(saved, POINT, same).GetTimeSamples(), same
    assert _attr(saved, "/Scene/Lights/User/S", "visibility").GetTimeSamples() == [1.0, 11.0]
    for attr in saved.GetPrimAtPath("/Scene/Lights/User/Still").GetAttributes():
        assert not attr.GetTimeSamples(), attr.GetName()  # an unkeyed light: default values only
    # what the renderers read at frame 6 of the saved stage: x = 0.5, radiance 3 x colour
    rec = {l.path: l for l in read_lights(saved, 6.0)}[POINT]
    np.testing.assert_array_equal(rec.to_world[:3, 3], [0.5, 0.8, -2.0])
    np.testing.assert_allclose(rec.radiance, [3.0, 1.5, 0.75], rtol=1e-7)
    assert "/Scene/Lights/User/S" not in {l.path for l in read_lights(saved, 11.0)}  # switched off there
    # state -> USD -> state: the keys come back exactly; a keyed light's state is its first key
    back = {}
    states, others = read_user_states(saved, {}, back)
    assert back == keys and not others
    assert {s.name: s for s in states} == {"P": keys["P"][1.0], "S": keys["S"][1.0], "Still": still}
    # a second timeline (a new session) on the saved stage: the same range and the same values between keys
    again = Timeline(saved, folder, {}, back)
    assert (again.start, again.end) == (1.0, 11.0)
    for t in (3.0, 6.0, 8.5):
        assert again.state_at("S", t) == tl.state_at("S", t) and again.state_at("P", t) == tl.state_at("P", t)


def test_one_key_delete_key_and_a_stage_at_30_fps(stage):
    """A single key survives a save (its time on the translate); deleting a key re-interpolates the others;
    a stage at 30 time codes/s keeps the saved samples where they were keyed (no sublayer rescaling)."""
    from pxr import Sdf

    folder = stage.parent
    root = Sdf.Layer.FindOrOpen(str(stage))
    root.framesPerSecond = root.timeCodesPerSecond = 30
    root.Save()
    tl = Timeline(open_stage(stage), folder, {})
    assert tl.fps == 30.0 and tl.timing() is None  # nothing keyed, the range as read: no metadata to write
    a = LightState("P", "point", intensity=1.0, position=(0.0, 0.5, -1.0))
    tl.set_key(a, 5.0)
    for t in (1.0, 5.0, 40.0):
        assert tl.state_at("P", t) == a
    tl.set_key(a.with_(intensity=3.0), 9.0)
    tl.set_key(a.with_(intensity=5.0), 13.0)
    assert tl.state_at("P", 7.0).intensity == 2.0 and tl.delete_key("P", 9.0) and not tl.delete_key("P", 9.0)
    assert tl.state_at("P", 7.0).intensity == 2.0 and tl.state_at("P", 9.0).intensity == 3.0  # 1 -> 5 over 5..13
    assert tl.delete_key("P", 13.0) and tl.key_times("P") == [5.0]
    write_user_layer(folder, [a], keys=tl.snapshot(), timing=tl.timing())
    saved = open_stage(stage)
    assert _attr(saved, POINT, "xformOp:translate").GetTimeSamples() == [5.0]
    back = {}
    read_user_states(saved, {}, back)
    assert back == {"P": {5.0: a}}
    tl.set_key(a.with_(position=(2.0, 0.5, -1.0)), 15.0)
    write_user_layer(folder, [a], keys=tl.snapshot(), timing=tl.timing())
    saved = open_stage(stage)
    assert saved.GetTimeCodesPerSecond() == 30.0
    assert _attr(saved, POINT, "xformOp:translate").GetTimeSamples() == [5.0, 15.0]
    rec = {l.path: l for l in read_lights(saved, 10.0)}[POINT]
    np.testing.assert_allclose(rec.to_world[:3, 3], [1.0, 0.5, -1.0], atol=1e-12)
    assert tl.delete_key("P", 5.0) and tl.delete_key("P", 15.0) and tl.state_at("P", 5.0) is None


def test_animated_lights_the_app_does_not_edit_follow_the_frame(stage):
    """A normalized DiskLight in the user's layer (not editable here) moving over time codes 1..11 is rendered
    where it is at the frame's time code."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    layer = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    s = Usd.Stage.Open(layer)
    s.OverridePrim("/Scene")
    disk = UsdLux.DiskLight.Define(s, "/Scene/Lights/User/Panel")
    disk.CreateRadiusAttr(0.2)
    disk.CreateNormalizeAttr(True)
    op = UsdGeom.Xformable(disk).AddTranslateOp()
    op.Set(Gf.Vec3d(0, 1, -2), Usd.TimeCode(1))
    op.Set(Gf.Vec3d(1, 1, -2), Usd.TimeCode(11))
    layer.Save()
    states, others = read_user_states(open_stage(stage), {})
    assert others == ["/Scene/Lights/User/Panel"] and not states
    live = LiveRelight(stage, max_side=SIDE, mode="add")
    live.keep_other(others)
    try:
        for t, x in ((1.0, 0.0), (6.0, 0.5), (11.0, 1.0)):
            (panel,) = live.others_at(t)
            assert panel.path == "/Scene/Lights/User/Panel" and panel.to_world[0, 3] == x
    finally:
        live.close()


def test_app_keys_plays_saves_and_exports_a_video(stage):
    pytest.importorskip("viser")
    av = pytest.importorskip("av", reason="PyAV (the video extra) is installed by scripts/setup.sh")
    from usdrelight.serve.app import ServeApp

    folder = stage.parent
    before = {p for p in folder.rglob("*") if p.is_file()}
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        tl, tg = app.timeline, app.timeline_gui
        name = app.add_light("point")
        app.set_light(name, position=(0.0, 0.8, -2.0), intensity=2.0)
        tg.set_key.value = True  # a click (viser calls the callbacks at once)
        tg.frame.value = 11.0
        assert tl.frame == 11.0
        app.set_light(name, position=(1.0, 0.8, -2.0), intensity=4.0)
        tg.set_key.value = True
        assert tl.key_times(name) == [1.0, 11.0] and tg.keys.content == f"Keys of {name}: 1, 11"
        tg.frame.value = 6.0
        assert app.states[name].position == (0.5, 0.8, -2.0) and app.states[name].intensity == 3.0
        shown = app.wait_shown(app.update())
        assert not shown.error
        tg.frame.value = float("nan")  # refused: the slider shows the app's frame again
        assert tl.frame == 6.0 and tg.frame.value == 6.0 and "not applied" in app.gui.status.content
        tg.start.value, tg.end.value = 2.0, 9.0
        assert (tl.start, tl.end, tg.frame.min, tg.frame.max) == (2.0, 9.0, 2.0, 9.0)
        tg.end.value = 0.0  # before the start: refused
        assert tl.end == 9.0 and tg.end.value == 9.0
        tg.play.value = True
        time.sleep(0.5)
        tg.play.value = True  # Stop
        assert tg.play.label == "Play" and 2.0 <= tl.frame <= 9.0
        stopped = tl.frame
        time.sleep(0.2)
        assert tl.frame == stopped
        tg.frame.value = 2.0
        tg.delete_key.value = True  # no key at 2: refused, nothing changes
        assert tl.key_times(name) == [1.0, 11.0]
        app.save()
        t0 = time.perf_counter()
        tg.export.value = True
        seconds = time.perf_counter() - t0
        assert app.gui.status.content.startswith("Exported export/relit.mp4 (8 frames"), app.gui.status.content
        assert tg.progress.value == 100.0 and not tg.progress.visible
        print(f"video: 8 frames in {seconds:.2f} s")
    video = folder.resolve() / "serve" / "export" / "relit.mp4"
    with av.open(str(video)) as c:
        s = c.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        assert s.frames == 8 and len(frames) == 8 and float(s.average_rate) == 24.0
    assert float(np.abs(frames[0].astype(float) - frames[-1].astype(float)).mean()) > 0.05  # the light moved
    after = {p for p in folder.rglob("*") if p.is_file()}
    new = {str(p.relative_to(folder)) for p in after - before if "cache" not in p.parts}
    assert new == {"serve/export/relit.mp4"}, new  # lights_user.usda changed in place; nothing else written
    with ServeApp(stage, port=0, max_side=SIDE) as again:  # a second session: the keys and the range
        assert again.timeline.key_times(name) == [1.0, 11.0] and (again.timeline.start, again.timeline.end) == (2, 9)
        assert again.states[name].position == (0.1, 0.8, -2.0)  # frame 2 of the move


def test_browser_keys_a_light_at_two_frames_and_saves(stage):
    """Headless Chromium adds a point light, keys it at frame 1, moves the frame slider to the end (48), moves
    the light, keys it again, saves: lights_user.usda holds the two time samples."""
    with app_page(stage) as (app, page):
        page.get_by_role("button", name="Add light").click()
        page.get_by_text("point Point1").wait_for(timeout=15000)
        page.get_by_role("button", name="Set key").click()
        page.get_by_text("Keys of Point1: 1").wait_for(timeout=15000)
        frame = page.locator("[role=slider][aria-valuemin='1'][aria-valuemax='48']")
        assert frame.count() == 1
        frame.focus()
        frame.press("End")
        deadline = time.monotonic() + 20
        while app.timeline.frame != 48.0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert app.timeline.frame == 48.0
        xyz = position_inputs(page)
        xyz.nth(0).fill("1.5")
        xyz.nth(0).press("Enter")
        while app.states["Point1"].position[0] != 1.5 and time.monotonic() < deadline:
            time.sleep(0.1)
        page.get_by_role("button", name="Set key").click()
        page.get_by_text("Keys of Point1: 1, 48").wait_for(timeout=15000)
        page.get_by_role("button", name="Save lights").click()
        page.get_by_text("Saved 1 light(s) to lights_user.usda").wait_for(timeout=20000)
        start = app.states["Point1"]
    saved = open_stage(stage)
    translate = _attr(saved, "/Scene/Lights/User/Point1", "xformOp:translate")
    assert translate.GetTimeSamples() == [1.0, 48.0]
    assert translate.Get(48.0)[0] == 1.5 and tuple(translate.Get(48.0))[1:] == start.position[1:]
    assert translate.Get(1.0)[0] != 1.5


def test_app_adds_keys_and_saves_an_area_light(stage):
    """A rect light from the app: its editor has its size, direction and position; it lights the frame; its
    width keyed at two frames is saved as time samples and read back as the same rect (with the sizes from
    USD's interpolation in between); out-of-range sizes from a client are clamped by the slider."""
    pytest.importorskip("viser")
    from usdrelight.serve.app import ServeApp

    from usdrelight.serve.live import LightSet

    with ServeApp(stage, port=0, max_side=SIDE) as app:
        name = app.add_light("rect")
        s = app.states[name]
        assert s.kind == "rect" and s.width == pytest.approx(1.5 * s.height)
        fields = app.gui._fields
        assert {"width", "height", "direction", "position"} <= set(fields) and "radius" not in fields
        assert not app.wait_shown(app.update()).error
        from usdrelight.serve.state import turned_towards

        before = app.states[name].rotation
        fields["direction"].value = (0.0, -1.0, 0.6)  # a client edits the direction: the rect keeps its roll
        assert app.states[name].rotation == pytest.approx(turned_towards(before, (0.0, -1.0, 0.6)), abs=1e-6)
        s = app.states[name]
        dark = app.live.render(LightSet((), fitted_on=True, mode="add"))[0]
        lit = app.live.render(LightSet((s,), fitted_on=True, mode="add"))[0]
        assert np.all(np.isfinite(lit)) and lit.mean() > 1.01 * dark.mean()  # the new rect adds light
        tl, tg = app.timeline, app.timeline_gui
        app.set_light(name, width=0.25)
        tg.set_key.value = True
        tg.frame.value = 11.0
        app.set_light(name, width=0.75)
        tg.set_key.value = True
        tg.frame.value = 6.0
        assert app.states[name].width == pytest.approx(0.5)  # linear, as USD reads the samples
        fields = app.gui._fields
        fields["height"].value = 1e9  # beyond the slider: clamped to its top
        assert app.states[name].height == pytest.approx(app.gui._ranges["height"][1][1])
        with pytest.raises(UsdRelightError, match=f"{name} changed at frame 6 without a key"):
            app.save()  # Save writes a keyed light from its keys: the new height would be lost, and nothing is
        assert "RectLight" not in (stage.parent / USER_LIGHTS).read_text()  # written
        tg.frame.value = 1.0  # another frame drops the change
        app.save()
    layer = (stage.parent / USER_LIGHTS).read_text()
    assert "RectLight" in layer and "float inputs:width.timeSamples" in layer
    back, _ = read_user_states(open_stage(stage), {}, keys := {})
    (rect,) = [b for b in back if b.name == name]
    assert rect.kind == "rect" and sorted(keys[name]) == [1.0, 11.0]
    assert keys[name][1.0].width == pytest.approx(0.25) and keys[name][11.0].width == pytest.approx(0.75)
    rec = [l for l in read_lights(open_stage(stage), 6.0) if l.path.endswith(name)][0]
    assert rec.kind == "rect" and rec.width == pytest.approx(0.5) and not rec.normalize
