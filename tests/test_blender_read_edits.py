"""A .blend usdrelight wrote, edited in Blender as a user would (bpy 5.0.1 in .venv-blender), read back: the
fitted and user lights keep their paths, and what Cycles renders is what comes back (a probe found renamed,
retyped, re-coloured, keyed, deleted and hidden fitted lights lost or doubled, user lights renamed on every
round trip, lights moved by a keyed parent read static, a light disabled in viewports read at the origin and
lights drawn through collection instances dropped). Positions in metres, Y up (Blender's (x, y, z) is (x, z, -y))."""
from __future__ import annotations

import numpy as np
import pytest

from usdrelight.converters.blender import run_blender
from usdrelight.converters.convert import convert
from usdrelight.stage.read import read_lights
from usdrelight.stage.validate import open_stage

FITTED = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
over "Scene" {
    def Scope "Lights" {
        def Scope "Fitted" {
%s
        }
    }
}
'''
POINT = '''            def SphereLight "Point%d" {
                float inputs:intensity = 2
                bool treatAsPoint = 1
                double3 xformOp:translate = (%d, 1, -2)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }'''
USER = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
over "Scene" {
    def Scope "Lights" {
        def Scope "User" {
            def SphereLight "Key" {
                float inputs:intensity = 5
                bool treatAsPoint = 1
                double3 xformOp:translate = (0, 2, 1)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
            def SphereLight "Fill" {
                float inputs:intensity = 1
                bool treatAsPoint = 1
                double3 xformOp:translate = (0, 3, 1)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
            def SphereLight "Gone" {
                float inputs:intensity = 1
                bool treatAsPoint = 1
                double3 xformOp:translate = (2, 3, 1)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
            def Xform "Rig" {
                double3 xformOp:translate = (0, 0, 5)
                uniform token[] xformOpOrder = ["xformOp:translate"]
                def SphereLight "Warm" (
                    prepend apiSchemas = ["ShapingAPI"]
                ) {
                    float inputs:intensity = 2
                    float inputs:exposure = 1
                    bool inputs:enableColorTemperature = 1
                    float inputs:colorTemperature = 3000
                    float inputs:shaping:cone:angle = 60
                    bool treatAsPoint = 1
                    double3 xformOp:translate = (0, 1, 1)
                    uniform token[] xformOpOrder = ["xformOp:translate"]
                }
            }
        }
    }
}
'''
SCENE = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    subLayers = [%s]
)
def Xform "Scene" {
}
'''

EDIT = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
by_path = {o.get("usd_path"): o for o in sc.objects if o.type == "LIGHT"}
p0 = by_path["/Scene/Lights/Fitted/Point0"]
p0.name = "KeyFromPhoto"  # renamed and made a 0.5 m square area light
p0.data.type = "AREA"
p0.data.size = 0.5
bpy.data.objects.remove(by_path["/Scene/Lights/Fitted/Point1"])  # deleted
by_path["/Scene/Lights/Fitted/Point2"].hide_render = True  # hidden from render
p3 = by_path["/Scene/Lights/Fitted/Point3"].data  # warmer: colour temperature on
p3.use_temperature, p3.temperature = True, 3000.0
bpy.data.objects.remove(by_path["/Scene/Lights/User/Gone"])  # a user light deleted
fill = by_path["/Scene/Lights/User/Fill"]  # a copy of a user light (Shift D)
dup = fill.copy(); dup.data = fill.data.copy(); dup.location.x += 1.0
sc.collection.objects.link(dup)


def light(name, loc, parent=None, coll=None):
    ob = bpy.data.objects.new(name, bpy.data.lights.new(name, "POINT"))
    ob.data.energy = 100.0
    ob.location = loc
    ob.parent = parent
    (coll or sc.collection).objects.link(ob)
    return ob


rig = bpy.data.objects.new("Rig", None)  # a light moved by its keyed parent only
sc.collection.objects.link(rig)
for f, x in ((1, 0.0), (5, 4.0)):
    rig.location = (x, 0, 0)
    rig.keyframe_insert("location", frame=f)
for fc in rig.animation_data.action.layers[0].strips[0].channelbags[0].fcurves:
    for kp in fc.keyframe_points:
        kp.interpolation = "LINEAR"
light("Rigged", (0, 0, 1), rig)
sc.frame_start, sc.frame_end = 1, 5
sc.frame_set(1)
holder = bpy.data.objects.new("Holder", None)  # disabled in viewports, then its parent moved
sc.collection.objects.link(holder)
vp = light("ViewportOff", (0, 0, 0), holder)
vp.hide_viewport = True
holder.location = (5, 0, 2)
lamp = bpy.data.collections.new("Lamp")  # a lamp asset, instanced twice, its own collection excluded
sc.collection.children.link(lamp)
light("Bulb", (0, 0, 1), coll=lamp)
bpy.context.view_layer.layer_collection.children["Lamp"].exclude = True
for name, x in (("LampA", 10.0), ("LampB", -10.0)):
    e = bpy.data.objects.new(name, None)
    e.instance_type, e.instance_collection = "COLLECTION", lamp
    e.location = (x, 0, 0)
    sc.collection.objects.link(e)
bg = next(n for n in sc.world.node_tree.nodes if n.type == "BACKGROUND")  # the World made brighter
bg.inputs["Color"].default_value = (0.2, 0.2, 0.2, 1.0)
bpy.ops.wm.save_as_mainfile(filepath=args[1])
'''


