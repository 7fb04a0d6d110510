"""The fast relight renderer: closed forms per light kind, agreement with Mitsuba, its cache, sequences."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from usd_scenes import add_closed_form_light, looking_down_at_floor
from usdrelight.engine.fast import EngineSettings, FastRenderer
from usdrelight.transport.cache import CACHE_DIR, TransportCache
from usdrelight.imageio import read_map, write_image
from usdrelight.mitsuba.render import render_record
from usdrelight.stage.light_specs import parse_light
from usdrelight.stage.lux import frame_pointing_along
from usdrelight.stage.read import read_scene
from usdrelight.stage.records import LightRecord
from usdrelight.stage.validate import open_stage

from conftest import build_procedural

ALBEDO = 0.5


def _floor(tmp_path):
    stage = looking_down_at_floor(tmp_path / "floor.usda", width=16, height=12)
    stage.GetRootLayer().Save()
    return read_scene(open_stage(tmp_path / "floor.usda"))


def _centre(img):
    h, w = img.shape[:2]
    return img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean((0, 1))


def _at(pos, direction=None):
    m = np.eye(4) if direction is None else frame_pointing_along(direction)
    m[:3, 3] = pos
    return m


def _rect_irradiance(L, w, h, d):
    """E below the centre of a w x h rectangle of radiance L at distance d (four corner rectangles)."""
    X, Y = (w / 2) / d, (h / 2) / d
    corner = X / math.sqrt(1 + X * X) * math.atan(Y / math.sqrt(1 + X * X)) \
        + Y / math.sqrt(1 + Y * Y) * math.atan(X / math.sqrt(1 + Y * Y))
    return 4 * (L / 2) * corner


# each case: light over the floor (camera 1 m above it looking down), expected centre radiance a/pi * E
CLOSED_FORMS = {
    "point": (LightRecord("/p", "sphere", _at([0, 1, 0]), np.full(3, 20.0), treat_as_point=True), ALBEDO * 20 / np.pi),
    "spot": (LightRecord("/s", "sphere", _at([0, 1, 0], [0, -1, 0]), np.full(3, 20.0), treat_as_point=True,
                         cone_angle_deg=30.0, cone_softness=0.2), ALBEDO * 20 / np.pi),
    "sphere": (LightRecord("/sp", "sphere", _at([0, 1, 0]), np.full(3, 10.0), radius=0.2), ALBEDO * 10 * 0.2 ** 2),
    # a soft spot (ShapingAPI on a sphere of radius 0.2, as Cycles' spot of that radius): the sphere's light, the
    # cone from its centre (was the sphere alone: lit all round); pointing away, 0 below it
    "sphere_spot": (LightRecord("/ss", "sphere", _at([0, 1, 0], [0, -1, 0]), np.full(3, 10.0), radius=0.2,
                                cone_angle_deg=30.0, cone_softness=0.2), ALBEDO * 10 * 0.2 ** 2),
    "sphere_spot_away": (LightRecord("/sa", "sphere", _at([0, 1, 0], [0, 1, 0]), np.full(3, 10.0), radius=0.2,
                                     cone_angle_deg=30.0, cone_softness=0.2), 0.0 * ALBEDO),
    "disk": (LightRecord("/d", "disk", _at([0, 1, 0], [0, -1, 0]), np.full(3, 4.0), radius=0.5),
             ALBEDO * 4 * 0.25 / 1.25),
    "rect": (LightRecord("/r", "rect", _at([0, 1, 0], [0, -1, 0]), np.full(3, 4.0), width=0.6, height=0.4),
             ALBEDO / np.pi * _rect_irradiance(4.0, 0.6, 0.4, 1.0)),
    "distant": (LightRecord("/sun", "distant", frame_pointing_along([0, -1, 0]), np.full(3, 3.0)), ALBEDO * 3 / np.pi),
    "distant_wide": (LightRecord("/sun", "distant", frame_pointing_along([0, -1, 0]), np.full(3, 3.0), angle_deg=20.0),
                     ALBEDO * 3 / np.pi * (1 + math.cos(math.radians(10))) / 2),
    "dome": (LightRecord("/dome", "dome", np.eye(4), np.full(3, 0.8)), ALBEDO * 0.8),
}


@pytest.fixture(scope="module")
def floor_renderer(tmp_path_factory):
    rec = _floor(tmp_path_factory.mktemp("floor"))
    return FastRenderer(rec, EngineSettings(max_side=None, area_samples=64, max_depth=2))


@pytest.mark.parametrize("kind", sorted(CLOSED_FORMS))
def test_closed_forms(floor_renderer, kind):
    light, expected = CLOSED_FORMS[kind]
    np.testing.assert_allclose(_centre(floor_renderer.render([light]).beauty), expected, rtol=0.02)


def test_the_usdlux_closed_form_scenes_agree(tmp_path):
    """The same three lights the Mitsuba tests use, authored in USD and read back."""
    for kind in ("point", "dome", "distant"):
        stage = looking_down_at_floor(tmp_path / f"{kind}.usda", width=16, height=12)
        expected = add_closed_form_light(stage, kind)
        stage.GetRootLayer().Save()
        rec = read_scene(open_stage(tmp_path / f"{kind}.usda"))
        img = FastRenderer(rec, EngineSettings(max_side=None)).render(rec.lights).beauty
        np.testing.assert_allclose(_centre(img), expected, rtol=0.02)


@pytest.fixture(scope="module")
def procedural(tmp_path_factory):
    out = tmp_path_factory.mktemp("proc") / "st"
    scene = build_procedural(out)
    return scene


SCENE_LIGHTS = {
    "point": ["point:0.5,1.0,-2.5:3,2.5,2"],
    "spot": ["spot:0,1.5,-2:0.2,-1,-0.5:8,8,8:30:0.4"],
    "sun": ["sun:0.4,-1,-0.3:2,2,2"],
    "sun_wide": ["sun:0.4,-1,-0.3:2,2,2:10"],
    "dome": ["dome:0.5,0.6,0.8"],
    "sphere": ["sphere:-0.5,1.0,-2.0:20,20,20:0.15"],
    "rect": ["rect:0.3,1.6,-3.0:0,-1,0.2:6,6,6:0.8,0.5"],
    "disk": ["disk:-0.6,1.5,-2.5:0.3,-1,0:6,6,6:0.3"],
    # a UsdLux CylinderLight (no --light spec): a 0.8 m tube of radius 5 cm along X, 1.4 m up over the floor
    "cylinder": [LightRecord("/cyl", "cylinder", _at([0.2, 1.4, -2.6]), np.full(3, 8.0), radius=0.05, length=0.8)],
}
AREA_RECORDS = {
    "sphere": LightRecord("/sp", "sphere", _at([-0.5, 1.0, -2.0]), np.full(3, 20.0), radius=0.15),
    "rect": LightRecord("/r", "rect", _at([0.3, 1.6, -3.0], [0, -1, 0.2]), np.full(3, 6.0), width=0.8, height=0.5),
    "disk": LightRecord("/d", "disk", _at([-0.6, 1.5, -2.5], [0.3, -1, 0]), np.full(3, 6.0), radius=0.3),
}
"""The area lights of SCENE_LIGHTS built by hand (UsdLux: local -Z along the direction, normalize off)."""


@pytest.mark.parametrize("kind", sorted(AREA_RECORDS))
def test_area_light_specs_are_the_records_they_name(kind, cli, procedural):
    """The --light spec of each area light is that UsdLux light (so the Mitsuba comparison below checks the specs):
    where it is, which way it faces (local -Z along D), where a rect's W lies; bad values are one line and exit 2."""
    spec = SCENE_LIGHTS[kind][0]
    got, want = parse_light(spec), AREA_RECORDS[kind]
    assert (got.kind, got.radius, got.width, got.height, got.normalize) == \
        (want.kind, want.radius, want.width, want.height, want.normalize)
    np.testing.assert_array_equal(got.to_world, want.to_world)
    np.testing.assert_array_equal(got.radiance, want.radiance)
    parts = spec.split(":")
    np.testing.assert_allclose(got.to_world[:3, 3], [float(x) for x in parts[1].split(",")])
    if kind != "sphere":
        d = np.array([float(x) for x in parts[2].split(",")])
        np.testing.assert_allclose(-got.to_world[:3, 2], d / np.linalg.norm(d), atol=1e-12)
    if kind == "rect":  # D (0, -1, 0.2) is within 25.8 degrees of -Y: W lies along +X x (-D)
        np.testing.assert_allclose(got.to_world[:3, 0], [0.0, 0.2, 1.0] / np.linalg.norm([0.0, 0.2, 1.0]), atol=1e-12)
    head = spec.rsplit(":", 1)[0]
    sizes = ("0", "-1", "5e-5", "1e9", "inf") if kind != "rect" else ("0,1", "1,-1", "1e-9,1", "1,1e9", "inf,1")
    for bad in sizes:
        rc, _, err = cli("relight", procedural, "--light", f"{head}:{bad}")
        assert rc == 2 and len(err.strip().splitlines()) == 1, (bad, err)
        assert ("must be in [0.0001, 10000] m" in err) or ("finite number" in err), (bad, err)
    arabic = spec.replace(parts[1], parts[1].translate(str.maketrans("0123456789", "٠١٢٣٤٥٦٧٨٩")))
    for bad in (head, f"{spec}:1", spec.replace(parts[1], "1e7,0,0"), arabic):  # a part missing, too many; far;
        # other scripts' digits (float() reads them; a spec is ASCII)
        rc, _, err = cli("relight", procedural, "--light", bad)
        assert rc == 2 and "bad --light" in err and len(err.strip().splitlines()) == 1, (bad, err)


