""".blend lights -> UsdLux (``usdrelight convert scene.blend lights.usda``) with Blender 5's per-light Normalize
and Exposure (bpy 5.0.1 in .venv-blender).

Expected values are written out here by hand from what Cycles renders (measured over a diffuse floor, 0.1% on
the centre's closed forms; README "Blender"): 2^exposure times, with Normalize on, I = P / 4 pi (point/spot),
L = P / (4 pi^2 r^2) (radius r), L = P / (pi A) (area), E = S (sun); with Normalize off I = P / pi, L = P / pi,
L = P / pi and, for a sun of angle a > 0, E = S pi sin^2(a / 2). One Blender process builds the .blend files and
renders (32 x 24 px: each case alone against the closed forms, six lights together against Mitsuba), one imports
a stage natively; one Mitsuba render closes the loop (~8 s in all).
"""
import json
import math

import numpy as np
import pytest
from pxr import Sdf, UsdLux

from blender_native import all_lights_stage, native_import
from usd_scenes import looking_down_at_floor
from usdrelight.converters.blender import run_blender
from usdrelight.imageio import read_map
from usdrelight.stage.lux import emitted_radiance, light_direction
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

BUILD = r'''
import bpy, json, math, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
for job in json.load(open(args[0])):
    bpy.ops.wm.open_mainfile(filepath=job["base"])
    scene = bpy.context.scene
    if job.get("unit_scale"):  # a .blend modelled in other units, not made by usdrelight
        scene.unit_settings.scale_length = job["unit_scale"]
        del scene["usdrelight_stage"]
    for s in job["lights"]:
        l = bpy.data.lights.new(s["name"], s["type"])
        l.energy, l.normalize, l.exposure = s["energy"], s["normalize"], s["exposure"]
        l.color = s.get("color", (1, 1, 1))
        if "temperature" in s:
            l.use_temperature, l.temperature = True, s["temperature"]
        if s["type"] in ("POINT", "SPOT"):
            l.shadow_soft_size, l.use_soft_falloff = s.get("radius", 0.0), False
        if s["type"] == "SPOT":
            l.spot_size, l.spot_blend = math.radians(s["spot_deg"]), 0.0
        if s["type"] == "AREA":
            l.shape, l.size, l.size_y = s["shape"], s["size"], s.get("size_y", s["size"])
        if s["type"] == "SUN":
            l.angle = math.radians(s["angle_deg"])
        for key in ("spread", "use_square", "diffuse_factor", "specular_factor", "volume_factor"):
            if key in s:
                setattr(l, key, s[key])
        ob = bpy.data.objects.new(s["name"], l)
        ob.location = s.get("at", (0, 0, 1))
        ob.rotation_euler = [math.radians(a) for a in s.get("rot_deg", (0, 0, 0))]  # default: facing down (-Z)
        ob.visible_camera, ob.hide_render = False, s.get("hide_render", False)
        scene.collection.objects.link(ob)
    bpy.ops.wm.save_as_mainfile(filepath=job["save"])
    lights = [ob for ob in scene.objects if ob.type == "LIGHT"]
    for ob in lights if job.get("each") else ():  # each light alone, 1 m above the floor's centre, facing down
        for other in lights:
            other.hide_render = other is not ob
        ob.location, ob.rotation_euler = (0, 0, 1), (0, 0, 0)
        scene.cycles.samples = 32
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.filepath = job["each"] + ob.name + ".exr"
        bpy.ops.render.render(write_still=True)
    if job.get("exr"):
        scene.cycles.samples = job["spp"]
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.filepath = job["exr"]
        bpy.ops.render.render(write_still=True)
'''

