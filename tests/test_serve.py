"""`usdrelight serve`: light <-> UI state <-> UsdLux mappings, the user-layer writer, safety rules, the
command's start/stop, and the app driven by a real headless Chromium (Playwright, system browser).

Stages are the procedural example built at stride 4 with one fitted point light written directly (no fit run),
rendered at 96 px: every app starts in about a second.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from dataclasses import replace

import numpy as np
import pytest

from conftest import build_procedural
from usdrelight.errors import UsdRelightError
from usdrelight.stage.layout import USER_LIGHTS
from usdrelight.stage.light_specs import parse_light
from usdrelight.stage.lights_layer import write_fitted_lights
from usdrelight.stage.read import read_scene
from usdrelight.stage.records import FitProvenance, PointLightValue
from usdrelight.stage.validate import open_stage
from usdrelight.serve.files import read_user_states, store_upload
from usdrelight.serve.saving import write_user_layer
from usdrelight.serve.state import (LightState, color_from_picker, from_record, picker_from_color,
                                    quat_pointing_along, to_record)

CHROMIUM = Path("/usr/bin/chromium")
SIDE = 96


def _stage(out: Path) -> Path:
    stage = build_procedural(out, stride=4)
    write_fitted_lights(out, [PointLightValue(np.array([0.5, 1.0, -1.5]), np.array([3.0, 3.0, 3.0]))], None,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 0))
    return stage


@pytest.fixture(scope="module")
def base_stage(tmp_path_factory):
    return _stage(tmp_path_factory.mktemp("serve") / "scene")


@pytest.fixture
def stage(base_stage, tmp_path):
    """A private copy of the stage (with its relight cache, so apps start from it)."""
    dst = tmp_path / "scene"
    shutil.copytree(base_stage.parent, dst)
    return dst / "scene.usda"


def _hdri(path: Path) -> Path:
    from usdrelight.imageio import write_image

    img = np.ones((8, 16, 3), np.float32) * np.linspace(0.1, 1.0, 16, dtype=np.float32)[None, :, None]
    return write_image(path, img, "float")


def _all_kinds(hdri_label: str) -> list[LightState]:
    return [
        LightState("Key", "point", color=(1.0, 0.5, 0.25), intensity=12.5, exposure=1.5, position=(0.3, 0.8, -2.0)),
        LightState("Spot1", "spot", color=color_from_picker((255, 128, 0)), intensity=40.0, position=(-1, 1, -1),
                   rotation=quat_pointing_along([0.5, -1.0, -0.7]), cone_angle=35.0, softness=0.3),
        LightState("Sun1", "sun", intensity=2.0, exposure=-1.0, rotation=quat_pointing_along([0.2, -1, -0.4]),
                   angle=0.53),
        LightState("Dome1", "dome", color=(0.2, 0.3, 0.5), intensity=0.7),
        LightState("Sky", "dome", intensity=0.5, hdri=hdri_label, rotation=quat_pointing_along([1, 0, 0])),
        LightState("Off", "point", intensity=3.0, position=(0, 2, -1), enabled=False),
        LightState("Ball", "sphere", intensity=30.0, position=(0.5, 1.2, -1.5), radius=0.125),
        LightState("Round", "disk", color=(1.0, 0.75, 0.5), intensity=8.0, position=(-0.5, 1.5, -2.0),
                   rotation=quat_pointing_along([0.3, -1.0, 0.1]), radius=0.3),
        LightState("Panel2", "rect", intensity=6.0, position=(0.2, 1.6, -2.5),
                   rotation=quat_pointing_along([0.0, -1.0, 0.2]), width=0.75, height=0.5),
    ]


# ---- mappings ---------------------------------------------------------------------------------------
def test_state_usd_state_round_trip_keeps_other_layers(stage):
    """state -> lights_user.usda -> state is exact for every kind; only lights_user.usda changes, and a light
    the app cannot edit (a normalized DiskLight a user put in the layer) stays as it was."""
    from pxr import Sdf, Usd, UsdLux

    folder = stage.parent
    hdri = _hdri(folder / "sky.exr")
    layer = Sdf.Layer.FindOrOpen(str(folder / USER_LIGHTS))
    s = Usd.Stage.Open(layer)
    s.OverridePrim("/Scene")
    panel = UsdLux.DiskLight.Define(s, "/Scene/Lights/User/Panel")
    panel.CreateRadiusAttr(0.25)
    panel.CreateNormalizeAttr(True)
    layer.Save()
    before = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file() and p.name != USER_LIGHTS}
    states = _all_kinds("sky")
    write_user_layer(folder, states, hdri_paths={"sky": hdri})
    after = {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file() and p.name != USER_LIGHTS}
    assert after == before  # no other layer (or file) touched, no temp file left
    names = {str(hdri.resolve()): "sky"}
    back, others = read_user_states(open_stage(stage), names)
    assert back == states
    assert others == ["/Scene/Lights/User/Panel"]
    # saving again after removing one light: it goes, the DiskLight stays
    write_user_layer(folder, states[1:], managed={s.name for s in states}, hdri_paths={"sky": hdri})
    back, others = read_user_states(open_stage(stage), names)
    assert back == states[1:] and others == ["/Scene/Lights/User/Panel"]
    # what the renderers read from the saved stage is exactly to_record of the states
    rec = {l.path: l for l in read_scene(open_stage(stage)).lights}
    for st in states[1:]:
        want = to_record(st, {"sky": hdri})
        if want is None:
            assert st.path not in rec  # switched off: invisible in the stage
            continue
        got = rec[st.path]
        np.testing.assert_allclose(got.radiance, want.radiance, rtol=1e-6)
        np.testing.assert_allclose(got.to_world, want.to_world, atol=1e-12)
        assert (got.kind, got.treat_as_point, got.cone_angle_deg, got.angle_deg) == \
               (want.kind, want.treat_as_point, want.cone_angle_deg, want.angle_deg)
        assert (got.radius, got.width, got.height, got.normalize) == (want.radius, want.width, want.height, False)
        assert (got.texture.path if got.texture else None) == (str(hdri.resolve()) if st.hdri else None)


def test_save_refused_while_another_process_writes_the_stage(stage):
    from usdrelight.atomic import LOCK_NAME

    folder = stage.parent
    before = (folder / USER_LIGHTS).read_bytes()
    (folder / LOCK_NAME).write_text(f"{os.getppid()}\n")  # a live writer (our parent process) holds the lock
    with pytest.raises(UsdRelightError, match="being written by PID"):
        write_user_layer(folder, [LightState("Key", "point")])
    assert (folder / USER_LIGHTS).read_bytes() == before
    (folder / LOCK_NAME).unlink()
    write_user_layer(folder, [LightState("Key", "point")])
    assert not (folder / LOCK_NAME).exists() and b"Key" in (folder / USER_LIGHTS).read_bytes()


def test_state_matches_light_specs_and_records():
    """A state renders exactly as the equivalent --light spec, and record -> state -> record is the identity."""
    cases = [
        (LightState("A", "point", color=(1.0, 0.5, 0.25), intensity=8.0, position=(0.5, 1, -2)),
         "point:0.5,1,-2:8,4,2"),
        (LightState("B", "spot", intensity=10.0, position=(-0.8, 0.6, -1),
                    rotation=quat_pointing_along([0.5, -0.3, -1]), cone_angle=35.0, softness=0.25),
         "spot:-0.8,0.6,-1:0.5,-0.3,-1:10,10,10:35:0.25"),
        (LightState("C", "sun", color=(0.5, 0.5, 1.0), intensity=4.0, rotation=quat_pointing_along([0.2, -1, 0.1]),
                    angle=0.5), "sun:0.2,-1,0.1:2,2,4:0.5"),
        (LightState("D", "dome", color=(0.25, 0.5, 1.0), intensity=0.5), "dome:0.125,0.25,0.5"),
        (LightState("E", "sphere", intensity=20.0, position=(-0.5, 1, -2), radius=0.25),
         "sphere:-0.5,1,-2:20,20,20:0.25"),
        (LightState("F", "disk", intensity=6.0, position=(-0.6, 1.5, -2.5), rotation=quat_pointing_along([0.3, -1, 0]),
                    radius=0.3), "disk:-0.6,1.5,-2.5:0.3,-1,0:6,6,6:0.3"),
        (LightState("G", "rect", intensity=6.0, position=(0.3, 1.6, -3), rotation=quat_pointing_along([0, -1, 0.2]),
                    width=0.75, height=0.5), "rect:0.3,1.6,-3:0,-1,0.2:6,6,6:0.75,0.5"),
    ]
    for state, spec in cases:
        rec, ref = to_record(state), parse_light(spec)
        np.testing.assert_allclose(rec.radiance, ref.radiance, rtol=1e-6)
        if state.kind not in ("sun", "dome"):
            np.testing.assert_allclose(rec.to_world[:3, 3], ref.to_world[:3, 3])
        if state.kind == "rect":  # the same rect: W along the same axis
            np.testing.assert_allclose(rec.to_world[:3, :3], ref.to_world[:3, :3], atol=1e-12)
        assert (rec.radius, rec.width, rec.height) == pytest.approx((ref.radius, ref.width, ref.height), rel=1e-7)
        assert rec.normalize == ref.normalize  # sizes: float32 in the app and in USD
        if state.kind in ("spot", "sun", "disk", "rect"):
            np.testing.assert_allclose(rec.to_world[:3, :3] @ [0, 0, -1], ref.to_world[:3, :3] @ [0, 0, -1],
                                       atol=1e-12)
        assert (rec.kind, rec.treat_as_point, rec.cone_angle_deg, rec.cone_softness, rec.angle_deg) == \
               (ref.kind, ref.treat_as_point, ref.cone_angle_deg, ref.cone_softness, ref.angle_deg)
        again = to_record(from_record(rec, state.name))
        np.testing.assert_allclose(again.radiance, rec.radiance, rtol=1e-6)
        np.testing.assert_allclose(again.to_world, rec.to_world, atol=1e-12)
    assert to_record(cases[0][0].with_(enabled=False)) is None


def test_the_3d_view_draws_an_area_light_where_and_as_large_as_it_renders():
    """light_outline, carried by the gizmo's frame (the record's to_world), lies on the emitting shape the engine
    samples: a rect's corners at to_world @ (+-W/2, +-H/2, 0), width along local X; a disk's circle at its
    radius around the light's position, in the plane normal to the direction it shines."""
    from usdrelight.serve.scene_view import light_outline
    from usdrelight.stage.lux import light_direction

    panel = LightState("Panel", "rect", intensity=6.0, position=(0.2, 1.6, -2.5),
                       rotation=quat_pointing_along([0.3, -1.0, 0.2]), width=0.75, height=0.5)
    rec = to_record(panel)
    seg = light_outline(panel)
    world = seg.reshape(-1, 3) @ rec.to_world[:3, :3].T + rec.to_world[:3, 3]
    want = np.array([[sx * 0.375, sy * 0.25, 0.0, 1.0] for sx in (-1, 1) for sy in (-1, 1)]) @ rec.to_world.T
    assert seg.shape == (4, 2, 3)
    np.testing.assert_allclose(np.unique(np.round(world, 9), axis=0), np.unique(np.round(want[:, :3], 9), axis=0),
                               atol=1e-9)
    edges = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    np.testing.assert_allclose(sorted(edges), [0.5, 0.5, 0.75, 0.75])
    assert np.allclose(seg[0, 1] - seg[0, 0], [0.75, 0.0, 0.0])  # the width lies along local X, as UsdLux's
    disk = LightState("Round", "disk", intensity=8.0, position=(-0.5, 1.5, -2.0),
                      rotation=quat_pointing_along([0.3, -1.0, 0.1]), radius=0.3)
    rec = to_record(disk)
    world = light_outline(disk).reshape(-1, 3) @ rec.to_world[:3, :3].T + rec.to_world[:3, 3]
    np.testing.assert_allclose(np.linalg.norm(world - np.array(disk.position), axis=1), 0.3, rtol=1e-6)
    np.testing.assert_allclose((world - np.array(disk.position)) @ light_direction(rec), 0.0, atol=1e-6)
    assert light_outline(LightState("P", "point")) is None and light_outline(LightState("B", "sphere")) is None