@pytest.fixture(scope="module")
def proc_renderer(procedural):
    rec = read_scene(open_stage(procedural))
    return rec, FastRenderer(rec, EngineSettings(max_side=128))


@pytest.mark.parametrize("kind", sorted(SCENE_LIGHTS))
def test_fast_matches_mitsuba_on_the_procedural_scene(proc_renderer, kind):
    rec, fr = proc_renderer
    lights = [parse_light(s) if isinstance(s, str) else s for s in SCENE_LIGHTS[kind]]
    fast = fr.render(lights).beauty
    ref = render_record(rec.with_lights(lights).with_camera(rec.camera.limited(128)), {"beauty"}, spp=512,
                        max_depth=3, hide_emitters=True)["beauty"]
    valid = fr.render(lights).valid
    rel = np.sqrt(np.mean((fast[valid] - ref[valid]) ** 2)) / np.sqrt(np.mean(ref[valid] ** 2))
    assert abs(fast[valid].mean() / ref[valid].mean() - 1) < 0.03
    assert rel < 0.08, rel  # 512-spp noise included


def test_longer_paths_add_the_bounces_mitsuba_adds(proc_renderer):
    """max_depth 5 against 3: the two further bounces add what Mitsuba's longer paths add (same sampler seed, so
    Mitsuba's difference is its extra bounces only), within the 2.5D gather's error; at 3 nothing is added."""
    rec, fr = proc_renderer
    lights = [parse_light("point:0.5,1.0,-2.5:3,2.5,2")]
    camera = rec.camera.limited(128)
    fast = {d: fr.render(lights, max_depth=d) for d in (3, 5)}
    ref = {d: render_record(rec.with_lights(lights).with_camera(camera), {"beauty"}, spp=512, max_depth=d,
                            hide_emitters=True, seed=0)["beauty"] for d in (3, 5)}
    valid = fast[3].valid
    added, added_ref = (fast[5].beauty - fast[3].beauty)[valid], (ref[5] - ref[3])[valid]
    assert added_ref.mean() > 0.005 * ref[3][valid].mean()
    assert 0.8 < added.mean() / added_ref.mean() < 1.25, (added.mean(), added_ref.mean())
    assert (added >= 0).all()
    np.testing.assert_array_equal(fr.render(lights).beauty, fast[3].beauty)  # the default is 3: nothing added