P, S, pi = 10.0, 2.0, math.pi
# name: (Blender light, UsdLux kind, expected emitted radiance: I [W/sr], L [W/(m^2 sr)] or E [W/m^2])
N, U = {"normalize": True}, {"normalize": False}
CASES = {
    "PointN": ({"type": "POINT", **N, "exposure": 0.0}, "sphere", P / (4 * pi)),
    "PointU1": ({"type": "POINT", **U, "exposure": 1.0}, "sphere", 2 * P / pi),
    "SphereN1": ({"type": "POINT", **N, "exposure": 1.0, "radius": 0.1}, "sphere", 2 * P / (4 * pi ** 2 * 0.01)),
    "SphereU": ({"type": "POINT", **U, "exposure": 0.0, "radius": 0.1}, "sphere", P / pi),
    "SpotN": ({"type": "SPOT", **N, "exposure": 0.0, "spot_deg": 50.0}, "sphere", P / (4 * pi)),
    "SpotU1": ({"type": "SPOT", **U, "exposure": 1.0, "spot_deg": 50.0}, "sphere", 2 * P / pi),
    "RectN1": ({"type": "AREA", **N, "exposure": 1.0, "shape": "RECTANGLE", "size": 0.5, "size_y": 0.25}, "rect",
               2 * P / (pi * 0.125)),
    "RectU": ({"type": "AREA", **U, "exposure": 0.0, "shape": "RECTANGLE", "size": 0.5, "size_y": 0.25}, "rect",
              P / pi),
    "SquareU1": ({"type": "AREA", **U, "exposure": 1.0, "shape": "SQUARE", "size": 0.4}, "rect", 2 * P / pi),
    "DiskN": ({"type": "AREA", **N, "exposure": 0.0, "shape": "DISK", "size": 0.4}, "disk", P / (pi * pi * 0.04)),
    "DiskU1": ({"type": "AREA", **U, "exposure": 1.0, "shape": "DISK", "size": 0.4}, "disk", 2 * P / pi),
    "EllipseN": ({"type": "AREA", **N, "exposure": 0.0, "shape": "ELLIPSE", "size": 0.5, "size_y": 0.2}, "disk",
                 P / (pi * pi * 0.25 * 0.1)),  # area pi (0.5/2)(0.2/2)
    "SunN0": ({"type": "SUN", **N, "exposure": 0.0, "angle_deg": 0.0}, "distant", S),
    "SunU0": ({"type": "SUN", **U, "exposure": 1.0, "angle_deg": 0.0}, "distant", 2 * S),
    "SunN1": ({"type": "SUN", **N, "exposure": 1.0, "angle_deg": 10.0}, "distant", 2 * S),
    "SunU": ({"type": "SUN", **U, "exposure": 0.0, "angle_deg": 10.0}, "distant",
             S * pi * math.sin(math.radians(5.0)) ** 2),
}
# lights of the rendered .blend: out of the camera's view (it looks down from 1 m), all kinds, Normalize off/on;
# placed so that no Mitsuba emitter shape (sphere, disk, rectangle: geometry there) shadows the sun in view
RENDERED = [
    {"name": "Pt", "type": "POINT", **U, "exposure": 1.0, "energy": 2.0, "at": (0.3, 0.2, 1.0),
     "temperature": 3000.0},
    {"name": "Sph", "type": "POINT", **U, "exposure": 0.0, "energy": 20.0, "radius": 0.1, "at": (-0.6, 0.0, 0.9)},
    {"name": "Spot", "type": "SPOT", **U, "exposure": -1.0, "energy": 6.0, "spot_deg": 60.0, "at": (0.0, -0.5, 1.0),
     "rot_deg": (-20.0, 0.0, 0.0), "color": (1.0, 0.6, 0.3)},
    {"name": "Rect", "type": "AREA", **U, "exposure": 1.0, "energy": 1.0, "shape": "RECTANGLE", "size": 0.4,
     "size_y": 0.2, "at": (0.0, 0.6, 1.0), "rot_deg": (30.0, 0.0, 0.0)},
    {"name": "Disk", "type": "AREA", **N, "exposure": 1.0, "energy": 5.0, "shape": "DISK", "size": 0.3,
     "at": (-0.7, -0.3, 1.0)},
    {"name": "Sun", "type": "SUN", **U, "exposure": 2.0, "energy": 3.0, "angle_deg": 20.0,
     "rot_deg": (0.0, 25.0, 0.0), "color": (0.3, 0.5, 1.0)},
]

