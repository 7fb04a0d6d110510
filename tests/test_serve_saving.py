"""The web app's Save leaves what it did not change: a TD's hand-written lights keep every opinion, another app's
saved edits are not overwritten, a layer at its own time rate keeps its time, a killed save leaves nothing."""
from __future__ import annotations

import numpy as np
import pytest

from test_serve import SIDE, base_stage, stage  # noqa: F401  (fixtures)
from usdrelight.errors import UsdRelightError
from usdrelight.serve.files import read_user_states, user_spec_texts
from usdrelight.serve.timeline import start_range
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.read import read_lights
from usdrelight.stage.validate import open_stage

pytest.importorskip("viser")

HAND = '''#usda 1.0
(
    doc = "hand written by a TD"
    customLayerData = {
        string studio = "keep me"
    }
)

over "Scene"
{
    def Scope "Lights"
    {
        def Scope "User"
        {
            def SphereLight "Hand1" (
                doc = "key light, animated by hand"
                prepend apiSchemas = ["ShadowAPI"]
            )
            {
                float inputs:diffuse = 0.5
                bool inputs:shadow:enable = 0
                float inputs:intensity = 99
                float inputs:intensity.timeSamples = {
                    1: 5,
                    10: 20,
                }
                bool treatAsPoint = 1
                custom string studio:note = "keep"
                double3 xformOp:translate = (0.3, 0.8, -2)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }

            def SphereLight "Rot1" (
                prepend apiSchemas = ["ShapingAPI"]
            )
            {
                float inputs:diffuse = 1
                float inputs:intensity = 30
                float inputs:shaping:cone:angle = 25
                bool treatAsPoint = 1
                double3 xformOp:translate = (0, 1.5, -2.5)
                float3 xformOp:rotateXYZ = (-60, 0, 0)
                uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:rotateXYZ"]
            }
        }
    }
}
'''


def _app(stage):
    from usdrelight.serve.app import ServeApp

    return ServeApp(stage, port=0, max_side=SIDE)


def test_save_rewrites_only_what_changed_and_never_drops_a_users_opinions(stage):
    """Hand1 carries what the app does not write (a diffuse of 0.5, shadows off, a custom attribute, doc
    metadata): not editable, kept byte for byte. Rot1's extras hold their fallbacks (diffuse 1): editable, and
    kept as written (its rotateXYZ, its default intensity) until it is edited; edited, it is the same light."""
    folder = stage.parent
    (folder / USER_LIGHTS).write_text(HAND)
    states, others = read_user_states(open_stage(stage), {})
    assert others == ["/Scene/Lights/User/Hand1"] and [s.name for s in states] == ["Rot1"]
    before = user_spec_texts(folder, ["Hand1", "Rot1"])
    spot = [l for l in read_lights(open_stage(stage), 1) if l.path.endswith("Rot1")][0]
    with _app(stage) as app:
        app.add_light("point")
        app.save()
        assert user_spec_texts(folder, ["Hand1", "Rot1"]) == before  # untouched: as written
        app.set_light("Rot1", intensity=45.0)
        app.save()
    after = user_spec_texts(folder, ["Hand1", "Rot1"])
    assert after["Hand1"] == before["Hand1"] and "xformOp:orient" in after["Rot1"]
    text = (folder / USER_LIGHTS).read_text()
    assert 'string studio = "keep me"' in text and "hand written by a TD" in text
    edited = [l for l in read_lights(open_stage(stage), 1) if l.path.endswith("Rot1")][0]
    np.testing.assert_allclose(edited.to_world, spot.to_world, atol=1e-6)  # the same frame, through orient
    assert edited.radiance[0] == pytest.approx(45.0) and edited.cone_angle_deg == pytest.approx(25.0)


def test_a_second_app_does_not_overwrite_the_first_apps_saved_edit(stage):
    """Two apps on one stage: B saving its new spot keeps A's saved intensity of Point1; B saving its own edit of
    Point1 afterwards is refused, naming it (the file is not written)."""
    with _app(stage) as app:
        name = app.add_light("point")
        app.save()
    with _app(stage) as a, _app(stage) as b:
        a.set_light(name, intensity=77.0)
        a.save()
        b.add_light("spot")
        b.save()
        st = open_stage(stage)
        assert st.GetAttributeAtPath(f"/Scene/Lights/User/{name}.inputs:intensity").Get() == pytest.approx(77.0)
        text = (stage.parent / USER_LIGHTS).read_text()
        b.set_light(name, intensity=5.0)
        with pytest.raises(UsdRelightError, match=f"changed {name} on disk"):
            b.save()
        assert (stage.parent / USER_LIGHTS).read_text() == text


def _layer(folder, body: str, head: str = "") -> None:
    (folder / USER_LIGHTS).write_text(f'#usda 1.0\n(\n{head}\n)\nover "Scene"\n{{\n{body}\n}}\n')


