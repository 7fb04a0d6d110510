"""What Blender's own USD importer (bpy 5.0.1, File > Import > USD with its defaults) makes of our stages: the
facts the README's "Native Blender import" note states. If a future Blender changes one, this fails and the
note (and benchmarks/bench_blender_native_import.py) need updating. One Blender process imports everything;
three tiny renders (32 x 24 px) check that the native light units render as the UsdLux closed forms say."""
import math

import numpy as np
import pytest
from pxr import UsdLux

from blender_native import all_lights_stage, native_import, zup_cm_point_stage
from usd_scenes import add_closed_form_light, looking_down_at_floor
from usdrelight.converters.blender import blender_lights
from usdrelight.imageio import read_map

STARTUP_GREY = 0.0508761  # Blender's startup World colour (linear), kept by the importer


@pytest.fixture(scope="module")
def native(tmp_path_factory):
    """Native imports (startup file; empty file) and our converter's .blend of the same stage."""
    from usdrelight.cli import main

    d = tmp_path_factory.mktemp("native")
    all_lights_stage(d / "all.usda")
    point = looking_down_at_floor(d / "point.usda")
    expected_point = add_closed_form_light(point, "point")
    point.GetRootLayer().Save()
    sun = looking_down_at_floor(d / "sun.usda")
    expected_sun = add_closed_form_light(sun, "distant")
    sun.GetRootLayer().Save()
    sharp = looking_down_at_floor(d / "sharp.usda")
    add_closed_form_light(sharp, "distant")
    UsdLux.DistantLight(sharp.GetPrimAtPath("/World/L")).CreateAngleAttr(0.0)
    sharp.GetRootLayer().Save()
    zup_cm_point_stage(d / "cm.usda", 32, 24)
    black = {"world_rgb": [0.0, 0.0, 0.0]}  # no ambient light from the startup World in the renders
    res = native_import([{"usd": d / "all.usda"}, {"usd": d / "all.usda", "empty": True},
                         {"usd": d / "point.usda", **black, "render": [32, 24, 16], "exr": d / "point.exr"},
                         {"usd": d / "sun.usda", **black, "render": [32, 24, 4], "exr": d / "sun.exr"},
                         {"usd": d / "sharp.usda", **black, "render": [32, 24, 4], "exr": d / "sharp.exr"},
                         {"usd": d / "cm.usda", **black, "render": [32, 24, 16], "exr": d / "cm.exr"}])
    assert main(["convert", str(d / "all.usda"), str(d / "all.blend")]) == 0
    ours = {l["name"].rsplit("_", 1)[-1]: l for l in blender_lights(d / "all.blend")}
    return {"startup": res[0], "empty": res[1], "lights": {l["name"]: l for l in res[0]["lights"]}, "ours": ours,
            "point_img": read_map(d / "point.exr", 3), "point_expected": expected_point,
            "sun_img": read_map(d / "sun.exr", 3), "sun_expected": expected_sun,
            "sharp_img": read_map(d / "sharp.exr", 3), "cm": res[5], "cm_img": read_map(d / "cm.exr", 3)}


def _centre(img):
    h, w = img.shape[:2]
    return float(img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean())


def test_point_light_is_pi_i_unnormalized_and_renders_like_ours(native):
    """Native: energy = pi I with Blender's normalize off; ours: 4 pi I normalized. Both give I W/sr in Cycles."""
    nat, ours = native["lights"]["Point"], native["ours"]["Point"]
    assert nat["type"] == "POINT" and nat["radius"] == 0.0
    assert nat["energy"] == pytest.approx(math.pi * 20.0, rel=1e-6)
    assert nat["normalize"] is False and nat["use_soft_falloff"] is True
    assert ours["power"] == pytest.approx(4 * math.pi * 20.0, rel=1e-6)
    # the unnormalized pi I renders as the closed form albedo/pi * I / r^2 (as our 4 pi I does, test_blender.py)
    assert _centre(native["point_img"]) == pytest.approx(native["point_expected"], rel=0.05)