@pytest.fixture(scope="module")
def edited(tmp_path_factory):
    d = tmp_path_factory.mktemp("blend_edits")
    (d / "lights_fitted.usda").write_text(FITTED % "\n".join(POINT % (i, i) for i in range(4)))
    (d / "lights_user.usda").write_text(USER)
    (d / "scene.usda").write_text(SCENE % '@./lights_user.usda@, @./lights_fitted.usda@')
    convert(d / "scene.usda", d / "s.blend")
    (d / "edit.py").write_text(EDIT)
    run_blender(d / "edit.py", str(d / "s.blend"), str(d / "edited.blend"))
    report = convert(d / "edited.blend", d / "back.usda")
    return d, report


def _composed(d, layers: str):
    (d / "composed.usda").write_text(SCENE % layers)
    return open_stage(d / "composed.usda")


def _at(lights, path):
    found = [l for l in lights if l.path == path]
    assert len(found) == 1, [l.path for l in lights]
    return found[0]


@pytest.mark.parametrize("layers", ["@./back.usda@, @./lights_fitted.usda@",  # copied over lights_user.usda
                                    "@./back.usda@, @./lights_user.usda@, @./lights_fitted.usda@"])  # sublayered
def test_edited_blend_read_back_keeps_every_light_once_at_its_path(edited, layers):
    d, report = edited
    lights = read_lights(_composed(d, layers), 3.0)
    paths = sorted(l.path for l in lights)
    # Point1 deleted and Point2 hidden: switched off (they lit the stage from lights_fitted.usda before)
    assert "/Scene/Lights/Fitted/Point1" not in paths and "/Scene/Lights/Fitted/Point2" not in paths
    assert "/Scene/Lights/User/Gone" not in paths  # deleted in Blender: off in both ways of using the layer
    # user lights at their own paths (they came back as Scene_Lights_User_Key: doubled when sublayered)
    assert paths.count("/Scene/Lights/User/Key") == 1 and paths.count("/Scene/Lights/User/Fill") == 1
    assert len(paths) == 10, paths  # Point0, Point3, Key, Fill, Fill's copy, Warm, Rigged, ViewportOff, 2 Bulbs
    # exposure 1 and 3000 K, a cone, under a translated Xform: applied once (sublayered, the exposure and the
    # temperature were applied twice and the Rig's translation added again: z 11)
    warm = _at(lights, "/Scene/Lights/User/Rig/Warm")
    orig = _at(read_lights(open_stage(d / "scene.usda")), "/Scene/Lights/User/Rig/Warm")
    np.testing.assert_allclose(warm.radiance, orig.radiance, rtol=1e-3)
    np.testing.assert_allclose(warm.to_world[:3, 3], orig.to_world[:3, 3], atol=1e-5)
    assert warm.cone_angle_deg == pytest.approx(60.0, rel=1e-4)
    p0 = _at(lights, "/Scene/Lights/Fitted/Point0")  # renamed and retyped: a 0.5 m rect (was a point light, 16x)
    assert p0.kind == "rect" and p0.width == pytest.approx(0.5) and p0.height == pytest.approx(0.5)
    np.testing.assert_allclose(p0.to_world[:3, 3], [0, 1, -2], atol=1e-5)
    p3 = _at(lights, "/Scene/Lights/Fitted/Point3")  # 3000 K: warm (was left out as unchanged)
    assert p3.radiance[2] < 0.5 * p3.radiance[0]
    key = _at(lights, "/Scene/Lights/User/Key")
    np.testing.assert_allclose(key.radiance, [5, 5, 5], rtol=1e-4)
    rigged = next(l for l in lights if l.path.endswith("/Rigged"))  # its parent's keys: x 0 -> 4 over 1..5
    np.testing.assert_allclose(rigged.to_world[:3, 3], [2.0, 1.0, 0.0], atol=1e-4)
    vp = next(l for l in lights if l.path.endswith("/ViewportOff"))  # was the origin
    np.testing.assert_allclose(vp.to_world[:3, 3], [5.0, 2.0, 0.0], atol=1e-4)
    bulbs = sorted(l.to_world[0, 3] for l in lights if "Bulb" in l.path)  # were dropped
    np.testing.assert_allclose(bulbs, [-10.0, 10.0], atol=1e-4)
    assert all(l.to_world[1, 3] == pytest.approx(1.0) for l in lights if "Bulb" in l.path)
    assert any(w.startswith("Blender World edited since usdrelight wrote it") for w in report.read_warnings)
    assert report.read_warnings.get("fitted light deleted or hidden from render in Blender (read back as an override "
                                    "that makes it invisible, at its path in lights_fitted.usda)") == 2