def test_colour_picker_round_trip_and_validation():
    for v in range(256):
        assert picker_from_color(color_from_picker((v, 255 - v, v // 2))) == (v, 255 - v, v // 2)
    assert color_from_picker((255, 255, 255)) == (1.0, 1.0, 1.0)
    for bad in ({"name": "../x"}, {"kind": "laser"}, {"intensity": -1.0}, {"color": (1, np.nan, 0)},
                {"cone_angle": 0.0}, {"softness": 2.0}, {"rotation": (0, 0, 0, 0)}, {"radius": 0.0},
                {"width": 1e-5}, {"height": 2e4}, {"radius": np.inf}):
        with pytest.raises(UsdRelightError):
            LightState(**{"name": "L", "kind": "spot", **bad})


def test_per_light_terms_are_reused_and_render_what_an_uncached_engine_renders(stage):
    """The renderer keeps each light's direct term (scaled by radiance): the app's frames equal those of an
    engine that keeps none, also after a light moved and another changed colour; unchanged lights are reused."""
    from dataclasses import replace

    from usdrelight.engine.fast import FastRenderer
    from usdrelight.serve.live import LightSet, LiveRelight
    from usdrelight.stage.read import read_scene

    live = LiveRelight(stage, max_side=SIDE, mode="add")
    engine = live.session("add").engine
    fresh = FastRenderer(read_scene(stage), replace(engine.settings, direct_terms=0))
    states = [LightState("P", "point", color=(1.0, 0.5, 0.2), intensity=6.0, position=(0.3, 0.8, -2.0)),
              LightState("S", "spot", intensity=9.0, position=(-0.5, 1.0, -1.5),
                         rotation=quat_pointing_along([0.3, -1.0, -0.5]), cone_angle=30.0, softness=0.3),
              LightState("Sun", "sun", intensity=1.5, rotation=quat_pointing_along([0.2, -1.0, -0.3])),
              LightState("Dome", "dome", color=(0.2, 0.3, 0.5), intensity=0.4)]
    for step in range(3):
        lights = live.lights(LightSet(tuple(states), fitted_on=True, dimmer=0.5, mode="ratio"))
        ref = fresh.render(lights).beauty
        got = engine.render(lights).beauty
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-6 * float(ref.max()))
        assert engine.terms_kept == 5 + step and fresh.terms_kept == 0  # 4 lights + the fitted one, + 1 per move
        states[0] = states[0].with_(position=(0.3 + 0.1 * (step + 1), 0.8, -2.0))
        states[1] = states[1].with_(color=color_from_picker((255, 60 * step, 0)), intensity=9.0 + step)
    live.close()


def test_a_moved_area_light_is_previewed_then_shown_at_the_full_count(stage):
    """The frame loop shows a moved rect light first with PREVIEW_SAMPLES shadow rays, then, after the settle
    time, the full frame, equal to `relight`'s; a colour change (its term kept) is one full frame; a newer request
    during the settle time supersedes the older request's full frame."""
    from usdrelight.relight.session import RelightSession
    from usdrelight.serve.live import PREVIEW_SAMPLES, FrameLoop, LightSet, LiveRelight

    live = LiveRelight(stage, max_side=SIDE)
    frames: list = []
    got = threading.Condition()

    def on_frame(frame):
        with got:
            frames.append(frame)
            got.notify_all()

    def wait_for(test):
        with got:
            assert got.wait_for(lambda: test(frames), timeout=120), [(f.request, f.preview) for f in frames]

    rect = LightState("Panel", "rect", intensity=6.0, position=(0.2, 1.6, -2.5),
                      rotation=quat_pointing_along([0.0, -1.0, 0.2]), width=0.75, height=0.5)
    ls = LightSet((rect,), fitted_on=False)
    loop = FrameLoop(live, on_frame, settle=0.05)
    try:
        n = loop.request(ls)
        wait_for(lambda fs: any(f.request == n and not f.preview for f in fs))
        assert [(f.request, f.preview) for f in frames] == [(n, True), (n, False)]
        assert frames[0].mode == frames[1].mode == "residual" and not frames[1].error
        with RelightSession(stage, max_side=SIDE, stage_lights=False, mode="residual") as s:
            np.testing.assert_array_equal(frames[1].image, s.render(live.lights(ls)).image)
            preview = s.render(live.lights(ls), area_samples=PREVIEW_SAMPLES).image
        np.testing.assert_array_equal(frames[0].image, preview)
        assert not np.array_equal(frames[0].image, frames[1].image)
        n2 = loop.request(LightSet((rect.with_(color=(1.0, 0.5, 0.2)),), fitted_on=False))
        wait_for(lambda fs: any(f.request == n2 for f in fs))
        time.sleep(0.3)
        assert [(f.request, f.preview) for f in frames[2:]] == [(n2, False)]
    finally:
        loop.stop()
    frames.clear()
    loop = FrameLoop(live, on_frame, settle=30.0)
    try:
        moved = LightSet((rect.with_(position=(0.4, 1.6, -2.5)),), fitted_on=False)
        n3 = loop.request(moved)
        wait_for(lambda fs: bool(fs))
        n4 = loop.request(LightSet((LightState("P", "point", intensity=6.0, position=(0.3, 0.8, -2.0)),),
                                   fitted_on=False))
        wait_for(lambda fs: any(f.request == n4 for f in fs))
        assert [(f.request, f.preview) for f in frames] == [(n3, True), (n4, False)]
        frames.clear()
        again = LightSet((rect.with_(position=(0.6, 1.6, -2.5)),), fitted_on=False)
        n5 = loop.request(again)
        wait_for(lambda fs: bool(fs))
        n6 = loop.request(again)  # the same state sent again (a GUI on mouse-up): the full frame answers it
        wait_for(lambda fs: any(not f.preview for f in fs))
        assert [(f.request, f.preview) for f in frames] == [(n5, True), (n6, False)]
    finally:
        loop.stop()
    frames.clear()
    live.hdris["Gone"] = str(stage.parent / "no_such_sky.exr")  # a dome whose HDRI went missing
    loop = FrameLoop(live, on_frame, settle=0.05)
    try:
        broken = LightSet((rect.with_(position=(0.8, 1.6, -2.5)), LightState("Sky", "dome", hdri="Gone")),
                          fitted_on=False)
        n7 = loop.request(broken)
        wait_for(lambda fs: bool(fs))
        time.sleep(0.3)
        assert [(f.request, f.preview, bool(f.error)) for f in frames] == [(n7, False, True)]  # final, not preview
    finally:
        loop.stop()
    live.close()


# ---- safety -------------------------------------------------------------------------------------------
def test_app_auto_mode_follows_relights_rule_per_frame(stage):
    """The app's default mode is auto, resolved per frame as `relight` resolves it (add with the photo's lighting
    on at 1, transfer dimmed, residual off), on one shared session; each frame equals the fixed mode's frame."""
    from usdrelight.relight.session import RelightSession
    from usdrelight.serve.live import DEFAULT_MODE, LightSet, LiveRelight

    assert DEFAULT_MODE == "auto"
    live = LiveRelight(stage, max_side=SIDE)
    assert live.mode == "auto"
    key = (LightState("P", "point", color=(1.0, 0.8, 0.6), intensity=6.0, position=(0.3, 0.8, -2.0)),)
    want = {(True, 1.0): "add", (True, 0.4): "transfer", (False, 1.0): "residual", (True, 0.0): "residual"}
    for (on, dimmer), mode in want.items():
        auto = LightSet(key, fitted_on=on, dimmer=dimmer, mode="auto")
        assert live.resolve(auto) == mode
        got = live.render(auto)[0]
        fixed = live.render(replace(auto, mode=mode))[0]
        np.testing.assert_array_equal(got, fixed)
        assert np.all(np.isfinite(got)) and got.min() >= 0
    assert len(live._sessions) == 1  # one renderer for every mode
    with RelightSession(stage, max_side=SIDE, stage_lights=False, mode="residual") as s:  # as relight makes it
        off = live.render(LightSet(key, fitted_on=False, mode="auto"))[0]
        np.testing.assert_allclose(off, s.render(live.lights(LightSet(key, fitted_on=False))).image, rtol=1e-6,
                                   atol=1e-7)
    live.close()


def test_a_fixed_mode_the_stage_cannot_run_falls_back_to_auto(tmp_path):
    """A stage without a fit cannot run ratio or transfer: the app starts in auto, which renders `render`."""
    from usdrelight.serve.live import LightSet, LiveRelight

    live = LiveRelight(build_procedural(tmp_path / "nofit", stride=4), max_side=SIDE, mode="ratio")
    ls = LightSet((LightState("P", "point", intensity=6.0, position=(0.3, 0.8, -2.0)),), mode=live.mode)
    assert live.mode == "auto" and live.resolve(ls) == "render"
    image = live.render(ls)[0]
    assert np.all(np.isfinite(image)) and image.max() > 0
    live.close()


def test_uploads_go_to_fixed_places(stage, tmp_path):
    folder = stage.parent
    content = _hdri(tmp_path / "x.exr").read_bytes()
    label, path = store_upload(folder, "../../../../etc/evil name.exr", content)
    assert path.parent == folder.resolve() / "serve" / "uploads"
    assert path.name.startswith("hdri-") and path.suffix == ".exr" and path.read_bytes() == content
    assert "/" not in label and ".." not in label
    assert not (tmp_path / "etc").exists()
    for name, data in (("sky.png", content), ("sky.exr", b"not an image"), ("sky.exr", b"")):
        with pytest.raises(UsdRelightError):
            store_upload(folder, name, data)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]  # the refused ones left nothing


def test_app_binds_loopback_and_refuses_share_links(stage):
    pytest.importorskip("viser")
    from usdrelight.cli import build_parser
    from usdrelight.serve.app import DEFAULT_HOST, ServeApp

    assert DEFAULT_HOST == "127.0.0.1"
    assert build_parser().parse_args(["serve", str(stage)]).host == "127.0.0.1"
    from pxr import Sdf, Usd, UsdLux

    layer = Sdf.Layer.FindOrOpen(str(stage.parent / USER_LIGHTS))
    area = Usd.Stage.Open(layer)
    area.OverridePrim("/Scene")
    UsdLux.SphereLight.Define(area, "/Scene/Lights/User/Point1").CreateRadiusAttr(0.1)  # an area light
    layer.Save()
    with ServeApp(stage, port=0, max_side=SIDE) as app:
        assert app.host == "127.0.0.1" and app.url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(app.url, timeout=10) as r:
            assert r.status == 200
        # not reachable through the machine's other addresses
        for addr in {a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)}:
            if not addr.startswith("127."):
                with pytest.raises(OSError):
                    socket.create_connection((addr, app.port), timeout=2).close()
        assert app.server.request_share_url() is None  # a client's share request opens no tunnel
        assert app.add_light("point") == "Point2"  # Point1 is a light of the layer the app cannot edit
        # the widgets: no free-text input anywhere (so no client-named path)
        kinds = {type(h).__name__ for h in app.server.gui._gui_input_handle_from_uuid.values()}
        assert not any("Text" in k for k in kinds), kinds
        # an edit, a save and an export write only where they should
        app.add_light("spot")
        app.wait_shown(app.update())
        app.save()
        saved = open_stage(stage)
        assert UsdLux.SphereLight(saved.GetPrimAtPath("/Scene/Lights/User/Point1")).GetRadiusAttr().Get() == \
            pytest.approx(0.1)  # kept
        assert saved.GetPrimAtPath("/Scene/Lights/User/Point2") and saved.GetPrimAtPath("/Scene/Lights/User/Spot1")
        live_cache = sorted((stage.parent / "cache").glob("relight-*.npz"))
        exr, png = app.export()
        assert exr == stage.parent.resolve() / "serve" / "export" / "relit.exr" and png.exists()
        assert set(live_cache) <= set((stage.parent / "cache").glob("relight-*.npz"))  # next start stays warm