def test_textured_dome_matches_mitsuba(proc_renderer, tmp_path):
    from usd_scenes import asymmetric_latlong

    rec, fr = proc_renderer
    write_image(tmp_path / "sky.exr", asymmetric_latlong(32, 64) * 0.5 + 0.05, "float")
    from usdrelight.stage.records import TextureRecord

    rot = np.eye(4)
    rot[:3, :3] = frame_pointing_along([1, 0, 0.3])[:3, :3]
    dome = LightRecord("/sky", "dome", rot, np.array([1.0, 0.9, 0.8]), texture=TextureRecord(str(tmp_path / "sky.exr"), "raw"))
    fast = fr.render([dome])
    ref = render_record(rec.with_lights([dome]).with_camera(rec.camera.limited(128)), {"beauty"}, spp=512,
                        max_depth=3, hide_emitters=True)["beauty"]
    v = fast.valid
    assert abs(fast.beauty[v].mean() / ref[v].mean() - 1) < 0.04
    # a rotated (wrong) dome differs: the test can tell orientations apart
    flipped = LightRecord("/sky", "dome", np.diag([-1.0, 1, -1, 1]) @ rot, dome.radiance, texture=dome.texture)
    assert abs(fr.render([flipped]).beauty[v].mean() / ref[v].mean() - 1) > 0.08