def test_a_lights_layer_at_its_own_rate_keeps_its_time_through_save(stage):
    """A lights layer from another tool at 48 time codes per second, range 1-40 (0.5 to 20 s of a 24-codes
    stage, as USD maps it and relight --frames renders it): the app's range is the same span in the stage's
    codes, and a key set by the app at stage frame 10 lands at the layer's 20; the layer keeps its rate and
    range, so every light renders at the time it did."""
    folder = stage.parent
    _layer(folder, '''    def Scope "Lights" {
        def Scope "User" {
            def SphereLight "Mover" {
                float inputs:intensity = 5
                bool treatAsPoint = 1
                double3 xformOp:translate.timeSamples = { 2: (-1, 0.5, -2), 40: (1, 0.5, -2) }
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
        }
    }''', "    timeCodesPerSecond = 48\n    startTimeCode = 1\n    endTimeCode = 40")
    assert start_range(open_stage(stage), folder) == (0.0, 20.0)  # 0.5 rounded to a whole frame
    moved = {t: [l for l in read_lights(open_stage(stage), t) if l.path.endswith("Mover")][0].to_world[0, 3]
             for t in (1.0, 10.0, 20.0)}
    with _app(stage) as app:
        tl, tg = app.timeline, app.timeline_gui
        name = app.add_light("point")
        tg.frame.value = 10.0
        app.set_light(name, intensity=3.0)
        tg.set_key.value = True
        tg.frame.value = 20.0
        app.set_light(name, intensity=9.0)
        tg.set_key.value = True
        app.save()
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(folder / USER_LIGHTS))
    layer.Reload()
    assert (layer.timeCodesPerSecond, layer.startTimeCode, layer.endTimeCode) == (48.0, 1.0, 40.0)
    assert layer.ListTimeSamplesForPath(f"/Scene/Lights/User/{name}.inputs:intensity") == [20.0, 40.0]
    st = open_stage(stage)
    for t, x in moved.items():
        assert [l for l in read_lights(st, t) if l.path.endswith("Mover")][0].to_world[0, 3] == pytest.approx(x)
    new = {t: [l for l in read_lights(st, t) if l.path.endswith(name)][0].radiance[0] for t in (10.0, 15.0, 20.0)}
    assert new == pytest.approx({10.0: 3.0, 15.0: 6.0, 20.0: 9.0})


def test_a_range_in_a_layer_sublayered_into_the_lights_layer_starts_the_timeline(stage):
    folder = stage.parent
    (folder / "anim.usda").write_text("#usda 1.0\n(\n    startTimeCode = 1\n    endTimeCode = 5\n)\n")
    _layer(folder, "", '    subLayers = [@./anim.usda@]')
    assert start_range(open_stage(stage), folder) == (1.0, 5.0)


def test_save_removes_what_a_killed_save_left(stage):
    folder = stage.parent
    stale = folder / ".lights_user.usdrelight-tmp-abcd1234.usda"
    other = folder / ".scene-backup.usda"  # the user's: never touched
    stale.write_text("")
    other.write_text("#usda 1.0\n")
    with _app(stage) as app:
        app.add_light("point")
        app.save()
    assert not stale.exists() and other.exists()


def test_a_save_with_nothing_changed_writes_nothing(stage):
    """The file (a comment, 3.50) stayed as it was only in its opinions: Save re-exported it anyway."""
    folder = stage.parent
    text = HAND.replace('float inputs:intensity = 30', 'float inputs:intensity = 3.50   # tuned')
    (folder / USER_LIGHTS).write_text(text)
    with _app(stage) as app:
        app.save()
    assert (folder / USER_LIGHTS).read_text() == text


def test_a_lights_layer_without_a_rate_keeps_its_samples_in_time(stage):
    """A layer that authors no rate is read by USD at 24 time codes per second; in a 30-codes stage its samples at
    24 and 48 are the stage's 30 and 60. Save wrote the stage's rate into it, moving the untouched light's keys to
    24 and 48 of the stage."""
    from pxr import Sdf

    folder = stage.parent
    root = Sdf.Layer.FindOrOpen(str(stage))
    root.timeCodesPerSecond = 30
    root.Save()
    _layer(folder, '''    def Scope "Lights" {
        def Scope "User" {
            def SphereLight "Hand" {
                float inputs:intensity.timeSamples = { 24: 1, 48: 5 }
                bool treatAsPoint = 1
                double3 xformOp:translate = (0, 1, -2)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
        }
    }''')

    def hand(t):
        return [l for l in read_lights(open_stage(stage), t) if l.path.endswith("Hand")][0].radiance[0]

    before = [hand(t) for t in (30.0, 45.0, 60.0)]
    assert before == pytest.approx([1.0, 3.0, 5.0])
    with _app(stage) as app:
        name = app.add_light("point")
        app.set_light(name, intensity=2.0)
        app.timeline_gui.set_key.value = True  # a key: Save writes timing
        app.save()
    assert [hand(t) for t in (30.0, 45.0, 60.0)] == pytest.approx(before)