def test_hdri_named_outside_the_stage_is_copied_in(stage, tmp_path):
    """--hdri files are copied under STAGE_DIR/serve/uploads, so a saved dome reads back (scene-folder
    confinement) and renders."""
    pytest.importorskip("viser")
    from usdrelight.serve.app import ServeApp

    outside = _hdri(tmp_path / "my sky.exr")
    with ServeApp(stage, port=0, max_side=SIDE, hdris=[outside]) as app:
        (label, path), = app.hdris.items()
        assert label == "my_sky" and path.parent == stage.parent.resolve() / "serve" / "uploads"
        name = app.add_light("dome")
        app.set_light(name, hdri=label, intensity=0.5)
        shown = app.wait_shown(app.update())
        assert not shown.error and shown.seconds["total"] > 0
        app.save()
    dome = {l.path: l for l in read_scene(open_stage(stage)).lights}[f"/Scene/Lights/User/{name}"]
    assert Path(dome.texture.path).resolve() == path


def test_stop_on_signals_puts_the_handlers_back():
    from usdrelight.serve.signals import stop_on_signals

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with stop_on_signals():
        assert all(signal.getsignal(s) is signal.default_int_handler for s in before)
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGTERM)
    assert {s: signal.getsignal(s) for s in before} == before


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_serve_command_prints_url_and_stops_on_ctrl_c(stage, sig):
    """Ctrl-C (SIGINT) and kill (SIGTERM) stop the app with exit 0, SIGINT also when the parent ignores it (as a
    shell does for a background job: the child inherits the ignored disposition)."""
    pytest.importorskip("viser")
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # SIGINT ignored in the child as a shell's background job has it (a trap before exec, not preexec_fn: this
    # process has threads)
    ignore = ["sh", "-c", 'trap "" INT; exec "$@"', "sh"] if sig == "SIGINT" else []
    proc = subprocess.Popen(ignore + [sys.executable, "-m", "usdrelight", "serve", str(stage), "--port", "0",
                                      "--max-side", str(SIDE), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env, text=True)
    try:
        text, summary = "", None
        while summary is None:  # the --json summary is printed once the app serves
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
            text += line
            try:
                summary = json.loads(text)
            except ValueError:
                pass
        assert summary["url"].startswith("http://127.0.0.1:") and summary["host"] == "127.0.0.1"
        with urllib.request.urlopen(summary["url"], timeout=10) as r:
            assert r.status == 200
    finally:
        proc.send_signal(getattr(signal, sig))
        try:
            _, err = proc.communicate(timeout=60)  # drains both pipes: a full stderr pipe must not hold the exit
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 0, err


def test_stage_without_camera_or_mesh_is_one_clear_error(tmp_path, cli):
    pytest.importorskip("viser")
    from pxr import Usd, UsdGeom

    from usd_scenes import looking_down_at_floor

    no_cam = Usd.Stage.CreateNew(str(tmp_path / "nocam.usda"))
    UsdGeom.Mesh.Define(no_cam, "/World/Mesh")
    no_cam.GetRootLayer().Save()
    no_mesh = looking_down_at_floor(tmp_path / "nomesh.usda", width=16, height=12)
    no_mesh.RemovePrim("/World/Floor")
    no_mesh.GetRootLayer().Save()
    for name, what in (("nocam", "no camera"), ("nomesh", "no mesh")):
        rc, out, err = cli("serve", tmp_path / f"{name}.usda", "--port", "0")
        assert rc == 2 and err.startswith("usdrelight: error: ") and what in err and err.count("\n") == 1, err


def test_without_viser_the_command_names_the_extra(stage, cli, monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)  # as if viser were not installed
    rc, out, err = cli("serve", stage, "--port", "0")
    assert rc == 2 and err == "usdrelight: error: usdrelight serve needs viser: pip install 'usdrelight[serve]'\n"


# ---- the browser ------------------------------------------------------------------------------------
@contextlib.contextmanager
def app_page(stage):
    """The web app on ``stage`` and a headless Chromium page on it (Debian's, driven by Playwright), its editor
    loaded (the "Add light" button shown); skipped with the reason when viser, Playwright or Chromium is missing."""
    pytest.importorskip("viser")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (the test extra)")
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} not found: scripts/setup.sh installs Debian's chromium (apt-get install chromium)")
    from usdrelight.serve.app import ServeApp

    with ServeApp(stage, port=0, max_side=SIDE) as app, sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=["--no-sandbox"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 850})
            page.goto(app.url)
            page.get_by_role("button", name="Add light").wait_for(timeout=30000)
            yield app, page
        finally:
            browser.close()