def test_renders_are_deterministic_and_finite(proc_renderer):
    _, fr = proc_renderer
    lights = [parse_light(s) for s in ("point:0.5,1,-2.5:3,3,3", "sun:0,-1,-1:1,1,1:5")]
    a, b = fr.render(lights).beauty, fr.render(lights).beauty
    assert np.array_equal(a, b) and np.all(np.isfinite(a)) and a.min() >= 0


@pytest.mark.parametrize("kind", sorted(AREA_RECORDS))
def test_a_light_that_moves_a_little_keeps_its_sample_pattern(proc_renderer, kind):
    """Area lights drew their samples from a stream seeded by the light's content: moving one by 0.1 mm changed
    its noise everywhere (a sphere light: 0.46% mean change, 35% at a pixel); seeded by its path, the change is
    the light's own (0.005%)."""
    from dataclasses import replace as _replace

    _, fr = proc_renderer
    light = AREA_RECORDS[kind]
    moved = light.to_world.copy()
    moved[0, 3] += 1e-4
    a, b = fr.render([light]).beauty, fr.render([_replace(light, to_world=moved)]).beauty
    assert np.abs(a - b).mean() < 5e-4 * a.mean(), np.abs(a - b).mean() / a.mean()


def test_cache_is_reused_and_invalidated(procedural, tmp_path):
    import shutil

    stage = tmp_path / "st"
    shutil.copytree(procedural.parent, stage, symlinks=True)  # its links into versions/current stay links
    settings = EngineSettings(max_side=64)
    rec = read_scene(open_stage(stage / "scene.usda"))
    cache = TransportCache(stage / CACHE_DIR)
    first = FastRenderer(rec, settings, cache)
    assert not first.cache_hit and len(list((stage / CACHE_DIR).glob("transport-*.npz"))) == 1
    second = FastRenderer(read_scene(open_stage(stage / "scene.usda")), settings, cache)
    assert second.cache_hit and second.key == first.key
    light = [parse_light("point:0.5,1,-2.5:3,3,3")]
    assert np.array_equal(first.render(light).beauty, second.render(light).beauty)
    # a new albedo texture (same file name): new key, rebuilt, and the render follows the new albedo
    alb = read_map(stage / "textures" / "albedo.exr", 3)
    write_image(stage / "textures" / "albedo.exr", alb * 0.5, "half")
    third = FastRenderer(read_scene(open_stage(stage / "scene.usda")), settings, cache)
    assert not third.cache_hit and third.key != first.key
    ratio = third.render(light).beauty.sum() / first.render(light).beauty.sum()
    assert 0.3 < ratio < 0.6  # half the albedo: direct light halves, the bounce quarters
    # the stale entry stays until the cache's limits evict it (another session may still use it)
    assert len(list((stage / CACHE_DIR).glob("transport-*.npz"))) == 2
    # new geometry: new key
    rec = read_scene(open_stage(stage / "scene.usda"))
    moved = rec.meshes[0].__class__(**{**rec.meshes[0].__dict__, "points": rec.meshes[0].points * 1.01})
    assert FastRenderer(rec.__class__(**{**rec.__dict__, "meshes": (moved,)}), settings).key != third.key