def test_area_and_spot_lights(native):
    L = native["lights"]
    assert L["Sphere"]["energy"] == pytest.approx(math.pi * 5.0, rel=1e-6) and L["Sphere"]["radius"] == pytest.approx(0.1)
    assert L["Sphere"]["normalize"] is False  # the UsdLux fallback, read as Blender's unnormalized mode
    spot = L["Spot"]
    assert spot["type"] == "SPOT" and spot["energy"] == pytest.approx(math.pi * 7.0, rel=1e-6)
    assert spot["exposure"] == 1.0  # kept as Blender's light exposure (ours folds 2^exposure into the power)
    assert native["ours"]["Spot"]["power"] == pytest.approx(4 * math.pi * 14.0, rel=1e-5)
    assert math.degrees(spot["spot_size"]) == pytest.approx(50.0, rel=1e-5) and spot["spot_blend"] == pytest.approx(0.2)
    rect, disk = L["Rect"], L["Disk"]
    assert (rect["shape"], rect["size"], rect["size_y"]) == ("RECTANGLE", 0.5, 0.25)
    assert rect["energy"] == pytest.approx(math.pi * 3.0, rel=1e-6) and rect["normalize"] is False
    assert disk["shape"] == "DISK" and disk["size"] == pytest.approx(0.4)
    assert disk["energy"] == pytest.approx(math.pi * 3.0, rel=1e-6) and disk["normalize"] is True


def test_distant_light_is_4i_with_a_doubled_angle_and_unnormalized_renders_dark(native):
    nat, ours = native["lights"]["Sun"], native["ours"]["Sun"]
    assert nat["type"] == "SUN" and nat["energy"] == pytest.approx(12.0)  # 4 I; ours: strength = I
    assert ours["strength"] == pytest.approx(3.0)
    assert math.degrees(nat["angle"]) == pytest.approx(2.0, rel=1e-5)  # 2 x angle; ours: angle
    assert math.degrees(ours["angle"]) == pytest.approx(1.0, rel=1e-5)
    assert nat["normalize"] is False
    # unnormalized: the 12 is the radiance of a sun disk 2 x 0.53 deg wide (the angle's fallback, doubled), not
    # an irradiance: the floor gets albedo/pi * 12 * (the disk's solid angle), 1/1000 of the UsdLux closed form
    solid_angle = 2 * math.pi * (1 - math.cos(math.radians(0.53)))
    assert _centre(native["sun_img"]) == pytest.approx(0.5 / math.pi * 12.0 * solid_angle, rel=0.02)
    assert _centre(native["sun_img"]) < 0.01 * native["sun_expected"]
    # with angle 0 (what `--light sun:` and the Mitsuba XML reader write) the 4 I is irradiance: 4x too bright
    assert _centre(native["sharp_img"]) == pytest.approx(4 * native["sun_expected"], rel=0.02)


def test_dome_world_resolution_and_camera(native):
    s, e = native["startup"], native["empty"]
    bg = next(n for n in s["world"]["nodes"] if n["type"] == "ShaderNodeBackground")
    assert bg["strength"] == pytest.approx(0.8)  # the dome's intensity ...
    np.testing.assert_allclose(bg["color"], STARTUP_GREY, rtol=1e-4)  # ... times the startup World's grey
    assert e["world"] is None  # an empty file has no World, and the importer makes none
    # RenderSettings ignored: the file's 1920 x 1080 stays; the imported camera is not made active
    assert s["resolution"][:2] == [1920, 1080] and s["scene_camera"] is None
    cam = s["cameras"][0]
    # focalLength / apertures read as tenths of a stage unit (metersPerUnit 1): 100 x our millimetre values
    assert cam["sensor_fit"] == "HORIZONTAL" and cam["sensor_width"] == pytest.approx(3600.0)
    assert cam["lens"] == pytest.approx(100 * 36.0 / (2 * math.tan(math.radians(20.0))), rel=1e-5)
    np.testing.assert_allclose(np.array(cam["matrix"])[:3, 3], [0, 0, 1], atol=1e-6)  # Y-up -> Z-up


def test_centimetre_z_up_stage_is_scaled_to_metres(native):
    """metersPerUnit 0.01, Z-up: objects scaled by 0.01 (camera 1 m up), lens in mm (focalLength is in tenths of a
    stage unit), and the point light 100 cm above the floor lights it as at 1 m: the closed form albedo/pi I/1^2."""
    cam = native["cm"]["cameras"][0]
    assert cam["lens"] == pytest.approx(36.0 / (2 * math.tan(math.radians(20.0))), rel=1e-5)
    np.testing.assert_allclose(np.array(cam["matrix"])[:3, 3], [0, 0, 1], atol=1e-6)
    assert np.array(cam["matrix"])[0, 0] == pytest.approx(0.01)
    assert _centre(native["cm_img"]) == pytest.approx(0.5 * 20 / math.pi, rel=0.05)