def test_the_rigged_light_follows_its_parent_at_every_frame(edited):
    d, _ = edited
    stage = open_stage(d / "back.usda")
    for t in (1.0, 2.0, 4.5, 5.0):
        rigged = next(l for l in read_lights(stage, t) if l.path.endswith("/Rigged"))
        assert rigged.to_world[0, 3] == pytest.approx(t - 1.0, abs=1e-4), t


FOREIGN = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.read_factory_settings(use_empty=True)
sc = bpy.context.scene
w = bpy.data.worlds.new("Sky")
sc.world = w
w.use_nodes = True
bg = next(n for n in w.node_tree.nodes if n.type == "BACKGROUND")
bg.inputs["Color"].default_value = (0.1, 0.2, 0.3, 1.0)
bg.inputs["Strength"].default_value = 2.0
bpy.ops.wm.save_as_mainfile(filepath=args[0])
'''


def test_a_foreign_blends_plain_colour_world_comes_back_as_a_dome(tmp_path):
    """A .blend made in Blender whose World is a colour x strength: it lights the Cycles render but was not read
    (no light, no warning); now a DomeLight of that radiance."""
    (tmp_path / "make.py").write_text(FOREIGN)
    run_blender(tmp_path / "make.py", str(tmp_path / "w.blend"))
    convert(tmp_path / "w.blend", tmp_path / "w.usda")
    (dome,) = read_lights(open_stage(tmp_path / "w.usda"))
    assert dome.kind == "dome" and dome.path == "/Scene/Lights/User/World"
    np.testing.assert_allclose(dome.radiance, [0.2, 0.4, 0.6], rtol=1e-5)


OLD_WRITER = r'''
import bpy, json, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
sc = bpy.context.scene
meta = json.loads(sc["usdrelight_stage"])
meta.pop("lights")
sc["usdrelight_stage"] = json.dumps(meta)
for o in sc.objects:
    if o.type == "LIGHT":
        snap = json.loads(o["usd_written"])
        o["usd_written"] = json.dumps(snap[:27] + [snap[30]])
bpy.ops.wm.save_as_mainfile(filepath=args[1])
'''


def test_a_blend_of_the_writer_before_keeps_its_unchanged_fitted_lights_out(edited):
    """The writer before recorded 28-number snapshots and no light list: its unchanged fitted lights came back
    as overrides (pinning their values over every later fit) once the snapshot grew."""
    d, _ = edited
    (d / "old.py").write_text(OLD_WRITER)
    run_blender(d / "old.py", str(d / "s.blend"), str(d / "old.blend"))
    report = convert(d / "old.blend", d / "old.usda")
    assert sum(v for k, v in report.read_warnings.items() if k.startswith("fitted light of the stage, unchanged")) == 4
    assert "Fitted" not in (d / "old.usda").read_text()


LAMP = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
def Xform "Lamp" {
    def SphereLight "Bulb" {
        float inputs:intensity = 3
        bool treatAsPoint = 1
        double3 xformOp:translate = (0, 0.5, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
}
'''
INSTANCED = '''#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
)
over "Scene" {
    def Scope "Lights" {
        def Scope "User" {
            def Xform "Lamp0" (
                instanceable = true
                prepend references = @./lamp.usda@</Lamp>
            ) {
                double3 xformOp:translate = (-1, 0, -2)
                uniform token[] xformOpOrder = ["xformOp:translate"]
            }
        }
    }
}
'''
MOVE_BULB = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
bulb = next(o for o in bpy.context.scene.objects if o.get("usd_path") == "/Scene/Lights/User/Lamp0/Bulb")
bulb.location.z += 0.5  # Blender's Z: USD's Y, up
bpy.ops.wm.save_as_mainfile(filepath=args[1])
'''


def test_a_light_inside_an_instance_edited_in_blender_comes_back_moved(tmp_path):
    """A lamp asset referenced instanceable into lights_user.usda, its bulb moved 0.5 m up in Blender: read
    back and sublayered over lights_user.usda, the bulb stayed where it was (USD ignores opinions below an
    instance); its parent is now authored instanceable = false in the layer, so the move applies."""
    d = tmp_path
    (d / "lamp.usda").write_text(LAMP)
    (d / "lights_user.usda").write_text(INSTANCED)
    (d / "scene.usda").write_text(SCENE % "@./lights_user.usda@")
    assert [l.to_world[1, 3] for l in read_lights(open_stage(d / "scene.usda"))] == [pytest.approx(0.5)]
    convert(d / "scene.usda", d / "s.blend")
    (d / "move.py").write_text(MOVE_BULB)
    run_blender(d / "move.py", str(d / "s.blend"), str(d / "moved.blend"))
    convert(d / "moved.blend", d / "back.usda")
    for layers in ("@./back.usda@, @./lights_user.usda@", "@./back.usda@"):
        (bulb,) = read_lights(_composed(d, layers))
        assert bulb.path == "/Scene/Lights/User/Lamp0/Bulb"
        np.testing.assert_allclose(bulb.to_world[:3, 3], [-1.0, 1.0, -2.0], atol=1e-5)