def test_sequence_writes_numbered_frames_and_reports_times(cli, procedural, tmp_path):
    seq = tmp_path / "lights.json"
    seq.write_text(json.dumps([["point:0.5,1,-2.5:3,3,3"], ["point:-0.5,1,-2.5:3,3,3"], ["sun:0,-1,-1:1,1,1"]]))
    rep = cli.json("relight", procedural, "--sequence", seq, "--light", "dome:0.05,0.05,0.05", "--max-side", "96",
                   "--mode", "neural", "-o", tmp_path / "out")
    assert rep["renderer"] == "fast" and len(rep["frames"]) == 3 and "prepare" in rep["seconds"]
    for i, f in enumerate(rep["frames"]):
        for key in ("render", "network", "total"):
            assert f["seconds"][key] >= 0
        for name in (f"relit_{i:04d}.exr", f"relit_{i:04d}.png", f"render_diffuse_{i:04d}.exr"):
            assert (tmp_path / "out" / name).is_file()
    d0, d1 = (read_map(tmp_path / "out" / f"render_diffuse_{i:04d}.exr", 3) for i in (0, 1))
    w = d0.shape[1]
    # the light moved from right to left: so did the light in the image
    assert d0[:, w // 2:].mean() > d0[:, :w // 2].mean() and d1[:, :w // 2].mean() > d1[:, w // 2:].mean()
    bad = tmp_path / "bad.json"
    bad.write_text('[["point:1,2"]]')
    rc, _, err = cli("relight", procedural, "--sequence", bad, "--mode", "neural")
    assert rc == 2 and "bad --light" in err


def test_single_relight_keeps_its_file_names_and_second_call_hits_the_cache(cli, procedural, tmp_path):
    args = ("relight", procedural, "--light", "point:0.5,1,-2.5:3,3,3", "--max-side", "80", "--mode", "neural",
            "-o", tmp_path / "one")
    first = cli.json(*args)
    second = cli.json(*args)
    assert second["cache"] == "hit" and first["frames"][0]["exr"].endswith("relit.exr")
    for name in ("relit.exr", "relit.png", "render_diffuse.exr"):
        assert (tmp_path / "one" / name).is_file()
    rc, _, err = cli("relight", procedural, "--light", "point:0,1,-2:1,-100,1")
    assert rc == 2 and "must be >= 0" in err


def test_non_lambertian_stage_falls_back_to_mitsuba_with_one_warning(tmp_path, caplog):
    from pxr import Sdf, UsdShade

    from usdrelight.relight.session import RelightSession

    stage = looking_down_at_floor(tmp_path / "s.usda", width=16, height=12)
    shader = UsdShade.Shader(stage.GetPrimAtPath("/World/Looks/Grey/Surface"))
    shader.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)  # metallic workflow: glossy
    stage.GetRootLayer().Save()
    import logging

    logger = logging.getLogger("usdrelight")  # the CLI tests turn its propagation off: listen on it directly
    logger.addHandler(caplog.handler)
    try:
        with caplog.at_level("WARNING", logger="usdrelight"):
            session = RelightSession(tmp_path / "s.usda", max_side=None, spp=4, mode="neural")
    finally:
        logger.removeHandler(caplog.handler)
    assert session.renderer == "mitsuba" and session.cache_hit is None
    # counted once per record (the handler sees a record twice when the logger also propagates to the root)
    assert len({id(r) for r in caplog.records if "rendering with Mitsuba" in r.getMessage()}) == 1
    frame = session.render(["point:0,1,0:20,20,20"])
    assert np.all(np.isfinite(frame.diffuse)) and frame.diffuse.mean() > 0


def test_sequence_frames_written_in_the_background_equal_single_relights(cli, procedural, tmp_path):
    """Frames are written on a writer thread while the next renders (at most two waiting): every file is there,
    each equals the single-frame relight of its lights bit for bit, and its write time is reported apart."""
    specs = [[f"point:{x:.2f},1,-2.5:3,3,3"] for x in (-0.6, -0.2, 0.2, 0.6, 1.0)]
    seq = tmp_path / "lights.json"
    seq.write_text(json.dumps(specs))
    rep = cli.json("relight", procedural, "--sequence", seq, "--max-side", "64", "--mode", "neural",
                   "-o", tmp_path / "seq")
    assert [f["exr"].rsplit("/", 1)[-1] for f in rep["frames"]] == [f"relit_{i:04d}.exr" for i in range(5)]
    for f in rep["frames"]:
        assert f["seconds"]["write"] > 0 and f["seconds"]["total"] >= f["seconds"]["render"] + f["seconds"]["write"]
    for i in (0, 3):
        cli.json("relight", procedural, "--light", specs[i][0], "--max-side", "64", "--mode", "neural",
                 "-o", tmp_path / f"one{i}")
        np.testing.assert_array_equal(read_map(tmp_path / "seq" / f"relit_{i:04d}.exr", 3),
                                      read_map(tmp_path / f"one{i}" / "relit.exr", 3))