# what UsdLux has a place for (diffuse / specular multipliers) and what it has not (warned)
EXTRA = [{"name": "Narrow", "type": "AREA", **N, "exposure": 0.0, "energy": 1.0, "shape": "SQUARE", "size": 0.2,
          "spread": 1.0, "diffuse_factor": 0.5, "specular_factor": 2.0},
         {"name": "Square", "type": "SPOT", **N, "exposure": 0.0, "energy": 1.0, "spot_deg": 40.0, "use_square": True,
          "volume_factor": 0.0},
         {"name": "Hidden", "type": "POINT", **N, "exposure": 0.0, "energy": 1.0, "hide_render": True}]


#: cases also read from a .blend made otherwise with unit scale 0.01 (1 Blender unit = 1 cm)
IN_CENTIMETRES = ("PointN", "SpotU1", "SphereN1", "RectN1", "DiskN", "SunN0")


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from usdrelight.cli import main

    d = tmp_path_factory.mktemp("blendread")
    floor = looking_down_at_floor(d / "floor.usda")
    floor.GetRootLayer().Save()
    assert main(["convert", str(d / "floor.usda"), str(d / "floor.blend")]) == 0
    cases = [{**spec, "name": name, "energy": S if spec["type"] == "SUN" else P,
              "at": (0.0, 3.0 * i, 2.0), "color": (1.0, 0.5, 0.25) if name == "PointU1" else (1, 1, 1)}
             for i, (name, (spec, _, _)) in enumerate(CASES.items())]
    jobs = [{"base": str(d / "floor.blend"), "save": str(d / "cases.blend"), "lights": cases, "each": str(d / "c_")},
            {"base": str(d / "floor.blend"), "save": str(d / "lit.blend"), "lights": RENDERED,
             "exr": str(d / "cycles.exr"), "spp": 128},
            {"base": str(d / "floor.blend"), "save": str(d / "extra.blend"), "lights": EXTRA},
            {"base": str(d / "floor.blend"), "save": str(d / "centimetres.blend"), "unit_scale": 0.01,
             "lights": [c for c in cases if c["name"] in IN_CENTIMETRES], "each": str(d / "cm_")}]
    (d / "jobs.json").write_text(json.dumps(jobs))
    (d / "build.py").write_text(BUILD)
    run_blender(d / "build.py", str(d / "jobs.json"))
    return d


def _lights(path):
    return {l.path.rsplit("/", 1)[-1]: l for l in read_scene(open_stage(path)).lights}


def test_every_kind_normalize_and_exposure(cli, built):
    rc, _, err = cli("convert", built / "cases.blend", built / "cases.usda")
    assert rc == 0, err
    got = _lights(built / "cases.usda")
    assert sorted(got) == sorted(CASES)
    for name, (spec, kind, expected) in CASES.items():
        rec = got[name]
        assert rec.kind == kind, name
        colour = np.array([1.0, 0.5, 0.25]) if name == "PointU1" else np.ones(3)
        np.testing.assert_allclose(emitted_radiance(rec), expected * colour, rtol=1e-5, err_msg=name)
        assert rec.treat_as_point == (kind == "sphere" and spec.get("radius", 0.0) == 0.0), name
    assert got["SphereU"].radius == pytest.approx(0.1, rel=1e-6)
    assert got["SpotU1"].cone_angle_deg == pytest.approx(25.0, rel=1e-5)
    assert (got["RectU"].width, got["RectU"].height) == pytest.approx((0.5, 0.25), rel=1e-6)
    assert got["EllipseN"].radius == pytest.approx(math.sqrt(0.5 * 0.2) / 2, rel=1e-6)  # the disk of equal area
    assert got["SunU"].angle_deg == pytest.approx(10.0, rel=1e-5)