def position_inputs(page):
    """The three number inputs of the selected light's Position field."""
    return page.get_by_label("Position").locator("xpath=ancestor::div[contains(@class,'mantine-Flex-root')][1]") \
        .locator("input[inputmode='decimal']")


def test_browser_adds_a_point_light_and_saves_it(stage):
    """Headless Chromium (Debian's, driven by Playwright) adds a point light through the UI, picks its colour
    and position, waits for the relit image to change, saves; lights_user.usda then holds that light."""
    from pxr import Gf, UsdLux

    picked, position = (255, 128, 0), (0.3, 0.8, -2.0)
    with app_page(stage) as (app, page):
        add = page.get_by_role("button", name="Add light")
        image = page.locator("img[src^='blob:']").first
        image.wait_for(timeout=30000)
        first_src = image.get_attribute("src")
        add.click()  # the kind dropdown starts at "point"
        page.get_by_text("point Point1").wait_for(timeout=15000)
        colour = page.locator("input.mantine-ColorInput-input").first
        colour.fill("rgb({}, {}, {})".format(*picked))
        colour.press("Enter")
        xyz = position_inputs(page)
        assert xyz.count() == 3
        for i, v in enumerate(position):
            xyz.nth(i).fill(str(v))
            xyz.nth(i).press("Enter")
        page.wait_for_function("s => { const i = document.querySelector(\"img[src^='blob:']\"); "
                               "return i && i.src !== s; }", arg=first_src, timeout=20000)
        deadline = time.monotonic() + 20
        while app.states["Point1"].position != position and time.monotonic() < deadline:
            time.sleep(0.1)
        page.get_by_role("button", name="Save lights").click()
        page.get_by_text("Saved 1 light(s) to lights_user.usda").wait_for(timeout=20000)
    saved = open_stage(stage)
    prim = saved.GetPrimAtPath("/Scene/Lights/User/Point1")
    assert prim and prim.GetTypeName() == "SphereLight"
    light = UsdLux.SphereLight(prim)
    assert light.GetTreatAsPointAttr().Get()
    np.testing.assert_allclose(light.GetColorAttr().Get(), color_from_picker(picked), rtol=1e-6)
    assert color_from_picker(picked)[1] == pytest.approx(0.2158605, abs=1e-6)  # sRGB 128 -> linear
    world = prim.GetAttribute("xformOp:translate").Get()
    assert Gf.IsClose(world, Gf.Vec3d(*position), 1e-9)