def test_a_preview_is_the_frame_of_its_count_and_never_stands_in_for_the_full_one(procedural):
    """render(area_samples=n) (the web app's preview of a moving area light) is bit for bit the frame of a renderer
    whose count is n; its terms are kept apart, so the full frame after it is the one a fresh renderer makes, and
    lights that do not sample (point, dome) are the same at any count."""
    from dataclasses import replace

    from usdrelight.errors import UsdRelightError
    from usdrelight.relight.session import RelightSession

    rec = read_scene(open_stage(procedural))
    settings = EngineSettings(max_side=64)
    kept = FastRenderer(rec, settings)
    lights = [AREA_RECORDS["rect"], AREA_RECORDS["sphere"], parse_light("point:0.5,1,-2.5:3,3,3"),
              parse_light("dome:0.05,0.05,0.06")]
    assert kept.missing_sampled_terms(lights) == lights[:2]
    preview = kept.render(lights, area_samples=2).beauty
    np.testing.assert_array_equal(preview, FastRenderer(rec, replace(settings, area_samples=2,
                                                                       direct_terms=0)).render(lights).beauty)
    assert kept.missing_sampled_terms(lights) == lights[:2]  # the preview's terms are not the full ones
    full = kept.render(lights).beauty
    np.testing.assert_array_equal(full, FastRenderer(rec, replace(settings, direct_terms=0)).render(lights).beauty)
    assert kept.missing_sampled_terms(lights) == [] and not np.array_equal(preview, full)
    rel = float(np.abs(preview - full).sum() / full.sum())
    assert 0 < rel < 0.25, rel  # two shadow rays instead of 16: near, not equal
    np.testing.assert_array_equal(kept.render(lights[2:], area_samples=2).beauty, kept.render(lights[2:]).beauty)
    for bad in (0, -3, 1025, 2.5, float("nan"), "16"):  # through the API: one clear error, nothing rendered
        with pytest.raises(UsdRelightError, match=r"area_samples \(--area-samples\) must be a whole number"):
            kept.render(lights, area_samples=bad)
    with pytest.raises(UsdRelightError, match=r"area_samples \(--area-samples\) must be a whole number"):
        FastRenderer(rec, replace(settings, area_samples=10 ** 9))
    for bad in (0, 10 ** 9, True):  # through a session: an error, not a fall-back to Mitsuba
        with pytest.raises(UsdRelightError, match=r"area_samples \(--area-samples\) must be a whole number"):
            RelightSession(procedural, max_side=32, settings=replace(settings, area_samples=bad))
    assert kept.sample_count(np.int64(16)) == 16 and kept.sample_count(np.float64(4.0)) == 4
    for step in range(3 * settings.direct_terms):  # a long drag of the rect: previews only, the sphere stays
        moved = replace(lights[0], to_world=_at([0.3 + 0.01 * step, 1.6, -3.0], [0, -1, 0.2]))
        kept.render([moved] + lights[1:], area_samples=2)
    assert kept.missing_sampled_terms(lights) == []  # the previews pushed no full term out
    with RelightSession(procedural, max_side=32, settings=replace(settings, area_samples=5)) as s:
        assert s.area_samples == 5  # what relight --json reports
    with RelightSession(procedural, max_side=32, renderer="mitsuba", spp=4) as s:
        assert s.area_samples is None  # Mitsuba takes spp, not shadow rays
        with pytest.raises(UsdRelightError, match="area_samples is a setting of the fast renderer"):
            s.render(["rect:0.3,1.6,-3.0:0,-1,0.2:6,6,6:0.8,0.5"], mode="render", area_samples=2)