def _centre_irradiance(rec, h=1.0, scale=1.0):
    """Irradiance at the floor point h (m) below the light record (facing it), from its UsdLux values alone;
    ``scale``: the record's sizes to metres."""
    L = float(emitted_radiance(rec)[0])
    r = rec.radius * scale
    if rec.kind == "sphere":
        return L / h ** 2 if rec.treat_as_point else pi * L * r ** 2 / h ** 2
    if rec.kind == "disk":
        return pi * L * r ** 2 / (h ** 2 + r ** 2)
    if rec.kind == "rect":  # four corner rectangles' form factors
        x, y = rec.width * scale / 2 / h, rec.height * scale / 2 / h
        f = (x / math.hypot(1, x) * math.atan(y / math.hypot(1, x)) + y / math.hypot(1, y) * math.atan(x / math.hypot(1, y)))
        return 2 * L * f
    return L  # distant: irradiance


def test_each_light_renders_in_cycles_as_the_usdlux_light_read_back(cli, built):
    """Every case alone 1 m above the floor in Cycles (32 spp): the centre is albedo / pi x the irradiance of the
    UsdLux light read back (closed forms; the ellipse read as the disk of its area: 1.1% brighter at 1 m)."""
    assert cli("convert", built / "cases.blend", built / "each.usda")[0] == 0
    got = _lights(built / "each.usda")
    for name in CASES:
        img = read_map(built / f"c_{name}.exr", 3)[..., 1]
        h, w = img.shape
        centre = float(img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean())
        colour = 0.5 if name == "PointU1" else 1.0  # its green
        expected = 0.5 / pi * _centre_irradiance(got[name]) * colour
        print(f"{name}: Cycles / closed form {centre / expected:.4f}")
        assert centre == pytest.approx(expected, rel=0.02 if name == "EllipseN" else 0.005), name


def test_a_blend_in_centimetres_comes_back_in_its_unit_lighting_as_cycles_shows_it(cli, built):
    """A .blend made otherwise with unit scale 0.01: the layer is in centimetres (metersPerUnit 0.01, every length
    the Blender number); Cycles renders a Blender unit as a metre, so each light 1 unit above the floor, read back
    and put 1 cm above a floor in metres, gives Cycles' centre: a point or spot light x 0.01^2, radiance as it is.
    (Before: the layer was in metres, 100x too large, and nothing said so.)"""
    from pxr import Gf, Usd, UsdGeom

    rc, _, err = cli("convert", built / "centimetres.blend", built / "cm.usda")
    assert rc == 0 and "unit scale 0.01" in err, err
    stage = Usd.Stage.Open(str(built / "cm.usda"))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01  # the decimal typed, not float32 0.009999999776
    got = _lights(built / "cm.usda")
    assert sorted(got) == sorted(IN_CENTIMETRES)
    i = list(CASES).index("RectN1")  # at Blender (0, 3 i, 2) units: Y-up (0, 2, -3 i) centimetres
    m = UsdGeom.Xformable(stage.GetPrimAtPath(got["RectN1"].path)).ComputeLocalToWorldTransform(0)
    assert Gf.Vec3d(m.ExtractTranslation()) == Gf.Vec3d(0, 2, -3 * i)
    rect = UsdLux.RectLight(stage.GetPrimAtPath(got["RectN1"].path))
    assert (rect.GetWidthAttr().Get(), rect.GetHeightAttr().Get()) == pytest.approx((0.5, 0.25))
    for name in IN_CENTIMETRES:
        rec = got[name]
        metres = np.linalg.norm(rec.to_world[:3, 0])  # read_scene's world matrix is in metres: 0.01 per unit
        assert metres == pytest.approx(0.01), name
        img = read_map(built / f"cm_{name}.exr", 3)[..., 1]
        h, w = img.shape
        centre = float(img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean())
        expected = 0.5 / pi * _centre_irradiance(rec, h=0.01, scale=0.01)
        assert centre == pytest.approx(expected, rel=0.005), (name, centre, expected)
    assert float(emitted_radiance(got["PointN"])[0]) == pytest.approx(P / (4 * pi) * 1e-4, rel=1e-6)