def test_area_lights_the_app_must_not_take_over_and_the_edges_it_must_take(stage):
    """A scaled DiskLight (its scale is its size), a sphere whose radius grows from 0 (point -> sphere), a rect
    with ShapingAPI and a point light with an animated radius stay as the user wrote them; the smallest size a
    slider offers (1e-4, float32 in USD) is a valid light; a rect turned to a new direction keeps its roll."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    layer_path = stage.parent / USER_LIGHTS
    s = Usd.Stage.Open(str(layer_path))
    s.OverridePrim("/Scene")
    scaled = UsdLux.DiskLight.Define(s, "/Scene/Lights/User/Scaled")
    scaled.CreateRadiusAttr(0.2)
    UsdGeom.Xformable(scaled).AddScaleOp().Set(Gf.Vec3f(3, 3, 3))
    grows = UsdLux.SphereLight.Define(s, "/Scene/Lights/User/Grows")
    grows.CreateRadiusAttr().Set(0.0, Usd.TimeCode(1))
    grows.GetRadiusAttr().Set(0.3, Usd.TimeCode(11))
    shaped = UsdLux.RectLight.Define(s, "/Scene/Lights/User/Shaped")
    UsdLux.ShapingAPI.Apply(shaped.GetPrim()).CreateShapingConeAngleAttr(40.0)
    pulse = UsdLux.SphereLight.Define(s, "/Scene/Lights/User/Pulse")
    pulse.CreateTreatAsPointAttr(True)
    pulse.CreateRadiusAttr().Set(0.1, Usd.TimeCode(1))
    pulse.GetRadiusAttr().Set(0.2, Usd.TimeCode(11))
    edge = UsdLux.DiskLight.Define(s, "/Scene/Lights/User/Edge")
    edge.CreateRadiusAttr(1e-4)
    s.GetRootLayer().Save()
    keys: dict = {}
    states, others = read_user_states(open_stage(stage), {}, keys)
    assert sorted(others) == [f"/Scene/Lights/User/{n}" for n in ("Grows", "Pulse", "Scaled", "Shaped")]
    (e,) = states
    assert e.name == "Edge" and e.kind == "disk" and e.radius == np.float32(1e-4)
    assert LightState("L", "rect", width=1e-4, height=1e4).width == np.float32(1e-4)
    with pytest.raises(UsdRelightError):
        LightState("L", "rect", width=9e-5)
    # from a record too: a scaled frame is not the app's
    rec = to_record(LightState("R", "rect", rotation=quat_pointing_along([0, -1, 0.2]), width=0.5, height=0.25))
    big = rec.__class__(**{**rec.__dict__, "to_world": rec.to_world @ np.diag([2.0, 2.0, 2.0, 1.0])})
    assert from_record(rec, "R") is not None and from_record(big, "R") is None
    # a rect's new direction: the smallest turn, its width axis kept as near as it can be
    from usdrelight.serve.state import quat_to_matrix, turned_towards

    r0 = quat_pointing_along([0, -1, 0.2])
    r1 = turned_towards(r0, [0, -1, 0.6])  # 20 degrees further from vertical, past quat_pointing_along's switch
    m0, m1 = quat_to_matrix(r0), quat_to_matrix(r1)
    d = np.array([0, -1, 0.6]) / np.linalg.norm([0, -1, 0.6])
    np.testing.assert_allclose(m1 @ [0, 0, -1], d, atol=1e-9)
    assert m0[:, 0] @ m1[:, 0] > 0.9  # the width axis turns with the light (cos 20 degrees)
    assert abs(quat_to_matrix(quat_pointing_along(d))[:, 0] @ m0[:, 0]) < 0.1  # rebuilt: a quarter turn off
    np.testing.assert_allclose(quat_to_matrix(turned_towards(r0, -(m0 @ [0, 0, -1]))) @ [0, 0, -1],
                               -(m0 @ [0, 0, -1]), atol=1e-9)  # half a turn