def test_sphere_and_wide_sun_rays_go_in_bounded_chunks_with_the_same_bits(procedural, monkeypatch):
    """Sphere and wide-sun shadow rays are traced RAY_CHUNK at a time (pixels x samples), so a photo of any size
    stays in memory; the samples are made per chunk from shifts drawn once, so any chunk size gives the same bits."""
    import usdrelight.engine.lights as engine_lights

    rec = read_scene(open_stage(procedural))
    lights = [AREA_RECORDS["sphere"], parse_light("sun:0.4,-1,-0.3:2,2,2:10")]
    whole = FastRenderer(rec, EngineSettings(max_side=64, direct_terms=0)).render(lights).beauty
    monkeypatch.setattr(engine_lights, "RAY_CHUNK", 997)  # a prime: chunks of 62 pixels at 16 samples, one short
    chunked = FastRenderer(rec, EngineSettings(max_side=64, direct_terms=0)).render(lights).beauty
    np.testing.assert_array_equal(chunked, whole)
    assert whole.max() > 0 and len(engine_lights._chunks(64 * 48, 16)) > 40


def test_relight_area_samples_option_is_the_renderers_count(cli, procedural, tmp_path):
    """`relight --area-samples N` renders what a fast renderer with area_samples N renders (render_diffuse.exr);
    out of range, zero or with the Mitsuba renderer it is one line and exit 2, and nothing is written."""
    spec = SCENE_LIGHTS["rect"][0]
    rec = read_scene(open_stage(procedural))
    for n in (2, 64):
        out = tmp_path / f"n{n}"
        rc, stdout, err = cli("relight", procedural, "--light", spec, "--mode", "render", "--area-samples", str(n),
                              "-o", out, "--json")
        assert rc == 0, err
        assert json.loads(stdout)["area_samples"] == n  # the summary says what rendered
        want = FastRenderer(rec, EngineSettings(max_side=None, area_samples=n)).render([parse_light(spec)]).beauty
        np.testing.assert_array_equal(read_map(out / "render_diffuse.exr", 3), want)
    for bad, words in ((["--area-samples", "0"], "in [1, 1024]"), (["--area-samples", "5000"], "in [1, 1024]"),
                       (["--area-samples", "4", "--renderer", "mitsuba"], "the mitsuba renderer takes --spp")):
        out = tmp_path / "bad"
        rc, _, err = cli("relight", procedural, "--light", spec, *bad, "-o", out)
        assert rc == 2 and len(err.strip().splitlines()) == 1 and words in err, (bad, err)
        assert not out.exists()


def test_a_rect_rounded_to_float32_renders_as_the_rect(proc_renderer):
    """A rect light's frame as a float32 rotation carries it (a DCC export, a .blend round trip): its axes are
    orthogonal to 1e-8, not 1e-9, and the renderer left its solid-angle sampler for area sampling (3.5% darker
    at 16 rays, up to 9% at a pixel); a real shear still goes to area sampling."""
    from dataclasses import replace as _replace

    from usdrelight.engine.lights import SHEAR_TOL

    _, fr = proc_renderer
    light = AREA_RECORDS["rect"]
    rounded = light.to_world.copy()
    ax, ay = rounded[:3, 0].copy(), rounded[:3, 1]
    rounded[:3, 0] += 3e-8 * np.linalg.norm(ax) * ay / np.linalg.norm(ay)  # cos between the axes 3e-8
    a, b = fr.render([light]).beauty, fr.render([_replace(light, to_world=rounded)]).beauty
    assert np.abs(a - b).max() < 1e-4 * a.max(), np.abs(a - b).max() / a.max()
    sheared = light.to_world.copy()
    sheared[:3, 1] += 10 * SHEAR_TOL * np.linalg.norm(sheared[:3, 1]) * sheared[:3, 0] / np.linalg.norm(sheared[:3, 0])
    c = fr.render([_replace(light, to_world=sheared)]).beauty
    assert np.abs(c - a).max() > 10 * np.abs(a - b).max()  # the other sampler: another pattern


def test_a_singular_disk_or_rect_frame_still_renders(proc_renderer):
    """A disk whose frame has two equal rows (a degenerate transform a user can author) went to area sampling and
    rendered; the cylinder's normal transform made every planar light invert its frame: LinAlgError."""
    from dataclasses import replace as _replace

    _, fr = proc_renderer
    for kind in ("disk", "rect"):
        light = AREA_RECORDS[kind]
        m = light.to_world.copy()
        m[1, :3] = m[0, :3]
        img = fr.render([_replace(light, to_world=m)]).beauty
        assert np.all(np.isfinite(img)) and img.min() >= 0