def test_cycles_of_the_blend_matches_mitsuba_of_the_lights_read_back(cli, built):
    """Cycles renders lit.blend (Normalize off, exposure -1..2, a 3000 K temperature); the lights read back from
    it, over the same floor and camera (floor.usda), rendered by Mitsuba: the same mean per channel (5%)."""
    from usdrelight.mitsuba.render import render_stage

    assert cli("convert", built / "lit.blend", built / "lit_lights.usda")[0] == 0
    st = open_stage(built / "floor.usda")
    layer = Sdf.Layer.CreateNew(str(built / "composed.usda"))
    layer.TransferContent(st.GetRootLayer())
    layer.subLayerPaths.append("lit_lights.usda")
    layer.Save()
    composed = open_stage(built / "composed.usda")
    assert len(read_scene(composed).lights) == len(RENDERED)
    mitsuba = read_map(render_stage(built / "composed.usda", built / "m", spp=128).files["color"], 3)
    cycles = read_map(built / "cycles.exr", 3)
    assert cycles.shape == mitsuba.shape
    m, c = mitsuba.mean((0, 1)), cycles.mean((0, 1))
    print("Cycles", c, "Mitsuba", m)
    np.testing.assert_allclose(c, m, rtol=0.02)  # measured within 0.15% per channel
    assert c[2] < 0.9 * c[0]  # the warm 3000 K and orange lights show: read back as colour, not dropped


def test_native_import_comes_back_with_the_stage_intensities(cli, built):
    """all_lights_stage imported by Blender's own USD importer (energy pi I, Normalize = UsdLux normalize, exposure
    kept, soft falloff on) and saved; converted back: the original emitted radiance of every light (1e-4),
    position and direction. The Sun comes back as what Blender renders: the importer wrote 4 x intensity, twice
    the angle and Normalize off, i.e. radiance 4 E over a 2 deg disk: E' = 4 E pi sin^2(1 deg)."""
    all_lights_stage(built / "all.usda")
    native_import([{"usd": built / "all.usda", "save": str(built / "native.blend")}])
    rc, _, err = cli("convert", built / "native.blend", built / "native_lights.usda")
    assert rc == 0, err
    assert "soft falloff" in err and " ".join(err.split()).count("): 1") == 1  # the sphere's, one line
    a = _lights(built / "all.usda")
    b = _lights(built / "native_lights.usda")
    # the importer made the Dome a World of strength 0.8 on Blender's default grey (0.050876): what Cycles renders
    assert sorted(b) == sorted(k if k != "Dome" else "World" for k in a)
    np.testing.assert_allclose(emitted_radiance(b.pop("World")), 0.8 * 0.0508761, rtol=1e-4)
    for k in b:
        want = emitted_radiance(a[k])
        if k == "Sun":
            want = want * 4 * math.pi * math.sin(math.radians(1.0)) ** 2
            assert b[k].angle_deg == pytest.approx(2.0, rel=1e-5)
        np.testing.assert_allclose(emitted_radiance(b[k]), want, rtol=1e-4, err_msg=k)
        np.testing.assert_allclose(b[k].to_world[:3, 3], a[k].to_world[:3, 3], atol=1e-5, err_msg=k)
        np.testing.assert_allclose(light_direction(b[k]), light_direction(a[k]), atol=1e-5, err_msg=k)
    assert b["Spot"].cone_angle_deg == pytest.approx(25.0, rel=1e-5)
    assert b["Sphere"].radius == pytest.approx(0.1, rel=1e-5) and b["Point"].treat_as_point


def test_multipliers_kept_and_the_rest_warned(cli, built):
    rc, _, err = cli("convert", built / "extra.blend", built / "extra.usda")
    assert rc == 0, err
    st = open_stage(built / "extra.usda")
    narrow = UsdLux.RectLight(st.GetPrimAtPath("/Scene/Lights/User/Narrow"))
    assert narrow.GetDiffuseAttr().Get() == pytest.approx(0.5) and narrow.GetSpecularAttr().Get() == pytest.approx(2.0)
    assert sorted(_lights(built / "extra.usda")) == ["Narrow", "Square"]  # not the light hidden from render
    text = " ".join(err.split())
    for kind in ("spread below 180 deg", "square spot", "volume factor", "hidden from render"):
        assert kind in text, kind
